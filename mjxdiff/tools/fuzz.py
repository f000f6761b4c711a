"""Differential fuzzing: Hypothesis generates models, states and controls; a
divergence is shrunk to a minimal MJCF and saved as a reproducer.

The property: for a generated MJX-supported model (a structure) and a batch of
variants of it, MJX and C rollouts agree under the same verdict as the sweep
(tolerance floors and the chaos envelope). Hypothesis explores structure; within
one structure, :func:`variants` draws many parameter sets, initial states and
control sequences at once, so that one compile (5-15 s) buys a batch of examples
rather than one. A failure is shrunk by Hypothesis (fewer bodies and geoms,
default options, smaller spreads of states and parameters), and Hypothesis's
example database keeps it so the next run tries it first.

Only the property's own divergence signal counts as a find: any other exception
raised while generating, simulating or judging an example stops the run and is
reported (:attr:`FuzzResult.harness_error`), never read as "no divergence".

Features whose C/MJX divergence is already known and documented (see
:data:`KNOWN_DIVERGENCES` and the scenario notes) are left out unless
``include_known`` is set, so that an unmodified MJX gives no alarm; those a generated model
cannot avoid by its features (contact differences of geom pairs it may well have) are set
aside by their measured signature only (:func:`known_contact_divergence`).
"""

from __future__ import annotations

import dataclasses
import functools
import sys
import time
import traceback
from pathlib import Path
from typing import Any

import numpy as np
from hypothesis import HealthCheck, Phase, assume, given, note, seed as hseed, settings, target
from hypothesis import strategies as st
from hypothesis.database import DirectoryBasedExampleDatabase
from hypothesis.errors import Flaky, HypothesisException

from mjxdiff.compat import data_impl, enable_x64, with_impl
from mjxdiff.errors import one_line
from mjxdiff.tools import interactions, strategies
from mjxdiff.output import report, reproducer
from mjxdiff.compare import segments
from mjxdiff.compare.support import KNOWN_DIVERGENCES
from mjxdiff.input.inputs import BatchedInputs
from mjxdiff.input.scenario import Tolerances
from mjxdiff.input.config import SweepConfig
from mjxdiff.runner.sweep import release_compiled_if_crowded
from mjxdiff.compare.verdict import TRUNCATION, ScenarioResult

__all__ = ["DEFAULT_BUDGET", "DEFAULT_VARIANTS", "KNOWN_DIVERGENCES", "FuzzResult", "fuzz", "model_strategy",
           "variants"]

#: How the fuzzer judges a structure's variants: their rollouts, with the drill-down. The one-step
#: check is not yet validated on generated models (their known divergences, a compile per
#: structure inside the budget), so the fuzzer judges rollouts, as before that check existed.
JUDGE = SweepConfig(diagnose="basic", onestep=False)

#: Seconds of generation before the fuzzer stops looking (shrinking a found failure may take longer).
DEFAULT_BUDGET = 60.0
#: Variants (parameters, state, controls) judged per generated structure: one compile serves them all.
DEFAULT_VARIANTS = 64

#: Sensor types MJX computes in ``sensor_acc``.
_ACC_SENSORS = frozenset({"mjSENS_ACCELEROMETER", "mjSENS_FORCE", "mjSENS_TORQUE", "mjSENS_FRAMELINACC",
                          "mjSENS_FRAMEANGACC", "mjSENS_TOUCH", "mjSENS_CONTACT"})


def known_divergence(m) -> str | None:
    """The :data:`KNOWN_DIVERGENCES` entry a generated model falls under that only its compiled
    form shows, or None: acceleration-stage sensors in a model MJX gives no constraint rows, a
    tendon with armature across kinematic trees."""
    import mujoco
    from mujoco import mjx

    types = {mujoco.mjtSensor(t).name for t in m.sensor_type}
    # MJX's constraint rows, in its JAX implementation's Data (MJX types _impl as a union of implementations)
    if types & _ACC_SENSORS and data_impl(mjx.make_data(m)).efc_J.size == 0:
        return "acceleration sensors without constraints"
    if any(len(_tendon_trees(m, k)) > 1 for k in np.flatnonzero(m.tendon_armature > 0)):
        return "tendon armature across trees"
    return None


