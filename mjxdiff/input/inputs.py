"""Scenario -> batched inputs: initial states, controls and per-member models.

Everything random is drawn here, from one :class:`numpy.random.Generator`
seeded by ``(seed, crc32(scenario name))``, so the same seed gives bit-identical
inputs and scenarios do not share streams. Both engines receive exactly these
numbers.
"""

from __future__ import annotations

import copy
import dataclasses
import re
import zlib
from typing import Callable

import mujoco
import numpy as np

from mjxdiff.input import joints
from mjxdiff.compat import disable_bit
from mjxdiff.input.joints import quat_mul, rotvec_quat  # here too: their first home
from mjxdiff.input.scenario import Randomization, Scenario, ScenarioError

__all__ = ["BatchedInputs", "make_inputs", "make_controls", "settable"]

#: Step and smooth controls change about every 0.1 s of simulated time (:func:`knot_every`).
CONTROL_KNOT_SECONDS = 0.1


@dataclasses.dataclass(frozen=True)
class BatchedInputs:
    """What both engines are given, for B batch members and T steps.

    Attributes:
      qpos: (B, nq) initial joint positions.
      qvel: (B, nv) initial joint velocities.
      act: (B, na) initial actuator activations.
      ctrl: (B, T, nu) controls applied before each step.
      models: B compiled C models, each with its own scaled parameters and
        ``mj_setConst`` re-run so derived constants follow.
      factors: parameter name -> (B, ...) multiplicative factors drawn, for
        the report.
      seed: the seed everything was drawn from.
      energy: whether both engines record potential and kinetic energy.
      member_ids: (B,) identity of each member within its scenario's batch
        (default 0..B-1); per-member draws made later (the noise floor's
        perturbations) are seeded by it, so a member replayed alone gets the
        same ones.
      horizon: the steps the rollout's compiled function is planned for, when more than
        ``steps`` (a ``--quick`` run plans for the full run's, so that both compile alike);
        None: ``steps``.
    """

    qpos: np.ndarray
    qvel: np.ndarray
    act: np.ndarray
    ctrl: np.ndarray
    models: tuple[mujoco.MjModel, ...]
    factors: dict[str, np.ndarray]
    seed: int
    energy: bool = False
    member_ids: np.ndarray | None = None
    horizon: int | None = None

    @property
    def ids(self) -> np.ndarray:
        return np.arange(self.batch) if self.member_ids is None else np.asarray(self.member_ids)

    @property
    def batch(self) -> int:
        return self.qpos.shape[0]

    @property
    def steps(self) -> int:
        return self.ctrl.shape[1]

    def take(self, members) -> "BatchedInputs":
        """The members selected by ``members`` (a slice or index array), keeping their identities."""

        def pick(x):
            return np.asarray(x)[members]

        ids = pick(self.ids)
        return dataclasses.replace(
            self, qpos=pick(self.qpos), qvel=pick(self.qvel), act=pick(self.act), ctrl=pick(self.ctrl),
            models=tuple(self.models[int(i)] for i in np.arange(self.batch)[members]),
            factors={k: pick(v) for k, v in self.factors.items()}, member_ids=ids)

    def members(self, idx: np.ndarray) -> "BatchedInputs":
        """The members ``idx`` (an index array; repeats, as padding makes, included), or ``self``
        when ``idx`` is every member in order."""
        return self if np.array_equal(idx, np.arange(self.batch)) else self.take(idx)

    def edit_models(self, edit: Callable[[mujoco.MjModel], None]) -> "BatchedInputs":
        """These inputs with ``edit`` applied to a copy of every member's model (members that
        share a model share its edited copy)."""
        copies: dict[int, mujoco.MjModel] = {}
        for mi in self.models:
            if id(mi) not in copies:
                copies[id(mi)] = copy.copy(mi)
                edit(copies[id(mi)])
        return dataclasses.replace(self, models=tuple(copies[id(mi)] for mi in self.models))

    def concat(self, other: "BatchedInputs") -> "BatchedInputs":
        """These members followed by ``other``'s (same model structure, steps and ``energy``)."""

        def join(a, b):
            return np.concatenate([np.asarray(a), np.asarray(b)])

        return dataclasses.replace(
            self, qpos=join(self.qpos, other.qpos), qvel=join(self.qvel, other.qvel), act=join(self.act, other.act),
            ctrl=join(self.ctrl, other.ctrl), models=self.models + other.models,
            factors={k: join(v, other.factors[k]) for k, v in self.factors.items() if k in other.factors},
            member_ids=join(self.ids, other.ids))


