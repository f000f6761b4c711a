"""Properties of MJX against MuJoCo C (issue 4), on generated models, with both real engines.

* **One step**: from the same state and control, one ``mjx.step`` lands where one
  ``mujoco.mj_step`` does, to float64 rounding, for generated MJX-supported models (the
  features of :data:`mjxdiff.tools.fuzz.KNOWN_DIVERGENCES` left out, and contacts only between the
  geom pairs MJX collides exactly: :data:`EXACT_PAIR_MASKS`); a 0.1% error injected into MJX's
  bias force fails that check.
* **Invariants**: quaternions of free and ball joints stay unit over an MJX rollout; time
  advances by exactly one timestep per step; a conservative system conserves energy in both
  engines; without gravity and at rest, the bias force is zero in both engines.
* **Unsupported models** are reported by :func:`mjxdiff.testing.compare` as ``unsupported``,
  naming the feature, never as a crash.
* **Findings**, each shrunk to a strict xfail that passes (and so fails) once fixed: MJX's
  ball/free spring has a dead zone below ~2e-8 rad; MJX ignores ``*_sameframe``; MJX's RK4
  is second-order on ball joints (slow); compare() says ``error`` for the two features MJX
  rejects after put_model.

Every model structure costs one XLA compile (seconds on 2 cores), so the properties over
generated models take few examples and check a fixed-size batch of states per model
(``vmap``: one compile per model); the others use one fixed model whose array shapes
never change, so their examples share one compile. Units are MuJoCo's (m, rad, s, J).
"""

import copy
import functools
import itertools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from hypothesis import Phase, assume, given, note, settings
from hypothesis import strategies as st
from mujoco import mjx
from mujoco.mjx._src import smooth as mjx_smooth

from _preconditions import precondition
from mjxdiff.compat import jit_for_few_calls
from mjxdiff.engine.engines import energy as mjx_energy
from mjxdiff.tools.fuzz import model_strategy
from mjxdiff.input.inputs import quat_mul, rotvec_quat
from mjxdiff.compare.noise import converge_solver
from mjxdiff.tools.strategies import UNSUPPORTED_FEATURES, State, control_sequences, initial_states, mjcf_models
from mjxdiff.testing import compare

# ---------------------------------------------------------------------------
# MJX and C, batched over states of one model.

#: States checked per generated model in the one-step property (one compile serves them all).
STATES_PER_MODEL = 8


def _canonical_ints(dx: mjx.Data) -> mjx.Data:
    """``dx`` with integer leaves in JAX's default int dtype: ``mjx.step`` returns int64 under x64
    where ``make_data`` gave int32, and a step fed its own output would otherwise recompile."""
    int_t = jnp.asarray(0).dtype
    return jax.tree.map(lambda x: x.astype(int_t) if jnp.issubdtype(x.dtype, jnp.integer) else x, dx)


def batched_data(m: mujoco.MjModel, state: State, ctrl: np.ndarray | None = None,
                 time: np.ndarray | None = None) -> tuple[mjx.Model, mjx.Data]:
    """``mjx.put_model(m)`` and a ``mjx.Data`` whose every leaf has a leading batch axis B.

    Args:
      m: the model.
      state: ``(B, nq)``, ``(B, nv)``, ``(B, na)`` initial state.
      ctrl: ``(B, nu)`` controls (default zeros).
      time: ``(B,)`` initial times, s (default zeros).
    """
    mx = mjx.put_model(m)
    d0 = _canonical_ints(mjx.make_data(mx))
    nbatch = state.qpos.shape[0]
    ctrl = np.zeros((nbatch, m.nu)) if ctrl is None else ctrl
    time = np.zeros(nbatch) if time is None else time
    dx = jax.vmap(lambda q, v, a, u, t: d0.replace(qpos=q, qvel=v, act=a, ctrl=u, time=t))(
        *(jnp.asarray(x, d0.qpos.dtype) for x in (state.qpos, state.qvel, state.act, ctrl, time)))
    # committed to the device, like every jit output: a step fed its own output then hits the
    # same compiled executable as the first step (uncommitted inputs compile a second one)
    return jax.device_put((mx, dx), jax.devices()[0])


def _step_fn():
    """A new jitted ``mjx.step`` of each state in turn (``lax.map``); a new one traces MJX's code
    afresh. Not ``vmap``: jax 0.10.2 on the CPU segfaults executing ``jit(vmap(mjx.step))`` with
    2 or more states of some generated models (two ellipsoids on a ball-jointed body and a
    capsule on a limited hinge, all against a plane: reproducible, while ``lax.map``, a batch of
    one, and mjxdiff's own scanned rollout of the same model run)."""
    return jit_for_few_calls(lambda mx, dx: jax.lax.map(functools.partial(mjx.step, mx), dx))


_mjx_step = _step_fn()


def mjx_one_step(m: mujoco.MjModel, state: State, ctrl: np.ndarray, step=None) -> State:
    """``(B, ...)`` state after one ``mjx.step`` from each of B states (ctrl ``(B, nu)``)."""
    mx, dx = batched_data(m, state, ctrl)
    dx = jax.block_until_ready((step or _mjx_step)(mx, dx))
    return State(qpos=np.asarray(dx.qpos), qvel=np.asarray(dx.qvel), act=np.asarray(dx.act))


def c_one_step(m: mujoco.MjModel, state: State, ctrl: np.ndarray) -> State:
    """``(B, ...)`` state after one ``mujoco.mj_step`` from each of B states (fresh data each)."""
    d = mujoco.MjData(m)
    out = State(*(np.zeros_like(x) for x in state))
    for b in range(state.qpos.shape[0]):
        mujoco.mj_resetData(m, d)
        d.qpos, d.qvel, d.act, d.ctrl = state.qpos[b], state.qvel[b], state.act[b], ctrl[b]
        mujoco.mj_step(m, d)
        out.qpos[b], out.qvel[b], out.act[b] = d.qpos, d.qvel, d.act
    return out


# ---------------------------------------------------------------------------
# 1. One MJX step matches one C step within rounding.

