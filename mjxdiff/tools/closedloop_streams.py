"""One policy in closed loop on MJX and on MuJoCo C, streamed a chunk of control steps at a time.

:func:`mjx_stream` runs the brax environment on MJX (``jit(vmap(scan(env.step)))``, the policy
inside the scan); :func:`c_stream` steps the environment's ``mj_model`` (:func:`c_model`) in a
:class:`mujoco.batch.Batch`, the environment's own ``reset``/``step`` code evaluated on C's
recorded physics. Each yields :class:`Episodes`; :mod:`mjxdiff.tools.closedloop` compares them
(and exports these names too).
"""

from __future__ import annotations

import copy
import dataclasses
import functools
from typing import Any, Callable, Iterator

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx
from mjxdiff.compat import BALANCED_COMPILE, Batch, data_impl, impl_fields, jit_for_few_calls, with_impl

__all__ = ["CHUNK", "Episodes", "c_model", "mjx_stream", "c_stream", "run_mjx", "run_c"]

#: Control steps per streamed chunk: memory holds episodes x CHUNK steps of each engine, and
#: the summaries (O(episodes)), whatever the episode length.
CHUNK = 50


@dataclasses.dataclass(frozen=True)
class Episodes:
    """Closed-loop control steps of one engine, every array ``(B, T, ...)``: a whole run, or one
    streamed chunk of it.

    Attributes:
      obs: the observation after control step t (the policy acts at t on the one before it).
      action: the action the policy took at step t.
      reward, done: after step t (``done`` as the environment reports it; episodes run on to
        the end, returns and behaviour count up to the first ``done``).
      qpos, qvel: the state after step t.
      ctrl: the ``ctrl`` the physics got at step t.
      metrics: the environment's ``state.metrics`` after step t, name -> (B, T).
      qpos0, qvel0, obs0: (B, ...) before the first step held here.
      warmstart, warmstart0: the solver's warm start after step t and before the first step
        (C only; empty for MJX).
    """

    obs: np.ndarray
    action: np.ndarray
    reward: np.ndarray
    done: np.ndarray
    qpos: np.ndarray
    qvel: np.ndarray
    ctrl: np.ndarray
    metrics: dict[str, np.ndarray]
    qpos0: np.ndarray
    qvel0: np.ndarray
    obs0: np.ndarray
    warmstart: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 0, 0)))
    warmstart0: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 0)))

    def state_before(self, episode: int, step: int) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """(qpos, qvel, solver warm start or None) before step ``step`` (counted in these steps)."""
        if step == 0:
            return self.qpos0[episode], self.qvel0[episode], self.warmstart0[episode] if self.warmstart0.size else None
        return (self.qpos[episode, step - 1], self.qvel[episode, step - 1],
                self.warmstart[episode, step - 1] if self.warmstart.size else None)

    @staticmethod
    def concat(chunks: list["Episodes"]) -> "Episodes":
        """Consecutive chunks as one record (the first chunk's starting state)."""
        first = chunks[0]

        def join(name):
            return np.concatenate([getattr(c, name) for c in chunks], axis=1)

        return dataclasses.replace(
            first, **{f: join(f) for f in ("obs", "action", "reward", "done", "qpos", "qvel", "ctrl")},
            metrics={k: np.concatenate([c.metrics[k] for c in chunks], axis=1) for k in first.metrics},
            warmstart=join("warmstart") if first.warmstart.size else first.warmstart)

    @property
    def length(self) -> np.ndarray:
        """(B,) control steps up to and including the first ``done`` (T if none)."""
        done = self.done > 0.5
        return np.where(done.any(1), done.argmax(1) + 1, done.shape[1])

    @property
    def returns(self) -> np.ndarray:
        """(B,) summed reward up to and including the first ``done``."""
        steps = np.arange(self.reward.shape[1])[None]
        return np.where(steps < self.length[:, None], self.reward, 0.0).sum(1)


# ----------------------------------------------------------------------------
# C's physics in the environment's code


def _with_pipeline(env: Any, init: Any = None, step: Any = None) -> Any:
    """A shallow copy of ``env`` whose physics is given: ``pipeline_init`` returns ``init``,
    ``pipeline_step`` returns ``step``; everything else (observations, rewards,
    terminations) is the environment's own code."""
    e = copy.copy(env)
    if init is not None:
        e.pipeline_init = lambda *args, **kwargs: init
    if step is not None:
        e.pipeline_step = lambda *args, **kwargs: step
    return e


