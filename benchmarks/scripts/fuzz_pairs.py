"""Interaction pairs per minute of a fuzzing run, for this revision or an older one.

    python benchmarks/scripts/fuzz_pairs.py --seed 0 --budget 120 [--out FILE]

Runs ``mjxdiff.tools.fuzz.fuzz`` and reads the interaction pairs (``mjxdiff.tools.interactions``, always
this file's tree) of every batch it generates, by wrapping ``fuzz.variants``: the same measure
for a revision whose fuzzer neither reports pairs nor aims at them (run with that revision's
package first on the path: ``PYTHONPATH=/tmp/old python benchmarks/scripts/fuzz_pairs.py``).
Prints the verdict, the pairwise coverage and the pairs per minute.
"""

import argparse
import importlib.util
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
_spec = importlib.util.spec_from_file_location("pairs_model", ROOT / "mjxdiff" / "tools" / "interactions.py")
interactions = importlib.util.module_from_spec(_spec)
sys.modules[_spec.name] = interactions  # its dataclasses look their module up
_spec.loader.exec_module(interactions)

from mjxdiff.engine import engines  # noqa: E402
from mjxdiff.tools import fuzz as fuzz_module  # noqa: E402


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--budget", type=float, default=120.0)
    parser.add_argument("--out", help="append one JSON line to this file")
    args = parser.parse_args(argv)
    engines.configure_jax("float64", None)
    first: dict = {}
    t0 = time.perf_counter()
    variants = fuzz_module.variants

    def recording(*a, **k):
        inputs = variants(*a, **k)
        now = time.perf_counter() - t0
        for p in interactions.member_pairs(inputs, max_members=4, max_steps=inputs.steps):
            first.setdefault(p, now)
        return inputs

    fuzz_module.variants = recording
    result = fuzz_module.fuzz(seed=args.seed, budget=args.budget, database=f"/tmp/fuzz_pairs_db_{args.seed}_{t0}")
    doc = interactions.pairwise({p: ("fuzz",) for p in first})
    minutes = result.seconds / 60
    verdict = "harness error: " + result.harness_error if result.harness_error else (
        "DIVERGENCE: " + result.failure["message"] if result.failure else "no divergence")
    print(f"seed {args.seed}: {verdict}; {result.structures} models, {result.seconds:.0f} s")
    print(interactions.format_text(doc, "interaction pairs generated").splitlines()[0]
          + f"; {len(first) / minutes:.0f} per minute")
    if args.out:
        with open(args.out, "a") as f:
            f.write(json.dumps(dict(seed=args.seed, budget=args.budget, verdict=verdict, structures=result.structures,
                                    seconds=result.seconds, percent=doc["percent"], covered=doc["covered"],
                                    feasible=doc["feasible"], per_minute=len(first) / minutes,
                                    groups=doc["groups"])) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
