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
compilation. Each artifact there is valid for the code its trace could have run
(:func:`dependencies`): every function of ``mujoco.mjx`` and ``mjxdiff.engine.engines`` on
the call stack of an operation it emitted, and every function those can call by
name, each digested by bytecode, constants and nested code, default arguments,
closure contents and the globals it reads. It is loaded only while all of them have
the same digest. MJX edited in
place, patched at run time or rebuilt under the same version number is therefore
traced again wherever the change reaches a function the rollout ran, and only there.
"""

from __future__ import annotations

import contextlib
import functools
import enum
import hashlib
import importlib.metadata
import json
import os
import pickle
import sys
import threading
import time
import types
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

import jax
import jax.core
import numpy as np
from jax import export

from mjxdiff.files import atomic_write

__all__ = ["audit", "bind", "call", "check", "clear", "code_digest", "code_read_once", "count", "events",
           "events_since", "evict", "export_dir", "fresh_digest", "loaded_count", "rollout_digest", "settings_digest",
           "tally", "traced_code", "uncovered", "untraced"]

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


#: Modules whose code a rollout traces: MJX's, and mjxdiff's own traced functions.
TRACED_MODULES = ("mujoco.mjx", "mjxdiff.engine.engines", "mjxdiff.engine.trajectory", "mjxdiff.input.joints",
                  "mjxdiff.compat", "mjxdiff.engine.stages")
#: JAX settings that change what a trace or XLA produces.
_JAX_SETTINGS = ("jax_enable_x64", "jax_default_matmul_precision", "jax_numpy_dtype_promotion",
                 "jax_default_prng_impl", "jax_threefry_partitionable", "jax_use_shardy_partitioner")

_UNTRACED: dict[int, Any] = {}  # id -> object: run-time state of traced modules, left out of digests


def untraced(value: Any) -> Any:
    """Marks ``value`` (a counter, a memo dict of a traced module) as run-time state that
    never changes what a trace produces, so that :func:`code_digest` leaves it out; returns it."""
    _UNTRACED[id(value)] = value
    return value


_CODE_MEMO: dict[int, tuple[types.CodeType, bytes]] = {}  # id -> (code, digest); code objects are immutable
_SIMPLE = (type(None), bool, int, float, complex, str, bytes, range, slice, type(Ellipsis))


def _code(code: types.CodeType) -> bytes:
    """Digest of what a code object does: bytecode, constants (nested code included), the
    names it reads, its signature; not its file name or line numbers."""
    memo = _CODE_MEMO.get(id(code))
    if memo is None or memo[0] is not code:
        h = hashlib.sha256()
        for part in (code.co_code, code.co_names, code.co_varnames, code.co_freevars, code.co_cellvars,
                     code.co_argcount, code.co_posonlyargcount, code.co_kwonlyargcount, code.co_flags):
            h.update(repr(part).encode())
        for const in code.co_consts:
            h.update(_code(const) if isinstance(const, types.CodeType) else _const(const).encode())
        memo = _CODE_MEMO[id(code)] = (code, h.digest())
    return memo[1]


def _const(value: Any) -> str:
    """A constant's repr that is the same in every process (a frozenset's order follows string hashing)."""
    if isinstance(value, (frozenset, set)):
        return f"{type(value).__name__}({sorted(_const(v) for v in value)})"
    if isinstance(value, tuple):
        return f"({', '.join(_const(v) for v in value)},)"
    return repr((type(value).__name__, value))


#: Packages whose objects MJX's warp backend (``mujoco.mjx.warp``) holds and whose attributes
#: change at run time (Warp's devices, kernels and modules once Warp initialises): fed by type.
#: The JAX implementation mjxdiff traces never runs them.
_FOREIGN_STATE = ("warp", "mujoco_warp")


class _Digest:
    """One digest of a set of values, functions followed into their closures and globals.

    Each object is fed once (a second visit feeds a back-reference), so
    mutually recursive functions and shared helpers cost one visit.
    """

    def __init__(self, modules: tuple[str, ...]):
        self.h, self.seen, self.modules = hashlib.sha256(), {}, modules

    def _ours(self, module: str | None) -> bool:
        return _under(module, self.modules)

    def feed(self, value: Any, depth: int = 0) -> None:
        h = self.h
        if isinstance(value, _SIMPLE) or isinstance(value, enum.Enum):
            h.update(repr((type(value).__name__, value)).encode())
            return
        if isinstance(value, types.ModuleType):
            h.update(b"module " + value.__name__.encode())
            if sys.modules.get(value.__name__) is not value:  # a copy bound by hand: its name loads other code
                h.update(b"unregistered " + _module_content(value))
            return
        if _UNTRACED.get(id(value)) is value:
            h.update(b"untraced")
            return
        module = getattr(type(value), "__module__", None)
        if _under(module, _FOREIGN_STATE):  # its run-time state is not code (warp's kernels after init)
            h.update(f"foreign {module}.{type(value).__qualname__}".encode())
            return
        if id(value) in self.seen:
            h.update(b"ref %d" % self.seen[id(value)])
            return
        self.seen[id(value)] = len(self.seen)
        self.seen.setdefault(-id(value), value)  # keeps it alive: ids stay unique while hashing
        if depth > 12:
            h.update(b"deep " + type(value).__qualname__.encode())
            return
        kind = type(value)
        h.update(kind.__qualname__.encode())
        if isinstance(value, types.FunctionType):
            self._function(value, depth)
        elif isinstance(value, types.CodeType):
            h.update(_code(value))
        elif isinstance(value, (types.MethodType, staticmethod, classmethod)):
            self.feed(value.__func__, depth + 1)
        elif isinstance(value, functools.partial):
            for part in (value.func, value.args, value.keywords):
                self.feed(part, depth + 1)
        elif isinstance(value, property):
            for part in (value.fget, value.fset, value.fdel):
                self.feed(part, depth + 1)
        elif isinstance(value, (tuple, list)):
            h.update(b"%d" % len(value))
            for item in value:
                self.feed(item, depth + 1)
        elif isinstance(value, (set, frozenset)):
            h.update(_const(value).encode())
        elif isinstance(value, dict):
            for k in sorted(value, key=repr):
                h.update(repr(k).encode())
                self.feed(value[k], depth + 1)
        elif isinstance(value, np.ndarray) or (isinstance(value, jax.Array) and not isinstance(value, jax.core.Tracer)):
            a = np.asarray(value)
            h.update(repr((a.dtype.str, a.shape)).encode() + (a.tobytes() if a.dtype != object else repr(a).encode()))
        elif isinstance(value, type) and issubclass(value, enum.Enum):  # members, not lazily filled lookup tables
            h.update(f"{value.__module__}.{value.__qualname__}".encode())
            h.update(repr([(m.name, m.value) for m in value]).encode())
            if self._ours(value.__module__):  # and its code: MJX's JointType.qpos_width, dof_width
                for k in sorted(vars(value)):
                    code = vars(value)[k]
                    if isinstance(code, (types.FunctionType, staticmethod, classmethod, property)):
                        h.update(k.encode())
                        self.feed(code, depth + 1)
        elif isinstance(value, type):
            h.update(f"{value.__module__}.{value.__qualname__}".encode())
            if self._ours(value.__module__):  # a class MJX or mjxdiff defines: its methods and attributes
                for k in sorted(vars(value)):
                    if not k.startswith("__") or k in ("__init__", "__call__", "__post_init__"):
                        h.update(k.encode())
                        self.feed(vars(value)[k], depth + 1)
        elif hasattr(value, "__wrapped__") or hasattr(value, "__dict__"):
            # jitted functions, custom_jvp/vjp, other callable objects: what they wrap and their
            # public attributes (custom_jvp's fun and jvp); private ones are JAX's caches
            wrapped = getattr(value, "__wrapped__", None)
            if wrapped is not None:
                self.feed(wrapped, depth + 1)
            for k, v in sorted(getattr(value, "__dict__", {}).items()):
                if not k.startswith("_"):
                    h.update(k.encode())
                    self.feed(v, depth + 1)
        else:  # builtins and other opaque values: their name, or a repr without addresses
            text = repr(value)
            h.update((getattr(value, "__qualname__", "") if " at 0x" in text else text).encode())

    def _function(self, fn: types.FunctionType, depth: int) -> None:
        h = self.h
        h.update(_code(fn.__code__))
        self.feed(fn.__defaults__, depth + 1)
        self.feed(fn.__kwdefaults__, depth + 1)
        for cell in fn.__closure__ or ():
            try:
                self.feed(cell.cell_contents, depth + 1)
            except ValueError:  # an empty cell
                h.update(b"empty cell")
        # the globals it reads: a module-level constant or helper of a user's patch counts too
        names = set(fn.__code__.co_names)
        stack = [c for c in fn.__code__.co_consts if isinstance(c, types.CodeType)]
        while stack:
            code = stack.pop()
            names.update(code.co_names)
            stack.extend(c for c in code.co_consts if isinstance(c, types.CodeType))
        for name in sorted(names):
            if name in fn.__globals__:
                h.update(name.encode())
                self.feed(fn.__globals__[name], depth + 1)


_IN_PROGRESS = threading.local()


def _module_content(module: types.ModuleType) -> bytes:
    """Digest of everything ``module`` holds, functions in full: for a module object that is not
    the one ``sys.modules`` has under its name (an edited copy bound where MJX imported the
    original), whose functions therefore cannot be found again by name."""
    busy = getattr(_IN_PROGRESS, "modules", None)
    if busy is None:
        busy = _IN_PROGRESS.modules = set()
    if id(module) in busy:
        return b"cycle"
    busy.add(id(module))
    try:
        d = _Digest(TRACED_MODULES)  # a plain digest: every function in full, none by name
        d.h.update(str(getattr(module, "__file__", "")).encode())
        _feed_module(d, module)
        return d.h.digest()
    finally:
        busy.discard(id(module))


def _feed_module(d: _Digest, module: types.ModuleType) -> None:
    """Feeds every module-level name and value of ``module`` to ``d``."""
    for attr in sorted(vars(module)):
        if not attr.startswith(("__", "@")):  # "@py_builtins": pytest's assertion rewriting
            d.h.update(attr.encode())
            d.feed(vars(module)[attr])


def _is_test(name: str) -> bool:
    leaf = name.rsplit(".", 1)[-1]
    return leaf.startswith("test_") or leaf.endswith("_test")


def _under(module: str | None, prefixes: tuple[str, ...]) -> bool:
    """Whether the module named ``module`` is one of ``prefixes`` or inside one of them."""
    return bool(module) and any(module == p or module.startswith(p + ".") for p in prefixes)


def _modules(prefixes: tuple[str, ...]) -> list[tuple[str, types.ModuleType]]:
    """Imported modules under ``prefixes``, test helpers aside (never traced by a rollout;
    pytest rewrites them, so their code differs between a test run and the CLI)."""
    return sorted((name, module) for name, module in list(sys.modules.items())
                  if module is not None and _under(name, prefixes) and not _is_test(name))


def code_digest(modules: tuple[str, ...] = ("mujoco.mjx",), names: Sequence[str] | None = None) -> str:
    """Hex SHA-256 of the code now loaded in ``modules`` (names, with their submodules):
    every module-level function, class and value, functions followed into their closures,
    defaults and the globals they read. Equal for the same code, whichever file it came from;
    different after any edit or monkeypatch that changes what runs. ``names``: exactly these
    modules (imported if they are not), as :func:`loaded_modules` listed them in another process.

    ``report.json`` names the MJX that was tested by ``code_digest()``.
    """
    if not _ONCE["depth"]:
        return _read_code(modules, names)
    once = (modules, None if names is None else tuple(sorted(names)))
    with _ONCE_LOCK:  # threads asking at once wait for the one reading
        if once not in _ONCE["memo"]:
            _ONCE["memo"][once] = _read_code(modules, names)
        return _ONCE["memo"][once]


def _read_code(modules: tuple[str, ...], names: Sequence[str] | None) -> str:
    d = _Digest(modules)
    found = _modules(modules) if names is None else [(n, importlib.import_module(n)) for n in sorted(names)]
    for name, module in found:
        d.h.update(b"module " + name.encode())
        _feed_module(d, module)
    return d.h.hexdigest()


_ONCE: dict[str, Any] = {"depth": 0, "memo": {}}  # open code_read_once blocks; (modules, names) -> digest
_ONCE_LOCK = threading.RLock()


@contextlib.contextmanager
def code_read_once() -> Iterator[None]:
    """While the block runs (in any thread), :func:`code_digest` reads each set of modules once:
    a sweep judges the code loaded when it began, and an edit or a patch made in the middle of
    one is seen by the next. A digest costs ~40 ms; a warm sweep asked for one ~130 times
    (each rollout's bind, each scenario's record), a tenth of its CPU time."""
    with _ONCE_LOCK:
        _ONCE["depth"] += 1
    try:
        yield
    finally:
        with _ONCE_LOCK:
            _ONCE["depth"] -= 1
            if not _ONCE["depth"]:
                _ONCE["memo"].clear()


def loaded_modules(modules: tuple[str, ...] = ("mujoco.mjx",)) -> list[str]:
    """Names of the modules :func:`code_digest` of ``modules`` digests now."""
    return [name for name, _ in _modules(modules)]


def settings_digest() -> str:
    """Hex SHA-256 of what else decides a compiled rollout: versions, JAX settings, XLA flags."""
    config = [(k, str(getattr(jax.config, k, None))) for k in _JAX_SETTINGS]
    return hashlib.sha256(repr((_versions(), config, os.environ.get("XLA_FLAGS", ""))).encode()).hexdigest()


def rollout_digest() -> str:
    """The code and settings a rollout traced now would depend on (:func:`code_digest` of
    :data:`TRACED_MODULES` and :func:`settings_digest`); part of every artifact's key."""
    return hashlib.sha256((code_digest(TRACED_MODULES) + settings_digest()).encode()).hexdigest()


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


