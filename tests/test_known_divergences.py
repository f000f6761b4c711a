"""Divergences of unmodified MJX found while widening the scenarios, each a strict xfail: it
fails (as expected) while MJX differs from C, and starts passing, turning the suite red, the
day MJX is fixed, so that the scenario it was kept out of can take it back."""

from pathlib import Path

import jax
import mujoco
import numpy as np
import pytest
from mujoco import mjx

from _preconditions import precondition
from mjxdiff.engine import engines
from mjxdiff.compat import jit_for_few_calls
from mjxdiff.compare.support import CATALOGUE, Entry

ROOT = Path(__file__).resolve().parent.parent
#: The catalogue's MJX bugs, each with its bundle (``mjxdiff shrink --bundle`` of tests/data/known/ID.xml).
BUGS = [e for e in CATALOGUE if e.kind == "bug" and "mjx" in e.impl]


def run_bundle(entry: Entry) -> int:
    """The exit code of the entry's bundle's ``repro.py``, run in this process as ``python
    repro.py`` would (1 while MJX and C differ), its printout kept from the test's output."""
    import contextlib
    import io
    import runpy

    with contextlib.redirect_stdout(io.StringIO()):
        try:
            runpy.run_path(str(ROOT / entry.bundle / "repro.py"), run_name="__main__")
        except SystemExit as e:
            return int(e.code or 0)
    return 0


@pytest.mark.xfail(raises=AssertionError, reason="each an MJX 3.17 bug of the catalogue (its evidence, and the "
                   "bundle's README.md); the bundle was shrunk from tests/data/known/ID.xml or a fuzz find")
@pytest.mark.parametrize("entry", BUGS, ids=[e.id for e in BUGS])
def test_the_catalogued_mjx_bug_is_fixed(entry):
    assert run_bundle(entry) == 0, f"{entry.id}: MJX still differs from C ({entry.bundle}/README.md)"


@pytest.mark.xfail(raises=AssertionError, reason="MJX 3.17: a plane-capsule contact has the fixed "
                   "tangent frame (0, 1, 0) where C's first tangent follows the capsule's axis; with a pyramidal cone "
                   "the friction pyramid turns: both solvers converge (3 iterations each, and 200 with tolerance 0) "
                   "to qacc 2.85 apart at step 25 of fuzz seed 2's member 22 (tests/data), with the same contacts, "
                   "mass matrix and smooth forces")
def test_plane_capsule_contacts_have_c_s_tangent_frame():
    m = mujoco.MjModel.from_xml_string(
        "<mujoco><worldbody><geom type='plane' size='1 1 .1'/><body pos='0 0 0.04' euler='1.4 0.3 0.7'>"
        "<freejoint/><geom type='capsule' size='0.05 0.1'/></body></worldbody></mujoco>")
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    dx = engines.forward(mjx.put_model(m), mjx.make_data(m))
    c = dx._impl.contact
    precondition(d.ncon == 1 and int((np.asarray(c.dist) < 0).sum()) == 1, "one contact on both sides")
    frame = np.asarray(c.frame)[np.asarray(c.dist) < 0].reshape(9)
    np.testing.assert_allclose(frame[:3], d.contact.frame[0][:3], atol=1e-9, err_msg="normal")
    np.testing.assert_allclose(frame[3:6], d.contact.frame[0][3:6], atol=1e-6, err_msg="first tangent")


@pytest.mark.xfail(raises=AssertionError, reason="MJX 3.17: plane_cylinder returns the near cap's three "
                   "contacts only; C also adds the far cap's lowest point when it is within the margin, so a cylinder "
                   "lying on its side (a wheel) rests on 2 contacts in C and 1 in MJX. Found by fuzz seed 2 once its "
                   "known-divergence filter stopped excusing every constrained divergence")
