"""Trajectories -> metrics -> a verdict per scenario.

The per-step error series come from :mod:`mjxdiff.metrics` (pure jax.numpy,
vmapped over the batch here); this module reduces them to the numbers a person
reads: the worst error of each field against its tolerance, the first step
where it is exceeded, which member and which named MuJoCo object, and the
scenario's status.

Statuses:
  ``pass``         every member within every bound (or enough of them: ``threshold``).
  ``fail``         a divergence: some field leaves its bound in too many members,
                   or MJX goes non-finite where MuJoCo C stays finite (the step,
                   and which fields were still finite, named).
  ``unsupported``  MJX refused the model; ``message`` names the feature.
  ``error``        MuJoCo C itself blows up (``error_kind='unstable'``: the
                   scenario is unstable, not MJX), bad input (``'input'``) or an
                   engine crash (``'engine'``).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from mjxdiff.input import joints
from mjxdiff.compat import jit_for_few_calls
from mjxdiff import metrics
from mjxdiff.engine import pairs
from mjxdiff.compare.ambiguity import CcdAmbiguity
from mjxdiff.engine.trajectory import Trajectory, first_diverged
from mjxdiff.compare.noise import FLOORS, NoiseFloor, fit_growth, noise_floor
from mjxdiff.input.scenario import Tolerances
# the verdict's data lives apart, without JAX (a report or an input error needs no JAX); public here too
from mjxdiff.compare.result import (OUTLIER_RATIO, SERIES_POINTS, STATUSES, TRUNCATION, WEAK_BOUND,  # noqa: F401
                            FieldResult, ScenarioResult, downsample)

__all__ = ["FieldResult", "Judge", "ScenarioResult", "judge", "error_series", "downsample", "OUTLIER_RATIO",
           "SERIES_POINTS", "STATUSES"]


def _name(m: mujoco.MjModel, obj: mujoco.mjtObj, i: int) -> str:
    return mujoco.mj_id2name(m, obj, int(i)) or f"#{int(i)}"


def joint_element(m: mujoco.MjModel, j: int) -> dict[str, str]:
    """Joint ``j`` as data: ``kind`` joint, its ``name``, its ``type`` (``free``, ``ball``, ``slide``, ``hinge``)."""
    kind = mujoco.mjtJoint(m.jnt_type[j]).name.removeprefix("mjJNT_").lower()
    return dict(kind="joint", name=_name(m, mujoco.mjtObj.mjOBJ_JOINT, j), type=kind)


def sensor_element(m: mujoco.MjModel, s: int) -> dict[str, str]:
    """Sensor ``s`` as data: ``kind`` sensor, its ``name``, its ``type`` (``accelerometer``, ``touch``, ...)."""
    kind = mujoco.mjtSensor(m.sensor_type[s]).name.removeprefix("mjSENS_").lower()
    return dict(kind="sensor", name=_name(m, mujoco.mjtObj.mjOBJ_SENSOR, s), type=kind)


def component_elements(m: mujoco.MjModel, layout: metrics.QposLayout) -> dict[str, list[dict[str, str]]]:
    """For each compared field, the MuJoCo element each column belongs to, as data:
    ``kind`` (``joint``, ``sensor``, ``actuator``), ``name`` and ``type`` (a joint's ``free``,
    ``ball``, ``slide`` or ``hinge``, a sensor's ``accelerometer``, ``contact``, ...; an
    actuator's ``""``). What known entries match on (:attr:`mjxdiff.compare.support.Entry.element`)."""

    qpos = [joint_element(m, j) for j in metrics.qpos_error_joint_ids(layout)]
    qvel = [joint_element(m, j) for j in m.dof_jntid]
    sens = []
    for s in range(m.nsensor):
        sens += [sensor_element(m, s)] * int(m.sensor_dim[s])
    act = []
    for a in range(m.nu):
        act += [dict(kind="actuator", name=_name(m, mujoco.mjtObj.mjOBJ_ACTUATOR, a), type="")] * max(
            int(m.actuator_actnum[a]), 0)
    return {"qpos": qpos, "qvel": qvel, "sensordata": sens, "act": act}


def describe(element: dict[str, str]) -> str:
    """An element of :func:`component_elements` as reports name it: ``joint 'hip'``,
    ``sensor 'imu' (accelerometer)``."""
    sensor = f" ({element['type']})" if element["kind"] == "sensor" else ""
    return f"{element['kind']} '{element['name']}'{sensor}"


def component_objects(m: mujoco.MjModel, layout: metrics.QposLayout) -> dict[str, list[str]]:
    """For each compared field, the MuJoCo object each column belongs to (:func:`describe`)."""
    return {f: [describe(e) for e in elements] for f, elements in component_elements(m, layout).items()}


def rangefinder_mask(m: mujoco.MjModel) -> np.ndarray:
    """(nsensordata,) True for rangefinder outputs, whose -1 means 'no hit'."""
    mask = np.zeros(m.nsensordata, bool)
    for s in np.flatnonzero(m.sensor_type == mujoco.mjtSensor.mjSENS_RANGEFINDER):
        mask[m.sensor_adr[s]:m.sensor_adr[s] + m.sensor_dim[s]] = True
    return mask


# ----------------------------------------------------------------------------
# error series (jax)


@functools.partial(jit_for_few_calls, static_argnames=("layout",))
def error_series(a: Trajectory, b: Trajectory, layout: metrics.QposLayout, rf_mask: jax.Array) -> dict[str, jax.Array]:
    """:func:`mjxdiff.metrics.trajectory_errors` of every member of ``a`` against ``b``:
    ``qpos`` (B, T, ncomp) [m | rad], ``qvel`` (B, T, nv), ``act`` (B, T, na),
    ``sensordata`` (B, T, nsensordata) relative above 1, ``rangefinder`` (B, T) rays
    with a hit/no-hit disagreement, ``ncon`` (B, T) contact-count difference."""
    return jax.vmap(metrics.trajectory_errors, in_axes=(0, 0, None, None))(a, b, layout, rf_mask)


class _FieldTrack:
    """Running per-member reduction of one field's (b, K, n) errors against (b, K) bounds.

    Keeps (B,) values: worst error, first step out of bound (with its
    component and C time), worst ratio error/bound (with its component), the
    last bound; and the (T,) batch-max error series. Each update covers the
    rows ``members`` of the batch and the steps from ``start``.
    """

    def __init__(self, batch: int, steps: int, tol: float):
        self.tol, self.above_tol, self.width = tol, False, 0
        self.max_error = np.zeros(batch)
        self.first_step = np.full(batch, -1)
        self.first_comp = np.zeros(batch, int)
        self.first_time = np.zeros(batch)
        self.max_ratio = np.zeros(batch)
        self.ratio_comp = np.zeros(batch, int)
        self.ratio_floor = np.zeros(batch, int)  # index into FLOORS of the bound at the worst ratio
        self.first_floor = np.zeros(batch, int)
        self.last_bound = np.full(batch, tol)
        self.batch_max = np.zeros(steps)
        self.batch_bound = np.zeros(steps)
        self.sumsq, self.count = 0.0, 0

    def update(self, err: np.ndarray, bound: np.ndarray, time: np.ndarray | jax.Array, start: int,
               members: np.ndarray, healthy: np.ndarray, floor: np.ndarray | None = None,
               values: np.ndarray | None = None) -> None:
        """Adds (b, K, n) errors against (b, K) bounds; ``floor`` (b, K) says which of
        :data:`FLOORS` each bound is (the tolerance when None); ``values`` (b, K, m) are C's
        values in the error's units, for the field's scale."""
        self.width = err.shape[-1]
        if self.width == 0:
            return
        if values is not None and values.size:
            kept = np.where(healthy[:, None, None] & np.isfinite(values), values, 0.0)
            self.sumsq += float(np.sum(kept ** 2))
            self.count += int(healthy.sum()) * values.shape[1] * values.shape[2]
        rows, K = np.arange(err.shape[0]), err.shape[1]
        per_step = err.max(axis=2)
        with np.errstate(invalid="ignore"):  # inf / inf where a blown-up member's envelope is infinite
            ratio = per_step / bound
        exceeded = np.asarray(metrics.exceeds(ratio, 1.0))  # NaN exceeds
        k = exceeded.argmax(axis=1)
        new = exceeded.any(axis=1) & (self.first_step[members] < 0)
        self.first_step[members] = np.where(new, start + k, self.first_step[members])
        self.first_comp[members] = np.where(new, err[rows, k].argmax(axis=-1), self.first_comp[members])
        self.first_time[members] = np.where(new, time[rows, k], self.first_time[members])
        at = np.nan_to_num(ratio, nan=np.inf).argmax(axis=1)
        better = ratio[rows, at] > self.max_ratio[members]
        self.ratio_comp[members] = np.where(better, err[rows, at].argmax(axis=-1), self.ratio_comp[members])
        if floor is not None:
            self.first_floor[members] = np.where(new, floor[rows, k], self.first_floor[members])
            self.ratio_floor[members] = np.where(better, floor[rows, at], self.ratio_floor[members])
        self.max_ratio[members] = np.fmax(self.max_ratio[members], np.nanmax(ratio, axis=1, initial=0.0))
        self.max_error[members] = np.maximum(self.max_error[members], per_step.max(axis=1))  # NaN propagates
        if start + K == len(self.batch_max):
            self.last_bound[members] = bound[:, -1]
        self.above_tol |= bool(np.any(bound > self.tol))
        window = slice(start, start + K)
        self.batch_max[window] = np.maximum(self.batch_max[window],
                                            np.where(healthy[:, None], per_step, 0.0).max(axis=0))
        self.batch_bound[window] = np.maximum(self.batch_bound[window],
                                              np.where(healthy[:, None], bound, 0.0).max(axis=0))

    def result(self, field: str, healthy: np.ndarray, objects: list[str], dt: float) -> FieldResult:
        if self.width == 0 or not healthy.any():
            return FieldResult(field, 0.0, self.tol, -1, -1, "", 0.0)
        out = healthy & (self.first_step >= 0)
        if out.any():
            step = int(self.first_step[out].min())
            member = int(np.flatnonzero(out & (self.first_step == step))[0])
            comp, floor = int(self.first_comp[member]), int(self.first_floor[member])
        else:
            step = -1
            member = int(np.where(healthy, self.max_ratio, 0.0).argmax())
            comp, floor = int(self.ratio_comp[member]), int(self.ratio_floor[member])
        growth = fit_growth(jnp.asarray(self.batch_max), dt)
        envelope = float(np.where(healthy, self.last_bound, 0.0).max()) if self.above_tol else 0.0
        scale = float(np.sqrt(self.sumsq / self.count)) if self.count else 0.0
        sharp = (0.0, 0.0)
        if scale > 0 and len(self.batch_bound):
            sharp = (float(self.batch_bound.min() / scale), float(np.median(self.batch_bound) / scale))
        return FieldResult(field, float(np.where(healthy, self.max_error, 0.0).max()), self.tol, step, member,
                           objects[comp] if objects else "", float(growth.rate), envelope,
                           float(np.where(healthy, self.max_ratio, 0.0).max()), FLOORS[floor],
                           downsample(self.batch_max, self.batch_bound), scale, sharp)


class _FractionTrack:
    """Running per-member sum and first non-zero step of a (b, K) mismatch series."""

    def __init__(self, batch: int, steps: int, tol: float):
        self.tol, self.steps = tol, steps
        self.total = np.zeros(batch)
        self.first_step = np.full(batch, -1)
        self.first_time = np.zeros(batch)

    def update(self, mismatch: np.ndarray, time: np.ndarray | jax.Array, start: int, members: np.ndarray) -> None:
        """Adds a piece of (b, K) mismatch per step, in [0, 1]."""
        out = mismatch > 0
        k = out.argmax(axis=1)
        new = out.any(axis=1) & (self.first_step[members] < 0)
        self.first_step[members] = np.where(new, start + k, self.first_step[members])
        self.first_time[members] = np.where(new, time[np.arange(len(k)), k], self.first_time[members])
        self.total[members] += mismatch.sum(axis=1)

    @property
    def fraction(self) -> np.ndarray:
        """(B,) mean mismatch over the horizon."""
        return self.total / max(self.steps, 1)

    def result(self, field: str, allowed: np.ndarray, healthy: np.ndarray) -> FieldResult:
        """A FieldResult of each member's mismatch fraction against its (B,) allowed fraction."""
        if not healthy.any():
            return FieldResult(field, 0.0, self.tol, -1, -1, "", 0.0)
        frac = np.where(healthy, self.fraction, 0.0)
        # with nothing allowed, any mismatch is out of bound: ratio inf, none 0
        ratio = np.divide(frac, allowed, out=np.where(frac > 0, np.inf, 0.0), where=allowed > 0)
        member = int(ratio.argmax())
        step = int(self.first_step[member]) if ratio[member] > 1 else -1
        return FieldResult(field, float(frac[member]), self.tol, step, member, "", 0.0,
                           float(allowed.max()) if np.any(allowed > self.tol) else 0.0, float(ratio.max()))


def _nonfinite_fields(traj: Trajectory, row: int | np.integer, k: int) -> list[str]:
    """The recorded fields of ``traj`` holding a non-finite value at row ``row``, step ``k``
    of the piece (empty for a stop on a MuJoCo instability warning with a finite state)."""
    if not 0 <= k < traj.qpos.shape[1]:
        return []
    return [f for f in _SERIES if not np.isfinite(np.asarray(getattr(traj, f))[row, k]).all()]


def _track(m: mujoco.MjModel, qpos: np.ndarray | jax.Array) -> np.ndarray | jax.Array:
    """(B, T, k) positions whose behaviour is summarised: the first free joint's
    translation if there is one, else every hinge/slide coordinate."""
    parts = joints.parts(m)
    translation = next((p for p in parts if p.kind == "translation"), None)
    if translation is not None:
        return qpos[..., translation.qpos]
    return qpos[..., [p.qpos_adr for p in parts if p.kind == "scalar"]]


@jit_for_few_calls
def _piece_behaviour(pos: jax.Array, dt: float) -> metrics.BehaviourStats:
    return jax.vmap(metrics.behaviour_stats, in_axes=(0, None))(pos, dt)


class _BehaviourTrack:
    """One engine's running :func:`metrics.behaviour_stats` per member, over pieces.

    Per member: first and last tracked position, path length and largest speed
    (each piece's stats, the previous piece's last position prepended); with
    energy, the first and last total energy and the sum of |total|.
    """

    def __init__(self, batch: int, steps: int, width: int):
        self.steps = steps
        self.first, self.last = np.zeros((batch, width)), np.zeros((batch, width))
        self.distance, self.max_speed = np.zeros(batch), np.zeros(batch)
        self.energy = np.zeros((batch, 3))  # first total, last total, sum |total|
        self.has_energy = False

    def update(self, pos: np.ndarray | jax.Array, energy: np.ndarray | jax.Array, start: int, members: np.ndarray,
               dt: float) -> None:
        if start == 0:
            self.first[members] = pos[:, 0]
        else:
            pos = np.concatenate([self.last[members][:, None], pos], axis=1)
        if pos.shape[1] >= 2:
            piece = _piece_behaviour(pos, dt)
            self.distance[members] += np.asarray(piece.distance)
            self.max_speed[members] = np.maximum(self.max_speed[members], np.asarray(piece.max_speed))
        self.last[members] = pos[:, -1]
        if energy.shape[-1]:
            self.has_energy = True
            total = energy.sum(axis=-1)
            if start == 0:
                self.energy[members, 0] = total[:, 0]
            self.energy[members, 1] = total[:, -1]
            self.energy[members, 2] += np.abs(total).sum(axis=1)

    def stats(self, dt: float, healthy: np.ndarray) -> dict[str, float]:
        """Batch means over healthy members of :class:`metrics.BehaviourStats` of the whole
        track (speeds in units/s, distance, displacement, path efficiency) and, with energy,
        :func:`metrics.energy_drift`."""
        displacement = np.linalg.norm(self.last - self.first, axis=-1)
        moved = self.distance > 0
        out = dict(mean_speed=self.distance / max(self.steps - 1, 1) / dt, max_speed=self.max_speed,
                   distance=self.distance, displacement=displacement,
                   path_efficiency=np.where(moved, displacement / np.where(moved, self.distance, 1), 1.0))
        if self.has_energy:
            first, last, total_abs = self.energy.T
            out["energy_drift"] = np.asarray(metrics.energy_drift_from(first, last, total_abs / self.steps))
        return {k: float(np.mean(np.asarray(v)[healthy])) for k, v in out.items()}


_SERIES = ("qpos", "qvel", "act", "sensordata")


@dataclasses.dataclass(frozen=True)
class _Decision:
    """What :meth:`Judge.result` decides from the data fed: the status (``kind``: the error kind;
    ``weak``: the weak fields of a pass), the field results, the first divergence (None unless a
    field failed the scenario), the blown-up members (:meth:`Judge._diverged`), (B,) masks of
    members where C (``c_bad``) or only MJX (``mjx_bad``) blew up, judged (C finite), healthy
    (both finite) and failing, the pass rate, each member's worst error / bound, the outlier
    member beyond :data:`OUTLIER_RATIO` (None if none) and the failed fields."""

    status: str
    kind: str
    weak: tuple[str, ...]
    fields: list[FieldResult]
    first: dict[str, Any] | None
    diverged: list[dict[str, Any]]
    c_bad: np.ndarray
    mjx_bad: np.ndarray
    judged: np.ndarray
    healthy: np.ndarray
    member_fails: np.ndarray
    pass_rate: Any
    worst_ratio: np.ndarray
    outlier: int | None
    failed: list[FieldResult]


def _contact_allowance(batch: int, tol: Tolerances, noise: NoiseFloor | None,
                       solver: NoiseFloor | None) -> np.ndarray:
    """(B,) fraction of steps whose contact count may differ: the tolerance, or up to twice the
    fraction C's own reruns show under each floor given (at most 1)."""
    allowed = np.full(batch, tol.contact_mismatch)
    for floor in (noise, solver):  # a contact-count mismatch may reach twice what C's own reruns show
        if floor is not None:
            allowed = np.maximum(allowed, np.minimum(1.0, 2 * floor.contact_fraction))
    return allowed


def _status(mjx_bad: bool, failed: bool, c_bad: bool, fields: list[FieldResult]) -> tuple[str, str, tuple[str, ...]]:
    """(status, error kind, weak fields): ``fail`` where MJX blew up in some member or some field
    failed, else ``error`` (``unstable``) where C blew up in some member, else ``pass`` with the
    fields whose bound is weak."""
    if mjx_bad or failed:
        return "fail", "", ()
    if c_bad:
        return "error", "unstable", ()
    return "pass", "", tuple(f.field for f in fields if f.weak)


def _unstable_c(d: _Decision) -> str:
    """The sentence on members where C itself blew up (the earliest named); empty if none."""
    if not d.c_bad.any():
        return ""
    d0 = min((x for x in d.diverged if x["engine"] == "c"), key=lambda x: x["step"])
    return (f"MuJoCo C itself goes non-finite or unstable in {int(d.c_bad.sum())} member(s) (first: "
            f"member {d0['member']} at step {d0['step']}, t={d0['time']:g} s)")


def _mjx_nonfinite_message(d: _Decision) -> str:
    """The message where MJX goes non-finite while C stays finite: the earliest such member, its
    fields still finite, and the first field out of bound where that came elsewhere or earlier."""
    d0 = min((x for x in d.diverged if x["engine"] == "mjx"), key=lambda x: x["step"])
    last = f"last finite step {d0['last_finite_step']}" if d0["step"] else "non-finite from the first step"
    message = (f"MJX goes non-finite at step {d0['step']} (t={d0['time']:g} s), member {d0['member']}, while "
               f"MuJoCo C stays finite ({int(d.mjx_bad.sum())} member(s)); non-finite: "
               f"{', '.join(d0['nonfinite_fields']) or 'state'}; still finite: "
               f"{', '.join(d0['finite_fields']) or 'nothing'}; {last}")
    first = d.first
    if first and (first["step"] < d0["step"] or first["member"] != d0["member"]):
        message += (f"; first out of bound: {first['field']} of {first['object'] or 'member'} "
                    f"at step {first['step']}, member {first['member']}")
    return message


def _failed_message(d: _Decision, enveloped: bool, threshold: float) -> str:
    """The message where a field fails: the first divergence, and the outlier where it alone
    fails a scenario whose pass rate would pass. ``enveloped``: judged against a noise floor."""
    first = d.first
    assert first is not None  # set for the first of the failed fields
    where = "leaves the envelope" if enveloped else f"exceeds {first['tolerance']:.1e}"
    message = (f"{first['field']} of {first['object'] or 'member ' + str(first['member'])} {where} "
               f"at step {first['step']} (t={first['time']:.4g} s), member {first['member']}; "
               f"worst {first['error']:.3g}")
    if d.outlier is not None and d.pass_rate >= threshold:
        message += (f"; member {d.outlier} is {d.worst_ratio[d.outlier]:.3g}x its bound: an outlier that far "
                    f"out fails the scenario whatever the pass rate ({d.pass_rate:.0%})")
    return message


def _pass_message(d: _Decision) -> str:
    """The message of a pass: the worst of qpos and qvel against its bound, the loosest weak
    bound, and how many members were out of tolerance."""
    fields = d.fields
    worst = max((f for f in fields if f.field in ("qpos", "qvel")), key=lambda f: f.ratio)
    message = f"worst {worst.field} {worst.max_error:.2g} (tol {worst.tolerance:.0e}"
    message += f", envelope {worst.envelope:.1e})" if worst.envelope else ")"
    if d.weak:
        loosest = max((f for f in fields if f.weak), key=lambda f: f.bound_scale[1])
        message += (f"; weak: the {loosest.field} bound is {loosest.bound_scale[1]:.2g}x its scale "
                    f"{loosest.scale:.2g} at the median step (a difference that large would pass)")
    if d.member_fails.any():
        message += (f"; {int(d.member_fails.sum())}/{int(d.judged.sum())} members out of tolerance, "
                    f"pass rate {d.pass_rate:.0%}")
    return message


def _message(d: _Decision, enveloped: bool, threshold: float) -> str:
    """The verdict's message, written from its data ``d``: why it failed, why it is an error, or
    how close a pass came; a failure also names the members C itself lost."""
    unstable_c = _unstable_c(d)
    if d.mjx_bad.any():
        message = _mjx_nonfinite_message(d)
    elif d.failed:
        message = _failed_message(d, enveloped, threshold)
    elif d.c_bad.any():
        message = (f"{unstable_c}: an unstable scenario, not an MJX divergence (lower the timestep, "
                   "the randomization or the stiffness)")
    else:
        message = _pass_message(d)
    if d.status == "fail" and unstable_c:
        message += f"; not judged: {unstable_c}"
    return message


class Judge:
    """Compares MJX against C (the reference) piece by piece and decides the scenario's status.

    Feed pieces of both rollouts, with the noise floor's envelope of each
    piece when judging against the chaos envelope (:meth:`update`), then ask
    for the verdict (:meth:`result`). A piece covers some members (all, or
    one group of a batch run in groups) and consecutive steps. Only
    per-member running values and (T,) batch-max series are kept, so memory
    depends on the batch size, not on the horizon.

    A member passes when every field stays within its bound at every step: the
    fixed tolerance, or with a noise floor, max(tolerance, chaos envelope).
    The scenario passes when the fraction of healthy members that pass is at
    least ``threshold`` (the pass-rate criterion of cross-platform validation).

    Args:
      batch, steps: B members and T steps in all.
    """

    def __init__(self, m: mujoco.MjModel, tol: Tolerances, batch: int, steps: int):
        self.m, self.tol, self.batch = m, tol, batch
        self.dt = float(m.opt.timestep)
        self.layout = metrics.qpos_layout(m)
        self.rf_mask = rangefinder_mask(m)
        self.fields = {key: _FieldTrack(batch, steps, getattr(tol, key)) for key in _SERIES}
        self.contacts = _FractionTrack(batch, steps, tol.contact_mismatch)
        #: (B,) steps whose contact count differs in grazing contacts alone (not judged)
        self.ambiguous = np.zeros(batch, int)
        #: C's own contacts rechecked at mismatching steps (:mod:`mjxdiff.compare.ambiguity`);
        #: None: not checked (set by the caller, who has the members' models)
        self.ccd: CcdAmbiguity | None = None
        #: per member, MJX's pair sums minus C's at its first pair mismatch (and that step)
        self.pair_delta = np.zeros((batch, 2), np.uint32)
        self.pair_delta_step = np.full(batch, -1)
        self.rangefinder = _FractionTrack(batch, steps, tol.rangefinder_mismatch)
        width = _track(m, np.zeros((1, m.nq))).shape[-1]
        self.behaviour = {"c": _BehaviourTrack(batch, steps, width), "mjx": _BehaviourTrack(batch, steps, width)}
        self.diverged_at = {"c": np.full(batch, -1), "mjx": np.full(batch, -1)}
        self.nonfinite: dict[str, dict[int, list[str]]] = {"c": {}, "mjx": {}}  # member -> fields at diverged_at

    def errors(self, traj_c: Trajectory, traj_mjx: Trajectory) -> dict[str, np.ndarray]:
        """A piece's :func:`error_series` of MJX against C, on the host."""
        return jax.tree.map(np.asarray, error_series(traj_mjx, traj_c, self.layout, jnp.asarray(self.rf_mask)))

    def exceeds_tolerance(self, series: dict[str, np.ndarray]) -> bool:
        """Whether some error of a piece (:meth:`errors`) is above its fixed tolerance or not finite.

        Only then can the chaos envelope change the verdict: the bound is
        max(tolerance, envelope), so an error within the tolerance is within
        every bound.
        """
        return not all(np.all(series[key] <= getattr(self.tol, key)) for key in _SERIES)

    def contacts_exceed_tolerance(self, members: np.ndarray | slice = slice(None)) -> bool:
        """Whether some of ``members`` already mismatch their contact count on more than the
        tolerated fraction of all steps (the sum only grows), so that the noise floor's
        contact changes decide whether they pass."""
        return bool(np.any(self.contacts.fraction[members] > self.tol.contact_mismatch))

    def update(self, traj_c: Trajectory, traj_mjx: Trajectory, envelope: dict[str, np.ndarray] | None = None,
               start: int = 0, members: np.ndarray | slice = slice(None),
               series: dict[str, np.ndarray] | None = None, source: dict[str, np.ndarray] | None = None) -> None:
        """Adds a piece: (b, K, ...) trajectories of ``members`` from step ``start``, and
        optionally field -> (b, K) envelopes, which floor each envelope value came from
        (``source``, indices into :data:`FLOORS`; rounding when None, see
        :func:`mjxdiff.compare.noise.combine`) and the piece's :meth:`errors` if already computed."""
        members = np.arange(self.batch)[members]
        for engine, traj in (("c", traj_c), ("mjx", traj_mjx)):
            at = self.diverged_at[engine]
            before = at[members].copy()
            at[members] = first_diverged([before, traj.diverged_at])
            for row in np.flatnonzero((before < 0) & (at[members] >= 0)):
                self.nonfinite[engine][int(members[row])] = _nonfinite_fields(traj, row, int(at[members[row]]) - start)
            with np.errstate(invalid="ignore", over="ignore"):  # a blown-up member is not healthy
                self.behaviour[engine].update(_track(self.m, traj.qpos), traj.energy, start, members, self.dt)
        healthy = (self.diverged_at["c"][members] < 0) & (self.diverged_at["mjx"][members] < 0)
        series = self.errors(traj_c, traj_mjx) if series is None else series
        for key, track in self.fields.items():
            tol = getattr(self.tol, key)
            bound, floor = np.full(series["ncon"].shape, tol), None
            if envelope is not None:
                floor = np.where(envelope[key] > tol, source[key] if source is not None else 1, 0)
                bound = np.maximum(bound, envelope[key])
            values = np.asarray(getattr(traj_c, key))
            if key == "sensordata":  # its errors are relative above 1
                values = np.minimum(np.abs(values), 1.0)
            track.update(series[key], bound, traj_c.time, start, members, healthy, floor, values)
        # a step where some geom pair's count of firm contacts differs; a count that differs only
        # in grazing contacts is ambiguous (mjxdiff.engine.pairs)
        differ = pairs.mismatch(traj_mjx.pairs, traj_c.pairs)
        self.ambiguous[members] += ((np.asarray(series["ncon"]) > 0) & ~differ).sum(axis=1)
        if self.ccd is not None:
            before = self.ccd.before(traj_c.qpos, members)
            tested = self.ccd.before(traj_mjx.qpos, members, "mjx")
            if differ.any():
                differ = self.ccd.filter(differ, before, members, start, (tested, np.asarray(traj_mjx.pairs)))
        self.contacts.update(differ.astype(float), traj_c.time, start, members)
        first = differ.argmax(axis=1)
        for row in np.flatnonzero(differ.any(axis=1) & (self.pair_delta_step[members] < 0)):
            i, k = int(members[row]), int(first[row])
            self.pair_delta_step[i] = start + k
            self.pair_delta[i] = np.asarray(traj_mjx.pairs)[row, k] - np.asarray(traj_c.pairs)[row, k]
        if self.rf_mask.any():
            self.rangefinder.update(series["rangefinder"] / self.rf_mask.sum(), traj_c.time, start, members)

    def result(self, name: str, threshold: float = 0.95, noise: NoiseFloor | None = None,
               solver: NoiseFloor | None = None) -> ScenarioResult:
        """The verdict on everything fed so far; ``noise`` is the rounding floor whose envelopes
        were fed, ``solver`` the solver floor when it was fed too.

        Members where MuJoCo C blows up are not judged (an unstable scenario: ``error`` if
        nothing else fails). A member where MJX goes non-finite while C stays finite fails,
        and the scenario with it, whatever the threshold.
        """
        d = self._decide(threshold, noise, solver)
        return ScenarioResult(
            name=name, status=d.status, message=_message(d, noise is not None, threshold), error_kind=d.kind,
            fields=tuple(d.fields),
            weak=d.weak,
            first_divergence=d.first, diverged_members=tuple(d.diverged),
            behaviour=self._behaviour(d.healthy), tolerances=self.tol.as_dict(),
            pass_rate=float(d.pass_rate), threshold=threshold,
            noise_rate=noise.rate if noise is not None else {})

    def _decide(self, threshold: float, noise: NoiseFloor | None, solver: NoiseFloor | None) -> _Decision:
        """The verdict's data on everything fed so far, its status included (see :meth:`result`)."""
        c_bad = self.diverged_at["c"] >= 0
        mjx_bad = (self.diverged_at["mjx"] >= 0) & ~c_bad
        judged, healthy = ~c_bad, ~c_bad & ~mjx_bad
        diverged = [self._diverged(engine, int(i)) for engine, bad in (("c", c_bad), ("mjx", mjx_bad))
                    for i in np.flatnonzero(bad)]
        elements = component_elements(self.m, self.layout)
        fields, member_fails = self._field_results(judged, mjx_bad, elements, noise, solver)
        pass_rate = 1.0 - member_fails.sum() / max(int(judged.sum()), 1)
        worst_ratio = np.where(healthy, np.nan_to_num(np.max([t.max_ratio for t in self.fields.values()], axis=0),
                                                      nan=np.inf), 0.0)
        outlier = int(worst_ratio.argmax()) if worst_ratio.max() > OUTLIER_RATIO else None
        failed = [f for f in fields if not f.ok] if (pass_rate < threshold or mjx_bad.any()
                                                     or outlier is not None) else []
        first = self._first_divergence(failed, elements) if failed else None
        status, kind, weak = _status(bool(mjx_bad.any()), bool(failed), bool(c_bad.any()), fields)
        return _Decision(status=status, kind=kind, weak=weak, fields=fields, first=first, diverged=diverged,
                         c_bad=c_bad, mjx_bad=mjx_bad, judged=judged, healthy=healthy,
                         member_fails=member_fails, pass_rate=pass_rate, worst_ratio=worst_ratio,
                         outlier=outlier, failed=failed)

    def _field_results(self, judged: np.ndarray, mjx_bad: np.ndarray, elements: dict[str, list[dict[str, str]]],
                       noise: NoiseFloor | None, solver: NoiseFloor | None) -> tuple[list[FieldResult], np.ndarray]:
        """The field results over the ``judged`` members (the series fields, ``contacts``, then
        ``rangefinder`` where the model has one) and which judged members fail: MJX non-finite
        (``mjx_bad``), a field out of its bound at some step, or more steps with a contact-count
        (rangefinder) mismatch than allowed (:func:`_contact_allowance`)."""
        objects = {f: [describe(e) for e in column] for f, column in elements.items()}
        fields = [track.result(key, judged, objects[key], self.dt) for key, track in self.fields.items()]
        allowed = _contact_allowance(self.batch, self.tol, noise, solver)
        fields.append(self._contact_result(allowed, judged))
        member_fails = mjx_bad.copy()
        for track in self.fields.values():
            member_fails |= track.first_step >= 0
        member_fails |= self.contacts.fraction > allowed
        if self.rf_mask.any():
            rf_allowed = np.full(self.batch, self.tol.rangefinder_mismatch)
            fields.append(self.rangefinder.result("rangefinder", rf_allowed, judged))
            member_fails |= self.rangefinder.fraction > rf_allowed
        member_fails &= judged
        return fields, member_fails

    def _contact_result(self, allowed: np.ndarray, judged: np.ndarray) -> FieldResult:
        """The ``contacts`` field: each member's fraction of steps with a pair mismatch against its
        allowance, its object the geom pairs that differ at the reported member's first one."""
        result = self.contacts.result("contacts", allowed, judged)
        if result.member < 0 or self.pair_delta_step[result.member] < 0:
            return result
        found = pairs.decode(self.m, self.pair_delta[result.member])
        return dataclasses.replace(result, object=pairs.describe_pairs(self.m, found))

    def _first_divergence(self, failed: list[FieldResult],
                          elements: dict[str, list[dict[str, str]]]) -> dict[str, Any]:
        """The first divergence among the ``failed`` fields (the one out of bound earliest): its
        ``field``, ``step``, ``time`` (C's time after that step; None without a member),
        ``member``, ``object``, ``element``, ``error`` (the field's worst) and ``tolerance``."""
        f = min(failed, key=lambda f: (f.first_step if f.first_step >= 0 else 1 << 30))
        step = max(f.first_step, 0)
        time = None
        if f.member >= 0:  # C's time after that step
            track = ({"contacts": self.contacts, "rangefinder": self.rangefinder}.get(f.field)
                     or self.fields[f.field])
            exact = track.first_step[f.member] == step
            time = float(track.first_time[f.member]) if exact else round((step + 1) * self.dt, 9)
        return dict(field=f.field, step=step, time=time, member=f.member, object=f.object,
                    element=next((e for e in elements.get(f.field, ()) if describe(e) == f.object), None),
                    error=f.max_error, tolerance=f.tolerance)

    def _diverged(self, engine: str, member: int) -> dict[str, Any]:
        """Where ``engine`` blew up in ``member``: step, time, which fields were non-finite there."""
        step = int(self.diverged_at[engine][member])
        bad = self.nonfinite[engine].get(member, [])
        return dict(engine=engine, member=member, step=step, time=round((step + 1) * self.dt, 9),
                    last_finite_step=step - 1, nonfinite_fields=bad,
                    finite_fields=[f for f in _SERIES if f not in bad])

    def _behaviour(self, healthy: np.ndarray) -> dict[str, Any]:
        """Batch-mean behaviour statistics of both engines and their relative difference."""
        if not healthy.any() or self.behaviour["c"].first.shape[-1] == 0 or self.behaviour["c"].steps < 2:
            return {}
        out = {engine: track.stats(self.dt, healthy) for engine, track in self.behaviour.items()}
        out["relative_difference"] = {
            k: abs(out["mjx"][k] - out["c"][k]) / max(abs(out["c"][k]), 1e-12) for k in out["c"]}
        return out


def judge(name: str, m: mujoco.MjModel, traj_c: Trajectory, traj_mjx: Trajectory, tol: Tolerances,
          threshold: float = 0.95, perturbed: Trajectory | None = None) -> ScenarioResult:
    """The verdict on whole trajectories (see :class:`Judge`).

    Args:
      perturbed: C rerun from perturbed initial states (:func:`mjxdiff.compare.noise.perturb`);
        when given, errors are judged against the chaos envelope it implies.
    """
    j = Judge(m, tol, *traj_c.time.shape)
    noise = None
    if perturbed is not None:
        noise, envelope = noise_floor(m, perturbed, traj_c, j.rf_mask)
    else:
        envelope = None
    j.update(traj_c, traj_mjx, envelope)
    return j.result(name, threshold, noise)
