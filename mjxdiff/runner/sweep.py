"""Runs scenarios end to end: scenario -> inputs -> both engines -> verdict.

One scenario's failure never stops the others: bad input, an MJX
``NotImplementedError`` or a crash inside an engine becomes that scenario's
status, and the sweep goes on.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import queue
import re
import sys
import threading
import time
import types
import warnings
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, Callable, Generator, Iterable, Iterator, Sequence, TypeVar

import jax
import mujoco
import numpy as np
from mujoco import mjx

from mjxdiff.compat import enable_x64
from mjxdiff.input.config import IMPLS, NOISE_FLOOR_MODES, SweepConfig  # noqa: F401 - public here
from mjxdiff.input.precision import Precision
from mjxdiff.errors import one_line
from mjxdiff.input import adjust, cost
from mjxdiff.compare import diagnose, onestep, reference, support, transfer
from mjxdiff.engine import engines, export_cache
from mjxdiff.output import report, reproducer
from mjxdiff.engine.engines import CEngine, MJXEngine, UnsupportedError
from mjxdiff.engine.trajectory import Engine, Trajectory
from mjxdiff.input.inputs import BatchedInputs, make_inputs
from mjxdiff.input.scenario import LaterFeatureError, Scenario, ScenarioError, Tolerances, is_bundled, load_model
from mjxdiff.compare.noise import SOLVER_MARGIN, STEP_JITTER, NoiseFloor, combine, converged, has_constraints, perturb
from mjxdiff.compare.verdict import TRUNCATION, FieldResult, Judge, ScenarioResult, rangefinder_mask


_T = TypeVar("_T")

__all__ = ["SweepConfig", "run_scenario", "sweep"]

# SweepConfig lives in mjxdiff.config (a reproducer reads one without the sweep); public here too


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
    with _running(config):
        prepared = _prepare(scenario, config)
        return _finish(prepared, under_test, c_engine)


#: The scenario a worker thread runs: its deadline (``time.monotonic()``) and its phase hook.
_SCENARIO = threading.local()


@contextlib.contextmanager
def _running(config: SweepConfig, hook: Callable[[str, dict], None] | None = None):
    """Sets this thread's scenario deadline (``config.budget``) and phase hook while it runs."""
    _SCENARIO.deadline = time.monotonic() + config.budget if config.budget else None
    _SCENARIO.hook, _SCENARIO.rerun_s = hook, 0.0
    try:
        yield
    finally:
        _SCENARIO.deadline = _SCENARIO.hook = None


def _phase(text: str, **detail) -> None:
    """Tells the phase hook (:func:`sweep`'s ``on_event``) what the scenario is doing now."""
    hook = getattr(_SCENARIO, "hook", None)
    if hook is not None:
        hook(text, detail)


def _out_of_time(rerun: bool = False) -> bool:
    """Whether the running scenario has spent its budget (``config.budget``); with ``rerun``,
    whether what is left is too short for another compile and rollout of it (the estimate's,
    :func:`_fit`): a rerun started then would be stopped from outside and take the verdict with it."""
    deadline = getattr(_SCENARIO, "deadline", None)
    need = getattr(_SCENARIO, "rerun_s", 0.0) if rerun else 0.0
    return deadline is not None and time.monotonic() + need > deadline


class BudgetSpent(Exception):
    """The scenario's budget ran out before this part of it could run."""

    def __init__(self):
        super().__init__("the scenario's budget (--budget) ran out")


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
    """The scenario's model (adjusted for MJX), the plan that fits its limits (:func:`_fit`) and
    its batched inputs; bad input, or a plan that cannot fit, becomes its result."""
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
    batch, steps = _fit(prepared, batch, steps)
    if prepared.early is not None:
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


