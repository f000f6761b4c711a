"""A catalogue of realistic, subtle bugs to inject into MJX (mujoco-mjx 3.17, ``mujoco.mjx._src``)
that show ONLY under a combination of two conditions: :data:`BUGS`, :data:`COMBINATIONS`.

Each bug is one-line-sized, like those of ``tests/injected_bugs.py`` (same :class:`Bug` record,
same way of patching: the module attribute that MJX's caller looks up at call time), but it sits
in a branch, a clamp or a term that only a combination reaches: a model option, flag or attribute
(condition A) AND another attribute or a state regime (condition B). With either condition absent
MJX's output is bit-identical to unmodified MJX (``tests/check_combination_bugs.py`` measures
both sides for every bug on tiny models). A tester that only varies one thing at a time, or that
never drives a model into the regime, cannot see them.

All are meant for the ``interactions`` scenario (written separately), which must contain each
combination of :data:`COMBINATIONS`. Usage is that of ``injected_bugs``::

    with pytest.MonkeyPatch.context() as mp:
        bug.patch(mp)
        engines.clear_compiled()
        ...  # run MJX
    engines.clear_compiled()
"""

from __future__ import annotations

import types

import jax.numpy as jnp
import numpy as np
import pytest
from mujoco.mjx._src import constraint as mjx_constraint
from mujoco.mjx._src import derivative as mjx_derivative
from mujoco.mjx._src import forward as mjx_forward
from mujoco.mjx._src import math as mjx_math
from mujoco.mjx._src import passive as mjx_passive
from mujoco.mjx._src import sensor as mjx_sensor
from mujoco.mjx._src import smooth as mjx_smooth
from mujoco.mjx._src import solver as mjx_solver
from mujoco.mjx._src import support as mjx_support
from mujoco.mjx._src.types import DisableBit, DynType, ObjType, SensorType

try:
    from injected_bugs import FRICTION, IMPEDANCE, PASSIVE, SENSORS, SOLVER, Bug
except ImportError:  # imported as a package module rather than from tests/ on sys.path
    from tests.injected_bugs import FRICTION, IMPEDANCE, PASSIVE, SENSORS, SOLVER, Bug

__all__ = ["BUGS", "CATEGORIES", "COMBINATIONS", "by_id"]

MODEL = "interactions"
#: The bundled scenarios written for issue 32 as covering arrays of the conditions MJX branches on
#: (benchmarks/scripts/make_combinations.py): they reach every condition on purpose, so claims
#: that "no earlier scenario reaches this code" (tests/test_sensing_scenario.py,
#: test_wider_reach.py, test_parameter_families.py) are about the scenarios before them.
COVERING_SCENARIOS = ("combinations", "combinations_implicit", "combinations_undamped")

ACTUATOR_LIMITS = "actuator limits and activation"
INTEGRATOR = "integrators"
EQUALITY = "equality constraints"
LIMITS = "joint limits"

#: Every category used here, in the order of :data:`BUGS`.
CATEGORIES: tuple[str, ...] = (ACTUATOR_LIMITS, PASSIVE, SENSORS, INTEGRATOR, FRICTION, SOLVER,
                               EQUALITY, LIMITS, IMPEDANCE)


def _set_col(a, col, fn):
    """``a`` with column ``col`` replaced by ``fn(a[:, col])`` (numpy or jax array)."""
    if isinstance(a, np.ndarray):
        a = a.copy()
        a[:, col] = fn(a[:, col])
        return a
    return a.at[:, col].set(fn(a[:, col]))


def _widen(a, side: int, frac: float):
    """A (n, 2) range array with end ``side`` moved outwards by ``frac`` of the span."""
    span = a[:, 1] - a[:, 0]
    sign = 1.0 if side == 1 else -1.0
    return _set_col(a, side, lambda x: x + sign * frac * span)


# -- actuator limits and activation --------------------------------------------------------------


