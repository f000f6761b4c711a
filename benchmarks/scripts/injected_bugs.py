"""Every bug of the catalogue tests/injected_bugs.py through the one-step check and a sweep.

    python benchmarks/scripts/injected_bugs.py [--no-sweep] [BUG_ID ...]   (from the repo root)

For each model of the catalogue: the unmodified one-step ratio first. Then per bug, one line:
id, category, caught (the one-step ratio), field, object, step; and, unless --no-sweep, the
sweep's verdict with the bug applied (``run_scenario(load_scenario(model), SweepConfig(seed=0,
diagnose="basic"))``): its status, the first line of its message and ``first_divergence``.
Compiled MJX functions are cleared around every bug, so each one re-traces the patched code.
"""

import argparse
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests"))

import injected_bugs  # noqa: E402

from mjxdiff.engine import engines  # noqa: E402
from mjxdiff.compare import onestep  # noqa: E402
from mjxdiff.engine.engines import CEngine, MJXEngine  # noqa: E402
from mjxdiff.input.inputs import make_inputs  # noqa: E402
from mjxdiff.input.scenario import load_model, load_scenario  # noqa: E402
from mjxdiff.runner.sweep import SweepConfig, run_scenario  # noqa: E402

#: The one-step check's batch and horizon, as tests/test_injected_bugs.py uses them.
BATCH, STEPS = 4, 120
#: A bug is caught when its one-step ratio exceeds this (unmodified MJX stays under 0.05).
CAUGHT = 10.0


def _model(name: str, cache: dict):
    """(scenario, model, inputs, C's rollout) of a catalogue model, made once."""
    if name not in cache:
        scenario = load_scenario(str(ROOT / "tests" / "data" / name))
        m = load_model(scenario)
        inputs = make_inputs(scenario, m, seed=0, batch=BATCH, steps=STEPS)
        cache[name] = scenario, m, inputs, CEngine().rollout(inputs)
    return cache[name]


def _check(model) -> dict:
    scenario, m, inputs, traj_c = model
    return onestep.check(m, inputs, traj_c, scenario.tolerance, MJXEngine(), CEngine())


def _line(found: dict) -> str:
    caught = "CAUGHT" if found["status"] == "fail" and found["ratio"] > CAUGHT else "not caught"
    return (f"{caught} (ratio {found['ratio']:.3g}) field {found.get('field', '-')} "
            f"object {found.get('object', '-') or '-'} step {found.get('step', '-')}")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("ids", nargs="*", help="bug ids (default: all)")
    parser.add_argument("--no-sweep", action="store_true", help="the one-step check only")
    args = parser.parse_args(argv)
    engines.configure_jax("float64", str(ROOT / ".jax_cache"))
    bugs = [injected_bugs.by_id(i) for i in args.ids] if args.ids else list(injected_bugs.BUGS)
    cache: dict = {}
    missed = []
    for name in dict.fromkeys(b.model for b in bugs):
        engines.clear_compiled()
        found = _check(_model(name, cache))
        print(f"unmodified {name}: {found['status']} (ratio {found['ratio']:.3g}) "
              f"field {found.get('field', '-')} object {found.get('object', '-') or '-'}", flush=True)
    for bug in bugs:
        t = time.perf_counter()
        with pytest.MonkeyPatch.context() as mp:
            bug.patch(mp)
            engines.clear_compiled()
            try:
                found = _check(_model(bug.model, cache))
                line = _line(found)
                if not line.startswith("CAUGHT"):
                    missed.append(bug.id)
            except Exception as e:  # noqa: BLE001 - report and go on to the next bug
                line, found = f"error {type(e).__name__}: {e}", {}
                missed.append(bug.id)
            sweep = ""
            if not args.no_sweep:
                result = run_scenario(load_scenario(str(ROOT / "tests" / "data" / bug.model)),
                                      SweepConfig(seed=0, diagnose="basic"))
                first = (result.message or "").splitlines()[0] if result.message else ""
                sweep = f"\n    sweep: {result.status}: {first}\n    first_divergence: {result.first_divergence}"
        engines.clear_compiled()
        print(f"{bug.id} [{bug.category}]: {line} ({time.perf_counter() - t:.0f} s){sweep}", flush=True)
    print(f"{len(bugs) - len(missed)}/{len(bugs)} caught by the one-step check"
          + (f"; not caught: {', '.join(missed)}" if missed else ""))
    return 1 if missed else 0


if __name__ == "__main__":
    sys.exit(main())
