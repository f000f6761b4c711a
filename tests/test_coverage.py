"""Coverage never goes down: the bundled scenarios trace at least the recorded share of MJX's
code and move at least the recorded parameters away from their defaults. A change may raise
the floor (rewrite tests/coverage_floor.json with the new numbers), never lower it."""

import json

import pytest

from mjxdiff.output import report
from mjxdiff.tools import coverage
from mjxdiff.cli import main
from mjxdiff.input.scenario import bundled_scenarios

FLOOR_FILE = "tests/coverage_floor.json"


@pytest.fixture(scope="module")
def measured():
    return coverage.measure(bundled_scenarios())


@pytest.fixture(scope="module")
def floor(repo_root):
    return json.loads((repo_root / FLOOR_FILE).read_text())


def test_code_coverage_stays_above_the_floor(measured, floor):
    totals = measured["code"]["totals"]
    assert totals["line_percent"] >= floor["line_percent"], totals
    assert totals["branch_percent"] >= floor["branch_percent"], totals
    newly_untraced = sorted(set(measured["code"]["functions_never_traced"]) - set(floor["functions_never_traced"]))
    assert newly_untraced == [], f"MJX functions no scenario traces any more: {newly_untraced}"


def test_lines_left_out_as_unreachable_never_ran_but_an_unsupported_feature_s_raise(measured):
    """A pattern of coverage.UNREACHABLE too wide would shrink the measure's denominator by code the
    scenarios do run: the only excluded lines allowed to run are raises of NotImplementedError
    (unsupported_pair's ellipsoid-box pair)."""
    ran = measured["code"]["excluded_but_ran"]
    assert all("NotImplementedError" in source for lines in ran.values() for _, source in lines), ran


def test_parameter_coverage_stays_above_the_floor(measured, floor):
    moved = {k for k, v in measured["parameters"]["fields"].items() if v}
    moved |= {f"opt.{k}" for k, v in measured["parameters"]["options"].items() if v}
    lost = sorted(set(floor["parameters_moved"]) - moved)
    assert lost == [], f"parameters no scenario moves from their default any more: {lost}"


def test_every_recorded_state_regime_is_still_reached(measured, floor):
    lost = sorted(set(floor["regimes_reached"]) - {r for r, v in measured["regimes"]["regimes"].items() if v})
    assert lost == [], f"state regimes no scenario reaches any more: {lost}"


def test_a_model_that_moves_nothing_moves_nothing(tmp_path):
    """The measure itself: a default pendulum moves no parameter but its own geometry."""
    xml = tmp_path / "plain.xml"
    xml.write_text('<mujoco><worldbody><body><joint/><geom size="0.1" pos="0 0 -1"/></body></worldbody></mujoco>')
    from mjxdiff.input.scenario import load_scenario

    doc = coverage.measure([load_scenario(str(xml))], code=False)
    moved = [k for k, v in doc["parameters"]["fields"].items() if v]
    assert "dof_damping" not in moved and "jnt_stiffness" not in moved and "opt.impratio" not in moved
    assert doc["parameters"]["options"]["impratio"] == []
    assert "lower limit active" in doc["regimes"]["never"] and "contact making" in doc["regimes"]["never"]


def test_cli_writes_coverage_json(tmp_path, capsys):
    assert main(["coverage", "pendulum", "--out", str(tmp_path)]) == 0
    doc = json.loads((tmp_path / "coverage.json").read_text())
    assert report.validate(doc, "coverage") == []
    assert doc["scenarios"] == ["pendulum"] and doc["code_coverage"]["totals"]["lines_covered"] > 0
    assert "MJX code traced" in capsys.readouterr().out
