"""MuJoCo C behind the engine interface: :class:`CEngine` steps every member of a batch with
:class:`mujoco.batch.Batch` (on all cores, or one thread for a small batch), one step at a time
so that each step's contacts are read by geom pair (:mod:`mjxdiff.engine.pairs`), recording as
``mj_step`` does (see :mod:`mjxdiff.engine.engines`, which re-exports it beside MJX's engines)."""

from __future__ import annotations

import copy
import dataclasses
import os
from typing import Any, Iterator

import mujoco
import numpy as np

from mjxdiff.compat import Batch, SimulationError
from mjxdiff.engine import pairs, stages
from mjxdiff.engine.stages import Forward
from mjxdiff.engine.trajectory import Streaming, Trajectory, first_true, resync_blocks, shifted
from mjxdiff.engine.xla import CORES
from mjxdiff.input.inputs import BatchedInputs, roundoff_moved
from mjxdiff.input.precision import Precision

__all__ = ["CEngine"]

#: Members up to which C steps on one thread (see :meth:`CEngine.stream`).
SMALL_BATCH = 16


def _record_buffer(m: mujoco.MjModel, d: mujoco.MjData, item, batch: int, steps: int) -> np.ndarray:
    """A zeroed (B, T, ...) array of the shape and dtype ``Batch.rollout`` records ``item`` in."""
    if not isinstance(item, str):  # an mjtState spec
        return np.zeros((batch, steps, mujoco.mj_stateSize(m, int(item))))
    value = getattr(d, item)
    template = value if isinstance(value, np.ndarray) else np.zeros((), np.int32)  # int scalars: int32
    return np.zeros((batch, steps, *template.shape), template.dtype)


def _with_energy(m: mujoco.MjModel) -> mujoco.MjModel:
    m = copy.copy(m)
    m.opt.enableflags |= mujoco.mjtEnableBit.mjENBL_ENERGY
    return m


class _Shake:
    """The per-step moves of :meth:`CEngine.stream`'s ``jitter``: one generator per member and field."""

    def __init__(self, inputs: BatchedInputs, jitter: np.ndarray):
        self.rows = np.flatnonzero(jitter)
        self.size = jitter[self.rows, None]
        self.rngs = [(np.random.default_rng([inputs.seed, int(inputs.ids[i]), 1]),
                      np.random.default_rng([inputs.seed, int(inputs.ids[i]), 2])) for i in self.rows]

    def move(self, x: np.ndarray, field: int) -> None:
        """Moves the jittered rows of ``x`` (B, n) in place, one step's worth."""
        signs = np.stack([2.0 * rng[field].integers(0, 2, x.shape[1]) - 1.0 for rng in self.rngs])
        x[self.rows] = roundoff_moved(x[self.rows], signs, self.size)


def _pair_sums(models: tuple[mujoco.MjModel, ...], shared_gaps: bool, b: Any, ids: np.ndarray, ncon: np.ndarray,
               data: mujoco.MjData) -> np.ndarray:
    """(len(ids), 2) uint32 pair sums (:mod:`mjxdiff.engine.pairs`) of the contacts members ``ids``
    of the persistent batch ``b`` hold (their ``ncon``), read through ``data``; every member's
    gaps ``models[0]``'s where ``shared_gaps`` (:func:`_same_gaps`), else each its own."""
    rows = np.flatnonzero(ncon)
    read = []
    for row in rows:
        d = b.get_data(int(ids[row]), data)
        c, n = d.contact, d.ncon
        read.append((pairs.keys(c.geom[:n], c.flex[:n]), c.dist[:n].copy(), c.includemargin[:n].copy()))
    if shared_gaps and read:
        key, dist, margin = (np.concatenate(x) for x in zip(*read))
        return pairs.host_sums(models[0], key, dist, margin, np.repeat(rows, ncon[rows]), len(ids))
    out = np.zeros((len(ids), 2), np.uint32)
    for row, (key, dist, margin) in zip(rows, read):
        out[row] = pairs.host_sums(models[int(ids[row])], key, dist, margin, np.zeros(len(dist), int), 1)[0]
    return out


