"""Which combinations of the conditions MJX branches on the scenarios exercise: pairwise coverage.

MJX's code selects on model options and element attributes (``if m.opt.disableflags &
DisableBit.EULERDAMP``, ``jp.where(m.actuator_ctrllimited, ...)``, ``if dyn_typ ==
DynType.FILTEREXACT``) and on the state (a control outside its range, the upper limit
active, a tendon longer than its spring's deadband). A bug in one branch shows only where
every condition that leads to it holds at once, so covering each condition once (a
parameter moved, a line traced) is not enough. This module records those conditions as
data (:data:`GROUPS`: factors, their levels and where MJX reads them) and measures which
*pairs* of levels some member of some scenario holds together.

A pair counts only where a compared field depends on it: within one element (the same
actuator is ctrllimited *and* driven outside its range), or, for options, in a model that
has the element the option acts on (``cone`` only where contacts occur). Levels that
depend on the state are read off MuJoCo C stepping the member's own inputs
(:func:`observe`). Pairs no model can hold are listed with the reason
(:attr:`Group.infeasible`) and left out of the percentage.

``python -m mjxdiff coverage`` reports it for the bundled scenarios, ``mjxdiff fuzz`` for
what it generated (and aims its generation at pairs not yet covered).
"""

from __future__ import annotations

import dataclasses
import itertools
from typing import Any, Iterable, Mapping, Sequence

import mujoco
import numpy as np

from mjxdiff.input.joints import active_limits

__all__ = ["GROUPS", "Factor", "Group", "Observed", "covered_pairs", "feasible_pairs", "format_text", "observe",
           "pair_name", "pairwise", "rows"]


@dataclasses.dataclass(frozen=True)
class Factor:
    """One condition MJX branches on.

    Attributes:
      name: ``<element>.<attribute>`` (MuJoCo's names) or ``opt.<option>``.
      levels: the values that take different MJX code paths.
      mjx: where MJX reads it (``file.py:function``).
    """

    name: str
    levels: tuple[str, ...]
    mjx: str


@dataclasses.dataclass(frozen=True)
class Group:
    """Factors whose levels combine in one MJX computation; their pairs are counted.

    Attributes:
      name: what the group covers.
      scope: the element each row describes (``actuator``, ``joint``, ``tendon``,
        ``equality``, ``sensor``) or ``model`` (one row per model).
      factors: its factors.
      infeasible: ``(factor, level, factor, level, reason)`` of pairs no model can hold
        (``"*"`` for any level).
    """

    name: str
    scope: str
    factors: tuple[Factor, ...]
    infeasible: tuple[tuple[str, str, str, str, str], ...] = ()


_ACT = ("unlimited", "limited", "stateless")
_ACTEARLY = ("known divergence: MJX 3.17 ignores actearly (its force uses the current activation, C's the next "
             "one), so no sweep can judge it (tests/test_known_divergences.py)")
_PASSIVE_FLAGS = ("known divergence: MJX 3.17's passive() returns no passive force at all (nor gravcomp) when "
                  "either the spring or the damper flag is disabled; C 4.0 drops only the one disabled "
                  "(tests/test_known_divergences.py)")
