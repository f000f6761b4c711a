"""The artifact cache fails closed: code from any file that ran inside a trace is part of its key,
several matching artifacts load none, and `mjxdiff cache check` finds what cannot be trusted.

The code variants (``tests/code_variants.py``) are the ways MJX is changed without touching its
installed files: an edited module copy bound by hand, a patch from another module, a module
whose ``__file__`` is not its code's file, and one workspace file edited twice."""

import functools
import json
import subprocess
import sys
from pathlib import Path

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mjxdiff.engine import engines, export_cache
from mjxdiff.cli import main
from mjxdiff.input.scenario import load_scenario
from mjxdiff.runner.sweep import SweepConfig, sweep

import code_variants

HERE = Path(__file__).resolve().parent

#: Runs the CLI with one code variant installed first: ``python -c RUN VARIANT WORKSPACE ARGS...``.
RUN = f"""
import sys
sys.path.insert(0, {str(HERE)!r})
import code_variants
code_variants.apply(sys.argv[1], sys.argv[2])
from mjxdiff.cli import main
sys.exit(main(sys.argv[3:]))
"""


def _cli_sweep(tmp_path: Path, variant: str, run: int, scenario: str = "pendulum",
               python: str = sys.executable) -> dict:
    out = tmp_path / f"{variant}-{run}"
    args = ["sweep", scenario, "--quick", "--diagnose", "none", "--no-history", "--out", str(out),
            "--cache-dir", str(tmp_path / "cache")]
    if scenario != "pendulum":  # only the rollout's artifact is asked about
        args += ["--no-onestep", "--no-transfer"]
    proc = subprocess.run([python, "-c", RUN, variant, str(tmp_path / "workspace"), *args],
                          capture_output=True, text=True, timeout=600)
    assert "Traceback" not in proc.stderr, proc.stderr[-3000:]
    doc = json.loads((out / "report.json").read_text())
    [scenario] = doc["scenarios"]
    return dict(exit=proc.returncode, status=scenario["status"], worst=scenario["fields"]["qpos"]["max_error"],
                cache=doc["code"]["cache"], stderr=proc.stderr)


def _site_with_mujoco_copy(tmp_path: Path) -> tuple[str, Path]:
    """A venv whose site-packages holds a copy of the installed ``mujoco`` package (links to its
    files, ``collision_primitive.py`` a file of its own) ahead of this environment's packages:
    an install of MJX that can be edited where it lies. (The interpreter, the file to edit.)"""
    import mujoco

    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=120)
    [site] = venv.glob("lib/python3*/site-packages")
    installed = Path(mujoco.__file__).parent
    subprocess.run(["cp", "-rs", str(installed), str(site / "mujoco")], check=True, timeout=120)
    edited = site / "mujoco" / "mjx" / "_src" / "collision_primitive.py"
    edited.unlink()
    edited.write_text((installed / "mjx" / "_src" / "collision_primitive.py").read_text())
    here = [p for p in sys.path if p.endswith("site-packages")]
    (site / "this_env.pth").write_text("".join(f"import site; site.addsitedir({p!r})\n" for p in here))
    return str(venv / "bin" / "python"), edited


def test_an_edit_inside_a_decorated_collider_or_in_the_installed_file_is_traced_afresh(tmp_path):
    """The sequence of issue 49, on one cache: unmodified MJX, a hand-bound copy whose plane-sphere
    contact point is wrong, another whose ``@collider``-decorated ``plane_capsule`` uses the radius
    for the half-length (before the fix it loaded the clean artifact and passed: the raw function
    lives only in the wrapper's closure), then the same edit made in the installed file where it
    lies (before the fix: every file under a venv's lib/python3.X was ignored), then unmodified
    MJX again, which loads its own artifact and gives its first numbers; an edited copy run again
    loads its own artifact too (before issue 49's first fix, clean MJX loaded an edited copy's
    artifact and failed). The property below sweeps every other variant in any order over one
    cache, in this process."""
    python, installed = _site_with_mujoco_copy(tmp_path)
    run = functools.partial(_cli_sweep, tmp_path, scenario="primitives_on_plane", python=python)
    clean = run("clean", 1)
    assert (clean["exit"], clean["status"], clean["cache"]["traced"]) == (0, "pass", 1), clean["stderr"][-2000:]
    first = {}
    for variant in code_variants.CONTACT_VARIANTS:
        first[variant] = edited = run(variant, 1)
        assert (edited["exit"], edited["status"]) == (1, "fail"), (variant, edited["stderr"][-2000:])
        assert edited["cache"]["traced"] == 1 and edited["cache"]["loaded"] == 0, (variant, edited["cache"])
    variant = code_variants.CONTACT_VARIANTS[0]
    reloaded = run(variant, 2)
    assert (reloaded["cache"]["loaded"], reloaded["cache"]["traced"]) == (1, 0), (variant, reloaded["cache"])
    assert (reloaded["exit"], reloaded["status"], reloaded["worst"]) == (1, "fail", first[variant]["worst"]), variant
    original = installed.read_text()
    installed.write_text(original.replace(code_variants._CAPSULE_OLD, "segment = axis * cap.size[0]"))
    in_place = run("clean", 2)
    assert (in_place["exit"], in_place["status"]) == (1, "fail"), in_place["stderr"][-2000:]
    assert in_place["cache"]["traced"] == 1 and in_place["cache"]["loaded"] == 0, in_place["cache"]
    installed.write_text(original)
    again = run("clean", 3)
    assert (again["exit"], again["status"], again["worst"]) == (0, "pass", clean["worst"]), again["stderr"][-2000:]
    assert again["cache"]["loaded"] == 1 and again["cache"]["traced"] == 0, again["cache"]
    checked = export_cache.check(tmp_path / "cache" / "mjxdiff-exports")
    assert not checked["ambiguous"] and not checked["unreadable"], checked


