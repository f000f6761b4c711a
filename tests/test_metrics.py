"""Tests for mjxdiff.metrics: hand-computed values, jit/vmap, float32/float64."""

import doctest
import math
import subprocess
import sys

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

import mjxdiff.metrics as metrics  # noqa: E402
from mjxdiff.metrics import (  # noqa: E402
    BehaviourStats,
    ErrorGrowth,
    QposLayout,
    behaviour_stats,
    contact_mismatch,
    energy_drift,
    error_growth,
    first_exceedance,
    max_over_time,
    qpos_error,
    qpos_error_joint_ids,
    qpos_layout,
    quat_angle,
    qvel_error,
    rangefinder_hit_mismatch,
    sensor_error,
    tree_max_abs_diff,
)

C45 = math.cos(math.pi / 4)
S45 = math.sin(math.pi / 4)
IDENTITY = [1.0, 0.0, 0.0, 0.0]


def _quat_z(angle):
  """Quaternion (w, x, y, z) of a rotation by `angle` rad about z."""
  return [math.cos(angle / 2), 0.0, 0.0, math.sin(angle / 2)]


# A free joint (qpos 0..6: xyz, quat) followed by a hinge (qpos 7); nq = 8.
FREE_HINGE = QposLayout(
    scalar_idx=[0, 1, 2, 7],
    scalar_jnt=[0, 0, 0, 1],
    quat_idx=[[3, 4, 5, 6]],
    quat_jnt=[0],
)

FOUR_JOINTS_XML = """
<mujoco>
  <worldbody>
    <body name="root" pos="0 0 1">
      <freejoint name="free"/>
      <geom size=".1"/>
      <body name="b1" pos="0 0 -.3">
        <joint name="ball" type="ball"/>
        <geom size=".05"/>
        <body name="b2" pos="0 0 -.3">
          <joint name="slide" type="slide" axis="1 0 0"/>
          <geom size=".05"/>
          <body name="b3" pos="0 0 -.3">
            <joint name="hinge" type="hinge" axis="0 1 0"/>
            <geom size=".05"/>
          </body>
        </body>
      </body>
    </body>
  </worldbody>
</mujoco>
"""


# ---------------------------------------------------------------------------
# Module hygiene
# ---------------------------------------------------------------------------


def test_all_is_complete_and_importable():
  for name in metrics.__all__:
    assert hasattr(metrics, name), name
  assert "qpos_error" in metrics.__all__
  assert "tree_max_abs_diff" in metrics.__all__


def test_module_itself_does_not_import_mujoco():
  # Load metrics.py on its own (bypassing the package __init__, which imports
  # the engines) and check that only jax/numpy/stdlib come in.
  code = (
      "import importlib.util, sys; "
      f"spec = importlib.util.spec_from_file_location('m', {metrics.__file__!r}); "
      "mod = importlib.util.module_from_spec(spec); "
      "spec.loader.exec_module(mod); "
      "bad = [m for m in sys.modules if m.split('.')[0] in "
      "('mujoco', 'mjxdiff', 'brax')]; "
      "assert not bad, bad; "
      "assert callable(mod.qpos_error); print('ok')"
  )
  out = subprocess.run([sys.executable, "-c", code], capture_output=True,
                       text=True, check=False)
  assert out.returncode == 0, out.stderr
  assert out.stdout.strip() == "ok"


def test_docstring_examples_run():
  result = doctest.testmod(metrics, optionflags=doctest.ELLIPSIS)
  assert result.attempted > 10
  assert result.failed == 0


def test_the_behaviour_statistics_are_exported_and_their_examples_run():
  """Defined in mjxdiff.compare.statistics and exported by metrics (imported on first use), so
  testmod(metrics) does not reach their examples."""
  from mjxdiff.compare import statistics
  for name in statistics.__all__:
    assert name in metrics.__all__ and getattr(metrics, name) is getattr(statistics, name), name
  result = doctest.testmod(statistics, optionflags=doctest.ELLIPSIS)
  assert result.attempted >= 4
  assert result.failed == 0