def c_model(env: Any) -> mujoco.MjModel:
    """The MjModel C steps for ``env``: its ``sys.mj_model`` with every option and numeric field
    the environment changed on its MJX system (brax's ant sets Newton, 1 iteration, 4 line
    searches and no Euler damping with ``sys.tree_replace``, which ``mj_model`` never sees)."""
    import copy as _copy

    sys, m = env.sys, _copy.copy(env.sys.mj_model)
    plain = mjx.put_model(m)  # what MJX makes of mj_model: fields the environment left alone compare equal

    def changed(a: Any, b: Any) -> bool:
        a, b = np.asarray(a), np.asarray(b)
        return a.shape != b.shape or not np.array_equal(a, b)

    for f in dataclasses.fields(sys.opt):
        if f.name != "_impl" and hasattr(m.opt, f.name) and changed(getattr(sys.opt, f.name),
                                                                    getattr(plain.opt, f.name)):
            value = np.asarray(getattr(sys.opt, f.name))
            setattr(m.opt, f.name, value.item() if value.ndim == 0 else value)
    for f in dataclasses.fields(sys):
        target = getattr(m, f.name, None) if f.name not in ("opt", "stat", "_impl") else None
        if isinstance(target, np.ndarray) and changed(getattr(sys, f.name), getattr(plain, f.name)):
            value = np.asarray(getattr(sys, f.name))
            if value.shape == target.shape:
                target[...] = value
    return m


def _data_fields(m: mujoco.MjModel) -> tuple[str, ...]:
    """The fields of MJX's data (public and JAX-implementation ones) that MjData holds with the
    same shape: what C records for the environment's code to read."""
    from mujoco.mjx._src import types

    d, dx = mujoco.MjData(m), mjx.make_data(m)
    out = []
    impl = data_impl(dx)
    # each field from where it lives: a DataJAX field read through Data is deprecated (and warns)
    fields = [(f.name, dx) for f in types.Data.fields()] + [(name, impl) for name in impl_fields()]
    for name, holder in fields:
        if name in ("_impl", "contact") or not hasattr(d, name):
            continue
        c = getattr(d, name)
        x = getattr(holder, name, None)
        if isinstance(c, np.ndarray) and x is not None and np.shape(x) == c.shape and c.dtype.kind == "f":
            out.append(name)
    return tuple(out)


def _pipeline_state(env: Any, template: Any, fields: dict[str, np.ndarray]) -> Any:
    """A batched brax MJX ``State`` holding C's values: ``template`` (one member's data from
    ``mjx.put_data``) with ``fields`` (B, ...) replaced, and brax's ``x``/``xd`` derived as
    ``brax.mjx.pipeline`` derives them."""
    B = next(iter(fields.values())).shape[0]
    data = jax.tree.map(lambda x: jnp.broadcast_to(x, (B, *jnp.shape(x))), template)
    public = {k: v for k, v in fields.items() if k in data.__dataclass_fields__}
    impl = {k: v for k, v in fields.items() if k not in public and hasattr(data_impl(data), k)}
    data = data.replace(**{k: jnp.asarray(v) for k, v in public.items()})
    data = with_impl(data, **{k: jnp.asarray(v) for k, v in impl.items()})
    return jax.vmap(functools.partial(_brax_state, env.sys))(data)


def _brax_state(sys: Any, data: Any) -> Any:
    from brax.base import Motion, Transform
    from brax.mjx.base import State

    x = Transform(pos=data.xpos[1:], rot=data.xquat[1:])
    cvel = Motion(vel=data.cvel[1:, 3:], ang=data.cvel[1:, :3])
    offset = Transform.create(pos=data.xpos[1:, :] - data.subtree_com[sys.body_rootid[1:]])
    xd = offset.vmap().do(cvel)
    from brax.mjx.pipeline import _reformat_contact

    # contacts are member 0's at the start (not recorded per step): brax environments read
    # positions, velocities, sensors and forces, not the contact list
    fields = dict(data.__dict__, contact=_reformat_contact(sys, data_impl(data).contact))
    return State(q=data.qpos, qd=data.qvel, x=x, xd=xd, **fields)


# ----------------------------------------------------------------------------
# the engines in closed loop


