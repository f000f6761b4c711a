"""Code the bundled scenarios reach since the coverage round of 2026-11-24 (tendon pulleys and
geom wrapping, actuators acting in a ball or free joint's parent frame, a rotated mocap body,
a maxforce contact sensor, tendon armature with a sparse mass matrix, tendon damping under
implicitfast, a camera in track mode; since 2026-11-29 gravity compensation routed through a
joint's actuators): a one-line slip in each is caught by the scenario that
now reaches it, while every other bundled model provably leaves that code out.

Each bug is a monkeypatch of one function inside mujoco.mjx._src that ignores one parameter or
mode (uses the default instead), as in test_parameter_families and test_sensing_scenario."""

import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco.mjx._src import derivative as mjx_derivative
from mujoco.mjx._src import passive as mjx_passive
from mujoco.mjx._src import sensor as mjx_sensor
from mujoco.mjx._src import smooth as mjx_smooth
from mujoco.mjx._src import support as mjx_support

from _bugs import Expect, caught, model_edited
from combination_bugs import COVERING_SCENARIOS
from mjxdiff.compat import data_impl, with_impl
from mjxdiff.input.scenario import bundled_scenarios, load_model, load_scenario
from mjxdiff.runner.sweep import SweepConfig

#: The rollout's verdict alone: a catch is the rollout's; the one-step check and the host-interface
#: check (more compiles of each patched MJX) have tests of their own (test_injected_bugs, test_transfer).
CONFIG = SweepConfig(seed=0, batch=2, steps=150, diagnose="none", onestep=False, transfer=False)
_W, _T, _S = mujoco.mjtWrap, mujoco.mjtTrn, mujoco.mjtSensor


def pulley_divisor_ignored(monkeypatch):
    """Tendon branches after a pulley count in full, as if every divisor were 1."""
    model_edited(monkeypatch, mjx_smooth, "tendon", lambda m: m.replace(
        wrap_prm=np.where(np.asarray(m.wrap_type) == int(_W.mjWRAP_PULLEY), 1.0, np.asarray(m.wrap_prm))))


def wrap_radius_off(monkeypatch):
    """Tendons wrap spheres and cylinders 1% larger than the geoms are."""
    model_edited(monkeypatch, mjx_smooth, "tendon", lambda m: m.replace(geom_size=m.geom_size * 1.01))


def jointinparent_as_joint(monkeypatch):
    """Actuators acting in a ball or free joint's parent frame act in the child frame instead."""
    model_edited(monkeypatch, mjx_smooth, "transmission", lambda m: m.replace(actuator_trntype=np.where(
        np.asarray(m.actuator_trntype) == int(_T.mjTRN_JOINTINPARENT), int(_T.mjTRN_JOINT),
        np.asarray(m.actuator_trntype))))


def mocap_quat_ignored(monkeypatch):
    """Mocap bodies keep the identity orientation whatever mocap_quat says."""
    orig = mjx_smooth.kinematics

    def kinematics(m, d):
        return orig(m, d.replace(mocap_quat=jnp.zeros_like(d.mocap_quat).at[:, 0].set(1.0)))
    monkeypatch.setattr(mjx_smooth, "kinematics", kinematics)


def maxforce_reduction_as_mindist(monkeypatch):
    """Contact sensors asked for the strongest contact report the deepest one."""
    model_edited(monkeypatch, mjx_sensor, "sensor_acc", lambda m: m.replace(sensor_intprm=np.where(
        (np.asarray(m.sensor_type)[:, None] == int(_S.mjSENS_CONTACT)) & (np.arange(3) == 1)
        & (np.asarray(m.sensor_intprm) == 2), 1, np.asarray(m.sensor_intprm))))


def sparse_tendon_armature_ignored(monkeypatch):
    """Tendon armature is lost from a sparse mass matrix (the dense one keeps it)."""
    model_edited(monkeypatch, mjx_smooth, "tendon_armature", lambda m: m.replace(
        tendon_armature=jnp.zeros_like(m.tendon_armature)) if mjx_support.is_sparse(m) else m)