# ---------------------------------------------------------------------------
# quat_angle
# ---------------------------------------------------------------------------


def test_quat_angle_90deg_about_z():
  q = jnp.array([C45, 0.0, 0.0, S45])
  angle = quat_angle(q, jnp.array(IDENTITY))
  assert angle.dtype == jnp.float64
  np.testing.assert_allclose(float(angle), math.pi / 2, rtol=1e-14)


@pytest.mark.parametrize("angle", [1e-3, 0.7, 2.0, 3.0, math.pi])
def test_quat_angle_known_rotations(angle):
  got = quat_angle(jnp.array(_quat_z(angle)), jnp.array(IDENTITY))
  np.testing.assert_allclose(float(got), angle, rtol=1e-12)


def test_quat_angle_sign_invariant_exact_zero():
  q = jnp.array([0.3, -0.5, 0.7, 0.1])
  assert float(quat_angle(q, -q)) == 0.0
  assert float(quat_angle(q, q)) == 0.0
  # 90 degrees is still 90 degrees against the negated quaternion.
  q90 = jnp.array([C45, 0.0, 0.0, S45])
  np.testing.assert_allclose(float(quat_angle(q90, -jnp.array(IDENTITY))),
                             math.pi / 2, rtol=1e-14)


def test_quat_angle_tiny_angle_float64():
  angle = 1e-9
  got = float(quat_angle(jnp.array(_quat_z(angle)), jnp.array(IDENTITY)))
  assert abs(got - angle) / angle < 1e-2
  # The naive arccos form cannot resolve this at all.
  naive = 2 * math.acos(min(1.0, abs(math.cos(angle / 2))))
  assert naive == 0.0 or abs(naive - angle) / angle > 1e-2


def test_quat_angle_tiny_angle_float32():
  angle = 1e-5
  qa = jnp.array(_quat_z(angle), dtype=jnp.float32)
  qb = jnp.array(IDENTITY, dtype=jnp.float32)
  got = quat_angle(qa, qb)
  assert got.dtype == jnp.float32
  assert abs(float(got) - angle) / angle < 1e-2


def test_quat_angle_normalises_inputs():
  q = 5.0 * jnp.array([C45, 0.0, 0.0, S45])
  np.testing.assert_allclose(float(quat_angle(q, 0.1 * jnp.array(IDENTITY))),
                             math.pi / 2, rtol=1e-14)


def test_quat_angle_matches_mujoco_subquat():
  rng = np.random.default_rng(0)
  qa = rng.normal(size=(50, 4))
  qb = rng.normal(size=(50, 4))
  qa /= np.linalg.norm(qa, axis=1, keepdims=True)
  qb /= np.linalg.norm(qb, axis=1, keepdims=True)
  got = np.asarray(quat_angle(jnp.asarray(qa), jnp.asarray(qb)))
  want = np.empty(50)
  for i in range(50):
    res = np.zeros(3)
    mujoco.mju_subQuat(res, qa[i], qb[i])
    want[i] = np.linalg.norm(res)
  assert got.shape == (50,)
  np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12)
  assert np.all((got >= 0) & (got <= math.pi + 1e-12))


def test_quat_angle_batched_shapes():
  qa = jnp.tile(jnp.array([C45, 0.0, 0.0, S45]), (3, 2, 1))
  got = quat_angle(qa, jnp.array(IDENTITY))  # broadcast (3, 2, 4) vs (4,)
  assert got.shape == (3, 2)
  np.testing.assert_allclose(np.asarray(got), math.pi / 2, rtol=1e-14)


# ---------------------------------------------------------------------------
# QposLayout / qpos_layout
# ---------------------------------------------------------------------------


