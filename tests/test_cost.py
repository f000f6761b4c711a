"""mjxdiff.input.cost: MJX's collision functions and costs read from a model, and the plan that fits."""

import pytest

from mjxdiff.input import adjust, cost
from mjxdiff.input.scenario import load_model, load_scenario

GB = 2**30


@pytest.fixture(scope="module")
def convex_mesh():
    return load_model(load_scenario("convex_mesh"))


def test_pair_groups_are_mjx_collision_functions_with_hull_sizes(convex_mesh):
    from mujoco.mjx._src import collision_driver

    groups, _ = cost.pair_groups(convex_mesh)
    assert sum(g.pairs for g in groups) == len(list(collision_driver.geom_pairs(convex_mesh)))
    mesh_mesh = [g for g in groups if g.types == ("mesh", "mesh")]
    assert mesh_mesh and all(h is not None and h[0] >= 4 for g in mesh_mesh for h in g.hulls)
    # costliest first, and a hull pair costs more than a primitive pair
    works = [g.work * g.pairs for g in groups]
    assert works == sorted(works, reverse=True)
    primitive, _ = cost.pair_groups(load_model(load_scenario("primitive_pairs")))
    assert min(g.work for g in mesh_mesh) > 1 == max(g.work for g in primitive if g.hulls == (None, None))


def test_estimate_grows_with_hull_pairs(convex_mesh):
    small = cost.estimate(load_model(load_scenario("pendulum")))
    big = cost.estimate(convex_mesh)
    assert big.compile_s > small.compile_s and big.member_bytes > small.member_bytes
    assert "mesh-mesh pairs" in big.line() and "per member" in big.line()
    assert small.costly == () and small.pairs_text() == ""


def test_a_compile_past_the_budget_stops_before_anything_runs(convex_mesh):
    est = cost.estimate(convex_mesh)
    stop = cost.plan(est, 8, 200, 8, budget_s=est.compile_s, memory_bytes=None)
    assert stop.kind == "budget" and est.line() in stop.stop and "--budget" in stop.stop
    assert cost.plan(est, 8, 200, 8, budget_s=1e6, memory_bytes=None) == cost.Plan(8, 200, 8)


def test_stepping_past_the_budget_shortens_the_horizon_then_the_batch():
    est = cost.Estimate(compile_s=60.0, member_bytes=2**20, step_s=0.1)
    # 0.6 x 600 s - 60 s of compile leaves 300 s: 300 / (2.5 x 0.1 s) = 1200 member-steps
    fit = cost.plan(est, 8, 200, 8, budget_s=600.0, memory_bytes=None)
    assert (fit.batch, fit.steps, fit.stop) == (8, 150, None)
    assert fit.changed == ("steps 200 -> 150 (~0.1 s per member-step, budget 10 min)",)
    fit = cost.plan(est, 8, 200, 8, budget_s=150.0, memory_bytes=None)  # 30 s: 120 member-steps
    assert (fit.batch, fit.steps) == (6, 20) and fit.group == 6 and len(fit.changed) == 2
    stop = cost.plan(est, 8, 200, 8, budget_s=110.0, memory_bytes=None)  # 6 s: 24 member-steps
    assert stop.kind == "budget" and "even 2 members x 20 steps" in stop.stop


def test_the_group_shrinks_to_the_memory_left_and_says_so():
    est = cost.Estimate(compile_s=5.0, member_bytes=GB, compile_bytes=GB)
    held = 2 * GB
    fit = cost.plan(est, 8, 200, 8, None, memory_bytes=held + GB + 3.5 * GB, held_bytes=held)
    assert fit.group == 3 and fit.stop is None and (fit.batch, fit.steps) == (8, 200)
    assert fit.changed and "8 -> 3" in fit.changed[0]
    none = cost.plan(est, 8, 200, 8, None, memory_bytes=held + GB + 0.5 * GB, held_bytes=held)
    assert none.kind == "memory" and "one member does not fit" in none.stop and "--max-memory" in none.stop
    assert cost.plan(est, 8, 200, 8, None, memory_bytes=100 * GB, held_bytes=held).group == 8


def test_hlo_features_count_ops_and_tensor_bytes():
    text = """func.func @main(%arg0: tensor<8x3xf64>) -> tensor<8x3xf64> {
    %0 = stablehlo.add %arg0, %arg0 : tensor<8x3xf64>
    %1 = stablehlo.while(%iterArg = %0) : tensor<8x3xf64>
    %2 = stablehlo.convert %1 : (tensor<8x3xf64>) -> tensor<8x3xi32>
    }"""
    f = cost.hlo_features(text)
    assert f["ops"] == 3 and f["whiles"] == 1
    assert f["largest_bytes"] == 8 * 3 * 8 and f["result_bytes"] == 2 * 192 + 96


def test_drop_costly_pairs_removes_only_hull_hull_pairs(convex_mesh):
    scenario = load_scenario("convex_mesh")
    bad = adjust.costly_pairs(convex_mesh)
    assert bad and all("mesh" in why for *_, why in bad)
    dropped, lines = adjust.for_mjx(convex_mesh, scenario.model_path, adjust=False, costly=True)
    assert lines and "--drop-costly-pairs" in lines[0]
    assert adjust.costly_pairs(dropped) == []
    assert str(len(bad)) in lines[0].split("dropped ")[1]


def test_newton_with_elliptic_cones_costs_per_contact_and_nefc_squared():
    """MJX's Newton solver builds a dense nefc x nefc cone Hessian, one unrolled update per contact."""
    import copy

    import mujoco

    elliptic = load_model(load_scenario("box_stack"))
    assert elliptic.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC
    pyramidal = copy.copy(elliptic)
    pyramidal.opt.cone = mujoco.mjtCone.mjCONE_PYRAMIDAL
    a, b = cost.estimate(elliptic), cost.estimate(pyramidal)
    assert a.ncon == b.ncon > 0 and a.cone_s == pytest.approx(cost.COMPILE_PER_CONE_S * a.ncon) and b.cone_s == 0
    assert a.compile_s - b.compile_s == pytest.approx(a.cone_s)
    assert a.member_bytes > 8 * a.nefc**2 + elliptic.nbuffer
