"""The sensing scenario reaches MJX code no other scenario traced (a ray against a mesh, camera
projection, contact sensors, the weld torque of force and torque sensors, a clamped joint
actuator force, Euler without implicit damping, site transmissions, a camera that follows its
target), and a one-line slip in any of them is caught there, while every other bundled
model provably leaves that code out (the slip could not show).

Each bug is a monkeypatch of one function inside mujoco.mjx._src (tests/_bugs.py: the catch, and
the same scenario and config passing unmodified).
The scenario's sparse mass matrix is traced but no slip in it is claimed: the inverse diagonal of
the sparse factor 0.1% off moved qvel by 2.9e-9 only, because a converged Newton solver finds
qacc from the mass matrix itself; qacc_smooth is all the factor decides there."""

import mujoco
import numpy as np
import pytest
from mujoco.mjx._src import forward as mjx_forward
from mujoco.mjx._src import ray as mjx_ray
from mujoco.mjx._src import sensor as mjx_sensor
from mujoco.mjx._src import smooth as mjx_smooth
from mujoco.mjx._src.types import GeomType

import _bugs
import test_wider_reach as wider_reach
from _bugs import Expect, caught, model_edited, sweep
from combination_bugs import COVERING_SCENARIOS
from mjxdiff.input.scenario import bundled_scenarios, load_model, load_scenario
from mjxdiff.runner.sweep import SweepConfig

#: The rollout's verdict alone: a catch is the rollout's; the one-step check and the host-interface
#: check (more compiles of each patched MJX) have tests of their own (test_injected_bugs, test_transfer).
CONFIG = SweepConfig(seed=0, batch=2, steps=150, diagnose="none", onestep=False, transfer=False)
_S = mujoco.mjtSensor


def ray_mesh_long(monkeypatch):
    """Rays report mesh hits 1% farther than they are."""
    orig = mjx_ray._RAY_FUNC[GeomType.MESH]

    def longer(*args, **kwargs):
        dist, *rest = orig(*args, **kwargs)
        return (dist * 1.01, *rest)
    monkeypatch.setitem(mjx_ray._RAY_FUNC, GeomType.MESH, longer)


def camprojection_resolution_off(monkeypatch):
    """Camera projections scale by a resolution one pixel larger."""
    model_edited(monkeypatch, mjx_sensor, "sensor_pos", lambda m: m.replace(cam_resolution=m.cam_resolution + 1))


def contact_sensor_high(monkeypatch):
    """Contact sensors report values 1% too large."""
    orig = mjx_sensor._sensor_contact

    def high(*args, **kwargs):
        sensors, adrs = orig(*args, **kwargs)
        return [s * 1.01 for s in sensors], adrs
    monkeypatch.setattr(mjx_sensor, "_sensor_contact", high)


def weld_torquescale_ignored(monkeypatch):
    """Force and torque sensors see welds' torque as if torquescale were 1."""
    model_edited(monkeypatch, mjx_smooth, "rne_postconstraint", lambda m: m.replace(
        eq_data=m.eq_data.at[:, 10].set(1.0)))


def actfrcrange_ignored(monkeypatch):
    """Joint actuator forces are not clamped to actuatorfrcrange."""
    model_edited(monkeypatch, mjx_forward, "fwd_actuation",
                  lambda m: m.replace(jnt_actfrclimited=np.zeros_like(m.jnt_actfrclimited)))


def site_gear_rotation_ignored(monkeypatch):
    """Site transmissions drop the rotational part of their gear (a torque about z here)."""
    model_edited(monkeypatch, mjx_smooth, "transmission",
                  lambda m: m.replace(actuator_gear=m.actuator_gear.at[:, 3:].set(0.0)))


def camera_target_ignored(monkeypatch):
    """Cameras in targetbody mode look at the world origin instead of their target."""
    model_edited(monkeypatch, mjx_smooth, "camlight",
                  lambda m: m.replace(cam_targetbodyid=np.zeros_like(m.cam_targetbodyid)))


def velocity_reference_frame_ignored(monkeypatch):
    """Frame velocity sensors with a reference frame report world-frame values."""
    model_edited(monkeypatch, mjx_sensor, "sensor_vel",
                  lambda m: m.replace(sensor_refid=np.full_like(m.sensor_refid, -1)))


_EULERDAMP = int(mujoco.mjtDisableBit.mjDSBL_EULERDAMP)


def eulerdamp_flag_ignored(monkeypatch):
    """Euler integrates damping implicitly even where the eulerdamp flag is disabled."""
    model_edited(monkeypatch, mjx_forward, "euler", lambda m: m.replace(
        opt=m.opt.replace(disableflags=m.opt.disableflags & ~_EULERDAMP)))


def _has_sensor(m, kind) -> bool:
    return bool(np.any(m.sensor_type == int(kind)))


