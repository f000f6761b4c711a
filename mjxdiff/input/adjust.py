"""What mjxdiff changes in a model before both engines step it, so that MJX can run it.

Every change is named in the scenario's result (``info['adjusted']``, and the
report line) and can be switched off; nothing is changed silently.

* **Harmless settings** (:func:`harmless`, on by default, ``--no-adjust`` turns
  it off): enable flags MJX refuses that change no quantity mjxdiff compares.
  ``energy`` only fills ``d.energy`` and ``fwdinv`` only fills the
  ``solver_fwdinv`` diagnostics; MuJoCo C steps ``qpos``, ``qvel``, ``act``,
  ``sensordata`` and contacts bit-identically with and without them (tested).
  A model with energy sensors keeps its flag (their values are what the flag computes).
* **Unsupported collision pairs** (:func:`drop_unsupported`, opt-in with
  ``--drop-unsupported``, never the default): geom pairs MJX has no collision
  function for, or mesh/height-field pairs with a margin, are removed from the
  model both engines step (``<pair>`` elements deleted, other pairs excluded
  body against body with ``<exclude>``), so that the rest of the model can be
  tested. This changes the dynamics being compared, so the result says which
  pairs were dropped, including supported pairs between the same bodies.
* **Costly collision pairs** (:func:`drop_costly`, opt-in with ``--drop-costly-pairs``): the
  mesh-mesh and box-mesh pairs whose dense separating-axis test makes MJX's compile take
  minutes and its stepping GBs per member (:mod:`mjxdiff.input.cost`), removed the same way, so
  that a robot's plain model gets a verdict on everything else.
"""

from __future__ import annotations

import copy
from pathlib import Path

import mujoco
import numpy as np

from mjxdiff.compare.support import HARMLESS_ENABLE_FLAGS

__all__ = ["HARMLESS_ENABLE_FLAGS", "costly_pairs", "drop_costly", "drop_unsupported", "for_mjx", "harmless",
           "unsupported_pairs"]

_ENERGY_SENSORS = (int(mujoco.mjtSensor.mjSENS_E_POTENTIAL), int(mujoco.mjtSensor.mjSENS_E_KINETIC))


def harmless(m: mujoco.MjModel) -> tuple[mujoco.MjModel, list[str]]:
    """``m`` without the :data:`HARMLESS_ENABLE_FLAGS` it sets (a copy; ``m`` itself when none),
    and one ``"<flag> disabled for MJX"`` line per flag removed."""
    flags = [bit for bit in HARMLESS_ENABLE_FLAGS if m.opt.enableflags & bit]
    if int(mujoco.mjtEnableBit.mjENBL_ENERGY) in flags and np.isin(m.sensor_type, _ENERGY_SENSORS).any():
        flags.remove(int(mujoco.mjtEnableBit.mjENBL_ENERGY))
    if not flags:
        return m, []
    m = copy.copy(m)
    for bit in flags:
        m.opt.enableflags &= ~bit
    return m, [f"{HARMLESS_ENABLE_FLAGS[bit]} disabled for MJX" for bit in flags]


def _geom(m: mujoco.MjModel, g: int) -> str:
    name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, int(g)) or f"#{int(g)}"
    kind = mujoco.mjtGeom(int(m.geom_type[g])).name.removeprefix("mjGEOM_").lower()
    return f"{kind} '{name}'"


def unsupported_pairs(m: mujoco.MjModel) -> list[tuple[int, int, int, str]]:
    """The geom pairs MJX's ``put_model`` would refuse: ``(geom1, geom2, pair id or -1, reason)``.

    The candidate pairs are MJX's own (``collision_driver.geom_pairs``: explicit
    ``<pair>`` elements, then contype/conaffinity, exclusions and parent filtering);
    a pair is refused when MJX has no collision function for its geom types, or
    when a mesh or height field in it has a margin.
    """
    from mujoco.mjx._src import collision_driver

    no_margin = {int(mujoco.mjtGeom.mjGEOM_MESH), int(mujoco.mjtGeom.mjGEOM_HFIELD)}
    out = []
    for g1, g2, ip in collision_driver.geom_pairs(m):
        t1, t2 = (int(t) for t in m.geom_type[[g1, g2]])
        # MJX annotates its GeomType enum; plain ints are equal to its members (an IntEnum)
        if not collision_driver.has_collision_fn(t1, t2):  # pyright: ignore[reportArgumentType]
            out.append((int(g1), int(g2), int(ip), "no MJX collision function"))
        elif no_margin & {t1, t2}:
            margin = m.pair_margin[ip] if ip != -1 else m.geom_margin[g1] + m.geom_margin[g2]
            if np.any(margin):
                out.append((int(g1), int(g2), int(ip), "margin on a mesh or height field"))
    return out


