"""How far from a false alarm is each bundled scenario? Unmodified MJX swept over many seeds in one
process (compiles shared), each scenario's worst ratio to its bound per check: the rollout (worst
field's error / tolerance or envelope), the one-step check and the converged twin where they ran.

    python benchmarks/scripts/margins.py --seeds 0:50 [--quick] [--scenarios A B ...] [--json OUT]
    python benchmarks/scripts/margins.py --merge A.json B.json ... --json OUT

Prints per scenario and check: seeds, median, 99th percentile and max ratio, and the probability
of a ratio >= 1 on one draw, from a normal in log10(ratio) fitted to the upper half of the seeds
where anything differed (:func:`p_exceed`; the tail of a few dozen draws says little on its own); the per-sweep
false-alarm estimate is one minus the product of the scenarios' chances to pass. Seeds that
fail are listed with their messages. The JSON keeps every seed's ratios (``per_seed``), so runs
over other seeds or scenarios merge (``--merge``: a later file's scenario replaces an earlier
file's for the seeds it ran).
"""
import argparse
import json
import math
import statistics
import sys
import time

from mjxdiff.engine import engines
from mjxdiff.input.scenario import bundled_scenarios, load_scenario
from mjxdiff.runner.sweep import SweepConfig, sweep


def _judged(result) -> list:
    """``result``'s fields that have a finite ratio to their bound."""
    return [f for f in result.fields if f.ratio is not None and math.isfinite(f.ratio)]


def ratios(result) -> dict[str, float]:
    """check -> worst ratio to its bound, for the checks that ran on ``result``."""
    out = {}
    fields = [f.ratio for f in _judged(result)]
    if fields:
        out["rollout"] = max(fields)
    for check in ("onestep", "twin"):
        found = result.info.get(check) or {}
        ratio = found.get("ratio") if check == "onestep" else (found.get("worst") or {}).get("ratio")
        if isinstance(ratio, (int, float)) and math.isfinite(ratio):
            out[check] = float(ratio)
    return out


def p_exceed(values: list[float]) -> float:
    """P(ratio >= 1) on one draw: the share of draws where anything differed (ratio > 0) times the
    chance that such a draw reaches 1, from a normal in log10(ratio) over those draws' upper half:
    centred on their median and scaled by the spread from the median to the largest of the k
    draws, which for a normal is about the quantile 1 - 1/(k + 1). The tail is where a false alarm
    comes from; draws where MJX and C agreed to the bit (ratio 0: energy_flag's one-step check on 9
    of 50 seeds) do not widen it, as they did where the median itself was 0 (in the 20-seed table of
    2026-11-27 a log10 of 1e-300 put gravcomp_arm's 0.14 at 0.03 per draw), nor does a ratio at
    rounding level (energy_flag's one-step check, at most 7e-12, came out at 0.32 from a fit to
    every value). Under 3 differing draws, the spread is taken as one decade about the largest."""
    if len(values) < 3:
        return float("nan")
    differing = sorted(v for v in values if v > 0)
    if not differing:
        return 0.0
    k = len(differing)
    if k < 3:
        conditional = 1 - statistics.NormalDist(math.log10(differing[-1]), 1.0).cdf(0.0)
    else:
        conditional = p_exceed_from(statistics.median(differing), differing[-1], k)
    return k / len(values) * conditional


def p_exceed_from(median: float, largest: float, n: int) -> float:
    """P(ratio >= 1) on one draw of a normal in log10(ratio) centred on ``median`` whose largest of
    ``n`` draws is ``largest``."""
    mu = math.log10(max(median, 1e-300))
    sd = max((math.log10(max(largest, 1e-300)) - mu) / statistics.NormalDist().inv_cdf(1 - 1 / (n + 1)), 1e-3)
    return 1 - statistics.NormalDist(mu, sd).cdf(0.0)


