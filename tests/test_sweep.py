"""The sweep's plumbing: C streamed from a background thread, an engine crash contained to its scenario."""

import dataclasses
import subprocess
import sys
import threading
import time

import pytest

from mjxdiff.engine.engines import CEngine
from mjxdiff.input.inputs import make_inputs
from mjxdiff.input.scenario import Randomization, Scenario, load_model, load_scenario
from mjxdiff.runner.stream import _ahead
from mjxdiff.runner.sweep import SweepConfig, run_inputs


def test_ahead_yields_every_item_in_order():
    assert list(_ahead(iter(range(7)), depth=2)) == list(range(7))
    assert list(_ahead(iter([]))) == []


def test_ahead_raises_the_producers_error_after_the_items_before_it():
    def items():
        yield 1
        yield 2
        raise RuntimeError("C crashed")

    got = []
    with pytest.raises(RuntimeError, match="C crashed"):
        for x in _ahead(items()):
            got.append(x)
    assert got == [1, 2]


def test_closing_ahead_stops_its_thread():
    produced = []

    def items():
        for i in range(1000):
            produced.append(i)
            yield i

    before = threading.active_count()
    stream = _ahead(items(), depth=1)
    assert next(stream) == 0
    stream.close()
    time.sleep(0.1)
    assert threading.active_count() == before
    assert len(produced) <= 3, "the producer ran on after the consumer stopped"


def test_a_c_crash_mid_stream_is_that_scenarios_engine_error(monkeypatch):
    scenario = load_scenario("pendulum")
    m = load_model(scenario)
    inputs = make_inputs(scenario, m, seed=0, batch=2, steps=100)
    real = CEngine.stream

    def crashing(self, inputs, chunk, *args, **kwargs):
        pieces = real(self, inputs, chunk, *args, **kwargs)
        yield next(pieces)  # a real first piece, then the crash
        raise RuntimeError("mj_step: simulated crash")

    monkeypatch.setattr(CEngine, "stream", crashing)
    result = run_inputs("pendulum", m, inputs, scenario.tolerance, SweepConfig(diagnose="none", piece_steps=50))
    assert (result.status, result.error_kind) == ("error", "engine")
    assert result.message == "MuJoCo C failed: RuntimeError: mj_step: simulated crash"


# ---------------------------------------------------------------------------------------------
# the noise floor on demand: C's perturbed rerun only where an error exceeds the fixed tolerance

TOUCHING_XML = """<mujoco><option timestep="0.002"/><worldbody><geom type="plane" size="1 1 0.1"/>
<body pos="0 0 0.1"><joint name="drop" type="slide" axis="0 0 1"/><geom type="sphere" size="0.1"/></body>
</worldbody></mujoco>"""


DECOY_XML = """<mujoco><option timestep="0.002"/><worldbody><geom name="floor" type="plane" size="1 1 0.1"/>
<geom name="decoy" type="box" size="0.1 0.1 0.1" pos="3 0 0"/>
<body pos="0 0 0.099"><freejoint/><geom name="ball" type="sphere" size="0.1"/></body>
</worldbody></mujoco>"""


def _c_batches(monkeypatch) -> list[int]:
    """The batch size of every C stream the sweep opens, in order."""
    sizes, real = [], CEngine.stream

    def recording(self, inputs, chunk, *args, **kwargs):
        sizes.append(inputs.batch)
        return real(self, inputs, chunk, *args, **kwargs)

    monkeypatch.setattr(CEngine, "stream", recording)
    return sizes


def _both_modes(m, inputs, tol, **config):
    """Both noise-floor modes; without the one-step check, whose C batches these tests do not count."""
    return {mode: run_inputs("x", m, inputs, tol, SweepConfig(diagnose="none", noise_floor=mode, onestep=False,
                                                              **config))
            for mode in ("on-demand", "always")}


def _same_verdict(a, b):
    assert (a.status, a.pass_rate, a.first_divergence, a.diverged_members) == (
        b.status, b.pass_rate, b.first_divergence, b.diverged_members)
    for fa, fb in zip(a.fields, b.fields, strict=True):
        assert (fa.field, fa.first_step, fa.max_error) == (fb.field, fb.first_step, fb.max_error)


