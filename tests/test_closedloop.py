"""Closed loop (mjxdiff.tools.closedloop): a brax environment on the MJX backend driven by a real,
randomly initialised brax PPO network, on MJX and on MuJoCo C. Unmodified MJX gives the same
episodes as C; a 2% actuator gain slip in MJX fails, with the first separation named; the
three policy forms load; a bad spec is one line and exit 2."""

import json
from pathlib import Path
import textwrap

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from brax.io import model as brax_model
from brax.training.acme import running_statistics, specs
from brax.training.agents.ppo import checkpoint as ppo_checkpoint
from brax.training.agents.ppo import networks as ppo_networks
from mujoco.mjx._src import forward as mjx_forward

from mjxdiff.output import report
from mjxdiff.tools import closedloop, closedloop_streams
from mjxdiff.compare import diagnose
from mjxdiff.cli import main

EPISODES, STEPS = 4, 40


@pytest.fixture(scope="module")
def x64():
    with jax.enable_x64(True):
        yield


@pytest.fixture(scope="module")
def env(x64):
    return closedloop.make_env("inverted_pendulum")


@pytest.fixture(scope="module")
def params(env):
    """A randomly initialised brax PPO network (the architecture brax trains), seed 0."""
    network = ppo_networks.make_ppo_networks(env.observation_size, env.action_size)
    key = jax.random.PRNGKey(0)
    normalizer = running_statistics.init_state(jax.ShapeDtypeStruct((env.observation_size,), jnp.float64))
    return network, (normalizer, network.policy_network.init(key), network.value_network.init(key))


@pytest.fixture(scope="module")
def checkpoint_dir(env, params, tmp_path_factory):
    """Written by brax's own PPO checkpoint code, as its training loop writes it."""
    path = tmp_path_factory.mktemp("ckpt")
    # the observation size as brax's PPO training passes it (a shape spec, not an int)
    obs_spec = specs.Array((env.observation_size,), jnp.dtype("float32"))
    config = ppo_checkpoint.network_config(obs_spec, env.action_size, True, ppo_networks.make_ppo_networks)
    ppo_checkpoint.save(str(path), 0, params[1], config)
    return next(p for p in path.iterdir() if p.is_dir())


@pytest.fixture(scope="module")
def clean(env, checkpoint_dir):
    policy = closedloop.load_policy(str(checkpoint_dir), env)
    comparison = closedloop.run(env, policy, EPISODES, STEPS, seed=0)
    return comparison, closedloop.judge(closedloop.c_model(env), comparison, n_frames=env._n_frames)


def test_unmodified_mjx_gives_c_s_episodes(clean):
    comparison, result = clean
    assert result["status"] == "pass", result["message"]
    s = comparison.summaries
    np.testing.assert_array_equal(s["mjx"].length, s["c"].length)
    assert comparison.separation["mjx"] < 1e-9 and comparison.obs_separation["mjx"] < 1e-9
    assert result["first_separation"] is None
    assert np.isfinite(result["gap"]["ci95"]).all() and result["test"] == closedloop.TEST
    assert {"|action|", "|Δaction|", "|qvel|"} <= set(result["behaviour"])
    assert not any(b["out_of_band"] for b in result["behaviour"].values()), result["behaviour"]


def _slip(monkeypatch, after: float = -1.0):
    """MJX's actuator gains 2% high once the simulation time passes ``after`` seconds."""
    orig = mjx_forward.fwd_actuation
    monkeypatch.setattr(mjx_forward, "fwd_actuation", lambda m, d: orig(
        m.replace(actuator_gainprm=m.actuator_gainprm * jnp.where(d.time > after, 1.02, 1.0)), d))


def test_a_two_percent_gain_slip_fails_and_names_the_first_separation(env, checkpoint_dir, monkeypatch, clean):
    _slip(monkeypatch)
    policy = closedloop.load_policy(str(checkpoint_dir), env)
    comparison = closedloop.run(env, policy, EPISODES, STEPS, seed=0)
    result = closedloop.judge(closedloop.c_model(env), comparison, n_frames=env._n_frames)
    assert result["status"] == "fail", result["message"]
    first = result["first_separation"]
    assert first is not None and first["step"] == 0 and first["joint"] in ("slider", "hinge")
    assert "first separation at control step 0" in result["message"]
    assert first["drill_down"]["first_stage"] == "actuation", first["drill_down"]
    assert first["drill_down"]["substep"] == 0
    assert "first stage to differ from C's state there (substep 0): actuation" in result["message"]
    # one control step from C's state differs beyond the floor under every ablation: MJX's own
    assert first["cause"]["cause"] == diagnose.GENUINE, first["cause"]
    assert first["cause"]["local_error"] > first["cause"]["local_floor"]
    # C and its perturbed rerun did not change: the slip is MJX's alone
    np.testing.assert_array_equal(comparison.summaries["c"].returns, clean[0].summaries["c"].returns)


