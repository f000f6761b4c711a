"""The one scaffold of the sweep-level injected-bug tests: *reaches, catches, passes clean*.

A bug is ``bug(mp: pytest.MonkeyPatch) -> None``: it patches one function inside
``mujoco.mjx._src`` for as long as ``mp`` is active (:func:`model_edited` builds the common kind,
MJX reading one model parameter wrong). :func:`sweep` runs a scenario with a bug applied, the
compiled rollouts cleared around it so the patch is traced and nothing patched outlives it.
:func:`caught` is the whole proof of a catch: the scenario at that config passes unmodified
(:func:`clean`, once per scenario and config in a test process), and with the bug it fails
naming the field and the object the bug must produce (:class:`Expect`), at a step inside the
rollout, beyond its tolerance.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Callable

import pytest

from mjxdiff import engines
from mjxdiff.scenario import Scenario, load_scenario
from mjxdiff.sweep import ScenarioResult, SweepConfig, run_scenario

Bug = Callable[[pytest.MonkeyPatch], None]


def model_edited(mp: pytest.MonkeyPatch, module, name: str, edit: Callable) -> None:
    """Patches ``module.name(m, d, *args)`` to run on ``edit(m)``: MJX reading a parameter wrong."""
    orig = getattr(module, name)
    mp.setattr(module, name, lambda m, d, *args: orig(edit(m), d, *args))


@dataclasses.dataclass(frozen=True)
class Expect:
    """What a catch must name. ``fields``: the first divergent field is one of these (``qpos``,
    ``qvel``, ``act``, ``sensordata``, ``contacts``); ``object``: a regular expression the
    first divergence's object (``"joint 'hinge'"``, ``"sensor 'r' (rangefinder)"``) matches
    in full."""

    fields: tuple[str, ...]
    object: str = ".*"


def _scenario(scenario: str | Scenario) -> Scenario:
    return load_scenario(scenario) if isinstance(scenario, str) else scenario


def sweep(scenario: str | Scenario, config: SweepConfig, bug: Bug | None = None) -> ScenarioResult:
    """``run_scenario`` with ``bug`` applied (None: unmodified MJX), traced afresh."""
    with pytest.MonkeyPatch.context() as mp:
        if bug is not None:
            bug(mp)
        engines.clear_compiled()
        try:
            return run_scenario(_scenario(scenario), config)
        finally:
            engines.clear_compiled()


_CLEAN: dict[tuple[str, SweepConfig], ScenarioResult] = {}


def clean(scenario: str | Scenario, config: SweepConfig) -> ScenarioResult:
    """The unmodified sweep of ``scenario`` at ``config``, run once per test process."""
    s = _scenario(scenario)
    key = (repr(s), config)
    if key not in _CLEAN:
        _CLEAN[key] = sweep(s, config)
    return _CLEAN[key]


def assert_passes_clean(scenario: str | Scenario, config: SweepConfig) -> None:
    result = clean(scenario, config)
    assert result.status == "pass", f"the control fails: unmodified MJX on {result.name}: {result.message}"


def assert_names(result: ScenarioResult, expect: Expect, what: str) -> dict:
    """``result`` is a fail whose first divergence names ``expect``'s field and object, at a step
    inside the rollout, with an error above its tolerance. Returns the first divergence."""
    assert result.status == "fail", f"{what} not caught by {result.name}: {result.message}"
    first = result.first_divergence
    assert first is not None, result.message
    assert first["field"] in expect.fields, f"{what}: named {first['field']}, expected {expect.fields}: {first}"
    assert re.fullmatch(expect.object, first["object"]), f"{what}: named {first['object']!r}: {first}"
    assert 0 <= first["step"] < result.info["steps"], first
    assert first["error"] > first["tolerance"], first
    return first


def caught(bug: Bug, scenario: str | Scenario, config: SweepConfig, expect: Expect) -> dict:
    """The proof of one catch: ``scenario`` at ``config`` passes unmodified, and fails with
    ``bug`` naming ``expect``. Returns the first divergence."""
    assert_passes_clean(scenario, config)
    return assert_names(sweep(scenario, config, bug), expect, bug.__name__)
