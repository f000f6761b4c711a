"""Hypothesis strategies for differential tests of MJX against MuJoCo C.

In the style of :mod:`hypothesis.extra.numpy`: public strategies whose
arguments take either a value or a strategy, composed with ``@st.composite``
for dependent draws (draw a model, then a ``qpos`` of length ``nq``).

Everything shrinks toward the simple case: fewer bodies and geoms, hinge
joints, spheres, no optional elements, :data:`DEFAULT_OPTIONS`, ``qpos0``,
zero velocities and controls, unit parameter factors, shorter horizons.

For one compiled model, :func:`initial_states`, :func:`control_sequences` and
:func:`parameter_perturbations` always give arrays of the same shapes, so a
property over many states of one model compiles its JAX step once.

Example::

    from hypothesis import given, strategies as st
    from mjxdiff.tools.strategies import mjcf_models, initial_states

    @given(st.data())
    def test_energy_is_finite(data):
        m = data.draw(mjcf_models(max_bodies=2)).model()
        state = data.draw(initial_states(m, batch=4))
        ...
"""


from __future__ import annotations

import functools
from collections.abc import Callable, Iterable
from typing import Any, NamedTuple

import mujoco
import numpy as np
from hypothesis import strategies as st
from hypothesis.errors import InvalidArgument
from hypothesis.extra import numpy as hnp

# what MJX supports lives in mjxdiff.compare.support; public here too, as before
from mjxdiff.compare.support import (SUPPORTED_PAIRS, UNSUPPORTED_FEATURES, UNSUPPORTED_PAIRS, UnsupportedFeature,  # noqa: F401
                             _TYPE_ORDER, pair_supported, refused_features)
from mjxdiff.input import joints
from mjxdiff.input.inputs import FACTOR_SHAPES, knot_every, knot_levels, sine_levels
from mjxdiff.input.joints import quat_mul, rotvec_quat
# the model's parts (mjcf_spec) and their draws (mjcf_draws); the public names here too, as before
from mjxdiff.tools.mjcf_draws import (_INJECTORS, DISABLE_FLAGS, _actuators, _disable_flags,  # noqa: F401
                                      _equalities, _floats, _geoms, _option_features, _options, _sampled,
                                      _sensors, _tendons, _tree, _value)
from mjxdiff.tools.mjcf_spec import _UNSUPPORTED_BY_NAME, DEFAULT_OPTIONS, GEOM_TYPES, JOINT_TYPES, MjcfModel, _Spec

__all__ = [
    "CONTROL_FAMILIES",
    "DEFAULT_OPTIONS",
    "GEOM_TYPES",
    "JOINT_TYPES",
    "PERTURBATION_FIELDS",
    "SUPPORTED_PAIRS",
    "UNSUPPORTED_FEATURES",
    "UNSUPPORTED_PAIRS",
    "MjcfModel",
    "State",
    "UnsupportedFeature",
    "control_sequences",
    "initial_states",
    "mjcf_models",
    "pair_supported",
    "parameter_perturbations",
]


class State(NamedTuple):
    """An initial state: ``(nq,)``, ``(nv,)``, ``(na,)`` arrays, or with a leading batch axis.

    Attributes:
      qpos: joint positions (m, rad, unit quaternions).
      qvel: joint velocities (m/s, rad/s).
      act: actuator activations.
    """

    qpos: np.ndarray
    qvel: np.ndarray
    act: np.ndarray


def _unsupported_names(unsupported: Any) -> tuple[str, ...]:
    refused = tuple(f.name for f in refused_features())  # the installed MJX's, which its MuJoCo can express
    if unsupported is True:
        return refused
    names = (unsupported,) if isinstance(unsupported, str) else tuple(unsupported)
    unknown = [n for n in names if n not in _UNSUPPORTED_BY_NAME]
    if unknown or not names:
        raise InvalidArgument(f"unsupported={unsupported!r}: expected a bool or names from UNSUPPORTED_FEATURES")
    if set(names) - set(refused):
        raise InvalidArgument(f"unsupported={unsupported!r}: the installed MuJoCo/MJX "
                              f"cannot express or does not refuse {sorted(set(names) - set(refused))} "
                              "(support.refused_features)")
    return names


