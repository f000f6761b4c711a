"""Every setting of a sweep, declared once: the engines it can judge (:data:`ENGINES`), the pairs
each ``--impl`` judges (:data:`PAIRS`), and the options (:class:`SweepOptions`) with their types,
choices, defaults, help and the :class:`~mjxdiff.input.config.SweepConfig` field each fills.

``mjxdiff sweep``'s flags (:func:`add_arguments`), ``SweepOptions``, the ``SweepConfig`` values
(:func:`config_values`) and the constants (:data:`IMPLS`, :data:`NOISE_FLOOR_MODES`, ...) are read
from here, so adding an option is one field below, and adding an engine one entry of
:data:`ENGINES` (plus the engine's code). No JAX or MuJoCo is imported: the CLI reads this to
answer ``--help``.

>>> from mjxdiff.input import options
>>> options.IMPLS
('mjx', 'warp', 'mjx.warp')
>>> [suffix for suffix, _ in options.PAIRS["both"]]
['', '@warp', '@mjx-warp']
>>> options.config_values(options.SweepOptions(drop_costly_pairs=True))["drop_costly"]
True
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import os
import re
import typing
from typing import Any, Callable, Literal, get_args

__all__ = ["COMPILE_MODES", "ENGINES", "IMPLS", "NOISE_FLOOR_MODES", "PAIRS", "WARP_IMPLS", "EngineEntry",
           "SweepOptions", "add_arguments", "config_values", "parse_size"]


@dataclasses.dataclass(frozen=True)
class EngineEntry:
    """An implementation judged against MuJoCo C: its :class:`~mjxdiff.engine.trajectory.Engine`
    class (``module``, ``name``; imported on first use), whether it computes in float32 only
    (then a sweep judges, perturbs and tolerances it as float32, and keeps its reproducers apart)
    and how messages name it beside C (``C 1, MJX 2 contacts``)."""

    module: str
    name: str
    float32: bool = False
    label: str = "MJX"


#: The implementations a sweep can judge, by ``SweepConfig.impl`` and ``--impl``. An engine's whole
#: registration: :data:`IMPLS`, :data:`PAIRS` (its own pair, and ``all``), the ``--impl`` choices and
#: :func:`mjxdiff.runner.sweep.engine_class` are read from here.
ENGINES: dict[str, EngineEntry] = {
    "mjx": EngineEntry("mjxdiff.engine.engines", "MJXEngine"),
    "warp": EngineEntry("mjxdiff.engine.mjwarp", "MJWarpEngine", float32=True, label="MuJoCo Warp"),
    "mjx.warp": EngineEntry("mjxdiff.engine.engines", "MJXWarpEngine", float32=True, label="MJX (warp)"),
}
#: Implementations a sweep can judge against MuJoCo C.
IMPLS = tuple(ENGINES)
#: The implementations that compute in float32 only (MuJoCo Warp, itself or MJX's vendored copy).
WARP_IMPLS = tuple(impl for impl, entry in ENGINES.items() if entry.float32)

#: MuJoWarp judged against MJX, C's envelope as the floor (no drill-down: C is not one of the two).
_WARP_VS_MJX = ("@mjx-warp", dict(impl="warp", reference="mjx", diagnose="none", reproducers=None))
#: The judged pairs of each ``--impl``: (result-name suffix, changes to the sweep's config). Each
#: engine alone against C; ``both``: MJX and MJWarp against C, and MJWarp against MJX; ``all``:
#: every engine against C, and MJWarp against MJX.
PAIRS: dict[str, tuple[tuple[str, dict[str, Any]], ...]] = {
    **{impl: (("", {} if impl == "mjx" else dict(impl=impl)),) for impl in ENGINES},
    "both": (("", {}), ("@warp", dict(impl="warp")), _WARP_VS_MJX),
    "all": (("", {}), *((f"@{impl}", dict(impl=impl)) for impl in ENGINES if impl != "mjx"), _WARP_VS_MJX),
}

NoiseFloor = Literal["on-demand", "always"]
Diagnose = Literal["none", "basic", "full"]
CompileMode = Literal["auto", "fast", "optimized"]
#: When C's perturbed rerun runs (:attr:`SweepConfig.noise_floor`).
NOISE_FLOOR_MODES: tuple[str, ...] = get_args(NoiseFloor)
#: How hard XLA optimises an MJX rollout (:func:`mjxdiff.engine.engines.xla_options`).
COMPILE_MODES: tuple[str, ...] = get_args(CompileMode)


# -- values of flags ------------------------------------------------------------------------------

def _integer(text: str, least: int, kind: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a {kind} integer, got {text!r}") from None
    if value < least:
        raise argparse.ArgumentTypeError(f"expected a {kind} integer, got {text!r}")
    return value


def positive(text: str) -> int:
    """A flag's value as an integer >= 1 (argparse's ``type``)."""
    return _integer(text, 1, "positive")


def non_negative(text: str) -> int:
    """A flag's value as an integer >= 0."""
    return _integer(text, 0, "non-negative")