GROUPS: tuple[Group, ...] = (
    Group("constraint solver", "model", (
        Factor("opt.cone", ("pyramidal", "elliptic"),
               "constraint.py:_instantiate_contact, solver.py:_update_constraint"),
        Factor("opt.solver", ("CG", "Newton"), "solver.py:solve"),
        Factor("opt.impratio", ("1", "above 1"), "constraint.py:make_efc (friction regularisation)"),
        Factor("flag.warmstart", ("on", "off"), "solver.py:solve (qacc_warmstart)"),
        Factor("dof.frictionloss", ("none", "present"), "constraint.py:_instantiate_friction"),
    )),
    Group("integrator and passive terms", "model", (
        Factor("opt.integrator", ("Euler", "RK4", "implicitfast"), "forward.py:forward/euler/rungekutta4/implicit"),
        Factor("flag.eulerdamp", ("on", "off"), "forward.py:euler (implicit damping)"),
        Factor("dof.damping", ("none", "present"), "passive.py:_spring_damper, derivative.py:deriv_smooth_vel"),
        Factor("stiffness", ("none", "present"), "passive.py:_spring_damper (joint and tendon springs)"),
        Factor("actuator.velocity", ("none", "present"), "derivative.py:deriv_smooth_vel (gain/bias prm[2])"),
        Factor("actuator.stateful", ("none", "present"), "forward.py:_advance (act integration)"),
    ), infeasible=tuple(
        ("opt.integrator", i, "flag.eulerdamp", "off", "eulerdamp is read by the Euler integrator only")
        for i in ("RK4", "implicitfast"))),
    Group("passive flags", "model", (
        Factor("flag.spring", ("on", "off"), "passive.py:passive, derivative.py:deriv_smooth_vel"),
        Factor("flag.damper", ("on", "off"), "passive.py:passive, derivative.py:deriv_smooth_vel"),
        Factor("stiffness", ("none", "present"), "passive.py:_spring_damper"),
        Factor("dof.damping", ("none", "present"), "passive.py:_spring_damper"),
    ), infeasible=(
        ("flag.spring", "off", "flag.damper", "on", _PASSIVE_FLAGS),
        ("flag.spring", "on", "flag.damper", "off", _PASSIVE_FLAGS),
        ("flag.spring", "off", "stiffness", "none", "the spring flag switches nothing in a model without springs"),
        ("flag.damper", "off", "dof.damping", "none", "the damper flag switches nothing in a model without damping"),
    )),
    Group("gravity", "model", (
        Factor("flag.gravity", ("on", "off"), "smooth.py:rne, passive.py:passive (gravcomp)"),
        Factor("body.gravcomp", ("none", "present"), "passive.py:passive"),
    )),
    Group("actuator limits", "actuator", (
        Factor("actuator.ctrllimited", ("no", "yes"), "forward.py:fwd_actuation (jp.clip of ctrl)"),
        Factor("ctrl", ("inside", "outside"), "forward.py:fwd_actuation (the clamp acts)"),
        Factor("flag.clampctrl", ("on", "off"), "forward.py:fwd_actuation"),
        Factor("actuator.forcelimited", ("no", "yes"), "forward.py:fwd_actuation (force clamp)"),
        Factor("actuator.actlimited", _ACT, "forward.py:_next_activation (act clamp)"),
    ), infeasible=(
        ("actuator.ctrllimited", "no", "ctrl", "outside", "an actuator without ctrllimited has no range to leave"),
    )),
    Group("actuator dynamics", "actuator", (
        Factor("actuator.gaintype", ("fixed", "affine", "muscle"), "forward.py:fwd_actuation get_force"),
        Factor("actuator.biastype", ("none", "affine", "muscle"), "forward.py:fwd_actuation get_force"),
        Factor("actuator.dyntype", ("none", "integrator", "filter", "filterexact", "muscle"),
               "forward.py:fwd_actuation get_act_dot, forward.py:_next_activation"),
        Factor("actuator.actearly", ("no", "yes"), "forward.py:fwd_actuation (next activation)"),
    ), infeasible=(
        ("actuator.actearly", "yes", "actuator.dyntype", "none", "actearly acts only on stateful actuators"),
    ) + tuple(("actuator.actearly", "yes", f, "*", _ACTEARLY) for f in ("actuator.gaintype", "actuator.biastype"))
      + tuple(("actuator.actearly", "yes", "actuator.dyntype", d, _ACTEARLY)
              for d in ("integrator", "filter", "filterexact", "muscle"))),
    Group("frame sensors", "sensor", (
        Factor("sensor.type", ("framepos", "framequat", "framexaxis", "framelinvel", "frameangvel", "framelinacc",
                               "frameangacc"), "sensor.py:sensor_pos/sensor_vel/sensor_acc"),
        Factor("sensor.objtype", ("body", "xbody", "geom", "site"), "sensor.py:sensor_pos (objtype_data)"),
        Factor("sensor.reftype", ("none", "body", "xbody", "geom", "site"), "sensor.py:sensor_pos/sensor_vel"),
        Factor("ref.frame", ("none", "identity", "rotated"), "sensor.py (xmatref.T @ ...)"),
    ), infeasible=tuple(
        [("sensor.type", k, "sensor.reftype", r, "MJCF has no reference frame for acceleration frame sensors")
         for k in ("framelinacc", "frameangacc") for r in ("body", "xbody", "geom", "site")]
        + [("sensor.type", k, "ref.frame", r, "MJCF has no reference frame for acceleration frame sensors")
           for k in ("framelinacc", "frameangacc") for r in ("identity", "rotated")]
        + [("sensor.reftype", "none", "ref.frame", r, "no reference object, no reference frame")
           for r in ("identity", "rotated")]
        + [("sensor.reftype", r, "ref.frame", "none", "a reference object has a frame") for r in
           ("body", "xbody", "geom", "site")])),
    Group("tendon springs", "tendon", (
        Factor("tendon.type", ("fixed", "spatial"), "smooth.py:tendon, passive.py:_spring_damper"),
        Factor("tendon.spring", ("none", "point", "range"), "passive.py:_spring_damper (deadband)"),
        Factor("tendon.length", ("below", "inside", "above"), "passive.py:_spring_damper (which end acts)"),
        Factor("tendon.limited", ("no", "yes"), "constraint.py:_instantiate_limit_tendon"),
        Factor("tendon.damping", ("none", "present"), "passive.py:_spring_damper"),
    ), infeasible=(
        ("tendon.spring", "none", "tendon.length", "*", "a tendon without a spring has no deadband to be in"),
        ("tendon.spring", "point", "tendon.length", "inside", "a point spring's deadband is empty"),
    )),
    Group("equality constraints", "equality", (
        Factor("eq.type", ("connect", "weld", "joint", "tendon"), "constraint.py:_instantiate_equality_*"),
        Factor("eq.solref", ("default", "custom", "unsafe"), "constraint.py:_kbi (refsafe clamps timeconst < 2 dt)"),
        Factor("flag.refsafe", ("on", "off"), "constraint.py:_kbi"),
    ), infeasible=tuple(
        ("eq.type", t, f, "*", "active connect and weld rows: C 4.0 and MJX 3.17 compute efc_aref differently "
         "(known divergence, scenarios/equality.toml notes), so no sweep can judge them")
        for t in ("connect", "weld") for f in ("eq.solref", "flag.refsafe"))),
    Group("joint limits", "joint", (
        Factor("joint.type", ("hinge", "slide", "ball"), "constraint.py:_instantiate_limit_ball/_slide_hinge"),
        Factor("joint.limit", ("none", "lower", "upper"), "constraint.py (dist = q - lo or hi - q)"),
        Factor("joint.solref", ("default", "custom", "unsafe"), "constraint.py:_kbi"),
        Factor("flag.refsafe", ("on", "off"), "constraint.py:_kbi"),
        Factor("joint.margin", ("zero", "positive"), "constraint.py (active while dist < margin)"),
    ), infeasible=(
        ("joint.type", "ball", "joint.limit", "lower", "a ball limit is one cone angle: reported as 'upper'"),
    )),
)

