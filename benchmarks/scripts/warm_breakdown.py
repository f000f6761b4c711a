"""Compile seconds of one ant sweep (batch 64, 100 steps) by JAX event: trace, lowering, XLA compile or cache load.

python benchmarks/scripts/warm_breakdown.py CACHE_DIR (run after compile_once.py has warmed CACHE_DIR).
"""
import sys
import time

import jax

from mjxdiff.engine import engines
from mjxdiff.input.scenario import load_scenario
from mjxdiff.runner.sweep import SweepConfig, run_scenario
engines.configure_jax("float64", sys.argv[1])
events = []
jax.monitoring.register_event_duration_secs_listener(lambda e, d, **k: events.append((e.split("/")[-1], d, k)))
t = time.perf_counter()
r = run_scenario(load_scenario("ant"), SweepConfig(batch=64, steps=100))
tot = {}
for e, d, k in events:
    if e in ("jaxpr_trace_duration", "jaxpr_to_mlir_module_duration", "backend_compile_duration"):
        tot.setdefault(e, []).append(d)
for e, ds in tot.items():
    print(e, len(ds), round(sum(ds), 2), "top", [round(x, 2) for x in sorted(ds)[-5:]])
print("compile total", round(sum(sum(d) for d in tot.values()), 2), "wall", round(time.perf_counter() - t, 1))
