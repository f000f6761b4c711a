"""The sweep's settings, declared once (mjxdiff.input.options): the flags, SweepOptions, SweepConfig's
values and the engine table are all read from that one declaration."""

import argparse
import dataclasses

import pytest

from mjxdiff.cli import build_parser
from mjxdiff.input import options
from mjxdiff.input.config import SweepConfig
from mjxdiff.input.options import ENGINES, IMPLS, PAIRS, WARP_IMPLS, SweepOptions, config_values, option, positive


def _sweep_actions() -> dict[str, argparse.Action]:
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return {a.dest: a for a in sub.choices["sweep"]._actions}


def test_every_flag_of_sweep_is_a_declared_field_with_its_default_choices_and_help():
    actions = _sweep_actions()
    for f in dataclasses.fields(SweepOptions):
        a = actions[f.name]
        assert a.help == (f.metadata["help"] or a.help), f.name
        if f.name not in ("scenarios", "isolate", "allow_untested_versions"):
            assert a.default == f.default, f.name
    assert actions["noise_floor"].choices == options.NOISE_FLOOR_MODES
    assert actions["compile"].choices == options.COMPILE_MODES
    assert actions["precision"].choices == ("float64", "float32")
    assert actions["impl"].choices == tuple(PAIRS)
    assert isinstance(actions["envelope"], argparse.BooleanOptionalAction)
    assert actions["max_memory"].type is options.size and actions["max_memory"].metavar == "SIZE"


def test_a_new_option_is_one_field():
    """One field, declared with ``option``: a flag with its type and help, parsed, and the
    SweepConfig value it fills."""
    @dataclasses.dataclass(frozen=True)
    class WithPieces(SweepOptions):
        piece_steps: int | None = option(None, "steps per streamed piece", parse=positive, metavar="N",
                                         config=True)

    parser = argparse.ArgumentParser()
    options.add_arguments(parser, WithPieces)
    args = vars(parser.parse_args(["--piece-steps", "25", "--no-envelope", "--drop-costly-pairs"]))
    picked = WithPieces(**{**args, "scenarios": ()})
    assert config_values(picked) == config_values(SweepOptions(envelope=False, drop_costly_pairs=True)) | {
        "piece_steps": 25}
    assert SweepConfig(**config_values(picked)).piece_steps == 25
    with pytest.raises(SystemExit):
        parser.parse_args(["--piece-steps", "0"])


def test_the_config_values_are_sweepconfig_fields_with_the_same_defaults():
    """Each option that fills a SweepConfig field names a real field, and both default alike,
    but for the budget (the CLI's 600 s; none for a library call)."""
    values = config_values(SweepOptions())
    config = SweepConfig()
    assert set(values) <= {f.name for f in dataclasses.fields(SweepConfig)}
    assert {k: v for k, v in values.items() if getattr(config, k) != v} == {"budget": 600.0}


def test_an_engine_is_one_entry_of_the_engine_table():
    """IMPLS, the float32 implementations, the judged pairs (each engine's own, and 'all'), the
    --impl choices and the sweep's engine classes are all read from ENGINES."""
    from mjxdiff.runner import sweep

    assert IMPLS == tuple(ENGINES)
    assert WARP_IMPLS == tuple(i for i, e in ENGINES.items() if e.float32)
    assert all(impl in PAIRS for impl in ENGINES)
    assert {s for s, _ in PAIRS["all"]} >= {f"@{i}" for i in ENGINES if i != "mjx"}
    assert _sweep_actions()["impl"].choices == tuple(PAIRS)
    assert sweep.engine_class("mjx") is __import__("mjxdiff.engine.engines", fromlist=["x"]).MJXEngine
    for impl in IMPLS:
        assert SweepConfig(impl=impl).precision == ("float32" if impl in WARP_IMPLS else "float64")
    with pytest.raises(ValueError, match="impl must be one of"):
        SweepConfig(impl="nope")
