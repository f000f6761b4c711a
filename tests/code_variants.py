"""Code variants of MJX for the artifact-cache tests: each changes what a rollout computes
without touching the installed files, the way users and developers do.

- ``clean``: MJX as installed.
- ``copy``: ``passive.py`` replaced by an edited copy compiled from a file outside the package
  (a workspace), under the module's own name, and bound where MJX imported it (``sys.modules``
  keeps the installed module, as a vendored or hand-loaded copy leaves it).
- ``copy2``: the same workspace file edited again (another damping factor): an artifact of
  ``copy`` must never serve it.
- ``patch``: a function of ``mjx_patches.py`` (another module, written beside the workspace)
  replaces ``forward.fwd_actuation``: actuator gains 2% high.
- ``mismatch``: ``smooth.py`` edited and compiled under a file name that is not its module's
  ``__file__`` (``co_filename`` points into the workspace, ``__file__`` at the installed file).

:func:`apply` installs one variant in this process and returns what undoes it.
"""

from __future__ import annotations

import importlib.util
import sys
import types
from pathlib import Path
from typing import Callable

VARIANTS = ("clean", "copy", "copy2", "patch", "mismatch")

_PASSIVE_OLD = "qfrc -= m.dof_damping * d.qvel"
_SMOOTH_OLD = "d = d.replace(qfrc_bias=qfrc_bias)"

PATCHES = '''
from mujoco.mjx._src import forward as _forward

_ORIGINAL = _forward.fwd_actuation
GAIN = 1.02


def fwd_actuation(m, d):
    return _ORIGINAL(m.replace(actuator_gainprm=m.actuator_gainprm * GAIN), d)
'''


def _setattr(undo: list, owner, attr: str, value) -> None:
    undo.append((owner, attr, getattr(owner, attr)))
    setattr(owner, attr, value)


def _rebind(name: str, new: types.ModuleType, register: bool, undo: list) -> None:
    """Points every MJX module that imported module ``name`` (or its functions) at ``new``; with
    ``register``, ``sys.modules`` too (else the installed module stays there, unused)."""
    old = sys.modules[name]
    if register:
        undo.append((sys.modules, name, old))
        sys.modules[name] = new
        parent, _, leaf = name.rpartition(".")
        _setattr(undo, sys.modules[parent], leaf, new)
    for mod_name, module in list(sys.modules.items()):
        if module is None or not mod_name.startswith("mujoco.mjx") or module in (new, old):
            continue
        for attr, value in list(vars(module).items()):
            if value is old:
                _setattr(undo, module, attr, new)
            elif getattr(value, "__module__", None) == name and hasattr(new, getattr(value, "__name__", "")):
                if callable(value) and not isinstance(value, type):
                    _setattr(undo, module, attr, getattr(new, value.__name__))


def _load_copy(name: str, source: str, code_file: Path, module_file: Path) -> types.ModuleType:
    """Module ``name`` from ``source`` compiled as ``code_file``, with ``__file__ = module_file``."""
    code_file.parent.mkdir(parents=True, exist_ok=True)
    code_file.write_text(source)
    spec = importlib.util.spec_from_file_location(name, module_file)
    module = importlib.util.module_from_spec(spec)
    exec(compile(source, str(code_file), "exec", dont_inherit=True), vars(module))
    return module


def _edited(module_name: str, old: str, new: str) -> str:
    source = Path(sys.modules[module_name].__file__).read_text()
    assert source.count(old) >= 1, f"the line to edit is not in this MJX: {old}"
    return source.replace(old, new)


def apply(variant: str, workspace: Path) -> Callable[[], None]:
    """Installs ``variant`` (one of :data:`VARIANTS`) in this process, its files under
    ``workspace``; returns a function that undoes it."""
    from mujoco.mjx._src import forward, passive, smooth  # noqa: F401 - imported so they can be replaced

    workspace, undo = Path(workspace), []
    if variant in ("copy", "copy2"):
        factor = "1.05" if variant == "copy" else "1.10"
        name = "mujoco.mjx._src.passive"
        source = _edited(name, _PASSIVE_OLD, f"qfrc -= m.dof_damping * d.qvel * {factor}")
        path = workspace / "passive.py"  # the same workspace file for both edits
        _rebind(name, _load_copy(name, source, path, path), register=False, undo=undo)
    elif variant == "patch":
        path = workspace / "mjx_patches.py"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(PATCHES)
        spec = importlib.util.spec_from_file_location("mjx_patches", path)
        patches = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(patches)
        _setattr(undo, forward, "fwd_actuation", patches.fwd_actuation)
    elif variant == "mismatch":
        name = "mujoco.mjx._src.smooth"
        source = _edited(name, _SMOOTH_OLD, "d = d.replace(qfrc_bias=1.02 * qfrc_bias)")
        installed = Path(sys.modules[name].__file__)
        _rebind(name, _load_copy(name, source, workspace / "elsewhere" / "smooth_edit.py", installed),
                register=True, undo=undo)
    elif variant != "clean":
        raise ValueError(f"unknown variant {variant!r}; one of {', '.join(VARIANTS)}")

    def restore() -> None:
        for owner, attr, value in reversed(undo):
            if owner is sys.modules:
                sys.modules[attr] = value
            else:
                setattr(owner, attr, value)
    return restore
