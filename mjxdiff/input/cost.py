"""What MJX's rollout of a model will cost, estimated before anything compiles.

A sweep compiles one MJX rollout per model structure. Most models compile in 2-15 s and step
in a few MiB per member; a model with many mesh-mesh collision pairs can take many minutes to
compile and many GB per member to step (MJX's separating-axis test is dense over every pair
of hull edges). This module reads the few model features those costs grow with, from MJX's
own collision grouping (``collision_driver._geom_groups``) and its convex hulls
(``mesh.convex``, as ``put_model`` builds them), and turns them into seconds and bytes with
constants calibrated on compiles measured on a 2-core machine
(``benchmarks/scripts/cost_calibration.py``; the table is in the README).

Nothing here traces or compiles: an estimate costs what ``put_model`` costs, and it is made
once per model structure.
"""
from __future__ import annotations

import dataclasses
import functools
import os
import re
import warnings

import mujoco

from mjxdiff.compat import data_impl

__all__ = ["Estimate", "PairGroup", "estimate", "hlo_features"]

@dataclasses.dataclass(frozen=True)
class PairGroup:
    """One collision function MJX compiles: a geom-type pair (and mesh sizes) with its pairs.

    Attributes:
      types: geom type names, e.g. ``("mesh", "mesh")``.
      pairs: geom pairs this function collides (vmapped over, per step and member).
      hulls: per side, ``(vertices, faces, max vertices per face, edges)`` of MJX's convex
        hull, for mesh sides (None for primitives).
      work: dense elements MJX's function evaluates per pair: for two hulls
        ``E1 E2 + F1 V2 + F2 V1 + F1 F2 P`` (edge pairs of the separating-axis test,
        face-vertex tests, face clipping); 1 for a primitive pair.
      geoms: names of the geoms of its first pairs (at most 4), for messages.
      members: every pair, ``(geom1, geom2, pair id or -1)`` as MJX groups them.
    """

    types: tuple[str, str]
    pairs: int
    hulls: tuple[tuple[int, int, int, int] | None, tuple[int, int, int, int] | None]
    work: float
    geoms: tuple[str, ...] = ()
    members: tuple[tuple[int, int, int], ...] = ()

    @property
    def label(self) -> str:
        return "-".join(self.types)


#: Compile seconds (trace and XLA, one module on about one core): ``COMPILE_BASE_S +
#: COMPILE_PER_NV_S x nv + COMPILE_PER_GROUP_S x primitive collision functions +
#: COMPILE_PER_HULL_GROUP_S x collision functions with a hull``; fitted on the compiles of
#: ``benchmarks/scripts/cost_calibration.py`` (table in the README).
COMPILE_BASE_S = 5.0
COMPILE_PER_NV_S = 0.09
COMPILE_PER_GROUP_S = 0.4
COMPILE_PER_HULL_GROUP_S = 2.65
#: Compile seconds and bytes per contact under Newton with elliptic cones (see :func:`estimate`):
#: the LEAP hand's plain model (6,728 contacts) traced in 33 s, then XLA compiled for more than
#: 6 min and reached 19 GB resident before it was stopped.
COMPILE_PER_CONE_S = 0.08
COMPILE_BYTES_PER_CONE = 3 * 2**20
#: MJX's seconds per member-step: ``STEP_BASE_S + STEP_PER_WORK_S x hull work`` (the dense
#: temporaries of the separating-axis tests dominate a robot's plain model: FR3, 22 M elements,
#: 0.16 s per member-step).
STEP_BASE_S = 3e-3
STEP_PER_WORK_S = 7.5e-9
#: Bytes a compile holds: ``COMPILE_BASE_BYTES + COMPILE_BYTES_PER_HULL_GROUP x hull groups``.
COMPILE_BASE_BYTES = 0.5 * 2**30
COMPILE_BYTES_PER_HULL_GROUP = 50 * 2**20
#: Copies of a member's C model a scenario holds at once (its inputs, the converged copies of
#: the one-step check and the twin): a sweep of ANYmal C (240 MB of visual meshes per model,
#: 8 members) peaked at 7.4 GB resident.
MODEL_COPIES = 3
#: Bytes per member while stepping, per element of hull work (XLA's temporaries, float64).
BYTES_PER_WORK = 8.0
#: A model estimated to compile this long, or to step this many bytes per member, gets the advice
#: to give its hull-hull pairs primitive collision geoms (:meth:`Estimate.advice_line`).
ADVISE_COMPILE_S = 60.0
ADVISE_MEMBER_BYTES = 256 * 2**20


