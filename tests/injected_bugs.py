"""A catalogue of realistic, subtle bugs to inject into MJX (mujoco-mjx 3.17, ``mujoco.mjx._src``),
for measuring what mjxdiff catches: :data:`BUGS`.

Each :class:`Bug` is one-line-sized: it wraps or replaces ONE MJX function so that one quantity
comes out wrong by about 0.5-2% (or, for the order and frame slips, by an amount of that order on
the quadruped's states), the size of slip that survives review and unit tests with loose
tolerances: a coefficient read from the wrong place, a stale or mis-scaled option, a
quaternion product in the wrong order, a frame off by a hundredth of a radian. Every bug reaches
the small quadruped of ``tests/data/quadruped_1iter.xml`` (or its copy with sensors,
``quadruped_1iter_sensors.xml``) from its first steps: the actuators and damping act from step
0, the knees start at their joint limits, with the default randomization (seed 0) some members
start with their feet pressed into the floor and the others land within about 25 steps.

A patch replaces the module attribute that MJX's caller looks up at call time (``smooth.crb``
is looked up in ``mujoco.mjx._src.smooth`` by ``forward.fwd_position`` on every trace; a name
bound by ``from x import f`` is patched where it was bound, e.g. the collision table of
``collision_driver``). Compiled rollouts are cached, so clear them around a patch
(:func:`mjxdiff.engine.engines.clear_compiled`, the ``fresh_mjx`` fixture of ``tests/conftest.py``)::

    with pytest.MonkeyPatch.context() as mp:
        bug.patch(mp)
        engines.clear_compiled()
        ...  # run MJX
    engines.clear_compiled()

Why each is realistic is in its ``description``; :func:`by_id` finds one by name.
"""

from __future__ import annotations

import dataclasses
import types
from typing import Callable

import jax
import jax.numpy as jnp
import pytest
from mujoco.mjx._src import collision_driver as mjx_collision_driver
from mujoco.mjx._src import collision_primitive as mjx_collision_primitive
from mujoco.mjx._src import constraint as mjx_constraint
from mujoco.mjx._src import derivative as mjx_derivative
from mujoco.mjx._src import forward as mjx_forward
from mujoco.mjx._src import math as mjx_math
from mujoco.mjx._src import passive as mjx_passive
from mujoco.mjx._src import sensor as mjx_sensor
from mujoco.mjx._src import smooth as mjx_smooth
from mujoco.mjx._src import solver as mjx_solver
from mujoco.mjx._src import support as mjx_support
from mujoco.mjx._src.types import GeomType

__all__ = ["BUGS", "CATEGORIES", "Bug", "by_id"]

QUADRUPED = "quadruped_1iter.xml"
QUADRUPED_SENSORS = "quadruped_1iter_sensors.xml"


@dataclasses.dataclass(frozen=True)
class Bug:
    """One injectable MJX bug.

    Attributes:
      id: short unique name.
      category: which part of the physics it breaks (:data:`CATEGORIES`).
      description: what it changes and why it is a realistic slip.
      model: the model it is meant for, a file name under ``tests/data``.
      patch: applies it, given a ``pytest.MonkeyPatch`` (undone with the MonkeyPatch).
    """

    id: str
    category: str
    description: str
    model: str
    patch: Callable[[pytest.MonkeyPatch], None]


# -- kinematics and orientation integration ------------------------------------------------------


def _quat_integrate_world_frame(mp: pytest.MonkeyPatch) -> None:
    orig = mjx_math.quat_integrate  # looked up as math.quat_integrate by forward._integrate_pos

    def buggy(q, v, dt):
        # q * exp(v dt) (body-frame angular velocity, right) became exp(v dt) * q (world frame)
        dq = orig(jnp.array([1.0, 0.0, 0.0, 0.0], q.dtype), v, dt)
        return mjx_math.normalize(mjx_math.quat_mul(dq, q))

    mp.setattr(mjx_math, "quat_integrate", buggy)


def _quat_integrate_angle(mp: pytest.MonkeyPatch) -> None:
    orig = mjx_math.quat_integrate
    mp.setattr(mjx_math, "quat_integrate", lambda q, v, dt: orig(q, v, dt * 1.01))


def _hinge_axis_unnormalized(mp: pytest.MonkeyPatch) -> None:
    orig = mjx_smooth.kinematics
    mp.setattr(mjx_smooth, "kinematics", lambda m, d: orig(m.replace(jnt_axis=m.jnt_axis * 1.01), d))


# -- inertia -------------------------------------------------------------------------------------