_SOLREF_DEFAULT = (0.02, 1.0)


def pair_name(pair: tuple[str, str, str, str, str]) -> str:
    """``"group: factor=level x factor=level"``."""
    g, fa, la, fb, lb = pair
    return f"{g}: {fa}={la} x {fb}={lb}"


def _infeasible(group: Group, fa: str, la: str, fb: str, lb: str) -> str | None:
    for a, al, b, bl, reason in group.infeasible:
        for (x, xl), (y, yl) in (((fa, la), (fb, lb)), ((fb, lb), (fa, la))):
            if x == a and y == b and al in ("*", xl) and bl in ("*", yl):
                return reason
    return None


def feasible_pairs(groups: Sequence[Group] = GROUPS) -> tuple[set, dict]:
    """All level pairs of every group's factors: ``(feasible, {infeasible pair: reason})``;
    a pair is ``(group, factor, level, factor, level)`` with factors in the group's order."""
    feasible, infeasible = set(), {}
    for g in groups:
        for a, b in itertools.combinations(g.factors, 2):
            for la, lb in itertools.product(a.levels, b.levels):
                reason = _infeasible(g, a.name, la, b.name, lb)
                pair = (g.name, a.name, la, b.name, lb)
                if reason:
                    infeasible[pair] = reason
                else:
                    feasible.add(pair)
    return feasible, infeasible