def _tendon_trees(m, k: int | np.integer) -> set[int]:
    """Kinematic trees tendon ``k`` spans: its joints' (fixed) or its sites' and geoms' bodies'."""
    import mujoco

    trees = set()
    for w in range(m.tendon_adr[k], m.tendon_adr[k] + m.tendon_num[k]):
        kind, obj = int(m.wrap_type[w]), int(m.wrap_objid[w])
        if kind == int(mujoco.mjtWrap.mjWRAP_JOINT):
            trees.add(int(m.dof_treeid[m.jnt_dofadr[obj]]))
        elif kind == int(mujoco.mjtWrap.mjWRAP_SITE):
            trees.add(int(m.body_treeid[m.site_bodyid[obj]]))
        elif kind in (int(mujoco.mjtWrap.mjWRAP_SPHERE), int(mujoco.mjtWrap.mjWRAP_CYLINDER)):
            trees.add(int(m.body_treeid[m.geom_bodyid[obj]]))
    return trees - {-1}


@dataclasses.dataclass(frozen=True)
class FuzzResult:
    """What a fuzzing run found.

    Attributes:
      examples: examples judged: variants (parameters, initial state, controls) of
        the structures tried, ``structures x variants``.
      seconds: wall time.
      failure: None, or the shrunk failing example: ``xml``, ``nbody``,
        ``ngeom``, ``features``, ``message`` and ``reproducer`` (path or None).
      harness_error: None, or ``"ExcType: message"`` (one line) of an exception
        raised by the fuzzing harness itself (generation, the engines, the
        verdict, Hypothesis), which stopped the run: then nothing can be
        concluded about divergence from the examples tried.
      harness_traceback: the full traceback text of ``harness_error``.
      harness_example: MJCF of the generated model being tried when the harness
        failed (None if it failed before a model was drawn).
      structures: generated models (structures) tried, each compiled once.
      interactions: pairwise coverage of what was generated
        (:func:`mjxdiff.tools.interactions.pairwise` without its per-pair sources), with
        ``pairs_per_minute`` and ``first_seconds`` (pair name -> when it was first covered).
      set_aside: structures judged (among ``structures``) whose verdict was neither a pass nor a
        find, by why (:func:`_why_set_aside`): ``C unstable``, ``MJX unsupported``, a truncated
        solver, or the :data:`KNOWN_DIVERGENCES` entry its signature shows
        (:func:`known_contact_divergence`). ``structures`` minus these passed.
    """

    examples: int
    seconds: float
    failure: dict[str, Any] | None
    harness_error: str | None = None
    harness_traceback: str | None = None
    harness_example: str | None = None
    structures: int = 0
    interactions: dict[str, Any] | None = None
    set_aside: dict[str, int] = dataclasses.field(default_factory=dict)

    def rates(self) -> dict[str, float]:
        """Examples and structures per minute of wall time."""
        minutes = max(self.seconds, 1e-9) / 60
        return dict(examples_per_minute=self.examples / minutes, structures_per_minute=self.structures / minutes)


class _Divergence(AssertionError):
    """The property's own signal: MJX and C disagree on this example (the only exception that is a find)."""


class _HarnessFailure(BaseException):
    """Carries an exception raised by the harness out of Hypothesis at once.

    Not an :class:`Exception`, so Hypothesis neither shrinks it nor mistakes it
    for a failing example (as it does with :class:`KeyboardInterrupt`).
    """

    def __init__(self, error: BaseException):
        super().__init__(error)
        self.error = error


def _is_find(e: BaseException) -> bool:
    """Whether ``e``, raised by the Hypothesis run, is only the property's divergence signal."""
    if isinstance(e, _Divergence):
        return True
    return isinstance(e, BaseExceptionGroup) and not isinstance(e, Flaky) and all(map(_is_find, e.exceptions))


def model_strategy(include_known: bool = False, max_bodies: int = 3) -> st.SearchStrategy:
    """MJX-supported models; without ``include_known``, none of :data:`KNOWN_DIVERGENCES`."""
    if include_known:
        return strategies.mjcf_models(max_bodies=max_bodies)
    options = st.fixed_dictionaries({
        "integrator": st.just("Euler"),
        "timestep": st.sampled_from([0.002, 0.005]),
        "cone": st.sampled_from(["pyramidal", "elliptic"]),
    })
    return strategies.mjcf_models(max_bodies=max_bodies, geom_types=("sphere", "capsule", "ellipsoid", "cylinder"),
                                  equality=False, options=options).filter(
        lambda mj: "tendon wrap sidesite" not in mj.features)


#: Members of each generated batch whose interaction pairs are read (stepping MuJoCo C): the
#: randomization that matters (controls outside their range, turned frames, deadbands) reaches
#: members 1 and 3 of every 4.
_PAIR_MEMBERS = 4