def test_a_cylinder_lying_on_a_plane_touches_it_at_both_caps():
    from mjxdiff.compare.diagnose import _contacts_c, _contacts_mjx

    m, d, dx = _forward_both(
        "<mujoco><compiler angle='radian'/><worldbody><geom type='plane' size='1 1 .1'/>"
        "<body pos='0 0 0.099' euler='0 1.5608 0'>"
        "<freejoint/><geom type='cylinder' size='0.1 0.2' margin='0.01'/></body></worldbody></mujoco>")
    precondition(len(_contacts_c(m, d)[(0, 1)]) == 2, "C: one contact on each cap's rim")
    assert len(_contacts_mjx(m, dx).get((0, 1), [])) == 2


@pytest.mark.xfail(raises=AssertionError, reason="MJX 3.17 collides a sphere, capsule, ellipsoid or cylinder with an "
                   "ellipsoid or cylinder by 10 steps of gradient descent on an SDF clearance (collision_sdf.py), "
                   "C 4.0 by GJK/EPA or analytically: an ellipsoid resting on a cylinder's top is 4.001 mm deep in C "
                   "along the axis, 3.575 mm in MJX along a normal tilted 0.033 rad (qacc 27.8 apart). Found by "
                   "fuzzing: tests/data/fuzz_ellipsoid_cylinder_contact.json, 2.882 mm in C, 1.354 mm in MJX")
def test_an_ellipsoid_resting_on_a_cylinder_gets_c_s_contact():
    _, d, dx = _forward_both(
        "<mujoco><worldbody><geom type='cylinder' size='0.1 0.1' pos='0 0 0.1'/>"
        "<body pos='0.03 0 0.266' euler='0.3 0.2 0'><freejoint/><geom type='ellipsoid' size='0.12 0.08 0.07'/>"
        "</body></worldbody></mujoco>")
    c = dx._impl.contact
    active = np.asarray(c.dist) < np.asarray(c.includemargin)
    precondition(d.ncon == 1 and int(active.sum()) == 1, "one contact on both sides")
    np.testing.assert_allclose(np.asarray(c.dist)[active], d.contact.dist[:1], atol=1e-6, err_msg="depth")
    np.testing.assert_allclose(np.asarray(c.frame).reshape(-1, 9)[active][0, :3], d.contact.frame[0][:3], atol=1e-6,
                               err_msg="normal")


def _forward_both(xml: str, **state):
    """(m, C's data, MJX's data) after ``mj_forward`` and ``mjx.forward`` from the same state
    (``qpos``/``qvel`` entries set by index: ``qvel={3: 1.0}``). MJX starts from fresh data, not
    put_data, which would carry C's results over."""
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    for field, values in state.items():
        for i, v in values.items():
            getattr(d, field)[i] = v
    mujoco.mj_forward(m, d)
    dx = engines.forward(mjx.put_model(m), mjx.make_data(m).replace(
        qpos=d.qpos.copy(), qvel=d.qvel.copy(), ctrl=d.ctrl.copy(), act=d.act.copy()))
    return m, d, dx


def _step_both(xml: str, qvel: list[float]):
    """(C's data, MJX's data) after one ``mj_step`` and one ``mjx.step`` from qpos0 and ``qvel``."""
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    d.qvel[:] = qvel
    dx = mjx.make_data(m).replace(qvel=d.qvel.copy())
    mujoco.mj_step(m, d)
    return d, jit_for_few_calls(mjx.step)(mjx.put_model(m), dx)


POLYNOMIAL_SPRING_DAMPER = """<mujoco>
  <worldbody><body>
    <joint type="hinge" axis="0 1 0" damping="0.05 0.5 0.3" stiffness="1 2 4"/>
    <geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.03" mass="1"/>
  </body></worldbody>
</mujoco>"""


@pytest.mark.xfail(raises=AssertionError, reason="MJX 3.17 ignores polynomial joint springs and dampers "
                                       "(jnt_stiffnesspoly, dof_dampingpoly: the 2nd and 3rd values of "
                                       "stiffness=/damping=); at qpos 0.3, qvel 1 the passive force is -1.438 in "
                                       "C, -0.35 in MJX. put_model accepts the model silently; a sweep of it "
                                       "fails at step 0 (qvel 0.78 off)")