def test_where_one_control_step_agrees_the_cause_is_accumulation(env):
    """Unmodified MJX from a C state agrees within the one-step floor: a separation found
    there grew over earlier steps, and attribution says so instead of blaming a stage."""
    m = closedloop.c_model(env)
    state = dict(qpos=m.qpos0 + 0.05, qvel=np.full(m.nv, 0.3), qacc_warmstart=None, ctrl=np.full(m.nu, 0.5))
    cause = closedloop.attribute(m, dict(c_state=state), n_frames=env._n_frames)
    assert cause["cause"] == closedloop.ACCUMULATED, cause
    assert cause["local_error"] <= cause["local_floor"] and cause["local_error"] < 1e-12


def test_streamed_in_chunks_the_verdict_is_the_same(env, checkpoint_dir, monkeypatch):
    """A slip that starts at t = 0.5 s separates inside the run; chunks of 7 control steps
    (crossing it) give the same first separation, C state and summaries as one chunk."""
    _slip(monkeypatch, after=0.5)
    policy = closedloop.load_policy(str(checkpoint_dir), env)
    whole, chunked = (closedloop.run(env, policy, EPISODES, STEPS, seed=0, chunk=k) for k in (STEPS, 7))
    assert whole.first is not None and whole.first["step"] > 7, whole.first
    assert chunked.first == whole.first
    for name, s in whole.summaries.items():
        np.testing.assert_array_equal(chunked.summaries[name].returns, s.returns)
        for k, v in s.behaviour.items():
            np.testing.assert_allclose(chunked.summaries[name].behaviour[k], v, rtol=1e-12, err_msg=k)


def test_summaries_count_steps_up_to_the_first_done_across_chunks():
    rng = np.random.default_rng(0)
    B, T, nq = 3, 10, 2
    done = np.zeros((B, T))
    done[0, 3], done[0, 6], done[1, 9] = 1, 1, 1  # episode 0 ends at step 3, 1 at the last, 2 never
    reward, action, qvel = rng.normal(size=(B, T)), rng.normal(size=(B, T, 1)), rng.normal(size=(B, T, nq))
    zeros = np.zeros((B, T, nq))

    def chunk(a, b):
        return closedloop.Episodes(obs=zeros[:, a:b], action=action[:, a:b], reward=reward[:, a:b],
                                   done=done[:, a:b], qpos=zeros[:, a:b], qvel=qvel[:, a:b], ctrl=action[:, a:b],
                                   metrics={"speed": 2 * reward[:, a:b]}, qpos0=zeros[:, 0], qvel0=zeros[:, 0],
                                   obs0=zeros[:, 0])

    m = mujoco.MjModel.from_xml_string("<mujoco><worldbody><body><joint/><geom size='.1'/></body>"
                                       "<body pos='1 0 0'><joint/><geom size='.1'/></body></worldbody></mujoco>")
    for cuts in ([0, T], [0, 2, 5, 6, T]):
        tally = closedloop._Tally(m, ["mjx", "c", "c_perturbed"], 1e-6)
        for a, b in zip(cuts, cuts[1:]):
            tally.add({k: chunk(a, b) for k in ("mjx", "c", "c_perturbed")})
        s = tally.result().summaries["c"]
        np.testing.assert_array_equal(s.length, [4, 10, 10])
        np.testing.assert_array_equal(s.terminated, [True, True, False])
        np.testing.assert_allclose(s.returns, [reward[0, :4].sum(), reward[1].sum(), reward[2].sum()])
        np.testing.assert_allclose(s.behaviour["speed"], 2 * s.returns / s.length)
        np.testing.assert_allclose(s.behaviour["|Δaction|"][1], np.abs(np.diff(action[1, :, 0])).sum() / T)
        assert tally.result().first is None


def test_the_three_policy_forms_load_and_act(env, params, checkpoint_dir, tmp_path, monkeypatch):
    obs, key = jnp.zeros(env.observation_size), jax.random.PRNGKey(1)
    from_checkpoint = closedloop.load_policy(str(checkpoint_dir), env)
    params_file = tmp_path / "params.pkl"
    brax_model.save_params(str(params_file), params[1])
    from_params = closedloop.load_policy(f"{params_file}::brax.training.agents.ppo.networks:make_ppo_networks", env)
    (tmp_path / "my_policy.py").write_text(textwrap.dedent("""
        import jax.numpy as jnp

        def policy(obs, key):
            return jnp.tanh(-obs[:1] - obs[1:2])
    """))
    monkeypatch.syspath_prepend(str(tmp_path))
    from_function = closedloop.load_policy("my_policy:policy", env)
    a1, a2, a3 = (np.asarray(p(obs, key)[0]) for p in (from_checkpoint, from_params, from_function))
    assert a1.shape == a2.shape == a3.shape == (env.action_size,)
    np.testing.assert_allclose(a1, a2)  # the same network and parameters


