"""grad: MJX's one-step Jacobians (jax.jacfwd) against C's finite differences. Smooth models agree
at every sampled state; a derivative-only bug (stop_gradient on the actuator force: forward values
bit-identical, the sweep passes it) fails with its block named; a forward bug fails here too;
states whose constraint set changes inside the stencil are non-smooth, not failures."""

import json

import jax
import mujoco
import numpy as np
import pytest
from mujoco.mjx._src import forward as mjx_forward

from mjxdiff.output import report
from mjxdiff.tools import grad
from mjxdiff.cli import main
from mjxdiff.input.scenario import load_model, load_scenario
from mjxdiff.runner.sweep import SweepConfig, run_scenario


@pytest.mark.parametrize("name", ["pendulum", "double_pendulum", "cartpole", "actuators"])
def test_smooth_models_agree_at_every_sampled_state(name):
    r = grad.check_scenario(load_scenario(name), count=4)
    assert r["status"] == "pass" and r["smooth"] == 4 and r["non_smooth"] == 0, r["message"]
    assert all(s["status"] == "pass" for s in r["results"])


def _stop_actuator_gradient(monkeypatch):
    orig = mjx_forward.fwd_actuation

    def patched(m, d):
        d = orig(m, d)
        return d.replace(qfrc_actuator=jax.lax.stop_gradient(d.qfrc_actuator))
    monkeypatch.setattr(mjx_forward, "fwd_actuation", patched)


def test_a_derivative_only_bug_passes_the_sweep_and_fails_grad_with_its_block(monkeypatch, fresh_mjx):
    _stop_actuator_gradient(monkeypatch)
    scenario = load_scenario("pendulum")
    sweep = run_scenario(scenario, SweepConfig(quick=True, transfer=False, compile_workers=0))
    assert sweep.status == "pass", sweep.message  # forward values are bit-identical
    r = grad.check_scenario(scenario, count=2)
    assert r["status"] == "fail", r["message"]
    worst = max(r["results"], key=lambda s: s["ratio"])["worst"]
    assert worst["matrix"] == "B" and worst["input"] == "ctrl of actuator 'torque'" and worst["mjx"] == 0.0
    assert worst["output"] == "qvel of joint 'hinge'" and worst["part"] == "smooth dynamics"
    assert worst["kind"] == "derivative only" and worst["mjx_fd"] == pytest.approx(worst["c"], rel=1e-6)


def test_a_forward_bug_fails_grad_too(monkeypatch):
    orig = mjx_forward.fwd_actuation
    monkeypatch.setattr(mjx_forward, "fwd_actuation",
                        lambda m, d: orig(m.replace(actuator_gainprm=m.actuator_gainprm * 1.02), d))
    r = grad.check_scenario(load_scenario("pendulum"), count=2)
    assert r["status"] == "fail" and "d qvel of joint 'hinge' / d ctrl of actuator 'torque'" in r["message"]
    assert "forward dynamics" in r["message"]  # MJX's own finite differences follow its (wrong) gradient


def test_a_contact_switching_inside_the_stencil_is_non_smooth():
    m = mujoco.MjModel.from_xml_string("""<mujoco><worldbody><geom type="plane" size="1 1 .1"/>
        <body pos="0 0 0.1"><freejoint/><geom size="0.1"/></body></worldbody></mujoco>""")
    touching = dict(qpos=m.qpos0.copy(), qvel=np.zeros(m.nv), act=np.zeros(0), ctrl=np.zeros(0))
    assert not grad.smooth_at(m, touching)  # dist 0: a contact appears or goes at +-eps in z
    resting = dict(touching, qpos=np.r_[0, 0, 0.099, m.qpos0[3:]])
    assert grad.smooth_at(m, resting)
    assert grad.judge_state(m, touching).status == "non-smooth"


def test_the_cli_reports_and_rejects_bad_input(tmp_path, capsys):
    assert main(["grad", "pendulum", "--states", "2", "--out", str(tmp_path)]) == 0
    doc = json.loads((tmp_path / "grad-report.json").read_text())
    assert report.validate(doc, "grad") == []
    assert doc["kind"] == "grad" and doc["scenarios"][0]["status"] == "pass" and doc["scenarios"][0]["smooth"] == 2
    assert "PASS" in capsys.readouterr().out
    assert main(["grad", "no_such_scenario"]) == 2
    err = capsys.readouterr().err.strip()
    assert "no_such_scenario" in err and "\n" not in err