def test_polynomial_springs_and_dampers_act():
    m, d, dx = _forward_both(POLYNOMIAL_SPRING_DAMPER, qpos={0: 0.3}, qvel={0: 1.0})
    precondition(abs(m.jnt_stiffnesspoly).sum() > 0 and abs(m.dof_dampingpoly).sum() > 0, "polynomial terms compiled")
    np.testing.assert_allclose(np.asarray(dx.qfrc_passive), d.qfrc_passive, atol=1e-9, err_msg="qfrc_passive")


SPHERE_IN_HFIELD_VALLEY = """<mujoco>
  <asset><hfield name="h" nrow="5" ncol="5" size="1 1 0.2 0.05"
    elevation="1 .5 0 .5 1  1 .5 0 .5 1  1 .5 0 .5 1  1 .5 0 .5 1  1 .5 0 .5 1"/></asset>
  <worldbody>
    <geom type="hfield" hfield="h"/>
    <body pos="0.1 0.03 0.104"><freejoint/><geom type="sphere" size="0.1" mass="1"/></body>
  </worldbody>
</mujoco>"""


@pytest.mark.xfail(raises=AssertionError, reason="MJX 3.17's hfield_sphere keeps only the contacts within 1 mm of the "
                                       "deepest (a manifold of at most 4); C keeps one per prism the sphere "
                                       "penetrates. A sphere across a valley: C 2 contacts (-12.3, -17.6 mm), "
                                       "MJX 1 (-17.6 mm), qacc 16.4 apart. Found writing a terrain scenario "
                                       "(sphere, capsule, box, mesh on a heightfield), which fails on unmodified "
                                       "MJX and is therefore not bundled; MJX's hfield code stays untraced")
def test_a_sphere_across_a_heightfield_crease_gets_every_contact():
    _, d, dx = _forward_both(SPHERE_IN_HFIELD_VALLEY)
    precondition(d.ncon == 2, "C: one contact per prism the sphere penetrates")
    np.testing.assert_allclose(np.asarray(dx.qacc), d.qacc, atol=1e-6, err_msg="qacc")


BOX_ON_A_HEIGHTFIELD_SLOPE = """<mujoco>
  <asset><hfield name="h" nrow="9" ncol="9" size="1 1 0.1 0.05" elevation="%s"/></asset>
  <worldbody>
    <geom type="hfield" hfield="h"/>
    <body pos="0.13 0.07 0.2"><freejoint/><geom type="box" size="0.1 0.08 0.05"/></body>
  </worldbody>
</mujoco>""" % " ".join(str(round(0.3 * (i % 9) / 8, 3)) for i in range(81))


@pytest.mark.xfail(raises=AssertionError, reason="MJX 3.17's hfield_convex: a box resting on a gentle heightfield "
                                       "slope (0.05) gets 4 contacts 6.9-7.9 mm deep in MJX, 3 contacts 4.5-6.1 mm "
                                       "deep in C, qacc z 1.11 vs 12.8; a capsule on flat terrain gets 2 "
                                       "contacts in MJX, 4 in C. No heightfield pair agrees, so no bundled "
                                       "scenario has a heightfield")
def test_a_box_on_a_heightfield_slope_gets_the_contacts_c_gives():
    _, d, dx = _forward_both(BOX_ON_A_HEIGHTFIELD_SLOPE,
                             qpos=dict(enumerate([0.1287, 0.0702, 0.1015, 0.9999, -0.0031, -0.0138, 0.0002])))
    precondition(d.ncon == 3, "C: three contacts on the slope")
    np.testing.assert_allclose(np.asarray(dx.qacc), d.qacc, atol=1e-6, err_msg="qacc")


