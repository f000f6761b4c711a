"""What the scenarios make MJX do: code coverage of ``mujoco/mjx/_src`` and parameter coverage.

A differential tester only catches bugs in what its scenarios exercise. Two measures:

* **Code** (:func:`code_coverage`): line and branch coverage of MJX's ``_src`` modules,
  recorded with ``coverage.py`` while ``mjx.put_model``, ``mjx.make_data`` and one
  ``mjx.step`` are traced for every scenario (MJX is Python traced once per model
  structure, so the trace visits every path the compiled rollout contains). Modules that
  cannot run in a CPU sweep are left out, each with its reason (:data:`EXCLUDED`).
* **Parameters** (:func:`parameter_coverage`): for every floating-point ``mjModel`` field
  MJX reads and every option, whether some member of some scenario holds a value other
  than MuJoCo's compiler default (the value an MJCF gets when it says nothing).
* **Interactions** (:mod:`mjxdiff.tools.interactions`): which pairs of the conditions MJX branches
  on (options, flags, element attributes, state regimes) some member holds together.
* **Regimes** (:func:`regime_coverage`): which state regimes that switch code paths
  (limits active on either side, friction loss sticking or sliding, contacts making and
  breaking, each friction cone, clamped activations, large rotations) some member
  reaches, read off MuJoCo C stepping the scenario's own inputs.

Both go into ``coverage.json`` (``python -m mjxdiff coverage --out DIR``).
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any, Iterable, Sequence

import mujoco
import numpy as np

from mjxdiff.input import joints
from mjxdiff.errors import one_line

__all__ = ["EXCLUDED", "REGIMES", "code_coverage", "parameter_coverage", "regime_coverage", "measure", "format_text"]

#: ``_src`` modules a CPU sweep cannot reach, with the reason.
EXCLUDED = {
    "render.py": "rendering: Warp backend only",
    "render_util.py": "rendering: Warp backend only",
    "bvh.py": "bounding volume hierarchies for rendering: Warp backend only",
    "inverse.py": "inverse dynamics: not part of mjx.step",
    "__init__.py": "imports only",
    "test_util.py": "MJX's own test and benchmark helpers: not simulation",
}

#: Statements no CPU sweep of a feature MJX supports can run: a regular expression (matched
#: against each source line; a match on a block's first line leaves out the whole block, on
#: any line of a statement the whole statement), with the reason.
UNREACHABLE = {
    r"\b(if|elif)\b.*\bimpl\s*==\s*(types\.)?Impl\.(WARP|CPP)\b":
        "another backend's branch (Warp: GPU kernels; cpp: MuJoCo C's own pointers, no MJX physics)",
    r"raise ValueError\(.*(requires|only supports) JAX backend":
        "guard against another backend's data",
    r"raise NotImplementedError\b":
        "raised for a feature MJX lacks (a sweep reports it as unsupported)",
    r"continue\s*# unsupported":
        "skips a sensor type MJX lacks",
    r"raise \w+Error\(\s*f?['\"](unrecognized|Unknown|Unsupported) ":
        "defensive: a type value MuJoCo's compiler never produces",
}
#: Functions left out whole, by a word in their name: the Warp and cpp backends' own code.
_OTHER_BACKENDS = ("warp", "_wp_", "_cpp")


def _src_dir() -> Path:
    import importlib.util

    # found without importing mujoco.mjx: the recording process must import it after starting
    spec = importlib.util.find_spec("mujoco.mjx")
    if spec is None or not spec.submodule_search_locations:
        raise RuntimeError("mujoco.mjx is not installed as a package: no MJX sources to measure")
    return Path(spec.submodule_search_locations[0], "_src")


def _trace_one(m: mujoco.MjModel) -> None:
    """``put_model``, ``make_data`` and one traced ``mjx.step`` of ``m`` (nothing compiled)."""
    import jax
    from mujoco import mjx

    mx = mjx.put_model(m)
    dx = mjx.make_data(mx)
    jax.make_jaxpr(mjx.step)(mx, dx)


def _record(folder: str | Path) -> None:
    """In a fresh process: records coverage from before ``mujoco.mjx`` is imported (so code MJX
    runs at import, its decorators and dataclass machinery, counts) while tracing the models
    ``folder`` holds (``names.json``, ``<i>.mjb``) and, where ``<i>.npz`` gives member 0's
    inputs, running the sweep's host-interface check (:mod:`mjxdiff.compare.transfer`) on them;
    writes ``cov.json`` and ``errors.json`` there."""
    import coverage

    src, folder = _src_dir(), Path(folder)
    cov = coverage.Coverage(data_file=None, branch=True, include=[str(src / "*.py")],
                            omit=[str(src / "*_test.py")] + [str(src / f) for f in EXCLUDED])
    for pattern in UNREACHABLE:
        cov.exclude(pattern)
    errors = {}
    cov.start()
    try:
        import mujoco.mjx  # recorded

        from mjxdiff.input import adjust
        from mjxdiff.compare import transfer

        for i, entry in enumerate(json.loads((folder / "names.json").read_text())):
            m = mujoco.MjModel.from_binary_path(str(folder / f"{i}.mjb"))
            try:
                _trace_one(m)
                if (folder / f"{i}.npz").exists():
                    # an MJB file does not keep the model's signature, which bind checks against
                    # the MjSpec: the same structure compiled again runs the same code
                    checked, _ = adjust.for_mjx(mujoco.MjSpec.from_file(entry["path"]).compile(), entry["path"])
                    with np.load(folder / f"{i}.npz") as z:
                        transfer.check_scenario_states(checked, z["qpos"], z["qvel"], z["act"], z["ctrl"], 0.0,
                                                       entry["path"], entry["precision"])
            except Exception as e:  # noqa: BLE001 - an unsupported model covers what it reached
                errors[entry["name"]] = one_line(e, 300)
    finally:
        cov.stop()
    cov.json_report(outfile=str(folder / "cov.json"))
    (folder / "errors.json").write_text(json.dumps(errors))
    # lines left out as unreachable that ran anyway (an excluded block's own if/elif test always
    # runs; its body must not): a pattern too wide would hide code the scenarios run
    ran_excluded = {}
    data = cov.get_data()
    for path in data.measured_files():
        excluded = set(cov.analysis2(path)[2]) & set(data.lines(path) or ())
        source = Path(path).read_text().splitlines()
        lines = [[n, source[n - 1].strip()] for n in sorted(excluded)
                 if not source[n - 1].lstrip().startswith(("if ", "elif "))]
        if lines:
            ran_excluded[Path(path).name] = lines
    (folder / "excluded_ran.json").write_text(json.dumps(ran_excluded))


_RECORDER = "import sys; from mjxdiff.tools.coverage import _record; _record(sys.argv[1])"


def code_coverage(models: Sequence[tuple[str, mujoco.MjModel]],
                  transfers: dict[str, tuple[Any, Any, Any, Any, str]] | None = None) -> dict[str, Any]:
    """Line and branch coverage of MJX's ``_src`` while each ``(name, model)`` is traced.

    Recorded in a fresh Python process (:func:`_record`), in this process's precision.
    ``transfers``: name -> ``(qpos, qvel, act, ctrl, model_path)`` of member 0, for the
    sweep's host-interface check (:func:`mjxdiff.compare.transfer.check_scenario_states`).

    Returns:
      ``{"totals": {...}, "modules": {file: {...}}, "functions_never_traced": [...],
      "excluded": EXCLUDED, "errors": {name: message}, "excluded_but_ran": {file: [[line, source]]}}``
      (lines :data:`UNREACHABLE` leaves out that ran all the same); percentages in [0, 100].
    """
    import jax

    transfers = transfers or {}
    # jax's Config class declares none of its flags
    precision = "float64" if jax.config.jax_enable_x64 else "float32"  # pyright: ignore[reportAttributeAccessIssue]
    with tempfile.TemporaryDirectory() as tmp:
        entries = []
        for i, (name, m) in enumerate(models):
            mujoco.mj_saveModel(m, str(Path(tmp) / f"{i}.mjb"), None)
            entries.append(dict(name=name, path=None, precision=precision))
            if name in transfers and Path(transfers[name][-1]).suffix.lower() == ".xml":
                qpos, qvel, act, ctrl, path = transfers[name]
                np.savez(Path(tmp) / f"{i}.npz", qpos=qpos, qvel=qvel, act=act, ctrl=ctrl)
                entries[-1]["path"] = str(path)
        (Path(tmp) / "names.json").write_text(json.dumps(entries))
        env = dict(os.environ, JAX_ENABLE_X64=str(bool(jax.config.jax_enable_x64)))  # pyright: ignore[reportAttributeAccessIssue]
        done = subprocess.run([sys.executable, "-c", _RECORDER, tmp], env=env, capture_output=True, text=True)
        if done.returncode:
            raise RuntimeError(f"recording MJX coverage failed: {done.stderr.strip()[-2000:]}")
        raw = json.loads(Path(tmp, "cov.json").read_text())
        errors = json.loads(Path(tmp, "errors.json").read_text())
        excluded_ran = json.loads(Path(tmp, "excluded_ran.json").read_text())
    # Function bodies only: module-level statements ran at import, before recording started.
    modules, never, warp = {}, [], []
    totals: dict[str, float] = dict.fromkeys(("lines", "lines_covered", "branches", "branches_covered"), 0)
    for path, data in sorted(raw["files"].items()):
        name = Path(path).name
        mod: dict[str, float] = dict.fromkeys(totals, 0)
        for fn, fd in data.get("functions", {}).items():
            if not fn:
                continue
            if any(w in fn.lower() for w in _OTHER_BACKENDS):  # cannot run in a JAX CPU sweep
                warp.append(f"{name}:{fn}")
                continue
            s = fd["summary"]
            got = dict(lines=s["num_statements"], lines_covered=s["covered_lines"],
                       branches=s.get("num_branches", 0), branches_covered=s.get("covered_branches", 0))
            for k, v in got.items():
                mod[k] += v
            if got["lines"] and not got["lines_covered"]:
                never.append(f"{name}:{fn}")
        mod["percent"] = round(100 * mod["lines_covered"] / max(mod["lines"], 1), 2)
        modules[name] = mod
        for k in totals:
            totals[k] += mod[k]
    totals["line_percent"] = round(100 * totals["lines_covered"] / max(totals["lines"], 1), 2)
    totals["branch_percent"] = round(100 * totals["branches_covered"] / max(totals["branches"], 1), 2)
    excluded = dict(EXCLUDED, **{f: "Warp or cpp backend only" for f in warp})
    return dict(totals=totals, modules=modules, functions_never_traced=sorted(never), excluded=excluded,
                errors=errors, excluded_but_ran=excluded_ran)


#: An MJCF with one element of each kind and no attributes: its values are MuJoCo's defaults.
_DEFAULTS_XML = """<mujoco>
  <worldbody>
    <body><joint name="a"/><geom name="a" size="0.1"/><site/></body>
    <body pos="1 0 0"><joint name="b"/><geom name="b" size="0.1"/></body>
  </worldbody>
  <contact><pair geom1="a" geom2="b"/></contact>
  <tendon><fixed><joint joint="a" coef="1"/></fixed></tendon>
  <equality><joint joint1="a" joint2="b"/></equality>
  <actuator><general joint="a"/></actuator>
  <sensor><jointpos joint="a"/></sensor>
