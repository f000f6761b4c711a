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
(:func:`dependencies`): every function of ``mujoco.mjx`` and ``mjxdiff.engines`` on
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
import types
from pathlib import Path
from typing import Any, Callable, Iterator

import jax
import numpy as np
from jax import export
from jax._src import config as _config

__all__ = ["bind", "call", "clear", "code_digest", "count", "evict", "export_dir", "fresh_digest", "loaded_count",
           "rollout_digest", "settings_digest", "tally", "untraced"]

# (arguments' key, whole-code digest, options key) -> (output tree structure, compiled call of an
# Exported, what the options chose)
_FUNCTIONS: dict[tuple[str, str, str], tuple[Any, Callable, Any]] = {}
_LOADED = {"count": 0}
_KEY_LOCKS: dict[tuple[str, str, str], threading.Lock] = {}  # one per key: threads binding the same function compile it once
_KEY_LOCKS_GUARD = threading.Lock()
_LOCAL = threading.local()


def count(kind: str, amount: float = 1) -> None:
    """Adds ``amount`` to this thread's open :func:`tally` (if any) under ``kind``."""
    ledger = getattr(_LOCAL, "tally", None)
    if ledger is not None:
        ledger[kind] = ledger.get(kind, 0) + amount


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
TRACED_MODULES = ("mujoco.mjx", "mjxdiff.engines")
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


def code_digest(modules: tuple[str, ...] = ("mujoco.mjx",)) -> str:
    """Hex SHA-256 of the code now loaded in ``modules`` (names, with their submodules):
    every module-level function, class and value, functions followed into their closures,
    defaults and the globals they read. Equal for the same code, whichever file it came from;
    different after any edit or monkeypatch that changes what runs.

    ``report.json`` names the MJX that was tested by ``code_digest()``.
    """
    d = _Digest(modules)
    for name, module in _modules(modules):
        d.h.update(b"module " + name.encode())
        for attr in sorted(vars(module)):
            if not attr.startswith(("__", "@")):  # "@py_builtins": pytest's assertion rewriting
                d.h.update(attr.encode())
                d.feed(vars(module)[attr])
    return d.h.hexdigest()


def settings_digest() -> str:
    """Hex SHA-256 of what else decides a compiled rollout: versions, JAX settings, XLA flags."""
    config = [(k, str(getattr(jax.config, k, None))) for k in _JAX_SETTINGS]
    return hashlib.sha256(repr((_versions(), config, os.environ.get("XLA_FLAGS", ""))).encode()).hexdigest()


def rollout_digest() -> str:
    """The code and settings a rollout traced now would depend on (:func:`code_digest` of
    :data:`TRACED_MODULES` and :func:`settings_digest`); part of every artifact's key."""
    return hashlib.sha256((code_digest(TRACED_MODULES) + settings_digest()).encode()).hexdigest()


def export_dir() -> Path | None:
    """Where artifacts live: ``mjxdiff-exports`` in JAX's compilation cache dir; None when that is off."""
    cache = jax.config.jax_compilation_cache_dir
    if not cache or "://" in str(cache):
        return None
    return Path(cache) / "mjxdiff-exports"


def loaded_count() -> int:
    """Compiled functions this process loaded from an artifact instead of tracing."""
    return _LOADED["count"]


def clear() -> None:
    """Forgets the functions loaded or exported in this process (the files stay)."""
    _FUNCTIONS.clear()
    _KEYS.clear()
    with _KEY_LOCKS_GUARD:
        _KEY_LOCKS.clear()


@functools.cache
def _versions() -> tuple[str, ...]:
    return tuple(importlib.metadata.version(p) for p in ("jax", "jaxlib", "mujoco", "mujoco-mjx"))


def _structure(treedef, h) -> None:
    # node by node: pickle.dumps of the whole treedef depends on which equal aux objects
    # happen to be shared (pickle's memo), so equal structures could hash differently
    h.update(pickle.dumps((treedef.node_data(), len(treedef.children()))))
    for child in treedef.children():
        _structure(child, h)


