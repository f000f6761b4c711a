"""Shared test settings: float64 JAX, a persistent compile cache, Hypothesis profiles."""

import os
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

from mjxdiff import engines
from mjxdiff.engines import configure_jax

ROOT = Path(__file__).resolve().parent.parent

# JIT compiles take seconds: no deadlines. `ci` is derandomized for reproducible CI runs.
settings.register_profile("dev", deadline=None, max_examples=20,
                          suppress_health_check=[HealthCheck.too_slow])
settings.register_profile("ci", deadline=None, max_examples=10, derandomize=True,
                          suppress_health_check=[HealthCheck.too_slow])
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "dev"))

# One cache for the whole session (and for later sessions): unmodified MJX
# compiles are shared; monkeypatched MJX traces to other HLO and never hits it.
os.environ.setdefault("MJXDIFF_CACHE", str(ROOT / ".jax_cache"))
configure_jax("float64")
# CLI sweeps run in this process (and in `python -m mjxdiff` children of tests) unless a test
# asks for the guard's child process (--isolate): many tests patch MJX here, and the guard would
# sweep in this process anyway when it sees that (tests/test_guard.py).
os.environ.setdefault("MJXDIFF_ISOLATE", "0")
# Sweeps run by tests append to a throwaway history, never the user's.
os.environ["MJXDIFF_HISTORY"] = tempfile.mkdtemp(prefix="mjxdiff-test-history-")


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return ROOT


@pytest.fixture
def fresh_mjx():
    """Compiled rollouts are cached per model structure; re-trace around a monkeypatch of MJX."""
    engines.clear_compiled()
    yield
    engines.clear_compiled()


#: Scenarios of the report tests: the gain slip of :func:`two_sweeps` breaks the first two
#: (actuated), not the third (no actuators).
REPORT_SCENARIOS = ("pendulum", "cartpole", "double_pendulum")


@pytest.fixture(scope="session")
def two_sweeps(tmp_path_factory):
    """A clean quick sweep of :data:`REPORT_SCENARIOS` (``clean/report.json``), then the same
    with MJX's actuator gains 2% high, against the clean one as baseline, with report.html
    (``bugged/``); both append to one history. Returns (directory, bugged exit code)."""
    from mujoco.mjx._src import forward as mjx_forward

    from mjxdiff.cli import main

    root = tmp_path_factory.mktemp("sweeps")
    common = ["--quick", "--history", str(root / "history"), "--cache-dir", ""]
    assert main(["sweep", *REPORT_SCENARIOS, *common, "--out", str(root / "clean")]) == 0
    orig = mjx_forward.fwd_actuation
    mp = pytest.MonkeyPatch()
    mp.setattr(mjx_forward, "fwd_actuation", lambda m, d: orig(m.replace(actuator_gainprm=m.actuator_gainprm * 1.02), d))
    engines.clear_compiled()
    try:
        code = main(["sweep", *REPORT_SCENARIOS, *common, "--out", str(root / "bugged"), "--baseline",
                     str(root / "clean"), "--plots", "failing", "--diagnose", "basic"])
    finally:
        mp.undo()
        engines.clear_compiled()
    return root, code
