"""Peak RSS of one scenario sweep.

python benchmarks/scripts/peak_memory.py CACHE_DIR SCENARIO BATCH STEPS (run from the repo root).
"""
import resource
import sys
import time

from mjxdiff.engine import engines
from mjxdiff.input.scenario import load_scenario
from mjxdiff.runner.sweep import SweepConfig, run_scenario
engines.configure_jax("float64", sys.argv[1])
name, batch, steps = sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
t = time.perf_counter()
r = run_scenario(load_scenario(name), SweepConfig(batch=batch, steps=steps, diagnose="none"))
print(f"{name} batch {batch} steps {steps}: {r.status}"
      f" peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss/1024:.0f} MiB, {time.perf_counter()-t:.1f} s")
