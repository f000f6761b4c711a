"""How hard XLA optimises a rollout changes compile time and stepping speed, never a verdict:
the same scenarios judged with rollouts compiled fast and with XLA's defaults agree (status,
first divergence, worst errors to rounding); ``auto`` picks fast for sweep-sized work."""

import pytest

from mjxdiff.engine import xla
from mjxdiff.input.scenario import load_scenario
from mjxdiff.runner.sweep import SweepConfig, run_scenario


@pytest.mark.parametrize("name", ["pendulum", "cartpole", "box_stack"])
def test_verdicts_do_not_depend_on_the_xla_options(name):
    results = {mode: run_scenario(load_scenario(name), SweepConfig(batch=4, steps=100, diagnose="none",
                                                                   compile=mode))
               for mode in ("fast", "optimized")}
    fast, optimized = results["fast"], results["optimized"]
    assert fast.info["xla"]["level"] == "fast" and optimized.info["xla"]["level"] == "optimized"
    assert fast.status == optimized.status == "pass", (fast.message, optimized.message)
    for a, b in zip(fast.fields, optimized.fields, strict=True):
        assert a.field == b.field and a.tolerance == b.tolerance
        # rounding-level differences of the two executables, amplified (box_stack is chaotic)
        # but far below the tolerance the verdict compares with
        assert abs(a.max_error - b.max_error) <= 0.1 * a.tolerance + 1e-12, (name, a.field, a.max_error, b.max_error)


class _Lowered:
    def __init__(self, flops):
        self.flops = flops

    def cost_analysis(self):
        return {"flops": self.flops}


def test_auto_compiles_fast_only_when_the_stepping_it_adds_is_small():
    budget_flops = xla.FAST_BUDGET_SECONDS / xla.FAST_SECONDS_PER_FLOP
    options, choice = xla.xla_options("auto", 300)(_Lowered(0.5 * budget_flops / 300))
    assert choice["level"] == "fast" and options == xla.FAST_COMPILE
    options, choice = xla.xla_options("auto", 10_000)(_Lowered(0.5 * budget_flops / 300))
    assert choice["level"] == "balanced" and options == xla.BALANCED_COMPILE
    assert xla.xla_options("optimized", 10)(_Lowered(1.0)) == ({}, {"mode": "optimized", "level": "optimized"})
    assert xla.xla_options("fast", 10**9)(_Lowered(1e12))[1]["level"] == "fast"
