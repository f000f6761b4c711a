"""A sweep with bounded memory and time: :func:`mjxdiff.runner.sweep.sweep` in a child process it watches.

XLA cannot be interrupted while it compiles, and a compile of a large model can hold tens of GB
(a robot hand's plain model: 22 GB after 9 minutes, then the kernel killed the process and
every verdict with it). So the sweep runs in a child process, and this one, which holds
nothing but results, watches it twice a second:

* **memory**: the child's resident memory against ``Limits.memory`` (default 85% of what the
  machine has available when the sweep starts). Past it, the child is killed, the scenario it
  was running ends as an ``error`` of kind ``memory`` naming the phase and the estimate, and a
  new child goes on with the next scenario. When two scenarios were in flight, both are retried
  one at a time, so that only the one that does not fit is blamed.
* **time**: each scenario's wall time from its start against ``Limits.budget``. The child stops
  a scenario itself at its budget where it can (between pieces of stepping, ablations of the
  diagnosis); past the budget plus a grace (:data:`GRACE_S`, or :data:`GRACE_SHARE` of the
  budget; a compile cannot be interrupted) it is
  killed, and the scenario ends as an ``error`` of kind ``budget`` that says how far it got.
  ``Limits.sweep_budget`` bounds the whole sweep; scenarios it leaves unrun are listed as such.
* **MJX's and XLA's own alarms** (a mesh with a coplanar face of more than 20 vertices, XLA's
  "Very slow compile"), printed on the child's stderr, become one line in the result of the
  scenario they concern (``info['alarms']``) instead of a flood of warnings.

Results come back in order, as from :func:`mjxdiff.runner.sweep.sweep`. The child loads the MJX a
fresh process loads; where the MJX of this process differs (patched in it, e.g. by a test),
the sweep runs here instead, without the child, and says so: a sweep never tests other code
than the code it was given.
"""
from __future__ import annotations

import contextlib
import dataclasses
import importlib
import os
import pickle
import queue
import re
import signal
import subprocess
import sys
import threading
import time
from typing import Callable, Sequence

from mjxdiff.input.options import parse_size
from mjxdiff.input.scenario import Scenario
from mjxdiff.compare.result import ScenarioResult

__all__ = ["Limits", "sweep", "default_memory", "parse_size"]

#: Seconds past a scenario's budget before its child is killed: the larger of GRACE_S and
#: GRACE_SHARE of the budget. The child stops by itself at the next piece or ablation and
#: finishes what it has (the verdict so far); a compile cannot be stopped but by the kill.
GRACE_S = 15.0
GRACE_SHARE = 0.1
#: Memory the machine must keep available (other processes may take what the limit assumed free):
#: below it the child is stopped as if past its limit.
MIN_AVAILABLE_BYTES = 256 * 2**20
#: Seconds between two looks at the child.
POLL_S = 0.5
#: Share of the memory available at the start that a sweep may hold by default.
MEMORY_SHARE = 0.85
#: Seconds between two progress lines of one long phase.
HEARTBEAT_S = 30.0
#: Estimated compile seconds from which progress shows the estimate.
LONG_S = 20.0

#: stderr lines of the child that are alarms about a scenario, not messages for the user:
#: (pattern, the line the result gets).
_ALARMS = (
    (re.compile(r'Mesh "?([^"]+?)"? has a coplanar face with more than (\d+) vertices'),
     lambda m: f"MJX: mesh {m.group(1)} has a coplanar face with more than {m.group(2)} vertices: decimate it"),
    (re.compile(r"Very slow compile\?|compilation of .* is taking|Constant folding an instruction is taking"),
     lambda m: "XLA: very slow compile (XLA's own alarm); see the estimate"),
)
#: stderr lines that only continue an alarm (the source line Python prints under a warning).
_CONTINUATION = re.compile(r"^\s+(warnings\.warn\(|\*+|$)|^\*{5,}")


@dataclasses.dataclass(frozen=True)
class Limits:
    """What a guarded sweep may spend.

    Attributes:
      memory: bytes the child process may hold resident.
      budget: seconds per scenario (None: no limit).
      sweep_budget: seconds for the whole sweep (None: no limit).
    """

    memory: float
    budget: float | None = 600.0
    sweep_budget: float | None = None


def default_memory() -> int:
    """:data:`MEMORY_SHARE` of the memory the machine has available now, bytes (8 GiB where /proc
    cannot tell)."""
    from mjxdiff.input import cost

    return int(MEMORY_SHARE * (cost.available_bytes() or 8 * 2**30 / MEMORY_SHARE))


