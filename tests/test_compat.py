"""The compatibility layer: the supported range, the version gate, and the loop that stands in
for mujoco.batch.Batch on MuJoCo releases before 4.0, checked against the real Batch here."""

import mujoco
import numpy as np
import pytest

from mjxdiff import cli, compat
from mjxdiff.input.inputs import make_inputs
from mjxdiff.input.scenario import load_model, load_scenario


def test_the_reference_set_is_supported():
    compat.check_versions(compat.REFERENCE)
    assert compat.installed() == compat.REFERENCE  # this environment is the reference set


@pytest.mark.parametrize("versions, words", [
    ({"mujoco": "3.2.7", "mujoco-mjx": "3.2.7", "jax": "0.4.38"}, ["mujoco 3.2.7", "mujoco-mjx 3.2.7", "jax 0.4.38"]),
    ({"mujoco": "4.1.0", "mujoco-mjx": "3.18.0", "jax": "0.10.2"}, ["mujoco 4.1.0", "supported 3.3.0 to 4.0.0"]),
    ({"mujoco": "3.9.0", "mujoco-mjx": "3.8.0", "jax": "0.7.2"}, ["mjx 3.8.0 is not the release of mujoco 3.9.0"]),
    ({"mujoco": "4.0.0", "mujoco-mjx": "not installed", "jax": "0.10.2"}, ["mujoco-mjx not installed"]),
    ({"mujoco": "3.3.5", "mujoco-mjx": "3.3.5", "jax": "0.10.2"}, ["jax 0.10.2 is newer than mujoco-mjx 3.3.5"]),
])
def test_versions_outside_the_range_are_named(versions, words):
    with pytest.raises(compat.UntestedVersions) as e:
        compat.check_versions(versions)
    for w in words:
        assert w in str(e.value)


@pytest.mark.parametrize("versions", [
    {"mujoco": "3.3.0", "mujoco-mjx": "3.3.0", "jax": "0.6.0"},
    {"mujoco": "3.3.5", "mujoco-mjx": "3.3.5", "jax": "0.7.0"},
    {"mujoco": "3.9.0", "mujoco-mjx": "3.9.0", "jax": "0.7.2"},
    {"mujoco": "4.0.0", "mujoco-mjx": "3.17.0.dev0", "jax": "0.10.2"},
])
def test_versions_inside_the_range_pass(versions):
    compat.check_versions(versions)