def _interaction_summary(first: dict[tuple, float], seconds: float) -> dict[str, Any]:
    """Pairwise coverage of the generated models, pairs per minute, when each was first reached."""
    doc = interactions.pairwise({p: ("fuzz",) for p in first})
    doc.pop("by")
    doc["pairs_per_minute"] = round(len(first) / max(seconds / 60, 1e-9), 1)
    doc["first_seconds"] = {interactions.pair_name(p): round(t, 1)
                            for p, t in sorted(first.items(), key=lambda x: x[1])}
    return doc


#: Spreads :func:`variants` draws from, simplest first (Hypothesis shrinks toward the first).
QPOS_SPREADS = (0.0, 0.05, 0.2, 0.5)
QVEL_SPREADS = (0.0, 0.1, 0.5, 1.0)
PARAMETER_SPREADS = (0.0, 0.1, 0.3)


def variants(m, seed: int, batch: int, steps: int, qpos_noise: float = 0.05, qvel_noise: float = 0.1,
             control: str = "smooth", spread: float = 0.1) -> BatchedInputs:
    """``batch`` variants of one model structure, drawn with NumPy from ``seed`` as a scenario's
    members are (:func:`mjxdiff.input.inputs.make_inputs`): initial states with Gaussian noise
    (``qpos_noise`` rad or m, ``qvel_noise`` rad/s or m/s), controls of the ``control`` family,
    and masses, frictions, damping and actuator gains each scaled by U[1 - spread, 1 + spread]
    (gravity by a fifth of that). Every variant has the model's structure, so one compiled
    rollout judges them all."""
    from mjxdiff.input.inputs import make_inputs
    from mjxdiff.input.scenario import Randomization, Scenario

    scale = {name: (1 - spread, 1 + spread) for name in ("body_mass", "geom_friction", "dof_damping",
                                                         "actuator_gain")}
    scale["gravity"] = (1 - spread / 5, 1 + spread / 5)
    randomize = Randomization(qpos_noise=qpos_noise, qvel_noise=qvel_noise, control=control, scale=scale)
    inputs = make_inputs(Scenario(name="fuzz", model="<generated>", randomize=randomize), m, seed, batch, steps)
    qpos = np.stack([_shallow(mi, q) for mi, q in zip(inputs.models, inputs.qpos)])
    return dataclasses.replace(inputs, qpos=qpos)


#: Deepest initial penetration (m) :func:`variants` starts a member with.
MAX_INITIAL_PENETRATION = 0.01


def _shallow(m, qpos: np.ndarray) -> np.ndarray:
    """``qpos`` or, where it starts a geom deeper than :data:`MAX_INITIAL_PENETRATION` inside
    another, its displacement from ``qpos0`` halved until it does not (at worst ``qpos0``).

    A member sunk into the floor (a slide joint displaced half a metre) is no physical
    state, and C and MJX legitimately part there (MJX's plane-cylinder test returns three
    contacts by design, C adds a fourth on the far cap when a cylinder is fully submerged).
    """
    import mujoco

    d = mujoco.MjData(m)
    v = np.zeros(m.nv)
    mujoco.mj_differentiatePos(m, v, 1.0, m.qpos0, qpos)
    for halving in range(8):
        q = m.qpos0.copy()
        mujoco.mj_integratePos(m, q, v * 0.5**halving, 1.0)
        d.qpos[:] = q
        mujoco.mj_forward(m, d)
        if d.ncon == 0 or d.contact.dist[:d.ncon].min() >= -MAX_INITIAL_PENETRATION:
            return q if halving else qpos
    return m.qpos0.copy()


def known_contact_divergence(m, inputs: BatchedInputs, result: ScenarioResult) -> str | None:
    """The :data:`KNOWN_DIVERGENCES` entry a divergence shows by its measured signature, or None.

    From C's states at the 3 steps up to the first divergent step of the first divergent member,
    with MJX's ``forward`` from each (never MJX's ``solver_niter``, which MJX 3.17's ``forward``
    does not write):

    - ``plane-cylinder far cap``: a plane-cylinder pair with more contacts in C than in MJX;
    - ``contact tangent frames``: at one of the 3 steps, an MJX contact at a C contact's place
      (same geoms, position and normal within 1e-6) whose first tangent differs by more than
      1e-6, where the friction depends on the tangent's direction (a pyramidal cone, or unequal
      friction coefficients across the tangents);
    - ``convex pairs by SDF descent``: at one of the 3 steps, a contact of a pair MJX collides by
      SDF descent (:func:`_sdf_pair`) that differs from C's;
    - ``capsule segment solves``: at one of the 3 steps, a sphere-capsule or capsule-capsule
      contact more than :data:`mjxdiff.compare.segments.TOLERANCE` from C's, where MJX's is its formulas
      with their 1e-6 regularization and C's the same exactly (:func:`mjxdiff.compare.segments.explains`);

    the last three only where, at every one of the 3 steps, MJX's forward given C's contacts for
    those (:func:`_with_c_contacts`) reproduces C's ``qacc`` and ``sensordata``
    (:func:`_c_contacts_explain`): then nothing else differs, a bias force or a constraint row.

    MJX runs in float64, as the fuzzer's verdict does, whatever the caller's JAX setting."""

    first = result.first_divergence or {}
    member: int = first.get("member", -1)
    step: int = first.get("step", -1)
    if member < 0 or step < 0:
        return None
    with enable_x64(True):  # the thresholds (1e-6, the drill-down's 1e-9) are float64's
        return _signature(inputs, member, step)