@functools.cache
def _versions() -> tuple[str, ...]:
    # mujoco-core (MuJoCo 4.0 on) is the C library itself, which `mujoco` pins but a user can
    # replace alone (pip install --no-deps mujoco-core==4.0.1): its model compiler feeds put_model
    return (*(importlib.metadata.version(p) for p in ("jax", "jaxlib", "mujoco", "mujoco-mjx", "numpy")),
            _installed("mujoco-core"),
            sys.version)  # with jax, jaxlib, numpy and the standard library left out of dependencies


def _installed(dist: str) -> str:
    """``dist``'s installed version, or ``""`` where it is not installed."""
    try:
        return importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        return ""


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
    """Digest of this file: the code that wraps every trace (``flat``) and decides what a key holds."""
    return hashlib.sha256(Path(__file__).read_bytes()).hexdigest()


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


_SEEN: dict[str, str | None] = {"digest": None}


def fresh_digest() -> str:
    """:func:`rollout_digest` now; when it differs from the last one this process saw, JAX's
    in-memory caches are cleared first (``jax.clear_caches``), so that no function compiled
    or traced from the old code (a jitted function, a cached scan body) runs again."""
    digest = rollout_digest()
    if _SEEN["digest"] not in (None, digest):
        jax.clear_caches()
        for memo in (_FUNCTION_DIGESTS, _MODULE_FUNCTIONS, _OWNERS, _REFERENCES, _METHODS):
            memo.clear()
    _SEEN["digest"] = digest
    return digest