@dataclasses.dataclass
class _Flight:
    """A scenario the child has started and not yet finished."""

    started: float
    phase: str = "preparing"
    phase_at: float = 0.0
    estimate: dict = dataclasses.field(default_factory=dict)
    said: float = 0.0
    peak: int = 0
    verdict: ScenarioResult | None = None


@dataclasses.dataclass
class _Watch:
    """The parent's view of the sweep: results by index, scenarios in flight, alarms."""

    n: int
    results: dict[int, ScenarioResult] = dataclasses.field(default_factory=dict)
    flying: dict[int, _Flight] = dataclasses.field(default_factory=dict)
    alarms: dict[int, list[str]] = dataclasses.field(default_factory=dict)
    peak: int = 0


def _stopped(name: str, kind: str, why: str, flight: _Flight | None, limits: Limits, peak: int) -> ScenarioResult:
    """The ``error`` result of a scenario the guard stopped."""
    from mjxdiff.input import cost

    info: dict = dict(guard=dict(kind=kind, peak_rss_bytes=peak, memory_limit_bytes=int(limits.memory),
                                 budget=limits.budget))
    line = ""
    if flight is not None:
        info["guard"].update(phase=flight.phase, seconds=round(time.monotonic() - flight.started, 1))
        if flight.estimate:
            info["estimate"] = flight.estimate
            line = f"; {flight.estimate.get('line', '')}"
        where = f" while {flight.phase} ({time.monotonic() - flight.started:.0f} s in)"
    else:
        where = ""
    if flight is not None and flight.verdict is not None and flight.verdict.status in ("pass", "fail"):
        # the rollout was judged: that verdict stands, without the checks that did not finish
        verdict = flight.verdict
        info = dict(verdict.info, guard=info["guard"])
        reason = why if kind == "budget" else "the memory limit (--max-memory) was reached"
        note = f"{reason}{where}: the checks after the rollout did not finish"
        return dataclasses.replace(verdict, info=info, message=f"{verdict.message}; {note}")
    if kind == "memory":
        message = (f"stopped before the machine ran out of memory: {cost.human_bytes(peak)} resident, limit "
                   f"{cost.human_bytes(limits.memory)} (--max-memory){where}{line}; try --batch 1, "
                   "--drop-costly-pairs, or primitive collision geoms")
    else:
        message = f"stopped: {why}{where}{line}"
    return ScenarioResult(name=name, status="error", error_kind=kind, message=message, info=info)


def _read_messages(stream, inbox: queue.Queue) -> None:
    """Unpickles the child's messages into ``inbox`` until the pipe closes, then puts None."""
    with stream, contextlib.suppress(EOFError, OSError, pickle.UnpicklingError, ValueError):
        while True:
            inbox.put(pickle.load(stream))
    inbox.put(None)


def _read_stderr(stream, watch: _Watch, lock: threading.Lock) -> None:
    """Passes the child's stderr on, except MJX's and XLA's alarms, which go to the scenario in
    flight (the most recently started one) as one line each."""
    with stream:
        _pass_stderr(stream, watch, lock)


def _pass_stderr(stream, watch: _Watch, lock: threading.Lock) -> None:
    skipping = False
    for raw in iter(stream.readline, b""):
        line = raw.decode(errors="replace")
        for pattern, say in _ALARMS:
            found = pattern.search(line)
            if found:
                with lock:
                    if watch.flying:
                        i = max(watch.flying, key=lambda k: watch.flying[k].started)
                        lines = watch.alarms.setdefault(i, [])
                        if say(found) not in lines:
                            lines.append(say(found))
                skipping = True
                break
        else:
            if skipping and _CONTINUATION.search(line):
                continue
            skipping = False
            sys.stderr.write(line)
            sys.stderr.flush()


def _with_alarms(result: ScenarioResult, alarms: list[str]) -> ScenarioResult:
    if not alarms:
        return result
    info = dict(result.info, alarms=list(alarms))
    return dataclasses.replace(result, info=info, message=f"{result.message}; {'; '.join(alarms)}")