#: One-step tolerance, ``|mjx - c| <= ONE_STEP_ATOL + ONE_STEP_RTOL * |c|`` per component of
#: qpos (m, rad, quaternion), qvel (m/s, rad/s) and act. Measured on unmodified MJX 3.17.0 /
#: MuJoCo 4.0.0, float64, over 55 generated models x 8 states as the property draws them
#: (max_bodies=3; 6 with contacts, 24 with limit/frictionloss rows): worst |mjx - c| 5.2e-13 in
#: qvel, 8.9e-16 in qpos, 0 in act, i.e. 5.2e-5 of the tolerance (a margin of ~2e4; a converged
#: Newton solve leaves ~1e-13, rounding alone ~1e-15). The injected 0.1% bias-force error moves qvel
#: by ~1e-4 (1.1e4 x the tolerance on ROTATING).
ONE_STEP_ATOL = 1e-8
ONE_STEP_RTOL = 1e-8


def excess(x: np.ndarray, c: np.ndarray, atol: float = ONE_STEP_ATOL, rtol: float = ONE_STEP_RTOL) -> np.ndarray:
    """Elementwise ``|x - c| / (atol + rtol |c|)``: above 1 means out of tolerance (NaN stays NaN)."""
    return np.abs(x - c) / (atol + rtol * np.abs(c))


def one_step_mismatches(mjx_state: State, c_state: State) -> list[str]:
    """What is out of one-step tolerance: one line per field (``(B, n)`` arrays), naming the
    worst state (batch member) and component, both values and the excess over tolerance."""
    lines = []
    for field in State._fields:
        x, c = getattr(mjx_state, field), getattr(c_state, field)
        if x.size == 0:
            continue
        r = excess(x, c)
        if not np.all(r <= 1):  # NaN fails too
            b, i = np.unravel_index(np.nanargmax(np.where(np.isnan(r), np.inf, r)), r.shape)
            lines.append(f"{field}[{i}] of state {b}: mjx {x[b, i]!r} vs c {c[b, i]!r}, "
                         f"{r[b, i]:.3g}x the tolerance ({np.sum(~(r <= 1))} components out)")
    return lines


def worst_excess(mjx_state: State, c_state: State) -> float:
    """The largest :func:`excess` over all fields (0 for empty ones)."""
    return max((float(np.max(excess(getattr(mjx_state, f), getattr(c_state, f))))
                for f in State._fields if getattr(mjx_state, f).size), default=0.0)


def check_one_step(m: mujoco.MjModel, state: State, ctrl: np.ndarray, step=None) -> list[str]:
    """Steps both engines once from ``state`` (``(B, ...)``) with ``ctrl`` (``(B, nu)``) and
    returns :func:`one_step_mismatches` (empty when MJX matches C)."""
    return one_step_mismatches(mjx_one_step(m, state, ctrl, step), c_one_step(m, state, ctrl))


#: contype, conaffinity by geom type under which only the pairs that MJX collides as C does (to
#: rounding) can touch: the ground plane with any geom, and sphere with sphere. Measured one step
#: from 8 penetrating states per pair (random orientations; tilts 0-1e-2 rad from flat on the plane):
#: those pairs stay below 1.3e-7 of the one-step tolerance (1.1e-4 for a cylinder 1e-4 rad from
#: flat). The others are known MJX approximations: sphere-capsule and capsule-capsule qvel differ by
#: ~1e-6 (95-150x the tolerance; MJX regularises closest_segment_point by 1e-6, see the notes of
#: scenarios/primitive_pairs.toml), and every pair of sphere, capsule, ellipsoid and cylinder that
#: involves an ellipsoid or a cylinder by ~1e-2 (MJX's SDF gradient descent, scenarios/wip/README.md).
EXACT_PAIR_MASKS = {int(mujoco.mjtGeom.mjGEOM_PLANE): (1, 2), int(mujoco.mjtGeom.mjGEOM_SPHERE): (1, 1)}
OTHER_GEOM_MASK = (2, 0)


def exact_contacts_only(m: mujoco.MjModel) -> mujoco.MjModel:
    """``m`` with contype/conaffinity set per :data:`EXACT_PAIR_MASKS` (other types: OTHER_GEOM_MASK)
    on every geom that could collide; geoms that collide with nothing stay so."""
    for g in np.flatnonzero(m.geom_contype | m.geom_conaffinity):
        m.geom_contype[g], m.geom_conaffinity[g] = EXACT_PAIR_MASKS.get(int(m.geom_type[g]), OTHER_GEOM_MASK)
    return m


def contact_possible(m: mujoco.MjModel) -> bool:
    """Whether some geom pair passes MuJoCo's filters: different bodies not welded together, not
    parent and child (filterparent; the world excepted), matching contype/conaffinity."""
    ct, ca, weld, parent = m.geom_contype, m.geom_conaffinity, m.body_weldid, m.body_parentid
    for i, j in itertools.combinations(range(m.ngeom), 2):
        wi, wj = weld[m.geom_bodyid[i]], weld[m.geom_bodyid[j]]
        if wi == wj or (parent[wi] == wj and wj) or (parent[wj] == wi and wi):
            continue
        if ct[i] & ca[j] or ct[j] & ca[i]:
            return True
    return False


def one_step_model(data, max_bodies: int) -> tuple[mujoco.MjModel, str]:
    """A generated model for the one-step property and its MJCF (before masking).

    :func:`mjxdiff.tools.fuzz.model_strategy` (Euler, no equality, sphere/capsule/ellipsoid/cylinder
    geoms: none of KNOWN_DIVERGENCES), then :func:`exact_contacts_only`; models where C's
    sameframe shortcut drops an offset are rejected (:func:`sameframe_drops_offset`, ~8% of
    draws). Masking may leave no possible contact; MJX 3.17 cannot trace mjx.step with an
    elliptic cone or a touch sensor then (see :func:`mjxdiff.tools.strategies.mjcf_models`), so the
    cone becomes pyramidal (no effect in C without contacts) and a model with a touch sensor is
    rejected.
    """
    mm = data.draw(model_strategy(max_bodies=max_bodies), label="model")
    m = exact_contacts_only(mm.model())
    assume(sameframe_drops_offset(m) is None)
    if not contact_possible(m):
        assume(int(mujoco.mjtSensor.mjSENS_TOUCH) not in m.sensor_type)
        m.opt.cone = mujoco.mjtCone.mjCONE_PYRAMIDAL
    return m, mm.xml


