"""The interaction model: pairs counted where a compared field depends on them, infeasible pairs
left out with a reason, and the bundled scenarios covering the feasible ones."""

import mujoco
import numpy as np

from mjxdiff.tools import interactions
from mjxdiff.input.inputs import make_inputs
from mjxdiff.input.scenario import bundled_scenarios, load_model

TWO_ACTUATORS = """<mujoco><worldbody>
  <body><joint name="a" axis="0 1 0" range="-1 1"/><geom type="capsule" fromto="0 0 0 0 0 -0.3" size="0.02"/>
    <site name="tip" pos="0 0 -0.3"/></body>
  <site name="w" pos="0 1 1" euler="30 0 0"/>
  </worldbody>
  <actuator>
    <motor name="limited" joint="a" ctrlrange="-1 1"/>
    <general name="forced" joint="a" forcerange="-0.1 0.1" dyntype="filter" dynprm="0.05"/>
  </actuator>
  <sensor><framepos objtype="site" objname="tip" reftype="site" refname="w"/>
    <framepos objtype="site" objname="tip"/></sensor>
</mujoco>"""


def _pairs(m, ctrl):
    seen = interactions.observe(m, m.qpos0, np.zeros(m.nv), np.zeros(m.na), ctrl)
    return interactions.covered_pairs(interactions.rows(m, seen))


def test_element_pairs_are_counted_within_one_element_only():
    m = mujoco.MjModel.from_xml_string(TWO_ACTUATORS)
    ctrl = np.tile([[1.5, 0.0]], (20, 1))  # the limited motor leaves its range, the other is unlimited
    pairs = _pairs(m, ctrl)
    limits = "actuator limits"
    assert (limits, "actuator.ctrllimited", "yes", "ctrl", "outside") in pairs
    assert (limits, "ctrl", "outside", "actuator.forcelimited", "no") in pairs
    # the motor is outside and unforced, the filter forced and inside: never forced AND outside
    assert (limits, "ctrl", "outside", "actuator.forcelimited", "yes") not in pairs
    assert (limits, "ctrl", "inside", "actuator.forcelimited", "yes") in pairs
    inside = _pairs(m, np.zeros((20, 2)))
    assert (limits, "actuator.ctrllimited", "yes", "ctrl", "outside") not in inside


def test_a_reference_frame_is_identity_or_rotated_as_c_computes_it():
    m = mujoco.MjModel.from_xml_string(TWO_ACTUATORS)
    pairs = _pairs(m, np.zeros((5, 2)))
    frames = "frame sensors"
    assert (frames, "sensor.reftype", "site", "ref.frame", "rotated") in pairs  # 'w' is turned 30 degrees
    assert (frames, "sensor.reftype", "none", "ref.frame", "none") in pairs
    m.site_quat[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, "w")] = [1, 0, 0, 0]
    assert (frames, "sensor.reftype", "site", "ref.frame", "identity") in _pairs(m, np.zeros((5, 2)))


def test_flags_switch_off_the_rows_they_disable():
    m = mujoco.MjModel.from_xml_string(TWO_ACTUATORS)
    m.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_ACTUATION) | int(mujoco.mjtDisableBit.mjDSBL_SENSOR)
    pairs = _pairs(m, np.ones((5, 2)))
    assert not {p for p in pairs if p[0] in ("actuator limits", "actuator dynamics", "frame sensors")}


def test_infeasible_pairs_have_reasons_and_are_not_counted():
    feasible, infeasible = interactions.feasible_pairs()
    assert feasible and infeasible and not feasible & set(infeasible)
    assert all(reason for reason in infeasible.values())
    assert ("actuator limits", "actuator.ctrllimited", "no", "ctrl", "outside") in infeasible
    doc = interactions.pairwise({next(iter(infeasible)): ["x"], next(iter(feasible)): ["y"]})
    assert doc["covered"] == 1 and doc["feasible"] == len(feasible)
    assert len(doc["uncovered"]) == len(feasible) - 1


def test_tendon_deadbands_are_reached_on_both_sides():
    xml = """<mujoco><worldbody><body><joint name="j" axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 0 0 -0.3" size="0.02"/></body></worldbody>
      <tendon><fixed name="t" stiffness="1" springlength="-0.1 0.1"><joint joint="j" coef="1"/></fixed></tendon>
    </mujoco>"""
    m = mujoco.MjModel.from_xml_string(xml)
    seen = interactions.observe(m, np.array([-0.5]), np.array([4.0]), np.zeros(0), np.zeros((60, 0)))
    assert seen.tendon_length[0] == {"below", "inside", "above"}


def test_the_bundled_scenarios_cover_95_percent_of_the_feasible_pairs():
    """The README's claim (issue 32), at seed 0: MuJoCo C steps the members, nothing compiles."""
    covered = {}
    for s in bundled_scenarios():
        m = load_model(s)
        try:
            inputs = make_inputs(s, m, 0)
        except Exception:
            raise
        for p in interactions.member_pairs(inputs):
            covered.setdefault(p, []).append(s.name)
    doc = interactions.pairwise(covered)
    assert doc["percent"] >= 95, interactions.format_text(doc)
    assert doc["groups"]["frame sensors"]["percent"] == 100
    assert doc["groups"]["actuator limits"]["percent"] == 100
