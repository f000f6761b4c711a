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
* **C again** from initial states moved by a few units of roundoff: the floor, how much C
  disagrees with itself in closed loop.

:func:`judge` compares per episode (paired): return, length, termination; the MJX-vs-C gap
is judged against the C-vs-C gap (:data:`TEST`), and the first control step where the
states separate beyond C's own separation is named, with the joints and observation
components that separate first.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import importlib
from pathlib import Path
from typing import Any, Callable

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx
from mujoco.batch import Batch

from mjxdiff.noise import converge_solver, has_constraints

__all__ = ["Episodes", "PolicyError", "load_policy", "make_env", "mjcf_env", "resolve_env", "run_mjx", "run_c",
           "run", "judge", "TEST", "PERTURB_ULPS"]

#: The statistical test, stated: the paired return gap (MJX - C) per episode, relative to the
#: mean |C return|; a 95% bootstrap CI (2000 resamples) of its mean. FAIL when that CI lies
#: wholly outside the C-vs-C band: ± the largest |paired C-vs-C gap| of any episode, or
#: ``RETURN_FLOOR`` of the return, whichever is larger; or when MJX and C terminate at
#: different steps in more episodes than C does against itself; or when the states separate
#: by more than max(``tol``, 10 x the C-vs-C separation) at some control step, returns agreeing
#: or not. Effect size: Cohen's d_z (mean paired gap / its standard deviation).
TEST = "95% bootstrap CI of the mean paired return gap outside the C-vs-C band"
RETURN_FLOOR = 1e-3
#: Units of roundoff the C-vs-C rerun moves each initial qpos/qvel component by.
PERTURB_ULPS = 4.0


class PolicyError(ValueError):
    """A policy spec that cannot be loaded; the message is one line that says what to do."""


@dataclasses.dataclass(frozen=True)
class Episodes:
    """Closed-loop episodes of one engine, every array ``(B, T, ...)`` over control steps.

    Attributes:
      obs: the observation the policy saw before control step t.
      action: the action it took.
      reward, done: after step t (``done`` as the environment reports it; episodes run
        on to T, the return counts up to the first ``done``).
      qpos, qvel: the state after step t.
      ctrl: the ``ctrl`` the physics got at step t.
      qpos0, qvel0: (B, ...) the initial state.
      warmstart: the solver's warm start after step t (C only; empty for MJX).
    """

    obs: np.ndarray
    action: np.ndarray
    reward: np.ndarray
    done: np.ndarray
    qpos: np.ndarray
    qvel: np.ndarray
    ctrl: np.ndarray
    qpos0: np.ndarray
    qvel0: np.ndarray
    warmstart: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 0, 0)))

    def state_before(self, episode: int, step: int) -> tuple[np.ndarray, np.ndarray]:
        """(qpos, qvel) before control step ``step`` of ``episode``."""
        if step == 0:
            return self.qpos0[episode], self.qvel0[episode]
        return self.qpos[episode, step - 1], self.qvel[episode, step - 1]

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
# policies


def load_policy(spec: str, env: Any | None = None) -> Callable:
    """``policy(obs, key) -> (action, extras)`` from what users have.

    * a brax PPO checkpoint directory (it holds ``ppo_network_config.json``): loaded with
      ``brax.training.agents.ppo.checkpoint.load_policy`` (deterministic);
    * ``PARAMS_FILE::module:factory``: parameters saved by ``brax.io.model.save_params`` and
      a function ``factory(observation_size, action_size)`` returning brax PPO networks
      (``make_ppo_networks``'s signature);
    * ``module:function``: a function of ``(observation_size, action_size)`` returning
      ``policy(obs, key) -> action`` (or ``(action, extras)``), or that policy itself when it
      takes ``(obs, key)``.

    Raises:
      PolicyError: one line saying what is wrong.
    """
    if "::" in spec:
        params_file, factory = spec.split("::", 1)
        return _from_params(params_file, factory, env)
    path = Path(spec)
    if path.is_dir():
        if not (path / "ppo_network_config.json").is_file():
            raise PolicyError(f"{spec}: not a brax PPO checkpoint (no ppo_network_config.json in it); give a "
                              "checkpoint directory, PARAMS_FILE::module:factory or module:function")
        try:
            return _load_checkpoint(path.resolve())
        except Exception as e:  # noqa: BLE001 - any loader failure is the user's file
            raise PolicyError(f"{spec}: brax could not load this checkpoint: {_one_line(e)}") from None
    if ":" in spec:
        fn = _attribute(spec)
        return _as_policy(fn, env, spec)
    raise PolicyError(f"{spec}: not a checkpoint directory, PARAMS_FILE::module:factory or module:function")