def c_advance(m: mujoco.MjModel, state: State, ctrl: np.ndarray, steps: int) -> State | None:
    """``(B, ...)`` states after ``steps`` ``mj_step`` calls from each of ``state`` with constant
    ``ctrl`` (``(B, nu)``): falling, swinging and landing, so contacts and limits become active.
    None if any member went non-finite or raised a MuJoCo warning (an unstable model)."""
    out = State(*(np.array(x) for x in state))
    d = mujoco.MjData(m)
    for b in range(out.qpos.shape[0]):
        mujoco.mj_resetData(m, d)
        d.qpos, d.qvel, d.act, d.ctrl = state.qpos[b], state.qvel[b], state.act[b], ctrl[b]
        for _ in range(steps):
            mujoco.mj_step(m, d)
        if any(w.number for w in d.warning) or not (np.isfinite(d.qpos).all() and np.isfinite(d.qvel).all()):
            return None
        out.qpos[b], out.qvel[b], out.act[b] = d.qpos, d.qvel, d.act
    return out


#: MJX's math.norm treats a vector whose components are all within 1e-8 of 0 as exactly 0
#: (``jp.allclose(x, 0)``, for safe gradients), so quat_sub, hence the spring torque of a ball or
#: free joint, is exactly 0 for rotations from qpos_spring whose quaternion vector part is that
#: small (under ~2e-8 rad); C applies ``-k * angle``. Found by this property (one step, qvel off by
#: 1.5e-8 for k = 10 N m/rad); see test_mjx_ball_spring_has_a_dead_zone_below_2e_8_rad. States in
#: that band are skipped by the one-step property, not the feature.
SPRING_DEAD_ZONE = 1e-8


def in_spring_dead_zone(m: mujoco.MjModel, qpos: np.ndarray) -> bool:
    """Whether some stiff ball/free joint of ``(B, nq)`` qpos is rotated from qpos_spring by a
    nonzero quaternion whose vector part is within :data:`SPRING_DEAD_ZONE` (MJX: no torque)."""
    for j in np.flatnonzero((m.jnt_stiffness > 0) & (m.jnt_type <= int(mujoco.mjtJoint.mjJNT_BALL))):
        adr = m.jnt_qposadr[j] + (3 if m.jnt_type[j] == int(mujoco.mjtJoint.mjJNT_FREE) else 0)
        spring = m.qpos_spring[adr:adr + 4] * np.array([1, -1, -1, -1])  # its inverse
        vec = np.abs(quat_mul(spring, qpos[:, adr:adr + 4])[:, 1:]).max(axis=1)
        if np.any((vec > 0) & (vec <= SPRING_DEAD_ZONE)):
            return True
    return False


_IDENTITY_QUAT = np.array([1.0, 0.0, 0.0, 0.0])


def sameframe_drops_offset(m: mujoco.MjModel) -> str | None:
    """The first body, geom or site whose ``*_sameframe`` flag makes C drop a nonzero offset, or None.

    MuJoCo's compiler flags a frame as coinciding with its body (or inertia) frame when the offset
    is below its tolerance (rotations up to ~2e-6 rad, measured), and ``mj_kinematics`` then copies
    that frame instead of applying the stored ``pos``/``quat``. MJX ignores the flags and applies
    them: e.g. an inertia frame rotated 4.5e-7 rad gives cinert and qM 6.4e-9 apart (found by this
    property; see test_mjx_ignores_sameframe_of_a_slightly_rotated_inertia). Hypothesis's tiny
    floats make such offsets (a second geom 6e-8 m off axis), so the one-step property skips them.
    """
    BODY, INERTIA, BODYROT, INERTIAROT = (int(mujoco.mjtSameFrame.mjSAMEFRAME_BODY),
                                          int(mujoco.mjtSameFrame.mjSAMEFRAME_INERTIA),
                                          int(mujoco.mjtSameFrame.mjSAMEFRAME_BODYROT),
                                          int(mujoco.mjtSameFrame.mjSAMEFRAME_INERTIAROT))
    for i in range(m.nbody):
        sf = int(m.body_sameframe[i])
        if (sf == BODY and m.body_ipos[i].any()
                or sf in (BODY, BODYROT) and (m.body_iquat[i] != _IDENTITY_QUAT).any()):
            return f"body {i}"
    for kind, n, frame, pos, quat, bodyid in (
            ("geom", m.ngeom, m.geom_sameframe, m.geom_pos, m.geom_quat, m.geom_bodyid),
            ("site", m.nsite, m.site_sameframe, m.site_pos, m.site_quat, m.site_bodyid)):
        for i in range(n):
            sf, b = int(frame[i]), bodyid[i]
            want_pos = {BODY: np.zeros(3), INERTIA: m.body_ipos[b]}.get(sf)
            want_quat = {BODY: _IDENTITY_QUAT, BODYROT: _IDENTITY_QUAT,
                         INERTIA: m.body_iquat[b], INERTIAROT: m.body_iquat[b]}.get(sf)
            if (want_pos is not None and (pos[i] != want_pos).any()
                    or want_quat is not None and (quat[i] != want_quat).any()):
                return f"{kind} {i}"
    return None


#: C steps taken from the generated states before the comparison (drawn; shrinks to 0). Generated
#: states start near qpos0, bodies 0.5 m above the ground, where contacts are rare (6% of states);
#: after 0.3-2 s of C dynamics many rest, roll or bounce on the ground or on each other.
ADVANCE_STEPS = (0, 150, 400)


def _one_step_property(data, max_bodies: int) -> None:
    m, xml = one_step_model(data, max_bodies)
    state = data.draw(initial_states(m, batch=STATES_PER_MODEL), label="states")
    ctrl = data.draw(control_sequences(m, 1, batch=STATES_PER_MODEL), label="ctrl")[:, 0]
    advance = data.draw(st.sampled_from(ADVANCE_STEPS), label="C steps before")
    note(xml)
    state = c_advance(m, state, ctrl, advance)
    assume(state is not None and not in_spring_dead_zone(m, state.qpos))
    # The one step with both solvers converged: stopped at the default tolerance (1e-8), each
    # leaves ~1e-8 of qvel where frictionloss holds a joint still, and they part by 3x ONE_STEP_ATOL
    # there (a generated slide joint with frictionloss after 400 C steps: 2.07e-8 vs 5.15e-8).
    converge_solver(m)
    bad = check_one_step(m, state, ctrl)
    assert not bad, ("one MJX step differs from one C step:\n" + "\n".join(bad)
                     + f"\n(after {advance} C steps; contacts only plane-any and sphere-sphere)\n" + xml)