def test_layout_hash_eq_and_static_pytree():
  other = QposLayout([0, 1, 2, 7], [0, 0, 0, 1], [[3, 4, 5, 6]], [0])
  assert other == FREE_HINGE
  assert hash(other) == hash(FREE_HINGE)
  assert FREE_HINGE != QposLayout([0, 1, 2, 7], [0, 0, 0, 2],
                                  [[3, 4, 5, 6]], [0])
  assert jax.tree_util.tree_leaves(FREE_HINGE) == []
  assert FREE_HINGE.ncomp == 5
  assert FREE_HINGE.quat_idx.shape == (1, 4)
  with pytest.raises(ValueError):
    FREE_HINGE.scalar_idx[0] = 3  # arrays are read-only (hash stays valid)
  with pytest.raises(AttributeError):
    FREE_HINGE.scalar_idx = np.array([1])  # frozen dataclass
  with pytest.raises(ValueError):
    QposLayout([0, 1], [0], np.zeros((0, 4), int), [])


def test_qpos_layout_from_model_free_ball_slide_hinge():
  m = mujoco.MjModel.from_xml_string(FOUR_JOINTS_XML)
  assert m.nq == 13 and m.nv == 11
  lay = qpos_layout(m)
  assert lay.scalar_idx.tolist() == [0, 1, 2, 11, 12]
  assert lay.scalar_jnt.tolist() == [0, 0, 0, 2, 3]
  assert lay.quat_idx.tolist() == [[3, 4, 5, 6], [7, 8, 9, 10]]
  assert lay.quat_jnt.tolist() == [0, 1]
  assert lay.ncomp == 7
  ids = qpos_error_joint_ids(lay)
  assert isinstance(ids, np.ndarray)
  names = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, int(j))
           for j in ids]
  assert names == ["free"] * 3 + ["slide", "hinge", "free", "ball"]
  assert qpos_layout(m) == lay and hash(qpos_layout(m)) == hash(lay)


def test_qpos_layout_hinge_only_model_has_no_quats():
  m = mujoco.MjModel.from_xml_string(
      '<mujoco><worldbody><body><joint type="hinge"/><geom size=".1"/>'
      '<body><joint type="slide"/><geom size=".1"/></body></body>'
      '</worldbody></mujoco>')
  lay = qpos_layout(m)
  assert lay.scalar_idx.tolist() == [0, 1]
  assert lay.quat_idx.shape == (0, 4)
  qa = jnp.zeros((4, 2))
  qb = qa.at[:, 1].set(0.5)
  err = qpos_error(qa, qb, lay)
  assert err.shape == (4, 2)
  np.testing.assert_array_equal(np.asarray(err[:, 1]), 0.5)


def test_qpos_error_on_real_rollout():
  m = mujoco.MjModel.from_xml_string(FOUR_JOINTS_XML)
  lay = qpos_layout(m)
  d = mujoco.MjData(m)
  d.qvel[:] = 0.3
  traj = []
  for _ in range(20):
    mujoco.mj_step(m, d)
    traj.append(d.qpos.copy())
  traj = np.stack(traj)
  assert float(jnp.max(qpos_error(traj, traj, lay))) == 0.0
  # Rotate the ball joint of "b" by 0.25 rad about z at every step.
  other = traj.copy()
  for t in range(len(other)):
    q = np.zeros(4)
    mujoco.mju_mulQuat(q, other[t, 7:11], np.array(_quat_z(0.25)))
    other[t, 7:11] = q
  other[:, 12] += 1e-3
  err = np.asarray(qpos_error(traj, other, lay))
  assert err.shape == (20, 7)
  np.testing.assert_allclose(err[:, 6], 0.25, rtol=1e-9)  # ball
  np.testing.assert_allclose(err[:, 4], 1e-3, rtol=1e-9)  # hinge
  np.testing.assert_allclose(err[:, [0, 1, 2, 3, 5]], 0.0, atol=1e-15)


# ---------------------------------------------------------------------------
# qpos_error / qvel_error
# ---------------------------------------------------------------------------


