"""Diagnosis names the stage: five more injected bugs, each in another stage of
the pipeline, are caught (chaotic scenarios included) and the drill-down names
the right stage and field; local error and envelope behave as documented;
replay reproduces a saved failure."""

import json

import numpy as np

import pytest
from mujoco.mjx._src import collision_driver as mjx_collision
from mujoco.mjx._src import constraint as mjx_constraint
from mujoco.mjx._src import smooth as mjx_smooth

import _bugs
from mjxdiff.cli import main
from mjxdiff.input.scenario import load_scenario
from mjxdiff.runner.sweep import SweepConfig, run_scenario
from tests import test_detection as core

BASIC = SweepConfig(seed=0, batch=4, diagnose="basic")


def kinematics_offset(monkeypatch):
    """Body centres of mass 1e-6 m too high after forward kinematics."""
    orig = mjx_smooth.kinematics

    def buggy(m, d):
        d = orig(m, d)
        return d.replace(xipos=d.xipos.at[1:, 2].add(1e-6))

    monkeypatch.setattr(mjx_smooth, "kinematics", buggy)


def inertia_scale(monkeypatch):
    """Joint-space inertia 0.01% too large."""
    orig = mjx_smooth.crb

    def buggy(m, d):
        d = orig(m, d)
        return d.replace(_impl=d._impl.replace(M=d._impl.M * (1 + 1e-4)))

    monkeypatch.setattr(mjx_smooth, "crb", buggy)


def bias_force(monkeypatch):
    """Coriolis/centrifugal/gravity force 1 ppm too large."""
    orig = mjx_smooth.rne
    monkeypatch.setattr(mjx_smooth, "rne", lambda m, d, *a, **k: (lambda d: d.replace(
        qfrc_bias=d.qfrc_bias * (1 + 1e-6)))(orig(m, d, *a, **k)))


def constraint_reference(monkeypatch):
    """Constraint reference acceleration (solref spring) 1% too stiff."""
    orig = mjx_constraint.make_constraint

    def buggy(m, d):
        d = orig(m, d)
        return d.replace(_impl=d._impl.replace(efc_aref=d._impl.efc_aref * 1.01))

    monkeypatch.setattr(mjx_constraint, "make_constraint", buggy)


def contact_distance(monkeypatch):
    """Contacts report 1e-5 m less penetration than there is."""
    orig = mjx_collision.collision

    def buggy(m, d):
        d = orig(m, d)
        c = d._impl.contact
        return d.replace(_impl=d._impl.replace(contact=c.replace(dist=c.dist + 1e-5)))

    monkeypatch.setattr(mjx_collision, "collision", buggy)


# bug -> (scenario, stage the drill-down must name, field it must name)
STAGE_BUGS = {
    kinematics_offset: ("cartpole", "kinematics", "xipos"),
    inertia_scale: ("pendulum", "inertia", "qM"),
    bias_force: ("double_pendulum", "bias", "qfrc_bias"),  # chaotic, at its full horizon
    constraint_reference: ("cartpole", "constraint", "qfrc_constraint"),
    contact_distance: ("primitives_on_plane", "collision", "contact"),
    # the core bugs, now also localised
    core.extra_damping: ("pendulum", "passive", "qfrc_passive"),
    core.actuator_gain: ("pendulum", "actuation", "actuator_force"),
    core.jointvel_sensor_gain: ("pendulum", "sensors", "sensordata"),
    core.contact_friction: ("slope_slide", "collision", "contact"),
    core.quaternion_update: ("ball_joint", "integration", "qpos/qvel update"),
}


def _switched(scenario: str) -> list:
    """The bugs ``scenario`` is to localise, switched in one compile of it where there are several
    (_bugs.install_switched)."""
    bugs = [b for b, (s, _, _) in STAGE_BUGS.items() if s == scenario]
    return bugs if len(bugs) > 1 else []