@pytest.mark.slow  # a compile per example (25 examples cost 6.7 CI minutes, 405 s)
@settings(max_examples=6)
@given(st.data())
def test_one_mjx_step_matches_one_c_step_wide(data):
    """Up to 3 bodies (a compile per model). A narrower twin (2 bodies, 3 examples) ran beside it
    in CI, 37 s, drawing from a subset of the same models: gone, one proof per claim."""
    _one_step_property(data, max_bodies=3)


#: A fixed model whose every joint carries a bias force under gravity: a free box and a ball-joint
#: arm with a hinged forearm (an elbow). No contacts (contype 0), which keeps its compile short;
#: the generated models cover contacts. Shared by the injected-bug test and the invariants below,
#: so one compile of ``jit(vmap(mjx.step))`` serves all of them (shapes never change).
ROTATING_XML = """
<mujoco>
  <option timestep="0.002"/>
  <default><geom contype="0" conaffinity="0"/></default>
  <worldbody>
    <body name="box" pos="0 0 1"><freejoint name="free"/><geom type="box" size=".1 .05 .02"/></body>
    <body name="arm" pos="1 0 1" euler="0.3 0.2 0.1"><joint name="shoulder" type="ball"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size=".03"/>
      <body name="forearm" pos="0.3 0 0"><joint name="elbow" type="hinge" axis="0 1 0"/>
        <geom type="sphere" size=".05" pos="0.2 0 0"/></body></body>
  </worldbody>
</mujoco>
"""
ROTATING = mujoco.MjModel.from_xml_string(ROTATING_XML)
#: States per example in the properties over ROTATING (fixed, so examples share one compile).
ROTATING_BATCH = 4


def rne_bias_0p1_percent(monkeypatch) -> None:
    """Monkeypatches MJX: Coriolis, centrifugal and gravity force (``qfrc_bias``) 0.1% too large."""
    orig = mjx_smooth.rne
    monkeypatch.setattr(mjx_smooth, "rne", lambda m, d, *a, **k: (lambda d: d.replace(
        qfrc_bias=d.qfrc_bias * (1 + 1e-3)))(orig(m, d, *a, **k)))


def test_one_step_check_catches_a_0p1_percent_bias_force_bug(monkeypatch):
    """The one-step check passes unmodified MJX and fails MJX with a 1e-3 relative bias-force error.

    The bug moves qvel by about ``dt * 1e-3 * |qacc_bias|`` (~2e-5 m/s under gravity at
    dt = 2 ms), orders of magnitude over the 1e-8 tolerance; asserting a 100x excess shows the
    property catches it with room to spare, not by a hair.
    """
    rng = np.random.default_rng(0)
    state = State(qpos=np.tile(ROTATING.qpos0, (ROTATING_BATCH, 1)),
                  qvel=rng.uniform(-1, 1, (ROTATING_BATCH, ROTATING.nv)), act=np.zeros((ROTATING_BATCH, 0)))
    ctrl = np.zeros((ROTATING_BATCH, 0))
    c = c_one_step(ROTATING, state, ctrl)
    assert not one_step_mismatches(mjx_one_step(ROTATING, state, ctrl), c)  # unmodified: passes
    rne_bias_0p1_percent(monkeypatch)
    # a new jit object traces the patched MJX code; the shared _mjx_step keeps the unmodified one
    patched = mjx_one_step(ROTATING, state, ctrl, step=_step_fn())
    bad = one_step_mismatches(patched, c)
    assert any(line.startswith("qvel") for line in bad), bad
    assert worst_excess(patched, c) > 100, worst_excess(patched, c)


BALL_SPRING_XML = """
<mujoco>
  <worldbody><body name="ball" pos="0 0 1"><joint name="ball" type="ball" stiffness="10"/><geom size=".1"/></body>
  </worldbody>
</mujoco>
"""


@pytest.mark.xfail(raises=AssertionError,
                   reason="MJX 3.17: math.norm is 0 for |components| <= 1e-8, so no ball/free spring torque "
                          "below ~2e-8 rad (C: -k * angle); see SPRING_DEAD_ZONE")
def test_mjx_ball_spring_has_a_dead_zone_below_2e_8_rad():
    """The finding behind SPRING_DEAD_ZONE, shrunk: a ball joint on a spring (k = 10 N m/rad)
    rotated 1e-8 rad about y. C's spring torque is -1e-7 N m; MJX's is 0 (strict xfail: it
    starts passing, and fails, when MJX fixes it)."""
    m = mujoco.MjModel.from_xml_string(BALL_SPRING_XML)
    qpos = rotvec_quat(np.array([0.0, 1e-8, 0.0]))
    d = mujoco.MjData(m)
    d.qpos = qpos
    mujoco.mj_fwdPosition(m, d)
    mujoco.mj_fwdVelocity(m, d)
    mx = mjx.put_model(m)
    dx = mjx.make_data(mx).replace(qpos=jnp.asarray(qpos))
    dx = mjx.passive(mx, dx)  # eager, no compile: springs need only qpos
    precondition(np.allclose(d.qfrc_spring, [0, -1e-7, 0], rtol=1e-6, atol=0), "C: -k * angle")
    np.testing.assert_allclose(np.asarray(dx.qfrc_passive), d.qfrc_spring, rtol=1e-6, atol=1e-12,
                               err_msg="MJX ball-joint spring torque at a 1e-8 rad rotation")


@pytest.mark.xfail(raises=AssertionError,
                   reason="MJX 3.17 ignores body_sameframe: C treats an inertia frame rotated < ~2e-6 rad "
                          "as the body frame, MJX rotates it")
