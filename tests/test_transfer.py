"""MJX's host interface checked against C (mjxdiff.compare.transfer): silent on unmodified MJX over
every bundled scenario, and a one-line slip in put_data, get_data, get_state/set_state,
id2name or bind is caught, with the call, the field and the C state named. The rollouts
never call these functions, so no trajectory comparison could have caught any of them."""

import dataclasses
import json

import mujoco
import numpy as np
from mujoco.mjx._src import io as mjx_io
from mujoco.mjx._src import support as mjx_support
from mujoco.mjx._src import types as mjx_types

from mjxdiff.input import adjust
from mjxdiff.compare import transfer
from mjxdiff.input.inputs import make_inputs
from mjxdiff.input.scenario import bundled_scenarios, load_model, load_scenario
from mjxdiff.runner.sweep import SweepConfig, run_scenario


def _check(name: str, precision: str = "float64") -> transfer.TransferCheck:
    s = load_scenario(name)
    m, _ = adjust.for_mjx(load_model(s), s.model_path)
    inputs = make_inputs(s, m, 0, 1)
    return transfer.check_scenario_states(inputs.models[0], inputs.qpos[0], inputs.qvel[0], inputs.act[0],
                                          inputs.ctrl[0], 0.0, s.model_path, precision)


def test_unmodified_mjx_agrees_with_c_on_every_bundled_scenario():
    checked = {}
    for s in bundled_scenarios():
        if s.name == "unsupported_pair":
            continue
        found = _check(s.name)
        assert found.mismatches == (), (s.name, found.mismatches[:3])
        checked[s.name] = found
    assert all(c.checked > 100 for c in checked.values())
    # contact states are reached: the second state has more contacts than the first
    assert {n for n, c in checked.items() if len(c.states) == 2} >= {"primitives_on_plane", "box_stack", "humanoid"}


def test_a_state_element_mjx_refuses_is_listed_not_failed():
    found = _check("pendulum")
    assert any(u.startswith("get_state(mjSTATE_PLASTIC)") for u in found.unsupported)


def _only(found: transfer.TransferCheck) -> set[tuple[str, str]]:
    assert found.mismatches, "the injected slip went unnoticed"
    return {(x.call, x.field) for x in found.mismatches}


def test_put_data_scaling_a_public_field_is_caught(monkeypatch):
    real = mjx_io._put_data_public_fields

    def slip(d):
        fields = real(d)
        fields["cvel"] = fields["cvel"] * 1.001
        return fields

    monkeypatch.setattr(mjx_io, "_put_data_public_fields", slip)
    assert ("get_data(put_data(d))", "cvel") in _only(_check("pendulum"))


def test_get_data_transposing_contact_frames_is_caught(monkeypatch):
    real = mjx_io._get_contact

    def slip(c, cx):
        real(c, cx.replace(frame=np.swapaxes(np.asarray(cx.frame), -1, -2)))

    monkeypatch.setattr(mjx_io, "_get_contact", slip)
    found = _check("primitives_on_plane")
    assert {call for call, _ in _only(found)} == {"get_data(put_data(d))"}
    assert any(x.field.startswith("contact") and x.state > 0 for x in found.mismatches), found.mismatches


def _swap_qpos_and_qvel(monkeypatch):
    monkeypatch.setitem(mjx_io._STATE_MAP, mujoco.mjtState.mjSTATE_QPOS, "qvel")
    monkeypatch.setitem(mjx_io._STATE_MAP, mujoco.mjtState.mjSTATE_QVEL, "qpos")


def test_get_state_with_two_elements_swapped_is_caught(monkeypatch):
    _swap_qpos_and_qvel(monkeypatch)
    found = _only(_check("pendulum"))  # a hinge: nq == nv, so only the values can tell
    assert ("get_state(mjSTATE_QPOS)", "mjSTATE_QPOS") in found
    sizes = _only(_check("primitives_on_plane"))  # free joints: nq != nv
    assert ("state_size(mjSTATE_QPOS)", "mjSTATE_QPOS") in sizes


def test_a_state_element_mjx_knows_but_cannot_size_is_a_mismatch_not_unsupported(monkeypatch):
    monkeypatch.setitem(mjx_io._STATE_MAP, mujoco.mjtState.mjSTATE_WARMSTART, "qacc")
    found = _check("pendulum")
    assert ("state_size(mjSTATE_WARMSTART)", "mjSTATE_WARMSTART") in _only(found)
    assert not any("WARMSTART" in u for u in found.unsupported)


def test_bind_giving_a_ball_or_free_joint_its_dof_width_in_qpos_is_caught(monkeypatch):
    monkeypatch.setattr(mjx_types.JointType, "qpos_width", mjx_types.JointType.dof_width)
    assert ("Data.bind(joints).qpos", "qpos") in _only(_check("primitives_on_plane"))