</mujoco>"""

_ELEMENT_PREFIXES = ("body_", "jnt_", "dof_", "geom_", "site_", "pair_", "tendon_", "eq_", "actuator_", "sensor_")
#: Fields derived from geometry and masses by the compiler: never at a "default", not parameters.
_DERIVED = ("_pos", "_quat", "_ipos", "_iquat", "_mass", "_inertia", "_rbound", "_aabb", "_size", "invweight0",
            "_subtreemass", "_M0", "_length0", "_acc0", "_lengthrange", "_adr", "_num", "_id", "_user", "_rgba",
            "_frame", "_group", "_simple", "_sameframe", "_type")


def _parameter_fields(defaults: mujoco.MjModel) -> list[str]:
    """Floating-point per-element fields MJX's model holds, that an MJCF sets (not derived)."""
    from mujoco.mjx._src import types

    # MJX's Model is a dataclass at runtime that its type declarations do not show as one
    mjx_fields = {f.name for f in dataclasses.fields(types.Model)}  # pyright: ignore[reportArgumentType]
    out = []
    for name in sorted(mjx_fields):
        if not name.startswith(_ELEMENT_PREFIXES) or any(name.endswith(s) for s in _DERIVED):
            continue
        value = getattr(defaults, name, None)
        if isinstance(value, np.ndarray) and value.dtype.kind == "f" and value.size:
            out.append(name)
    return out


