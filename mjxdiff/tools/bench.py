"""Platform performance: MJX and MuJoCo C on the same batch, horizon and cores.

For each scenario, :func:`bench_scenario` measures

* steps/s of each engine (member-steps, batch x horizon, per second of wall
  time; best of ``repeats`` warm runs), for several batch sizes (a small
  throughput curve), and their ratio MJX/C;
* MJX compile seconds (first call minus a warm run) and what that first call
  did: ``compiled`` (traced and compiled), ``loaded`` (a saved rollout from the
  persistent cache: then the seconds are loading, not compiling) or ``warm``
  (already in memory);
* peak memory of each side: the largest rise of the process's resident set
  over its value when the rollout started, sampled every 5 ms, MiB;
* CPU utilisation of each side: process CPU time / (wall time x cores);
* the speedup of MJX's batch split over host devices against one device;
* the tester's own cost: a warm :func:`mjxdiff.runner.sweep.run_inputs` (both
  engines, noise floor on demand and always, metrics, verdict) against the
  two engines alone;
* where MuJoCo Warp is installed (``mjxdiff[warp]``), its steps/s on the same batches, CPU,
  memory and the first call's extra seconds (kernels compiled, or loaded from Warp's cache).

:func:`recommendations` turns those numbers into plain-language advice.
"""

from __future__ import annotations

import dataclasses
import os
import threading
import time
from typing import Any, Callable, Sequence

from mjxdiff.engine import export_cache
from mjxdiff.engine.engines import SPLIT_MIN_MEMBERS, CEngine, MJXEngine, compile_count, device_count
from mjxdiff.input.inputs import BatchedInputs, make_inputs
from mjxdiff.input.options import NoiseFloor
from mjxdiff.input.scenario import Scenario, load_model
from mjxdiff.runner.sweep import SweepConfig, run_inputs

__all__ = ["DEFAULT_BATCHES", "Measurement", "bench_scenario", "format_text", "measure", "recommendations"]

#: Batch sizes of the throughput curve.
DEFAULT_BATCHES = (8, 32, 128)