def _load_checkpoint(path: Path) -> Callable:
    """brax's ``ppo.checkpoint.load_policy``, reading the network config itself: brax 0.14.2
    writes ``null`` for a kernel initialiser left at its default (``mean_kernel_init_fn``)
    and then fails to read it back (``KeyError: None``); here such keys keep the factory's
    default. Its training also writes the observation size as a serialised ShapeDtypeStruct,
    which its loader takes for an observation dict (``KeyError: 'state'``)."""
    import json

    from brax.training import checkpoint as brax_checkpoint
    from brax.training import networks
    from brax.training.agents.ppo import checkpoint
    from brax.training.agents.ppo import networks as ppo_networks
    from ml_collections import config_dict

    loaded = json.loads((path / "ppo_network_config.json").read_text())
    kwargs = loaded["network_factory_kwargs"]
    for key in list(kwargs):
        if key.endswith("_init_fn") and kwargs[key] is None:
            del kwargs[key]
        elif key.endswith("_init_fn"):
            kwargs[key] = networks.KERNEL_INITIALIZER[kwargs[key]]
    if "activation" in kwargs:
        kwargs["activation"] = networks.ACTIVATION[kwargs["activation"]]
    # training writes the observation size as brax's ShapeDtypeStruct, {"shape": [n], "dtype": ...},
    # which reads back as an observation dict without its "state" key
    loaded["observation_size"] = _size(loaded["observation_size"])
    network = brax_checkpoint.get_network(config_dict.create(**loaded), ppo_networks.make_ppo_networks)
    return ppo_networks.make_inference_fn(network)(checkpoint.load(path), deterministic=True)


def _size(saved: Any) -> Any:
    """An observation size as the network factory takes it, from its JSON in a checkpoint."""
    if isinstance(saved, dict) and "shape" in saved:
        shape = tuple(saved["shape"])
        return shape[0] if len(shape) == 1 else shape
    if isinstance(saved, dict):
        return {k: _size(v) for k, v in saved.items()}
    return saved


def _one_line(e: BaseException) -> str:
    return " ".join(f"{type(e).__name__}: {e}".split())[:300]


def _attribute(ref: str) -> Any:
    module, _, name = ref.partition(":")
    try:
        return functools.reduce(getattr, name.split("."), importlib.import_module(module))
    except (ImportError, AttributeError, ValueError) as e:
        raise PolicyError(f"{ref}: cannot import it ({_one_line(e)}); give module:function") from None


def _as_policy(fn: Callable, env: Any, spec: str) -> Callable:
    import inspect

    try:
        params = list(inspect.signature(fn).parameters)
    except (TypeError, ValueError):
        params = []
    if params[:2] == ["observation_size", "action_size"]:
        if env is None:
            raise PolicyError(f"{spec}: a policy factory needs the environment's sizes")
        fn = fn(env.observation_size, env.action_size)

    def policy(obs, key):
        out = fn(obs, key)
        return out if isinstance(out, tuple) else (out, {})
    return policy


def _from_params(params_file: str, factory_ref: str, env: Any) -> Callable:
    from brax.io import model
    from brax.training.agents.ppo import networks as ppo_networks

    if not Path(params_file).is_file():
        raise PolicyError(f"{params_file}: no such parameters file (saved by brax.io.model.save_params)")
    if env is None:
        raise PolicyError(f"{params_file}: a network factory needs the environment's sizes")
    factory = _attribute(factory_ref)
    try:
        params = model.load_params(params_file)
        network = factory(env.observation_size, env.action_size)
        return ppo_networks.make_inference_fn(network)(params, deterministic=True)
    except Exception as e:  # noqa: BLE001 - a mismatched file or factory is the user's
        raise PolicyError(f"{params_file} with {factory_ref}: {_one_line(e)}") from None


# ----------------------------------------------------------------------------
# environments


def make_env(name: str, **kwargs) -> Any:
    """A brax environment on the MJX backend (``brax.envs.get_environment``)."""
    from brax import envs

    if name not in envs._envs:  # noqa: SLF001 - brax lists its environments there
        raise PolicyError(f"{name}: not a brax environment (one of {', '.join(sorted(envs._envs))})")
    return envs.get_environment(name, backend="mjx", **kwargs)