def test_a_calm_scenario_never_runs_the_perturbed_rerun(monkeypatch):
    scenario = load_scenario("pendulum")
    m = load_model(scenario)
    inputs = make_inputs(scenario, m, seed=0, batch=4, steps=300)
    batches = _c_batches(monkeypatch)
    runs = _both_modes(m, inputs, scenario.tolerance)
    assert batches == [4, 8], "on demand: the reference alone; always: reference and rerun as one batch"
    assert runs["on-demand"].status == "pass" and runs["on-demand"].info["noise_floor_members"] == 0
    assert runs["on-demand"].noise_rate == {}
    assert runs["always"].info["noise_floor_members"] == 4 and set(runs["always"].noise_rate) >= {"qpos", "qvel"}
    _same_verdict(runs["on-demand"], runs["always"])


def test_the_rerun_starts_mid_stream_and_catches_up_to_the_envelope_of_always(monkeypatch):
    """Tolerances of 1e-13 on the double pendulum: rounding exceeds them after some steps and only
    the envelope lets it pass; the rerun, started late in each group of two, gives the same
    envelope and growth rate as one that ran from the start."""
    scenario = load_scenario("double_pendulum")
    m = load_model(scenario)
    inputs = make_inputs(scenario, m, seed=0, batch=4, steps=300)
    tight = dataclasses.replace(scenario.tolerance, qpos=1e-13, qvel=1e-12, sensordata=1e-12)
    batches = _c_batches(monkeypatch)
    runs = _both_modes(m, inputs, tight, group_size=2, piece_steps=25)
    assert batches[:2] == [2, 4] and batches[-1] == 4 and 2 not in batches[-2:], batches
    fixed = run_inputs("x", m, inputs, tight, SweepConfig(diagnose="none", envelope=False, group_size=2,
                                                          piece_steps=25))
    assert fixed.status == "fail" and fixed.first_divergence["step"] >= 25, "the tolerance must be exceeded late"
    lazy, eager = runs["on-demand"], runs["always"]
    assert lazy.status == "pass", lazy.message
    assert lazy.info["noise_floor_members"] == 4
    _same_verdict(lazy, eager)
    assert lazy.noise_rate == pytest.approx(eager.noise_rate, rel=1e-12)
    assert [f.envelope for f in lazy.fields] == pytest.approx([f.envelope for f in eager.fields], rel=1e-12)


def test_an_injected_bug_fails_the_same_with_the_rerun_on_demand(monkeypatch, fresh_mjx):
    from tests.test_detection import extra_damping

    extra_damping(monkeypatch)
    scenario = load_scenario("pendulum")
    m = load_model(scenario)
    inputs = make_inputs(scenario, m, seed=0, batch=4, steps=300)
    runs = _both_modes(m, inputs, scenario.tolerance, group_size=2, piece_steps=50)
    assert runs["on-demand"].status == "fail" and runs["on-demand"].first_divergence["field"] in ("qpos", "qvel")
    _same_verdict(runs["on-demand"], runs["always"])


def test_a_grazing_contact_is_ambiguous_not_a_mismatch_and_starts_no_rerun(tmp_path, monkeypatch):
    """A sphere resting exactly on a plane: C counts the touching contact at step 0, MJX
    (``dist < margin``, strictly) does not. It grazes its threshold (MuJoCo's parity method's
    1e-5 m), so it is left out on both sides: each member's step 0 is counted ambiguous, the
    contacts do not fail even with no mismatch tolerated, and no rerun starts for it."""
    (tmp_path / "touching.xml").write_text(TOUCHING_XML)
    scenario = Scenario(name="touching", model=str(tmp_path / "touching.xml"), randomize=Randomization(
        qpos_noise=0.0, qvel_noise=0.0, control="zero", scale={"gravity": (0.9, 1.1)}))
    m = load_model(scenario)
    inputs = make_inputs(scenario, m, seed=0, batch=4, steps=100)
    tol = dataclasses.replace(scenario.tolerance, contact_mismatch=1e-9)
    batches = _c_batches(monkeypatch)
    runs = _both_modes(m, inputs, tol, piece_steps=50)
    lazy = runs["on-demand"]
    assert lazy.status == "pass" and lazy.field("contacts").max_error == 0, lazy.message
    assert lazy.info["ambiguous_contact_steps"] == 4, "step 0 of each member: C 1 contact, MJX 0"
    assert batches[0] == 4 and lazy.info["noise_floor_members"] == 0
    _same_verdict(lazy, runs["always"])


