"""The divergence a model shows, from one state: its :class:`Signature` (the first stage of the
forward pass that differs, or the first field of one converged step beyond :data:`STEP_RTOL`),
the :class:`State` it is seen from, kept by name, and the state a model first diverges at
(:func:`find_state`). What :mod:`mjxdiff.tools.shrink` keeps fixed while it edits the model."""

from __future__ import annotations

import copy
import dataclasses
import re
from typing import Callable

import mujoco
import numpy as np

from mjxdiff.input.joints import DOF_WIDTH, QPOS_WIDTH

__all__ = ["KINDS", "OPTIONS", "STEP_RTOL", "Signature", "State", "drill", "find_state", "focus_bodies", "probe",
           "scaled_error", "significant", "step_errors", "transfer_contacts"]

#: Relative disagreement (|mjx - c| / (1 + max|c|)) of one converged step above which it differs:
#: far above a step's rounding (1e-15 of the scale) and a converged solver's residue.
STEP_RTOL = 1e-6
#: XLA compiles a shrink keeps in JAX's in-memory caches before it clears them.
KEEP_COMPILED = 16
#: The fields a step compares, in order.
STEP_FIELDS = ("qpos", "qvel", "act", "sensordata")
#: Element lists delta debugging drops from, coarse to fine (MjSpec attribute names).
KINDS = ("bodies", "joints", "geoms", "sites", "actuators", "sensors", "tendons", "equalities", "pairs", "excludes",
         "keys", "cameras", "lights", "numerics", "texts", "tuples", "materials", "textures")
#: Options reset one by one to MuJoCo's defaults (``mjOption``), after the elements.
OPTIONS = ("integrator", "cone", "jacobian", "solver", "iterations", "ls_iterations", "tolerance", "ls_tolerance",
           "noslip_iterations", "impratio", "timestep", "gravity", "wind", "magnetic", "density", "viscosity",
           "o_margin", "o_solref", "o_solimp", "o_friction")


@dataclasses.dataclass(frozen=True)
class Signature:
    """What diverges, independent of names and sizes: which ``check``, the first differing
    ``stage`` and ``field``, and for contacts the geom ``kinds`` (e.g. ``box-box``)."""

    check: str
    stage: str
    field: str
    kinds: str = ""

    def describe(self) -> str:
        if self.check == "transfer":
            return f"mjx.get_data(mjx.put_data(C's data)) differs from C's data: {self.field}"
        where = f"{self.stage}: {self.field}" + (f" ({self.kinds})" if self.kinds else "")
        return f"{'mj_forward' if self.check == 'forward' else 'one mj_step'} differs first at {where}"


@dataclasses.dataclass(frozen=True)
class State:
    """One state by name. ``joints``: (name, qpos, qvel) per joint; ``actuators``: (name, ctrl,
    act) per actuator (act empty without activation); ``time`` in seconds."""

    joints: tuple[tuple[str, tuple[float, ...], tuple[float, ...]], ...]
    actuators: tuple[tuple[str, float, tuple[float, ...]], ...]
    time: float = 0.0

    @classmethod
    def of(cls, m: mujoco.MjModel, d: mujoco.MjData) -> State:
        joints = tuple((_name(m, mujoco.mjtObj.mjOBJ_JOINT, j), tuple(d.qpos[_qpos(m, j)].tolist()),
                        tuple(d.qvel[_dofs(m, j)].tolist())) for j in range(m.njnt))
        acts = tuple((_name(m, mujoco.mjtObj.mjOBJ_ACTUATOR, a), float(d.ctrl[a]),
                      tuple(d.act[m.actuator_actadr[a]:m.actuator_actadr[a] + m.actuator_actnum[a]].tolist())
                      if m.actuator_actadr[a] >= 0 else ()) for a in range(m.nu))
        return cls(joints, acts, float(d.time))

    def data(self, m: mujoco.MjModel) -> mujoco.MjData:
        """An ``MjData`` of ``m`` in this state: joints and actuators it does not name keep
        their defaults (``qpos0``, zero)."""
        d = mujoco.MjData(m)
        joints = {n: (q, v) for n, q, v in self.joints}
        for j in range(m.njnt):
            name = _name(m, mujoco.mjtObj.mjOBJ_JOINT, j)
            if name not in joints:
                continue
            q, v = joints[name]
            if len(q) == len(d.qpos[_qpos(m, j)]) and len(v) == len(d.qvel[_dofs(m, j)]):
                d.qpos[_qpos(m, j)], d.qvel[_dofs(m, j)] = q, v
        acts = {n: (c, a) for n, c, a in self.actuators}
        for i in range(m.nu):
            c, a = acts.get(_name(m, mujoco.mjtObj.mjOBJ_ACTUATOR, i), (0.0, ()))
            d.ctrl[i] = c
            if m.actuator_actadr[i] >= 0 and len(a) == m.actuator_actnum[i]:
                d.act[m.actuator_actadr[i]:m.actuator_actadr[i] + len(a)] = a
        d.time = self.time
        return d

    def rounded(self, digits: int) -> State:
        """Every number to ``digits`` significant digits."""
        def r(xs):
            return tuple(significant(x, digits) for x in xs)
        return State(tuple((n, r(q), r(v)) for n, q, v in self.joints),
                     tuple((n, significant(c, digits), r(a)) for n, c, a in self.actuators),
                     significant(self.time, digits))