def sweep(scenarios: Sequence[Scenario], config, limits: Limits | None = None, progress: bool | None = None,
          on_result: Callable[[ScenarioResult], None] | None = None, cache_dir: str | None = None,
          devices: int | None = None) -> list[ScenarioResult]:
    """:func:`mjxdiff.runner.sweep.sweep` of ``scenarios`` with ``config``, in child processes held to
    ``limits`` (default: :func:`default_memory`, 600 s per scenario; see the module docstring).

    ``cache_dir`` and ``devices`` are :func:`mjxdiff.engine.engines.configure_jax`'s for the child.
    ``config.budget`` and ``config.max_memory``, when unset, become the limits', so that the
    child plans within them (:func:`mjxdiff.input.cost.plan`).
    """
    from mjxdiff.engine.digest import code_digest, loaded_modules

    sweep_module = importlib.import_module("mjxdiff.runner.sweep")
    limits = limits or Limits(default_memory())
    config = dataclasses.replace(config, budget=config.budget or limits.budget,
                                 max_memory=config.max_memory or limits.memory)
    progress = sys.stderr.isatty() if progress is None else progress
    names = loaded_modules()
    digest = code_digest(names=names)
    watch = _Watch(len(scenarios))
    lock = threading.Lock()
    t0 = time.monotonic()
    sequential = False
    delivered = 0

    def deliver() -> None:
        nonlocal delivered
        while delivered < len(scenarios) and delivered in watch.results:
            if on_result is not None:
                on_result(watch.results[delivered])
            delivered += 1

    while len(watch.results) < len(scenarios):
        todo = [i for i in range(len(scenarios)) if i not in watch.results]
        if limits.sweep_budget is not None and time.monotonic() - t0 > limits.sweep_budget:
            for i in todo:
                watch.results[i] = ScenarioResult(
                    name=scenarios[i].name, status="error", error_kind="budget",
                    message=f"not run: the sweep's budget of {limits.sweep_budget:.0f} s (--sweep-budget) ran out")
            break
        child_config = dataclasses.replace(config, compile_workers=0) if sequential else config
        outcome = _run_child([scenarios[i] for i in todo], todo, child_config, limits, watch, lock, names, digest,
                             cache_dir, devices, progress, t0, deliver)
        if outcome == "patched":
            print("mjxdiff: the MJX loaded in this process differs from the one a new process loads (patched "
                  "here?): sweeping in this process, without the memory and time guard", file=sys.stderr)
            rest = sweep_module.sweep([scenarios[i] for i in todo], config, progress,
                                      on_result=None)
            for i, r in zip(todo, rest):
                watch.results[i] = r
            break
        if outcome == "crowded":
            sequential = True
    deliver()
    return [watch.results[i] for i in range(len(scenarios))]


def _run_child(scenarios: list[Scenario], index: list[int], config, limits: Limits, watch: _Watch,
               lock: threading.Lock, names: list[str], digest: str, cache_dir, devices, progress: bool | None,
               t0: float, deliver: Callable[[], None]) -> str:
    """One child process sweeping ``scenarios`` (their indices in the whole sweep: ``index``),
    until it finishes or is killed. Returns ``done``, ``stopped`` (a scenario ended by a limit;
    the rest to be run by another child), ``crowded`` (killed for memory with several scenarios
    in flight: run the rest one at a time), ``patched`` (the child's MJX is not this process's)."""
    from mjxdiff.input import cost
    from mjxdiff.engine import export_cache
    proc, inbox = _start_child(scenarios, config, names, cache_dir, devices, watch, lock)
    done = 0  # results of this child, in its order
    outcome = "done"
    try:
        while True:
            try:
                msg = inbox.get(timeout=POLL_S)
            except queue.Empty:
                msg = ()
            if msg is None:  # the child is gone
                break
            if msg:
                kind = msg[0]
                if kind == "digest" and msg[1] != digest:
                    _kill(proc)
                    return "patched"
                if kind == "cache":
                    export_cache.merge_events(msg[1])
                elif kind == "event":
                    _record_event(msg, index, scenarios, watch, lock, progress, t0)
                    if msg[2] == "finished":
                        deliver()
                elif kind == "result":  # in order; a scenario's own "finished" may have brought it
                    if index[done] not in watch.results:
                        _finished(index[done], msg[1], watch, lock)
                    done += 1
                    deliver()
            rss = cost.resident_bytes(proc.pid)
            watch.peak = max(watch.peak, rss)
            now = time.monotonic()
            with lock:
                flying = dict(watch.flying)
                for flight in flying.values():
                    flight.peak = max(flight.peak, rss)
            _heartbeats(flying, now, progress, scenarios, index, watch, t0)
            stop = _enforce_limits(proc, flying, rss, now, scenarios, index, limits, watch, t0)
            if stop is not None:
                outcome = stop
                break
    finally:
        _kill(proc)
        with lock:
            watch.flying.clear()
    if outcome == "done" and done < len(scenarios):  # the child died on its own (a crash, a signal)
        lost = [i for i in index if i not in watch.results]
        i = lost[0]
        watch.results[i] = _died(scenarios[index.index(i)].name, proc.returncode)
        outcome = "stopped"
    return outcome


