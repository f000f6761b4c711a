"""Regenerates the documentation's pictures: ``python docs/scripts/screenshots.py [STEP ...]``.

Steps (default: all but ``sharpness-sweep``, which is slow):

- ``failing``: a quick sweep of pendulum and cartpole with MJX's actuator gains 2% high (the
  test suite's injected bug, monkeypatched in this process), then headless Chromium's screenshot
  of its ``report.html``: ``docs/img/report_failing.png``.
- ``drilldown``: a quick sweep of ``tests/data/tilted_box_on_plane.xml`` with unmodified MJX (a
  real divergence: MJX keeps fewer plane-box corners than C), and its drill-down (each forward
  stage's difference from C's state at the first divergent step) drawn with matplotlib:
  ``docs/img/drilldown.png``.
- ``sharpness``: each bundled scenario's loosest bound at the median step over its field's
  scale, from ``docs/data/sharpness.json``: ``docs/img/sharpness.png``.
- ``sharpness-sweep``: the full default sweep (minutes), whose ``report.json`` refreshes
  ``docs/data/sharpness.json``; then ``sharpness``.
- ``site``: ``mkdocs build`` into a temporary directory and screenshots of three pages (home,
  the sweep guide, the findings page) under ``--shots`` (default ``/tmp/mjxdiff-site-shots``);
  these are for looking at, not committed.

Needs the ``docs`` extra and Chromium (``chromium``, ``chromium-browser`` or ``google-chrome``).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
IMG = ROOT / "docs" / "img"
DATA = ROOT / "docs" / "data" / "sharpness.json"
#: viewport of every screenshot, pixels (width, height)
WINDOW = (1280, 900)


def browser() -> str:
    """The headless Chromium to screenshot with; exits with a message when none is installed."""
    found = next((shutil.which(b) for b in ("chromium", "chromium-browser", "google-chrome") if shutil.which(b)), None)
    if found is None:
        sys.exit("screenshots: no Chromium found (apt-get install chromium)")
    return found


def screenshot(url: str, out: Path, window: tuple[int, int] = WINDOW) -> Path:
    """Headless Chromium's screenshot of ``url`` (``file://`` or ``http://``), ``window`` in pixels."""
    subprocess.run([browser(), "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
                    "--disable-background-networking", f"--screenshot={out}",
                    f"--window-size={window[0]},{window[1]}", url],
                   check=True, capture_output=True, timeout=120)
    print(f"screenshots: wrote {out}")
    return out


def sweep(args: list[str]) -> int:
    """``mjxdiff sweep ARGS`` in this process (so a patch applied here is what is tested), no
    history; returns the exit code."""
    from mjxdiff.cli import main

    return main(["sweep", *args, "--no-history"])


def failing(work: Path) -> None:
    """The report page of a sweep that fails: MJX's actuator gains 2% high."""
    from mujoco.mjx._src import forward as mjx_forward

    from mjxdiff.engine import engines

    orig = mjx_forward.fwd_actuation
    mjx_forward.fwd_actuation = lambda m, d: orig(m.replace(actuator_gainprm=m.actuator_gainprm * 1.02), d)
    engines.clear_compiled()
    try:
        code = sweep(["pendulum", "cartpole", "--quick", "--cache-dir", "", "--diagnose", "basic",
                      "--out", str(work / "failing")])
    finally:
        mjx_forward.fwd_actuation = orig
        engines.clear_compiled()
    assert code == 1, f"the injected bug was not caught (exit {code})"
    screenshot((work / "failing" / "report.html").as_uri(), IMG / "report_failing.png", (1280, 1250))


def drilldown(work: Path) -> None:
    """The drill-down of a real divergence (tilted box on a plane), as a bar chart."""
    out = work / "drilldown"
    sweep([str(ROOT / "tests" / "data" / "tilted_box_on_plane.xml"), "--quick", "--diagnose", "basic",
           "--out", str(out)])
    report = json.loads((out / "report.json").read_text())
    failed = next(s for s in report["scenarios"] if s["status"] == "fail")
    draw_drilldown(failed, IMG / "drilldown.png")