def _check_subset(name: str, values: Iterable[str], allowed: tuple[str, ...]) -> tuple[str, ...]:
    values = tuple(values)
    if not values or set(values) - set(allowed):
        raise InvalidArgument(f"{name}={values!r}: expected a non-empty subset of {allowed}")
    return tuple(v for v in allowed if v in values)  # simplest first, whatever the caller's order


def _extras(draw: Callable, spec: _Spec, geom_types: tuple[str, ...], touch: bool, *, tendons: Any,
            actuators: Any, equality: Any, sensors: Any, flags: Any) -> None:
    """:func:`mjcf_models`' optional parts, in this order, each where allowed (and drawn): tendons,
    actuators, equality constraints, sensors (touch only when ``touch``), a disable flag."""
    if _value(draw, tendons) and draw(st.booleans()):
        _tendons(draw, spec, geom_types)
    if _value(draw, actuators) and draw(st.booleans()):
        _actuators(draw, spec)
    if _value(draw, equality) and draw(st.booleans()):
        _equalities(draw, spec)
    if _value(draw, sensors) and draw(st.booleans()):
        _sensors(draw, spec, touch)
    if _value(draw, flags):
        _disable_flags(draw, spec)


def _inject_unsupported(draw: Callable, spec: _Spec, unsupported: Any) -> None:
    """Adds one feature of ``unsupported`` (:func:`mjcf_models`' argument), drawn, to ``spec``."""
    name = draw(_sampled(_unsupported_names(unsupported)))
    _INJECTORS[name](draw, spec)
    spec.unsupported = name
    spec.features.add(name)


@st.composite
def mjcf_models(draw: Callable, *, max_bodies: Any = 4, max_geoms_per_body: Any = 2,
                joint_types: Any = JOINT_TYPES, geom_types: Any = None, actuators: Any = True,
                tendons: Any = True, equality: Any = True, sensors: Any = True, contacts: Any = True,
                mjx_only: Any = True, unsupported: Any = False, options: Any = True, flags: Any = True) -> MjcfModel:
    """Random MJCF models: a kinematic tree of bodies with joints, geoms, and optional extras.

    Each body has one joint (free only on children of the world; hinge and
    slide ranges, when drawn, contain 0) and 1 to ``max_geoms_per_body``
    geoms (sizes 0.02-0.3 m). A ground plane, contact parameters, actuators,
    tendons, equality constraints, sensors and non-default options are each
    drawn when allowed; all shrink away. The minimal model is one body with
    a hinge and a sphere, and :data:`DEFAULT_OPTIONS`. Angles in the XML are
    radians. Every argument accepts a value or a strategy.

    With ``mjx_only``, a model in which no geom pair can collide gets the
    pyramidal cone and no touch sensor, whatever was drawn: MJX 3.17 fails
    to trace ``mjx.step`` (a TypeError or ValueError, not NotImplementedError)
    for an elliptic cone or a touch sensor when there are constraints but no
    possible contacts; without contacts the cone changes nothing in C.

    Args:
      max_bodies: at most this many bodies (at least 1), world excluded.
      max_geoms_per_body: at most this many geoms per body (at least 1).
      joint_types: joint types to draw from, a subset of :data:`JOINT_TYPES`.
      geom_types: geom types to draw from, a subset of :data:`GEOM_TYPES`
        (None: all of them).
      actuators: whether actuators may be drawn (on hinge/slide joints and fixed tendons).
      tendons: whether fixed and spatial tendons may be drawn.
      equality: whether connect, weld and joint equality constraints may be drawn.
      sensors: whether sensors may be drawn.
      contacts: whether geoms collide; False sets every contype/conaffinity to 0.
      mjx_only: use only what MJX supports: colliding geom pairs limited to
        :data:`SUPPORTED_PAIRS` through contype/conaffinity masks, no margin
        when there are meshes, no condim 1 under an elliptic cone, no PGS
        solver or implicit integrator. False also draws those.
      unsupported: False; True to add one feature drawn from those of
        :data:`UNSUPPORTED_FEATURES` the installed MJX refuses
        (:func:`~mjxdiff.compare.support.refused_features`) to an otherwise MJX-only model;
        or a name (or names) from them to add that one. Requires ``mjx_only=True``.
      options: True to draw ``<option>`` values, False for
        :data:`DEFAULT_OPTIONS`, or a mapping of ``<option>`` attributes
        overriding them (not checked against ``mjx_only``).
      flags: whether a disable flag may be drawn (one of :data:`DISABLE_FLAGS`, shrinking to
        none; springs and dampers only together: MJX 3.17 drops both when either is off).

    Returns:
      A strategy of :class:`MjcfModel`.
    """
    max_bodies = _value(draw, max_bodies)
    max_geoms = _value(draw, max_geoms_per_body)
    if max_bodies < 1 or max_geoms < 1:
        raise InvalidArgument(f"max_bodies={max_bodies}, max_geoms_per_body={max_geoms}: both must be >= 1")
    joint_types = _check_subset("joint_types", _value(draw, joint_types), JOINT_TYPES)
    geom_types = _check_subset("geom_types", _value(draw, geom_types) or GEOM_TYPES, GEOM_TYPES)
    mjx_only, unsupported = _value(draw, mjx_only), _value(draw, unsupported)
    if unsupported is not False and unsupported is not None and not mjx_only:
        raise InvalidArgument("unsupported requires mjx_only=True: the model must use exactly one unsupported feature")

    spec = _Spec(option=_options(draw, options, bool(mjx_only)))
    spec.features |= _option_features(spec.option)
    _tree(draw, spec, max_bodies, joint_types)
    _geoms(draw, spec, max_geoms, geom_types, bool(_value(draw, contacts)), bool(mjx_only))
    touch = True
    if mjx_only and not spec.contact_possible():  # see the docstring: MJX 3.17 trace failures
        spec.option["cone"] = "pyramidal"
        spec.features.discard("elliptic cone")
        touch = False
    _extras(draw, spec, geom_types, touch, tendons=tendons, actuators=actuators, equality=equality,
            sensors=sensors, flags=flags)
    if unsupported:
        _inject_unsupported(draw, spec, unsupported)
    ngeom = len(spec.world_geoms) + sum(len(b.geoms) for b in spec.bodies)
    return MjcfModel(xml=spec.render(), nbody=len(spec.bodies) + spec.mocap_bodies, ngeom=ngeom,
                     features=tuple(sorted(spec.features)), unsupported_feature=spec.unsupported)


