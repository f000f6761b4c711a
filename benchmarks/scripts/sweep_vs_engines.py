"""End-to-end sweep vs the two engines alone, back to back, on the same scenarios (interleaved, best of N).
python benchmarks/scripts/sweep_vs_engines.py BATCH STEPS SCENARIO [SCENARIO ...]

engines: CEngine.rollout + MJXEngine.rollout of each scenario's inputs; verify: run_inputs on
the same inputs (both engines, C's perturbed rerun on demand, metrics, verdict); sweep: run_scenario
(also loads the model and draws the inputs)."""
import sys
import time

from mjxdiff.engine import engines
from mjxdiff.input.inputs import make_inputs
from mjxdiff.input.scenario import load_model, load_scenario
from mjxdiff.runner.sweep import SweepConfig, run_inputs, run_scenario

engines.configure_jax("float64")
B, T, names = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3:]
config = SweepConfig(batch=B, steps=T, diagnose="none")
c, x = engines.CEngine(), engines.MJXEngine()
cases = []
for name in names:
    s = load_scenario(name)
    m = load_model(s)
    cases.append((s, m, make_inputs(s, m, config.seed, B, T)))
runs = {
    "engines": lambda: [(c.rollout(i), x.rollout(i)) for _, _, i in cases],
    "verify": lambda: [run_inputs(s.name, m, i, s.tolerance, config, x, c) for s, m, i in cases],
    "sweep": lambda: [run_scenario(s, config) for s, _, _ in cases],
}
for fn in runs.values():
    fn()  # warm
times = {k: [] for k in runs}
for _ in range(int(__import__("os").environ.get("REPEATS", 5))):
    for k, fn in runs.items():
        t = time.perf_counter()
        fn()
        times[k].append(time.perf_counter() - t)
best = {k: min(v) for k, v in times.items()}
steps = len(cases) * B * T
for k, v in best.items():
    print(f"{k:8s} best {v:.3f} s  median {sorted(times[k])[len(times[k]) // 2]:.3f} s  {steps / v:,.0f} steps/s  "
          f"ratio to engines {best['engines'] / v:.2f}")
