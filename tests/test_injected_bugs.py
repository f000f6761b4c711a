"""The catalogue of injected MJX bugs (tests/injected_bugs.py) against the one-step check: a
representative bug from each of five categories is caught, by orders of magnitude, and named by
field, object and step, while the same model unmodified stays far inside its bound. The whole
catalogue is run by benchmarks/scripts/injected_bugs.py (every bug costs an MJX compile)."""

import contextlib
from pathlib import Path

import pytest

import _bugs
from injected_bugs import BUGS, CATEGORIES, by_id
from mjxdiff.compare import onestep
from mjxdiff.engine.engines import CEngine, MJXEngine
from mjxdiff.input.inputs import make_inputs
from mjxdiff.input.scenario import load_model, load_scenario

#: One bug per category here, five categories: (bug id, field it must be caught in, object prefix).
SUBSET = (
    ("quat_integrate_angle", "qpos", "joint 'root'"),
    ("actuator_bias", "qvel", "joint "),
    ("contact_normal_tilt", "qvel", "joint "),
    ("constraint_impedance", "qvel", "joint "),
    ("accelerometer_gravity", "sensordata", "sensor 'imu_acc' (accelerometer)"),
)


def _setup(repo_root: Path, model: str):
    scenario = load_scenario(str(repo_root / "tests" / "data" / model))
    m = load_model(scenario)
    inputs = make_inputs(scenario, m, seed=0, batch=4, steps=120)
    return scenario, m, inputs, CEngine().rollout(inputs)


@pytest.fixture(scope="module")
def models(repo_root):
    """(scenario, model, inputs, C's rollout) per catalogue model, made on first use."""
    made = {}

    def get(model: str):
        if model not in made:
            made[model] = _setup(repo_root, model)
        return made[model]

    return get


def _check(setup) -> dict:
    scenario, m, inputs, traj_c = setup
    return onestep.check(m, inputs, traj_c, scenario.tolerance, MJXEngine(), CEngine())


def test_the_catalogue_covers_every_category_with_distinct_bugs(repo_root):
    assert len(BUGS) >= 12 and len({b.id for b in BUGS}) == len(BUGS)
    assert {b.category for b in BUGS} == set(CATEGORIES)
    assert {
        "kinematics and orientation integration", "inertia", "actuator gain", "actuator bias", "passive forces",
        "contact geometry and frames", "constraint impedance and reference", "friction cones", "sensors",
    } <= set(CATEGORIES)
    for bug in BUGS:
        assert (repo_root / "tests" / "data" / bug.model).is_file(), bug
        assert bug.description and by_id(bug.id) is bug
    assert {b.model for b in BUGS if b.category == "sensors"} == {"quadruped_1iter_sensors.xml"}


def test_every_patch_is_undone_with_its_monkeypatch():
    import mujoco.mjx._src as src
    from mujoco.mjx._src import collision_driver

    modules = {name: getattr(src, name) for name in (
        "collision_primitive", "constraint", "derivative", "forward", "math", "passive", "sensor", "smooth",
        "solver", "support")}
    before = {name: dict(vars(mod)) for name, mod in modules.items()}
    table = dict(collision_driver._COLLISION_FUNC)
    with pytest.MonkeyPatch.context() as mp:
        for bug in BUGS:
            bug.patch(mp)
        changed = [name for name, mod in modules.items() if dict(vars(mod)) != before[name]]
        assert changed and collision_driver._COLLISION_FUNC != table
    assert all(dict(vars(mod)) == before[name] for name, mod in modules.items())
    assert collision_driver._COLLISION_FUNC == table


@pytest.mark.parametrize("model", sorted({by_id(bug_id).model for bug_id, _, _ in SUBSET}))
def test_unmodified_mjx_is_far_inside_its_bound(models, model, fresh_mjx):
    found = _check(models(model))
    assert found["status"] == "pass" and found["ratio"] < 0.05, found


def _switched(model: str) -> list:
    """The subset's bugs for ``model``, switched in one compile of it (_bugs.install_switched), but
    the quaternion one: it patches a function given no model to read the switch from."""
    return [b.patch for b in map(by_id, (s[0] for s in SUBSET)) if b.model == model and b.id != "quat_integrate_angle"]


@pytest.mark.parametrize("bug_id, field, object_prefix", SUBSET, ids=[s[0] for s in SUBSET])
def test_an_injected_bug_is_caught_and_named(models, bug_id, field, object_prefix, monkeypatch, fresh_mjx):
    bug = by_id(bug_id)
    setup = models(bug.model)
    among = _switched(bug.model)
    if bug.patch in among:
        patched = _bugs.live(bug.patch, among, (setup[1], *setup[2].models))
    else:
        bug.patch(monkeypatch)
        patched = contextlib.nullcontext()
    with patched:
        found = _check(setup)
    assert found["status"] == "fail" and found["ratio"] > 10, (bug.id, found)
    assert found["field"] == field and found["object"].startswith(object_prefix), (bug.id, found)
    assert 0 <= found["step"] < setup[2].steps, (bug.id, found)
    if field == "sensordata":  # a sensor bug leaves the dynamics alone
        assert max(found["ratios"].get(f, 0.0) for f in ("qpos", "qvel")) < 0.05, (bug.id, found)