# ---------------------------------------------------------------------------
# States, controls, parameter factors for one compiled model (fixed shapes).


def _unit_floats() -> st.SearchStrategy:
    return _floats(-1.0, 1.0)


@functools.cache
def _unit_array(shape: tuple[int, ...]) -> st.SearchStrategy:
    """float64 arrays of ``shape`` with elements in [-1, 1], shrinking to zeros."""
    return hnp.arrays(np.float64, shape, elements=_unit_floats())


def _perturbed_qpos(m: mujoco.MjModel, noise: np.ndarray, scale: float, within_limits: bool) -> np.ndarray:
    """``qpos0`` moved by ``scale * noise``: ``(B, nv)`` noise in [-1, 1] to ``(B, nq)`` qpos.

    Scalars and free-joint positions move by the noise (m or rad); quaternions
    are rotated by the noise as a rotation vector (rad) and renormalised.
    """
    qpos = np.tile(m.qpos0, (noise.shape[0], 1))
    limited = m.jnt_limited.astype(bool)
    for p in joints.parts(m):
        j, q, v = p.joint, p.qpos_adr, p.dof_adr
        if p.kind == "translation":
            qpos[:, p.qpos] += scale * noise[:, p.dof]
        elif p.kind == "rotation":
            rotvec = scale * noise[:, p.dof]
            if within_limits and limited[j] and m.jnt_type[j] == mujoco.mjtJoint.mjJNT_BALL:
                # ball limit: rotation angle (from qpos0, usually identity) below range[1]
                top = (1 - 1e-3) * m.jnt_range[j, 1]
                angle = np.linalg.norm(rotvec, axis=-1, keepdims=True)
                rotvec = rotvec * np.minimum(1.0, top / np.maximum(angle, 1e-300))
            quat = quat_mul(qpos[:, p.qpos], rotvec_quat(rotvec))
            qpos[:, p.qpos] = quat / np.linalg.norm(quat, axis=-1, keepdims=True)
        else:
            qpos[:, q] += scale * noise[:, v]
            if within_limits and limited[j]:
                lo, hi = m.jnt_range[j]
                margin = 1e-3 * (hi - lo)  # strictly inside: a start on the limit is a grazing contact
                qpos[:, q] = np.clip(qpos[:, q], lo + margin, hi - margin)
    return qpos