def _same_gaps(models: tuple[mujoco.MjModel, ...]) -> bool:
    """Whether every member's geom and pair gaps are the first one's (a randomized gap is not)."""
    return all(np.array_equal(mi.geom_gap, models[0].geom_gap) and np.array_equal(mi.pair_gap, models[0].pair_gap)
               for mi in models[1:])


def _step_each(b: Any, models: tuple[mujoco.MjModel, ...], control: np.ndarray, record: tuple,
               out: dict, sums: np.ndarray, shake: _Shake | None) -> np.ndarray:
    """``b.rollout(k, ...)`` one step at a time (k = ``control``'s steps), recording into ``out``
    as it would, and each step's pair sums into ``sums`` (B, k, 2); ``shake``, if given, moves the
    state after each step. As in one call, a member whose warning counters rise stops stepping
    and its records repeat. Returns the ids of the members MuJoCo raised a
    :class:`SimulationError` for."""
    B, k = control.shape[:2]
    going = np.ones(B, bool)
    warned = b.warning[:, :, 1].sum(axis=1)
    data = mujoco.MjData(models[0])
    shared_gaps = _same_gaps(models)
    raised: list[np.ndarray] = []
    ids, one = np.arange(B), {item: np.zeros_like(buf[:, :1]) for item, buf in out.items()}
    for i in range(k):
        if not going.all() and len(ids) != going.sum():  # a member stopped: step the rest
            ids = np.flatnonzero(going)
            one = {item: np.zeros_like(buf[ids, :1]) for item, buf in out.items()}
        if len(ids):
            try:
                b.rollout(1, control=control[ids, i:i + 1], record=record, out=one, ids=ids)
            except SimulationError as e:
                raised.append(np.asarray(e.ids))
        for item, buf in out.items():
            buf[ids, i] = one[item][:, 0]
        sums[ids, i] = _pair_sums(models, shared_gaps, b, ids, one["ncon"][:, 0], data)
        if i and len(ids) < B:
            stopped = ~going
            for item, buf in out.items():
                buf[stopped, i] = buf[stopped, i - 1]
            sums[stopped, i] = sums[stopped, i - 1]
        if shake is not None:
            shake.move(b.qpos, 0)  # views of the batch's state: moved in place
            shake.move(b.qvel, 1)
        going &= b.warning[:, :, 1].sum(axis=1) <= warned
    return np.concatenate(raised) if raised else np.zeros(0, int)


