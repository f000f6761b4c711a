"""MuJoCo Warp beside MJX and C on the same batch (pendulum, cartpole, ant: 32 members x 200
steps): steps/s of the three engines, and MJWarp's kernel compile seconds, cold (an empty
kernel cache, in a fresh process) and warm (the cache from the cold run, a fresh process).

Run: ``python -m pytest benchmarks/test_mjwarp.py --benchmark-only`` (needs mjxdiff[warp])."""

import os
import subprocess
import sys

import pytest

pytest.importorskip("mujoco_warp")

from mjxdiff.engine.engines import CEngine, MJXEngine
from mjxdiff.input.inputs import make_inputs
from mjxdiff.engine.mjwarp import MJWarpEngine
from mjxdiff.output.report import versions
from mjxdiff.input.scenario import load_model, load_scenario

BATCH, STEPS = 32, 200
SCENARIOS = ("pendulum", "cartpole", "ant")


@pytest.fixture(scope="module", params=SCENARIOS)
def inputs(request):
    scenario = load_scenario(request.param)
    return request.param, make_inputs(scenario, load_model(scenario), 0, BATCH, STEPS)


@pytest.mark.parametrize("engine", ["c", "mjx", "warp"])
def test_steps_per_second(benchmark, inputs, engine):
    name, inputs = inputs
    run = {"c": CEngine(), "mjx": MJXEngine(), "warp": MJWarpEngine()}[engine]
    run.rollout(inputs)  # compile / load kernels
    benchmark.pedantic(run.rollout, args=(inputs,), rounds=3, iterations=1)
    benchmark.extra_info.update(versions(), engine=engine, scenario=name, batch=BATCH, steps=STEPS,
                                steps_per_s=BATCH * STEPS / benchmark.stats.stats.mean)


_ONE = """
import time, sys
from mjxdiff.engine import engines
engines.configure_jax("float32", {cache!r})
from mjxdiff.input.inputs import make_inputs
from mjxdiff.engine.mjwarp import MJWarpEngine
from mjxdiff.input.scenario import load_model, load_scenario
s = load_scenario("pendulum")
inputs = make_inputs(s, load_model(s), 0, 8, 2)
t = time.perf_counter()
MJWarpEngine().rollout(inputs)
print(time.perf_counter() - t)
"""


def test_kernel_compile_cold_and_warm(benchmark, tmp_path):
    """Seconds of MJWarp's first two steps of a pendulum in a fresh process: with an empty kernel
    cache (compiling) and again with the cache the first run filled (loading)."""
    cache = str(tmp_path / "cache")

    def first_steps():
        out = subprocess.run([sys.executable, "-c", _ONE.format(cache=cache)], capture_output=True, text=True,
                             check=True, env=dict(os.environ, MJXDIFF_CACHE=cache))
        return float(out.stdout.split()[-1])

    cold = first_steps()
    warm = benchmark.pedantic(first_steps, rounds=1, iterations=1)
    benchmark.extra_info.update(versions(), cold_s=cold, warm_s=warm)
