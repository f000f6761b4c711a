"""The two precisions MJX is judged in, and every threshold that depends on which.

C always runs in float64; ``precision`` is the engine under test's (MJWarp on CPU is float32).
"""

from __future__ import annotations

import dataclasses
from typing import Literal

import numpy as np

__all__ = ["PRECISIONS", "STAGE_TOLERANCE_FLOAT32", "THRESHOLDS", "Precision", "Thresholds"]

Precision = Literal["float64", "float32"]
PRECISIONS: tuple[Precision, ...] = ("float64", "float32")


@dataclasses.dataclass(frozen=True)
class Thresholds:
    """Per-precision thresholds.

    Attributes:
      eps: machine epsilon (the unit of :func:`mjxdiff.compare.noise.perturb`'s perturbation).
      stage_rtol: the drill-down's default threshold, ``|mjx - c| <= stage_rtol (1 + max|c|)``.
      stage_tolerance: per stage of ``mj_forward``, ``(atol, rtol)``: a field of that stage
        agrees when ``max|mjx - c| <= atol + rtol max|c|`` (:func:`mjxdiff.compare.diagnose.drill_down`);
        a stage not named here uses ``(stage_rtol, stage_rtol)``. See :data:`STAGE_TOLERANCE_FLOAT32`.
      transfer_rtol: relative threshold of the host-interface check (:mod:`mjxdiff.compare.transfer`).
      tolerance_floor: least rollout tolerance per field (:meth:`mjxdiff.input.scenario.Tolerances.for_precision`);
        float32 rounding (eps ~1.2e-7) accumulates over hundreds of steps, and these floors
        were measured on the bundled calm scenarios (see README). ``contact_mismatch``: float32
        collision arithmetic is not C's float64 on a float32 state (the shadow): MJX's
        plane-cylinder distance in float32 was 2.1e-5 m from C's at the same rounded state, past
        the grazing band, so a contact may start a step apart (primitives_on_plane, seed 2).
    """

    eps: float
    stage_rtol: float
    transfer_rtol: float
    tolerance_floor: dict[str, float]
    stage_tolerance: dict[str, tuple[float, float]] = dataclasses.field(default_factory=dict)

    def stage_bound(self, stage: str, scale: float) -> float:
        """The largest ``|mjx - c|`` a field of ``stage`` may show, its C values' largest
        magnitude being ``scale``: ``atol + rtol scale`` (same units as the field)."""
        atol, rtol = self.stage_tolerance.get(stage, (self.stage_rtol, self.stage_rtol))
        return atol + rtol * scale


#: The float32 drill-down's ``(atol, rtol)`` per stage: MuJoCo's parity method's defaults
#: (``mujoco/doc/skills/parity/SKILL.md``, MuJoCo 4.0.1: kinematics and tendons 1e-5/1e-4, the
#: mass matrix 1e-8/1e-5, forces 1e-3/1e-3, qacc_smooth 1e-2/1e-3, the constraint solver's output
#: 1e-1/1e-2), with ``rtol`` scaling the field's largest C value rather than each component's (a
#: component near zero in a field of large values is that field's rounding: the parity method adds
#: bounds per component for it). Sensors, which the method leaves out, as forces. float64 keeps one
#: threshold for every stage (1e-9 of the field's scale): its rounding is 1e-16 relative, so any
#: algorithmic difference stands out in every stage alike.
STAGE_TOLERANCE_FLOAT32: dict[str, tuple[float, float]] = {
    "kinematics": (1e-5, 1e-4), "inertia": (1e-8, 1e-5), "tendons": (1e-5, 1e-4),
    "passive": (1e-3, 1e-3), "bias": (1e-3, 1e-3), "actuation": (1e-3, 1e-3),
    "smooth acceleration": (1e-2, 1e-3), "constraint": (1e-1, 1e-2), "acceleration": (1e-1, 1e-2),
    "sensors": (1e-3, 1e-3),
}


THRESHOLDS: dict[Precision, Thresholds] = {
    "float64": Thresholds(eps=float(np.finfo(np.float64).eps), stage_rtol=1e-9, transfer_rtol=1e-12,
                          tolerance_floor={}),
    "float32": Thresholds(eps=float(np.finfo(np.float32).eps), stage_rtol=1e-4, transfer_rtol=1e-6,
                          tolerance_floor={"qpos": 1e-3, "qvel": 1e-2, "act": 1e-3, "sensordata": 5e-2,
                                           # float32 collision arithmetic misplaces a contact by more than the
                                           # 1e-5 m grazing band (MJX's plane-cylinder: 2.1e-5 m, measured)
                                           "contact_mismatch": 0.05},
                          stage_tolerance=STAGE_TOLERANCE_FLOAT32),
}
