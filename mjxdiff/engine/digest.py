"""The code digest: the code loaded now as one hash, for the keys of compiled MJX rollouts.

:func:`code_digest` digests every module-level function, class and value of a set of modules,
functions followed into their closures, defaults and the globals they read: equal for the same
code whichever file it came from, different after any edit or monkeypatch that changes what
runs. :func:`rollout_digest` is that of :data:`TRACED_MODULES` (the modules whose code an MJX
rollout traces) with :func:`settings_digest` (versions, JAX and XLA settings). :func:`untraced`
marks a traced module's run-time state (counters, memos) as not code.

What one trace depended on is named with these digests in :mod:`mjxdiff.engine.trace_deps`;
:mod:`mjxdiff.engine.export_cache` keys its artifacts on both.
"""

from __future__ import annotations

import contextlib
import enum
import functools
import hashlib
import importlib
import importlib.metadata
import os
import sys
import threading
import types
from typing import Any, Iterator, Sequence

import jax
import jax.core
import numpy as np

__all__ = ["TRACED_MODULES", "code_digest", "code_read_once", "loaded_modules", "rollout_digest", "settings_digest",
           "untraced"]


#: Modules whose code a rollout traces: MJX's, and mjxdiff's own traced functions (the rollout's
#: compile counter, ``_traced``, is :mod:`mjxdiff.engine.xla`'s). Never this module, nor the
#: store's or the dependencies' (:data:`mjxdiff.engine.trace_deps.HARNESS`): their run-time state
#: is not code, and their files are part of every key.
TRACED_MODULES = ("mujoco.mjx", "mjxdiff.engine.engines", "mjxdiff.engine.trajectory", "mjxdiff.input.joints",
                  "mjxdiff.compat", "mjxdiff.engine.stages", "mjxdiff.engine.xla",
                  "mjxdiff.engine.pairs")
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
        elif isinstance(value, type):
            self._class(value, depth)
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

    def _class(self, cls: type, depth: int) -> None:
        h = self.h
        h.update(f"{cls.__module__}.{cls.__qualname__}".encode())
        if issubclass(cls, enum.Enum):  # members, not lazily filled lookup tables
            h.update(repr([(m.name, m.value) for m in cls]).encode())
            if self._ours(cls.__module__):  # and its code: MJX's JointType.qpos_width, dof_width
                for k in sorted(vars(cls)):
                    code = vars(cls)[k]
                    if isinstance(code, (types.FunctionType, staticmethod, classmethod, property)):
                        h.update(k.encode())
                        self.feed(code, depth + 1)
        elif self._ours(cls.__module__):  # a class MJX or mjxdiff defines: its methods and attributes
            for k in sorted(vars(cls)):
                if not k.startswith("__") or k in ("__init__", "__call__", "__post_init__"):
                    h.update(k.encode())
                    self.feed(vars(cls)[k], depth + 1)

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
