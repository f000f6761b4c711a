"""Shared test settings: float64 JAX, a persistent compile cache, Hypothesis profiles."""

import os
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

from mjxdiff.engine import engines
from mjxdiff.engine.engines import configure_jax

ROOT = Path(__file__).resolve().parent.parent

# JIT compiles take seconds: no deadlines. `ci` is derandomized for reproducible CI runs.
settings.register_profile("dev", deadline=None, max_examples=20,
                          suppress_health_check=[HealthCheck.too_slow])
settings.register_profile("ci", deadline=None, max_examples=10, derandomize=True,
                          suppress_health_check=[HealthCheck.too_slow])
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "dev"))

# The user's cache, outside the clone (``$MJXDIFF_CACHE`` or ~/.cache/mjxdiff/jax), shared by the
# test processes, the README's sweep and later runs: its entries are keyed by the HLO and by the
# code digest of what was traced (README, "The compile cache"), so a warm cache is safe;
# monkeypatched MJX traces to other HLO and never hits an unmodified entry. Tests that need a
# cold path pass ``--cache-dir ""`` or a temporary directory of their own.
os.environ.setdefault("MJXDIFF_CACHE", str(Path.home() / ".cache" / "mjxdiff" / "jax"))
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
    mp.setattr(mjx_forward, "fwd_actuation",
               lambda m, d: orig(m.replace(actuator_gainprm=m.actuator_gainprm * 1.02), d))
    engines.clear_compiled()
    try:
        code = main(["sweep", *REPORT_SCENARIOS, *common, "--out", str(root / "bugged"), "--baseline",
                     str(root / "clean"), "--plots", "failing", "--diagnose", "basic"])
    finally:
        mp.undo()
        engines.clear_compiled()
    return root, code


# -- where a test's time goes ----------------------------------------------------------------------

#: ``MJXDIFF_TEST_JAX_TIMES=DIR``: each test process writes ``DIR/jax-times.<pid>.json``, per test
#: id its wall seconds and JAX's own durations summed over the test (``jax.monitoring``: tracing,
#: lowering to MLIR, XLA's compile, persistent-cache hits), to find what compiles where:
#: ``python benchmarks/scripts/jax_times.py DIR``. Off (nothing registered) when unset.
JAX_TIMES = os.environ.get("MJXDIFF_TEST_JAX_TIMES")
_JAX_EVENTS = {"/jax/core/compile/jaxpr_trace_duration": "trace",
               "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
               "/jax/core/compile/backend_compile_duration": "compile",
               "/jax/compilation_cache/compile_time_saved_sec": "cache_saved"}
_TIMES: dict[str, dict[str, float]] = {}
_CURRENT = {"test": "(outside tests)"}

if JAX_TIMES:
    import jax.monitoring

    def _on_duration(event: str, seconds: float, **_) -> None:
        if event in _JAX_EVENTS:
            row = _TIMES.setdefault(_CURRENT["test"], {})
            row[_JAX_EVENTS[event]] = row.get(_JAX_EVENTS[event], 0.0) + seconds

    jax.monitoring.register_event_duration_secs_listener(_on_duration)

    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_protocol(item, nextitem):
        import time

        _CURRENT["test"], start = item.nodeid, time.perf_counter()
        yield
        row = _TIMES.setdefault(item.nodeid, {})
        row["wall"] = row.get("wall", 0.0) + time.perf_counter() - start
        _CURRENT["test"] = "(outside tests)"

    def pytest_sessionfinish(session):
        import json

        Path(JAX_TIMES).mkdir(parents=True, exist_ok=True)
        (Path(JAX_TIMES) / f"jax-times.{os.getpid()}.json").write_text(json.dumps(_TIMES, indent=1))


# -- CI's guarantees ------------------------------------------------------------------------------

#: ``MJXDIFF_REQUIRE_ALL=1`` (set by .ci/run): a skip (an optional dependency missing, no
#: browser) is a failure, so a test that cannot run in CI cannot pass there unseen.
REQUIRE_ALL = os.environ.get("MJXDIFF_REQUIRE_ALL") == "1"


def _skip_to_failure(report) -> None:
    if REQUIRE_ALL and report.skipped and not hasattr(report, "wasxfail"):
        reason = report.longrepr[2] if isinstance(report.longrepr, tuple) else str(report.longrepr)
        report.outcome = "failed"
        report.longrepr = f"skipped where MJXDIFF_REQUIRE_ALL=1 (CI runs every test): {reason}"


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    _skip_to_failure(outcome.get_result())


@pytest.hookimpl(hookwrapper=True)
def pytest_make_collect_report(collector):
    outcome = yield
    _skip_to_failure(outcome.get_result())


#: Test files whose module- or session-scoped fixtures are expensive (a sweep, a coverage trace,
#: an MJX compile, a wheel build), each run whole on one xdist worker so they are built once; the
#: files using :func:`two_sweeps` share one group, so it is built once in the run. Every other
#: test is scheduled on its own, which balances the two workers best.
GROUPS = {
    **{name: "two_sweeps" for name in ("test_baseline.py", "test_history.py", "test_html_report.py",
                                       "test_pipeline.py")},
    # one compile of the sensing scenario with both files' bugs switched (_bugs.install_switched)
    **{name: "sensing_bugs" for name in ("test_sensing_scenario.py", "test_wider_reach.py")},
    **{name: name for name in ("test_coverage.py", "test_closedloop.py", "test_journal.py",
                               "test_executors.py", "test_engines.py", "test_packaging.py",
                               # one compile of each model with its bugs switched (_bugs.install_switched)
                               "test_parameter_families.py", "test_onestep.py", "test_injected_bugs.py")},
}


#: Files of long tests (a compile each of patched MJX or of generated models, fuzz searches,
#: a cold cache), scheduled first with the ``slow`` ones and :data:`GROUPS`.
LONG_FILES = ("test_export_cache_fail_closed.py", "test_fuzz.py", "test_sensing_scenario.py", "test_wider_reach.py",
              "test_contact_geometry.py",
              "test_stale_code.py", "test_solver_floor.py")


def _long_first(item) -> int:
    return 0 if (item.get_closest_marker("slow") or item.path.name in GROUPS or item.path.name in LONG_FILES) else 1


def pytest_collection_modifyitems(config, items):
    """Longest first, then groups for ``--dist loadgroup``.

    Order: xdist's scheduler hands out work in collection order and lets a worker queue up to 3
    tests, so long tests collected last leave one worker idle at the end; the long ones (by
    :func:`_long_first`) go first, each set in its collection order (the same on every worker).

    Groups (:data:`GROUPS`) on the node id, where xdist's scheduler reads them: a test
    ``tests/test_coverage.py::test_x`` becomes ``...::test_x@test_coverage.py``. Not through
    xdist's own ``xdist_group`` marker: xdist 3.8 appends the group to ``item._nodeid``, which
    pytest 9 no longer reads (its node id is ``item._id``), so every test was scheduled alone
    and a module's fixtures were built on both workers."""
    items.sort(key=_long_first)
    if not config.getoption("loadgroup", default=False):
        return
    from _pytest.nodeid import coerce_node_id

    for item in items:
        group = GROUPS.get(item.path.name)
        if group is not None and "@" not in item.nodeid:
            item._id = coerce_node_id(f"{item.nodeid}@{group}")
