"""Compiled MJX rollouts kept across processes: ``jax.export`` artifacts beside JAX's cache.

JAX's persistent compilation cache keeps XLA's output, but every new process
still traces ``mjx.step`` in Python to find the cache key (2.5-3 s for an ant
rollout, most of a warm sweep's compile time). :func:`bind` traces a jitted
function once, saves it as a serialized :mod:`jax.export` artifact (StableHLO
plus its input and output structure), and in later processes loads that
instead of tracing; XLA's compile of the loaded module is a persistent-cache
hit. Numbers are unchanged: the cold run already executes the exported module.

A cache is only as good as its key. Artifacts live in a directory keyed on the
tree structure of the arguments (which holds an ``mjx.Model``'s static fields),
each leaf's shape, dtype and sharding, the static arguments, the versions of jax,
jaxlib, mujoco and mujoco-mjx, and the JAX and XLA settings that change
compilation (:func:`mjxdiff.engine.digest.settings_digest`). Each artifact there is valid for the
code its trace could have run (:func:`mjxdiff.engine.trace_deps.dependencies`): every function of
``mujoco.mjx`` and mjxdiff's traced modules on the call stack of an operation it emitted, and every
function those can call by name, each digested by bytecode, constants and nested code, default
arguments, closure contents and the globals it reads. It is loaded only while all of them have
the same digest. MJX edited in
place, patched at run time or rebuilt under the same version number is therefore
traced again wherever the change reaches a function the rollout ran, and only there.

This module is the store: the artifacts on disk, their keys, binding, the counters of what a
thread compiled (:func:`tally`) and of what the store did (:func:`events`). The code digest and
a trace's dependencies are :mod:`mjxdiff.engine.digest` and :mod:`mjxdiff.engine.trace_deps`.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import json
import os
import pickle
import sys
import threading
import time
import types
from pathlib import Path
from typing import Any, Callable

import jax
from jax import export

from mjxdiff.engine.digest import TRACED_MODULES, code_digest, settings_digest
# the code digest's API the other stages read through the store (mjxdiff.runner.sweep, .pipeline, .executors,
# .guard, mjxdiff.compare.transfer, mjxdiff.tools.grad, .shrink, .bundle): mjxdiff.engine.digest's own names
from mjxdiff.engine.digest import code_read_once, loaded_modules, rollout_digest  # noqa: F401
from mjxdiff.engine.trace_deps import (HARNESS, Unaccounted, _holds, _live_functions, _where, dependencies,
                                       dependency_mode, fresh_digest, trace_codes, traced_code, uncovered)
from mjxdiff.files import atomic_write

__all__ = ["audit", "bind", "call", "check", "clear", "code_digest", "code_read_once", "count", "events",
           "events_since", "evict", "export_dir", "fresh_digest", "loaded_count", "loaded_modules", "rollout_digest",
           "tally"]

# (arguments' key, whole-code digest, options key) -> (output tree structure, compiled call of an
# Exported, what the options chose)
_FUNCTIONS: dict[tuple[str, str, str], tuple[Any, Callable, Any]] = {}
# one per key: threads binding the same function compile it once
_KEY_LOCKS: dict[tuple[str, str, str], threading.Lock] = {}
_KEY_LOCKS_GUARD = threading.Lock()
_LOCAL = threading.local()


def count(kind: str, amount: float = 1) -> None:
    """Adds ``amount`` to this thread's open :func:`tally` (if any) under ``kind``, and to the
    thread's running total (:func:`so_far`)."""
    ledger = getattr(_LOCAL, "tally", None)
    if ledger is not None:
        ledger[kind] = ledger.get(kind, 0) + amount
    totals = getattr(_LOCAL, "totals", None)
    if totals is None:
        totals = _LOCAL.totals = {}
    totals[kind] = totals.get(kind, 0) + amount


def so_far(kind: str = "seconds") -> float:
    """This thread's running total of ``kind`` (:func:`count`) since it started: a phase's
    compile seconds are the difference of two readings, whatever tallies are open."""
    return float(getattr(_LOCAL, "totals", {}).get(kind, 0))


