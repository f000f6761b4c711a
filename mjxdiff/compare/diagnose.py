"""Why a scenario diverges: local error, pipeline drill-down, cause attribution.

* :func:`local_error` re-synchronises MJX to the C state every k steps, so chaos
  cannot amplify the error: a real bug shows as a one-step error far above
  rounding; chaos does not.
* :func:`drill_down` evaluates ``mj_forward`` and ``mjx.forward`` from the same
  C state at the first divergent step and names the earliest pipeline stage
  (kinematics, inertia, tendons, collision, passive, bias, actuation, smooth
  acceleration, constraint, acceleration, sensors) whose quantities disagree.
* :func:`attribute_cause` re-runs the scenario under ablations (float64, a
  converged solver, contacts disabled, a smaller timestep, another integrator)
  and reports the first that makes it pass.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
from typing import TYPE_CHECKING, Any, Callable, Protocol, Self, TypeVar

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from mjxdiff.engine.stages import PARAMETERS, Contacts, contacts_c as _contacts_c, contacts_mjx as _contacts_mjx  # noqa: F401
from mjxdiff.input.options import ENGINES
from mjxdiff.input.precision import THRESHOLDS, Precision
from mjxdiff.errors import one_line
from mjxdiff.compat import full_inertia, sensor_types
from mjxdiff import metrics
from mjxdiff.engine.engines import CEngine, MJXEngine, Trajectory
from mjxdiff.input.inputs import BatchedInputs
from mjxdiff.compare.support import NO_CONTACTS
from mjxdiff.compare.noise import converge_solver

if TYPE_CHECKING:
    from mjxdiff.engine.trajectory import Engine

__all__ = ["STAGES", "CONTACT_FREE_STAGES", "StageDiff", "DrillDown", "contact_detail", "drill_down", "reconcile_cause",
           "first_fields", "local_error", "attribute_cause", "ABLATIONS", "GENUINE", "UNCLASSIFIED"]

#: Pipeline stages in the order ``mj_forward`` computes them, with their fields.
STAGES: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("kinematics", ("xpos", "xquat", "xipos")),
    ("inertia", ("qM",)),
    ("tendons", ("ten_length",)),
    ("collision", ("contact",)),
    ("passive", ("qfrc_passive",)),
    ("bias", ("qfrc_bias",)),
    ("actuation", ("actuator_force", "qfrc_actuator")),
    ("smooth acceleration", ("qacc_smooth",)),
    ("constraint", ("qfrc_constraint",)),
    ("acceleration", ("qacc",)),
    ("sensors", ("sensordata",)),
)

#: Stages after ``collision`` that read no contact: what they compute from the same state must agree
#: whatever contacts the engines made.
CONTACT_FREE_STAGES = ("passive", "bias", "actuation", "smooth acceleration")

#: Relative disagreement (|mjx - c| / (1 + max|c|)) above which a stage differs.
STAGE_RTOL = {p: t.stage_rtol for p, t in THRESHOLDS.items()}


@dataclasses.dataclass(frozen=True)
class StageDiff:
    """One field of one stage: worst scaled error ``|mjx - c| / (1 + max|c|)`` and the object it
    belongs to; ``bound``, the largest ``|mjx - c|`` the stage allows (the precision's
    :meth:`~mjxdiff.input.precision.Thresholds.stage_bound`, field units; NaN for ``contact``, judged
    on its own scale); for the ``contact`` field, the worst geom pair as data
    (:func:`contact_detail`), what known entries and the shrinker match on (never the object's text)."""

    stage: str
    field: str
    error: float
    object: str
    differs: bool
    contact: dict[str, Any] | None = None
    bound: float = float("nan")
    #: the element behind :attr:`object`, as data (:func:`_element`); None for a body or a contact
    element: dict[str, str] | None = None


@dataclasses.dataclass(frozen=True)
class DrillDown:
    """Stage-by-stage comparison from one C state.

    Attributes:
      member, step: where the state was taken (the state before ``step``).
      first_stage / first_field / object: the earliest stage that differs,
        or ``None`` when every stage agrees at that state.
      fields: every compared field, in pipeline order.
      contact: the worst geom pair's :func:`contact_detail`, where the first field is ``contact``.
    """

    member: int
    step: int
    first_stage: str | None
    first_field: str | None
    object: str
    fields: tuple[StageDiff, ...]
    #: the first differing field's :attr:`StageDiff.contact`, where that field is ``contact``
    contact: dict[str, Any] | None = None
    #: the element of :attr:`object` as data (``kind``, ``name``, ``type``: a tendon's ``fixed``,
    #: ``spatial`` or ``spatial-sidesite``, a joint's type, a sensor's), what catalogue entries
    #: match on (:attr:`mjxdiff.compare.support.Entry.element`); None for a body or a contact
    element: dict[str, str] | None = None
    #: where the first stage to differ is ``collision``: the first field of a later stage that
    #: reads no contact (:data:`CONTACT_FREE_STAGES`) that differs too, as ``stage``, ``field``
    #: and ``object``; None if none does. A contact difference is then not the whole story: the
    #: engines part where contacts play no part (a velocity or bias-force bug beside a known
    #: contact approximation), and no contact entry of the catalogue labels the failure.
    beside_contacts: dict[str, str] | None = None


def _name(m: mujoco.MjModel, obj: mujoco.mjtObj, i: int) -> str:
    return mujoco.mj_id2name(m, obj, int(i)) or f"#{int(i)}"


def _object(m: mujoco.MjModel, field: str, index: int, element: dict[str, str] | None) -> str:
    """The MuJoCo object behind a flat index into ``field``, as reports name it (``element``: its
    :func:`_element`)."""
    from mjxdiff.compare.verdict import describe

    if field in ("xpos", "xquat", "xipos"):
        return f"body '{_name(m, mujoco.mjtObj.mjOBJ_BODY, index)}'"
    return describe(element) if element else ""


def _tendon_type(m: mujoco.MjModel, t: int) -> str:
    """``fixed``, ``spatial``, or ``spatial-sidesite`` (a spatial tendon that wraps a sphere or
    cylinder on the side of a sidesite)."""
    wraps = range(m.tendon_adr[t], m.tendon_adr[t] + m.tendon_num[t])
    if any(m.wrap_type[i] == int(mujoco.mjtWrap.mjWRAP_JOINT) for i in wraps):
        return "fixed"
    geom = (int(mujoco.mjtWrap.mjWRAP_SPHERE), int(mujoco.mjtWrap.mjWRAP_CYLINDER))
    return "spatial-sidesite" if any(m.wrap_type[i] in geom and m.wrap_prm[i] >= 0 for i in wraps) else "spatial"


def _element(m: mujoco.MjModel, field: str, index: int) -> dict[str, str] | None:
    """The MuJoCo element behind a flat index into ``field``, as data (``kind``, ``name``, ``type``,
    as :func:`mjxdiff.compare.verdict.component_elements` gives them for the rollout's fields): a joint's
    ``free``/``ball``/``slide``/``hinge``, a sensor's ``accelerometer``, ..., a tendon's
    :func:`_tendon_type`; None for a body or a field without one."""
    from mjxdiff.compare.verdict import joint_element, sensor_element

    if field in ("qM", "qfrc_passive", "qfrc_bias", "qfrc_actuator", "qacc_smooth", "qfrc_constraint", "qacc"):
        return joint_element(m, int(m.dof_jntid[index % m.nv if field == "qM" else index]))
    if field == "ten_length":
        return dict(kind="tendon", name=_name(m, mujoco.mjtObj.mjOBJ_TENDON, index), type=_tendon_type(m, index))
    if field == "actuator_force":
        return dict(kind="actuator", name=_name(m, mujoco.mjtObj.mjOBJ_ACTUATOR, index), type="")
    if field == "sensordata":
        return sensor_element(m, int(np.searchsorted(m.sensor_adr, index, side="right") - 1))
    return None


def contact_detail(pair: str, geoms: tuple[str, ...], c: int, mjx: int, part: str | None,
                   explained: str | None = None) -> dict[str, Any]:
    """A geom pair's contact disagreement as data: ``pair`` the geom types, sorted and joined by
    ``-`` (``plane-mesh``; a flex is ``flex``), ``geoms`` their names, ``c`` and ``mjx`` each
    engine's contact count, ``part`` what differs where the counts agree (the geometry first:
    ``dist``, ``position`` or ``normal``; else ``friction`` or ``tangent frame``), ``count`` where
    they do not; ``explained`` what known formula accounts for the difference in full, where one
    does (``segment regularisation``: :func:`mjxdiff.compare.segments.explains`), else absent."""
    out = dict(pair=pair, geoms=list(geoms), c=c, mjx=mjx, part=part if c == mjx else "count")
    return out | (dict(explained=explained) if explained else {})


#: What each number of a collected contact is (:func:`_contacts_c`).
_CONTACT_PARTS = (("dist",) + ("position",) * 3 + ("friction",) * 2 + ("normal",) * 3 + ("tangent frame",) * 6
                  + tuple(name for name, n in PARAMETERS for _ in range(n)))
#: The numbers of a contact's geometry: where they differ, a frame or friction that differs with
#: them follows from them, and the geometry is what the contact's difference is.
_GEOMETRY = np.array([i for i, part in enumerate(_CONTACT_PARTS) if part in ("dist", "position", "normal")])
_NORMAL = slice(6, 9)


def _part(diff: np.ndarray, floor: float) -> tuple[str, float]:
    """(what differs, by how much) of a geom pair's contacts, from ``diff`` (per number, the
    largest |mjx - c| over its matched contacts): the geometry's largest where it is over
    ``floor``, else the largest of all."""
    i = int(_GEOMETRY[diff[_GEOMETRY].argmax()]) if diff[_GEOMETRY].max() > floor else int(diff.argmax())
    return _CONTACT_PARTS[i], float(diff[i])


def _normal_angle(a: list[tuple[float, ...]], b: list[tuple[float, ...]]) -> float:
    """The largest angle, degrees, between matched contacts' normals."""
    na, nb = np.asarray(a)[:, _NORMAL], np.asarray(b)[:, _NORMAL]
    cos = np.sum(na * nb, axis=1) / np.maximum(np.linalg.norm(na, axis=1) * np.linalg.norm(nb, axis=1), 1e-300)
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))).max())


