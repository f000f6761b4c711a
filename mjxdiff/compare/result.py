"""A verdict's data: :class:`ScenarioResult` (one scenario) and :class:`FieldResult` (one field
of it), with the constants they are read by. NumPy only, no JAX or MuJoCo: a report, a journal
or an input error can be read and written without them; :mod:`mjxdiff.compare.verdict` computes them.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

__all__ = ["STATUSES", "OUTLIER_RATIO", "SERIES_POINTS", "WEAK_BOUND", "TRUNCATION", "FieldResult", "ScenarioResult",
           "downsample"]

STATUSES = ("pass", "fail", "unsupported", "error")
#: A healthy member whose error exceeds its bound by more than this factor fails the scenario
#: whatever the pass rate: two deterministic implementations of the same equations do not
#: scatter like noisy platforms, so one member that far out is a bug in the code it reached.
#: Unmodified MJX keeps every member of every bundled scenario within its bound (ratio <= 1).
OUTLIER_RATIO = 100.0
#: Most rows of a field's kept error series (:attr:`FieldResult.series`).
SERIES_POINTS = 256
#: A field whose bound at the median step exceeds this fraction of the field's own scale
#: (:attr:`FieldResult.bound_scale`) could not have seen a bug of that size: its pass is weak.
WEAK_BOUND = 0.01
#: The cause (``diagnosis['cause']['cause']``) of a failure that only the model's own solver
#: settings explain: the engines part as configured, held only by the solver floor, and agree
#: with a converged solver (:func:`mjxdiff.runner.followup._truncation`).
TRUNCATION = "solver truncation"


def downsample(error: np.ndarray, bound: np.ndarray, most: int = SERIES_POINTS) -> tuple[tuple[int, float, float], ...]:
    """(T,) error and bound series as at most ``most`` rows (first step, max error, max bound)
    over consecutive windows of steps.

    >>> downsample(np.array([0.0, 1.0, 5.0, 2.0]), np.array([1.0, 1.0, 1.0, 2.0]), most=2)
    ((0, 1.0, 1.0), (2, 5.0, 2.0))
    """
    T = len(error)
    if T == 0:
        return ()
    starts = np.unique(np.linspace(0, T, min(most, T) + 1).astype(int)[:-1])
    return tuple((int(k), float(e), float(b)) for k, e, b in
                 zip(starts, np.maximum.reduceat(error, starts), np.maximum.reduceat(bound, starts)))


@dataclasses.dataclass(frozen=True)
class FieldResult:
    """How one compared field did over the whole batch.

    Attributes:
      field: ``qpos``, ``qvel``, ``act``, ``sensordata``, ``contacts`` or ``rangefinder``.
      max_error: worst error over members, steps and components (the field's
        units; fractions for ``contacts``/``rangefinder``).
      tolerance: the fixed floor of the bound it is judged against.
      first_step: first step (0-based) where any member exceeds its bound; -1 if none.
      member: batch member of the worst error (or of ``first_step`` when exceeded).
      object: the MuJoCo object of that component, e.g. ``joint 'hip_2'``.
      growth_rate: exponential growth rate of the batch-max error, 1/s.
      envelope: batch-max chaos envelope at the last step (0 without a noise
        floor); the bound at (member, step) is max(tolerance, envelope there).
      ratio: worst error / bound over members and steps (> 1 means out); steps
        judged before a member's noise floor started (on demand) count against the
        tolerance alone.
      floor: which bound held the field where it came closest to it (at ``first_step``
        when exceeded): ``tolerance``, ``rounding`` (the chaos envelope) or ``solver``
        (C's freedom under its own solver settings), see :data:`mjxdiff.compare.noise.FLOORS`.
      series: the streamed per-step series the verdict kept, at most :data:`SERIES_POINTS`
        rows ``(step, batch-max error, batch-max bound)``; each row covers the steps from its
        own to the next row's, error and bound taken as their maxima there (peaks survive).
        Empty for fraction fields (``contacts``, ``rangefinder``).
      scale: the field's own size in its error's units: RMS of C's values over healthy
        members, steps and components (``sensordata``: of min(|value|, 1), its errors being
        relative above 1); 0 when there is nothing to measure.
      bound_scale: (tightest, median) over steps of the batch-max bound / ``scale``: how large
        a difference the check could still have passed, relative to the field. Above
        :data:`WEAK_BOUND` at the median step the field is :attr:`weak`.
    """

    field: str
    max_error: float
    tolerance: float
    first_step: int
    member: int
    object: str
    growth_rate: float
    envelope: float = 0.0
    ratio: float = 0.0
    floor: str = "tolerance"
    series: tuple[tuple[int, float, float], ...] = ()
    scale: float = 0.0
    bound_scale: tuple[float, float] = (0.0, 0.0)

    @property
    def ok(self) -> bool:
        return self.first_step < 0 and bool(np.isfinite(self.max_error))

    @property
    def weak(self) -> bool:
        """Whether the bound at the median step exceeds :data:`WEAK_BOUND` of the field's scale."""
        return self.scale > 0 and self.bound_scale[1] > WEAK_BOUND


@dataclasses.dataclass(frozen=True)
class ScenarioResult:
    """The verdict on one scenario, with everything the report shows; ``weak`` names the fields
    of a pass whose bound was too wide to see a bug of a percent of their scale
    (:attr:`FieldResult.weak`)."""

    name: str
    status: str
    message: str
    error_kind: str = ""
    fields: tuple[FieldResult, ...] = ()
    first_divergence: dict[str, Any] | None = None
    diverged_members: tuple[dict[str, Any], ...] = ()
    behaviour: dict[str, Any] = dataclasses.field(default_factory=dict)
    tolerances: dict[str, float] = dataclasses.field(default_factory=dict)
    info: dict[str, Any] = dataclasses.field(default_factory=dict)
    pass_rate: float | None = None
    threshold: float | None = None
    noise_rate: dict[str, float] = dataclasses.field(default_factory=dict)
    diagnosis: dict[str, Any] = dataclasses.field(default_factory=dict)
    weak: tuple[str, ...] = ()
    #: Files computed for the caller's output step to write (:func:`mjxdiff.output.report.write_pending`):
    #: ``(info key, path, JSON document)``, e.g. a failure's reproducer; not part of the verdict.
    pending: tuple[tuple[str, str, dict[str, Any]], ...] = dataclasses.field(default=(), compare=False, repr=False)

    def field(self, name: str) -> FieldResult:
        return next(f for f in self.fields if f.field == name)


# ----------------------------------------------------------------------------
# names of components
