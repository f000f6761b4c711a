"""Models MJX refuses: harmless settings are set aside and said so, unsupported collision pairs
are dropped only when asked (and listed), structural limits are 'unsupported' with the reason."""

import mujoco
import numpy as np

from mjxdiff.input import adjust
from mjxdiff.input.scenario import load_scenario
from mjxdiff.runner.sweep import SweepConfig, run_scenario

SMALL = SweepConfig(seed=0, batch=2, steps=60, diagnose="none")

CONTACTS_WITH_FLAGS = """<mujoco>
  <option timestep="0.004"><flag energy="enable" fwdinv="enable"/></option>
  <worldbody>
    <geom type="plane" size="2 2 0.1"/>
    <body pos="0 0 0.3" euler="10 20 30"><freejoint/><geom type="box" size="0.1 0.08 0.05"/>
      <site name="s" size="0.12"/></body>
    <body pos="0.3 0 0.3"><freejoint/><geom type="sphere" size="0.05"/></body>
  </worldbody>
  <sensor><touch site="s"/><accelerometer site="s"/><framequat objtype="site" objname="s"/></sensor>
</mujoco>"""


def _c_record(m: mujoco.MjModel, steps: int = 300) -> dict[str, np.ndarray]:
    d = mujoco.MjData(m)
    d.qvel[:] = 0.5
    out = {k: [] for k in ("qpos", "qvel", "act", "sensordata", "ncon")}
    for _ in range(steps):
        mujoco.mj_step(m, d)
        for k in out:
            out[k].append(np.copy(getattr(d, k)))
    return {k: np.asarray(v) for k, v in out.items()}


def test_harmless_flags_change_nothing_c_computes():
    """The claim the adjustment rests on: C with and without the flags is bit-identical."""
    m = mujoco.MjModel.from_xml_string(CONTACTS_WITH_FLAGS)
    plain, lines = adjust.harmless(m)
    assert lines == ["energy flag disabled for MJX", "fwdinv flag disabled for MJX"]
    assert plain.opt.enableflags == 0 and m.opt.enableflags != 0, "the caller's model is left as it was"
    with_flags, without = _c_record(m), _c_record(plain)
    assert with_flags["ncon"].max() > 0, "the comparison covers contacts"
    for key in with_flags:
        np.testing.assert_array_equal(with_flags[key], without[key], err_msg=key)


def test_energy_sensors_keep_the_energy_flag():
    m = mujoco.MjModel.from_xml_string("""<mujoco><option><flag energy="enable"/></option>
      <worldbody><body><joint type="hinge"/><geom size=".1" pos="0 0 -1"/></body></worldbody>
      <sensor><e_potential/></sensor></mujoco>""")
    same, lines = adjust.harmless(m)
    assert same is m and lines == []


def test_energy_flag_scenario_passes_adjusted_and_says_so():
    scenario = load_scenario("energy_flag")
    result = run_scenario(scenario, SMALL)
    assert result.status == "pass", result.message
    assert result.info["adjusted"] == ["energy flag disabled for MJX", "fwdinv flag disabled for MJX"]
    refused = run_scenario(scenario, SweepConfig(seed=0, batch=2, steps=60, diagnose="none", adjust=False))
    assert refused.status == "unsupported" and "mjENBL_ENERGY" in refused.message
    assert "adjusted" not in refused.info


def test_unsupported_pair_is_named_and_dropped_only_on_request():
    scenario = load_scenario("unsupported_pair")
    refused = run_scenario(scenario, SMALL)
    assert refused.status == "unsupported", refused.message
    assert "mjGEOM_ELLIPSOID" in refused.message and "mjGEOM_BOX" in refused.message
    dropped = run_scenario(scenario, SweepConfig(seed=0, batch=2, steps=60, diagnose="none", drop_unsupported=True))
    assert dropped.status == "pass", dropped.message
    [line] = dropped.info["adjusted"]
    assert "dropped 1 geom pair" in line and "box 'platform' / ellipsoid 'egg'" in line


def test_dropping_by_bodies_lists_the_supported_pairs_it_takes_along(tmp_path):
    xml = tmp_path / "m.xml"
    xml.write_text("""<mujoco><worldbody>
      <body name="table"><geom name="top" type="box" size=".3 .3 .02"/><geom name="leg" type="sphere" size=".05"
        pos="0 0 -.2"/></body>
      <body pos="0 0 .2"><freejoint/><geom name="can" type="cylinder" size=".05 .05"/></body>
    </worldbody></mujoco>""")
    m = mujoco.MjModel.from_xml_path(str(xml))
    assert [(g1, g2) for g1, g2, _, _ in adjust.unsupported_pairs(m)] == [(2, 0)]  # MJX orders pairs by type
    dropped, [line] = adjust.drop_unsupported(m, xml)
    assert adjust.unsupported_pairs(dropped) == [] and dropped.nexclude == 1
    assert "dropped 2 geom pair(s)" in line and "box 'top' / cylinder 'can' (no MJX collision function)" in line
    assert "sphere 'leg' / cylinder 'can' (same bodies as a dropped pair)" in line


def test_explicit_pairs_are_deleted(tmp_path):
    xml = tmp_path / "m.xml"
    xml.write_text("""<mujoco><worldbody>
      <geom name="floor" type="plane" size="1 1 .1" contype="0" conaffinity="0"/>
      <geom name="block" type="box" size=".1 .1 .1" contype="0" conaffinity="0"/>
      <body pos="0 0 .5"><freejoint/><geom name="can" type="cylinder" size=".05 .05" contype="0" conaffinity="0"/>
      </body></worldbody>
      <contact><pair geom1="can" geom2="block"/><pair geom1="can" geom2="floor"/></contact></mujoco>""")
    m = mujoco.MjModel.from_xml_path(str(xml))
    dropped, [line] = adjust.drop_unsupported(m, xml)
    assert dropped.npair == 1 and "dropped 1 geom pair" in line and "box 'block' / cylinder 'can'" in line


def test_a_model_without_dofs_is_unsupported_with_the_reason(tmp_path):
    xml = tmp_path / "static.xml"
    xml.write_text("""<mujoco><worldbody><geom type="plane" size="1 1 .1"/>
      <body pos="0 0 1"><geom type="box" size=".1 .1 .1"/></body></worldbody>
      <sensor><framepos objtype="body" objname="world"/></sensor></mujoco>""")
    result = run_scenario(load_scenario(str(xml)), SMALL)
    assert result.status == "unsupported", result.message
    assert "without degrees of freedom (nv = 0)" in result.message