def _regularisation_explains(m: mujoco.MjModel, d: mujoco.MjData | None, pair: tuple[int, ...],
                             b: list[tuple[float, ...]]) -> bool:
    """Whether a geom pair's single contact differs between C and the engine (``b``, its collected
    contacts: :func:`mjxdiff.engine.stages.contacts_c`'s form) by MJX's regularized segment solve
    alone (:func:`mjxdiff.compare.segments.explains`, read from C's own contact in ``d``: C's data
    after ``mj_forward`` at the state; None: not known, so not explained)."""
    from mjxdiff.compare import segments

    if d is None or len(b) != 1 or min(pair) < 0:  # a flex side has no segment
        return False
    cons = [c for c in d.contact[:d.ncon] if tuple(sorted((int(c.geom1), int(c.geom2)))) == pair]
    if len(cons) != 1:
        return False
    x = np.asarray(b[0])
    sign = 1.0 if cons[0].geom1 < cons[0].geom2 else -1.0  # collected normals point to the higher geom id
    return segments.explains(m, d, cons[0], (float(x[0]), x[1:4], sign * x[6:9]))


def _contact_diff(m: mujoco.MjModel, cc: Contacts, cx: Contacts, floor: float = 0.0,
                  d: mujoco.MjData | None = None, label: str = "MJX") -> tuple[float, str, dict[str, Any] | None]:
    """Worst contact disagreement: inf for a geom pair whose contact count differs, else the
    largest |dist|, |pos|, |friction| or frame difference, each engine's contacts matched by
    position. What differs (:func:`_part`) is the geometry where it differs by more than
    ``floor``; a normal's difference is said as an angle. ``d``: C's data after ``mj_forward``,
    to tell MJX's capsule regularisation (:func:`_regularisation_explains`); ``label`` names the
    engine under test in the description.
    Returns (error, the pair's description, its :func:`contact_detail`; None if no pair)."""
    worst, obj, detail = 0.0, "", None
    for pair in sorted(set(cc) | set(cx)):

        def by_pos(c):
            return (round(c[1], 6), round(c[2], 6), round(c[3], 6))

        a, b = sorted(cc.get(pair, []), key=by_pos), sorted(cx.get(pair, []), key=by_pos)
        diff = np.abs(np.subtract(a, b)).max(axis=0) if len(a) == len(b) and a else np.zeros(0)
        err = np.inf if len(a) != len(b) else float(diff.max(initial=0.0))
        if err > worst:
            named = tuple(_name(m, mujoco.mjtObj.mjOBJ_GEOM, g) if g >= 0 else
                          f"flex '{_name(m, mujoco.mjtObj.mjOBJ_FLEX, -1 - g)}'" for g in pair)
            names = " / ".join(named)
            geoms = [g for g in pair if g >= 0]
            kinds = "-".join(["flex"] * (len(pair) - len(geoms)) + [
                mujoco.mjtGeom(t).name[len("mjGEOM_"):].lower() for t in sorted(m.geom_type[geoms])])
            which, amount = _part(diff, floor) if diff.size else (None, 0.0)
            said = (f"; normal differs by {_normal_angle(a, b):.2g} degrees" if which == "normal"
                    else f"; {which} differs by {amount:.2g}" if which else "")
            explained = "segment regularisation" if diff.size and _regularisation_explains(m, d, pair, b) else None
            worst, obj = err, f"geoms {names} ({kinds}: C {len(a)}, {label} {len(b)} contacts{said})"
            detail = contact_detail(kinds, named, len(a), len(b), which, explained)
    return worst, obj, detail


