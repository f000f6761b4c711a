"""The tester catches bugs: subtly wrong MJX internals make the sweep fail,
naming the field, the object and the step; unmodified MJX passes the same
scenarios. Each bug is a monkeypatch of one function inside mujoco.mjx._src."""

import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco.mjx._src import collision_driver as mjx_collision
from mujoco.mjx._src import forward as mjx_forward
from mujoco.mjx._src import math as mjx_math
from mujoco.mjx._src import passive as mjx_passive
from mujoco.mjx._src import sensor as mjx_sensor

import _bugs
from mjxdiff.input.inputs import make_inputs
from mjxdiff.input.scenario import load_model, load_scenario
from mjxdiff.runner.sweep import SweepConfig, run_scenario

# Detection is the rollout verdict's job: the diagnosis of these bugs is tested in test_diagnose.py,
# the one-step and host-interface checks (more compiles of each patched MJX) in test_onestep.py
# and test_transfer.py.
CONFIG = SweepConfig(seed=0, batch=4, diagnose="none", onestep=False, transfer=False)


def extra_damping(monkeypatch):
    """0.1% more joint damping force than the model says."""
    orig = mjx_passive._spring_damper
    monkeypatch.setattr(mjx_passive, "_spring_damper", lambda m, d: orig(m, d) - 1e-3 * m.dof_damping * d.qvel)


def jointvel_sensor_gain(monkeypatch):
    """jointvel sensors read 0.1% high."""
    orig = mjx_sensor.sensor_vel

    def buggy(m, d):
        d = orig(m, d)
        idx = np.concatenate([np.arange(m.sensor_adr[s], m.sensor_adr[s] + m.sensor_dim[s])
                              for s in np.flatnonzero(m.sensor_type == mujoco.mjtSensor.mjSENS_JOINTVEL)])
        return d.replace(sensordata=d.sensordata.at[idx].multiply(1 + 1e-3))

    monkeypatch.setattr(mjx_sensor, "sensor_vel", buggy)


def actuator_gain(monkeypatch):
    """Actuator gain (gainprm[0]) 0.1% too high."""
    orig = mjx_forward.fwd_actuation
    monkeypatch.setattr(mjx_forward, "fwd_actuation",
                        lambda m, d: orig(m.replace(
                            actuator_gainprm=m.actuator_gainprm.at[:, 0].multiply(1 + 1e-3)), d))


def contact_friction(monkeypatch):
    """Contacts get 1% less friction than the geoms combine to."""
    orig = mjx_collision.collision

    def buggy(m, d):
        d = orig(m, d)
        c = d._impl.contact
        return d.replace(_impl=d._impl.replace(contact=c.replace(friction=c.friction * 0.99)))

    monkeypatch.setattr(mjx_collision, "collision", buggy)


def quaternion_update(monkeypatch):
    """Quaternion integration rotates 0.01% too far."""
    orig = mjx_math.quat_integrate
    monkeypatch.setattr(mjx_math, "quat_integrate", lambda q, v, dt: orig(q, v, dt * (1 + 1e-4)))


# bug -> (scenario that should catch it, fields allowed to be named first, object pattern)
BUGS = {
    extra_damping: ("pendulum", {"qpos", "qvel"}, r"joint 'hinge'"),
    jointvel_sensor_gain: ("pendulum", {"sensordata"}, r"sensor '.*' \(jointvel\)"),
    actuator_gain: ("pendulum", {"qpos", "qvel"}, r"joint 'hinge'"),
    contact_friction: ("slope_slide", {"qpos", "qvel"}, r"joint '.*'"),
    quaternion_update: ("ball_joint", {"qpos", "sensordata"}, r"(joint|sensor) '.*'"),
}


@pytest.mark.parametrize("bug", list(BUGS), ids=lambda b: b.__name__)
def test_injected_bug_is_caught(bug):
    scenario_name, fields, obj = BUGS[bug]
    first = _bugs.caught(bug, scenario_name, CONFIG, _bugs.Expect(tuple(fields), obj))
    # t is the simulated time after that step: (step + 1) * the member's (randomized) timestep
    scenario = load_scenario(scenario_name)
    dt = load_model(scenario).opt.timestep
    lo, hi = scenario.randomize.scale["timestep"]
    assert lo * dt * (first["step"] + 1) * (1 - 1e-9) <= first["time"] <= hi * dt * (first["step"] + 1) * (1 + 1e-9)


@pytest.mark.parametrize("scenario_name", sorted({s for s, _, _ in BUGS.values()}))
def test_unmodified_mjx_passes(scenario_name):
    """The controls of the catches above, on their own (shared with them: one run each)."""
    _bugs.assert_passes_clean(scenario_name, CONFIG)
    assert all(f.ok for f in _bugs.clean(scenario_name, CONFIG).fields)


def test_mjx_going_non_finite_where_c_does_not_is_a_fail_at_that_step(monkeypatch, fresh_mjx):
    """The strongest divergence there is: MJX's passive force turns NaN from t > 0.1025 s (step 21
    of the 5 ms pendulum); C stays finite. A fail (not an error) naming the step, the fields that
    were still finite, and a diagnosis of the state before it."""
    orig = mjx_passive._spring_damper
    monkeypatch.setattr(mjx_passive, "_spring_damper",
                        lambda m, d: orig(m, d) + jnp.where(d.time > 0.1025, jnp.nan, 0.0))
    scenario = load_scenario("pendulum")
    result = run_scenario(scenario, SweepConfig(seed=0, batch=2, steps=60, diagnose="basic"))
    assert result.status == "fail", result.message
    # members have randomized timesteps: the first step that starts after t = 0.1025 s
    models = make_inputs(scenario, load_model(scenario), 0, 2, 60).models
    expected = [int(np.floor(0.1025 / mi.opt.timestep)) + 1 for mi in models]
    assert [(d["engine"], d["step"], d["last_finite_step"]) for d in result.diverged_members] == [
        ("mjx", k, k - 1) for k in expected]
    first = min(expected)
    assert f"MJX goes non-finite at step {first}" in result.message and "still finite:" in result.message
    assert result.first_divergence["step"] == first
    drill = result.diagnosis["drill_down"]
    assert drill["step"] == first and drill["first_field"] == "qfrc_passive", drill
