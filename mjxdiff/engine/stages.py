"""An engine's ``forward`` read back on the host, for the drill-down: the stage fields by their
MjData names, the full mass matrix and the active contacts by geom pair, in one form whatever
the engine (:meth:`mjxdiff.engine.trajectory.Engine.forward`)."""

from __future__ import annotations

import dataclasses
from typing import Any

import mujoco
import numpy as np

from mjxdiff.compat import data_impl, full_inertia

__all__ = ["PARAMETERS", "Contacts", "Forward", "contact_gap", "contacts_c", "contacts_mjx", "contacts_mjx_warp",
           "frame", "read"]


Contacts = dict[tuple[int, ...], list[tuple[float, ...]]]


def frame(m: mujoco.MjModel, nine: np.ndarray, friction: np.ndarray, geom: np.ndarray) -> tuple[float, ...]:
    """The part of a contact frame (9 numbers, rows normal and two tangents) that shapes the
    constraint, made comparable between engines: the normal, pointing from the lower geom id to
    the higher; the tangents, each up to its sign (a friction pyramid is the same with either),
    where friction is directional (a pyramidal cone turns with them, and so does anisotropic
    friction), else zeros."""
    rows = np.asarray(nine, float).reshape(3, 3).copy()
    if geom[0] > geom[1]:
        rows[0] = -rows[0]
    directional = m.opt.cone == mujoco.mjtCone.mjCONE_PYRAMIDAL or friction[0] != friction[1]
    if not directional:
        rows[1:] = 0.0
    for t in rows[1:]:
        t *= np.sign(t[np.abs(t).argmax()]) or 1.0
    return tuple(map(float, rows.ravel()))


#: The contact parameters a contact tuple ends with, after its geometry, friction and frame:
#: what the constraint is built from (field of C's ``mjContact``, how many numbers).
PARAMETERS = (("solref", 2), ("solreffriction", 2), ("solimp", 5), ("includemargin", 1), ("dim", 1))


def _tuple(m: mujoco.MjModel, dist, pos, friction, frame9, geom, params) -> tuple[float, ...]:
    """One contact as the drill-down compares it (:func:`contacts_c`)."""
    return (float(dist), *map(float, pos), float(friction[0]), float(friction[1]), *frame(m, frame9, friction, geom),
            *(float(x) for p in params for x in np.ravel(p)))


def contacts_c(m: mujoco.MjModel, d: mujoco.MjData) -> Contacts:
    """Contacts by geom pair, the ``d.ncon`` of them (a gap's inactive ones too): (dist, pos x, y, z,
    friction[0], friction[1], frame (9,), :func:`frame`, then the :data:`PARAMETERS`) each. A flex
    side of a contact (geom -1) is keyed ``-1 - flex id``."""
    out: Contacts = {}
    for c in d.contact[:d.ncon]:
        # geom1/geom2 are not filled by mujoco_warp.get_data_into
        key = tuple(sorted(int(g) if g >= 0 else -1 - int(f) for g, f in zip(c.geom, c.flex)))
        out.setdefault(key, []).append(_tuple(m, c.dist, c.pos, c.friction, c.frame, c.geom,
                                              [getattr(c, name) for name, _ in PARAMETERS]))
    return out


def contact_gap(m: Any, geom: Any, xp: Any = np) -> Any:
    """(C,) the gap, m, that C gives each of C contacts (``engine_collision_driver.c``): an explicit
    pair's ``pair_gap``, else the larger ``geom_gap`` of its two geoms.

    C keeps a contact whose ``dist`` lies in ``[includemargin, includemargin + gap)`` in ``d.contact``
    (and ``d.ncon``) with ``exclude = 1`` and no constraint; MJX drops it. Counting MJX's contacts
    with ``dist < includemargin + gap`` counts what ``d.ncon`` counts.

    Args:
      m: a C ``MjModel`` or an MJX ``Model`` (``geom_gap``, ``pair_geom1``, ``pair_geom2``,
        ``pair_gap``; the pair ids are NumPy in both).
      geom: (C, 2) int geom ids of each contact.
      xp: ``numpy``, or ``jax.numpy`` inside a trace.
    """
    gap = xp.maximum(m.geom_gap[geom[:, 0]], m.geom_gap[geom[:, 1]])
    p1, p2 = np.asarray(m.pair_geom1), np.asarray(m.pair_geom2)
    if p1.size == 0:
        return gap
    a, b = geom[:, 0, None], geom[:, 1, None]
    match = ((a == p1) & (b == p2)) | ((a == p2) & (b == p1))
    return xp.where(match.any(axis=1), m.pair_gap[xp.argmax(match, axis=1)], gap)


def contacts_mjx(m: mujoco.MjModel, dx: Any) -> Contacts:
    """:func:`contacts_c` of MJX's data: its contacts closer than C's margin (``includemargin +``
    :func:`contact_gap`), the ones ``d.contact[:d.ncon]`` holds."""
    c = data_impl(dx).contact  # MJX's contacts
    dist, margin, geom = np.asarray(c.dist), np.asarray(c.includemargin), np.asarray(c.geom)
    keep = np.flatnonzero(dist < margin + contact_gap(m, geom))
    return _collect(m, {f: np.asarray(getattr(c, f)) for f in _READ}, keep)


#: The contact fields :func:`_collect` reads.
_READ = ("dist", "geom", "pos", "friction", "frame") + tuple(name for name, _ in PARAMETERS)


def _collect(m: mujoco.MjModel, fields: dict[str, np.ndarray], rows: Any) -> Contacts:
    """:func:`contacts_c`'s form of the contacts ``rows`` of arrays ``fields`` (by ``mjContact`` name)."""
    out: Contacts = {}
    for i in rows:
        geom = fields["geom"][i]
        key = tuple(sorted(int(g) for g in geom))
        out.setdefault(key, []).append(_tuple(m, fields["dist"][i], fields["pos"][i], fields["friction"][i],
                                              fields["frame"][i], geom, [fields[name][i] for name, _ in PARAMETERS]))
    return out


def contacts_mjx_warp(m: mujoco.MjModel, dx: Any) -> Contacts:
    """:func:`contacts_c` of MJX's warp implementation's data (one world): its ``nacon`` active
    contacts read from its own buffers (``contact__geom``, ...). Not through ``mjx.get_data``: in
    MJX 3.17 that returns the warp implementation's contacts with garbage geom ids (a sphere on a
    plane came back as geoms (22013, 0), geom1 -2004796448) while the buffers hold C's."""
    impl = data_impl(dx)
    n = int(np.asarray(impl.nacon).ravel()[0])
    return _collect(m, {f: np.asarray(getattr(impl, f"contact__{f}"))[:n] for f in _READ}, range(n))


@dataclasses.dataclass(frozen=True)
class Forward:
    """One engine's forward from one state: ``values`` (field name -> flat array, MjData's
    names), ``qM`` (nv, nv) the full mass matrix, ``contacts`` by geom pair (:func:`contacts_c`)."""

    values: dict[str, np.ndarray]
    qM: np.ndarray
    contacts: Contacts


def read(m: mujoco.MjModel, d: Any, fields: tuple[str, ...]) -> Forward:
    """The :class:`Forward` of an ``MjData`` ``d`` after ``mj_forward`` (or an engine's data read
    back into one)."""
    return Forward({f: np.asarray(getattr(d, f)).ravel() for f in fields}, full_inertia(m, d), contacts_c(m, d))