@dataclasses.dataclass(frozen=True)
class Estimate:
    """MJX's cost for one model structure, before compiling.

    Attributes:
      compile_s: seconds XLA will take to compile the rollout (one module, about one core).
      member_bytes: bytes MJX holds per member while stepping (data, solver and collision
        temporaries).
      groups: the collision functions MJX will compile, costliest first.
      advice: MJX's own advice on this model (a mesh with large coplanar faces), one line each.
      nv: degrees of freedom.
      step_s: seconds MJX takes per member-step.
      compile_bytes: bytes the compile holds beyond the process.
      ncon, nefc: contacts and constraint rows MJX allocates per member.
      cone_s: the part of ``compile_s`` due to Newton's elliptic-cone Hessian, unrolled per contact.
    """

    compile_s: float
    member_bytes: int
    groups: tuple[PairGroup, ...] = ()
    advice: tuple[str, ...] = ()
    nv: int = 0
    step_s: float = STEP_BASE_S
    compile_bytes: float = COMPILE_BASE_BYTES
    ncon: int = 0
    nefc: int = 0
    cone_s: float = 0.0

    def batch_that_fits(self, available_bytes: float) -> int:
        """Members whose stepping fits ``available_bytes`` (0: not even one)."""
        return int(available_bytes // max(self.member_bytes, 1))

    @property
    def costly(self) -> tuple[PairGroup, ...]:
        """Groups with a mesh and two hulls (mesh-mesh, box-mesh): what makes a model slow and large."""
        return tuple(g for g in self.groups if "mesh" in g.types and all(h is not None for h in g.hulls))

    def pairs_text(self) -> str:
        """``mesh-mesh pairs: 12 (hulls up to 120 edges)``; '' when the model has none."""
        costly = self.costly
        if not costly:
            return ""
        by_type: dict[str, int] = {}
        for g in costly:
            by_type[g.label] = by_type.get(g.label, 0) + g.pairs
        edges = max(h[3] for g in costly for h in g.hulls if h is not None)
        return ", ".join(f"{k} pairs: {v}" for k, v in by_type.items()) + f" (hulls up to {edges} edges)"

    def line(self) -> str:
        """``MJX: compile ~3 min (mesh-mesh pairs: 12 ...), ~2.1 GB per member``."""
        pairs = self.pairs_text()
        step = f", ~{self.step_s:.2g} s per member-step" if self.step_s >= 0.01 else ""
        held = f" and ~{human_bytes(self.compile_bytes)} of memory" if self.compile_bytes >= 2 * 2**30 else ""
        return (f"MJX: compile ~{human_seconds(self.compile_s)}{held}{f' ({pairs})' if pairs else ''}, "
                f"~{human_bytes(self.member_bytes)} per member{step}")

    def advice_line(self) -> str:
        """MJX's advice on this model in one line ('' when it has none): the meshes to decimate and,
        for a costly model, the pairs to give primitive collision geoms."""
        parts = []
        meshes = [a.split()[2] for a in self.advice if a.startswith("decimate mesh ")]
        if meshes:
            shown = ", ".join(meshes[:6]) + (f" and {len(meshes) - 6} more" if len(meshes) > 6 else "")
            parts.append(f"decimate mesh{'es' if len(meshes) > 1 else ''} {shown} (a coplanar face of more "
                         "than 20 vertices slows MJX's collisions)")
        costly = self.costly
        if costly and (self.compile_s >= ADVISE_COMPILE_S or self.member_bytes >= ADVISE_MEMBER_BYTES):
            pairs = sum(g.pairs for g in costly)
            parts.append(f"use primitive collision geoms for the {pairs} hull-hull pairs (e.g. {costly[0].geoms[0]}), "
                         "as the MJX variants of robots do, or --drop-costly-pairs")
        if self.cone_s >= ADVISE_COMPILE_S:
            parts.append(f"MJX's Newton solver unrolls the elliptic-cone Hessian over all {self.ncon} contacts "
                         f"(~{human_seconds(self.cone_s)} of compile, {human_bytes(8 * self.nefc**2)} per member): "
                         "cone=\"pyramidal\", or fewer contact pairs (contype/conaffinity, <exclude>)")
        return "MJX advises: " + "; ".join(parts) if parts else ""

    def as_dict(self) -> dict:
        return dict(compile_s=round(self.compile_s, 1), member_bytes=int(self.member_bytes),
                    step_s=self.step_s, compile_bytes=int(self.compile_bytes), ncon=self.ncon, nefc=self.nefc,
                    nv=self.nv, line=self.line(), advice=list(self.advice), advice_line=self.advice_line(),
                    groups=[dict(types=g.label, pairs=g.pairs, work=g.work, hulls=g.hulls, geoms=list(g.geoms))
                            for g in self.groups])


def human_seconds(s: float) -> str:
    return f"{s:.0f} s" if s < 90 else f"{s / 60:.0f} min" if s < 5400 else f"{s / 3600:.1f} h"


def human_bytes(b: float) -> str:
    for unit, size in (("GB", 2**30), ("MB", 2**20)):
        if b >= size:
            return f"{b / size:.1f} {unit}"
    return f"{b / 2**10:.0f} kB"


def _hull(m: mujoco.MjModel, data_id: int, advice: list[str]) -> tuple[int, int, int, int]:
    """(vertices, faces, max vertices per face, edges) of MJX's hull of mesh ``data_id``."""
    from mujoco.mjx._src import mesh

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        c = mesh.convex(m, data_id)
    for w in caught:
        if "coplanar" in str(w.message):
            name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_MESH, data_id) or f"#{data_id}"
            advice.append(f"decimate mesh {name} (MJX: a coplanar face with more than 20 vertices slows collisions)")
    return int(c.vert.shape[0]), int(c.face.shape[0]), int(c.face.shape[1]), int(c.edge.shape[0])


