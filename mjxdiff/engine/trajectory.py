"""What every engine gives and what the comparison needs of one: :class:`Trajectory`, a batch of
rollouts in one shape whatever the engine, and :class:`Engine`, the interface MuJoCo C
(:class:`mjxdiff.engine.engines.CEngine`), MJX (:class:`mjxdiff.engine.engines.MJXEngine`) and MuJoCo Warp
(:class:`mjxdiff.engine.mjwarp.MJWarpEngine`) implement. The verdict, the noise floor and the metrics
read trajectories without importing any engine.

Recording follows ``mj_step``: after step k, ``qpos``/``qvel``/``act``/``time`` are the new
state, while ``sensordata``, ``ncon`` and ``pairs`` were computed from the state before the step.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Iterator, Protocol

import jax
import numpy as np

if TYPE_CHECKING:
    import mujoco

    from mjxdiff.input.inputs import BatchedInputs
    from mjxdiff.engine.stages import Forward
    from mjxdiff.input.precision import Precision

__all__ = ["Engine", "Streaming", "Trajectory", "concat", "first_diverged", "first_true", "resync_blocks", "shifted"]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Trajectory:
    """A batch of rollouts, every field shaped ``(B, T, ...)``.

    Attributes:
      qpos: (B, T, nq) positions after each step.
      qvel: (B, T, nv) velocities after each step.
      act: (B, T, na) actuator activations after each step.
      sensordata: (B, T, nsensordata) sensors, evaluated before each step.
      time: (B, T) simulated time after each step, s.
      ncon: (B, T) number of contacts, C's ``d.ncon`` (a gap's inactive ones included), evaluated
        before each step.
      pairs: (B, T, 2) uint32 sums of two hashes of each firm contact's geom pair, before each
        step (:mod:`mjxdiff.engine.pairs`): equal where every geom pair has the same number of
        contacts, grazing ones left out.
      energy: (B, T, 2) potential and kinetic energy (J) before each step, as
        MuJoCo's ``d.energy``; (B, T, 0) unless the inputs ask for energy.
        Exact for Euler and implicitfast. Under RK4 neither record is the
        pre-step energy: C's is that of its last RK stage, MJX's mixes stage-4
        kinematics with the pre-step qpos/qvel (measured 1e-3 apart, relative).
      diverged_at: (B,) first step at which the engine produced a non-finite
        state or stopped on a MuJoCo instability warning; -1 if never.
    """

    qpos: np.ndarray | jax.Array
    qvel: np.ndarray | jax.Array
    act: np.ndarray | jax.Array
    sensordata: np.ndarray | jax.Array
    time: np.ndarray | jax.Array
    ncon: np.ndarray | jax.Array
    pairs: np.ndarray | jax.Array
    energy: np.ndarray | jax.Array
    diverged_at: np.ndarray | jax.Array

    def to_numpy(self) -> "Trajectory":
        return jax.tree.map(np.asarray, self)


class Engine(Protocol):
    """What the comparison needs from a simulator: batched inputs in, trajectories out, whole or
    in pieces, and one step at a time from another engine's states. The sweep, the verdict,
    the one-step check and the diagnosis use engines through this alone.

    Attributes:
      name: ``c``, ``mjx`` or ``warp``: how reports name the engine.
      precision: the floating point it steps in (C always ``float64``; MuJoCo Warp ``float32``).
      capabilities: what else the engine offers the sweep: ``estimate`` (mjxdiff's compile-time
        and memory model applies: :mod:`mjxdiff.input.cost`), ``transfer`` (a host interface to check
        against C: :mod:`mjxdiff.compare.transfer`).
    """

    name: str
    capabilities: frozenset[str]

    @property
    def precision(self) -> Precision: ...

    def rollout(self, inputs: BatchedInputs) -> Trajectory:
        """The whole rollout of ``inputs``."""
        ...

    def stream(self, inputs: BatchedInputs, chunk: int) -> Iterator[Trajectory]:
        """The rollout in consecutive pieces of ``chunk`` steps that :func:`concat` joins to
        :meth:`rollout`'s, bit for bit."""
        ...

    def resync(self, inputs: BatchedInputs, reference: Trajectory, every: int = 1) -> Trajectory:
        """The engine restarted from ``reference``'s state every ``every`` steps (record t: after
        step t from the reference state after step ``every * floor(t / every) - 1``)."""
        ...

    def batch_cap(self) -> int:
        """Members a sweep should give the engine at once."""
        ...

    def split(self, batch: int) -> int:
        """Devices a batch of ``batch`` members is split over (1: not split)."""
        ...

    def compile_ahead(self, inputs: BatchedInputs, chunk: int) -> None:
        """Prepares what :meth:`stream` of ``inputs`` will run (best effort; may do nothing)."""
        ...

    def forward(self, m: mujoco.MjModel, d: mujoco.MjData, fields: tuple[str, ...]) -> Forward:
        """The engine's forward from C's state ``d`` (``d`` unchanged), read back on the host:
        ``fields`` by MjData name, the mass matrix, the contacts (for the drill-down)."""
        ...