def _free_hinge_pair():
  """Two (2, 8) qpos trajectories with hand-known errors."""
  qa = np.array([
      [0.0, 0.0, 1.0] + IDENTITY + [0.1],
      [1.0, 2.0, 3.0] + [C45, 0.0, 0.0, S45] + [-0.5],
  ])
  qb = np.array([
      [0.5, 0.0, 1.25] + [C45, 0.0, 0.0, S45] + [0.1],  # 90 deg about z
      [1.0, 1.0, 3.0] + [-C45, 0.0, 0.0, -S45] + [0.5],  # same rotation
  ])
  want = np.array([
      [0.5, 0.0, 0.25, 0.0, math.pi / 2],
      [0.0, 1.0, 0.0, 1.0, 0.0],
  ])
  return qa, qb, want


def test_qpos_error_free_plus_hinge_hand_values():
  qa, qb, want = _free_hinge_pair()
  err = qpos_error(jnp.asarray(qa), jnp.asarray(qb), FREE_HINGE)
  assert err.shape == (2, 5)
  assert err.dtype == jnp.float64
  np.testing.assert_allclose(np.asarray(err), want, atol=1e-14)
  assert qpos_error_joint_ids(FREE_HINGE).tolist() == [0, 0, 0, 1, 0]


def test_qpos_error_float32_keeps_dtype():
  qa, qb, want = _free_hinge_pair()
  err = qpos_error(jnp.asarray(qa, jnp.float32), jnp.asarray(qb, jnp.float32),
                   FREE_HINGE)
  assert err.dtype == jnp.float32
  np.testing.assert_allclose(np.asarray(err), want, atol=1e-6)


def test_qpos_error_rejects_layout_wider_than_qpos():
  with pytest.raises(ValueError, match="nq"):
    qpos_error(jnp.zeros((3, 7)), jnp.zeros((3, 7)), FREE_HINGE)


def test_qpos_error_under_jit_layout_as_arg_and_static():
  qa, qb, want = _free_hinge_pair()
  as_pytree = jax.jit(qpos_error)(qa, qb, FREE_HINGE)
  as_static = jax.jit(qpos_error, static_argnums=2)(qa, qb, FREE_HINGE)
  np.testing.assert_allclose(np.asarray(as_pytree), want, atol=1e-14)
  np.testing.assert_allclose(np.asarray(as_static), want, atol=1e-14)


def test_qvel_error():
  a = jnp.array([[1.0, -2.0, 0.0], [0.25, 0.0, 3.0]])
  b = jnp.array([[0.5, 1.0, 0.0], [0.0, 0.0, -1.0]])
  err = qvel_error(a, b)
  assert err.shape == (2, 3)
  np.testing.assert_array_equal(np.asarray(err),
                                [[0.5, 3.0, 0.0], [0.25, 0.0, 4.0]])
  assert bool(jnp.isnan(qvel_error(jnp.array([[jnp.nan]]),
                                   jnp.array([[0.0]]))[0, 0]))


# ---------------------------------------------------------------------------
# Sensors
# ---------------------------------------------------------------------------


def test_sensor_error_with_rangefinders():
  # columns: rf both no-hit, rf only a no-hit, rf only b no-hit, rf both hit,
  # a non-rangefinder sensor that happens to read -1 (a real value).
  mask = np.array([True, True, True, True, False])
  a = jnp.array([[-1.0, -1.0, 0.7, 2.0, -1.0],
                 [-1.0, 1.5, 0.7, 2.0, 3.0]])
  b = jnp.array([[-1.0, 3.0, -1.0, 2.5, 0.5],
                 [-1.0, 1.0, 0.2, 1.0, 3.0]])
  err = sensor_error(a, b, mask)
  assert err.shape == (2, 5)
  np.testing.assert_allclose(np.asarray(err),
                             [[0.0, 0.0, 0.0, 0.5, 1.5],
                              [0.0, 0.5, 0.5, 1.0, 0.0]], atol=1e-15)
  mism = rangefinder_hit_mismatch(a, b, mask)
  assert mism.shape == (2,)
  assert mism.tolist() == [2, 0]