def _ctrl_clamp_upper(mp: pytest.MonkeyPatch) -> None:
    orig = mjx_forward.fwd_actuation  # ctrlrange is read only by the ctrl clamp there
    mp.setattr(mjx_forward, "fwd_actuation",
               lambda m, d: orig(m.replace(actuator_ctrlrange=_widen(m.actuator_ctrlrange, 1, 0.02)), d))


def _force_clamp_lower(mp: pytest.MonkeyPatch) -> None:
    orig = mjx_forward.fwd_actuation  # forcerange is read only by the actuator_force clamp
    mp.setattr(mjx_forward, "fwd_actuation",
               lambda m, d: orig(m.replace(actuator_forcerange=_widen(m.actuator_forcerange, 0, 0.02)), d))


def _act_clamp_upper(mp: pytest.MonkeyPatch) -> None:
    orig = mjx_forward._next_activation  # looked up by forward._advance at call time
    mp.setattr(mjx_forward, "_next_activation",
               lambda m, d, act_dot: orig(m.replace(actuator_actrange=_widen(m.actuator_actrange, 1, 0.02)),
                                          d, act_dot))


def _filterexact_as_euler(mp: pytest.MonkeyPatch) -> None:
    orig = mjx_forward._next_activation

    def buggy(m, d, act_dot):
        # the FILTEREXACT test of the integration branch lost: act += act_dot * dt for it as well
        dyntype = np.where(m.actuator_dyntype == DynType.FILTEREXACT, DynType.FILTER, m.actuator_dyntype)
        return orig(m.replace(actuator_dyntype=dyntype), d, act_dot)

    mp.setattr(mjx_forward, "_next_activation", buggy)


def _tendon_actfrc_lower(mp: pytest.MonkeyPatch) -> None:
    orig = mjx_forward.fwd_actuation  # tendon_actfrcrange is read only by the tendon force scaling
    mp.setattr(mjx_forward, "fwd_actuation",
               lambda m, d: orig(m.replace(tendon_actfrcrange=_widen(m.tendon_actfrcrange, 0, 0.02)), d))


def _actgravcomp_after_clamp(mp: pytest.MonkeyPatch) -> None:
    orig = mjx_forward.fwd_actuation

    def buggy(m, d):
        d2 = orig(m, d)
        if not m.nu or m.opt.disableflags & DisableBit.ACTUATION or not m.flg_gravcomp:
            return d2
        dof_mask = (np.asarray(m.jnt_actfrclimited) & np.asarray(m.jnt_actgravcomp).astype(bool))[m.dof_jntid]
        if not dof_mask.any():
            return d2
        # clamp the actuators' own force to actfrcrange first, add the gravity compensation after
        qfrc = d._impl.actuator_moment.T @ d2.actuator_force
        rng = m.jnt_actfrcrange[m.dof_jntid]
        late = jnp.clip(qfrc, rng[:, 0], rng[:, 1]) + d.qfrc_gravcomp
        return d2.replace(qfrc_actuator=jnp.where(dof_mask, late, d2.qfrc_actuator))

    mp.setattr(mjx_forward, "fwd_actuation", buggy)


# -- passive forces ------------------------------------------------------------------------------


def _tendon_deadband_upper(mp: pytest.MonkeyPatch) -> None:
    orig = mjx_passive._spring_damper  # looked up by passive.passive at call time

    def buggy(m, d):
        qfrc = orig(m, d)
        if m.opt.disableflags & DisableBit.SPRING or not m.ntendon:
            return qfrc
        # the upper branch's force k * (hi - L) written as k * (lo - L): add k * (lo - hi) there
        lo, hi = m.tendon_lengthspring[:, 0], m.tendon_lengthspring[:, 1]
        above = hi - d.ten_length
        extra = jnp.where(above < 0, m.tendon_stiffness * (lo - hi), 0.0)
        return qfrc + d._impl.ten_J.T @ extra

    mp.setattr(mjx_passive, "_spring_damper", buggy)