def _body_mass(mp: pytest.MonkeyPatch) -> None:
    orig = mjx_smooth.com_pos  # the composite inertias (cinert) of 1% heavier bodies
    mp.setattr(mjx_smooth, "com_pos", lambda m, d: orig(m.replace(body_mass=m.body_mass * 1.01), d))


def _armature(mp: pytest.MonkeyPatch) -> None:
    orig = mjx_smooth.crb  # builds M = crb + diag(armature)
    mp.setattr(mjx_smooth, "crb", lambda m, d: orig(m.replace(dof_armature=m.dof_armature * 1.02), d))


# -- actuators -----------------------------------------------------------------------------------


def _actuator_gain(mp: pytest.MonkeyPatch) -> None:
    orig = mjx_forward.fwd_actuation
    mp.setattr(mjx_forward, "fwd_actuation",
               lambda m, d: orig(m.replace(actuator_gainprm=m.actuator_gainprm * 1.02), d))


def _actuator_bias(mp: pytest.MonkeyPatch) -> None:
    orig = mjx_forward.fwd_actuation
    mp.setattr(mjx_forward, "fwd_actuation",
               lambda m, d: orig(m.replace(actuator_biasprm=m.actuator_biasprm.at[:, 1].multiply(1.01)), d))


# -- passive forces ------------------------------------------------------------------------------


def _passive_damping(mp: pytest.MonkeyPatch) -> None:
    orig = mjx_passive._spring_damper
    mp.setattr(mjx_passive, "_spring_damper", lambda m, d: orig(m, d) * 1.01)


def _implicit_damping(mp: pytest.MonkeyPatch) -> None:
    orig = mjx_derivative.deriv_smooth_vel  # looked up as derivative.deriv_smooth_vel by forward.implicit
    mp.setattr(mjx_derivative, "deriv_smooth_vel",
               lambda m, d: orig(m.replace(dof_damping=m.dof_damping * 1.02), d))


# -- contact geometry and frames ------------------------------------------------------------------


def _contact_distance(mp: pytest.MonkeyPatch) -> None:
    orig = mjx_collision_primitive._plane_sphere  # looked up at call time by plane_sphere
    mp.setattr(mjx_collision_primitive, "_plane_sphere",
               lambda normal, plane_pos, sphere_pos, radius: orig(normal, plane_pos, sphere_pos, radius * 1.01))


def _contact_normal_tilt(mp: pytest.MonkeyPatch) -> None:
    key = (GeomType.PLANE, GeomType.SPHERE)
    orig = mjx_collision_driver._COLLISION_FUNC[key]  # the table binds plane_sphere at import

    def collide(m, d, k, geom):
        dist, pos, frame = orig(m, d, k, geom)
        normal = frame[:, 0] + 0.01 * frame[:, 1]  # tilted 0.01 rad towards the first tangent
        return dist, pos, jax.vmap(mjx_math.make_frame)(normal)

    collide.ncon = orig.ncon
    mp.setitem(mjx_collision_driver._COLLISION_FUNC, key, collide)


# -- constraint impedance and reference -----------------------------------------------------------


def _kbi_patch(mp: pytest.MonkeyPatch, k_scale=1.0, b_scale=1.0, imp_scale=1.0) -> None:
    orig = mjx_constraint._kbi  # looked up at call time by make_constraint

    def buggy(m, solref, solimp, pos):
        k, b, imp = orig(m, solref, solimp, pos)
        return k * k_scale, b * b_scale, imp * imp_scale

    mp.setattr(mjx_constraint, "_kbi", buggy)


def _constraint_stiffness(mp: pytest.MonkeyPatch) -> None:
    _kbi_patch(mp, k_scale=1.02)


def _constraint_damping(mp: pytest.MonkeyPatch) -> None:
    _kbi_patch(mp, b_scale=1.02)


def _constraint_impedance(mp: pytest.MonkeyPatch) -> None:
    _kbi_patch(mp, imp_scale=0.995)


# -- constraint solver ---------------------------------------------------------------------------


def _constraint_force(mp: pytest.MonkeyPatch) -> None:
    orig = mjx_solver.solve

    def buggy(m, d):
        d = orig(m, d)
        extra = 0.01 * d.qfrc_constraint
        return d.replace(qfrc_constraint=d.qfrc_constraint + extra, qacc=d.qacc + mjx_smooth.solve_m(m, d, extra))

    mp.setattr(mjx_solver, "solve", buggy)


# -- friction cones ------------------------------------------------------------------------------


def _friction_coefficient(mp: pytest.MonkeyPatch) -> None:
    orig = mjx_forward.fwd_position
    mp.setattr(mjx_forward, "fwd_position", lambda m, d: orig(m.replace(geom_friction=m.geom_friction * 0.98), d))