def test_an_untested_version_exits_2_in_one_line_unless_allowed(monkeypatch, capsys):
    monkeypatch.setattr(compat, "installed", lambda: {"mujoco": "3.2.7", "mujoco-mjx": "3.2.7", "jax": "0.4.38"})
    monkeypatch.delenv("MJXDIFF_ALLOW_UNTESTED_VERSIONS", raising=False)
    assert cli.main(["sweep", "pendulum", "--quick"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "untested versions: mujoco 3.2.7" in err[0] and "--allow-untested-versions" in err[0]
    assert cli.main(["list"]) == 0  # commands that run no engine are not gated
    capsys.readouterr()
    # allowed: the gate lets it through (to a bad-input exit, so nothing is stepped here)
    assert cli.main(["sweep", "no-such-scenario", "--allow-untested-versions", "--no-history"]) == 2
    assert "untested" not in capsys.readouterr().err


def test_mjx_lacks_names_only_what_is_missing():
    assert compat.mjx_lacks("put_model", "make_data", "no_such_function") == ["no_such_function"]


def _record(b, inputs, chunks):
    """Rollouts of ``b`` over the inputs, ``chunks`` calls in turn; every record item joined."""
    b.set_models(list(inputs.models))
    b.qpos[:], b.qvel[:] = inputs.qpos, inputs.qvel
    record = ("qpos", "qvel", "act", "sensordata", "ncon", mujoco.mjtState.mjSTATE_TIME)
    pieces = []
    for part in np.array_split(np.arange(inputs.steps), chunks):
        pieces.append(b.rollout(len(part), control=inputs.ctrl[:, part], record=record))
    return {k: np.concatenate([p[k] for p in pieces], axis=1) for k in record}, b.warning[:, :, 1].copy()


def test_the_loop_is_the_batch_bit_for_bit():
    """LoopBatch against MuJoCo 4.0's Batch on a scenario with contacts and a model per member,
    stepped in three calls: every record identical, warnings included."""
    scenario = load_scenario("primitives_on_plane")
    m = load_model(scenario)
    inputs = make_inputs(scenario, m, seed=0, batch=3, steps=60)
    from mujoco.batch import Batch  # the reference set has it

    batch, batch_warnings = _record(Batch(m, inputs.batch), inputs, 3)
    loop, loop_warnings = _record(compat.LoopBatch(m, inputs.batch), inputs, 3)
    assert batch["ncon"].max() > 0, "the scenario makes contacts"
    for k in batch:
        np.testing.assert_array_equal(loop[k], batch[k], err_msg=str(k))
    np.testing.assert_array_equal(loop_warnings, batch_warnings)


def test_a_member_whose_warnings_rise_stops_and_repeats_its_last_record():
    """As Batch: a member that goes unstable stops; its records repeat; the others run on."""
    xml = """<mujoco><option timestep="0.01"/><worldbody><body><joint name="s" type="slide"/>
             <geom size=".1" mass="1"/></body></worldbody><actuator><motor joint="s" gear="1"/></actuator></mujoco>"""
    m = mujoco.MjModel.from_xml_string(xml)
    control = np.zeros((2, 20, 1))
    control[1, 5:] = 1e160  # member 1's force overflows: bad qacc, a warning, a reset
    from mujoco.batch import Batch

    out = {type(b).__name__: b.rollout(20, control=control, record=("qpos", "qvel"))
           for b in (Batch(m, 2), compat.LoopBatch(m, 2))}
    for k in ("qpos", "qvel"):
        np.testing.assert_array_equal(out["LoopBatch"][k], out["Batch"][k], err_msg=k)
    assert (out["Batch"]["qvel"][1, -1] == out["Batch"]["qvel"][1, -2]).all()


@pytest.mark.parametrize("mujoco_version, message, later", [
    ("3.3.5", "XML Error: Schema violation: unrecognized attribute: 'spring' Element 'flag', line 4", True),
    ("3.3.0", "XML Error: Schema violation: unrecognized element 'contact' Element 'sensor'", True),
    ("3.3.5", "XML Error: unknown joint 'j9' in actuator", False),  # malformed anywhere
    ("4.0.0", "XML Error: Schema violation: unrecognized attribute: 'sprng'", False),  # a typo on the reference
])
def test_a_model_an_older_mujoco_cannot_compile_is_a_later_feature(mujoco_version, message, later):
    why = compat.later_feature(message, {"mujoco": mujoco_version})
    assert (why is not None) == later
    if later:
        assert f"MuJoCo {mujoco_version} cannot compile this model" in why and message in why


def test_the_python_api_is_gated_as_the_cli_is(monkeypatch):
    from mjxdiff.runner import pipeline

    monkeypatch.setattr(compat, "installed", lambda: {"mujoco": "3.2.7", "mujoco-mjx": "3.2.7", "jax": "0.4.38"})
    monkeypatch.delenv("MJXDIFF_ALLOW_UNTESTED_VERSIONS", raising=False)
    with pytest.raises(pipeline.OptionsError, match="untested versions: mujoco 3.2.7"):
        pipeline.compute(pipeline.SweepOptions(scenarios=("pendulum",)))
    assert compat.gate(allowed=True) is None


def test_a_later_feature_is_unsupported_in_a_sweep_and_says_so_everywhere(tmp_path, monkeypatch):
    from mjxdiff.input.scenario import LaterFeatureError, ScenarioError, load_model, load_scenario
    from mjxdiff.runner.sweep import SweepConfig, sweep

    xml = tmp_path / "later.xml"
    xml.write_text('<mujoco><option><flag sprng="disable"/></option><worldbody><body><joint/><geom size=".1"/>'
                   "</body></worldbody></mujoco>")
    scenario = load_scenario(xml)
    with pytest.raises(ScenarioError) as e:  # on the reference: a malformed model
        load_model(scenario)
    assert not isinstance(e.value, LaterFeatureError)
    monkeypatch.setattr(compat, "installed", lambda: {**compat.REFERENCE, "mujoco": "3.3.5"})
    with pytest.raises(LaterFeatureError, match="MuJoCo 3.3.5 cannot compile this model"):
        load_model(scenario)
    [r] = sweep([scenario], SweepConfig(seed=0, batch=2, steps=10))
    assert r.status == "unsupported" and "a later MuJoCo added" in r.message, r.message


def test_c_steps_and_reads_contacts_the_same_through_the_loop(monkeypatch):
    """CEngine steps one step a call and reads each member's contacts by geom pair: through
    LoopBatch (MuJoCo before 4.0: its ``ids`` and ``get_data(sim, data)``) every record, the
    pair sums included, is the Batch's bit for bit."""
    from mjxdiff.engine import c as c_engine

    scenario = load_scenario("primitives_on_plane")
    m = load_model(scenario)
    inputs = make_inputs(scenario, m, seed=0, batch=3, steps=60)
    batch = c_engine.CEngine().rollout(inputs)
    monkeypatch.setattr(c_engine, "Batch", compat.LoopBatch)
    loop = c_engine.CEngine().rollout(inputs)
    assert batch.pairs.any(), "the scenario makes contacts"
    for f in ("qpos", "qvel", "sensordata", "ncon", "pairs", "time", "diverged_at"):
        np.testing.assert_array_equal(getattr(loop, f), getattr(batch, f), err_msg=f)
