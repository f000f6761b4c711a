"""Hypothesis strategies: models compile, MJX accepts or rejects them as labelled,
draws stay in range, and everything shrinks to the simple case."""

import itertools

import jax
import mujoco
import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, find, given, settings
from hypothesis import strategies as st
from hypothesis.errors import InvalidArgument
from mujoco import mjx

from mjxdiff import compat
from mjxdiff.tools import mjcf_spec, strategies
from mjxdiff.compare.support import refused_features
from mjxdiff.tools.strategies import (
    CONTROL_FAMILIES,
    DEFAULT_OPTIONS,
    PERTURBATION_FIELDS,
    SUPPORTED_PAIRS,
    UNSUPPORTED_FEATURES,
    UNSUPPORTED_PAIRS,
    control_sequences,
    initial_states,
    mjcf_models,
    pair_supported,
    parameter_perturbations,
)

FAST = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
FEW = settings(max_examples=5, deadline=None, suppress_health_check=[HealthCheck.too_slow])
ONE = settings(max_examples=1, deadline=None, database=None, phases=[Phase.generate])
# find() with an always-true condition: generate, then shrink (explain would only re-run it)
MINIMAL = settings(database=None, deadline=None, phases=[Phase.generate, Phase.shrink],
                   suppress_health_check=list(HealthCheck))

FIXED_XML = """
<mujoco>
  <compiler angle="radian"/>
  <worldbody>
    <body name="a" pos="0 0 1"><joint name="h" type="hinge" range="-0.5 0.5" limited="true"/><geom size=".1"/>
      <body name="b" pos="0 0 -.3"><joint type="ball" range="0 0.3" limited="true"/><geom size=".1"/></body></body>
    <body name="f" pos="1 0 1"><freejoint/><geom type="box" size=".1 .1 .1"/></body>
    <body name="s" pos="2 0 1"><joint name="sl" type="slide" range="-0.1 0.2" limited="true"/><geom size=".1"/></body>
  </worldbody>
  <actuator>
    <motor joint="h" ctrlrange="0.5 3" ctrllimited="true"/>
    <motor joint="h"/>
    <general joint="sl" dyntype="integrator" actlimited="true" actrange="-0.2 0.1" ctrlrange="-1 1"/>
  </actuator>
</mujoco>"""


FIXED = mujoco.MjModel.from_xml_string(FIXED_XML)


@pytest.fixture(scope="module")
def fixed_model():
    return mujoco.MjModel.from_xml_string(FIXED_XML)


def _mjx_stage_error(m: mujoco.MjModel, stage: str) -> NotImplementedError | None:
    """Runs MJX up to ``stage`` (put_model, make_data, step: traced with eval_shape, no compile)."""
    try:
        mx = mjx.put_model(m)
        if stage in ("make_data", "step"):
            dx = mjx.make_data(mx)
            if stage == "step":
                jax.eval_shape(mjx.step, mx, dx)
    except NotImplementedError as e:
        return e
    return None


def _steps_in_c(m: mujoco.MjModel, n: int = 3) -> None:
    d = mujoco.MjData(m)
    for _ in range(n):
        mujoco.mj_step(m, d)
    assert np.isfinite(d.qpos).all() and np.isfinite(d.qvel).all()


# --- models ------------------------------------------------------------------------


@FAST
@given(mjcf_models())
def test_mjx_only_models_compile_step_in_c_and_put_in_mjx(mm):
    m = mm.model()
    assert (m.nbody - 1, m.ngeom) == (mm.nbody, mm.ngeom), mm.xml
    assert mm.unsupported_feature is None and mm.unsupported is None
    _steps_in_c(m)
    mx = mjx.put_model(m)  # raises NotImplementedError on anything MJX lacks
    mjx.make_data(mx)  # condim 1 under an elliptic cone is only caught here


@FEW
@given(mjcf_models(max_bodies=2))
def test_mjx_only_models_trace_mjx_step(mm):
    # eval_shape traces mjx.step (where NotImplementedError and shape bugs surface) without compiling
    m = mm.model()
    mx = mjx.put_model(m)
    jax.eval_shape(mjx.step, mx, mjx.make_data(mx))


@FAST
@given(mjcf_models(unsupported=True))
def test_unsupported_models_raise_named_error(mm):
    m = mm.model()
    _steps_in_c(m)
    feature = mm.unsupported
    assert feature is not None and feature.name in mm.features
    err = _mjx_stage_error(m, feature.stage)
    assert err is not None, f"{feature.name}: MJX accepted it\n{mm.xml}"
    assert feature.message in str(err), (feature, str(err))