#: Every edited variant fails at least one of these, and no two give the same verdicts (asserted
#: below); a third scenario (double_pendulum, swept here before) added only compiles.
SCENARIOS = ("pendulum", "cartpole")
VARIANTS = code_variants.VARIANTS
_FRESH: dict[str, list] = {}


def _verdicts(variant: str, workspace: Path, exports: Path | None, monkeypatch) -> list:
    """(status, worst qpos error) per scenario of a quick sweep of :data:`SCENARIOS` with
    ``variant`` installed, artifacts in ``exports`` (None: none kept, every rollout traced)."""
    undo = code_variants.apply(variant, workspace)
    try:
        with monkeypatch.context() as mp:
            mp.setattr(export_cache, "export_dir", lambda: exports)
            engines.clear_compiled()  # a new process, as far as compiled functions go
            # the rollout's verdict: the one-step check steps the same artifact, the host interface none
            config = SweepConfig(quick=True, diagnose="none", compile_workers=0, onestep=False, transfer=False)
            results = sweep([load_scenario(n) for n in SCENARIOS], config, progress=False)
    finally:
        undo()
        engines.clear_compiled()
    return [(r.name, r.status, {f.field: f.max_error for f in r.fields}.get("qpos")) for r in results]


def _fresh(variant: str, workspace: Path, monkeypatch) -> list:
    if variant not in _FRESH:
        _FRESH[variant] = _verdicts(variant, workspace, None, monkeypatch)
    return _FRESH[variant]


