"""``report.html``: one self-contained page of a sweep, for people.

Everything comes from the report (``report.to_json``) and the per-step series the verdict
kept (:attr:`mjxdiff.compare.verdict.FieldResult.series`); nothing is re-run. Images are PNGs drawn
by matplotlib (Agg, no display) and embedded as ``data:`` URIs, so the page opens offline.

The page: the summary; a pass-rate bar chart per scenario with the threshold line; a table of
scenarios (status, known label, baseline change, worst field, ratio to bound, first step,
timings); for every failing scenario (every scenario with ``plots="all"``) the error of each
failing field (every field) against time on a log axis, with the tolerance, the C-vs-C
envelope and the first exceedance marked; behaviour statistics of both engines side by side;
the diagnosis and links to reproducer files; anomalies and baseline changes where given.
"""

from __future__ import annotations

import base64
import html
import io
import json
import os
from pathlib import Path
from typing import Any

from mjxdiff.files import atomic_write
from mjxdiff.output import report

__all__ = ["render", "write", "render_grad", "write_grad", "PLOTS"]

PLOTS = ("failing", "all", "none")


def _png(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    import matplotlib.pyplot as plt

    plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def _num(x: Any) -> float:
    try:
        return float(x)
    except (TypeError, ValueError):
        return float("nan")


def pass_rate_chart(scenarios: list[dict[str, Any]], threshold: float) -> str:
    """Member pass rate per scenario as bars, the threshold as a dashed line."""
    import matplotlib.pyplot as plt

    shown = [s for s in scenarios if s.get("pass_rate") is not None]
    fig, ax = plt.subplots(figsize=(max(6.0, 0.32 * len(shown) + 2), 3.2))
    colours = {"pass": "#3a7d44", "fail": "#c0392b"}
    ax.bar(range(len(shown)), [_num(s["pass_rate"]) for s in shown],
           color=[colours.get(s["status"], "#888888") for s in shown])
    for i, sc in enumerate(shown):  # the rate over each bar: a failing scenario's may be 0
        ax.text(i, min(_num(sc["pass_rate"]), 1.0) + 0.02, f"{_num(sc['pass_rate']):.0%}", ha="center", fontsize=6)
    ax.axhline(threshold, color="black", linestyle="--", linewidth=1, label=f"threshold {threshold:.0%}")
    ax.set_xticks(range(len(shown)), [s["name"] for s in shown], rotation=60, ha="right", fontsize=8)
    ax.set_ylim(0, 1.12)
    ax.set_ylabel("members within bound")
    ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=8)
    return _png(fig)


def error_plot(name: str, field: str, f: dict[str, Any]) -> str:
    """Batch-max error of one field against time (log y), with the tolerance, the C-vs-C
    envelope (the bound where it is above the tolerance) and the first exceedance."""
    import matplotlib.pyplot as plt

    rows = f.get("series") or []
    steps = [r[0] for r in rows]
    x = steps  # members' timesteps may be randomized: steps, not seconds
    err = [e if e > 0 else float("nan") for e in (_num(r[1]) for r in rows)]  # exact agreement: no point on a log axis
    bound = [_num(r[2]) for r in rows]
    tol = _num(f.get("tolerance"))
    fig, ax = plt.subplots(figsize=(6.4, 2.8))
    ax.semilogy(x, err, color="#c0392b", linewidth=1.2, label="MJX vs C (batch max)")
    if any(b > tol * (1 + 1e-9) for b in bound):
        ax.semilogy(x, bound, color="#2c7fb8", linewidth=1, label="bound (C-vs-C envelope)")
    ax.axhline(tol, color="black", linestyle="--", linewidth=1, label=f"tolerance {tol:.2g}")
    first = int(f.get("first_step", -1))
    if first >= 0:
        ax.axvline(first, color="#e67e22", linewidth=1,
                   label=f"first exceedance (step {first})")
    ax.set_xlabel("step")
    ax.set_ylabel(f"{field} error")
    ax.set_title(f"{name}: {field}", fontsize=10)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    return _png(fig)


_STYLE = """body{font-family:sans-serif;margin:2em;max-width:75em}table{border-collapse:collapse;font-size:90%}
td,th{border:1px solid #ccc;padding:3px 6px;text-align:left}th{background:#eee}.pass{color:#3a7d44}
.fail{color:#c0392b;font-weight:bold}.unsupported,.error{color:#888}pre{white-space:pre-wrap;background:#f6f6f6;
padding:.5em;font-size:85%}img{max-width:100%}"""