# --- what one trace depended on -------------------------------------------------------------
#
# An artifact is valid for the code its trace ran. Its dependencies are every code object on the
# call stack of every operation it emitted (JAX's tracebacks in the jaxpr, sub-jaxprs included),
# below the wrapper the trace starts from, and the functions of TRACED_MODULES those can call by
# name (dependency_mode() "functions"), or those sys.settrace saw run ("traced"). Code of
# TRACED_MODULES is named by module and qualname and digested "shallowly": its code (nested
# functions included), defaults, closure and the globals it reads, where a function of
# TRACED_MODULES stands for itself by name (its own code counts only where it is a dependency).
# An edit of one collision function therefore retraces only the rollouts that can reach it.
# Code from any other file is named by file and qualname and digested in full; jax, jaxlib, numpy
# and the standard library are left out (their versions are in the key). Code that cannot be
# named leaves the trace unsaved: the key fails closed.

_FUNCTION_DIGESTS: dict[tuple[str, str], str] = {}  # (module, qualname) -> shallow digest; cleared on a code change


class _Shallow(_Digest):
    """A :class:`_Digest` in which functions of the traced modules met below the top stand for
    themselves by name, where that name finds them again (:func:`_resolve`: their own dependency
    entry digests them). Any other function is digested in full: a second closure of one
    qualname (each of MJX's ``@collider`` wrappers), or a function of an edited copy of a module
    bound by hand where MJX holds the original (a dispatch table's entry), whose name finds the
    installed function instead."""

    def feed(self, value: Any, depth: int = 0) -> None:
        if depth > 0:
            fn = _unwrap(value)
            if (isinstance(fn, types.FunctionType) and self._ours(getattr(fn, "__module__", None))
                    and _resolve(fn.__module__, fn.__code__.co_qualname) is fn):
                self.h.update(f"fn {fn.__module__}.{fn.__code__.co_qualname}".encode())
                return
        super().feed(value, depth)


