"""Runs scenarios end to end: scenario -> inputs -> both engines -> verdict -> follow-up checks.

This module orchestrates: it prepares each scenario, runs the parts of its run in order and
hands out scenarios to worker threads. The parts are modules of their own: the memory and time
plan (:mod:`mjxdiff.runner.plan`), the streamed verdict (:mod:`mjxdiff.runner.stream`), the
checks after it (:mod:`mjxdiff.runner.followup`) and what they share on the scenario's thread
(:mod:`mjxdiff.runner.current`).

One scenario's failure never stops the others: bad input, an MJX
``NotImplementedError`` or a crash inside an engine becomes that scenario's
status, and the sweep goes on.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import sys
import time
import types
import warnings
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, Callable, Iterable, Sequence

import mujoco

from mjxdiff.compare import support, transfer
from mjxdiff.compare.noise import has_constraints
from mjxdiff.compare.verdict import FieldResult, ScenarioResult
from mjxdiff.engine import engines, export_cache
from mjxdiff.engine.digest import code_digest, code_read_once
from mjxdiff.engine.engines import CEngine, MJXEngine, UnsupportedError
from mjxdiff.engine.trajectory import Engine
from mjxdiff.errors import one_line
from mjxdiff.input import adjust
from mjxdiff.input.config import IMPLS, NOISE_FLOOR_MODES, SweepConfig  # noqa: F401 - public here
from mjxdiff.input.inputs import BatchedInputs, make_inputs
from mjxdiff.input.options import ENGINES
from mjxdiff.input.precision import Precision
from mjxdiff.input.scenario import LaterFeatureError, Scenario, ScenarioError, Tolerances, is_bundled, load_model
from mjxdiff.output import report, reproducer
from mjxdiff.runner import plan
from mjxdiff.runner.current import SCENARIO, BudgetSpent, clocked, jax_precision, out_of_time, phase, running
from mjxdiff.runner.followup import diagnose_failure, sharp, solver_floor, suspect_reference
from mjxdiff.runner.plan import OUT_OF_MEMORY, SLOW_STEP_S, layout, out_of_memory, release_compiled_if_crowded, stopped
from mjxdiff.runner.stream import Case, EngineFailed, verdict

__all__ = ["SweepConfig", "run_scenario", "sweep"]

# SweepConfig lives in mjxdiff.input.config (a reproducer reads one without the sweep); public here too


def run_scenario(scenario: Scenario, config: SweepConfig = SweepConfig(),
                 under_test: Engine | None = None, c_engine: CEngine | None = None) -> ScenarioResult:
    """Sweeps one scenario and returns its verdict; never raises for bad input.

    With ``config.reproducers`` set, a failing verdict carries the reproducer of its first
    divergent member (:mod:`mjxdiff.output.reproducer`) in ``pending``, to be written as
    ``<reproducers>/<name>-member<i>.json`` by the caller's output step
    (:func:`mjxdiff.output.report.write_pending`; :func:`mjxdiff.runner.pipeline.write` does it), the name made
    a plain file name (:func:`mjxdiff.output.report.safe_filename`) so it stays in that directory. The
    sweep itself writes nothing.
    """
    with running(config):
        prepared = _prepare(scenario, config)
        return _finish(prepared, under_test, c_engine)


@dataclasses.dataclass
class _Prepared:
    """A scenario made ready to run: its model and inputs, or the result that ends it early
    (bad input, a plan that does not fit); ``ahead`` is what compiling ahead did
    (:func:`_compile_ahead`); ``config`` the sweep's, with the plan's member group."""

    scenario: Scenario
    tol: Tolerances
    info: dict
    config: SweepConfig
    m: mujoco.MjModel | None = None
    inputs: BatchedInputs | None = None
    early: ScenarioResult | None = None
    ahead: dict | None = None
    plan_for: tuple[int, int] | None = None


def _prepare(scenario: Scenario, config: SweepConfig) -> _Prepared:
    """The scenario's model (adjusted for MJX), the plan that fits its limits
    (:func:`mjxdiff.runner.plan.fit`) and its batched inputs; bad input, or a plan that cannot
    fit, becomes its result."""
    batch, steps = config.sizes(scenario)
    tol = scenario.tolerance.for_precision(config.precision)
    info: dict[str, Any] = dict(batch=batch, steps=steps, model=str(scenario.model),
                                exercises=list(scenario.exercises), notes=scenario.notes)
    prepared = _Prepared(scenario, tol, info, config)
    t0, cpu0 = export_cache.clock(), time.process_time()
    try:
        m = load_model(scenario)
    except ScenarioError as e:
        later = isinstance(e, LaterFeatureError)
        prepared.early = ScenarioResult(name=scenario.name, status="unsupported" if later else "error",
                                        error_kind="" if later else "input", message=str(e),
                                        info=info, tolerances=tol.as_dict())
        return prepared
    try:
        m, adjusted = adjust.for_mjx(m, scenario.model_path, config.adjust, config.drop_unsupported,
                                     config.drop_costly)
    except Exception as e:  # noqa: BLE001 - the model stays as it is, and says why
        adjusted = [f"--drop-unsupported/--drop-costly-pairs could not rewrite the model: {one_line(e)}"]
    if adjusted:
        info["adjusted"] = adjusted
    prepared.m = m
    if capable(config, "estimate"):
        fit = plan.fit(m, config, info, batch, steps)
        batch, steps, prepared.config = fit.batch, fit.steps, fit.config
        if fit.stop is not None:
            prepared.early = ScenarioResult(name=scenario.name, status="error", error_kind=fit.stop[0],
                                            message=fit.stop[1], info=info, tolerances=tol.as_dict())
            return prepared
    try:
        inputs = make_inputs(scenario, m, config.seed, batch, steps)
    except ScenarioError as e:
        prepared.early = ScenarioResult(name=scenario.name, status="error", error_kind="input", message=str(e),
                                        info=info, tolerances=tol.as_dict())
        return prepared
    info.update(batch=batch, steps=steps, factors=sorted(inputs.factors),
                seconds=dict(inputs=export_cache.clock() - t0), cpu_seconds=dict(inputs=time.process_time() - cpu0))
    if scenario.randomize.values:
        info["set"] = {k: list(v) for k, v in sorted(scenario.randomize.values.items())}
    prepared.inputs = inputs
    # padded to the full run's group, a quick run steps every member of it: not where stepping is slow
    if config.quick and not info.get("plan", {}).get("changed") and (
            info.get("estimate", {}).get("step_s", 0.0) < SLOW_STEP_S):
        prepared.plan_for = dataclasses.replace(config, quick=False).sizes(scenario)
        prepared.inputs = dataclasses.replace(inputs, horizon=prepared.plan_for[1])
    return prepared


def _compile_ahead(scenario: Scenario, config: SweepConfig, under_test: Engine) -> _Prepared:
    """:func:`_prepare`, then MJX's rollout of the scenario compiled (best effort: a problem is
    left for the sweep to meet and report); run by a compile worker of :func:`sweep`."""
    t = time.perf_counter()
    with export_cache.tally() as work:
        prepared = _prepare(scenario, config)
        if prepared.early is None:
            assert prepared.inputs is not None  # a prepared scenario without an early result has its inputs
            groups, chunk = layout(prepared.m, prepared.inputs, prepared.config, under_test, prepared.plan_for)
            phase("compiling", estimate_s=prepared.info.get("estimate", {}).get("compile_s"))
            first = prepared.inputs.members(groups[0])
            under_test.compile_ahead(first, chunk)
    prepared.ahead = dict(work, wall=time.perf_counter() - t)
    return prepared


def _finish(prepared: _Prepared, under_test: Engine | None,
            c_engine: CEngine | None) -> ScenarioResult:
    """Runs a prepared scenario: both engines, the verdict, a reproducer of a failure."""
    changed = prepared.info.get("plan", {}).get("changed")
    advice = "; ".join(([f"plan: {', '.join(changed)}"] if changed else []) +
                       [prepared.info.get("estimate", {}).get("advice_line") or ""]).strip("; ")
    if prepared.early is not None:
        return _advised(prepared.early, advice)
    scenario, m, inputs, tol, config = prepared.scenario, prepared.m, prepared.inputs, prepared.tol, prepared.config
    assert inputs is not None  # a prepared scenario without an early result has its inputs
    result = _advised(run_inputs(scenario.name, m, inputs, tol, config, under_test, c_engine,
                                 dict(prepared.info, bundled=is_bundled(scenario), plan_for=prepared.plan_for),
                                 prepared.ahead), advice)
    if result.status == "fail" and config.reproducers is not None:
        result = _with_reproducer(result, scenario, inputs, tol, config)
    transfer = config.transfer and capable(config, "transfer") and result.status in ("pass", "fail")
    if transfer and out_of_time():
        result = dataclasses.replace(result, message=f"{result.message}; host-interface check not run: {BudgetSpent()}")
    elif transfer:
        result = _with_transfer(result, inputs, scenario.model_path, config.precision)
    return result


def _with_reproducer(result: ScenarioResult, scenario: Scenario, inputs: BatchedInputs, tol: Tolerances,
                     config: SweepConfig) -> ScenarioResult:
    """``result`` carrying the reproducer of its first divergent member (``pending``: the caller's
    output step writes it, :func:`mjxdiff.output.report.write_pending`)."""
    assert result.first_divergence is not None and config.reproducers is not None  # a failure names where
    member = result.first_divergence["member"]
    try:
        path = report.path_under(config.reproducers, f"{report.safe_filename(scenario.name)}-member{member}.json")
        doc = reproducer.document(scenario.name, member, inputs, scenario.model_path.read_text(), tol,
                                  config.as_dict(), report.result_dict(result))
    except Exception as e:  # noqa: BLE001 - the verdict stands without its reproducer
        return dataclasses.replace(result, message=f"{result.message}; reproducer not saved: {one_line(e)}",
                                   info={**result.info, "reproducer": None})
    return dataclasses.replace(result, pending=(("reproducer", str(path), doc),))


def _advised(result: ScenarioResult, advice: str | None) -> ScenarioResult:
    """``result`` with MJX's advice on its model (:meth:`mjxdiff.input.cost.Estimate.advice_line`) as the
    last part of its line, once."""
    if not advice or advice in result.message:
        return result
    return dataclasses.replace(result, message=f"{result.message}; {advice}")


def _with_transfer(result: ScenarioResult, inputs: BatchedInputs, model_path, precision: Precision) -> ScenarioResult:
    """``result`` with :func:`mjxdiff.compare.transfer.check_scenario_states` of member 0 in its ``info``
    and, when MJX's host interface disagrees with C, a failing ``transfer`` field."""
    t, cpu = export_cache.clock(), time.process_time()
    try:
        with jax_precision(precision):
            found, loaded = transfer.cached_check_scenario_states(
                export_cache.cache_root(), inputs.models[0], inputs.qpos[0], inputs.qvel[0], inputs.act[0],
                inputs.ctrl[0], 0.0, model_path, precision)
    except Exception as e:  # noqa: BLE001 - the trajectory verdict stands; say why this part is missing
        info = {**result.info, "transfer": dict(error=one_line(e))}
        return dataclasses.replace(result, info=info)
    info = {**result.info, "transfer": found.as_dict()}
    if loaded:
        info["checks_loaded"] = [*info.get("checks_loaded", []), "transfer"]
    info["seconds"] = {**info.get("seconds", {}), "transfer": export_cache.clock() - t}
    info["cpu_seconds"] = {**info.get("cpu_seconds", {}), "transfer": time.process_time() - cpu}
    if not found.mismatches:
        return dataclasses.replace(result, info=info)
    worst = max(found.mismatches, key=lambda x: x.error)
    first = found.mismatches[0]
    field = FieldResult(field="transfer", max_error=worst.error, tolerance=transfer.RTOL[precision],
                        first_step=first.state, member=0, object=f"{first.call}", growth_rate=0.0,
                        ratio=float("inf") if worst.error == float("inf") else worst.error / transfer.RTOL[precision])
    said = (f"MJX's host interface disagrees with MuJoCo C: {first.call} ({first.field}) at the C state after "
            f"step {first.state} of member 0: {first.detail}; {len(found.mismatches)} mismatch(es)")
    message = said if result.status == "pass" else f"{result.message}; also {said}"
    first_divergence = result.first_divergence or dict(field="transfer", step=first.state, time=None, member=0,
                                                        object=first.call, error=first.error,
                                                        tolerance=transfer.RTOL[precision])
    return dataclasses.replace(result, status="fail", message=message, fields=result.fields + (field,),
                               first_divergence=first_divergence, info=info)