def clock() -> float:
    """Wall seconds that stand still while this thread compiles (the ``seconds`` it counted:
    JAX's compile events, artifact loads, binds): the difference of two readings is a phase's
    time without its compiling."""
    return time.perf_counter() - so_far()


@contextlib.contextmanager
def tally():
    """Counts what this thread compiles while the block runs: yields a dict that gains
    ``traced`` (rollouts traced), ``loaded`` (artifacts loaded) and ``seconds`` (JAX's compile
    events: trace, lowering, XLA compile or cache load). Per thread, so that work done ahead
    by another thread (a sweep compiles upcoming scenarios concurrently) is not mixed in."""
    outer = getattr(_LOCAL, "tally", None)
    ledger: dict[str, float] = {}
    _LOCAL.tally = ledger
    try:
        yield ledger
    finally:
        _LOCAL.tally = outer
        if outer is not None:
            for k, v in ledger.items():
                outer[k] = outer.get(k, 0) + v


#: Prefix of the per-CPU-type directory of XLA's executables under the cache root (:func:`cpu_type`).
XLA_PREFIX = "xla-"


def cpu_type() -> str:
    """A tag of this CPU's instruction set: the machine and a digest of the features
    ``/proc/cpuinfo`` lists (``x86_64-3f9a0c12d4e5``). XLA's CPU executables depend on them and
    its cache key does not carry them, so each CPU type keeps its own executables."""
    import platform

    flags = ""
    try:
        with open("/proc/cpuinfo") as f:
            flags = next((line.split(":", 1)[1] for line in f if line.startswith(("flags", "Features"))), "")
    except OSError:
        flags = platform.processor()
    return f"{platform.machine()}-{hashlib.sha256(' '.join(sorted(flags.split())).encode()).hexdigest()[:12]}"


def cache_root() -> Path | None:
    """The cache directory the user gave (``--cache-dir``, ``$MJXDIFF_CACHE``): JAX's
    compilation cache dir, or its parent when that is the per-CPU-type ``xla-<cpu type>``
    directory; None when the cache is off."""
    cache = jax.config.jax_compilation_cache_dir  # pyright: ignore[reportAttributeAccessIssue] - jax's Config
    if not cache or "://" in str(cache):
        return None
    cache = Path(cache)
    return cache.parent if cache.name.startswith(XLA_PREFIX) else cache


def export_dir() -> Path | None:
    """Where artifacts live: ``mjxdiff-exports`` in the cache root (:func:`cache_root`), shared by
    every CPU type (a ``jax.export`` artifact is portable); None when the cache is off."""
    root = cache_root()
    return None if root is None else root / "mjxdiff-exports"


def loaded_count() -> int:
    """Compiled functions this process loaded from an artifact instead of tracing."""
    return _EVENTS["loaded"]


def clear() -> None:
    """Forgets the functions loaded or exported in this process (the files stay)."""
    _FUNCTIONS.clear()
    _KEYS.clear()
    with _KEY_LOCKS_GUARD:
        _KEY_LOCKS.clear()


def _structure(treedef, h) -> None:
    # node by node: pickle.dumps of the whole treedef depends on which equal aux objects
    # happen to be shared (pickle's memo), so equal structures could hash differently
    h.update(pickle.dumps((treedef.node_data(), len(treedef.children()))))
    for child in treedef.children():
        _structure(child, h)


#: Artifacts' format: 2 records every frame of a trace (1 left frames of other files out).
FORMAT = 2


@functools.cache
def _harness() -> str:
    """Digest of the harness's files (:data:`~mjxdiff.engine.trace_deps.HARNESS`): the code that wraps
    every trace (``flat``, in this file) and decides what a key holds (this store, the code digest and
    the dependencies of a trace), none of which is a dependency itself."""
    h = hashlib.sha256()
    for file in HARNESS:
        h.update(hashlib.sha256(Path(file).read_bytes()).digest())
    return h.hexdigest()