def _unwrap(value: Any) -> Any:
    for _ in range(8):
        inner = getattr(value, "__wrapped__", None)
        if inner is None or inner is value:
            break
        value = inner
    return value


_MODULE_FUNCTIONS: dict[str, dict[str, types.FunctionType]] = {}  # cleared on a code change, with the digests


def _functions(module: str) -> dict[str, types.FunctionType]:
    """``co_qualname`` -> function, for the functions ``module`` defines that can be found from its
    namespace: module-level functions and methods (unwrapped), and the functions held in their
    closures (a decorator's wrapper keeps the decorated function there: MJX's colliders)."""
    if module not in _MODULE_FUNCTIONS:
        found: dict[str, types.FunctionType] = {}
        visited: set[int] = set()

        def visit(value: Any, depth: int) -> None:
            fn = _unwrap(value.__func__ if isinstance(value, (staticmethod, classmethod)) else value)
            if isinstance(value, property):
                for part in (value.fget, value.fset, value.fdel):
                    visit(part, depth)
                return
            if not isinstance(fn, types.FunctionType) or fn.__module__ != module:
                return
            if fn.__code__.co_filename.startswith("<"):  # generated (a dataclass's __init__): one qualname for all
                return
            found.setdefault(fn.__code__.co_qualname, fn)
            # every wrapper's closure, not only the first of a qualname: each of MJX's colliders is
            # a `collider.<locals>.wrapper.<locals>.collide` holding its own raw function
            if id(fn) in visited or depth > 3:
                return
            visited.add(id(fn))
            for cell in fn.__closure__ or ():
                with contextlib.suppress(ValueError):
                    visit(cell.cell_contents, depth + 1)

        for value in list(vars(sys.modules[module]).values()):
            if isinstance(value, type) and value.__module__ == module:
                for member in list(vars(value).values()):
                    visit(member, 0)
            else:
                visit(value, 0)
        _MODULE_FUNCTIONS[module] = found
    return _MODULE_FUNCTIONS[module]


def _resolve(module: str, qualname: str) -> Any:
    return _functions(module).get(qualname) if module in sys.modules else None


def function_digest(module: str, qualname: str) -> str:
    """Shallow digest of the module-level function or method ``module.qualname`` as loaded now
    ("missing" if there is none); for ``*``, :func:`code_digest` of the whole module."""
    key = (module, qualname)
    if key not in _FUNCTION_DIGESTS and qualname == "*":
        _FUNCTION_DIGESTS[key] = code_digest((module,)) if module in sys.modules else "missing"
    if key not in _FUNCTION_DIGESTS:
        obj = _resolve(module, qualname)
        if obj is None:
            _FUNCTION_DIGESTS[key] = "missing"
        else:
            d = _Shallow(TRACED_MODULES)
            d.feed(obj)
            _FUNCTION_DIGESTS[key] = d.h.hexdigest()
    return _FUNCTION_DIGESTS[key]


_OWNERS: dict[str, dict[int, tuple[types.CodeType, tuple[str, str]]]] = {}  # cleared on a code change


def _nested(code: types.CodeType) -> Iterator[types.CodeType]:
    """``code`` and every code object nested in it (its functions, lambdas, comprehensions)."""
    yield code
    for const in code.co_consts:
        if isinstance(const, types.CodeType):
            yield from _nested(const)