def _work(hulls) -> float:
    a, b = hulls
    if a is None or b is None:  # a primitive against a hull: linear in the hull
        h = a or b
        return float(h[0] + h[1] * h[2]) if h else 1.0
    (v1, f1, p1, e1), (v2, f2, p2, e2) = a, b
    return float(e1 * e2 + f1 * v2 + f2 * v1 + f1 * f2 * max(p1, p2))


def _geom_name(m: mujoco.MjModel, g: int) -> str:
    """A geom's name, or its body's name and its id where it has none."""
    name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, int(g))
    if name:
        return name
    body = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, int(m.geom_bodyid[g])) or f"body #{m.geom_bodyid[g]}"
    return f"geom #{int(g)} of {body}"


def pair_groups(m: mujoco.MjModel) -> tuple[tuple[PairGroup, ...], tuple[str, ...]]:
    """MJX's collision functions for ``m`` (costliest first) and MJX's mesh advice."""
    from mujoco.mjx._src import collision_driver

    advice: list[str] = []
    hulls: dict[int, tuple[int, int, int, int]] = {}
    out = []
    for key, pairs in collision_driver._geom_groups(m).items():  # noqa: SLF001 - MJX's own collision grouping
        types = tuple(mujoco.mjtGeom(int(t)).name[len("mjGEOM_"):].lower() for t in key.types)
        sides = []
        for t, data_id in zip(types, key.data_ids):
            if t == "mesh" and data_id >= 0:
                if data_id not in hulls:
                    hulls[data_id] = _hull(m, int(data_id), advice)
                sides.append(hulls[data_id])
            elif t == "box":
                sides.append((8, 6, 4, 12))
            else:
                sides.append(None)
        work = _work(sides) if any(s is not None for s in sides) else 1.0
        names = tuple(f"{_geom_name(m, g1)} / {_geom_name(m, g2)}" for g1, g2, _ in pairs[:4])
        out.append(PairGroup(types, len(pairs), tuple(sides), work, names,
                             tuple((int(a), int(b), int(c)) for a, b, c in pairs)))
    out.sort(key=lambda g: -g.work * g.pairs)
    return tuple(out), tuple(dict.fromkeys(advice))


#: MJX's working set per member while stepping, in multiples of the size of its ``mjx.Data``
#: (scan carry, solver and collision temporaries, one piece of records).
WORKING_SET_FACTOR = 40


def member_bytes(m: mujoco.MjModel) -> int:
    """Estimated bytes MJX holds per batch member while stepping ``m``: WORKING_SET_FACTOR x its data;
    0 when MJX cannot make data for ``m`` (the rollout then reports why, e.g. as unsupported)."""
    return WORKING_SET_FACTOR * data_sizes(m)[0]


