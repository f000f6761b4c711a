"""Shrinking a model that diverges to a minimal MJCF that still shows the same divergence.

Delta debugging (Zeller and Hildebrandt's ddmin) over :class:`mujoco.MjSpec` edits, coarse to
fine: drop bodies (with their subtrees), then joints (a body without its joint is welded to its
parent), geoms, sites, actuators, sensors, tendons, equality constraints, explicit pairs and
excludes, keyframes, cameras, lights, custom data, materials and textures (another pass while
one drops something: what named an element may be gone); then fuse bodies without joints into
their parents (MuJoCo's ``fusestatic``) and replace meshes with boxes; then options and flags
back to MuJoCo's defaults; then round the model's numbers and the state. A candidate is kept
when it compiles in C and shows the same :class:`Signature`, checked from one state
(:class:`State`, the one-step check's end point: one C state, one step):

- ``forward``: the first stage of ``mj_forward`` whose fields differ
  (:func:`mjxdiff.compare.diagnose.drill_down`), its first field, and for contacts the geom-type pair;
- ``step``: every forward stage agrees and one step does not (``mj_step`` against
  ``mjx.step`` from the state, both solvers converged): the first field beyond
  :data:`STEP_RTOL`.

The state is kept by name (each joint's ``qpos``/``qvel``, each actuator's ``ctrl``/``act``),
so it follows the model as parts are dropped; a joint dropped takes its coordinates with it.
Candidates of one structure share one compile: MJX's forward and step are jitted with the
model as an argument, and only a new structure traces again (:attr:`Shrunk.compiles`).
Deterministic: the edits are tried in a fixed order, and nothing is random.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import time
from typing import Callable, Iterable, Sequence

import jax
import mujoco
import numpy as np

from mjxdiff.tools.shrink_probe import (KEEP_COMPILED, KINDS, OPTIONS, STEP_RTOL, Signature,  # noqa: F401
                                        State, drill, find_state, focus_bodies, probe, scaled_error, significant,
                                        step_errors, transfer_contacts)

__all__ = ["KINDS", "OPTIONS", "ROUNDED", "STEP_RTOL", "Counts", "Shrunk", "Signature", "State", "boxed",
           "changed_options", "counts", "ddmin", "drop", "element_names", "find_state", "focus_bodies", "fused",
           "mesh_geoms", "named", "probe", "rounded", "scaled_error", "shrink", "significant", "step_errors",
           "transfer_contacts"]

@dataclasses.dataclass(frozen=True)
class Counts:
    """A model's size: bodies (the world excluded), geoms, joints, actuators, sensors, tendons,
    equalities, options (differing from MuJoCo's defaults) and steps."""

    bodies: int
    geoms: int
    joints: int
    actuators: int
    sensors: int
    tendons: int
    equalities: int
    options: int
    steps: int = 1

    def __str__(self) -> str:
        return ", ".join(f"{v} {k}" for k, v in dataclasses.asdict(self).items())


def changed_options(spec: mujoco.MjSpec) -> list[str]:
    """The :data:`OPTIONS` of ``spec`` that differ from MuJoCo's defaults (``mjOption``)."""
    default = mujoco.MjSpec().option
    return [o for o in OPTIONS
            if not np.array_equal(np.asarray(getattr(spec.option, o)), np.asarray(getattr(default, o)))]


def _option_changes(spec: mujoco.MjSpec) -> int:
    n = len(changed_options(spec))
    return n + bin(spec.option.disableflags).count("1") + bin(spec.option.enableflags).count("1")


def counts(spec: mujoco.MjSpec, steps: int = 1) -> Counts:
    m = spec.compile()
    return Counts(m.nbody - 1, m.ngeom, m.njnt, m.nu, m.nsensor, m.ntendon, m.neq, _option_changes(spec), steps)


def named(spec: mujoco.MjSpec) -> mujoco.MjSpec:
    """``spec`` with every element of :data:`KINDS` named (``mjxdiff_<kind><i>`` where it had
    none), so that edits and the state can refer to it. Name a spec before taking a
    :class:`State` of its model: a state names each joint as the compiled model does."""
    for kind in KINDS:
        for i, e in enumerate(getattr(spec, kind)):
            if not e.name:
                e.name = f"mjxdiff_{kind}{i}"
    return spec


def element_names(spec: mujoco.MjSpec, kind: str) -> list[str]:
    """The names of ``spec``'s elements of ``kind`` (:data:`KINDS`), the world body left out."""
    return [e.name for e in getattr(spec, kind) if kind != "bodies" or e.name != "world"]


#: Each of :data:`KINDS` in the singular: MjSpec's finder (``spec.body(name)``) and a message's word.
SINGULAR = {"bodies": "body", "joints": "joint", "geoms": "geom", "sites": "site", "actuators": "actuator",
            "sensors": "sensor", "tendons": "tendon", "equalities": "equality", "pairs": "pair", "excludes": "exclude",
            "keys": "key", "cameras": "camera", "lights": "light", "numerics": "numeric", "texts": "text",
            "tuples": "tuple", "materials": "material", "textures": "texture"}


def _without(spec: mujoco.MjSpec, kind: str, names: Iterable[str]) -> mujoco.MjSpec:
    out = spec.copy()
    find = getattr(out, SINGULAR[kind])
    if kind == "materials":  # what wears a dropped material goes plain
        for e in [*out.geoms, *out.sites]:
            if e.material in names:
                e.material = ""
    for n in names:
        e = find(n)
        if e is not None:  # a body's descendants go with it
            out.delete(e)
    return out


def _explicit(spec: mujoco.MjSpec) -> mujoco.MjSpec:
    """``spec`` with every body's frame (``pos``, ``quat``) and, where it has mass, its inertia
    written out as compiled: the same model, whose geoms can go without its bodies losing
    their mass, and whose joints can be welded at a state (:func:`_welded`). Bodies placed in
    a ``<frame>`` keep their frames as written."""
    m = spec.compile()
    out = spec.copy()
    for b in out.bodies:
        if b.name == "world" or b.frame is not None:
            continue
        i = m.body(b.name).id
        b.pos, b.quat = m.body_pos[i], m.body_quat[i]
        b.alt.type = mujoco.mjtOrientation.mjORIENTATION_QUAT
        if m.body_mass[i] > 0:
            b.explicitinertial = True
            b.mass, b.ipos, b.iquat, b.inertia = m.body_mass[i], m.body_ipos[i], m.body_iquat[i], m.body_inertia[i]
    return out


def _welded(spec: mujoco.MjSpec, m: mujoco.MjModel, state: State, names: Iterable[str]) -> mujoco.MjSpec:
    """``spec`` without the joints ``names``, each body welded to its parent where ``state``
    holds it (``m``: ``spec`` compiled): a hinge's or slide's displacement from ``qpos0``, a
    ball's rotation, a free body's pose become the body's frame. The actuators, sensors and
    equality constraints naming a dropped joint are dropped with it."""
    out = spec.copy()
    qpos = state.data(m).qpos
    for n in names:
        joint = out.joint(n)
        if joint is None:
            continue
        j = m.joint(n).id
        body = out.body(m.body(int(m.jnt_bodyid[j])).name)
        adr, kind = int(m.jnt_qposadr[j]), int(m.jnt_type[j])
        pos, quat = np.array(body.pos, float), np.array(body.quat, float)
        if body.frame is None:
            if kind == mujoco.mjtJoint.mjJNT_FREE:
                pos, quat = qpos[adr:adr + 3].copy(), qpos[adr + 3:adr + 7].copy()
            else:
                turn = np.array([1.0, 0, 0, 0])
                shift = np.zeros(3)
                if kind == mujoco.mjtJoint.mjJNT_BALL:
                    turn = qpos[adr:adr + 4].copy()
                elif kind == mujoco.mjtJoint.mjJNT_HINGE:
                    mujoco.mju_axisAngle2Quat(turn, m.jnt_axis[j], qpos[adr] - m.qpos0[adr])
                else:
                    shift = m.jnt_axis[j] * (qpos[adr] - m.qpos0[adr])
                # a point p of the body: pos + R(quat) (R(turn) (p - jpos) + jpos + shift)
                moved = np.zeros(3)
                mujoco.mju_rotVecQuat(moved, m.jnt_pos[j], turn)
                offset = np.zeros(3)
                mujoco.mju_rotVecQuat(offset, m.jnt_pos[j] - moved + shift, quat)
                pos = pos + offset
                mujoco.mju_mulQuat(quat, quat.copy(), turn)
            body.pos, body.quat = pos, quat
            body.alt.type = mujoco.mjtOrientation.mjORIENTATION_QUAT
        for e in [*out.actuators, *out.sensors, *out.equalities]:  # what acts on or reads the joint goes with it
            if n in (getattr(e, "target", None), getattr(e, "objname", None), getattr(e, "name1", None),
                     getattr(e, "name2", None)):
                out.delete(e)
        out.delete(joint)
    return out


def fused(spec: mujoco.MjSpec) -> mujoco.MjSpec:
    """``spec`` with every body that has no joint merged into its parent, as MuJoCo's compiler
    does with ``fusestatic``: its geoms and sites move into a ``<frame>`` of the parent and its
    mass into the parent's. Bodies other elements name (an equality's, a sensor's) stay."""
    out = spec.copy()
    out.compiler.fusestatic = True
    try:
        out.compile()  # the compiler fuses in the spec itself
    except Exception:  # noqa: BLE001 - shrink() calls this outside its candidate guard: nothing fused
        return spec.copy()
    out.compiler.fusestatic = False
    return out


def mesh_geoms(spec: mujoco.MjSpec) -> list[str]:
    """The names of ``spec``'s mesh geoms that are not placed in a ``<frame>``."""
    return [g.name for g in spec.geoms if g.type == mujoco.mjtGeom.mjGEOM_MESH and g.frame is None]


def boxed(spec: mujoco.MjSpec, m: mujoco.MjModel, names: Iterable[str]) -> mujoco.MjSpec:
    """``spec`` with the mesh geoms ``names`` replaced by boxes of their bounding boxes (``m``:
    ``spec`` compiled: ``geom_aabb``, centre and half sizes in the geom's frame), and mesh assets
    no geom uses any more dropped. Bodies keep their inertia where it is explicit
    (:func:`_explicit`)."""
    out = spec.copy()
    for n in names:
        g, i = out.geom(n), m.geom(n).id
        centre = np.zeros(3)
        mujoco.mju_rotVecQuat(centre, m.geom_aabb[i][:3], m.geom_quat[i])
        g.type, g.meshname = mujoco.mjtGeom.mjGEOM_BOX, ""
        g.pos, g.quat, g.size = m.geom_pos[i] + centre, m.geom_quat[i], m.geom_aabb[i][3:]
        g.alt.type = mujoco.mjtOrientation.mjORIENTATION_QUAT
        g.fromto = np.full(6, np.nan)
    used = {g.meshname for g in out.geoms}
    for mesh in list(out.meshes):
        if mesh.name not in used:
            out.delete(mesh)
    return out


#: Numbers :func:`rounded` rounds, per element list: MjSpec attribute names (orientations are
#: left alone: a rounded quaternion is another rotation).
ROUNDED = {"bodies": ("pos", "mass", "ipos", "inertia"), "geoms": ("pos", "size"), "sites": ("pos", "size"),
           "joints": ("pos", "range", "damping", "stiffness", "armature", "frictionloss", "springref"),
           "actuators": ("gear", "ctrlrange", "forcerange", "gainprm", "biasprm"),
           "tendons": ("range", "damping", "stiffness", "armature", "frictionloss", "springlength")}


def rounded(spec: mujoco.MjSpec, digits: int) -> mujoco.MjSpec:
    """``spec`` with the numbers of :data:`ROUNDED` to ``digits`` significant digits."""
    out = spec.copy()
    for kind, attrs in ROUNDED.items():
        for e in getattr(out, kind):
            if kind == "bodies" and e.name == "world":
                continue
            for a in attrs:
                value = getattr(e, a)
                setattr(e, a, [significant(v, digits) for v in value] if np.ndim(value) else significant(value, digits))
    return out


def drop(spec: mujoco.MjSpec, kind: str, names: Sequence[str], m: mujoco.MjModel, state: State) -> mujoco.MjSpec:
    """``spec`` without its elements of ``kind`` named ``names``; joints welded where ``state``
    holds them (``m``: ``spec`` compiled)."""
    return _welded(spec, m, state, names) if kind == "joints" else _without(spec, kind, names)


def ddmin(items: Sequence[str], keeps: Callable[[list[str]], bool]) -> list[str]:
    """The smallest subset of ``items`` delta debugging finds for which ``keeps`` holds
    (``keeps(list(items))`` is assumed): all dropped at once first, then complements of ``n``
    chunks, ``n`` doubling to single items (Zeller and Hildebrandt 2002, ddmin)."""
    items = list(items)
    if items and keeps([]):
        return []
    n = 2
    while len(items) >= 2 or (len(items) == 1 and n == 2):
        size = math.ceil(len(items) / n)
        chunks = [items[i:i + size] for i in range(0, len(items), size)]
        for chunk in chunks:
            rest = [x for x in items if x not in chunk]
            if keeps(rest):
                items, n = rest, max(n - 1, 2)
                break
        else:
            if n >= len(items):
                break
            n = min(2 * n, len(items))
    return items


@dataclasses.dataclass(frozen=True)
class Shrunk:
    """What :func:`shrink` found: the minimal ``spec``, its ``state`` and the kept
    ``signature``; sizes ``before`` and ``after``; ``candidates`` checked, ``compiles`` (MJX
    XLA compiles: one per structure for forward, and for step), ``seconds``, the ``log`` of kept edits, and
    whether it stopped on its ``budget`` or an interrupt (``complete`` False: the best so far)."""

    spec: mujoco.MjSpec
    state: State
    signature: Signature
    before: Counts
    after: Counts
    candidates: int
    compiles: int
    seconds: float
    log: tuple[str, ...]
    complete: bool


class _Budget(Exception):
    pass


def _compiles() -> int:
    """XLA compiles in this process so far (a new structure's forward or step; a persistent
    cache hit counts too)."""
    from mjxdiff.engine import engines
    return engines.xla_compiles()


def shrink(spec: mujoco.MjSpec, state: State, signature: Signature | None = None, budget: float = 600.0,
           say: Callable[[str], None] = lambda s: None, steps_before: int = 1) -> Shrunk:
    """Shrinks ``spec`` (not changed) while it shows ``signature`` from ``state`` (default: what
    it shows there now), for at most ``budget`` seconds; Ctrl-C stops it with the best so far.

    Raises ValueError when the model does not show a divergence from ``state``."""
    t0, compiles0 = time.perf_counter(), _compiles()
    best = named(spec.copy())
    target = probe(best.compile(), state)
    if target is None:
        raise ValueError("the model shows no divergence from this state: nothing to shrink (a state of an "
                         "unnamed model names its joints as shrink.named(spec) does)")
    if signature is not None and target != signature:
        raise ValueError(f"from this state the model shows '{target.describe()}', not '{signature.describe()}'")
    explicit = _explicit(best)
    if _shows_safely(explicit, state, target):
        best = explicit
    before = counts(best, steps_before)
    run = _Shrinking(best, state, target, t0, budget, say)
    complete = True
    try:
        if target.check == "forward":  # first, only the bodies of what the drill-down names
            run.focus()
        run.drop_elements()
        run.fuse_and_box()
        run.default_options()
        say(f"shrink: options {_option_changes(spec)} -> {_option_changes(run.best)} changed from the defaults")
        run.round()
    except (_Budget, KeyboardInterrupt):
        complete = False
        say("shrink: stopped (budget or interrupt): the best so far")
    return Shrunk(run.best, run.state, target, before, counts(run.best), run.tried, _compiles() - compiles0,
                  time.perf_counter() - t0, tuple(run.log), complete)


@dataclasses.dataclass
class _Shrinking:
    """A shrink in progress (:func:`shrink`): the smallest model so far, ``best``, and the
    ``state`` it shows ``target`` from, the ``log`` of what each pass removed and the candidates
    ``tried``. Each pass keeps what it removes as it goes, so that a stop (the budget, Ctrl-C)
    keeps the best so far."""

    best: mujoco.MjSpec
    state: State
    target: Signature
    t0: float
    budget: float
    say: Callable[[str], None]
    log: list[str] = dataclasses.field(default_factory=list)
    tried: int = 0
    kept_compiles: int = dataclasses.field(default_factory=_compiles)

    def shows(self, candidate: mujoco.MjSpec, s: State) -> bool:
        """Whether ``candidate``, compiled by C (and from its own MJCF), shows the target from
        ``s``; raises :class:`_Budget` once the budget is spent."""
        if time.perf_counter() - self.t0 > self.budget:
            raise _Budget
        self.tried += 1
        if _compiles() - self.kept_compiles >= KEEP_COMPILED:
            # each structure's executables stay in JAX's caches: a humanoid's shrink ran LLVM out of
            # memory ("Cannot allocate memory") after some 60; few structures are ever tried twice
            jax.clear_caches()
            self.kept_compiles = _compiles()
        try:
            m = candidate.compile()
            mujoco.MjSpec.from_string(candidate.to_xml()).compile()  # and one whose MJCF a bundle can write and load
        except Exception:  # noqa: BLE001 - a candidate C cannot compile is not kept
            return False
        try:
            return probe(m, s) == self.target
        except Exception:  # noqa: BLE001 - nor one an engine cannot run
            return False

    def focus(self) -> None:
        """Keeps only the bodies of the object the drill-down names, where that still shows."""
        m = self.best.compile()
        focus, names = focus_bodies(m, drill(m, self.state).object), element_names(self.best, "bodies")
        if focus and len(focus) < len(names):
            candidate = drop(self.best, "bodies", [n for n in names if n not in focus], m, self.state)
            if self.shows(candidate, self.state):
                self.best = candidate
                self.log.append(f"bodies: {len(names)} -> {len(focus)} (those of the object named)")
                self.say(f"shrink: bodies {len(names)} -> {len(focus)}, those of the object the drill-down names")

    def drop_elements(self) -> None:
        """Drops elements of each kind (:data:`KINDS`, :func:`ddmin`), again while a pass drops
        something."""
        state = self.state
        dropped_any = True
        while dropped_any:  # again while a pass drops something: what an element named may go now
            dropped_any = False
            for kind in KINDS:
                best = self.best
                names = element_names(best, kind)
                if not names:
                    continue
                m = best.compile()

                def edit(dropped, k=kind, b=best, m=m):
                    return drop(b, k, dropped, m, state)
                kept = ddmin(names, lambda keep, ns=names: self.shows(edit([n for n in ns if n not in keep]), state))
                smaller = edit([n for n in names if n not in kept])
                with contextlib.suppress(Exception):  # compiling adds back what <size nkey="5"/> asks for
                    smaller.compile()
                if len(element_names(smaller, kind)) < len(names):  # else no progress
                    self.best, dropped_any = smaller, True
                    self.log.append(f"{kind}: {len(names)} -> {len(kept)}")
                    self.say(f"shrink: {kind} {len(names)} -> {len(kept)} ({self.tried} candidates, "
                             f"{time.perf_counter() - self.t0:.0f} s)")

    def fuse_and_box(self) -> None:
        """Fuses bodies without joints into their parents, and replaces meshes by boxes, where
        that still shows."""
        state, shows, log = self.state, self.shows, self.log
        best = self.best
        if len(best.bodies) > 1:
            candidate = fused(best)
            if len(candidate.bodies) < len(best.bodies) and shows(candidate, state):
                log.append(f"bodies without joints fused: {len(best.bodies) - 1} -> {len(candidate.bodies) - 1}")
                self.best = best = candidate
        meshes = mesh_geoms(best)
        if meshes:
            m = best.compile()
            kept = ddmin(meshes, lambda keep, b=best, m=m: shows(boxed(b, m, [n for n in meshes if n not in keep]),
                                                                  state))
            if len(kept) < len(meshes):
                self.best = boxed(best, m, [n for n in meshes if n not in kept])
                log.append(f"meshes as boxes: {len(meshes) - len(kept)} of {len(meshes)}")

    def default_options(self) -> None:
        """Sets each option changed from the default back to it, and clears each set bit of the
        disable and enable flags, where that still shows."""
        default = mujoco.MjSpec().option
        for o in changed_options(self.best):
            candidate = self.best.copy()
            setattr(candidate.option, o, getattr(default, o))
            if self.shows(candidate, self.state):
                self.best = candidate
                self.log.append(f"option {o}: default")
        for flags in ("disableflags", "enableflags"):
            for bit in range(32):
                if getattr(self.best.option, flags) & (1 << bit):
                    candidate = self.best.copy()
                    setattr(candidate.option, flags, getattr(self.best.option, flags) & ~(1 << bit))
                    if self.shows(candidate, self.state):
                        self.best = candidate
                        self.log.append(f"option {flags}: bit {bit} cleared")

    def round(self) -> None:
        """Rounds the model's numbers, then the state's, to the fewest significant digits (2, 3
        or 6) that still show."""
        for digits in (2, 3, 6):
            candidate = rounded(self.best, digits)
            if self.shows(candidate, self.state):
                self.best = candidate
                self.log.append(f"model: {digits} significant digits")
                break
        for digits in (2, 3, 6):
            shorter = self.state.rounded(digits)
            if self.shows(self.best, shorter):
                self.state = shorter
                self.log.append(f"state: {digits} significant digits")
                break


def _shows_safely(spec: mujoco.MjSpec, state: State, target: Signature) -> bool:
    try:
        return probe(spec.compile(), state) == target
    except Exception:  # noqa: BLE001 - a model C or MJX cannot run shows nothing
        return False