def _owners() -> dict[int, tuple[types.CodeType, tuple[str, str]]]:
    """id(code) -> (code, (module, qualname)) for the code of TRACED_MODULES as loaded now: every
    function :func:`_functions` finds (its nested code under its name), functions held in a
    module's tables (``*``: the whole module), and each module's own body (``*``)."""
    if "index" not in _OWNERS:
        index: dict[int, tuple[types.CodeType, tuple[str, str]]] = {}

        def own(code: types.CodeType, owner: tuple[str, str]) -> None:
            for c in _nested(code):
                index.setdefault(id(c), (c, owner))

        for name, module in _modules(TRACED_MODULES):
            for qualname, fn in _functions(name).items():
                own(fn.__code__, (name, qualname))
            for value in list(vars(module).values()):
                if isinstance(value, type) and value.__module__ == name:  # a dataclass's generated methods
                    for member in list(vars(value).values()):
                        fn = member.__func__ if isinstance(member, (staticmethod, classmethod)) else member
                        if isinstance(fn, types.FunctionType) and fn.__code__.co_filename.startswith("<"):
                            own(fn.__code__, (name, "*"))
                # lambdas and partials in dispatch tables
                items = (list(value.values()) if isinstance(value, dict)
                         else value if isinstance(value, (list, tuple)) else ())
                for item in items:
                    for part in (item if isinstance(item, tuple) else (item,)):
                        fn = _unwrap(part.func if isinstance(part, functools.partial) else part)
                        if isinstance(fn, types.FunctionType) and fn.__module__ == name:
                            own(fn.__code__, (name, "*"))
        _OWNERS["index"] = index
    return _OWNERS["index"]


def _module_files() -> dict[str, str]:
    """Source file -> module of TRACED_MODULES, by ``__file__`` and by its functions' ``co_filename``
    (they differ for a module compiled from another file): where a module's own body runs."""
    out = {}
    for name, module in _modules(TRACED_MODULES):
        files = {getattr(module, "__file__", None)} | {f.__code__.co_filename for f in _functions(name).values()}
        for file in files - {None}:
            out.setdefault(file, name)
    return out


@functools.cache
def _ignored_packages() -> tuple[str, ...]:
    """Directories of the packages whose code is left out of dependencies, their versions being
    in the key (:func:`settings_digest`): jax, jaxlib and numpy."""
    import jaxlib

    dirs = []
    for m in (jax, jaxlib, np):
        assert m.__file__ is not None  # regular packages, not namespace ones
        dirs.append(os.path.dirname(m.__file__).rstrip(os.sep) + os.sep)
    return tuple(sorted(dirs))


@functools.cache
def _stdlib_roots() -> tuple[str, ...]:
    """The standard library's directories; not a venv's ``sysconfig`` "platstdlib", which holds
    only ``site-packages``. In a plain install they hold ``site-packages`` too, which
    :func:`_ignored` never leaves out."""
    import sysconfig

    roots = {sysconfig.get_path("stdlib"), os.path.dirname(os.__file__)}
    return tuple(sorted(r.rstrip(os.sep) + os.sep for r in roots if r))


_INSTALLED = (f"{os.sep}site-packages{os.sep}", f"{os.sep}dist-packages{os.sep}")


def _ignored(file: str) -> bool:
    """Whether code from ``file`` is left out of dependencies: jax's, jaxlib's, numpy's, the
    standard library's and this module's. An installed package other than those three (MJX in a
    venv's ``lib/python3.X/site-packages``, under the standard library's directory in a plain
    install) never is, so MJX edited where it is installed changes the key."""
    if file.startswith("<frozen ") or file == __file__ or file.startswith(_ignored_packages()):
        return True
    return file.startswith(_stdlib_roots()) and not any(part in file for part in _INSTALLED)


def _is_flat(code: types.CodeType) -> bool:
    """Whether ``code`` is the wrapper :func:`_export` traces: frames above it are outside the trace."""
    return code.co_filename == __file__ and code.co_name == "flat"


def trace_codes(closed_jaxpr) -> set[types.CodeType]:
    """The code objects on the call stack of every operation of ``closed_jaxpr`` and of the
    jaxprs inside it (scan, while, cond, pjit bodies), from JAX's tracebacks, inside the trace:
    frames below :func:`_export`'s wrapper. A stack that does not reach the wrapper (a body
    traced from a callback, whose Python stack starts there, or one JAX took from its caches)
    keeps its frames up to the outermost of TRACED_MODULES, or all of them if it has none."""
    from jax._src import core

    codes: set[types.CodeType] = set()
    stacks: set[tuple[int, ...]] = set()
    seen_jaxprs: set[int] = set()
    todo = [closed_jaxpr.jaxpr]
    owners = _owners()
    while todo:
        jaxpr = todo.pop()
        if id(jaxpr) in seen_jaxprs:
            continue
        seen_jaxprs.add(id(jaxpr))
        for eqn in jaxpr.eqns:
            tb = eqn.source_info.traceback
            if tb is not None:
                stack = tb.raw_frames()[0]
                key = tuple(map(id, stack))
                if key not in stacks:
                    stacks.add(key)
                    cut = next((i for i, c in enumerate(stack) if _is_flat(c)), None)
                    if cut is None:
                        ours = [i for i, c in enumerate(stack) if id(c) in owners]
                        cut = ours[-1] + 1 if ours else len(stack)
                    codes.update(stack[:cut])
            todo.extend(core.jaxprs_in_params(eqn.params))
    return codes


class Unaccounted(Exception):
    """A frame of a trace whose code the key cannot name: the artifact is not saved."""