# -- sensors -------------------------------------------------------------------------------------


def _framepos_ref_untransposed(mp: pytest.MonkeyPatch) -> None:
    orig = mjx_sensor.sensor_pos  # looked up as sensor.sensor_pos by forward.forward

    def buggy(m, d):
        d = orig(m, d)
        if m.opt.disableflags & DisableBit.SENSOR:
            return d
        sel = np.nonzero((m.sensor_type == SensorType.FRAMEPOS) & (m.sensor_refid >= 0))[0]
        if not sel.size:
            return d
        frames = {
            int(ObjType.BODY): (d.xipos, d.ximat),
            int(ObjType.XBODY): (d.xpos, d.xmat),
            int(ObjType.GEOM): (d.geom_xpos, d.geom_xmat),
            int(ObjType.SITE): (d.site_xpos, d.site_xmat),
            int(ObjType.CAMERA): (d.cam_xpos, d.cam_xmat),
        }
        sensordata = d.sensordata
        for i in sel:
            xpos = frames[int(m.sensor_objtype[i])][0][m.sensor_objid[i]]
            pos_ref, mat_ref = (x[m.sensor_refid[i]] for x in frames[int(m.sensor_reftype[i])])
            value = mat_ref @ (xpos - pos_ref)  # R @ v, should be R.T @ v
            if m.sensor_cutoff[i] > 0:
                value = jnp.clip(value, -m.sensor_cutoff[i], m.sensor_cutoff[i])
            adr = int(m.sensor_adr[i])
            sensordata = sensordata.at[adr:adr + 3].set(value)
        return d.replace(sensordata=sensordata)

    mp.setattr(mjx_sensor, "sensor_pos", buggy)


def _framequat_ref_uninverted(mp: pytest.MonkeyPatch) -> None:
    # sensor.py's own view of math: quat_inv is called there only for a framequat's reference
    # orientation, r^-1 * q; the view returns r itself (the conjugation dropped)
    view = types.SimpleNamespace(**{k: getattr(mjx_math, k) for k in dir(mjx_math) if not k.startswith("__")})
    view.quat_inv = lambda q: q
    mp.setattr(mjx_sensor, "math", view)


def _framelinvel_ref_spin_sign(mp: pytest.MonkeyPatch) -> None:
    orig = mjx_sensor.sensor_vel  # looked up as sensor.sensor_vel by forward.forward

    def buggy(m, d):
        d = orig(m, d)
        if m.opt.disableflags & DisableBit.SENSOR:
            return d
        sel = np.nonzero((m.sensor_type == SensorType.FRAMELINVEL) & (m.sensor_refid >= 0))[0]
        if not sel.size:
            return d
        frames = {
            int(ObjType.BODY): (d.xipos, d.ximat, np.arange(m.nbody)),
            int(ObjType.XBODY): (d.xpos, d.xmat, np.arange(m.nbody)),
            int(ObjType.GEOM): (d.geom_xpos, d.geom_xmat, m.geom_bodyid),
            int(ObjType.SITE): (d.site_xpos, d.site_xmat, m.site_bodyid),
            int(ObjType.CAMERA): (d.cam_xpos, d.cam_xmat, m.cam_bodyid),
        }
        sensordata = d.sensordata
        for i in sel:
            xpos = frames[int(m.sensor_objtype[i])][0][m.sensor_objid[i]]
            pos_ref, mat_ref, body_ref = (x[m.sensor_refid[i]] for x in frames[int(m.sensor_reftype[i])])
            angvel_ref = d.cvel[body_ref, :3]
            # the reference's spin term + w_ref x r entered with the wrong sign: subtract 2 w_ref x r
            fix = mat_ref.T @ (-2.0 * jnp.cross(xpos - pos_ref, angvel_ref))
            if m.sensor_cutoff[i] > 0:
                raise NotImplementedError("framelinvel with cutoff")
            adr = int(m.sensor_adr[i])
            sensordata = sensordata.at[adr:adr + 3].add(fix)
        return d.replace(sensordata=sensordata)

    mp.setattr(mjx_sensor, "sensor_vel", buggy)