_OPTIONS = ("impratio", "tolerance", "ls_tolerance", "noslip_tolerance", "density", "viscosity", "wind",
            "magnetic", "o_margin", "o_solref", "o_solimp", "o_friction", "integrator", "cone", "jacobian",
            "solver", "iterations", "ls_iterations", "disableflags", "enableflags")


def parameter_coverage(models: Iterable[tuple[str, Sequence[mujoco.MjModel]]]) -> dict[str, Any]:
    """Which parameters some scenario moves away from MuJoCo's default.

    Args:
      models: (scenario name, its members' models).

    Returns:
      ``{"fields": {field: [scenario, ...]}, "options": {option: [...]}, "never": [...],
      "percent": ...}``: for each parameter, the scenarios in which some member's value
      (of some element) differs from the default; ``never`` lists those none moves.
    """
    defaults = mujoco.MjModel.from_xml_string(_DEFAULTS_XML)
    names = _parameter_fields(defaults)
    fields: dict[str, list[str]] = {n: [] for n in names}
    options: dict[str, list[str]] = {o: [] for o in _OPTIONS}
    for scenario, members in models:
        for name in names:
            default = np.asarray(getattr(defaults, name))[0]
            if any(np.asarray(getattr(mi, name)).size and np.any(np.asarray(getattr(mi, name)) != default)
                   for mi in members):
                fields[name].append(scenario)
        for o in _OPTIONS:
            default = np.asarray(getattr(defaults.opt, o))
            if any(np.any(np.asarray(getattr(mi.opt, o)) != default) for mi in members):
                options[o].append(scenario)
    never = sorted([n for n, v in fields.items() if not v] + [f"opt.{o}" for o, v in options.items() if not v])
    total = len(fields) + len(options)
    return dict(fields=fields, options=options, never=never,
                percent=round(100 * (total - len(never)) / max(total, 1), 2))