def _key(fn: Callable, treedef, leaves: list, static: dict[str, Any], code: str) -> str:
    h = hashlib.sha256()
    _structure(treedef, h)
    for part in (FORMAT, _harness(), code, fn.__module__, fn.__qualname__,
                 sorted((k, repr(v)) for k, v in static.items()),
                 [(x.shape, str(x.dtype), str(getattr(x, "sharding", None))) for x in leaves]):
        h.update(repr(part).encode())
    return h.hexdigest()


_KEYS: dict[tuple, str] = {}  # (fn, treedef, leaf types, static, code) -> key: hashing a model's structure takes ~30 ms


def _key_of(fn: Callable, treedef, leaves: list, static: dict[str, Any], code: str) -> str:
    memo = (fn, treedef, tuple((x.shape, x.dtype, getattr(x, "sharding", None)) for x in leaves),
            tuple(sorted(static.items())), code)
    if memo not in _KEYS:
        _KEYS[memo] = _key(fn, treedef, leaves, static, code)
    return _KEYS[memo]


#: Most bytes of artifacts kept (~2,500 of 130-230 KB); beyond it the least recently used go.
MAX_BYTES = 512 * 2**20


def _load(path: Path, touch: bool = True):
    try:
        out_tree, blob = pickle.loads(path.read_bytes())
        found = out_tree, export.deserialize(bytearray(blob))
    except Exception:  # noqa: BLE001 - unreadable or from another format: trace again and overwrite
        return None
    if touch:
        with contextlib.suppress(OSError):
            os.utime(path)  # recently used: evicted last
    return found


def _write(path: Path, data: bytes) -> None:
    atomic_write(path, data)  # a concurrent reader sees the old file or the whole new one


def _save(directory: Path, out_tree, exported, deps: dict[str, str]) -> Path:
    """Writes the artifact and, last, its dependencies (``<digest of deps>.jaxexport`` and
    ``.deps`` in ``directory``, the arguments' key): a reader only trusts complete pairs."""
    directory.mkdir(parents=True, exist_ok=True)
    if not (directory / "FORMAT").exists():
        _write(directory / "FORMAT", str(FORMAT).encode())  # what `mjxdiff cache check` trusts
    stem = hashlib.sha256(json.dumps(deps, sort_keys=True).encode()).hexdigest()[:32]
    path = directory / f"{stem}.jaxexport"
    _write(path, pickle.dumps((out_tree, bytes(exported.serialize()))))
    _write(path.with_suffix(".deps"), json.dumps(deps, sort_keys=True).encode())
    evict(directory.parent, keep=path)
    return path


def _read_deps(path: Path) -> dict[str, str] | None:
    try:
        deps = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    ok = isinstance(deps, dict) and all(isinstance(k, str) and isinstance(v, str) for k, v in deps.items())
    return deps if ok else None


def matching(directory: Path) -> list[Path]:
    """The artifacts in ``directory`` (one arguments' key) whose recorded dependencies all still
    have the digests they had when they were traced: those the code loaded now may run. More
    than one means some key was incomplete (:func:`bind` then loads none)."""
    try:
        candidates = sorted(directory.glob("*.deps"))
    except OSError:
        return []
    read = [(p, _read_deps(p)) for p in candidates]
    # names of TRACED_MODULES first (memoized digests); live functions, one pass, only if needed
    local = [(p, deps) for p, deps in read if deps is not None
             and all(_holds(n, d) for n, d in deps.items() if not n.startswith("@"))]
    live = _live_functions({n for _, deps in local for n in deps if n.startswith("@")})
    return [p.with_suffix(".jaxexport") for p, deps in local
            if all(_holds(n, d, live) for n, d in deps.items() if n.startswith("@"))]


