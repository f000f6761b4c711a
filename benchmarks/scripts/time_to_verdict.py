"""Time to verdict, the cold cases that need a fresh cache directory: a cold and a warm default
sweep, and a fuzz run, each a fresh ``python -m mjxdiff`` process.

    python benchmarks/scripts/time_to_verdict.py [--fuzz-budget 60] [--only cold,warm,fuzz] [-- SWEEP ARGS]

Prints one JSON line per run: wall seconds, CPU seconds of the process and its children, cores
in use on average ((user + sys) / wall), the report's compile seconds, seconds per scenario, and
for fuzz the examples and structures per minute. Runs alone on the machine give comparable numbers.
"""

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def _run(argv: list[str]) -> dict:
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "mjxdiff", *argv], capture_output=True, text=True)
    wall = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return dict(rc=proc.returncode, wall_s=round(wall, 1), cpu_s=round(cpu, 1), cores=round(cpu / wall, 2),
                last_line=(proc.stdout.strip().splitlines() or [""])[-1])


def sweep(cache: Path, out: Path, extra: list[str]) -> dict:
    result = _run(["sweep", "--cache-dir", str(cache), "--out", str(out), *extra])
    report = json.loads((out / "report.json").read_text())
    summary = report["summary"]
    n = summary["total"]
    return dict(result, scenarios=n, seconds_per_scenario=round(result["wall_s"] / n, 2),
                compile_seconds=round(summary["compile_seconds"], 1), mjx_compiles=summary["mjx_compiles"],
                mjx_loaded=summary["mjx_loaded"], verdict=summary["verdict"])


def fuzz(cache: Path, out: Path, budget: float) -> dict:
    result = _run(["fuzz", "--budget", str(budget), "--seed", "0", "--cache-dir", str(cache), "--out", str(out)])
    doc = json.loads((out / "fuzz-report.json").read_text())
    return dict(result, examples=doc["examples"], structures=doc.get("structures"),
                examples_per_minute=round(doc["examples"] / doc["seconds"] * 60, 1),
                structures_per_minute=round(doc.get("structures", doc["examples"]) / doc["seconds"] * 60, 1))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", default="cold,warm,fuzz")
    parser.add_argument("--fuzz-budget", type=float, default=60.0)
    parser.add_argument("sweep_args", nargs="*")
    args = parser.parse_args()
    only = args.only.split(",")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        cache = tmp / "cache"
        if "cold" in only or "warm" in only:
            print(json.dumps(dict(run="cold sweep", **sweep(cache, tmp / "cold", args.sweep_args))), flush=True)
        if "warm" in only:
            print(json.dumps(dict(run="warm sweep", **sweep(cache, tmp / "warm", args.sweep_args))), flush=True)
        if "fuzz" in only:
            print(json.dumps(dict(run="fuzz", budget_s=args.fuzz_budget,
                                  **fuzz(tmp / "fuzz-cache", tmp / "fuzz", args.fuzz_budget))), flush=True)


if __name__ == "__main__":
    os.environ.pop("MJXDIFF_CACHE", None)
    main()
