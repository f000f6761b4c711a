"""MuJoCo C behind the engine interface: :class:`CEngine` steps every member of a batch on all
cores with :class:`mujoco.batch.Batch`, recording as ``mj_step`` does (see
:mod:`mjxdiff.engine.engines`, which re-exports it beside MJX's engines)."""

from __future__ import annotations

import copy
import dataclasses
import os
from typing import Any, Iterator

import mujoco
import numpy as np

from mjxdiff.compat import Batch, SimulationError
from mjxdiff.engine import stages
from mjxdiff.engine.stages import Forward
from mjxdiff.engine.trajectory import Streaming, Trajectory, first_true, resync_blocks, shifted
from mjxdiff.engine.xla import CORES
from mjxdiff.input.inputs import BatchedInputs, roundoff_moved
from mjxdiff.input.precision import Precision

__all__ = ["CEngine"]


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


def _rollout_shaken(b: Any, k: int, control: np.ndarray, record: tuple, out: dict, shake: _Shake) -> np.ndarray:
    """``b.rollout(k, ...)`` one step at a time, ``shake`` moving the state after each step.
    Returns the ids of the members MuJoCo raised a :class:`SimulationError` for."""
    one = {item: np.zeros_like(buf[:, :1]) for item, buf in out.items()}
    raised: list[np.ndarray] = []
    for i in range(k):
        try:
            b.rollout(1, control=control[:, i:i + 1], record=record, out=one)
        except SimulationError as e:
            raised.append(np.asarray(e.ids))
        for item, buf in out.items():
            buf[:, i] = one[item][:, 0]
        shake.move(b.qpos, 0)  # views of the batch's state: moved in place
        shake.move(b.qvel, 1)
    return np.concatenate(raised) if raised else np.zeros(0, int)


class CEngine(Streaming):
    """MuJoCo C: :class:`mujoco.batch.Batch` over all cores, one model per member."""

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
        b = Batch(m, B, nthread=self.nthread)
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
            try:
                if shake is None:
                    b.rollout(k, control=inputs.ctrl[:, start:start + k], record=record, out=out)
                else:
                    raised[_rollout_shaken(b, k, inputs.ctrl[:, start:start + k], record, out, shake)] = True
            except SimulationError as e:
                raised[np.asarray(e.ids)] = True
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
                             energy=out.get("energy", np.zeros((B, k, 0))),
                             diverged_at=shifted(diverged, start))