def _contact_labelled_decoy(decoy: int, floor: int):
    """MJX's collision driver labels a contact with the floor as one with ``decoy``, another geom
    of the world body: the physics is the same (same bodies, same parameters), the count is the
    same, only the pair a contact sensor or a reward reading ``contact.geom`` sees is wrong."""
    import jax.numpy as jnp
    from mujoco.mjx._src import collision_driver

    orig = collision_driver.collision

    def wrong(m, d):
        d = orig(m, d)
        c = d._impl.contact
        relabel = lambda g: jnp.where(g == floor, decoy, g)  # noqa: E731
        c = c.replace(geom=relabel(c.geom), geom1=relabel(c.geom1), geom2=relabel(c.geom2))
        return d.replace(_impl=d._impl.replace(contact=c))
    return collision_driver, "collision", wrong


def test_a_contact_in_the_wrong_pair_with_the_same_count_fails_naming_both_pairs(tmp_path, monkeypatch,
                                                                                  fresh_mjx):
    """Contacts are matched by geom pair: a contact labelled with the wrong geom (same count, same
    physics) fails the rollout, the first divergence naming the pair C has and the pair MJX has;
    the mismatch starts C's rerun on demand (which finds C's own pairs steady) and the verdict is
    the one the rerun from the start gives. Unmodified, the same rollout passes."""
    (tmp_path / "decoy.xml").write_text(DECOY_XML)
    scenario = Scenario(name="decoy", model=str(tmp_path / "decoy.xml"), randomize=Randomization(
        qpos_noise=1e-3, qvel_noise=0.0, control="zero"))
    m = load_model(scenario)
    inputs = make_inputs(scenario, m, seed=0, batch=4, steps=100)
    config = dict(piece_steps=50)
    clean = run_inputs("x", m, inputs, scenario.tolerance, SweepConfig(diagnose="none", onestep=False, **config))
    assert clean.status == "pass" and clean.field("contacts").max_error == 0, clean.message
    monkeypatch.setattr(*_contact_labelled_decoy(decoy=1, floor=0))
    batches = _c_batches(monkeypatch)
    runs = _both_modes(m, inputs, scenario.tolerance, **config)
    lazy = runs["on-demand"]
    assert lazy.status == "fail" and lazy.first_divergence["field"] == "contacts", lazy.message
    assert lazy.first_divergence["object"] == "pair 'decoy'/'ball' (1 more in MJX), 'floor'/'ball' (1 more in C)"
    assert [f.max_error for f in lazy.fields if f.field in ("qpos", "qvel")] == [
        f.max_error for f in clean.fields if f.field in ("qpos", "qvel")], "the same physics"
    assert batches[0] == 4 and batches[1] == 8 and lazy.info["noise_floor_members"] == 4, batches
    _same_verdict(lazy, runs["always"])


def test_scenarios_side_by_side_judge_as_one_after_another_each_in_its_own_precision(monkeypatch):
    """Workers run whole scenarios at once, each setting jax_enable_x64 for its own thread only:
    a float32 sweep on two workers, next to a float64 thread, judges exactly as one after another.
    Each sweep reads MJX's code once, whatever its scenarios and threads ask."""
    import jax
    import mujoco.mjx
    import numpy as np

    from mjxdiff.engine import digest
    from mjxdiff.runner.current import jax_precision
    from mjxdiff.runner.sweep import sweep

    reads = []
    feed = digest._feed_module
    monkeypatch.setattr(digest, "_feed_module", lambda d, module: (reads.append(module), feed(d, module))[1])

    scenarios = [load_scenario(n) for n in ("pendulum", "cartpole", "double_pendulum")]
    config = SweepConfig(seed=1, batch=2, steps=40, diagnose="none", precision="float32")
    before = jax.config.jax_enable_x64
    stop = threading.Event()
    seen = []  # the neighbour's dtypes: an assert in a thread would only warn

    def other_precision():  # a thread busy in float64 all along
        with jax_precision("float64"):
            while not stop.is_set():
                seen.append(jax.numpy.zeros(1).dtype)
                time.sleep(0.001)

    neighbour = threading.Thread(target=other_precision)
    neighbour.start()
    try:
        side_by_side = sweep(scenarios, dataclasses.replace(config, compile_workers=2))
    finally:
        stop.set()
        neighbour.join()
    assert seen and set(seen) == {np.dtype(np.float64)}, "the float64 thread kept its precision throughout"
    # the rollouts' code (mjx and mjxdiff's traced modules) and the report's (mjx alone): two readings
    assert reads.count(mujoco.mjx) == 2, len(reads)
    one_by_one = sweep(scenarios, dataclasses.replace(config, compile_workers=0))
    assert reads.count(mujoco.mjx) == 4, len(reads)
    assert jax.config.jax_enable_x64 == before, "the process-wide setting is left as it was"
    assert [r.name for r in side_by_side] == [s.name for s in scenarios]
    for a, b in zip(side_by_side, one_by_one, strict=True):
        assert a.status == b.status == "pass", (a.name, a.message)
        assert [f.max_error for f in a.fields] == [f.max_error for f in b.fields], a.name
        assert a.tolerances == b.tolerances and a.tolerances["qpos"] > 1e-5, "float32 tolerances"