@pytest.mark.parametrize("bug", list(STAGE_BUGS), ids=lambda b: b.__name__)
def test_drill_down_names_the_stage(bug, fresh_mjx):
    scenario, stage, field = STAGE_BUGS[bug]
    result = _bugs.sweep(scenario, BASIC, bug, among=_switched(scenario))
    assert result.status == "fail", result.message
    drill = result.diagnosis["drill_down"]
    assert (drill["first_stage"], drill["first_field"]) == (stage, field), result.message
    assert "first field to differ" in result.message or "integration" in result.message
    # the one-step (re-synchronised) error shows the bug, far above rounding
    assert max(result.diagnosis["local_error"].values()) > 1e-12


@pytest.mark.slow  # four ablations, each a recompile
def test_cause_attribution_blames_contacts_for_a_contact_bug(fresh_mjx, monkeypatch):
    contact_distance(monkeypatch)
    result = run_scenario(load_scenario("primitives_on_plane"), SweepConfig(seed=0, batch=4, diagnose="full"))
    cause = result.diagnosis["cause"]
    assert cause["cause"] == "contact generation", cause
    assert "likely cause: contact generation" in result.message


def test_cause_attribution_calls_a_damping_bug_genuine(fresh_mjx, monkeypatch):
    core.extra_damping(monkeypatch)
    result = run_scenario(load_scenario("pendulum"), SweepConfig(seed=0, batch=4, diagnose="full"))
    assert result.diagnosis["cause"]["cause"] == "genuine discrepancy"
    assert len(result.diagnosis["cause"]["tried"]) == 4


def test_chaotic_scenario_passes_under_envelope_not_fixed_tolerance():
    """float32 rounding alone decorrelates the double pendulum over 1500 steps."""
    args = ["sweep", "double_pendulum", "--precision", "float32", "--steps", "1500", "--batch", "4", "--format", "json"]
    import subprocess
    import sys

    runs = {flag: subprocess.run([sys.executable, "-m", "mjxdiff", *args, flag], capture_output=True, text=True,
                                 timeout=600) for flag in ("--envelope", "--no-envelope")}
    enveloped = json.loads(runs["--envelope"].stdout)["scenarios"][0]
    fixed = json.loads(runs["--no-envelope"].stdout)["scenarios"][0]
    assert runs["--envelope"].returncode == 0 and enveloped["status"] == "pass", enveloped["message"]
    assert runs["--no-envelope"].returncode == 1 and fixed["status"] == "fail", fixed["message"]
    assert enveloped["fields"]["qpos"]["envelope"] > enveloped["fields"]["qpos"]["tolerance"]
    assert enveloped["noise_rate"]["qpos"] > 0.5  # chaotic: positive finite-time growth rate, 1/s


def test_local_error_is_rounding_level_on_a_chaotic_scenario():
    result = run_scenario(load_scenario("double_pendulum"), SweepConfig(seed=0, batch=4, diagnose="basic"))
    assert result.status == "pass"
    from mjxdiff.compare import diagnose
    from mjxdiff.engine.engines import CEngine
    from mjxdiff.input.inputs import make_inputs
    from mjxdiff.input.scenario import load_model
    from mjxdiff.compare.verdict import rangefinder_mask

    scenario = load_scenario("double_pendulum")
    m = load_model(scenario)
    inputs = make_inputs(scenario, m, 0, 4, scenario.steps)
    traj_c = CEngine().rollout(inputs)
    local = diagnose.local_error(inputs, traj_c, m, rangefinder_mask(m))
    free = result.field("qpos").max_error
    assert local["qpos"] < 1e-13 < free  # chaos amplifies the free-running error, not the local one


def test_replay_reproduces_a_saved_failure_bit_for_bit(fresh_mjx, monkeypatch, tmp_path, capsys):
    core.extra_damping(monkeypatch)
    assert main(["sweep", "pendulum", "--batch", "4", "--diagnose", "basic", "--out", str(tmp_path)]) == 1
    (path,) = (tmp_path / "reproducers").glob("pendulum-member*.json")
    capsys.readouterr()
    outs = []
    for _ in range(2):
        assert main(["replay", str(path), "--format", "json"]) == 1
        outs.append(json.loads(capsys.readouterr().out))
    assert outs[0]["reproduced"] is True
    a, b = outs[0]["replayed"], outs[1]["replayed"]
    for doc in (a, b):
        for key in ("seconds", "cpu_seconds", "compile_seconds", "mjx_compiles", "mjx_loaded", "checks_loaded"):
            doc["info"].pop(key, None)  # timings and what the caches held
    assert a == b  # every number identical
    assert a["diagnosis"]["drill_down"]["first_field"] == "qfrc_passive"