def test_mjx_ignores_sameframe_of_a_slightly_rotated_inertia():
    """The finding behind :func:`sameframe_drops_offset`, shrunk: an inertia frame rotated 4.4e-7 rad
    about x (``quat="1 -2.2e-7 0 0"``) is flagged mjSAMEFRAME_BODYROT, so C's ximat is the body's
    (identity); MJX's is rotated by 4.4e-7 rad, and cinert/qM follow (strict xfail)."""
    m = mujoco.MjModel.from_xml_string("""<mujoco><worldbody><body pos="0 0 1"><joint type="ball"/>
      <inertial pos="0 0 -0.07" quat="1 -2.2e-7 0 0" mass="1" diaginertia="0.03 0.03 0.02"/></body></worldbody>
      </mujoco>""")
    precondition(m.body_sameframe[1] == mujoco.mjtSameFrame.mjSAMEFRAME_BODYROT
                 and sameframe_drops_offset(m) == "body 1",
                 "C snaps the inertia frame to the body frame")
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    mx = mjx.put_model(m)
    dx = mjx.kinematics(mx, mjx.make_data(mx))  # eager: one stage, no compile
    np.testing.assert_allclose(np.asarray(dx.ximat[1]).ravel(), d.ximat[1], atol=1e-12,
                               err_msg="MJX ximat of a body whose inertia frame C snaps to the body frame")


# ---------------------------------------------------------------------------
# 2. Invariants.

#: Largest allowed | |q| - 1 | of a free or ball joint quaternion over a rollout. MJX renormalises
#: after every integration (math.quat_integrate): measured worst 2.2e-16 (1 ulp) over 30 examples
#: of the property. 1e-9 is far above rounding and far below the drift of an unnormalised update,
#: ~(dt |omega|)^2 / 8 ~ 4e-4 per step at 30 rad/s.
QUAT_NORM_TOL = 1e-9
ROLLOUT_STEPS = 150


def quaternion_addresses(m: mujoco.MjModel) -> list[int]:
    """qpos addresses of the 4 quaternion components of every free and ball joint."""
    out = []
    for j in range(m.njnt):
        adr, jtype = int(m.jnt_qposadr[j]), m.jnt_type[j]
        if jtype == mujoco.mjtJoint.mjJNT_FREE:
            out.append(adr + 3)
        elif jtype == mujoco.mjtJoint.mjJNT_BALL:
            out.append(adr)
    return out


def quaternion_norm_error(qpos: np.ndarray, addresses: list[int]) -> np.ndarray:
    """``| |q| - 1 |`` for every quaternion: ``(..., nq)`` qpos to ``(..., len(addresses))``."""
    quats = np.stack([qpos[..., a:a + 4] for a in addresses], axis=-2)
    return np.abs(np.linalg.norm(quats, axis=-1) - 1)


def mjx_rollout(mx: mjx.Model, dx: mjx.Data, steps: int) -> dict[str, np.ndarray]:
    """``(B, T, ...)`` qpos, qvel and time (s) after each of ``steps`` calls of the shared
    ``jit(vmap(mjx.step))`` (a Python loop, so it reuses the one-step compile)."""
    rec = {"qpos": [], "qvel": [], "time": []}
    for _ in range(steps):
        dx = _mjx_step(mx, dx)
        for k in rec:
            rec[k].append(getattr(dx, k))
    return {k: np.stack([np.asarray(x) for x in v], axis=1) for k, v in rec.items()}


@settings(max_examples=5)
@given(states=initial_states(ROTATING, batch=ROTATING_BATCH, qpos_scale=3.0,
                             qvel_scale=st.floats(0.0, 30.0)))
def test_quaternions_stay_unit_over_an_mjx_rollout(states):
    """Free and ball quaternions keep unit norm over 150 steps (0.3 s), spinning up to 30 rad/s."""
    mx, dx = batched_data(ROTATING, states)
    qpos = mjx_rollout(mx, dx, ROLLOUT_STEPS)["qpos"]
    err = quaternion_norm_error(qpos, quaternion_addresses(ROTATING))
    assert np.isfinite(qpos).all()
    b, t, k = np.unravel_index(np.argmax(err), err.shape)
    assert err[b, t, k] <= QUAT_NORM_TOL, \
        f"quaternion {k} of state {b} is {err[b, t, k]:.3g} off unit norm after step {t + 1}"


def float_clock(t0: float, dt: float, steps: int) -> np.ndarray:
    """``(steps,)`` times after each step when every step does ``t = t + dt`` in float64, as
    ``mj_step`` does (``d->time += m->opt.timestep``)."""
    out, t = np.empty(steps), np.float64(t0)
    for k in range(steps):
        t = t + np.float64(dt)
        out[k] = t
    return out


@settings(max_examples=5)
@given(dt=st.floats(1e-4, 1e-2), t0=st.floats(0.0, 1e3), states=initial_states(ROTATING, batch=ROTATING_BATCH))
def test_time_advances_by_exactly_the_timestep(dt, t0, states):
    """After each MJX step, time is the previous time plus ``opt.timestep``, bit for bit (the
    float64 sum C computes), from any start time; within ``steps * ulp`` of ``t0 + k dt``."""
    steps = 40
    mx, dx = batched_data(ROTATING, states, time=np.full(ROTATING_BATCH, t0))
    # a leaf of the same type and placement as put_model's: no recompile
    mx = mx.replace(opt=mx.opt.replace(timestep=jax.device_put(jnp.full_like(mx.opt.timestep, dt), jax.devices()[0])))
    time = mjx_rollout(mx, dx, steps)["time"]  # (B, T)
    expected = float_clock(t0, dt, steps)
    np.testing.assert_array_equal(time, np.broadcast_to(expected, time.shape),
                                  err_msg=f"MJX time is not t0 + dt + dt + ... (t0={t0!r}, dt={dt!r})")
    m = mujoco.MjModel.from_xml_string(ROTATING_XML)
    m.opt.timestep = dt
    d = mujoco.MjData(m)
    d.time = t0
    c_time = np.empty(steps)
    for k in range(steps):
        mujoco.mj_step(m, d)
        c_time[k] = d.time
    np.testing.assert_array_equal(c_time, expected, err_msg="MuJoCo C time is not t0 + dt + dt + ...")
    k = np.arange(1, steps + 1)
    assert np.all(np.abs(expected - (t0 + k * dt)) <= k * np.spacing(t0 + k * dt))


