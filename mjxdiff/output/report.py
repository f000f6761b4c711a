"""Verdicts -> what people and machines read: text lines and ``report.json``.

``report.json`` is versioned by :data:`SCHEMA_VERSION`; bump it when a key
changes meaning or disappears (adding keys is compatible).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import platform
import re
from importlib import metadata
from pathlib import Path
from typing import Any, Sequence

from mjxdiff.errors import one_line
from mjxdiff.files import atomic_write
from mjxdiff.compare.result import TRUNCATION, WEAK_BOUND, FieldResult, ScenarioResult

__all__ = ["ENVELOPE", "KINDS", "SCHEMA_VERSION", "code", "envelope", "summary", "to_json", "format_text",
           "validate", "write_report", "write_pending", "versions", "safe_filename", "path_under"]

SCHEMA_VERSION = 3  # 3: every output in one envelope (kind, seed, code, machine); 2: summary.input_error, verdict, code

#: What every JSON output begins with (:func:`envelope`), in this order.
ENVELOPE = ("kind", "schema_version", "versions", "code", "machine", "config", "seed")
#: The kinds of JSON output, by the file they are written to.
KINDS = {"sweep": "report.json", "grad": "grad-report.json", "policy": "policy-report.json",
         "policy-reproducer": "policy-reproducer.json", "bench": "bench.json", "coverage": "coverage.json",
         "fuzz": "fuzz-report.json", "reproducer": "reproducers/NAME-memberI.json",
         "grad-reproducer": "reproducers/NAME-grad-stateI.json", "versions": "versions.json"}
_SYMBOL = {"pass": "PASS", "fail": "FAIL", "unsupported": "UNSUP", "error": "ERROR"}


def versions() -> dict[str, str]:
    """Versions of everything that decides the numbers."""
    out = {"python": platform.python_version()}
    # mujoco-core: MuJoCo C itself from 4.0 on (`mujoco` pins it, a user can replace it alone)
    for dist in ("mjxdiff", "jax", "jaxlib", "mujoco", "mujoco-core", "mujoco-mjx", "numpy"):
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[dist] = "not installed"
    return out


def machine() -> dict[str, Any]:
    """What the numbers were measured on: cores, and the host devices MJX's batch is split over."""
    from mjxdiff.engine.xla import device_count

    return dict(cpus=os.cpu_count(), platform=platform.machine(), jax_cpu_devices=device_count())


def summary(results: Sequence[ScenarioResult], threshold: float) -> dict[str, Any]:
    """Counts per status and the scenario pass rate.

    ``error`` counts engine crashes and scenarios where MuJoCo C itself blew up;
    ``input_error`` counts scenarios that could not run (a missing file, an invalid
    MJCF): neither says anything about MJX. ``pass_rate`` is over the scenarios
    that ran (unsupported and input errors aside). ``consistent`` is True when every
    scenario that ran passed and none had an input error; ``verdict`` says in one
    word what was found: ``consistent``, ``divergent`` (some fail), ``error`` or
    ``input-error``. ``adjusted`` counts scenarios whose model mjxdiff changed
    so that MJX could run it (:mod:`mjxdiff.input.adjust`), whatever their status.
    ``weak`` counts passes whose bound was wider than :data:`~mjxdiff.compare.verdict.WEAK_BOUND` of
    a field's scale (:attr:`~mjxdiff.compare.verdict.ScenarioResult.weak`): they could not have seen
    a bug of that size. ``truncation`` counts failures whose cause is the model's own solver
    settings (:data:`~mjxdiff.compare.verdict.TRUNCATION`: apart as configured, together when converged).
    ``limited`` counts errors of scenarios stopped by a limit (:data:`LIMIT_KINDS`).
    """
    counts = {s: sum(r.status == s for r in results) for s in ("pass", "fail", "unsupported")}
    counts["weak"] = sum(r.status == "pass" and bool(r.weak) for r in results)
    counts["truncation"] = sum(r.status == "fail" and (r.diagnosis.get("cause") or {}).get("cause") == TRUNCATION
                               for r in results)
    counts["error"] = sum(r.status == "error" and r.error_kind != "input" for r in results)
    counts["input_error"] = sum(r.status == "error" and r.error_kind == "input" for r in results)
    counts["limited"] = sum(r.status == "error" and r.error_kind in LIMIT_KINDS for r in results)
    counts["adjusted"] = sum(bool(r.info.get("adjusted")) for r in results)
    ran = len(results) - counts["unsupported"] - counts["input_error"]
    rate = counts["pass"] / ran if ran else 1.0
    compiles = sum(r.info.get("mjx_compiles", 0) for r in results)
    loaded = sum(r.info.get("mjx_loaded", 0) for r in results)
    compile_s = sum(r.info.get("seconds", {}).get("compile", 0.0) for r in results)
    verdict = ("divergent" if counts["fail"] else "error" if counts["error"] else
               "input-error" if counts["input_error"] else "consistent")
    return dict(total=len(results), **counts, pass_rate=rate, member_pass_threshold=threshold,
                consistent=verdict == "consistent", verdict=verdict, mjx_compiles=compiles,
                mjx_loaded=loaded, compile_seconds=compile_s)