def test_a_failing_run_saves_its_episode_and_replay_reruns_it(checkpoint_dir, tmp_path, monkeypatch, capsys):
    with monkeypatch.context() as patch:
        _slip(patch)
        assert main(["policy", "inverted_pendulum", "--policy", str(checkpoint_dir), "--episodes", "3",
                     "--steps", "20", "--out", str(tmp_path)]) == 1
        saved = json.loads((tmp_path / "policy-reproducer.json").read_text())
        assert report.validate(saved, "policy-reproducer") == []
        assert saved["episode"] == 0 and saved["config"]["episodes"] == 3 and saved["policy"] == str(checkpoint_dir)
        assert main(["policy", "--replay", str(tmp_path / "policy-reproducer.json")]) == 1
        assert "first separation at control step 0 of episode 0" in capsys.readouterr().out
    assert main(["policy", "--replay", str(tmp_path / "policy-reproducer.json")]) == 0  # unmodified MJX


@pytest.mark.parametrize("target, spec, says", [
    ("inverted_pendulum", "no/such/dir", "not a checkpoint directory"),
    ("inverted_pendulum", "no_such_module:policy", "cannot import"),
    ("inverted_pendulum", "missing.pkl::brax.training.agents.ppo.networks:make_ppo_networks", "no such parameters"),
    ("no_such_env", "mjxdiff:x", "not a brax environment"),
    (None, "no_such_reproducer.json", "not a policy reproducer"),
])
def test_a_bad_spec_is_one_line_and_exit_2(target, spec, says, capsys):
    assert main(["policy", target, "--policy", spec] if target else ["policy", "--replay", spec]) == 2
    err = capsys.readouterr().err.strip()
    assert says in err and "\n" not in err and "Traceback" not in err


def test_cli_on_a_bundled_scenario_writes_the_report(tmp_path, capsys, x64):
    (tmp_path / "zero.py").write_text("import jax.numpy as jnp\n\n"
                                      "def policy(obs, key):\n    return -jnp.tanh(obs[:1])\n")
    import sys
    sys.path.insert(0, str(tmp_path))
    try:
        rc = main(["policy", "cartpole", "--policy", "zero:policy", "--episodes", "2", "--steps", "30",
                   "--out", str(tmp_path)])
    finally:
        sys.path.remove(str(tmp_path))
    assert rc == 0, capsys.readouterr().out
    doc = json.loads((tmp_path / "policy-report.json").read_text())
    assert report.validate(doc, "policy") == []
    assert doc["kind"] == "policy" and doc["status"] == "pass" and len(doc["returns"]["c"]) == 2


def test_c_steps_what_the_environment_changed_on_its_mjx_system(x64):
    """brax's ant sets its solver on the MJX system with tree_replace; mj_model never sees it."""
    env = closedloop.make_env("ant")
    assert env.sys.mj_model.opt.iterations != 1  # the XML's
    m = closedloop.c_model(env)
    assert (m.opt.iterations, m.opt.ls_iterations) == (1, 4)
    assert m.opt.disableflags == int(env.sys.opt.disableflags)


def test_observations_from_c_s_derived_fields(x64):
    """hopper observes the torso height from x.pos: C's side must compute it (mj_forward of the
    Batch's start states), not read zeros."""
    env = closedloop.make_env("hopper")

    def policy(obs, key):
        return jnp.tanh(obs[:3]), {}
    reset_keys, policy_keys = closedloop_streams._keys(0, 2, 5)
    first, chunks = closedloop.mjx_stream(env, policy, reset_keys, policy_keys)
    mj = next(chunks)
    c = next(closedloop.c_stream(env, policy, reset_keys, policy_keys, np.asarray(first.pipeline_state.qpos),
                                 np.asarray(first.pipeline_state.qvel)))
    np.testing.assert_allclose(c.obs0, mj.obs0, atol=1e-12)
    np.testing.assert_allclose(c.obs, mj.obs, atol=1e-12)
    assert c.obs0[0, 0] > 1.0  # the torso's height


#: A policy brax's own PPO trained on inverted_pendulum with the MJX backend, as brax's training
#: loop wrote its last checkpoint: ``python benchmarks/scripts/train_policy.py --out DIR
#: --timesteps 100000`` (seed 0; 396 s on this machine, last evaluation 189 of 200: the README
#: of the directory). Committed, so that CI loads a trained policy instead of training one.
TRAINED = Path(__file__).resolve().parent / "data" / "policies" / "inverted_pendulum_ppo"


def test_a_policy_brax_trained_passes_and_a_gain_slip_fails(monkeypatch):
    """A policy that balances (brax-trained, :data:`TRAINED`), over 8 episodes: unmodified MJX
    passes, a 2% gain slip fails."""
    assert (TRAINED / "ppo_network_config.json").is_file()
    assert main(["policy", "inverted_pendulum", "--policy", str(TRAINED), "--episodes", "8"]) == 0
    _slip(monkeypatch)
    assert main(["policy", "inverted_pendulum", "--policy", str(TRAINED), "--episodes", "8"]) == 1