def drill_down(m: mujoco.MjModel, qpos: np.ndarray | jax.Array, qvel: np.ndarray | jax.Array,
               act: np.ndarray | jax.Array, ctrl: np.ndarray, time: float, precision: Precision = "float64",
               member: int = 0, step: int = 0, qacc_warmstart: np.ndarray | None = None,
               engine: Engine | None = None) -> DrillDown:
    """Compares every stage of ``mj_forward`` and the other implementation's forward from one state.

    Args:
      m: the member's C model.
      qpos, qvel, act, ctrl, time: the state and controls before the step.
      precision: sets each stage's threshold (:meth:`mjxdiff.input.precision.Thresholds.stage_bound`:
        ``max|mjx - c| <= atol + rtol max|c|``, per stage under float32).
      qacc_warmstart: the solver's warm start there (both engines start from it); None: zero.
      engine: the engine under test (default MJX), whose ``forward`` (:meth:`mjxdiff.engine.trajectory.Engine.forward`)
        is compared with C's.
    """
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:], d.ctrl[:], d.time = qpos, qvel, ctrl, time
    if qacc_warmstart is not None:
        d.qacc_warmstart[:] = qacc_warmstart
    if m.na:
        d.act[:] = act
    fields = tuple(f for _, fs in STAGES for f in fs if f not in ("qM", "contact"))
    under_test = (engine or MJXEngine()).forward(m, d, fields)
    values_x, contacts_x = dict(under_test.values, qM=under_test.qM.ravel()), under_test.contacts
    reference = CEngine().forward(m, d, fields)
    values_c = dict(reference.values, qM=reference.qM.ravel())
    thresholds = THRESHOLDS[precision]
    rtol = thresholds.stage_rtol
    extra = float32_rounding(m, d) if precision == "float32" else {}
    diffs = []
    for stage, fields in STAGES:
        for f in fields:
            if f == "contact":
                dc = copy.copy(d)
                mujoco.mj_forward(m, dc)  # C's poses, for the capsule formulas
                label = ENGINES.get(getattr(engine, "name", "mjx"), ENGINES["mjx"]).label
                err, obj, detail = _contact_diff(m, reference.contacts, contacts_x, 1e3 * rtol, dc, label)
                diffs.append(StageDiff(stage, f, err, obj, err > 1e3 * rtol, detail))
                continue
            c, x = values_c[f], values_x[f]
            if c.size == 0:
                continue
            scale = float(np.max(np.abs(c)))
            gap = np.abs(x - c)
            bound = thresholds.stage_bound(stage, scale) + extra.get(f, 0.0)  # scalar, or per component
            over = np.where(np.isnan(gap), np.inf, gap - bound)
            i = int(np.argmax(over))
            element = _element(m, f, i)
            diffs.append(StageDiff(stage, f, float(gap[i]) / (1 + scale), _object(m, f, i, element), not over[i] <= 0,
                                   bound=float(np.broadcast_to(bound, gap.shape)[i]), element=element))
    first = next((s for s in diffs if s.differs), None)
    beside = next((s for s in diffs if s.differs and s.stage in CONTACT_FREE_STAGES), None) if (
        first is not None and first.stage == "collision") else None
    return DrillDown(member=member, step=step, first_stage=first and first.stage, first_field=first and first.field,
                     object=first.object if first else "", fields=tuple(diffs), contact=first and first.contact,
                     element=first and first.element,
                     beside_contacts=beside and dict(stage=beside.stage, field=beside.field, object=beside.object))