def implicit_tendon_damping_ignored(monkeypatch):
    """implicitfast leaves tendon damping out of the velocity derivative it integrates with."""
    model_edited(monkeypatch, mjx_derivative, "deriv_smooth_vel",
                  lambda m: m.replace(tendon_damping=jnp.zeros_like(m.tendon_damping)))


def track_camera_fixed(monkeypatch):
    """Cameras in track mode stay where the model put them instead of following their body."""
    model_edited(monkeypatch, mjx_smooth, "camlight", lambda m: m.replace(cam_mode=np.where(
        np.asarray(m.cam_mode) == int(mujoco.mjtCamLight.mjCAMLIGHT_TRACK), int(mujoco.mjtCamLight.mjCAMLIGHT_FIXED),
        np.asarray(m.cam_mode))))


def actgravcomp_routing_ignored(monkeypatch):
    """Gravity compensation of a joint with actuatorgravcomp also goes into qfrc_passive: counted twice
    (a source mutation of MJX's passive that passed every bundled scenario before gravcomp_arm's elbow
    got actuatorgravcomp)."""
    model_edited(monkeypatch, mjx_passive, "passive", lambda m: m.replace(
        jnt_actgravcomp=np.zeros_like(np.asarray(m.jnt_actgravcomp))))


def implicit_affine_gain_velocity_ignored(monkeypatch):
    """implicitfast leaves an affine gain's velocity term (gainprm[2] * ctrl) out of the velocity
    derivative it integrates with (a blind spot of a source-mutation audit: no implicit scenario
    had such an actuator before integrator_implicitfast's a3)."""
    model_edited(monkeypatch, mjx_derivative, "deriv_smooth_vel",
                  lambda m: m.replace(actuator_gainprm=m.actuator_gainprm.at[:, 2].set(0.0)))


def touch_ray_unflipped(monkeypatch):
    """Touch sensors cast every contact's ray as if the sensor's body were the contact's first,
    never flipping it for the second (a source mutation of MJX's sensor_acc that passed every
    bundled scenario while imu_sensors' sole site enclosed the contact points)."""
    orig = mjx_sensor.sensor_acc

    def sensor_acc(m, d):
        c = data_impl(d).contact
        return orig(m, with_impl(d, contact=c.replace(geom=c.geom[:, ::-1], geom1=c.geom2, geom2=c.geom1)))
    monkeypatch.setattr(mjx_sensor, "sensor_acc", sensor_acc)


def _wraps(m, *kinds) -> bool:
    return bool(np.isin(m.wrap_type, [int(k) for k in kinds]).any())


def _camprojection_on(m, mode) -> bool:
    cams = m.sensor_refid[m.sensor_type == int(_S.mjSENS_CAMPROJECTION)]
    return bool(np.any(m.cam_mode[cams] == int(mode)))


_BALL_OR_FREE = [int(mujoco.mjtJoint.mjJNT_BALL), int(mujoco.mjtJoint.mjJNT_FREE)]

