"""64 variants of one model: compiles per precision and compile seconds.

python benchmarks/scripts/compile_once.py CACHE_DIR SCENARIO (run twice: cold, then warm).
"""
import json
import sys
import time

from mjxdiff.engine import engines
from mjxdiff.input.scenario import load_scenario
from mjxdiff.runner.sweep import SweepConfig, run_scenario
cache = sys.argv[1]
name = sys.argv[2]
engines.configure_jax("float64", cache)
out = {}
for precision in ("float64", "float32"):
    engines.configure_jax(precision, cache)
    c0, s0, t0 = engines.compile_count(), engines.compile_seconds(), time.perf_counter()
    r = run_scenario(load_scenario(name), SweepConfig(batch=64, steps=100, precision=precision))
    out[precision] = dict(status=r.status, mjx_compiles=r.info["mjx_compiles"], mjx_loaded=r.info["mjx_loaded"],
                          compile_s=engines.compile_seconds() - s0, wall_s=time.perf_counter() - t0)
print(json.dumps(out))