def first_fields(drill: DrillDown) -> str:
    """``first field to differ: FIELD (STAGE, OBJECT)``, and the first contact-free field that differs
    beside a contact (:attr:`DrillDown.beside_contacts`); "" where every stage agrees."""
    if not drill.first_field:
        return ""
    said = f"first field to differ: {drill.first_field} ({drill.first_stage}, {drill.object})"
    b = drill.beside_contacts
    return said + (f"; apart from contacts: {b['field']} ({b['stage']}, {b['object']})" if b else "")


#: How many float32 roundings a rounding bound allows (MuJoCo's parity method's factor).
FLOAT32_ROUNDING_FACTOR = 8.0


def float32_rounding(m: mujoco.MjModel, d: mujoco.MjData) -> dict[str, np.ndarray]:
    """Per-component float32 rounding bounds (field units) that the float32 drill-down adds to a
    stage's tolerance where rounding is amplified beyond the field's scale (MuJoCo's parity method,
    ``mujoco/doc/skills/parity/SKILL.md``; ``F = FLOAT32_ROUNDING_FACTOR``, ``eps`` float32's):

    - stiff affine actuators: a force is a difference of large terms, so rounding ``L``
      (``actuator_length``) or ``V`` (``actuator_velocity``) costs
      ``actuator_force: F eps (|g0| + |g1 L| + |g2 V|) |u| + F eps (|b0| + |b1 L| + |b2 V|)``
      (``u`` the clamped control, or the activation), and
      ``qfrc_actuator: |moment|^T actuator_force's bound``;
    - an ill-conditioned mass matrix: ``M`` sums parallel-axis terms far larger than its entries,
      and solving with it amplifies their rounding by ``|M^-1|``:
      ``qM: F eps S`` and ``qacc_smooth, qacc: F eps |M^-1| (S |qacc| + |qfrc|)``, ``S`` the
      magnitude of the spatial-inertia terms summed into each entry of ``M``.

    ``d``: the state before the step (a copy is forwarded here). Shapes: each field's, ``qM``
    (nv * nv) row-major as the drill-down reads it.
    """
    d = copy.copy(d)
    mujoco.mj_forward(m, d)
    eps = float(np.finfo(np.float32).eps)
    out: dict[str, np.ndarray] = {}
    if m.nu and not m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_ACTUATION:
        out.update(_actuator_rounding(m, d, eps))
    if m.nv:
        out.update(_mass_rounding(m, d, eps))
    return out