def run_inputs(name: str, m, inputs: BatchedInputs, tol: Tolerances, config: SweepConfig = SweepConfig(),
               under_test: Engine | None = None, c_engine: CEngine | None = None,
               info: dict | None = None, ahead: dict | None = None) -> ScenarioResult:
    """Both engines on given inputs, then the verdict (and diagnosis of a failure).

    The comparison is streamed in pieces of :func:`mjxdiff.runner.plan.piece_steps` steps, so its
    memory does not grow with the horizon; a failing scenario's C trajectory
    is rerun in full for the diagnosis. MJX runs in ``config.precision``
    (``jax_enable_x64`` is set for the call and restored after it). ``ahead``: what a
    compile worker did for these inputs beforehand (its :func:`export_cache.tally` and
    ``wall`` seconds), counted in the scenario's compile numbers.
    """
    engines._ensure_safe_backend()  # noqa: SLF001 - mjxdiff's own helper
    with jax_precision(config.precision), export_cache.tally() as work:  # MJX's dtype follows the config
        result = _run_inputs(name, m, inputs, tol, config, under_test, c_engine, info)
    ahead = ahead or {}
    info = result.info
    info["seconds"]["compile"] = work.get("seconds", 0.0) + ahead.get("seconds", 0.0)
    info["compile_seconds"] = {k: work.get(k, 0.0) + ahead.get(k, 0.0) for k in report.COMPILE_PARTS}
    if ahead:
        info["seconds"]["compiled_ahead"] = ahead.get("wall", 0.0)
    if result.status != "error" or result.error_kind != "input":
        info.update(mjx_compiles=int(work.get("traced", 0) + ahead.get("traced", 0)),
                    mjx_loaded=int(work.get("loaded", 0) + ahead.get("loaded", 0)))
    return result


