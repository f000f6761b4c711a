"""fuzz never reads a failure of its own harness as "no divergence": only the property's
divergence signal is a find; any other exception ends the run with exit code 2, one
error line, the traceback, and DIR/fuzz-report.json. No engine runs here: the function
the property calls to simulate is replaced by one that answers at once."""

import dataclasses
import json

import pytest

from mjxdiff.output import report
from mjxdiff import cli
from mjxdiff.tools import fuzz
from mjxdiff.compare.verdict import ScenarioResult

ARGS = ["fuzz", "--max-examples", "3", "--budget", "30"]


def _raising(error):
    def divergence(*args, **kwargs):
        raise error
    return divergence


@pytest.mark.parametrize("error, line", [
    (AssertionError("harness bug"), "AssertionError: harness bug"),
    (KeyError("qfrc_missing"), "KeyError: 'qfrc_missing'"),
])
def test_harness_error_is_reported_not_read_as_no_divergence(error, line, monkeypatch, tmp_path, capsys):
    monkeypatch.setattr(fuzz, "_divergence", _raising(error))
    code = cli.main([*ARGS, "--out", str(tmp_path)])
    out, err = capsys.readouterr()
    assert code == 2, (out, err)
    assert "no divergence" not in out
    lines = err.splitlines()
    assert lines[0] == f"mjxdiff: error: fuzz harness failed: {line}", err
    assert lines[1] == "Traceback (most recent call last):"
    assert "in divergence" in err and line in lines[-2:]  # the raising frame, then the error itself
    doc = json.loads((tmp_path / "fuzz-report.json").read_text())
    assert report.validate(doc, "fuzz") == []
    assert doc["harness_error"] == line
    assert doc["traceback"].startswith("Traceback (most recent call last):")
    assert "in divergence" in doc["traceback"] and line in doc["traceback"]
    assert doc["traceback"].rstrip("\n") in err
    assert doc["failure"] is None and doc["structures"] == 1  # stopped at once, not shrunk
    assert doc["harness_example"].startswith("<mujoco")
    assert isinstance(doc["seconds"], float)
    assert not (tmp_path / "reproducers").exists()


def test_harness_error_after_passing_examples(monkeypatch, tmp_path):
    """Examples that passed before the harness broke prove nothing either."""
    calls = []

    def divergence(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise ValueError("broke on the second example")
        return ScenarioResult(name="fuzz", status="pass", message="ok")

    monkeypatch.setattr(fuzz, "_divergence", divergence)
    result = fuzz.fuzz(max_examples=3, budget=30, out=tmp_path)
    assert result.failure is None
    assert result.harness_error == "ValueError: broke on the second example"
    assert "Traceback" in result.harness_traceback and "in divergence" in result.harness_traceback


def test_clean_run_writes_a_report(monkeypatch, tmp_path, capsys):
    monkeypatch.setattr(fuzz, "_divergence", lambda *a, **k: ScenarioResult(name="fuzz", status="pass", message="ok"))
    assert cli.main([*ARGS, "--out", str(tmp_path)]) == 0
    out, err = capsys.readouterr()
    assert out.startswith(f"no divergence in {3 * fuzz.DEFAULT_VARIANTS} examples (3 generated models x "
                          f"{fuzz.DEFAULT_VARIANTS} variants"), out
    doc = json.loads((tmp_path / "fuzz-report.json").read_text())
    assert doc["structures"] == 3 and doc["examples"] == 3 * fuzz.DEFAULT_VARIANTS
    assert doc["failure"] is None and doc["harness_error"] is None
    assert doc["traceback"] is None
    assert "mjxdiff: error" not in err


def test_a_find_is_still_a_find(monkeypatch, tmp_path, capsys):
    """The property's own divergence signal is shrunk and reported, exit 1, reproducer inside --out."""
    monkeypatch.setattr(fuzz, "_divergence",
                        lambda *a, **k: ScenarioResult(name="fuzz", status="fail", message="qvel differs"))
    assert cli.main([*ARGS, "--out", str(tmp_path)]) == 1
    out, err = capsys.readouterr()
    assert out.startswith("DIVERGENCE (fail)") and "qvel differs" in out
    doc = json.loads((tmp_path / "fuzz-report.json").read_text())
    assert doc["harness_error"] is None and doc["failure"]["message"] == "qvel differs"
    assert doc["failure"]["reproducer"] == str(tmp_path / "reproducers" / "fuzz.json")
    assert (tmp_path / "reproducers" / "fuzz.json").is_file()


def test_c_blowing_up_or_mjx_refusing_is_not_a_find(tmp_path):
    """A generated model on which MuJoCo C itself goes unstable says nothing about MJX."""
    from mjxdiff.tools.fuzz import is_divergence
    from mjxdiff.input.scenario import load_scenario
    from mjxdiff.runner.sweep import SweepConfig, run_scenario
    from tests.test_cli import UNSTABLE_XML

    path = tmp_path / "unstable.xml"
    path.write_text(UNSTABLE_XML)
    unstable = run_scenario(load_scenario(str(path)), SweepConfig(batch=2, steps=60, diagnose="none"))
    assert (unstable.status, unstable.error_kind) == ("error", "unstable")
    assert not is_divergence(unstable)
    refused = run_scenario(load_scenario("unsupported_pair"), SweepConfig(batch=2, steps=20, diagnose="none"))
    assert refused.status == "unsupported" and not is_divergence(refused)
    assert is_divergence(dataclasses.replace(unstable, status="fail", error_kind=""))
