"""mjxdiff: differential testing of MuJoCo MJX against MuJoCo C.

The public surface, one name per line; everything else is an implementation
detail of its module.
"""

from mjxdiff import engines  # noqa: F401  (first: sets XLA_FLAGS before JAX's backend starts)
from mjxdiff import metrics
from mjxdiff.engines import CEngine
from mjxdiff.engines import MJXEngine
from mjxdiff.engines import Trajectory
from mjxdiff.engines import UnsupportedError
from mjxdiff.engines import configure_jax
from mjxdiff.inputs import BatchedInputs
from mjxdiff.inputs import make_inputs
from mjxdiff.scenario import Scenario
from mjxdiff.scenario import ScenarioError
from mjxdiff.scenario import Tolerances
from mjxdiff.scenario import bundled_scenarios
from mjxdiff.scenario import load_scenario
from mjxdiff.sweep import SweepConfig
from mjxdiff.sweep import run_scenario
from mjxdiff.sweep import sweep
from mjxdiff.verdict import ScenarioResult
from mjxdiff.verdict import judge

__version__ = "0.1.0"

__all__ = [
    "BatchedInputs",
    "CEngine",
    "MJXEngine",
    "Scenario",
    "ScenarioError",
    "ScenarioResult",
    "SweepConfig",
    "Tolerances",
    "Trajectory",
    "UnsupportedError",
    "bundled_scenarios",
    "configure_jax",
    "judge",
    "load_scenario",
    "make_inputs",
    "metrics",
    "run_scenario",
    "sweep",
]