def conservative(m: mujoco.MjModel) -> mujoco.MjModel:
    """A copy of ``m`` whose only forces are gravity and springs, which are conservative and
    counted in MuJoCo's potential energy: constraints (contacts, joint limits, frictionloss,
    equalities) and actuation disabled, joint and tendon damping and fluid forces zeroed."""
    m = copy.copy(m)
    m.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONSTRAINT | mujoco.mjtDisableBit.mjDSBL_ACTUATION
    m.dof_damping[:] = 0
    m.tendon_damping[:] = 0
    m.dof_frictionloss[:] = 0
    m.tendon_frictionloss[:] = 0
    m.opt.density = m.opt.viscosity = 0
    return m


def stiffest_frequency(m: mujoco.MjModel) -> float:
    """Largest natural frequency (rad/s) of the joint and tendon springs at ``qpos0``:
    ``sqrt(max eig(M^-1 K))`` with ``K = diag(dof stiffness) + sum_t k_t J_t^T J_t``."""
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    M = np.zeros((m.nv, m.nv))
    mujoco.mj_fullM(m, d, M)
    K = np.diag(m.jnt_stiffness[m.dof_jntid])
    if m.ntendon:
        J = np.zeros((m.ntendon, m.nv))
        mujoco.mju_sparse2dense(J, d.ten_J, m.ten_J_rownnz, m.ten_J_rowadr, m.ten_J_colind)
        K = K + J.T @ (m.tendon_stiffness[:, None] * J)
    return float(np.sqrt(max(np.max(np.linalg.eigvals(np.linalg.solve(M, K)).real), 0.0)))


#: RK4 steps per rollout in the energy properties, and the largest ``omega * dt`` allowed: the
#: timestep is ``min(2 ms, ENERGY_OMEGA_DT / stiffest_frequency)`` so that RK4 resolves every spring.
ENERGY_STEPS = 200
ENERGY_OMEGA_DT = 0.02
#: Energy bound, J: ``|E_t - E_0| <= ENERGY_RTOL * exchanged + ENERGY_ROUNDING * magnitude``, where
#: ``exchanged`` is the largest kinetic energy plus the range of potential energy over the rollout
#: (the energy that changes hands) and ``magnitude`` the largest |potential| + kinetic (rounding of
#: sums like ``-sum m g z`` scales with it, whatever moves). RK4's energy error is O((omega dt)^4)
#: relative per radian of motion: at omega dt <= 0.02 over 200 steps, <= ~1e-7 of ``exchanged``.
#: Measured: SPRINGY drifts 1.1e-8 of ``exchanged`` in both engines (1.1% of the bound); generated
#: hinge/slide models (12) at most 2e-4 of the bound in either engine, drift at the rounding floor.
ENERGY_RTOL = 1e-6
ENERGY_ROUNDING = 1e-12


@jit_for_few_calls
def _mjx_energies(mx: mjx.Model, dx: mjx.Data, qpos: jax.Array, qvel: jax.Array) -> jax.Array:
    """``(B, T, 2)`` potential and kinetic energy (J) of ``(B, T, nq)``/``(B, T, nv)`` states, by
    :func:`mjxdiff.engine.engines.energy` after MJX's kinematics, tendons and mass matrix of each state
    (``dx``: one unbatched ``mjx.Data`` to fill in)."""
    def one(q, v):
        d = dx.replace(qpos=q, qvel=v)
        for stage in (mjx.kinematics, mjx.com_pos, mjx.tendon, mjx.crb, mjx.tendon_armature):
            d = stage(mx, d)
        return mjx_energy(mx, d, q, v)
    return jax.vmap(jax.vmap(one))(qpos, qvel)


