"""The one-step check: MJX put in C's state and stepped once beside C, converged solver in both,
bounded by C's own rounding. Sharp where the rollout is not: on a quadruped tuned for speed (one
solver iteration) unmodified MJX stays far inside its bound while injected bugs of several
kinds exceed it by orders of magnitude, each named by field and step."""

import numpy as np
import pytest
from mujoco.mjx._src import forward as mjx_forward
from mujoco.mjx._src import passive as mjx_passive
from mujoco.mjx._src import smooth as mjx_smooth

import _bugs
from mjxdiff.compare import onestep
from mjxdiff.output import report
from mjxdiff.engine.engines import CEngine, MJXEngine
from mjxdiff.input.inputs import make_inputs
from mjxdiff.input.scenario import load_model, load_scenario
from mjxdiff.runner.sweep import SweepConfig, run_scenario
from test_solver_floor import _one_percent_more_constraint_force


@pytest.fixture(scope="module")
def quadruped(repo_root):
    scenario = load_scenario(str(repo_root / "tests" / "data" / "quadruped_1iter.xml"))
    m = load_model(scenario)
    inputs = make_inputs(scenario, m, seed=0, batch=4, steps=120)
    return scenario, m, inputs, CEngine().rollout(inputs)


def _check(quadruped):
    scenario, m, inputs, traj_c = quadruped
    return onestep.check(m, inputs, traj_c, scenario.tolerance, MJXEngine(), CEngine())


def test_states_are_the_first_steps_the_busiest_and_the_fastest(quadruped):
    _, _, inputs, traj_c = quadruped
    steps = onestep.sample_steps(traj_c)
    assert steps[0] == -1 and {0, 1} <= set(steps) and len(steps) <= onestep.STATES + 1
    assert steps.max() <= inputs.steps - 2
    assert int(np.asarray(traj_c.ncon).max(axis=0)[:-1].argmax()) in steps


def test_one_step_inputs_start_from_cs_states_with_a_converged_solver(quadruped):
    _, _, inputs, traj_c = quadruped
    steps = np.array([-1, 5])
    one = onestep.one_step_inputs(inputs, traj_c, steps)
    assert one.batch == 2 * inputs.batch and one.steps == 1
    np.testing.assert_array_equal(one.qpos[0], inputs.qpos[0])  # member 0, initial state
    np.testing.assert_array_equal(one.qvel[3], traj_c.qvel[1, 5])  # member 1, after step 5
    np.testing.assert_array_equal(one.ctrl[3, 0], inputs.ctrl[1, 6])  # with step 6's control
    assert all(mi.opt.iterations == 200 and mi.opt.tolerance == 1e-14 for mi in one.models)
    assert inputs.models[0].opt.iterations == 1, "the scenario's own models are untouched"


def test_unmodified_mjx_is_far_inside_its_bound(quadruped, fresh_mjx):
    found = _check(quadruped)
    assert found["status"] == "pass" and found["ratio"] < 0.05, found
    assert found["pairs"] == 4 * len(found["states"])


def _gain(monkeypatch):
    orig = mjx_forward.fwd_actuation
    monkeypatch.setattr(mjx_forward, "fwd_actuation",
                        lambda m, d: orig(m.replace(actuator_gainprm=m.actuator_gainprm * 1.02), d))


def _damping(monkeypatch):
    orig = mjx_passive._spring_damper
    monkeypatch.setattr(mjx_passive, "_spring_damper", lambda m, d: orig(m, d) * 1.01)


def _friction(monkeypatch):
    orig = mjx_forward.fwd_position
    monkeypatch.setattr(mjx_forward, "fwd_position",
                        lambda m, d: orig(m.replace(geom_friction=m.geom_friction * 0.9), d))


def _inertia(monkeypatch):
    orig = mjx_smooth.com_pos  # the composite inertias (cinert) of 1% heavier bodies
    monkeypatch.setattr(mjx_smooth, "com_pos", lambda m, d: orig(m.replace(body_mass=m.body_mass * 1.01), d))


