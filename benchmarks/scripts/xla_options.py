"""Compile seconds and stepping speed of MJX rollouts under XLA's option sets, and how far
their results are from XLA's defaults (the numbers behind ``mjxdiff.engine.xla.xla_options``).

    python benchmarks/scripts/xla_options.py [SCENARIOS] [BATCH] [STEPS]
    (default: ant,humanoid,box_stack,primitive_pairs 8 200)

Each scenario's rollout is traced once (``jax.export``) and compiled ahead of time under each
option set with the persistent cache off; one JSON line per (scenario, option set) with
compile_s, steps_per_s (member-steps per second, best of 3) and max_rel_diff (largest
|x - x_default| / (1 + |x_default|) over the float outputs).
"""

import json
import sys
import time

from mjxdiff.engine.engines import configure_jax

configure_jax("float64", cache_dir="")

import jax  # noqa: E402
import numpy as np  # noqa: E402

from mjxdiff.engine import engines, export_cache  # noqa: E402
from mjxdiff.engine.engines import MJXEngine, _rollout  # noqa: E402
from mjxdiff.input.inputs import make_inputs  # noqa: E402
from mjxdiff.input.scenario import load_model, load_scenario  # noqa: E402

OPTION_SETS = {
    "xla defaults": {},
    "level 0": {"xla_backend_optimization_level": 0},
    "balanced (level 1, classic emitters)": engines.BALANCED_COMPILE,
    "fast (level 0, classic emitters)": engines.FAST_COMPILE,
}


def exported(name: str, batch: int, steps: int):
    scenario = load_scenario(name)
    inputs = make_inputs(scenario, load_model(scenario), 0, batch, steps)
    mx, varying, dx0, place, mesh = MJXEngine()._prepare(inputs)
    dx = jax.tree.map(lambda x: np.broadcast_to(np.asarray(x), (batch, *x.shape)), jax.device_get(dx0))
    dx = place(dx.replace(qpos=np.asarray(inputs.qpos), qvel=np.asarray(inputs.qvel), act=np.asarray(inputs.act)))
    leaves, treedef = jax.tree.flatten((mx, dx, place(np.asarray(inputs.ctrl))))
    t = time.perf_counter()
    _, exp = export_cache._export(_rollout, treedef, leaves, dict(varying=varying, with_energy=False, mesh=mesh))
    return exp, leaves, time.perf_counter() - t


def main() -> None:
    names = (sys.argv[1] if len(sys.argv) > 1 else "ant,humanoid,box_stack,primitive_pairs").split(",")
    batch = int(sys.argv[2]) if len(sys.argv) > 2 else 8
    steps = int(sys.argv[3]) if len(sys.argv) > 3 else 200
    for name in names:
        exp, leaves, trace = exported(name, batch, steps)
        reference = None
        for label, options in OPTION_SETS.items():
            lowered = jax.jit(exp.call).lower(*leaves)
            t = time.perf_counter()
            compiled = lowered.compile(compiler_options=dict(options) or None)
            compile_s = time.perf_counter() - t
            jax.block_until_ready(compiled(*leaves))
            best = float("inf")
            for _ in range(3):
                t = time.perf_counter()
                out = jax.block_until_ready(compiled(*leaves))
                best = min(best, time.perf_counter() - t)
            flat = [np.asarray(x) for x in jax.tree.leaves(out) if np.asarray(x).dtype.kind == "f"]
            reference = reference or flat
            diff = max((float(np.max(np.abs(a - b) / (1 + np.abs(b)))) for a, b in zip(flat, reference) if a.size),
                       default=0.0)
            print(json.dumps(dict(scenario=name, options=label, batch=batch, steps=steps, trace_s=round(trace, 2),
                                  compile_s=round(compile_s, 2), steps_per_s=round(batch * steps / best),
                                  max_rel_diff=diff)), flush=True)


if __name__ == "__main__":
    main()
