"""The streaming verdict: both engines (and C's perturbed rerun) stepped piece by piece, C in a
background thread, each piece judged as it arrives, so memory does not grow with the horizon.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import queue
import threading
from typing import Any, Callable, Generator, Iterable, Iterator

import jax
import mujoco
import numpy as np

from mjxdiff.compare.ambiguity import CcdAmbiguity
from mjxdiff.compare.noise import SOLVER_MARGIN, STEP_JITTER, NoiseFloor, combine, converged, perturb
from mjxdiff.compare.verdict import Judge, ScenarioResult, rangefinder_mask
from mjxdiff.compat import enable_x64
from mjxdiff.engine import engines, export_cache
from mjxdiff.engine.engines import CEngine, MJXEngine, UnsupportedError
from mjxdiff.engine.trajectory import Engine, Trajectory
from mjxdiff.errors import one_line
from mjxdiff.input.config import SweepConfig
from mjxdiff.input.inputs import BatchedInputs
from mjxdiff.input.precision import Precision
from mjxdiff.input.scenario import Tolerances
from mjxdiff.runner.current import BudgetSpent, clocked, out_of_time, phase
from mjxdiff.runner.plan import layout


class EngineFailed(Exception):
    """An engine (``engine``: ``c``, ``mjx`` or ``reference``) crashed while stepping; the message
    is the error's one line."""

    def __init__(self, engine: str, error: BaseException):
        super().__init__(one_line(error))
        self.engine = engine


@contextlib.contextmanager
def _engine_call(engine: str, seconds: dict[str, float]):
    """Wall time of the stepping added to ``seconds[engine]`` (:func:`mjxdiff.runner.current.clocked`: a compile in it
    is not stepping); a crash becomes :class:`EngineFailed` (MJX's :class:`UnsupportedError`
    passes through)."""
    with clocked(seconds, engine):
        try:
            yield
        except UnsupportedError:
            raise
        except Exception as e:  # reported as this scenario's error, the sweep goes on
            raise EngineFailed(engine, e) from e


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
class Case:
    """What the rollout's verdict and every check after it read: the scenario's ``name``, its C
    model ``m`` (each member's own in ``inputs.models``), the inputs, tolerances and settings,
    the engine under test and MuJoCo C. A check on other inputs (the converged twin, an
    ablation) judges a :func:`dataclasses.replace` of it. ``plan_for``: the (batch, steps) a
    ``--quick`` run plans (and compiles) for (:func:`mjxdiff.runner.plan.layout`), or None."""

    name: str
    m: mujoco.MjModel
    inputs: BatchedInputs
    tol: Tolerances
    config: SweepConfig
    under_test: Engine
    c_engine: CEngine
    plan_for: tuple[int, int] | None = None


def verdict(case: Case, seconds: dict[str, Any], solver: bool = False) -> tuple[ScenarioResult, dict[str, Any]]:
    """Streams both engines (and C's perturbed rerun) piece by piece into a :class:`Judge`.

    Members run in groups of at most :func:`mjxdiff.runner.plan.group_size` (memory) and the MJX
    engine's :meth:`~mjxdiff.engine.engines.MJXEngine.batch_cap` (speed), steps in pieces of
    :func:`mjxdiff.runner.plan.piece_steps`; ``seconds`` gains wall time per engine and for the verdict.
    With ``config.noise_floor == 'on-demand'`` a group's perturbed rerun starts (from step
    0) at its first piece with an error above the fixed tolerances: before that, no
    envelope could have changed the verdict. With ``solver`` (and the envelope on), C's
    rerun with a converged solver runs beside the perturbed one, and errors are judged
    against the larger of both floors (:func:`mjxdiff.compare.noise.combine`).

    Returns:
      The verdict, and the counts of ``groups``, ``pieces``, ``noise_floor_members`` (members
      whose perturbed rerun ran) and ``ambiguous_contact_steps`` (member-steps whose contacts
      differ in grazing contacts alone, :mod:`mjxdiff.engine.pairs`, or in pairs C itself
      changes under the parity method's perturbations, :mod:`mjxdiff.compare.ambiguity`: not judged)
      and ``contact_steps_explained_by_state`` (member-steps whose pairs differ where C, at the
      tested engine's own state, makes the tested engine's pairs: not judged).

    Raises:
      UnsupportedError, EngineFailed: from the engines.
    """
    name, m, inputs, tol, config, under_test, c_engine = (
        case.name, case.m, case.inputs, case.tol, case.config, case.under_test, case.c_engine)
    B, T = inputs.batch, inputs.steps
    groups, chunk = layout(m, inputs, config, under_test, case.plan_for)
    judge = Judge(m, tol, B, T)
    judge.ccd = CcdAmbiguity(inputs.models, inputs.qpos, inputs.seed)
    floor = NoiseFloor(m, rangefinder_mask(m), B, T) if config.envelope else None
    solver_floor = NoiseFloor(m, rangefinder_mask(m), B, T, SOLVER_MARGIN) if floor and solver else None
    done: list[np.ndarray] = []
    for idx in groups:
        phase("stepping", group=len(done) + 1, groups=len(groups))
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
                if out_of_time():
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
    with clocked(seconds, "verdict"):
        noise = floor if floor is not None and floor.fed.any() else None
        result = judge.result(name, config.threshold, noise, solver_floor if noise is not None else None)
    return result, _counts(judge, floor, len(groups) * -(-T // chunk), len(groups))


def _counts(judge: Judge, floor: NoiseFloor | None, pieces: int, groups: int) -> dict[str, Any]:
    """What :func:`verdict` returns beside the verdict, from its judge and noise floor."""
    assert judge.ccd is not None  # set by verdict
    return dict(groups=groups, pieces=pieces, xla=engines.last_choice(),
                noise_floor_members=int(floor.fed.sum()) if floor is not None else 0,
                ambiguous_contact_steps=int(judge.ambiguous.sum() + judge.ccd.found.sum()),
                contact_steps_explained_by_state=int(judge.ccd.explained.sum()))