def resolve_env(target: str, n_frames: int = 1) -> Any:
    """A brax environment name, a bundled scenario name or scenario ``.toml``, or an MJCF path.

    Raises:
      PolicyError: one line, when it is none of them.
    """
    from brax import envs

    if target in envs._envs:  # noqa: SLF001
        return make_env(target)
    from mjxdiff.scenario import ScenarioError, load_model, load_scenario

    try:
        m = load_model(load_scenario(target))
    except ScenarioError as e:
        raise PolicyError(f"{target}: not a brax environment ({', '.join(sorted(envs._envs))}) and {e}") from None
    return mjcf_env(m, n_frames=n_frames)


def mjcf_env(m: mujoco.MjModel, n_frames: int = 1, qpos_noise: float = 0.01, qvel_noise: float = 0.01) -> Any:
    """A brax environment (MJX backend) around any model: observations ``qpos``, ``qvel``,
    ``sensordata``; actions in [-1, 1] mapped onto each limited actuator's ``ctrlrange`` (as
    they are for an unlimited one); reward 0 and no termination (compare behaviour and
    states); ``reset`` draws ``qpos0`` plus uniform noise of ``qpos_noise`` (rad or m) and
    velocities of ``qvel_noise``; ``n_frames`` substeps per control step."""
    from brax.envs.base import PipelineEnv, State
    from brax.io import mjcf

    noisy = np.ones(m.nq, bool)  # no noise on quaternions: they stay normalised
    for j in range(m.njnt):
        adr, jtype = m.jnt_qposadr[j], m.jnt_type[j]
        if jtype == mujoco.mjtJoint.mjJNT_FREE:
            noisy[adr + 3:adr + 7] = False
        elif jtype == mujoco.mjtJoint.mjJNT_BALL:
            noisy[adr:adr + 4] = False
    limited = np.asarray(m.actuator_ctrllimited, bool)
    lo = np.where(limited, m.actuator_ctrlrange[:, 0], -1.0)
    hi = np.where(limited, m.actuator_ctrlrange[:, 1], 1.0)

    class MjcfEnv(PipelineEnv):
        def __init__(self):
            super().__init__(sys=mjcf.load_model(m), backend="mjx", n_frames=n_frames)

        def reset(self, rng):
            k1, k2 = jax.random.split(rng)
            q = jnp.asarray(m.qpos0) + noisy * jax.random.uniform(k1, (m.nq,), minval=-qpos_noise, maxval=qpos_noise)
            qd = jax.random.uniform(k2, (m.nv,), minval=-qvel_noise, maxval=qvel_noise)
            ps = self.pipeline_init(q, qd)
            return State(ps, self._obs(ps), jnp.zeros(()), jnp.zeros(()), {}, {})

        def step(self, state, action):
            ctrl = lo + (jnp.clip(action, -1.0, 1.0) + 1.0) * 0.5 * (hi - lo)
            ps = self.pipeline_step(state.pipeline_state, ctrl)
            return state.replace(pipeline_state=ps, obs=self._obs(ps), reward=jnp.zeros(()), done=jnp.zeros(()))

        @property
        def action_size(self):
            return m.nu

        def _obs(self, ps):
            return jnp.concatenate([ps.qpos, ps.qvel, ps.sensordata])

    return MjcfEnv()


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
    for f in types.Data.fields() + types.DataJAX.fields():
        if f.name in ("_impl", "contact") or not hasattr(d, f.name):
            continue
        c = getattr(d, f.name)
        x = getattr(dx, f.name, None)
        if x is None:
            x = getattr(dx._impl, f.name, None)  # noqa: SLF001
        if isinstance(c, np.ndarray) and x is not None and np.shape(x) == c.shape and c.dtype.kind == "f":
            out.append(f.name)
    return tuple(out)