# -- integrators ---------------------------------------------------------------------------------


def _eulerdamp_flag_ignored(mp: pytest.MonkeyPatch) -> None:
    orig = mjx_forward.euler  # looked up by forward.step at call time

    def buggy(m, d):
        if not m.opt.disableflags & DisableBit.EULERDAMP:
            return orig(m, d)  # the enabled path is right
        # disabled path: damping still integrated implicitly, written as the correction
        # qacc - (M + h D)^-1 h D qacc (zero when there is no damping)
        hd = m.opt.timestep * m.dof_damping
        if mjx_support.is_sparse(m):
            diag_adr = m.M_rowadr + m.M_rownnz - 1
            mh = d._impl.M.at[diag_adr].add(hd)
        else:
            mh = d._impl.M + jnp.diag(hd)
        dh = mjx_smooth.factor_m(m, d.tree_replace({"_impl.M": mh}))
        qacc = d.qacc - mjx_smooth.solve_m(m, dh, hd * d.qacc)
        return mjx_forward._advance(m, d, d.act_dot, qacc)

    mp.setattr(mjx_forward, "euler", buggy)


def _implicit_actuator_vel(mp: pytest.MonkeyPatch) -> None:
    orig = mjx_derivative.deriv_smooth_vel  # looked up as derivative.deriv_smooth_vel by forward.implicit

    def buggy(m, d):
        scale = lambda a: _set_col(a, 2, lambda x: x * 1.02)
        return orig(m.replace(actuator_biasprm=scale(m.actuator_biasprm),
                              actuator_gainprm=scale(m.actuator_gainprm)), d)

    mp.setattr(mjx_derivative, "deriv_smooth_vel", buggy)


# -- friction cones and solver -------------------------------------------------------------------


def _elliptic_impratio_nosqrt(mp: pytest.MonkeyPatch) -> None:
    orig = mjx_solver.solve  # impratio is read in the solver only for the elliptic mu

    def buggy(m, d):
        # mu = friction / impratio instead of friction / sqrt(impratio)
        return orig(m.replace(opt=m.opt.replace(impratio=m.opt.impratio * m.opt.impratio)), d)

    mp.setattr(mjx_solver, "solve", buggy)


def _newton_cone_hessian_sign(mp: pytest.MonkeyPatch) -> None:
    orig = mjx_solver._update_constraint  # looked up by Context.create and solve's body

    def buggy(m, d, ctx):
        ctx = orig(m, d, ctx)
        h = ctx.h
        if getattr(h, "ndim", 0) != 3:  # only Newton x elliptic builds the cone Hessian
            return ctx
        # first row/column (1, -mu/T U) of the cone Hessian written as (1, +mu/T U)
        h = h.at[:, 0, 1:].multiply(-1.0).at[:, 1:, 0].multiply(-1.0)
        return ctx.replace(h=h)

    mp.setattr(mjx_solver, "_update_constraint", buggy)


# -- equality constraints and limits -------------------------------------------------------------


def _weld_relpose_conjugate(mp: pytest.MonkeyPatch) -> None:
    orig = mjx_constraint._efc_equality_weld  # looked up by make_constraint at call time

    def buggy(m, d):
        # relpose's quaternion (eq_data[6:10]) used conjugated: q1 * relpose^-1 instead of q1 * relpose
        data = m.eq_data.at[:, 7:10].multiply(-1.0)
        return orig(m.replace(eq_data=data), d)

    mp.setattr(mjx_constraint, "_efc_equality_weld", buggy)


def _joint_limit_upper(mp: pytest.MonkeyPatch) -> None:
    orig = mjx_constraint._efc_limit_slide_hinge  # looked up by make_constraint at call time
    mp.setattr(mjx_constraint, "_efc_limit_slide_hinge",
               lambda m, d: orig(m.replace(jnt_range=_widen(m.jnt_range, 1, 0.01)), d))