@pytest.mark.parametrize("feature", UNSUPPORTED_FEATURES, ids=lambda f: f.name)
def test_each_unsupported_feature_is_what_the_table_says_on_this_version(feature, monkeypatch):
    """The per-version table (``since``, ``refused_since``) on the installed MuJoCo/MJX: a feature
    C cannot express is a schema error a sweep reports as unsupported; one this MJX accepts is
    accepted at every stage; one it refuses raises NotImplementedError at its stage, nothing
    earlier. (Run on every release of the CI matrix.)"""
    mjx_release = compat._release(compat.installed()["mujoco-mjx"])
    monkeypatch.setattr(strategies, "refused_features", lambda: UNSUPPORTED_FEATURES)  # draw it regardless
    stages = ("put_model", "make_data", "step")

    @ONE
    @given(mjcf_models(unsupported=feature.name, max_bodies=2))
    def check(mm):
        assert mm.unsupported_feature == feature.name
        if compat._release(feature.since) > compat.matching_mujoco(mjx_release):
            with pytest.raises(ValueError) as e:
                mm.model()
            assert compat.later_feature(str(e.value)), str(e.value)
            return
        m = mm.model()
        _steps_in_c(m)
        if compat._release(feature.refused_since) > mjx_release:
            assert all(_mjx_stage_error(m, stage) is None for stage in stages), feature
            return
        for stage in stages[:stages.index(feature.stage)]:  # nothing raises before the documented stage
            assert _mjx_stage_error(m, stage) is None, (feature, stage)
        err = _mjx_stage_error(m, feature.stage)
        assert err is not None, feature
        if mjx_release >= (3, 14):  # the messages the table quotes (MJX 3.13 words the discrete one otherwise)
            assert feature.message in str(err), (feature, err)

    check()
    assert (feature in refused_features()) == (compat._release(feature.refused_since) <= mjx_release and
                                               compat._release(feature.since) <= compat.matching_mujoco(mjx_release))


def test_refused_features_follow_the_measured_releases():
    names = {v: {f.name for f in refused_features(v)} for v in ("3.3.0", "3.3.5", "3.9.0", "3.17.0")}
    assert names["3.17.0"] == {f.name for f in UNSUPPORTED_FEATURES}
    assert {"flex", "insidesite sensor", "dcmotor actuator", "diagexact flag", "pid actuator"}.isdisjoint(
        names["3.3.0"])
    assert {"flex", "insidesite sensor"} <= names["3.3.5"] and "dcmotor actuator" not in names["3.3.5"]
    assert {"dcmotor actuator", "diagexact flag"} <= names["3.9.0"]
    assert "pid actuator" not in names["3.9.0"] and "speculative flag" not in names["3.9.0"]
    assert names["3.3.0"] < names["3.3.5"] < names["3.9.0"] < names["3.17.0"]


def test_minimal_model_is_one_body_one_geom_default_options():
    mm = find(mjcf_models(), lambda x: True, settings=MINIMAL)
    assert (mm.nbody, mm.ngeom) == (1, 1)
    assert mm.features == ("hinge joint", "sphere geom")
    m = mm.model()
    assert (m.nu, m.ntendon, m.neq, m.nsensor) == (0, 0, 0, 0)
    assert m.opt.timestep == DEFAULT_OPTIONS["timestep"]
    assert m.opt.integrator == mujoco.mjtIntegrator.mjINT_EULER
    assert m.opt.cone == mujoco.mjtCone.mjCONE_PYRAMIDAL
    assert m.opt.solver == mujoco.mjtSolver.mjSOL_NEWTON
    assert (m.opt.iterations, m.opt.tolerance) == (DEFAULT_OPTIONS["iterations"], DEFAULT_OPTIONS["tolerance"])


def test_options_false_gives_defaults_and_mapping_overrides():
    mm = find(mjcf_models(options=False, max_bodies=1), lambda x: True, settings=MINIMAL)
    assert "<option " in mm.xml and mm.model().opt.iterations >= 20 and mm.model().opt.tolerance <= 1e-8
    mm = find(mjcf_models(options={"integrator": "RK4"}, max_bodies=1), lambda x: True, settings=MINIMAL)
    assert mm.model().opt.integrator == mujoco.mjtIntegrator.mjINT_RK4


@FAST
@given(mjcf_models(mjx_only=False, max_bodies=3))
def test_unrestricted_models_compile_and_step_in_c(mm):
    _steps_in_c(mm.model())


