"""Closed loop: does a policy behave the same in MJX (brax) as in MuJoCo C?

A policy trained in MJX acts on what the simulator shows it, so small per-step differences
feed back through it. :func:`run` drives the same brax environment (MJX backend) with the
same policy, initial states and policy keys three ways, in float64:

* **MJX**: ``jit(vmap(scan(env.step)))`` over episodes, the policy inside the scan;
* **C**: a :class:`mujoco.batch.Batch` of the environment's ``mj_model`` steps ``n_frames``
  substeps per control step with the policy's action as ``ctrl``; observations, rewards and
  terminations come from the environment's own ``reset``/``step`` code evaluated on C's
  physics (its ``pipeline_init``/``pipeline_step`` replaced by C's state, recorded field by
  field), and the policy is jitted over the batch of C observations;
* **C again** from initial states moved by a few units of roundoff, and, where the model has
  constraints, with a converged solver: the floor, how much C disagrees with itself in
  closed loop.

All engines are streamed in lockstep, :data:`CHUNK` control steps at a time, into per-episode
summaries (:class:`Comparison`), so memory does not grow with the episode length.
:func:`judge` compares per episode (paired): return, length, termination and behaviour
statistics (:class:`Summary`); the MJX-vs-C gaps are judged against C's reruns
(:data:`TEST`). The first control step where the states separate beyond C's own separation
is named, with the joint and observation components that separate first; at C's state there
the sweep's stage drill-down and cause attribution (:func:`attribute`) say why.
"""

from __future__ import annotations

import copy
import dataclasses
from typing import Any, Callable

import mujoco
import numpy as np
from mujoco import mjx
from mjxdiff.compat import jit_for_few_calls

from mjxdiff.input.precision import Precision
from mjxdiff.compare.noise import converge_solver, has_constraints
# the policies and environments (policies), the engines in closed loop (closedloop_streams): public here too
from mjxdiff.tools.closedloop_streams import (CHUNK, Episodes, _keys, c_model, c_stream, mjx_stream, run_c,
                                              run_mjx)
from mjxdiff.tools.policies import PolicyError, _one_line, load_policy, make_env, mjcf_env, resolve_env

__all__ = ["Episodes", "Summary", "Comparison", "PolicyError", "load_policy", "make_env", "mjcf_env", "resolve_env",
           "mjx_stream", "c_stream", "run_mjx", "run_c", "run", "paired", "attribute", "judge", "TEST", "PERTURB_ULPS",
           "CHUNK", "ACCUMULATED", "REMOVES", "c_model"]

#: The statistical test, stated: the paired return gap (MJX - C) per episode, relative to the
#: mean |C return|; a 95% bootstrap CI (2000 resamples) of its mean. FAIL when that CI lies
#: wholly outside the C-vs-C band: ± the largest |paired C-vs-C gap| of any episode, or
#: ``RETURN_FLOOR`` of the return, whichever is larger; or when MJX and C terminate at
#: different steps in more episodes than C does against itself; or when the states separate
#: by more than max(``tol``, 10 x the C-vs-C separation) at some control step, returns agreeing
#: or not. Each behaviour statistic (:class:`Summary`) is tested as the return is, relative to
#: the root mean square of C's values. Effect size: Cohen's d_z (mean paired gap / its
#: standard deviation).
TEST = "95% bootstrap CI of the mean paired return gap outside the C-vs-C band"
RETURN_FLOOR = 1e-3
#: Units of roundoff the C-vs-C rerun moves each initial qpos/qvel component by.
PERTURB_ULPS = 4.0