# -- flags a model disables, and attributes read in the wrong branch (added with issue 32's
#    scenarios: each needs a disabled flag or an attribute pair the earlier scenarios never held)


def _without(m, bit):
    """``m`` with disable flag ``bit`` cleared: MJX then runs the code the flag turns off."""
    return m.replace(opt=m.opt.replace(disableflags=m.opt.disableflags & ~bit))


def _clampctrl_flag_ignored(mp: pytest.MonkeyPatch) -> None:
    orig = mjx_forward.fwd_actuation  # looked up as forward's module global by forward()
    mp.setattr(mjx_forward, "fwd_actuation", lambda m, d: orig(_without(m, DisableBit.CLAMPCTRL), d))


def _refsafe_flag_ignored(mp: pytest.MonkeyPatch) -> None:
    orig = mjx_constraint._kbi  # looked up by constraint's _row builders at call time
    mp.setattr(mjx_constraint, "_kbi", lambda m, solref, solimp, pos: orig(_without(m, DisableBit.REFSAFE),
                                                                          solref, solimp, pos))


def _gravcomp_ignores_gravity_flag(mp: pytest.MonkeyPatch) -> None:
    orig = mjx_passive.passive  # looked up as passive.passive by forward.fwd_velocity
    mp.setattr(mjx_passive, "passive", lambda m, d: orig(_without(m, DisableBit.GRAVITY), d))


def _muscle_bias_needs_muscle_gain(mp: pytest.MonkeyPatch) -> None:
    orig = mjx_forward.fwd_actuation

    def buggy(m, d):
        # the muscle bias branch nested under the muscle gain's: other gains drop a muscle bias
        drop = (np.asarray(m.actuator_biastype) == 2) & (np.asarray(m.actuator_gaintype) != 2)
        return orig(m.replace(actuator_biastype=np.where(drop, 0, m.actuator_biastype)), d)

    mp.setattr(mjx_forward, "fwd_actuation", buggy)


def _tendon_equality_default_solref(mp: pytest.MonkeyPatch) -> None:
    orig = mjx_constraint._efc_equality_tendon  # looked up by make_constraint at call time

    def buggy(m, d):
        tendon = (np.asarray(m.eq_type) == 3)[:, None]
        return orig(m.replace(eq_solref=jnp.where(tendon, jnp.array([0.02, 1.0]), m.eq_solref)), d)

    mp.setattr(mjx_constraint, "_efc_equality_tendon", buggy)


def _xbody_reads_inertial_frame(mp: pytest.MonkeyPatch) -> None:
    orig = mjx_sensor.sensor_pos  # looked up as sensor.sensor_pos by forward.forward

    def buggy(m, d):
        # objtype XBODY mapped to (xipos, ximat) like BODY: a slip in the object-type table
        return d.replace(sensordata=orig(m, d.replace(xpos=d.xipos, xmat=d.ximat)).sensordata)

    mp.setattr(mjx_sensor, "sensor_pos", buggy)