def test_sensor_error_single_mismatch_counts_one():
  mask = np.array([True])
  a = jnp.array([[-1.0]])
  b = jnp.array([[4.0]])
  assert float(sensor_error(a, b, mask)[0, 0]) == 0.0
  assert int(rangefinder_hit_mismatch(a, b, mask)[0]) == 1
  # Both no-hit: zero error, no mismatch.
  assert float(sensor_error(a, a, mask)[0, 0]) == 0.0
  assert int(rangefinder_hit_mismatch(a, a, mask)[0]) == 0


def test_sensor_error_near_minus_one_is_a_hit():
  mask = np.array([True])
  a = jnp.array([[-1.0 + 1e-12]])  # not exactly -1: a (weird) hit value
  b = jnp.array([[-1.0]])
  assert int(rangefinder_hit_mismatch(a, b, mask)[0]) == 1
  assert float(sensor_error(a, b, mask)[0, 0]) == 0.0


def test_sensor_error_without_mask_and_nan_propagates():
  a = jnp.array([[1.0, jnp.nan]])
  b = jnp.array([[-1.0, 0.0]])
  err = sensor_error(a, b)
  assert float(err[0, 0]) == 2.0
  assert bool(jnp.isnan(err[0, 1]))
  err_m = sensor_error(a, b, np.array([False, True]))
  assert bool(jnp.isnan(err_m[0, 1]))


def test_sensor_functions_under_jit():
  mask = jnp.array([True, False])
  a = jnp.array([[-1.0, 2.0]])
  b = jnp.array([[5.0, 1.0]])
  err = jax.jit(sensor_error)(a, b, mask)
  np.testing.assert_array_equal(np.asarray(err), [[0.0, 1.0]])
  assert jax.jit(rangefinder_hit_mismatch)(a, b, mask).tolist() == [1]


# ---------------------------------------------------------------------------
# first_exceedance / max_over_time
# ---------------------------------------------------------------------------


def test_first_exceedance_never_and_first_index():
  err = jnp.array([0.0, 0.5, 1.0, 1.5, 0.2, 3.0])
  assert int(first_exceedance(err, 10.0)) == -1
  assert int(first_exceedance(err, 1.0)) == 3  # strictly greater
  assert int(first_exceedance(err, 0.1)) == 1
  assert int(first_exceedance(err, -1.0)) == 0


def test_first_exceedance_2d_reduces_with_max():
  err = jnp.array([[0.0, 0.1], [0.2, 0.0], [0.0, 0.9], [2.0, 0.0]])
  assert int(first_exceedance(err, 0.5)) == 2
  assert int(first_exceedance(err, 5.0)) == -1
  # per-component tolerance
  assert int(first_exceedance(err, jnp.array([0.1, 1.0]))) == 1


def test_first_exceedance_under_jit():
  f = jax.jit(first_exceedance)
  err = jnp.linspace(0.0, 1.0, 11)
  assert int(f(err, 0.45)) == 5
  assert int(f(err, 2.0)) == -1
  assert jnp.issubdtype(f(err, 2.0).dtype, jnp.integer)


def test_first_exceedance_nan_is_an_exceedance():
  """A blown-up engine is never within tolerance: the same rule as the verdict's."""
  err = jnp.array([0.0, jnp.nan, 2.0])
  assert int(first_exceedance(err, 1.0)) == 1
  assert int(first_exceedance(jnp.array([[0.0, 0.0], [0.0, jnp.inf]]), 1e300)) == 1


def test_max_over_time_plain_max_and_nan():
  assert float(max_over_time(jnp.array([[0.1, 0.7], [0.3, -2.0]]))) == 0.7
  assert bool(jnp.isnan(max_over_time(jnp.array([[0.1, jnp.nan],
                                                 [5.0, 1.0]]))))
  assert float(jax.jit(max_over_time)(jnp.arange(5.0))) == 4.0


# ---------------------------------------------------------------------------
# error_growth
# ---------------------------------------------------------------------------