def _has_section(sc: dict, plots: str) -> bool:
    """Whether the page gives the scenario a section of its own (a failure, or every one with
    ``--plots all``)."""
    return sc["status"] == "fail" or plots == "all"


def tested(info: dict) -> str:
    """What a scenario's verdict covered, from its ``info``: members x steps, what was randomized
    beyond the initial state and controls, and the checks that ran.

    >>> tested(dict(batch=4, steps=50, onestep={"status": "pass"}, twin={"status": "skipped"}))
    '4 members x 50 steps; randomized: state, controls; checks: one-step; did not run: converged twin (skipped)'
    """
    parts = [f"{info.get('batch', '?')} members x {info.get('steps', '?')} steps",
             "randomized: " + ", ".join(["state", "controls", *info.get("factors", [])])]
    ran, not_run = [], []
    for name, key in (("one-step", "onestep"), ("converged twin", "twin"), ("host interface", "transfer")):
        check = info.get(key)
        if not isinstance(check, dict):
            continue
        if check.get("status") in ("pass", "fail") or "checked" in check:  # the host interface has no status
            refused = [str(u).split(":")[0] for u in check.get("unsupported") or ()]
            ran.append(name + (f" (MJX cannot: {', '.join(refused)})" if refused else ""))
        else:
            not_run.append(f"{name} ({check.get('status') or 'error'})")
    return "; ".join(parts + ([f"checks: {', '.join(ran)}"] if ran else [])
                     + ([f"did not run: {', '.join(not_run)}"] if not_run else []))


def _e(x: Any) -> str:
    return html.escape(str(x))


def _scenario_row(sc: dict[str, Any], ch: dict[str, Any], plots: str) -> str:
    """The scenarios table's row of ``sc``: its name (a link to its section where it has one),
    status, what was tested, known entry, baseline change ``ch``, worst field, that field's ratio
    to its bound and first step out, seconds, compile seconds and sharp checks."""
    fields = sc.get("fields") or {}
    worst = max(fields.items(), key=lambda kv: _num(kv[1].get("ratio")), default=(None, {}))
    secs = (sc.get("info") or {}).get("seconds", {})
    total = sum(x for k, x in secs.items() if k != "compiled_ahead" and isinstance(x, (int, float)))
    first = worst[1].get("first_step")
    name = (f"<a href='#{_e(sc['name'])}'>{_e(sc['name'])}</a>" if _has_section(sc, plots)
            else _e(sc["name"]))
    return (f"<tr><td>{name}</td>"
            f"<td class='{_e(sc['status'])}'>{_e(sc['status'])}{' (weak)' if sc.get('weak') else ''}</td>"
            f"<td>{_e(tested(sc.get('info') or {}))}</td>"
            f"<td>{_e(sc.get('known', {}).get('id', ''))}"
            f"</td><td>{_e(ch.get('change', ''))}</td><td>{_e(worst[0] or '')}</td>"
            f"<td>{_num(worst[1].get('ratio')):.3g}</td>"
            f"<td>{_e(first if isinstance(first, int) and first >= 0 else 'none')}</td>"
            f"<td>{total:.2f}</td><td>{_num(secs.get('compile')):.2f}</td>"
            f"<td>{_e(report.format_checks(sc.get('info') or {}).removeprefix('checks: '))}</td></tr>")


def _scenario_section(sc: dict[str, Any], out_dir: str | Path | None, plots: str) -> list[str]:
    """The parts of ``sc``'s own section: heading, known entry and advice, message, error plots
    (per ``plots``), behaviour table, diagnosis and reproducer link (relative to ``out_dir``)."""
    failing = sc["status"] == "fail"
    parts = [f"<h2 id='{_e(sc['name'])}'>{_e(sc['name'])}: {_e(sc['status'])}</h2>"]
    if sc.get("known"):
        k = sc["known"]
        parts.append(f"<p><b>known: {_e(k['id'])}</b> ({_e(k['title'])}). Evidence: {_e(k['evidence'])}</p>")
        if k.get("advice"):
            parts.append(f"<p><b>What to do</b>: {_e(k['advice'])}</p>")
    parts.append(f"<pre>{_e(sc.get('message', ''))}</pre>")
    if plots != "none":
        for field, f in (sc.get("fields") or {}).items():
            if f.get("series") and (not failing or int(f.get("first_step", -1)) >= 0 or plots == "all"):
                parts.append(f"<img alt='{_e(sc['name'])} {_e(field)} error vs time' "
                             f"src='{error_plot(sc['name'], field, f)}'>")
    b = sc.get("behaviour") or {}
    if b.get("c") and b.get("mjx"):
        parts.append("<table><tr><th>behaviour</th><th>MuJoCo C</th><th>MJX</th><th>relative difference</th></tr>"
                     + "".join(f"<tr><td>{_e(k)}</td><td>{_num(b['c'][k]):.6g}</td><td>{_num(b['mjx'].get(k)):.6g}"
                               f"</td><td>{_num(b.get('relative_difference', {}).get(k)):.3g}</td></tr>"
                               for k in b["c"]) + "</table>")
    if sc.get("diagnosis"):
        parts.append(f"<details><summary>diagnosis</summary><pre>{_e(json.dumps(sc['diagnosis'], indent=1))}"
                     "</pre></details>")
    rep = (sc.get("info") or {}).get("reproducer")
    if rep:
        href = os.path.relpath(rep, out_dir) if out_dir else rep
        parts.append(f"<p>reproducer: <a href='{_e(Path(href).as_posix())}'>{_e(href)}</a> "
                     f"(<code>python -m mjxdiff replay {_e(rep)}</code>)</p>")
    return parts