def _keys(seed: int, episodes: int, steps: int) -> tuple[jax.Array, jax.Array]:
    """Reset keys (B,) and policy keys (B, T) shared by every engine."""
    reset, act = jax.random.split(jax.random.PRNGKey(seed))
    return jax.random.split(reset, episodes), jax.vmap(lambda k: jax.random.split(k, steps))(
        jax.random.split(act, episodes))


def _np(tree: Any) -> Any:
    return jax.tree.map(np.asarray, tree)


def mjx_stream(env: Any, policy: Callable, reset_keys: jax.Array, policy_keys: jax.Array,
               chunk: int = CHUNK) -> tuple[Any, Iterator[Episodes]]:
    """MJX: every episode from ``env.reset(key)``, the policy inside the scan, ``chunk``
    control steps per compiled call (the last chunk is padded with repeated keys and cut, so
    one executable serves every chunk).

    Returns:
      The batch of reset states (their ``q``/``qd`` start C's episodes), and the chunks.
    """
    reset, advance = _mjx_functions(env, policy)
    first = reset(reset_keys)
    T = policy_keys.shape[1]
    chunk = min(chunk, T)

    def chunks() -> Iterator[Episodes]:
        state = first
        for t0 in range(0, T, chunk):
            keys = policy_keys[:, t0:t0 + chunk]
            n = keys.shape[1]
            if n < chunk:
                keys = jnp.concatenate([keys, jnp.repeat(keys[:, -1:], chunk - n, axis=1)], axis=1)
            before, (state, rec) = state, advance(state, keys)
            obs, action, reward, done, qpos, qvel, ctrl, metrics = (_np(x) for x in rec)

            def cut(x):
                return x[:, :n]

            yield Episodes(cut(obs), cut(action), cut(reward), cut(done), cut(qpos), cut(qvel), cut(ctrl),
                           {k: cut(v) for k, v in metrics.items()}, qpos0=np.asarray(before.pipeline_state.qpos),
                           qvel0=np.asarray(before.pipeline_state.qvel), obs0=np.asarray(before.obs))

    return first, chunks()


def run_mjx(env: Any, policy: Callable, reset_keys: jax.Array, policy_keys: jax.Array,
            chunk: int = CHUNK) -> tuple[Episodes, Any]:
    """:func:`mjx_stream` held whole: the episodes and the batch of reset states."""
    first, chunks = mjx_stream(env, policy, reset_keys, policy_keys, chunk)
    return Episodes.concat(list(chunks)), first


@functools.lru_cache(maxsize=8)  # one compiled pair per (environment, policy) object
def _mjx_functions(env: Any, policy: Callable) -> tuple[Callable, Callable]:
    def control_step(state, key):
        action, _ = policy(state.obs, key)
        nxt = env.step(state, action)
        ps = nxt.pipeline_state
        return nxt, (nxt.obs, action, nxt.reward, nxt.done, ps.qpos, ps.qvel, ps.ctrl, nxt.metrics)

    advance = jax.vmap(lambda state, keys: jax.lax.scan(control_step, state, keys))
    # compiled as a sweep compiles a rollout that steps for long (mjxdiff.engine.engines.xla_options):
    # XLA's compile at its default level was 60-80% of a short run's time (tests/test_closedloop.py,
    # cold: jax.monitoring's backend_compile_duration against each test's wall time)
    return jit_for_few_calls(jax.vmap(env.reset)), jax.jit(advance, compiler_options=dict(BALANCED_COMPILE))


@functools.lru_cache(maxsize=8)
def _c_functions(env: Any, policy: Callable) -> tuple[Callable, Callable, Callable]:
    """Jitted, over the batch: reset and step of the environment's code on given physics, and
    the policy's action with the ctrl it becomes."""
    def reset(keys, template, fields):
        ps = _pipeline_state(env, template, fields)
        return jax.vmap(lambda key, ps: _with_pipeline(env, init=ps).reset(key))(keys, ps)

    def step(state, action, template, fields):
        ps = _pipeline_state(env, template, fields)
        return jax.vmap(lambda state, action, ps: _with_pipeline(env, step=ps).step(state, action))(state, action, ps)

    # the brax state is built from C's recorded fields inside the compiled function: one call a step
    act = jit_for_few_calls(jax.vmap(functools.partial(_act, env, policy)))
    return jit_for_few_calls(reset), jit_for_few_calls(step), act