# -- reading levels off a member --------------------------------------------------------------------


@dataclasses.dataclass
class Observed:
    """What MuJoCo C stepping one member showed (per element; indices into the model's arrays).

    Attributes:
      contacts: whether any contact occurred.
      limit: joint -> sides active ("lower", "upper"; a ball limit is "upper").
      tendon_length: tendon -> where its length was relative to its spring's deadband.
      ref_rotated: sensor -> whether its reference frame was turned more than 0.05 rad from
        the world's at some observed step.
      ctrl_outside: actuators whose control left ``ctrlrange`` at some step.
    """

    contacts: bool = False
    limit: dict[int, set] = dataclasses.field(default_factory=dict)
    tendon_length: dict[int, set] = dataclasses.field(default_factory=dict)
    ref_rotated: dict[int, bool] = dataclasses.field(default_factory=dict)
    ctrl_outside: set = dataclasses.field(default_factory=set)


def _ref_xmat(m: mujoco.MjModel, d: mujoco.MjData, reftype: int, refid: int) -> np.ndarray | None:
    Obj = mujoco.mjtObj
    if reftype == int(Obj.mjOBJ_BODY):
        return d.ximat[refid]
    if reftype == int(Obj.mjOBJ_XBODY):
        return d.xmat[refid]
    if reftype == int(Obj.mjOBJ_GEOM):
        return d.geom_xmat[refid]
    if reftype == int(Obj.mjOBJ_SITE):
        return d.site_xmat[refid]
    if reftype == int(Obj.mjOBJ_CAMERA):
        return d.cam_xmat[refid]
    return None


def _turned(xmat: np.ndarray) -> bool:
    # rotation angle from the identity: cos(angle) = (trace - 1) / 2
    return float(np.arccos(np.clip((xmat[0] + xmat[4] + xmat[8] - 1) / 2, -1, 1))) > 0.05


def observe(m: mujoco.MjModel, qpos: np.ndarray, qvel: np.ndarray, act: np.ndarray, ctrl: np.ndarray,
            max_steps: int = 200) -> Observed:
    """Steps one member in MuJoCo C (``ctrl``: (T, nu); at most ``max_steps`` steps) and records
    the state-dependent levels (:class:`Observed`)."""
    out = Observed()
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:] = qpos, qvel
    if m.na:
        d.act[:] = act
    lo, hi = m.actuator_ctrlrange[:, 0], m.actuator_ctrlrange[:, 1]
    limited = m.actuator_ctrllimited.astype(bool)
    if m.nu and len(ctrl):
        outside = limited & (np.any(ctrl < lo, axis=0) | np.any(ctrl > hi, axis=0))
        out.ctrl_outside = set(np.flatnonzero(outside).tolist())
    refs = [(s, int(m.sensor_reftype[s]), int(m.sensor_refid[s])) for s in range(m.nsensor) if m.sensor_refid[s] >= 0]
    spring = np.flatnonzero(m.tendon_stiffness > 0) if m.ntendon else np.zeros(0, int)
    mujoco.mj_forward(m, d)
    for t in range(min(len(ctrl), max_steps)):
        if m.nu:
            d.ctrl[:] = ctrl[t]
        mujoco.mj_step(m, d)
        if not np.all(np.isfinite(d.qpos)):
            break
        out.contacts |= d.ncon > 0
        for j, side in active_limits(m, d):  # a ball limit is one cone angle: its "upper" end
            out.limit.setdefault(j, set()).add("upper" if side == "ball" else side)
        for k in spring:
            length, (a, b) = d.ten_length[k], m.tendon_lengthspring[k]
            out.tendon_length.setdefault(int(k), set()).add("below" if length < a else "above" if length > b
                                                           else "inside")
        for s, reftype, refid in refs:
            if not out.ref_rotated.get(s):
                xmat = _ref_xmat(m, d, reftype, refid)
                out.ref_rotated[s] = xmat is not None and _turned(xmat)
    return out