def significant(x: float, digits: int) -> float:
    """``x`` to ``digits`` significant digits (the shortest decimal: ``0.12``, not ``0.12000000000000001``)."""
    return float(f"{x:.{digits}g}")


def _name(m: mujoco.MjModel, obj: mujoco.mjtObj, i: int) -> str:
    return mujoco.mj_id2name(m, obj, int(i)) or f"#{int(i)}"


def _qpos(m: mujoco.MjModel, j: int) -> slice:
    a = int(m.jnt_qposadr[j])
    return slice(a, a + QPOS_WIDTH[int(m.jnt_type[j])])


def _dofs(m: mujoco.MjModel, j: int) -> slice:
    a = int(m.jnt_dofadr[j])
    return slice(a, a + DOF_WIDTH[int(m.jnt_type[j])])


# -- the check ------------------------------------------------------------------------------------

_JITTED: dict[str, Callable] = {}


def _jitted(name: str) -> Callable:
    """``mjx.<name>`` jitted with the model as an argument (one compile per structure), compiled
    quickly (:func:`mjxdiff.compat.jit_for_few_calls`): a shrink compiles once per candidate
    structure and runs each once."""
    if name not in _JITTED:
        from mujoco import mjx

        from mjxdiff import compat
        _JITTED[name] = compat.jit_for_few_calls(getattr(mjx, name))
    return _JITTED[name]


class _Forward:
    """The engine :func:`probe`'s drill-down runs: MJX's forward as
    :meth:`mjxdiff.engine.engines.MJXEngine.forward`, compiled by :func:`_jitted`."""

    name = "mjx"

    def forward(self, m: mujoco.MjModel, d: mujoco.MjData, fields: tuple[str, ...]):
        from mujoco import mjx

        from mjxdiff.engine import stages
        from mjxdiff.engine.trace_deps import fresh_digest
        from mjxdiff.engine.stages import Forward
        fresh_digest()  # never a trace of MJX code since changed
        mx = mjx.put_model(m)
        dx = _jitted("forward")(mx, mjx.put_data(m, d))
        return Forward({f: np.asarray(getattr(dx, f)).ravel() for f in fields}, np.asarray(mjx.full_m(mx, dx)),
                       stages.contacts_mjx(m, dx))


def scaled_error(c: np.ndarray, x: np.ndarray) -> float:
    """``max |x - c| / (1 + max |c|)`` (inf where ``x`` has a NaN); 0 for empty arrays."""
    c, x = np.ravel(c), np.ravel(x)
    if c.size == 0:
        return 0.0
    e = np.abs(x - c) / (1.0 + np.max(np.abs(c)))
    return float(np.inf) if np.isnan(e).any() else float(e.max())


def step_errors(m: mujoco.MjModel, state: State) -> dict[str, float]:
    """One step from ``state``, C against MJX, both solvers converged: the scaled error
    ``max |mjx - c| / (1 + max |c|)`` of each of :data:`STEP_FIELDS`."""
    from mujoco import mjx

    from mjxdiff.compare.noise import converge_solver

    m = copy.copy(m)
    converge_solver(m)
    d = state.data(m)
    dx = _jitted("step")(mjx.put_model(m), mjx.put_data(m, d))
    mujoco.mj_step(m, d)
    return {f: scaled_error(getattr(d, f), np.asarray(getattr(dx, f))) for f in STEP_FIELDS}