def _also_matching(directory: Path, saved: Path, deps: dict[str, str]) -> list[Path]:
    """The artifacts of ``directory`` besides ``saved`` (just traced, with ``deps``) that the code
    loaded now may run too; without a pass over live functions: code from other files counts as
    matching only where ``deps`` names it with the same digest (else the artifact is left for
    the next :func:`matching` to judge)."""
    out = []
    for p in sorted(directory.glob("*.deps")):
        other = _read_deps(p) if p.with_suffix(".jaxexport") != saved else None
        if other and all(deps.get(n) == d if n.startswith("@") else _holds(n, d) for n, d in other.items()):
            out.append(p.with_suffix(".jaxexport"))
    return out


def _remove(path: Path) -> None:
    for part in (path.with_suffix(".deps"), path, path.with_suffix(".cost")):
        with contextlib.suppress(OSError):
            part.unlink()


def _load_matching(directory: Path):
    """(out_tree, Exported, path) of the one artifact in ``directory`` the code loaded now may
    run; None when there is none, or more than one (recorded in :func:`events` as ambiguous)."""
    found = matching(directory)
    if len(found) > 1:
        _event("ambiguous", f"{directory.name[:12]}: {len(found)} artifacts match the code loaded now")
        return None
    for path in found:
        loaded = _load(path) if path.exists() else None
        if loaded is not None:
            return (*loaded, path)
        _remove(path)  # unreadable: never tried again
    return None


_EVENTS: dict[str, Any] = {"loaded": 0, "traced": 0, "saved": 0, "unsaved": [], "ambiguous": [], "removed": 0}
_EVENTS_LOCK = threading.Lock()


def _event(kind: str, detail: Any = 1) -> None:
    with _EVENTS_LOCK:
        if isinstance(_EVENTS[kind], list):
            _EVENTS[kind].append(detail)
        else:
            _EVENTS[kind] += detail


def events() -> dict[str, Any]:
    """What the artifact cache did in this process so far: ``loaded`` (artifacts loaded instead of
    a trace), ``traced``, ``saved``, ``unsaved`` (one line each: why a trace could not be saved),
    ``ambiguous`` (keys where several artifacts matched: none was loaded) and ``removed``
    (artifacts deleted as untrustworthy). :func:`events_since` gives one run's share."""
    with _EVENTS_LOCK:
        return {k: list(v) if isinstance(v, list) else v for k, v in _EVENTS.items()}


def merge_events(other: dict[str, Any]) -> None:
    """Adds :func:`events` of another process (a guarded sweep's child) to this process's."""
    with _EVENTS_LOCK:
        for k, v in other.items():
            if k in _EVENTS:
                _EVENTS[k] = _EVENTS[k] + v if isinstance(v, (int, float, list)) else _EVENTS[k]


def events_since(before: dict[str, Any]) -> dict[str, Any]:
    """:func:`events` since the snapshot ``before``, with the cache directory (None: off)."""
    now = events()
    out = {k: now[k][len(before[k]):] if isinstance(now[k], list) else now[k] - before[k] for k in now}
    out["dir"] = str(export_dir()) if export_dir() is not None else None
    return out


