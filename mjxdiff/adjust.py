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
"""

from __future__ import annotations

import copy
from pathlib import Path

import mujoco
import numpy as np

__all__ = ["HARMLESS_ENABLE_FLAGS", "for_mjx", "harmless", "unsupported_pairs", "drop_unsupported"]

#: Enable flags MJX refuses and C's compared quantities do not depend on, with the label reported.
HARMLESS_ENABLE_FLAGS: dict[int, str] = {
    int(mujoco.mjtEnableBit.mjENBL_ENERGY): "energy flag",
    int(mujoco.mjtEnableBit.mjENBL_FWDINV): "fwdinv flag",
}

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
        if not collision_driver.has_collision_fn(t1, t2):
            out.append((int(g1), int(g2), int(ip), "no MJX collision function"))
        elif no_margin & {t1, t2}:
            margin = m.pair_margin[ip] if ip != -1 else m.geom_margin[g1] + m.geom_margin[g2]
            if np.any(margin):
                out.append((int(g1), int(g2), int(ip), "margin on a mesh or height field"))
    return out


def _candidates(m: mujoco.MjModel) -> set[tuple[int, int]]:
    from mujoco.mjx._src import collision_driver

    return {tuple(sorted((int(g1), int(g2)))) for g1, g2, _ in collision_driver.geom_pairs(m)}


def drop_unsupported(m: mujoco.MjModel, path: str | Path) -> tuple[mujoco.MjModel, list[str]]:
    """``m`` compiled again from ``path`` without the pairs of :func:`unsupported_pairs`, and what was dropped.

    Explicit ``<pair>`` elements are deleted; a pair found by contype/conaffinity
    is removed by an ``<exclude>`` of its two bodies, which also removes every
    other pair between them (reported too). Returns ``m`` unchanged when nothing
    is unsupported; otherwise the model compiled from ``path``, so apply
    :func:`harmless` after this (:func:`for_mjx` does).
    """
    bad = unsupported_pairs(m)
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
        raise ValueError(f"{Path(path).name}: recompiling without the unsupported pairs changed its geoms")
    reasons = {tuple(sorted((g1, g2))): why for g1, g2, _, why in bad}
    gone = sorted(_candidates(m) - _candidates(dropped))
    lines = [f"dropped {len(gone)} geom pair(s) MJX cannot collide (--drop-unsupported): "
             + ", ".join(f"{_geom(m, a)} / {_geom(m, b)} ({reasons.get((a, b), 'same bodies as an unsupported pair')})"
                         for a, b in gone)]
    return dropped, lines


def for_mjx(m: mujoco.MjModel, path: str | Path, adjust: bool = True,
            drop: bool = False) -> tuple[mujoco.MjModel, list[str]]:
    """The model both engines step and the adjustments made: :func:`drop_unsupported` when
    ``drop``, then :func:`harmless` when ``adjust``."""
    lines: list[str] = []
    if drop:
        m, lines = drop_unsupported(m, path)
    if adjust:
        m, more = harmless(m)
        lines += more
    return m, lines
