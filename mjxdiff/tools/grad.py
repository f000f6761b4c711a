"""Derivative consistency: are MJX's one-step Jacobians the ones MuJoCo C's dynamics imply?

At states sampled from a scenario (initial states and states along C rollouts), the transition
Jacobians of one step, A = d x' / d x and B = d x' / d u (and for the sensors C and D) with the state x = (qpos in the
tangent space, qvel, act) as MuJoCo's ``mjd_transitionFD`` defines it, are computed

* in MJX by forward-mode autodiff (``jax.jacfwd``) of one ``mjx.step`` in float64, free and
  ball joints perturbed and differenced in the tangent space;
* in C by centred finite differences (``mujoco.mjd_transitionFD``) at two step sizes, ``EPS``
  and ``EPS / 10``.

**Floor.** Finite differences have their own error. Per entry, the floor is
``3 x |A(EPS) - A(EPS/10)|`` (the truncation and solver-noise part, measured; at least 3 x the
largest such change in the same row, that output's noise) plus roundoff,
``1e-15 x (1 + |x'|) / (EPS/10)``, plus ``1e-9 x (1 + |A|)``; an entry fails when
``|A_mjx - A_c(EPS/10)|`` exceeds it plus ``RTOL x max(|A_mjx|, |A_c|)`` (implementation
differences the forward sweep accepts, such as where a contact point sits).
**Non-smooth states**: where the constraint set (which contacts and limits are active, and each
row's state) differs anywhere in the FD stencil, the dynamics are not differentiable there; such
states are reported as ``non-smooth`` and not judged. Models with constraints are compared with
a converged solver on both sides (a solver stopped after a few iterations is differentiated as an
iteration, not as the solution).

**Localise.** The worst entry is named (output and input component with their joints or
actuators, the state) and, recomputed with constraints disabled on both sides, attributed to
the ``smooth dynamics`` (the disagreement stays) or the ``constraint`` part (it goes).
The sensor Jacobians C = d sensordata / d x and D = d sensordata / d u (the sensors at the
state, as ``mjd_transitionFD`` defines them) are judged the same way, each row's roundoff
scaled by its sensor's largest component.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
from typing import Any

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from mjxdiff.compat import enable_x64, jit_for_few_calls
from mjxdiff.errors import one_line
from mjxdiff.input import joints
from mjxdiff.compare.noise import converge_solver, has_constraints

__all__ = ["EPS", "RTOL", "SMOOTH", "MATRICES", "StateResult", "sample_states", "mjx_jacobians", "mjx_fd",
           "c_jacobians", "floor", "smooth_at", "judge_state", "check_scenario", "log10_ratios", "replay",
           "format_state", "format_text"]

#: The larger finite-difference step; C is also differenced at EPS / 10.
EPS = 1e-6
#: Relative tolerance added to the finite-difference floor: implementation differences the
#: forward sweep accepts (where a contact point sits, a converged solver's last digits) move
#: derivatives too (sensing: d qvel' / d qpos of a yawing box on the floor, MJX and C 8.8e-6
#: apart, MJX's own finite differences agreeing with its gradient). A 2% gain slip or a cut
#: gradient is orders of magnitude above it.
RTOL = 1e-4
#: Bundled scenarios without contacts: every sampled state is smooth (``grad``'s default).
SMOOTH = ("pendulum", "double_pendulum", "cartpole", "actuators", "gravcomp_arm")


@dataclasses.dataclass(frozen=True)
class StateResult:
    """The verdict at one state: ``pass``, ``fail`` or ``non-smooth``; for a failure the worst
    entry (matrix ``A`` or ``B``, row, column, named), its MJX and C values, error / floor, and
    where it sits (``smooth dynamics`` or ``constraint``)."""

    index: int
    member: int
    step: int
    status: str
    ratio: float = 0.0
    worst: dict[str, Any] = dataclasses.field(default_factory=dict)


# ----------------------------------------------------------------------------
# the state and its tangent space


# ----------------------------------------------------------------------------
# Jacobians both ways


def _next(parts: tuple, nv: int):
    """f(mx, dx, ref_qpos, x, u): the next state (qpos as a tangent vector from ``ref_qpos``, qvel,
    act) and the sensors after one ``mjx.step`` from ``dx`` moved by the state tangent ``x``,
    with controls ``u``."""
    def f(mx, dx, ref_qpos, x, u):
        qpos = joints.integrate(parts, dx.qpos, x[:nv])
        d1 = mjx.step(mx, dx.replace(qpos=qpos, qvel=dx.qvel + x[nv:2 * nv], act=dx.act + x[2 * nv:], ctrl=u))
        # its sensordata are the sensors at (x, u), as in mjd_transitionFD
        return jnp.concatenate([joints.difference(parts, nv, d1.qpos, ref_qpos), d1.qvel, d1.act, d1.sensordata])
    return f


def _reference(mx, dx, u):
    """qpos after one step from ``dx`` with ``u``: the point the tangent differences are taken at."""
    return jax.lax.stop_gradient(mjx.step(mx, dx.replace(ctrl=u)).qpos)


@functools.lru_cache(maxsize=16)
def _jacobian_fn(parts: tuple, nv: int, na: int, code: str):
    """jit(jacfwd) of one mjx.step around a state, for models with these joints (the model
    itself is an argument: one compile serves every member and state) and this MJX ``code``
    (:func:`mjxdiff.engine.digest.code_digest`: an edited or patched MJX is traced anew). Called
    once per state, so compiled for compile time (:func:`mjxdiff.compat.jit_for_few_calls`)."""
    f = _next(parts, nv)

    def jac(mx, dx, u):
        x = jnp.zeros(2 * nv + na, dx.qpos.dtype)
        return jax.jacfwd(f, argnums=(3, 4))(mx, dx, _reference(mx, dx, u), x, u)

    return jit_for_few_calls(jac)


@functools.lru_cache(maxsize=16)
def _values_fn(parts: tuple, nv: int, na: int, code: str):
    """jit(vmap) of :func:`_next` over a batch of (x, u): MJX's own finite-difference stencil."""
    f = jax.vmap(_next(parts, nv), in_axes=(None, None, None, 0, 0))
    return jit_for_few_calls(lambda mx, dx, u, xs, us: f(mx, dx, _reference(mx, dx, u), xs, us))


