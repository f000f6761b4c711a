"""Behaviour statistics of one rollout, in jax.numpy: speeds and path of a position track, energy drift.

Public through :mod:`mjxdiff.metrics` (:func:`~mjxdiff.metrics.behaviour_stats`,
:func:`~mjxdiff.metrics.energy_drift`, ...), which imports this module on first use; the
conventions are that module's: time on the leading axis, pure ``jax.numpy``, ``jax.jit``-able,
float32 and float64 alike. Like it, this module imports only jax and the standard library.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

__all__ = ["BehaviourStats", "behaviour_stats", "energy_drift", "energy_drift_from"]


def _as_float(x: Any) -> jax.Array:
    """Returns ``x`` as a jax array with a floating dtype (ints/bools promoted); as in
    :mod:`mjxdiff.metrics`, which cannot import it from here (it imports no other module of mjxdiff)."""
    x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.result_type(float))
    return x


class BehaviourStats(NamedTuple):
    """Summary of a position track (a pytree; see :func:`behaviour_stats`).

    Attributes:
      mean_speed: mean of per-step speeds (units/s).
      max_speed: max of per-step speeds (units/s).
      distance: path length sum_t ||pos[t+1] - pos[t]|| (units).
      displacement: ||pos[-1] - pos[0]|| (units).
      path_efficiency: displacement / distance in [0, 1]; 1 when distance == 0.
    """

    mean_speed: jax.Array
    max_speed: jax.Array
    distance: jax.Array
    displacement: jax.Array
    path_efficiency: jax.Array


def behaviour_stats(pos: jax.Array, dt: float | jax.Array) -> BehaviourStats:
    """Speed and path statistics of a position track.

    ``speed_t = ||pos[t+1] - pos[t]|| / dt`` for t in [0, T-1),
    ``distance = sum_t ||pos[t+1] - pos[t]||``,
    ``displacement = ||pos[-1] - pos[0]||``,
    ``path_efficiency = displacement / distance`` (1.0 if distance == 0).

    Args:
      pos: (T, k) positions (e.g. a body's xpos, k=3, in m), T >= 2.
      dt: time between samples in s.

    Returns:
      :class:`BehaviourStats` of scalars.

    Example:
      >>> s = behaviour_stats(jnp.array([[0., 0.], [3., 4.], [6., 8.]]), 0.5)
      >>> float(s.mean_speed), float(s.distance), float(s.path_efficiency)
      (10.0, 10.0, 1.0)
    """
    pos = _as_float(pos)
    if pos.ndim != 2 or pos.shape[0] < 2:
        raise ValueError(f"pos must have shape (T>=2, k), got {pos.shape}")
    step = jnp.linalg.norm(jnp.diff(pos, axis=0), axis=-1)
    speed = step / jnp.asarray(dt, pos.dtype)
    distance = jnp.sum(step)
    displacement = jnp.linalg.norm(pos[-1] - pos[0])
    moved = distance > 0
    efficiency = jnp.where(moved, displacement / jnp.where(moved, distance, 1),
                           1.0).astype(pos.dtype)
    return BehaviourStats(
        mean_speed=jnp.mean(speed),
        max_speed=jnp.max(speed),
        distance=distance,
        displacement=displacement,
        path_efficiency=efficiency,
    )


def energy_drift(energy: jax.Array) -> jax.Array:
    """Relative drift of total mechanical energy over a rollout.

    ``total_t = energy[t, 0] + energy[t, 1]`` (potential + kinetic, as MuJoCo's
    ``d.energy`` with the energy flag enabled), and

      drift = (total[-1] - total[0]) / max(|total[0]|, mean_t |total_t|, tiny)

    with ``tiny = finfo(dtype).tiny``.

    Args:
      energy: (T, 2) potential and kinetic energy (J).

    Returns:
      dimensionless scalar; 0 for perfect conservation.

    Example:
      >>> float(energy_drift(jnp.array([[1., 1.], [0.5, 1.], [1., 1.5]])))
      0.25
    """
    energy = _as_float(energy)
    total = jnp.sum(energy, axis=-1)
    return energy_drift_from(total[0], total[-1], jnp.mean(jnp.abs(total)))


def energy_drift_from(first: ArrayLike, last: ArrayLike,
                      mean_abs: ArrayLike) -> jax.Array:
    """:func:`energy_drift` from running values, for rollouts seen in pieces.

    ``(last - first) / max(|first|, mean_abs, tiny)`` with ``first``/``last``
    the first and last total energy (J) and ``mean_abs`` the mean of |total|
    over the rollout. Shapes broadcast (e.g. (B,) per member).

    Example:
      >>> float(energy_drift_from(2.0, 2.5, 2.0))
      0.25
    """
    first, last, mean_abs = (_as_float(x) for x in (first, last, mean_abs))
    tiny = jnp.finfo(first.dtype).tiny
    return (last - first) / jnp.maximum(jnp.maximum(jnp.abs(first), mean_abs), tiny)
