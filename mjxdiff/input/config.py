"""The settings of a sweep (:class:`SweepConfig`), shared by every scenario in it; read back
from reproducers without the sweep itself."""

from __future__ import annotations

import dataclasses

from mjxdiff.input.options import COMPILE_MODES, IMPLS, NOISE_FLOOR_MODES, WARP_IMPLS, CompileMode, Diagnose, NoiseFloor
from mjxdiff.input.precision import Precision
from mjxdiff.input.scenario import Scenario

__all__ = ["IMPLS", "NOISE_FLOOR_MODES", "WARP_IMPLS", "SweepConfig"]


@dataclasses.dataclass(frozen=True)
class SweepConfig:
    """Settings shared by every scenario of a sweep. The values a sweep's options fill, their
    types and choices are declared once, in :mod:`mjxdiff.input.options`.

    Attributes:
      seed: master seed for all randomization.
      batch: overrides each scenario's batch size when set.
      steps: overrides each scenario's horizon when set.
      precision: ``float64`` or ``float32`` (MJX side; C is always float64).
      quick: a smoke run: batch <= 4 and steps <= 50, without the converged twin and the
        diagnosis's ablations (each a compile of its own; the verdict says what was skipped).
        Its members are stepped through the full run's compiled piece (padded to its member
        group, the 50 steps a run-time trip count): a quick run after a full one, or before it,
        compiles nothing the other has not (not where stepping is slow: hull-hull contacts).
      threshold: least fraction of batch members within tolerance for a scenario to pass.
      envelope: judge against the chaos envelope from C's self-divergence
        (:mod:`mjxdiff.compare.noise`); False holds errors to the fixed tolerances only.
      noise_floor: when C's perturbed rerun (the envelope's source) runs: ``on-demand``
        only for groups of members whose errors exceed the fixed tolerances (or whose
        contact counts mismatch too often), the only ones whose verdict it can change;
        ``always`` for every member, so that every report carries the envelope and
        ``noise_rate``.
      diagnose: for failing scenarios, ``none``; ``basic``: local
        (re-synchronised) error and the stage drill-down; ``full``: also the
        cause attribution by ablations (each ablation recompiles).
      reproducers: directory for the reproducers of failing members (written by the caller:
        :func:`mjxdiff.output.report.write_pending`), or None.
      piece_steps: steps per streamed piece; None: :func:`piece_steps` of the memory budget.
      group_size: members MJX steps at once; None: the smaller of :func:`group_size` (memory
        budget) and the MJX engine's ``batch_cap()`` (32 members per device).
      adjust: set aside settings MJX refuses that change nothing compared (the energy
        flag; :func:`mjxdiff.input.adjust.harmless`), reported as ``adjusted``.
      drop_unsupported: remove the geom pairs MJX cannot collide from the model both
        engines step (:func:`mjxdiff.input.adjust.drop_unsupported`); changes the dynamics, so
        off by default and reported as ``adjusted``.
      compile: how hard XLA optimises each MJX rollout: ``auto`` (from the stepping it
        will do, :func:`mjxdiff.engine.xla.xla_options`), ``fast`` or ``optimized``.
      compile_workers: threads that run scenarios side by side, each from compile to
        verdict (:func:`sweep`); None: :func:`default_compile_workers`; 0: none, one
        scenario after another on the calling thread.
      transfer: also check MJX's host interface (``put_data``, ``get_data``,
        ``get_state``/``set_state``, names, ``bind``) against C at two C states of member 0
        (:mod:`mjxdiff.compare.transfer`); a mismatch fails the scenario as field ``transfer``.
      onestep: the one-step check on every scenario that ran (:mod:`mjxdiff.compare.onestep`): from
        states of C's rollout, one step in both engines, bounded by C's own rounding; it can
        fail the scenario on its own (``info['onestep']``), and it tells whether the model's
        solver settings converge, which decides the converged twin (:func:`mjxdiff.runner.followup.sharp`).
      impl: the implementation judged against C: ``mjx`` or ``warp`` (MuJoCo Warp on the
        CPU, :mod:`mjxdiff.engine.mjwarp`; float32, so ``precision`` becomes ``float32``: tolerance
        floors, the perturbation of C's rerun and the metrics are float32's; no host-interface
        check; the drill-down compares MJWarp's forward stages with C's, the local error
        restarts MJWarp from C's states, the cause attribution runs its ablations on MJWarp).
        ``mjx.warp``: MJX's own warp implementation (``mjx.put_model(m, impl='warp')``, MJX's
        vendored MuJoCo Warp under ``jit(vmap(scan(mjx.step)))``, :class:`mjxdiff.engine.engines.MJXWarpEngine`),
        float32 likewise.
      reference: what ``impl`` is judged against: ``c``, or ``mjx`` (with ``impl='warp'``:
        MJWarp against MJX, in float32, still with C's own envelope and solver floor).
      budget: seconds a scenario may take (None: no limit). A compile estimated past it
        (:mod:`mjxdiff.input.cost`) ends the scenario before it starts, as an ``error`` of kind
        ``budget``; past it, the diagnosis and the sharp checks are cut short (each says so).
        :func:`mjxdiff.runner.guard.sweep` also stops a scenario that runs past it.
      max_memory: bytes of resident memory the process may hold (None: no limit): MJX's member
        group shrinks until its stepping fits, and a model one member of which cannot fit ends
        as an ``error`` of kind ``memory``, before it starts (:func:`mjxdiff.input.cost.plan`).
      drop_costly: remove the mesh-mesh and box-mesh pairs from the model both engines step
        (:func:`mjxdiff.input.adjust.drop_costly`); changes the dynamics, so off by default.
    """

    seed: int = 0
    batch: int | None = None
    steps: int | None = None
    precision: Precision = "float64"
    quick: bool = False
    threshold: float = 0.95
    envelope: bool = True
    noise_floor: NoiseFloor = "on-demand"
    diagnose: Diagnose = "full"
    reproducers: str | None = None
    piece_steps: int | None = None
    group_size: int | None = None
    adjust: bool = True
    drop_unsupported: bool = False
    compile: CompileMode = "auto"
    compile_workers: int | None = None
    transfer: bool = True
    onestep: bool = True
    impl: str = "mjx"
    reference: str = "c"
    budget: float | None = None
    max_memory: float | None = None
    drop_costly: bool = False

    def __post_init__(self):
        if self.impl not in IMPLS:
            raise ValueError(f"impl must be one of {IMPLS}, not {self.impl!r}")
        if self.impl in WARP_IMPLS:  # MuJoCo Warp computes in float32: judged, perturbed and toleranced so
            object.__setattr__(self, "precision", "float32")
        if self.reference not in ("c", "mjx") or (self.reference == "mjx" and self.impl != "warp"):
            raise ValueError(f"reference must be 'c', or 'mjx' with impl='warp', not {self.reference!r}")
        if self.noise_floor not in NOISE_FLOOR_MODES:
            raise ValueError(f"noise_floor must be one of {NOISE_FLOOR_MODES}, not {self.noise_floor!r}")
        if self.compile not in COMPILE_MODES:
            raise ValueError(f"compile must be one of {COMPILE_MODES}, not {self.compile!r}")
        if self.compile_workers is not None and self.compile_workers < 0:
            raise ValueError(f"compile_workers must be >= 0, not {self.compile_workers!r}")

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)

    def sizes(self, scenario: Scenario) -> tuple[int, int]:
        batch = self.batch or scenario.batch
        steps = self.steps or scenario.steps
        if self.quick:
            batch, steps = min(batch, 4), min(steps, 50)
        return batch, steps