def _perturbed(x: np.ndarray, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return x + rng.choice([-1.0, 1.0], x.shape) * PERTURB_ULPS * np.finfo(np.float64).eps * np.maximum(np.abs(x), 1.0)


# ----------------------------------------------------------------------------
# streamed summaries


@dataclasses.dataclass(frozen=True)
class Summary:
    """Per-episode outcome of one engine, every array (B,).

    Attributes:
      returns: summed reward up to and including the first ``done``.
      length: control steps up to and including the first ``done`` (T if none).
      terminated: whether the episode reported ``done`` (a fall, for brax's locomotion tasks).
      behaviour: statistic name -> per-episode mean over the steps counted in the return:
        ``|action|`` (mean absolute action component), ``|Δaction|`` (mean absolute change of
        an action component from one step to the next: smoothness), ``|qvel|`` (mean absolute
        joint velocity, rad/s or m/s), and every metric the environment reports in
        ``state.metrics`` (e.g. brax's ``x_velocity``, ``reward_ctrl``; ``success`` where an
        environment defines it).
    """

    returns: np.ndarray
    length: np.ndarray
    terminated: np.ndarray
    behaviour: dict[str, np.ndarray]


@dataclasses.dataclass(frozen=True)
class Comparison:
    """What :func:`run` keeps of a closed-loop run: O(episodes) memory, whatever its length.

    Attributes:
      summaries: engine -> :class:`Summary` (``mjx``, ``c``, ``c_perturbed``, and ``c_solver``
        where the model has constraints).
      separation: engine -> largest |qpos| or |qvel| difference from C over every step.
      obs_separation: engine -> largest observation difference from C.
      first: the first control step where MJX and C separate beyond the floor
        (max(``tol``, 10 x C-vs-C, 10 x converged-solver C-vs-C) at that step), with C's state
        before it, or None.
      tol: the absolute floor of the separation (rad, m, rad/s, m/s).
      steps: control steps per episode.
    """

    summaries: dict[str, Summary]
    separation: dict[str, float]
    obs_separation: dict[str, float]
    first: dict[str, Any] | None
    tol: float
    steps: int


def _separation(a: Episodes, b: Episodes) -> np.ndarray:
    """(B, T) largest |qpos| or |qvel| difference per control step."""
    return np.maximum(np.abs(a.qpos - b.qpos).max(-1, initial=0.0), np.abs(a.qvel - b.qvel).max(-1, initial=0.0))


class _Tally:
    """Folds streamed chunks of every engine into :class:`Comparison` (memory O(episodes))."""

    def __init__(self, m: mujoco.MjModel, names: list[str], tol: float):
        self.m, self.names, self.tol, self.t0 = m, names, tol, 0
        self.sums: dict[str, dict[str, np.ndarray]] = {}
        self.ended: dict[str, np.ndarray] = {}
        self.length: dict[str, np.ndarray] = {}
        self.last_action: dict[str, np.ndarray] = {}
        self.separation = {n: 0.0 for n in names if n != "c"}
        self.obs_separation = dict(self.separation)
        self.first: dict[str, Any] | None = None

    def add(self, chunks: dict[str, Episodes]) -> None:
        for name, e in chunks.items():
            self._behaviour(name, e)
        c = chunks["c"]
        seps = {n: _separation(e, c) for n, e in chunks.items() if n != "c"}
        for n, e in chunks.items():
            if n != "c":
                self.separation[n] = max(self.separation[n], float(seps[n].max(initial=0.0)))
                self.obs_separation[n] = max(self.obs_separation[n], float(np.abs(e.obs - c.obs).max(initial=0.0)))
        floor = np.maximum(self.tol, 10 * seps["c_perturbed"])
        if "c_solver" in seps:
            floor = np.maximum(floor, 10 * seps["c_solver"])
        out = seps["mjx"] > floor
        if self.first is None and out.any():
            steps = np.where(out.any(1), out.argmax(1), out.shape[1])
            episode = int(steps.argmin())
            self.first = self._details(chunks["mjx"], c, episode, int(steps[episode]), seps["mjx"], floor)
        self.t0 += c.qpos.shape[1]

    def _behaviour(self, name: str, e: Episodes) -> None:
        B, K = e.reward.shape[:2]
        if name not in self.sums:
            self.sums[name] = {}
            self.ended[name], self.length[name] = np.zeros(B, bool), np.zeros(B, int)
            self.last_action[name] = e.action[:, 0]
        sums = self.sums[name]
        stats = {"return": e.reward, "|action|": np.abs(e.action).mean(-1),
                 "|Δaction|": np.abs(np.diff(e.action, axis=1, prepend=self.last_action[name][:, None])).mean(-1),
                 "|qvel|": np.abs(e.qvel).mean(-1) if e.qvel.shape[-1] else np.zeros((B, K)),
                 **{k: v for k, v in e.metrics.items() if np.ndim(v) == 2}}
        ended = self.ended[name]
        done = e.done > 0.5
        # a step counts while the episode had not reported done before it
        live = ~(np.cumsum(done, axis=1) - done > 0) & ~ended[:, None]
        for k, v in stats.items():
            sums[k] = sums.get(k, 0.0) + np.where(live, v, 0.0).sum(1)
        self.length[name] = self.length[name] + live.sum(1)
        self.ended[name] = ended | (live & done).any(1)
        self.last_action[name] = e.action[:, -1]

    def _details(self, mj: Episodes, c: Episodes, episode: int, step: int, sep: np.ndarray,
                 floor: np.ndarray) -> dict[str, Any]:
        m = self.m
        dq = np.abs(mj.qpos[episode, step] - c.qpos[episode, step])
        dv = np.abs(mj.qvel[episode, step] - c.qvel[episode, step])
        dof = int(dv.argmax()) if dv.size else 0
        joint = int(m.dof_jntid[dof]) if m.nv else -1
        dobs = np.abs(mj.obs[episode, step] - c.obs[episode, step])  # the observation that step produced
        qpos, qvel, warm = c.state_before(episode, step)
        return dict(episode=episode, step=self.t0 + step, separation=float(sep[episode, step]),
                    floor=float(floor[episode, step]),
                    joint=mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, joint) or f"#{joint}",
                    qpos_error=float(dq.max(initial=0.0)), qvel_error=float(dv.max(initial=0.0)),
                    observation_components=[int(i) for i in np.argsort(-dobs)[:3]],
                    c_state=dict(qpos=qpos.tolist(), qvel=qvel.tolist(),
                                 qacc_warmstart=None if warm is None else warm.tolist(),
                                 ctrl=c.ctrl[episode, step].tolist()))

    def result(self) -> Comparison:
        summaries = {}
        for name, sums in self.sums.items():
            n = np.maximum(self.length[name], 1)
            summaries[name] = Summary(returns=sums["return"], length=self.length[name],
                                      terminated=self.ended[name],
                                      behaviour={k: v / n for k, v in sums.items() if k != "return"})
        return Comparison(summaries, self.separation, self.obs_separation, self.first, self.tol, self.t0)


