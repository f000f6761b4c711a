"""The artifact key is complete: every MJX or mjxdiff function whose code a bundled scenario's
rollout trace runs (seen by ``sys.settrace``, independently of how the key is found) is in the key
its artifact is saved with, by a digest taken over that very code (:func:`export_cache.audit`)."""

import pytest

from mjxdiff.engine import engines, export_cache
from mjxdiff.input.adjust import for_mjx
from mjxdiff.input.inputs import make_inputs
from mjxdiff.input.scenario import bundled_scenarios, load_model, load_scenario

#: Bundled scenarios whose traces, together, run every MJX and mjxdiff code object that any
#: bundled scenario's trace runs (a greedy set cover, from
#: ``python benchmarks/scripts/cache_completeness.py``, which audits every bundled scenario:
#: 13 of 28, about half the audit time).
COVER = ("cg_frictionless", "combinations", "combinations_implicit", "convex_mesh", "gravcomp_arm",
         "imu_sensors", "integrator_rk4", "joint_parameters", "lidar", "muscles_and_limits",
         "primitive_pairs", "primitives_on_plane", "sensing")


def _audit(name: str) -> tuple[list[str], list[str], dict[str, str] | str]:
    scenario = load_scenario(name)
    m, _ = for_mjx(load_model(scenario), scenario.model_path)
    (fn, args, static), _, _ = engines.MJXEngine(devices=1).piece(make_inputs(scenario, m, seed=0, batch=2, steps=4), 4)
    return export_cache.audit(fn, args, static)


def test_the_cover_names_bundled_scenarios():
    assert set(COVER) <= {s.name for s in bundled_scenarios()}


@pytest.mark.slow
def test_every_function_a_bundled_scenario_traces_is_in_its_artifacts_key():
    """Fails before issue 49's fix: on a venv every file under lib/python3.X (MJX included) was
    left out, and of MJX's ``@collider`` wrappers (one qualname) only the first closure was
    followed, so ``plane_capsule``, ``plane_cylinder``, ``plane_ellipsoid`` (and every collider
    after the first) were neither named nor digested."""
    missed, runs = {}, {}
    for name in COVER:
        ran, missing, deps = _audit(name)
        assert isinstance(deps, dict), f"{name}: the artifact would not be saved: {deps}"
        runs[name] = ran
        if missing:
            missed[name] = missing
    assert not missed, f"code a trace ran that its key would not see changing: {missed}"
    assert all(len(ran) > 100 for ran in runs.values()), {n: len(r) for n, r in runs.items()}
    colliders = {line.rsplit(":", 1)[1] for line in runs["primitives_on_plane"] if "collision_primitive" in line}
    assert {"plane_capsule", "plane_cylinder", "plane_ellipsoid", "_plane_sphere"} <= colliders, colliders
