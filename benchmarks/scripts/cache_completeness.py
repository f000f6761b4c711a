"""Is the artifact cache's key complete? Every bundled scenario's rollout traced under
``sys.settrace``: the MJX and mjxdiff code objects it ran, and those its artifact's key would
miss (:func:`mjxdiff.engine.export_cache.audit`). Exits 1 if any key misses code its trace ran.

    python benchmarks/scripts/cache_completeness.py [SCENARIO ...] [--json OUT]
"""
import argparse
import json
import sys
import time

from mjxdiff.engine import engines, export_cache
from mjxdiff.input.adjust import for_mjx
from mjxdiff.input.inputs import make_inputs
from mjxdiff.input.scenario import bundled_scenarios, load_model, load_scenario


def audit(name: str) -> dict:
    scenario = load_scenario(name)
    m, _ = for_mjx(load_model(scenario), scenario.model_path)
    inputs = make_inputs(scenario, m, seed=0, batch=2, steps=4)
    start = time.perf_counter()
    try:
        (fn, args, static), _, _ = engines.MJXEngine(devices=1).piece(inputs, 4)
    except engines.UnsupportedError as e:
        return dict(status="unsupported", why=str(e)[:120])
    ran, missing, deps = export_cache.audit(fn, args, static)
    return dict(status="saved" if isinstance(deps, dict) else deps, missing=missing, ran=ran,
                dependencies=len(deps) if isinstance(deps, dict) else 0, seconds=round(time.perf_counter() - start, 2))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenarios", nargs="*")
    parser.add_argument("--json", help="write the table here too")
    a = parser.parse_args()
    engines.configure_jax("float64", None)
    names = a.scenarios or [s.name for s in bundled_scenarios()]
    table = {}
    for name in names:
        table[name] = row = audit(name)
        print(f"{name:28s} {row['status']:12s} deps {row.get('dependencies', '-'):>4} "
              f"{row.get('seconds', '-'):>6} s  missing {len(row.get('missing', []))} {row.get('missing', [])[:4]}",
              flush=True)
    if a.json:
        with open(a.json, "w") as f:
            json.dump(table, f, indent=1, sort_keys=True)
    cover = covering(table)
    print(f"{len(cover)} scenarios run every traced function any of the {len(table)} runs: {' '.join(cover)}")
    return 1 if any(row.get("missing") for row in table.values()) else 0


def covering(table: dict) -> list[str]:
    """A small set of scenarios (greedy set cover) whose traces run every MJX and mjxdiff code
    object (file:qualname) that any scenario of ``table`` runs."""
    left = set().union(*(row.get("ran", []) for row in table.values()))
    chosen = []
    while left:
        best = max(sorted(table), key=lambda n: len(left & set(table[n].get("ran", []))))
        chosen.append(best)
        left -= set(table[best]["ran"])
    return sorted(chosen)


if __name__ == "__main__":
    sys.exit(main())