def transfer_contacts(m: mujoco.MjModel, state: State) -> tuple[int, int]:
    """(C's contact count after ``mj_forward`` from ``state``, the count ``mjx.get_data`` gives
    back from ``mjx.put_data`` of that data): the host interface, no MJX physics."""
    from mujoco import mjx

    d = state.data(m)
    mujoco.mj_forward(m, d)
    back = mjx.get_data(m, mjx.put_data(m, d))  # one MjData for unbatched data
    return d.ncon, back.ncon if isinstance(back, mujoco.MjData) else back[0].ncon


def probe(m: mujoco.MjModel, state: State) -> Signature | None:
    """The divergence ``m`` shows from ``state``, or None: the forward drill-down's first
    differing stage, else the first field of one step beyond :data:`STEP_RTOL`, else contacts
    lost between C and MJX's data (:func:`transfer_contacts`). Physics with the solver converged
    (:func:`mjxdiff.compare.noise.converge_solver`): a solver stopped after a few iterations parts MJX
    from C by truncation, which is no bug to shrink."""

    dd = drill(m, state)
    if dd.first_stage is not None:
        return Signature("forward", dd.first_stage, str(dd.first_field), (dd.contact or {}).get("pair", ""))
    errors = step_errors(m, state)
    field = next((f for f in STEP_FIELDS if not errors[f] <= STEP_RTOL), None)
    if field:
        return Signature("step", "integration", field)
    c, back = transfer_contacts(m, state)
    return Signature("transfer", "transfer", "contact") if c != back else None


def drill(m: mujoco.MjModel, state: State):
    """The forward drill-down from ``state``, both solvers converged."""
    from mjxdiff.compare.diagnose import drill_down
    from mjxdiff.compare.noise import converge_solver

    m = copy.copy(m)
    converge_solver(m)
    d = state.data(m)
    return drill_down(m, d.qpos.copy(), d.qvel.copy(), d.act.copy(), d.ctrl.copy(), float(d.time),
                      engine=_Forward())  # pyright: ignore[reportArgumentType]


def focus_bodies(m: mujoco.MjModel, obj: str) -> set[str]:
    """The bodies holding what a drill-down's ``obj`` names (a geom pair ``geoms a / b``, a
    ``joint 'j'``, a ``body 'b'``), with their ancestors, by name; empty where it names none
    of these."""
    ids: list[int] = []
    pair = re.match(r"geoms (\S+) / (\S+) \(", obj)
    if pair:
        ids = [int(m.geom_bodyid[m.geom(g).id]) for g in pair.groups() if not g.startswith("#")]
    for kind, name in re.findall(r"(joint|body) '([^']+)'", obj):
        ids.append(int(m.jnt_bodyid[m.joint(name).id]) if kind == "joint" else m.body(name).id)
    out: set[str] = set()
    for b in ids:
        while b > 0:
            out.add(m.body(b).name)
            b = int(m.body_parentid[b])
    return out


def find_state(m: mujoco.MjModel, steps: int = 200, key: int | None = None,
               ctrl: Callable[[int], np.ndarray] | None = None,
               start: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> tuple[State, Signature, int] | None:
    """The first state of C's rollout from ``key`` (a keyframe), or ``start`` (qpos, qvel, act),
    else ``qpos0`` at rest, with controls ``ctrl(step)`` (default zero) at which :func:`probe`
    finds a divergence, checked before each of ``steps`` steps: (state, signature, step), or None."""
    d = mujoco.MjData(m)
    if key is not None:
        mujoco.mj_resetDataKeyframe(m, d, key)
    elif start is not None:
        d.qpos[:], d.qvel[:] = start[0], start[1]
        if m.na:
            d.act[:] = start[2]
    for k in range(steps):
        if ctrl is not None:
            d.ctrl[:] = ctrl(k)
        state = State.of(m, d)
        sig = probe(m, state)
        if sig is not None:
            return state, sig, k
        mujoco.mj_step(m, d)
    return None


# -- the model ------------------------------------------------------------------------------------


