"""Both engines, real: same trajectory structure, agreement where physics says so."""

import dataclasses
import os
import subprocess
import sys

import jax
import numpy as np
import pytest

from mjxdiff.engine.engines import CEngine, MJXEngine, UnsupportedError, compile_count, put_models
from mjxdiff.input.inputs import make_inputs
from mjxdiff.input.scenario import load_model, load_scenario

XML = """<mujoco><option timestep="0.002"/>
<worldbody>
  <body name="p" pos="0 0 1"><joint name="h" type="hinge" axis="0 1 0" stiffness="3" damping="0.1"/>
    <geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.05"/>
    <body pos="0 0 -0.5"><joint name="b" type="ball" stiffness="2"/>
      <geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.05"/></body></body>
  <body name="f" pos="1 0 2"><freejoint/><geom type="box" size=".1 .2 .3"/></body>
</worldbody>
<actuator><motor joint="h" ctrlrange="-1 1"/></actuator>
<sensor><jointpos joint="h"/><framequat objtype="body" objname="f"/></sensor>
</mujoco>"""


@pytest.fixture(scope="module")
def rollouts(tmp_path_factory):
    path = tmp_path_factory.mktemp("m") / "springs.xml"
    path.write_text(XML)
    scenario = dataclasses.replace(load_scenario(path), energy=True)
    m = load_model(scenario)
    inputs = make_inputs(scenario, m, seed=0, batch=4, steps=120)
    return m, inputs, CEngine().rollout(inputs), MJXEngine().rollout(inputs)


def test_same_fields_and_shapes(rollouts):
    m, inputs, c, x = rollouts
    for field in ("qpos", "qvel", "act", "sensordata", "time", "ncon", "energy", "diverged_at"):
        assert np.shape(getattr(c, field)) == np.shape(getattr(x, field)), field
    assert c.qpos.shape == (4, 120, m.nq) and c.energy.shape == (4, 120, 2)


def test_engines_agree_on_a_contact_free_model(rollouts):
    m, inputs, c, x = rollouts
    np.testing.assert_allclose(x.qpos, c.qpos, atol=1e-9, err_msg="qpos, springs model, 120 steps")
    np.testing.assert_allclose(x.qvel, c.qvel, atol=1e-8, err_msg="qvel, springs model, 120 steps")
    np.testing.assert_array_equal(x.time, c.time)
    np.testing.assert_array_equal(c.diverged_at, -1)


def test_jax_energy_matches_c_energy(rollouts):
    _, _, c, x = rollouts
    # potential (gravity, hinge/ball/free springs) and kinetic, before each step
    np.testing.assert_allclose(x.energy, c.energy, rtol=1e-10, atol=1e-10)
    assert np.all(c.energy[..., 1] >= 0)


def test_randomized_members_really_differ(rollouts):
    _, inputs, c, _ = rollouts
    assert len({float(mi.body_mass[1]) for mi in inputs.models}) == 4
    assert not np.allclose(c.qpos[0], c.qpos[1])


def test_varying_parameters_are_batched_leaves(rollouts):
    _, inputs, _, _ = rollouts
    mx, varying = put_models(inputs.models)
    assert any(varying) and not all(varying)
    assert mx.body_mass.shape == (4, len(inputs.models[0].body_mass))
    assert mx.opt.gravity.shape == (4, 3)


def test_one_compile_serves_other_seeds(rollouts):
    m, inputs, _, _ = rollouts
    scenario = load_scenario("pendulum")
    pm = load_model(scenario)
    engine = MJXEngine()
    engine.rollout(make_inputs(scenario, pm, seed=0, batch=4, steps=60))
    before = compile_count()
    engine.rollout(make_inputs(scenario, pm, seed=1, batch=4, steps=60))
    engine.rollout(make_inputs(scenario, pm, seed=2, batch=4, steps=60))
    assert compile_count() == before


SPLIT_CHECK = """
import jax, numpy as np
from mjxdiff.engine.engines import CEngine, MJXEngine, configure_jax, device_count
from mjxdiff.input.inputs import make_inputs
from mjxdiff.input.scenario import load_model, load_scenario
configure_jax("float64")
assert device_count() == 2, device_count()
scenario = load_scenario("cartpole")
inputs = make_inputs(scenario, load_model(scenario), seed=0, batch=3, steps=60)  # 3 members: padded to 4
assert MJXEngine(devices=2).split(3) == 2 and MJXEngine().split(3) == 1  # too small to split by itself
# within rounding, whatever the options: the two batch shapes vectorise differently (seen: 1 ulp;
# bit for bit with XLA's defaults while a piece was a fixed-length scan, not a run-time trip count)
for mode in ("optimized", "fast"):
    one, split = MJXEngine(devices=1, compile=mode).rollout(inputs), MJXEngine(devices=2, compile=mode).rollout(inputs)
    for field in ("qpos", "qvel", "sensordata"):
        np.testing.assert_allclose(getattr(split, field), getattr(one, field), rtol=1e-12, atol=1e-14,
                                   err_msg=f"{mode} {field}")
c = CEngine().rollout(inputs)
np.testing.assert_array_equal(MJXEngine(devices=2, compile="optimized").resync(inputs, c, 10).qpos,
                              MJXEngine(devices=1, compile="optimized").resync(inputs, c, 10).qpos)
print("identical")
"""