#: State regimes that switch MJX code paths, as read off MuJoCo C's data after a step.
REGIMES = ("lower limit active", "upper limit active", "ball limit active", "tendon limit active",
           "frictionloss sticking", "frictionloss sliding", "contact making", "contact breaking",
           "pyramidal cone contact", "elliptic cone contact", "activation clamped", "quaternion far from identity",
           "equality active")


def _regimes(m: mujoco.MjModel, d: mujoco.MjData, before: int) -> set[str]:
    """The :data:`REGIMES` present in ``d`` (after a step; ``before``: ncon before it)."""
    C, S = mujoco.mjtConstraint, mujoco.mjtConstraintState
    out = set()
    types, state = d.efc_type, d.efc_state
    for j, side in joints.active_limits(m, d):
        out.add(f"{side} limit active")
    if np.any(types == int(C.mjCNSTR_LIMIT_TENDON)):
        out.add("tendon limit active")
    friction = np.isin(types, [int(C.mjCNSTR_FRICTION_DOF), int(C.mjCNSTR_FRICTION_TENDON)])
    if np.any(friction & (state == int(S.mjCNSTRSTATE_QUADRATIC))):
        out.add("frictionloss sticking")
    if np.any(friction & np.isin(state, [int(S.mjCNSTRSTATE_LINEARNEG), int(S.mjCNSTRSTATE_LINEARPOS)])):
        out.add("frictionloss sliding")
    if d.ncon > before:
        out.add("contact making")
    if d.ncon < before:
        out.add("contact breaking")
    if np.any(types == int(C.mjCNSTR_CONTACT_PYRAMIDAL)):
        out.add("pyramidal cone contact")
    if np.any(types == int(C.mjCNSTR_CONTACT_ELLIPTIC)):
        out.add("elliptic cone contact")
    if np.any(types == int(C.mjCNSTR_EQUALITY)):
        out.add("equality active")
    for a in np.flatnonzero(m.actuator_actlimited):
        adr = m.actuator_actadr[a]
        if adr >= 0 and (d.act[adr] <= m.actuator_actrange[a, 0] or d.act[adr] >= m.actuator_actrange[a, 1]):
            out.add("activation clamped")
    for p in joints.parts(m):
        if p.kind == "rotation" and 2 * np.arccos(min(1.0, abs(d.qpos[p.qpos_adr]))) > 1.0:  # turned > 1 rad
            out.add("quaternion far from identity")
    return out