def draw_drilldown(scenario: dict, out: Path) -> None:
    """Each forward stage's field against its scaled MJX-vs-C difference (log axis; exact
    agreement drawn at the axis floor), the first differing field marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    drill = scenario["diagnosis"]["drill_down"]
    rows = drill["fields"][::-1]
    floor = 1e-17
    finite = [float(r["error"]) for r in rows if float(r["error"]) < float("inf")]
    top = max(finite + [1.0]) * 100  # where a count mismatch (error "inf") is drawn
    errors = [min(max(float(r["error"]), floor), top) for r in rows]
    fig, ax = plt.subplots(figsize=(10, 0.32 * len(rows) + 1.6), dpi=110)
    ax.barh([f"{r['stage']}: {r['field']}" for r in rows], errors, left=floor,
            color=["#c0392b" if r["differs"] else "#7f8c8d" for r in rows])
    for y, (r, e) in enumerate(zip(rows, errors)):
        if r["differs"]:
            ax.text(e, y, f"  {r['object'].removeprefix('geoms ')}", va="center", fontsize=8)
    ax.set_xscale("log")
    ax.set_xlim(floor, top * 1e12)
    ax.set_xlabel("|MJX - C| from the same C state (0 drawn at 1e-17; a contact-count mismatch at the right)")
    ax.set_title(f"{scenario['name']}, member {drill['member']}, step {drill['step']}: mj_forward and mjx.forward "
                 f"stage by stage from C's state\nfirst to differ: {drill['first_stage']} ({drill['first_field']}, "
                 f"{drill['object']})", fontsize=9)
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)
    print(f"screenshots: wrote {out}")


def sharpness_from_report(report: dict) -> dict[str, dict]:
    """Scenario -> its loosest field at the median step: ``{"field", "bound_scale", "weak"}``
    (``bound_scale``: the batch-max bound over the field's scale, dimensionless); passing
    scenarios only (a failure's bound is not what decided it)."""
    out = {}
    for s in report["scenarios"]:
        scaled = {k: f["bound_scale"][1] for k, f in (s.get("fields") or {}).items() if f.get("bound_scale")}
        if s["status"] == "pass" and scaled:
            field = max(scaled, key=lambda k: scaled[k])
            out[s["name"]] = {"field": field, "bound_scale": scaled[field], "weak": bool(s.get("weak"))}
    return out


def draw_sharpness(data: dict, out: Path) -> None:
    """Horizontal bars of each scenario's loosest bound over scale (log axis), with the weak-pass
    line (:data:`mjxdiff.compare.verdict.WEAK_BOUND`)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mjxdiff.compare.verdict import WEAK_BOUND

    rows = sorted(data["scenarios"].items(), key=lambda kv: kv[1]["bound_scale"])
    fig, ax = plt.subplots(figsize=(8, 0.27 * len(rows) + 1.6), dpi=110)
    ax.barh([f"{name} ({r['field']})" for name, r in rows], [r["bound_scale"] for _, r in rows],
            color=["#e67e22" if r["weak"] else "#2980b9" for _, r in rows])
    ax.axvline(WEAK_BOUND, color="#c0392b", linestyle="--", label=f"weak above {WEAK_BOUND:g} of the scale")
    ax.set_xscale("log")
    ax.set_xlabel("bound at the median step / the field's scale (the loosest field)")
    ax.set_title(f"Sharpness of each bundled scenario's pass\n{data['source']}", fontsize=9)
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)
    print(f"screenshots: wrote {out}")


def sharpness_sweep(work: Path) -> None:
    """The full default sweep; its sharpness refreshes :data:`DATA`."""
    sweep(["--out", str(work / "full"), "--compile-workers", "1"])  # one core: leave the other to whoever shares it
    report = json.loads((work / "full" / "report.json").read_text())
    versions = report["versions"]
    data = {"source": f"default sweep, seed {report['seed']}, MuJoCo {versions['mujoco']}, "
                      f"MJX {versions['mujoco-mjx']}, {time.strftime('%Y-%m-%d')}",
            "scenarios": sharpness_from_report(report)}
    DATA.parent.mkdir(parents=True, exist_ok=True)
    DATA.write_text(json.dumps(data, indent=1) + "\n")
    print(f"screenshots: wrote {DATA}")


def sharpness(_: Path) -> None:
    draw_sharpness(json.loads(DATA.read_text()), IMG / "sharpness.png")


def site(_: Path, shots: Path) -> None:
    """Builds the site and screenshots home, the sweep guide and the findings page."""
    shots.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as built:
        subprocess.run([sys.executable, "-m", "mkdocs", "build", "--quiet", "--site-dir", built],
                       check=True, cwd=ROOT)
        for name, page in (("home", "index.html"), ("sweep-guide", "how-to/sweep-robot/index.html"),
                           ("findings", "findings/index.html")):
            screenshot((Path(built) / page).as_uri(), shots / f"{name}.png")


STEPS = {"failing": failing, "drilldown": drilldown, "sharpness-sweep": sharpness_sweep, "sharpness": sharpness}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("steps", nargs="*", choices=[*STEPS, "site"], metavar="STEP",
                        help="failing, drilldown, sharpness, sharpness-sweep, site (default: all but sharpness-sweep)")
    parser.add_argument("--shots", type=Path, default=Path("/tmp/mjxdiff-site-shots"),
                        help="where the site's screenshots go")
    args = parser.parse_args()
    steps = args.steps or ["failing", "drilldown", "sharpness", "site"]
    IMG.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as work:
        for step in steps:
            if step == "site":
                site(Path(work), args.shots)
            else:
                STEPS[step](Path(work))


if __name__ == "__main__":
    main()
