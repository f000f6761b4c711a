"""Time to verdict of the default sweep, cold then warm, each a fresh ``python -m mjxdiff sweep``
process with a fresh cache (``MJXDIFF_CACHE`` and ``XDG_CACHE_HOME`` in a temporary directory).

Run: ``python -m pytest benchmarks/test_sweep_time.py --benchmark-only -s`` (about 10 minutes on
2 cores; ``MJXDIFF_BENCH_SCENARIOS="pendulum ant"`` sweeps only those). Each result's
``extra_info`` holds the process's wall and CPU seconds (user + system, its children included),
the report's per-phase table (``report.json`` ``timing``) and the ratio the verdict is judged by:
wall seconds / the engines' own stepping (``info.seconds.mjx + info.seconds.c`` summed over the
scenarios). The cold run must come first: the warm one reuses its cache.
"""

import json
import os
import resource
import subprocess
import sys
import time

import pytest

SCENARIOS = os.environ.get("MJXDIFF_BENCH_SCENARIOS", "").split()


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("sweep-time-cache")


def _sweep(cache, out) -> dict:
    """One sweep process: its wall and CPU seconds and the report's timing table."""
    env = dict(os.environ, MJXDIFF_CACHE=str(cache / "jax"), XDG_CACHE_HOME=str(cache / "xdg"))
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "mjxdiff", "sweep", *SCENARIOS, "--out", str(out)],
                          capture_output=True, text=True, env=env, timeout=3600)
    wall = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    timing = json.loads((out / "report.json").read_text())["timing"]
    cpu = after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime
    return dict(wall_s=round(wall, 1), cpu_s=round(cpu, 1), stepping_s=timing["stepping"],
                ratio=round(wall / timing["stepping"], 2), phases=timing["phases"], compile=timing["compile"],
                process=timing["process"])


@pytest.mark.parametrize("run", ["cold", "warm"])
def test_default_sweep_time_to_verdict(benchmark, cache, tmp_path, run):
    found = benchmark.pedantic(_sweep, args=(cache, tmp_path / run), rounds=1, iterations=1)
    benchmark.extra_info.update(found, run=run, scenarios=SCENARIOS or "all bundled")
    print(f"\n{run}: {found['wall_s']} s wall, {found['cpu_s']} CPU-s, engines' stepping {found['stepping_s']} s, "
          f"ratio {found['ratio']}x; phases {found['phases']}")