def estimate(m: mujoco.MjModel, batch: int = 1, steps: int = 1) -> Estimate:
    """MJX's compile seconds and bytes per member for ``m`` (see :class:`Estimate`).

    ``batch`` and ``steps`` do not change either (a rollout compiles once, whatever its
    size; memory is per member); they are accepted for a plan's convenience.
    """
    try:
        groups, advice = pair_groups(m)
    except Exception:  # noqa: BLE001 - no grouping (MJX refuses the model): primitives only
        groups, advice = (), ()
    work = sum(g.work * g.pairs for g in groups if g.work > 1)  # every group with a hull
    hull = sum(any(h is not None for h in g.hulls) for g in groups)
    data, ncon, nefc = data_sizes(m)
    # Newton with elliptic cones: MJX adds each contact's cone Hessian into a dense nefc x nefc
    # matrix, one unrolled update per contact (solver._update_gradient)
    elliptic = int(m.opt.solver) == int(mujoco.mjtSolver.mjSOL_NEWTON) and \
        int(m.opt.cone) == int(mujoco.mjtCone.mjCONE_ELLIPTIC)
    cone_s = COMPILE_PER_CONE_S * ncon if elliptic else 0.0
    compile_s = (COMPILE_BASE_S + COMPILE_PER_NV_S * m.nv + COMPILE_PER_GROUP_S * (len(groups) - hull)
                 + COMPILE_PER_HULL_GROUP_S * hull + cone_s)
    # each member has its own copies of the C model (visual meshes included: 240 MB for
    # ANYmal C), beside MJX's working set, its hull-hull temporaries and the cone Hessian
    member = (WORKING_SET_FACTOR * data + MODEL_COPIES * m.nbuffer + BYTES_PER_WORK * work
              + (8 * nefc**2 if elliptic else 0))
    return Estimate(compile_s, int(member), groups, advice, m.nv, STEP_BASE_S + STEP_PER_WORK_S * work,
                    COMPILE_BASE_BYTES + COMPILE_BYTES_PER_HULL_GROUP * hull
                    + (COMPILE_BYTES_PER_CONE * ncon if elliptic else 0), ncon=ncon, nefc=nefc, cone_s=cone_s)


def data_sizes(m: mujoco.MjModel) -> tuple[int, int, int]:
    """Bytes of one member's ``mjx.Data``, its contacts and its constraint rows (zeros where MJX
    cannot make data for ``m``: the rollout then says why)."""
    import jax
    from mujoco import mjx

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            dx = mjx.make_data(m)
    except Exception:  # noqa: BLE001 - an estimate; put_model names the problem properly
        return 0, 0, 0
    data = sum(x.size * x.dtype.itemsize for x in jax.tree.leaves(dx))
    impl = data_impl(dx)  # MJX's contact and constraint sizes
    # the JAX implementation's Data, whose fields MJX's union of implementations does not show
    return data, int(impl.contact.dist.shape[0]), int(impl.efc_J.shape[0])  # pyright: ignore[reportAttributeAccessIssue]