def _pipeline_state(env: Any, template: Any, fields: dict[str, np.ndarray]) -> Any:
    """A batched brax MJX ``State`` holding C's values: ``template`` (one member's data from
    ``mjx.put_data``) with ``fields`` (B, ...) replaced, and brax's ``x``/``xd`` derived as
    ``brax.mjx.pipeline`` derives them."""
    B = next(iter(fields.values())).shape[0]
    data = jax.tree.map(lambda x: jnp.broadcast_to(x, (B, *jnp.shape(x))), template)
    public = {k: v for k, v in fields.items() if hasattr(data, k) and k in data.__dataclass_fields__}
    impl = {k: v for k, v in fields.items() if k not in public and hasattr(data._impl, k)}  # noqa: SLF001
    data = data.replace(**{k: jnp.asarray(v) for k, v in public.items()})
    data = data.replace(_impl=data._impl.replace(**{k: jnp.asarray(v) for k, v in impl.items()}))  # noqa: SLF001
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
    fields = dict(data.__dict__, contact=_reformat_contact(sys, data._impl.contact))  # noqa: SLF001
    return State(q=data.qpos, qd=data.qvel, x=x, xd=xd, **fields)


# ----------------------------------------------------------------------------
# the engines in closed loop


def _keys(seed: int, episodes: int, steps: int) -> tuple[jax.Array, jax.Array]:
    """Reset keys (B,) and policy keys (B, T) shared by every engine."""
    reset, act = jax.random.split(jax.random.PRNGKey(seed))
    return jax.random.split(reset, episodes), jax.vmap(lambda k: jax.random.split(k, steps))(
        jax.random.split(act, episodes))


def run_mjx(env: Any, policy: Callable, reset_keys: jax.Array, policy_keys: jax.Array) -> tuple[Episodes, Any]:
    """MJX: every episode from ``env.reset(key)``, the policy inside the scan.

    Returns:
      The episodes, and the batch of reset states (their ``q``/``qd`` start C's episodes).
    """

    first, rec = _mjx_episodes(env, policy)(reset_keys, policy_keys)
    return Episodes(*(np.asarray(x) for x in rec), qpos0=np.asarray(first.pipeline_state.qpos),
                    qvel0=np.asarray(first.pipeline_state.qvel)), first


@functools.lru_cache(maxsize=8)  # one compiled function per (environment, policy) object
def _mjx_episodes(env: Any, policy: Callable) -> Callable:
    def episode(reset_key, keys):
        state = env.reset(reset_key)

        def control_step(state, key):
            action, _ = policy(state.obs, key)
            nxt = env.step(state, action)
            return nxt, (state.obs, action, nxt.reward, nxt.done, nxt.pipeline_state.qpos, nxt.pipeline_state.qvel,
                         nxt.pipeline_state.ctrl)

        return state, jax.lax.scan(control_step, state, keys)[1]

    return jax.jit(jax.vmap(episode))


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
    act = jax.jit(jax.vmap(functools.partial(_act, env, policy)))
    return jax.jit(reset), jax.jit(step), act


def run_c(env: Any, policy: Callable, reset_keys: jax.Array, policy_keys: jax.Array, qpos0: np.ndarray,
          qvel0: np.ndarray, nthread: int = 0, seconds: dict[str, float] | None = None,
          model: mujoco.MjModel | None = None) -> Episodes:
    """MuJoCo C from ``qpos0``/``qvel0`` (B, ...): a Batch steps ``n_frames`` substeps per
    control step; the environment's code reads C's recorded fields. ``seconds`` gains the wall
    time spent stepping C (``c``) and in the policy and the environment's code (``policy``)."""
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
    rec = {k: [] for k in ("obs", "action", "reward", "done", "qpos", "qvel", "ctrl", "warmstart")}
    n_frames = int(env._n_frames)  # noqa: SLF001 - brax's substeps per control step
    for t in range(T):
        t0 = time.perf_counter()
        action, ctrl = act(state, policy_keys[:, t])
        action, ctrl = np.asarray(action, dtype=np.float64), np.asarray(ctrl, dtype=np.float64)
        t1 = time.perf_counter()
        out = b.rollout(n_frames, control=np.repeat(ctrl[:, None], n_frames, axis=1), record=fields)
        t2 = time.perf_counter()
        last = {f: out[f][:, -1] for f in fields}
        nxt = step(state, jnp.asarray(action), template, last)
        for k, v in (("obs", state.obs), ("action", action), ("reward", nxt.reward), ("done", nxt.done),
                     ("qpos", last["qpos"]), ("qvel", last["qvel"]), ("ctrl", ctrl),
                     ("warmstart", last["qacc_warmstart"])):
            rec[k].append(np.asarray(v))
        state = nxt
        seconds["c"] = seconds.get("c", 0.0) + t2 - t1
        seconds["policy"] = seconds.get("policy", 0.0) + (t1 - t0) + (time.perf_counter() - t2)
    return Episodes(**{k: np.stack(v, axis=1) for k, v in rec.items()}, qpos0=np.asarray(qpos0),
                    qvel0=np.asarray(qvel0))


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