ELLIPSOID_FLUID_MODEL = """<mujoco>
  <option density="1.2" viscosity="0.00002" wind="1 0 0"/>
  <worldbody>
    <body pos="0 0 1"><freejoint/><geom type="box" size="0.1 0.05 0.02" mass="0.05" fluidshape="ellipsoid"/></body>
  </worldbody>
</mujoco>"""


@pytest.mark.xfail(raises=AssertionError, reason="MJX 3.17 ignores fluidshape='ellipsoid' (geom_fluid) and applies the "
                                       "inertia-box fluid model to every body, silently: a falling plate's fluid "
                                       "force on z is 0.0158 in C, 0.0120 in MJX (C's own inertia-box value); "
                                       "a sweep of it fails at step 0")
def test_the_ellipsoid_fluid_model_is_used_where_a_geom_asks_for_it():
    m, d, dx = _forward_both(ELLIPSOID_FLUID_MODEL, qvel=dict(enumerate([0.5, 0.2, -1, 1, 2, 0.5])))
    precondition(m.geom_fluid[0, 0] == 1, "the geom asks for the ellipsoid model")
    np.testing.assert_allclose(np.asarray(dx.qfrc_passive), d.qfrc_passive, atol=1e-9, err_msg="qfrc_passive")


MARGIN_CONTACT = """<mujoco>
  <worldbody>
    <geom name="floor" type="plane" size="1 1 .1"/>
    <body pos="0 0 0.102"><freejoint/><geom type="sphere" size="0.1" margin="0.005"/></body>
  </worldbody>
</mujoco>"""


@pytest.mark.xfail(raises=ValueError, reason="MJX 3.17 with MuJoCo 4.0: mjx.get_state does not know mjSTATE_PLASTIC "
                                   "(new in MuJoCo 4), which mjSTATE_PHYSICS, FULLPHYSICS and INTEGRATION "
                                   "include, so get_state with any of them raises ValueError; mjxdiff's "
                                   "transfer check lists the element as unsupported")
def test_get_state_takes_the_physics_state_spec():
    m = mujoco.MjModel.from_xml_string(MARGIN_CONTACT)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    spec = mujoco.mjtState.mjSTATE_PHYSICS
    expected = np.empty(mujoco.mj_stateSize(m, spec))
    mujoco.mj_getState(m, d, expected, spec)
    np.testing.assert_array_equal(np.asarray(mjx.get_state(mjx.put_model(m), mjx.put_data(m, d), spec)), expected)


@pytest.mark.xfail(raises=AssertionError, reason="MJX 3.17: d(orientation after a step) / d(angular "
                   "velocity) is 0 for a free or ball joint whose angular velocity is below ~1e-8 (a body at rest): "
                   "math.quat_integrate's normalize_with_norm cuts the gradient; C (and the exact exponential map) "
                   "give the timestep. Found by mjxdiff grad on primitives_on_plane (resting box and mesh)")
def test_the_gradient_of_a_resting_body_s_orientation_with_respect_to_its_angular_velocity():
    import jax

    from mjxdiff.tools import grad

    m = mujoco.MjModel.from_xml_string("<mujoco><option timestep='0.01'/><worldbody><body><freejoint/>"
                                       "<geom size='.1'/></body></worldbody></mujoco>")
    state = dict(qpos=m.qpos0.copy(), qvel=np.zeros(6), act=np.zeros(0), ctrl=np.zeros(0))
    with jax.enable_x64(True):
        A, *_ = grad.mjx_jacobians(m, state)
    C, *_ = grad.c_jacobians(m, state, 1e-7)
    precondition(np.allclose(np.diag(C[3:6, 9:12]), 0.01, rtol=1e-6, atol=0), "C: the timestep")
    np.testing.assert_allclose(A[3:6, 9:12], C[3:6, 9:12], atol=1e-6)


@pytest.mark.xfail(raises=AssertionError, reason="MJX 3.17: with an elliptic friction cone, jax.jacfwd of "
                   "mjx.step is NaN in every entry for a body resting on a contact (no slip); the pyramidal cone, or "
                   "a sliding body (0.1 m/s), gives finite Jacobians, and C's finite differences are smooth there. "
                   "Found by mjxdiff grad on slope_slide and contact_parameters")
