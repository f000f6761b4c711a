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

A model's solver settings allow a second kind of freedom: the constraint
solver may stop anywhere within its tolerance (or at its iteration cap), and
chaos amplifies where it stopped. Rounding-perturbed reruns cannot show this
(both stop at the same iteration). The **solver floor** is C against itself
with the solver converged (:func:`converge_solver`), with the envelope

    solver_envelope_i(t) = SOLVER_MARGIN * max_{s <= t} |C_i(t) - C_converged_i(t)|

The sweep consults it only for a failing scenario whose drill-down starts in
the constraint or acceleration stage, or finds every forward stage agreeing (the
step's own constraint solves, e.g. RK4's four; see :func:`mjxdiff.runner.followup.solver_floor`); each
field then reports which bound held it (:data:`FLOORS`).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from mjxdiff.input.precision import THRESHOLDS, Precision
from mjxdiff import metrics
from mjxdiff.compat import jit_for_few_calls
from mjxdiff.engine import pairs
from mjxdiff.engine.trajectory import Trajectory
from mjxdiff.input.inputs import BatchedInputs, roundoff_moved

__all__ = ["EPS", "FLOORS", "SOLVER_MARGIN", "NoiseFloor", "combine", "converge_solver", "converged",
           "has_constraints", "noise_floor", "perturb", "STEP_JITTER"]

#: Unit roundoff of each precision MJX can run in.
EPS = {p: t.eps for p, t in THRESHOLDS.items()}
#: Perturbation size, in units of the precision's eps (relative to |x|, absolute below 1).
ULPS = 4.0
#: Relative size of the move C's perturbed rerun takes after every step (:meth:`mjxdiff.engine.engines.CEngine.stream`'s
#: ``jitter``), per precision under test. float32: MuJoCo's parity method's shadow of C, whose state
#: is rounded as a float32 engine's would be at every step, so that a contact or a tendon's wrap
#: that float32 rounding alone decides shows in C's own spread (measured on the bundled scenarios,
#: ``--precision float32``: docs/explanation/float64.md). float64: none, the rerun is perturbed
#: at its start only; float64 rounding is what C itself does.
STEP_JITTER: dict[Precision, float] = {"float64": 0.0, "float32": ULPS * EPS["float32"]}
#: How far above the self-divergence an MJX error may sit and still count as rounding.
MARGIN = 1e3
#: How far above C's divergence from its converged self an MJX error may sit and still count as
#: solver freedom. Small: both engines run the same solver settings, so MJX's truncation is of
#: the size of C's (measured: MJX within 1e-13 of C where C's own freedom reached 3.6e-3).
SOLVER_MARGIN = 10.0
#: What bounded a field where it came closest to its bound: the fixed tolerance, the rounding
#: envelope (:class:`NoiseFloor` of :func:`perturb`), or the solver floor (of :func:`converged`).
FLOORS = ("tolerance", "rounding", "solver")


class NoiseFloor:
    """Self-divergence of C under ulp-level perturbations, followed piece by piece.

    Feed it pieces of the perturbed and the reference C rollout
    (:meth:`update`, the same pieces the :class:`~mjxdiff.compare.verdict.Judge`
    gets); each call returns that piece's envelope. Only (B,) running values
    and a (T,) batch-max series per field are kept. Each member's pieces
    must come in order from step 0; members never fed (the sweep computes the
    floor only where errors exceed the fixed tolerances) count as never
    diverging from themselves and are left out of :attr:`rate`.

    Args:
      batch, steps: B members and T steps in all.
      margin: envelope factor over the running max of the self-divergence.
    """

    def __init__(self, m: mujoco.MjModel, rf_mask: np.ndarray, batch: int, steps: int, margin: float = MARGIN):
        self.margin, self.steps, self.batch = margin, steps, batch
        self.dt = float(m.opt.timestep)
        self._layout, self._rf_mask = metrics.qpos_layout(m), jnp.asarray(rf_mask)
        self._running: dict[str, np.ndarray] = {}  # field -> (B,) running max so far
        self._batch_max: dict[str, np.ndarray] = {}  # field -> (T,)
        self._blown = np.zeros(batch, bool)  # the perturbed rerun has blown up
        self._contact_changes = np.zeros(batch)
        self.fed = np.zeros(batch, bool)  # members whose perturbed rerun was fed

    def update(self, perturbed: Trajectory, reference: Trajectory, start: int = 0,
               members: np.ndarray | slice = slice(None)) -> dict[str, np.ndarray]:
        """The envelope of each field over this piece, (b, K): margin x running max of the self-divergence."""
        members = np.arange(self.batch)[members]
        K = reference.time.shape[1]
        div = jax.tree.map(np.asarray, _self_divergence_fields(perturbed, reference, self._layout, self._rf_mask))
        # a perturbed member that blew up is all envelope: nothing can be judged after that step
        at = np.where(perturbed.diverged_at >= 0, perturbed.diverged_at - start, K)
        blown = self._blown[members, None] | (np.arange(K)[None, :] >= at[:, None])
        self._blown[members] = blown[:, -1]
        envelope = {}
        for key, v in div.items():
            v = np.where(blown | ~np.isfinite(v), np.inf, v)
            series = self._batch_max.setdefault(key, np.zeros(self.steps))
            series[start:start + K] = np.maximum(series[start:start + K], np.where(np.isfinite(v), v, 0).max(axis=0))
            running = self._running.setdefault(key, np.zeros(self.batch))
            piece = np.maximum(np.maximum.accumulate(v, axis=1), running[members, None])
            running[members] = piece[:, -1]
            envelope[key] = self.margin * piece
        self._contact_changes[members] += pairs.mismatch(perturbed.pairs, reference.pairs).sum(axis=1)
        self.fed[members] = True
        return envelope

    @property
    def contact_fraction(self) -> np.ndarray:
        """(B,) fraction of the steps where some geom pair's count of firm contacts changed
        (:mod:`mjxdiff.engine.pairs`; a grazing contact's change is not counted)."""
        return self._contact_changes / max(self.steps, 1)

    @property
    def rate(self) -> dict[str, float]:
        """Field -> finite-time Lyapunov-style growth rate of the batch-max self-divergence, 1/s
        (over the members fed; an empty dict when none was)."""
        if not self.fed.any():
            return {}
        return {k: float(fit_growth(jnp.asarray(v), self.dt).rate) for k, v in self._batch_max.items()}