def _key(fn: Callable, treedef, leaves: list, static: dict[str, Any], code: str) -> str:
    h = hashlib.sha256()
    _structure(treedef, h)
    for part in (code, fn.__module__, fn.__qualname__, sorted((k, repr(v)) for k, v in static.items()),
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


_SEEN = {"digest": None}


def fresh_digest() -> str:
    """:func:`rollout_digest` now; when it differs from the last one this process saw, JAX's
    in-memory caches are cleared first (``jax.clear_caches``), so that no function compiled
    or traced from the old code (a jitted function, a cached scan body) runs again."""
    digest = rollout_digest()
    if _SEEN["digest"] not in (None, digest):
        jax.clear_caches()
        for memo in (_FUNCTION_DIGESTS, _MODULE_FUNCTIONS, _LINE_INDEX, _REFERENCES, _METHODS):
            memo.clear()
    _SEEN["digest"] = digest
    return digest


# --- what one trace depended on -------------------------------------------------------------
#
# An artifact is valid for the code its trace ran. Its dependencies are the functions of
# TRACED_MODULES on the call stack of every operation it emitted (the StableHLO's locations,
# which a sub-trace JAX took from its caches keeps) and those they can call by name
# (dependency_mode() "functions"), or those sys.settrace saw run ("traced"). Each is digested
# "shallowly": its code (nested functions included), defaults, closure and the globals it reads,
# where a function of TRACED_MODULES stands for itself by name (its own code counts only where
# it is a dependency). An edit of one collision function therefore retraces only the rollouts
# that can reach it.

_FUNCTION_DIGESTS: dict[tuple[str, str], str] = {}  # (module, qualname) -> shallow digest; cleared on a code change
_LOCATION = __import__("re").compile(r'loc\("([^"]+)":(\d+):')


class _Shallow(_Digest):
    """A :class:`_Digest` in which functions of the traced modules met below the top stand for
    themselves by name."""

    def feed(self, value: Any, depth: int = 0) -> None:
        if depth > 0:
            fn = _unwrap(value)
            if isinstance(fn, types.FunctionType) and self._ours(getattr(fn, "__module__", None)):
                self.h.update(f"fn {fn.__module__}.{fn.__qualname__}".encode())
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

        def visit(value: Any, depth: int) -> None:
            fn = _unwrap(value.__func__ if isinstance(value, (staticmethod, classmethod)) else value)
            if isinstance(value, property):
                for part in (value.fget, value.fset, value.fdel):
                    visit(part, depth)
                return
            if not isinstance(fn, types.FunctionType) or fn.__module__ != module:
                return
            if found.setdefault(fn.__code__.co_qualname, fn) is not fn or depth > 3:
                return
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
    ("missing" if there is none)."""
    key = (module, qualname)
    if key not in _FUNCTION_DIGESTS:
        obj = _resolve(module, qualname)
        if obj is None:
            _FUNCTION_DIGESTS[key] = "missing"
        else:
            d = _Shallow(TRACED_MODULES)
            d.feed(obj)
            _FUNCTION_DIGESTS[key] = d.h.hexdigest()
    return _FUNCTION_DIGESTS[key]


def _traced_files() -> dict[str, str]:
    """Source file -> module name, for the modules of TRACED_MODULES."""
    return {os.path.realpath(m.__file__): name for name, m in _modules(TRACED_MODULES) if getattr(m, "__file__", None)}


_LINE_INDEX: dict[str, list[tuple[int, int, str]]] = {}  # cleared on a code change, with the digests


def _line_index(module: str) -> list[tuple[int, int, str]]:
    """(first line, last line, qualname) of every function :func:`_functions` finds in ``module``."""
    if module in _LINE_INDEX:
        return _LINE_INDEX[module]
    out = []

    def lines(code: types.CodeType) -> list[int]:
        found = [line for _, _, line in code.co_lines() if line is not None]
        for const in code.co_consts:
            if isinstance(const, types.CodeType):
                found += lines(const)
        return found

    for qualname, fn in _functions(module).items():
        found = lines(fn.__code__)
        if found:
            out.append((min(found), max(found), qualname))
    _LINE_INDEX[module] = out  # whole: another compile worker may read it at once
    return out


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
        if _ours(value) and not value.__code__.co_filename.startswith("<"):  # not generated (dataclass __init__)
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
#: (flatten, hash, equality) rather than MJX code by name.
ALWAYS_DEPENDED_ON = ("mujoco.mjx._src.dataclasses",)


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


def dependencies(called: set[types.CodeType], mlir_text: str, follow: bool = True) -> dict[str, str]:
    """``"module:qualname"`` -> :func:`function_digest` for each module-level function or method
    of TRACED_MODULES a trace ran (``called``: code objects of its frames) or whose lines
    emitted an operation (locations in ``mlir_text``, each with its call stack) and, with
    ``follow``, each function those can call by name (:func:`_closure`) and every function of
    :data:`ALWAYS_DEPENDED_ON`. ``*`` for a qualname: the whole module."""
    files = _traced_files()
    found: set[tuple[str, str]] = set()
    for code in called:
        module = files.get(os.path.realpath(code.co_filename))
        if module is not None:
            found.add(_as_dependency(module, code.co_qualname))
    by_file: dict[str, set[int]] = {}
    for file, line in _LOCATION.findall(mlir_text):
        by_file.setdefault(file, set()).add(int(line))
    for file, lines in by_file.items():
        module = files.get(os.path.realpath(file))
        if module is None:
            continue
        index = _line_index(module)
        for line in lines:
            spans = [(last - first, q) for first, last, q in index if first <= line <= last]
            if spans:  # a function _line_index found by name: resolvable again
                found.add((module, min(spans)[1]))
            else:  # a line of no function (module level): depend on the whole module
                found.add((module, "*"))
    if follow:
        found = _closure(found) | {(m, "*") for m in ALWAYS_DEPENDED_ON if m in sys.modules}
    return {f"{m}:{q}": (code_digest((m,)) if q == "*" else function_digest(m, q)) for m, q in sorted(found)}


def _deps_hold(deps: dict[str, str]) -> bool:
    for name, digest in deps.items():
        module, qualname = name.split(":", 1)
        if module not in sys.modules:
            return False
        if (code_digest((module,)) if qualname == "*" else function_digest(module, qualname)) != digest:
            return False
    return True


#: Most bytes of artifacts kept (~2,500 of 130-230 KB); beyond it the least recently used go.
MAX_BYTES = 512 * 2**20


def _load(path: Path):
    try:
        out_tree, blob = pickle.loads(path.read_bytes())
        found = out_tree, export.deserialize(bytearray(blob))
    except Exception:  # noqa: BLE001 - unreadable or from another format: trace again and overwrite
        return None
    with contextlib.suppress(OSError):
        os.utime(path)  # recently used: evicted last
    return found


def _write(path: Path, data: bytes) -> None:
    tmp = path.with_suffix(f".{os.getpid()}.{threading.get_ident()}.tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)  # atomic: a concurrent reader sees the old file or the whole new one


def _save(directory: Path, out_tree, exported, deps: dict[str, str]) -> Path:
    """Writes the artifact and, last, its dependencies (``<digest of deps>.jaxexport`` and
    ``.deps`` in ``directory``, the arguments' key): a reader only trusts complete pairs."""
    directory.mkdir(parents=True, exist_ok=True)
    stem = hashlib.sha256(json.dumps(deps, sort_keys=True).encode()).hexdigest()[:32]
    path = directory / f"{stem}.jaxexport"
    _write(path, pickle.dumps((out_tree, bytes(exported.serialize()))))
    _write(path.with_suffix(".deps"), json.dumps(deps, sort_keys=True).encode())
    evict(directory.parent, keep=path)
    return path


def matching(directory: Path) -> list[Path]:
    """The artifacts in ``directory`` (one arguments' key) whose recorded dependencies all still
    have the digests they had when they were traced: those the code loaded now may run."""
    try:
        candidates = sorted(directory.glob("*.deps"))
    except OSError:
        return []
    out = []
    for deps_path in candidates:
        try:
            deps = json.loads(deps_path.read_text())
        except (OSError, ValueError):
            continue
        if isinstance(deps, dict) and _deps_hold(deps):
            out.append(deps_path.with_suffix(".jaxexport"))
    return out


def _load_matching(directory: Path):
    """(out_tree, Exported, path) of the first artifact in ``directory`` the code loaded now may run."""
    for path in matching(directory):
        found = _load(path) if path.exists() else None
        if found is not None:
            return (*found, path)
        for part in (path.with_suffix(".deps"), path, path.with_suffix(".cost")):  # unreadable: never tried again
            with contextlib.suppress(OSError):
                part.unlink()
    return None


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
         options_key: Any = None) -> Callable:
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
    (:func:`fresh_digest`).
    """
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
            found = _load_matching(directory / key) if directory is not None else None
            if found is None:
                traced = _export(fn, treedef, leaves, static)
                if traced is None:
                    return direct
                (out_tree, exported, deps), artifact = traced, None
                if directory is not None:
                    with contextlib.suppress(Exception):  # unwritable cache dir, no flatbuffers: use it unsaved
                        artifact = _save(directory / key, out_tree, exported, deps)
            else:
                _LOADED["count"] += 1
                count("loaded")
                out_tree, exported, artifact = found
            lowered = jax.jit(exported.call).lower(*leaves)
            chosen, choice = options(_Lowered(lowered, artifact)) if options is not None else ({}, None)
            try:
                compiled = lowered.compile(compiler_options=chosen or None)
            except Exception as e:  # noqa: BLE001 - e.g. an option this XLA does not know: its defaults
                if not chosen:
                    raise
                compiled = lowered.compile()
                if isinstance(choice, dict):
                    choice = dict(choice, level="optimized", options_refused=" ".join(str(e).split())[:200])
            _FUNCTIONS[memo] = out_tree, compiled, choice
    return Bound(*_FUNCTIONS[memo])


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


def _export(fn: Callable, treedef, leaves: list, static: dict[str, Any]):
    """(output tree structure, Exported, dependencies) of ``fn`` over flat leaves (:func:`dependencies`
    of the trace), or None if it cannot be exported."""
    out_tree = []
    python = getattr(fn, "__wrapped__", fn)  # traced afresh, never a jitted function's cached trace

    def flat(*leaves):
        out, tree = jax.tree.flatten(python(*jax.tree.unflatten(treedef, leaves), **static))
        out_tree.append(tree)
        return out

    shapes = [jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=getattr(x, "sharding", None)) for x in leaves]
    mode = dependency_mode()
    record = mode == "traced"
    called: set[types.CodeType] = set()
    before = sys.gettrace()

    def tracer(frame, event, arg):  # frames the trace runs: a 'call' event each, no line events
        called.add(frame.f_code)
        return before(frame, event, arg) if before is not None else None

    if record:
        sys.settrace(tracer)
    try:
        # every operation's whole call stack in its location: the roots of the dependencies
        with _config.include_full_tracebacks_in_locations(True), _config.traceback_in_locations_limit(-1):
            exported = export.export(jax.jit(flat), platforms=["cpu"])(*shapes)
    except Exception:  # noqa: BLE001 - the direct call that follows raises MJX's own error, if any
        return None
    finally:
        if record:
            sys.settrace(before)
    deps = ({f"{m}:*": code_digest((m,)) for m in TRACED_MODULES} if mode == "code"
            else dependencies(called, exported.mlir_module(), follow=mode == "functions"))
    return out_tree[0], exported, deps