def test_replay_rejects_a_non_reproducer(tmp_path, capsys):
    bad = tmp_path / "x.json"
    bad.write_text("{}")
    assert main(["replay", str(bad)]) == 2
    assert "not a reproducer" in capsys.readouterr().err


def test_a_collision_stage_divergence_no_ablation_removes_is_still_contact_generation(fresh_mjx, monkeypatch):
    """The drill-down saw other contacts from the same state; when no ablation passes (here the
    only one tried changes nothing), the cause says so instead of 'genuine discrepancy'."""
    from mjxdiff.compare import diagnose

    contact_distance(monkeypatch)
    monkeypatch.setattr(diagnose, "ABLATIONS", (("integration", "nothing changed", lambda m: None),))
    result = run_scenario(load_scenario("primitives_on_plane"), SweepConfig(seed=0, batch=4, diagnose="full"))
    assert result.status == "fail" and result.diagnosis["drill_down"]["first_stage"] == "collision"
    cause = result.diagnosis["cause"]
    assert cause["cause"] == "contact generation" and cause["ablation"] is None
    assert "drill-down: geoms" in cause["evidence"] and "something else differs as well" in result.message


CAPSULE_ON_PLANE = ("<mujoco><option cone='{cone}'/><worldbody><geom type='plane' size='1 1 .1'/>"
                    "<body pos='0 0 0.04' euler='1.4 0.3 0.7'><freejoint/><geom type='capsule' size='0.05 0.1'/>"
                    "</body></worldbody></mujoco>")


@pytest.mark.parametrize("cone, differs", [("pyramidal", True), ("elliptic", False)])
def test_the_drill_down_compares_contact_tangents_where_they_turn_the_friction_cone(cone, differs):
    """MJX's plane-capsule tangent frame is not C's (a known divergence): a pyramidal cone turns
    with it, so the drill-down names the collision stage and the tangent frame; an elliptic cone
    with isotropic friction does not care, and the contacts agree."""
    import mujoco

    from mjxdiff.compare import diagnose

    m = mujoco.MjModel.from_xml_string(CAPSULE_ON_PLANE.format(cone=cone))
    drill = diagnose.drill_down(m, m.qpos0, np.zeros(m.nv), np.zeros(0), np.zeros(0), 0.0)
    if differs:
        assert drill.first_stage == "collision", drill
        assert "(plane-capsule: C 1, MJX 1 contacts; tangent frame differs by" in drill.object, drill
    else:
        assert drill.first_stage != "collision", drill


def test_each_stage_is_judged_by_its_own_tolerance_under_float32(fresh_mjx, monkeypatch):
    """The bias force 0.05% too large: float64's one threshold (1e-9 of the field's scale) names
    the bias stage; float32's per-stage tolerances (MuJoCo's parity method: forces 1e-3 + 1e-3 of
    the scale) let it pass as float32 rounding, where the uniform 1e-4 would have named it, and
    the bound reported is that stage's."""
    import mujoco

    from mjxdiff.compare import diagnose
    from mjxdiff.input.precision import THRESHOLDS

    orig = mjx_smooth.rne
    monkeypatch.setattr(mjx_smooth, "rne", lambda m, d, *a, **k: (lambda d: d.replace(
        qfrc_bias=d.qfrc_bias * (1 + 5e-4)))(orig(m, d, *a, **k)))
    m = mujoco.MjModel.from_xml_string(
        "<mujoco><worldbody><body pos='0 0 1'><joint name='j' type='hinge' axis='0 1 0'/>"
        "<geom type='capsule' fromto='0 0 0 0 0 -0.5' size='0.03' mass='1'/></body></worldbody>"
        "<actuator><motor joint='j' name='m'/></actuator></mujoco>")
    state = (np.array([0.7]), np.array([1.5]), np.zeros(0), np.array([0.3]), 0.0)
    f64 = diagnose.drill_down(m, *state, precision="float64")
    f32 = diagnose.drill_down(m, *state, precision="float32")
    assert (f64.first_stage, f64.first_field) == ("bias", "qfrc_bias"), f64
    bias = next(s for s in f32.fields if s.field == "qfrc_bias")
    assert f32.first_stage is None and 1e-4 < bias.error < 1e-3, f32
    atol, rtol = THRESHOLDS["float32"].stage_tolerance["bias"]
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:], d.ctrl[:] = state[0], state[1], state[3]
    mujoco.mj_forward(m, d)
    assert bias.bound == pytest.approx(atol + rtol * np.abs(d.qfrc_bias).max())