BUGS: tuple[Bug, ...] = (
    Bug("ctrl_clamp_upper", ACTUATOR_LIMITS,
        "The control clamp's upper bound sits 2% of the range above ctrlrange[1] (a slack meant "
        "for a separate range check), the lower bound right. Exposed only when an actuator is "
        "ctrllimited AND its control goes above ctrlrange[1]; a control inside the range, or an "
        "unlimited actuator, is untouched (forward.fwd_actuation).",
        MODEL, _ctrl_clamp_upper),
    Bug("force_clamp_lower", ACTUATOR_LIMITS,
        "The actuator_force clamp lets the force go 2% of the range below forcerange[0] (the "
        "lower end of the clip computed from a widened range), the upper end right. Exposed "
        "only when an actuator is forcelimited AND its force goes below forcerange[0] "
        "(forward.fwd_actuation).",
        MODEL, _force_clamp_lower),
    Bug("act_clamp_upper", ACTUATOR_LIMITS,
        "Activation is clamped after integration with an upper end 2% of actrange's span too "
        "high, so an integrator/filter state overshoots actrange[1] slightly. Exposed only when "
        "an actuator is actlimited AND its activation would pass actrange[1] "
        "(forward._next_activation).",
        MODEL, _act_clamp_upper),
    Bug("filterexact_as_euler", ACTUATOR_LIMITS,
        "filterexact activations are integrated with the explicit formula act += dt (u - act) / "
        "tau instead of the exact act += (u - act) (1 - exp(-dt / tau)): the dyntype test of the "
        "integration branch sees FILTEREXACT as FILTER. Exposed only for dyntype filterexact "
        "AND an activation away from its control (act != ctrl, so act_dot != 0); dyntype "
        "filter is right (forward._next_activation).",
        MODEL, _filterexact_as_euler),
    Bug("tendon_actfrc_lower", ACTUATOR_LIMITS,
        "The total actuator force on a tendon is scaled back to 2% of the range below "
        "tendon actfrcrange[0] instead of to it. Exposed only when a tendon is actuatorfrclimited "
        "AND the actuators' total force on it goes below its lower end (forward.fwd_actuation).",
        MODEL, _tendon_actfrc_lower),
    Bug("actgravcomp_after_clamp", ACTUATOR_LIMITS,
        "Gravity compensation routed through the actuators (joint actuatorgravcomp) is added "
        "after qfrc_actuator is clamped to the joint's actuatorfrcrange instead of before, so "
        "the clamp no longer bounds it: a statement-order slip. Exposed only when a gravcomp "
        "body's joint has actuatorgravcomp AND is actuatorfrclimited (with the sum reaching the "
        "range) (forward.fwd_actuation).",
        MODEL, _actgravcomp_after_clamp),
    Bug("tendon_deadband_upper", PASSIVE,
        "A tendon spring with a deadband (springlength lo < hi) pulls back from above with "
        "k (lo - L) instead of k (hi - L): the upper branch copy-pasted from the lower one. "
        "Exposed only when a stiff tendon has a deadband (lo < hi) AND its length goes above hi; "
        "with lo == hi the two ends coincide, and below hi the branch is not taken "
        "(passive._spring_damper).",
        MODEL, _tendon_deadband_upper),
    Bug("framepos_ref_untransposed", SENSORS,
        "framepos with a reference frame expresses the offset as R_ref (x - x_ref) instead of "
        "R_ref^T (x - x_ref): the rotation un-transposed. Exposed only when a framepos sensor has "
        "a reference object (reftype/refname) AND that frame is rotated (R_ref not symmetric); "
        "without a reference, or with an unrotated one, the value is the same "
        "(sensor.sensor_pos).",
        MODEL, _framepos_ref_untransposed),
    Bug("framequat_ref_uninverted", SENSORS,
        "framequat with a reference frame is computed as q_ref * q instead of q_ref^-1 * q (the "
        "conjugation of the reference dropped). Exposed only when a framequat sensor has a "
        "reference object AND that frame is rotated (sensor.sensor_pos via sensor.math).",
        MODEL, _framequat_ref_uninverted),
    Bug("framelinvel_ref_spin_sign", SENSORS,
        "framelinvel with a reference frame adds the reference's spin term w_ref x r with the "
        "wrong sign (- instead of +). Exposed only when a framelinvel sensor has a reference "
        "object AND that frame rotates (nonzero angular velocity) with the object off its origin "
        "(sensor.sensor_vel).",
        MODEL, _framelinvel_ref_spin_sign),
    Bug("eulerdamp_flag_ignored", INTEGRATOR,
        "With the eulerdamp flag disabled the Euler integrator still integrates joint damping "
        "implicitly ((M + h D) qacc = f): the flag test dropped. Exposed only when eulerdamp is "
        "disabled AND some dof has damping > 0; with eulerdamp enabled the path is the right "
        "one, without damping the correction is zero (forward.euler).",
        MODEL, _eulerdamp_flag_ignored),
    Bug("implicit_actuator_vel", INTEGRATOR,
        "implicitfast's velocity derivative of the actuator force uses the velocity terms "
        "(biasprm[2], gainprm[2]) 2% strong, inconsistent with the force itself. Exposed only "
        "with integrator implicitfast AND an actuator with a velocity-dependent bias or gain "
        "(a velocity servo, a position servo with kv) (derivative.deriv_smooth_vel).",
        MODEL, _implicit_actuator_vel),
    Bug("elliptic_impratio_nosqrt", FRICTION,
        "The solver's elliptic cone uses mu = friction / impratio instead of friction / "
        "sqrt(impratio) (the square root forgotten). Exposed only with cone elliptic AND "
        "impratio != 1, for contacts with friction; pyramidal cones do not read it "
        "(solver.solve).",
        MODEL, _elliptic_impratio_nosqrt),
    Bug("newton_cone_hessian_sign", SOLVER,
        "The Newton solver's elliptic-cone Hessian has its first row and column (1, -mu/T U) "
        "with the wrong sign (+mu/T U): a sign slip in a block that only preconditions. The cost "
        "and gradient stay right, but Newton's steps differ and it stops (tolerance or iteration "
        "budget) at a different qacc; on a sliding box the rollout drifts visibly with the "
        "default 100 iterations as well as with 1. Exposed only with solver Newton AND cone "
        "elliptic, for a contact in the cone's middle zone (sliding); CG does not use the "
        "Hessian, pyramidal has none (solver._update_constraint).",
        MODEL, _newton_cone_hessian_sign),
    Bug("weld_relpose_conjugate", EQUALITY,
        "A weld's orientation error uses its relpose quaternion conjugated (q1 * relpose^-1 "
        "instead of q1 * relpose), as when the relative pose is stored in the other direction. "
        "Exposed only with a weld equality AND a rotated relpose (quaternion part not identity) "
        "(constraint._efc_equality_weld).",
        MODEL, _weld_relpose_conjugate),
    Bug("joint_limit_upper", LIMITS,
        "A slide/hinge joint's upper-limit distance is measured from range[1] + 1% of the span "
        "(a one-sided slack), the lower one right. Exposed only when a joint is limited AND it "
        "reaches its upper end; hitting the lower end only is untouched "
        "(constraint._efc_limit_slide_hinge).",
        MODEL, _joint_limit_upper),
)