def test_sensor_jacobians_are_compared_and_a_sensor_gradient_bug_is_named(monkeypatch, fresh_mjx):
    from mujoco.mjx._src import sensor as mjx_sensor

    scenario = load_scenario("pendulum")
    model, _, _, state = grad.sample_states(scenario, load_model(scenario), 1)[0]
    with jax.enable_x64(True):
        A, B, C, D = grad.mjx_jacobians(model, state)
    assert C.shape == (5, 2) and D.shape == (5, 1)  # angle, angvel, tip_pos[3] by (qpos, qvel) and ctrl
    assert C[0, 0] == pytest.approx(1.0) and C[1, 1] == pytest.approx(1.0)
    orig = mjx_sensor.sensor_pos

    def patched(m, d):  # forward values bit-identical, the position sensors' gradient gone
        out = orig(m, d)
        return out.replace(sensordata=jax.lax.stop_gradient(out.sensordata))
    monkeypatch.setattr(mjx_sensor, "sensor_pos", patched)
    r = grad.check_scenario(scenario, count=1)
    assert r["status"] == "fail", r["message"]
    worst = r["results"][0]["worst"]
    assert worst["matrix"] == "C" and worst["output"].startswith("sensor '") and worst["mjx"] == 0.0


def test_a_failing_state_is_saved_and_replays_to_the_same_entry(monkeypatch, tmp_path, capsys):
    orig = mjx_forward.fwd_actuation
    monkeypatch.setattr(mjx_forward, "fwd_actuation",
                        lambda m, d: orig(m.replace(actuator_gainprm=m.actuator_gainprm * 1.02), d))
    assert main(["grad", "pendulum", "--states", "1", "--out", str(tmp_path), "--format", "json"]) == 1
    row = json.loads(capsys.readouterr().out)["scenarios"][0]
    path = tmp_path / "reproducers" / "pendulum-grad-state0.json"
    assert row["reproducer"] == str(path) and path.is_file()
    assert report.validate(json.loads(path.read_text()), "grad-reproducer") == []
    assert main(["replay", str(path)]) == 1  # still wrong: the same entry
    out = capsys.readouterr().out
    assert "reproduced: same status and worst entry" in out and "B[1, 0]" in out
    monkeypatch.undo()  # MJX mended: the saved state passes
    assert main(["replay", str(path), "--format", "json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["replayed"]["status"] == "pass" and doc["reproduced"] is False


def test_a_scenario_with_no_smooth_state_is_not_a_pass(monkeypatch, tmp_path):
    xml = tmp_path / "touching.xml"
    xml.write_text("""<mujoco><worldbody><geom type="plane" size="1 1 .1"/>
        <body pos="0 0 0.1"><freejoint/><geom size="0.1"/></body></worldbody></mujoco>""")
    m = mujoco.MjModel.from_xml_path(str(xml))
    touching = dict(qpos=m.qpos0.copy(), qvel=np.zeros(m.nv), act=np.zeros(0), ctrl=np.zeros(0))
    monkeypatch.setattr(grad, "sample_states", lambda *a, **k: [(m, 0, 0, touching), (m, 1, 0, touching)])
    r = grad.check_scenario(load_scenario(str(xml)), count=2)
    assert r["status"] == "non-smooth" and r["smooth"] == 0 and r["non_smooth"] == 2, r
    assert "no smooth state to judge" in r["message"]
    assert grad.format_text([r]).startswith("NONSM")


@pytest.mark.parametrize("name, entry, nv", [("grad_resting_orientation", "A[5, 11]", 6),
                                             ("grad_elliptic_cone_at_rest", "A[11, 11]", 6),
                                             ("grad_cg_solver_cross_coupling", "A[27, 2]", 18)])
def test_the_committed_reproducers_of_mjx_gradient_bugs_load(name, entry, nv):
    """The reproducers of the MJX gradient bugs (tests/test_known_divergences.py) that the
    closing note cites: 'python -m mjxdiff replay tests/data/NAME.json'."""
    from pathlib import Path

    from mjxdiff.output import reproducer

    rep = reproducer.load_any(Path(__file__).parent / "data" / f"{name}.json")
    assert isinstance(rep, reproducer.GradReproducer) and rep.model.nv == nv
    assert rep.verdict["status"] == "fail" and rep.verdict["worst"]["kind"] == "derivative only"
    assert entry in grad.format_state(grad.StateResult(**rep.verdict))


def test_c_differences_written_out_match_mjd_transition_fd_and_serve_rk4():
    """mjd_transitionFD refuses RK4; grad differences mj_step itself there. Where both run they
    agree (to roundoff: 6e-11 measured on ball_joint)."""
    scenario = load_scenario("ball_joint")
    model, _, _, state = grad.sample_states(scenario, load_model(scenario), 3)[2]
    for ours, theirs in zip(grad._c_fd(model, state, grad.EPS), grad.c_jacobians(model, state, grad.EPS)):
        np.testing.assert_allclose(ours, theirs, atol=1e-9)
    rk4 = load_model(load_scenario("integrator_rk4"))
    assert rk4.opt.integrator == mujoco.mjtIntegrator.mjINT_RK4
    state = dict(qpos=rk4.qpos0.copy(), qvel=np.full(rk4.nv, 0.1), act=np.zeros(rk4.na), ctrl=np.zeros(rk4.nu))
    A, B, C, D = grad.c_jacobians(rk4, state, grad.EPS)
    assert A.shape == (2 * rk4.nv + rk4.na,) * 2 and np.isfinite(A).all() and np.abs(A).max() > 0
