"""MJX's regularized segment solves, written out in numpy, and whether a capsule contact's
difference from C is theirs alone.

MJX 3.17 collides a sphere or a capsule with a capsule through closest points on segments
(``mjx/_src/math.py``), and adds ``eps = 1e-6`` to each solve's denominator:

- point to segment ``a b``: ``t = (p - a) . (b - a) / (|b - a|^2 + eps)``, clipped to [0, 1];
- segment to segment (unit directions ``u``, ``v``, mid-points ``a``, ``b``, ``w = a - b``):
  ``t_a = (-u.w + (u.v) v.w) / (1 - (u.v)^2 + eps)``, ``t_b = v.w + t_a u.v``, each clipped to its
  half-length, then the better of re-projecting either clipped point onto the other segment.

C 4.0 solves the same problems exactly, so both engines' contact points and normals part by
about ``eps / (1 - (u.v)^2)`` (relative), more for short segments and near-parallel capsules.
With a deep, stiff contact that is enough to move one step's ``qacc`` beyond the chaos
envelope at step 0. :func:`explains` tells that difference (the formulas here with ``eps`` =
1e-6 give MJX's contact and with ``eps`` = 0 C's) from a collider that computes something else.
"""

from __future__ import annotations

import numpy as np

__all__ = ["EPS", "TOLERANCE", "contact", "explains", "regularized"]

#: What MJX 3.17 adds to the denominator of its segment solves.
EPS = 1e-6
#: How closely (m, and unit normal) the formulas must reproduce each engine's contact.
TOLERANCE = 1e-9

_SPHERE, _CAPSULE = 2, 3  # mjtGeom


def regularized(types: tuple[int, int]) -> bool:
    """Whether MJX collides geoms of these types (``mjtGeom`` values, either order) by a
    regularized segment solve: sphere-capsule or capsule-capsule."""
    return tuple(sorted(int(t) for t in types)) in {(_SPHERE, _CAPSULE), (_CAPSULE, _CAPSULE)}


def _point_on_segment(a: np.ndarray, b: np.ndarray, p: np.ndarray, eps: float) -> np.ndarray:
    ab = b - a
    t = np.dot(p - a, ab) / (np.dot(ab, ab) + eps)
    return a + np.clip(t, 0.0, 1.0) * ab


def _segment_points(a0, a1, b0, b1, eps: float) -> tuple[np.ndarray, np.ndarray]:
    """Closest points of segments ``a0 a1`` and ``b0 b1`` as MJX's
    ``closest_segment_to_segment_points`` computes them, with ``eps`` in its denominators."""
    len_a, len_b = np.linalg.norm(a1 - a0), np.linalg.norm(b1 - b0)
    u, v = (a1 - a0) / len_a, (b1 - b0) / len_b
    a_mid, b_mid = a0 + u * len_a / 2, b0 + v * len_b / 2
    w = a_mid - b_mid
    uv, uw, vw = u @ v, u @ w, v @ w
    t_a = (-uw + uv * vw) / (1 - uv * uv + eps)
    t_b = vw + t_a * uv
    best_a = a_mid + u * np.clip(t_a, -len_a / 2, len_a / 2)
    best_b = b_mid + v * np.clip(t_b, -len_b / 2, len_b / 2)
    new_a, new_b = _point_on_segment(a0, a1, best_b, eps), _point_on_segment(b0, b1, best_a, eps)
    if np.linalg.norm(best_b - new_a) < np.linalg.norm(best_a - new_b):
        return new_a, best_b
    return best_a, new_b


def _spheres(p1: np.ndarray, r1: float, p2: np.ndarray, r2: float) -> tuple[float, np.ndarray, np.ndarray]:
    """(dist, pos, normal) of spheres at ``p1``, ``p2``, the normal from the first to the second."""
    gap = np.linalg.norm(p2 - p1)
    n = (p2 - p1) / gap if gap > 0 else np.array([1.0, 0.0, 0.0])
    dist = gap - (r1 + r2)
    return float(dist), p1 + n * (r1 + dist / 2), n


def contact(m, d, g1: int, g2: int, eps: float) -> tuple[float, np.ndarray, np.ndarray]:
    """(dist (m), pos (3,), normal (3,), from ``g1`` to ``g2``) of a sphere-capsule or
    capsule-capsule pair at C's geom poses in ``d``, by MJX's formulas with ``eps``."""

    def segment(g):
        half = d.geom_xmat[g].reshape(3, 3)[:, 2] * m.geom_size[g, 1]
        return d.geom_xpos[g] - half, d.geom_xpos[g] + half

    r1, r2 = m.geom_size[g1, 0], m.geom_size[g2, 0]
    if m.geom_type[g1] == _SPHERE:
        return _spheres(d.geom_xpos[g1], r1, _point_on_segment(*segment(g2), d.geom_xpos[g1], eps), r2)
    p1, p2 = _segment_points(*segment(g1), *segment(g2), eps)
    return _spheres(p1, r1, p2, r2)


def _close(got: tuple[float, np.ndarray, np.ndarray], want: tuple[float, np.ndarray, np.ndarray]) -> bool:
    return all(np.abs(np.subtract(x, y)).max() <= TOLERANCE for x, y in zip(got, want))


def explains(m, d, c_contact, mjx_contact: tuple[float, np.ndarray, np.ndarray]) -> bool:
    """Whether a sphere-capsule or capsule-capsule contact's difference between C
    (``c_contact``, an ``MjContact`` of ``d``) and MJX (``mjx_contact``: dist, pos, normal of
    the same geoms in the same order) is the regularization's alone: MJX's is the formulas
    with :data:`EPS`, C's the same with 0, each within :data:`TOLERANCE`."""
    g1, g2 = int(c_contact.geom1), int(c_contact.geom2)
    if not regularized((m.geom_type[g1], m.geom_type[g2])):
        return False
    c = (float(c_contact.dist), np.asarray(c_contact.pos), np.asarray(c_contact.frame[:3]))
    return _close(c, contact(m, d, g1, g2, 0.0)) and _close(mjx_contact, contact(m, d, g1, g2, EPS))
