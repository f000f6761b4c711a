"""Measures what MJX's rollout of a model costs to trace, compile and run, beside the features
:mod:`mjxdiff.input.cost` estimates from, to calibrate (and check) its estimate.

    python benchmarks/scripts/cost_calibration.py MODEL.xml [MODEL.xml ...] [--timeout 600] [--rss-gb 18]

Each model runs in a fresh process with an empty compilation cache (so it traces and
compiles), as a sweep of it with default settings would: the scenario's inputs, the sweep's
plan (member group, piece length), then :meth:`MJXEngine.compile_ahead`, then one piece.
The parent kills a child past ``--timeout`` seconds or ``--rss-gb`` resident and says so.
One JSON line per model: the estimate (made before compiling), the measured seconds
(trace + lower, compile, first piece), XLA's memory analysis and the child's peak RSS.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time


def child(path: str) -> None:
    import resource

    from mjxdiff.input import cost
    from mjxdiff.engine import engines, export_cache, xla
    from mjxdiff.input.scenario import load_scenario
    from mjxdiff.runner.plan import layout
    from mjxdiff.runner.sweep import SweepConfig, _prepare

    engines.configure_jax("float64", cache_dir=tempfile.mkdtemp(prefix="calib-"))
    import jax

    out: dict = dict(model=path)
    t0 = time.perf_counter()
    prepared = _prepare(load_scenario(path), SweepConfig())
    if prepared.early is not None:
        print(json.dumps(dict(out, error=prepared.early.message)))
        return
    m, inputs = prepared.m, prepared.inputs
    out.update(prepare_s=round(time.perf_counter() - t0, 2))
    t = time.perf_counter()
    est = cost.estimate(m, inputs.batch, inputs.steps)
    out.update(estimate=est.as_dict(), estimate_s=round(time.perf_counter() - t, 2))
    print(json.dumps(dict(out, phase="estimated")), flush=True)
    engine = engines.MJXEngine()
    groups, chunk = layout(m, inputs, SweepConfig(), engine)
    group = inputs.take(groups[0]) if len(groups) > 1 else inputs
    seen = {}
    choose0 = xla.xla_options

    def xla_options(mode, steps):
        inner = choose0(mode, steps)

        def choose(lowered):
            seen["lowered_at"] = time.perf_counter()
            seen["features"] = cost.hlo_features(lowered.as_text())
            print(json.dumps(dict(out, phase="lowered", trace_lower_s=round(seen["lowered_at"] - t, 2),
                                  rollout_features=seen["features"])), flush=True)
            return inner(lowered)
        return choose

    xla.xla_options = xla_options
    t = time.perf_counter()
    with jax.enable_x64(True):
        engine.compile_ahead(group, chunk)
        done = time.perf_counter()
        out.update(group=group.batch, chunk=chunk, trace_lower_s=round(seen.get("lowered_at", done) - t, 2),
                   compile_s=round(done - seen.get("lowered_at", t), 2), rollout_features=seen.get("features"))
        for _, compiled, _ in export_cache._FUNCTIONS.values():
            with_mem = compiled.memory_analysis()
            out["xla_temp_bytes"] = int(getattr(with_mem, "temp_size_in_bytes", 0))
            out["xla_arg_bytes"] = int(getattr(with_mem, "argument_size_in_bytes", 0))
        print(json.dumps(dict(out, phase="compiled")), flush=True)
        t = time.perf_counter()
        try:
            engine.first_piece(group, chunk)
            out["first_piece_s"] = round(time.perf_counter() - t, 2)
        except Exception as e:  # noqa: BLE001 - recorded
            out["run_error"] = " ".join(str(e).split())[:300]
    out["peak_rss_gb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20, 2)
    print(json.dumps(dict(out, phase="done")), flush=True)


#: Resident bytes of a process that has imported mjxdiff, JAX and MJX (measured: 0.4-0.5 GB).
BASELINE_BYTES = 0.45 * 2**30


def features(path: str) -> dict:
    """The model features :func:`mjxdiff.input.cost.estimate` reads: nv, collision groups, hull work."""
    from mjxdiff.input import cost
    from mjxdiff.input.scenario import load_scenario
    from mjxdiff.runner.sweep import SweepConfig, _prepare

    m = _prepare(load_scenario(path), SweepConfig()).m
    if m is None:
        return {}
    est = cost.estimate(m)
    hull = sum(any(h is not None for h in g.hulls) for g in est.groups)
    work = sum(g.work * g.pairs for g in est.groups if g.work > 1)
    return dict(nv=m.nv, groups=len(est.groups) - hull, hull=hull, work=work, est=est)


def fit(path: str) -> None:
    """Least squares of measured (trace + compile) seconds on the estimate's features, and the
    table of estimate against measurement (and peak RSS against the per-member estimate)."""
    import numpy as np

    from mjxdiff.input import cost

    rows = [json.loads(x) for x in open(path) if x.startswith("{")]
    rows = [r for r in rows if r.get("compile_s")]  # killed after its compile: that is measured
    feats = [features(r["model"]) for r in rows]
    X = np.array([[1.0, f["nv"], f["groups"], f["hull"]] for f in feats])
    y = np.array([r["trace_lower_s"] + r["compile_s"] for r in rows])
    coef, *_ = np.linalg.lstsq(X, y, rcond=None)
    print("compile fit: base %.2f s, %.3f s per dof, %.2f s per primitive function, %.2f s per hull function"
          % tuple(coef))
    steps = [(f["work"], r["first_piece_s"] / (r["group"] * r["chunk"])) for r, f in zip(rows, feats)
             if r.get("first_piece_s")]
    print("stepping: " + ", ".join(f"{w:.0f} -> {s * 1e3:.2f} ms" for w, s in steps))
    print("| model | nv | functions (hull) | hull work | compile measured | estimate | ratio | "
          "per member-step measured | estimate | XLA temp per member | estimate | peak RSS | estimate |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r, f, yy in zip(rows, feats, y):
        est = f["est"]
        step = r["first_piece_s"] / (r["group"] * r["chunk"]) if r.get("first_piece_s") else None
        temp = r.get("xla_temp_bytes", 0) / r["group"]
        name = r["model"].split("/")[-2] if "robots" in r["model"] else r["model"].split("/")[-1]
        print(f"| {name} | {f['nv']} | {f['groups'] + f['hull']} ({f['hull']}) | {f['work']:.3g} | {yy:.1f} s | "
              f"{est.compile_s:.1f} s | {est.compile_s / yy:.2f} | "
              + (f"{step * 1e3:.2f} ms | {est.step_s * 1e3:.2f} ms" if step else "- | -")
              + f" | {cost.human_bytes(temp)} | {cost.human_bytes(est.member_bytes)} | "
              f"{r.get('peak_rss_gb') or r.get('polled_peak_gb')} GB{' (killed)' if r.get('killed') else ''} | "
              f"{(BASELINE_BYTES + est.compile_bytes + r['group'] * est.member_bytes) / 2**30:.2f} GB |")


def rss_gb(pid: int) -> float:
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 2**20
    except OSError:
        pass
    return 0.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("models", nargs="+")
    ap.add_argument("--timeout", type=float, default=600)
    ap.add_argument("--rss-gb", type=float, default=18)
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--fit", action="store_true", help="MODELS is one JSON-lines output of this script: fit it")
    args = ap.parse_args()
    if args.fit:
        fit(args.models[0])
        return
    if args.child:
        child(args.models[0])
        return
    for path in args.models:
        t = time.perf_counter()
        with tempfile.TemporaryFile("w+") as log:
            proc = subprocess.Popen([sys.executable, __file__, "--child", path], stdout=log,
                                    stderr=subprocess.DEVNULL, env=dict(os.environ, PYTHONUNBUFFERED="1"))
            peak, why = 0.0, None
            while proc.poll() is None:
                time.sleep(0.5)
                peak = max(peak, rss_gb(proc.pid))
                if peak > args.rss_gb:
                    why = f"killed at {peak:.1f} GB resident"
                elif time.perf_counter() - t > args.timeout:
                    why = f"killed after {args.timeout:.0f} s"
                if why:
                    proc.kill()
                    proc.wait()
            log.seek(0)
            lines = [json.loads(x) for x in log.read().splitlines() if x.startswith("{")]
        last = lines[-1] if lines else dict(model=path)
        print(json.dumps(dict(last, wall_s=round(time.perf_counter() - t, 1), polled_peak_gb=round(peak, 2),
                              killed=why, rc=proc.returncode)), flush=True)


if __name__ == "__main__":
    main()