def available_bytes() -> int:
    """Memory the kernel could still give (``MemAvailable``), bytes; 0 where /proc cannot tell."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError):
        pass
    return 0


def resident_bytes(pid: int | str = "self") -> int:
    """Resident memory of process ``pid`` (this one by default), bytes; 0 once it is gone."""
    try:
        with open(f"/proc/{pid}/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return 0


_TENSOR = re.compile(r"tensor<((?:\d+x)*)(f64|f32|i64|i32|i1|i8|ui8|f16|bf16|ui32|ui64)>")
_BITS = dict(f64=64, i64=64, ui64=64, f32=32, i32=32, ui32=32, f16=16, bf16=16, i8=8, ui8=8, i1=8)


def hlo_features(text: str) -> dict:
    """Counts of a lowered module's StableHLO text: ``ops`` (lines defining values), ``whiles``,
    ``largest_bytes`` (largest tensor type), ``result_bytes`` (sum over op results)."""
    ops = whiles = 0
    largest = total = 0
    for line in text.splitlines():
        if " = " not in line:
            continue
        ops += 1
        whiles += "stablehlo.while" in line
        for dims, kind in _TENSOR.findall(line.rsplit("->", 1)[-1]):
            size = functools.reduce(lambda a, b: a * b, (int(d) for d in dims.split("x") if d), 1)
            size *= _BITS[kind] // 8
            largest = max(largest, size)
            total += size
    return dict(ops=ops, whiles=whiles, largest_bytes=largest, result_bytes=total)


@dataclasses.dataclass(frozen=True)
class Plan:
    """How a scenario runs within its limits (:func:`plan`).

    Attributes:
      batch, steps: members and horizon to run.
      group: members MJX steps at once.
      stop: why nothing is run (the estimate does not fit, whatever the plan), else None.
      changed: what the plan changed from the default, one line each ("steps 200 -> 87
        (...)").
      kind: with ``stop``, what does not fit: ``budget`` or ``memory``.
    """

    batch: int
    steps: int
    group: int
    stop: str | None = None
    changed: tuple[str, ...] = ()
    kind: str = ""


#: Share of a scenario's budget the plan gives MJX's compile and the rollout's stepping; the
#: rest is for the one-step check, the host-interface check and a diagnosis.
PLAN_SHARE = 0.6
#: MJX stepping the plan counts per member-step of the rollout: the rollout, and the one-step
#: check's stepping from C's states (up to one piece per member), with a margin.
STEP_PASSES = 2.5
#: Least horizon and batch a plan shortens to before it gives up.
MIN_STEPS = 20
MIN_BATCH = 2


def plan(est: Estimate, batch: int, steps: int, group: int, budget_s: float | None,
         memory_bytes: float | None, held_bytes: float = 0.0) -> Plan:
    """The plan that fits ``est`` within ``budget_s`` seconds and ``memory_bytes`` of resident
    memory (None: no limit), for ``batch`` members and ``steps`` steps asked for, ``group``
    members stepped at once by default, and ``held_bytes`` the process holds already.

    Time: a compile cannot be shortened by a smaller batch or horizon, so a compile estimated
    past :data:`PLAN_SHARE` of the budget stops the scenario before it starts; otherwise the
    horizon shortens (to :data:`MIN_STEPS`), then the batch (to :data:`MIN_BATCH`), until
    :data:`STEP_PASSES` x ``batch x steps x est.step_s`` fits what is left of that share.
    Memory: one member that does not fit with the compile's own memory stops the scenario;
    otherwise the member group shrinks until its stepping fits.
    """
    todo = ("to get a verdict: give it more time (--budget), drop the costly pairs (--drop-costly-pairs, "
            "changes the dynamics) or use primitive collision geoms, as MJX variants of models do")
    changed: list[str] = []
    if budget_s is not None:
        if est.compile_s > PLAN_SHARE * budget_s:
            return Plan(batch, steps, group, kind="budget", stop=(
                f"{est.line()}: the compile alone exceeds the scenario's budget of {human_seconds(budget_s)} "
                f"(with the checks after it); nothing was run; {todo}"))
        member_steps = (PLAN_SHARE * budget_s - est.compile_s) / (STEP_PASSES * est.step_s)
        if batch * steps > member_steps:
            new_steps = max(min(steps, MIN_STEPS), int(member_steps // batch))
            new_batch = max(min(batch, MIN_BATCH), min(batch, int(member_steps // new_steps)))
            if new_batch * new_steps > member_steps:
                return Plan(batch, steps, group, kind="budget", stop=(
                    f"{est.line()}, ~{human_seconds(est.step_s)} per member-step: even {new_batch} members x "
                    f"{new_steps} steps exceed the scenario's budget of {human_seconds(budget_s)}; nothing was "
                    f"run; {todo}"))
            why = f"~{est.step_s:.2g} s per member-step, budget {human_seconds(budget_s)}"
            if new_steps < steps:
                changed.append(f"steps {steps} -> {new_steps} ({why})")
            if new_batch < batch:
                changed.append(f"batch {batch} -> {new_batch} ({why})")
            batch, steps, group = new_batch, new_steps, min(group, new_batch)
    if memory_bytes is None:
        return Plan(batch, steps, group, changed=tuple(changed))
    left = memory_bytes - held_bytes - est.compile_bytes
    fits = est.batch_that_fits(left) if left > 0 else 0
    if fits < 1:
        return Plan(batch, steps, group, kind="memory", stop=(
            f"{est.line()}, ~{human_bytes(est.compile_bytes)} to compile: one member does not fit in the memory "
            f"left ({human_bytes(max(memory_bytes - held_bytes, 0))} of the {human_bytes(memory_bytes)} limit); "
            f"nothing was run; {todo.replace('more time (--budget)', 'more memory (--max-memory)')}"))
    if fits < group:
        changed.append(f"members stepped at once: {group} -> {fits} (~{human_bytes(est.member_bytes)} each, "
                       f"{human_bytes(left)} left of the {human_bytes(memory_bytes)} limit)")
        group = fits
    return Plan(batch, steps, group, changed=tuple(changed))
