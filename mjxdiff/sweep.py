"""Runs scenarios end to end: scenario -> inputs -> both engines -> verdict.

One scenario's failure never stops the others: bad input, an MJX
``NotImplementedError`` or a crash inside an engine becomes that scenario's
status, and the sweep goes on.
"""

from __future__ import annotations

import dataclasses
import sys
import time
from typing import Callable, Iterable, Sequence

from mjxdiff import engines
from mjxdiff.engines import CEngine, MJXEngine, UnsupportedError
from mjxdiff.inputs import make_inputs
from mjxdiff.scenario import Scenario, ScenarioError, load_model
from mjxdiff.noise import noise_floor
from mjxdiff.verdict import ScenarioResult, judge, rangefinder_mask

__all__ = ["SweepConfig", "run_scenario", "sweep"]


@dataclasses.dataclass(frozen=True)
class SweepConfig:
    """Settings shared by every scenario of a sweep.

    Attributes:
      seed: master seed for all randomization.
      batch: overrides each scenario's batch size when set.
      steps: overrides each scenario's horizon when set.
      precision: ``float64`` or ``float32`` (MJX side; C is always float64).
      quick: a smoke run: batch <= 4 and steps <= 50.
      threshold: least fraction of batch members within tolerance for a scenario to pass.
      envelope: judge against the chaos envelope from C's self-divergence
        (:mod:`mjxdiff.noise`); False holds errors to the fixed tolerances only.
    """

    seed: int = 0
    batch: int | None = None
    steps: int | None = None
    precision: str = "float64"
    quick: bool = False
    threshold: float = 0.95
    envelope: bool = True

    def sizes(self, scenario: Scenario) -> tuple[int, int]:
        batch = self.batch or scenario.batch
        steps = self.steps or scenario.steps
        if self.quick:
            batch, steps = min(batch, 4), min(steps, 50)
        return batch, steps


def _one_line(e: BaseException) -> str:
    return " ".join(f"{type(e).__name__}: {e}".split())


def run_scenario(scenario: Scenario, config: SweepConfig = SweepConfig(),
                 mjx_engine: MJXEngine | None = None, c_engine: CEngine | None = None) -> ScenarioResult:
    """Sweeps one scenario and returns its verdict; never raises for bad input."""
    batch, steps = config.sizes(scenario)
    tol = scenario.tolerance.for_precision(config.precision)
    info = dict(batch=batch, steps=steps, model=str(scenario.model), exercises=list(scenario.exercises),
                notes=scenario.notes)
    base = dict(name=scenario.name, tolerances=tol.as_dict())
    t0 = time.perf_counter()
    try:
        m = load_model(scenario)
        inputs = make_inputs(scenario, m, config.seed, batch, steps)
    except ScenarioError as e:
        return ScenarioResult(status="error", error_kind="input", message=str(e), info=info, **base)
    info["factors"] = sorted(inputs.factors)
    t1 = time.perf_counter()
    try:
        traj_c = (c_engine or CEngine()).rollout(inputs)
    except Exception as e:  # noqa: BLE001 - reported as this scenario's error, the sweep goes on
        return ScenarioResult(status="error", error_kind="engine", message=f"MuJoCo C failed: {_one_line(e)}",
                              info=info, **base)
    t2 = time.perf_counter()
    compiles = engines.compile_count()
    try:
        traj_mjx = (mjx_engine or MJXEngine()).rollout(inputs)
    except UnsupportedError as e:
        return ScenarioResult(status="unsupported", message=f"MJX does not support: {e.feature}",
                              info=info, **base)
    except Exception as e:  # noqa: BLE001
        return ScenarioResult(status="error", error_kind="engine", message=f"MJX failed: {_one_line(e)}",
                              info=info, **base)
    t3 = time.perf_counter()
    floor = None
    if config.envelope:
        floor = noise_floor(m, inputs, traj_c, config.precision, rangefinder_mask(m), c_engine)
    t4 = time.perf_counter()
    result = judge(scenario.name, m, traj_c, traj_mjx, tol, config.threshold, floor)
    t5 = time.perf_counter()
    info.update(seconds=dict(inputs=t1 - t0, c=t2 - t1, mjx=t3 - t2, noise_floor=t4 - t3, metrics=t5 - t4),
                mjx_compiles=engines.compile_count() - compiles,
                nq=m.nq, nv=m.nv, nu=m.nu, nsensordata=m.nsensordata)
    return dataclasses.replace(result, info=info)


class _Progress:
    """``[3/17] name ... status`` on stderr, only when stderr is a terminal (or forced)."""

    def __init__(self, total: int, enabled: bool | None = None):
        self.total = total
        self.enabled = sys.stderr.isatty() if enabled is None else enabled
        self.t0 = time.perf_counter()

    def start(self, i: int, name: str) -> None:
        if self.enabled:
            print(f"[{i + 1}/{self.total}] {name} ... ({time.perf_counter() - self.t0:.0f} s elapsed)",
                  file=sys.stderr, flush=True)


def sweep(scenarios: Sequence[Scenario], config: SweepConfig = SweepConfig(),
          progress: bool | None = None,
          on_result: Callable[[ScenarioResult], None] | None = None) -> list[ScenarioResult]:
    """Runs every scenario in order, returning one verdict each."""
    mjx_engine, c_engine = MJXEngine(), CEngine()
    bar = _Progress(len(scenarios), progress)
    results = []
    for i, scenario in enumerate(scenarios):
        bar.start(i, scenario.name)
        result = run_scenario(scenario, config, mjx_engine, c_engine)
        results.append(result)
        if on_result:
            on_result(result)
    return results


def exit_code(results: Iterable[ScenarioResult]) -> int:
    """0 consistent, 1 a divergence (fail or non-finite), 2 bad input."""
    results = list(results)
    if any(r.status == "error" and r.error_kind == "input" for r in results):
        return 2
    if any(r.status in ("fail", "error") for r in results):
        return 1
    return 0