@FAST
@given(mjcf_models(contacts=False, joint_types=("free",), geom_types=("box", "mesh"), max_bodies=3))
def test_restricting_arguments(mm):
    m = mm.model()
    assert not m.geom_contype.any() and not m.geom_conaffinity.any()
    assert (m.jnt_type == mujoco.mjtJoint.mjJNT_FREE).all() and (m.body_parentid[1:] == 0).all()
    body_geoms = set(m.geom_type[m.geom_bodyid > 0].tolist())
    assert body_geoms <= {int(mujoco.mjtGeom.mjGEOM_BOX), int(mujoco.mjtGeom.mjGEOM_MESH)}


def test_invalid_arguments_are_rejected():
    for kwargs in ({"joint_types": ("hinge", "universal")}, {"geom_types": ("sdf",)}, {"max_bodies": 0},
                   {"unsupported": True, "mjx_only": False}, {"unsupported": "no such feature"}):
        with pytest.raises(InvalidArgument):
            find(mjcf_models(**kwargs), lambda x: True, settings=ONE)


def test_supported_pairs_table_matches_installed_mjx():
    """Re-measures SUPPORTED_PAIRS: a static geom of one type, a free body with the other, mjx.put_model."""
    sizes = {"sphere": "0.1", "capsule": "0.05 0.1", "box": "0.1 0.1 0.1", "ellipsoid": "0.1 0.08 0.06",
             "cylinder": "0.05 0.1", "plane": "0 0 1"}

    def geom(t):
        return {"mesh": '<geom type="mesh" mesh="m"/>', "hfield": '<geom type="hfield" hfield="h"/>'}.get(
            t, f'<geom type="{t}" size="{sizes.get(t)}"/>')

    types = strategies._TYPE_ORDER
    for a, b in itertools.combinations_with_replacement(types, 2):
        if {a, b} <= {"plane", "hfield"}:
            continue
        static = a in ("plane", "hfield")
        xml = f"""<mujoco><asset><mesh name="m" vertex="0 0 0 .1 0 0 0 .1 0 0 0 .1"/>
          <hfield name="h" nrow="2" ncol="2" size="1 1 .1 .1" elevation="0 0 0 0"/></asset><worldbody>
          {geom(a) if static else f'<body pos="0 0 .5"><freejoint/>{geom(a)}</body>'}
          <body pos=".05 0 .7"><freejoint/>{geom(b)}</body></worldbody></mujoco>"""
        err = _mjx_stage_error(mujoco.MjModel.from_xml_string(xml), "put_model")
        assert (err is None) == pair_supported(a, b), (a, b, err)
        assert ((a, b) in SUPPORTED_PAIRS) != ((a, b) in UNSUPPORTED_PAIRS), (a, b)


def test_collision_masks_allow_exactly_the_supported_pairs():
    masks = mjcf_spec._MASKS
    for a, b in itertools.combinations_with_replacement(masks, 2):
        if a == b == "plane":
            continue  # planes are static: never tested against each other
        assert bool(masks[a] & masks[b]) == pair_supported(a, b), (a, b)


# --- states, controls, parameters --------------------------------------------------


@FAST
@given(st.data())
def test_initial_states_are_normalised_and_within_limits(data):
    mm = data.draw(mjcf_models(max_bodies=3, unsupported=False), label="model")
    m = mm.model()
    state = data.draw(initial_states(m, batch=3), label="state")
    assert state.qpos.shape == (3, m.nq) and state.qvel.shape == (3, m.nv) and state.act.shape == (3, m.na)
    assert np.isfinite(state.qpos).all() and (np.abs(state.qvel) <= 1.0).all()
    _check_state(m, state.qpos)


def _check_state(m: mujoco.MjModel, qpos: np.ndarray) -> None:
    for j in range(m.njnt):
        adr, jtype = int(m.jnt_qposadr[j]), int(m.jnt_type[j])
        if jtype in (mujoco.mjtJoint.mjJNT_FREE, mujoco.mjtJoint.mjJNT_BALL):
            q = qpos[:, adr + 3 * (jtype == mujoco.mjtJoint.mjJNT_FREE):][:, :4]
            np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, rtol=1e-12, err_msg=f"joint {j}")
            if m.jnt_limited[j] and jtype == mujoco.mjtJoint.mjJNT_BALL:
                angle = 2 * np.arctan2(np.linalg.norm(q[:, 1:], axis=-1), np.abs(q[:, 0]))
                assert (angle < m.jnt_range[j, 1]).all(), (j, angle)
        elif m.jnt_limited[j]:
            lo, hi = m.jnt_range[j]
            assert ((qpos[:, adr] > lo) & (qpos[:, adr] < hi)).all(), (j, qpos[:, adr], lo, hi)