def check(root: Path | None = None, fix: bool = False) -> dict[str, Any]:
    """Verifies every artifact under ``root`` (default :func:`export_dir`) against the code loaded
    now, importing the modules their dependencies name; with ``fix``, removes what cannot be
    trusted: every artifact of an ambiguous key (more than one matches the code loaded now),
    unreadable ones, files without their pair, interrupted writes, and structure directories
    of an older format. Artifacts of other code are kept (they are valid for that code).

    Returns ``dict(root, structures, artifacts, bytes, matching, other_code, ambiguous,
    unreadable, orphans, old_format, removed, per_structure)``; the lists name files (paths
    relative to ``root``), ``per_structure`` gives each key's artifacts, matches and bytes.
    """
    import importlib

    root = Path(root) if root is not None else export_dir()
    out: dict[str, Any] = dict(root=str(root), structures=0, artifacts=0, bytes=0, matching=0, other_code=0,
                               ambiguous=[], unreadable=[], orphans=[], old_format=[], removed=0, per_structure={})
    if root is None or not root.is_dir():
        return out
    rel = lambda p: str(p.relative_to(root))  # noqa: E731
    bad: list[Path] = []
    for directory in sorted(p for p in root.iterdir() if p.is_dir()):
        files = sorted(p for p in directory.iterdir() if p.is_file())
        size = sum(p.stat().st_size for p in files)
        out["structures"] += 1
        out["bytes"] += size
        if not (directory / "FORMAT").exists() or (directory / "FORMAT").read_text().strip() != str(FORMAT):
            out["old_format"].append(rel(directory))
            bad.append(directory)
            continue
        pairs = []
        for p in files:
            paired = all((directory / f"{p.stem}{suffix}").exists() for suffix in (".jaxexport", ".deps"))
            if p.suffix == ".tmp" or (p.suffix in (".jaxexport", ".deps", ".cost") and not paired):
                out["orphans"].append(rel(p))  # an interrupted write, or half of an evicted pair
                bad.append(p)
            elif p.suffix == ".jaxexport":
                pairs.append(p)
        readable = []
        for path in pairs:
            deps = _read_deps(path.with_suffix(".deps"))
            if deps is None or _load(path, touch=False) is None:
                out["unreadable"].append(rel(path))
                bad.append(path)
                continue
            for name in {n.split(":", 1)[0] for n in deps if not n.startswith("@")}:
                with contextlib.suppress(Exception):  # a module this MJX lacks: that dependency fails
                    importlib.import_module(name)
            readable.append(path)
        fresh_digest()  # the imports above may have changed the code loaded now
        found = [p for p in matching(directory) if p in readable]
        if len(found) > 1:
            out["ambiguous"].extend(rel(p) for p in found)
            bad.extend(found)
        out["artifacts"] += len(readable)
        out["matching"] += len(found)
        out["other_code"] += len(readable) - len(found)
        out["per_structure"][directory.name] = dict(artifacts=len(readable), matching=len(found), bytes=size)
    if fix:
        import shutil

        for path in bad:
            if path.is_dir():
                shutil.rmtree(path, ignore_errors=True)
            elif path.suffix in (".jaxexport", ".deps"):
                _remove(path.with_suffix(".jaxexport"))
            else:
                with contextlib.suppress(OSError):
                    path.unlink()
            out["removed"] += 1
    return out


class _Lowered:
    """A lowered function whose ``cost_analysis()`` is read from beside its artifact once
    computed: XLA's cost analysis converts the whole module to HLO (0.1-0.4 s a rollout),
    which a warm sweep would otherwise pay for every scenario."""

    def __init__(self, lowered, artifact: Path | None):
        self._lowered, self._path = lowered, artifact.with_suffix(".cost") if artifact is not None else None

    def __getattr__(self, name):
        return getattr(self._lowered, name)

    def cost_analysis(self) -> dict[str, float]:
        if self._path is not None:
            with contextlib.suppress(OSError, ValueError):
                found = json.loads(self._path.read_text())
                if isinstance(found, dict):
                    return found
        cost = self._lowered.cost_analysis()
        cost = cost[0] if isinstance(cost, (list, tuple)) else cost
        cost = {k: float(v) for k, v in dict(cost or {}).items() if isinstance(v, (int, float))}
        if self._path is not None:
            with contextlib.suppress(OSError):
                _write(self._path, json.dumps(cost, sort_keys=True).encode())
        return cost


def evict(directory: Path, keep: Path | None = None, budget: int = MAX_BYTES) -> int:
    """Deletes the least recently used artifacts in ``directory`` (oldest modification time
    first; loading one touches it) until the rest fit in ``budget`` bytes, never ``keep``.
    Returns how many it deleted. JAX's own cache eviction does not see these files, and every
    new model structure (a fuzz run makes hundreds) adds one."""
    files = []
    for path in directory.rglob("*.jaxexport"):
        with contextlib.suppress(OSError):
            st = path.stat()
            files.append((st.st_mtime, st.st_size, path))
    total, deleted = sum(size for _, size, _ in files), 0
    for _, size, path in sorted(files):
        if total <= budget:
            break
        if path != keep:
            with contextlib.suppress(OSError):  # another process got there first
                path.with_suffix(".deps").unlink(missing_ok=True)
                path.with_suffix(".cost").unlink(missing_ok=True)
                path.unlink()
                deleted += 1
            total -= size
    return deleted