def test_elliptic_cone_gradients_are_finite_for_a_body_at_rest():
    import jax

    from mjxdiff.tools import grad

    m = mujoco.MjModel.from_xml_string(
        "<mujoco><option cone='elliptic' iterations='200' tolerance='1e-14'/><worldbody>"
        "<geom type='plane' size='1 1 .1'/><body pos='0 0 0.099'><freejoint/><geom size='0.1'/></body>"
        "</worldbody></mujoco>")
    state = dict(qpos=np.r_[0, 0, 0.099, 1, 0, 0, 0.0], qvel=np.zeros(6), act=np.zeros(0), ctrl=np.zeros(0))
    precondition(grad.smooth_at(m, state), "the same constraint rows and states throughout the stencil")
    with jax.enable_x64(True):
        A, *_ = grad.mjx_jacobians(m, state)
    assert np.isfinite(A).all(), f"{int(np.isnan(A).sum())} of {A.size} entries NaN"


@pytest.mark.xfail(raises=AssertionError, reason="MJX 3.17: with the CG solver, jax.jacfwd of mjx.step "
                   "couples free bodies that share no constraint: at a cg_frictionless state (three bodies resting on "
                   "the floor, the pill spinning) d qvel of 'pill' (rot x) / d qpos of 'slick' (z) is 1.49, where C's "
                   "and MJX's own finite differences give 0 (1.4e-9); the Newton solver gives 1.8e-11 at the same "
                   "state, and 30 to 1000 CG iterations or tolerance 0 do not change it. Found by mjxdiff grad on "
                   "cg_frictionless")
def test_cg_solver_gradients_do_not_couple_unconnected_bodies():
    from mjxdiff.tools import grad
    from mjxdiff.output import reproducer

    rep = reproducer.load_any(Path(__file__).parent / "data" / "grad_cg_solver_cross_coupling.json")
    precondition(rep.model.opt.solver == mujoco.mjtSolver.mjSOL_CG, "the CG solver")
    with jax.enable_x64(True):
        A, *_ = grad.mjx_jacobians(rep.model, rep.state)
    C, *_ = grad.c_jacobians(rep.model, rep.state, 1e-7)
    precondition(abs(C[27, 2]) < 1e-6, "C: the slick's height does not move the pill")
    np.testing.assert_allclose(A[27, 2], C[27, 2], atol=1e-3)


def test_the_sweep_names_the_clamped_servo_and_the_catalogue_knows_it(repo_root):
    """The one-step check fails the model at the integration stage, the cause attribution finds
    that removing the actuator force clamps (with a converged solver) makes it pass, and the
    catalogue entry says why."""
    from mjxdiff.compare import known
    from mjxdiff.output import report
    from mjxdiff.input.scenario import load_scenario
    from mjxdiff.runner.sweep import SweepConfig, run_scenario

    result = run_scenario(load_scenario(str(repo_root / "tests" / "data" / "clamped_servo_implicitfast.xml")),
                          SweepConfig(seed=0, batch=4, steps=100))
    assert result.status == "fail" and result.info["onestep"]["status"] == "fail", result.message
    assert "every forward stage agrees (the difference is in the integration)" in result.message
    assert result.diagnosis["cause"]["cause"] == "actuator force clamping", result.diagnosis
    assert known.match(report.result_dict(result)).id == "implicit-clamped-actuator"


SPRING_WITH_DAMPER_DISABLED = """<mujoco>
  <option><flag damper="disable"/></option>
  <worldbody>
    <body><joint name="j" type="hinge" axis="0 1 0" stiffness="2" damping="0.5"/>
      <geom type="capsule" fromto="0 0 0 0 0 -0.3" size="0.02"/></body>
  </worldbody>
</mujoco>"""