def _foreign_key(code: types.CodeType, qualname: str | None = None) -> str:
    """``@file:qualname`` of ``code`` (or of its enclosing ``qualname``); for generated code (a file
    name like ``<string>``, shared by every namedtuple's ``__new__``), ``#`` and its code's digest."""
    key = f"@{code.co_filename}:{qualname or code.co_qualname}"
    if code.co_filename.startswith("<") and qualname is None:
        key += "#" + _code(code).hex()[:16]
    return key


def _live_functions(keys: set[str]) -> dict[str, list[types.FunctionType]]:
    """``@file:qualname`` -> the live functions of that code's file and qualified name (one pass
    over the objects the garbage collector tracks, ~0.1-0.2 s; only traces that ran code outside
    TRACED_MODULES and the ignored packages need it)."""
    import gc

    out: dict[str, list[types.FunctionType]] = {}
    if not keys:
        return out
    files = {k[1:].rsplit(":", 1)[0] for k in keys}
    # gc.get_objects() holds a reference to every tracked object, tuples another thread is still
    # building included; if that thread resumed and resized one (tuple(generator)), CPython would
    # raise "SystemError: Objects/tupleobject.c:927: bad argument to internal function" there (seen
    # once in a host-interface check beside a compile worker). So no other thread runs until the
    # list is gone. No gc.collect() (~0.5 s): a dead function not yet collected only makes a key
    # stricter.
    # Only the filter runs meanwhile (hashing, which may release the GIL, comes after).
    interval = sys.getswitchinterval()
    sys.setswitchinterval(1e6)
    try:
        objects = gc.get_objects()
        try:
            found = [o for o in objects if type(o) is types.FunctionType and o.__code__.co_filename in files]
        finally:
            del objects
    finally:
        sys.setswitchinterval(interval)
    for fn in found:
        for key in {_foreign_key(fn.__code__), _foreign_key(fn.__code__, fn.__code__.co_qualname)}:
            if key in keys:
                out.setdefault(key, []).append(fn)
    return out


def _foreign_digest(functions: list[types.FunctionType]) -> str:
    """Digest of live functions of one file and qualified name: each one's code, defaults,
    closure and the globals it reads (functions of TRACED_MODULES by name), in a stable order."""
    digests = []
    for fn in functions:
        d = _Shallow(TRACED_MODULES)
        d.feed(fn)
        digests.append(d.h.hexdigest())
    return hashlib.sha256(repr(sorted(digests)).encode()).hexdigest() if digests else "missing"


def _generated_by_ignored(functions: list[types.FunctionType]) -> bool:
    """Whether generated functions (``exec``'d by dataclasses, namedtuple) all belong to modules
    of the ignored packages (:func:`_ignored`), or are a namedtuple's ``__new__`` (module
    ``namedtuple_<name>``: ``lambda _cls, a, b: _tuple_new(_cls, (a, b))``, all of it in the
    code's own digest, which is part of the key)."""
    def ignored(fn: types.FunctionType) -> bool:
        module = fn.__module__
        if not module:  # exec'd with no __name__ in its globals: no package to account it to (fail closed)
            return False
        if module.startswith("namedtuple_"):
            return True
        file = getattr(sys.modules.get(module), "__file__", None)
        return file is not None and _ignored(file)
    return bool(functions) and all(ignored(fn) for fn in functions)


def _enclosing(qualname: str) -> list[str]:
    """``a.<locals>.b.<locals>.c`` -> ``["a.<locals>.b", "a"]``: the functions a nested one is defined in."""
    parts = qualname.split(".<locals>.")
    return [".<locals>.".join(parts[:i]) for i in range(len(parts) - 1, 0, -1)]


def _account(codes: set[types.CodeType]) -> tuple[set[tuple[str, str]], dict[str, str]]:
    """Names every code object a trace ran: ``(found, foreign)``.

    - code of TRACED_MODULES (by identity, :func:`_owners`): ``(module, qualname)`` in ``found``;
    - a module's own body: ``(module, "*")``;
    - code of jax, jaxlib, numpy, the standard library and this file: left out (:func:`_ignored`);
    - any other code (a patch from a user's module, an edited copy of an MJX module loaded from
      another file, a module whose ``__file__`` is not its code's file): ``@file:qualname`` in
      ``foreign``, with :func:`_foreign_digest` of the live functions that hold it, or of the
      nearest enclosing function that does (a closure made during the trace).

    Raises :class:`Unaccounted` for code no live function holds, nor contains.
    """
    owners, files = _owners(), None
    found: set[tuple[str, str]] = set()
    others: list[types.CodeType] = []
    for code in codes:
        owner = owners.get(id(code))
        if owner is not None and owner[0] is code:
            found.add(owner[1])
        elif _ignored(code.co_filename):
            continue
        elif code.co_name == "<module>":
            files = _module_files() if files is None else files
            if code.co_filename not in files:
                raise Unaccounted(f"module-level code of {code.co_filename} ran inside the trace")
            found.add((files[code.co_filename], "*"))
        else:
            others.append(code)
    foreign: dict[str, str] = {}
    if others:
        wanted = {_foreign_key(c, q) for c in others for q in [None, *_enclosing(c.co_qualname)]}
        live = _live_functions(wanted)
        for code in others:
            if code.co_filename.startswith("<") and _generated_by_ignored(live.get(_foreign_key(code), [])):
                continue  # a jax or standard-library class's generated __init__, a namedtuple's __new__
            for qualname in [None, *_enclosing(code.co_qualname)]:
                key = _foreign_key(code, qualname)
                if any(c is code for fn in live.get(key, ()) for c in _nested(fn.__code__)):
                    foreign[key] = _foreign_digest(live[key])
                    break
            else:
                raise Unaccounted(f"{code.co_qualname} ({code.co_filename}:{code.co_firstlineno}) ran inside the "
                                  f"trace, but no live function holds its code")
    return found, foreign


