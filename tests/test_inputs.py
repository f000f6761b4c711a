"""Randomized inputs: reproducible bit for bit, inside the model's ranges."""

import mujoco
import numpy as np
import pytest

from mjxdiff.input.inputs import make_controls, make_inputs
from mjxdiff.input.scenario import Randomization, Scenario

XML = """
<mujoco>
  <worldbody>
    <body name="a"><joint name="h" type="hinge" range="-0.5 0.5" limited="true"/><geom size=".1" mass="1"/>
      <body name="b" pos="0 0 -.3"><joint type="ball"/><geom size=".1"/></body></body>
    <body name="f" pos="1 0 1"><freejoint/><geom type="box" size=".1 .1 .1"/></body>
  </worldbody>
  <actuator><motor joint="h" ctrlrange="-2 3" ctrllimited="true"/><motor joint="h"/></actuator>
</mujoco>"""


@pytest.fixture(scope="module")
def model():
    return mujoco.MjModel.from_xml_string(XML)


def _scenario(**randomize):
    return Scenario(name="t", model="unused.xml", batch=6, steps=50, randomize=Randomization(**randomize))


def test_same_seed_bit_identical(model):
    a, b = make_inputs(_scenario(), model, seed=7), make_inputs(_scenario(), model, seed=7)
    for field in ("qpos", "qvel", "act", "ctrl"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    assert a.factors.keys() == b.factors.keys()
    for k in a.factors:
        np.testing.assert_array_equal(a.factors[k], b.factors[k])
    np.testing.assert_array_equal(a.models[3].body_mass, b.models[3].body_mass)
    c = make_inputs(_scenario(), model, seed=8)
    assert not np.array_equal(a.qpos, c.qpos)


def test_quaternions_normalised_and_limits_respected(model):
    inp = make_inputs(_scenario(qpos_noise=2.0), model, seed=0)
    np.testing.assert_allclose(np.linalg.norm(inp.qpos[:, 1:5], axis=1), 1, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(inp.qpos[:, 8:12], axis=1), 1, atol=1e-12)
    assert np.all(np.abs(inp.qpos[:, 0]) < 0.5)


@pytest.mark.parametrize("family", ["zero", "smooth", "sinusoid", "step"])
def test_controls_clipped_to_ctrlrange(model, family):
    ctrl = make_controls(model, Randomization(control=family, control_scale=3.0, ctrl_outside=0.0), 4, 200, 0.002,
                         np.random.default_rng(0))
    assert ctrl.shape == (4, 200, 2)
    assert ctrl[..., 0].min() >= -2 and ctrl[..., 0].max() <= 3
    assert ctrl[..., 1].min() >= -1 and ctrl[..., 1].max() <= 1  # unlimited: [-1, 1] scaled
    if family == "zero":
        assert not ctrl.any()
    else:
        assert ctrl.std() > 0.1


def test_scaled_parameters_recompute_constants(model):
    inp = make_inputs(_scenario(), model, seed=1)
    m1 = inp.models[1]
    np.testing.assert_allclose(m1.body_mass, model.body_mass * inp.factors["body_mass"][1])
    # mj_setConst ran: the subtree mass follows the new masses
    assert m1.body_subtreemass[0] == pytest.approx(m1.body_mass.sum())
    np.testing.assert_allclose(m1.opt.gravity, model.opt.gravity * inp.factors["gravity"][1])


def test_concat_then_take_gives_back_both_batches(model):
    scenario = _scenario(scale={"body_mass": (0.8, 1.2)})
    a, b = (make_inputs(scenario, model, seed=1, batch=3, steps=5),
            make_inputs(scenario, model, seed=2, batch=2, steps=5))
    both = a.concat(b)
    assert both.batch == 5 and both.models == a.models + b.models
    for part, rows in ((a, slice(0, 3)), (b, slice(3, 5))):
        back = both.take(rows)
        for field in ("qpos", "qvel", "act", "ctrl"):
            np.testing.assert_array_equal(getattr(back, field), getattr(part, field), err_msg=field)
        np.testing.assert_array_equal(back.ids, part.ids)
        np.testing.assert_array_equal(back.factors["body_mass"], part.factors["body_mass"])


@pytest.mark.parametrize("family", ["smooth", "sinusoid", "step"])
def test_the_last_quarter_of_the_batch_drives_controls_outside_ctrlrange(model, family):
    """Clamping is behaviour too: the last floor(B/4) members leave the range, the others are
    drawn exactly as without them (the same draws, clipped)."""
    draw = lambda outside: make_controls(model, Randomization(control=family, ctrl_outside=outside), 8, 400, 0.002,
                                         np.random.default_rng(0))
    inside, mixed = draw(0.0), draw(0.25)
    np.testing.assert_array_equal(mixed[:6], inside[:6])
    lo, hi = model.actuator_ctrlrange[0]
    for member in mixed[6:]:
        assert member[:, 0].max() > hi or member[:, 0].min() < lo
    assert np.all((inside[..., 0] >= lo) & (inside[..., 0] <= hi))


def test_odd_members_get_turned_sensor_frames_and_spring_deadbands():
    xml = """<mujoco><worldbody><body><joint name="j" axis="0 1 0"/><geom size="0.1"/>
      <site name="s" pos="0 0 -0.2"/><site name="ray" pos="0 0 -0.1"/></body>
      <site name="w" pos="0 1 1"/></worldbody>
      <tendon><fixed name="t" stiffness="1"><joint joint="j" coef="1"/></fixed></tendon>
      <sensor><framepos objtype="site" objname="s" reftype="site" refname="w"/><rangefinder site="ray"/></sensor>
    </mujoco>"""
    m = mujoco.MjModel.from_xml_string(xml)
    inp = make_inputs(_scenario(), m, seed=0, batch=4)
    even, odd = inp.models[0], inp.models[1]
    np.testing.assert_array_equal(even.site_quat, m.site_quat)
    turned = np.abs(odd.site_quat - m.site_quat).max(axis=1) > 1e-6
    site = {n: mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, n) for n in ("s", "w", "ray")}
    # s and w (sensor frames), not the rangefinder's ray
    assert [bool(turned[site[n]]) for n in ("s", "w", "ray")] == [True, True, False]
    # MJX compiles site_sameframe: every member says "no shortcut" for the turned sites
    assert all(mi.site_sameframe[site["s"]] == 0 and mi.site_sameframe[site["w"]] == 0 for mi in inp.models)
    assert even.tendon_lengthspring[0, 0] == even.tendon_lengthspring[0, 1]
    lo, hi = odd.tendon_lengthspring[0]
    assert hi - lo > 0.09 and np.isclose((lo + hi) / 2, m.tendon_lengthspring[0, 0])


def test_disable_flags_are_drawn_per_scenario():
    m = mujoco.MjModel.from_xml_string(
        "<mujoco><worldbody><body><joint/><geom size='0.1'/></body></worldbody></mujoco>")
    bit = int(mujoco.mjtDisableBit.mjDSBL_WARMSTART)
    drawn = {seed: bool(make_inputs(_scenario(disable=("warmstart",)), m, seed=seed).models[0].opt.disableflags & bit)
             for seed in range(8)}
    assert set(drawn.values()) == {True, False}, drawn  # some seeds disable it, some do not
    for seed, off in drawn.items():  # one draw for the whole scenario
        flags = {mi.opt.disableflags & bit
                 for mi in make_inputs(_scenario(disable=("warmstart",)), m, seed=seed).models}
        assert flags == {bit if off else 0}
    assert not make_inputs(_scenario(), m, seed=0).models[0].opt.disableflags & bit