def _start_child(scenarios: list[Scenario], config, names: list[str], cache_dir, devices, watch: _Watch,
                 lock: threading.Lock) -> tuple[subprocess.Popen, queue.Queue]:
    """Starts the child process sweeping ``scenarios`` (sent pickled on its stdin) and the threads
    that read its messages (into the returned queue) and its stderr; returns (process, queue)."""
    read, write = os.pipe()
    proc = subprocess.Popen([sys.executable, "-m", "mjxdiff.runner.guard", str(write)], stdin=subprocess.PIPE,
                            stderr=subprocess.PIPE, pass_fds=(write,), env=dict(os.environ, PYTHONUNBUFFERED="1"))
    os.close(write)
    inbox: queue.Queue = queue.Queue()
    stream = os.fdopen(read, "rb")
    threading.Thread(target=_read_messages, args=(stream, inbox), daemon=True).start()
    threading.Thread(target=_read_stderr, args=(proc.stderr, watch, lock), daemon=True).start()
    assert proc.stdin is not None  # stdin=PIPE
    pickle.dump(dict(scenarios=scenarios, config=config, names=names, cache_dir=cache_dir, devices=devices,
                     progress=False), proc.stdin)
    proc.stdin.close()
    return proc, inbox


def _record_event(msg: tuple, index: list[int], scenarios: list[Scenario], watch: _Watch, lock: threading.Lock,
                  progress: bool | None, t0: float) -> None:
    """Records the child's ``("event", k, phase, detail)`` on its scenario ``k``: a finished
    scenario's result, the rollout's verdict (before the checks after it), or the phase it
    entered (with the estimate), said as progress."""
    if msg[2] == "finished":
        _finished(index[msg[1]], msg[3]["result"], watch, lock)
    elif msg[2] == "verdict":  # the rollout's, before the checks after it
        with lock:
            watch.flying.setdefault(index[msg[1]], _Flight(time.monotonic())).verdict = msg[3]["result"]
    else:
        _, k, phase, detail = msg
        i = index[k]
        with lock:
            flight = watch.flying.setdefault(i, _Flight(time.monotonic()))
            flight.phase, flight.phase_at = phase, time.monotonic()
            if phase == "estimated":
                flight.estimate = dict(line=detail.get("line"), compile_s=detail.get("compile_s"),
                                       member_bytes=detail.get("member_bytes"),
                                       stepping_s=detail.get("stepping_s"))
        _say(progress, i, len(watch.results), watch.n, scenarios[k].name, flight, t0)


def _heartbeats(flying: dict[int, _Flight], now: float, progress: bool | None, scenarios: list[Scenario],
                index: list[int], watch: _Watch, t0: float) -> None:
    """Says again, with ``progress``, each scenario in flight that has been compiling or stepping
    for more than :data:`HEARTBEAT_S` since it was last said."""
    for i, flight in flying.items():
        if progress and flight.phase in ("compiling", "stepping") and now - max(flight.said, flight.phase_at) \
                > HEARTBEAT_S:
            flight.said = now
            _say(progress, i, len(watch.results), watch.n, scenarios[index.index(i)].name, flight, t0,
                 heartbeat=True)


def _enforce_limits(proc: subprocess.Popen, flying: dict[int, _Flight], rss: int, now: float,
                    scenarios: list[Scenario], index: list[int], limits: Limits, watch: _Watch,
                    t0: float) -> str | None:
    """Kills the child past a limit and records the scenarios it stopped: the memory limit (or the
    machine's :data:`MIN_AVAILABLE_BYTES`), a scenario's budget plus its grace, the sweep's
    budget. Returns ``stopped``, ``crowded`` (memory, several scenarios in flight) or None (within
    every limit)."""
    from mjxdiff.input import cost

    if rss > limits.memory or 0 < cost.available_bytes() < MIN_AVAILABLE_BYTES:
        _kill(proc)
        if len(flying) > 1:
            return "crowded"
        # none in flight: the next one was about to start
        i = next(iter(flying), next(j for j in index if j not in watch.results))
        flight = flying.get(i)
        watch.results[i] = _with_alarms(_stopped(scenarios[index.index(i)].name, "memory", "", flight,
                                                 limits, rss), watch.alarms.pop(i, []))
        return "stopped"
    late = [i for i, f in flying.items()
            if limits.budget is not None and now - f.started > limits.budget + _grace(limits.budget)]
    if late:
        _kill(proc)
        for i in late:
            why = f"its budget of {limits.budget:.0f} s (--budget) ran out"
            watch.results[i] = _with_alarms(_stopped(scenarios[index.index(i)].name, "budget", why,
                                                     flying[i], limits, rss), watch.alarms.pop(i, []))
        return "stopped"
    if limits.sweep_budget is not None and now - t0 > limits.sweep_budget:
        _kill(proc)
        for i, flight in flying.items():
            watch.results[i] = _stopped(scenarios[index.index(i)].name, "budget",
                                        f"the sweep's budget of {limits.sweep_budget:.0f} s (--sweep-budget) "
                                        "ran out", flight, limits, rss)
        return "stopped"
    return None


