"""Importing mjxdiff changes nothing in the user's process; the Python API honours its config."""

import subprocess
import sys

import jax
import numpy as np

from mjxdiff.engine.engines import MJXEngine
from mjxdiff.input.scenario import load_scenario
from mjxdiff.runner.sweep import SweepConfig, run_scenario

IMPORT_CHECK = """
import os, sys
import jax  # jax itself sets TF_CPP_MIN_LOG_LEVEL and TPU_SKIP_MDS_QUERY on import: the baseline
env, config = dict(os.environ), (jax.config.jax_enable_x64, jax.config.jax_compilation_cache_dir)
import {module}
assert dict(os.environ) == env, set(os.environ.items()) ^ set(env.items())
assert (jax.config.jax_enable_x64, jax.config.jax_compilation_cache_dir) == config
heavy = sorted(m for m in sys.modules if m == "mujoco" or m.startswith(("mujoco.", "mjxdiff.engine.engines")))
assert not heavy, heavy
from jax._src import xla_bridge
assert not xla_bridge.backends_are_initialized()
print("untouched", os.environ.get("XLA_FLAGS"))
"""


def _run(code: str, **env) -> subprocess.CompletedProcess:
    import os

    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                          env=dict(os.environ, **env))


def test_importing_the_package_or_the_metrics_changes_nothing():
    for module in ("mjxdiff", "mjxdiff.metrics", "mjxdiff.pytest_plugin"):
        proc = _run(IMPORT_CHECK.format(module=module), XLA_FLAGS="--xla_cpu_use_thunk_runtime=true")
        assert proc.returncode == 0, (module, proc.stderr[-2000:])
        assert proc.stdout.split() == ["untouched", "--xla_cpu_use_thunk_runtime=true"], module


def test_configure_jax_sets_the_flags_before_the_backend_starts_and_says_so_after():
    code = """
import os, jax, mjxdiff
mjxdiff.configure_jax(devices=3, cache_dir="")
print(os.environ["XLA_FLAGS"]); print(os.environ["PJRT_NPROC"]); print(len(jax.devices("cpu")))
"""
    proc = _run(code, XLA_FLAGS="--xla_cpu_use_thunk_runtime=true")
    assert proc.returncode == 0, proc.stderr[-2000:]
    flags, nproc, devices = proc.stdout.split("\n")[:3]
    assert "--xla_cpu_use_thunk_runtime=true" in flags and "--xla_force_host_platform_device_count=3" in flags
    assert "--xla_cpu_enable_concurrency_optimized_scheduler=false" in flags
    assert int(devices) == 3 and int(nproc) >= 4
    late = _run("import jax, mjxdiff; jax.numpy.zeros(1); mjxdiff.configure_jax(devices=3, cache_dir='')")
    assert late.returncode == 0
    lines = [line for line in late.stderr.splitlines() if line.startswith("mjxdiff:")]
    assert len(lines) == 1 and "already started" in lines[0], late.stderr


class _DtypeSpy(MJXEngine):
    """The real MJX engine, noting the dtype of every piece it hands over."""

    def __init__(self):
        super().__init__(devices=1)
        self.dtypes = set()

    def stream(self, inputs, chunk):
        for piece in super().stream(inputs, chunk):
            self.dtypes.add(piece.qpos.dtype)
            yield piece


def test_sweep_config_precision_decides_mjx_dtype_in_the_python_api():
    assert jax.config.jax_enable_x64  # the test session runs float64 (conftest)
    scenario = load_scenario("pendulum")
    spy = _DtypeSpy()
    result = run_scenario(scenario, SweepConfig(precision="float32", batch=2, steps=30, diagnose="none"), spy)
    assert spy.dtypes == {np.dtype(np.float32)}, spy.dtypes
    assert result.status == "pass", result.message
    assert result.tolerances["qpos"] == 1e-3  # float32 floors
    assert jax.config.jax_enable_x64, "the process's precision is restored"
    spy64 = _DtypeSpy()
    run_scenario(scenario, SweepConfig(precision="float64", batch=2, steps=30, diagnose="none"), spy64)
    assert spy64.dtypes == {np.dtype(np.float64)}