#: bug id -> (condition A, condition B): both must hold for the bug to show.
COMBINATIONS: dict[str, tuple[str, str]] = {
    "ctrl_clamp_upper": ("actuator ctrllimited", "ctrl above ctrlrange[1]"),
    "force_clamp_lower": ("actuator forcelimited", "actuator force below forcerange[0]"),
    "act_clamp_upper": ("actuator actlimited (integrator/filter dyntype)", "act driven past actrange[1]"),
    "filterexact_as_euler": ("actuator dyntype filterexact", "act != ctrl (activation moving)"),
    "tendon_actfrc_lower": ("tendon actuatorfrclimited with an actuator on it",
                            "total actuator force on the tendon below actuatorfrcrange[0]"),
    "actgravcomp_after_clamp": ("gravcomp body with joint actuatorgravcomp=true",
                                "joint actuatorfrclimited (range reached)"),
    "tendon_deadband_upper": ("tendon spring with a deadband (springlength lo < hi, stiffness > 0)",
                              "tendon length above the upper end hi"),
    "framepos_ref_untransposed": ("framepos sensor with a reference object", "reference frame rotated"),
    "framequat_ref_uninverted": ("framequat sensor with a reference object", "reference frame rotated"),
    "framelinvel_ref_spin_sign": ("framelinvel sensor with a reference object",
                                  "reference frame rotating, object off its origin"),
    "eulerdamp_flag_ignored": ("Euler integrator with eulerdamp disabled", "dof damping > 0"),
    "implicit_actuator_vel": ("integrator implicitfast",
                              "actuator with velocity-dependent bias/gain (biasprm[2] or gainprm[2] != 0)"),
    "elliptic_impratio_nosqrt": ("cone elliptic", "impratio != 1 (with frictional contact)"),
    "newton_cone_hessian_sign": ("solver Newton", "cone elliptic (with a sliding contact)"),
    "weld_relpose_conjugate": ("weld equality", "rotated relpose (quaternion not identity)"),
    "joint_limit_upper": ("limited slide/hinge joint", "joint reaching its upper range end"),
    "clampctrl_flag_ignored": ("clampctrl disabled", "a ctrllimited actuator's control outside ctrlrange"),
    "refsafe_flag_ignored": ("refsafe disabled", "a constraint solref timeconst below 2 timesteps"),
    "gravcomp_ignores_gravity_flag": ("gravity disabled", "a body with gravcomp"),
    "muscle_bias_needs_muscle_gain": ("biastype muscle", "gaintype not muscle"),
    "tendon_equality_default_solref": ("tendon equality", "solref other than the default"),
    "xbody_reads_inertial_frame": ("a frame sensor's object or reference of type xbody",
                                   "a body whose inertial frame is not its own (centre of mass off the origin)"),
}