def _died(name: str, code: int | None) -> ScenarioResult:
    """The ``error`` (``engine``) of the scenario running when the child died on its own with
    return ``code`` (negative: the signal)."""
    how = f"signal {signal.Signals(-code).name}" if code and code < 0 else f"exit status {code}"
    return ScenarioResult(
        name=name, status="error", error_kind="engine",
        message=f"the sweep's process died ({how}) while running this scenario; the others go on")


def _grace(budget: float) -> float:
    """Seconds past ``budget`` before the guard stops a scenario from outside (see :data:`GRACE_S`)."""
    return max(GRACE_S, GRACE_SHARE * budget)


def _finished(i: int, result: ScenarioResult, watch: _Watch, lock: threading.Lock) -> None:
    """Records scenario ``i``'s result: no longer in flight, with its alarms and the child's peak."""
    with lock:
        flight = watch.flying.pop(i, None)
        if flight is not None:  # what the child held while this scenario ran
            result.info["guard"] = dict(peak_rss_bytes=flight.peak)
        watch.results[i] = _with_alarms(result, watch.alarms.pop(i, []))


def _kill(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.kill()
    proc.wait()


def _say(progress: bool | None, i: int, finished: int, n: int, name: str, flight: _Flight, t0: float,
         heartbeat: bool = False) -> None:
    """A progress line on stderr: the scenario, its phase, and for a long compile the estimate as ETA."""
    if not progress:
        return
    from mjxdiff.input import cost

    now = time.monotonic()
    text = flight.phase
    if flight.phase == "estimated":
        costly = ((flight.estimate.get("compile_s") or 0) >= LONG_S
                  or (flight.estimate.get("member_bytes") or 0) >= 2**28)
        if not costly:
            return
        text = flight.estimate.get("line") or text
    elif flight.phase == "compiling" and flight.estimate.get("compile_s"):
        spent = now - flight.phase_at
        if not heartbeat and flight.estimate["compile_s"] < LONG_S:
            return
        text = (f"compiling MJX's rollout, {cost.human_seconds(spent)} of ~"
                f"{cost.human_seconds(flight.estimate['compile_s'])} estimated" if heartbeat else
                f"compiling MJX's rollout (~{cost.human_seconds(flight.estimate['compile_s'])} estimated)")
    elif heartbeat and flight.phase == "stepping" and flight.estimate.get("stepping_s"):
        text = (f"stepping MJX's rollout, {cost.human_seconds(now - flight.phase_at)} of ~"
                f"{cost.human_seconds(flight.estimate['stepping_s'])} estimated")
    elif heartbeat:
        text = f"still {flight.phase} ({cost.human_seconds(now - flight.phase_at)})"
    elif flight.phase != "preparing":
        return
    print(f"[{i + 1}/{n}] {name}: {text} ({now - t0:.0f} s elapsed, {finished} done)", file=sys.stderr, flush=True)


def _child(fd: int) -> None:
    """The child's side: reads its task from stdin, sweeps, and sends every event and result."""
    os.dup2(2, 1)  # stdout is the parent's report (--format json): anything printed here goes to stderr
    parent = os.getppid()

    def orphaned() -> None:  # the guard was killed (Ctrl-C twice, SIGKILL): stop too, even mid-compile
        while os.getppid() == parent:
            time.sleep(1.0)
        os._exit(3)

    threading.Thread(target=orphaned, daemon=True).start()
    task = pickle.load(sys.stdin.buffer)
    out = os.fdopen(fd, "wb")
    lock = threading.Lock()

    def send(*msg) -> None:
        with lock:
            pickle.dump(msg, out)
            out.flush()

    from mjxdiff.engine import engines, export_cache
    from mjxdiff.engine.digest import code_digest

    sweep_module = importlib.import_module("mjxdiff.runner.sweep")

    engines.configure_jax(task["config"].precision, task["cache_dir"], task["devices"])
    send("digest", code_digest(names=task["names"]))
    sweep_module.sweep(task["scenarios"], task["config"], progress=False,
                       on_result=lambda r: send("result", r),
                       on_event=lambda k, phase, detail: send("event", k, phase, detail))
    send("cache", export_cache.events())
    send("done")
    out.close()


if __name__ == "__main__":
    _child(int(sys.argv[1]))