def test_device_split_is_bit_identical_to_one_device():
    """MJXDIFF_DEVICES=2 splits the batch over two host devices (padded: 3 members) and changes no number
    beyond rounding; resync, a fixed-length scan, bit for bit."""
    env = dict(os.environ, MJXDIFF_DEVICES="2")
    proc = subprocess.run([sys.executable, "-c", SPLIT_CHECK], env=env, capture_output=True, text=True, timeout=400)
    assert proc.returncode == 0 and "identical" in proc.stdout, proc.stderr[-3000:]


def test_unsupported_feature_named(tmp_path):
    path = tmp_path / "energy.xml"
    path.write_text('<mujoco><option><flag energy="enable"/></option>'
                    '<worldbody><body><joint/><geom size=".1"/></body></worldbody></mujoco>')
    m = load_model(load_scenario(path))
    with pytest.raises(UnsupportedError, match="(?i)energy"):
        put_models((m,))


def _per_member_leaves(models):
    import jax
    from mujoco import mjx

    return [[np.asarray(x) for x in jax.tree.leaves(mjx.put_model(mi))] for mi in models]


@pytest.mark.parametrize("change", ["randomized", "derived"])
def test_put_models_equals_put_model_per_member(change):
    """Stacked leaves read from the C models (one put_model, not B) are put_model's, member by member;
    a field MJX turns into a derived leaf (opt.o_margin -> opt._impl.o_margin) takes the slow path."""
    import jax
    from mujoco import mjx

    from mjxdiff.engine.models import _patched_columns

    scenario = load_scenario("ant")
    models = list(make_inputs(scenario, load_model(scenario), 3, 5, 2).models)
    if change == "derived":
        for i, mi in enumerate(models):
            mi.opt.o_margin = 1e-3 * i
    assert (_patched_columns(models, mjx.put_model(models[0])) is None) == (change == "derived")
    mx, varying = put_models(tuple(models))
    leaves = [np.asarray(x) for x in jax.tree.leaves(mx)]
    for i, expected in enumerate(_per_member_leaves(models)):
        for k, (leaf, want) in enumerate(zip(leaves, expected, strict=True)):
            np.testing.assert_array_equal(leaf[i] if varying[k] else leaf, want)


@pytest.mark.parametrize("saved", [False, True], ids=["jit", "export_cache"])
def test_pieces_of_a_stream_share_one_compiled_function(saved, monkeypatch):
    """Every piece runs the same executable: the carried MJX data keeps the shardings and commitment
    the first piece was given (an empty leaf once came back replicated and cost a second compile)."""
    from mjxdiff.engine import engines, export_cache

    if not saved:
        monkeypatch.setattr(export_cache, "export_dir", lambda: None)
    engines.clear_compiled()
    scenario = load_scenario("cartpole")
    inputs = make_inputs(scenario, load_model(scenario), seed=5, batch=2, steps=21)
    pieces = list(MJXEngine().stream(inputs, 7))
    assert len(pieces) == 3
    # one ahead-of-time compiled executable, which raises rather than recompiles for arguments
    # sharded or committed differently: every piece ran it
    [(_, run, choice)] = export_cache._FUNCTIONS.values()
    assert isinstance(run, jax.stages.Compiled)
    assert choice["level"] in ("fast", "balanced")


def test_xla_options_follow_the_planned_horizon(monkeypatch):
    """A short run planned for a longer horizon (``--quick`` after the full run's plan) chooses
    XLA's options for the planned stepping, so both compile one executable; a run planned for
    its own steps chooses for those (before, the quick run of a scenario stepped in pieces got
    ``fast`` where the full run got ``balanced``, and XLA compiled the loaded rollout again)."""
    from mjxdiff.engine import xla

    asked = []
    choose = xla.xla_options
    monkeypatch.setattr(xla, "xla_options", lambda mode, steps: asked.append(steps) or choose(mode, steps))
    scenario = load_scenario("pendulum")
    inputs = make_inputs(scenario, load_model(scenario), seed=0, batch=2, steps=10)
    engine = MJXEngine()
    engine.first_piece(inputs, 10)
    engine.first_piece(dataclasses.replace(inputs, horizon=35), 10)
    engine.first_piece(dataclasses.replace(inputs.members(np.array([0, 0])), horizon=35), 10)
    assert asked == [10, 40, 40]


def test_automatic_split_needs_enough_members_per_device():
    from mjxdiff.engine.engines import MEMBERS_PER_DEVICE, SPLIT_MIN_MEMBERS, device_count

    n = device_count()
    assert MJXEngine().split(n * SPLIT_MIN_MEMBERS) == n
    assert MJXEngine().split(n * SPLIT_MIN_MEMBERS - 1) == (1 if n > 1 else n)
    assert MJXEngine(devices=1).split(1000) == 1
    assert MJXEngine().batch_cap() == n * MEMBERS_PER_DEVICE and MJXEngine(devices=1).batch_cap() == MEMBERS_PER_DEVICE