def fraction(text: str) -> float:
    """A flag's value as a number in [0, 1]."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number in [0, 1], got {text!r}") from None
    if not 0 <= value <= 1:
        raise argparse.ArgumentTypeError(f"expected a number in [0, 1], got {text!r}")
    return value


def seconds(text: str) -> float:
    """A flag's value as seconds, > 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected seconds (a positive number), got {text!r}") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"expected seconds (a positive number), got {text!r}")
    return value


def parse_size(text: str) -> int:
    """Bytes of ``'12G'``, ``'800M'``, ``'1.5GB'``, ``'4096'`` (bytes); ValueError otherwise."""
    found = re.fullmatch(r"\s*([0-9]*\.?[0-9]+)\s*([kKmMgGtT]?)(i?[bB])?\s*", text)
    if not found:
        raise ValueError(f"not a size: {text!r} (e.g. 12G, 800M)")
    scale = {"": 1, "k": 2**10, "m": 2**20, "g": 2**30, "t": 2**40}[found.group(2).lower()]
    return int(float(found.group(1)) * scale)


def size(text: str) -> int:
    """A flag's value as bytes > 0 (:func:`parse_size`)."""
    try:
        value = parse_size(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None
    if value <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive size (e.g. 12G, 800M), got {text!r}")
    return value


# -- the options ----------------------------------------------------------------------------------

def option(default: Any = None, help: str = "", *, parse: Callable[[str], Any] | None = None,
           metavar: str | None = None, choices: tuple[str, ...] | None = None, config: bool | str = False,
           switch: bool = False, factory: Callable[[], Any] | None = None, flag: bool = True) -> Any:
    """A field of :class:`SweepOptions`: its default (or ``factory``), the help of its flag, how the
    flag's text is read (``parse``; a ``Literal`` annotation gives the choices, a ``bool`` gives
    ``--x/--no-x``, or ``--x`` alone where ``switch``), and the ``SweepConfig`` field it fills
    (``config``: True for the same name, or the other name). ``flag=False``: a flag every command
    has (added by the CLI itself)."""
    meta = dict(help=help, parse=parse, metavar=metavar, choices=choices, config=config, switch=switch,
                flag=flag)
    if factory is not None:
        return dataclasses.field(default_factory=factory, metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def _isolate_default() -> bool:
    return os.environ.get("MJXDIFF_ISOLATE", "1") != "0"


@dataclasses.dataclass(frozen=True)
class SweepOptions:
    """Everything ``mjxdiff sweep`` takes, by its flag's name (``--noise-floor`` is
    ``noise_floor``), with the same defaults; ``mjxdiff sweep --help`` says what each does."""

    scenarios: tuple[str, ...] = option((), "bundled scenario name, path to a scenario .toml, or path to any MJCF "
                                        ".xml (default: every bundled scenario; see 'mjxdiff list')")
    seed: int = option(0, "master seed of all randomization (default 0)", parse=int, config=True)
    batch: int | None = option(None, "batch members per scenario (default: the scenario's)", parse=positive,
                               config=True)
    steps: int | None = option(None, "steps per rollout (default: the scenario's)", parse=positive, config=True)
    precision: Literal["float64", "float32"] = option(
        "float64", "MJX precision; float64 (default) keeps rounding far below algorithmic differences; float32 "
        "(as most users train) uses looser tolerance floors and judges MJX against C's float32 shadow (C rounded "
        "at every step), so a landing that rounding decides passes, said to be weak", config=True)
    threshold: float = option(0.95, "least fraction of batch members within tolerance for a scenario to pass "
                              "(default 0.95)", parse=fraction, config=True)
    envelope: bool = option(True, "judge errors against the chaos envelope measured from C's own divergence under "
                            "rounding-level perturbations (default); --no-envelope uses fixed tolerances only",
                            config=True)
    noise_floor: NoiseFloor = option(
        "on-demand", "when C's perturbed rerun (the envelope's source) runs: on-demand (default) only for members "
        "whose errors exceed the fixed tolerances, the only ones the envelope can change; always: for every "
        "member, so that every report gives the envelope and noise_rate", config=True)
    diagnose: Diagnose = option(
        "full", "for failing scenarios: basic = re-synchronised one-step error and the first pipeline stage that "
        "differs; full (default) = also the likely cause, from reruns with a converged solver, no contacts, a "
        "smaller timestep, another integrator", config=True)
    adjust: bool = option(True, "set aside settings MJX refuses that change nothing compared (the energy and fwdinv "
                          "flags) and mark the result 'adjusted' (default); --no-adjust reports such models "
                          "unsupported", config=True)
    drop_unsupported: bool = option(
        False, "remove geom pairs MJX cannot collide (e.g. cylinder-box) from the model both engines step and test "
        "the rest; changes the dynamics, so it is never the default and every dropped pair is listed in the result",
        switch=True, config=True)
    drop_costly_pairs: bool = option(
        False, "remove the mesh-mesh and box-mesh geom pairs (MJX's dense separating-axis test: minutes of compile, "
        "GBs per member on robots' plain models) from the model both engines step; changes the dynamics, so never "
        "the default; every dropped pair is listed", switch=True, config="drop_costly")
    budget: float = option(600.0, "wall time per scenario (default 600). A compile estimated past it stops the "
                           "scenario at once, with the estimate and what to do; a scenario that runs past it ends as "
                           "an ERROR saying how far it got, and the sweep goes on", parse=seconds,
                           metavar="SECONDS", config=True)
    sweep_budget: float | None = option(None, "wall time for the whole sweep (default: none); scenarios left when it "
                                        "runs out are reported as not run", parse=seconds, metavar="SECONDS")
    max_memory: int | None = option(
        None, "resident memory the sweep may hold, e.g. 12G (default: 85%% of what the machine has available at "
        "the start). MJX steps fewer members at once to fit; a scenario that would still exceed it ends as an "
        "ERROR naming the cause, before the kernel would kill it", parse=size, metavar="SIZE", config=True)
    isolate: bool = option(
        help="run the sweep in a child process watched for --max-memory and --budget, which can stop even an XLA "
        "compile (default; MJXDIFF_ISOLATE=0 changes the default); --no-isolate runs it in this process, where "
        "only the plan and the checks between pieces hold the limits", factory=_isolate_default)
    onestep: bool = option(
        True, "check every scenario one step at a time from C's states with a converged solver in both engines, "
        "bounded by C's own rounding (sharp where chaos or a truncated solver make the rollout's bound wide); it "
        "can fail the scenario on its own (default on)", config=True)
    transfer: bool = option(
        True, "also check MJX's host interface against C at two C states of each scenario (default): "
        "get_data(put_data(d)) gives C's fields and penetrating contacts back, get_state/set_state/state_size "
        "match mj_getState/mj_stateSize, id2name/name2id and Model.bind/Data.bind read what C holds; a mismatch "
        "fails the scenario as field 'transfer'; state elements MJX refuses are listed, not failed", config=True)
    compile: CompileMode = option(
        "auto", "how hard XLA optimises each MJX rollout: auto (default) compiles quickly (about 60%% less compile "
        "time than XLA's defaults, 3x slower stepping) when the rollout steps too little for that to matter, as a "
        "sweep's do, and for stepping otherwise (40%% less compile time, about the same speed); fast forces the "
        "first, optimized XLA's defaults; results agree to rounding whichever is used", config=True)
    compile_workers: int | None = option(
        None, "scenarios run side by side, each on its own thread from compile to verdict; results are reported in "
        "order (default: one per core, at most 4; 0: one after another)", parse=non_negative, metavar="N",
        config=True)
    out: str | None = option(None, "write DIR/report.json (versions, config, per-scenario metrics) and "
                             "DIR/report.html (one self-contained page with plots); each scenario's verdict is also "
                             "appended to DIR/journal.jsonl as it arrives, so an interrupted sweep loses nothing "
                             "(--resume)", metavar="DIR")
    resume: str | None = option(
        None, "finish an interrupted sweep: reuse the verdicts DIR/journal.jsonl holds for the same scenario, model, "
        "seed, settings, MJX and mjxdiff code and versions, run the rest (and units whose worker or engine "
        "failed), and write the report to DIR (or --out); records of other code or settings are listed as stale, "
        "never reused", metavar="DIR")
    rerun: Literal["errors", "failed"] = option(
        "errors", "with --resume: rerun only units that did not settle (errors, the default: a worker or engine "
        "failed, a limit ran out), or also the failures (failed, as pytest's --lf)")
    executor: Literal["local", "ray"] = option(
        "local", "where the units run: on this machine (local, the default) or as one Ray task per unit on a Ray "
        "cluster (ray; pip install 'mjxdiff[ray]'): self-contained tasks (the model's files shipped), retried when "
        "a worker or node is lost, results journaled as they arrive and reported in the sweep's order")
    address: str | None = option(None, "with --executor ray: the cluster to join (ray.init's address, e.g. 'auto' "
                                 "or 'ray://head:10001'; default: start a Ray instance on this machine)",
                                 metavar="ADDR")
    cpus_per_scenario: int | None = option(None, "with --executor ray: CPUs each unit's task asks for, and all it "
                                           "uses (XLA host devices, C threads; default 1)", parse=positive,
                                           metavar="K")
    shard: str | None = option(None, "run only the I-th of N deterministic slices of the sweep's units (scenario x "
                               "judged pair, every N-th from the I-th); 'mjxdiff merge' joins the shards' --out "
                               "directories into one report (a CI matrix: one job per shard)", metavar="I/N")
    impl: str = option(
        "mjx", "what is judged against MuJoCo C: MJX (default), MuJoCo Warp on Warp's CPU device (float32, so "
        "float32 tolerance floors; needs pip install 'mjxdiff[warp]'; kernels compile on first use, ~30 s, then "
        "load from the cache), mjx.warp: MJX's own warp implementation (mjx.put_model(m, impl='warp'), MJX's "
        "vendored MuJoCo Warp through JAX; float32, needs the warp extra too), or both: one verdict per pair, MJX "
        "vs C ('NAME'), MJWarp vs C ('NAME@warp') and MJWarp vs MJX ('NAME@mjx-warp', float32, C's envelope as the "
        "floor); all: both, and MJX's warp implementation vs C ('NAME@mjx.warp')", choices=tuple(PAIRS))
    plots: Literal["failing", "all", "none"] = option(
        "failing", "report.html's error-vs-time plots: of failing scenarios (default), of all, or none")
    history: str | None = option(
        None, "append this run (one row per scenario x field) to the Parquet history in DIR and flag errors that "
        "moved outside their own history (default $MJXDIFF_HISTORY, else $XDG_DATA_HOME/mjxdiff/history or "
        "~/.local/share/mjxdiff/history; see 'mjxdiff history')", metavar="DIR")
    no_history: bool = option(False, "do not read or append the run history", switch=True)
    history_keep: int = option(500, "runs kept in the history; older ones are deleted (default 500)",
                               parse=positive, metavar="N")
    baseline: str | None = option(None, "compare with a trusted run: a report.json, a directory holding one, or a "
                                  "history run id; each scenario is 'same', 'new failure', 'fixed', 'error grew' or "
                                  "'error shrank'", metavar="REF")
    fail_on: Literal["any", "new"] = option(
        "any", "exit 1 on any divergence (default), or only on new ones: failures that no accepted known entry "
        "explains (e.g. 'solver-truncation': your solver settings, not MJX, part the engines) and, with "
        "--baseline, that the baseline did not already have")
    known: str | None = option(None, "your own known divergences ([[known]] tables, see mjxdiff.compare.known), "
                               "tried before the catalogue shipped with mjxdiff", metavar="FILE")
    format: Literal["text", "json"] = option("text", "stdout format (default text)")
    quick: bool = option(
        False, "smoke run: batch <= 4, steps <= 50, and none of the checks that compile on their own (the converged "
        "twin, the ablations that name a likely cause): each verdict says what it skipped; it steps the full run's "
        "compiled code, so either run warms the cache for the other", switch=True, config=True)
    cache_dir: str | None = option(
        None, "JAX persistent compilation cache, plus traced MJX rollouts in DIR/mjxdiff-exports so a second run "
        "skips tracing mjx.step (default $MJXDIFF_CACHE or ~/.cache/mjxdiff/jax; '' disables both)", metavar="DIR")
    progress: bool | None = option(None, "progress lines on stderr (default: when stderr is a terminal)")
    allow_untested_versions: bool = option(False, flag=False)

    def as_config(self) -> dict[str, Any]:
        """The options as ``report.json``'s ``config`` records them."""
        return dict(command="sweep", **dataclasses.asdict(self)) | dict(scenarios=list(self.scenarios))


@functools.cache
def _types(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _choices(cls: type, f: dataclasses.Field) -> tuple[str, ...] | None:
    """A field's choices: declared, or the values of its ``Literal`` annotation."""
    hint = _types(cls)[f.name]
    return f.metadata["choices"] or (get_args(hint) if typing.get_origin(hint) is Literal else None)


def _argument(cls: type, f: dataclasses.Field) -> tuple[tuple[str, ...], dict[str, Any]]:
    """The ``add_argument`` flags and keywords of one field of ``cls``."""
    meta = f.metadata
    default = f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
    if f.name == "scenarios":
        return ("scenarios",), dict(nargs="*", metavar="SCENARIO", help=meta["help"])
    kw: dict[str, Any] = dict(help=meta["help"])
    hint = _types(cls)[f.name]
    if meta["switch"]:
        kw.update(action="store_true")
    elif hint in (bool, bool | None):
        kw.update(action=argparse.BooleanOptionalAction, default=default)
    else:
        kw.update(default=default, type=meta["parse"], choices=_choices(cls, f), metavar=meta["metavar"])
    return (f"--{f.name.replace('_', '-')}",), {k: v for k, v in kw.items() if v is not None or k == "default"}


def add_arguments(parser: argparse.ArgumentParser, cls: type = SweepOptions) -> None:
    """Adds one flag per field of ``cls`` (:class:`SweepOptions`) to ``parser``, in field order:
    ``--name-with-dashes``, its type, choices, default and help from the declaration."""
    for f in dataclasses.fields(cls):
        if f.metadata.get("flag", True):
            flags, kw = _argument(cls, f)
            parser.add_argument(*flags, **kw)


def config_values(options: Any) -> dict[str, Any]:
    """The :class:`~mjxdiff.input.config.SweepConfig` keywords that ``options`` fills: each field
    declared with ``config``, under its config name (``drop_costly_pairs`` fills ``drop_costly``)."""
    out = {}
    for f in dataclasses.fields(options):
        name = f.metadata.get("config")
        if name:
            out[f.name if name is True else name] = getattr(options, f.name)
    return out