def test_error_growth_recovers_exponential_rate():
  dt = 0.01
  t = np.arange(300) * dt
  err = jnp.asarray(1e-10 * np.exp(3.0 * t))
  g = error_growth(err, dt)
  assert isinstance(g, ErrorGrowth)
  assert abs(float(g.rate) - 3.0) / 3.0 < 1e-6
  np.testing.assert_allclose(float(g.doubling_time), math.log(2) / 3.0,
                             rtol=1e-6)


def test_error_growth_ignores_zeros_and_floor():
  dt = 0.002
  t = np.arange(200) * dt
  err = 1e-12 * np.exp(5.0 * t)
  err[:40] = 0.0  # identical engines for a while
  g = error_growth(jnp.asarray(err), dt)
  np.testing.assert_allclose(float(g.rate), 5.0, rtol=1e-8)
  # A round-off plateau below the floor is ignored too.
  err2 = err.copy()
  err2[:40] = 1e-16
  g2 = error_growth(jnp.asarray(err2), dt, floor=1e-14)
  np.testing.assert_allclose(float(g2.rate), 5.0, rtol=1e-8)


def test_error_growth_degenerate_and_decaying():
  g0 = error_growth(jnp.zeros(50), 0.01)
  assert float(g0.rate) == 0.0 and math.isinf(float(g0.doubling_time))
  g1 = error_growth(jnp.zeros(50).at[7].set(1e-3), 0.01)  # one usable point
  assert float(g1.rate) == 0.0
  t = np.arange(100) * 0.01
  gd = error_growth(jnp.asarray(np.exp(-2.0 * t)), 0.01)
  np.testing.assert_allclose(float(gd.rate), -2.0, rtol=1e-9)
  assert math.isinf(float(gd.doubling_time)) and float(gd.doubling_time) > 0
  gn = error_growth(jnp.array([1e-3, jnp.nan, 1e-2]), 0.01)
  assert math.isnan(float(gn.rate))


def test_error_growth_float32_and_jit():
  dt = 0.01
  t = np.arange(100) * dt
  err = jnp.asarray(1e-6 * np.exp(3.0 * t), dtype=jnp.float32)
  g = jax.jit(error_growth)(err, dt)
  assert g.rate.dtype == jnp.float32
  np.testing.assert_allclose(float(g.rate), 3.0, rtol=1e-4)


# ---------------------------------------------------------------------------
# behaviour_stats
# ---------------------------------------------------------------------------


def test_behaviour_stats_straight_line_constant_speed():
  dt = 0.02
  speed = 1.5
  direction = np.array([1.0, 2.0, 2.0]) / 3.0
  t = np.arange(51) * dt
  pos = jnp.asarray(np.array([0.3, -0.1, 1.0]) + speed * t[:, None] * direction)
  s = behaviour_stats(pos, dt)
  assert isinstance(s, BehaviourStats)
  np.testing.assert_allclose(float(s.mean_speed), speed, rtol=1e-12)
  np.testing.assert_allclose(float(s.max_speed), speed, rtol=1e-12)
  np.testing.assert_allclose(float(s.distance), speed * 50 * dt, rtol=1e-12)
  np.testing.assert_allclose(float(s.displacement), speed * 50 * dt,
                             rtol=1e-12)
  np.testing.assert_allclose(float(s.path_efficiency), 1.0, rtol=1e-12)


def test_behaviour_stats_square_loop():
  pos = jnp.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0], [0.0, 0.0]])
  s = behaviour_stats(pos, 0.1)
  assert float(s.distance) == 4.0
  assert float(s.displacement) == 0.0
  assert float(s.path_efficiency) == 0.0
  np.testing.assert_allclose(float(s.mean_speed), 10.0, rtol=1e-14)
  np.testing.assert_allclose(float(s.max_speed), 10.0, rtol=1e-14)


def test_behaviour_stats_stationary_and_variable_speed():
  s = behaviour_stats(jnp.ones((10, 3)), 0.01)
  assert float(s.distance) == 0.0
  assert float(s.path_efficiency) == 1.0
  assert float(s.mean_speed) == 0.0
  assert not any(bool(jnp.isnan(x)) for x in s)
  # steps of 1 then 3 along x, dt = 0.5 -> speeds 2 and 6.
  s2 = behaviour_stats(jnp.array([[0.0], [1.0], [4.0]]), 0.5)
  assert float(s2.mean_speed) == 4.0 and float(s2.max_speed) == 6.0
  with pytest.raises(ValueError):
    behaviour_stats(jnp.zeros((1, 3)), 0.01)


