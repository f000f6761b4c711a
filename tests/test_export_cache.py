"""Saved rollouts: loaded without tracing, bit-identical, never used for patched MJX or another structure."""

import functools
import json
import os
import subprocess
import sys

import jax
import mujoco
import numpy as np
import pytest
from mujoco.mjx._src import passive as mjx_passive

from mjxdiff.engine import digest, engines, export_cache, trace_deps
from mjxdiff.engine.engines import MJXEngine, put_models
from mjxdiff.input.inputs import make_inputs
from mjxdiff.input.scenario import load_model, load_scenario


@pytest.fixture(scope="module")
def pendulum():
    scenario = load_scenario("pendulum")
    m = load_model(scenario)
    return m, make_inputs(scenario, m, seed=3, batch=4, steps=60)


def _rollout(inputs):
    engines.clear_compiled()  # forget this process's functions: the next call loads or traces
    return MJXEngine(devices=1).rollout(inputs)


def test_a_saved_rollout_is_loaded_without_tracing_and_matches_the_traced_one(pendulum, monkeypatch):
    _, inputs = pendulum
    assert export_cache.export_dir() is not None  # tests run with the persistent cache on
    _rollout(inputs)  # saves the artifact if an earlier run has not
    compiles, loaded = engines.compile_count(), export_cache.loaded_count()
    saved = _rollout(inputs)
    assert engines.compile_count() == compiles, "a saved rollout was traced again"
    assert export_cache.loaded_count() == loaded + 1
    monkeypatch.setattr(export_cache, "export_dir", lambda: None)  # the plain jit path
    traced = _rollout(inputs)
    for field in ("qpos", "qvel", "act", "sensordata", "time", "ncon"):
        np.testing.assert_array_equal(getattr(saved, field), getattr(traced, field), err_msg=field)


def test_patched_mjx_is_traced_and_its_own_artifact_reused_for_that_code_only(pendulum, monkeypatch):
    _, inputs = pendulum
    clean = _rollout(inputs)
    clean_code = digest.rollout_digest()
    orig = mjx_passive._spring_damper
    monkeypatch.setattr(mjx_passive, "_spring_damper", lambda m, d: orig(m, d) - 1e-3 * m.dof_damping * d.qvel)
    assert digest.rollout_digest() != clean_code
    compiles, loaded = engines.compile_count(), export_cache.loaded_count()
    patched = _rollout(inputs)  # traced, or loaded from an earlier run of this very patch
    assert engines.compile_count() + export_cache.loaded_count() == compiles + loaded + 1
    assert np.abs(patched.qvel - clean.qvel).max() > 1e-9, "the patched damping did not reach the rollout"
    compiles = engines.compile_count()
    again = _rollout(inputs)  # the same patched code: its own artifact
    assert engines.compile_count() == compiles
    np.testing.assert_array_equal(again.qvel, patched.qvel)
    monkeypatch.undo()
    assert digest.rollout_digest() == clean_code
    np.testing.assert_array_equal(_rollout(inputs).qvel, clean.qvel)
    assert engines.compile_count() == compiles, "the clean code's artifact is loaded again"


def test_an_edit_retraces_only_the_rollouts_that_ran_the_edited_function(pendulum, monkeypatch):
    """Artifacts depend on the functions their trace ran, not on all of MJX: an edit of a collision
    function the pendulum never runs keeps its artifact; an edit of one it runs does not."""
    from mujoco.mjx._src import collision_primitive, smooth

    _, inputs = pendulum
    clean = _rollout(inputs)
    sphere_sphere = collision_primitive._sphere_sphere
    monkeypatch.setattr(collision_primitive, "_sphere_sphere",
                        lambda *a: (lambda dist, pos, n: (dist * 1.001, pos, n))(*sphere_sphere(*a)))
    compiles, loaded = engines.compile_count(), export_cache.loaded_count()
    np.testing.assert_array_equal(_rollout(inputs).qpos, clean.qpos)
    assert (engines.compile_count(), export_cache.loaded_count()) == (compiles, loaded + 1), "not retraced"
    rne = smooth.rne
    monkeypatch.setattr(smooth, "rne", lambda m, d, *a, **k: (lambda d: d.replace(
        qfrc_bias=d.qfrc_bias * (1 + 1e-3)))(rne(m, d, *a, **k)))
    patched = _rollout(inputs)
    assert engines.compile_count() + export_cache.loaded_count() == compiles + loaded + 2
    assert np.abs(patched.qpos - clean.qpos).max() > 1e-9, "the edited rne ran"