def _run_inputs(name: str, m, inputs: BatchedInputs, tol: Tolerances, config: SweepConfig,
                under_test: Engine | None, c_engine: CEngine | None,
                info: dict | None) -> ScenarioResult:
    """:func:`run_inputs` less its compile numbers: the streamed verdict (:func:`mjxdiff.runner.stream.verdict`),
    then the follow-up checks (:mod:`mjxdiff.runner.followup`); an engine's trouble or the budget
    running out becomes the result."""
    info = dict(info or {}, batch=inputs.batch, steps=inputs.steps)
    bundled = bool(info.pop("bundled", False))  # how a truncation is worded, not part of the result
    plan_for = info.pop("plan_for", None)  # the sizes a --quick run plans (and compiles) for
    seconds = info.setdefault("seconds", {})
    base: dict[str, Any] = dict(name=name, tolerances=tol.as_dict(), info=info)
    under_test, c_engine = under_test or simulator(config), c_engine or CEngine()
    info["impl"] = under_test.name
    info["features"] = list(support.model_features(m))
    clock: dict[str, Any] = {}  # seconds per engine and for the verdict, and how far the stepping got
    cpu = info.setdefault("cpu_seconds", {})
    case = Case(name, m, inputs, tol, config, under_test, c_engine, plan_for)
    t0 = time.monotonic()
    try:
        with clocked({}, "stepping", cpu):  # the engines and the verdict run at once: one CPU window
            result, counts = verdict(case, clock)
    except UnsupportedError as e:
        return ScenarioResult(status="unsupported", message=f"MJX does not support: {e.feature}", **base)
    except EngineFailed as e:
        engine = "MuJoCo C" if e.engine == "c" else "MJX"
        if e.engine != "c" and OUT_OF_MEMORY.search(str(e)):
            return ScenarioResult(status="error", error_kind="memory", message=out_of_memory(str(e), inputs, info),
                                  **base)
        return ScenarioResult(status="error", error_kind="engine", message=f"{engine} failed: {e}", **base)
    except BudgetSpent:
        return ScenarioResult(status="error", error_kind="budget", message=stopped(info, clock), **base)
    # a rerun costs what this verdict took (measured, whatever the machine's load) and a compile
    SCENARIO.rerun_s = max(getattr(SCENARIO, "rerun_s", 0.0),
                           time.monotonic() - t0 + info.get("estimate", {}).get("compile_s", 0.0))
    seconds.update(c=clock.get("c", 0.0), mjx=clock.get("mjx", 0.0), verdict=clock.get("verdict", 0.0))
    phase("verdict", result=dataclasses.replace(result, info=dict(info)))  # the guard keeps it, should a check overrun
    traj_c = drill = None
    if result.status == "fail" and config.envelope and has_constraints(m) and not any(
            d["engine"] == "mjx" for d in result.diverged_members):
        with clocked(seconds, "solver_floor", cpu):
            result, traj_c, drill, info["solver_floor"] = solver_floor(result, case, {})
    if result.status == "fail" and config.diagnose != "none":
        with clocked(seconds, "diagnosis", cpu):
            result = diagnose_failure(result, case, traj_c, drill)
    if config.reference == "c" and result.status in ("pass", "fail"):
        result = sharp(result, case, traj_c, info, bundled)
    if config.reference == "c":
        result = suspect_reference(result, m, info)
    if counts.get("xla") is not None:
        info["xla"] = counts.pop("xla")
    info.update(mjx_code=code_digest(),
                integrator=mujoco.mjtIntegrator(m.opt.integrator).name[len("mjINT_"):].lower(),
                nq=m.nq, nv=m.nv, nu=m.nu, neq=m.neq,
                nsensordata=m.nsensordata, **counts)
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