def _cone_impratio(mp: pytest.MonkeyPatch) -> None:
    orig = mjx_solver.solve  # the elliptic cone's mu = friction / sqrt(impratio) is formed in the solver

    def buggy(m, d):
        return orig(m.replace(opt=m.opt.replace(impratio=m.opt.impratio * 1.02)), d)

    mp.setattr(mjx_solver, "solve", buggy)


def _friction_regularizer(mp: pytest.MonkeyPatch) -> None:
    orig = mjx_constraint._efc_contact_elliptic  # friction rows' invweight = normal's / impratio

    def buggy(m, d, condim):
        return orig(m.replace(opt=m.opt.replace(impratio=m.opt.impratio * 1.02)), d, condim)

    mp.setattr(mjx_constraint, "_efc_contact_elliptic", buggy)


# -- sensors -------------------------------------------------------------------------------------


def _framequat_order(mp: pytest.MonkeyPatch) -> None:
    # sensor.py's own view of math: quat_mul's arguments swapped, so a site's orientation is
    # site_quat * xquat instead of xquat * site_quat (only sensor.py calls through it)
    view = types.SimpleNamespace(**{k: getattr(mjx_math, k) for k in dir(mjx_math) if not k.startswith("__")})
    view.quat_mul = lambda u, v: mjx_math.quat_mul(v, u)
    mp.setattr(mjx_sensor, "math", view)


def _accelerometer_gravity(mp: pytest.MonkeyPatch) -> None:
    orig = mjx_smooth.rne_postconstraint  # cacc, for acceleration sensors only
    mp.setattr(mjx_smooth, "rne_postconstraint",
               lambda m, d: orig(m.replace(opt=m.opt.replace(gravity=m.opt.gravity * 1.01)), d))


def _touch_force(mp: pytest.MonkeyPatch) -> None:
    orig = mjx_support.contact_force_dim  # contact forces as sensors see them

    def buggy(m, d, dim):
        force, idx = orig(m, d, dim)
        return force * 1.01, idx

    mp.setattr(mjx_support, "contact_force_dim", buggy)


KINEMATICS = "kinematics and orientation integration"
INERTIA = "inertia"
GAIN = "actuator gain"
BIAS = "actuator bias"
PASSIVE = "passive forces"
CONTACT = "contact geometry and frames"
IMPEDANCE = "constraint impedance and reference"
SOLVER = "constraint solver"
FRICTION = "friction cones"
SENSORS = "sensors"

#: Every category, in the order of :data:`BUGS`.
CATEGORIES: tuple[str, ...] = (KINEMATICS, INERTIA, GAIN, BIAS, PASSIVE, CONTACT, IMPEDANCE, SOLVER, FRICTION, SENSORS)

