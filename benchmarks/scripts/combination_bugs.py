"""Sweeps every bug of tests/combination_bugs.py: caught by which scenario, at which field and step.

    python benchmarks/scripts/combination_bugs.py [--scenarios A,B,...] [--seed N] [--out FILE] [BUG_ID ...]

For each bug (each visible only under a combination of two conditions, stated in its
``COMBINATIONS`` entry), the bundled scenarios (or ``--scenarios``) are swept in process with the
bug patched into MJX (``run_scenario(s, SweepConfig(seed, diagnose="basic"))``, the default
sweep's verdict without the cause-finding reruns), stopping at the first scenario that does not
pass: the bug is caught there. Unmodified MJX is swept first; every scenario must pass.

To measure the sweep of another revision on the same bugs, run this file with that revision's
package and scenarios first on the path (the catalogue is read from this file's tree)::

    git worktree add /tmp/old REV
    MJXDIFF_SCENARIOS=/tmp/old/scenarios PYTHONPATH=/tmp/old python benchmarks/scripts/combination_bugs.py
"""

import argparse
import json
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests"))

import combination_bugs  # noqa: E402

from mjxdiff.engine import engines  # noqa: E402
from mjxdiff.input.scenario import bundled_scenarios  # noqa: E402
from mjxdiff.runner.sweep import SweepConfig, run_scenario  # noqa: E402


#: Verdicts that catch a bug (``unsupported`` is the unmodified verdict of unsupported_pair).
CAUGHT = ("fail", "error")


def _sweep(scenarios, config: SweepConfig, stop: bool) -> list[dict]:
    out = []
    for s in scenarios:
        t = time.perf_counter()
        r = run_scenario(s, config)
        fd = r.first_divergence or {}
        out.append(dict(scenario=s.name, status=r.status, message=r.message.splitlines()[0][:300],
                        field=fd.get("field"), step=fd.get("step"), seconds=round(time.perf_counter() - t, 1)))
        if stop and r.status in CAUGHT:
            break
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("ids", nargs="*", help="bug ids (default: all)")
    parser.add_argument("--scenarios", help="comma-separated bundled scenario names (default: all)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-baseline", action="store_true", help="skip the unmodified sweep")
    parser.add_argument("--out", help="append one JSON line per bug to this file")
    args = parser.parse_args(argv)
    engines.configure_jax("float64", None)
    names = args.scenarios.split(",") if args.scenarios else None
    scenarios = [s for s in bundled_scenarios() if names is None or s.name in names]
    config = SweepConfig(seed=args.seed, diagnose="basic")
    bugs = [combination_bugs.by_id(i) for i in args.ids] if args.ids else list(combination_bugs.BUGS)
    missed = []
    if not args.no_baseline:
        engines.clear_compiled()
        base = _sweep(scenarios, config, stop=False)
        bad = [b for b in base if b["status"] in CAUGHT]
        print(f"unmodified: {len(base) - len(bad)}/{len(base)} pass or unsupported" + "".join(
            f"\n  {b['scenario']}: {b['status']} {b['message']}" for b in bad), flush=True)
    for bug in bugs:
        t = time.perf_counter()
        with pytest.MonkeyPatch.context() as mp:
            bug.patch(mp)
            engines.clear_compiled()
            runs = _sweep(scenarios, config, stop=True)
        engines.clear_compiled()
        caught = runs[-1] if runs and runs[-1]["status"] in CAUGHT else None
        if caught is None:
            missed.append(bug.id)
        a, b = combination_bugs.COMBINATIONS[bug.id]
        where = (f"CAUGHT by {caught['scenario']} ({caught['status']}): {caught['field']} step {caught['step']}"
                 if caught else f"not caught ({len(runs)} scenarios pass)")
        print(f"{bug.id} [{a} x {b}]: {where} ({time.perf_counter() - t:.0f} s)", flush=True)
        if args.out:
            with open(args.out, "a") as f:
                f.write(json.dumps(dict(bug=bug.id, combination=[a, b], seed=args.seed, caught=caught is not None,
                                        runs=runs)) + "\n")
    print(f"caught {len(bugs) - len(missed)} of {len(bugs)}" + (f"; missed: {', '.join(missed)}" if missed else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