def _rss_mib() -> float:
    """Resident set size of this process, MiB (Linux ``/proc``; peak RSS elsewhere)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except OSError:
        import resource

        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


@dataclasses.dataclass(frozen=True)
class Measurement:
    """One timed call: wall seconds, CPU utilisation (0-1 of all cores), peak RSS rise (MiB)."""

    seconds: float
    cpu: float
    peak_mib: float


def measure(fn: Callable[[], Any], interval: float = 0.005) -> tuple[Any, Measurement]:
    """Calls ``fn()`` and returns its result with wall time, CPU utilisation and peak RSS rise."""
    base = peak = _rss_mib()
    done = threading.Event()

    def sample() -> None:
        nonlocal peak
        while not done.wait(interval):
            peak = max(peak, _rss_mib())

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    cpu0, t0 = time.process_time(), time.perf_counter()
    try:
        out = fn()
    finally:
        wall, cpu = time.perf_counter() - t0, time.process_time() - cpu0
        done.set()
        sampler.join()
    peak = max(peak, _rss_mib())
    return out, Measurement(wall, cpu / max(wall, 1e-9) / (os.cpu_count() or 1), peak - base)


def _best(fn: Callable[[], Any], repeats: int) -> Measurement:
    """The fastest of ``repeats`` warm calls (peak memory: the largest seen)."""
    runs = [measure(fn)[1] for _ in range(repeats)]
    fastest = min(runs, key=lambda r: r.seconds)
    return dataclasses.replace(fastest, peak_mib=max(r.peak_mib for r in runs))


def _point(inputs: BatchedInputs, repeats: int) -> dict[str, Any]:
    """Both engines on one batch: steps/s, CPU, memory, MJX compile seconds."""
    c_engine, under_test = CEngine(), MJXEngine()
    steps = inputs.batch * inputs.steps
    compiles, loaded = compile_count(), export_cache.loaded_count()
    _, first = measure(lambda: under_test.rollout(inputs))
    first_call = ("compiled" if compile_count() > compiles else
                  "loaded" if export_cache.loaded_count() > loaded else "warm")
    mjx = _best(lambda: under_test.rollout(inputs), repeats)
    c = _best(lambda: c_engine.rollout(inputs), repeats)
    out = dict(batch=inputs.batch, steps=inputs.steps,
               c_steps_per_s=steps / c.seconds, mjx_steps_per_s=steps / mjx.seconds,
               mjx_over_c=c.seconds / mjx.seconds, compile_s=max(first.seconds - mjx.seconds, 0.0),
               first_call=first_call,
               c_cpu=c.cpu, mjx_cpu=mjx.cpu, c_peak_mib=c.peak_mib, mjx_peak_mib=max(mjx.peak_mib, first.peak_mib))
    return dict(out, **_warp_point(inputs, repeats))


def _warp_point(inputs: BatchedInputs, repeats: int) -> dict[str, Any]:
    """MuJoCo Warp on the same batch, where it is installed: steps/s, CPU, memory, and the first
    call's extra seconds (its kernels compiled, or loaded from Warp's cache)."""
    from mjxdiff.engine import mjwarp

    if mjwarp.available() is not None:
        return {}
    engine = mjwarp.MJWarpEngine()
    _, first = measure(lambda: engine.rollout(inputs))
    warm = _best(lambda: engine.rollout(inputs), repeats)
    return dict(warp_steps_per_s=inputs.batch * inputs.steps / warm.seconds,
                warp_first_s=max(first.seconds - warm.seconds, 0.0), warp_cpu=warm.cpu,
                warp_peak_mib=max(warm.peak_mib, first.peak_mib))


def bench_scenario(scenario: Scenario, batches: Sequence[int] = DEFAULT_BATCHES, steps: int = 200,
                   seed: int = 0, repeats: int = 2,
                   progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Measures one scenario; see the module docstring for what.

    Returns:
      A JSON-ready dict: ``curve`` (one entry per batch size), ``best`` (the
      entry with the highest MJX steps/s), ``split`` (MJX steps/s at the best
      batch on one device and on the devices MJXEngine splits it over),
      ``tester`` (seconds of the engines alone and of a warm verification,
      and their ratio), and ``recommendations``.
    """
    say = progress or (lambda _: None)
    m = load_model(scenario)
    full = make_inputs(scenario, m, seed, max(batches), steps)
    curve = []
    for b in sorted(batches):
        say(f"{scenario.name}: batch {b}")
        curve.append(_point(full.take(slice(b)), repeats))
    best = max(curve, key=lambda p: p["mjx_steps_per_s"])
    inputs = full.take(slice(best["batch"]))
    split: dict[str, float] = dict(devices=MJXEngine().split(inputs.batch), steps_per_s=best["mjx_steps_per_s"])
    if split["devices"] > 1:
        say(f"{scenario.name}: batch {best['batch']} on one device")
        single = MJXEngine(devices=1)
        single.rollout(inputs)
        one = _best(lambda: single.rollout(inputs), repeats)
        split.update(one_device_steps_per_s=inputs.batch * inputs.steps / one.seconds,
                     speedup=best["mjx_steps_per_s"] * one.seconds / (inputs.batch * inputs.steps))
    say(f"{scenario.name}: verification overhead at batch {best['batch']}")
    tester = _tester_overhead(scenario, m, inputs, repeats)
    out = dict(scenario=scenario.name, nq=m.nq, nv=m.nv, nu=m.nu, curve=curve, best=best, split=split,
               tester=tester)
    out["recommendations"] = recommendations(out)
    return out


def _tester_overhead(scenario: Scenario, m, inputs: BatchedInputs, repeats: int) -> dict[str, float]:
    """Warm seconds of the two engines back to back, and of a whole verification of the same inputs
    with the noise floor's perturbed rerun on demand (the default) and always.

    The three are interleaved, best of ``max(repeats, 5)``, so that a slow spell of the machine
    hits all of them; CPU seconds of the fastest runs are reported beside the wall seconds (the
    work done, which the machine's noise disturbs less).
    """
    c_engine, under_test = CEngine(), MJXEngine()
    tol = scenario.tolerance.for_precision("float64")

    def verify(mode: NoiseFloor) -> Callable[[], Any]:
        config = SweepConfig(diagnose="none", noise_floor=mode)
        return lambda: run_inputs(scenario.name, m, inputs, tol, config, under_test, c_engine)

    runs: dict[str, Callable[[], Any]] = dict(engines=lambda: (c_engine.rollout(inputs), under_test.rollout(inputs)),
                verify=verify("on-demand"), verify_always=verify("always"))
    members = runs["verify"]().info["noise_floor_members"]  # warm: compiles the metrics too
    for fn in runs.values():
        fn()
    times: dict[str, list[tuple[float, float]]] = {key: [] for key in runs}
    for _ in range(max(repeats, 5)):
        for key, fn in runs.items():
            wall, cpu = time.perf_counter(), time.process_time()
            fn()
            times[key].append((time.perf_counter() - wall, time.process_time() - cpu))
    (engines_s, engines_cpu), (verify_s, verify_cpu), (always_s, always_cpu) = (min(times[k]) for k in runs)
    return dict(engines_s=engines_s, verify_s=verify_s, throughput_ratio=engines_s / verify_s,
                engines_cpu_s=engines_cpu, verify_cpu_s=verify_cpu, cpu_ratio=engines_cpu / verify_cpu,
                noise_floor_members=members, members=inputs.batch,
                always_s=always_s, always_ratio=engines_s / always_s, always_cpu_ratio=engines_cpu / always_cpu)


