"""Warm verification (run_inputs) vs the two engines back to back, with its c/mjx/verdict seconds.

python benchmarks/scripts/verification_overhead.py humanoid 64 200 [PIECE_STEPS].
"""
import sys
import time

from mjxdiff.engine import engines
from mjxdiff.input.scenario import load_scenario, load_model
from mjxdiff.input.inputs import make_inputs
from mjxdiff.runner.sweep import SweepConfig, run_inputs
engines.configure_jax("float64")
name, B, T = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
sc = load_scenario(name)
m = load_model(sc)
inp = make_inputs(sc, m, 0, B, T)
c, x = engines.CEngine(), engines.MJXEngine()
cfg = SweepConfig(diagnose="none", piece_steps=int(sys.argv[4]) if len(sys.argv) > 4 else None)
r = run_inputs(name, m, inp, sc.tolerance, cfg, x, c)
for rep in range(3):
    t = time.perf_counter()
    c.rollout(inp)
    x.rollout(inp)
    e = time.perf_counter() - t
    t = time.perf_counter()
    r = run_inputs(name, m, inp, sc.tolerance, cfg, x, c)
    v = time.perf_counter() - t
    s = r.info["seconds"]
    print(f"engines {e:.3f}s verify {v:.3f}s ratio {e/v:.2f} |"
          f" c {s['c']:.3f} mjx {s['mjx']:.3f} verdict {s['verdict']:.3f} pieces {r.info['pieces']}", flush=True)