def _actuator_rounding(m: mujoco.MjModel, d: mujoco.MjData, eps: float) -> dict[str, np.ndarray]:
    length, velocity = d.actuator_length, d.actuator_velocity
    gain, bias = m.actuator_gainprm, m.actuator_biasprm
    ctrl = d.ctrl.copy()
    if not m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CLAMPCTRL:
        lim = m.actuator_ctrllimited.astype(bool)
        ctrl[lim] = np.clip(ctrl[lim], m.actuator_ctrlrange[lim, 0], m.actuator_ctrlrange[lim, 1])
    drive = np.abs(ctrl)
    stateful = m.actuator_actnum > 0
    if stateful.any():
        act = d.act[m.actuator_actadr[stateful] + m.actuator_actnum[stateful] - 1].copy()
        lim = m.actuator_actlimited[stateful].astype(bool)
        act[lim] = np.clip(act[lim], m.actuator_actrange[stateful][lim, 0], m.actuator_actrange[stateful][lim, 1])
        drive[stateful] = np.abs(act)
    affine_gain = m.actuator_gaintype == mujoco.mjtGain.mjGAIN_AFFINE
    affine_bias = m.actuator_biastype == mujoco.mjtBias.mjBIAS_AFFINE
    gains = np.abs(gain[:, 0]) + np.where(affine_gain, np.abs(gain[:, 1] * length) + np.abs(gain[:, 2] * velocity), 0)
    biases = np.where(affine_bias, np.abs(bias[:, 0]) + np.abs(bias[:, 1] * length) + np.abs(bias[:, 2] * velocity), 0)
    affine = ((affine_gain | (m.actuator_gaintype == mujoco.mjtGain.mjGAIN_FIXED))
              & (affine_bias | (m.actuator_biastype == mujoco.mjtBias.mjBIAS_NONE)))
    force = np.where(affine, FLOAT32_ROUNDING_FACTOR * eps * (gains * drive + biases), 0.0)
    moment = np.zeros((m.nu, m.nv))
    mujoco.mju_sparse2dense(moment, d.actuator_moment, d.moment_rownnz, d.moment_rowadr, d.moment_colind)
    return {"actuator_force": force, "qfrc_actuator": np.abs(moment).T @ force}