def test_dependencies_name_the_functions_a_trace_ran(pendulum):
    _, inputs = pendulum
    _rollout(inputs)
    [path] = export_cache.matching(export_cache.export_dir() / next(iter(export_cache._FUNCTIONS))[0])
    deps = json.loads(path.with_suffix(".deps").read_text())
    assert "mujoco.mjx._src.smooth:rne" in deps and "mujoco.mjx._src.forward:forward" in deps
    assert "mjxdiff.engine.engines:_scan_steps" in deps
    # no contacts: a pair's colliders are named (MJX's collision table), not what they call
    assert not {"mujoco.mjx._src.collision_primitive:_sphere_sphere",
                "mujoco.mjx._src.collision_primitive:*"} & set(deps)


def test_a_loaded_rollout_reads_its_cost_analysis_from_beside_the_artifact(pendulum, monkeypatch):
    """``auto``'s estimate needs XLA's cost analysis (the whole module as HLO): computed once per
    artifact and kept beside it, so a warm sweep never converts a rollout to HLO."""
    _, inputs = pendulum
    _rollout(inputs)
    [path] = export_cache.matching(export_cache.export_dir() / next(iter(export_cache._FUNCTIONS))[0])
    cost = json.loads(path.with_suffix(".cost").read_text())
    assert cost["flops"] > 0
    calls = []
    real = jax.stages.Lowered.cost_analysis
    monkeypatch.setattr(jax.stages.Lowered, "cost_analysis", lambda self: calls.append(1) or real(self))
    engines.clear_compiled()
    MJXEngine(devices=1, compile="auto").rollout(inputs)
    assert calls == [], "the cost analysis was computed again"
    assert engines.last_choice()["flops_per_step"] == cost["flops"]


def _key(*models: mujoco.MjModel) -> str:
    mx, varying = put_models(models if len(models) > 1 else models * 2)
    leaves, treedef = jax.tree.flatten(mx)
    return export_cache._key(engines._rollout, treedef, leaves, dict(varying=varying, with_energy=False, mesh=None),
                             digest.rollout_digest())


def test_the_key_follows_static_structure_not_parameter_values(pendulum):
    m, _ = pendulum
    heavier = load_model(load_scenario("pendulum"))
    heavier.body_mass[:] *= 2
    heavier.dof_damping[:] += 0.5
    assert _key(heavier) == _key(m), "parameter values are inputs, not part of the compiled function"
    other = load_model(load_scenario("pendulum"))
    other.opt.integrator = int(mujoco.mjtIntegrator.mjINT_RK4)  # static in mjx.Model: another function
    assert _key(other) != _key(m)
    assert _key(m, heavier) != _key(m), "which leaves vary between members is part of the function"


FACTOR = 1e-3


def _damping_patch(scale):
    orig = mjx_passive._spring_damper
    return lambda m, d: orig(m, d) - scale * m.dof_damping * d.qvel


def _global_patch(m, d):  # reads the module-level FACTOR
    return FACTOR * d.qvel


@pytest.mark.parametrize("change", [
    "mjxdiff's own traced code", "a partial", "a closure's value", "a global the patch reads",
    "an MJX module constant", "a default argument", "a moved helper the rollout calls (mjxdiff.input.joints)",
    "a method of an MJX enum",
])
def test_every_kind_of_code_change_changes_the_digest(change, monkeypatch):
    before = digest.rollout_digest()
    if change == "mjxdiff's own traced code":
        monkeypatch.setattr(engines, "_contacts", lambda dx: 0)  # would count no contacts
    elif change == "a partial":
        monkeypatch.setattr(mjx_passive, "_spring_damper", functools.partial(mjx_passive._spring_damper))
    elif change == "a closure's value":  # same code, another captured number
        monkeypatch.setattr(mjx_passive, "_spring_damper", _damping_patch(1e-3))
        first = digest.rollout_digest()
        monkeypatch.setattr(mjx_passive, "_spring_damper", _damping_patch(2e-3))
        assert digest.rollout_digest() != first
    elif change == "a global the patch reads":
        monkeypatch.setattr(mjx_passive, "_spring_damper", _global_patch)
        first = digest.rollout_digest()
        monkeypatch.setitem(globals(), "FACTOR", 2e-3)
        assert digest.rollout_digest() != first
    elif change == "a moved helper the rollout calls (mjxdiff.input.joints)":  # engines' energy walks joints.parts
        from mjxdiff.input import joints

        orig = joints.parts
        monkeypatch.setattr(joints, "parts", lambda m: orig(m)[::-1])
    elif change == "a method of an MJX enum":  # was left out: an enum was digested by its members alone
        from mujoco.mjx._src import types as mjx_types

        monkeypatch.setattr(mjx_types.JointType, "qpos_width", mjx_types.JointType.dof_width)
    elif change == "an MJX module constant":
        from mujoco.mjx._src import collision_driver

        monkeypatch.setattr(collision_driver, "_MAX_NCON", collision_driver._MAX_NCON + 1)
    else:
        from mujoco.mjx._src import forward as mjx_forward

        advance = mjx_forward._advance.__wrapped__  # under MJX's named_scope decorator
        assert advance.__defaults__ == (None,)  # qvel=None: semi-implicit
        monkeypatch.setattr(advance, "__defaults__", (0.0,))
    assert digest.rollout_digest() != before, change
    monkeypatch.undo()
    assert digest.rollout_digest() == before


