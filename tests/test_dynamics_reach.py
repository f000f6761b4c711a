"""Dynamics a source-mutation audit of MJX 3.17 found unreached (2026-12): two one-line slips in
the integrator and the passive forces that passed every bundled scenario, each now caught by
ball_joint, whose model reaches the branch, and each paired with ball_joint passing unmodified.

* Euler's implicit damping on a sparse mass matrix adds ``timestep * dof_damping`` one entry past
  each row's diagonal (forward.euler: ``diag_adr = m.M_rowadr + m.M_rownnz``, the ``- 1``
  dropped): the first entry of the next row, nothing for the last one. Only ``sensing`` was
  sparse, and it disables eulerdamp (a global flag it is there to test), so the branch was never
  run. ball_joint is now sparse with eulerdamp on: its ball joints' damped dofs have ancestors,
  so a row holds several entries and its diagonal is its last (the row start, and qM's diagonal
  address ``dof_Madr``, are caught alike at step 0 on the elbow: measured).
* The free joint's rotational spring subtracts the quaternions the wrong way round
  (passive._spring_damper: ``quat_sub(qs, q)``, the rotation from the body to its rest frame):
  the spring pushes away from rest. No scenario had a free joint with stiffness (humanoid's root
  has none). ball_joint's ``buoy`` hangs on its free joint's spring (stiffness 8, damping 0.05)
  to a rest frame turned 60 degrees away from the world's (a slip that forgot the rest frame
  would show too); the randomized start turns it away from rest.

Each bug is the audit's own mutation: the function's source with one line changed, compiled in
its module's namespace and patched in for the test (:func:`_bugs.mutant`)."""

import mujoco
import numpy as np
import pytest
from mujoco.mjx._src import forward as mjx_forward
from mujoco.mjx._src import passive as mjx_passive

from _bugs import Expect, caught, mutant
from mjxdiff.input.scenario import load_model, load_scenario
from mjxdiff.runner.sweep import SweepConfig

#: The rollout's verdict alone, as in test_contact_geometry.
CONFIG = SweepConfig(seed=0, batch=2, steps=150, diagnose="none", onestep=False, transfer=False)


def sparse_damping_past_the_diagonal(monkeypatch):
    """Euler adds the implicit damping of a sparse mass matrix's row one entry past its diagonal."""
    monkeypatch.setattr(mjx_forward, "euler", mutant(
        mjx_forward, mjx_forward.euler,
        "diag_adr = m.M_rowadr + m.M_rownnz - 1", "diag_adr = m.M_rowadr + m.M_rownnz"))


def free_spring_quaternions_swapped(monkeypatch):
    """A free joint's rotational spring turns the body from its rest frame instead of back to it."""
    monkeypatch.setattr(mjx_passive, "_spring_damper", mutant(
        mjx_passive, mjx_passive._spring_damper,
        "qfrc = qfrc.at[3:6].set(-stiffness[i] * math.quat_sub(q[3:7], qs[3:7]))",
        "qfrc = qfrc.at[3:6].set(-stiffness[i] * math.quat_sub(qs[3:7], q[3:7]))"))


_MOVES = ("qpos", "qvel")
#: bug -> (the scenario that catches it, what its catch must name: measured at CONFIG, step 0)
CATCHES = {
    sparse_damping_past_the_diagonal: ("ball_joint", Expect(_MOVES, r"joint 'elbow'")),
    free_spring_quaternions_swapped: ("ball_joint", Expect(_MOVES, r"joint 'buoy'")),
}


def _model():
    return load_model(load_scenario("ball_joint"))


def test_ball_joint_integrates_damping_implicitly_on_rows_whose_diagonal_is_not_alone():
    m = _model()
    assert m.opt.jacobian == mujoco.mjtJacobian.mjJAC_SPARSE
    assert m.opt.integrator == mujoco.mjtIntegrator.mjINT_EULER
    assert not m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_EULERDAMP
    elbow = m.jnt_dofadr[m.joint("elbow").id] + np.arange(3)
    assert np.all(m.dof_damping[elbow] > 0) and np.all(m.M_rownnz[elbow] > 1)


def test_the_buoy_springs_back_to_a_turned_rest_frame():
    m = _model()
    j = m.joint("buoy").id
    assert m.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE and m.jnt_stiffness[j] > 0
    rest = m.qpos_spring[m.jnt_qposadr[j] + 3:m.jnt_qposadr[j] + 7]
    assert 2 * np.arccos(min(abs(rest[0]), 1.0)) > 0.5  # radians from the world's frame
    assert load_scenario("ball_joint").randomize.qpos_noise > 0  # the start is turned off rest


@pytest.mark.slow  # two compiles of ball_joint (unmodified, and with its bug)
@pytest.mark.parametrize("bug", list(CATCHES), ids=lambda b: b.__name__)
def test_the_scenario_that_reaches_it_catches_it(bug):
    scenario, expect = CATCHES[bug]
    caught(bug, scenario, CONFIG, expect)
