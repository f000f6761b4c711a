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
- ``closure``: ``smooth.py`` copied to the workspace with an edit inside a closure (``crb``'s
  nested ``crb_fn``: children's inertia 2% high), bound by hand.
- ``partial``: a ``functools.partial`` of a patch function (its gain a keyword) replaces
  ``forward.fwd_actuation``.

For contacts (:data:`CONTACT_VARIANTS`, on a scenario with primitives on a plane):

- ``sphere``: ``collision_primitive.py`` copied to the workspace, ``_plane_sphere``'s contact
  point moved by 1 mm along the normal, bound by hand (module attributes and the collision
  driver's dispatch table).
- ``decorated``: the same copy with an edit inside a ``@collider``-decorated function:
  ``plane_capsule`` takes the capsule's radius where its half-length belongs. The decorator's
  wrapper holds the edited function in its closure; no module attribute does.

:func:`apply` installs one variant in this process and returns what undoes it.
"""

from __future__ import annotations

import functools
import importlib.util
import sys
import types
from pathlib import Path
from typing import Callable

VARIANTS = ("clean", "copy", "copy2", "patch", "mismatch", "closure", "partial")
CONTACT_VARIANTS = ("sphere", "decorated")

_CRB_OLD = "crb_body += crb_child"
_CAPSULE_OLD = "segment = axis * cap.size[1]"
_SPHERE_OLD = "pos = sphere_pos - plane_normal * (sphere_radius + 0.5 * dist)"

_PASSIVE_OLD = "qfrc -= m.dof_damping * d.qvel"
_SMOOTH_OLD = "d = d.replace(qfrc_bias=qfrc_bias)"

PATCHES = '''
from mujoco.mjx._src import forward as _forward

_ORIGINAL = _forward.fwd_actuation
GAIN = 1.02


def fwd_actuation(m, d):
    return _ORIGINAL(m.replace(actuator_gainprm=m.actuator_gainprm * GAIN), d)


def scaled_actuation(m, d, gain):
    return _ORIGINAL(m.replace(actuator_gainprm=m.actuator_gainprm * gain), d)
'''


def _setattr(undo: list, owner, attr: str, value) -> None:
    undo.append((owner, attr, getattr(owner, attr)))
    setattr(owner, attr, value)


def _rebind(name: str, new: types.ModuleType, register: bool, undo: list) -> None:
    """Points every MJX module that imported module ``name`` (or its functions) at ``new``, by
    identity: module attributes and the values of module-level dicts (a dispatch table such as
    ``collision_driver._COLLISION_FUNC``); with ``register``, ``sys.modules`` too (else the
    installed module stays there, unused)."""
    old = sys.modules[name]
    replacement = {id(value): getattr(new, attr) for attr, value in vars(old).items()
                   if callable(value) and not isinstance(value, type) and hasattr(new, attr)
                   and getattr(value, "__module__", None) == name}
    replacement[id(old)] = new
    if register:
        undo.append((sys.modules, name, old))
        sys.modules[name] = new
        parent, _, leaf = name.rpartition(".")
        _setattr(undo, sys.modules[parent], leaf, new)
    for mod_name, module in list(sys.modules.items()):
        if module is None or not mod_name.startswith("mujoco.mjx") or module in (new, old):
            continue
        for attr, value in list(vars(module).items()):
            if id(value) in replacement:
                _setattr(undo, module, attr, replacement[id(value)])
            elif isinstance(value, dict) and not attr.startswith("__"):
                for key, item in list(value.items()):
                    if id(item) in replacement:
                        undo.append((value, key, item))
                        value[key] = replacement[id(item)]


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
    elif variant in ("patch", "partial"):
        path = workspace / "mjx_patches.py"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(PATCHES)
        spec = importlib.util.spec_from_file_location("mjx_patches", path)
        patches = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(patches)
        patched = (patches.fwd_actuation if variant == "patch"
                   else functools.partial(patches.scaled_actuation, gain=1.03))
        _setattr(undo, forward, "fwd_actuation", patched)
    elif variant == "closure":
        name = "mujoco.mjx._src.smooth"
        path = workspace / "smooth_closure.py"
        _rebind(name, _load_copy(name, _edited(name, _CRB_OLD, "crb_body += 1.02 * crb_child"), path, path),
                register=False, undo=undo)
    elif variant in CONTACT_VARIANTS:
        from mujoco.mjx._src import collision_driver  # noqa: F401 - its table is rebound

        name = "mujoco.mjx._src.collision_primitive"
        source = (_edited(name, _SPHERE_OLD, _SPHERE_OLD + " + 1e-3 * plane_normal") if variant == "sphere"
                  else _edited(name, _CAPSULE_OLD, "segment = axis * cap.size[0]"))
        path = workspace / f"collision_primitive_{variant}.py"
        _rebind(name, _load_copy(name, source, path, path), register=False, undo=undo)
    elif variant == "mismatch":
        name = "mujoco.mjx._src.smooth"
        source = _edited(name, _SMOOTH_OLD, "d = d.replace(qfrc_bias=1.02 * qfrc_bias)")
        installed = Path(sys.modules[name].__file__)
        _rebind(name, _load_copy(name, source, workspace / "elsewhere" / "smooth_edit.py", installed),
                register=True, undo=undo)
    elif variant != "clean":
        raise ValueError(f"unknown variant {variant!r}; one of {', '.join(VARIANTS + CONTACT_VARIANTS)}")

    def restore() -> None:
        for owner, attr, value in reversed(undo):
            if isinstance(owner, dict):  # sys.modules, or a dispatch table
                owner[attr] = value
            else:
                setattr(owner, attr, value)
    return restore