def perturb(inputs: BatchedInputs, precision: Precision) -> BatchedInputs:
    """``inputs`` with ``qpos``/``qvel`` moved by ``ULPS`` units of roundoff, random sign.

    delta = ULPS * eps * max(|x|, 1) for each component; the signs of member
    i are drawn from a generator seeded by (seed, member id), so a member
    replayed alone is perturbed the same way.
    """
    eps = ULPS * EPS[precision]
    rngs = [np.random.default_rng([inputs.seed, int(i)]) for i in inputs.ids]

    def move(x: np.ndarray) -> np.ndarray:
        signs = np.stack([rng.choice([-1.0, 1.0], x.shape[1:]) for rng in rngs])
        return roundoff_moved(x, signs, eps)

    return dataclasses.replace(inputs, qpos=move(inputs.qpos), qvel=move(inputs.qvel))


def converge_solver(m: mujoco.MjModel) -> None:
    """Edits ``m`` in place so that its constraint solver converges: 200 iterations, 100
    line-search iterations, tolerance 1e-14."""
    m.opt.iterations, m.opt.ls_iterations, m.opt.tolerance = 200, 100, 1e-14


def converged(inputs: BatchedInputs) -> BatchedInputs:
    """``inputs`` with every member's solver converged (:func:`converge_solver`): the rerun
    whose divergence from the reference is the solver floor."""
    return inputs.edit_models(converge_solver)


def has_constraints(m: mujoco.MjModel) -> bool:
    """Whether the constraint solver can have work: contacts between geoms that may collide,
    limits, equalities or friction loss, with constraints enabled."""
    if m.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_CONSTRAINT):
        return False
    colliding = (m.geom_contype | m.geom_conaffinity) != 0
    contacts = m.npair > 0 or (colliding.sum() > 1
                               and not m.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_CONTACT))
    return bool(contacts or m.neq or m.jnt_limited.any() or m.tendon_limited.any() or m.dof_frictionloss.any()
                or m.tendon_frictionloss.any())


def combine(rounding: dict[str, np.ndarray], solver: dict[str, np.ndarray] | None
            ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray] | None]:
    """The envelope of both floors, field -> (b, K) elementwise max, and which one it came
    from (index into :data:`FLOORS`: 1 rounding, 2 solver); ``(rounding, None)`` without a solver floor."""
    if solver is None:
        return rounding, None
    envelope = {k: np.maximum(v, solver[k]) for k, v in rounding.items()}
    source = {k: np.where(solver[k] > v, 2, 1) for k, v in rounding.items()}
    return envelope, source


#: :func:`mjxdiff.metrics.error_growth` compiled quickly (:func:`~mjxdiff.compat.jit_for_few_calls`):
#: a sweep fits a few per scenario, each of its own length.
fit_growth = jit_for_few_calls(lambda err, dt: metrics.error_growth(err, dt))


@jit_for_few_calls
def _self_divergence_fields(a: Trajectory, b: Trajectory, layout: metrics.QposLayout, rf_mask: jax.Array):
    """(B, T) worst component of each judged field of :func:`metrics.trajectory_errors`:
    the same errors the verdict computes for MJX against C."""
    errors = jax.vmap(metrics.trajectory_errors, in_axes=(0, 0, None, None))(a, b, layout, rf_mask)
    return {key: jnp.max(errors[key], axis=2, initial=0.0) for key in ("qpos", "qvel", "act", "sensordata")}


def noise_floor(m: mujoco.MjModel, perturbed: Trajectory, reference: Trajectory, rf_mask: np.ndarray,
                margin: float = MARGIN) -> tuple[NoiseFloor, dict[str, np.ndarray]]:
    """The noise floor of whole trajectories: (floor, field -> (B, T) envelope)."""
    floor = NoiseFloor(m, rf_mask, *reference.time.shape, margin=margin)
    return floor, floor.update(perturbed, reference)