# ---------------------------------------------------------------------------
# energy_drift / contact_mismatch
# ---------------------------------------------------------------------------


def test_energy_drift_hand_values():
  # totals 2, 1.5, 2.5 -> (2.5 - 2) / max(2, 2) = 0.25
  e = jnp.array([[1.0, 1.0], [0.5, 1.0], [1.0, 1.5]])
  np.testing.assert_allclose(float(energy_drift(e)), 0.25, rtol=1e-14)
  # totals 0, 4, 2 -> |total[0]| = 0, mean |total| = 2 -> 2 / 2 = 1
  e2 = jnp.array([[0.0, 0.0], [2.0, 2.0], [1.0, 1.0]])
  np.testing.assert_allclose(float(energy_drift(e2)), 1.0, rtol=1e-14)
  # negative potential: totals -4, -3 -> (1) / max(4, 3.5) = 0.25
  e3 = jnp.array([[-5.0, 1.0], [-5.0, 2.0]])
  np.testing.assert_allclose(float(energy_drift(e3)), 0.25, rtol=1e-14)
  # conserved / all-zero energy -> exactly 0, no NaN
  assert float(energy_drift(jnp.zeros((5, 2)))) == 0.0
  assert float(energy_drift(jnp.tile(jnp.array([[3.0, 1.0]]), (4, 1)))) == 0.0


def test_contact_mismatch():
  a = jnp.array([0, 1, 4, 2, 3], dtype=jnp.int32)
  b = jnp.array([0, 2, 4, 5, 3], dtype=jnp.int32)
  np.testing.assert_allclose(float(contact_mismatch(a, b)), 2 / 5)
  np.testing.assert_allclose(float(contact_mismatch(a, b, atol=1)), 1 / 5)
  assert float(contact_mismatch(a, b, atol=3)) == 0.0
  assert float(jax.jit(contact_mismatch)(a, a)) == 0.0


# ---------------------------------------------------------------------------
# tree_max_abs_diff
# ---------------------------------------------------------------------------


def test_tree_max_abs_diff():
  ta = {"qpos": jnp.array([[1.0, 2.0], [3.0, 4.0]]),
        "nested": (jnp.array(3), jnp.array([True, False])),
        "empty": jnp.zeros((0, 3))}
  tb = {"qpos": jnp.array([[1.5, 2.0], [3.0, 1.0]]),
        "nested": (jnp.array(-1), jnp.array([True, True])),
        "empty": jnp.zeros((0, 3))}
  for f in (tree_max_abs_diff, jax.jit(tree_max_abs_diff)):
    d = f(ta, tb)
    assert jax.tree.structure(d) == jax.tree.structure(ta)
    assert float(d["qpos"]) == 3.0
    assert int(d["nested"][0]) == 4
    assert int(d["nested"][1]) == 1
    assert float(d["empty"]) == 0.0
    assert all(leaf.shape == () for leaf in jax.tree.leaves(d))
  dn = tree_max_abs_diff({"x": jnp.array([0.0, jnp.nan])},
                         {"x": jnp.array([1.0, 0.0])})
  assert bool(jnp.isnan(dn["x"]))
  with pytest.raises(ValueError):
    tree_max_abs_diff({"x": jnp.zeros(2)}, {"y": jnp.zeros(2)})


# ---------------------------------------------------------------------------
# Batching: vmap over scenarios, jit around it
# ---------------------------------------------------------------------------


