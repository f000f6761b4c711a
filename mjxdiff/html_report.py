"""``report.html``: one self-contained page of a sweep, for people.

Everything comes from the report (``report.to_json``) and the per-step series the verdict
kept (:attr:`mjxdiff.verdict.FieldResult.series`); nothing is re-run. Images are PNGs drawn
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

__all__ = ["render", "write", "PLOTS"]

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


def _e(x: Any) -> str:
    return html.escape(str(x))


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
                 f"{_e(v.get('mujoco-mjx'))}, jax {_e(v.get('jax'))}; MJX code {_e(doc.get('code', {}).get('mjx', ''))[:12]}; "
                 f"seed {_e(doc.get('config', {}).get('seed'))}.</p>")
    if scenarios:
        parts.append(f"<h2>Pass rate per scenario</h2><img alt='pass rate per scenario' "
                     f"src='{pass_rate_chart(scenarios, threshold)}'>")
    parts.append("<h2>Scenarios</h2><table><tr><th>scenario</th><th>status</th><th>known</th><th>baseline</th>"
                 "<th>worst field</th><th>ratio to bound</th><th>first step</th><th>seconds</th>"
                 "<th>compile s</th></tr>")
    for sc in scenarios:
        fields = sc.get("fields") or {}
        worst = max(fields.items(), key=lambda kv: _num(kv[1].get("ratio")), default=(None, {}))
        secs = (sc.get("info") or {}).get("seconds", {})
        total = sum(x for k, x in secs.items() if k != "compiled_ahead" and isinstance(x, (int, float)))
        ch = changes.get(sc["name"], {})
        parts.append(f"<tr><td><a href='#{_e(sc['name'])}'>{_e(sc['name'])}</a></td>"
                     f"<td class='{_e(sc['status'])}'>{_e(sc['status'])}</td><td>{_e(sc.get('known', {}).get('id', ''))}"
                     f"</td><td>{_e(ch.get('change', ''))}</td><td>{_e(worst[0] or '')}</td>"
                     f"<td>{_num(worst[1].get('ratio')):.3g}</td><td>{_e(worst[1].get('first_step', ''))}</td>"
                     f"<td>{total:.2f}</td><td>{_num(secs.get('compile')):.2f}</td></tr>")
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
        failing = sc["status"] == "fail"
        if not failing and plots != "all":
            continue
        parts.append(f"<h2 id='{_e(sc['name'])}'>{_e(sc['name'])}: {_e(sc['status'])}</h2>")
        if sc.get("known"):
            k = sc["known"]
            parts.append(f"<p><b>known: {_e(k['id'])}</b> ({_e(k['title'])}). Evidence: {_e(k['evidence'])}</p>")
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
    parts.append("</body></html>")
    return "\n".join(parts)


def write(out_dir: str | Path, doc: dict[str, Any], plots: str = "failing") -> Path:
    """Writes ``out_dir/report.html`` (atomically: a temporary file renamed into place)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "report.html"
    tmp = out / ".report.html.tmp"
    tmp.write_text(render(doc, out, plots), encoding="utf-8")
    os.replace(tmp, path)
    return path