def _signature(inputs: BatchedInputs, member: int, step: int) -> str | None:
    """:func:`known_contact_divergence` of ``member`` whose first divergent step is ``step``."""
    import mujoco
    from mujoco import mjx

    from mjxdiff.compare.diagnose import _contacts_c, _contacts_mjx

    mi = inputs.models[member]
    d = mujoco.MjData(mi)
    d.qpos[:], d.qvel[:], d.act[:] = inputs.qpos[member], inputs.qvel[member], inputs.act[member]
    mx = mjx.put_model(mi)
    states, shown = [], []
    for t in range(step + 1):
        d.ctrl[:] = inputs.ctrl[member, t]
        if t >= step - 2:
            mujoco.mj_forward(mi, d)
            states.append(_state(d))
            dx = _mjx_forward(mx, mi, states[-1])
            cc, cx = _contacts_c(mi, d), _contacts_mjx(mi, dx)
            if _cylinder_contact_missing(mi, cc, cx):
                return "plane-cylinder far cap"
            if _tangent_turned(mi, d, dx):
                shown.append("contact tangent frames")
            if _sdf_contact_differs(mi, cc, cx):
                shown.append("convex pairs by SDF descent")
            if _regularized_slots(mi, d, dx):
                shown.append("capsule segment solves")
        mujoco.mj_step(mi, d)
    if shown and _c_contacts_explain(mi, states):
        return shown[0]  # the first shown, where a model shows both
    return None


#: The parts of a C state (MjData fields) that ``forward`` starts from; the solver's warm start
#: too, so that both solvers start from the same point.
_STATE_FIELDS = ("qpos", "qvel", "act", "ctrl", "mocap_pos", "mocap_quat", "qacc_warmstart")


def _state(d) -> dict[str, np.ndarray]:
    """A copy of C's state in ``d`` (:data:`_STATE_FIELDS`)."""
    return {k: getattr(d, k).copy() for k in _STATE_FIELDS}


def _mjx_forward(mx, m, state: dict[str, np.ndarray]):
    """MJX's ``forward`` of ``mx`` (put from ``m``) from C's ``state`` (:func:`_state`)."""
    from mujoco import mjx

    from mjxdiff.engine import engines

    return engines.forward(mx, mjx.make_data(m).replace(**{k: v.copy() for k, v in state.items()}))


def _cylinder_contact_missing(m, cc: dict, cx: dict) -> bool:
    """Whether a plane-cylinder pair has more contacts in C (``cc``) than in MJX (``cx``), both
    by geom pair as :mod:`mjxdiff.compare.diagnose` collects them."""
    import mujoco

    cylinder = {int(mujoco.mjtGeom.mjGEOM_PLANE), int(mujoco.mjtGeom.mjGEOM_CYLINDER)}
    return any({int(g) for g in m.geom_type[list(pair)]} == cylinder and len(cc[pair]) > len(cx.get(pair, []))
               for pair in cc)


def _tangent_turned(m, d, dx) -> bool:
    """Whether an MJX contact at a C contact's place (same geoms, position and normal within 1e-6)
    has a first tangent more than 1e-6 from C's, where friction depends on the tangent's direction."""
    import mujoco

    pyramidal = m.opt.cone == mujoco.mjtCone.mjCONE_PYRAMIDAL
    c = data_impl(dx).contact  # MJX's contacts
    geom, pos, frame = np.asarray(c.geom), np.asarray(c.pos), np.asarray(c.frame).reshape(-1, 9)
    for con in d.contact[:d.ncon]:
        direction = (pyramidal or con.friction[0] != con.friction[1]
                     or (con.dim == 6 and con.friction[3] != con.friction[4]))
        if con.dim < 3 or not direction:
            continue
        same = ((geom == (con.geom1, con.geom2)).all(axis=1) & (np.abs(pos - con.pos).max(axis=1) < 1e-6)
                & (np.abs(frame[:, :3] - con.frame[:3]).max(axis=1) < 1e-6))
        if same.any() and (np.abs(frame[same][:, 3:6] - con.frame[3:6]).max(axis=1) > 1e-6).all():
            return True
    return False


