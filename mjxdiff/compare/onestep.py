"""The one-step check: MJX put in C's exact state and stepped once, against C stepped once from the
same state, with a converged solver in both. Chaos cannot amplify a one-step difference, and a
solver stopped after one iteration cannot hide one, so where a rollout's pass was weak (its bound
as large as the motion: :attr:`mjxdiff.compare.verdict.ScenarioResult.weak`) this check is still sharp.

States are taken along C's own rollout (:func:`sample_steps`): the first steps, evenly spaced
ones, the step with the most contacts and the fastest one. Every (member, state) pair becomes one
member of a one-step batch (:func:`one_step_inputs`), so one compiled step serves them all. The
bound of each pair is C's own: ``max(tolerance, ROUNDING_FACTOR x |C(x) - C(x + 4 ulps)|)``, the
per-step analogue of the rollout's chaos envelope.

The same states tell whether the model's own solver settings converge: C stepped once as
configured against C stepped once converged, beyond the same bound, means they do not (a
speed-tuned robot's one iteration). The sweep then runs the converged twin
(:func:`mjxdiff.runner.followup._twin`) and, with ``evidence``, MJX's truncated step is compared with C's.
Both engines start each step from a cold solver (no warm start) at time 0 and the scenario's
mocap poses; a converged solve does not depend on its starting point.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import jax
import numpy as np

from mjxdiff.input.precision import Precision
from mjxdiff import metrics
from mjxdiff.engine.trajectory import Engine, Trajectory
from mjxdiff.input.inputs import BatchedInputs
from mjxdiff.input.scenario import Tolerances
from mjxdiff.compare.noise import converged, perturb
from mjxdiff.compare.verdict import WEAK_BOUND, component_elements, describe, error_series, rangefinder_mask

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


def one_step_inputs(inputs: BatchedInputs, traj_c: Trajectory, steps: np.ndarray,
                    converge: bool = True) -> BatchedInputs:
    """One member per (member, sampled state), in member-major order, each starting from C's state
    after record ``j`` with the control of step ``j + 1``, for one step, with a converged solver
    (``converge=False``: the model's own solver settings)."""
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
    return converged(one) if converge else one


def _per_pair(a: Trajectory, b: Trajectory, layout, mask) -> dict[str, np.ndarray]:
    """Field -> (P, n) errors of one-step pairs ``a`` against ``b`` (the step's only record)."""
    err = jax.tree.map(np.asarray, error_series(a, b, layout, jax.numpy.asarray(mask)))
    return {f: err[f][:, 0] for f in FIELDS}


def _worst(e: np.ndarray) -> np.ndarray:
    """(P,) worst component of (P, n) errors, non-finite as inf."""
    return np.where(np.isfinite(e), e, np.inf).max(axis=1, initial=0.0)


def _pair_bound(tol: Tolerances, field: str, own: np.ndarray) -> np.ndarray:
    """(P,) bound of each pair: max(tolerance, ROUNDING_FACTOR x C's own worst difference under a
    4-ulp nudge, ``own`` (P, n))."""
    return np.maximum(getattr(tol, field), ROUNDING_FACTOR * np.nan_to_num(_worst(own), posinf=0.0))


def _first_record(traj: Trajectory) -> Trajectory:
    """The first step of a rollout, as a one-step Trajectory."""
    first = jax.tree.map(lambda a: a[:, :1] if np.ndim(a) >= 2 else a, traj)
    return dataclasses.replace(first, diverged_at=np.where(np.asarray(traj.diverged_at) == 0, 0, -1))


def _rows(traj: Trajectory, rows: np.ndarray) -> Trajectory:
    return jax.tree.map(lambda a: np.asarray(a)[rows], traj)


def _through_rollout(inputs: BatchedInputs, configured: BatchedInputs, engine, reuse, S: int):
    """MJX's step as configured from one sampled state per member of the sweep's first member
    group, through the sweep's own compiled rollout (``engine.first_piece``: no compile of its
    own). Returns (pair rows into ``configured``, the one-step Trajectory)."""
    group, chunk = reuse
    base = inputs.members(group)
    row_of = {int(i): r for r, i in enumerate(inputs.ids)}
    rows = np.array([row_of[int(i)] * S + k % S for k, i in enumerate(base.ids)])
    ctrl = np.zeros_like(np.asarray(base.ctrl))
    ctrl[:, 0] = np.asarray(configured.ctrl)[rows, 0]
    pairs = dataclasses.replace(base, qpos=np.asarray(configured.qpos)[rows], qvel=np.asarray(configured.qvel)[rows],
                                act=np.asarray(configured.act)[rows], ctrl=ctrl)
    return rows, _first_record(engine.first_piece(pairs, chunk, steps=1))


def _c_steps(c_engine: Engine, one: BatchedInputs, configured: BatchedInputs, precision: Precision):
    """C's one step from every pair, in one rollout: (converged, converged from the 4-ulp nudged
    state, as configured, as configured from the nudged state), each a one-step Trajectory."""
    P = one.batch
    batches = [one, perturb(one, precision), configured, perturb(configured, precision)]
    joined = c_engine.rollout(functools.reduce(BatchedInputs.concat, batches))
    return tuple(jax.tree.map(lambda a, i=i: a[i * P:(i + 1) * P], joined) for i in range(4))


def _solver(tol: Tolerances, own: dict[str, np.ndarray], trunc: dict[str, np.ndarray],
            healthy: np.ndarray) -> dict[str, Any]:
    """Whether the model's own solver settings converge: ``ratio`` the worst |C as configured - C
    converged| (``trunc``) / the pair's bound over healthy pairs and fields, ``field`` where it
    is, ``converged`` whether that ratio is at most 1."""
    solver: dict[str, Any] = dict(converged=True, ratio=0.0, field="")
    for field in FIELDS:
        if trunc[field].shape[-1]:
            bound = _pair_bound(tol, field, own[field])
            t = float(np.where(healthy, _worst(trunc[field]) / bound, 0.0).max())
            if t > solver["ratio"]:
                solver.update(ratio=t, field=field)
    solver["converged"] = solver["ratio"] <= 1.0
    return solver


def _bound_scale(field: str, reference: Trajectory, healthy,
                 bound: np.ndarray) -> tuple[float, float] | None:
    """(tightest, median) over healthy pairs of ``bound`` / RMS of C's values of ``field`` after
    the step (sensor values clipped to 1 in magnitude); None where that RMS is 0."""
    values = np.asarray(getattr(reference, field))[healthy]
    values = np.minimum(np.abs(values), 1.0) if field == "sensordata" else values
    scale = float(np.sqrt(np.mean(np.where(np.isfinite(values), values, 0.0) ** 2)))
    if scale > 0:
        return float(bound[healthy].min() / scale), float(np.median(bound[healthy]) / scale)
    return None


def _judge_pairs(err: dict[str, np.ndarray], own: dict[str, np.ndarray], reference: Trajectory,
                 healthy, tol: Tolerances, elements, member: np.ndarray, step: np.ndarray):
    """The pairs judged field by field: (field -> worst error / bound over healthy pairs,
    field -> :func:`_bound_scale`, the worst pair over fields as a dict of ``field``, ``object``,
    ``element``, ``member``, ``step`` (the step applied, 0-based), ``error``, ``bound``, ``ratio``,
    or None where no field has components). ``member``, ``step``: each pair's member id and record."""
    ratios: dict[str, float] = {}
    scales: dict[str, tuple[float, float]] = {}
    worst = None
    for field in FIELDS:
        e = err[field]
        if e.shape[-1] == 0:
            continue
        per_pair = _worst(e)
        bound = _pair_bound(tol, field, own[field])
        ratio = np.where(healthy, per_pair / bound, 0.0)
        ratios[field] = float(ratio.max())
        scale = _bound_scale(field, reference, healthy, bound)
        if scale is not None:
            scales[field] = scale
        i = int(ratio.argmax())
        if worst is None or ratio[i] > worst["ratio"]:
            comp = int(np.nan_to_num(e[i], nan=np.inf).argmax())
            element = elements[field][comp] if elements.get(field) else None
            worst = dict(field=field, object=describe(element) if element else "", element=element,
                         member=int(member[i]), step=int(step[i]) + 1,
                         error=float(per_pair[i]), bound=float(bound[i]), ratio=float(ratio[i]))
    return ratios, scales, worst


def _as_configured(mjx_cfg: dict[str, np.ndarray], trunc: dict[str, np.ndarray], rows: np.ndarray,
                   ok: np.ndarray) -> dict[str, Any]:
    """Per field, the worst over the pairs ``ok`` of MJX's truncated step against C's
    (``mjx_cfg``: ``error``) and of C's truncated step against its converged one (``trunc`` at
    ``rows``: ``truncation``); ``field`` the one with the largest ``error / truncation``, and
    ``ratio`` that ratio."""
    fields = {}
    for field in FIELDS:
        if trunc[field].shape[-1] == 0:
            continue
        e = float(np.where(ok, _worst(mjx_cfg[field]), 0.0).max())
        t = float(np.where(ok, np.nan_to_num(_worst(trunc[field][rows]), posinf=0.0), 0.0).max())
        fields[field] = dict(error=e, truncation=t)
    key = max(fields, key=lambda f: fields[f]["error"] / max(fields[f]["truncation"], 1e-300))
    return dict(fields=fields, field=key, ratio=fields[key]["error"] / max(fields[key]["truncation"], 1e-300))


def check(m, inputs: BatchedInputs, traj_c: Trajectory, tol: Tolerances, engine: Engine, c_engine: Engine,
          precision: Precision = "float64", states: int = STATES, evidence: bool = False,
          steps: np.ndarray | None = None, reuse: tuple[np.ndarray, int] | None = None) -> dict[str, Any]:
    """The one-step check of ``engine`` (MJX or MJWarp) against ``c_engine`` (C) from states of
    C's rollout ``traj_c`` of ``inputs``, and whether the model's own solver settings converge.

    From every sampled state C steps once with a converged solver and once with the model's own
    settings: where those differ beyond the pair's bound, the settings are **not converged**
    (``solver['converged']`` False; its ``ratio`` the worst |C as configured - C converged| /
    bound, ``field`` where), and ``engine`` steps every pair with a converged solver (one compile
    of a one-step function). Where they converge and ``reuse`` = (member indices of the sweep's
    first group, steps per piece) is given, ``engine`` steps as configured through the sweep's own
    compiled rollout instead (``engine.first_piece``; one state per member of that group, each
    member at another sampled state), judged against C as configured: the same check without a
    compile of its own (``settings`` says which). With ``evidence``, for a model not converged,
    ``engine`` also steps as configured: ``as_configured`` holds, per field, MJX's truncated step
    against C's (``error``), C's truncated step against its converged one (``truncation``), and
    for the field with the largest ``error / truncation`` that ratio (<= 1: MJX's truncation is of
    the size of C's). ``steps``: the record indices to start from (:func:`sample_steps` when None).

    Returns a dict: ``status`` (``pass``, ``fail``, or ``error`` when C itself goes non-finite
    from every state), ``states`` (record indices), ``pairs`` judged, ``settings``, ``solver``,
    ``bound_scale`` (field -> (tightest, median) over pairs of the bound / RMS of C's values after
    the step, as :attr:`mjxdiff.compare.verdict.FieldResult.bound_scale`), ``weak`` (fields whose median
    exceeds :data:`~mjxdiff.compare.verdict.WEAK_BOUND`), and for the worst pair (largest error / bound
    over fields): ``field``, ``object``, ``member``, ``step`` (the step applied, 0-based),
    ``error``, ``bound``, ``ratio``; ``ratios`` the worst ratio per field.
    """
    steps = sample_steps(traj_c, states) if steps is None else np.asarray(steps)
    S = len(steps)
    configured = one_step_inputs(inputs, traj_c, steps, converge=False)
    one = converged(configured)
    P = one.batch
    c, nudged, c_cfg, nudged_cfg = _c_steps(c_engine, one, configured, precision)
    layout, mask = metrics.qpos_layout(m), rangefinder_mask(m)
    member_of, step_of = np.repeat(np.asarray(inputs.ids), S), np.tile(steps, inputs.batch)
    out: dict[str, Any] = dict(states=[int(j) for j in steps], ratios={}, bound_scale={})
    healthy = (c.diverged_at < 0) & (nudged.diverged_at < 0)
    if not healthy.any():
        return dict(out, pairs=0, status="error", message="MuJoCo C goes non-finite from every sampled state")
    own, trunc = _per_pair(nudged, c, layout, mask), _per_pair(c_cfg, c, layout, mask)
    solver = _solver(tol, own, trunc, healthy)
    rows = np.arange(P)
    through = reuse is not None and hasattr(engine, "first_piece")
    if solver["converged"] and through:
        rows, x = _through_rollout(inputs, configured, engine, reuse, S)
        reference, nudged_ref, settings = _rows(c_cfg, rows), _rows(nudged_cfg, rows), "as configured (converged)"
    else:
        x, reference, nudged_ref, settings = engine.rollout(one), c, nudged, "converged"
    err, own = _per_pair(x, reference, layout, mask), _per_pair(nudged_ref, reference, layout, mask)
    healthy = (reference.diverged_at < 0) & (nudged_ref.diverged_at < 0)
    out.update(pairs=int(healthy.sum()), settings=settings)
    ratios, scales, worst = _judge_pairs(err, own, reference, healthy, tol, component_elements(m, layout),
                                         member_of[rows], step_of[rows])
    out.update(ratios=ratios, bound_scale=scales)
    out.update(worst or dict(ratio=0.0), solver=solver,
               weak=[f for f, (_, median) in out["bound_scale"].items() if median > WEAK_BOUND])
    out["status"] = "fail" if out["ratio"] > 1.0 else "pass"
    if evidence and not solver["converged"]:
        if through:
            rows, x_cfg = _through_rollout(inputs, configured, engine, reuse, S)
        else:
            rows, x_cfg = np.arange(P), engine.rollout(configured)
        ok = (np.asarray(c.diverged_at)[rows] < 0) & (np.asarray(nudged.diverged_at)[rows] < 0)
        out["as_configured"] = _as_configured(_per_pair(x_cfg, _rows(c_cfg, rows), layout, mask), trunc, rows, ok)
    return out