def run(env: Any, policy: Callable, episodes: int, steps: int, seed: int = 0, only: list[int] | None = None,
        tol: float = 1e-6, chunk: int = CHUNK) -> Comparison:
    """MJX, C, C from perturbed initial states (and C with a converged solver where the model
    has constraints), each ``episodes`` x ``steps`` control steps, same reset and policy keys
    (float64: run under ``jax.enable_x64``), streamed in lockstep ``chunk`` control steps at a
    time. ``only``: run just these episodes of the ``episodes`` (their keys are the same; the
    perturbation of C's rerun is drawn for them alone)."""
    reset_keys, policy_keys = _keys(seed, episodes, steps)
    if only is not None:
        reset_keys, policy_keys = reset_keys[np.asarray(only)], policy_keys[np.asarray(only)]
    first, mjx_chunks = mjx_stream(env, policy, reset_keys, policy_keys, chunk)
    q0, qd0 = np.asarray(first.pipeline_state.qpos), np.asarray(first.pipeline_state.qvel)
    m = c_model(env)
    streams = {"mjx": mjx_chunks,
               "c": c_stream(env, policy, reset_keys, policy_keys, q0, qd0, model=m, chunk=chunk),
               "c_perturbed": c_stream(env, policy, reset_keys, policy_keys, _perturbed(q0, seed),
                                       _perturbed(qd0, seed + 1), model=m, chunk=chunk)}
    if has_constraints(m):  # C with a converged solver: how much the solver's own stopping point moves C
        solved = copy.copy(m)
        converge_solver(solved)
        streams["c_solver"] = c_stream(env, policy, reset_keys, policy_keys, q0, qd0, model=solved, chunk=chunk)
    tally = _Tally(m, list(streams), tol)
    for chunks in zip(*streams.values()):
        tally.add(dict(zip(streams, chunks)))
    return tally.result()