def _mass_scale(m: mujoco.MjModel, d: mujoco.MjData) -> np.ndarray:
    """(nv, nv): magnitude of the spatial-inertia terms summed into each entry of ``M``."""
    cinert = np.abs(d.cinert)
    inertia = np.zeros((m.nbody, 6, 6))
    for k, (r, c) in enumerate(((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))):
        inertia[:, r, c] = inertia[:, c, r] = cinert[:, k]
    mc = cinert[:, 6:9]
    skew = np.zeros((m.nbody, 3, 3))
    skew[:, 0, 1] = skew[:, 1, 0] = mc[:, 2]
    skew[:, 0, 2] = skew[:, 2, 0] = mc[:, 1]
    skew[:, 1, 2] = skew[:, 2, 1] = mc[:, 0]
    inertia[:, :3, 3:] = skew
    inertia[:, 3:, :3] = skew
    inertia[:, 3:, 3:] = cinert[:, 9, None, None] * np.eye(3)
    for b in range(m.nbody - 1, 0, -1):
        inertia[m.body_parentid[b]] += inertia[b]
    cdof = np.abs(d.cdof)
    scale = np.zeros((m.nv, m.nv))
    for i in range(m.nv):
        crb_cdof = inertia[m.dof_bodyid[i]] @ cdof[i]
        j = i
        while j >= 0:
            scale[i, j] = scale[j, i] = cdof[j] @ crb_cdof
            j = m.dof_parentid[j]
    scale[np.diag_indices(m.nv)] += m.dof_armature
    return scale


def _mass_rounding(m: mujoco.MjModel, d: mujoco.MjData, eps: float) -> dict[str, np.ndarray]:
    mass = full_inertia(m, d)
    scale = _mass_scale(m, d)
    abs_inv = np.abs(np.linalg.inv(mass))

    def bound(x: np.ndarray, f: np.ndarray) -> np.ndarray:
        return FLOAT32_ROUNDING_FACTOR * eps * (abs_inv @ (scale @ np.abs(x) + f))

    return {"qM": FLOAT32_ROUNDING_FACTOR * eps * scale.ravel(),
            "qacc_smooth": bound(d.qacc_smooth, np.abs(d.qfrc_smooth)),
            "qacc": bound(d.qacc, np.abs(d.qfrc_smooth) + np.abs(d.qfrc_constraint))}


def state_before(inputs: BatchedInputs, traj_c: Trajectory, member: int, step: int):
    """(qpos, qvel, act, ctrl, time) of C's state before ``step`` of ``member``."""
    if step == 0:
        return inputs.qpos[member], inputs.qvel[member], inputs.act[member], inputs.ctrl[member, 0], 0.0
    k = step - 1
    return (traj_c.qpos[member, k], traj_c.qvel[member, k], traj_c.act[member, k], inputs.ctrl[member, step],
            float(traj_c.time[member, k]))


def local_error(inputs: BatchedInputs, traj_c: Trajectory, m: mujoco.MjModel, rf_mask: np.ndarray,
                every: int = 1, engine: Engine | None = None) -> dict[str, float]:
    """Worst re-synchronised error per field: MJX restarted from C every ``every`` steps.

    Returns:
      field -> max over members, steps and components (same units as the
      free-running errors: m | rad, m/s | rad/s, relative sensor error).
    """
    from mjxdiff.compare.verdict import error_series

    resynced = (engine or MJXEngine()).resync(inputs, traj_c, every)
    series = error_series(resynced, traj_c, metrics.qpos_layout(m), jnp.asarray(rf_mask))
    return {f: float(np.max(np.asarray(series[f]), initial=0.0)) for f in ("qpos", "qvel", "act", "sensordata")}


# ----------------------------------------------------------------------------
# cause attribution


