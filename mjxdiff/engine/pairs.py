"""Contacts by geom pair, one step at a time, in two 32-bit numbers: every engine records, per
step, the sums over its *firm* contacts of two hashes of the contact's geom pair (order-insensitive,
``(min, max)``, as MuJoCo's parity method keys them). Two engines with the same count of firm
contacts in every pair have the same sums; a pair touched in one engine and another pair in the
other differ in them however many contacts each has, and :func:`decode` names the pairs from
the difference alone.

A contact is firm when C counts it (``dist < includemargin + gap``) and its ``dist`` is more than
:data:`GRAZING` from both thresholds, ``includemargin`` (where its constraint starts) and
``includemargin + gap`` (where C keeps it at all). A grazing contact, the parity method's
``|dist - includemargin| <= 1e-5``, may fall on either side of its threshold under a rounding
difference (and MJX counts ``dist < margin`` strictly where C keeps touching contacts): it is
left out on both sides, so a difference in it alone is ambiguous, not a mismatch.

The hashes are MurmurHash3's finaliser of the pair's keys, with two seeds; uint32 sums wrap
modulo 2**32 in NumPy and XLA alike, so an engine inside a trace (``xp = jax.numpy``) and one on the host
(``xp = numpy``) agree bit for bit.
"""

from __future__ import annotations

from typing import Any

import mujoco
import numpy as np

from mjxdiff.engine.stages import contact_gap

__all__ = ["GRAZING", "decode", "describe_pairs", "firm", "gaps", "hashes", "host_sums", "keys", "mismatch", "of_data",
           "sums"]

#: m: a contact whose ``dist`` lies this close to ``includemargin`` (or ``includemargin + gap``)
#: is grazing: counted by neither engine's pair sums (MuJoCo's parity method's ``dist_tolerance``).
GRAZING = 1e-5

_SEEDS = (0x243F6A88, 0x85A308D3)


def _mix(x: Any, xp: Any) -> Any:
    """MurmurHash3's 32-bit finaliser of uint32 ``x``, elementwise."""
    u = xp.uint32
    x = x ^ (x >> u(16))
    x = x * u(0x85EBCA6B)
    x = x ^ (x >> u(13))
    x = x * u(0xC2B2AE35)
    return x ^ (x >> u(16))


def keys(geom: Any, flex: Any | None, xp: Any = np) -> Any:
    """(C, 2) int side keys of C contacts: the geom id, or ``-1 - flex id`` on a flex side
    (``geom`` -1), as :func:`mjxdiff.engine.stages.contacts_c` keys them."""
    if flex is None or flex.shape != geom.shape:  # MuJoCo Warp leaves flex (0, 2) in a model without flexes
        return geom
    return xp.where(geom >= 0, geom, -1 - flex)


def hashes(key: Any, xp: Any = np) -> Any:
    """(C, 2) uint32: the two hashes of each contact's unordered pair of side keys ``key`` (C, 2)."""
    lo = xp.minimum(key[:, 0], key[:, 1]).astype(xp.uint32)  # a flex side's negative key wraps: still one key
    hi = xp.maximum(key[:, 0], key[:, 1]).astype(xp.uint32)
    return xp.stack([_mix(_mix(lo ^ xp.uint32(s), xp) + hi, xp) for s in _SEEDS], axis=-1)


def firm(dist: Any, includemargin: Any, gap: Any, xp: Any = np) -> Any:
    """(C,) bool: the contacts C counts (``dist < includemargin + gap``) that are not grazing."""
    top = includemargin + gap
    return (dist < top) & (xp.abs(dist - includemargin) > GRAZING) & (xp.abs(dist - top) > GRAZING)


def gaps(m: Any, key: Any, xp: Any = np) -> Any:
    """(C,) the gap of each contact by its side keys ``key`` (C, 2): :func:`mjxdiff.engine.stages.contact_gap`'s
    for two geoms, 0 with a flex side. ``m``: a C ``MjModel`` or an MJX ``Model``."""
    return xp.where(key.min(axis=1) >= 0, contact_gap(m, xp.maximum(key, 0), xp), 0.0)


