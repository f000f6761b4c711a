"""mjxdiff: differential testing of MuJoCo MJX against MuJoCo C.

Code map, one folder per stage (data flows down; docs/explanation/architecture.md draws it):

- ``input``: scenario files, the settings (``options``, declared once; ``config``), precision,
  batched inputs, joints, adjustments, cost.
- ``engine``: the Trajectory and Engine protocol, MuJoCo C (``c``), MJX (``engines``,
  ``models``, ``xla``), MuJoCo Warp (``mjwarp``), compiled rollouts across processes
  (``export_cache``, ``digest``, ``trace_deps``), a forward pass stage by stage (``stages``).
- ``compare``: C's rounding envelope (``noise``), ``verdict`` and ``result``, ``onestep``,
  ``transfer``, ``diagnose``, the catalogue (``known``, ``support``), ``segments``, ``reference``.
- ``output``: ``report``, ``html_report``, ``reproducer``, ``history``, ``baseline``.
- ``runner``: ``sweep`` and its parts (``stream``, ``followup``, ``plan``, ``current``),
  ``guard``, ``pipeline``, ``journal``, ``executors``, ``scaling``.
- ``tools``: ``versions``, ``shrink``, ``bundle``, ``fuzz``, ``strategies``, ``interactions``,
  ``coverage``, ``grad``, ``closedloop``, ``bench``; ``cli``: ``python -m mjxdiff``.
- At the top: ``metrics`` (jax.numpy), ``compat``, ``testing``, ``pytest_plugin``, ``files``,
  ``errors``.

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
import importlib.abc
import importlib.util
import sys as _sys
import time as _time

__version__ = "0.1.0"
#: perf_counter() when mjxdiff was first imported: the start of a run's "start-up" phase
_IMPORTED_AT = _time.perf_counter()

#: public name -> module that defines it
_PUBLIC = {
    "BatchedInputs": "mjxdiff.input.inputs",
    "CEngine": "mjxdiff.engine.engines",
    "Engine": "mjxdiff.engine.trajectory",  # the protocol C, MJX and MuJoCo Warp implement
    "MJWarpEngine": "mjxdiff.engine.mjwarp",  # needs the warp extra
    "MJXEngine": "mjxdiff.engine.engines",
    "Scenario": "mjxdiff.input.scenario",
    "ScenarioError": "mjxdiff.input.scenario",
    "ScenarioResult": "mjxdiff.compare.verdict",
    "SweepConfig": "mjxdiff.runner.sweep",
    "SweepOptions": "mjxdiff.runner.pipeline",
    "Tolerances": "mjxdiff.input.scenario",
    "Trajectory": "mjxdiff.engine.trajectory",
    "UnsupportedError": "mjxdiff.engine.engines",
    "bundled_scenarios": "mjxdiff.input.scenario",
    "baseline": None,  # the module: what changed since a trusted run
    "closedloop": None,  # the module: a policy in closed loop on MJX and on C
    "grad": None,  # the module: MJX's one-step Jacobians against C's finite differences
    "guard": None,  # the module: a sweep in a watched child process, memory and time bounded
    "history": None,  # the module: the Parquet run history and its anomalies
    "known": None,  # the module: the catalogue of known MJX-vs-C approximations
    "onestep": None,  # the module: one step from C's states, converged solver, C's rounding as the bound
    "transfer": None,  # the module: MJX's host interface checked against C
    "configure_jax": "mjxdiff.engine.engines",
    "judge": "mjxdiff.compare.verdict",
    "load_scenario": "mjxdiff.input.scenario",
    "make_inputs": "mjxdiff.input.inputs",
    "merge": "mjxdiff.runner.pipeline",  # one report from the journals of a sweep's shards or resumed runs
    "metrics": None,  # the module itself
    "run": "mjxdiff.runner.pipeline",  # a whole sweep as the CLI runs it: verdicts, known, history, baseline, files
    "run_scenario": "mjxdiff.runner.sweep",
    "shrink": None,  # the module: a diverging model shrunk to a minimal one with the same divergence
    "sweep": None,  # the module, callable as its function: mjxdiff.sweep(scenarios, config)
}

__all__ = sorted(_PUBLIC)  # pyright: ignore[reportUnsupportedDunderAll] - the lazy exports below


#: module -> its stage subpackage, for the modules that were at the top level before 0.2:
#: ``import mjxdiff.sweep`` or ``from mjxdiff.scenario import load_scenario`` keeps working
#: for this release and gives the very module ``mjxdiff.runner.sweep``, ``mjxdiff.input.scenario``.
_MOVED = {
    **dict.fromkeys(["scenario", "config", "precision", "inputs", "joints", "adjust", "cost"], "input"),
    **dict.fromkeys(["trajectory", "engines", "mjwarp", "export_cache", "stages"], "engine"),
    **dict.fromkeys(["noise", "verdict", "result", "onestep", "transfer", "diagnose", "segments", "known",
                     "support", "reference"], "compare"),
    **dict.fromkeys(["sweep", "guard", "pipeline", "journal", "executors", "scaling"], "runner"),
    **dict.fromkeys(["report", "html_report", "reproducer", "history", "baseline"], "output"),
    **dict.fromkeys(["versions", "shrink", "bundle", "fuzz", "strategies", "interactions", "coverage", "grad",
                     "closedloop", "bench"], "tools"),
}


class _MovedModules(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Imports ``mjxdiff.<old>`` as the module it moved to (one module object under both names)."""

    def find_spec(self, fullname, path, target=None):
        leaf = fullname.removeprefix("mjxdiff.")
        if fullname.startswith("mjxdiff.") and leaf in _MOVED:
            return importlib.util.spec_from_loader(fullname, self)
        return None

    def create_module(self, spec):
        leaf = spec.name.removeprefix("mjxdiff.")
        return importlib.import_module(f"mjxdiff.{_MOVED[leaf]}.{leaf}")

    def exec_module(self, module):
        pass  # already executed under its own name


_sys.meta_path.append(_MovedModules())


def __getattr__(name: str):
    if name not in _PUBLIC:
        raise AttributeError(f"module 'mjxdiff' has no attribute {name!r}")
    module = _PUBLIC[name]
    if module is None:
        value = importlib.import_module(f"mjxdiff.{_MOVED[name]}.{name}" if name in _MOVED else f"mjxdiff.{name}")
    else:
        value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_PUBLIC))