def _sdf_pair(m, pair: tuple[int, ...]) -> bool:
    """Whether MJX collides geoms ``pair`` by gradient descent on signed distance functions, as its
    own table of colliders says (3.17: a sphere, capsule, ellipsoid or cylinder against an
    ellipsoid or cylinder, ``collision_sdf.py``)."""
    from mujoco.mjx._src import collision_driver, collision_sdf

    types = tuple(sorted(int(t) for t in m.geom_type[list(pair)]))
    # MJX's table of colliders, keyed by its GeomType IntEnum (plain ints are equal to its members)
    collide = collision_driver._COLLISION_FUNC.get(types)  # noqa: SLF001  # pyright: ignore[reportArgumentType]
    return collide is not None and collide.__module__ == collision_sdf.__name__


def _sdf_contact_differs(m, cc: dict, cx: dict) -> bool:
    """Whether a pair MJX collides by SDF descent (:func:`_sdf_pair`) has other contacts in C
    (``cc``) than in MJX (``cx``), both by geom pair as :mod:`mjxdiff.compare.diagnose` collects them:
    another count, or a distance, position, friction or frame more than 1e-6 apart."""
    from mjxdiff.compare.diagnose import _contact_diff

    sdf = {p for p in cc.keys() | cx.keys() if _sdf_pair(m, p)}
    return _contact_diff(m, {p: cc[p] for p in sdf & cc.keys()}, {p: cx[p] for p in sdf & cx.keys()})[0] > 1e-6


def _regularized_slots(m, d, dx) -> dict[int, Any]:
    """MJX's contact slots (index -> C's ``MjContact``) of sphere-capsule and capsule-capsule
    contacts that differ from C's by MJX's regularized segment solves alone
    (:func:`mjxdiff.compare.segments.explains`), more than :data:`mjxdiff.compare.segments.TOLERANCE`."""
    c = data_impl(dx).contact  # MJX's contacts
    geom, dist, pos, frame = (np.asarray(x) for x in (c.geom, c.dist, c.pos, c.frame))
    slots = {}
    for con in d.contact[:d.ncon]:
        if not segments.regularized((m.geom_type[con.geom1], m.geom_type[con.geom2])):
            continue
        for s in np.flatnonzero((geom == (con.geom1, con.geom2)).all(axis=1)):
            mjx_contact = (float(dist[s]), pos[s], frame[s].reshape(3, 3)[0])
            apart = max(abs(mjx_contact[0] - con.dist), np.abs(pos[s] - con.pos).max(),
                        np.abs(mjx_contact[2] - con.frame[:3]).max())
            if apart > segments.TOLERANCE and segments.explains(m, d, con, mjx_contact):
                slots[int(s)] = con
    return slots


def _c_contacts_explain(m, states: list[dict[str, np.ndarray]]) -> bool:
    """Whether, from each of C's ``states`` (:func:`_state`), MJX's ``forward`` given C's
    contacts where they differ by a known kind (:func:`_with_c_contacts`) reproduces C's
    ``qacc`` and ``sensordata`` within the drill-down's float64 tolerance. Both engines run a
    copy of ``m`` with a converged solver (:func:`mjxdiff.compare.noise.converge_solver`), from C's warm
    start: two solvers stopped by the model's own tolerance part by far more than 1e-9 (a
    generated model's 1e-10: qacc 1.1e-5 apart, 1.1e-13 converged). Any other error (a bias
    force, a constraint row) remains and fails the match."""
    import copy

    import mujoco
    from mujoco import mjx

    from mjxdiff.compare.noise import converge_solver

    m = copy.deepcopy(m)
    converge_solver(m)
    mx = mjx.put_model(m)
    for state in states:
        d = mujoco.MjData(m)
        for k, v in state.items():
            getattr(d, k)[:] = v
        mujoco.mj_forward(m, d)
        dx = _mjx_forward(mx, m, state)
        contact = _with_c_contacts(m, d, dx)
        if contact is None or data_impl(dx).efc_J.size == 0:
            return False
        given = _forward_given_contacts()(mx, dx, contact)
        if not (_agree(given.qacc, d.qacc) and _agree(given.sensordata, d.sensordata)):
            return False
    return True


