"""One scenario's trouble stays that scenario's: a diagnosis step or an ablation that raises
becomes a line of that scenario's diagnosis, the verdict stands, and the sweep goes on."""

import json
from pathlib import Path

import mujoco
import pytest

from mjxdiff.compare import diagnose
from mjxdiff.output import report
from mjxdiff.input.scenario import load_scenario
from mjxdiff.runner.sweep import SweepConfig, sweep
from tests.test_detection import extra_damping


def _refused_by_mjx(m: mujoco.MjModel) -> None:
    """An ablation MJX cannot run: the override flag makes put_model raise NotImplementedError."""
    m.opt.enableflags |= int(mujoco.mjtEnableBit.mjENBL_OVERRIDE)


def _raises_in_c(m: mujoco.MjModel) -> None:
    raise ValueError("this edit cannot be made")


@pytest.fixture
def two_ablations_that_cannot_run(monkeypatch):
    monkeypatch.setattr(diagnose, "ABLATIONS", (
        ("solver convergence", "override flag", _refused_by_mjx),
        ("integration", "broken edit", _raises_in_c),
        ("integration", "timestep / 4", diagnose._quarter_timestep),
    ))


def test_ablations_that_raise_are_lines_of_the_diagnosis(fresh_mjx, monkeypatch, two_ablations_that_cannot_run,
                                                         tmp_path):
    extra_damping(monkeypatch)
    config = SweepConfig(seed=0, batch=2, steps=100, diagnose="full", reproducers=str(tmp_path))
    first, second = sweep([load_scenario("pendulum"), load_scenario("cartpole")], config)
    assert first.status == "fail" and first.first_divergence["field"] in ("qpos", "qvel", "sensordata")
    tried = first.diagnosis["cause"]["tried"]
    assert [t["passed"] for t in tried] == [None, None, False], tried
    assert "mjENBL_OVERRIDE" in tried[0]["error"] and "cannot be made" in tried[1]["error"]
    assert first.diagnosis["cause"]["cause"] == diagnose.GENUINE  # the one ablation that ran did not pass
    assert "ablation 'override flag' could not run" in first.message
    assert "ablation 'broken edit' could not run: ValueError: this edit cannot be made" in first.message
    assert first.pending and not Path(first.pending[0][1]).exists(), "the sweep itself writes nothing"
    first = report.write_pending(first)  # the caller's output step
    assert first.info["reproducer"], "the reproducer is still written"
    assert report.validate(json.loads(Path(first.info["reproducer"]).read_text()), "reproducer") == []
    assert second.name == "cartpole" and second.status in ("pass", "fail"), "the sweep went on"


def test_no_ablation_running_is_unclassified_not_genuine(fresh_mjx, monkeypatch):
    extra_damping(monkeypatch)
    monkeypatch.setattr(diagnose, "ABLATIONS", (("integration", "broken edit", _raises_in_c),))
    [result] = sweep([load_scenario("pendulum")], SweepConfig(seed=0, batch=2, steps=100, diagnose="full"))
    assert result.status == "fail"
    assert result.diagnosis["cause"]["cause"] == diagnose.UNCLASSIFIED


def test_a_drill_down_that_raises_leaves_the_verdict_and_the_rest(fresh_mjx, monkeypatch):
    extra_damping(monkeypatch)

    def broken(*args, **kwargs):
        raise RuntimeError("drill-down exploded")

    monkeypatch.setattr(diagnose, "drill_down", broken)
    [result] = sweep([load_scenario("pendulum")], SweepConfig(seed=0, batch=2, steps=100, diagnose="basic"))
    assert result.status == "fail"
    assert "drill-down could not run: RuntimeError: drill-down exploded" in result.message
    assert "local_error" in result.diagnosis and "drill_down" not in result.diagnosis


@pytest.mark.parametrize("where", ["_prepare", "_finish"])
@pytest.mark.parametrize("workers", [0, 2])
def test_an_internal_error_is_that_scenarios_error(monkeypatch, where, workers):
    """mjxdiff failing on one scenario, while it is prepared and compiled (ahead, on a compile
    worker, or in order) or while it runs, is that scenario's error; the next one runs."""
    import mjxdiff.runner.sweep as sweep_module

    real = getattr(sweep_module, where)

    def flaky(first, *args, **kwargs):
        scenario = first if where == "_prepare" else first.scenario
        if scenario.name == "pendulum":
            raise KeyError("boom")
        return real(first, *args, **kwargs)

    monkeypatch.setattr(sweep_module, where, flaky)
    first, second = sweep([load_scenario("pendulum"), load_scenario("cartpole")],
                          SweepConfig(seed=0, batch=2, steps=30, diagnose="none", compile_workers=workers))
    assert (first.status, first.error_kind) == ("error", "internal") and "KeyError" in first.message
    assert second.status == "pass", second.message


def test_a_crowded_process_lets_go_of_its_compiled_functions():
    """A long sweep must not run into the kernel's memory-map limit (LLVM then fails and the
    process segfaults): past the budget, compiled functions are dropped and the maps freed."""
    from mjxdiff.runner.plan import _memory_maps, release_compiled_if_crowded
    from mjxdiff.runner.sweep import SweepConfig, run_scenario

    run_scenario(load_scenario("pendulum"), SweepConfig(batch=2, steps=20, diagnose="none"))
    held, limit = _memory_maps()
    assert limit > 0 and held > 0
    assert release_compiled_if_crowded(budget=1.0) is False
    assert release_compiled_if_crowded(budget=0.0) is True
    assert _memory_maps()[0] < held, "dropping the compiled functions frees their memory maps"
    again = run_scenario(load_scenario("pendulum"), SweepConfig(batch=2, steps=20, diagnose="none"))
    assert again.status == "pass", "and the next scenario compiles or loads them again"
