"""Fuzzing: finds an injected MJX bug from scratch and shrinks it; no alarm on unmodified MJX;
the pytest plugin's assertion helper carries the diagnosis."""

import mujoco
import pytest
from mujoco.mjx._src import smooth as mjx_smooth

from mjxdiff import engines
from mjxdiff.fuzz import DEFAULT_BUDGET, fuzz
from mjxdiff.testing import MJXMismatch, assert_mjx_matches_c, compare


def bias_force_0p1_percent(monkeypatch):
    """Coriolis/centrifugal/gravity force 0.1% too large (any moving model shows it)."""
    orig = mjx_smooth.rne
    monkeypatch.setattr(mjx_smooth, "rne", lambda m, d, *a, **k: (lambda d: d.replace(
        qfrc_bias=d.qfrc_bias * (1 + 1e-3)))(orig(m, d, *a, **k)))


@pytest.mark.slow  # ~4 min: a default-budget search plus shrinking, every candidate a new compile
def test_fuzz_finds_and_shrinks_an_injected_bug(fresh_mjx, monkeypatch, tmp_path):
    bias_force_0p1_percent(monkeypatch)
    result = fuzz(budget=DEFAULT_BUDGET, out=tmp_path, seed=0, shrink_budget=60)
    assert result.failure is not None, f"not found in {result.examples} models"
    failure = result.failure
    assert failure["nbody"] <= 3 and failure["ngeom"] <= 4, failure["xml"]
    assert "qfrc_bias" in failure["message"]
    # the shrunk model still fails, with the bug, from its own saved state
    from mjxdiff import reproducer
    from mjxdiff.scenario import Tolerances
    from mjxdiff.sweep import SweepConfig, run_inputs

    rep = reproducer.load(failure["reproducer"])
    again = run_inputs("shrunk", rep.model, rep.inputs, Tolerances(), SweepConfig(diagnose="none"))
    assert again.status == "fail"


@pytest.mark.slow  # the full default budget
def test_fuzz_on_unmodified_mjx_finds_nothing(tmp_path):
    result = fuzz(budget=DEFAULT_BUDGET, out=tmp_path, seed=1)
    assert result.failure is None, result.failure and (result.failure["message"] + "\n" + result.failure["xml"])
    assert result.examples >= 5


def test_fuzz_smoke_unmodified(tmp_path):
    """A short search in CI: examples run, nothing is flagged, the budget is respected."""
    result = fuzz(budget=15, out=tmp_path, seed=2, max_examples=20)
    assert result.failure is None, result.failure and result.failure["message"]
    assert result.examples >= 1
    assert not (tmp_path / "reproducers").exists()


PENDULUM = """<mujoco><option timestep="0.002"/><worldbody>
  <body pos="0 0 1"><joint name="swing" type="hinge" axis="0 1 0" damping="0.1"/>
  <geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.03" mass="1"/></body></worldbody>
  <actuator><motor name="m" joint="swing" ctrlrange="-1 1"/></actuator></mujoco>"""


def test_assert_helper_passes_unmodified_and_explains_a_bug(fresh_mjx, monkeypatch, mjx_matches_c):
    m = mujoco.MjModel.from_xml_string(PENDULUM)
    assert mjx_matches_c is assert_mjx_matches_c  # the plugin's fixture
    result = mjx_matches_c(m, qpos=[0.5], ctrl=[[0.3]] * 100)
    assert result.status == "pass"
    bias_force_0p1_percent(monkeypatch)
    engines.clear_compiled()
    with pytest.raises(MJXMismatch, match=r"joint 'swing'.*first field to differ: qfrc_bias") as info:
        mjx_matches_c(m, qpos=[0.5], ctrl=[[0.3]] * 100)
    assert info.value.result.status == "fail"


def test_compare_batches_states():
    m = mujoco.MjModel.from_xml_string(PENDULUM)
    result = compare(m, qpos=[[0.1], [0.2], [0.3]], steps=50)
    assert result.status == "pass" and result.info["batch"] == 3