def _agree(mjx_value, c_value: np.ndarray) -> bool:
    """Whether an MJX array matches C's as the drill-down's float64 stages do:
    |mjx - c| <= rtol (1 + max|c|)."""
    from mjxdiff.compare.diagnose import STAGE_RTOL

    err = np.abs(np.asarray(mjx_value) - c_value).max(initial=0.0)
    return bool(err <= STAGE_RTOL["float64"] * (1 + np.abs(c_value).max(initial=0.0)))


def _with_c_contacts(m, d, dx):
    """MJX's contacts (``dx``) with C's (``d``) where they differ by a known kind: in the slots of
    every pair MJX collides by SDF descent, C's distance, position and frame in the pair's first
    slots, its other slots beyond the margin (no constraint rows); of other pairs, C's frame
    (its tangents) in a slot at C's place (same geoms, position and normal within 1e-6); of a
    sphere-capsule or capsule-capsule contact apart by MJX's regularized segment solves alone
    (:func:`_regularized_slots`), C's distance, position and frame. None
    where C has a contact of an SDF pair MJX has no slot for (more contacts than slots, or its
    geoms in the other order)."""
    c = data_impl(dx).contact  # MJX's contacts
    geom, margin = np.asarray(c.geom), np.asarray(c.includemargin)
    dist, pos, frame = (np.array(x) for x in (c.dist, c.pos, c.frame))
    rows = frame.reshape(-1, 9)
    for s, con in _regularized_slots(m, d, dx).items():
        dist[s], pos[s], rows[s] = con.dist, con.pos, con.frame
    ours: dict[tuple[int, int], list] = {}
    for con in d.contact[:d.ncon]:
        if _sdf_pair(m, (con.geom1, con.geom2)):
            ours.setdefault((int(con.geom1), int(con.geom2)), []).append(con)
            continue
        same = ((geom == (con.geom1, con.geom2)).all(axis=1) & (np.abs(pos - con.pos).max(axis=1) < 1e-6)
                & (np.abs(rows[:, :3] - con.frame[:3]).max(axis=1) < 1e-6))
        rows[same] = con.frame
    for pair in {(int(a), int(b)) for a, b in geom if _sdf_pair(m, (a, b))} | ours.keys():
        slots = np.flatnonzero((geom == pair).all(axis=1))
        cons = ours.get(pair, [])
        if len(cons) > len(slots):
            return None
        for s, con in zip(slots, cons):
            dist[s], pos[s], rows[s] = con.dist, con.pos, con.frame
        rest = slots[len(cons):]
        dist[rest] = margin[rest] + 1.0
    return c.replace(dist=dist, pos=pos, frame=rows.reshape(frame.shape))


@functools.cache
def _forward_given_contacts():
    """MJX's ``forward`` from its collision on, compiled: ``(mx, dx, contact) -> dx`` with
    ``contact`` in place of ``dx``'s (constraint rows, solver, acceleration sensors; the other
    stages do not read contacts)."""
    from mujoco.mjx._src import constraint, sensor, solver

    from mjxdiff.engine import engines

    def after_collision(mx, dx, contact):
        dx = with_impl(dx, contact=contact)
        return sensor.sensor_acc(mx, solver.solve(mx, constraint.make_constraint(mx, dx)))

    return engines.jit_for_few_calls(after_collision)


def _divergence(m, inputs: BatchedInputs, config) -> ScenarioResult:
    from mjxdiff.runner.sweep import run_inputs

    return run_inputs("fuzz", m, inputs, Tolerances(), config)


def is_divergence(result: ScenarioResult) -> bool:
    """Whether a generated example's verdict is a find: anything but a pass, except MuJoCo C
    itself blowing up (``error``/``unstable``: an unstable model, whatever MJX did), MJX
    refusing the model (``unsupported``) and a solver truncation (the generated solver settings
    part the engines, and the converged twin agrees: :data:`mjxdiff.compare.verdict.TRUNCATION`)."""
    unstable = result.status == "error" and result.error_kind == "unstable"
    truncation = (result.diagnosis.get("cause") or {}).get("cause") == TRUNCATION  # the settings, not MJX
    return result.status != "pass" and not unstable and result.status != "unsupported" and not truncation


def _why_set_aside(result: ScenarioResult) -> str:
    """Why a verdict that :func:`is_divergence` does not count and that is no pass is set aside."""
    if result.status == "unsupported":
        return "MJX unsupported"
    if result.status == "error" and result.error_kind == "unstable":
        return "C unstable"
    return TRUNCATION