def _candidates(m: mujoco.MjModel) -> set[tuple[int, ...]]:
    from mujoco.mjx._src import collision_driver

    return {tuple(sorted((int(g1), int(g2)))) for g1, g2, _ in collision_driver.geom_pairs(m)}


def costly_pairs(m: mujoco.MjModel) -> list[tuple[int, int, int, str]]:
    """The geom pairs MJX collides with its dense separating-axis test between two hulls (mesh-mesh,
    box-mesh): ``(geom1, geom2, pair id or -1, reason)``, the pairs that make a model slow to
    compile and large to step (:mod:`mjxdiff.input.cost`)."""
    from mjxdiff.input import cost

    out = []
    groups, _ = cost.pair_groups(m)
    for group in cost.Estimate(0.0, 0, groups).costly:
        for g1, g2, ip in group.members:
            out.append((int(g1), int(g2), int(ip), f"{group.label} pair, {group.work:.0f} elements per step"))
    return out


def drop_unsupported(m: mujoco.MjModel, path: str | Path) -> tuple[mujoco.MjModel, list[str]]:
    """``m`` compiled again from ``path`` without the pairs of :func:`unsupported_pairs`, and what was dropped.

    Explicit ``<pair>`` elements are deleted; a pair found by contype/conaffinity
    is removed by an ``<exclude>`` of its two bodies, which also removes every
    other pair between them (reported too). Returns ``m`` unchanged when nothing
    is unsupported; otherwise the model compiled from ``path``, so apply
    :func:`harmless` after this (:func:`for_mjx` does).
    """
    return drop_pairs(m, path, unsupported_pairs(m), _UNSUPPORTED)


def drop_costly(m: mujoco.MjModel, path: str | Path) -> tuple[mujoco.MjModel, list[str]]:
    """:func:`drop_unsupported` for the pairs of :func:`costly_pairs` (``--drop-costly-pairs``)."""
    return drop_pairs(m, path, costly_pairs(m), _COSTLY)


#: Dropped pairs a line names; the rest are counted.
_LISTED = 12
_UNSUPPORTED = "geom pair(s) MJX cannot collide (--drop-unsupported)"
_COSTLY = "costly hull-hull geom pair(s) (--drop-costly-pairs)"


def drop_pairs(m: mujoco.MjModel, path: str | Path, bad: list[tuple[int, int, int, str]],
               what: str) -> tuple[mujoco.MjModel, list[str]]:
    """``m`` compiled again from ``path`` without the geom pairs ``bad`` (see :func:`drop_unsupported`),
    and one line naming every pair dropped as ``what``."""
    if not bad:
        return m, []
    spec = mujoco.MjSpec.from_file(str(path))
    for i, body in enumerate(spec.bodies):  # an exclude names its bodies
        if not body.name:
            body.name = f"mjxdiff_body_{i}"
    named = spec.compile()
    names = {b: mujoco.mj_id2name(named, mujoco.mjtObj.mjOBJ_BODY, b) for b in range(named.nbody)}
    pairs = list(spec.pairs)
    excluded = set()
    for g1, g2, ip, _ in bad:
        if ip != -1:
            spec.delete(pairs[ip])
            continue
        b1, b2 = sorted((int(m.geom_bodyid[g1]), int(m.geom_bodyid[g2])))
        if (b1, b2) not in excluded:
            excluded.add((b1, b2))
            spec.add_exclude(bodyname1=names[b1], bodyname2=names[b2])
    dropped = spec.compile()
    if dropped.ngeom != m.ngeom or not np.array_equal(dropped.geom_type, m.geom_type):
        raise ValueError(f"{Path(path).name}: recompiling without the dropped pairs changed its geoms")
    reasons = {tuple(sorted((g1, g2))): why for g1, g2, _, why in bad}
    gone = sorted(_candidates(m) - _candidates(dropped))
    named = [f"{_geom(m, a)} / {_geom(m, b)} ({reasons.get((a, b), 'same bodies as a dropped pair')})"
             for a, b in gone]
    more = f", and {len(named) - _LISTED} more" if len(named) > _LISTED else ""
    lines = [f"dropped {len(gone)} {what}: " + ", ".join(named[:_LISTED]) + more]
    return dropped, lines


def for_mjx(m: mujoco.MjModel, path: str | Path, adjust: bool = True,
            drop: bool = False, costly: bool = False) -> tuple[mujoco.MjModel, list[str]]:
    """The model both engines step and the adjustments made: :func:`drop_unsupported` when
    ``drop``, :func:`drop_costly` when ``costly``, then :func:`harmless` when ``adjust``."""
    chosen = [(find, what) for wanted, find, what in ((drop, unsupported_pairs, _UNSUPPORTED),
                                                       (costly, costly_pairs, _COSTLY)) if wanted]
    m, lines = drop_pairs(m, path, [p for find, _ in chosen for p in find(m)], " and ".join(w for _, w in chosen))
    if adjust:
        m, more = harmless(m)
        lines += more
    return m, lines
