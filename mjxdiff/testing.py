"""Assertions for users' own test suites: ``assert_mjx_matches_c``.

    from mjxdiff.testing import assert_mjx_matches_c

    def test_my_robot():
        m = mujoco.MjModel.from_xml_path("robot.xml")
        assert_mjx_matches_c(m, qpos=my_qpos, ctrl=my_ctrl, steps=100)

On a divergence the ``AssertionError`` carries the localised diagnosis: field,
MuJoCo object, step, time, the first pipeline stage that differs and the
one-step error. The same helper is offered as the ``mjx_matches_c`` fixture by
mjxdiff's pytest plugin.
"""

from __future__ import annotations

from typing import Any

import numpy as np

import mujoco

from mjxdiff.input.inputs import BatchedInputs
from mjxdiff.input.options import Diagnose
from mjxdiff.input.scenario import Tolerances
from mjxdiff.compare.result import ScenarioResult

__all__ = ["assert_mjx_matches_c", "compare", "MJXMismatch"]


class MJXMismatch(AssertionError):
    """MJX and MuJoCo C disagree; ``result`` holds the full verdict, ``known`` the catalogue entry
    that explains it (:mod:`mjxdiff.compare.known`; its id and what to do are in the message), or None."""

    def __init__(self, message: str, result: ScenarioResult, known: Any = None):
        super().__init__(message)
        self.result = result
        self.known = known


def _batch(x: np.ndarray | None, default: np.ndarray | None, ndim: int) -> np.ndarray:
    x = default if x is None else np.asarray(x, dtype=np.float64)
    assert x is not None, "neither a value nor a default"
    return x[None] if x.ndim == ndim else x


def compare(m: mujoco.MjModel, qpos=None, qvel=None, act=None, ctrl=None, steps: int | None = None,
            tolerances: Tolerances | None = None, envelope: bool = True, diagnose: Diagnose = "basic",
            seed: int = 0, name: str = "model") -> ScenarioResult:
    """Rolls out MJX and C from the given state(s) and controls and returns the verdict.

    Args:
      m: the model (every member uses it).
      qpos, qvel, act: initial state, ``(n,)`` or batched ``(B, n)``; default qpos0 / zeros.
      ctrl: controls ``(T, nu)`` or ``(B, T, nu)``; default zeros for ``steps`` steps.
      steps: horizon when ``ctrl`` is not given (default 100).
      tolerances: fixed tolerance floors (default :class:`~mjxdiff.input.scenario.Tolerances`).
      envelope: judge against the chaos envelope as the sweep does.
      diagnose: ``none``, ``basic`` or ``full``, as in the sweep.
    """
    from mjxdiff.runner.sweep import SweepConfig, run_inputs

    qpos = _batch(qpos, m.qpos0.copy(), 1)
    batch = qpos.shape[0]
    qvel = _batch(qvel, np.zeros(m.nv), 1)
    act = _batch(act, np.zeros(m.na), 1)
    if ctrl is None:
        ctrl = np.zeros((steps or 100, m.nu))
    ctrl = _batch(ctrl, None, 2)
    qvel, act, ctrl = (np.broadcast_to(x, (batch, *x.shape[1:])).copy() for x in (qvel, act, ctrl))
    inputs = BatchedInputs(qpos=qpos, qvel=qvel, act=act, ctrl=ctrl, models=(m,) * batch, factors={}, seed=seed)
    config = SweepConfig(seed=seed, envelope=envelope, diagnose=diagnose)
    return run_inputs(name, m, inputs, tolerances or Tolerances(), config)


def assert_mjx_matches_c(m: mujoco.MjModel, qpos=None, qvel=None, act=None, ctrl=None,
                         steps: int | None = None, **kwargs) -> ScenarioResult:
    """Asserts MJX follows C from the given state and controls; see :func:`compare` for arguments.

    Raises:
      MJXMismatch: an AssertionError whose message is the localised diagnosis and, where the
        known-divergence catalogue explains it, ``[known: <id>; what to do: ...]``.
    """
    from mjxdiff.compare import known
    from mjxdiff.output import report

    result = compare(m, qpos, qvel, act, ctrl, steps, **kwargs)
    if result.status != "pass":
        entry = known.match(report.result_dict(result))
        label = f" [known: {entry.id}; what to do: {known.advice(entry)}]" if entry else ""
        raise MJXMismatch(f"MJX does not match MuJoCo C ({result.status}): {result.message}{label}", result, entry)
    return result