_REFERENCES: dict[tuple[str, str], tuple[tuple[tuple[str, str], bool], ...]] = {}  # cleared on a code change


def _ours(value: Any) -> bool:
    return _under(getattr(value, "__module__", None), TRACED_MODULES)


def _as_dependency(module: str, qualname: str) -> tuple[str, str]:
    """(module, qualname) code of ``module.qualname`` is a dependency as: its outermost enclosing
    function's name (a nested function's code is part of it), or ``*`` (the whole module) when
    that cannot be found again by name (a lambda in a dict)."""
    qualname = qualname.split(".<locals>")[0]
    return (module, qualname if qualname != "*" and _resolve(module, qualname) is not None else "*")


def _name_of(fn: types.FunctionType) -> tuple[str, str]:
    return _as_dependency(fn.__module__, fn.__code__.co_qualname)


def _code_names(code: types.CodeType) -> set[str]:
    names = set(code.co_names) | set(code.co_freevars)
    for const in code.co_consts:
        if isinstance(const, types.CodeType):
            names |= _code_names(const)
    return names


def _functions_in(value: Any, depth: int = 0) -> Iterator[types.FunctionType]:
    """The functions of TRACED_MODULES ``value`` stands for: itself (unwrapped), a class's
    methods (a class called runs its ``__init__``, protocols run the rest), a partial's or a
    custom derivative's functions."""
    if depth > 3:
        return
    if isinstance(value, (staticmethod, classmethod)):
        value = value.__func__
    if isinstance(value, property):
        for part in (value.fget, value.fset, value.fdel):
            yield from _functions_in(part, depth + 1)
        return
    value = _unwrap(value)
    if isinstance(value, types.FunctionType):
        if _ours(value):  # generated code (a dataclass's __init__) stands for its whole module
            yield value
        return
    if isinstance(value, functools.partial):
        yield from _functions_in(value.func, depth + 1)
        return
    if isinstance(value, type):
        if _ours(value):
            for member in list(vars(value).values()):
                yield from _functions_in(member, depth + 1)
        return
    for attr in ("fun", "jvp", "fwd", "bwd"):  # jax.custom_jvp / custom_vjp
        inner = getattr(type(value), "__module__", "").startswith("jax") and getattr(value, attr, None)
        if callable(inner):
            yield from _functions_in(inner, depth + 1)


def _references(module: str, qualname: str) -> tuple[tuple[tuple[str, str], bool], ...]:
    """The functions of TRACED_MODULES that ``module.qualname`` can call by name, each with
    whether its own references count (False for functions held in a module-level table, which
    a dispatch picks from: counted, not followed)."""
    key = (module, qualname)
    if key in _REFERENCES:
        return _REFERENCES[key]
    fn = _resolve(module, qualname)
    found: dict[tuple[str, str], bool] = {}
    if fn is not None:
        names = _code_names(fn.__code__)
        spaces = [fn.__globals__] + [vars(v) for v in list(fn.__globals__.values())
                                     if isinstance(v, types.ModuleType) and _under(v.__name__, TRACED_MODULES)]
        candidates = [space[n] for n in names for space in spaces if n in space]
        candidates += [method for n in names for method in _methods().get(n, ())]  # x.method() on our objects
        for cell in fn.__closure__ or ():
            with contextlib.suppress(ValueError):
                candidates.append(cell.cell_contents)
        candidates += list(fn.__defaults__ or ()) + list((fn.__kwdefaults__ or {}).values())
        for value in candidates:
            if isinstance(value, (dict, list, tuple, set, frozenset)):
                items = list(value.items()) if isinstance(value, dict) else list(value)
                for item in items:
                    for part in (item if isinstance(item, tuple) else (item,)):
                        for f in _functions_in(part):
                            found.setdefault(_name_of(f), False)
                continue
            for f in _functions_in(value):
                found[_name_of(f)] = True
    out = tuple(sorted(found.items()))
    _REFERENCES[key] = out
    return out


_METHODS: dict[str, dict[str, list]] = {}  # cleared on a code change


def _methods() -> dict[str, list]:
    """Attribute name -> the methods of that name of every class of TRACED_MODULES."""
    if "index" not in _METHODS:
        index: dict[str, list] = {}
        for _, module in _modules(TRACED_MODULES):
            for value in list(vars(module).values()):
                if isinstance(value, type) and value.__module__ == module.__name__:
                    for attr, member in list(vars(value).items()):
                        index.setdefault(attr, []).append(member)
        _METHODS["index"] = index
    return _METHODS["index"]


#: Modules whose every function a trace depends on: MJX's pytree machinery, which JAX calls
#: (flatten, hash, equality) rather than MJX code by name, and the types whose generated
#: methods (``__init__``, ``__eq__``) every ``replace`` runs.
ALWAYS_DEPENDED_ON = ("mujoco.mjx._src.dataclasses", "mujoco.mjx._src.types")


