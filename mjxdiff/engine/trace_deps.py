"""What one trace depended on: the functions and code a saved MJX rollout is valid for.

An artifact of :mod:`mjxdiff.engine.export_cache` is loaded only while every function its trace
could have run has the digest it had then. :func:`trace_codes` reads the code objects on the
call stack of every operation a trace emitted, :func:`dependencies` names them (``module:qualname``
for code of :data:`~mjxdiff.engine.digest.TRACED_MODULES`, ``@file:qualname`` for any other) with
the functions they can call by name, each with its digest, failing closed (:class:`Unaccounted`)
for code it cannot name; :func:`uncovered` checks a key against the code a trace really ran.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import os
import sys
import types
from typing import Any, Iterator

import jax
import numpy as np

from mjxdiff.engine import digest as _digest_module
from mjxdiff.engine.digest import (_UNTRACED, TRACED_MODULES, _code, _Digest, _modules, _under, code_digest,
                                   rollout_digest)

__all__ = ["DEPENDENCY_MODES", "HARNESS", "Unaccounted", "dependencies", "dependency_mode", "fresh_digest",
           "function_digest", "trace_codes", "traced_code", "uncovered"]

#: The harness: the files of the code that wraps every trace (``flat``, in
#: :mod:`~mjxdiff.engine.export_cache`) and decides what a key holds (the store, the code digest,
#: this module). Their code is never a dependency (:func:`_ignored`): the store digests the files
#: into every key instead.
HARNESS = (os.path.join(os.path.dirname(__file__), "export_cache.py"), str(_digest_module.__file__), __file__)


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
    in the key (:func:`~mjxdiff.engine.digest.settings_digest`): jax, jaxlib and numpy."""
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
    standard library's and the harness's (:data:`HARNESS`). An installed package other than those
    three (MJX in a venv's ``lib/python3.X/site-packages``, under the standard library's directory
    in a plain install) never is, so MJX edited where it is installed changes the key."""
    if file.startswith("<frozen ") or file in HARNESS or file.startswith(_ignored_packages()):
        return True
    return file.startswith(_stdlib_roots()) and not any(part in file for part in _INSTALLED)


def _is_flat(code: types.CodeType) -> bool:
    """Whether ``code`` is the wrapper the store's ``_export`` traces (``flat``, in
    :mod:`mjxdiff.engine.export_cache`): frames above it are outside the trace."""
    return code.co_filename == HARNESS[0] and code.co_name == "flat"


def trace_codes(closed_jaxpr) -> set[types.CodeType]:
    """The code objects on the call stack of every operation of ``closed_jaxpr`` and of the
    jaxprs inside it (scan, while, cond, pjit bodies), from JAX's tracebacks, inside the trace:
    frames below the store's wrapper (:func:`_is_flat`). A stack that does not reach the wrapper (a body
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
    - code of jax, jaxlib, numpy, the standard library and the harness: left out (:func:`_ignored`);
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
    :func:`~mjxdiff.engine.digest.untraced` (a JAX event listener that counts compiles) run during
    a trace but emit nothing into it: they are not asked for."""
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