BUGS: tuple[Bug, ...] = (
    Bug("quat_integrate_world_frame", KINEMATICS,
        "The free joint's orientation update composes the rotation increment on the wrong side, "
        "exp(w dt) * q (as if qvel's angular part were in the world frame) instead of q * exp(w dt) "
        "(it is in the body frame). A classic convention slip: exact for an upright body, off by "
        "about tilt x rotation per step otherwise (math.quat_integrate).",
        QUADRUPED, _quat_integrate_world_frame),
    Bug("quat_integrate_angle", KINEMATICS,
        "The orientation increment turns 1% too far (angle 1.01 |w| dt), as when the rotational "
        "part uses a time step of its own, scaled or stale (math.quat_integrate).",
        QUADRUPED, _quat_integrate_angle),
    Bug("hinge_axis_unnormalized", KINEMATICS,
        "Hinge axes enter forward kinematics 1% long: the joint's rotation quaternion is no longer "
        "unit and the motion axes (cdof) scale with it. MuJoCo normalizes axes when compiling; a "
        "path that folds a scale into the axis (units, gear) does not (smooth.kinematics).",
        QUADRUPED, _hinge_axis_unnormalized),
    Bug("body_mass", INERTIA,
        "Composite inertias built from 1% heavier bodies (mass read with a stale scale factor, "
        "e.g. after domain randomization rescaled only part of the model) (smooth.com_pos).",
        QUADRUPED, _body_mass),
    Bug("armature", INERTIA,
        "Joint armature (rotor inertia) added to the mass matrix 2% high, as when reflected "
        "inertia is recomputed from gear and rotor inertia with a rounded ratio (smooth.crb).",
        QUADRUPED, _armature),
    Bug("actuator_gain", GAIN,
        "Actuator gains 2% high (gainprm scaled): the force per unit control is off, as with a "
        "kp taken from a different actuator class or a units slip (forward.fwd_actuation).",
        QUADRUPED, _actuator_gain),
    Bug("actuator_bias", BIAS,
        "The position term of the actuators' affine bias (-kp x length) 1% strong while the gain "
        "stays right: gain and bias of a position servo no longer cancel at the setpoint "
        "(forward.fwd_actuation).",
        QUADRUPED, _actuator_bias),
    Bug("passive_damping", PASSIVE,
        "Joint spring-damper forces 1% high (here: the joint damping), e.g. a damping coefficient "
        "applied with a stale scale (passive._spring_damper).",
        QUADRUPED, _passive_damping),
    Bug("implicit_damping", PASSIVE,
        "The implicit integrator's velocity derivative of the passive force uses damping 2% "
        "high, inconsistent with the damping force itself: implicitfast's M - dt D is off "
        "(derivative.deriv_smooth_vel).",
        QUADRUPED, _implicit_damping),
    Bug("contact_distance", CONTACT,
        "Plane-sphere contacts measure distance (and place the contact point) with the sphere's "
        "radius 1% large, as when a margin or an rbound stands in for the size "
        "(collision_primitive._plane_sphere).",
        QUADRUPED, _contact_distance),
    Bug("contact_normal_tilt", CONTACT,
        "Plane-sphere contact frames tilted 0.01 rad: the normal leans towards the first tangent, "
        "as with a normal taken from a slightly wrong rotation (a stale geom_xmat, a transposed "
        "plane frame on a tilted plane) (collision_driver's plane-sphere collider).",
        QUADRUPED, _contact_normal_tilt),
    Bug("constraint_stiffness", IMPEDANCE,
        "The reference acceleration's stiffness k (from solref's time constant and damping ratio) "
        "2% high, e.g. dmax squared once too few or a rounded time constant (constraint._kbi).",
        QUADRUPED, _constraint_stiffness),
    Bug("constraint_damping", IMPEDANCE,
        "The reference acceleration's damping b = 2 / (dmax timeconst) 2% high (constraint._kbi).",
        QUADRUPED, _constraint_damping),
    Bug("constraint_impedance", IMPEDANCE,
        "The impedance from solimp 0.5% low (e.g. the sigmoid's midpoint or power misread): the "
        "constraint regularizer R = invweight (1 - imp) / imp grows by about 10% "
        "(constraint._kbi).",
        QUADRUPED, _constraint_impedance),
    Bug("constraint_force", SOLVER,
        "The constraint solver's force comes out 1% too large (and the acceleration follows it), "
        "as tests/test_solver_floor.py injects (solver.solve).",
        QUADRUPED, _constraint_force),
    Bug("friction_coefficient", FRICTION,
        "Contact friction coefficients 2% low (geom friction read with a stale scale, or the "
        "pair's friction mixed by mean instead of max where they differ) (forward.fwd_position).",
        QUADRUPED, _friction_coefficient),
    Bug("cone_impratio", FRICTION,
        "The elliptic cone in the solver uses impratio 2% high (mu = friction / sqrt(impratio) "
        "formed from a different impratio than the constraint rows') (solver.solve).",
        QUADRUPED, _cone_impratio),
    Bug("friction_regularizer", FRICTION,
        "The elliptic cone's friction rows get their regularizing weight invweight / impratio "
        "with impratio 2% high, the normal row unchanged (constraint._efc_contact_elliptic).",
        QUADRUPED, _friction_regularizer),
    Bug("framequat_order", SENSORS,
        "Frame-orientation sensors compose the quaternion product in the wrong order, "
        "site_quat x xquat instead of xquat x site_quat: exact for an unrotated site or an "
        "upright body, off by about tilt x mount angle on the yawed IMU (sensor.sensor_pos).",
        QUADRUPED_SENSORS, _framequat_order),
    Bug("accelerometer_gravity", SENSORS,
        "Accelerometers see gravity 1% strong: the acceleration pass for sensors "
        "(rne_postconstraint) starts from a gravity of its own (smooth.rne_postconstraint).",
        QUADRUPED_SENSORS, _accelerometer_gravity),
    Bug("touch_force", SENSORS,
        "Contact forces as sensors read them 1% high (touch, force, torque), the dynamics "
        "unchanged (support.contact_force_dim).",
        QUADRUPED_SENSORS, _touch_force),
)


def by_id(bug_id: str) -> Bug:
    """The bug of :data:`BUGS` named ``bug_id``."""
    for bug in BUGS:
        if bug.id == bug_id:
            return bug
    raise KeyError(f"no injected bug {bug_id!r}; known: {', '.join(b.id for b in BUGS)}")