def _holding(engine: Engine):
    """``engine.holding()`` (one prepared, compiled piece per model set within a scenario) where
    the engine has it (MJX), else nothing."""
    return engine.holding() if isinstance(engine, MJXEngine) else contextlib.nullcontext()


def default_compile_workers() -> int:
    """Scenario workers of a sweep: one per core (XLA compiles a module, and steps a rollout,
    on about one core), at most :data:`MAX_COMPILE_WORKERS` (each compile holds up to ~1 GiB)."""
    return max(1, min(engines.CORES, MAX_COMPILE_WORKERS))


#: Most compile workers :func:`default_compile_workers` gives a sweep.
MAX_COMPILE_WORKERS = 4


def sweep(scenarios: Sequence[Scenario], config: SweepConfig = SweepConfig(),
          progress: bool | None = None,
          on_result: Callable[[ScenarioResult], None] | None = None,
          on_event: Callable[[int, str, dict], None] | None = None) -> list[ScenarioResult]:
    """Runs every scenario, returning one verdict each, in order.

    ``config.compile_workers`` threads (default one per core) each take the next scenario
    and run all of it: prepare, compile MJX's rollout, step both engines, judge. A cold
    sweep is mostly XLA compiling, on about one core per module, and a warm one mostly
    stepping and judging, which XLA and MuJoCo C also do on about one core each, so
    scenarios side by side keep every core busy either way. This thread hands out at most
    twice as many scenarios as there are workers (bounding memory) and reports the results
    in order; results are those of running the scenarios one by one (each worker sets its own
    precision: :func:`mjxdiff.runner.current.jax_precision`). With no workers, the scenarios run
    here, one by one.

    ``on_event(index, phase, detail)`` hears, from the thread running scenario ``index``, what
    it does: ``preparing``, ``estimated`` (``line``, ``compile_s``, ``member_bytes``,
    ``stepping_s``: MJX's cost, :mod:`mjxdiff.input.cost`), ``compiling``, ``stepping``, ``one-step
    check``, ``diagnosing``, ``finished`` (``result``: the verdict, as soon as it is known).
    Memory and time limits that hold even while XLA compiles are :func:`mjxdiff.runner.guard.sweep`'s.
    """
    # MJX warns once per mesh with a large coplanar face; the estimate turns that into one line
    # of the scenario's result (mjxdiff.input.cost.Estimate.advice_line)
    warnings.filterwarnings("ignore", message=r"Mesh .* has a coplanar face")
    under_test, c_engine = simulator(config), CEngine()
    bar = _Progress(len(scenarios), progress)
    workers = default_compile_workers() if config.compile_workers is None else config.compile_workers
    pool = ThreadPoolExecutor(workers, thread_name_prefix="mjxdiff-scenario") if workers else None
    futures: dict[int, Future] = {}

    def run(i: int, scenario: Scenario) -> ScenarioResult:
        hook = functools.partial(on_event, i) if on_event is not None else None
        with jax_precision(config.precision), running(config, hook), _holding(under_test):
            phase("preparing")
            prepared = _compile_ahead(scenario, config, under_test) if pool is not None else _prepare(scenario, config)
            result = _finish(prepared, under_test, c_engine)
            phase("finished", result=result)  # before its turn comes to be reported in order
            return result

    def submit(i: int) -> None:
        if pool is not None and i < len(scenarios):
            futures[i] = pool.submit(run, i, scenarios[i])

    results = []
    with code_read_once():  # one reading of the code serves the whole sweep
        try:
            for i in range(2 * workers):
                submit(i)
            for i, scenario in enumerate(scenarios):
                submit(i + 2 * workers)
                bar.start(i, scenario.name)
                try:
                    result = futures.pop(i).result() if i in futures else run(i, scenario)
                except Exception as e:  # noqa: BLE001 - one scenario's trouble stays that scenario's
                    result = ScenarioResult(name=scenario.name, status="error", error_kind="internal",
                                            message=f"mjxdiff itself failed on this scenario: {one_line(e)}")
                results.append(result)
                if on_result:
                    on_result(result)
                release_compiled_if_crowded()
        finally:
            if pool is not None:
                pool.shutdown(wait=True, cancel_futures=True)
    return results