def render(doc: dict[str, Any], out_dir: str | Path | None = None, plots: str = "failing") -> str:
    """The page as a string; ``out_dir`` makes reproducer links relative to where it is written."""
    import matplotlib

    matplotlib.use("Agg", force=True)
    s = doc.get("summary", {})
    threshold = _num(s.get("member_pass_threshold", 0.95))
    scenarios = doc.get("scenarios", [])
    changes = {c["scenario"]: c for c in (doc.get("baseline") or {}).get("changes", [])}
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>mjxdiff report</title>"
             f"<style>{_STYLE}</style></head><body><h1>mjxdiff: MJX vs MuJoCo C</h1>"]
    v = doc.get("versions", {})
    parts.append(f"<p><b>{_e(s.get('verdict', ''))}</b>: {s.get('total', 0)} scenarios, {s.get('pass', 0)} pass, "
                 f"{s.get('fail', 0)} fail, {s.get('unsupported', 0)} unsupported, {s.get('error', 0)} error; "
                 f"pass rate {_num(s.get('pass_rate')):.0%}. mujoco {_e(v.get('mujoco'))}, mujoco-mjx "
                 f"{_e(v.get('mujoco-mjx'))}, jax {_e(v.get('jax'))}; "
                 f"MJX code {_e(doc.get('code', {}).get('mjx', ''))[:12]}; "
                 f"seed {_e(doc.get('config', {}).get('seed'))}.</p>")
    if scenarios:
        parts.append(f"<h2>Pass rate per scenario</h2><img alt='pass rate per scenario' "
                     f"src='{pass_rate_chart(scenarios, threshold)}'>")
    parts.append("<h2>Scenarios</h2><table><tr><th>scenario</th><th>status</th><th>tested</th><th>known</th>"
                 "<th>baseline</th><th>worst field</th><th>ratio to bound</th><th>first step out</th><th>seconds</th>"
                 "<th>compile s</th><th>sharp checks (one-step, converged twin)</th></tr>")
    parts.extend(_scenario_row(sc, changes.get(sc["name"], {}), plots) for sc in scenarios)
    parts.append("</table>")
    for section, key in (("History anomalies", "anomalies"),):
        items = (doc.get("history") or {}).get(key) or []
        if items:
            parts.append(f"<h2>{section}</h2><ul>" + "".join(f"<li>{_e(a['message'])}</li>" for a in items) + "</ul>")
    if changes:
        parts.append(f"<h2>Against baseline {_e(doc['baseline'].get('ref', ''))}</h2><ul>" + "".join(
            f"<li>{_e(c['change'])}: {_e(c['scenario'])} {_e(c.get('detail', ''))}</li>"
            for c in changes.values() if c["change"] != "same") + "</ul>")
    for sc in scenarios:
        if _has_section(sc, plots):
            parts.extend(_scenario_section(sc, out_dir, plots))
    parts.append("</body></html>")
    return "\n".join(parts)


def _write(path: Path, text: str) -> Path:
    """``text`` into ``path`` atomically (:func:`mjxdiff.files.atomic_write`)."""
    return atomic_write(path, text)


def write(out_dir: str | Path, doc: dict[str, Any], plots: str = "failing") -> Path:
    """Writes ``out_dir/report.html`` (atomically: a temporary file renamed into place)."""
    return _write(Path(out_dir) / "report.html", render(doc, Path(out_dir), plots))


