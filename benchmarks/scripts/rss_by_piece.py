"""Resident memory piece by piece of a long ant sweep (batch 64).

python benchmarks/scripts/rss_by_piece.py CACHE_DIR STEPS EVERY [PIECE_BUDGET_MIB].
"""
import resource
import sys

from mjxdiff.engine import engines
from mjxdiff.runner import plan
from mjxdiff.compare import verdict
from mjxdiff.input.scenario import load_scenario
from mjxdiff.runner.sweep import SweepConfig, run_scenario
engines.configure_jax("float64", sys.argv[1])
if len(sys.argv) > 4:
    plan.PIECE_BUDGET_MIB = float(sys.argv[4])


def rss():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096 / 2**20


orig = verdict.Judge.update
n = [0]


def upd(self, *a, **k):
    orig(self, *a, **k)
    n[0] += 1
    if n[0] % int(sys.argv[3]) == 0:
        print(f"piece {n[0]} rss {rss():.0f} MiB peak {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss/1024:.0f}",
              flush=True)


verdict.Judge.update = upd
r = run_scenario(load_scenario("ant"), SweepConfig(batch=64, steps=int(sys.argv[2]), diagnose="none"))
print(r.status, r.info["pieces"], "peak", resource.getrusage(resource.RUSAGE_SELF).ru_maxrss/1024)