# ----------------------------------------------------------------------------
# the verdict


def _bootstrap_ci(x: np.ndarray, seed: int = 0, resamples: int = 2000) -> tuple[float, float]:
    if len(x) < 2:
        return float(x.mean()), float(x.mean())
    rng = np.random.default_rng(seed)
    means = x[rng.integers(0, len(x), (resamples, len(x)))].mean(1)
    return float(np.quantile(means, 0.025)), float(np.quantile(means, 0.975))


def paired(x_mjx: np.ndarray, x_c: np.ndarray, floors: list[np.ndarray], scale: float,
           seed: int = 0) -> dict[str, Any]:
    """The paired test of :data:`TEST` on one per-episode quantity.

    Args:
      x_mjx, x_c: (B,) the quantity per episode on MJX and on C.
      floors: (B,) the same quantity on C's reruns (perturbed start, converged solver).
      scale: what gaps are relative to (a return's mean |C|).

    Returns:
      ``mean`` and ``ci95`` of the relative paired gap (MJX - C) / scale, ``band`` (the
      largest relative |C rerun - C| of any episode, at least :data:`RETURN_FLOOR`),
      ``effect_size_dz`` (mean / standard deviation of the gaps) and ``out_of_band``.
    """
    scale = max(scale, 1e-12)
    gap = (x_mjx - x_c) / scale
    band = max([RETURN_FLOOR] + [float(np.abs((f - x_c) / scale).max(initial=0.0)) for f in floors])
    lo, hi = _bootstrap_ci(gap, seed)
    sd = float(gap.std(ddof=1)) if len(gap) > 1 else 0.0
    mean = float(gap.mean())
    return dict(mean=mean, ci95=[lo, hi], band=band, out_of_band=bool(lo > band or hi < -band),
                effect_size_dz=mean / sd if sd > 0 else (0.0 if mean == 0 else float("inf")))


def _c_local(m: mujoco.MjModel, state: dict[str, Any], n_frames: int, qpos=None, qvel=None) -> np.ndarray:
    d = mujoco.MjData(m)
    d.qpos[:] = state["qpos"] if qpos is None else qpos
    d.qvel[:] = state["qvel"] if qvel is None else qvel
    if state["qacc_warmstart"] is not None:
        d.qacc_warmstart[:] = state["qacc_warmstart"]
    d.ctrl[:] = state["ctrl"]
    for _ in range(n_frames):
        mujoco.mj_step(m, d)
    return np.concatenate([d.qpos, d.qvel])


def _mjx_local(m: mujoco.MjModel, state: dict[str, Any], n_frames: int) -> np.ndarray:
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:], d.ctrl[:] = state["qpos"], state["qvel"], state["ctrl"]
    if state["qacc_warmstart"] is not None:
        d.qacc_warmstart[:] = state["qacc_warmstart"]
    mx, dx = mjx.put_model(m), mjx.put_data(m, d)
    step = jit_for_few_calls(lambda mx, dx: mjx.step(mx, dx))  # a fresh function: no trace cached under a patched MJX
    for _ in range(n_frames):
        dx = step(mx, dx)
    return np.concatenate([np.asarray(dx.qpos), np.asarray(dx.qvel)])


def _local_floor(m: mujoco.MjModel, state: dict[str, Any], n_frames: int, tol: float, seed: int) -> float:
    """The one-control-step floor at C's state: max(tol, 10 x |C - C from a perturbed state|,
    10 x |C - C with a converged solver|)."""
    c = _c_local(m, state, n_frames)
    q, v = np.asarray(state["qpos"]), np.asarray(state["qvel"])
    floors = [tol, 10 * np.abs(_c_local(m, state, n_frames, _perturbed(q, seed), _perturbed(v, seed + 1)) - c).max()]
    if has_constraints(m):
        solved = copy.copy(m)
        converge_solver(solved)
        floors.append(10 * np.abs(_c_local(solved, state, n_frames) - c).max())
    return float(max(floors))


