"""The checks that follow a rollout's verdict, each judging a :class:`~mjxdiff.runner.stream.Case`
again: the solver floor, the one-step check, the converged twin, solver truncation, the
suspect-reference caveat, and the diagnosis of a failure (drill-down, local error, likely cause).

Every check here never raises: one that cannot run becomes a line of the verdict, which stands.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any, Callable, TypeVar

import jax
import mujoco
import numpy as np

from mjxdiff.compare import diagnose, onestep, reference
from mjxdiff.compare.noise import SOLVER_MARGIN, converged
from mjxdiff.compare.verdict import TRUNCATION, ScenarioResult, rangefinder_mask
from mjxdiff.engine.trajectory import Engine, Trajectory
from mjxdiff.errors import one_line
from mjxdiff.input.inputs import BatchedInputs
from mjxdiff.input.precision import Precision
from mjxdiff.runner.current import BudgetSpent, clocked, jax_precision, out_of_time, phase
from mjxdiff.runner.plan import layout
from mjxdiff.runner.stream import Case, verdict

_T = TypeVar("_T")


def _drill(result: ScenarioResult, inputs: BatchedInputs, traj_c: Trajectory, precision: Precision,
           engine: Engine | None = None, step: int | None = None) -> diagnose.DrillDown:
    """The stage drill-down at the state before the first divergent step (or before ``step``, of
    the same member)."""
    assert result.first_divergence is not None  # drilled down only for a failure
    member: int = result.first_divergence["member"]
    at: int = result.first_divergence["step"] if step is None else step
    return diagnose.drill_down(inputs.models[member], *diagnose.state_before(inputs, traj_c, member, at),
                               precision=precision, member=member, step=at, engine=engine)


#: How many states before the first divergence the drill-down tries where every stage agrees at it.
DRILL_BACK = 16


def _earlier_difference(result: ScenarioResult, inputs: BatchedInputs, traj_c: Trajectory, precision: Precision,
                        engine: Engine | None = None) -> diagnose.DrillDown | None:
    """The drill-down at the latest of the :data:`DRILL_BACK` states before the first divergent step
    where a stage differs, or None: where every stage agrees at the state the error left its bound,
    the step that set it off (a contact made one step apart, a landing) lies before it."""
    assert result.first_divergence is not None
    step: int = result.first_divergence["step"]
    for k in range(step - 1, max(step - DRILL_BACK, 0) - 1, -1):
        drill = _drill(result, inputs, traj_c, precision, engine, step=k)
        if drill.first_field:
            return drill
    return None


def solver_floor(result: ScenarioResult, case: Case, clock: dict[str, float]):
    """A second look at a failure that starts in the constraint stage (or in no forward stage at
    all, the step's own use of the solver): judged again against the
    larger of the rounding envelope and the solver floor (C against C with a converged solver,
    :mod:`mjxdiff.compare.noise`). Chaos amplifying where a solver stopped within its own settings
    then passes; a constraint MJX gets wrong does not.

    Returns:
      (result, C's whole trajectory or None, the drill-down or None, what was checked for
      ``info['solver_floor']``); the trajectory and drill-down are reused by the diagnosis.
      Never raises.
    """
    inputs, config = case.inputs, case.config
    traj_c = drill = None
    if out_of_time(rerun=True):  # its drill-down compiles MJX's stages, its rerun steps again
        return result, None, None, dict(status=f"not run: {BudgetSpent()}")
    try:
        traj_c = case.c_engine.rollout(inputs)
        drill = _drill(result, inputs, traj_c, config.precision, case.under_test)
        check: dict[str, Any] = dict(
            first_stage=drill.first_stage, first_field=drill.first_field, object=drill.object, contact=drill.contact,
            element=drill.element, beside_contacts=drill.beside_contacts, margin=SOLVER_MARGIN,
            status=f"not needed: the divergence starts in the {drill.first_stage} stage")
        # None: every stage of one forward agrees, so the difference is in what a step does with
        # them, and under RK4 a step solves the constraints four times, from states the drill-down
        # does not see (control-suite cartpole: 1.9e-6 at step 175, gone with a converged solver)
        if drill.first_stage not in ("constraint", "acceleration", None):
            return result, traj_c, drill, check
        if out_of_time(rerun=True):
            raise BudgetSpent()
        second, _ = verdict(case, clock, solver=True)
    except Exception as e:  # noqa: BLE001 - the verdict stands
        return result, traj_c, drill, dict(status=f"could not run: {one_line(e)}")
    first = result.first_divergence
    assert first is not None  # a failure names where it starts
    check["status"] = second.status
    gap = result.field(first["field"]) if any(f.field == first["field"] for f in result.fields) else None
    check["first"] = first
    check["gap"] = dict(field=first["field"], object=first["object"], step=first["step"],
                        error=gap.max_error if gap else first["error"], steps=inputs.steps,
                        tolerance=first["tolerance"])
    if second.status != "pass":
        return result, traj_c, drill, check
    held = [f.field for f in second.fields if f.floor == "solver"]
    where = (f"starts in the {drill.first_stage} stage ({drill.first_field}, {drill.object})" if drill.first_stage
             else "starts where every forward stage agrees (in what the step's constraint solves do)")
    message = (f"{second.message}; within C's own solver freedom: the divergence of {first['field']} at step "
               f"{first['step']} {where} and stays within {SOLVER_MARGIN:g}x C's divergence from its converged self"
               + (f" (solver floor bounds {', '.join(held)})" if held else ""))
    return dataclasses.replace(second, message=message), traj_c, drill, check


def sharp(result: ScenarioResult, case: Case, traj_c: Trajectory | None, info: dict,
          bundled: bool = False) -> ScenarioResult:
    """The checks that stay sharp where the rollout's verdict cannot: the one-step check
    (:func:`_onestep`, with ``config.onestep``), then, where the rollout's pass was held only by
    the solver floor, or was weak on a model whose solver settings the one-step check found not
    converged, the converged twin (:func:`_twin`); a pass held only by the solver floor becomes a
    ``solver truncation`` failure (:func:`_truncation`). Never raises."""
    if out_of_time(rerun=True):
        return dataclasses.replace(result, message=f"{result.message}; one-step check and converged twin not run: "
                                                   f"{BudgetSpent()}")
    excused = result.status == "pass" and info.get("solver_floor", {}).get("status") == "pass"
    found: dict = {}
    if case.config.onestep:
        phase("one-step check")
        with clocked(info["seconds"], "onestep", info["cpu_seconds"]):
            result, found, traj_c = _onestep(result, case, traj_c, evidence=excused or bool(result.weak))
        info["onestep"] = found
    converged_ = found.get("solver", {}).get("converged", True)
    twin = None
    if result.status == "pass" and (excused or (result.weak and not converged_)) and case.config.quick:
        info["twin"] = twin = dict(status="skipped", message=QUICK_SKIPS["twin"])
        result = dataclasses.replace(result, message=f"{result.message}; {QUICK_SKIPS['twin']}")
    elif result.status == "pass" and (excused or (result.weak and not converged_)):
        with clocked(info["seconds"], "twin", info["cpu_seconds"]):
            result, info["twin"] = _twin(result, case, {})
        twin = info["twin"]
    if result.status == "pass" and excused:
        result = _truncation(result, case.m, info["solver_floor"], found, twin, bundled=bundled)
    return result


def suspect_reference(result: ScenarioResult, m, info: dict) -> ScenarioResult:
    """A failure on a model where the installed C is known to be wrong (:func:`reference.suspect`)
    says so, with what to run to rule C out (``info['suspect_reference']``); a pass is left alone."""
    found = reference.suspect(m) if result.status == "fail" else None
    if found is None:
        return result
    info["suspect_reference"] = found
    return dataclasses.replace(result, message=f"{result.message}; {reference.caveat(found)}")


def _drilled(found: dict, drill: Callable[[], diagnose.DrillDown]) -> diagnose.DrillDown | None:
    """``drill()``, its first stage, field, object and contact added to ``found``; None where it
    raised, the reason in ``found["drill_error"]`` (one line): the verdict stands without its
    drill-down, and says that it could not run."""
    try:
        result = drill()
    except Exception as e:  # noqa: BLE001 - any failure of the drill-down is reported, not raised
        found["drill_error"] = one_line(e, 300)
        return None
    found.update(first_stage=result.first_stage, first_field=result.first_field, stage_object=result.object,
                 contact=result.contact, beside_contacts=result.beside_contacts, stage_element=result.element)
    return result


def _onestep(result: ScenarioResult, case: Case, traj_c: Trajectory | None,
             evidence: bool = False) -> tuple[ScenarioResult, dict, Trajectory | None]:
    """``result`` judged again by :func:`mjxdiff.compare.onestep.check` (kept in ``info['onestep']``): a
    failure there fails a passing scenario, naming the field, object, step and (from the stage
    drill-down at that state, with a converged solver) the first stage and field that differ; a
    failing scenario keeps its verdict and gains the one-step result as evidence. Never raises.

    Returns (result, what the check found, C's whole rollout or None)."""
    m, inputs, config, under_test, c_engine = case.m, case.inputs, case.config, case.under_test, case.c_engine
    try:
        traj_c = traj_c if traj_c is not None else c_engine.rollout(inputs)
        groups, chunk = layout(m, inputs, config, under_test, case.plan_for)
        found = onestep.check(m, inputs, traj_c, case.tol, under_test, c_engine, config.precision, evidence=evidence,
                              reuse=(groups[0], chunk))
    except Exception as e:  # noqa: BLE001 - the rollout's verdict stands
        found = dict(status="error", message=one_line(e))
        return dataclasses.replace(result, message=f"{result.message}; one-step check could not run: "
                                                   f"{one_line(e)}"), found, traj_c
    if found["status"] == "error":
        return (dataclasses.replace(result, message=f"{result.message}; one-step check: {found['message']}"),
                found, traj_c)
    if found["status"] == "pass":  # its own line in the report (mjxdiff.output.report.format_checks)
        return result, found, traj_c
    member, step = found["member"], found["step"]
    def at_the_state():
        row = int(np.flatnonzero(inputs.ids == member)[0])
        return diagnose.drill_down(converged(inputs.take([row])).models[0],
                                   *diagnose.state_before(inputs, traj_c, row, step),
                                   precision=config.precision, member=member, step=step, engine=under_test)

    drill = _drilled(found, at_the_state)
    if drill is None:
        where = f"; the drill-down could not run: {found['drill_error']}"
    else:
        where = (f"; {diagnose.first_fields(drill)}"
                 if drill.first_stage else "; every forward stage agrees (the difference is in the integration)")
    if config.diagnose == "full":
        found["cause"] = diagnose.reconcile_cause(_onestep_cause(case, traj_c, member, step), drill)
        if found["cause"]["ablation"]:
            where += f"; one-step cause: {found['cause']['cause']} (passes with {found['cause']['ablation']})"
    said = (f"one-step check: {found['field']} of {found['object'] or 'member ' + str(member)} after step "
            f"{step} from C's state, member {member}, {found.get('settings', 'converged')} solver in both: "
            f"error {found['error']:.3g}, "
            f"bound {found['bound']:.3g} ({found['ratio']:.3g}x){where}")
    diagnosis = result.diagnosis
    if found.get("cause", {}).get("ablation") and (diagnosis.get("cause") or {}).get("cause") in (
            None, diagnose.GENUINE, diagnose.UNCLASSIFIED):  # the one-step ablation is the sharper witness
        diagnosis = dict(diagnosis, cause=dict(found["cause"], check="onestep"))
    if result.status == "fail":
        return dataclasses.replace(result, message=f"{result.message}; {said}", diagnosis=diagnosis), found, traj_c
    first = dict(field=found["field"], step=step, time=round((step + 1) * float(m.opt.timestep), 9), member=member,
                 object=found["object"], element=found.get("element"), error=found["error"], tolerance=found["bound"],
                 check="onestep")
    return dataclasses.replace(result, status="fail", message=f"{said}; the rollout alone passed ({result.message})",
                               first_divergence=first, diagnosis=diagnosis), found, traj_c


def _onestep_cause(case: Case, traj_c: Trajectory, member: int, step: int) -> dict:
    """:func:`mjxdiff.compare.diagnose.attribute_cause` on the one failing member-state of the one-step
    check: the first ablation under which that one step agrees names the cause. Chaos cannot
    blur it, unlike the rollout's ablations on a model with several differences (a robot)."""
    row = int(np.flatnonzero(case.inputs.ids == member)[0])
    single, traj_row = case.inputs.take([row]), jax.tree.map(lambda a: a[row:row + 1], traj_c)

    def passes(ablated: BatchedInputs, precision: Precision) -> bool:
        with jax_precision(precision):
            return onestep.check(ablated.models[0], ablated, traj_row, case.tol, case.under_test, case.c_engine,
                                 precision, steps=np.array([step - 1]))["status"] == "pass"

    return diagnose.attribute_cause(passes, single, case.config.precision, skip=("solver convergence",))


def _twin(result: ScenarioResult, case: Case, clock: dict[str, float]) -> tuple[ScenarioResult, dict | None]:
    """The converged twin: both engines rerun with a converged solver
    (:func:`mjxdiff.compare.noise.converged`), judged as sharply as any converged scenario (rounding
    envelope, never the solver floor). Returns the result and what the twin found (for
    ``info['twin']``: status, worst qpos/qvel ratio, per-field ratio and ``bound_scale``, weak
    fields, seconds). A twin that fails fails the scenario, naming field, step, member and (from
    the drill-down at that state) the first stage and field that differ. Never raises."""
    t = time.perf_counter()
    twin_inputs = converged(case.inputs)
    try:
        if out_of_time(rerun=True):  # a converged solver compiles again
            raise BudgetSpent()
        twin, _ = verdict(dataclasses.replace(case, inputs=twin_inputs), clock)
    except Exception as e:  # noqa: BLE001 - the rollout's verdict stands, and says what is missing
        return dataclasses.replace(result, message=f"{result.message}; converged twin could not run: "
                                                   f"{one_line(e)}"), dict(status="error", message=one_line(e))
    worst = max((f for f in twin.fields if f.field in ("qpos", "qvel")), key=lambda f: f.ratio, default=None)
    found = dict(status=twin.status, message=twin.message, weak=list(twin.weak),
                 fields={f.field: dict(max_error=f.max_error, ratio=f.ratio, bound_scale=list(f.bound_scale),
                                       floor=f.floor) for f in twin.fields},
                 worst=dict(field=worst.field, max_error=worst.max_error, ratio=worst.ratio) if worst else None,
                 seconds=0.0)
    if twin.status == "pass":
        found["seconds"] = time.perf_counter() - t
        return result, found
    message = f"converged twin (both engines with a converged solver): {twin.message}"
    first = dict(twin.first_divergence or {}, check="twin")
    if twin.status == "fail" and twin.first_divergence:
        drill = _drilled(found, lambda: _drill(twin, twin_inputs, case.c_engine.rollout(twin_inputs),
                                               case.config.precision, case.under_test))
        if drill is None:
            message += f"; the drill-down could not run: {found['drill_error']}"
        elif drill.first_stage:
            message += f"; {diagnose.first_fields(drill)}"
    found["seconds"] = time.perf_counter() - t
    status = "fail" if twin.status == "fail" else result.status
    if status == "pass":  # the twin could not be judged (C unstable with a converged solver): say so
        return dataclasses.replace(result, message=f"{result.message}; converged twin: {twin.status}: "
                                                   f"{twin.message}"), found
    return dataclasses.replace(result, status="fail", message=f"{message}; as configured the rollout passed "
                                                            f"({result.message})", first_divergence=first), found


#: What ``--quick`` leaves out, each a compile of its own, as the verdict's line says it.
QUICK_SKIPS = {
    "twin": "converged twin not run (--quick: a compile of its own); without --quick it tells solver truncation "
            "from a bug",
    "ablations": "likely cause not sought (--quick: each ablation compiles and steps again); without --quick the "
                 "ablations name it",
}


def _solver_settings(m) -> str:
    """``CG, 200 iteration(s), 50 line-search steps, tolerance 1e-12``: the model's solver as MJCF names it."""
    solver = mujoco.mjtSolver(m.opt.solver).name.removeprefix("mjSOL_")
    return (f"{solver}, {m.opt.iterations} iteration(s), {m.opt.ls_iterations} line-search steps, "
            f"tolerance {m.opt.tolerance:g}")


def _truncation(result: ScenarioResult, m, floor: dict, found: dict, twin: dict | None,
                bundled: bool = False) -> ScenarioResult:
    """A rollout that parts from C beyond its tolerance and rounding envelope, held only by C's
    freedom under its own solver settings, is not a pass: a ``fail`` whose cause is
    :data:`TRUNCATION` (the ``solver-truncation`` entry of :mod:`mjxdiff.compare.known`, accepted by
    ``--fail-on new``), stating the gap, the converged twin, the one-step check and MJX's truncated
    step against C's. The settings are "your" settings only on the user's model; on a ``bundled``
    scenario they are the scenario's, whose pass is meant to be sharp: a defect to report."""
    gap = floor.get("gap") or {}
    whose = ("this bundled scenario's own solver settings" if bundled else "your solver settings")
    parts = [f"solver truncation: {whose} ({_solver_settings(m)}) make MJX and C differ by "
             f"{gap.get('error', float('nan')):.3g} in {gap.get('field')} ({gap.get('object') or 'a member'}) over "
             f"{gap.get('steps')} steps, from step {gap.get('step')} "
             f"(tolerance {gap.get('tolerance', float('nan')):.0e}"
             "; only C's freedom under the same settings, the solver floor, covers it)"]
    if twin and twin.get("worst"):
        w = twin["worst"]
        parts.append(f"with a converged solver they agree (twin: worst {w['field']} {w['max_error']:.2g}, "
                     f"{w['ratio']:.2g} of its bound)")
    if found.get("status") in ("pass", "fail"):
        parts.append(f"the one-step check {'passes' if found['status'] == 'pass' else 'fails'} "
                     f"({found['ratio']:.2g} of its bound)")
    evidence = found.get("as_configured")
    if evidence:
        f = evidence["fields"][evidence["field"]]
        parts.append(f"one step as configured from C's states: MJX vs C {f['error']:.2g}, C vs its converged self "
                     f"{f['truncation']:.2g} ({evidence['field']})")
    first = dict(floor["first"], check="rollout") if floor.get("first") else result.first_divergence
    if not (twin and twin.get("status") == "pass"):  # without the twin's agreement, no excuse is proven
        parts[0] = parts[0].replace("solver truncation: ", "", 1)
        said = twin or {}
        parts.append(said["message"] if said.get("status") == "skipped" else
                     f"the converged twin could not tell truncation from a bug: {said.get('status', 'not run')}"
                     f" {said.get('message', '')}".rstrip())
        return dataclasses.replace(result, status="fail", message="; ".join(parts), first_divergence=first)
    if bundled:  # only where the twin proved the engines agree: then the scenario is at fault, not MJX
        parts.append("the scenario's solver does not converge on this draw: a defect of the scenario, not of MJX "
                     "(please report it with the seed)")
    diagnosis = dict(result.diagnosis, cause=dict(cause=TRUNCATION, ablation=None, tried=[],
                                                  evidence="; ".join(parts[1:])))
    return dataclasses.replace(result, status="fail", message="; ".join(parts),
                               diagnosis=diagnosis, first_divergence=first)


def diagnose_failure(result: ScenarioResult, case: Case, traj_c: Trajectory | None = None,
                     drill: diagnose.DrillDown | None = None) -> ScenarioResult:
    """Adds local error, the stage drill-down and (``full``) the likely cause to a failing verdict;
    ``traj_c`` (C's whole rollout) and ``drill`` when already computed.

    Never raises: a part of the diagnosis that cannot run (an engine refusing
    the state or an ablated model) becomes a line in ``diagnosis['notes']``
    and in the message, and the verdict stands.
    """
    m, inputs, tol, config, under_test = case.m, case.inputs, case.tol, case.config, case.under_test
    diagnosis: dict = {}
    notes: list[str] = []
    message = result.message

    def attempt(label: str, fn: Callable[[], _T]) -> _T | None:
        try:
            if out_of_time(rerun=True):  # each part compiles MJX functions of its own
                raise BudgetSpent()
            return fn()
        except Exception as e:  # noqa: BLE001 - one scenario's diagnosis, never the sweep
            notes.append(f"{label} could not run: {one_line(e)}")
            return None

    if traj_c is None:  # whole, for the failing scenario only
        traj_c = attempt("C's full rerun", lambda: case.c_engine.rollout(inputs))
    local = None
    if traj_c is not None:
        if drill is None:
            drill = attempt("drill-down", lambda: _drill(result, inputs, traj_c, config.precision, under_test))
        local = attempt("local error", lambda: diagnose.local_error(
            inputs, traj_c, m, rangefinder_mask(m), 1, under_test))
    if local is not None:
        diagnosis["local_error"] = local
    if drill is not None:
        if drill.first_field:
            message += f"; {diagnose.first_fields(drill)}"
        elif local is not None and max(local[f] / max(getattr(tol, f), 1e-300) for f in local) > 1e-3:
            # mj_forward agrees from the same state, yet one step does not: the update after it
            drill = dataclasses.replace(drill, first_stage="integration", first_field="qpos/qvel update")
            message += "; every forward stage agrees, the one-step error does not: integration"
        else:
            whole = traj_c
            earlier = None if whole is None else attempt("the search of earlier states", lambda: _earlier_difference(
                result, inputs, whole, config.precision, under_test))
            if earlier is not None:
                drill = earlier
                message += (f"; every stage agrees at that state; the last to differ before it is step "
                            f"{earlier.step}: {diagnose.first_fields(earlier)}")
            else:
                before = min(DRILL_BACK, result.first_divergence["step"]) if result.first_divergence else 0
                message += (f"; every stage agrees at that state and at the {before} before it (an accumulation "
                            "of small differences)")
        diagnosis["drill_down"] = dataclasses.asdict(drill)
    if config.diagnose == "full" and config.quick:
        notes.append(QUICK_SKIPS["ablations"])
    elif config.diagnose == "full":
        phase("diagnosing")
        cause = diagnosis["cause"] = _likely_cause(case, drill)
        message += f"; likely cause: {cause['cause']}"
        if cause["ablation"]:
            message += f" (passes with {cause['ablation']})"
        elif "evidence" in cause:
            message += f" ({cause['evidence']})"
        notes += [f"ablation '{t['ablation']}' could not run: {t['error']}" for t in cause["tried"] if t["error"]]
    if notes:
        diagnosis["notes"] = notes
        message += "; diagnosis incomplete: " + "; ".join(notes)
    return dataclasses.replace(result, message=message, diagnosis=diagnosis)


def _likely_cause(case: Case, drill: diagnose.DrillDown | None) -> dict:
    """The failure's likely cause (``diagnosis['cause']``): :func:`mjxdiff.compare.diagnose.attribute_cause`,
    the first ablation of the whole rollout under which the verdict passes, reconciled with the
    drill-down (:func:`mjxdiff.compare.diagnose.reconcile_cause`). Each ablation compiles and steps
    again: one the budget leaves no time for raises :class:`BudgetSpent`, which the attribution
    records as an ablation that could not run."""

    def passes(ablated: BatchedInputs, precision: Precision) -> bool:
        if out_of_time(rerun=True):  # each ablation compiles and steps again
            raise BudgetSpent()
        with jax_precision(precision):
            ablation = dataclasses.replace(case, m=ablated.models[0], inputs=ablated)
            return verdict(ablation, {})[0].status == "pass"

    cause = diagnose.reconcile_cause(diagnose.attribute_cause(passes, case.inputs, case.config.precision), drill)
    if (cause["cause"] == diagnose.GENUINE and "steered_clear" not in cause and drill is not None
            and drill.first_stage == "collision"):
        # the drill-down saw the engines generate other contacts from the same state; that no
        # single ablation passes means something else differs too, which the line says (an
        # ablation that passed and was set aside keeps reconcile_cause's evidence)
        cause = dict(cause, cause="contact generation",
                     evidence=f"drill-down: {drill.object} at step {drill.step}; no ablation passes, so "
                              "something else differs as well")
    return cause