def c_stream(env: Any, policy: Callable, reset_keys: jax.Array, policy_keys: jax.Array, qpos0: np.ndarray,
             qvel0: np.ndarray, nthread: int = 0, seconds: dict[str, float] | None = None,
             model: mujoco.MjModel | None = None, chunk: int = CHUNK) -> Iterator[Episodes]:
    """MuJoCo C from ``qpos0``/``qvel0`` (B, ...), ``chunk`` control steps at a time: a Batch
    steps ``n_frames`` substeps per control step; the environment's code reads C's recorded
    fields. ``seconds`` gains the wall time spent stepping C (``c``) and in the policy and the
    environment's code (``policy``)."""
    import time

    seconds = {} if seconds is None else seconds
    m = c_model(env) if model is None else model
    B, T = policy_keys.shape[:2]
    fields = _data_fields(m)
    b = Batch(m, B, nthread=nthread)
    b.qpos[:], b.qvel[:] = qpos0, qvel0
    starts = []
    for i in range(B):  # a Batch hands out states; the derived fields are mj_forward's
        d = b.get_data(i)
        mujoco.mj_forward(m, d)
        starts.append(d)
    template = mjx.put_data(m, starts[0])
    start = {f: np.stack([getattr(d, f) for d in starts]) for f in fields}

    reset, step, act = _c_functions(env, policy)
    state = reset(reset_keys, template, start)
    qpos, qvel, warm = np.asarray(qpos0), np.asarray(qvel0), start["qacc_warmstart"]
    n_frames = int(env._n_frames)  # noqa: SLF001 - brax's substeps per control step
    for t0 in range(0, T, chunk):
        rec: dict[str, list] = {k: [] for k in ("obs", "action", "reward", "done", "qpos", "qvel", "ctrl",
                                                "warmstart", "metrics")}
        before = dict(qpos0=qpos, qvel0=qvel, obs0=np.asarray(state.obs), warmstart0=warm)
        for t in range(t0, min(t0 + chunk, T)):
            t1 = time.perf_counter()
            action, ctrl = act(state, policy_keys[:, t])
            action, ctrl = np.asarray(action, dtype=np.float64), np.asarray(ctrl, dtype=np.float64)
            t2 = time.perf_counter()
            out = b.rollout(n_frames, control=np.repeat(ctrl[:, None], n_frames, axis=1), record=fields)
            t3 = time.perf_counter()
            last = {f: out[f][:, -1] for f in fields}
            state = step(state, jnp.asarray(action), template, last)
            qpos, qvel, warm = last["qpos"], last["qvel"], last["qacc_warmstart"]
            for k, v in (("obs", state.obs), ("action", action), ("reward", state.reward), ("done", state.done),
                         ("qpos", qpos), ("qvel", qvel), ("ctrl", ctrl), ("warmstart", warm),
                         ("metrics", state.metrics)):
                rec[k].append(_np(v))
            seconds["c"] = seconds.get("c", 0.0) + t3 - t2
            seconds["policy"] = seconds.get("policy", 0.0) + (t2 - t1) + (time.perf_counter() - t3)
        yield Episodes(**{k: np.stack(v, axis=1) for k, v in rec.items() if k != "metrics"},
                       metrics={k: np.stack([r[k] for r in rec["metrics"]], axis=1) for k in rec["metrics"][0]},
                       **before)


def run_c(env: Any, policy: Callable, reset_keys: jax.Array, policy_keys: jax.Array, qpos0: np.ndarray,
          qvel0: np.ndarray, nthread: int = 0, seconds: dict[str, float] | None = None,
          model: mujoco.MjModel | None = None, chunk: int = CHUNK) -> Episodes:
    """:func:`c_stream` held whole."""
    return Episodes.concat(list(c_stream(env, policy, reset_keys, policy_keys, qpos0, qvel0, nthread, seconds,
                                         model, chunk)))


def _act(env: Any, policy: Callable, state: Any, key: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The policy's action in ``state`` and the ``ctrl`` the environment's ``step`` hands its
    physics for it (environments scale or clip actions in their own code): read off a
    ``pipeline_step`` that only looks at its argument."""
    action, _ = policy(state.obs, key)
    seen = []
    e = copy.copy(env)
    e.pipeline_step = lambda pipeline_state, ctrl: (seen.append(ctrl), pipeline_state)[1]
    e.step(state, action)
    return action, seen[0]