def sums(m: Any, key: Any, dist: Any, includemargin: Any, valid: Any = True, xp: Any = np) -> Any:
    """(2,) uint32 pair sums of C contacts (``valid`` ones): (C, 2) side keys, (C,) ``dist`` and
    ``includemargin``; inside a trace with ``xp = jax.numpy``."""
    ok = valid & firm(dist, includemargin, gaps(m, key, xp), xp)
    return xp.sum(xp.where(ok[:, None], hashes(key, xp), xp.uint32(0)), axis=0, dtype=xp.uint32)


def host_sums(m: mujoco.MjModel, key: np.ndarray, dist: np.ndarray, includemargin: np.ndarray,
              world: np.ndarray, nworld: int) -> np.ndarray:
    """(nworld, 2) uint32 pair sums of the C contacts of ``nworld`` worlds, on the host: (C, 2)
    side keys, (C,) ``dist``, ``includemargin`` and world index."""
    out = np.zeros((nworld, 2), np.uint32)
    if len(dist):
        ok = firm(dist, includemargin, gaps(m, key))
        np.add.at(out, world[ok], hashes(np.asarray(key)[ok]))
    return out


def mismatch(a: Any, b: Any) -> np.ndarray:
    """(...,) bool: where two (..., 2) pair-sum records differ (some pair's firm count differs)."""
    return np.any(np.asarray(a) != np.asarray(b), axis=-1)


def _candidates(m: mujoco.MjModel) -> tuple[np.ndarray, np.ndarray]:
    """Every unordered pair of side keys of ``m`` (geoms and flexes): (P, 2) keys, (P, 2) hashes."""
    sides = np.arange(-m.nflex, m.ngeom)
    i, j = np.triu_indices(len(sides))
    key = np.stack([sides[i], sides[j]], -1)
    return key, hashes(key)


def _pair(row: np.ndarray) -> tuple[int, int]:
    return int(row[0]), int(row[1])


def decode(m: mujoco.MjModel, delta: np.ndarray) -> list[tuple[tuple[int, int], int]]:
    """The pair counts behind a difference of two engines' sums ``delta`` = a - b (2,) uint32:
    [(pair of side keys, a's count - b's count)], when one pair differs by up to 4 contacts or
    two pairs by one each (a contact in one pair in ``a``, in another in ``b``); [] when the
    difference is none of these (checked on both hashes)."""
    delta = np.asarray(delta, np.uint32)
    key, h = _candidates(m)
    with np.errstate(over="ignore"):
        for k in (1, -1, 2, -2, 3, -3, 4, -4):
            hit = np.flatnonzero(np.all(h * np.uint32(k % (1 << 32)) == delta, axis=-1))
            if len(hit):
                return [(_pair(key[hit[0]]), k)]
        # delta = h[p] - h[q], so h[p] = delta + h[q]: looked up among the sorted first hashes
        order = np.argsort(h[:, 0])
        first = h[order, 0]
        target = h[:, 0] + delta[0]
        at = np.minimum(np.searchsorted(first, target), len(first) - 1)
        for q in np.flatnonzero(first[at] == target):
            p = order[at[q]]
            if p != q and h[p, 1] - h[q, 1] == delta[1]:
                return [(_pair(key[p]), 1), (_pair(key[q]), -1)]
    return []


def _side_name(m: mujoco.MjModel, k: int) -> str:
    if k < 0:
        name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_FLEX, -1 - k)
        return f"flex {name or -1 - k}"
    return mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, k) or f"geom {k}"


def describe_pairs(m: mujoco.MjModel, decoded: list[tuple[tuple[int, int], int]], a: str = "MJX",
                   b: str = "C") -> str:
    """The pairs :func:`decode` found, in words: ``pair 'ball'/'floor' (1 more in MJX)``."""
    if not decoded:
        return "geom pairs (more than two differ)"
    parts = []
    for (g1, g2), k in decoded:
        more = a if k > 0 else b
        parts.append(f"'{_side_name(m, g1)}'/'{_side_name(m, g2)}' ({abs(k)} more in {more})")
    return "pair " + ", ".join(parts)


def of_data(m: mujoco.MjModel, d: mujoco.MjData) -> np.ndarray:
    """(2,) uint32 pair sums of the contacts C's ``d`` holds (after a forward pass)."""
    n, c = d.ncon, d.contact
    return host_sums(m, keys(c.geom[:n], c.flex[:n]), c.dist[:n], c.includemargin[:n], np.zeros(n, int), 1)[0]
