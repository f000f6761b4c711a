"""Baselines: what changed since a run you trusted?

:func:`load` reads a baseline (a ``report.json``, a directory holding one, or a run id of
the history); :func:`compare` classifies every scenario of a new report against it
(:data:`CLASSES`).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from mjxdiff.errors import one_line

__all__ = ["CLASSES", "GROWTH", "BaselineError", "load", "compare", "format_text", "new_failures"]

#: The classes, in the order the text report lists them.
CLASSES = ("new failure", "fixed", "error grew", "error shrank", "same", "new scenario", "not in this run")
#: A passing field whose max error changes by this factor or more, on a calm scenario (no
#: chaos envelope in either run), is ``error grew`` / ``error shrank``; changes where both
#: errors are below ``RELEVANT`` x the tolerance (rounding) are ``same``.
GROWTH = 10.0
RELEVANT = 1e-6


class BaselineError(ValueError):
    """A baseline that cannot be read; the message is one line that says what to give."""


def load(ref: str, history_dir: str | Path | None = None) -> dict[str, Any]:
    """A baseline report from ``ref``: a ``report.json``, a directory with one, or a run id
    (or its unique prefix) of the history in ``history_dir``. Run ids give back a report of
    statuses and per-field errors, what :func:`compare` reads."""
    path = Path(ref)
    if path.is_dir():
        path = path / "report.json"
    if path.is_file():
        try:
            doc = json.loads(path.read_text())
            doc["scenarios"]
        except (ValueError, KeyError, TypeError) as e:
            raise BaselineError(f"{ref}: not a sweep report.json ({one_line(e)})") from None
        return doc
    from mjxdiff.output import history

    h = history.open_history(history_dir)
    found = h.sql("SELECT DISTINCT run_id FROM history WHERE starts_with(run_id, ?)", (ref,))
    if len(found) != 1:
        raise BaselineError(f"{ref}: no such report.json, directory or history run id "
                            f"({len(found)} runs in {h.directory} match; 'mjxdiff history --runs' lists them)")
    scenarios: dict[str, dict[str, Any]] = {}
    for r in h.sql("SELECT * FROM history WHERE run_id = ?", (found[0]["run_id"],)):
        s = scenarios.setdefault(r["scenario"], dict(name=r["scenario"], status=r["status"], fields={}))
        if r["field"]:
            s["fields"][r["field"]] = dict(max_error=r["max_error"], tolerance=r["tolerance"], ratio=r["ratio"],
                                           first_step=r["first_step"], envelope=r["envelope"])
    return dict(run_id=found[0]["run_id"], scenarios=list(scenarios.values()))


def _num(x: Any) -> float:
    try:
        return float(x)
    except (TypeError, ValueError):
        return math.nan


def _growth(old: dict[str, Any], new: dict[str, Any]) -> tuple[str, str]:
    """('error grew' | 'error shrank' | 'same', detail) of two passing scenarios' fields."""
    grew, shrank = [], []
    for name, f in new.get("fields", {}).items():
        g = old.get("fields", {}).get(name)
        if g is None:
            continue
        if _num(f.get("envelope")) > 0 or _num(g.get("envelope")) > 0:
            continue  # chaotic: the bound moves with the envelope, errors with it
        a, b, tol = _num(g.get("max_error")), _num(f.get("max_error")), _num(f.get("tolerance"))
        if not (math.isfinite(a) and math.isfinite(b)) or max(a, b) < RELEVANT * tol:
            continue
        if b >= GROWTH * max(a, 1e-300):
            grew.append(f"{name} {a:.3g} -> {b:.3g}")
        elif a >= GROWTH * max(b, 1e-300):
            shrank.append(f"{name} {a:.3g} -> {b:.3g}")
    if grew:
        return "error grew", "; ".join(grew)
    if shrank:
        return "error shrank", "; ".join(shrank)
    return "same", ""


def compare(base: dict[str, Any], doc: dict[str, Any]) -> list[dict[str, Any]]:
    """Each scenario of ``doc`` (and of ``base`` missing from it) with its class:

    * ``new failure``: fails now (``fail``, or an engine ``error``), did not in the baseline
      or was not in it;
    * ``fixed``: failed in the baseline, passes now;
    * ``error grew`` / ``error shrank``: passes in both, and some field's max error changed
      :data:`GROWTH` x or more on a calm scenario;
    * ``same``: anything else with the same status (a failure that was already there is
      ``same``); ``new scenario`` / ``not in this run``: present on one side only.
    """
    old = {s["name"]: s for s in base.get("scenarios", [])}
    out = []
    for s in doc.get("scenarios", []):
        b = old.pop(s["name"], None)
        now, then = s["status"], b["status"] if b else None
        failing = now in ("fail", "error")
        detail = ""
        if failing and then not in ("fail", "error"):
            cls, detail = "new failure", f"{then or 'absent'} -> {now}"
        elif then in ("fail", "error") and now == "pass":
            cls, detail = "fixed", f"{then} -> pass"
        elif b is None:
            cls = "new scenario"
        elif now == then == "pass":
            cls, detail = _growth(b, s)
        else:
            cls, detail = "same", "" if now == then else f"{then} -> {now}"
        out.append(dict(scenario=s["name"], status=now, baseline=then, change=cls, detail=detail))
    out += [dict(scenario=name, status=None, baseline=b["status"], change="not in this run", detail="")
            for name, b in old.items()]
    return out


def new_failures(changes: list[dict[str, Any]]) -> list[str]:
    return [c["scenario"] for c in changes if c["change"] == "new failure"]


def format_text(changes: list[dict[str, Any]], ref: str) -> str:
    counts = {c: sum(x["change"] == c for x in changes) for c in CLASSES}
    lines = [f"against baseline {ref}: " + ", ".join(f"{n} {c}" for c, n in counts.items() if n)]
    for c in changes:
        if c["change"] != "same":
            lines.append(f"  {c['change']:<16} {c['scenario']}" + (f"  ({c['detail']})" if c["detail"] else ""))
    return "\n".join(lines)