def _check_batch(batch: Any) -> int:
    if batch is not None and (isinstance(batch, st.SearchStrategy) or int(batch) < 1):
        raise InvalidArgument(f"batch={batch!r}: expected None or a positive int (shapes stay fixed)")
    return 1 if batch is None else int(batch)


@st.composite
def initial_states(draw: Callable, m: mujoco.MjModel, *, batch: int | None = None,
                   qpos_scale: Any = _floats(0, 0.5), qvel_scale: Any = _floats(0, 1.0),
                   act_scale: Any = _floats(0, 1.0), within_limits: bool = True) -> State:
    """Initial states near ``qpos0``, shrinking to ``qpos0`` and zero velocities and activations.

    Args:
      m: a compiled model.
      batch: None for ``(nq,)``, ``(nv,)``, ``(na,)`` arrays; an int B for ``(B, ...)``.
      qpos_scale: largest displacement from ``qpos0`` per coordinate (m or
        rad; rotation-vector components for quaternions). Value or strategy.
      qvel_scale: largest joint velocity (m/s or rad/s). Value or strategy.
      act_scale: largest activation magnitude (clipped to ``actrange`` where limited).
      within_limits: keep limited hinge/slide joints strictly inside their
        range and limited ball joints below their angle.

    Returns:
      A strategy of :class:`State`; quaternions have unit norm.
    """
    nbatch = _check_batch(batch)
    qpos_scale, qvel_scale, act_scale = (float(_value(draw, s)) for s in (qpos_scale, qvel_scale, act_scale))
    qpos = _perturbed_qpos(m, draw(_unit_array((nbatch, m.nv))), qpos_scale, within_limits)
    qvel = qvel_scale * draw(_unit_array((nbatch, m.nv)))
    act = act_scale * draw(_unit_array((nbatch, m.na)))
    if m.na:
        adr = m.actuator_actadr
        for i in np.flatnonzero((adr >= 0) & m.actuator_actlimited.astype(bool)):
            a = slice(adr[i], adr[i] + m.actuator_actnum[i])
            act[:, a] = np.clip(act[:, a], *m.actuator_actrange[i])
    state = State(qpos=qpos, qvel=qvel + 0.0, act=act + 0.0)  # + 0.0 turns -0.0 into 0.0
    return state if batch is not None else State(*(x[0] for x in state))


CONTROL_FAMILIES = ("zero", "constant", "step", "smooth", "sinusoid", "noise")
"""Control families of :func:`control_sequences`, simplest first."""

def _ctrl_bounds(m: mujoco.MjModel) -> tuple[np.ndarray, np.ndarray]:
    """(nu,) lower and upper control bounds; [-1, 1] where unlimited."""
    limited = m.actuator_ctrllimited.astype(bool)
    return (np.where(limited, m.actuator_ctrlrange[:, 0], -1.0),
            np.where(limited, m.actuator_ctrlrange[:, 1], 1.0))


