"""Walks over qpos by joint type: parts, quaternions, integrate and difference."""

import jax.numpy as jnp
import mujoco
import numpy as np

from mjxdiff.input import joints
from mjxdiff.compat import enable_x64

MODEL = """<mujoco><worldbody>
  <body><freejoint/><geom size=".1"/>
    <body><joint type="ball"/><geom size=".1"/>
      <body><joint type="hinge"/><joint type="slide"/><geom size=".1"/></body>
    </body>
  </body></worldbody></mujoco>"""


def test_parts_split_each_joint_as_it_moves():
    m = mujoco.MjModel.from_xml_string(MODEL)
    got = [(p.joint, p.kind, p.qpos, p.dof) for p in joints.parts(m)]
    assert got == [(0, "translation", slice(0, 3), slice(0, 3)), (0, "rotation", slice(3, 7), slice(3, 6)),
                   (1, "rotation", slice(7, 11), slice(6, 9)), (2, "scalar", slice(11, 12), slice(9, 10)),
                   (3, "scalar", slice(12, 13), slice(10, 11))]
    assert sum(p.nq for p in joints.parts(m)) == m.nq and sum(p.nv for p in joints.parts(m)) == m.nv


def test_the_quaternion_product_is_the_same_in_numpy_and_jax():
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(5, 4)), rng.normal(size=(5, 4))
    with enable_x64(True):
        assert np.allclose(joints.quat_mul(a, b), np.asarray(joints.quat_mul(jnp.asarray(a), jnp.asarray(b))),
                           rtol=0, atol=1e-15)
    q = joints.rotvec_quat(np.array([0.0, 0.0, np.pi]))  # half a turn about z
    assert np.allclose(joints.quat_mul(q, q), [-1, 0, 0, 0])


def test_difference_undoes_integrate_to_first_order():
    """difference(integrate(q, dq), q) = dq + O(|dq|^2) for every part, rotations included."""
    m = mujoco.MjModel.from_xml_string(MODEL)
    parts = joints.parts(m)
    rng = np.random.default_rng(1)
    with enable_x64(True):
        q0 = jnp.asarray(m.qpos0).at[3:7].set(joints.rotvec_quat(rng.normal(size=3)))
        for size in (1e-3, 1e-5):
            dq = jnp.asarray(rng.normal(size=m.nv) * size)
            back = joints.difference(parts, m.nv, joints.integrate(parts, q0, dq), q0)
            assert np.abs(np.asarray(back - dq)).max() < 10 * size**2