def test_the_digest_is_stable_across_rollouts_and_processes(pendulum):
    _, inputs = pendulum
    before = digest.code_digest()
    _rollout(inputs)
    assert digest.code_digest() == before, "run-time state (counters, caches) is not code"
    code = "from mjxdiff.engine import digest, engines; print(digest.code_digest())"
    other = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert other.stdout.split()[-1] == before, other.stderr[-2000:]


def test_inside_code_read_once_the_code_is_read_once_and_a_patch_is_seen_after(monkeypatch):
    """A sweep reads the code once (a warm sweep asked ~130 times, a tenth of its CPU); a patch
    made inside is seen as soon as the block ends, and outside every call reads afresh."""
    before = digest.rollout_digest()
    reads = []
    feed = digest._feed_module
    monkeypatch.setattr(digest, "_feed_module", lambda d, module: (reads.append(module), feed(d, module))[1])
    with digest.code_read_once():
        assert digest.rollout_digest() == before
        first = len(reads)
        assert first
        monkeypatch.setattr(mjx_passive, "_spring_damper", _damping_patch(1e-3))
        assert digest.rollout_digest() == before, "the block's one reading"
        assert len(reads) == first, "the code was read again inside the block"
    patched = digest.rollout_digest()
    assert patched != before
    assert len(reads) == 2 * first
    monkeypatch.setattr(mjx_passive, "_spring_damper", _damping_patch(2e-3))
    assert digest.rollout_digest() != patched


def _artifact():
    """The file of the one rollout compiled in this process (artifacts live in a directory named by
    the arguments' key, one file per set of traced code)."""
    [((key, _, _), _)] = export_cache._FUNCTIONS.items()
    [path] = export_cache.matching(export_cache.export_dir() / key)
    return path


@pytest.fixture
def own_export_dir(tmp_path):
    """Artifacts in a directory of this test's own (JAX's cache dir setting, read at each use by
    export_dir): what it damages and counts is not shared with the user's warm cache."""
    before = jax.config.jax_compilation_cache_dir
    jax.config.update("jax_compilation_cache_dir", str(tmp_path))
    yield tmp_path / "mjxdiff-exports"
    jax.config.update("jax_compilation_cache_dir", before)


def test_a_damaged_artifact_is_traced_again_and_rewritten(pendulum, own_export_dir):
    _, inputs = pendulum
    reference = _rollout(inputs)
    assert export_cache.export_dir() == own_export_dir
    path = _artifact()  # this rollout's artifact, just loaded or saved
    for damaged in (b"", b"not a pickle", path.read_bytes()[:100]):
        path.write_bytes(damaged)
        loaded = export_cache.loaded_count()
        again = _rollout(inputs)
        np.testing.assert_array_equal(again.qpos, reference.qpos)
        assert export_cache.loaded_count() == loaded, "a damaged artifact cannot have been loaded"
        assert not path.exists() or path.read_bytes() != damaged, "it is deleted or replaced..."
        assert export_cache.matching(path.parent), "...by a good one..."
        _rollout(inputs)
        assert export_cache.loaded_count() == loaded + 1, "...which the next process loads"