#: bug -> where its code runs in a model
REACHES = {
    ray_mesh_long: lambda m: _has_sensor(m, _S.mjSENS_RANGEFINDER) and bool(np.any(m.geom_type == int(GeomType.MESH))),
    camprojection_resolution_off: lambda m: _has_sensor(m, _S.mjSENS_CAMPROJECTION),
    contact_sensor_high: lambda m: _has_sensor(m, _S.mjSENS_CONTACT),
    weld_torquescale_ignored: lambda m: bool(np.any(m.eq_type == int(mujoco.mjtEq.mjEQ_WELD))) and (
        _has_sensor(m, _S.mjSENS_FORCE) or _has_sensor(m, _S.mjSENS_TORQUE)),
    actfrcrange_ignored: lambda m: bool(np.any(m.jnt_actfrclimited)),
    site_gear_rotation_ignored: lambda m: bool(np.any(
        (m.actuator_trntype == int(mujoco.mjtTrn.mjTRN_SITE)) & np.any(m.actuator_gear[:, 3:] != 0, axis=1))),
    camera_target_ignored: lambda m: _has_sensor(m, _S.mjSENS_CAMPROJECTION) and bool(np.any(np.isin(
        m.cam_mode, [int(mujoco.mjtCamLight.mjCAMLIGHT_TARGETBODY),
                     int(mujoco.mjtCamLight.mjCAMLIGHT_TARGETBODYCOM)]))),
    velocity_reference_frame_ignored: lambda m: bool(np.any(np.isin(
        m.sensor_type, [int(_S.mjSENS_FRAMELINVEL), int(_S.mjSENS_FRAMEANGVEL)]) & (m.sensor_refid > -1))),
    eulerdamp_flag_ignored: lambda m: bool(m.opt.disableflags & _EULERDAMP) and bool(np.any(m.dof_damping > 0))
    and m.opt.integrator == int(mujoco.mjtIntegrator.mjINT_EULER),
}


@pytest.mark.parametrize("bug", list(REACHES), ids=lambda b: b.__name__)
def test_no_other_scenario_reaches_the_code(bug):
    assert REACHES[bug](load_model(load_scenario("sensing")))
    others = [s.name for s in bundled_scenarios()
              if s.name not in ("sensing", *COVERING_SCENARIOS) and REACHES[bug](load_model(s))]
    assert others == [], f"{bug.__name__} can show in {others} too"


#: bug -> what its catch must name (measured at CONFIG: each at step 0, the object the slip acts on)
_MOVES = ("qpos", "qvel")
CATCHES = {
    ray_mesh_long: Expect(("sensordata",), r"sensor 'down' \(rangefinder\)"),
    camprojection_resolution_off: Expect(("sensordata",), r"sensor 'cube_tracked' \(camprojection\)"),
    contact_sensor_high: Expect(("sensordata",), r"sensor 'strongest' \(contact\)"),
    weld_torquescale_ignored: Expect(("sensordata",), r"sensor 'cube_torque' \(torque\)"),
    actfrcrange_ignored: Expect(_MOVES, r"joint 'yaw'"),
    site_gear_rotation_ignored: Expect(_MOVES, r"joint 'puck'"),
    camera_target_ignored: Expect(("sensordata",), r"sensor 'puck_follow' \(camprojection\)"),
    velocity_reference_frame_ignored: Expect(("sensordata",), r"sensor 'wrist_linvel_rel' \(framelinvel\)"),
    eulerdamp_flag_ignored: Expect(_MOVES, r"joint 'lift'"),
}


def test_every_bug_has_its_expected_catch():
    assert set(CATCHES) == set(REACHES)


#: Every bug the sensing scenario is to catch, this file's and test_wider_reach's, switched in one
#: compile of the scenario (_bugs.install_switched; both files run on one xdist worker).
SWITCHED = [*REACHES, *(bug for bug, (catcher, _, _) in wider_reach.REACHES.items() if catcher == "sensing")]


@pytest.mark.slow  # one compile of the scenario with every bug switched (about 70 s), then a loaded run each
@pytest.mark.parametrize("bug", list(REACHES), ids=lambda b: b.__name__)
def test_the_sensing_scenario_catches_it(bug):
    caught(bug, "sensing", CONFIG, CATCHES[bug], among=SWITCHED)


@pytest.mark.slow
def test_with_no_bug_live_the_switched_set_passes_as_unmodified_mjx_does():
    """The switch's off position is unmodified MJX: every check passes with each field's worst
    error the unmodified sweep's (measured equal to the bit; the selects could change XLA's
    fusion, not its arithmetic)."""
    off, clean = sweep("sensing", CONFIG, None, among=SWITCHED), _bugs.clean("sensing", CONFIG)
    assert off.status == clean.status == "pass", off.message
    assert [f.field for f in off.fields] == [f.field for f in clean.fields]
    for f, g in zip(off.fields, clean.fields):
        assert f.ok and f.max_error == pytest.approx(g.max_error, rel=1e-6), (f, g)