def _flag(m: mujoco.MjModel, name: str) -> str:
    return "off" if m.opt.disableflags & int(getattr(mujoco.mjtDisableBit, f"mjDSBL_{name.upper()}")) else "on"


def _solref(solref: np.ndarray, timestep: float) -> str:
    if solref[0] > 0 and solref[0] < 2 * timestep:
        return "unsafe"
    return "default" if np.allclose(solref, _SOLREF_DEFAULT) else "custom"


_INTEGRATORS = {int(mujoco.mjtIntegrator.mjINT_EULER): "Euler", int(mujoco.mjtIntegrator.mjINT_RK4): "RK4",
                int(mujoco.mjtIntegrator.mjINT_IMPLICITFAST): "implicitfast",
                int(mujoco.mjtIntegrator.mjINT_IMPLICIT): "implicit"}
_GAIN = {0: "fixed", 1: "affine", 2: "muscle"}
_BIAS = {0: "none", 1: "affine", 2: "muscle"}
_DYN = {0: "none", 1: "integrator", 2: "filter", 3: "filterexact", 4: "muscle"}
_FRAME_SENSORS = {int(getattr(mujoco.mjtSensor, f"mjSENS_{k.upper()}")): k
                  for k in next(g for g in GROUPS if g.name == "frame sensors").factors[0].levels}
_OBJ = {int(mujoco.mjtObj.mjOBJ_BODY): "body", int(mujoco.mjtObj.mjOBJ_XBODY): "xbody",
        int(mujoco.mjtObj.mjOBJ_GEOM): "geom", int(mujoco.mjtObj.mjOBJ_SITE): "site"}


def _present(x) -> str:
    """``present`` where some of ``x`` is nonzero, else ``none``."""
    return "present" if np.any(x) else "none"


def _frame_sensor_rows(m: mujoco.MjModel, seen: Observed) -> list[dict[str, str]]:
    """The ``frame sensors`` group's rows: one per frame sensor (none with sensors disabled)."""
    out = []
    if not m.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_SENSOR):
        for s in range(m.nsensor):
            kind = _FRAME_SENSORS.get(int(m.sensor_type[s]))
            if kind is None:
                continue
            ref = _OBJ.get(int(m.sensor_reftype[s]), "none") if m.sensor_refid[s] >= 0 else "none"
            frame = "none" if ref == "none" else "rotated" if seen.ref_rotated.get(s) else "identity"
            out.append({"sensor.type": kind,
                        "sensor.objtype": _OBJ.get(int(m.sensor_objtype[s]), "other"),
                        "sensor.reftype": ref, "ref.frame": frame})
    return out


def _tendon_rows(m: mujoco.MjModel, seen: Observed) -> list[dict[str, str]]:
    """The ``tendon springs`` group's rows: per tendon, one per side of its spring's length
    observed (one without the length where none was)."""
    out = []
    for k in range(m.ntendon):
        a, b = m.tendon_lengthspring[k]
        spring = "none" if m.tendon_stiffness[k] <= 0 else "range" if b > a else "point"
        fixed = m.wrap_type[m.tendon_adr[k]] == int(mujoco.mjtWrap.mjWRAP_JOINT)
        row = {"tendon.type": "fixed" if fixed else "spatial",
               "tendon.spring": spring, "tendon.limited": "yes" if m.tendon_limited[k] else "no",
               "tendon.damping": _present(m.tendon_damping[k])}
        for where in sorted(seen.tendon_length.get(k, ())) or [None]:
            out.append(dict(row, **({"tendon.length": where} if where else {})))
    return out


