"""MJX steps/s split over the host devices vs one device.

python benchmarks/scripts/split_curve.py ant,humanoid STEPS 16,32,64 (run from the repo root).
"""
import sys
import time

from mjxdiff.engine import engines
from mjxdiff.input.scenario import load_scenario, load_model
from mjxdiff.input.inputs import make_inputs
engines.configure_jax("float64")
T = int(sys.argv[2])
for name in sys.argv[1].split(","):
    sc = load_scenario(name)
    m = load_model(sc)
    for b in [int(x) for x in sys.argv[3].split(",")]:
        inp = make_inputs(sc, m, 0, b, T)
        res = {}
        for label, eng in (("one", engines.MJXEngine(devices=1)), ("split", engines.MJXEngine())):
            eng.rollout(inp)
            best = min((lambda t0: (eng.rollout(inp), time.perf_counter() - t0)[1])(time.perf_counter())
                       for _ in range(3))
            res[label] = b * T / best
        print(f"{name:10s} B={b:4d} one {res['one']:8,.0f} split {res['split']:8,.0f}"
              f" ratio {res['split']/res['one']:.2f}", flush=True)