def call(fn: Callable, args: tuple, static: dict[str, Any], options: Options | None = None, options_key: Any = None):
    """``fn(*args, **static)`` for a ``jax.jit`` function ``fn``, through a saved artifact when possible
    (:func:`bind`)."""
    return bind(fn, args, static, options, options_key)(*args)


def _key_lock(key: tuple[str, str, str]) -> threading.Lock:
    with _KEY_LOCKS_GUARD:
        return _KEY_LOCKS.setdefault(key, threading.Lock())


#: Chooses XLA compiler options for a lowered function: ``options(lowered) -> (options, choice)``,
#: ``choice`` being what to report about it.
Options = Callable[[Any], tuple[dict[str, Any], Any]]


class Bound:
    """A compiled function bound by :func:`bind`: call it like the function; ``choice`` is what
    the options callback chose for it (None without one)."""

    def __init__(self, out_tree, run: Callable, choice: Any = None):
        self.out_tree, self.run, self.choice = out_tree, run, choice

    def __call__(self, *args):
        return jax.tree.unflatten(self.out_tree, self.run(*jax.tree.leaves(args)))


def bind(fn: Callable, args: tuple, static: dict[str, Any], options: Options | None = None,
         options_key: Any = None, counted: bool = True) -> Callable:
    """``fn`` with ``static`` bound and compiled, for calls whose arguments are shaped, typed and
    sharded like ``args``: a loaded or freshly exported artifact (exported on first use, from
    ``args``' shapes; saved when the cache is on), compiled ahead of time by XLA with the
    options ``options(lowered)`` chooses (a persistent-cache hit after the first process).

    Binding once and calling many times (the pieces of a stream) spares each call the
    structure's key. Threads binding the same function wait for one compile; binding is
    safe from any thread (a sweep compiles upcoming scenarios on idle cores). ``options_key``
    stands for what ``options`` depends on besides the function (the expected work): it is
    part of the in-memory key. Falls back to ``fn`` itself when the function cannot be
    exported (calling it then raises MJX's own error, e.g. ``NotImplementedError`` for an
    unsupported feature). Either way the code that runs is the code loaded now
    (:func:`fresh_digest`). ``counted=False``: a helper function (the drill-down's ``forward``),
    left out of :func:`events`, which count the rollouts a run loaded, traced and saved.
    """
    def event(kind: str, detail: Any = 1) -> None:
        if counted:
            _event(kind, detail)

    code = fresh_digest()
    direct = functools.partial(fn, **static)
    directory = export_dir()
    leaves, treedef = jax.tree.flatten(args)
    try:
        key = _key_of(fn, treedef, leaves, static, settings_digest())
    except (pickle.PicklingError, TypeError, AttributeError):  # static data that cannot be pickled
        return direct
    memo = key, code, repr(options_key)
    with _key_lock(memo):
        if memo not in _FUNCTIONS:
            t = time.perf_counter()
            found = _load_matching(directory / key) if directory is not None else None
            if found is not None:  # a compile phase: reading the artifact replaces the trace
                t = time.perf_counter() - t
                count("seconds", t)
                count("cache_load", t)
            if found is None:
                traced = _export(fn, treedef, leaves, static)
                if traced is None:
                    return direct
                (out_tree, exported, deps), artifact = traced, None
                event("traced")
                if isinstance(deps, str):  # a frame the key cannot name: used, never saved
                    event("unsaved", deps)
                elif directory is not None:
                    with contextlib.suppress(Exception):  # unwritable cache dir, no flatbuffers: use it unsaved
                        artifact = _save(directory / key, out_tree, exported, deps)
                        event("saved")
                        for other in _also_matching(directory / key, artifact, deps):  # keyed incompletely
                            _remove(other)
                            event("removed")
            else:
                event("loaded")
                if counted:
                    count("loaded")
                out_tree, exported, artifact = found
            lowered = jax.jit(exported.call).lower(*leaves)
            chosen, choice = options(_Lowered(lowered, artifact)) if options is not None else ({}, None)
            try:
                compiled = lowered.compile(compiler_options=chosen or None)
            except Exception as e:  # e.g. an option this XLA does not know: its defaults
                if not chosen:
                    raise
                compiled = lowered.compile()
                if isinstance(choice, dict):
                    choice = dict(choice, level="optimized", options_refused=" ".join(str(e).split())[:200])
            _FUNCTIONS[memo] = out_tree, compiled, choice
    return Bound(*_FUNCTIONS[memo])