def _equality_rows(m: mujoco.MjModel, refsafe: str) -> list[dict[str, str]]:
    """The ``equality constraints`` group's rows: one per active equality constraint of a known
    type (none with equality constraints disabled); ``refsafe`` the flag's state."""
    out = []
    if m.neq and not m.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_EQUALITY):
        names = {0: "connect", 1: "weld", 2: "joint", 3: "tendon"}
        for e in range(m.neq):
            kind = names.get(int(m.eq_type[e]))
            if kind is None:
                continue
            if m.eq_active0[e]:
                out.append({"eq.type": kind, "eq.solref": _solref(m.eq_solref[e], m.opt.timestep),
                            "flag.refsafe": refsafe})
    return out


def _limit_rows(m: mujoco.MjModel, seen: Observed, refsafe: str) -> list[dict[str, str]]:
    """The ``joint limits`` group's rows: per limited ball, slide or hinge joint, one per limit
    side observed (``none`` where none was; no rows with limits disabled)."""
    out = []
    if not m.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_LIMIT):
        types = {0: None, 1: "ball", 2: "slide", 3: "hinge"}
        for j in np.flatnonzero(m.jnt_limited):
            kind = types.get(int(m.jnt_type[j]))
            if kind is None:
                continue
            base = {"joint.type": kind, "joint.solref": _solref(m.jnt_solref[j], m.opt.timestep),
                    "flag.refsafe": refsafe, "joint.margin": "positive" if m.jnt_margin[j] > 0 else "zero"}
            for side in sorted(seen.limit.get(int(j), ())) or ["none"]:
                out.append(dict(base, **{"joint.limit": side}))
    return out


def rows(m: mujoco.MjModel, seen: Observed) -> dict[str, list[dict[str, str]]]:
    """Group name -> one ``{factor: level}`` per element of the group's scope that a compared
    field depends on (one per model for ``model`` groups; none where the group's elements are
    absent or switched off)."""
    dis = mujoco.mjtDisableBit
    flags = {f: _flag(m, f) for f in ("warmstart", "eulerdamp", "spring", "damper", "gravity", "clampctrl",
                                      "refsafe")}
    integrator = _INTEGRATORS[int(m.opt.integrator)]
    out: dict[str, list[dict[str, str]]] = {g.name: [] for g in GROUPS}
    present = _present
    actuation = m.nu and not m.opt.disableflags & int(dis.mjDSBL_ACTUATION)
    velocity = actuation and np.any(((m.actuator_gaintype == 1) & (m.actuator_gainprm[:, 2] != 0))
                                    | ((m.actuator_biastype == 1) & (m.actuator_biasprm[:, 2] != 0)))
    if seen.contacts and not m.opt.disableflags & int(dis.mjDSBL_CONSTRAINT):
        out["constraint solver"].append({
            "opt.cone": "elliptic" if m.opt.cone == int(mujoco.mjtCone.mjCONE_ELLIPTIC) else "pyramidal",
            "opt.solver": {0: "PGS", 1: "CG", 2: "Newton"}[int(m.opt.solver)],
            "opt.impratio": "above 1" if m.opt.impratio > 1 else "1",
            "flag.warmstart": flags["warmstart"], "dof.frictionloss": present(m.dof_frictionloss)})
    out["integrator and passive terms"].append({
        "opt.integrator": integrator, "flag.eulerdamp": flags["eulerdamp"], "dof.damping": present(m.dof_damping),
        "stiffness": present(np.concatenate([m.jnt_stiffness, m.tendon_stiffness])),
        "actuator.velocity": "present" if velocity else "none",
        "actuator.stateful": "present" if actuation and m.na else "none"})
    out["passive flags"].append({"flag.spring": flags["spring"], "flag.damper": flags["damper"],
                                 "stiffness": present(np.concatenate([m.jnt_stiffness, m.tendon_stiffness])),
                                 "dof.damping": present(m.dof_damping)})
    out["gravity"].append({"flag.gravity": flags["gravity"], "body.gravcomp": present(m.body_gravcomp)})
    for a in range(m.nu if actuation else 0):
        stateful = m.actuator_dyntype[a] != 0
        out["actuator limits"].append({
            "actuator.ctrllimited": "yes" if m.actuator_ctrllimited[a] else "no",
            "ctrl": "outside" if a in seen.ctrl_outside else "inside", "flag.clampctrl": flags["clampctrl"],
            "actuator.forcelimited": "yes" if m.actuator_forcelimited[a] else "no",
            "actuator.actlimited": (("limited" if m.actuator_actlimited[a] else "unlimited") if stateful
                                    else "stateless")})
        out["actuator dynamics"].append({
            "actuator.gaintype": _GAIN.get(int(m.actuator_gaintype[a]), "user"),
            "actuator.biastype": _BIAS.get(int(m.actuator_biastype[a]), "user"),
            "actuator.dyntype": _DYN.get(int(m.actuator_dyntype[a]), "user"),
            "actuator.actearly": "yes" if m.actuator_actearly[a] else "no"})
    out["frame sensors"].extend(_frame_sensor_rows(m, seen))
    out["tendon springs"].extend(_tendon_rows(m, seen))
    out["equality constraints"].extend(_equality_rows(m, flags["refsafe"]))
    out["joint limits"].extend(_limit_rows(m, seen, flags["refsafe"]))
    return out


