"""What runs in closed loop: a policy loaded from what users have, and the brax environment it acts in.

:func:`load_policy` turns a brax PPO checkpoint, saved parameters with their network factory,
or a Python function into ``policy(obs, key) -> (action, extras)``; :func:`make_env`,
:func:`resolve_env` and :func:`mjcf_env` give the brax environment (MJX backend) for a brax
name, a scenario or any model. A spec that cannot be loaded raises :class:`PolicyError`, one
line. :mod:`mjxdiff.tools.closedloop` runs and judges them (and exports these names too).
"""

from __future__ import annotations

import functools
import importlib
from pathlib import Path
from typing import Any, Callable

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from mjxdiff.errors import one_line
from mjxdiff.input import joints

__all__ = ["PolicyError", "load_policy", "make_env", "mjcf_env", "resolve_env"]


class PolicyError(ValueError):
    """A policy spec that cannot be loaded; the message is one line that says what to do."""


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
    # brax types get_network as any of its agents' networks (this one is PPO's, made just above) and
    # checkpoint.load's path as etils' Path, which a pathlib.Path is at runtime
    return ppo_networks.make_inference_fn(network)(  # pyright: ignore[reportArgumentType]
        checkpoint.load(path), deterministic=True)  # pyright: ignore[reportArgumentType]


def _size(saved: Any) -> Any:
    """An observation size as the network factory takes it, from its JSON in a checkpoint."""
    if isinstance(saved, dict) and "shape" in saved:
        shape = tuple(saved["shape"])
        return shape[0] if len(shape) == 1 else shape
    if isinstance(saved, dict):
        return {k: _size(v) for k, v in saved.items()}
    return saved


def _one_line(e: BaseException) -> str:
    return one_line(e, 300)


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
        raise PolicyError(f"{name}: not a brax environment (one of {', '.join(sorted(envs._envs))})")  # noqa: SLF001
    return envs.get_environment(name, backend="mjx", **kwargs)


def resolve_env(target: str, n_frames: int = 1) -> Any:
    """A brax environment name, a bundled scenario name or scenario ``.toml``, or an MJCF path.

    Raises:
      PolicyError: one line, when it is none of them.
    """
    from brax import envs

    if target in envs._envs:  # noqa: SLF001
        return make_env(target)
    from mjxdiff.input.scenario import ScenarioError, load_model, load_scenario

    try:
        m = load_model(load_scenario(target))
    except ScenarioError as e:
        raise PolicyError(f"{target}: not a brax environment ({', '.join(sorted(envs._envs))}) and {e}") from None  # noqa: SLF001
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
    for p in joints.parts(m):
        noisy[p.qpos] = p.kind != "rotation"
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
            # numpy + jax.Array is a jax.Array (numpy's stubs say ndarray); brax's State is a flax
            # dataclass, with the replace its type declarations do not show
            ps = self.pipeline_step(state.pipeline_state, ctrl)  # pyright: ignore[reportArgumentType]
            return state.replace(  # pyright: ignore[reportAttributeAccessIssue]
                pipeline_state=ps, obs=self._obs(ps), reward=jnp.zeros(()), done=jnp.zeros(()))

        @property
        def action_size(self):
            return m.nu

        def _obs(self, ps):
            return jnp.concatenate([ps.qpos, ps.qvel, ps.sensordata])

    return MjcfEnv()
