"""XLA compile time of a function a sweep runs a few times per compile: the verdict's per-piece
``error_series``, compiled with XLA's defaults and with :func:`mjxdiff.compat.jit_for_few_calls`'s
options (the sweep's choice).

Run: ``python -m pytest benchmarks/test_compile_few_calls.py --benchmark-only``. The persistent
compile cache is off while it runs: every round is a real XLA compile. ``extra_info`` holds the
shapes and the options.
"""

import itertools

import jax
import jax.numpy as jnp
import pytest

from mjxdiff import compat, metrics
from mjxdiff.engine.engines import CEngine
from mjxdiff.input.inputs import make_inputs
from mjxdiff.output.report import versions
from mjxdiff.input.scenario import load_model, load_scenario
from mjxdiff.compare.verdict import error_series, rangefinder_mask

OPTIONS = {"defaults": {}, "few_calls": compat.FAST_COMPILE if compat.fast_compile_validated()
           else compat.BALANCED_COMPILE}


@pytest.fixture(scope="module")
def lower():
    """Lowers the verdict's error series of a piece one step shorter per call: every round a new
    module, which no cache holds."""
    scenario = load_scenario("ant")
    m = load_model(scenario)
    traj = CEngine().rollout(make_inputs(scenario, m, seed=0, batch=8, steps=100))
    steps = itertools.count(100, -1)

    def piece():
        t = next(steps)
        cut = jax.tree.map(lambda x: x[:, :t] if x.ndim >= 2 else x, traj)
        plain = jax.jit(error_series.__wrapped__, static_argnames=("layout",))  # its options are the test's
        return (plain.lower(cut, cut, metrics.qpos_layout(m), jnp.asarray(rangefinder_mask(m))),), {}
    return piece


@pytest.fixture
def no_persistent_cache():
    before = jax.config.jax_enable_compilation_cache  # pyright: ignore[reportAttributeAccessIssue]
    jax.config.update("jax_enable_compilation_cache", False)
    yield
    jax.config.update("jax_enable_compilation_cache", before)


@pytest.mark.parametrize("options", list(OPTIONS))
def test_error_series_compile(benchmark, lower, no_persistent_cache, options):
    benchmark.pedantic(lambda lowered: lowered.compile(compiler_options=dict(OPTIONS[options]) or None),
                       setup=lower, rounds=3, iterations=1)
    benchmark.extra_info.update(versions())
    benchmark.extra_info.update(function="verdict.error_series", scenario="ant", batch=8, steps=100,
                                options=OPTIONS[options])