@pytest.mark.xfail(raises=AssertionError, reason="MJX 3.17: passive() returns zero passive force (and no gravcomp) "
                                       "when EITHER the spring or the damper flag is disabled "
                                       "(`disableflags & (SPRING | DAMPER)`); C 4.0 drops only the disabled "
                                       "one; found by the combinations_rk4 scenario (issue 32)")
def test_a_spring_acts_with_only_the_damper_disabled():
    _, d, dx = _forward_both(SPRING_WITH_DAMPER_DISABLED, qpos={0: 0.3})
    precondition(abs(d.qfrc_passive[0] + 0.6) < 1e-12, "C: the spring's -k q")
    np.testing.assert_allclose(np.asarray(dx.qfrc_passive), d.qfrc_passive, atol=1e-12, err_msg="qfrc_passive")


ACTEARLY_FILTER = """<mujoco>
  <worldbody>
    <body><joint name="j" type="hinge" axis="0 1 0"/><geom type="capsule" fromto="0 0 0 0 0 -0.3" size="0.02"/></body>
  </worldbody>
  <actuator><general joint="j" dyntype="filter" dynprm="0.05" gainprm="0.4" ctrlrange="0 1" actearly="true"/></actuator>
</mujoco>"""


@pytest.mark.xfail(raises=AssertionError, reason="MJX 3.17 ignores actearly: the force uses the current activation "
                                       "(0.08 here), C 4.0 the next one (0.088); found by the combinations "
                                       "scenario's actuator bank (issue 32)")
def test_actearly_uses_the_next_activation():
    _, d, dx = _forward_both(ACTEARLY_FILTER, ctrl={0: 0.7}, act={0: 0.2})
    np.testing.assert_allclose(np.asarray(dx.actuator_force), d.actuator_force, atol=1e-12, err_msg="actuator_force")


DAMPING_WITH_DAMPER_DISABLED = """<mujoco>
  <option><flag spring="disable" damper="disable"/></option>
  <worldbody>
    <body><joint type="hinge" axis="0 1 0" damping="2"/><geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.02"/></body>
  </worldbody>
</mujoco>"""


@pytest.mark.xfail(raises=AssertionError, reason="MJX 3.17's Euler step adds timestep * dof_damping to the mass "
                                       "matrix (implicit damping) even with the damper flag disabled; C 4.0 "
                                       "does not (qvel 1.0713 vs 1.0934 after one step from 1 rad/s); "
                                       "found while covering the passive flags (issue 32)")
def test_the_euler_step_damps_nothing_with_the_damper_disabled():
    d, dx = _step_both(DAMPING_WITH_DAMPER_DISABLED, [1.0])
    np.testing.assert_allclose(np.asarray(dx.qvel), d.qvel, atol=1e-12, err_msg="qvel after one Euler step")


TENDON_DAMPING_ACROSS_TREES = """<mujoco>
  <option integrator="implicitfast"/>
  <worldbody>
    <body pos="0 0 1"><joint name="a" axis="0 1 0"/><geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.02"/></body>
    <body pos="1 0 1"><joint name="b" axis="0 1 0"/><geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.02"/></body>
  </worldbody>
  <tendon><fixed damping="0.5"><joint joint="a" coef="1"/><joint joint="b" coef="-1"/></fixed></tendon>
</mujoco>"""


@pytest.mark.xfail(raises=AssertionError, reason="implicitfast with a damped tendon coupling two kinematic trees: "
                                       "C 4.0 keeps qDeriv within the mass matrix's sparsity (the trees' "
                                       "cross terms dropped), MJX 3.17 adds the dense J^T D J; found by the "
                                       "combinations_implicit scenario (issue 32)")
def test_implicitfast_damps_a_tendon_across_two_trees_as_c_does():
    d, dx = _step_both(TENDON_DAMPING_ACROSS_TREES, [1.0, -0.5])
    np.testing.assert_allclose(np.asarray(dx.qvel), d.qvel, atol=1e-12, err_msg="qvel after one implicitfast step")