def _fit(prepared: _Prepared, batch: int, steps: int) -> tuple[int, int]:
    """MJX's estimated cost of the prepared model (``info['estimate']``, :func:`mjxdiff.input.cost.estimate`)
    and the plan that fits the config's budget and memory (``info['plan']``, :func:`mjxdiff.input.cost.plan`):
    the batch and horizon to run (a smaller member group goes into ``prepared.config``), or an
    early ``error`` of kind ``budget`` or ``memory`` that says what to do."""
    config, info, m = prepared.config, prepared.info, prepared.m
    assert m is not None  # _prepare loads the model before planning its run
    if not capable(config, "estimate"):
        return batch, steps
    est = cost.estimate(m)
    info["estimate"] = est.as_dict()
    group = min(config.group_size or batch, batch)
    fit = cost.plan(est, batch, steps, group, config.budget, config.max_memory, cost.resident_bytes())
    _phase("estimated", line=est.line(), compile_s=est.compile_s, member_bytes=est.member_bytes,
           stepping_s=est.step_s * fit.batch * fit.steps)
    _SCENARIO.rerun_s = est.compile_s + est.step_s * fit.batch * fit.steps
    info["plan"] = dict(batch=fit.batch, steps=fit.steps, group=fit.group, changed=list(fit.changed),
                        budget=config.budget, max_memory=config.max_memory)
    if fit.stop and _refused_by_mjx(m):  # unsupported is the verdict, whatever it would cost
        return batch, steps
    if fit.stop:
        prepared.early = ScenarioResult(name=prepared.scenario.name, status="error", error_kind=fit.kind,
                                        message=fit.stop, info=info, tolerances=prepared.tol.as_dict())
    else:
        if fit.group < fit.batch:
            prepared.config = dataclasses.replace(prepared.config, group_size=fit.group)
        # slow stepping (hull-hull pairs) in short pieces: the budget is checked between pieces
        piece = max(1, int(PIECE_SECONDS // (est.step_s * fit.group)))
        if est.step_s >= SLOW_STEP_S and piece < fit.steps and config.piece_steps is None:
            prepared.config = dataclasses.replace(prepared.config, piece_steps=piece)
            info["plan"]["piece_steps"] = piece
    return fit.batch, fit.steps


#: Seconds of MJX stepping a piece may take (estimated) when a member-step takes at least
#: SLOW_STEP_S: the budget is checked between pieces.
PIECE_SECONDS = 10.0
SLOW_STEP_S = 0.01


def _refused_by_mjx(m) -> bool:
    """Whether MJX's ``put_model`` refuses ``m`` (the sweep then reports it ``unsupported``)."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            mjx.put_model(m)
    except NotImplementedError:
        return True
    except Exception:  # noqa: BLE001 - any other trouble is the sweep's to report
        return False
    return False


def _compile_ahead(scenario: Scenario, config: SweepConfig, under_test: Engine) -> _Prepared:
    """:func:`_prepare`, then MJX's rollout of the scenario compiled (best effort: a problem is
    left for the sweep to meet and report); run by a compile worker of :func:`sweep`."""
    t = time.perf_counter()
    with export_cache.tally() as work:
        prepared = _prepare(scenario, config)
        if prepared.early is None:
            assert prepared.inputs is not None  # a prepared scenario without an early result has its inputs
            groups, chunk = _plan(prepared.m, prepared.inputs, prepared.config, under_test, prepared.plan_for)
            _phase("compiling", estimate_s=prepared.info.get("estimate", {}).get("compile_s"))
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
    if transfer and _out_of_time():
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
        with _precision(precision):
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


#: Budget for the memory one piece of a rollout holds (records of C, C's perturbed rerun and
#: MJX, with XLA's scan buffers and the errors and bounds computed from them), MiB.
PIECE_BUDGET_MIB = 32
#: Shortest piece, steps: shorter ones spend more time in per-call overhead than they save.
MIN_PIECE_STEPS = 50
#: Budget for MJX's working set while it steps one group of members, MiB.
GROUP_BUDGET_MIB = 4096


def piece_steps(m, batch: int, steps: int, budget_mib: float = PIECE_BUDGET_MIB) -> int:
    """Steps per piece of a streamed comparison: equal pieces that fit ``budget_mib``.

    A member-step records ``nq + nv + na + nsensordata + 4`` numbers; measured
    on the ant (batch 64, 625-step pieces), a piece holds about 24 float64
    copies of them at its peak (both C rollouts, MJX's records on the device
    and on the host, the next MJX piece already running, the error and bound
    arrays), so K steps of B members take about
    ``192 (nq + nv + na + nsensordata + 4) B K`` bytes.
    """
    width = 192 * (m.nq + m.nv + m.na + m.nsensordata + 4)
    most = max(MIN_PIECE_STEPS, int(budget_mib * 2**20 // (width * batch)))
    pieces = -(-steps // most)
    return -(-steps // pieces)


def group_size(m, batch: int, budget_mib: float = GROUP_BUDGET_MIB) -> int:
    """Members MJX steps at once: all of them, unless their working set exceeds ``budget_mib``
    (:func:`mjxdiff.engine.engines.member_bytes` per member)."""
    per_member = cost.member_bytes(m)
    return max(1, min(batch, int(budget_mib * 2**20 // per_member))) if per_member else batch


def member_groups(batch: int, most: int) -> list[np.ndarray]:
    """Member indices in equal groups of at most ``most``, in order; the last group is padded
    with repeats of the last member, so that every group runs the same compiled function."""
    n = -(-batch // most)
    size = -(-batch // n)
    idx = np.minimum(np.arange(n * size), batch - 1)
    return [idx[i * size:(i + 1) * size] for i in range(n)]


def _plan(m, inputs: BatchedInputs, config: SweepConfig, under_test: Engine,
          plan_for: tuple[int, int] | None = None) -> tuple[list[np.ndarray], int]:
    """How the verdict steps ``inputs``: member groups (:func:`member_groups`) and steps per piece.

    ``plan_for`` (batch, steps): the sizes to plan for instead of the inputs' own, larger ones (a
    ``--quick`` run plans for the full sweep's): the one group of ``inputs`` is padded to the
    group those sizes would have and stepped in their pieces, so that both runs step one compiled
    piece (the quick run's horizon a run-time trip count of it) and a quick run after a full one,
    or before it, compiles nothing the other has not."""
    batch, steps = plan_for or (inputs.batch, inputs.steps)
    size = config.group_size or min(group_size(m, batch), under_test.batch_cap())
    groups = member_groups(inputs.batch, size)
    if plan_for is not None and len(groups) == 1:
        groups = [np.minimum(np.arange(size), inputs.batch - 1)]
    return groups, config.piece_steps or piece_steps(m, len(groups[0]), steps)


class _EngineFailed(Exception):
    def __init__(self, engine: str, error: BaseException):
        super().__init__(one_line(error))
        self.engine = engine


@contextlib.contextmanager
def _clock(seconds: dict[str, Any], key: str, cpu: dict[str, float] | None = None):
    """Adds the block's wall seconds less its compiling (:func:`export_cache.clock`) to ``seconds[key]``, so
    that a scenario's phases do not overlap; with ``cpu``, adds the process's CPU seconds over
    the block (compiling and other threads' work included) to ``cpu[key]``."""
    t, used = export_cache.clock(), time.process_time()
    try:
        yield
    finally:
        seconds[key] = seconds.get(key, 0.0) + max(export_cache.clock() - t, 0.0)
        if cpu is not None:
            cpu[key] = cpu.get(key, 0.0) + time.process_time() - used


@contextlib.contextmanager
def _engine_call(engine: str, seconds: dict[str, float]):
    """Wall time of the stepping added to ``seconds[engine]`` (:func:`_clock`: a compile in it
    is not stepping); a crash becomes :class:`_EngineFailed` (MJX's :class:`UnsupportedError`
    passes through)."""
    with _clock(seconds, engine):
        try:
            yield
        except UnsupportedError:
            raise
        except Exception as e:  # reported as this scenario's error, the sweep goes on
            raise _EngineFailed(engine, e) from e


def _timed(stream: Callable[[], Iterable[Trajectory]], engine: str,
           seconds: dict[str, float]) -> Iterator[Trajectory]:
    """The pieces of ``stream()`` (called now: MJX prepares and dispatches its first piece
    in that call), each call timed and guarded by :func:`_engine_call`."""
    with _engine_call(engine, seconds):
        it = iter(stream())

    def pieces():
        while True:
            with _engine_call(engine, seconds):
                piece = next(it, None)
            if piece is None:
                return
            yield piece

    return pieces()


def _rows(x, rows: int | slice):
    """Members of a piece (a Trajectory or a dict of (b, ...) arrays): the first ``rows``, or a slice."""
    rows = rows if isinstance(rows, slice) else slice(0, rows)
    return jax.tree.map(lambda a: a[rows], x)


def _ahead(items: Iterable, depth: int = 1) -> Generator:
    """The items of ``items``, produced by a background thread at most ``depth`` items ahead of the
    consumer; an exception there is raised here. Closing the generator stops the thread.

    MuJoCo C releases the GIL while it steps, so C's pieces are computed while
    MJX steps its own on the same cores: C fills the cycles MJX leaves idle
    (humanoid, 64 members, 200 steps: MJX alone 0.79 s; MJX with both C
    rollouts (reference and perturbed) in a thread 0.82 s; one after the other 0.96 s).
    """
    slots: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()

    def put(entry) -> bool:
        while not stop.is_set():
            try:
                slots.put(entry, timeout=0.05)
                return True
            except queue.Full:
                pass
        return False

    def produce() -> None:
        try:
            for item in items:
                if not put((True, item)):
                    return
            put((False, None))
        except BaseException as e:  # noqa: BLE001 - handed to the consumer
            put((False, e))

    # this thread's setting (thread-local) holds in the producer too; jax's Config declares no flags
    x64 = jax.config.jax_enable_x64  # pyright: ignore[reportAttributeAccessIssue]

    def produce_here() -> None:
        with enable_x64(x64):
            produce()

    worker = threading.Thread(target=produce_here, name="mjxdiff-c", daemon=True)
    worker.start()
    try:
        while True:
            more, item = slots.get()
            if not more:
                if item is not None:
                    raise item
                return
            yield item
    finally:
        stop.set()
        worker.join()


class _CPieces:
    """C's pieces of one group of members, (reference, perturbed rerun or None, converged rerun
    or None), computed in a background thread (:func:`_ahead`).

    Without the noise floor C steps the reference alone. :meth:`start_floor`
    restarts it from step 0 with the reference and its perturbed rerun (and,
    with ``solver``, its rerun with a converged solver) as one batch (fewer
    thread-pool rounds than separate batches; each member's rows are
    bit-identical to a run of its own) and feeds the noise floor the pieces it
    missed, so that the floor's running maxima are those of a rerun that ran
    from the start. C steps ~8x faster than MJX, so catching up costs little.
    """

    def __init__(self, c_engine: CEngine, group: BatchedInputs, chunk: int, precision: Precision,
                 seconds: dict[str, float], floor: bool, solver: bool = False):
        self.c_engine, self.group, self.chunk, self.seconds = c_engine, group, chunk, seconds
        self.precision: Precision = precision
        self.solver, self.floor = solver, floor
        self._pieces = self._open(floor)

    def _open(self, floor: bool) -> Generator[tuple[Trajectory, Trajectory | None, Trajectory | None], None, None]:
        group, stream = self.group, self.c_engine.stream
        if not floor:
            return _ahead((p, None, None) for p in _timed(lambda: stream(group, self.chunk), "c", self.seconds))
        batches = [group, perturb(group, self.precision)] + ([converged(group)] if self.solver else [])
        joined = functools.reduce(BatchedInputs.concat, batches)
        jitter = np.zeros(joined.batch)
        jitter[group.batch:2 * group.batch] = STEP_JITTER[self.precision]  # the perturbed rerun's rows
        pieces = _timed(lambda: stream(joined, self.chunk, jitter), "c", self.seconds)
        B = group.batch
        return _ahead(tuple(_rows(p, slice(i * B, (i + 1) * B)) if i < len(batches) else None for i in range(3))
                      for p in pieces)

    def __next__(self) -> tuple[Trajectory, Trajectory | None, Trajectory | None]:
        return next(self._pieces)

    def start_floor(self, until: int,
                    feed: Callable[[Trajectory, Trajectory, Trajectory | None, int], object]) -> float:
        """Restarts with the reruns; ``feed(reference, perturbed, converged, start)`` gets the
        pieces before step ``until``, and the next piece is the one starting there.
        Returns the seconds it took (C's time, mostly)."""
        t = export_cache.clock()
        self.close()
        self._pieces, self.floor, start = self._open(True), True, 0
        while start < until:
            reference, perturbed, solved = next(self)
            assert perturbed is not None  # opened with the floor just above
            feed(reference, perturbed, solved, start)
            start += reference.time.shape[1]
        return export_cache.clock() - t

    def close(self) -> None:
        self._pieces.close()


@dataclasses.dataclass(frozen=True)
class _Case:
    """What the rollout's verdict and every check after it read: the scenario's ``name``, its C
    model ``m`` (each member's own in ``inputs.models``), the inputs, tolerances and settings,
    the engine under test and MuJoCo C. A check on other inputs (the converged twin, an
    ablation) judges a :func:`dataclasses.replace` of it."""

    name: str
    m: mujoco.MjModel
    inputs: BatchedInputs
    tol: Tolerances
    config: SweepConfig
    under_test: Engine
    c_engine: CEngine
    plan_for: tuple[int, int] | None = None


def _verdict(case: _Case, seconds: dict[str, Any], solver: bool = False) -> tuple[ScenarioResult, dict[str, Any]]:
    """Streams both engines (and C's perturbed rerun) piece by piece into a :class:`Judge`.

    Members run in groups of at most :func:`group_size` (memory) and the MJX
    engine's :meth:`~mjxdiff.engine.engines.MJXEngine.batch_cap` (speed), steps in pieces of
    :func:`piece_steps`; ``seconds`` gains wall time per engine and for the verdict.
    With ``config.noise_floor == 'on-demand'`` a group's perturbed rerun starts (from step
    0) at its first piece with an error above the fixed tolerances: before that, no
    envelope could have changed the verdict. With ``solver`` (and the envelope on), C's
    rerun with a converged solver runs beside the perturbed one, and errors are judged
    against the larger of both floors (:func:`mjxdiff.compare.noise.combine`).

    Returns:
      The verdict, and the counts of ``groups``, ``pieces`` and ``noise_floor_members``
      (members whose perturbed rerun ran).

    Raises:
      UnsupportedError, _EngineFailed: from the engines.
    """
    name, m, inputs, tol, config, under_test, c_engine = (
        case.name, case.m, case.inputs, case.tol, case.config, case.under_test, case.c_engine)
    B, T = inputs.batch, inputs.steps
    groups, chunk = _plan(m, inputs, config, under_test, case.plan_for)
    judge = Judge(m, tol, B, T)
    floor = NoiseFloor(m, rangefinder_mask(m), B, T) if config.envelope else None
    solver_floor = NoiseFloor(m, rangefinder_mask(m), B, T, SOLVER_MARGIN) if floor and solver else None
    done: list[np.ndarray] = []
    for idx in groups:
        _phase("stepping", group=len(done) + 1, groups=len(groups))
        members = idx[:len(np.unique(idx))]  # the padding repeats come last
        n = len(members)
        group = inputs.members(idx)

        def feed(reference, perturbed, solved, at):
            """Both floors' envelopes of a piece, and which floor each value came from."""
            reference = _rows(reference, n)
            assert floor is not None  # fed only when the envelope is on
            envelope = floor.update(_rows(perturbed, n), reference, at, members)
            return combine(envelope, solver_floor and solver_floor.update(_rows(solved, n), reference, at, members))
        # MJX first: its first piece is stepping before C's thread starts
        mjx = _timed(lambda: under_test.stream(group, chunk), "mjx", seconds)
        # judged against MJX instead of C (MJX vs MJWarp): C still gives the envelope
        ref = _timed(lambda: MJXEngine(compile=config.compile).stream(group, chunk), "reference", seconds) \
            if config.reference == "mjx" else None
        start = 0
        # C in a thread, MJX dispatching its next piece before handing this one over: both engines
        # keep stepping while the verdict of a piece is computed
        with contextlib.closing(_CPieces(c_engine, group, chunk, config.precision, seconds,
                                         floor is not None and config.noise_floor == "always",
                                         solver_floor is not None)) as c:
            for piece_mjx in mjx:
                seconds["progress"] = (f"stepped {start} of {T} steps of member group {len(done) + 1} of "
                                       f"{len(groups)}")
                if _out_of_time():
                    raise BudgetSpent()
                piece_c, piece_p, piece_s = next(c)
                piece_ref = next(ref) if ref is not None else piece_c
                t = export_cache.clock()
                reference, simulated = _rows(piece_ref, n), _rows(piece_mjx, n)
                series = judge.errors(reference, simulated)
                if floor and not c.floor and judge.exceeds_tolerance(series):
                    t += c.start_floor(start, feed)
                    piece_c, piece_p, piece_s = next(c)
                envelope, source = feed(piece_c, piece_p, piece_s, start) if piece_p is not None else (None, None)
                judge.update(reference, simulated, envelope, start, members, series, source)
                start += piece_c.time.shape[1]
                if floor and not c.floor and judge.contacts_exceed_tolerance(members):
                    t += c.start_floor(start, feed)
                seconds["verdict"] = seconds.get("verdict", 0.0) + export_cache.clock() - t
        done.append(idx)
    with _clock(seconds, "verdict"):
        noise = floor if floor is not None and floor.fed.any() else None
        result = judge.result(name, config.threshold, noise, solver_floor if noise is not None else None)
    counts = dict(groups=len(groups), pieces=len(groups) * -(-T // chunk), xla=engines.last_choice(),
                  noise_floor_members=int(floor.fed.sum()) if floor is not None else 0)
    return result, counts


def run_inputs(name: str, m, inputs: BatchedInputs, tol: Tolerances, config: SweepConfig = SweepConfig(),
               under_test: Engine | None = None, c_engine: CEngine | None = None,
               info: dict | None = None, ahead: dict | None = None) -> ScenarioResult:
    """Both engines on given inputs, then the verdict (and diagnosis of a failure).

    The comparison is streamed in pieces of :func:`piece_steps` steps, so its
    memory does not grow with the horizon; a failing scenario's C trajectory
    is rerun in full for the diagnosis. MJX runs in ``config.precision``
    (``jax_enable_x64`` is set for the call and restored after it). ``ahead``: what a
    compile worker did for these inputs beforehand (its :func:`export_cache.tally` and
    ``wall`` seconds), counted in the scenario's compile numbers.
    """
    engines._ensure_safe_backend()  # noqa: SLF001 - mjxdiff's own helper
    with _precision(config.precision), export_cache.tally() as work:  # MJX's dtype follows the config
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
    case = _Case(name, m, inputs, tol, config, under_test, c_engine, plan_for)
    t0 = time.monotonic()
    try:
        with _clock({}, "stepping", cpu):  # the engines and the verdict run at once: one CPU window
            result, counts = _verdict(case, clock)
    except UnsupportedError as e:
        return ScenarioResult(status="unsupported", message=f"MJX does not support: {e.feature}", **base)
    except _EngineFailed as e:
        engine = "MuJoCo C" if e.engine == "c" else "MJX"
        if e.engine != "c" and _OUT_OF_MEMORY.search(str(e)):
            return ScenarioResult(status="error", error_kind="memory", message=_out_of_memory(str(e), inputs, info),
                                  **base)
        return ScenarioResult(status="error", error_kind="engine", message=f"{engine} failed: {e}", **base)
    except BudgetSpent:
        return ScenarioResult(status="error", error_kind="budget", message=_stopped(info, clock), **base)
    # a rerun costs what this verdict took (measured, whatever the machine's load) and a compile
    _SCENARIO.rerun_s = max(getattr(_SCENARIO, "rerun_s", 0.0),
                            time.monotonic() - t0 + info.get("estimate", {}).get("compile_s", 0.0))
    seconds.update(c=clock.get("c", 0.0), mjx=clock.get("mjx", 0.0), verdict=clock.get("verdict", 0.0))
    _phase("verdict", result=dataclasses.replace(result, info=dict(info)))  # the guard keeps it, should a check overrun
    traj_c = drill = None
    if result.status == "fail" and config.envelope and has_constraints(m) and not any(
            d["engine"] == "mjx" for d in result.diverged_members):
        with _clock(seconds, "solver_floor", cpu):
            result, traj_c, drill, info["solver_floor"] = _solver_floor(result, case, {})
    if result.status == "fail" and config.diagnose != "none":
        with _clock(seconds, "diagnosis", cpu):
            result = _diagnose(result, case, traj_c, drill)
    if config.reference == "c" and result.status in ("pass", "fail"):
        result = _sharp(result, case, traj_c, info, bundled)
    if config.reference == "c":
        result = _suspect_reference(result, m, info)
    if counts.get("xla") is not None:
        info["xla"] = counts.pop("xla")
    info.update(mjx_code=export_cache.code_digest(),
                integrator=mujoco.mjtIntegrator(m.opt.integrator).name[len("mjINT_"):].lower(),
                nq=m.nq, nv=m.nv, nu=m.nu, neq=m.neq,
                nsensordata=m.nsensordata, **counts)
    return dataclasses.replace(result, info=info)


_OUT_OF_MEMORY = re.compile(r"RESOURCE_EXHAUSTED|[Oo]ut of memory")


def _out_of_memory(error: str, inputs: BatchedInputs, info: dict) -> str:
    """The one-line error of an XLA allocation MJX's stepping could not make, with the batch that fits."""
    found = re.search(r"allocating (\d+) bytes", error)
    group = info.get("plan", {}).get("group") or inputs.batch
    line = f"out of memory: MJX's stepping of {group} member(s) at once"
    if found:
        per = int(found.group(1)) / group
        limit = info.get("plan", {}).get("max_memory") or cost.available_bytes()
        fits = int(max(limit - cost.resident_bytes(), 0) // max(per, 1))
        line += f" asked XLA for {cost.human_bytes(int(found.group(1)))} (~{cost.human_bytes(per)} per member)"
        line += (f"; a batch of {fits} would fit (--batch {fits})" if fits else
                 "; not even one member fits: --drop-costly-pairs, or primitive collision geoms")
    return line + f" [{' '.join(error.split())[:160]}]"


def _stopped(info: dict, clock: dict[str, float]) -> str:
    """The one-line error of a scenario stopped by its budget: how far it got, and the estimate."""
    done = clock.get("progress", "MJX's first piece of stepping had not come back")
    est = info.get("estimate", {}).get("line", "")
    return f"stopped at its budget of {info.get('plan', {}).get('budget'):g} s: {done}" + (f"; {est}" if est else "")


def _drill(result: ScenarioResult, inputs: BatchedInputs, traj_c: Trajectory, precision: Precision,
           engine: Engine | None = None, step: int | None = None) -> diagnose.DrillDown:
    """The stage drill-down at the state before the first divergent step (or before ``step``, of
    the same member)."""
    assert result.first_divergence is not None  # drilled down only for a failure
    member: int = result.first_divergence["member"]
    at: int = result.first_divergence["step"] if step is None else step
    return diagnose.drill_down(inputs.models[member], *diagnose.state_before(inputs, traj_c, member, at),
                               precision=precision, member=member, step=at, engine=engine)


#: How many states before the first divergence the drill-down tries where every stage agrees at it.
DRILL_BACK = 16


def _earlier_difference(result: ScenarioResult, inputs: BatchedInputs, traj_c: Trajectory, precision: Precision,
                        engine: Engine | None = None) -> diagnose.DrillDown | None:
    """The drill-down at the latest of the :data:`DRILL_BACK` states before the first divergent step
    where a stage differs, or None: where every stage agrees at the state the error left its bound,
    the step that set it off (a contact made one step apart, a landing) lies before it."""
    assert result.first_divergence is not None
    step: int = result.first_divergence["step"]
    for k in range(step - 1, max(step - DRILL_BACK, 0) - 1, -1):
        drill = _drill(result, inputs, traj_c, precision, engine, step=k)
        if drill.first_field:
            return drill
    return None


def _solver_floor(result: ScenarioResult, case: _Case, clock: dict[str, float]):
    """A second look at a failure that starts in the constraint stage (or in no forward stage at
    all, the step's own use of the solver): judged again against the
    larger of the rounding envelope and the solver floor (C against C with a converged solver,
    :mod:`mjxdiff.compare.noise`). Chaos amplifying where a solver stopped within its own settings
    then passes; a constraint MJX gets wrong does not.

    Returns:
      (result, C's whole trajectory or None, the drill-down or None, what was checked for
      ``info['solver_floor']``); the trajectory and drill-down are reused by the diagnosis.
      Never raises.
    """
    inputs, config = case.inputs, case.config
    traj_c = drill = None
    if _out_of_time(rerun=True):  # its drill-down compiles MJX's stages, its rerun steps again
        return result, None, None, dict(status=f"not run: {BudgetSpent()}")
    try:
        traj_c = case.c_engine.rollout(inputs)
        drill = _drill(result, inputs, traj_c, config.precision, case.under_test)
        check: dict[str, Any] = dict(
            first_stage=drill.first_stage, first_field=drill.first_field, object=drill.object, contact=drill.contact,
            element=drill.element, beside_contacts=drill.beside_contacts, margin=SOLVER_MARGIN,
            status=f"not needed: the divergence starts in the {drill.first_stage} stage")
        # None: every stage of one forward agrees, so the difference is in what a step does with
        # them, and under RK4 a step solves the constraints four times, from states the drill-down
        # does not see (control-suite cartpole: 1.9e-6 at step 175, gone with a converged solver)
        if drill.first_stage not in ("constraint", "acceleration", None):
            return result, traj_c, drill, check
        if _out_of_time(rerun=True):
            raise BudgetSpent()
        second, _ = _verdict(case, clock, solver=True)
    except Exception as e:  # noqa: BLE001 - the verdict stands
        return result, traj_c, drill, dict(status=f"could not run: {one_line(e)}")
    first = result.first_divergence
    assert first is not None  # a failure names where it starts
    check["status"] = second.status
    gap = result.field(first["field"]) if any(f.field == first["field"] for f in result.fields) else None
    check["first"] = first
    check["gap"] = dict(field=first["field"], object=first["object"], step=first["step"],
                        error=gap.max_error if gap else first["error"], steps=inputs.steps,
                        tolerance=first["tolerance"])
    if second.status != "pass":
        return result, traj_c, drill, check
    held = [f.field for f in second.fields if f.floor == "solver"]
    where = (f"starts in the {drill.first_stage} stage ({drill.first_field}, {drill.object})" if drill.first_stage
             else "starts where every forward stage agrees (in what the step's constraint solves do)")
    message = (f"{second.message}; within C's own solver freedom: the divergence of {first['field']} at step "
               f"{first['step']} {where} and stays within {SOLVER_MARGIN:g}x C's divergence from its converged self"
               + (f" (solver floor bounds {', '.join(held)})" if held else ""))
    return dataclasses.replace(second, message=message), traj_c, drill, check


def _sharp(result: ScenarioResult, case: _Case, traj_c: Trajectory | None, info: dict,
           bundled: bool = False) -> ScenarioResult:
    """The checks that stay sharp where the rollout's verdict cannot: the one-step check
    (:func:`_onestep`, with ``config.onestep``), then, where the rollout's pass was held only by
    the solver floor, or was weak on a model whose solver settings the one-step check found not
    converged, the converged twin (:func:`_twin`); a pass held only by the solver floor becomes a
    ``solver truncation`` failure (:func:`_truncation`). Never raises."""
    if _out_of_time(rerun=True):
        return dataclasses.replace(result, message=f"{result.message}; one-step check and converged twin not run: "
                                                   f"{BudgetSpent()}")
    excused = result.status == "pass" and info.get("solver_floor", {}).get("status") == "pass"
    found: dict = {}
    if case.config.onestep:
        _phase("one-step check")
        with _clock(info["seconds"], "onestep", info["cpu_seconds"]):
            result, found, traj_c = _onestep(result, case, traj_c, evidence=excused or bool(result.weak))
        info["onestep"] = found
    converged_ = found.get("solver", {}).get("converged", True)
    twin = None
    if result.status == "pass" and (excused or (result.weak and not converged_)) and case.config.quick:
        info["twin"] = twin = dict(status="skipped", message=QUICK_SKIPS["twin"])
        result = dataclasses.replace(result, message=f"{result.message}; {QUICK_SKIPS['twin']}")
    elif result.status == "pass" and (excused or (result.weak and not converged_)):
        with _clock(info["seconds"], "twin", info["cpu_seconds"]):
            result, info["twin"] = _twin(result, case, {})
        twin = info["twin"]
    if result.status == "pass" and excused:
        result = _truncation(result, case.m, info["solver_floor"], found, twin, bundled=bundled)
    return result


def _suspect_reference(result: ScenarioResult, m, info: dict) -> ScenarioResult:
    """A failure on a model where the installed C is known to be wrong (:func:`reference.suspect`)
    says so, with what to run to rule C out (``info['suspect_reference']``); a pass is left alone."""
    found = reference.suspect(m) if result.status == "fail" else None
    if found is None:
        return result
    info["suspect_reference"] = found
    return dataclasses.replace(result, message=f"{result.message}; {reference.caveat(found)}")


def _drilled(found: dict, drill: Callable[[], diagnose.DrillDown]) -> diagnose.DrillDown | None:
    """``drill()``, its first stage, field, object and contact added to ``found``; None where it
    raised, the reason in ``found["drill_error"]`` (one line): the verdict stands without its
    drill-down, and says that it could not run."""
    try:
        result = drill()
    except Exception as e:  # noqa: BLE001 - any failure of the drill-down is reported, not raised
        found["drill_error"] = one_line(e, 300)
        return None
    found.update(first_stage=result.first_stage, first_field=result.first_field, stage_object=result.object,
                 contact=result.contact, beside_contacts=result.beside_contacts, stage_element=result.element)
    return result


def _onestep(result: ScenarioResult, case: _Case, traj_c: Trajectory | None,
             evidence: bool = False) -> tuple[ScenarioResult, dict, Trajectory | None]:
    """``result`` judged again by :func:`mjxdiff.compare.onestep.check` (kept in ``info['onestep']``): a
    failure there fails a passing scenario, naming the field, object, step and (from the stage
    drill-down at that state, with a converged solver) the first stage and field that differ; a
    failing scenario keeps its verdict and gains the one-step result as evidence. Never raises.

    Returns (result, what the check found, C's whole rollout or None)."""
    m, inputs, config, under_test, c_engine = case.m, case.inputs, case.config, case.under_test, case.c_engine
    try:
        traj_c = traj_c if traj_c is not None else c_engine.rollout(inputs)
        groups, chunk = _plan(m, inputs, config, under_test, case.plan_for)
        found = onestep.check(m, inputs, traj_c, case.tol, under_test, c_engine, config.precision, evidence=evidence,
                              reuse=(groups[0], chunk))
    except Exception as e:  # noqa: BLE001 - the rollout's verdict stands
        found = dict(status="error", message=one_line(e))
        return dataclasses.replace(result, message=f"{result.message}; one-step check could not run: "
                                                   f"{one_line(e)}"), found, traj_c
    if found["status"] == "error":
        return (dataclasses.replace(result, message=f"{result.message}; one-step check: {found['message']}"),
                found, traj_c)
    if found["status"] == "pass":  # its own line in the report (mjxdiff.output.report.format_checks)
        return result, found, traj_c
    member, step = found["member"], found["step"]
    def at_the_state():
        row = int(np.flatnonzero(inputs.ids == member)[0])
        return diagnose.drill_down(converged(inputs.take([row])).models[0],
                                   *diagnose.state_before(inputs, traj_c, row, step),
                                   precision=config.precision, member=member, step=step, engine=under_test)

    drill = _drilled(found, at_the_state)
    if drill is None:
        where = f"; the drill-down could not run: {found['drill_error']}"
    else:
        where = (f"; {diagnose.first_fields(drill)}"
                 if drill.first_stage else "; every forward stage agrees (the difference is in the integration)")
    if config.diagnose == "full":
        found["cause"] = diagnose.reconcile_cause(_onestep_cause(case, traj_c, member, step), drill)
        if found["cause"]["ablation"]:
            where += f"; one-step cause: {found['cause']['cause']} (passes with {found['cause']['ablation']})"
    said = (f"one-step check: {found['field']} of {found['object'] or 'member ' + str(member)} after step "
            f"{step} from C's state, member {member}, {found.get('settings', 'converged')} solver in both: "
            f"error {found['error']:.3g}, "
            f"bound {found['bound']:.3g} ({found['ratio']:.3g}x){where}")
    diagnosis = result.diagnosis
    if found.get("cause", {}).get("ablation") and (diagnosis.get("cause") or {}).get("cause") in (
            None, diagnose.GENUINE, diagnose.UNCLASSIFIED):  # the one-step ablation is the sharper witness
        diagnosis = dict(diagnosis, cause=dict(found["cause"], check="onestep"))
    if result.status == "fail":
        return dataclasses.replace(result, message=f"{result.message}; {said}", diagnosis=diagnosis), found, traj_c
    first = dict(field=found["field"], step=step, time=round((step + 1) * float(m.opt.timestep), 9), member=member,
                 object=found["object"], element=found.get("element"), error=found["error"], tolerance=found["bound"],
                 check="onestep")
    return dataclasses.replace(result, status="fail", message=f"{said}; the rollout alone passed ({result.message})",
                               first_divergence=first, diagnosis=diagnosis), found, traj_c


def _onestep_cause(case: _Case, traj_c: Trajectory, member: int, step: int) -> dict:
    """:func:`mjxdiff.compare.diagnose.attribute_cause` on the one failing member-state of the one-step
    check: the first ablation under which that one step agrees names the cause. Chaos cannot
    blur it, unlike the rollout's ablations on a model with several differences (a robot)."""
    row = int(np.flatnonzero(case.inputs.ids == member)[0])
    single, traj_row = case.inputs.take([row]), jax.tree.map(lambda a: a[row:row + 1], traj_c)

    def passes(ablated: BatchedInputs, precision: Precision) -> bool:
        with _precision(precision):
            return onestep.check(ablated.models[0], ablated, traj_row, case.tol, case.under_test, case.c_engine,
                                 precision, steps=np.array([step - 1]))["status"] == "pass"

    return diagnose.attribute_cause(passes, single, case.config.precision, skip=("solver convergence",))


def _twin(result: ScenarioResult, case: _Case, clock: dict[str, float]) -> tuple[ScenarioResult, dict | None]:
    """The converged twin: both engines rerun with a converged solver
    (:func:`mjxdiff.compare.noise.converged`), judged as sharply as any converged scenario (rounding
    envelope, never the solver floor). Returns the result and what the twin found (for
    ``info['twin']``: status, worst qpos/qvel ratio, per-field ratio and ``bound_scale``, weak
    fields, seconds). A twin that fails fails the scenario, naming field, step, member and (from
    the drill-down at that state) the first stage and field that differ. Never raises."""
    t = time.perf_counter()
    twin_inputs = converged(case.inputs)
    try:
        if _out_of_time(rerun=True):  # a converged solver compiles again
            raise BudgetSpent()
        twin, _ = _verdict(dataclasses.replace(case, inputs=twin_inputs), clock)
    except Exception as e:  # noqa: BLE001 - the rollout's verdict stands, and says what is missing
        return dataclasses.replace(result, message=f"{result.message}; converged twin could not run: "
                                                   f"{one_line(e)}"), dict(status="error", message=one_line(e))
    worst = max((f for f in twin.fields if f.field in ("qpos", "qvel")), key=lambda f: f.ratio, default=None)
    found = dict(status=twin.status, message=twin.message, weak=list(twin.weak),
                 fields={f.field: dict(max_error=f.max_error, ratio=f.ratio, bound_scale=list(f.bound_scale),
                                       floor=f.floor) for f in twin.fields},
                 worst=dict(field=worst.field, max_error=worst.max_error, ratio=worst.ratio) if worst else None,
                 seconds=0.0)
    if twin.status == "pass":
        found["seconds"] = time.perf_counter() - t
        return result, found
    message = f"converged twin (both engines with a converged solver): {twin.message}"
    first = dict(twin.first_divergence or {}, check="twin")
    if twin.status == "fail" and twin.first_divergence:
        drill = _drilled(found, lambda: _drill(twin, twin_inputs, case.c_engine.rollout(twin_inputs),
                                               case.config.precision, case.under_test))
        if drill is None:
            message += f"; the drill-down could not run: {found['drill_error']}"
        elif drill.first_stage:
            message += f"; {diagnose.first_fields(drill)}"
    found["seconds"] = time.perf_counter() - t
    status = "fail" if twin.status == "fail" else result.status
    if status == "pass":  # the twin could not be judged (C unstable with a converged solver): say so
        return dataclasses.replace(result, message=f"{result.message}; converged twin: {twin.status}: "
                                                   f"{twin.message}"), found
    return dataclasses.replace(result, status="fail", message=f"{message}; as configured the rollout passed "
                                                            f"({result.message})", first_divergence=first), found


#: What ``--quick`` leaves out, each a compile of its own, as the verdict's line says it.
QUICK_SKIPS = {
    "twin": "converged twin not run (--quick: a compile of its own); without --quick it tells solver truncation "
            "from a bug",
    "ablations": "likely cause not sought (--quick: each ablation compiles and steps again); without --quick the "
                 "ablations name it",
}


def _solver_settings(m) -> str:
    """``CG, 200 iteration(s), 50 line-search steps, tolerance 1e-12``: the model's solver as MJCF names it."""
    solver = mujoco.mjtSolver(m.opt.solver).name.removeprefix("mjSOL_")
    return (f"{solver}, {m.opt.iterations} iteration(s), {m.opt.ls_iterations} line-search steps, "
            f"tolerance {m.opt.tolerance:g}")


def _truncation(result: ScenarioResult, m, floor: dict, found: dict, twin: dict | None,
                bundled: bool = False) -> ScenarioResult:
    """A rollout that parts from C beyond its tolerance and rounding envelope, held only by C's
    freedom under its own solver settings, is not a pass: a ``fail`` whose cause is
    :data:`TRUNCATION` (the ``solver-truncation`` entry of :mod:`mjxdiff.compare.known`, accepted by
    ``--fail-on new``), stating the gap, the converged twin, the one-step check and MJX's truncated
    step against C's. The settings are "your" settings only on the user's model; on a ``bundled``
    scenario they are the scenario's, whose pass is meant to be sharp: a defect to report."""
    gap = floor.get("gap") or {}
    whose = ("this bundled scenario's own solver settings" if bundled else "your solver settings")
    parts = [f"solver truncation: {whose} ({_solver_settings(m)}) make MJX and C differ by "
             f"{gap.get('error', float('nan')):.3g} in {gap.get('field')} ({gap.get('object') or 'a member'}) over "
             f"{gap.get('steps')} steps, from step {gap.get('step')} "
             f"(tolerance {gap.get('tolerance', float('nan')):.0e}"
             "; only C's freedom under the same settings, the solver floor, covers it)"]
    if twin and twin.get("worst"):
        w = twin["worst"]
        parts.append(f"with a converged solver they agree (twin: worst {w['field']} {w['max_error']:.2g}, "
                     f"{w['ratio']:.2g} of its bound)")
    if found.get("status") in ("pass", "fail"):
        parts.append(f"the one-step check {'passes' if found['status'] == 'pass' else 'fails'} "
                     f"({found['ratio']:.2g} of its bound)")
    evidence = found.get("as_configured")
    if evidence:
        f = evidence["fields"][evidence["field"]]
        parts.append(f"one step as configured from C's states: MJX vs C {f['error']:.2g}, C vs its converged self "
                     f"{f['truncation']:.2g} ({evidence['field']})")
    first = dict(floor["first"], check="rollout") if floor.get("first") else result.first_divergence
    if not (twin and twin.get("status") == "pass"):  # without the twin's agreement, no excuse is proven
        parts[0] = parts[0].replace("solver truncation: ", "", 1)
        said = twin or {}
        parts.append(said["message"] if said.get("status") == "skipped" else
                     f"the converged twin could not tell truncation from a bug: {said.get('status', 'not run')}"
                     f" {said.get('message', '')}".rstrip())
        return dataclasses.replace(result, status="fail", message="; ".join(parts), first_divergence=first)
    if bundled:  # only where the twin proved the engines agree: then the scenario is at fault, not MJX
        parts.append("the scenario's solver does not converge on this draw: a defect of the scenario, not of MJX "
                     "(please report it with the seed)")
    diagnosis = dict(result.diagnosis, cause=dict(cause=TRUNCATION, ablation=None, tried=[],
                                                  evidence="; ".join(parts[1:])))
    return dataclasses.replace(result, status="fail", message="; ".join(parts),
                               diagnosis=diagnosis, first_divergence=first)


def _diagnose(result: ScenarioResult, case: _Case, traj_c: Trajectory | None = None,
              drill: diagnose.DrillDown | None = None) -> ScenarioResult:
    """Adds local error, the stage drill-down and (``full``) the likely cause to a failing verdict;
    ``traj_c`` (C's whole rollout) and ``drill`` when already computed.

    Never raises: a part of the diagnosis that cannot run (an engine refusing
    the state or an ablated model) becomes a line in ``diagnosis['notes']``
    and in the message, and the verdict stands.
    """
    m, inputs, tol, config, under_test = case.m, case.inputs, case.tol, case.config, case.under_test
    diagnosis: dict = {}
    notes: list[str] = []
    message = result.message

    def attempt(label: str, fn: Callable[[], _T]) -> _T | None:
        try:
            if _out_of_time(rerun=True):  # each part compiles MJX functions of its own
                raise BudgetSpent()
            return fn()
        except Exception as e:  # noqa: BLE001 - one scenario's diagnosis, never the sweep
            notes.append(f"{label} could not run: {one_line(e)}")
            return None

    if traj_c is None:  # whole, for the failing scenario only
        traj_c = attempt("C's full rerun", lambda: case.c_engine.rollout(inputs))
    local = None
    if traj_c is not None:
        if drill is None:
            drill = attempt("drill-down", lambda: _drill(result, inputs, traj_c, config.precision, under_test))
        local = attempt("local error", lambda: diagnose.local_error(
            inputs, traj_c, m, rangefinder_mask(m), 1, under_test))
    if local is not None:
        diagnosis["local_error"] = local
    if drill is not None:
        if drill.first_field:
            message += f"; {diagnose.first_fields(drill)}"
        elif local is not None and max(local[f] / max(getattr(tol, f), 1e-300) for f in local) > 1e-3:
            # mj_forward agrees from the same state, yet one step does not: the update after it
            drill = dataclasses.replace(drill, first_stage="integration", first_field="qpos/qvel update")
            message += "; every forward stage agrees, the one-step error does not: integration"
        else:
            whole = traj_c
            earlier = None if whole is None else attempt("the search of earlier states", lambda: _earlier_difference(
                result, inputs, whole, config.precision, under_test))
            if earlier is not None:
                drill = earlier
                message += (f"; every stage agrees at that state; the last to differ before it is step "
                            f"{earlier.step}: {diagnose.first_fields(earlier)}")
            else:
                before = min(DRILL_BACK, result.first_divergence["step"]) if result.first_divergence else 0
                message += (f"; every stage agrees at that state and at the {before} before it (an accumulation "
                            "of small differences)")
        diagnosis["drill_down"] = dataclasses.asdict(drill)
    if config.diagnose == "full" and config.quick:
        notes.append(QUICK_SKIPS["ablations"])
    elif config.diagnose == "full":
        _phase("diagnosing")

        def passes(ablated: BatchedInputs, precision: Precision) -> bool:
            if _out_of_time(rerun=True):  # each ablation compiles and steps again
                raise BudgetSpent()
            with _precision(precision):
                ablation = dataclasses.replace(case, m=ablated.models[0], inputs=ablated)
                return _verdict(ablation, {})[0].status == "pass"

        cause = diagnose.reconcile_cause(diagnose.attribute_cause(passes, inputs, config.precision), drill)
        if (cause["cause"] == diagnose.GENUINE and "steered_clear" not in cause and drill is not None
                and drill.first_stage == "collision"):
            # the drill-down saw the engines generate other contacts from the same state; that no
            # single ablation passes means something else differs too, which the line says (an
            # ablation that passed and was set aside keeps reconcile_cause's evidence)
            cause = dict(cause, cause="contact generation",
                         evidence=f"drill-down: {drill.object} at step {drill.step}; no ablation passes, so "
                                  "something else differs as well")
        diagnosis["cause"] = cause
        message += f"; likely cause: {cause['cause']}"
        if cause["ablation"]:
            message += f" (passes with {cause['ablation']})"
        elif "evidence" in cause:
            message += f" ({cause['evidence']})"
        notes += [f"ablation '{t['ablation']}' could not run: {t['error']}" for t in cause["tried"] if t["error"]]
    if notes:
        diagnosis["notes"] = notes
        message += "; diagnosis incomplete: " + "; ".join(notes)
    return dataclasses.replace(result, message=message, diagnosis=diagnosis)


def _precision(precision: Precision):
    """``jax_enable_x64`` as ``precision`` says, for the calling thread only (JAX's thread-local
    setting): scenarios a sweep runs at once on its workers never see each other's (a float32
    sweep's float64 ablation), and the process-wide setting is left as it was."""
    return enable_x64(precision == "float64")


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


#: Share of the kernel's memory-map limit (``vm.max_map_count``) a sweep's process may hold
#: before it lets go of its compiled functions.
MAP_BUDGET = 0.5


def _memory_maps() -> tuple[int, int]:
    """(memory maps this process holds, the kernel's limit); (0, 0) where /proc cannot tell."""
    try:
        with open("/proc/self/maps", "rb") as f:
            held = sum(1 for _ in f)
        with open("/proc/sys/vm/max_map_count") as f:
            return held, int(f.read())
    except (OSError, ValueError):
        return 0, 0


def release_compiled_if_crowded(budget: float = MAP_BUDGET) -> bool:
    """Drops every compiled function (JAX's in-memory caches and MJX's rollouts) once the process
    holds more than ``budget`` of the kernel's memory-map limit, and says whether it did.

    Each XLA CPU executable maps ~500-1,000 regions (measured: 981 -> 4,056 maps after four
    small scenarios, 1,082 after clearing); a sweep whose failing scenarios each compile their
    ablations reaches Linux's default limit of 65,530 within about fifteen of them, and LLVM
    then fails to allocate ('Cannot allocate memory') and the process segfaults (seen: an edited
    MJX failing every scenario). The persistent caches keep what is dropped a load away.
    """
    held, limit = _memory_maps()
    if not limit or held <= budget * limit:
        return False
    engines.clear_compiled()
    jax.clear_caches()
    import gc

    gc.collect()
    return True


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
    precision: :func:`_precision`). With no workers, the scenarios run here, one by one.

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
    running: dict[int, Future] = {}

    def run(i: int, scenario: Scenario) -> ScenarioResult:
        hook = functools.partial(on_event, i) if on_event is not None else None
        with _precision(config.precision), _running(config, hook), _holding(under_test):
            _phase("preparing")
            prepared = _compile_ahead(scenario, config, under_test) if pool is not None else _prepare(scenario, config)
            result = _finish(prepared, under_test, c_engine)
            _phase("finished", result=result)  # before its turn comes to be reported in order
            return result

    def submit(i: int) -> None:
        if pool is not None and i < len(scenarios):
            running[i] = pool.submit(run, i, scenarios[i])

    results = []
    with export_cache.code_read_once():  # one reading of the code serves the whole sweep
        try:
            for i in range(2 * workers):
                submit(i)
            for i, scenario in enumerate(scenarios):
                submit(i + 2 * workers)
                bar.start(i, scenario.name)
                try:
                    result = running.pop(i).result() if i in running else run(i, scenario)
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


#: The engines judged against C, by ``SweepConfig.impl``: module and class, imported on first use
#: (MuJoCo Warp is an extra).
ENGINES = {"mjx": ("mjxdiff.engine.engines", "MJXEngine"), "warp": ("mjxdiff.engine.mjwarp", "MJWarpEngine"),
           "mjx.warp": ("mjxdiff.engine.engines", "MJXWarpEngine")}


def engine_class(impl: str) -> type:
    """The :class:`~mjxdiff.engine.trajectory.Engine` class of ``impl`` (:data:`ENGINES`)."""
    import importlib

    module, name = ENGINES[impl]
    return getattr(importlib.import_module(module), name)


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