def _perturbed(x: np.ndarray, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return x + rng.choice([-1.0, 1.0], x.shape) * PERTURB_ULPS * np.finfo(np.float64).eps * np.maximum(np.abs(x), 1.0)


def run(env: Any, policy: Callable, episodes: int, steps: int, seed: int = 0,
        only: list[int] | None = None) -> dict[str, Episodes]:
    """MJX, C and C from perturbed initial states, each ``episodes`` x ``steps`` control steps,
    same reset and policy keys (float64: run under ``jax.enable_x64``). ``only``: run just these
    episodes of the ``episodes`` (their keys are the same; the perturbation of C's rerun is
    drawn for them alone)."""
    reset_keys, policy_keys = _keys(seed, episodes, steps)
    if only is not None:
        reset_keys, policy_keys = reset_keys[np.asarray(only)], policy_keys[np.asarray(only)]
    traj_mjx, first = run_mjx(env, policy, reset_keys, policy_keys)
    q0, qd0 = np.asarray(first.pipeline_state.qpos), np.asarray(first.pipeline_state.qvel)
    m = c_model(env)
    traj_c = run_c(env, policy, reset_keys, policy_keys, q0, qd0, model=m)
    traj_cc = run_c(env, policy, reset_keys, policy_keys, _perturbed(q0, seed), _perturbed(qd0, seed + 1), model=m)
    runs = {"mjx": traj_mjx, "c": traj_c, "c_perturbed": traj_cc}
    if has_constraints(m):  # C with a converged solver: how much the solver's own stopping point moves C
        solved = copy.copy(m)
        converge_solver(solved)
        runs["c_solver"] = run_c(env, policy, reset_keys, policy_keys, q0, qd0, model=solved)
    return runs


# ----------------------------------------------------------------------------
# the verdict


def _bootstrap_ci(x: np.ndarray, seed: int = 0, resamples: int = 2000) -> tuple[float, float]:
    if len(x) < 2:
        return float(x.mean()), float(x.mean())
    rng = np.random.default_rng(seed)
    means = x[rng.integers(0, len(x), (resamples, len(x)))].mean(1)
    return float(np.quantile(means, 0.025)), float(np.quantile(means, 0.975))


def _separation(a: Episodes, b: Episodes) -> np.ndarray:
    """(B, T) largest |qpos| or |qvel| difference per control step."""
    return np.maximum(np.abs(a.qpos - b.qpos).max(-1), np.abs(a.qvel - b.qvel).max(-1))


def _first_separation(m: mujoco.MjModel, runs: dict[str, Episodes], tol: float) -> dict[str, Any] | None:
    """The first control step where MJX and C separate by more than max(tol, 10 x C-vs-C)."""
    sep = _separation(runs["mjx"], runs["c"])
    floor = np.maximum(tol, 10 * _separation(runs["c_perturbed"], runs["c"]))
    if "c_solver" in runs:
        floor = np.maximum(floor, 10 * _separation(runs["c_solver"], runs["c"]))
    out = sep > floor
    if not out.any():
        return None
    steps = np.where(out.any(1), out.argmax(1), out.shape[1])
    episode = int(steps.argmin())
    step = int(steps[episode])
    mj, c = runs["mjx"], runs["c"]
    dq = np.abs(mj.qpos[episode, step] - c.qpos[episode, step])
    dv = np.abs(mj.qvel[episode, step] - c.qvel[episode, step])
    dof = int(dv.argmax())
    joint = int(m.dof_jntid[dof])
    obs_step = min(step + 1, mj.obs.shape[1] - 1)  # the observation that step produces
    dobs = np.abs(mj.obs[episode, obs_step] - c.obs[episode, obs_step])
    return dict(episode=episode, step=step, separation=float(sep[episode, step]),
                floor=float(floor[episode, step]),
                joint=mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, joint) or f"#{joint}",
                qpos_error=float(dq.max()), qvel_error=float(dv.max()),
                observation_components=[int(i) for i in np.argsort(-dobs)[:3]])