def engine_class(impl: str) -> type:
    """The :class:`~mjxdiff.engine.trajectory.Engine` class of ``impl``
    (:data:`mjxdiff.input.options.ENGINES`; imported on first use: MuJoCo Warp is an extra)."""
    import importlib

    entry = ENGINES[impl]
    return getattr(importlib.import_module(entry.module), entry.name)


def capable(config: SweepConfig, capability: str) -> bool:
    """Whether the engine ``config`` judges offers ``capability`` (``Engine.capabilities``)."""
    return capability in engine_class(config.impl).capabilities


def simulator(config: SweepConfig) -> Engine:
    """The engine judged against C: :class:`MJXEngine`, or MuJoCo Warp's
    (:class:`mjxdiff.engine.mjwarp.MJWarpEngine`) for ``impl='warp'``, compiling as ``config.compile`` says."""
    return engine_class(config.impl)(compile=config.compile)


def exit_code(results: Iterable[ScenarioResult]) -> int:
    """0 consistent, 1 a divergence (fail, MJX non-finite) or an engine error (a crash, C
    itself unstable), 2 bad input."""
    results = list(results)
    if any(r.status == "error" and r.error_kind == "input" for r in results):
        return 2
    if any(r.status in ("fail", "error") for r in results):
        return 1
    return 0


class _CallableModule(types.ModuleType):
    """This module, callable as its :func:`sweep`: ``mjxdiff.runner.sweep`` is one object whichever came
    first, ``import mjxdiff.runner.sweep`` (which binds the module to the package) or the package's
    lazy ``mjxdiff.runner.sweep``, and ``mjxdiff.sweep(scenarios, config)`` runs a sweep either way."""

    def __call__(self, scenarios: Sequence[Scenario], config: SweepConfig = SweepConfig(),
                 **kwargs) -> list[ScenarioResult]:
        return sweep(scenarios, config, **kwargs)


sys.modules[__name__].__class__ = _CallableModule