STIFF_SERVO = """<mujoco><worldbody><body pos="0 0 1"><joint name="a" type="hinge" axis="0 1 0"/>
  <geom type="capsule" fromto="0 0 0 0.05 0 0" size="0.005" mass="0.001"/></body></worldbody>
  <actuator><position joint="a" kp="100000" kv="10"/></actuator></mujoco>"""


def test_the_float32_actuator_bound_covers_float32_arithmetic_that_the_stage_tolerance_does_not():
    """A stiff position servo (kp 1e5): its force computed in float32 from C's own length,
    velocity and control (as a float32 engine computes it) is off by more than the actuation
    stage's tolerance (1e-3 + 1e-3 of the force) in some states, so a float32 drill-down would
    name the actuation stage for rounding alone; within the rounding bound in every state."""
    import mujoco

    from mjxdiff.compare import diagnose
    from mjxdiff.input.precision import THRESHOLDS

    m = mujoco.MjModel.from_xml_string(STIFF_SERVO)
    d = mujoco.MjData(m)
    rng = np.random.default_rng(0)
    f32 = np.float32
    beyond_stage = 0
    for _ in range(50):
        d.qpos[:], d.qvel[:] = rng.uniform(-3, 3, 1), rng.uniform(-2, 2, 1)
        d.ctrl[:] = d.qpos + rng.normal(0, 1e-4, 1)
        mujoco.mj_forward(m, d)
        kp, kv = f32(m.actuator_gainprm[0, 0]), f32(-m.actuator_biasprm[0, 2])
        force32 = kp * f32(d.ctrl[0]) - kp * f32(d.actuator_length[0]) - kv * f32(d.actuator_velocity[0])
        gap = abs(float(force32) - d.actuator_force[0])
        assert gap <= diagnose.float32_rounding(m, d)["actuator_force"][0], (gap, d.qpos)
        beyond_stage += gap > THRESHOLDS["float32"].stage_bound("actuation", abs(d.actuator_force[0]))
    assert beyond_stage >= 10, beyond_stage  # 0 would leave the bound untested


class _LimitedPendulum:
    """MuJoCo C as the engine under test, its hinge limited to |q| < 0.3 rad where C's is free: the
    constraint stage differs at states past 0.3 rad and nowhere else (an injected difference that
    comes and goes with the state)."""

    name = "c-limited"

    def forward(self, m, d, fields):
        import mujoco

        from mjxdiff.engine.engines import CEngine

        limited = mujoco.MjModel.from_xml_string(PENDULUM.replace('range="-3 3"', 'range="-0.3 0.3"'))
        return CEngine().forward(limited, d, fields)


PENDULUM = """<mujoco><compiler angle="radian"/><option timestep="0.01"/><worldbody><body>
  <joint name="hinge" type="hinge" axis="0 1 0" limited="true" range="-3 3"/>
  <geom type="capsule" fromto="0 0 0 0 0 -1" size="0.05"/></body></worldbody></mujoco>"""