def _levels_to_ctrl(level: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Levels in [-1, 1] to controls in [lo, hi]: 0 is the control closest to 0, +-1 the bounds."""
    z = np.clip(0.0, lo, hi)
    ctrl = np.where(level >= 0, z + level * (hi - z), z + level * (z - lo))
    return np.clip(ctrl, lo, hi)


@st.composite
def control_sequences(draw: Callable, m: mujoco.MjModel, steps: Any, *, batch: int | None = None,
                      family: Any = None) -> np.ndarray:
    """Control sequences within ``ctrlrange``, shrinking to zeros (the in-range value nearest 0).

    Families (one per draw, parameters per batch member), with levels in [-1, 1]
    mapped onto ``ctrlrange`` ([-1, 1] where unlimited): ``zero``; ``constant``;
    ``step`` (a new level every ~0.1 s of simulated time); ``smooth`` (those
    knots interpolated linearly); ``sinusoid`` (amplitude in [-1, 1], 0.5-2 Hz,
    any phase); ``noise`` (a new level every step).

    Args:
      m: a compiled model; its timestep sets the knot spacing.
      steps: number of steps T, an int or a strategy (shorter shrinks first).
      batch: None for ``(T, nu)``; an int B for ``(B, T, nu)``.
      family: None for any of :data:`CONTROL_FAMILIES`, a name, or a strategy of names.

    Returns:
      A strategy of float64 arrays.
    """
    nbatch = _check_batch(batch)
    steps = int(_value(draw, steps))
    if steps < 1:
        raise InvalidArgument(f"steps={steps}: expected >= 1")
    family = draw(st.sampled_from(CONTROL_FAMILIES)) if family is None else _value(draw, family)
    if family not in CONTROL_FAMILIES:
        raise InvalidArgument(f"family={family!r}: expected one of {CONTROL_FAMILIES}")
    nu = m.nu
    t = np.arange(steps) * m.opt.timestep
    every = knot_every(m.opt.timestep)
    if family == "zero" or nu == 0:
        level = np.zeros((nbatch, steps, nu))
    elif family == "constant":
        level = np.broadcast_to(draw(_unit_array((nbatch, 1, nu))), (nbatch, steps, nu))
    elif family in ("step", "smooth"):
        level = knot_levels(draw(_unit_array((nbatch, steps // every + 2, nu))), steps, every, family)
    elif family == "sinusoid":
        amp = draw(_unit_array((nbatch, 1, nu)))
        freq = draw(hnp.arrays(np.float64, (nbatch, 1, nu), elements=_floats(0.5, 2.0)))  # Hz
        phase = draw(hnp.arrays(np.float64, (nbatch, 1, nu), elements=_floats(0.0, 2 * np.pi)))
        level = amp * sine_levels(freq, phase, t)
    else:
        level = draw(_unit_array((nbatch, steps, nu)))
    lo, hi = _ctrl_bounds(m)
    ctrl = _levels_to_ctrl(level, lo, hi) + 0.0
    return ctrl if batch is not None else ctrl[0]


PERTURBATION_FIELDS = FACTOR_SHAPES
"""Parameter name -> factor shape for a model, as :mod:`mjxdiff.input.inputs` scales them."""


@st.composite
def parameter_perturbations(draw: Callable, m: mujoco.MjModel, *, max_relative: Any = 0.2,
                            batch: int | None = None, fields: Iterable[str] | None = None
                            ) -> dict[str, np.ndarray]:
    """Multiplicative parameter factors in ``[1 - max_relative, 1 + max_relative]``, shrinking to ones.

    Args:
      m: a compiled model (sets the shapes).
      max_relative: largest relative change, in [0, 1); a value or a strategy.
      batch: None for the shapes of :data:`PERTURBATION_FIELDS`; an int B
        prepends a batch axis (the layout of ``BatchedInputs.factors``).
      fields: which of :data:`PERTURBATION_FIELDS` to draw (None: all).

    Returns:
      A strategy of dicts name -> float64 array (0-d for ``gravity`` and ``timestep``).
    """
    nbatch = _check_batch(batch)
    max_relative = float(_value(draw, max_relative))
    if not 0 <= max_relative < 1:
        raise InvalidArgument(f"max_relative={max_relative}: expected 0 <= max_relative < 1")
    names = tuple(PERTURBATION_FIELDS) if fields is None else tuple(fields)
    unknown = set(names) - set(PERTURBATION_FIELDS)
    if unknown:
        raise InvalidArgument(f"fields: unknown {sorted(unknown)}; expected names from {tuple(PERTURBATION_FIELDS)}")
    out = {}
    for name in names:
        shape = PERTURBATION_FIELDS[name](m)
        u = draw(_unit_array((nbatch, *shape)))
        factor = 1.0 + max_relative * u
        out[name] = factor if batch is not None else factor[0]
    return out
