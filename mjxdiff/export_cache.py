"""Compiled MJX rollouts kept across processes: ``jax.export`` artifacts beside JAX's cache.

JAX's persistent compilation cache keeps XLA's output, but every new process
still traces ``mjx.step`` in Python to find the cache key (2.5-3 s for an ant
rollout, most of a warm sweep's compile time). :func:`call` traces a jitted
function once, saves it as a serialized :mod:`jax.export` artifact (StableHLO
plus its input and output structure), and in later processes loads that
instead of tracing; XLA's compile of the loaded module is a persistent-cache
hit. Numbers are unchanged: the cold run already executes the exported module.

An artifact is keyed on everything the trace depended on: the tree structure
of the arguments (which holds an ``mjx.Model``'s static fields), each leaf's
shape, dtype and sharding, the static arguments, x64, and the versions of
jax, jaxlib, mujoco, mujoco-mjx and the source of the module that defines the
function. Code is not in the key, so artifacts are used only while MJX's
modules (and mjxdiff.engines) hold the functions they were imported with, all
written in installed packages (:func:`mjx_pristine`): a test that
monkeypatches MJX to inject a bug, before or after importing mjxdiff, always
traces its patched code.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import importlib.metadata
import inspect
import os
import pickle
import sys
import sysconfig
import types
from pathlib import Path
from typing import Any, Callable

import jax
from jax import export

__all__ = ["bind", "call", "clear", "evict", "export_dir", "loaded_count", "mjx_pristine"]

_FUNCTIONS: dict[str, tuple[Any, Callable]] = {}  # key -> (output tree structure, jitted call of an Exported)
_LOADED = {"count": 0}


def _traced_functions() -> dict[tuple[str, str], Any]:
    """Module-level callables of MJX and of mjxdiff.engines (the code a rollout traces), classes
    and modules aside: functions, and what may stand in for one (a partial, a jitted function)."""
    return {(name, attr): value for name, module in list(sys.modules.items())
            if module is not None and (name in ("mujoco.mjx", "mjxdiff.engines") or name.startswith("mujoco.mjx."))
            for attr, value in list(vars(module).items())
            if callable(value) and not isinstance(value, (type, types.ModuleType))}


#: Where genuine MJX code lives: installed packages, the standard library and mjxdiff itself.
_GENUINE_ROOTS = tuple(sorted({os.path.join(Path(sysconfig.get_paths()[k]).resolve(), "")  # trailing separator:
                               for k in ("purelib", "platlib", "stdlib")}  # .../mjxdiff is not .../mjxdiff_x
                              | {os.path.join(Path(__file__).resolve().parent, "")}))


@functools.cache
def _installed(filename: str) -> bool:
    return str(Path(filename).resolve()).startswith(_GENUINE_ROOTS)


def _genuine(value: Any) -> bool:
    """False for a callable whose code was written outside the installed packages (a test's or
    a user's patch), seen through partials and ``functools.wraps``/``jax.jit`` wrappers."""
    while isinstance(value, functools.partial):
        value = value.func
    try:
        value = inspect.unwrap(value)
    except ValueError:  # a cycle of __wrapped__
        return False
    code = getattr(value, "__code__", None)
    return code is None or _installed(code.co_filename)


_PRISTINE = _traced_functions()  # mjxdiff.engines imports mujoco.mjx (all of _src) before this module


def mjx_pristine() -> bool:
    """True while every callable of MJX's modules and of mjxdiff.engines is the one first seen
    (imported at start-up, or at the first check for ones defined later) and was written in an
    installed package: nothing patched, before or after mjxdiff was imported. (A pre-import
    patch by a partial of MJX's own function with other arguments is not seen.)"""
    current = _traced_functions()
    for k, v in current.items():
        _PRISTINE.setdefault(k, v)
    return all(_PRISTINE[k] is v for k, v in current.items()) and all(_genuine(v) for v in current.values())


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


@functools.cache
def _versions() -> tuple[str, ...]:
    return tuple(importlib.metadata.version(p) for p in ("jax", "jaxlib", "mujoco", "mujoco-mjx"))


@functools.cache
def _source_digest(fn: Callable) -> bytes:
    return hashlib.sha256(Path(inspect.getsourcefile(inspect.unwrap(fn)) or "").read_bytes()).digest()


def _structure(treedef, h) -> None:
    # node by node: pickle.dumps of the whole treedef depends on which equal aux objects
    # happen to be shared (pickle's memo), so equal structures could hash differently
    h.update(pickle.dumps((treedef.node_data(), len(treedef.children()))))
    for child in treedef.children():
        _structure(child, h)


def _key(fn: Callable, treedef, leaves: list, static: dict[str, Any]) -> str:
    h = hashlib.sha256()
    _structure(treedef, h)
    for part in (_versions(), jax.config.jax_enable_x64, _source_digest(fn), fn.__qualname__,
                 sorted((k, repr(v)) for k, v in static.items()),
                 [(x.shape, str(x.dtype), str(getattr(x, "sharding", None))) for x in leaves]):
        h.update(repr(part).encode() if not isinstance(part, bytes) else part)
    return h.hexdigest()


_KEYS: dict[tuple, str] = {}  # (fn, treedef, leaf types, static) -> key: hashing a model's structure takes ~30 ms


def _key_of(fn: Callable, treedef, leaves: list, static: dict[str, Any]) -> str:
    memo = (fn, treedef, tuple((x.shape, x.dtype, getattr(x, "sharding", None)) for x in leaves),
            tuple(sorted(static.items())), jax.config.jax_enable_x64)
    if memo not in _KEYS:
        _KEYS[memo] = _key(fn, treedef, leaves, static)
    return _KEYS[memo]


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


def _save(path: Path, out_tree, exported) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(f".{os.getpid()}.tmp")
    tmp.write_bytes(pickle.dumps((out_tree, bytes(exported.serialize()))))
    os.replace(tmp, path)  # atomic: a concurrent reader sees the old file or the whole new one
    evict(path.parent, keep=path)


def evict(directory: Path, keep: Path | None = None, budget: int = MAX_BYTES) -> int:
    """Deletes the least recently used artifacts in ``directory`` (oldest modification time
    first; loading one touches it) until the rest fit in ``budget`` bytes, never ``keep``.
    Returns how many it deleted. JAX's own cache eviction does not see these files, and every
    new model structure (a fuzz run makes hundreds) adds one."""
    files = []
    for path in directory.glob("*.jaxexport"):
        with contextlib.suppress(OSError):
            st = path.stat()
            files.append((st.st_mtime, st.st_size, path))
    total, deleted = sum(size for _, size, _ in files), 0
    for _, size, path in sorted(files):
        if total <= budget:
            break
        if path != keep:
            with contextlib.suppress(OSError):  # another process got there first
                path.unlink()
                deleted += 1
            total -= size
    return deleted


def call(fn: Callable, args: tuple, static: dict[str, Any]):
    """``fn(*args, **static)`` for a ``jax.jit`` function ``fn``, through a saved artifact when possible."""
    return bind(fn, args, static)(*args)


def bind(fn: Callable, args: tuple, static: dict[str, Any]) -> Callable:
    """``fn`` with ``static`` bound, for calls whose arguments are shaped, typed and sharded like ``args``:
    a loaded or freshly exported artifact when possible (exported on first use, from ``args``' shapes).

    Binding once and calling many times (the pieces of a stream) spares each call the
    structure's key. Falls back to ``fn`` itself when caching is off, MJX is patched,
    or the function cannot be exported (calling it then raises MJX's own error, e.g.
    ``NotImplementedError`` for an unsupported feature).
    """
    direct = functools.partial(fn, **static)
    directory = export_dir()
    if directory is None or not mjx_pristine():
        return direct
    leaves, treedef = jax.tree.flatten(args)
    try:
        key = _key_of(fn, treedef, leaves, static)
    except (pickle.PicklingError, TypeError, AttributeError):  # static data that cannot be pickled
        return direct
    if key not in _FUNCTIONS:
        path = directory / f"{key}.jaxexport"
        found = _load(path) if path.exists() else None
        if found is None:
            found = _export(fn, treedef, leaves, static)
            if found is None:
                return direct
            with contextlib.suppress(Exception):  # unwritable cache dir, no flatbuffers: use it unsaved
                _save(path, *found)
        else:
            _LOADED["count"] += 1
        out_tree, exported = found
        _FUNCTIONS[key] = out_tree, jax.jit(exported.call)
    out_tree, run = _FUNCTIONS[key]
    return lambda *args: jax.tree.unflatten(out_tree, run(*jax.tree.leaves(args)))


def _export(fn: Callable, treedef, leaves: list, static: dict[str, Any]):
    """(output tree structure, Exported) of ``fn`` over flat leaves, or None if it cannot be exported."""
    out_tree = []

    def flat(*leaves):
        out, tree = jax.tree.flatten(fn(*jax.tree.unflatten(treedef, leaves), **static))
        out_tree.append(tree)
        return out

    shapes = [jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=getattr(x, "sharding", None)) for x in leaves]
    try:
        exported = export.export(jax.jit(flat), platforms=["cpu"])(*shapes)
    except Exception:  # noqa: BLE001 - the direct call that follows raises MJX's own error, if any
        return None
    return out_tree[0], exported