def test_the_least_recently_used_artifacts_are_evicted_beyond_the_budget(tmp_path):
    for i in range(5):  # a.jaxexport oldest ... e newest, 100 bytes each
        path = tmp_path / f"{'abcde'[i]}.jaxexport"
        path.write_bytes(b"x" * 100)
        os.utime(path, (1000 + i, 1000 + i))
    (tmp_path / "other.bin").write_bytes(b"y" * 1000)  # not an artifact: never counted or touched
    keep = tmp_path / "a.jaxexport"
    assert export_cache.evict(tmp_path, keep=keep, budget=250) == 3
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.jaxexport", "e.jaxexport", "other.bin"]
    assert export_cache.evict(tmp_path, budget=1000) == 0


def test_loading_an_artifact_marks_it_recently_used(pendulum):
    _, inputs = pendulum
    _rollout(inputs)
    path = _artifact()
    os.utime(path, (1000, 1000))
    _rollout(inputs)  # loads it
    assert path.stat().st_mtime > 1000


def test_scanning_for_live_functions_leaves_tuples_other_threads_build_alone():
    """The scan for live functions (gc.get_objects) holds every object, tuples another thread is
    still building included; that thread's resize then raised "SystemError: Objects/tupleobject.c:927:
    bad argument to internal function" (once in a sweep's host-interface check beside a compile
    worker; with the scan unguarded, within 3 of these scans). 100 scans beside a thread building
    tuples from a generator that lets the scanner run: no SystemError."""
    import threading
    import time

    errors, stop = [], threading.Event()

    def build():
        def slow():
            for i in range(40):
                time.sleep(0)  # lets the scanning thread run while the tuple is half built
                yield i
        while not stop.is_set():
            try:
                tuple(slow())
            except SystemError as e:
                errors.append(e)
                return

    builder = threading.Thread(target=build)
    builder.start()
    try:
        for _ in range(100):
            trace_deps._live_functions({f"@{__file__}:nothing"})
            if errors:
                break
    finally:
        stop.set()
        builder.join()
    assert errors == []


def test_xla_executables_are_kept_per_cpu_type_and_artifacts_shared(tmp_path):
    """configure_jax puts XLA's executables under ``xla-<cpu type>`` (its cache key does not name
    the instruction set) and mjxdiff's portable artifacts, and MuJoCo Warp's kernels, beside them."""
    from mjxdiff.engine import engines, mjwarp

    before = jax.config.jax_compilation_cache_dir
    try:
        engines.configure_jax("float64", str(tmp_path))
        tag = export_cache.cpu_type()
        assert jax.config.jax_compilation_cache_dir == str(tmp_path / f"xla-{tag}")
        assert export_cache.cache_root() == tmp_path and export_cache.export_dir() == tmp_path / "mjxdiff-exports"
        assert mjwarp.kernel_cache_dir() == tmp_path / "warp"
        assert tag.split("-")[0] and len(tag.split("-")[-1]) == 12 and export_cache.cpu_type() == tag
    finally:
        jax.config.update("jax_compilation_cache_dir", before)


def test_a_drill_down_s_forward_is_traced_once_loaded_after_and_traced_again_for_patched_mjx(
        pendulum, tmp_path, monkeypatch):
    """The drill-down's ``mjx.forward`` is an artifact like a rollout: a later process (compiled
    functions forgotten) loads it, the same numbers; an MJX patched since is traced afresh and
    differs; and none of it counts among the rollouts a run loaded or traced."""
    m, _ = pendulum
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:] = 0.3, -0.7
    monkeypatch.setattr(export_cache, "export_dir", lambda: tmp_path)
    traces = []
    export = export_cache._export
    monkeypatch.setattr(export_cache, "_export", lambda *a, **k: traces.append(1) or export(*a, **k))
    before = export_cache.events()

    def forward():
        engines.clear_compiled()
        return MJXEngine().forward(m, d, ("qfrc_passive", "qacc")).values

    first, again = forward(), forward()
    assert len(traces) == 1 and any(tmp_path.iterdir()), "traced once, saved, then loaded"
    np.testing.assert_array_equal(again["qacc"], first["qacc"])
    orig = mjx_passive._spring_damper
    monkeypatch.setattr(mjx_passive, "_spring_damper", lambda m, d: orig(m, d) * 1.01)
    patched = forward()
    assert len(traces) == 2 and not np.array_equal(patched["qfrc_passive"], first["qfrc_passive"])
    after, counted = export_cache.events(), ("loaded", "traced", "saved")
    assert {k: after[k] for k in counted} == {k: before[k] for k in counted}