class _OneControlStep:
    """One control step from C's state at the first separation, under a model (what
    :func:`mjxdiff.compare.diagnose.attribute_cause` edits and reruns)."""

    def __init__(self, m: mujoco.MjModel):
        self.m = m

    def edit_models(self, edit: Callable[[mujoco.MjModel], None]) -> "_OneControlStep":
        m = copy.copy(self.m)
        edit(m)
        return _OneControlStep(m)


#: Cause when one control step from C's state agrees within the floor: the separation grew
#: over earlier steps, through the policy's feedback or the system's own sensitivity.
ACCUMULATED = "accumulated (one control step from C's state agrees within the floor)"


#: An ablation names the cause when it cuts the one-control-step error below the floor or by
#: at least this factor. A discrepancy the ablation leaves in place keeps its size: the
#: ablated step covers the same time (a quarter timestep takes 4 x the substeps), so a wrong
#: force moves the state as much as before.
REMOVES = 10.0


def attribute(m: mujoco.MjModel, first: dict[str, Any], n_frames: int, tol: float = 1e-6,
              seed: int = 0) -> dict[str, Any]:
    """Cause attribution at the first separation: MJX and C take one control step (``n_frames``
    substeps, C's ctrl and warm start) from C's state before it. If they agree within the
    one-step floor (:func:`_local_floor`), the cause is :data:`ACCUMULATED`; otherwise the
    sweep's ablations (:data:`mjxdiff.compare.diagnose.ABLATIONS`) are tried on both engines in order
    and the first that cuts the error below its floor or :data:`REMOVES` x names the cause
    (else :data:`mjxdiff.compare.diagnose.GENUINE`). Returns ``{"cause", "ablation", "local_error",
    "local_floor", "tried"}`` (errors: largest |qpos| or |qvel| difference after the step)."""
    from mjxdiff.compare import diagnose

    state = first["c_state"]

    def gap(mi: mujoco.MjModel) -> float:
        n = max(1, round(n_frames * m.opt.timestep / mi.opt.timestep))  # the same time span
        return float(np.abs(_mjx_local(mi, state, n) - _c_local(mi, state, n)).max())

    try:
        error, floor = gap(m), _local_floor(m, state, n_frames, tol, seed)
        if error <= floor:
            return dict(cause=ACCUMULATED, ablation=None, local_error=error, local_floor=floor, tried=[])

        def passes(x: _OneControlStep, precision: Precision) -> bool:
            n = max(1, round(n_frames * m.opt.timestep / x.m.opt.timestep))
            return gap(x.m) <= max(_local_floor(x.m, state, n, tol, seed), error / REMOVES)

        return dict(diagnose.attribute_cause(passes, _OneControlStep(m), "float64"), local_error=error,
                    local_floor=floor)
    except Exception as e:  # noqa: BLE001 - the verdict stands without its attribution
        return dict(cause=diagnose.UNCLASSIFIED, ablation=None, error=_one_line(e), tried=[])


def _drill(m: mujoco.MjModel, first: dict[str, Any], n_frames: int) -> dict[str, Any]:
    """The sweep's stage drill-down (:func:`mjxdiff.compare.diagnose.drill_down`) substep by substep
    through the first separating control step, C replayed from its state (and solver warm
    start) before it with the ctrl it applied: the first substep where a stage differs."""
    from mjxdiff.compare import diagnose

    state = first["c_state"]
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:], d.ctrl[:] = state["qpos"], state["qvel"], state["ctrl"]
    if state["qacc_warmstart"] is not None:
        d.qacc_warmstart[:] = state["qacc_warmstart"]
    try:
        for k in range(n_frames):
            drill = diagnose.drill_down(m, d.qpos.copy(), d.qvel.copy(), d.act.copy(), d.ctrl.copy(), d.time,
                                        member=first["episode"], step=first["step"],
                                        qacc_warmstart=d.qacc_warmstart.copy())
            if drill.first_stage:
                break
            mujoco.mj_step(m, d)
    except Exception as e:  # noqa: BLE001 - the verdict stands without its drill-down
        return dict(error=_one_line(e))
    return dict(substep=k, first_stage=drill.first_stage, first_field=drill.first_field, object=drill.object,
                contact=drill.contact, fields=[dataclasses.asdict(f) for f in drill.fields])