_CONTACT_SENSORS = sensor_types("mjSENS_TOUCH", "mjSENS_CONTACT")


def _no_contacts(m: mujoco.MjModel) -> None:
    """Contacts off. MJX 3.17 cannot trace two things without any contact, so they go too:
    sensors where the model reads contacts (a touch sensor: 'Need at least one array to
    concatenate'), and the elliptic cone, which becomes pyramidal (the cone only shapes
    contacts, so C computes the same without them; MJX's solver otherwise indexes with an
    empty float array: 'Indexer must have integer or boolean type')."""
    m.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
    if np.isin(m.sensor_type, _CONTACT_SENSORS).any():
        m.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_SENSOR)
    m.opt.cone = int(mujoco.mjtCone.mjCONE_PYRAMIDAL)


def _quarter_timestep(m: mujoco.MjModel) -> None:
    m.opt.timestep /= 4


def _no_actuator_clamps(m: mujoco.MjModel) -> None:
    """Actuator forces unclamped: at the actuator (``forcerange``) and at the joint or tendon
    (``actuatorfrcrange``). Under the implicit integrators MuJoCo C leaves a clamped actuator's
    velocity derivative out of the implicit update; MJX 3.17 keeps it."""
    m.actuator_forcelimited[:] = 0
    m.jnt_actfrclimited[:] = 0
    if hasattr(m, "tendon_actfrclimited"):
        m.tendon_actfrclimited[:] = 0


def _has_actuator_clamps(m: mujoco.MjModel) -> bool:
    return bool(m.actuator_forcelimited.any() or m.jnt_actfrclimited.any()
                or getattr(m, "tendon_actfrclimited", np.zeros(0)).any())


def _no_equality(m: mujoco.MjModel) -> None:
    """Equality constraints off (connect, weld, joint, tendon, flex): where MJX and C then agree,
    what parts them is in those rows (MJX 3.17's connect and weld reference acceleration,
    known: equality-aref)."""
    m.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_EQUALITY)


def _other_integrator(m: mujoco.MjModel) -> None:
    euler = int(mujoco.mjtIntegrator.mjINT_EULER)
    m.opt.integrator = int(mujoco.mjtIntegrator.mjINT_RK4) if m.opt.integrator == euler else euler


def _with_converged_solver(edit: Callable[[mujoco.MjModel], None], m: mujoco.MjModel) -> None:
    edit(m)
    converge_solver(m)


#: Cause of a failure that no ablation removes: MJX computes something else than C.
GENUINE = "genuine discrepancy"
#: Cause when no ablation could run: the diagnosis is incomplete, not a verdict on MJX.
UNCLASSIFIED = "unclassified (no ablation could run)"

#: Cause of a failure that removing the actuator force clamps removes.
CLAMPED = "actuator force clamping"
#: Cause of a failure that disabling the equality constraints removes.
EQUALITY = "equality constraints"

#: Ablations tried only on models that have what they remove (else they would pass or fail as
#: the model does, and name a cause that is not there).
_APPLIES: dict[Callable[[mujoco.MjModel], None], Callable[[mujoco.MjModel], bool]] = {
    _no_actuator_clamps: _has_actuator_clamps, _no_equality: lambda m: m.neq > 0}

#: (cause class, ablation label, model edit) in the order they are tried; after the first (the
#: converged solver) each also converges the solver, so that on a model whose own settings do
#: not converge, truncation amplified by chaos cannot hide what the ablation removes.
ABLATIONS: tuple[tuple[str, str, Callable[[mujoco.MjModel], None]], ...] = (
    ("solver convergence", "converged solver (200 iterations, tolerance 1e-14)", converge_solver),
    ("contact generation", NO_CONTACTS, _no_contacts),
    (CLAMPED, "actuator force clamps removed (forcerange, actuatorfrcrange)", _no_actuator_clamps),
    (EQUALITY, "equality constraints disabled", _no_equality),
    ("integration", "timestep / 4", _quarter_timestep),
    ("integration", "other integrator (Euler <-> RK4)", _other_integrator),
)


