"""The pipeline: the Python API gives what ``mjxdiff sweep`` gives, on the same arguments."""

import dataclasses
import json

import pytest

import mjxdiff
from mjxdiff.engine import engines
from mjxdiff.output import history
from mjxdiff.runner import pipeline
from mjxdiff.cli import build_parser, main
from tests.conftest import REPORT_SCENARIOS

#: What differs between two runs of the same sweep: wall times, where the files went, what was
#: compiled or loaded (the second run reuses the first's) and the cost model's estimates (it
#: learns from each compile).
_VOLATILE_CONFIG = {"seconds", "mjx_compiles", "out", "history"}
_VOLATILE = {"seconds", "compile_seconds", "cpu_seconds", "reproducer", "memory", "mjx_loaded", "mjx_compiles",
             "checks_loaded", "estimate", "xla"}


def _scenario(s: dict) -> dict:
    return {k: v for k, v in s.items() if k != "info"} | dict(
        info={k: v for k, v in s.get("info", {}).items() if k not in _VOLATILE})


def _comparable(doc: dict) -> dict:
    return dict(config={k: v for k, v in doc["config"].items() if k not in _VOLATILE_CONFIG},
                summary={k: v for k, v in doc["summary"].items() if k not in _VOLATILE},
                scenarios=[_scenario(s) for s in doc["scenarios"]], baseline=doc.get("baseline"),
                anomalies=doc["history"]["anomalies"], versions=doc["versions"], mjx=doc["code"]["mjx"])


def _differences(a, b, path="") -> list[str]:
    """The paths at which two JSON values differ."""
    if isinstance(a, dict) and isinstance(b, dict):
        return [d for k in sorted(a.keys() | b.keys()) for d in
                (_differences(a[k], b[k], f"{path}/{k}") if k in a and k in b else [f"{path}/{k}"])]
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in _differences(x, y, f"{path}[{i}]")]
    return [] if a == b else [f"{path}: {a!r:.80} != {b!r:.80}"]


def _history_rows(directory) -> list[dict]:
    drop = {"run_id", "time", "seconds", "compile_seconds"}
    got = history.open_history(directory).sql("SELECT * FROM history ORDER BY scenario, field")
    return [{k: v for k, v in r.items() if k not in drop} for r in got]


def test_the_options_are_the_sweep_command_s_flags():
    """Every flag of ``mjxdiff sweep`` is an option of the pipeline, with the same default."""
    args = vars(build_parser().parse_args(["sweep"]))
    fields = {f.name: f for f in dataclasses.fields(pipeline.SweepOptions)}
    assert set(args) - {"command", "func"} == set(fields)
    defaults = pipeline.SweepOptions()
    assert {k: getattr(defaults, k) for k in fields if k != "scenarios"} == {
        k: v for k, v in args.items() if k in fields and k != "scenarios"}


def test_the_python_api_gives_what_the_cli_gives(two_sweeps, tmp_path, monkeypatch):
    """With MJX's actuator gains 2% high, against the clean sweep as baseline, failing only on
    new failures: ``mjxdiff.run`` and ``mjxdiff sweep`` give the same exit code, report (but
    for wall times and paths), history rows, baseline classes and page."""
    from mujoco.mjx._src import forward as mjx_forward

    root, _ = two_sweeps
    orig = mjx_forward.fwd_actuation
    monkeypatch.setattr(mjx_forward, "fwd_actuation",
                        lambda m, d: orig(m.replace(actuator_gainprm=m.actuator_gainprm * 1.02), d))
    engines.clear_compiled()
    common = dict(quick=True, cache_dir="", baseline=str(root / "clean"), fail_on="new", diagnose="basic")
    code = main(["sweep", *REPORT_SCENARIOS, "--quick", "--cache-dir", "", "--baseline", str(root / "clean"),
                 "--fail-on", "new", "--diagnose", "basic", "--history", str(tmp_path / "cli-history"),
                 "--out", str(tmp_path / "cli")])
    run = mjxdiff.run(scenarios=REPORT_SCENARIOS, history=str(tmp_path / "api-history"), out=str(tmp_path / "api"),
                      **common)
    engines.clear_compiled()

    assert code == run.exit_code == 1
    cli_doc = json.loads((tmp_path / "cli" / "report.json").read_text())
    assert json.loads((tmp_path / "api" / "report.json").read_text()) == run.doc
    differences = _differences(_comparable(cli_doc), _comparable(run.doc))
    assert differences == [], "\n".join(differences[:60])  # all of them: a rounding-level flake to explain
    assert [c["change"] for c in run.changes] == ["new failure", "new failure", "same"]
    assert [r.status for r in run.results] == ["fail", "fail", "pass"]
    assert _history_rows(tmp_path / "cli-history") == _history_rows(tmp_path / "api-history")
    assert run.files == dict(history=run.doc["history"]["run_file"], report=str(tmp_path / "api" / "report.json"),
                             page=str(tmp_path / "api" / "report.html"))
    pages = [(tmp_path / d / "report.html").read_text() for d in ("cli", "api")]
    assert all(f">{name}<" in page for page in pages for name in REPORT_SCENARIOS)


def test_unusable_options_raise_one_line(tmp_path):
    with pytest.raises(pipeline.OptionsError, match="^[^\n]*$"):
        mjxdiff.run(scenarios=["pendulum"], known=str(tmp_path / "missing.toml"))
    with pytest.raises(pipeline.OptionsError, match="unexpected keyword|batchh"):
        mjxdiff.run(batchh=3)