def test_id2name_reading_another_objects_name_table_is_caught(monkeypatch):
    real = mjx_support._getadr

    def slip(m, typ):
        return real(m, mujoco.mjtObj.mjOBJ_BODY if typ == mujoco.mjtObj.mjOBJ_GEOM else typ)

    monkeypatch.setattr(mjx_support, "_getadr", slip)
    assert "id2name" in {call for call, _ in _only(_check("primitives_on_plane"))}


def test_the_sweep_fails_a_scenario_whose_trajectories_agree_when_the_host_interface_slips(monkeypatch):
    config = SweepConfig(seed=0, batch=2, steps=20, diagnose="none")
    clean = run_scenario(load_scenario("pendulum"), config)
    assert clean.status == "pass" and clean.info["transfer"]["mismatches"] == []
    _swap_qpos_and_qvel(monkeypatch)
    result = run_scenario(load_scenario("pendulum"), config)
    assert result.status == "fail"
    assert all(f.ok for f in result.fields if f.field != "transfer"), "the trajectories still agree"
    field = result.field("transfer")
    assert field.object == "get_state(mjSTATE_QPOS)" and field.first_step == 0
    assert "get_state(mjSTATE_QPOS)" in result.message and "mismatch" in result.message
    off = run_scenario(load_scenario("pendulum"), dataclasses.replace(config, transfer=False))
    assert off.status == "pass" and "transfer" not in off.info


def test_float32_rounds_once_and_passes():
    assert _check("primitives_on_plane", "float32").mismatches == ()


def test_a_named_light_is_listed_as_refused_by_mjx_names_and_the_rest_is_checked():
    """MJX 3.17's ``name2id`` keeps no table for lights (a KeyError): dm_control's cheetah, which
    names its light, once ended the whole check with ``KeyError: 8`` and swept as a silent PASS."""
    m = mujoco.MjModel.from_xml_string(
        "<mujoco><worldbody><light name='top' pos='0 0 3'/><body name='b'><joint name='j'/>"
        "<geom name='g' size='.1' pos='0 0 .2'/></body></worldbody></mujoco>")
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    found = transfer.check(m, d)
    assert found.mismatches == () and found.checked > 10
    assert "id2name/name2id(mjOBJ_LIGHT): KeyError, no name table in MJX" in found.unsupported, found.unsupported


def test_a_host_interface_check_that_could_not_run_says_so_on_the_checks_line():
    from mjxdiff.output.report import format_checks

    line = format_checks({"transfer": {"error": "KeyError: 8"}})
    assert line == "checks: host-interface check did not run: KeyError: 8"


def test_a_check_is_loaded_only_for_the_same_model_state_and_code(tmp_path, monkeypatch):
    """The check's result is saved under the cache and loaded for the very same check; another
    MJX (a patched state map), another state, or a damaged entry checks afresh, and the undone
    patch loads the clean result again."""
    s = load_scenario("pendulum")
    m, _ = adjust.for_mjx(load_model(s), s.model_path)
    i = make_inputs(s, m, 0, 1)

    def check(qvel=i.qvel[0]):
        return transfer.cached_check_scenario_states(tmp_path, i.models[0], i.qpos[0], qvel, i.act[0], i.ctrl[0],
                                                     0.0, s.model_path)

    clean, loaded = check()
    assert not loaded and clean.mismatches == () and clean.checked > 100
    assert check() == (clean, True)
    with monkeypatch.context() as patch:
        _swap_qpos_and_qvel(patch)
        slipped, loaded = check()
        assert not loaded and ("get_state(mjSTATE_QPOS)", "mjSTATE_QPOS") in _only(slipped)
        assert check() == (slipped, True), "the slipped MJX's own result, for that code only"
    assert check() == (clean, True)
    assert check(i.qvel[0] + 0.1)[1] is False
    key = transfer._key(i.models[0], i.qpos[0], i.qvel[0], i.act[0], i.ctrl[0], 0.0, s.model_path, "float64")
    entry = tmp_path / "mjxdiff-checks" / f"transfer-{key}.json"
    assert json.loads(entry.read_text()) == clean.as_dict()
    entry.write_text("{damaged")
    assert check() == (clean, False) and check() == (clean, True)


def test_a_sweep_loads_the_check_it_made_before_and_says_so(tmp_path, monkeypatch):
    from mjxdiff.engine import export_cache

    monkeypatch.setattr(export_cache, "cache_root", lambda: tmp_path)
    config = SweepConfig(seed=0, batch=2, steps=20, diagnose="none")
    first, second = (run_scenario(load_scenario("pendulum"), config) for _ in range(2))
    assert "checks_loaded" not in first.info and second.info["checks_loaded"] == ["transfer"]
    assert first.info["transfer"] == second.info["transfer"] and second.status == first.status == "pass"
