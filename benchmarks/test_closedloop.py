"""Closed-loop throughput: episodes per second of MJX (vmapped episodes, the policy inside the
scan) and of MuJoCo C (a Batch, the policy jitted over the batch each control step), and the
share of C's closed loop spent outside C (the policy and the environment's own code on C's
state), and the peak memory of a whole streamed comparison at two episode lengths. brax's
inverted_pendulum (MJX backend) with a randomly initialised brax PPO network.

Run: ``python -m pytest benchmarks/test_closedloop.py --benchmark-only``."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax.training.acme import running_statistics
from brax.training.agents.ppo import networks as ppo_networks

from mjxdiff.tools import closedloop, closedloop_streams
from mjxdiff.output.report import versions

EPISODES, STEPS = 32, 200


@pytest.fixture(scope="module")
def setup():
    env = closedloop.make_env("inverted_pendulum")
    policy = _random_policy(env)
    reset_keys, policy_keys = closedloop_streams._keys(0, EPISODES, STEPS)
    return env, policy, reset_keys, policy_keys


def test_mjx_closed_loop(benchmark, setup):
    env, policy, reset_keys, policy_keys = setup
    closedloop.run_mjx(env, policy, reset_keys, policy_keys)  # compile
    benchmark.pedantic(closedloop.run_mjx, args=setup, rounds=3, iterations=1)
    benchmark.extra_info.update(versions(), engine="mjx", episodes=EPISODES, steps=STEPS,
                                episodes_per_s=EPISODES / benchmark.stats.stats.mean)


def test_c_closed_loop(benchmark, setup):
    env, policy, reset_keys, policy_keys = setup
    _, first = closedloop.run_mjx(env, policy, reset_keys, policy_keys)
    q0, qd0 = np.asarray(first.pipeline_state.qpos), np.asarray(first.pipeline_state.qvel)
    closedloop.run_c(env, policy, reset_keys, policy_keys, q0, qd0)  # compile
    seconds = {}
    benchmark.pedantic(closedloop.run_c, args=(env, policy, reset_keys, policy_keys, q0, qd0),
                       kwargs=dict(seconds=seconds), rounds=3, iterations=1)
    benchmark.extra_info.update(versions(), engine="c", episodes=EPISODES, steps=STEPS,
                                episodes_per_s=EPISODES / benchmark.stats.stats.mean,
                                outside_c_share=seconds["policy"] / (seconds["policy"] + seconds["c"]))


_RSS = """
import resource, sys, jax
jax.config.update("jax_enable_x64", True)
sys.path.insert(0, {here!r})
from test_closedloop import _random_policy
from mjxdiff.tools import closedloop
env = closedloop.make_env("inverted_pendulum")
closedloop.run(env, _random_policy(env), 16, {steps})
print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
"""


def _random_policy(env):
    network = ppo_networks.make_ppo_networks(env.observation_size, env.action_size)
    key = jax.random.PRNGKey(0)
    normalizer = running_statistics.init_state(jax.ShapeDtypeStruct((env.observation_size,), jnp.float64))
    params = (normalizer, network.policy_network.init(key), network.value_network.init(key))
    return ppo_networks.make_inference_fn(network)(params, deterministic=True)


@pytest.mark.parametrize("steps", [200, 2000])
def test_streamed_peak_memory(benchmark, steps):
    """Peak resident memory (MiB) of a whole closed-loop comparison (MJX, C, C perturbed; 16
    episodes), in a fresh process: streamed in chunks, it should not grow with the length."""
    import os
    import subprocess
    import sys

    here = os.path.dirname(os.path.abspath(__file__))
    out = benchmark.pedantic(lambda: subprocess.run([sys.executable, "-c", _RSS.format(here=here, steps=steps)],
                                                    capture_output=True, text=True, check=True).stdout,
                             rounds=1, iterations=1)
    benchmark.extra_info.update(versions(), steps=steps, episodes=16, peak_rss_mib=float(out.split()[-1]))