def _drill(m: mujoco.MjModel, c: Episodes, first: dict[str, Any], n_frames: int) -> dict[str, Any]:
    """The sweep's stage drill-down (:func:`mjxdiff.diagnose.drill_down`) substep by substep
    through the first separating control step, C replayed from its state (and solver warm
    start) before it with the ctrl it applied: the first substep where a stage differs."""
    from mjxdiff import diagnose

    episode, step = first["episode"], first["step"]
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:] = c.state_before(episode, step)
    if step > 0 and c.warmstart.size:
        d.qacc_warmstart[:] = c.warmstart[episode, step - 1]
    d.ctrl[:] = c.ctrl[episode, step]
    try:
        for k in range(n_frames):
            drill = diagnose.drill_down(m, d.qpos.copy(), d.qvel.copy(), d.act.copy(), d.ctrl.copy(), d.time,
                                        member=episode, step=step, qacc_warmstart=d.qacc_warmstart.copy())
            if drill.first_stage:
                break
            mujoco.mj_step(m, d)
    except Exception as e:  # noqa: BLE001 - the verdict stands without its drill-down
        return dict(error=_one_line(e))
    return dict(substep=k, first_stage=drill.first_stage, first_field=drill.first_field, object=drill.object,
                fields=[dataclasses.asdict(f) for f in drill.fields])


def judge(m: mujoco.MjModel, runs: dict[str, Episodes], tol: float = 1e-6, seed: int = 0,
          n_frames: int = 1) -> dict[str, Any]:
    """Paired per-episode comparison of MJX and C against C-vs-C (see :data:`TEST`); ``m`` is
    the model C stepped (:func:`c_model`), ``n_frames`` its substeps per control step."""
    mj, c, cc = runs["mjx"], runs["c"], runs["c_perturbed"]
    scale = max(float(np.abs(c.returns).mean()), 1e-12)
    gap = (mj.returns - c.returns) / scale
    gap_cc = (cc.returns - c.returns) / scale
    band = max(float(np.abs(gap_cc).max()), RETURN_FLOOR)
    solver = runs.get("c_solver")
    if solver is not None:
        band = max(band, float(np.abs((solver.returns - c.returns) / scale).max()))
    lo, hi = _bootstrap_ci(gap, seed)
    length_differs = float((mj.length != c.length).mean())
    length_differs_cc = float((cc.length != c.length).mean())
    if solver is not None:
        length_differs_cc = max(length_differs_cc, float((solver.length != c.length).mean()))
    sd = float(gap.std(ddof=1)) if len(gap) > 1 else 0.0
    out_of_band = lo > band or hi < -band
    first = _first_separation(m, runs, tol)
    # behaviour first (what a user sees), then the states: separating beyond C's own floor is
    # a divergence even while returns still agree
    fail = out_of_band or length_differs > length_differs_cc + 1e-12 or first is not None

    def mean_sd(x):
        return float(x.mean()), float(x.std(ddof=1)) if len(x) > 1 else 0.0

    (rm, rs), (rc, rcs) = mean_sd(mj.returns), mean_sd(c.returns)
    message = (f"MJX return {rm:.4g} ± {rs:.2g}, C {rc:.4g} ± {rcs:.2g}, paired gap {100 * gap.mean():+.3g}% "
               f"(95% CI {100 * lo:+.3g}..{100 * hi:+.3g}%), C-vs-C gap ±{100 * band:.3g}%; episode lengths "
               f"differ in {length_differs:.0%} (C vs C {length_differs_cc:.0%}): {'FAIL' if fail else 'PASS'}")
    if first is not None:
        message += (f"; first separation at control step {first['step']} of episode {first['episode']}, "
                    f"joint '{first['joint']}' (qvel {first['qvel_error']:.3g} > floor {first['floor']:.3g})")
        first["drill_down"] = drill = _drill(m, c, first, n_frames)
        if drill.get("first_stage"):
            message += (f"; first stage to differ from C's state there (substep {drill['substep']}): "
                        f"{drill['first_stage']} ({drill['first_field']}, {drill['object']})")
    return dict(status="fail" if fail else "pass", message=message, test=TEST,
                returns=dict(mjx=mj.returns.tolist(), c=c.returns.tolist(), c_perturbed=cc.returns.tolist()),
                lengths=dict(mjx=mj.length.tolist(), c=c.length.tolist(), c_perturbed=cc.length.tolist()),
                gap=dict(mean=float(gap.mean()), ci95=[lo, hi], band=band, effect_size_dz=float(gap.mean() / sd)
                         if sd > 0 else (0.0 if gap.mean() == 0 else float("inf"))),
                length_differs=length_differs, length_differs_c_vs_c=length_differs_cc, first_separation=first)
