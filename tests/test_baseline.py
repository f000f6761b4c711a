"""--baseline: a monkeypatched MJX bug against a clean run names exactly the scenarios it breaks
as 'new failure'; --fail-on new; a bad baseline is one line and exit 2."""

import json

import pytest
from conftest import REPORT_SCENARIOS

from mjxdiff.output import baseline
from mjxdiff.cli import main


def test_the_bug_s_scenarios_and_only_they_are_new_failures(two_sweeps):
    root, code = two_sweeps
    assert code == 1
    doc = json.loads((root / "bugged" / "report.json").read_text())
    changes = {c["scenario"]: c["change"] for c in doc["baseline"]["changes"]}
    assert changes == {"pendulum": "new failure", "cartpole": "new failure", "double_pendulum": "same"}


def test_against_itself_a_failing_run_has_nothing_new(two_sweeps):
    root, _ = two_sweeps
    doc = json.loads((root / "bugged" / "report.json").read_text())
    changes = baseline.compare(doc, doc)
    assert {c["change"] for c in changes} == {"same"} and not baseline.new_failures(changes)


def test_fixed_grew_and_shrank():
    def report(status, err, envelope=0.0):
        return dict(scenarios=[dict(name="s", status=status, fields=dict(
            qvel=dict(max_error=err, tolerance=1e-6, envelope=envelope, ratio=err / 1e-6)))])

    cls = lambda a, b: baseline.compare(a, b)[0]["change"]
    assert cls(report("fail", 1e-3), report("pass", 1e-12)) == "fixed"
    assert cls(report("pass", 1e-9), report("pass", 1e-8)) == "error grew"
    assert cls(report("pass", 1e-8), report("pass", 1e-9)) == "error shrank"
    assert cls(report("pass", 1e-9), report("pass", 5e-9)) == "same"
    assert cls(report("pass", 1e-16), report("pass", 1e-14)) == "same"  # rounding
    assert cls(report("pass", 1e-9, 1e-7), report("pass", 1e-8, 1e-7)) == "same"  # chaotic: no claim


def test_a_run_id_of_the_history_is_a_baseline(two_sweeps):
    root, _ = two_sweeps
    clean = json.loads((root / "clean" / "report.json").read_text())
    run_file = clean["history"]["run_file"]
    run_id = run_file.rsplit("-", 1)[1].removesuffix(".parquet")
    base = baseline.load(run_id[:8], root / "history")
    assert {s["name"]: s["status"] for s in base["scenarios"]} == {n: "pass" for n in REPORT_SCENARIOS}
    assert not baseline.new_failures(baseline.compare(base, clean))


@pytest.mark.parametrize("argv, says", [
    (["--baseline", "no/such/report.json"], "no such report.json, directory or history run id"),
    (["--known", "no_such_file.toml"], "not a known-divergences file"),
])
def test_bad_baseline_options_are_one_line_and_exit_2(argv, says, capsys, tmp_path):
    assert main(["sweep", "pendulum", "--quick", "--history", str(tmp_path), *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert says in err and "\n" not in err and "Traceback" not in err
