"""Bugs that show only under a combination (tests/combination_bugs.py) are caught by the sweep's
randomization and scenarios, and the same scenario without the combination cannot see them.

Each test sweeps one bundled scenario three ways, same seed: unmodified (pass), with the bug
(fail), and with the bug but without the randomization that reaches the combination (pass: the
sweep before issue 32 drew its controls inside ctrlrange). The full catalogue, swept on every
scenario before and after, is benchmarks/scripts/combination_bugs.py (README, Coverage).
"""

import dataclasses

import pytest

import _bugs
from combination_bugs import by_id
from mjxdiff.input.scenario import load_scenario
from mjxdiff.runner.sweep import SweepConfig

#: The rollout's verdict only (no cause-finding reruns, no one-step check): what catches is the
#: rollout; batch 4 keeps one member (the last) driving its controls outside their range.
CONFIG = SweepConfig(seed=0, batch=4, steps=30, diagnose="none", onestep=False, transfer=False)


def _sweep(name: str, bug_id: str | None = None, ctrl_outside: float | None = None):
    scenario = load_scenario(name)
    if ctrl_outside is not None:
        scenario = dataclasses.replace(
            scenario, randomize=dataclasses.replace(scenario.randomize, ctrl_outside=ctrl_outside))
    return _bugs.sweep(scenario, CONFIG, by_id(bug_id).patch if bug_id is not None else None)


@pytest.mark.parametrize("scenario, bug_id, field", [
    # a clamp 2% too wide: seen only when a limited actuator's control leaves its range
    ("actuators", "ctrl_clamp_upper", ("act", "qpos", "qvel")),
    # the clamp applied with clampctrl disabled: seen only with the flag off AND a control outside
    ("combinations_implicit", "clampctrl_flag_ignored", ("qpos", "qvel")),
])
def test_a_clamp_bug_is_caught_only_with_controls_outside_their_range(scenario, bug_id, field):
    _bugs.assert_passes_clean(scenario, CONFIG)
    caught = _sweep(scenario, bug_id)
    _bugs.assert_names(caught, _bugs.Expect(field, r"(joint|actuator) '.*'"), bug_id)
    assert caught.first_divergence["member"] == CONFIG.batch - 1, "the member whose controls leave the range"
    inside = _sweep(scenario, bug_id, ctrl_outside=0.0)
    assert inside.status == "pass", f"controls inside their range cannot show a clamp slip: {inside.message}"
