"""Trajectories -> metrics -> a verdict per scenario.

The per-step error series come from :mod:`mjxdiff.metrics` (pure jax.numpy,
vmapped over the batch here); this module reduces them to the numbers a person
reads: the worst error of each field against its tolerance, the first step
where it is exceeded, which member and which named MuJoCo object, and the
scenario's status.

Statuses:
  ``pass``         every healthy member within every tolerance.
  ``fail``         some field exceeds its tolerance (a divergence).
  ``unsupported``  MJX refused the model; ``message`` names the feature.
  ``error``        bad input (``error_kind='input'``) or a non-finite/unstable
                   rollout (``error_kind='nan'``, naming engine, member, step).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from mjxdiff import metrics
from mjxdiff.engines import Trajectory
from mjxdiff.noise import NoiseFloor
from mjxdiff.scenario import Tolerances

__all__ = ["FieldResult", "ScenarioResult", "judge", "error_series", "STATUSES"]

STATUSES = ("pass", "fail", "unsupported", "error")


@dataclasses.dataclass(frozen=True)
class FieldResult:
    """How one compared field did over the whole batch.

    Attributes:
      field: ``qpos``, ``qvel``, ``act``, ``sensordata``, ``contacts`` or ``rangefinder``.
      max_error: worst error over members, steps and components (the field's
        units; fractions for ``contacts``/``rangefinder``).
      tolerance: the fixed floor of the bound it is judged against.
      first_step: first step (0-based) where any member exceeds its bound; -1 if none.
      member: batch member of the worst error (or of ``first_step`` when exceeded).
      object: the MuJoCo object of that component, e.g. ``joint 'hip_2'``.
      growth_rate: exponential growth rate of the batch-max error, 1/s.
      envelope: batch-max chaos envelope at the last step (0 without a noise
        floor); the bound at (member, step) is max(tolerance, envelope there).
      ratio: worst error / bound over members and steps (> 1 means out).
    """

    field: str
    max_error: float
    tolerance: float
    first_step: int
    member: int
    object: str
    growth_rate: float
    envelope: float = 0.0
    ratio: float = 0.0

    @property
    def ok(self) -> bool:
        return self.first_step < 0 and bool(np.isfinite(self.max_error))


@dataclasses.dataclass(frozen=True)
class ScenarioResult:
    """The verdict on one scenario, with everything the report shows."""

    name: str
    status: str
    message: str
    error_kind: str = ""
    fields: tuple[FieldResult, ...] = ()
    first_divergence: dict[str, Any] | None = None
    diverged_members: tuple[dict[str, Any], ...] = ()
    behaviour: dict[str, Any] = dataclasses.field(default_factory=dict)
    tolerances: dict[str, float] = dataclasses.field(default_factory=dict)
    info: dict[str, Any] = dataclasses.field(default_factory=dict)
    pass_rate: float | None = None
    threshold: float | None = None
    noise_rate: dict[str, float] = dataclasses.field(default_factory=dict)
    diagnosis: dict[str, Any] = dataclasses.field(default_factory=dict)

    def field(self, name: str) -> FieldResult:
        return next(f for f in self.fields if f.field == name)


# ----------------------------------------------------------------------------
# names of components


def _name(m: mujoco.MjModel, obj: mujoco.mjtObj, i: int) -> str:
    return mujoco.mj_id2name(m, obj, int(i)) or f"#{int(i)}"


def component_objects(m: mujoco.MjModel, layout: metrics.QposLayout) -> dict[str, list[str]]:
    """For each compared field, the MuJoCo object each column belongs to."""
    jnt = lambda j: f"joint '{_name(m, mujoco.mjtObj.mjOBJ_JOINT, j)}'"
    qpos = [jnt(j) for j in metrics.qpos_error_joint_ids(layout)]
    qvel = [jnt(j) for j in m.dof_jntid]
    sens = []
    for s in range(m.nsensor):
        kind = mujoco.mjtSensor(m.sensor_type[s]).name.removeprefix("mjSENS_").lower()
        sens += [f"sensor '{_name(m, mujoco.mjtObj.mjOBJ_SENSOR, s)}' ({kind})"] * int(m.sensor_dim[s])
    act = []
    for a in range(m.nu):
        act += [f"actuator '{_name(m, mujoco.mjtObj.mjOBJ_ACTUATOR, a)}'"] * max(int(m.actuator_actnum[a]), 0)
    return {"qpos": qpos, "qvel": qvel, "sensordata": sens, "act": act}


def rangefinder_mask(m: mujoco.MjModel) -> np.ndarray:
    """(nsensordata,) True for rangefinder outputs, whose -1 means 'no hit'."""
    mask = np.zeros(m.nsensordata, bool)
    for s in np.flatnonzero(m.sensor_type == mujoco.mjtSensor.mjSENS_RANGEFINDER):
        mask[m.sensor_adr[s]:m.sensor_adr[s] + m.sensor_dim[s]] = True
    return mask


# ----------------------------------------------------------------------------
# error series (jax)


@functools.partial(jax.jit, static_argnames=("layout",))
def error_series(a: Trajectory, b: Trajectory, layout: metrics.QposLayout, rf_mask: jax.Array) -> dict[str, jax.Array]:
    """Per member, step and component errors of trajectory ``a`` against ``b``.

    Returns:
      dict of ``qpos`` (B, T, ncomp) [m | rad], ``qvel`` (B, T, nv),
      ``act`` (B, T, na), ``sensordata`` (B, T, nsensordata) relative for
      values above 1 (``|a - b| / max(1, |b|)``), ``rangefinder`` (B, T)
      rays with a hit/no-hit disagreement, ``ncon`` (B, T) contact-count
      difference.
    """
    def one(qa, qb, va, vb, aa, ab, sa, sb):
        sens = metrics.sensor_error(sa, sb, rf_mask) / jnp.maximum(1.0, jnp.abs(sb))
        return dict(qpos=metrics.qpos_error(qa, qb, layout), qvel=metrics.qvel_error(va, vb),
                    act=jnp.abs(aa - ab), sensordata=sens,
                    rangefinder=metrics.rangefinder_hit_mismatch(sa, sb, rf_mask))

    out = jax.vmap(one)(a.qpos, b.qpos, a.qvel, b.qvel, a.act, b.act, a.sensordata, b.sensordata)
    out["ncon"] = jnp.abs(a.ncon - b.ncon)
    return out


def _field_result(field: str, err: np.ndarray, bound: np.ndarray, tol: float, healthy: np.ndarray,
                  objects: list[str], dt: float) -> FieldResult:
    """Reduces a (B, T, n) error array over healthy members against a (B, T) bound."""
    if err.shape[-1] == 0 or not healthy.any():
        return FieldResult(field, 0.0, tol, -1, -1, "", 0.0)
    e = np.where(healthy[:, None, None], err, 0.0)
    per_step = e.max(axis=2)  # (B, T)
    ratio = per_step / bound
    exceeded = ~(ratio <= 1.0)  # NaN exceeds
    if exceeded.any():
        step = int(exceeded.any(axis=0).argmax())
        member = int(exceeded[:, step].argmax())
    else:
        step, member = -1, int(ratio.max(axis=1).argmax())
    at = step if step >= 0 else int(ratio[member].argmax())
    comp = int(e[member, at].argmax())
    growth = metrics.error_growth(jnp.asarray(per_step.max(axis=0)), dt)
    envelope = float(np.where(healthy, bound[:, -1], 0).max()) if np.any(bound > tol) else 0.0
    return FieldResult(field, float(e.max()), tol, step, member, objects[comp] if objects else "",
                       float(growth.rate), envelope, float(np.nanmax(ratio)))


def _fraction_result(field: str, mismatched: np.ndarray, allowed: np.ndarray, tol: float,
                     healthy: np.ndarray) -> FieldResult:
    """A mismatch-fraction metric: (B, T) booleans -> fraction per member vs (B,) allowed fractions."""
    if not healthy.any():
        return FieldResult(field, 0.0, tol, -1, -1, "", 0.0)
    frac = np.where(healthy, mismatched.mean(axis=1), 0.0)
    ratio = frac / allowed
    member = int(ratio.argmax())
    step = int(mismatched[member].argmax()) if ratio[member] > 1 else -1
    return FieldResult(field, float(frac[member]), tol, step, member, "", 0.0,
                       float(allowed.max()) if np.any(allowed > tol) else 0.0, float(ratio.max()))


def _track(m: mujoco.MjModel, qpos: np.ndarray) -> np.ndarray:
    """(B, T, k) positions whose behaviour is summarised: the first free joint's
    translation if there is one, else every hinge/slide coordinate."""
    free = np.flatnonzero(m.jnt_type == mujoco.mjtJoint.mjJNT_FREE)
    if free.size:
        adr = m.jnt_qposadr[free[0]]
        return qpos[..., adr:adr + 3]
    scalar = [m.jnt_qposadr[j] for j in range(m.njnt)
              if int(m.jnt_type[j]) in (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))]
    return qpos[..., scalar]


def behaviour(m: mujoco.MjModel, traj_c: Trajectory, traj_mjx: Trajectory, dt: float,
              healthy: np.ndarray) -> dict[str, Any]:
    """Batch-mean behaviour statistics of both engines and their relative difference.

    Speeds (m/s or rad/s), distance and displacement of :func:`_track`; path
    efficiency = displacement / distance; with energy recorded, the relative
    energy drift (E_end - E_0) / |E_0|.
    """
    if not healthy.any() or _track(m, traj_c.qpos[:1]).shape[-1] == 0:
        return {}
    stats = jax.vmap(metrics.behaviour_stats, in_axes=(0, None))
    out = {}
    for engine, traj in (("c", traj_c), ("mjx", traj_mjx)):
        s = stats(jnp.asarray(_track(m, traj.qpos[healthy])), dt)
        out[engine] = {k: float(np.mean(v)) for k, v in s._asdict().items()}
        if traj.energy.shape[-1]:
            out[engine]["energy_drift"] = float(np.mean(jax.vmap(metrics.energy_drift)(jnp.asarray(traj.energy[healthy]))))
    out["relative_difference"] = {
        k: abs(out["mjx"][k] - out["c"][k]) / max(abs(out["c"][k]), 1e-12) for k in out["c"]}
    return out


def _bounds(series: dict[str, np.ndarray], tol: Tolerances, noise: NoiseFloor | None) -> dict[str, np.ndarray]:
    """Per field, the bound each member's error is held to: (B, T) for series, (B,) for fractions.

    Without a noise floor the bound is the fixed tolerance; with one it is
    max(tolerance, envelope) per member and step, and a contact-count mismatch
    may reach twice what C's own perturbed rerun shows.
    """
    B, T = series["ncon"].shape
    out = {}
    for key in ("qpos", "qvel", "act", "sensordata"):
        fixed = np.full((B, T), getattr(tol, key))
        out[key] = fixed if noise is None else np.maximum(fixed, noise.envelope(key))
    frac = np.full(B, tol.contact_mismatch)
    out["contacts"] = frac if noise is None else np.maximum(frac, np.minimum(1.0, 2 * noise.contact_fraction))
    out["rangefinder"] = np.full(B, tol.rangefinder_mismatch)
    return out


def _member_fails(series: dict[str, np.ndarray], bounds: dict[str, np.ndarray], nrays: int) -> np.ndarray:
    """(B,) True for members where some field exceeds its bound."""
    bad = np.zeros(series["qpos"].shape[0], bool)
    for key in ("qpos", "qvel", "act", "sensordata"):
        if series[key].shape[-1]:
            bad |= ~(series[key].max(axis=2) <= bounds[key]).all(axis=1)  # NaN counts as exceeding
    bad |= (series["ncon"] > 0).mean(axis=1) > bounds["contacts"]
    if nrays:
        bad |= (series["rangefinder"] / nrays).mean(axis=1) > bounds["rangefinder"]
    return bad


def judge(name: str, m: mujoco.MjModel, traj_c: Trajectory, traj_mjx: Trajectory,
          tol: Tolerances, threshold: float = 0.95, noise: NoiseFloor | None = None) -> ScenarioResult:
    """Compares MJX against C (the reference) and decides the scenario's status.

    A member passes when every field stays within its bound at every step: the
    fixed tolerance, or with a ``noise`` floor, max(tolerance, chaos envelope).
    The scenario passes when the fraction of healthy members that pass is at
    least ``threshold`` (the pass-rate criterion of cross-platform validation).
    """
    layout = metrics.qpos_layout(m)
    dt = float(m.opt.timestep)
    diverged = []
    for engine, traj in (("c", traj_c), ("mjx", traj_mjx)):
        for i in np.flatnonzero(traj.diverged_at >= 0):
            step = int(traj.diverged_at[i])
            diverged.append(dict(engine=engine, member=int(i), step=step, time=round((step + 1) * dt, 9)))
    healthy = (traj_c.diverged_at < 0) & (traj_mjx.diverged_at < 0)
    series = jax.tree.map(np.asarray, error_series(traj_mjx, traj_c, layout, jnp.asarray(rangefinder_mask(m))))
    objects = component_objects(m, layout)
    bounds = _bounds(series, tol, noise)
    fields = [_field_result(key, series[key], bounds[key], getattr(tol, key), healthy, objects[key], dt)
              for key in ("qpos", "qvel", "act", "sensordata")]
    fields.append(_fraction_result("contacts", series["ncon"] > 0, bounds["contacts"], tol.contact_mismatch, healthy))
    rf = rangefinder_mask(m)
    if rf.any():
        fields.append(_fraction_result("rangefinder", series["rangefinder"] / rf.sum(), bounds["rangefinder"],
                                       tol.rangefinder_mismatch, healthy))
    member_fails = _member_fails(series, bounds, int(rf.sum())) & healthy
    pass_rate = 1.0 - member_fails.sum() / max(int(healthy.sum()), 1)
    failed = [f for f in fields if not f.ok] if pass_rate < threshold else []
    first = None
    if failed:
        f = min(failed, key=lambda f: (f.first_step if f.first_step >= 0 else 1 << 30))
        step = max(f.first_step, 0)
        first = dict(field=f.field, step=step, time=float(traj_c.time[f.member, step]) if f.member >= 0 else None,
                     member=f.member, object=f.object, error=f.max_error, tolerance=f.tolerance)
    if diverged:
        d0 = min(diverged, key=lambda d: d["step"])
        engines = sorted({d["engine"] for d in diverged})
        status, kind = "error", "nan"
        message = (f"non-finite or unstable state in {len(diverged)} member(s) ({'/'.join(engines)}); "
                   f"first: {d0['engine']} member {d0['member']} at step {d0['step']} (t={d0['time']:g} s)")
    elif failed:
        status, kind = "fail", ""
        where = "leaves the envelope" if noise is not None else f"exceeds {first['tolerance']:.1e}"
        message = (f"{first['field']} of {first['object'] or 'member ' + str(first['member'])} {where} "
                   f"at step {first['step']} (t={first['time']:.4g} s), member {first['member']}; "
                   f"worst {first['error']:.3g}")
    else:
        worst = max((f for f in fields if f.field in ("qpos", "qvel")), key=lambda f: f.ratio)
        status, kind = "pass", ""
        message = f"worst {worst.field} {worst.max_error:.2g} (tol {worst.tolerance:.0e}"
        message += f", envelope {worst.envelope:.1e})" if worst.envelope else ")"
        if member_fails.any():
            message += f"; {int(member_fails.sum())}/{int(healthy.sum())} members out of tolerance, pass rate {pass_rate:.0%}"
    return ScenarioResult(
        name=name, status=status, message=message, error_kind=kind, fields=tuple(fields),
        first_divergence=first, diverged_members=tuple(diverged),
        behaviour=behaviour(m, traj_c, traj_mjx, dt, healthy), tolerances=tol.as_dict(),
        pass_rate=float(pass_rate), threshold=threshold,
        noise_rate=dict(noise.rate) if noise is not None else {})
