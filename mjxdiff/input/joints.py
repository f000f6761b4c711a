"""Walks over ``qpos`` by joint type, and the quaternion arithmetic they need, in one place.

A joint's ``qpos`` splits into parts that move alike (:func:`parts`): a free joint into a
translation (3 numbers, 3 dofs) and a rotation (a unit quaternion: 4 numbers, 3 dofs), a ball
joint into a rotation, a hinge or slide into one scalar. Noise, limits, integration and
differences are per part. Quaternions are (w, x, y, z); NumPy arrays give NumPy, JAX arrays
(traced ones too) give JAX. Needs no MuJoCo import: ``m`` is any object with MuJoCo's joint
fields (``MjModel``, an MJX ``Model``).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Literal

import numpy as np

__all__ = ["DOF_WIDTH", "QPOS_WIDTH", "Part", "active_limits", "difference", "integrate", "parts", "quat_mul",
           "rotvec_quat"]

FREE, BALL, SLIDE, HINGE = 0, 1, 2, 3  # mjtJoint
_LIMIT_JOINT = 3  # mjtConstraint.mjCNSTR_LIMIT_JOINT
#: qpos and qvel widths of a joint, by mjtJoint.
QPOS_WIDTH = {FREE: 7, BALL: 4, SLIDE: 1, HINGE: 1}
DOF_WIDTH = {FREE: 6, BALL: 3, SLIDE: 1, HINGE: 1}


@dataclasses.dataclass(frozen=True)
class Part:
    """One part of a joint's ``qpos``: ``qpos[qpos_adr:qpos_adr + nq]``, moving along
    ``qvel[dof_adr:dof_adr + nv]``."""

    joint: int
    kind: Literal["translation", "rotation", "scalar"]
    qpos_adr: int
    dof_adr: int

    @property
    def nq(self) -> int:
        return {"translation": 3, "rotation": 4, "scalar": 1}[self.kind]

    @property
    def nv(self) -> int:
        return 1 if self.kind == "scalar" else 3

    @property
    def qpos(self) -> slice:
        return slice(self.qpos_adr, self.qpos_adr + self.nq)

    @property
    def dof(self) -> slice:
        return slice(self.dof_adr, self.dof_adr + self.nv)


def parts(m: Any) -> tuple[Part, ...]:
    """Every joint's parts, in joint order (a free joint's translation before its rotation)."""
    out = []
    for j in range(int(m.njnt)):
        jtype, q, v = int(m.jnt_type[j]), int(m.jnt_qposadr[j]), int(m.jnt_dofadr[j])
        if jtype == FREE:
            out += [Part(j, "translation", q, v), Part(j, "rotation", q + 3, v + 3)]
        elif jtype == BALL:
            out.append(Part(j, "rotation", q, v))
        else:
            out.append(Part(j, "scalar", q, v))
    return tuple(out)


def _xp(*arrays) -> Any:
    """NumPy for NumPy arrays, else jax.numpy."""
    if all(isinstance(a, np.ndarray) for a in arrays):
        return np
    import jax.numpy as jnp

    return jnp


def quat_mul(a, b):
    """Hamilton product of (w, x, y, z) quaternions, ``(..., 4) x (..., 4) -> (..., 4)``."""
    xp = _xp(a, b)
    w1, x1, y1, z1 = xp.moveaxis(xp.asarray(a), -1, 0)
    w2, x2, y2, z2 = xp.moveaxis(xp.asarray(b), -1, 0)
    return xp.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
                     w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
                     w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], axis=-1)


def rotvec_quat(rotvec: np.ndarray) -> np.ndarray:
    """Unit quaternions (w, x, y, z) of rotation vectors (rad), ``(..., 3) -> (..., 4)``."""
    angle = np.linalg.norm(rotvec, axis=-1, keepdims=True)
    axis = np.divide(rotvec, angle, out=np.zeros_like(rotvec), where=angle > 0)
    return np.concatenate([np.cos(angle / 2), axis * np.sin(angle / 2)], axis=-1)


def integrate(joint_parts: tuple[Part, ...], qpos, dq):
    """(nq,) ``qpos`` moved by the tangent vector ``dq`` (nv,), in JAX, over a model's
    :func:`parts`; exact to first order at ``dq = 0`` (all that a Jacobian there needs): a
    rotation by w is normalise(q * (1, w / 2))."""
    import jax.numpy as jnp

    out = qpos
    for p in joint_parts:
        if p.kind == "rotation":
            q = quat_mul(qpos[p.qpos], jnp.concatenate([jnp.ones(1), dq[p.dof] / 2]))
            out = out.at[p.qpos].set(q / jnp.linalg.norm(q))
        else:
            out = out.at[p.qpos].add(dq[p.dof])
    return out


def difference(joint_parts: tuple[Part, ...], nv: int, qpos, ref):
    """The tangent vector (nv,) from ``ref`` to ``qpos`` (nq,), in JAX, over a model's
    :func:`parts`; exact to first order where they coincide: a rotation's is 2 x the vector part
    of ref^-1 * q, signed by its scalar part."""
    import jax.numpy as jnp

    out = jnp.zeros(nv, qpos.dtype)
    for p in joint_parts:
        if p.kind == "rotation":
            rel = quat_mul(ref[p.qpos] * jnp.array([1.0, -1.0, -1.0, -1.0]), qpos[p.qpos])
            out = out.at[p.dof].set(2 * rel[1:] * jnp.sign(rel[0]))
        else:
            out = out.at[p.dof].set(qpos[p.qpos] - ref[p.qpos])
    return out


def active_limits(m: Any, d: Any) -> list[tuple[int, str]]:
    """``(joint, side)`` of every active joint-limit row of ``d``: side ``lower`` or ``upper``
    (whichever end the joint is nearer) for hinges and slides, ``ball`` for ball joints."""
    out = []
    for row in np.flatnonzero(d.efc_type == _LIMIT_JOINT):
        j = int(d.efc_id[row])
        if m.jnt_type[j] == BALL:
            out.append((j, "ball"))
        else:
            q = d.qpos[m.jnt_qposadr[j]]
            out.append((j, "lower" if q - m.jnt_range[j, 0] < m.jnt_range[j, 1] - q else "upper"))
    return out