def test_any_sequence_of_code_variants_sharing_a_cache_gets_the_verdicts_of_a_fresh_cache(
        tmp_path_factory, monkeypatch):
    """Property: runs of different code, one after another over one artifact cache, each give
    exactly the verdicts (status and worst error, bit for bit) of the same code with no cache.

    It could not fail if the variants computed the same thing: first, each edited variant fails
    at least one scenario and no two give the same verdicts. (One test, so that the fresh
    verdicts, a sweep of each variant, are computed in one process: xdist would otherwise run
    them again on the other worker.)"""
    workspace = tmp_path_factory.getbasetemp() / "variants-workspace"  # one workspace file, edited between runs
    fresh = {v: _fresh(v, workspace, monkeypatch) for v in VARIANTS}
    assert all(status == "pass" for _, status, _ in fresh["clean"])
    for v in VARIANTS[1:]:
        assert any(status == "fail" for _, status, _ in fresh[v]), v
    assert len({repr(f) for f in fresh.values()}) == len(VARIANTS)

    @settings(max_examples=2, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
    @given(runs=st.lists(st.sampled_from(VARIANTS), min_size=2, max_size=4))
    def sequence_matches_fresh(runs):
        exports = tmp_path_factory.mktemp("shared") / "mjxdiff-exports"
        for variant in runs:
            assert _verdicts(variant, workspace, exports, monkeypatch) == fresh[variant], f"{variant} after {runs}"
        assert not export_cache.check(exports)["ambiguous"]

    sequence_matches_fresh()


def _made_during_the_trace(orig):
    """A damping patch that compiles a function while MJX is traced, calls it and drops it."""
    def damped(m, d):
        namespace: dict = {}
        exec(compile("scale = lambda q: q * 1.0", "<made during the trace>", "exec"), namespace)
        out = namespace["scale"](orig(m, d))
        # the lambda and its globals form a cycle, freed only at the collector's next pass (the
        # artifact is then keyed on it and saved, when that pass had not run: order-dependent);
        # breaking it frees the lambda now, as the test means
        namespace.clear()
        return out
    return damped


def test_code_no_live_function_holds_leaves_the_trace_unsaved(tmp_path, monkeypatch):
    """Fail closed: a frame whose code cannot be named (a function made and dropped inside the
    trace) makes the artifact unsaveable, with one line saying why; the rollout still runs."""
    from mujoco.mjx._src import passive

    from mjxdiff.input.inputs import make_inputs
    from mjxdiff.input.scenario import load_model

    monkeypatch.setattr(passive, "_spring_damper", _made_during_the_trace(passive._spring_damper))
    monkeypatch.setattr(export_cache, "export_dir", lambda: tmp_path)
    before = export_cache.events()
    engines.clear_compiled()
    try:
        scenario = load_scenario("pendulum")
        out = engines.MJXEngine(devices=1).rollout(
            make_inputs(scenario, load_model(scenario), seed=0, batch=2, steps=5))
    finally:
        engines.clear_compiled()
    assert out.qpos.shape == (2, 5, 1)
    events = export_cache.events_since(before)
    assert events["traced"] == 1 and events["saved"] == 0, events
    [why] = events["unsaved"]
    assert "<made during the trace>" in why and "no live function holds its code" in why and "\n" not in why
    assert not list(tmp_path.rglob("*.jaxexport"))


def _two_artifacts_one_key(tmp_path, monkeypatch):
    """A structure directory where two artifacts match the code loaded now: the pendulum's, and a
    copy of it recorded with one dependency fewer (what an incomplete key left behind)."""
    from mjxdiff.input.inputs import make_inputs
    from mjxdiff.input.scenario import load_model

    monkeypatch.setattr(export_cache, "export_dir", lambda: tmp_path)
    scenario = load_scenario("pendulum")
    inputs = make_inputs(scenario, load_model(scenario), seed=0, batch=2, steps=5)
    engines.clear_compiled()
    reference = engines.MJXEngine(devices=1).rollout(inputs)
    [path] = tmp_path.rglob("*.jaxexport")
    deps = json.loads(path.with_suffix(".deps").read_text())
    deps.pop(sorted(deps)[0])
    twin = path.with_name("0" * 32 + ".jaxexport")
    twin.write_bytes(path.read_bytes())
    twin.with_suffix(".deps").write_text(json.dumps(deps))
    return inputs, reference, path, twin


def test_several_matching_artifacts_load_none_and_the_untrusted_one_is_removed(tmp_path, monkeypatch):
    import numpy as np

    inputs, reference, path, twin = _two_artifacts_one_key(tmp_path, monkeypatch)
    assert len(export_cache.matching(path.parent)) == 2
    before = export_cache.events()
    engines.clear_compiled()
    again = engines.MJXEngine(devices=1).rollout(inputs)
    engines.clear_compiled()
    events = export_cache.events_since(before)
    assert events["loaded"] == 0 and events["traced"] == 1 and len(events["ambiguous"]) == 1, events
    assert events["removed"] == 1 and not twin.exists() and path.exists()
    np.testing.assert_array_equal(again.qpos, reference.qpos)
    assert export_cache.matching(path.parent) == [path]


def test_cache_check_lists_what_cannot_be_trusted_and_fix_removes_it(tmp_path, monkeypatch, capsys):
    _, _, path, twin = _two_artifacts_one_key(tmp_path, monkeypatch)
    (path.parent / ("1" * 32 + ".deps")).write_text("{}")  # half a pair
    (path.parent / "stem.123.456.tmp").write_bytes(b"interrupted")
    old = tmp_path / ("f" * 64)
    old.mkdir()
    (old / "x.jaxexport").write_bytes(b"old")  # no FORMAT marker: an older format
    monkeypatch.setattr(engines, "configure_jax", lambda *a, **k: None)  # the export dir is patched already
    assert main(["cache", "check"]) == 1
    text = capsys.readouterr().out
    assert "2 ambiguous" in text and "2 orphaned files" in text and "1 directories of an older format" in text
    assert main(["cache", "check", "--format", "json"]) == 1
    found = json.loads(capsys.readouterr().out)
    assert sorted(found["ambiguous"]) == sorted(str(p.relative_to(tmp_path)) for p in (path, twin))
    assert main(["cache", "check", "--fix"]) == 0
    assert not path.exists() and not twin.exists() and not old.exists()
    assert not list(path.parent.glob("*.tmp")) and not list(path.parent.glob("1*.deps"))
    assert main(["cache", "check"]) == 0
    assert "0 ambiguous" in capsys.readouterr().out


def test_cache_check_without_a_cache_is_a_usage_error(tmp_path, capsys):
    assert main(["cache", "check", "--cache-dir", str(tmp_path / "none")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no saved MJX rollouts" in err
