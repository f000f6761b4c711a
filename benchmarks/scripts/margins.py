"""How far from a false alarm is each bundled scenario? Unmodified MJX swept over many seeds in one
process (compiles shared), each scenario's worst ratio to its bound per check: the rollout (worst
field's error / tolerance or envelope), the one-step check and the converged twin where they ran.

    python benchmarks/scripts/margins.py --seeds 0:50 [--quick] [--scenarios A B ...] [--json OUT]

Prints per scenario and check: seeds, median, 99th percentile and max ratio, and the probability
of a ratio >= 1 on one draw, from a normal in log10(ratio) fitted to the upper half of the seeds
(:func:`p_exceed`; the tail of a few dozen draws says little on its own); the per-sweep
false-alarm estimate is one minus the product of the scenarios' chances to pass. Seeds that
fail are listed with their messages.
"""
import argparse
import json
import math
import statistics
import sys
import time

from mjxdiff import engines
from mjxdiff.scenario import bundled_scenarios, load_scenario
from mjxdiff.sweep import SweepConfig, sweep


def ratios(result) -> dict[str, float]:
    """check -> worst ratio to its bound, for the checks that ran on ``result``."""
    out = {}
    fields = [f.ratio for f in result.fields if f.ratio is not None and math.isfinite(f.ratio)]
    if fields:
        out["rollout"] = max(fields)
    for check in ("onestep", "twin"):
        found = result.info.get(check) or {}
        ratio = found.get("ratio") if check == "onestep" else (found.get("worst") or {}).get("ratio")
        if isinstance(ratio, (int, float)) and math.isfinite(ratio):
            out[check] = float(ratio)
    return out


def p_exceed(values: list[float]) -> float:
    """P(ratio >= 1) on one draw, from the upper half of ``values``: a normal in log10(ratio)
    centred on the median and scaled by the spread from the median to the largest of the n
    draws, which for a normal is about the quantile 1 - 1/(n + 1). The tail is where a false alarm
    comes from; a ratio of 0 (nothing differed) or at rounding level does not widen it, as it did
    a fit to every value (energy_flag's one-step check, at most 7e-12, came out at 0.32)."""
    if len(values) < 3:
        return float("nan")
    values = sorted(values)
    return p_exceed_from(statistics.median(values), values[-1], len(values))


def p_exceed_from(median: float, largest: float, n: int) -> float:
    """:func:`p_exceed` from a row's median, max and number of seeds."""
    mu = math.log10(max(median, 1e-300))
    sd = max((math.log10(max(largest, 1e-300)) - mu) / statistics.NormalDist().inv_cdf(1 - 1 / (n + 1)), 1e-3)
    return 1 - statistics.NormalDist(mu, sd).cdf(0.0)


def summarize(table: dict) -> dict:
    rows = {}
    for name, per_seed in table.items():
        for check in sorted({c for r in per_seed.values() for c in r["ratios"]}):
            values = sorted(r["ratios"][check] for r in per_seed.values() if check in r["ratios"])
            q99 = values[min(len(values) - 1, math.ceil(0.99 * len(values)) - 1)]
            rows[f"{name} {check}"] = dict(seeds=len(values), median=statistics.median(values), p99=q99,
                                           max=values[-1], p_exceed=p_exceed(values))
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="0:50", help="FIRST:END (END excluded)")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--scenarios", nargs="*")
    parser.add_argument("--json")
    a = parser.parse_args()
    engines.configure_jax("float64", None)
    first, end = map(int, a.seeds.split(":"))
    scenarios = [load_scenario(n) for n in a.scenarios] if a.scenarios else bundled_scenarios()
    table: dict = {s.name: {} for s in scenarios}
    failures = []
    for seed in range(first, end):
        t = time.perf_counter()
        for r in sweep(scenarios, SweepConfig(seed=seed, quick=a.quick), progress=False):
            table[r.name][seed] = dict(status=r.status, ratios=ratios(r))
            if r.status not in ("pass", "unsupported"):
                failures.append(dict(seed=seed, name=r.name, status=r.status, message=r.message[:400]))
        print(f"seed {seed}: {time.perf_counter() - t:.1f} s, failures so far {len(failures)}", file=sys.stderr,
              flush=True)
    rows = summarize(table)
    p_pass = math.prod(1 - r["p_exceed"] for r in rows.values() if math.isfinite(r["p_exceed"]))
    for key, r in rows.items():
        print(f"{key:40s} {r['seeds']:3d} seeds  median {r['median']:.3g}  p99 {r['p99']:.3g}  max {r['max']:.3g}"
              f"  P(>=1) {r['p_exceed']:.1e}")
    print(f"per-sweep false-alarm estimate: {1 - p_pass:.2e}; failures: {len(failures)}")
    for f in failures:
        print(f"  seed {f['seed']} {f['name']} {f['status']}: {f['message']}")
    if a.json:
        with open(a.json, "w") as f:
            json.dump(dict(seeds=[first, end], quick=a.quick, rows=rows, failures=failures,
                           per_sweep_false_alarm=1 - p_pass), f, indent=1, sort_keys=True)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