@FAST
@given(initial_states(FIXED, batch=4, qpos_scale=2.0, qvel_scale=3.0, act_scale=1.0))
def test_initial_states_fixed_model_shapes_limits(state):
    m = mujoco.MjModel.from_xml_string(FIXED_XML)
    assert [x.shape for x in state] == [(4, m.nq), (4, m.nv), (4, m.na)]
    _check_state(m, state.qpos)
    lo, hi = m.actuator_actrange[2]
    assert ((state.act >= lo) & (state.act <= hi)).all()


def test_initial_states_shrink_to_qpos0_and_rest(fixed_model):
    state = find(initial_states(fixed_model), lambda s: True, settings=MINIMAL)
    np.testing.assert_array_equal(state.qpos, fixed_model.qpos0)
    assert state.qpos.shape == (fixed_model.nq,)
    assert not state.qvel.any() and not state.act.any()


@FAST
@given(st.data())
def test_controls_within_ctrlrange_and_fixed_shape(data):
    m = data.draw(mjcf_models(max_bodies=2), label="model").model()
    steps = data.draw(st.integers(1, 40), label="steps")
    ctrl = data.draw(control_sequences(m, steps, batch=2), label="ctrl")
    assert ctrl.shape == (2, steps, m.nu)
    lo, hi = strategies._ctrl_bounds(m)
    assert ((ctrl >= lo) & (ctrl <= hi)).all()


@pytest.mark.parametrize("family", CONTROL_FAMILIES)
def test_control_families_stay_in_range(fixed_model, family):
    @settings(max_examples=5, deadline=None, database=None)
    @given(control_sequences(fixed_model, 120, family=family))
    def check(ctrl):
        assert ctrl.shape == (120, fixed_model.nu)
        assert (ctrl[:, 0] >= 0.5).all() and (ctrl[:, 0] <= 3).all()  # limited [0.5, 3]
        assert (np.abs(ctrl[:, 1:]) <= 1).all()  # unlimited: [-1, 1]

    check()


def test_controls_shrink_to_zero_and_short_horizons(fixed_model):
    ctrl = find(control_sequences(fixed_model, st.integers(1, 50)), lambda c: True, settings=MINIMAL)
    assert ctrl.shape == (1, fixed_model.nu)
    # zero where 0 is in range; the nearest bound (0.5) for the actuator limited to [0.5, 3]
    np.testing.assert_array_equal(ctrl, [[0.5, 0.0, 0.0]])


@FAST
@given(st.data())
def test_parameter_perturbations_shapes_and_bounds(data):
    m = data.draw(mjcf_models(max_bodies=2), label="model").model()
    factors = data.draw(parameter_perturbations(m, max_relative=0.2, batch=2), label="factors")
    assert set(factors) == set(PERTURBATION_FIELDS)
    for name, f in factors.items():
        assert f.shape == (2, *PERTURBATION_FIELDS[name](m)), name
        assert ((f >= 0.8) & (f <= 1.2)).all(), name


def test_parameter_perturbations_shrink_to_ones(fixed_model):
    factors = find(parameter_perturbations(fixed_model, fields=("body_mass", "gravity")), lambda f: True,
                   settings=MINIMAL)
    assert factors["body_mass"].shape == (fixed_model.nbody,) and factors["gravity"].shape == ()
    assert all((f == 1).all() for f in factors.values())


@pytest.mark.parametrize("feature", ["joint springref", "limit solref", "limit solimp", "limit margin",
                                     "affine gain", "affine bias", "filterexact dynamics", "tendon frictionloss",
                                     "joint equality polycoef", "impratio", "fluid drag",
                                     "tendon pulley", "tendon geom wrap", "tendon wrap sidesite",
                                     "ball joint actuator", "free joint actuator", "jointinparent actuator",
                                     "mocap body", "ballangvel sensor", "clock sensor", "actuatorpos sensor"])
def test_fuzz_reaches_the_parameter_families_the_scenarios_exercise(feature):
    """The generated models move the same parameters away from their defaults as the bundled
    parameter-family scenarios, so that fuzz can find bugs there too."""
    mm = find(mjcf_models(max_bodies=3), lambda x: feature in x.features,
              settings=settings(max_examples=2000, database=None, deadline=None, phases=[Phase.generate],
                                suppress_health_check=list(HealthCheck)))
    mm.model()  # compiles in MuJoCo C