def c_energies(m: mujoco.MjModel, qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
    """``(..., 2)`` MuJoCo C ``d.energy`` (potential, kinetic; J) of ``(..., nq)``/``(..., nv)`` states
    (``mj_forward`` of each with mjENBL_ENERGY)."""
    m = copy.copy(m)
    m.opt.enableflags |= mujoco.mjtEnableBit.mjENBL_ENERGY
    d = mujoco.MjData(m)
    out = np.zeros(qpos.shape[:-1] + (2,))
    for idx in np.ndindex(qpos.shape[:-1]):
        d.qpos, d.qvel = qpos[idx], qvel[idx]
        mujoco.mj_forward(m, d)
        out[idx] = d.energy
    return out


def c_rollout(m: mujoco.MjModel, state: State, steps: int) -> dict[str, np.ndarray]:
    """``(B, T, ...)`` qpos and qvel after each of ``steps`` ``mj_step`` calls, zero controls."""
    nbatch = state.qpos.shape[0]
    qpos, qvel = np.zeros((nbatch, steps, m.nq)), np.zeros((nbatch, steps, m.nv))
    d = mujoco.MjData(m)
    for b in range(nbatch):
        mujoco.mj_resetData(m, d)
        d.qpos, d.qvel, d.act = state.qpos[b], state.qvel[b], state.act[b]
        for t in range(steps):
            mujoco.mj_step(m, d)
            qpos[b, t], qvel[b, t] = d.qpos, d.qvel
    return {"qpos": qpos, "qvel": qvel}


def energy_drift(e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(B,)`` worst ``|E_t - E_0|`` and ``(B,)`` bound (J), from ``(B, T, 2)`` energies
    (potential, kinetic) whose first record is the initial state; see ENERGY_RTOL."""
    total = e.sum(-1)
    drift = np.max(np.abs(total - total[:, :1]), axis=1)
    exchanged = np.max(e[..., 1], axis=1) + np.ptp(e[..., 0], axis=1)
    magnitude = np.max(np.abs(e[..., 0]) + e[..., 1], axis=1)
    return drift, ENERGY_RTOL * exchanged + ENERGY_ROUNDING * magnitude


def energy_violations(engine: str, e: np.ndarray) -> list[str]:
    """One line per state whose energy (``(B, T, 2)``) leaves the bound of :func:`energy_drift`."""
    drift, bound = energy_drift(e)
    return [f"{engine}: state {b} energy drifts by {drift[b]:.3g} J (bound {bound[b]:.3g} J, "
            f"worst at step {np.argmax(np.abs(e[b].sum(-1) - e[b, 0].sum()))})"
            for b in np.flatnonzero(~(drift <= bound))]


def check_energy(m: mujoco.MjModel, state: State) -> list[str]:
    """Rolls out ``m`` (conservative, RK4) from ``(B, ...)`` states for ENERGY_STEPS in both engines;
    returns the energy violations of each (empty when both conserve energy). Also asserts MJX's and
    C's energy of the initial states agree to rounding (``rtol`` 1e-10)."""
    c = c_rollout(m, state, ENERGY_STEPS)
    mx, dx = batched_data(m, state)
    x = mjx_rollout(mx, dx, ENERGY_STEPS)
    with_start = lambda r: {k: np.concatenate([getattr(state, k)[:, None], r[k]], axis=1) for k in ("qpos", "qvel")}
    c, x = with_start(c), with_start(x)
    e_c = c_energies(m, c["qpos"], c["qvel"])
    e_x = np.asarray(_mjx_energies(mx, jax.tree.map(lambda a: a[0], dx), x["qpos"], x["qvel"]))
    np.testing.assert_allclose(e_x[:, 0], e_c[:, 0], rtol=1e-10, atol=1e-12,
                               err_msg="MJX's and C's energies of the same initial state differ")
    return energy_violations("MuJoCo C", e_c) + energy_violations("MJX", e_x)


#: A fixed conservative model for the CI energy property (one compile): a double pendulum on hinge
#: springs, a slider on a spring, a fixed tendon coupling them and a spatial tendon from the
#: forearm to an anchor, both with stiffness (every kind of potential energy MuJoCo counts, and
#: gravity), RK4, nothing dissipative. Hinges and slides only: MJX's RK4 loses two orders on ball
#: and free joints (RK4_QUATERNION_FINDING).
SPRINGY_XML = """
<mujoco>
  <option timestep="0.002" integrator="RK4"/>
  <default><geom contype="0" conaffinity="0"/></default>
  <worldbody>
    <site name="anchor" pos="0 1 1.5"/>
    <body name="arm" pos="0 0 1"><joint name="shoulder" type="hinge" axis="0 1 0" stiffness="2"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size=".03"/>
      <body name="forearm" pos="0.3 0 0"><joint name="elbow" type="hinge" axis="1 0 0" stiffness="1"/>
        <geom type="sphere" size=".05" pos="0 0.2 0"/><site name="hand" pos="0 0.2 0"/></body></body>
    <body name="slider" pos="1 0 1"><joint name="slide" type="slide" axis="1 0 1" stiffness="20"/>
      <geom type="sphere" size=".08"/></body>
  </worldbody>
  <tendon>
    <fixed name="coupling" stiffness="5"><joint joint="elbow" coef="1"/><joint joint="slide" coef="-0.5"/></fixed>
    <spatial name="rope" stiffness="10"><site site="hand"/><site site="anchor"/></spatial>
  </tendon>
</mujoco>
"""
SPRINGY = mujoco.MjModel.from_xml_string(SPRINGY_XML)
SPRINGY.opt.timestep = min(2e-3, ENERGY_OMEGA_DT / stiffest_frequency(SPRINGY))


@settings(max_examples=4)
@given(states=initial_states(SPRINGY, batch=4, qpos_scale=1.0, qvel_scale=st.floats(0.0, 3.0)))
def test_conservative_system_conserves_energy_in_both_engines(states):
    """SPRINGY (RK4, every spring resolved): over 200 steps from 4 states, total energy stays
    within ``1e-6 * exchanged + 1e-12 * magnitude`` of its start in MJX and in MuJoCo C.

    A leak or a wrong force (0.1% in the bias force breaks the balance of gravity's work and
    potential energy, a missing spring term, a wrong mass matrix) moves energy by 1e-4 of what is
    exchanged and more, far outside; RK4's own error is ~1e-7 of it at most (see ENERGY_RTOL).
    """
    bad = check_energy(SPRINGY, states)
    assert not bad, "\n".join(bad) + f"\n(timestep {SPRINGY.opt.timestep:.3g} s)"


def _armature_off_one_chain(m: mujoco.MjModel) -> bool:
    """Whether a tendon with armature moves two bodies' joints neither of which is an ancestor of
    the other (in two kinematic trees, or on two branches of one): MJX 3.17's mass matrix then
    differs from C's, and so does the kinetic energy of the same state (generated models drew
    both: 0.0455 against 0.0352 J across two trees, 0.00833 against 0.00760 J across two branches;
    the catalogue's tendon-armature-trees)."""
    def chain(body: int) -> list[int]:  # the body and its ancestors, the world left out
        out = []
        while body > 0:
            out.append(body)
            body = int(m.body_parentid[body])
        return out

    for t in np.flatnonzero(m.tendon_armature > 0):
        bodies: set[int] = set()
        for w in range(m.tendon_adr[t], m.tendon_adr[t] + m.tendon_num[t]):
            if m.wrap_type[w] == mujoco.mjtWrap.mjWRAP_JOINT:
                bodies.add(int(m.jnt_bodyid[m.wrap_objid[w]]))
            elif m.wrap_type[w] == mujoco.mjtWrap.mjWRAP_SITE:
                bodies.update(chain(int(m.site_bodyid[m.wrap_objid[w]])))
        moved = [b for b in bodies if m.body_dofnum[b] > 0]
        if any(a not in chain(b) and b not in chain(a) for a, b in itertools.combinations(moved, 2)):
            return True
    return False


@pytest.mark.slow  # a compile per example (10 examples cost 5 CI minutes, 296 s)
@settings(max_examples=4)
@given(st.data())
def test_generated_conservative_systems_conserve_energy_in_both_engines(data):
    """As above on generated models made :func:`conservative`, RK4 at ``omega dt <= 0.02``;
    hinge and slide joints only (RK4_QUATERNION_FINDING)."""
    mm = data.draw(mjcf_models(max_bodies=3, joint_types=("hinge", "slide"), contacts=False, equality=False,
                               actuators=False, sensors=False, options={"integrator": "RK4"}), label="model")
    note(mm.xml)
    m = conservative(mm.model())
    # known divergences of the catalogue that change the energy itself: another mass matrix
    # (tendon-armature-trees), another tendon length and so spring energy (tendon-wrap-sidesite)
    assume(not _armature_off_one_chain(m) and "tendon wrap sidesite" not in mm.features)
    m.opt.timestep = min(2e-3, ENERGY_OMEGA_DT / max(stiffest_frequency(m), 1e-9))
    bad = check_energy(m, data.draw(initial_states(m, batch=4), label="states"))
    assert not bad, "\n".join(bad) + f"\n(timestep {m.opt.timestep:.3g} s)\n" + mm.xml


#: MJX 3.17's RK4 is second-order accurate on ball joints where C's is fourth-order: a ball-joint
#: pendulum's energy drift over 0.4 s falls 4x per halving of dt in MJX (9.3e-6, 2.3e-6, 5.7e-7 J at
#: dt = 4, 2, 1 ms) and 16x in C (4.9e-9, 3.3e-10, 2.1e-11 J); hinge-only models agree to the digit.
#: The differing free/ball rotations under RK4 in KNOWN_DIVERGENCES are this.
RK4_QUATERNION_FINDING = "MJX RK4 is second-order on ball joints (energy drift ~dt^2; C ~dt^4)"
BALL_PENDULUM_XML = """
<mujoco>
  <option integrator="RK4"/>
  <worldbody>
    <body pos="0 0 1"><joint type="ball"/><geom type="capsule" fromto="0 0 0 0.3 0.1 0" size=".03"/></body>
  </worldbody>
</mujoco>
"""


@pytest.mark.slow  # an RK4 compile of its own (~13 s cold): documents the finding outside CI's budget
@pytest.mark.xfail(raises=AssertionError, reason=RK4_QUATERNION_FINDING)
def test_mjx_rk4_conserves_energy_of_a_ball_pendulum():
    """The finding behind RK4_QUATERNION_FINDING, shrunk: a capsule on a ball joint swinging and
    spinning (|qvel| <= 3 rad/s), RK4 at 2 ms for 0.4 s. C stays within the energy bound (asserted
    first), MJX does not (strict xfail)."""
    m = mujoco.MjModel.from_xml_string(BALL_PENDULUM_XML)
    m.opt.timestep = 2e-3
    state = State(np.tile(m.qpos0, (4, 1)), np.random.default_rng(0).uniform(-3, 3, (4, m.nv)), np.zeros((4, 0)))
    bad = check_energy(m, state)
    precondition(not [line for line in bad if line.startswith("MuJoCo C")],
                 "C keeps the energy bound: " + "; ".join(bad))
    assert not bad, "\n".join(bad)


@jit_for_few_calls
def _mjx_bias(mx: mjx.Model, dx: mjx.Data) -> jax.Array:
    """``(B, nv)`` MJX ``qfrc_bias`` of a batch of states: the stages of ``mjx.forward`` that
    produce it (kinematics, com_pos, tendon, com_vel, rne, tendon_bias), leaving out collision,
    constraints and actuation, which do not enter it and would lengthen each model's compile."""
    def one(d):
        for stage in (mjx.kinematics, mjx.com_pos, mjx.tendon, mjx.com_vel, mjx.rne, mjx.tendon_bias):
            d = stage(mx, d)
        return d.qfrc_bias
    return jax.vmap(one)(dx)


@settings(max_examples=3)
@given(st.data())
def test_bias_force_is_zero_at_rest_without_gravity(data):
    """With gravity disabled (mjDSBL_GRAVITY) and qvel = 0, qfrc_bias is exactly 0 in MJX and C.

    Exactly, not to a tolerance: every term of the recursive Newton-Euler bias (Coriolis,
    centrifugal, tendon armature) is a product with a zero velocity, and the gravity term is
    switched off, so any nonzero value is a term that should not be there.
    """
    mm = data.draw(mjcf_models(max_bodies=3), label="model")
    note(mm.xml)
    m = mm.model()
    m.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_GRAVITY
    state = data.draw(initial_states(m, batch=4, qvel_scale=0.0), label="states")
    assert not state.qvel.any()
    mx, dx = batched_data(m, state)
    bias_mjx = np.asarray(_mjx_bias(mx, dx))
    d = mujoco.MjData(m)
    bias_c = np.zeros_like(bias_mjx)
    for b in range(state.qpos.shape[0]):
        d.qpos, d.qvel, d.act = state.qpos[b], state.qvel[b], state.act[b]
        mujoco.mj_forward(m, d)
        bias_c[b] = d.qfrc_bias
    for engine, bias in (("MJX", bias_mjx), ("MuJoCo C", bias_c)):
        b, i = np.unravel_index(np.argmax(np.abs(bias)), bias.shape) if bias.size else (0, 0)
        assert not bias.any(), f"{engine}: qfrc_bias[{i}] of state {b} is {bias[b, i]!r} at rest without gravity"


# ---------------------------------------------------------------------------
# 3. Unsupported models: reported, never a crash.

#: Random models use the put_model features (one compile-free check each); every feature,
#: also those MJX raises later (make_data, tracing mjx.step), is checked once below.
_PUT_MODEL_FEATURES = tuple(f.name for f in UNSUPPORTED_FEATURES if f.stage == "put_model")


def _check_reported_unsupported(mm) -> None:
    feature = mm.unsupported
    result = compare(mm.model(), steps=3, diagnose="none")
    assert result.status == "unsupported", (feature.name, result.status, result.message, mm.xml)
    assert result.message.startswith("MJX does not support: ") and feature.message in result.message, \
        (feature, result.message)


@settings(max_examples=5)
@given(mjcf_models(unsupported=_PUT_MODEL_FEATURES, max_bodies=2))
def test_unsupported_models_are_reported_unsupported_by_compare(mm):
    """Random models with one feature MJX rejects at put_model: status `unsupported`, feature named."""
    _check_reported_unsupported(mm)


@pytest.mark.parametrize("feature", UNSUPPORTED_FEATURES, ids=lambda f: f.name)
def test_each_unsupported_feature_is_reported_unsupported_by_compare(feature):
    """Every feature of UNSUPPORTED_FEATURES, end to end through :func:`mjxdiff.testing.compare`."""
    @settings(max_examples=1, database=None, phases=[Phase.generate])
    @given(mjcf_models(unsupported=feature.name, max_bodies=1))
    def check(mm):
        _check_reported_unsupported(mm)

    check()