def _rng(seed: int, name: str) -> np.random.Generator:
    return np.random.default_rng([seed, zlib.crc32(name.encode())])


def _initial_qpos(m: mujoco.MjModel, base: np.ndarray, noise: float, batch: int,
                  rng: np.random.Generator) -> np.ndarray:
    """(B, nq) ``base`` plus noise: Gaussian on scalars, random small rotations on quaternions."""
    qpos = np.tile(base, (batch, 1))
    for p in joints.parts(m):
        j, adr = p.joint, p.qpos_adr
        if p.kind == "translation":
            qpos[:, p.qpos] += rng.normal(0, noise, (batch, 3))
        elif p.kind == "rotation":
            q = quat_mul(qpos[:, p.qpos], rotvec_quat(rng.normal(0, noise, (batch, 3))))
            qpos[:, p.qpos] = q / np.linalg.norm(q, axis=-1, keepdims=True)
        else:
            qpos[:, adr] += rng.normal(0, noise, batch)
            if m.jnt_limited[j]:
                lo, hi = m.jnt_range[j]
                # stay strictly inside the limits: a start on the limit is a grazing contact
                margin = 1e-3 * (hi - lo)
                qpos[:, adr] = np.clip(qpos[:, adr], lo + margin, hi - margin)
    return qpos


def roundoff_moved(x: np.ndarray, signs: np.ndarray, size: float | np.ndarray) -> np.ndarray:
    """``x + signs * size * max(|x|, 1)``: ``x`` moved by ``size`` relative units of roundoff per
    component (absolute below 1), in the direction of ``signs`` (+-1, ``x``'s shape). The move of
    C's perturbed rerun (:func:`mjxdiff.compare.noise.perturb`) and of its float32 shadow's every step."""
    return x + signs * size * np.maximum(np.abs(x), 1.0)


def knot_every(timestep: float) -> int:
    """Steps between two knots of step and smooth controls: about :data:`CONTROL_KNOT_SECONDS`
    of simulated time, at least 1. A rollout of T steps has ``T // knot_every + 2`` knots."""
    return max(1, int(round(CONTROL_KNOT_SECONDS / timestep)))


def knot_levels(knots: np.ndarray, steps: int, every: int, family: str) -> np.ndarray:
    """(B, T, nu) levels from (B, K, nu) knots ``every`` steps apart: ``step`` holds each knot,
    ``smooth`` interpolates linearly between neighbours."""
    s = np.arange(steps) / every
    i = np.floor(s).astype(int)
    if family == "step":
        return knots[:, i]
    w = (s - i)[None, :, None]
    return knots[:, i] * (1 - w) + knots[:, i + 1] * w