def _data(m: mujoco.MjModel, state: dict[str, np.ndarray]) -> mujoco.MjData:
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:], d.ctrl[:] = state["qpos"], state["qvel"], state["ctrl"]
    if m.na:
        d.act[:] = state["act"]
    return d


def mjx_jacobians(m: mujoco.MjModel, state: dict[str, np.ndarray], code: str | None = None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(A, B, C, D) of one ``mjx.step`` at ``state`` (qpos, qvel, act, ctrl), by ``jax.jacfwd`` in
    float64 (run under ``jax.enable_x64``): A (n, n) and B (n, nu) of the next state, C
    (nsensordata, n) and D (nsensordata, nu) of the sensors at the state, n = 2 nv + na.
    ``code``: the MJX code digest when the caller has it (:func:`mjxdiff.engine.digest.code_digest`,
    computed here otherwise: about 0.4 s)."""
    from mjxdiff.engine.digest import code_digest

    d = _data(m, state)
    fn = _jacobian_fn(joints.parts(m), m.nv, m.na, code or code_digest())
    AC, BD = (np.asarray(j) for j in fn(mjx.put_model(m), mjx.put_data(m, d), jnp.asarray(d.ctrl)))
    n = 2 * m.nv + m.na
    return AC[:n], BD[:n], AC[n:], BD[n:]


def mjx_fd(m: mujoco.MjModel, state: dict[str, np.ndarray], code: str | None = None
           ) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """MJX's own centred finite differences of one ``mjx.step``, per matrix of :data:`MATRICES`:
    (at EPS / 10, at EPS), all 4 (n + nu) perturbed steps in one vmapped call. Beside its
    ``jax.jacfwd`` they tell a derivative-only disagreement (MJX's differences agree with C's)
    from a forward one (they agree with MJX's gradient) and from MJX's forward jumping inside
    the stencil (its differences grow as 1 / eps)."""
    from mjxdiff.engine.digest import code_digest

    d = _data(m, state)
    n, nu = 2 * m.nv + m.na, m.nu
    fn = _values_fn(joints.parts(m), m.nv, m.na, code or code_digest())
    basis = np.eye(n + nu)
    steps = np.concatenate([sign * eps * basis for eps in (EPS / 10, EPS) for sign in (1.0, -1.0)])
    out = np.asarray(fn(mjx.put_model(m), mjx.put_data(m, d), jnp.asarray(d.ctrl), jnp.asarray(steps[:, :n]),
                        jnp.asarray(d.ctrl + steps[:, n:])))
    k = n + nu
    fd = [(out[i * 2 * k:i * 2 * k + k] - out[i * 2 * k + k:(i + 1) * 2 * k]).T / (2 * eps)
          for i, eps in enumerate((EPS / 10, EPS))]  # (outputs, inputs) at each step size
    split = {"A": (slice(0, n), slice(0, n)), "B": (slice(0, n), slice(n, k)),
             "C": (slice(n, None), slice(0, n)), "D": (slice(n, None), slice(n, k))}
    return {name: (fd[0][split[name]], fd[1][split[name]]) for name, *_ in MATRICES}


def c_jacobians(m: mujoco.MjModel, state: dict[str, np.ndarray], eps: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(A, B, C, D) of one ``mj_step`` at ``state`` by centred finite differences
    (``mujoco.mjd_transitionFD``; shapes as :func:`mjx_jacobians`)."""
    if m.opt.integrator == mujoco.mjtIntegrator.mjINT_RK4:  # mjd_transitionFD: "RK4 ... not supported"
        return _c_fd(m, state, eps)
    d = _data(m, state)
    n = 2 * m.nv + m.na
    A, B = np.zeros((n, n)), np.zeros((n, m.nu))
    C, D = np.zeros((m.nsensordata, n)), np.zeros((m.nsensordata, m.nu))
    mujoco.mjd_transitionFD(m, d, eps, True, A, B, C if m.nsensordata else None, D if m.nsensordata else None)
    return A, B, C, D


def _c_fd(m: mujoco.MjModel, state: dict[str, np.ndarray], eps: float
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(A, B, C, D) as ``mjd_transitionFD`` defines them, by centred differences of ``mj_step``
    written out (qpos moved with ``mj_integratePos``, differenced with ``mj_differentiatePos``):
    for the integrators ``mjd_transitionFD`` refuses (RK4)."""
    nv, na, nu = m.nv, m.na, m.nu
    n = 2 * nv + na
    d = _data(m, state)
    mujoco.mj_step(m, d)
    ref = d.qpos.copy()

    def after(dx: np.ndarray, du: np.ndarray) -> np.ndarray:
        d = _data(m, state)
        mujoco.mj_integratePos(m, d.qpos, dx[:nv], 1.0)
        d.qvel[:] += dx[nv:2 * nv]
        d.act[:] += dx[2 * nv:]
        d.ctrl[:] += du
        mujoco.mj_step(m, d)
        dq = np.zeros(nv)
        mujoco.mj_differentiatePos(m, dq, 1.0, ref, d.qpos)
        return np.concatenate([dq, d.qvel, d.act, d.sensordata])

    basis = np.eye(n + nu) * eps
    J = np.stack([(after(e[:n], e[n:]) - after(-e[:n], -e[n:])) / (2 * eps) for e in basis], axis=1)
    return J[:n, :n], J[:n, n:], J[n:, :n], J[n:, n:]


def floor(m: mujoco.MjModel, state: dict[str, np.ndarray], fine: np.ndarray, coarse: np.ndarray,
          sensors: bool = False) -> np.ndarray:
    """Per-entry error floor of the finite-difference Jacobian ``fine`` (at EPS / 10) given the
    same at EPS: 3 x max(|fine - coarse|, its row's largest) + roundoff + 1e-9 x (1 + |fine|)
    (see the module docstring). The row's largest change is the noise of that output's finite
    differences: one entry's change can be small by chance (ball_joint: 1.3e-9 where its row's
    noise was 1.7e-6 and MJX's exact derivative 2e-7 away).
    Roundoff scales with the largest output: the next state, or (``sensors``) per row the
    sensor's own largest value."""
    d = _data(m, state)
    mujoco.mj_step(m, d)
    if sensors:
        size = 1 + np.abs(_per_sensor_max(m, d.sensordata))[:, None]
    else:
        size = 1 + float(np.max(np.abs(np.concatenate([d.qpos, d.qvel, d.act]))))
    change = np.abs(fine - coarse)
    row_noise = change.max(axis=1, keepdims=True) if change.size else change
    return 3 * np.maximum(change, row_noise) + 1e-15 * size / (EPS / 10) + 1e-9 * (1 + np.abs(fine))


def _per_sensor_max(m: mujoco.MjModel, sensordata: np.ndarray) -> np.ndarray:
    """(nsensordata,): each entry replaced by the largest |value| of its sensor's components."""
    out = np.abs(sensordata).copy()
    for i in range(m.nsensor):
        a, n = int(m.sensor_adr[i]), int(m.sensor_dim[i])
        out[a:a + n] = np.max(out[a:a + n])
    return out


def _signature(m: mujoco.MjModel, d: mujoco.MjData) -> tuple:
    mujoco.mj_forward(m, d)
    return (tuple(d.efc_type[:d.nefc]), tuple(d.efc_id[:d.nefc]), tuple(d.efc_state[:d.nefc]))


def smooth_at(m: mujoco.MjModel, state: dict[str, np.ndarray], eps: float = EPS) -> bool:
    """Whether the constraint set (active rows, their ids and states) is the same at every point
    of the finite-difference stencil: in qpos (tangent), qvel, act and ctrl, +-eps each."""
    d = _data(m, state)
    center = _signature(m, d)
    for field, size in (("qpos", m.nv), ("qvel", m.nv), ("act", m.na), ("ctrl", m.nu)):
        for i in range(size):
            for sign in (-1.0, 1.0):
                p = _data(m, state)
                if field == "qpos":
                    dq = np.zeros(m.nv)
                    dq[i] = sign * eps
                    mujoco.mj_integratePos(m, p.qpos, dq, 1.0)
                else:
                    getattr(p, field)[i] += sign * eps
                if _signature(m, p) != center:
                    return False
    return True


# ----------------------------------------------------------------------------
# names and the verdict


def _component(m: mujoco.MjModel, i: int | np.integer, inputs: bool, control: bool = False) -> str:
    """Name of row/column ``i`` of A (state) or of a column of B (``control``)."""
    def joint_of(dof):
        j = int(m.dof_jntid[dof])
        name = f"'{mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j) or f'#{j}'}'"
        axes = {mujoco.mjtJoint.mjJNT_FREE: ("x", "y", "z", "rot x", "rot y", "rot z"),
                mujoco.mjtJoint.mjJNT_BALL: ("rot x", "rot y", "rot z")}.get(int(m.jnt_type[j]))
        return f"{name} ({axes[dof - int(m.jnt_dofadr[j])]})" if axes else name
    if control:
        return f"ctrl of actuator '{mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_ACTUATOR, i) or f'#{i}'}'"
    if i < m.nv:
        return f"qpos of joint {joint_of(i)}"
    if i < 2 * m.nv:
        return f"qvel of joint {joint_of(i - m.nv)}"
    a = i - 2 * m.nv
    actuator = int(m.actuator_actadr.tolist().index(a)) if a in m.actuator_actadr else a
    return f"act of actuator '{mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_ACTUATOR, actuator) or a}'"


def _sensor(m: mujoco.MjModel, i: int | np.integer) -> str:
    """Name of sensordata entry ``i``: the sensor, its type and (several components) which one."""
    k = int(np.searchsorted(m.sensor_adr, i, side="right")) - 1
    name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_SENSOR, k) or f"#{k}"
    kind = mujoco.mjtSensor(int(m.sensor_type[k])).name.removeprefix("mjSENS_").lower()
    part = f"[{i - int(m.sensor_adr[k])}]" if m.sensor_dim[k] > 1 else ""
    return f"sensor '{name}'{part} ({kind})"


#: The compared matrices: name, output rows are sensors, columns are controls.
MATRICES = (("A", False, False), ("B", False, True), ("C", True, False), ("D", True, True))


def _ratios(m: mujoco.MjModel, state: dict[str, np.ndarray], code: str | None) -> dict[str, tuple]:
    """Per matrix of :data:`MATRICES` (those with entries): (|MJX - C| / bound with NaN as inf,
    MJX, C at EPS / 10, C at EPS, the bound): the bound is :func:`floor` plus
    ``RTOL x max(|MJX|, |C|)``."""
    mjx_all = mjx_jacobians(m, state, code)
    fine_all = c_jacobians(m, state, EPS / 10)
    coarse_all = c_jacobians(m, state, EPS)
    out = {}
    for (name, sensors, _), x, fine, coarse in zip(MATRICES, mjx_all, fine_all, coarse_all):
        if x.size:
            fl = floor(m, state, fine, coarse, sensors) + RTOL * np.maximum(np.abs(x), np.abs(fine))
            ratio = np.abs(x - fine) / fl
            out[name] = (np.where(np.isnan(ratio), np.inf, ratio), x, fine, coarse, fl)
    return out


#: How many failing entries besides the worst a failure lists (``worst["entries"]``).
ENTRIES = 5


def _describe(m: mujoco.MjModel, name: str, i: int | np.integer, j: int | np.integer) -> dict[str, Any]:
    sensors, control = next((s, c) for n, s, c in MATRICES if n == name)
    return dict(matrix=name, row=int(i), column=int(j), output=_sensor(m, i) if sensors else _component(m, i, False),
                input=_component(m, j, True, control=control))


def _worst(m: mujoco.MjModel, ratios: dict[str, tuple]) -> tuple[float, dict[str, Any]]:
    """The largest ratio and its entry (named, with MJX's and C's values), plus in ``entries``
    the :data:`ENTRIES` largest failing entries (ratio > 1) over all matrices."""
    flat = sorted(((float(r[i, j]), name, i, j) for name, (r, *_) in ratios.items()
                   for i, j in zip(*np.nonzero(r > 1))), reverse=True)[:ENTRIES]
    if not flat:
        name, (r, *_) = max(ratios.items(), key=lambda kv: float(kv[1][0].max()))
        i, j = np.unravel_index(int(np.argmax(r)), r.shape)
        flat = [(float(r[i, j]), name, i, j)]
    ratio, name, i, j = flat[0]
    _, x, fine, coarse, _ = ratios[name]
    entries = [dict(_describe(m, n, a, b), ratio=q) for q, n, a, b in flat if q > 1]
    nan = sum(int(np.isnan(v[1]).sum()) for v in ratios.values())
    return ratio, dict(_describe(m, name, i, j), mjx=float(x[i, j]), c=float(fine[i, j]),
                       c_coarse=float(coarse[i, j]), entries=entries, nan=nan,
                       size=sum(int(v[1].size) for v in ratios.values()))


def _jumps(ratios: dict[str, tuple], fd: dict[str, tuple]) -> dict[str, np.ndarray]:
    """Per matrix, the failing entries where MJX's own forward is not smooth inside the stencil:
    its finite differences at EPS / 10 and EPS part by more than 1000 x C's floor and 1e-3 x
    (1 + |C|) (a jump in MJX's dynamics, such as a tie in its contact selection, grows them as
    1 / eps; C's constraint set stayed the same)."""
    return {name: (r > 1) & (np.abs(fd[name][0] - fd[name][1]) > np.maximum(1e3 * fl, 1e-3 * (1 + np.abs(fine))))
            for name, (r, _, fine, _, fl) in ratios.items()}


def _kind(ad: float, c: float, mjx_fd: float) -> str:
    """Whether MJX's gradient ``ad`` is wrong for its own dynamics (its finite differences
    ``mjx_fd`` agree with C's ``c``: ``derivative only``) or follows dynamics that differ from C's
    (they agree with ``ad``: ``forward dynamics``)."""
    off = abs(ad - c) if np.isfinite(ad) else np.inf
    if abs(mjx_fd - c) < off / 10:
        return "derivative only"
    return "forward dynamics" if abs(mjx_fd - ad) < off / 10 else "derivative and forward"


def judge_state(m: mujoco.MjModel, state: dict[str, np.ndarray], index: int = 0, member: int = 0,
                step: int = 0, code: str | None = None) -> StateResult:
    """The verdict at one state (see the module docstring); ``code`` as for :func:`mjx_jacobians`.

    A failure is checked against MJX's own finite differences (:func:`mjx_fd`): entries where
    MJX's forward jumps inside the stencil are set aside (only such entries: ``non-smooth``,
    ``worst["reason"]`` says so); the worst of the rest is classed ``derivative only`` or
    ``forward dynamics`` (``worst["kind"]``) and sits in the ``constraint`` part when, with
    constraints disabled on both sides, that same entry agrees; else in the ``smooth dynamics``."""
    if has_constraints(m) and not smooth_at(m, state):
        return StateResult(index, member, step, "non-smooth")
    ratios = _ratios(m, state, code)
    ratio, worst = _worst(m, ratios)
    if not ratio > 1:
        return StateResult(index, member, step, "pass", ratio, worst)
    fd = mjx_fd(m, state, code)
    jumps = _jumps(ratios, fd)
    if all(not (r > 1)[~jumps[name]].any() for name, (r, *_) in ratios.items()):
        reason = (f"MJX's forward jumps inside the stencil (C's does not): its own finite differences of "
                  f"d {worst['output']} / d {worst['input']} are "
                  f"{fd[worst['matrix']][1][worst['row'], worst['column']]:.4g} "
                  f"at {EPS:g} and {fd[worst['matrix']][0][worst['row'], worst['column']]:.4g} at {EPS / 10:g}")
        return StateResult(index, member, step, "non-smooth", ratio, dict(worst, reason=reason))
    kept = {name: (np.where(jumps[name], 0.0, r), *rest) for name, (r, *rest) in ratios.items()}
    ratio, worst = _worst(m, kept)
    kind = _kind(worst["mjx"], worst["c"], float(fd[worst["matrix"]][1][worst["row"], worst["column"]]))
    part = "smooth dynamics"
    if has_constraints(m):
        free = copy.copy(m)
        free.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONSTRAINT)
        unconstrained = _ratios(free, state, code)[worst["matrix"]][0][worst["row"], worst["column"]]
        part = "constraint" if unconstrained <= 1 else "smooth dynamics"
    return StateResult(index, member, step, "fail", ratio,
                       dict(worst, part=part, kind=kind,
                            mjx_fd=float(fd[worst["matrix"]][1][worst["row"], worst["column"]])))


def sample_states(scenario, m: mujoco.MjModel, count: int, seed: int = 0, steps: int | None = None
                  ) -> list[tuple[mujoco.MjModel, int, int, dict[str, np.ndarray]]]:
    """``count`` states: (member model, member, step, state); members' initial states and states
    along their C rollouts, evenly spaced over the horizon."""
    from mjxdiff.engine.engines import CEngine
    from mjxdiff.input.inputs import make_inputs

    members = max(1, min(count, 4))
    T = steps or min(scenario.steps, 200)
    inputs = make_inputs(scenario, m, seed, members, T)
    traj = CEngine().rollout(inputs)
    per = -(-count // members)
    out = []
    for k in range(per):
        step = int(round(k * (T - 1) / max(per - 1, 1))) if per > 1 else 0
        for b in range(members):
            if len(out) == count:
                break
            if step == 0:
                q, v, a = inputs.qpos[b], inputs.qvel[b], inputs.act[b]
            else:
                q, v, a = traj.qpos[b, step - 1], traj.qvel[b, step - 1], traj.act[b, step - 1]
            state = dict(qpos=np.array(q), qvel=np.array(v), act=np.array(a), ctrl=np.array(inputs.ctrl[b, step]))
            out.append((inputs.models[b], b, step, state))
    return out


def check_scenario(scenario, count: int = 8, seed: int = 0, reproducers=None) -> dict[str, Any]:
    """Every sampled state of a scenario judged; models with constraints get a converged solver
    on both sides. Returns a JSON-ready dict: status (``pass``/``fail``/``non-smooth`` (no state
    was smooth: nothing judged)/``unsupported``/``error``), message, smooth and non-smooth counts,
    the worst ratio and each state's result. ``reproducers``: a directory where the worst failing
    state is saved for ``mjxdiff replay`` (``reproducer`` in the dict: its path)."""
    import time

    from mjxdiff.input.scenario import load_model

    t0 = time.perf_counter()
    try:
        m = load_model(scenario)
        states = sample_states(scenario, m, count, seed)
    except Exception as e:  # noqa: BLE001 - one scenario's trouble is its own
        return dict(name=scenario.name, status="error", message=one_line(e))
    from mjxdiff.engine.digest import code_digest
    from mjxdiff.engine.trace_deps import fresh_digest

    fresh_digest()  # JAX's own caches forget MJX code that has changed since
    from mjxdiff.runner.sweep import release_compiled_if_crowded

    if release_compiled_if_crowded():  # many scenarios in one process: the kernel's map limit
        _jacobian_fn.cache_clear()
        _values_fn.cache_clear()
    code = code_digest()
    results: list[StateResult] = []
    judged_at: list[tuple[mujoco.MjModel, dict[str, np.ndarray]]] = []
    try:
        with enable_x64(True):
            for i, (mi, member, step, state) in enumerate(states):
                if has_constraints(mi):
                    mi = copy.copy(mi)
                    converge_solver(mi)
                results.append(judge_state(mi, state, i, member, step, code))
                judged_at.append((mi, state))
    except NotImplementedError as e:
        return dict(name=scenario.name, status="unsupported", message=f"MJX does not support: {e}")
    except mujoco.FatalError as e:  # e.g. "mjd_transitionFD: RK4 integrator is not supported"
        status = "unsupported" if "not supported" in str(e) else "error"
        return dict(name=scenario.name, status=status, message=f"MuJoCo C: {' '.join(str(e).split())}")
    except Exception as e:  # noqa: BLE001 - one scenario's trouble is its own; the others go on
        return dict(name=scenario.name, status="error", message=one_line(e))
    judged = [r for r in results if r.status != "non-smooth"]
    failed = [r for r in judged if r.status == "fail"]
    worst = max(judged, key=lambda r: r.ratio, default=None)
    non_smooth = len(results) - len(judged)
    if failed:
        w = max(failed, key=lambda r: r.ratio)
        message = (f"{len(failed)} of {len(judged)} smooth states fail; worst at state {w.index} (member {w.member}, "
                   f"step {w.step}): {_entry(w)}")
        status = "fail"
    elif worst:
        message = f"{len(judged)} smooth states agree (worst {worst.ratio:.2g}x the bound)"
        status = "pass"
    else:  # judged nothing: neither a pass nor a failure
        message = "no smooth state to judge: sample more states (--states) or states away from contact changes"
        status = "non-smooth"
    if non_smooth:
        message += f"; {non_smooth} of {len(results)} states non-smooth (constraint set changes in the stencil)"
    path = heatmap = None
    if failed:
        w = max(failed, key=lambda r: r.ratio)
        if reproducers is not None:
            path = _save_reproducer(reproducers, scenario, w, judged_at, dict(states=count, seed=seed))
        with enable_x64(True):
            heatmap = dict(state=w.index, log10_ratio=log10_ratios(*judged_at[w.index], code))
    return dict(name=scenario.name, status=status, message=message, states=len(results), smooth=len(judged),
                non_smooth=non_smooth, worst_ratio=worst.ratio if worst else None,
                seconds=time.perf_counter() - t0, results=[dataclasses.asdict(r) for r in results], reproducer=path,
                heatmap=heatmap)


def log10_ratios(m: mujoco.MjModel, state: dict[str, np.ndarray], code: str | None = None
                 ) -> dict[str, list[list[float]]]:
    """log10(|MJX - C| / floor) of every entry of A, B, C and D at one state (NaN in MJX, or a
    ratio above 1e12, as 12; below 1e-3 as -3), rounded to 0.01: the report page's heat maps."""
    return {name: np.clip(np.log10(np.maximum(r, 1e-3)), -3, 12).round(2).tolist()
            for name, (r, *_) in _ratios(m, state, code).items()}


def _save_reproducer(directory, scenario, result: StateResult, judged_at, config: dict[str, Any]) -> str | None:
    """The failing state ``result`` saved under ``directory`` for ``mjxdiff replay``; its path.
    ``config``: how the states were drawn (count, seed)."""
    from mjxdiff.output import report, reproducer

    m, state = judged_at[result.index]
    file = f"{report.safe_filename(scenario.name)}-grad-state{result.index}.json"
    return str(reproducer.save_grad(report.path_under(directory, file), scenario.name, result.index, m,
                                    scenario.model_path.read_text(), state, dataclasses.asdict(result), config))


def replay(rep) -> tuple[StateResult, bool]:
    """A derivative reproducer (:class:`mjxdiff.output.reproducer.GradReproducer`) judged again: the
    result, and whether it has the saved status and worst entry (matrix, row, column)."""
    from mjxdiff.engine.digest import code_digest
    from mjxdiff.engine.trace_deps import fresh_digest

    fresh_digest()
    with enable_x64(True):
        r = judge_state(rep.model, rep.state, rep.index, rep.verdict.get("member", 0), rep.verdict.get("step", 0),
                        code_digest())
    then = rep.verdict.get("worst") or {}
    same = r.status == rep.verdict["status"] and (
        r.status != "fail" or all(then.get(k) == r.worst.get(k) for k in ("matrix", "row", "column")))
    return r, same


def _entry(r: StateResult) -> str:
    """A failing state's worst entry, in words."""
    x = r.worst
    nan = f"; {x['nan']} of {x['size']} MJX entries NaN" if x.get("nan") else ""
    return (f"d {x['output']} / d {x['input']} ({x['matrix']}[{x['row']}, {x['column']}]) MJX {x['mjx']:.6g}, "
            f"C {x['c']:.6g}, {r.ratio:.3g}x its bound; in the {x['part']}, {x['kind']} (MJX's own finite "
            f"difference {x['mjx_fd']:.6g}){nan}")


def format_state(r: StateResult) -> str:
    """One line for one state's verdict."""
    head = f"state {r.index} (member {r.member}, step {r.step}): {r.status}"
    if r.status == "fail":
        return f"{head}: {_entry(r)}"
    return head + (f", worst {r.ratio:.2g}x the bound" if r.status == "pass" else "")


def format_text(rows: list[dict[str, Any]]) -> str:
    symbol = {"pass": "PASS", "fail": "FAIL", "non-smooth": "NONSM", "unsupported": "UNSUP", "error": "ERROR"}
    return "\n".join(f"{symbol[r['status']]:<6} {r['name']:<28} {r['message']}" for r in rows)
