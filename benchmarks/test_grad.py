"""Jacobians per second of each side: MJX (jax.jacfwd of one mjx.step, jitted, warm) and C
(mujoco.mjd_transitionFD, centred) on an ant-class and a humanoid-class model, one state each.

Run: ``python -m pytest benchmarks/test_grad.py --benchmark-only``."""

import jax
import pytest

from mjxdiff.tools import grad
from mjxdiff.output.report import versions
from mjxdiff.input.scenario import load_model, load_scenario


@pytest.fixture(scope="module", params=["ant", "humanoid"])
def state(request):
    scenario = load_scenario(request.param)
    m = load_model(scenario)
    return request.param, grad.sample_states(scenario, m, 1)[0]


@pytest.mark.parametrize("side", ["mjx", "c"])
def test_jacobians_per_second(benchmark, state, side):
    from mjxdiff.engine import digest

    name, (m, _, _, s) = state
    code = digest.code_digest()
    with jax.enable_x64(True):
        fn = (lambda: grad.mjx_jacobians(m, s, code)) if side == "mjx" else (lambda: grad.c_jacobians(m, s, grad.EPS))
        fn()  # compile
        benchmark.pedantic(fn, rounds=5, iterations=1)
    benchmark.extra_info.update(versions(), scenario=name, side=side, nv=m.nv, nu=m.nu,
                                jacobians_per_s=1 / benchmark.stats.stats.mean)