def recommendations(r: dict[str, Any]) -> list[str]:
    """Plain-language advice from one scenario's numbers."""
    best, curve, out = r["best"], r["curve"], []
    out.append(f"best batch size for MJX here: {best['batch']} ({best['mjx_steps_per_s']:,.0f} steps/s)")
    if len(curve) > 1 and curve[-1] is not best and curve[-1]["mjx_steps_per_s"] < 0.9 * best["mjx_steps_per_s"]:
        out.append(f"larger batches are slower per step (batch {curve[-1]['batch']}: "
                   f"{curve[-1]['mjx_steps_per_s']:,.0f} steps/s): split big sweeps into batches of {best['batch']}")
    slow, fast = ("MJX", "C") if best["mjx_over_c"] < 1 else ("C", "MJX")
    factor = 1 / best["mjx_over_c"] if best["mjx_over_c"] < 1 else best["mjx_over_c"]
    out.append(f"bottleneck: {slow} ({factor:.1f}x slower than {fast} on the same batch and cores)")
    if (best.get("first_call", "compiled") == "compiled"
            and best["compile_s"] > 5 * best["batch"] * best["steps"] / best["mjx_steps_per_s"]):
        out.append(f"compiling ({best['compile_s']:.1f} s) costs more than 5 runs: keep the persistent "
                   "compilation cache (--cache-dir) and sweep many variants per compile")
    split = r["split"]
    if "speedup" in split:
        verdict = "keep it" if split["speedup"] >= 1.1 else "it does not pay for this model; try MJXDIFF_DEVICES=1"
        out.append(f"device split over {split['devices']} host devices: {split['speedup']:.2f}x one device ({verdict})")
    elif device_count() > 1:
        out.append(f"batch {best['batch']} is not split over the {device_count()} host devices (fewer than "
                   f"{SPLIT_MIN_MEMBERS} members each); larger batches are")
    else:
        out.append("one host device (one core, or MJXDIFF_DEVICES=1): MJX's batch is not split")
    tester = r["tester"]
    ratio, cpu = tester["throughput_ratio"], tester["cpu_ratio"]
    cost = "metrics and verdict are cheap" if ratio >= 0.85 else "metrics and verdict are a noticeable cost"
    text = f"verification runs at {ratio:.2f}x the engines' own throughput, {cpu:.2f}x in CPU seconds ({cost})"
    if "always_ratio" in tester:
        text += (f"; C's perturbed rerun ran for {tester['noise_floor_members']}/{tester['members']} members "
                 f"(on demand); with --noise-floor always: {tester['always_ratio']:.2f}x")
    out.append(text)
    return out


def _compile_cell(p: dict[str, Any]) -> str:
    """Compile seconds, marked ``*`` when the first call loaded a saved rollout instead."""
    return f"{p['compile_s']:.1f}" + ("*" if p.get("first_call") == "loaded" else "")


def format_text(results: Sequence[dict[str, Any]]) -> str:
    """A table per scenario and its recommendations."""
    lines = []
    for r in results:
        lines.append(f"{r['scenario']} (nq {r['nq']}, nv {r['nv']}, nu {r['nu']}), {r['curve'][0]['steps']} steps")
        lines.append(f"  {'batch':>6} {'MJX steps/s':>12} {'C steps/s':>12} {'MJX/C':>7} {'compile s':>10} "
                     f"{'MJX cpu':>8} {'C cpu':>6} {'MJX MiB':>8} {'C MiB':>6}")
        for p in r["curve"]:
            lines.append(f"  {p['batch']:>6} {p['mjx_steps_per_s']:>12,.0f} {p['c_steps_per_s']:>12,.0f} "
                         f"{p['mjx_over_c']:>7.3f} {_compile_cell(p):>10} {p['mjx_cpu']:>8.0%} {p['c_cpu']:>6.0%} "
                         f"{p['mjx_peak_mib']:>8.0f} {p['c_peak_mib']:>6.0f}")
        if "warp_steps_per_s" in r["curve"][0]:
            lines.append(f"  {'batch':>6} {'MJWarp steps/s':>14} {'first call +s':>14} {'MJWarp cpu':>10} {'MiB':>6}")
            for p in r["curve"]:
                lines.append(f"  {p['batch']:>6} {p['warp_steps_per_s']:>14,.0f} {p['warp_first_s']:>14.1f} "
                             f"{p['warp_cpu']:>10.0%} {p['warp_peak_mib']:>6.0f}")
        if any(p.get("first_call") == "loaded" for p in r["curve"]):
            lines.append("  * a saved rollout was loaded from the persistent cache: seconds of loading, not compiling")
        lines += [f"  - {text}" for text in r["recommendations"]]
    return "\n".join(lines)