def judge(m: mujoco.MjModel, comparison: Comparison, seed: int = 0, n_frames: int = 1) -> dict[str, Any]:
    """Paired per-episode comparison of MJX and C against C's reruns (see :data:`TEST`); ``m``
    is the model C stepped (:func:`c_model`), ``n_frames`` its substeps per control step."""
    s = comparison.summaries
    mj, c = s["mjx"], s["c"]
    reruns = [s[k] for k in ("c_perturbed", "c_solver") if k in s]
    ret = paired(mj.returns, c.returns, [r.returns for r in reruns], float(np.abs(c.returns).mean()), seed)
    behaviour = {}
    for k in c.behaviour:
        x = c.behaviour[k]
        behaviour[k] = dict(mjx=float(mj.behaviour[k].mean()), c=float(x.mean()),
                            **paired(mj.behaviour[k], x, [r.behaviour[k] for r in reruns],
                                     float(np.sqrt(np.mean(x ** 2))), seed))
    length_differs = float((mj.length != c.length).mean())
    length_differs_cc = max(float((r.length != c.length).mean()) for r in reruns)
    first = comparison.first
    drifted = sorted(k for k, b in behaviour.items() if b["out_of_band"])
    # behaviour first (what a user sees), then the states: separating beyond C's own floor is
    # a divergence even while returns still agree
    fail = ret["out_of_band"] or bool(drifted) or length_differs > length_differs_cc + 1e-12 or first is not None

    def mean_sd(x):
        return float(x.mean()), float(x.std(ddof=1)) if len(x) > 1 else 0.0

    (rm, rs), (rc, rcs) = mean_sd(mj.returns), mean_sd(c.returns)
    lo, hi = ret["ci95"]
    message = (f"MJX return {rm:.4g} ± {rs:.2g}, C {rc:.4g} ± {rcs:.2g}, paired gap {100 * ret['mean']:+.3g}% "
               f"(95% CI {100 * lo:+.3g}..{100 * hi:+.3g}%), C-vs-C gap ±{100 * ret['band']:.3g}%; episode lengths "
               f"differ in {length_differs:.0%} (C vs C {length_differs_cc:.0%})")
    if drifted:
        message += "; behaviour outside C's band: " + ", ".join(
            f"{k} {100 * behaviour[k]['mean']:+.3g}% (±{100 * behaviour[k]['band']:.3g}%)" for k in drifted)
    message += f": {'FAIL' if fail else 'PASS'}"
    if first is not None:
        message += (f"; first separation at control step {first['step']} of episode {first['episode']}, "
                    f"joint '{first['joint']}' (qvel {first['qvel_error']:.3g} > floor {first['floor']:.3g})")
        first = dict(first, drill_down=_drill(m, first, n_frames),
                     cause=attribute(m, first, n_frames, comparison.tol, seed))
        drill, cause = first["drill_down"], first["cause"]
        if drill.get("first_stage"):
            message += (f"; first stage to differ from C's state there (substep {drill['substep']}): "
                        f"{drill['first_stage']} ({drill['first_field']}, {drill['object']})")
        message += f"; cause: {cause['cause']}" + (f" (passes with {cause['ablation']})" if cause["ablation"] else "")
    gaps = np.abs(mj.returns - c.returns)
    return dict(status="fail" if fail else "pass", message=message, test=TEST,
                returns={k: v.returns.tolist() for k, v in s.items()},
                lengths={k: v.length.tolist() for k, v in s.items()},
                terminated={k: float(v.terminated.mean()) for k, v in s.items()},
                gap={k: v for k, v in ret.items() if k != "out_of_band"},
                behaviour=behaviour, length_differs=length_differs, length_differs_c_vs_c=length_differs_cc,
                separation=dict(max=comparison.separation, observation_max=comparison.obs_separation,
                                tol=comparison.tol),
                worst_episode=int(gaps.argmax()) if gaps.size else 0, first_separation=first)