def worst_field(result) -> str | None:
    """``field object`` of ``result``'s field with the largest ratio to its bound (None where none has one)."""
    fields = _judged(result)
    worst = max(fields, key=lambda f: f.ratio) if fields else None
    return worst and f"{worst.field} {worst.object}"


def summarize(table: dict) -> dict:
    rows = {}
    for name, per_seed in table.items():
        for check in sorted({c for r in per_seed.values() for c in r["ratios"]}):
            values = sorted(r["ratios"][check] for r in per_seed.values() if check in r["ratios"])
            q99 = values[min(len(values) - 1, math.ceil(0.99 * len(values)) - 1)]
            rows[f"{name} {check}"] = dict(seeds=len(values), differing=sum(v > 0 for v in values),
                                           median=statistics.median(values), p99=q99, max=values[-1],
                                           p_exceed=p_exceed(values))
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="0:50", help="FIRST:END (END excluded)")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--scenarios", nargs="*")
    parser.add_argument("--json")
    parser.add_argument("--merge", nargs="+", metavar="JSON", help="summarize these runs' seeds, no sweep")
    a = parser.parse_args()
    if a.merge:
        return report(*merged(a.merge), a.json)
    engines.configure_jax("float64", None)
    first, end = map(int, a.seeds.split(":"))
    scenarios = [load_scenario(n) for n in a.scenarios] if a.scenarios else bundled_scenarios()
    table: dict = {s.name: {} for s in scenarios}
    failures = []
    for seed in range(first, end):
        t = time.perf_counter()
        for r in sweep(scenarios, SweepConfig(seed=seed, quick=a.quick), progress=False):
            table[r.name][seed] = dict(status=r.status, ratios=ratios(r), worst=worst_field(r))
            if r.status not in ("pass", "unsupported"):
                failures.append(dict(seed=seed, name=r.name, status=r.status, message=r.message[:400]))
        print(f"seed {seed}: {time.perf_counter() - t:.1f} s, failures so far {len(failures)}", file=sys.stderr,
              flush=True)
    return report(table, failures, [first, end], a.quick, a.json)


def merged(paths: list[str]) -> tuple[dict, list, list[int], bool]:
    """The per-seed table, failures, seed range and quick flag of the runs in ``paths``, merged."""
    table: dict = {}
    failures: list = []
    first, end, quick = math.inf, -math.inf, False
    for path in paths:
        with open(path) as f:
            data = json.load(f)
        for name, per_seed in data["per_seed"].items():
            table.setdefault(name, {}).update({int(k): v for k, v in per_seed.items()})
            failures = [x for x in failures if not (x["name"] == name and str(x["seed"]) in per_seed)]
        failures += data["failures"]
        first, end, quick = min(first, data["seeds"][0]), max(end, data["seeds"][1]), quick or data["quick"]
    return table, failures, [int(first), int(end)], quick


def report(table: dict, failures: list, seeds: list[int], quick: bool, out: str | None) -> int:
    """Prints the summary of ``table`` and writes it, with every seed's ratios, to ``out``."""
    rows = summarize(table)
    p_pass = math.prod(1 - r["p_exceed"] for r in rows.values() if math.isfinite(r["p_exceed"]))
    for key, r in rows.items():
        print(f"{key:40s} {r['seeds']:3d} seeds  median {r['median']:.3g}  p99 {r['p99']:.3g}  max {r['max']:.3g}"
              f"  P(>=1) {r['p_exceed']:.1e}")
    print(f"per-sweep false-alarm estimate: {1 - p_pass:.2e}; failures: {len(failures)}")
    for f in failures:
        print(f"  seed {f['seed']} {f['name']} {f['status']}: {f['message']}")
    if out:
        with open(out, "w") as f:
            json.dump(dict(seeds=seeds, quick=quick, rows=rows, failures=failures, per_sweep_false_alarm=1 - p_pass,
                           per_seed=table), f, indent=1, sort_keys=True)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