def test_vmap_qpos_error_and_first_exceedance():
  rng = np.random.default_rng(1)
  n_batch, n_t = 4, 30
  qa = np.zeros((n_batch, n_t, 8))
  qa[..., 3] = 1.0  # identity orientation
  qa[..., :3] = rng.normal(size=(n_batch, n_t, 3))
  qb = qa.copy()
  # Scenario i: the hinge drifts by 0.01*(t - 5*i) once t >= 5*i; scenario 3
  # also rotates its free body by 0.5 rad about z from t = 2.
  onset = np.array([0, 5, 10, 15])
  for i in range(n_batch):
    ramp = np.clip(np.arange(n_t) - onset[i], 0, None) * 0.01
    qb[i, :, 7] += ramp
  qb[3, 2:, 3:7] = _quat_z(0.5)

  def per_scenario(a, b, layout):
    err = qpos_error(a, b, layout)
    return err, first_exceedance(err, 0.045)

  batched = jax.jit(jax.vmap(per_scenario, in_axes=(0, 0, None)))
  err, first = batched(jnp.asarray(qa), jnp.asarray(qb), FREE_HINGE)
  assert err.shape == (n_batch, n_t, 5)
  # hinge error 0.01*(t - onset) > 0.045 first at t = onset + 5
  assert first.tolist() == [5, 10, 15, 2]
  np.testing.assert_allclose(np.asarray(err[3, 2:, 4]), 0.5, rtol=1e-12)
  np.testing.assert_allclose(np.asarray(err[:3, :, 4]), 0.0, atol=1e-15)
  # Same answers scenario by scenario without vmap.
  for i in range(n_batch):
    e_i, f_i = per_scenario(qa[i], qb[i], FREE_HINGE)
    np.testing.assert_allclose(np.asarray(err[i]), np.asarray(e_i), atol=0)
    assert int(f_i) == int(first[i])


def test_vmap_reductions_and_stats():
  dt = 0.01
  t = np.arange(100) * dt
  rates = np.array([1.0, 2.0, 4.0])
  err = jnp.asarray(1e-9 * np.exp(rates[:, None] * t[None, :]))
  g = jax.jit(jax.vmap(error_growth, in_axes=(0, None)))(err, dt)
  np.testing.assert_allclose(np.asarray(g.rate), rates, rtol=1e-9)
  np.testing.assert_allclose(np.asarray(g.doubling_time), math.log(2) / rates,
                             rtol=1e-9)

  pos = jnp.stack([
      jnp.stack([jnp.arange(5.0), jnp.zeros(5)], axis=-1),  # straight, v=10
      jnp.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0], [0.0, 0.0]]),
  ])
  s = jax.jit(jax.vmap(behaviour_stats, in_axes=(0, None)))(pos, 0.1)
  np.testing.assert_allclose(np.asarray(s.path_efficiency), [1.0, 0.0])
  np.testing.assert_allclose(np.asarray(s.mean_speed), [10.0, 10.0])

  # totals (2, 2.5): 0.5 / max(2, mean 2.25); totals (2, 2): 0.
  energy = jnp.array([[[1.0, 1.0], [1.0, 1.5]], [[2.0, 0.0], [2.0, 0.0]]])
  np.testing.assert_allclose(np.asarray(jax.vmap(energy_drift)(energy)),
                             [0.5 / 2.25, 0.0], rtol=1e-14)

  ncon_a = jnp.array([[0, 1], [2, 2]])
  ncon_b = jnp.array([[0, 2], [2, 2]])
  np.testing.assert_allclose(
      np.asarray(jax.vmap(contact_mismatch)(ncon_a, ncon_b)), [0.5, 0.0])

  mask = np.array([True, False])
  sa = jnp.array([[[-1.0, 1.0]], [[2.0, 1.0]]])
  sb = jnp.array([[[3.0, 1.5]], [[2.5, 1.0]]])
  se = jax.vmap(sensor_error, in_axes=(0, 0, None))(sa, sb, mask)
  np.testing.assert_allclose(np.asarray(se), [[[0.0, 0.5]], [[0.5, 0.0]]])
  mm = jax.vmap(rangefinder_hit_mismatch, in_axes=(0, 0, None))(sa, sb, mask)
  assert mm.tolist() == [[1], [0]]
