"""The one-step check: MJX put in C's exact state and stepped once, against C stepped once from the
same state, with a converged solver in both. Chaos cannot amplify a one-step difference, and a
solver stopped after one iteration cannot hide one, so where a rollout's pass was weak (its bound
as large as the motion: :attr:`mjxdiff.verdict.ScenarioResult.weak`) this check is still sharp.

States are taken along C's own rollout (:func:`sample_steps`): the first steps, evenly spaced
ones, the step with the most contacts and the fastest one. Every (member, state) pair becomes one
member of a one-step batch (:func:`one_step_inputs`), so one compiled step serves them all. The
bound of each pair is C's own: ``max(tolerance, ROUNDING_FACTOR x |C(x) - C(x + 4 ulps)|)``, the
per-step analogue of the rollout's chaos envelope.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import numpy as np

from mjxdiff import metrics
from mjxdiff.engines import Trajectory
from mjxdiff.inputs import BatchedInputs
from mjxdiff.scenario import Tolerances
from mjxdiff.noise import converged, perturb
from mjxdiff.verdict import component_objects, error_series, rangefinder_mask

__all__ = ["FIELDS", "ROUNDING_FACTOR", "STATES", "check", "one_step_inputs", "sample_steps"]

#: States sampled per member.
STATES = 8
#: A one-step difference within this many times C's own difference under a 4-ulp nudge of the
#: state is rounding (the rollout's chaos envelope uses the same factor).
ROUNDING_FACTOR = 1000.0
#: Fields compared after the step.
FIELDS = ("qpos", "qvel", "act", "sensordata")


def sample_steps(traj_c: Trajectory, states: int = STATES) -> np.ndarray:
    """Sorted record indices ``j`` (-1 for the initial state): the check starts from C's state
    after step ``j`` and applies step ``j + 1``. The first three, the step with the most
    contacts, the fastest one (largest batch-max |qvel|), the rest evenly spaced."""
    T = traj_c.qpos.shape[1]
    if T < 2:
        return np.array([-1])
    picks = {-1, 0, 1} & set(range(-1, T - 1))
    with np.errstate(invalid="ignore"):
        picks.add(int(np.nan_to_num(np.asarray(traj_c.ncon, float)).max(axis=0)[:T - 1].argmax()))
        picks.add(int(np.nan_to_num(np.abs(traj_c.qvel)).max(axis=(0, 2))[:T - 1].argmax()))
    spread = np.linspace(2, T - 2, max(states - len(picks), 1)).astype(int)
    picks.update(int(j) for j in spread if 0 <= j <= T - 2)
    return np.array(sorted(picks))


def one_step_inputs(inputs: BatchedInputs, traj_c: Trajectory, steps: np.ndarray) -> BatchedInputs:
    """One member per (member, sampled state), in member-major order, each starting from C's state
    after record ``j`` with the control of step ``j + 1``, for one step, with a converged solver."""
    B, S = inputs.batch, len(steps)
    rows = steps + 1  # index into [initial, record 0, record 1, ...]

    def state(field: str, initial: np.ndarray) -> np.ndarray:
        full = np.concatenate([np.asarray(initial)[:, None], np.asarray(getattr(traj_c, field))], axis=1)
        return full[:, rows].reshape(B * S, *full.shape[2:])

    ctrl = np.asarray(inputs.ctrl)[:, rows].reshape(B * S, 1, -1)
    one = dataclasses.replace(
        inputs, qpos=state("qpos", inputs.qpos), qvel=state("qvel", inputs.qvel), act=state("act", inputs.act),
        ctrl=ctrl, models=tuple(mi for mi in inputs.models for _ in range(S)),
        factors={k: np.repeat(np.asarray(v), S, axis=0) for k, v in inputs.factors.items()},
        member_ids=np.arange(B * S))
    return converged(one)


def check(m, inputs: BatchedInputs, traj_c: Trajectory, tol: Tolerances, engine, c_engine,
          precision: str = "float64", states: int = STATES) -> dict[str, Any]:
    """The one-step check of ``engine`` (MJX or MJWarp) against ``c_engine`` (C) from states of
    C's rollout ``traj_c`` of ``inputs``.

    Returns a dict: ``status`` (``pass``, ``fail``, or ``error`` when C itself goes non-finite
    from every state), ``states`` (record indices), ``pairs`` judged, and for the worst pair
    (largest error / bound over fields): ``field``, ``object``, ``member``, ``step`` (the step
    applied, 0-based), ``error``, ``bound``, ``ratio``; ``ratios`` the worst ratio per field.
    """
    steps = sample_steps(traj_c, states)
    one = one_step_inputs(inputs, traj_c, steps)
    c = c_engine.rollout(one)
    nudged = c_engine.rollout(perturb(one, precision))
    x = engine.rollout(one)
    layout, mask = metrics.qpos_layout(m), rangefinder_mask(m)
    err = jax.tree.map(np.asarray, error_series(x, c, layout, jax.numpy.asarray(mask)))
    own = jax.tree.map(np.asarray, error_series(nudged, c, layout, jax.numpy.asarray(mask)))
    healthy = (c.diverged_at < 0) & (nudged.diverged_at < 0)
    objects = component_objects(m, layout)
    S = len(steps)
    out: dict[str, Any] = dict(states=[int(j) for j in steps], pairs=int(healthy.sum()), ratios={})
    if not healthy.any():
        return dict(out, status="error", message="MuJoCo C goes non-finite from every sampled state")
    worst = None
    for field in FIELDS:
        e = err[field]
        if e.shape[-1] == 0:
            continue
        per_pair = np.where(np.isfinite(e), e, np.inf).max(axis=(1, 2))
        bound = np.maximum(getattr(tol, field), ROUNDING_FACTOR * np.nan_to_num(own[field]).max(axis=(1, 2)))
        ratio = np.where(healthy, per_pair / bound, 0.0)
        out["ratios"][field] = float(ratio.max())
        i = int(ratio.argmax())
        if worst is None or ratio[i] > worst["ratio"]:
            comp = int(np.nan_to_num(e[i, 0], nan=np.inf).argmax())
            worst = dict(field=field, object=objects[field][comp] if objects.get(field) else "",
                         member=int(inputs.ids[i // S]), step=int(steps[i % S]) + 1,
                         error=float(per_pair[i]), bound=float(bound[i]), ratio=float(ratio[i]))
    out.update(worst or dict(ratio=0.0))
    out["status"] = "fail" if out["ratio"] > 1.0 else "pass"
    return out
