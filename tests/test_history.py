"""The run history: rows round-trip through DuckDB, an interrupted write leaves earlier rows
readable, retention drops the oldest runs, and a 10x error growth on a passing scenario is
flagged against the scenario's own history."""

import copy
import json

import pytest
from conftest import REPORT_SCENARIOS

from mjxdiff.output import history
from mjxdiff.cli import main


@pytest.fixture
def clean_doc(two_sweeps):
    root, _ = two_sweeps
    return json.loads((root / "clean" / "report.json").read_text())


def test_rows_round_trip_through_duckdb(clean_doc, tmp_path):
    history.append(tmp_path, clean_doc)
    h = history.open_history(tmp_path)
    got = {(r["scenario"], r["field"]): r for r in h.sql("SELECT * FROM history")}
    want = {(r["scenario"], r["field"]): r for r in history.rows(clean_doc)}
    assert got.keys() == want.keys() and {s for s, _ in got} == set(REPORT_SCENARIOS)
    for key, row in want.items():
        for column in ("status", "max_error", "tolerance", "ratio", "first_step", "config_key", "mjx", "mjx_digest"):
            assert got[key][column] == row[column], (key, column)


def test_an_interrupted_write_leaves_earlier_rows_readable(clean_doc, tmp_path, monkeypatch):
    history.append(tmp_path, clean_doc)
    with monkeypatch.context() as patch:
        def interrupted(*args):
            raise KeyboardInterrupt
        patch.setattr(history.os, "replace", interrupted)
        with pytest.raises(KeyboardInterrupt):
            history.append(tmp_path, clean_doc)
    (tmp_path / "run-29990101T000000000000-broken.parquet").write_bytes(b"PAR1 cut short")  # a lost disk write
    h = history.open_history(tmp_path)
    assert h.runs == 1 and h.skipped == ["run-29990101T000000000000-broken.parquet"]
    assert len(h.sql("SELECT * FROM history")) == len(history.rows(clean_doc))


def test_retention_keeps_the_newest_runs(clean_doc, tmp_path):
    files = [history.append(tmp_path, clean_doc, keep=3) for _ in range(5)]
    assert sorted(tmp_path.glob("run-*.parquet")) == files[2:]


def _with_error(doc, scenario: int, field: str, error: float):
    doc = copy.deepcopy(doc)
    doc["scenarios"][scenario]["fields"][field]["max_error"] = error
    return doc


def test_a_tenfold_growth_on_a_passing_scenario_is_flagged(clean_doc, tmp_path):
    """cartpole's qvel error set to 2e-9 in four earlier runs (a scenario whose error is well
    above rounding: 1e-4 of its tolerance), then 2e-8: still a pass, flagged."""
    assert clean_doc["scenarios"][1]["status"] == "pass"
    base = _with_error(clean_doc, 1, "qvel", 2e-9)
    for _ in range(4):
        history.append(tmp_path, base)
    h = history.open_history(tmp_path)
    assert history.anomalies(h, base) == []  # the same numbers again
    flagged = history.anomalies(h, _with_error(clean_doc, 1, "qvel", 2e-8))
    assert [(a["scenario"], a["field"]) for a in flagged] == [("cartpole", "qvel")]
    assert flagged[0]["status"] == "pass" and flagged[0]["decades"] == pytest.approx(1.0, abs=0.01)
    assert history.anomalies(h, _with_error(clean_doc, 1, "qvel", 4e-9)) == []  # 2x: inside the spread


def test_rounding_level_changes_are_not_anomalies(clean_doc, tmp_path):
    """A new MJX build moves float64 rounding (1e-16 -> 1e-15): nothing to flag."""
    for _ in range(4):
        history.append(tmp_path, clean_doc)
    grown = _with_error(clean_doc, 1, "qvel", 10 * max(float(clean_doc["scenarios"][1]["fields"]["qvel"]["max_error"]),
                                                       1e-16))
    assert history.anomalies(history.open_history(tmp_path), grown) == []


def test_the_history_command_queries_trends_versions_and_runs(two_sweeps, capsys):
    root, _ = two_sweeps
    directory = str(root / "history")
    assert main(["history", "--dir", directory, "--scenario", "pendulum", "--format", "json"]) == 0
    rows = json.loads(capsys.readouterr().out)["rows"]
    assert {r["field"] for r in rows} >= {"qpos", "qvel"} and all(r["runs"] == 2 for r in rows)
    assert all(r["passed"] == 1 and r["last_status"] == "fail" for r in rows)
    assert main(["history", "--history", directory, "--by-version", "--format", "json"]) == 0
    # one MJX version, two code digests: the monkeypatched MJX is other code under the same number
    clean, bugged = json.loads(capsys.readouterr().out)["rows"]
    assert clean["mjx"] == bugged["mjx"] and clean["mjx_digest"] != bugged["mjx_digest"]
    assert (clean["scenario_passes"], clean["scenario_failures"]) == (3, 0)
    assert (bugged["scenario_passes"], bugged["scenario_failures"]) == (1, 2)
    assert main(["history", "--history", directory, "--runs", "--since", "1d"]) == 0
    assert "2 runs in" in capsys.readouterr().out


def test_a_bad_since_is_exit_2(capsys):
    with pytest.raises(SystemExit) as e:
        main(["history", "--since", "someday"])
    assert e.value.code == 2 and "not a date, time or age" in capsys.readouterr().err