def _closure(found: set[tuple[str, str]]) -> set[tuple[str, str]]:
    """``found`` and every function of TRACED_MODULES it can reach by name (:func:`_references`)."""
    out, todo = set(found), [f for f in found if f[1] != "*"]
    while todo:
        for ref, follow in _references(*todo.pop()):
            if ref not in out:
                out.add(ref)
                if follow and ref[1] != "*":
                    todo.append(ref)
    return out


def dependencies(codes: set[types.CodeType], follow: bool = True) -> dict[str, str]:
    """What an artifact's trace depended on: ``"module:qualname"`` -> :func:`function_digest` for
    each function of TRACED_MODULES among ``codes`` (the frames of the trace: :func:`trace_codes`,
    and with ``MJXDIFF_DEPENDENCIES=traced`` every function it called) and, with ``follow``, each
    function those can call by name (:func:`_closure`) and every function of
    :data:`ALWAYS_DEPENDED_ON`; ``*`` for a qualname: the whole module. Code from any other file
    is named ``"@file:qualname"`` with the digest of the live functions holding it (:func:`_account`).

    Fails closed: raises :class:`Unaccounted` for a frame it cannot name, and the artifact is
    then not saved."""
    found, foreign = _account(codes)
    if follow:
        found = _closure(found) | {(m, "*") for m in ALWAYS_DEPENDED_ON if m in sys.modules}
    deps = {f"{m}:{q}": function_digest(m, q) for m, q in sorted(found)}
    deps.update(foreign)
    return dict(sorted(deps.items()))


def uncovered(codes: set[types.CodeType], deps: dict[str, str]) -> list[str]:
    """The code objects among ``codes`` (frames a trace ran, e.g. seen by ``sys.settrace``) that are
    MJX's or mjxdiff's traced code (:data:`TRACED_MODULES`, and any file under MJX's package
    directory) but whose edit would leave ``deps`` (an artifact's key) unchanged, as sorted
    ``file:qualname`` lines; empty when the key is complete for that trace.

    Judged from the code objects alone, independently of how :func:`dependencies` named them: a
    code object is covered when a dependency's digest is taken over it, i.e. it is nested in the
    code of the function a ``module:qualname`` resolves to now (:func:`function_digest` hashes
    that code with every code object in its constants) or of a live function an ``@file:qualname``
    names, or when its module is a dependency as a whole (``module:*``). Functions marked
    :func:`untraced` (a JAX event listener that counts compiles) run during a trace but emit
    nothing into it: they are not asked for."""
    files = _module_files()
    whole = {name.rsplit(":", 1)[0] for name in deps if name.endswith(":*")}
    holders: list[types.FunctionType] = []
    for name in deps:
        if not name.startswith("@") and not name.endswith(":*"):
            fn = _resolve(*name.rsplit(":", 1))
            if isinstance(fn, types.FunctionType):
                holders.append(fn)
    foreign = _live_functions({name for name in deps if name.startswith("@")})
    holders += [fn for fns in foreign.values() for fn in fns]
    covered = {id(c) for fn in holders for c in _nested(fn.__code__)}
    covered |= {id(v.__code__) for v in list(_UNTRACED.values()) if isinstance(v, types.FunctionType)}
    return sorted({_where(code) for code in traced_code(codes)
                   if id(code) not in covered and files.get(code.co_filename) not in whole})


def _where(code: types.CodeType) -> str:
    return f"{code.co_filename}:{code.co_qualname}"


def traced_code(codes: set[types.CodeType]) -> list[types.CodeType]:
    """The code objects among ``codes`` that a key must cover: those of the files of
    :data:`TRACED_MODULES` and of any file under MJX's package directory."""
    import mujoco.mjx

    mjx_dir = os.path.dirname(mujoco.mjx.__file__ or "") + os.sep
    ours = set(_module_files())
    return [c for c in codes if c.co_filename in ours or c.co_filename.startswith(mjx_dir)]


def _holds(name: str, digest: str, live: dict[str, list[types.FunctionType]] | None = None) -> bool:
    if name.startswith("@"):
        return live is not None and _foreign_digest(live.get(name, [])) == digest
    module, qualname = name.split(":", 1)
    if module not in sys.modules:
        return False
    return function_digest(module, qualname) == digest


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


#: Values of ``$MJXDIFF_DEPENDENCIES``: what an artifact is recorded to depend on.
DEPENDENCY_MODES = ("functions", "traced", "code")


def dependency_mode() -> str:
    """What traces record as their artifact's dependencies, from ``$MJXDIFF_DEPENDENCIES``:

    - ``functions`` (the default): the functions whose lines emitted an operation (the
      StableHLO's locations, with the call stack of each) and every function of
      TRACED_MODULES those can call by name (:func:`_references`), found without slowing
      the trace;
    - ``traced``: the functions the trace ran (``sys.settrace``: ~1.8x slower traces, and
      Python holds the GIL for all of it) and those whose lines emitted an operation; what
      ``functions`` is tested against (it must include all of these);
    - ``code``: all of MJX's code (an edit retraces every rollout, though unchanged ones still
      hit XLA's persistent cache).
    """
    mode = os.environ.get("MJXDIFF_DEPENDENCIES", "functions")
    return mode if mode in DEPENDENCY_MODES else "functions"


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