def sine_levels(freq: np.ndarray, phase: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(B, T, nu) ``sin(2 pi freq t + phase)`` of (B, 1, nu) frequencies (Hz) and phases (rad)
    at times ``t`` (T,) in seconds."""
    return np.sin(2 * np.pi * freq * t[None, :, None] + phase)


def make_controls(m: mujoco.MjModel, randomize: Randomization, batch: int, steps: int,
                  timestep: float, rng: np.random.Generator) -> np.ndarray:
    """(B, T, nu) controls of the scenario's family, clipped to ``ctrlrange``.

    With c the range centre and a = ``control_scale`` * half-width:
    ``zero``: 0; ``sinusoid``: c + a sin(2 pi f t + phi), f ~ U[0.5, 2] Hz;
    ``step``: c + a * (a new U[-1, 1] level every ~0.1 s);
    ``smooth``: the same knots, linearly interpolated.
    The last ``floor(ctrl_outside * B)`` members get c + 1.5 a level, not clipped: they
    leave the range about a third of the time (the draws are the same as without them).
    """
    nu = m.nu
    lo = np.where(m.actuator_ctrllimited, m.actuator_ctrlrange[:, 0], -1.0)
    hi = np.where(m.actuator_ctrllimited, m.actuator_ctrlrange[:, 1], 1.0)
    centre, amp = (hi + lo) / 2, randomize.control_scale * (hi - lo) / 2
    t = np.arange(steps) * timestep
    family = randomize.control
    if family == "zero" or nu == 0:
        ctrl = np.zeros((batch, steps, nu))
    elif family == "sinusoid":
        freq = rng.uniform(0.5, 2.0, (batch, 1, nu))
        phase = rng.uniform(0, 2 * np.pi, (batch, 1, nu))
        ctrl = centre + amp * sine_levels(freq, phase, t)
    else:
        every = knot_every(timestep)
        knots = rng.uniform(-1, 1, (batch, steps // every + 2, nu))
        ctrl = centre + amp * knot_levels(knots, steps, every, family)
    outside = int(np.floor(randomize.ctrl_outside * batch))
    clipped = np.clip(ctrl, lo, hi)
    if outside and family != "zero" and nu:
        clipped[batch - outside:] = centre + 1.5 * (ctrl[batch - outside:] - centre)
    return clipped


Setter = Callable[[mujoco.MjModel, np.ndarray], None]


def settable(m: mujoco.MjModel, key: str) -> tuple[tuple[int, ...], Setter]:
    """Where a ``[randomize.set]`` key writes: the shape of its values and a setter.

    ``key`` is a floating-point ``mjModel`` field (``dof_armature``), one column of
    one (``"geom_solref[0]"``), or an option (``"opt.impratio"``, ``"opt.wind"``).
    Values are absolute, one per element.

    Raises:
      ScenarioError: no such field, not floating point, or empty in this model.
    """
    match = re.fullmatch(r"(opt\.)?([a-z][a-z0-9_]*)(?:\[(\d+)\])?", key)
    owner = m.opt if match and match[1] else m
    value = getattr(owner, match[2], None) if match else None
    where = f"[randomize.set] '{key}'"
    if value is None or isinstance(value, (bool, int)) or key in ("opt.timestep", "opt.gravity"):
        raise ScenarioError(f"{where}: not a floating-point model field or option (timestep and gravity are "
                            "[randomize.scale] parameters)")
    assert match is not None  # value, not None, was read through it
    if isinstance(value, float):
        if match[3] is not None:
            raise ScenarioError(f"{where}: '{match[2]}' is a scalar, it has no columns")
        return (), lambda mi, v: setattr(mi.opt, match[2], float(v))
    value = np.asarray(value)
    if value.dtype.kind != "f" or value.size == 0:
        raise ScenarioError(f"{where}: {'empty in this model' if value.size == 0 else 'not floating point'}")
    name, col = match[2], None if match[3] is None else int(match[3])
    if col is not None:
        if value.ndim != 2 or col >= value.shape[1]:
            raise ScenarioError(f"{where}: '{name}' has no column {col} (shape {value.shape})")
        return value.shape[:1], lambda mi, v: getattr(mi.opt if match[1] else mi, name).__setitem__(
            (slice(None), col), v)
    return value.shape, lambda mi, v: getattr(mi.opt if match[1] else mi, name).__setitem__(..., v)


def _scaled_model(m: mujoco.MjModel, factors: dict[str, np.ndarray], i: int, d: mujoco.MjData,
                  values: dict[str, tuple[Setter, np.ndarray]] | None = None) -> mujoco.MjModel:
    """A copy of ``m`` with member ``i``'s factors and set values applied and constants
    recomputed (``d``: scratch data of ``m``'s sizes; allocating one per member cost more
    than the copy itself)."""
    mi = copy.copy(m)
    for setter, drawn in (values or {}).values():
        setter(mi, drawn[i])
    f = {k: v[i] for k, v in factors.items()}
    if "body_mass" in f:
        mi.body_mass[:] = m.body_mass * f["body_mass"]
        mi.body_inertia[:] = m.body_inertia * f["body_mass"][:, None]  # same density scaling
    if "geom_friction" in f:
        mi.geom_friction[:] = m.geom_friction * f["geom_friction"][:, None]
    if "dof_damping" in f:
        mi.dof_damping[:] = m.dof_damping * f["dof_damping"]
    if "actuator_gain" in f:
        # gain and the affine bias terms together, so a position servo stays a servo
        mi.actuator_gainprm[:, 0] = m.actuator_gainprm[:, 0] * f["actuator_gain"]
        mi.actuator_biasprm[:, 1:3] = m.actuator_biasprm[:, 1:3] * f["actuator_gain"][:, None]
    if "gravity" in f:
        mi.opt.gravity[:] = m.opt.gravity * f["gravity"]
    if "timestep" in f:
        mi.opt.timestep = m.opt.timestep * f["timestep"]
    # C reads derived constants (subtree masses, invweights) that MJX's
    # put_model copies; recompute them so both engines see one consistent model.
    mujoco.mj_setConst(mi, d)
    return mi


def _with_flags(m: mujoco.MjModel, candidates: tuple[str, ...], rng: np.random.Generator) -> mujoco.MjModel:
    """``m`` or a copy with each of ``candidates`` (disable flag names) disabled with probability 1/2."""
    drawn = [f for f in candidates if rng.uniform() < 0.5]
    if not drawn:
        return m
    m = copy.copy(m)
    for f in drawn:
        m.opt.disableflags |= disable_bit(f)
    return m


#: Sensors whose output depends on their site's frame and nothing else about it (a touch sensor's
#: site is a volume, a rangefinder's a ray: turning those changes what they see, not how).
_FRAME_READERS = {int(getattr(mujoco.mjtSensor, f"mjSENS_{k}")) for k in (
    "FRAMEPOS", "FRAMEQUAT", "FRAMEXAXIS", "FRAMEYAXIS", "FRAMEZAXIS", "FRAMELINVEL", "FRAMEANGVEL",
    "FRAMELINACC", "FRAMEANGACC", "ACCELEROMETER", "VELOCIMETER", "GYRO", "FORCE", "TORQUE", "MAGNETOMETER")}


def _frame_sites(m: mujoco.MjModel) -> np.ndarray:
    """Sites that frame, velocity and force sensors read and nothing else uses."""
    site = int(mujoco.mjtObj.mjOBJ_SITE)
    read = set()
    for s in range(m.nsensor):
        if int(m.sensor_type[s]) in _FRAME_READERS:
            if m.sensor_objtype[s] == site:
                read.add(int(m.sensor_objid[s]))
            if m.sensor_reftype[s] == site and m.sensor_refid[s] >= 0:
                read.add(int(m.sensor_refid[s]))
    used = {int(m.sensor_objid[s]) for s in range(m.nsensor)
            if int(m.sensor_type[s]) not in _FRAME_READERS and m.sensor_objtype[s] == site}
    for a in range(m.nu):
        if m.actuator_trntype[a] == int(mujoco.mjtTrn.mjTRN_SITE):
            used |= {int(x) for x in m.actuator_trnid[a] if x >= 0}
    used |= {int(m.eq_obj1id[e]) for e in range(m.neq) if m.eq_objtype[e] == site}
    used |= {int(m.eq_obj2id[e]) for e in range(m.neq) if m.eq_objtype[e] == site}
    return np.array(sorted(read - used), dtype=int)


def _frame_turns(m: mujoco.MjModel, std: float, batch: int, rng: np.random.Generator) -> dict:
    """Per odd member, random rotations (rad, rotation vectors) of :func:`_frame_sites`."""
    sites = _frame_sites(m)
    if not std or not sites.size:
        return {}
    return {i: (sites, rng.normal(0, std, (sites.size, 3))) for i in range(1, batch, 2)}


def _deadbands(m: mujoco.MjModel, width: float, batch: int, rng: np.random.Generator) -> dict:
    """Per odd member, spring deadbands ``(tendons, half-widths)`` for tendon springs at one length."""
    if not width or not m.ntendon:
        return {}
    tendons = np.flatnonzero((m.tendon_stiffness > 0) & (m.tendon_lengthspring[:, 0] == m.tendon_lengthspring[:, 1]))
    if not tendons.size:
        return {}
    return {i: (tendons, width * rng.uniform(0.5, 1.0, tendons.size)) for i in range(1, batch, 2)}


def _interacting(mi: mujoco.MjModel, i: int, turns: dict, deadbands: dict, d: mujoco.MjData) -> mujoco.MjModel:
    """Member ``i``'s model (a fresh copy) with its turned frames and deadbands."""
    if i not in turns and i not in deadbands and not turns:
        return mi
    if i in turns:
        sites, rotvec = turns[i]
        q = quat_mul(mi.site_quat[sites], rotvec_quat(rotvec))
        mi.site_quat[sites] = q / np.linalg.norm(q, axis=-1, keepdims=True)
    if i in deadbands:
        tendons, w = deadbands[i]
        length = mi.tendon_lengthspring[tendons, 0].copy()
        mi.tendon_lengthspring[tendons, 0] = length - w
        mi.tendon_lengthspring[tendons, 1] = length + w
    mujoco.mj_setConst(mi, d)
    if turns:
        # MJX compiles site_sameframe into the rollout: a site turned in some member is "in no body's
        # frame" in all of them (exact for any frame; it only skips a shortcut, in C as in MJX)
        mi.site_sameframe[next(iter(turns.values()))[0]] = 0
    return mi


#: Parameter name -> shape of its per-member factors for a model.
FACTOR_SHAPES = {
    "body_mass": lambda m: (m.nbody,),
    "geom_friction": lambda m: (m.ngeom,),
    "dof_damping": lambda m: (m.nv,),
    "actuator_gain": lambda m: (m.nu,),
    "gravity": lambda m: (),
    "timestep": lambda m: (),
}


def make_inputs(scenario: Scenario, m: mujoco.MjModel, seed: int,
                batch: int | None = None, steps: int | None = None) -> BatchedInputs:
    """Draws the scenario's batch: same ``seed`` and arguments, bit-identical result.

    Args:
      scenario: the scenario (randomization, keyframe, defaults for batch/steps).
      m: its compiled C model.
      seed: master seed.
      batch: overrides ``scenario.batch``.
      steps: overrides ``scenario.steps``.
    """
    batch = batch or scenario.batch
    steps = steps or scenario.steps
    rz = scenario.randomize
    m_in = m
    rng = _rng(seed, scenario.name)
    d = mujoco.MjData(m)
    if scenario.keyframe is not None:
        mujoco.mj_resetDataKeyframe(m, d, mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, scenario.keyframe))
    qpos = _initial_qpos(m, d.qpos.copy(), rz.qpos_noise, batch, rng)
    qvel = np.tile(d.qvel, (batch, 1)) + rng.normal(0, rz.qvel_noise, (batch, m.nv))
    act = np.tile(d.act, (batch, 1))
    factors = {}
    for name in sorted(rz.scale):
        lo, hi = rz.scale[name]
        if lo == hi == 1.0:
            continue
        factors[name] = rng.uniform(lo, hi, (batch, *FACTOR_SHAPES[name](m)))
    ctrl = make_controls(m, rz, batch, steps, m.opt.timestep, rng)
    values = {}
    for key in sorted(rz.values):  # drawn last: scenarios without them draw what they always drew
        try:
            shape, setter = settable(m, key)
        except ScenarioError as e:
            raise ScenarioError(f"{scenario.name}: {e}") from None
        lo, hi = rz.values[key]
        values[key] = (setter, rng.uniform(lo, hi, (batch, *shape)))
    # the interaction draws (flags, frames, deadbands) come from a stream of their own, so that
    # every draw above is what it was before they existed
    extra = np.random.default_rng([seed, zlib.crc32(scenario.name.encode()), 1])
    m = _with_flags(m, rz.disable, extra)
    turns = _frame_turns(m, rz.frame_rotation, batch, extra)
    deadbands = _deadbands(m, rz.spring_range, batch, extra)
    if factors or values or turns or deadbands or m is not m_in:
        scratch = mujoco.MjData(m)
        models = tuple(_interacting(_scaled_model(m, factors, i, scratch, values), i, turns, deadbands, scratch)
                       for i in range(batch))
    else:
        models = (m,) * batch
    return BatchedInputs(qpos=qpos, qvel=qvel, act=act, ctrl=ctrl, models=models, factors=factors, seed=seed,
                        energy=scenario.energy)