def _database_dir(database: str | Path | None, out: str | Path | None) -> Path:
    """Hypothesis's example database directory: ``database``, else ``out/.hypothesis``, else
    ``~/.cache/mjxdiff/hypothesis``."""
    return Path(database) if database else (Path(out) / ".hypothesis" if out else
                                            Path.home() / ".cache" / "mjxdiff" / "hypothesis")


def _spread(data) -> dict[str, Any]:
    """The spreads of a structure's variants, drawn from ``data``: of initial positions and
    velocities, the control family, and of parameters (:func:`variants`' keywords)."""
    return dict(qpos_noise=data.draw(st.sampled_from(QPOS_SPREADS), label="qpos spread"),
                qvel_noise=data.draw(st.sampled_from(QVEL_SPREADS), label="qvel spread"),
                control=data.draw(st.sampled_from(strategies.CONTROL_FAMILIES), label="controls"),
                spread=data.draw(st.sampled_from(PARAMETER_SPREADS), label="parameter spread"))


@dataclasses.dataclass
class _Search:
    """One fuzz run: its settings (see :func:`fuzz`; ``t0`` when it started) and what it has seen:
    ``seen`` (structures tried while searching, the last find, the XML being judged),
    ``first`` (interaction pair -> seconds into the run it was first generated) and
    ``set_aside`` (why -> structures judged, neither a pass nor a find, while searching)."""

    config: Any
    include_known: bool
    batch: int
    steps: int
    progress: bool
    budget: float
    shrink_budget: float
    t0: float
    seen: dict[str, Any] = dataclasses.field(default_factory=lambda: {"examples": 0, "last_failure": None,
                                                                       "xml": None})
    first: dict[tuple, float] = dataclasses.field(default_factory=dict)
    set_aside: dict[str, int] = dataclasses.field(default_factory=dict)

    def example(self, data) -> None:
        """One example of the property: a structure drawn from ``data`` and its variants, judged;
        raises :class:`_Divergence` on a find (kept in ``seen``)."""
        seen, first, set_aside, t0 = self.seen, self.first, self.set_aside, self.t0
        include_known, batch, steps = self.include_known, self.batch, self.steps
        mj = data.draw(model_strategy(include_known), label="model")
        seen["xml"] = mj.xml
        m = mj.model()
        if not include_known and known_divergence(m) is not None:
            assume(False)  # not generated by default: see KNOWN_DIVERGENCES
        spread = _spread(data)
        variant_seed = data.draw(st.integers(0, 2**32 - 1), label="variant seed")
        # Out of time: pass without simulating (drawing stays deterministic, which Hypothesis
        # checks). While shrinking a find, allow shrink_budget more; the smallest failure so
        # far is kept in `seen`.
        searching = seen["last_failure"] is None
        if time.perf_counter() - t0 > (self.budget if searching else self.budget + self.shrink_budget):
            return
        seen["examples"] += searching
        if self.progress:
            print(f"[fuzz] structure {seen['examples']}: {mj.nbody} bodies, {mj.ngeom} geoms, {batch} variants"
                  f" ({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)
        release_compiled_if_crowded()  # every generated structure compiles anew
        inputs = variants(m, variant_seed, batch, steps, **spread)
        if searching:
            # aim generation at interaction pairs not generated yet (issue 32): Hypothesis's
            # targeted phase mutates toward examples that score higher
            pairs = interactions.member_pairs(inputs, max_members=_PAIR_MEMBERS, max_steps=steps)
            new = pairs - first.keys()
            target(float(len(new)), label="new interaction pairs")
            now = time.perf_counter() - t0
            first.update(dict.fromkeys(new, now))
        result = _divergence(m, inputs, self.config)
        if not is_divergence(result):
            if searching and result.status != "pass":
                why = _why_set_aside(result)
                set_aside[why] = set_aside.get(why, 0) + 1
            assume(result.status == "pass")  # C blew up or MJX refused the model: not a divergence either
            return
        known = None if include_known else known_contact_divergence(m, inputs, result)
        if known:
            if searching:
                set_aside[known] = set_aside.get(known, 0) + 1
            assume(False)  # a known divergence: see KNOWN_DIVERGENCES
        seen["last_failure"] = dict(mj=mj, inputs=inputs, result=result)
        note(mj.xml)
        raise _Divergence(result.message)


def _search(property_, seen: dict[str, Any]) -> tuple[BaseException | None, str | None]:
    """Runs the Hypothesis property; returns (the harness's own failure, None where there was
    none, and the XML of the example it failed on). A find, or Hypothesis concluding nothing
    (e.g. ``Unsatisfiable``) where there was a find, is no harness failure."""
    harness: BaseException | None = None
    example_xml = None
    try:
        property_()
    except _HarnessFailure as e:
        harness, example_xml = e.error, seen["xml"]
    except Flaky as e:
        # with a find: its final replay came after the shrink budget and passed; without one,
        # an exception was raised once and not again, by the harness
        if seen["last_failure"] is None:
            harness = e
    except Exception as e:  # noqa: BLE001 - a find, or else the harness's own error, reported
        if not _is_find(e):  # e.g. Hypothesis's Unsatisfiable: no conclusion either
            harness = e
    return harness, example_xml


def _fuzz_result(search: _Search, seconds: float, harness: BaseException | None, example_xml: str | None,
                 out: str | Path | None) -> FuzzResult:
    """The :class:`FuzzResult` of a finished search that took ``seconds``: the harness's failure
    if any, the interactions generated, and the find with its reproducer saved under ``out``."""
    config, batch, seen = search.config, search.batch, search.seen
    errors: dict[str, Any] = {}
    if harness is not None:
        errors = dict(harness_error=one_line(harness),
                      harness_traceback="".join(traceback.format_exception(harness)), harness_example=example_xml)
    found = seen["last_failure"]
    structures = seen["examples"]
    errors["interactions"] = _interaction_summary(search.first, seconds)
    set_aside = search.set_aside
    if found is None:
        return FuzzResult(structures * batch, seconds, None, structures=structures, set_aside=set_aside, **errors)
    mj, result, inputs = found["mj"], found["result"], found["inputs"]
    path = None
    if out is not None:
        member = max(result.first_divergence["member"], 0) if result.first_divergence else 0
        path = reproducer.save(report.path_under(Path(out) / "reproducers", "fuzz.json"), "fuzz", member, inputs,
                               mj.xml, Tolerances(), config.as_dict(), report.result_dict(result))
    return FuzzResult(structures * batch, seconds, dict(
        xml=mj.xml, nbody=mj.nbody, ngeom=mj.ngeom, features=list(mj.features), message=result.message,
        status=result.status, reproducer=str(path) if path else None), structures=structures, set_aside=set_aside,
        **errors)


def fuzz(max_examples: int = 300, seed: int = 0, budget: float = DEFAULT_BUDGET, out: str | Path | None = None,
         database: str | Path | None = None, include_known: bool = False, batch: int = DEFAULT_VARIANTS,
         steps: int = 40, progress: bool = False, shrink_budget: float | None = None) -> FuzzResult:
    """Runs the differential property until a divergence, ``max_examples`` or ``budget`` seconds.

    Args:
      max_examples: most structures (generated models) to try.
      seed: Hypothesis seed (same seed and database, same sequence).
      budget: seconds of generation; once spent, further examples are skipped.
      out: directory for the reproducer of a found divergence.
      database: Hypothesis example database directory (default ``out/.hypothesis``
        or ``~/.cache/mjxdiff/hypothesis``).
      include_known: also generate features with known divergences.
      batch: variants (parameters, states, controls; :func:`variants`) judged per
        structure, by one compiled rollout.
      steps: horizon of every rollout (fixed, so that a structure compiles once).
      shrink_budget: seconds allowed for shrinking a find (default max(120, 2 x budget));
        each shrink candidate is a new model structure, hence a new compile.
    """
    db_dir = _database_dir(database, out)
    search = _Search(JUDGE, include_known, batch, steps, progress, budget,
                     max(120.0, 2 * budget) if shrink_budget is None else shrink_budget, time.perf_counter())
    seen, example = search.seen, search.example

    @hseed(seed)
    @settings(max_examples=max_examples, deadline=None, database=DirectoryBasedExampleDatabase(str(db_dir)),
              # Hypothesis's HealthCheck enum has a metaclass that hides its members' type from pyright
              suppress_health_check=list(HealthCheck),  # pyright: ignore[reportArgumentType]
              phases=[Phase.reuse, Phase.generate, Phase.shrink],
              derandomize=False, print_blob=False)
    @given(data=st.data())
    def property_(data):
        seen["xml"] = None
        try:
            example(data)
        except (_Divergence, HypothesisException):  # a find, or Hypothesis's control flow (assume)
            raise
        except Exception as e:  # the harness itself failed: stop, and say so
            raise _HarnessFailure(e) from e

    harness, example_xml = _search(property_, seen)
    return _fuzz_result(search, time.perf_counter() - search.t0, harness, example_xml, out)