class Streaming:
    """What an engine that steps on the host gets for free: :meth:`rollout` is its joined
    :meth:`stream`, no cap on the batch, no split, nothing to compile ahead."""

    def stream(self, inputs: BatchedInputs, chunk: int) -> Iterator[Trajectory]:
        raise NotImplementedError

    def rollout(self, inputs: BatchedInputs) -> Trajectory:
        return concat(list(self.stream(inputs, inputs.steps)))

    def batch_cap(self) -> int:
        return 1 << 30

    def split(self, batch: int) -> int:
        return 1

    def compile_ahead(self, inputs: BatchedInputs, chunk: int) -> None:
        """Nothing ahead (C has nothing to compile; Warp compiles its kernels on the first step,
        once per kernel, cached)."""


def first_true(mask: np.ndarray) -> np.ndarray:
    """(B,) index of the first True along axis 1 of a (B, T) mask, -1 if none."""
    return np.where(mask.any(axis=1), mask.argmax(axis=1), -1)


def concat(pieces: list[Trajectory]) -> Trajectory:
    """One trajectory from consecutive pieces (as the engines' ``stream`` yields them)."""
    if len(pieces) == 1:
        return pieces[0]
    fields = {f.name: np.concatenate([getattr(p, f.name) for p in pieces], axis=1)
              for f in dataclasses.fields(Trajectory) if f.name != "diverged_at"}
    return Trajectory(**fields, diverged_at=first_diverged([p.diverged_at for p in pieces]))


def shifted(diverged_at: np.ndarray | jax.Array, start: int) -> np.ndarray:
    """A piece's ``diverged_at`` (steps within the piece, -1 if none) counted from the rollout's start."""
    return np.where(diverged_at >= 0, diverged_at + start, -1)


def first_diverged(diverged_at: list[np.ndarray | jax.Array]) -> np.ndarray:
    """(B,) the first non-negative ``diverged_at`` of consecutive pieces, -1 if none."""
    out = np.asarray(diverged_at[0])
    for later in diverged_at[1:]:
        out = np.where(out >= 0, out, later)
    return out




def resync_blocks(inputs: BatchedInputs, reference: Trajectory, every: int
                  ) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray]:
    """Where an engine restarts when re-synchronised to ``reference`` every ``every`` steps
    (:meth:`Engine.resync`): S = ceil(T / every) blocks, block s starting from the reference's
    state after step ``s * every - 1`` (the initial state for s = 0).

    Returns ``(states, ctrl, starts)``: ``states`` maps qpos, qvel, act and time to (B, S, ...)
    restart states (time 0 at the initial state); ``ctrl`` is (B, S, every, nu), the controls
    of each block, zero past step T; ``starts`` is (S,), each block's first step."""
    B, T = inputs.batch, inputs.steps
    S = -(-T // every)
    starts = np.arange(S) * every
    initial = dict(qpos=inputs.qpos, qvel=inputs.qvel, act=inputs.act, time=np.zeros(B))
    states = {field: np.concatenate([np.asarray(x)[:, None], np.asarray(getattr(reference, field))], axis=1)[:, starts]
              for field, x in initial.items()}
    ctrl = np.zeros((B, S * every, inputs.ctrl.shape[2]))
    ctrl[:, :T] = inputs.ctrl
    return states, ctrl.reshape(B, S, every, -1), starts