def regime_coverage(runs: Iterable[tuple[str, Any]]) -> dict[str, Any]:
    """Which :data:`REGIMES` some member of some scenario reaches, stepping MuJoCo C.

    Args:
      runs: (scenario name, its :class:`~mjxdiff.input.inputs.BatchedInputs`).

    Returns:
      ``{"regimes": {regime: [scenario, ...]}, "never": [...]}``.
    """
    reached: dict[str, list[str]] = {r: [] for r in REGIMES}
    for name, inputs in runs:
        seen: set[str] = set()
        for i, mi in enumerate(inputs.models):
            d = mujoco.MjData(mi)
            d.qpos[:], d.qvel[:] = inputs.qpos[i], inputs.qvel[i]
            if mi.na:
                d.act[:] = inputs.act[i]
            mujoco.mj_forward(mi, d)
            for t in range(inputs.steps):
                before = d.ncon
                d.ctrl[:] = inputs.ctrl[i, t]
                mujoco.mj_step(mi, d)
                seen |= _regimes(mi, d, before)
        for r in sorted(seen):
            reached[r].append(name)
    return dict(regimes=reached, never=[r for r, v in reached.items() if not v])


def measure(scenarios, seed: int = 0, batch: int = 4, code: bool = True) -> dict[str, Any]:
    """Both measures over ``scenarios`` (their randomized members, ``batch`` of each)."""
    from mjxdiff.input import adjust
    from mjxdiff.input.inputs import make_inputs
    from mjxdiff.input.scenario import ScenarioError, load_model

    members, first, runs, skipped, transfers = [], [], [], {}, {}
    for s in scenarios:
        try:
            m = load_model(s)
            m, _ = adjust.for_mjx(m, s.model_path)
            inputs = make_inputs(s, m, seed, batch)
        except ScenarioError as e:
            skipped[s.name] = str(e)
            continue
        members.append((s.name, inputs.models))
        first.append((s.name, inputs.models[0]))
        transfers[s.name] = (inputs.qpos[0], inputs.qvel[0], inputs.act[0], inputs.ctrl[0], s.model_path)
        runs.append((s.name, inputs))
    from mjxdiff.tools import interactions

    pairs: dict[tuple, list[str]] = {}
    for name, inputs in runs:
        for p in interactions.member_pairs(inputs):
            pairs.setdefault(p, []).append(name)
    out = dict(scenarios=[n for n, _ in members], skipped=skipped, parameters=parameter_coverage(members),
               regimes=regime_coverage(runs), interactions=interactions.pairwise(pairs))
    if code:
        out["code"] = code_coverage(first, transfers)
    return out


def format_text(doc: dict[str, Any]) -> str:
    lines = []
    if "code" in doc:
        t = doc["code"]["totals"]
        lines.append(f"MJX code traced: {t['line_percent']:.1f}% of {t['lines']} lines, "
                     f"{t['branch_percent']:.1f}% of {t['branches']} branches "
                     f"({len(doc['scenarios'])} scenarios)")
        for name, mod in doc["code"]["modules"].items():
            lines.append(f"  {name:<24} {mod['percent']:6.1f}%  ({mod['lines_covered']}/{mod['lines']} lines, "
                         f"{mod['branches_covered']}/{mod['branches']} branches)")
        never = doc["code"]["functions_never_traced"]
        lines.append(f"  functions never traced ({len(never)}): {', '.join(never)}")
        left = doc["code"]["excluded"]
        lines.append(f"  left out ({len(left)}): " + "; ".join(f"{k} ({v})" for k, v in EXCLUDED.items())
                     + f"; {len(left) - len(EXCLUDED)} Warp- or cpp-backend functions")
        lines.append("  statements left out by pattern (mjxdiff.tools.coverage.UNREACHABLE): "
                     + "; ".join(UNREACHABLE.values()))
        for name, err in doc["code"]["errors"].items():
            lines.append(f"  {name}: traced until {err}")
    p = doc["parameters"]
    lines.append(f"parameters moved from their default: {p['percent']:.1f}% "
                 f"({len(p['fields']) + len(p['options']) - len(p['never'])} of "
                 f"{len(p['fields']) + len(p['options'])})")
    lines.append(f"  never moved ({len(p['never'])}): {', '.join(p['never'])}")
    r = doc["regimes"]
    lines.append(f"state regimes reached: {len(REGIMES) - len(r['never'])} of {len(REGIMES)}"
                 + (f"; never: {', '.join(r['never'])}" if r["never"] else ""))
    if "interactions" in doc:
        from mjxdiff.tools import interactions

        lines.append(interactions.format_text(doc["interactions"]))
    return "\n".join(lines)
