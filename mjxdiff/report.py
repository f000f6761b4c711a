"""Verdicts -> what people and machines read: text lines and ``report.json``.

``report.json`` is versioned by :data:`SCHEMA_VERSION`; bump it when a key
changes meaning or disappears (adding keys is compatible).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import platform
from importlib import metadata
from pathlib import Path
from typing import Any, Sequence

from mjxdiff.verdict import ScenarioResult

__all__ = ["SCHEMA_VERSION", "summary", "to_json", "format_text", "write_report", "versions"]

SCHEMA_VERSION = 1
_SYMBOL = {"pass": "PASS", "fail": "FAIL", "unsupported": "UNSUP", "error": "ERROR"}


def versions() -> dict[str, str]:
    """Versions of everything that decides the numbers."""
    out = {"python": platform.python_version()}
    for dist in ("mjxdiff", "jax", "jaxlib", "mujoco", "mujoco-mjx", "numpy"):
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[dist] = "not installed"
    return out


def machine() -> dict[str, Any]:
    """What the numbers were measured on: cores, and the host devices MJX's batch is split over."""
    from mjxdiff.engines import device_count

    return dict(cpus=os.cpu_count(), platform=platform.machine(), jax_cpu_devices=device_count())


def summary(results: Sequence[ScenarioResult], threshold: float) -> dict[str, Any]:
    """Counts per status and the scenario pass rate (unsupported scenarios excluded).

    ``consistent`` is True when no scenario failed or errored: the pass rate
    over the scenarios that ran is then 1.
    """
    counts = {s: sum(r.status == s for r in results) for s in ("pass", "fail", "unsupported", "error")}
    ran = len(results) - counts["unsupported"]
    rate = counts["pass"] / ran if ran else 1.0
    compiles = sum(r.info.get("mjx_compiles", 0) for r in results)
    loaded = sum(r.info.get("mjx_loaded", 0) for r in results)
    compile_s = sum(r.info.get("seconds", {}).get("compile", 0.0) for r in results)
    return dict(total=len(results), **counts, pass_rate=rate, member_pass_threshold=threshold,
                consistent=counts["fail"] == 0 and counts["error"] == 0, mjx_compiles=compiles,
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
    """One verdict as a JSON-ready dict, fields keyed by name."""
    d = dataclasses.asdict(r)
    d["fields"] = {f.pop("field"): f for f in d["fields"]}
    return _clean(d)


def to_json(results: Sequence[ScenarioResult], config: dict[str, Any]) -> dict[str, Any]:
    """The whole report as a JSON-ready dict."""
    return _clean(dict(
        schema_version=SCHEMA_VERSION,
        versions=versions(),
        machine=machine(),
        config=config,
        summary=summary(results, config.get("threshold", 0.95)),
        scenarios=[result_dict(r) for r in results],
    ))


def write_report(out_dir: str | Path, report: dict[str, Any], name: str = "report.json") -> Path:
    """Writes ``report`` as JSON to ``out_dir/name``, creating the directory; returns the path."""
    path = Path(out_dir)
    path.mkdir(parents=True, exist_ok=True)
    path = path / name
    path.write_text(json.dumps(report, indent=2, sort_keys=False) + "\n")
    return path


def format_line(r: ScenarioResult) -> str:
    """One line per scenario: status, name, and what happened."""
    return f"{_SYMBOL[r.status]:<6} {r.name:<28} {r.message}"


def format_text(results: Sequence[ScenarioResult], threshold: float, seconds: float | None = None) -> str:
    s = summary(results, threshold)
    tail = f" in {seconds:.0f} s" if seconds is not None else ""
    verdict = "consistent" if s["consistent"] else "DIVERGENT"
    lines = [format_line(r) for r in results]
    lines.append(f"{s['total']} scenarios{tail}: {s['pass']} pass, {s['fail']} fail, "
                 f"{s['unsupported']} unsupported, {s['error']} error; "
                 f"pass rate {s['pass_rate']:.0%} -> {verdict}")
    return "\n".join(lines)