def _clean(x: Any) -> Any:
    """JSON-safe: non-finite floats become strings ("nan", "inf")."""
    if isinstance(x, float) and not math.isfinite(x):
        return str(x)
    if isinstance(x, dict):
        return {str(k): _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    return x


def result_dict(r: ScenarioResult) -> dict[str, Any]:
    """One verdict as a JSON-ready dict, fields keyed by name (its unwritten files left out)."""
    d = dataclasses.asdict(dataclasses.replace(r, pending=()))
    del d["pending"]
    d["fields"] = {f.pop("field"): f for f in d["fields"]}
    return _clean(d)


_FLOATS = ("max_error", "tolerance", "growth_rate", "envelope", "ratio", "scale")


def result_from_dict(d: dict[str, Any]) -> ScenarioResult:
    """The verdict :func:`result_dict` wrote (a journal's record, a merged shard's), with its
    fields' numbers floats again ("inf" and "nan" included): ``result_dict(result_from_dict(d))
    == d`` (keys a report adds, such as ``known``, aside)."""
    fields = tuple(FieldResult(field=name, **{**f, **{k: float(f[k]) for k in _FLOATS if k in f},
                                              "series": tuple((int(k), float(e), float(b)) for k, e, b in f["series"]),
                                              "bound_scale": tuple(float(x) for x in f["bound_scale"])})
                   for name, f in d["fields"].items())
    own = {f.name for f in dataclasses.fields(ScenarioResult)}  # a report's labels ("known") aside
    return ScenarioResult(**{**{k: v for k, v in d.items() if k in own}, "fields": fields,
                             "diverged_members": tuple(d["diverged_members"]), "weak": tuple(d["weak"])})


def write_pending(r: ScenarioResult) -> ScenarioResult:
    """Writes the files a verdict carries (:attr:`ScenarioResult.pending`); returns the verdict
    with each file's path under its key in ``info``. A file that cannot be written is a part of
    the message (``<key> not saved: why``) and a None path: the verdict stands without it."""
    info, message = dict(r.info), r.message
    for key, path, doc in r.pending:
        try:
            info[key] = str(atomic_write(path, json.dumps(doc, indent=1) + "\n"))
        except Exception as e:  # noqa: BLE001 - the verdict stands without its file
            info[key] = None
            message = f"{message}; {key} not saved: {one_line(e)}"
    return dataclasses.replace(r, info=info, message=message, pending=())


def code() -> dict[str, str]:
    """What was tested, by content rather than version string: SHA-256 digests of the MJX code
    loaded in this process and of everything a compiled rollout depends on
    (:func:`mjxdiff.engine.digest.code_digest`, :func:`~mjxdiff.engine.digest.rollout_digest`)."""
    from mjxdiff.engine import digest

    return dict(mjx=digest.code_digest(), rollout=digest.rollout_digest())


def format_cache(cache: dict[str, Any]) -> str:
    """One line on what the cache of traced rollouts did in a run (:func:`mjxdiff.engine.export_cache.events_since`):
    how many were loaded instead of traced and from where (``where``: by whom, when not this
    process), and any trace it could not save or key it did not trust."""
    if cache.get("dir") is None:
        return f"cache: off ({cache.get('traced', 0)} MJX rollouts traced)"
    line = f"cache: {cache['loaded']} MJX rollouts loaded from {cache['dir']}, {cache['traced']} traced"
    if cache.get("where"):
        line += f" (by {cache['where']})"
    if cache["unsaved"]:
        line += f"; {len(cache['unsaved'])} not saved ({cache['unsaved'][0]})"
    if cache["ambiguous"]:
        line += (f"; {len(cache['ambiguous'])} ambiguous keys traced afresh (run 'mjxdiff cache check'),"
                 f" {cache['removed']} untrusted artifacts removed")
    return line


#: A scenario's phases, in the order it runs them: ``info['seconds']`` holds their wall seconds,
#: which do not overlap (compiling is taken out of every other phase and counted in ``compile``),
#: so they sum to the scenario's time. ``mjx`` and ``c`` are the rollouts' stepping and nothing
#: else (the twin's and the solver floor's reruns count in their own phases).
PHASES = {"inputs": "inputs", "compile": "compile", "mjx": "MJX stepping", "c": "C stepping",
          "verdict": "verdict", "solver_floor": "solver floor", "diagnosis": "drill-down and ablations",
          "onestep": "one-step check", "twin": "converged twin", "transfer": "host interface"}
#: The parts of ``compile`` (``info['compile_seconds']``): MJX's model and initial state put on
#: the devices with the cache key digested, JAX's trace and lowering, XLA's own compile, and
#: loads from the caches (an artifact instead of a trace, XLA's persistent cache instead of a compile).
COMPILE_PARTS = {"prepare": "model to device and key", "trace": "trace", "lower": "lowering",
                 "xla": "XLA compile", "cache_load": "cache load"}
#: ``info['cpu_seconds']``: the process's CPU seconds over a phase's windows, other threads' work
#: and compiling included; the engines and the verdict run at once, so they share one window.
CPU_WINDOWS = ("inputs", "stepping", "solver_floor", "diagnosis", "onestep", "twin", "transfer")


def timing(scenarios: Sequence[dict[str, Any]], process: dict[str, dict[str, float]]) -> dict[str, Any]:
    """Where a sweep's time went: ``process`` (wall and CPU seconds of the process-level phases:
    ``startup`` (interpreter, imports), ``prepare`` (options, scenarios, keys), ``sweep`` (the
    scenarios, a guard's child process included), ``finish``), and summed over ``scenarios``
    (report.json's): ``phases`` (wall seconds, :data:`PHASES`), ``compile`` (:data:`COMPILE_PARTS`),
    ``cpu`` (:data:`CPU_WINDOWS`); ``stepping`` = the summed ``mjx`` + ``c``, and ``ratio`` = the
    process's wall seconds / ``stepping`` (1.0: the verdict cost what stepping the engines cost).
    Scenarios that compiled ahead overlap: their summed phases may exceed the sweep's wall time."""
    def total(key: str, names) -> dict[str, float]:
        return {n: round(sum(float(((sc.get("info") or {}).get(key) or {}).get(n) or 0.0) for sc in scenarios), 3)
                for n in names}

    phases = total("seconds", PHASES)
    wall = sum(p.get("wall", 0.0) for p in process.values())
    cpu = sum(p.get("cpu", 0.0) for p in process.values())
    stepping = phases["mjx"] + phases["c"]
    return dict(process={k: {x: round(y, 3) for x, y in v.items()} for k, v in process.items()},
                wall=round(wall, 3), cpu=round(cpu, 3), phases=phases,
                compile=total("compile_seconds", COMPILE_PARTS), cpu_phases=total("cpu_seconds", CPU_WINDOWS),
                stepping=round(stepping, 3), ratio=round(wall / stepping, 2) if stepping > 0 else None)


def format_timing(t: dict[str, Any]) -> str:
    """One line of :func:`timing`: the process's wall and CPU seconds, start-up, the scenarios'
    phases summed (compile's parts in brackets; phases under 0.05 s left out, but never the
    engines' stepping) and the ratio of wall time to the engines' own stepping."""
    def part(names: dict[str, str], values: dict[str, float]) -> str:
        return ", ".join(f"{label} {values[k]:.3g}" for k, label in names.items()
                         if values.get(k, 0.0) >= 0.05 or k in ("mjx", "c"))

    compile_ = part(COMPILE_PARTS, t["compile"])
    phases = part(PHASES, t["phases"]).replace(f"compile {t['phases']['compile']:.3g}",
                                               f"compile {t['phases']['compile']:.3g} [{compile_}]" if compile_
                                               else f"compile {t['phases']['compile']:.3g}", 1)
    start = t["process"].get("startup", {})
    line = (f"time: {t['wall']:.0f} s wall, {t['cpu']:.0f} CPU-s; start-up {start.get('wall', 0.0):.1f} s; "
            f"scenarios (s, summed): {phases or 'none ran'}")
    if t.get("ratio") is not None:
        line += f"; wall / engines' stepping {t['ratio']:.2g}x"
    return line


def envelope(kind: str, config: dict[str, Any], **body: Any) -> dict[str, Any]:
    """A JSON output of ``kind`` (:data:`KINDS`) in the one shape every output has: ``kind``,
    ``schema_version``, ``versions`` (:func:`versions`), ``code`` (digests of the MJX code
    tested, :func:`code`), ``machine``, ``config`` (what the run was asked), ``seed`` (the
    config's, None where it has none), then ``body``; JSON-ready (non-finite floats as strings)."""
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {sorted(KINDS)}, not {kind!r}")
    if set(body) & set(ENVELOPE):
        raise ValueError(f"the body of a {kind} output repeats envelope keys: {sorted(set(body) & set(ENVELOPE))}")
    return _clean(dict(kind=kind, schema_version=SCHEMA_VERSION, versions=versions(), code=code(), machine=machine(),
                       config=config, seed=config.get("seed"), **body))


def validate(doc: Any, kind: str | None = None) -> list[str]:
    """What is wrong with ``doc`` as a JSON output (of ``kind``, when given): the
    :data:`ENVELOPE` keys first, in order; a known kind; this :data:`SCHEMA_VERSION`; the
    versions of MuJoCo, MJX and JAX; the MJX code digest (64 hex digits); a config object; an
    integer seed or null. Empty when it is a valid output.

    >>> validate([])
    ['not an object: list']
    >>> validate({"kind": "sweep"})[1]
    'schema_version None, not 3'
    """
    if not isinstance(doc, dict):
        return [f"not an object: {type(doc).__name__}"]
    problems = []
    if list(doc)[:len(ENVELOPE)] != list(ENVELOPE):
        problems.append(f"begins with {list(doc)[:len(ENVELOPE)]}, not {list(ENVELOPE)}")
    if doc.get("kind") not in KINDS or (kind is not None and doc.get("kind") != kind):
        problems.append(f"kind {doc.get('kind')!r}, not {kind or sorted(KINDS)!r}")
    if doc.get("schema_version") != SCHEMA_VERSION:
        problems.append(f"schema_version {doc.get('schema_version')!r}, not {SCHEMA_VERSION}")
    if not all((doc.get("versions") or {}).get(k) for k in ("mujoco", "mujoco-mjx", "jax")):
        problems.append(f"versions {doc.get('versions')!r} lack mujoco, mujoco-mjx or jax")
    if not re.fullmatch(r"[0-9a-f]{64}", str((doc.get("code") or {}).get("mjx"))):
        problems.append(f"code.mjx {(doc.get('code') or {}).get('mjx')!r} is no SHA-256 digest")
    if not isinstance(doc.get("config"), dict):
        problems.append("config is not an object")
    if not (doc.get("seed") is None or isinstance(doc.get("seed"), int)):
        problems.append(f"seed {doc.get('seed')!r} is neither an integer nor null")
    return problems


def to_json(results: Sequence[ScenarioResult], config: dict[str, Any]) -> dict[str, Any]:
    """The whole sweep report as a JSON-ready dict (:func:`envelope` of kind ``sweep``)."""
    return envelope("sweep", config, summary=summary(results, config.get("threshold", 0.95)),
                    scenarios=[result_dict(r) for r in results])


#: Longest file name :func:`safe_filename` returns (well under the usual 255-byte limit,
#: leaving room for suffixes such as ``-member12.json``).
MAX_FILENAME = 100
_UNSAFE = re.compile(r"[^A-Za-z0-9._-]")


def safe_filename(name: str, max_len: int = MAX_FILENAME) -> str:
    """``name`` as one plain file name: no directories, no escape from the directory it goes in.

    Characters outside ``[A-Za-z0-9._-]`` become ``_`` (so ``/``, ``\\``, spaces and
    non-ASCII letters do), leading dots are dropped (no hidden files, no ``.``/``..``),
    an empty result becomes ``_``, and a name longer than ``max_len`` is cut and
    ended with a short hash of the whole name, so long names stay distinct.

    >>> safe_filename("../my robot/ü.xml")
    '_my_robot__.xml'
    >>> len(safe_filename("x" * 300))
    100
    """
    safe = _UNSAFE.sub("_", str(name)).lstrip(".") or "_"
    if len(safe) > max_len:
        digest = hashlib.sha256(str(name).encode("utf-8", "surrogatepass")).hexdigest()[:8]
        safe = f"{safe[:max(max_len - 9, 1)]}-{digest}"
    return safe


def path_under(directory: str | Path, name: str | Path) -> Path:
    """``directory / name``, or ValueError if that path, resolved, is not inside ``directory`` resolved.

    Symbolic links are followed on both sides, so a link inside ``directory``
    that points elsewhere is refused too. Nothing is created.
    """
    base = Path(directory)
    path = base / name
    root, target = base.resolve(), path.resolve()
    if target == root or root not in target.parents:
        raise ValueError(f"refusing to write {str(name)!r}: {target} is not inside {root}")
    return path


def write_report(out_dir: str | Path, report: dict[str, Any], name: str = "report.json") -> Path:
    """Writes ``report`` as JSON to ``out_dir/name``, creating the directory; returns the path.

    ``name`` is made a plain file name first (:func:`safe_filename`), so the file
    always lands directly in ``out_dir``.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    return atomic_write(path_under(out, safe_filename(name)), json.dumps(report, indent=2, sort_keys=False) + "\n")


#: ``error_kind`` of a scenario stopped by a limit (:mod:`mjxdiff.runner.guard`, :func:`mjxdiff.input.cost.plan`).
LIMIT_KINDS = ("budget", "memory")


def format_line(r: ScenarioResult) -> str:
    """One line per scenario: status, name, and what happened; a second, indented line with the
    sharp checks (:func:`format_checks`) when they ran."""
    symbol = "INPUT" if r.status == "error" and r.error_kind == "input" else _SYMBOL[r.status]
    adjusted = f" [adjusted: {'; '.join(r.info['adjusted'])}]" if r.info.get("adjusted") else ""
    checks = format_checks(r.info)
    return f"{symbol:<6} {r.name:<28} {r.message}{adjusted}" + (f"\n{'':<6} {'':<28} {checks}" if checks else "")


def format_checks(info: dict[str, Any]) -> str:
    """The sharp checks of a scenario (its ``info``) in one line: the one-step check
    (``info['onestep']``, :func:`mjxdiff.compare.onestep.check`), the converged twin (``info['twin']``)
    and, where it could not run, the host-interface check (``info['transfer']``),
    each with its worst ratio to its bound and how large that bound is against the field's scale;
    '' when neither ran."""
    parts = []
    one, twin = info.get("onestep"), info.get("twin")
    if one and one.get("status") in ("pass", "fail"):
        scale = (one.get("bound_scale") or {}).get(one.get("field"))
        text = (f"one-step {one['status']}: {one.get('field')} {_num(one.get('ratio')):.2g} of its bound "
                f"({one.get('pairs')} states of C, {_SETTINGS.get(one.get('settings'), 'converged solver')}"
                + (f"; bound {scale[1]:.1g} of the field's scale" if scale else "") + ")")
        solver = one.get("solver") or {}
        if not solver.get("converged", True):
            text += (f"; your solver settings do not converge (C's truncated step {_num(solver.get('ratio')):.2g}x "
                     f"the bound in {solver.get('field')})")
        parts.append(text)
    elif one:
        parts.append(f"one-step {one.get('status')}: {one.get('message', '')}")
    if twin and twin.get("worst"):
        w, scale = twin["worst"], (twin.get("fields") or {}).get(twin["worst"]["field"], {}).get("bound_scale")
        parts.append(f"converged twin {twin['status']}: {w['field']} {_num(w['ratio']):.2g} of its bound"
                     + (f" (bound {scale[1]:.1g} of the field's scale)" if scale else "")
                     + (f", weak: {', '.join(twin['weak'])}" if twin.get("weak") else ""))
    elif twin and twin.get("status") == "skipped":
        parts.append(twin.get("message", "converged twin not run"))
    elif twin:
        parts.append(f"converged twin {twin.get('status')}: {twin.get('message', '')}")
    host = info.get("transfer")
    if host and host.get("error"):
        parts.append(f"host-interface check did not run: {host['error']}")
    return ("checks: " + "; ".join(parts)) if parts else ""


#: How the one-step check's solver ran (``info['onestep']['settings']``), as the checks line says it.
_SETTINGS = {"converged": "converged solver", "as configured (converged)": "solver as configured, which converges"}


def _num(x: Any) -> float:
    try:
        return float(x)
    except (TypeError, ValueError):
        return float("nan")


def format_text(results: Sequence[ScenarioResult], threshold: float, seconds: float | None = None) -> str:
    s = summary(results, threshold)
    tail = f" in {seconds:.0f} s" if seconds is not None else ""
    verdict = {"consistent": "consistent",
               "divergent": "DIVERGENT",
               "error": "ERROR (an engine crashed or MuJoCo C itself blew up; see above)",
               "input-error": "INPUT ERROR (fix the input above; nothing diverged in the rest)"}[s["verdict"]]
    if s["verdict"] == "error" and s["limited"] == s["error"]:
        verdict = (f"ERROR ({s['limited']} stopped by a limit before a verdict: --budget, --max-memory; "
                   "each line says what to do)")
    lines = [format_line(r) for r in results]
    inputs = f", {s['input_error']} input error" if s["input_error"] else ""
    inputs += f" ({s['adjusted']} adjusted for MJX)" if s["adjusted"] else ""
    weak = f" ({s['weak']} weak: bound over {WEAK_BOUND:.0%} of the field's scale)" if s["weak"] else ""
    truncation = f" ({s['truncation']} solver truncation)" if s["truncation"] else ""
    lines.append(f"{s['total']} scenarios{tail}: {s['pass']} pass{weak}, {s['fail']} fail{truncation}, "
                 f"{s['unsupported']} unsupported, {s['error']} error{inputs}; "
                 + (f"pass rate {s['pass_rate']:.0%}" if s["pass"] + s["fail"] + s["error"] else "nothing judged")
                 + f" -> {verdict}")
    return "\n".join(lines)