class CEngine(Streaming):
    """MuJoCo C: :class:`mujoco.batch.Batch`, one model per member."""

    name = "c"
    precision: Precision = "float64"
    capabilities: frozenset[str] = frozenset()

    def __init__(self, nthread: int | None = None):
        #: C threads (0: all CPUs); default :data:`CORES`, all of them unless ``MJXDIFF_CORES`` says otherwise
        self.nthread = (0 if CORES == (os.cpu_count() or 1) else CORES) if nthread is None else nthread

    def forward(self, m: mujoco.MjModel, d: mujoco.MjData, fields: tuple[str, ...]) -> Forward:
        """``mj_forward`` of a copy of ``d``, read back (:func:`mjxdiff.engine.stages.read`)."""
        d = copy.copy(d)
        mujoco.mj_forward(m, d)
        return stages.read(m, d, fields)

    def resync(self, inputs: BatchedInputs, reference: Trajectory, every: int = 1) -> Trajectory:
        """C restarted from ``reference``'s state every ``every`` steps (as MJX's
        :meth:`~mjxdiff.engine.engines.MJXEngine.resync`): the S = ceil(T / every) blocks of every
        member step side by side, as B x S members of one rollout of ``every`` steps; ``time``
        continues from the reference's."""
        B, T, k = inputs.batch, inputs.steps, every
        states, ctrl, starts = resync_blocks(inputs, reference, every)
        S = len(starts)
        flat = {f: x.reshape(B * S, *x.shape[2:]) for f, x in states.items()}
        blocks = dataclasses.replace(inputs, qpos=flat["qpos"], qvel=flat["qvel"], act=flat["act"],
                                     ctrl=ctrl.reshape(B * S, k, -1), factors={},
                                     models=tuple(mi for mi in inputs.models for _ in range(S)), member_ids=None)
        traj = self.rollout(blocks)

        def back(x):
            return np.asarray(x).reshape(B, S * k, *np.shape(x)[2:])[:, :T]
        fields = {f.name: back(getattr(traj, f.name)) for f in dataclasses.fields(Trajectory)
                  if f.name not in ("diverged_at", "time")}
        at = np.asarray(traj.diverged_at).reshape(B, S)
        at = np.where(at >= 0, at + starts, -1)
        first = np.where((at >= 0).any(axis=1), at[np.arange(B), (at >= 0).argmax(axis=1)], -1)
        time = np.asarray(traj.time) + flat["time"][:, None]
        return Trajectory(**fields, time=back(time), diverged_at=np.where(first < T, first, -1))

    def stream(self, inputs: BatchedInputs, chunk: int, jitter: np.ndarray | None = None) -> Iterator[Trajectory]:
        """The rollout in consecutive pieces of ``chunk`` steps (the last may be shorter).

        One :class:`~mujoco.batch.Batch` carries on from where the previous
        piece stopped, so the pieces concatenate to :meth:`rollout`'s result
        bit for bit. ``diverged_at`` counts steps from the start of the
        rollout and may repeat in later pieces; the first one counts.

        ``jitter``: (B,) relative sizes; after every step, member ``i``'s ``qpos`` and ``qvel``
        move by ``jitter[i] * max(|x|, 1)`` per component with a random sign (drawn from
        generators seeded by (seed, member id), so the pieces are the same however the steps are
        cut): MuJoCo's parity method's float32 shadow of C (:data:`mjxdiff.compare.noise.STEP_JITTER`).
        Records are taken before the move.
        """
        models = inputs.models
        if inputs.energy:  # C computes d.energy itself; MJX refuses the flag, so only C's copies get it
            models = tuple(_with_energy(mi) for mi in models)
        m, B = models[0], inputs.batch
        # persistent: each member's contacts stay readable. Stepped one step a call, a small batch
        # runs faster on one thread: waking the pool costs ~80 us a call (measured, 8 members)
        b = Batch(m, B, nthread=1 if B <= SMALL_BATCH else self.nthread, persistent=True)
        b.set_models(list(models))
        b.qpos[:] = inputs.qpos
        b.qvel[:] = inputs.qvel
        if m.na:
            b.act[:] = inputs.act
        time_spec = mujoco.mjtState.mjSTATE_TIME
        record = ("qpos", "qvel", "act", "sensordata", "ncon", time_spec) + (("energy",) if inputs.energy else ())
        d = mujoco.MjData(m)
        raised = np.zeros(B, bool)
        last_time = np.zeros((B, 1))
        shake = None if jitter is None or not np.any(jitter) else _Shake(inputs, np.asarray(jitter, float))
        for start in range(0, inputs.steps, chunk):
            k = min(chunk, inputs.steps - start)
            # preallocated, so that records survive a SimulationError in some members
            out = {item: _record_buffer(m, d, item, B, k) for item in record}
            sums = np.zeros((B, k, 2), np.uint32)
            raised[_step_each(b, models, inputs.ctrl[:, start:start + k], record, out, sums, shake)] = True
            time = out[time_spec][..., 0]
            # A member whose warning counters rise stops, and its records then repeat.
            warned = (b.warning[:, :, 1].sum(axis=1) > 0) | raised
            stalled = first_true(time <= np.concatenate([last_time, time[:, :-1]], axis=1))
            last_time = time[:, -1:]
            # numpy's stubs type .all(axis) as maybe a scalar
            nonfinite = first_true(~np.isfinite(out["qpos"]).all(-1) | ~np.isfinite(out["qvel"]).all(-1))  # pyright: ignore[reportArgumentType]
            diverged = np.where(warned, np.maximum(stalled, 0), nonfinite)
            yield Trajectory(qpos=out["qpos"], qvel=out["qvel"], act=out["act"],
                             sensordata=out["sensordata"], time=time, ncon=out["ncon"].astype(np.int64),
                             pairs=sums, energy=out.get("energy", np.zeros((B, k, 0))),
                             diverged_at=shifted(diverged, start))
