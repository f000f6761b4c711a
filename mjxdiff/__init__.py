"""mjxdiff: differential testing of MuJoCo MJX against MuJoCo C.

Code map, by stage (data flows down):

- Input: ``scenario`` (scenario files, tolerances), ``config`` (a sweep's settings),
  ``precision`` (float64/float32 and their thresholds), ``inputs`` (scenario -> batched
  initial states, controls, per-member models), ``joints`` (qpos walks, quaternions),
  ``adjust`` (what is changed so MJX can run a model), ``cost`` (compile and memory estimate).
- Engines: ``trajectory`` (Trajectory, the Engine protocol), ``engines`` (MuJoCo C, MJX),
  ``mjwarp`` (MuJoCo Warp), ``export_cache`` (compiled MJX rollouts across processes),
  ``compat`` (every difference between the supported MuJoCo/MJX/JAX releases).
- Comparison: ``metrics`` (errors and behaviour statistics in jax.numpy), ``noise`` (C's own
  rounding envelope), ``verdict`` (trajectories -> a verdict per scenario; its data, without
  JAX, in ``result``), ``onestep`` (one
  step from C's states), ``transfer`` (MJX's host interface), ``diagnose`` (drill-down, causes),
  ``segments`` (MJX's regularized capsule contacts, in NumPy).
- Running: ``sweep`` (scenarios end to end), ``guard`` (a sweep in a watched child process),
  ``pipeline`` (a whole sweep with known labels, history, baseline, files: :func:`run`;
  shards, resume, :func:`merge`), ``journal`` (each finished unit on disk at once),
  ``executors`` (a sweep's units as Ray tasks), ``scaling`` (wall time over more nodes).
- Output: ``report`` (text, report.json), ``html_report`` (report.html), ``reproducer``
  (failing members, replay), ``history`` (Parquet run history), ``baseline`` (what changed),
  ``known`` (the known-divergence catalogue), ``files`` (atomic writes), ``errors`` (one-line
  exceptions).
- Other uses: ``versions`` (the same sweep on several MJX releases), ``shrink`` (a diverging
  model to a minimal one with the same divergence), ``bundle`` (that as a bug report an MJX
  maintainer can run), ``fuzz`` and ``strategies``
  (Hypothesis), ``interactions`` and ``coverage`` (what the scenarios reach), ``grad``
  (Jacobians), ``closedloop`` (policies), ``bench`` (performance), ``testing`` and
  ``pytest_plugin`` (users' own tests), ``cli`` (``python -m mjxdiff``).

The public surface, one name per line; everything else is an implementation
detail of its module. Names are imported on first use (PEP 562), so that
``import mjxdiff`` and ``import mjxdiff.metrics`` import neither MuJoCo nor MJX
and change nothing in the process: XLA's flags are set by :func:`configure_jax`
(the CLI calls it), not by an import.

>>> import mjxdiff
>>> "run" in mjxdiff.__all__ and "metrics" in mjxdiff.__all__
True
>>> mjxdiff.metrics.__name__             # imported on first use
'mjxdiff.metrics'
"""

import importlib
import time as _time

__version__ = "0.1.0"
#: perf_counter() when mjxdiff was first imported: the start of a run's "start-up" phase
_IMPORTED_AT = _time.perf_counter()

#: public name -> module that defines it
_PUBLIC = {
    "BatchedInputs": "mjxdiff.inputs",
    "CEngine": "mjxdiff.engines",
    "Engine": "mjxdiff.trajectory",  # the protocol C, MJX and MuJoCo Warp implement
    "MJWarpEngine": "mjxdiff.mjwarp",  # needs the warp extra
    "MJXEngine": "mjxdiff.engines",
    "Scenario": "mjxdiff.scenario",
    "ScenarioError": "mjxdiff.scenario",
    "ScenarioResult": "mjxdiff.verdict",
    "SweepConfig": "mjxdiff.sweep",
    "SweepOptions": "mjxdiff.pipeline",
    "Tolerances": "mjxdiff.scenario",
    "Trajectory": "mjxdiff.trajectory",
    "UnsupportedError": "mjxdiff.engines",
    "bundled_scenarios": "mjxdiff.scenario",
    "baseline": None,  # the module: what changed since a trusted run
    "closedloop": None,  # the module: a policy in closed loop on MJX and on C
    "grad": None,  # the module: MJX's one-step Jacobians against C's finite differences
    "guard": None,  # the module: a sweep in a watched child process, memory and time bounded
    "history": None,  # the module: the Parquet run history and its anomalies
    "known": None,  # the module: the catalogue of known MJX-vs-C approximations
    "onestep": None,  # the module: one step from C's states, converged solver, C's rounding as the bound
    "transfer": None,  # the module: MJX's host interface checked against C
    "configure_jax": "mjxdiff.engines",
    "judge": "mjxdiff.verdict",
    "load_scenario": "mjxdiff.scenario",
    "make_inputs": "mjxdiff.inputs",
    "merge": "mjxdiff.pipeline",  # one report from the journals of a sweep's shards or resumed runs
    "metrics": None,  # the module itself
    "run": "mjxdiff.pipeline",  # a whole sweep as the CLI runs it: verdicts, known, history, baseline, files
    "run_scenario": "mjxdiff.sweep",
    "shrink": None,  # the module: a diverging model shrunk to a minimal one with the same divergence
    "sweep": None,  # the module, callable as its function: mjxdiff.sweep(scenarios, config)
}

__all__ = sorted(_PUBLIC)  # pyright: ignore[reportUnsupportedDunderAll] - the lazy exports below


def __getattr__(name: str):
    if name not in _PUBLIC:
        raise AttributeError(f"module 'mjxdiff' has no attribute {name!r}")
    module = _PUBLIC[name]
    value = importlib.import_module(f"mjxdiff.{name}") if module is None else getattr(
        importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_PUBLIC))