def covered_pairs(member_rows: Mapping[str, list[dict[str, str]]]) -> set:
    """The ``(group, factor, level, factor, level)`` pairs that ``member_rows`` (:func:`rows`) hold."""
    out = set()
    for g in GROUPS:
        for row in member_rows.get(g.name, ()):
            for a, b in itertools.combinations(g.factors, 2):
                if a.name in row and b.name in row:
                    out.add((g.name, a.name, row[a.name], b.name, row[b.name]))
    return out


def member_pairs(inputs: Any, max_members: int | None = None, max_steps: int = 200) -> set:
    """Pairs every member of ``inputs`` (:class:`~mjxdiff.input.inputs.BatchedInputs`) covers."""
    out = set()
    for i in range(inputs.batch if max_members is None else min(inputs.batch, max_members)):
        mi = inputs.models[i]
        seen = observe(mi, inputs.qpos[i], inputs.qvel[i], inputs.act[i], inputs.ctrl[i], max_steps)
        out |= covered_pairs(rows(mi, seen))
    return out


def pairwise(covered: Mapping[tuple, Iterable[str]], groups: Sequence[Group] = GROUPS) -> dict[str, Any]:
    """Pairwise coverage of ``covered`` (pair -> the scenarios holding it).

    Returns:
      ``{"percent", "covered", "feasible", "groups": {group: {"covered", "feasible", "percent"}},
      "uncovered": [pair name, ...], "infeasible": {pair name: reason}, "by": {pair name: [scenario]}}``.
    """
    feasible, infeasible = feasible_pairs(groups)
    have = {p for p in covered if p in feasible}
    per = {}
    for g in groups:
        f = [p for p in feasible if p[0] == g.name]
        c = [p for p in f if p in have]
        per[g.name] = dict(covered=len(c), feasible=len(f), percent=round(100 * len(c) / max(len(f), 1), 1))
    return dict(percent=round(100 * len(have) / max(len(feasible), 1), 1), covered=len(have), feasible=len(feasible),
                groups=per, uncovered=sorted(pair_name(p) for p in feasible - have),
                infeasible={pair_name(p): r for p, r in sorted(infeasible.items())},
                by={pair_name(p): sorted(set(covered[p])) for p in sorted(have)})


def format_text(doc: Mapping[str, Any], title: str = "interaction pairs", listed: str = "coverage.json") -> str:
    """A few lines: the percentage, per group, and the uncovered pairs."""
    lines = [f"{title} covered: {doc['percent']:.1f}% ({doc['covered']} of {doc['feasible']} feasible; "
             f"{len(doc['infeasible'])} infeasible, listed in {listed})"]
    for name, g in doc["groups"].items():
        lines.append(f"  {name:<30} {g['percent']:5.1f}% ({g['covered']}/{g['feasible']})")
    if doc["uncovered"]:
        lines.append(f"  uncovered ({len(doc['uncovered'])}): " + "; ".join(doc["uncovered"]))
    return "\n".join(lines)
