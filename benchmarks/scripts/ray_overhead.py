"""Ray against local on the whole default sweep, cold and warm, in one run; the same answers
checked; the scaling model fed the measured units and plotted.

    python benchmarks/scripts/ray_overhead.py [SCENARIO ...] [--quick] [--plot PNG]

Every phase is a ``python -m mjxdiff sweep`` process, timed from start to exit, as a user runs it:

1. Ray's fixed cost: ``ray.init`` of a local instance + one trivial task + ``ray.shutdown``.
2. local, cold (an empty ``--cache-dir``) then warm (the same directory again).
3. Ray, cold (another empty directory) then warm: ``--executor ray --cpus-per-scenario 1``, a
   local instance of this machine's CPUs (two tasks at once here).
4. Shards 1/3, 2/3, 3/3 (local, warm) joined by ``mjxdiff merge``.
5. The same answers: every run's verdicts and per-field numbers, timings and worker details
   aside, equal to the local warm run's; printed, and the exit status is 1 when they differ.
6. Overhead: Ray's wall minus local's, cold and warm, and per unit after the fixed cost.
7. The model (:mod:`mjxdiff.runner.scaling`) fed each Ray run's journal (a node = this machine: its
   CPUs // 1 slots), checked against the measured Ray wall at 1 node, then 1-64 nodes; with
   ``--plot``, the predicted speed-up against nodes, cold and warm, as a PNG.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called")

#: What differs between two runs of one unit: wall times, memory, compile or load counts, the worker.
RUN_INFO = {"seconds", "guard", "plan", "mjx_compiles", "mjx_loaded", "reproducer", "worker"}


def verdicts(out: Path) -> list[dict]:
    doc = json.loads((out / "report.json").read_text())
    return [{**s, "info": {k: v for k, v in s["info"].items() if k not in RUN_INFO}} for s in doc["scenarios"]]


def sweep(name: str, tmp: Path, scenarios, quick: bool, cache: Path, extra=()) -> tuple[Path, float]:
    out = tmp / name
    argv = [sys.executable, "-m", "mjxdiff", "sweep", *scenarios, "--no-history", "--out", str(out),
            "--cache-dir", str(cache), *(["--quick"] if quick else []), *extra]
    t0 = time.perf_counter()
    with open(tmp / f"{name}.log", "w") as log:
        code = subprocess.call(argv, stdout=log, stderr=subprocess.STDOUT)
    wall = time.perf_counter() - t0
    if code not in (0, 1):
        raise SystemExit(f"{name}: exit {code}; see {tmp / f'{name}.log'}")
    print(f"  {name}: {wall:.1f} s (exit {code})", flush=True)
    return out, wall


def ray_fixed_cost() -> float:
    import ray

    t0 = time.perf_counter()
    ray.init(address="local", num_cpus=os.cpu_count(), object_store_memory=200 << 20, include_dashboard=False,
             log_to_driver=False, logging_level=logging.ERROR)
    t1 = time.perf_counter()
    ray.get(ray.remote(lambda: os.getpid()).remote())
    t2 = time.perf_counter()
    ray.shutdown()
    fixed = time.perf_counter() - t0
    print(f"Ray fixed cost: init {t1 - t0:.1f} s, first task {t2 - t1:.1f} s, shutdown {time.perf_counter() - t2:.1f}"
          f" s = {fixed:.1f} s", flush=True)
    return fixed


def plot(predictions: dict[str, list], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.6), dpi=120)
    for label, table in predictions.items():
        nodes = [p.nodes for p in table]
        ax.plot(nodes, [p.speedup for p in table], marker="o", label=f"{label} (bound: {table[0].longest})")
        ax.axhline(table[0].wall / table[0].bound, linestyle=":", linewidth=0.8, color=ax.lines[-1].get_color())
    ax.set(xscale="log", yscale="log", xlabel=f"nodes ({os.cpu_count()} CPUs each, 1 per unit)",
           ylabel="predicted speed-up",
           title="Default sweep on Ray: speed-up over one node")
    ax.set_xticks([1, 2, 4, 8, 16, 32, 64], labels=["1", "2", "4", "8", "16", "32", "64"])
    ax.set_yticks([1, 2, 3, 4, 6], labels=["1", "2", "3", "4", "6"])
    ax.minorticks_off()
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    print(f"plot: {path}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scenarios", nargs="*", help="default: the default sweep")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--plot", type=Path, help="write the predicted speed-up to this PNG")
    args = parser.parse_args()
    from mjxdiff.runner import journal, scaling

    fixed = ray_fixed_cost()
    cpus = os.cpu_count() or 1
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        run = dict(tmp=tmp, scenarios=args.scenarios, quick=args.quick)
        walls, outs = {}, {}
        for name, cache, extra in (("local-cold", "a", ()), ("local-warm", "a", ()),
                                   ("ray-cold", "b", ("--executor", "ray", "--cpus-per-scenario", "1")),
                                   ("ray-warm", "b", ("--executor", "ray", "--cpus-per-scenario", "1"))):
            outs[name], walls[name] = sweep(name, cache=tmp / f"cache-{cache}", extra=extra, **run)
        for i in (1, 2, 3):
            outs[f"shard{i}"], walls[f"shard{i}"] = sweep(f"shard{i}", cache=tmp / "cache-a",
                                                          extra=("--shard", f"{i}/3"), **run)
        merged = tmp / "merged"
        code = subprocess.call([sys.executable, "-m", "mjxdiff", "merge", str(merged),
                                *(str(outs[f"shard{i}"]) for i in (3, 1, 2))],
                               stdout=subprocess.DEVNULL, env={**os.environ, "MJXDIFF_HISTORY": str(tmp / "history")})
        print(f"  merge of shards 3, 1, 2: exit {code}")
        outs["merged"] = merged

        reference = verdicts(outs["local-warm"])
        same = True
        for name in ("local-cold", "ray-cold", "ray-warm", "merged"):
            other = verdicts(outs[name])
            differing = [a["name"] for a, b in zip(reference, other, strict=False) if a != b]
            ok = len(other) == len(reference) and not differing
            same &= ok
            print(f"same answers as local-warm: {name}: {'yes' if ok else 'NO'} ({len(other)} units"
                  + (f"; differ: {differing}" if differing else "") + ")")

        units = {k: [(r["unit"], float(r["seconds"])) for r in journal.read(outs[k] / journal.FILE).units]
                 for k in ("local-cold", "local-warm", "ray-cold", "ray-warm")}
        n = len(units["ray-warm"])
        for heat in ("cold", "warm"):
            extra = walls[f"ray-{heat}"] - walls[f"local-{heat}"]
            print(f"{heat}: local {walls[f'local-{heat}']:.1f} s, Ray {walls[f'ray-{heat}']:.1f} s: Ray costs "
                  f"{extra:+.1f} s, fixed {fixed:.1f} s + {(extra - fixed) / n:+.2f} s per unit ({n} units)")
        predictions = {}
        for heat in ("cold", "warm"):
            work, measured = units[f"ray-{heat}"], walls[f"ray-{heat}"]
            # the check: one node of this machine's CPUs (one slot per unit), Ray's fixed cost, no
            # per-unit cost; what the measured wall holds beyond it is the per-unit cost, which the
            # table for more nodes then includes
            bare = scaling.predict(work, nodes=(1,), slots=cpus, fixed=fixed)[0].wall
            per_task = max(0.0, (measured - bare) * cpus / n)
            table = scaling.predict(work, slots=cpus, fixed=fixed, per_task=per_task)
            predictions[heat] = table
            print(f"\n{heat} caches: units' worker seconds {sum(s for _, s in work):.1f}; 1 node predicted "
                  f"{bare:.1f} s without a per-unit cost, measured {measured:.1f} s "
                  f"({(bare - measured) / measured:+.0%})"
                  f" -> {per_task:.2f} s per unit")
            print(scaling.format_table(table))
        if args.plot:
            plot(predictions, args.plot)
        print(json.dumps(dict(fixed=fixed, walls=walls, same=same, units=n,
                              predicted={h: {p.nodes: round(p.wall, 1) for p in t} for h, t in predictions.items()})))
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
