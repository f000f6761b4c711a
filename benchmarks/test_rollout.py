"""Rollout throughput of each engine, compile time and peak memory.

Run: ``python -m pytest benchmarks --benchmark-only`` (compare runs with
``--benchmark-autosave`` then ``--benchmark-compare``). Every result carries the
versions, batch size and horizon in ``extra_info``; ``steps_per_s`` counts
member-steps (batch x horizon) per second of wall time.
"""

import resource
import time

import pytest

from mjxdiff.engine import engines
from mjxdiff.engine.engines import CEngine, MJXEngine, device_count
from mjxdiff.input.inputs import make_inputs
from mjxdiff.output.report import versions
from mjxdiff.input.scenario import load_model, load_scenario
from mjxdiff.compare.noise import perturb
from mjxdiff.runner.sweep import SweepConfig, run_scenario
from mjxdiff.compare.verdict import judge

# small, medium and large model structures
SCENARIOS = ["pendulum", "cartpole", "ant"]
BATCH, STEPS = 32, 200


def _peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _inputs(name):
    scenario = load_scenario(name)
    m = load_model(scenario)
    return make_inputs(scenario, m, seed=0, batch=BATCH, steps=STEPS)


def _extra(benchmark, **info):
    benchmark.extra_info.update(versions())
    benchmark.extra_info.update(batch=BATCH, steps=STEPS, jax_cpu_devices=device_count(), **info)


@pytest.mark.parametrize("name", SCENARIOS)
def test_c_rollout(benchmark, name):
    inputs = _inputs(name)
    engine = CEngine()
    benchmark.pedantic(engine.rollout, args=(inputs,), rounds=5, iterations=1, warmup_rounds=1)
    _extra(benchmark, engine="c", steps_per_s=BATCH * STEPS / benchmark.stats.stats.mean,
           peak_rss_mib=_peak_rss_mib())


@pytest.mark.parametrize("name", SCENARIOS)
def test_mjx_rollout(benchmark, name):
    inputs = _inputs(name)
    engine = MJXEngine()
    engines.clear_compiled()
    t0 = time.perf_counter()
    engine.rollout(inputs)  # compile (or load from the persistent cache) + one run
    first = time.perf_counter() - t0
    benchmark.pedantic(engine.rollout, args=(inputs,), rounds=3, iterations=1)
    run = benchmark.stats.stats.mean
    _extra(benchmark, engine="mjx", steps_per_s=BATCH * STEPS / run, compile_s=first - run,
           peak_rss_mib=_peak_rss_mib())


@pytest.mark.parametrize("rerun", [True, False], ids=["with-rerun", "without-rerun"])
@pytest.mark.parametrize("name", SCENARIOS)
def test_metrics_overhead(benchmark, name, rerun):
    """Metrics + verdict on finished trajectories, with the noise floor's perturbed C rerun (what
    ``--noise-floor always`` adds) or without it (a calm scenario on demand), against the two
    rollouts' time."""
    inputs = _inputs(name)
    scenario = load_scenario(name)
    c_engine, mjx_engine = CEngine(), MJXEngine()
    mjx_engine.rollout(inputs)
    t0 = time.perf_counter()
    traj_c, traj_mjx = c_engine.rollout(inputs), mjx_engine.rollout(inputs)
    rollouts = time.perf_counter() - t0
    verdict = lambda: judge(name, inputs.models[0], traj_c, traj_mjx, scenario.tolerance,
                            perturbed=c_engine.rollout(perturb(inputs, "float64")) if rerun else None)
    result = benchmark.pedantic(verdict, rounds=3, iterations=1, warmup_rounds=1)
    assert result.status == "pass", result.message
    _extra(benchmark, rollouts_s=rollouts, metrics_over_rollouts=benchmark.stats.stats.mean / rollouts)


@pytest.mark.parametrize("noise_floor", ["on-demand", "always"])
def test_sweep_end_to_end(benchmark, noise_floor):
    """Verified scenario-steps per second for a whole sweep of the three scenarios."""
    config = SweepConfig(batch=BATCH, steps=STEPS, noise_floor=noise_floor)
    scenarios = [load_scenario(n) for n in SCENARIOS]
    for s in scenarios:  # warm the compile cache
        run_scenario(s, config)
    results = benchmark.pedantic(lambda: [run_scenario(s, config) for s in scenarios], rounds=2, iterations=1)
    assert all(r.status == "pass" for r in results), [r.message for r in results]
    _extra(benchmark, scenarios=SCENARIOS,
           steps_per_s=len(SCENARIOS) * BATCH * STEPS / benchmark.stats.stats.mean)