def audit(fn: Callable, args: tuple, static: dict[str, Any]) -> tuple[list[str], list[str], dict[str, str] | str]:
    """Traces ``fn`` as :func:`bind` would (no compile, nothing saved) under ``sys.settrace``:
    (the :func:`traced_code` it ran as ``file:qualname`` lines, those of them :func:`uncovered`,
    the dependencies its artifact would be saved with or why it would not be saved). The key is
    complete for this trace when the second is empty; slower than a plain trace (~1.8x)."""
    fresh_digest()  # as bind does: memos of code since changed (a test's patch, undone) are dropped
    leaves, treedef = jax.tree.flatten(args)
    ran: set[types.CodeType] = set()
    traced = _export(fn, treedef, leaves, static, ran=ran)
    if traced is None:
        raise ValueError(f"{getattr(fn, '__qualname__', fn)} cannot be exported with these arguments")
    deps = traced[2]
    ours = sorted({_where(c) for c in traced_code(ran)})
    return ours, (uncovered(ran, deps) if isinstance(deps, dict) else []), deps


def _export(fn: Callable, treedef, leaves: list, static: dict[str, Any], ran: set[types.CodeType] | None = None):
    """(output tree structure, Exported, dependencies) of ``fn`` over flat leaves (:func:`dependencies`
    of the trace), or None if it cannot be exported. ``ran``: a set that gains every code object
    the trace ran (``sys.settrace``), without changing how dependencies are found."""
    out_tree = []
    python = getattr(fn, "__wrapped__", fn)  # traced afresh, never a jitted function's cached trace

    def flat(*leaves):
        out, tree = jax.tree.flatten(python(*jax.tree.unflatten(treedef, leaves), **static))
        out_tree.append(tree)
        return out

    shapes = [jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=getattr(x, "sharding", None)) for x in leaves]
    mode = dependency_mode()
    record = mode == "traced" or ran is not None
    called: set[types.CodeType] = set() if ran is None else ran
    before = sys.gettrace()

    def tracer(frame, event, arg):  # frames the trace runs: a 'call' event each, no line events
        called.add(frame.f_code)
        return before(frame, event, arg) if before is not None else None

    if record:
        sys.settrace(tracer)
    jitted = jax.jit(flat)
    try:
        exported = export.export(jitted, platforms=["cpu"])(*shapes)
    except Exception:  # noqa: BLE001 - the direct call that follows raises MJX's own error, if any
        return None
    finally:
        if record:
            sys.settrace(before)
    try:
        # the jaxpr export just traced (JAX's trace cache: ~2 ms), for its operations' call stacks
        codes = trace_codes(jitted.trace(*shapes).jaxpr) | (called if mode == "traced" else set())
        deps: dict[str, str] | str = dependencies(codes, follow=mode == "functions")
        if mode == "code":
            deps = {**{f"{m}:*": code_digest((m,)) for m in TRACED_MODULES},
                    **{k: v for k, v in deps.items() if k.startswith("@")}}
    except Unaccounted as e:
        deps = f"not saved: {e}"
    return out_tree[0], exported, deps
