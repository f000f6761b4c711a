"""The two precisions MJX is judged in, and every threshold that depends on which.

C always runs in float64; ``precision`` is the engine under test's (MJWarp on CPU is float32).
"""

from __future__ import annotations

import dataclasses
from typing import Literal

import numpy as np

__all__ = ["PRECISIONS", "THRESHOLDS", "Precision", "Thresholds"]

Precision = Literal["float64", "float32"]
PRECISIONS: tuple[Precision, ...] = ("float64", "float32")


@dataclasses.dataclass(frozen=True)
class Thresholds:
    """Per-precision thresholds.

    Attributes:
      eps: machine epsilon (the unit of :func:`mjxdiff.noise.perturb`'s perturbation).
      stage_rtol: relative threshold of the drill-down's stage comparison,
        ``|mjx - c| <= stage_rtol (1 + max|c|)`` (:func:`mjxdiff.diagnose.drill_down`).
      transfer_rtol: relative threshold of the host-interface check (:mod:`mjxdiff.transfer`).
      tolerance_floor: least rollout tolerance per field (:meth:`mjxdiff.scenario.Tolerances.for_precision`);
        float32 rounding (eps ~1.2e-7) accumulates over hundreds of steps, and these floors
        were measured on the bundled calm scenarios (see README).
    """

    eps: float
    stage_rtol: float
    transfer_rtol: float
    tolerance_floor: dict[str, float]


THRESHOLDS: dict[Precision, Thresholds] = {
    "float64": Thresholds(eps=float(np.finfo(np.float64).eps), stage_rtol=1e-9, transfer_rtol=1e-12,
                          tolerance_floor={}),
    "float32": Thresholds(eps=float(np.finfo(np.float32).eps), stage_rtol=1e-4, transfer_rtol=1e-6,
                          tolerance_floor={"qpos": 1e-3, "qvel": 1e-2, "act": 1e-3, "sensordata": 5e-2}),
}