def test_where_every_stage_agrees_at_the_failing_state_the_drill_down_names_the_last_state_that_differs():
    """A pendulum swinging down from 0.5 rad: while the engine under test's limit pushes (past 0.3
    rad, moving out), its constraint stage differs, and agrees from the step it stops; a failure
    seen after that is traced back to the last state where the limit pushed."""
    import dataclasses

    import mujoco

    from mjxdiff.engine.engines import CEngine
    from mjxdiff.input.inputs import BatchedInputs
    from mjxdiff.compare.result import ScenarioResult
    from mjxdiff.runner.followup import DRILL_BACK, _earlier_difference

    m = mujoco.MjModel.from_xml_string(PENDULUM)
    limited = mujoco.MjModel.from_xml_string(PENDULUM.replace('range="-3 3"', 'range="-0.3 0.3"'))
    steps = 40
    inputs = BatchedInputs(qpos=np.array([[0.5]]), qvel=np.zeros((1, 1)), act=np.zeros((1, 0)),
                           ctrl=np.zeros((1, steps, 0)), models=(m,), factors={}, seed=0)
    traj_c = CEngine().rollout(inputs)

    def pushes(k: int) -> bool:  # the limit's force at the state before step k
        d = mujoco.MjData(limited)
        d.qpos[:], d.qvel[:] = (traj_c.qpos[0, k - 1], traj_c.qvel[0, k - 1]) if k else (inputs.qpos[0], 0)
        mujoco.mj_forward(limited, d)
        return bool(np.abs(d.qfrc_constraint).max() > 1e-6)

    last = max(k for k in range(steps) if pushes(k))
    assert pushes(0) and last + 6 < steps
    failing = ScenarioResult(name="pendulum", status="fail", message="", first_divergence=dict(member=0, step=last + 6))
    earlier = _earlier_difference(failing, inputs, traj_c, "float64", _LimitedPendulum())
    assert earlier is not None and (earlier.step, earlier.first_stage) == (last, "constraint"), earlier
    # out of reach: nothing differs in the DRILL_BACK states before a later failure
    late = dataclasses.replace(failing, first_divergence=dict(member=0, step=last + 1 + DRILL_BACK))
    assert _earlier_difference(late, inputs, traj_c, "float64", _LimitedPendulum()) is None


def test_a_bias_bug_beside_a_known_contact_approximation_is_named_and_not_labelled_known(fresh_mjx, monkeypatch):
    """primitive_pairs' first state: MJX's box-box manifold puts the table's contacts 0.28 mm from C's
    (a catalogued approximation), so the collision stage differs first. Unmodified, nothing else
    differs, and the failure a sweep would see there is labelled ``box-box-manifold``; with MJX's
    bias forces 1% high (a stage that reads no contact) the drill-down names the bias stage beside
    the contacts, and no contact entry labels it (a mutation of MJX's com_vel was labelled so)."""
    import dataclasses

    from _preconditions import precondition
    from mjxdiff.compare import diagnose, known
    from mjxdiff.input.inputs import make_inputs
    from mjxdiff.input.scenario import load_model

    scenario = load_scenario("primitive_pairs")
    m = load_model(scenario)
    inputs = make_inputs(scenario, m, seed=0, batch=1, steps=1)
    state = (inputs.qpos[0], inputs.qvel[0], inputs.act[0], inputs.ctrl[0, 0], 0.0)

    def failing(drill):
        return dict(name="primitive_pairs", status="fail", message="", info=dict(impl="mjx"),
                    diagnosis=dict(drill_down=dataclasses.asdict(drill)))

    clean = diagnose.drill_down(inputs.models[0], *state)
    precondition(clean.first_stage == "collision" and clean.contact["pair"] == "box-box", "the box-box manifold")
    assert clean.beside_contacts is None
    assert known.match(failing(clean)).id == "box-box-manifold"
    rne = mjx_smooth.rne
    monkeypatch.setattr(mjx_smooth, "rne", lambda m, d, *a, **k: (lambda r: r.replace(
        qfrc_bias=r.qfrc_bias * 1.01))(rne(m, d, *a, **k)))
    bugged = diagnose.drill_down(inputs.models[0], *state)
    assert bugged.first_stage == "collision" and bugged.beside_contacts["stage"] == "bias", bugged.beside_contacts
    assert "apart from contacts: qfrc_bias (bias, " in diagnose.first_fields(bugged)
    assert known.match(failing(bugged)) is None


def test_a_drill_down_names_its_element_as_data_a_tendon_by_its_kind_of_path():
    """What catalogue entries match on (tendon-wrap-sidesite: a spatial tendon that wraps a geom on a
    sidesite's side), from the tendons scenario's five tendons."""
    import mujoco

    from mjxdiff.compare import diagnose
    from mjxdiff.input.scenario import load_model

    m = load_model(load_scenario("tendons"))
    kinds = {mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_TENDON, t): diagnose._element(m, "ten_length", t)["type"]
             for t in range(m.ntendon)}
    assert kinds == dict(coupling="fixed", cable="spatial", lift="spatial", flexor="spatial",
                         extensor="spatial-sidesite")
    assert diagnose._element(m, "qfrc_bias", 0)["kind"] == "joint" and diagnose._element(m, "xpos", 1) is None