# ----------------------------------------------------------------------------
# the derivative report (``mjxdiff grad``)


def heatmap(name: str, state: int, matrices: dict[str, list[list[float]]]) -> str:
    """log10(|MJX - C| / floor) of A, B, C, D side by side; above 0 (red) fails."""
    import matplotlib.pyplot as plt
    import numpy as np

    shown = {k: np.asarray(v, float) for k, v in matrices.items() if np.size(v)}
    fig, axes = plt.subplots(1, len(shown), figsize=(3.2 * len(shown) + 1, 3.4), squeeze=False)
    image = None
    for ax, (k, v) in zip(axes[0], shown.items()):
        image = ax.imshow(v, cmap="RdBu_r", vmin=-3, vmax=3, interpolation="nearest", aspect="auto")
        ax.set_title({"A": "A = dx'/dx", "B": "B = dx'/du", "C": "C = ds/dx", "D": "D = ds/du"}[k], fontsize=9)
        ax.set_xlabel("input", fontsize=8)
        ax.set_ylabel("output", fontsize=8)
        ax.tick_params(labelsize=7)
    assert image is not None  # subplots refuses zero columns: some matrix was drawn
    fig.colorbar(image, ax=list(axes[0]), label="log10 |MJX - C| / floor")
    fig.suptitle(f"{name}: state {state}", fontsize=10)
    return _png(fig)


def render_grad(doc: dict[str, Any], out_dir: str | Path | None = None) -> str:
    """The page of a ``grad`` report: a table of scenarios, then per failing scenario its
    message, a heat map of its worst state and the reproducer's link."""
    import matplotlib

    matplotlib.use("Agg", force=True)
    rows = doc.get("scenarios", [])
    v = doc.get("versions", {})
    counts = {k: sum(r["status"] == k for r in rows) for k in ("pass", "fail", "non-smooth", "unsupported", "error")}
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>mjxdiff grad report</title>"
             f"<style>{_STYLE}</style></head><body><h1>mjxdiff grad: MJX's Jacobians vs MuJoCo C's finite "
             "differences</h1>",
             f"<p>{len(rows)} scenarios: " + ", ".join(f"{n} {k}" for k, n in counts.items()) +
             f". mujoco {_e(v.get('mujoco'))}, mujoco-mjx {_e(v.get('mujoco-mjx'))}, jax {_e(v.get('jax'))}; "
             f"seed {_e(doc.get('config', {}).get('seed'))}, "
             f"{_e(doc.get('config', {}).get('states'))} states each.</p>",
             "<table><tr><th>scenario</th><th>status</th><th>smooth</th><th>non-smooth</th>"
             "<th>worst ratio to floor</th><th>seconds</th></tr>"]
    for r in rows:
        anchor = f"<a href='#{_e(r['name'])}'>{_e(r['name'])}</a>" if r.get("heatmap") else _e(r["name"])
        parts.append(f"<tr><td>{anchor}</td><td class='{_e(r['status'])}'>{_e(r['status'])}</td>"
                     f"<td>{_e(r.get('smooth', ''))}</td><td>{_e(r.get('non_smooth', ''))}</td>"
                     f"<td>{_num(r.get('worst_ratio')):.3g}</td><td>{_num(r.get('seconds')):.1f}</td></tr>")
    parts.append("</table>")
    for r in rows:
        if r["status"] in ("pass",) and not r.get("heatmap"):
            continue
        parts.append(f"<h2 id='{_e(r['name'])}'>{_e(r['name'])}: {_e(r['status'])}</h2>"
                     f"<pre>{_e(r.get('message', ''))}</pre>")
        h = r.get("heatmap")
        if h:
            parts.append(f"<img alt='{_e(r['name'])} Jacobian error map' "
                         f"src='{heatmap(r['name'], h['state'], h['log10_ratio'])}'>")
        if r.get("reproducer"):
            href = os.path.relpath(r["reproducer"], out_dir) if out_dir else r["reproducer"]
            parts.append(f"<p>reproducer: <a href='{_e(Path(href).as_posix())}'>{_e(href)}</a> "
                         f"(<code>python -m mjxdiff replay {_e(r['reproducer'])}</code>)</p>")
    parts.append("</body></html>")
    return "\n".join(parts)


def write_grad(out_dir: str | Path, doc: dict[str, Any]) -> Path:
    """Writes ``out_dir/grad-report.html``."""
    return _write(Path(out_dir) / "grad-report.html", render_grad(doc, Path(out_dir)))