#: One bug of each kind, switched in one compile of the quadruped (_bugs.install_switched).
BUGS = (_gain, _damping, _one_percent_more_constraint_force, _friction, _inertia)


@pytest.mark.parametrize("bug", BUGS,
                         ids=["actuator gain", "passive damping", "constraint force", "friction", "inertia"])
def test_injected_bugs_exceed_the_bound_by_orders_of_magnitude(quadruped, bug, fresh_mjx):
    _, m, inputs, _ = quadruped
    with _bugs.live(bug, BUGS, (m, *inputs.models)):
        found = _check(quadruped)
    assert found["status"] == "fail" and found["ratio"] > 10, found
    assert found["field"] in ("qpos", "qvel") and found["object"].startswith("joint ")
    assert 0 <= found["step"] < quadruped[2].steps


def test_every_scenario_carries_the_one_step_verdict(repo_root):
    scenario = load_scenario(str(repo_root / "tests" / "data" / "quadruped_1iter.xml"))
    result = run_scenario(scenario, SweepConfig(seed=0, diagnose="none"))
    assert result.info["onestep"]["status"] == "pass" and result.info["onestep"]["ratio"] < 0.05
    assert "checks: one-step pass: " in report.format_line(result)
    off = run_scenario(scenario, SweepConfig(seed=0, diagnose="none", onestep=False))
    assert "onestep" not in off.info and "one-step" not in report.format_line(off)


def test_a_one_step_failure_fails_the_weak_pass_and_names_the_stage(quadruped, monkeypatch, fresh_mjx):
    """The sweep's second look at a weak pass: the gain bug makes it a failure that names the
    field, the member and step, and the first forward stage that differs from that state."""
    from mjxdiff.runner import followup
    from mjxdiff.runner.stream import Case
    from mjxdiff.compare.verdict import ScenarioResult

    scenario, m, inputs, traj_c = quadruped
    weak = ScenarioResult(name="quadruped_1iter", status="pass", message="worst qpos 3.1 (...)", weak=("qpos",))
    _gain(monkeypatch)
    case = Case("quadruped_1iter", m, inputs, scenario.tolerance, SweepConfig(), MJXEngine(), CEngine())
    result, found, _ = followup._onestep(weak, case, traj_c)
    assert result.status == "fail" and found["status"] == "fail"
    assert result.message.startswith(f"one-step check: {found['field']} of {found['object']} after step ")
    assert found["first_stage"] == "actuation" and "first field to differ: actuator_force (actuation" in result.message
    assert result.first_divergence["check"] == "onestep" and result.first_divergence["member"] == found["member"]
    assert "the rollout alone passed (worst qpos 3.1" in result.message
    # a drill-down that cannot run is said, with why, and the verdict stands without it
    from mjxdiff.compare import diagnose

    monkeypatch.setattr(diagnose, "drill_down", lambda *a, **k: 1 / 0)
    result, found, _ = followup._onestep(weak, case, traj_c)
    assert result.status == "fail" and "first_stage" not in found
    assert found["drill_error"] == "ZeroDivisionError: division by zero", found
    assert "; the drill-down could not run: ZeroDivisionError: division by zero" in result.message


def test_a_converged_model_is_checked_through_its_own_compiled_rollout():
    """Where the model's solver converges, the one-step check steps MJX as configured through the
    sweep's compiled rollout: no compile of its own (one MJX rollout traced or loaded in all)."""
    result = run_scenario(load_scenario("double_pendulum"), SweepConfig(seed=0, diagnose="none", transfer=False))
    one = result.info["onestep"]
    assert one["status"] == "pass" and one["settings"] == "as configured (converged)" and one["solver"]["converged"]
    assert one["pairs"] == result.info["batch"] and one["ratio"] < 0.01, one
    assert result.info["mjx_compiles"] + result.info["mjx_loaded"] == 1, result.info