#: The drill-down's first differing stages an ablation's cause can explain: a smaller timestep or
#: another integrator changes the whole trajectory (and a one-step error scales with the timestep),
#: so it can pass by never reaching, or shrinking, a difference that lies in a forward stage;
#: disabling contacts removes what a contact sensor or force reads, so it can pass where the
#: engines compute a touch, a limit or a passive force differently from the same contacts.
CAUSE_STAGES: dict[str, tuple[str | None, ...]] = {
    "integration": (None, "integration"),
    # a contact's parameters are compared at collision too (stages.PARAMETERS): a difference first
    # seen later is the solver's or the impedance's, which turning contacts off also removes
    "contact generation": (None, "collision"),
}


def reconcile_cause(cause: dict[str, Any], drill: DrillDown | None) -> dict[str, Any]:
    """``cause`` (:func:`attribute_cause`), unless its ablation passed while the drill-down found
    a first differing stage that cause cannot explain (:data:`CAUSE_STAGES`): a ball joint's
    limit margin MJX ignored passed with a quarter timestep (the finer rollout never entered the
    limit band), a touch sensor's ray flipped passed with contacts disabled (both read 0). Then
    the cause is :data:`GENUINE`, with ``evidence`` saying why and the ablation kept as
    ``steered_clear``."""
    stages = CAUSE_STAGES.get(cause.get("cause") or "")
    if stages is None or drill is None or drill.first_stage in stages:
        return cause
    return dict(cause, cause=GENUINE, ablation=None, steered_clear=cause.get("ablation"),
                evidence=f"'{cause.get('ablation')}' passes, yet from C's state at step {drill.step} the engines "
                         f"already differ in {drill.first_stage} ({drill.first_field} of {drill.object}), which "
                         f"{cause.get('cause')} does not explain: the ablation removed the state or the input "
                         "where they part, not the difference")


class Ablatable(Protocol):
    """What :func:`attribute_cause` ablates: inputs whose models can be edited
    (:class:`~mjxdiff.input.inputs.BatchedInputs`, or :mod:`mjxdiff.tools.closedloop`'s one control step)."""

    def edit_models(self, edit: Callable[[mujoco.MjModel], None]) -> Self: ...


_Inputs = TypeVar("_Inputs", bound=Ablatable)


def attribute_cause(passes: Callable[[_Inputs, Precision], bool], inputs: _Inputs,
                    precision: Precision, skip: tuple[str, ...] = ()) -> dict[str, Any]:
    """Tries ablations in order; the first under which the scenario passes names the cause.

    An ablation that cannot run (MJX or C raises on the ablated model, e.g. a
    sensor MJX cannot evaluate without contacts) is recorded with its error and
    skipped: a diagnosis never raises.

    Args:
      passes: reruns the scenario on the given inputs at the given precision
        and says whether it passes.
      inputs: the failing scenario's inputs.
      precision: the precision it failed at.
      skip: causes whose ablations are not tried (the one-step check's solver is converged already).

    Returns:
      ``{"cause": class, "ablation": label, "tried": [{"ablation", "passed", "error"}, ...]}``;
      ``passed`` is None where the ablation could not run. The cause is
      :data:`GENUINE` when no ablation that ran passes, and :data:`UNCLASSIFIED`
      when none could run at all.
    """
    tried: list[dict[str, Any]] = []

    def attempt(label: str, cause: str, ablated: Callable[[], _Inputs], at: Precision) -> dict[str, Any] | None:
        try:
            ok = bool(passes(ablated(), at))
        except Exception as e:  # noqa: BLE001 - recorded; the verdict stands
            tried.append(dict(ablation=label, passed=None, error=one_line(e)))
            return None
        tried.append(dict(ablation=label, passed=ok, error=""))
        return dict(cause=cause, ablation=label, tried=tried) if ok else None

    if precision == "float32" and (found := attempt("float64", "precision", lambda: inputs, "float64")):
        return found
    # BatchedInputs' first model, or closedloop's one step's (pyright does not narrow a protocol by hasattr)
    m = inputs.models[0] if hasattr(inputs, "models") else getattr(inputs, "m", None)  # pyright: ignore[reportAttributeAccessIssue]
    for i, (cause, label, edit) in enumerate(ABLATIONS):
        if cause in skip or (m is not None and edit in _APPLIES and not _APPLIES[edit](m)):
            continue
        if i:
            edit = functools.partial(_with_converged_solver, edit)
        if found := attempt(label, cause, lambda: inputs.edit_models(edit), precision):
            return found
    ran = any(t["passed"] is not None for t in tried)
    return dict(cause=GENUINE if ran else UNCLASSIFIED, ablation=None, tried=tried)
