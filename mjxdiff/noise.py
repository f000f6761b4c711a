"""Noise floor: how fast MuJoCo C diverges from itself under rounding-level perturbations.

Two simulators that agree to the last bit at step 1 can part ways after a few
hundred steps of a chaotic system from rounding alone. To tell that apart from
a real discrepancy, each scenario's C rollout is repeated from initial states
perturbed by a few ulps of the compared precision; the per-member, per-step
self-divergence (measured with the same metrics as MJX-vs-C) grows like
``delta * exp(lambda t)`` on chaotic systems and stays at rounding level on
calm ones. The envelope an MJX error is judged against is

    envelope_i(t) = margin * max_{s <= t} self_divergence_i(s)

(a running maximum, so that a chance zero crossing of the self-divergence does
not close the envelope), floored by the scenario's fixed tolerance.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from mjxdiff import metrics
from mjxdiff.engines import CEngine, Trajectory
from mjxdiff.inputs import BatchedInputs

__all__ = ["EPS", "NoiseFloor", "noise_floor", "perturb"]

#: Unit roundoff of each precision MJX can run in.
EPS = {"float64": float(np.finfo(np.float64).eps), "float32": float(np.finfo(np.float32).eps)}
#: Perturbation size, in units of the precision's eps (relative to |x|, absolute below 1).
ULPS = 4.0
#: How far above the self-divergence an MJX error may sit and still count as rounding.
MARGIN = 1e3


@dataclasses.dataclass(frozen=True)
class NoiseFloor:
    """Self-divergence of C under ulp-level perturbations, per member and step.

    Attributes:
      self_divergence: field -> (B, T) max-over-components error of the perturbed
        C rollout against the reference C rollout (same units as the MJX errors).
      contact_fraction: (B,) fraction of steps whose contact count changed.
      rate: field -> finite-time Lyapunov-style growth rate of the batch-max
        self-divergence, 1/s.
      margin: envelope factor over the running max of the self-divergence.
    """

    self_divergence: dict[str, np.ndarray]
    contact_fraction: np.ndarray
    rate: dict[str, float]
    margin: float = MARGIN

    def envelope(self, field: str) -> np.ndarray:
        """(B, T) the envelope of ``field``: margin x running max of the self-divergence."""
        return self.margin * np.maximum.accumulate(self.self_divergence[field], axis=1)


def perturb(inputs: BatchedInputs, precision: str) -> BatchedInputs:
    """``inputs`` with ``qpos``/``qvel`` moved by ``ULPS`` units of roundoff, random sign.

    delta = ULPS * eps * max(|x|, 1) for each component; the signs of member
    i are drawn from a generator seeded by (seed, member id), so a member
    replayed alone is perturbed the same way.
    """
    eps = ULPS * EPS[precision]
    rngs = [np.random.default_rng([inputs.seed, int(i)]) for i in inputs.ids]

    def move(x: np.ndarray) -> np.ndarray:
        signs = np.stack([rng.choice([-1.0, 1.0], x.shape[1:]) for rng in rngs])
        return x + signs * eps * np.maximum(np.abs(x), 1.0)

    return dataclasses.replace(inputs, qpos=move(inputs.qpos), qvel=move(inputs.qvel))


@jax.jit
def _self_divergence_fields(a: Trajectory, b: Trajectory, layout: metrics.QposLayout, rf_mask: jax.Array):
    def one(qa, qb, va, vb, aa, ab, sa, sb):
        sens = metrics.sensor_error(sa, sb, rf_mask) / jnp.maximum(1.0, jnp.abs(sb))
        reduce = lambda e: jnp.max(e, axis=1, initial=0.0)
        return dict(qpos=reduce(metrics.qpos_error(qa, qb, layout)), qvel=reduce(metrics.qvel_error(va, vb)),
                    act=reduce(jnp.abs(aa - ab)), sensordata=reduce(sens))

    return jax.vmap(one)(a.qpos, b.qpos, a.qvel, b.qvel, a.act, b.act, a.sensordata, b.sensordata)


def noise_floor(m: mujoco.MjModel, inputs: BatchedInputs, reference: Trajectory, precision: str,
                rf_mask: np.ndarray, c_engine: CEngine | None = None, margin: float = MARGIN) -> NoiseFloor:
    """Runs C once more from perturbed initial states and measures the divergence from ``reference``."""
    perturbed = (c_engine or CEngine()).rollout(perturb(inputs, precision))
    div = jax.tree.map(np.asarray, _self_divergence_fields(perturbed, reference, metrics.qpos_layout(m),
                                                           jnp.asarray(rf_mask)))
    # a perturbed member that blew up is all envelope: nothing can be judged after that step
    blown = np.arange(inputs.steps)[None, :] >= np.where(perturbed.diverged_at >= 0, perturbed.diverged_at,
                                                          inputs.steps)[:, None]
    div = {k: np.where(blown | ~np.isfinite(v), np.inf, v) for k, v in div.items()}
    dt = float(m.opt.timestep)
    rate = {k: float(metrics.error_growth(jnp.asarray(np.where(np.isfinite(v), v, 0).max(axis=0)), dt).rate)
            for k, v in div.items()}
    contacts = (perturbed.ncon != reference.ncon).mean(axis=1)
    return NoiseFloor(self_divergence=div, contact_fraction=contacts, rate=rate, margin=margin)