def test_c_members_do_not_depend_on_their_batch_neighbours():
    """The sweep steps C's reference and perturbed rerun as one batch: each member's records must be
    those it has alone."""
    from mjxdiff.compare.noise import perturb

    scenario = load_scenario("cartpole")
    inputs = make_inputs(scenario, load_model(scenario), seed=4, batch=3, steps=40)
    moved = perturb(inputs, "float64")
    both = CEngine().rollout(inputs.concat(moved))
    for part, rows in ((CEngine().rollout(inputs), slice(0, 3)), (CEngine().rollout(moved), slice(3, 6))):
        for field in ("qpos", "qvel", "act", "sensordata", "time", "ncon", "diverged_at"):
            np.testing.assert_array_equal(getattr(both, field)[rows], getattr(part, field), err_msg=field)


def test_c_s_float32_shadow_moves_only_its_rows_the_same_however_the_steps_are_cut():
    """``CEngine.stream``'s ``jitter`` (the sweep's float32 shadow of C): a row with none is the
    plain rollout bit for bit, a jittered row parts from it by about its size at the first
    step, and pieces of any length give the same records."""
    from mjxdiff.compare.noise import STEP_JITTER
    from mjxdiff.engine.trajectory import concat

    scenario = load_scenario("cartpole")
    inputs = make_inputs(scenario, load_model(scenario), seed=4, batch=2, steps=30)
    both = inputs.concat(inputs)
    jitter = np.array([0.0, 0.0, STEP_JITTER["float32"], STEP_JITTER["float32"]])
    whole = concat(list(CEngine().stream(both, 30, jitter)))
    cut = concat(list(CEngine().stream(both, 7, jitter)))
    plain = CEngine().rollout(inputs)
    for field in ("qpos", "qvel", "sensordata", "time", "ncon"):
        np.testing.assert_array_equal(getattr(whole, field), getattr(cut, field), err_msg=field)
        np.testing.assert_array_equal(getattr(whole, field)[:2], getattr(plain, field), err_msg=field)
    first = np.abs(whole.qvel[2:, 1] - plain.qvel[:, 1]).max()  # after one move
    assert whole.qpos[2:, 0].tobytes() == plain.qpos[:, 0].tobytes()  # records are taken before the move
    assert 0 < first < 1e3 * STEP_JITTER["float32"] * max(1.0, np.abs(plain.qvel).max())


def test_a_held_piece_is_bound_once_and_steps_as_a_fresh_one(monkeypatch):
    """Within ``holding()``, the stream and the one-step check's first piece of the same models
    share one bind (the code digested and the models put on the devices once); outside it every
    call binds afresh. Either way the records are the same, and ``first_piece(steps=1)`` is the
    stream's first step."""
    from mjxdiff.engine import export_cache

    scenario = load_scenario("cartpole")
    m = load_model(scenario)
    inputs = make_inputs(scenario, m, seed=0, batch=2, steps=30)
    engine = MJXEngine()
    binds = []
    bind = export_cache.bind
    monkeypatch.setattr(export_cache, "bind", lambda *a, **k: binds.append(1) or bind(*a, **k))
    fresh = np.concatenate([p.qpos for p in engine.stream(inputs, 10)], axis=1)
    assert len(binds) == 1
    with engine.holding():
        held = np.concatenate([p.qpos for p in engine.stream(inputs, 10)], axis=1)
        first = engine.first_piece(inputs, 10, steps=1)
    assert len(binds) == 2, "the held stream bound once, its first piece reused it"
    np.testing.assert_array_equal(held, fresh)
    assert first.qpos.shape == (2, 1, m.nq)
    np.testing.assert_array_equal(first.qpos[:, 0], fresh[:, 0])
    engine.first_piece(inputs, 10, steps=1)
    assert len(binds) == 3, "outside the block: bound afresh"


def test_a_held_piece_is_not_shared_across_precisions():
    """A float32 sweep's float64 ablation steps the same model objects within the scenario's
    ``holding()`` block: it gets a float64 piece of its own, not the float32 one held (which made
    every float32 failure's ``precision`` ablation fail, and named another cause)."""
    from mjxdiff.compat import enable_x64

    scenario = load_scenario("pendulum")
    m = load_model(scenario)
    inputs = make_inputs(scenario, m, seed=0, batch=2, steps=10)
    engine = MJXEngine()
    with engine.holding():
        with enable_x64(False):
            single = engine.first_piece(inputs, 10, steps=10)
        with enable_x64(True):
            double = engine.first_piece(inputs, 10, steps=10)
    assert single.qpos.dtype == np.float32 and double.qpos.dtype == np.float64
    c = CEngine().rollout(inputs).qpos
    assert np.abs(double.qpos - c).max() < 1e-12 < np.abs(single.qpos - c).max()