def test_a_scenarios_phases_do_not_overlap_and_stepping_is_only_stepping(fresh_mjx):
    """The rollout is compiled (or loaded) inside MJX's first call: that time is ``compile``'s, not
    ``mjx``'s, so ``mjx + c`` is the engines' own stepping; the phases sum to no more than the
    scenario's wall time, and the report's table sums them per phase."""
    from mjxdiff.output import report
    from mjxdiff.runner.sweep import run_scenario

    t = time.perf_counter()
    r = run_scenario(load_scenario("pendulum"), SweepConfig(batch=4, steps=50))
    wall = time.perf_counter() - t
    seconds = r.info["seconds"]
    assert r.status == "pass" and set(seconds) <= set(report.PHASES), seconds
    assert min(seconds.values()) >= 0.0 and sum(seconds.values()) <= wall, (seconds, wall)
    assert seconds["compile"] > 10 * seconds["mjx"] > 0, seconds  # 4 members x 50 steps of a pendulum: ms
    assert sum(r.info["compile_seconds"].values()) == pytest.approx(seconds["compile"], abs=1e-6)
    assert {"stepping", "onestep", "transfer"} <= set(r.info["cpu_seconds"]), r.info["cpu_seconds"]
    table = report.timing([report.result_dict(r)], dict(sweep=dict(wall=wall, cpu=wall)))
    assert table["stepping"] == pytest.approx(seconds["mjx"] + seconds["c"], abs=1e-3)
    assert table["ratio"] == pytest.approx(wall / table["stepping"], rel=0.01)
    line = report.format_timing(table)
    assert line.startswith(f"time: {wall:.0f} s wall") and "MJX stepping" in line and "compile" in line, line


def test_a_quick_sweep_steps_the_full_sweeps_compiled_piece(fresh_mjx):
    """``--quick`` judges its 4 members over 50 steps padded to the full sweep's member group and
    stepped in its pieces (the horizon a run-time trip count): after the full sweep of a scenario
    it compiles nothing more, not even a load, and still judges only its own members and steps."""
    from mjxdiff.runner.sweep import run_scenario

    scenario = load_scenario("cartpole")
    full = run_scenario(scenario, SweepConfig(diagnose="none", transfer=False))
    quick = run_scenario(scenario, SweepConfig(quick=True, diagnose="none", transfer=False))
    assert full.status == quick.status == "pass", (full.message, quick.message)
    assert (quick.info["batch"], quick.info["steps"]) == (4, 50), quick.info
    assert full.info["batch"] > 4 and full.info["steps"] > 50, full.info
    assert (quick.info["mjx_compiles"], quick.info["mjx_loaded"]) == (0, 0), quick.info
    assert quick.info["groups"] == 1 and quick.info["onestep"]["status"] == "pass", quick.info


@pytest.mark.parametrize("first", ["f = mjxdiff.sweep; mjxdiff.SweepConfig", "mjxdiff.SweepConfig; f = mjxdiff.sweep",
                                   "import mjxdiff.sweep; f = mjxdiff.sweep",
                                   "import mjxdiff.runner.sweep; f = mjxdiff.sweep"])
def test_mjxdiff_sweep_means_one_thing_whatever_is_imported_first(first):
    """``mjxdiff.sweep`` is the module ``mjxdiff.runner.sweep``, callable as its ``sweep`` function,
    in whatever order the package, the module (by its old name or its new one) and its names are
    first touched (a fresh interpreter per order)."""
    code = (f"import mjxdiff; {first}; assert mjxdiff.sweep is f; from mjxdiff import sweep as g; assert g is f; "
            "import mjxdiff.runner.sweep as module; assert module is f; "
            "from mjxdiff.sweep import sweep as run; import inspect; assert inspect.isfunction(run); "
            "assert f([], mjxdiff.SweepConfig()) == run([], mjxdiff.SweepConfig()) == []")
    subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, timeout=120)