@pytest.mark.parametrize("first_stage", [None, "integration", "constraint"])
def test_an_integration_ablation_names_the_cause_only_where_every_forward_stage_agrees(first_stage):
    """A ball-joint limit margin MJX ignored was blamed on "integration (passes with timestep / 4)":
    the finer rollout never entered the limit band, while the drill-down from C's state had found
    qfrc_constraint of the shoulder. A forward stage that differs outranks the integration ablation."""
    from mjxdiff.compare import diagnose

    drill = diagnose.DrillDown(member=1, step=77, first_stage=first_stage, object="joint 'shoulder'", fields=(),
                               first_field=None if first_stage is None else "qfrc_constraint")
    cause = dict(cause="integration", ablation="timestep / 4", tried=[dict(ablation="timestep / 4", passed=True)])
    found = diagnose.reconcile_cause(cause, drill)
    if first_stage == "constraint":
        assert found["cause"] == diagnose.GENUINE and found["ablation"] is None
        assert found["steered_clear"] == "timestep / 4" and "in constraint (qfrc_constraint" in found["evidence"]
        assert found["tried"] == cause["tried"]
    else:
        assert found == cause
    contacts = dict(cause="contact generation", ablation="contacts disabled", tried=[])
    assert (diagnose.reconcile_cause(contacts, drill) == contacts) is (first_stage is None)
    assert diagnose.reconcile_cause(cause, None) == cause


def test_contacts_disabled_names_the_cause_only_where_the_difference_can_come_from_contacts():
    """A touch sensor's ray flipped for the contact's second body passed with contacts disabled
    (both engines then read 0): the first stage to differ, sensors, is not contact generation's.
    Nor is constraint, now that a contact's parameters (solref, solimp, ...) are compared at
    collision: a slip in the solver's line search or in the impedance passes with contacts
    disabled too (no contact, no rows to solve), and showed as "contact generation" before."""
    from mjxdiff.compare import diagnose

    contacts = dict(cause="contact generation", ablation="contacts disabled", tried=[])
    for stage, explained in (("sensors", False), ("passive", False), ("collision", True), ("constraint", False)):
        drill = diagnose.DrillDown(member=0, step=3, first_stage=stage, first_field="x", object="y", fields=())
        found = diagnose.reconcile_cause(contacts, drill)
        assert (found == contacts) is explained, stage
        assert explained or (found["cause"] == diagnose.GENUINE and found["steered_clear"] == "contacts disabled")


def test_a_contact_s_mixed_parameters_are_named_at_collision(monkeypatch, fresh_mjx):
    """A contact's solref, solimp and friction parameters are part of what the collision stage
    compares: two geoms of equal priority mixing their solref with each other's weight (the
    solmix source mutation) are named at collision, the floor-ball pair, by the parameter
    that differs, rather than first at constraint (qfrc_constraint). Unmodified, the same state
    has no differing stage."""
    import mujoco

    from mjxdiff.compare import diagnose
    from mjxdiff.input.scenario import load_model
    from test_parameter_families import solmix_swapped

    m = load_model(load_scenario("contact_parameters"))
    d = mujoco.MjData(m)
    for _ in range(60):  # the ball (solmix 2) rests on the floor (solmix 1), both priority 1
        mujoco.mj_step(m, d)
    state = (d.qpos, d.qvel, d.act, d.ctrl, d.time)
    clean = diagnose.drill_down(m, *state, qacc_warmstart=d.qacc_warmstart)
    assert clean.first_stage is None, diagnose.first_fields(clean)
    solmix_swapped(monkeypatch)
    bugged = diagnose.drill_down(m, *state, qacc_warmstart=d.qacc_warmstart)
    assert bugged.first_stage == "collision" and bugged.contact["geoms"] == ["floor", "ball"], bugged.contact
    assert bugged.contact["part"] in ("solref", "solimp") and bugged.contact["c"] == bugged.contact["mjx"] == 1