BUGS += (
    Bug("clampctrl_flag_ignored", ACTUATOR_LIMITS,
        "fwd_actuation clamps the controls even with clampctrl disabled (the flag test dropped in a "
        "refactor). Shows only with the flag disabled AND a limited actuator's control outside its "
        "range; otherwise clamping is what C does, or changes nothing.", MODEL, _clampctrl_flag_ignored),
    Bug("refsafe_flag_ignored", LIMITS,
        "_kbi clamps timeconst to 2 timesteps even with refsafe disabled. Shows only with the flag "
        "disabled AND a solref timeconst below 2 dt (a stiff limit or equality).", MODEL, _refsafe_flag_ignored),
    Bug("gravcomp_ignores_gravity_flag", PASSIVE,
        "passive adds gravity compensation even with gravity disabled (the gravity test dropped). "
        "Shows only with gravity disabled AND a body with gravcomp.", MODEL, _gravcomp_ignores_gravity_flag),
    Bug("muscle_bias_needs_muscle_gain", ACTUATOR_LIMITS,
        "The muscle bias is computed only inside the muscle gain's branch, so an actuator with a muscle "
        "bias and another gain loses its bias. Shows only for biastype muscle AND gaintype fixed or "
        "affine (a <muscle> has both).", MODEL, _muscle_bias_needs_muscle_gain),
    Bug("tendon_equality_default_solref", EQUALITY,
        "Tendon equality rows use the default solref (0.02, 1) instead of eq_solref. Shows only for a "
        "tendon equality AND a solref other than the default.", MODEL, _tendon_equality_default_solref),
    Bug("xbody_reads_inertial_frame", SENSORS,
        "sensor_pos's object-type table maps xbody to the inertial frame (xipos, ximat), as for body. "
        "Shows only for a frame sensor whose object or reference is an xbody AND a body whose centre of "
        "mass or principal axes are off its frame.", MODEL, _xbody_reads_inertial_frame),
)

assert set(COMBINATIONS) == {b.id for b in BUGS}, "COMBINATIONS must name every bug"
assert len({b.id for b in BUGS}) == len(BUGS), "bug ids must be unique"


def by_id(bug_id: str) -> Bug:
    """The bug of :data:`BUGS` named ``bug_id``."""
    for bug in BUGS:
        if bug.id == bug_id:
            return bug
    raise KeyError(f"no combination bug {bug_id!r}; known: {', '.join(b.id for b in BUGS)}")