#: bug -> (the scenario that catches it, the other scenarios that reach it since this round,
#: where its code runs in a model)
REACHES = {
    pulley_divisor_ignored: ("tendons", (), lambda m: _wraps(m, _W.mjWRAP_PULLEY)),
    wrap_radius_off: ("tendons", (), lambda m: _wraps(m, _W.mjWRAP_SPHERE, _W.mjWRAP_CYLINDER)),
    jointinparent_as_joint: ("ball_joint", ("sensing",), lambda m: bool(np.any(
        (m.actuator_trntype == int(_T.mjTRN_JOINTINPARENT))
        & np.isin(m.jnt_type[np.clip(m.actuator_trnid[:, 0], 0, None)], _BALL_OR_FREE)))),
    mocap_quat_ignored: ("sensing", (), lambda m: bool(np.any(
        np.abs(m.body_quat[m.body_mocapid >= 0] - [1, 0, 0, 0]) > 1e-6))),
    maxforce_reduction_as_mindist: ("sensing", (), lambda m: bool(np.any(
        (m.sensor_type == int(_S.mjSENS_CONTACT)) & (m.sensor_intprm[:, 1] == 2)))),
    sparse_tendon_armature_ignored: ("sensing", (), lambda m: bool(np.any(m.tendon_armature > 0))
                                      and m.opt.jacobian == int(mujoco.mjtJacobian.mjJAC_SPARSE)),
    implicit_tendon_damping_ignored: ("integrator_implicitfast", (), lambda m: bool(
        m.opt.integrator == int(mujoco.mjtIntegrator.mjINT_IMPLICITFAST) and np.any(m.tendon_damping > 0))),
    track_camera_fixed: ("sensing", (), lambda m: _camprojection_on(m, mujoco.mjtCamLight.mjCAMLIGHT_TRACK)),
    actgravcomp_routing_ignored: ("gravcomp_arm", (), lambda m: bool(np.any(m.jnt_actgravcomp))),
    implicit_affine_gain_velocity_ignored: ("integrator_implicitfast", (), lambda m: bool(
        m.opt.integrator == int(mujoco.mjtIntegrator.mjINT_IMPLICITFAST) and np.any(
            (m.actuator_gaintype == int(mujoco.mjtGain.mjGAIN_AFFINE)) & (m.actuator_gainprm[:, 2] != 0)))),
    # slope_slide's touch site is a 1 cm sphere at the block's centre: corner contacts' rays miss it
    touch_ray_unflipped: ("imu_sensors", ("slope_slide",),
                          lambda m: bool(np.any(m.sensor_type == int(_S.mjSENS_TOUCH)))),
}


@pytest.mark.parametrize("bug", list(REACHES), ids=lambda b: b.__name__)
def test_no_other_scenario_reaches_the_code(bug):
    catcher, also, reaches = REACHES[bug]
    assert reaches(load_model(load_scenario(catcher)))
    others = [s.name for s in bundled_scenarios()
              if s.name != catcher and s.name not in (*also, *COVERING_SCENARIOS) and reaches(load_model(s))]
    assert others == [], f"{bug.__name__} can show in {others} too"


#: bug -> what its catch must name (measured at CONFIG: each at step 0 or 1, the object the slip acts on)
_MOVES = ("qpos", "qvel")
CATCHES = {
    pulley_divisor_ignored: Expect(_MOVES, r"joint 's1'"),
    wrap_radius_off: Expect(_MOVES, r"joint 'h2'"),
    jointinparent_as_joint: Expect(_MOVES, r"joint 'elbow'"),
    mocap_quat_ignored: Expect(("sensordata",), r"sensor 'target_quat' \(framequat\)"),
    maxforce_reduction_as_mindist: Expect(("sensordata",), r"sensor 'strongest' \(contact\)"),
    sparse_tendon_armature_ignored: Expect(_MOVES, r"joint 'pitch'"),
    implicit_tendon_damping_ignored: Expect(_MOVES, r"joint 'j3'"),
    track_camera_fixed: Expect(("sensordata",), r"sensor 'cube_tracked' \(camprojection\)"),
    actgravcomp_routing_ignored: Expect((*_MOVES, "sensordata"), r"joint 'elbow'|sensor 'elbow_actfrc' \(.*\)"),
    implicit_affine_gain_velocity_ignored: Expect((*_MOVES, "sensordata"), r"joint 'j3'|sensor 'j3_pos' \(.*\)"),
    touch_ray_unflipped: Expect(("sensordata",), r"sensor 'sole_touch' \(touch\)"),
}


def test_every_bug_has_its_expected_catch():
    assert set(CATCHES) == set(REACHES)


@pytest.mark.slow  # one compile of each scenario with its bugs switched (~35-70 s), then a loaded run each
@pytest.mark.parametrize("bug", list(REACHES), ids=lambda b: b.__name__)
def test_the_scenario_that_reaches_it_catches_it(bug):
    catcher, _, _ = REACHES[bug]
    if catcher == "sensing":  # switched with the sensing scenario's own bugs: one compile for all
        from test_sensing_scenario import SWITCHED as among
    else:
        among = [b for b, (c, _, _) in REACHES.items() if c == catcher]
    caught(bug, catcher, CONFIG, CATCHES[bug], among=among)
