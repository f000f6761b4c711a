"""The command line: exit codes, one-line errors, reports, reproducibility."""

import json
import subprocess
import sys

import pytest

from mjxdiff.output import report
from mjxdiff.cli import main

SMALL = ["--batch", "2", "--steps", "60"]

UNSTABLE_XML = """<mujoco><option timestep="0.01"/>
  <worldbody><body><joint name="spring" type="hinge" stiffness="1e14"/><geom size=".1"/></body></worldbody>
</mujoco>"""


def _run(*args):
    return subprocess.run([sys.executable, "-m", "mjxdiff", *args], capture_output=True, text=True, timeout=600)


@pytest.mark.parametrize("args, message", [
    (["sweep", "--bogus"], "unrecognized arguments: --bogus (see"),
    (["sweep", "--quik"], "unrecognized arguments: --quik; did you mean --quick?"),
    (["sweep", "--scenarios", "pendulum"], "'mjxdiff sweep' takes SCENARIO ... as arguments, without a flag"),
    (["list", "--impl", "mjx"], "--impl is a flag of 'mjxdiff sweep'"),
    (["sweep", "--batch", "0"], "expected a positive integer"),
    (["sweep", "--precision", "float16"], "invalid choice"),
    (["sweep", "--noise-floor", "sometimes"], "invalid choice"),
    (["sweep", "--max-memory", "lots"], "not a size"),
    (["sweep", "--budget", "0"], "expected seconds"),
    (["sweep", "--sweep-budget", "soon"], "expected seconds"),
    (["frobnicate"], "invalid choice"),
    ([], "required"),
])
def test_bad_flags_exit_2_with_one_line(args, message):
    proc = _run(*args)
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1 and message in proc.stderr
    assert "Traceback" not in proc.stderr


def test_a_sweep_of_nothing_but_bad_scenarios_is_one_line_without_jax_or_mjx(tmp_path, repo_root):
    """Every named scenario unreadable (a typo, a missing file, an MJCF cut short): exit 2 with one
    line naming each, before JAX or MJX is imported (the same check in a sweep with a good
    scenario beside reports them and runs it)."""
    cut = tmp_path / "cut.xml"  # cut short after line 16: MuJoCo's parser blames line 1, where <mujoco> opens
    cut.write_text("".join((repo_root / "scenarios" / "models" / "cg_frictionless.xml").read_text()
                           .splitlines(keepends=True)[:16]))
    code = (f"import sys; from mjxdiff.cli import main; rc = main(['sweep', 'pendulm', '/no/such.xml', '{cut}']); "
            "print([m for m in ('jax', 'mujoco.mjx') if m in sys.modules]); sys.exit(rc)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 2 and proc.stdout.strip() == "[]", proc.stdout + proc.stderr
    assert proc.stderr.count("\n") == 1 and "did you mean 'pendulum'" in proc.stderr and "/no/such.xml" in proc.stderr
    assert "cut.xml: not well-formed XML: the file ends at line 17 with elements still open" in proc.stderr


def test_version_names_mjxdiff_and_the_engines_it_would_test():
    from importlib import metadata

    proc = _run("--version")
    assert proc.returncode == 0 and proc.stdout.count("\n") == 1, proc.stdout + proc.stderr
    assert proc.stdout.startswith("mjxdiff ") and f"mujoco-mjx {metadata.version('mujoco-mjx')}" in proc.stdout
    assert f"jax {metadata.version('jax')}" in proc.stdout


def test_help_teaches_statuses_and_exit_codes():
    proc = _run("sweep", "--help")
    assert proc.returncode == 0
    for word in ("--seed", "--precision", "--out", "--noise-floor", "exit codes", "UNSUP", "examples",
                 "--drop-unsupported", "--no-adjust", "adjusted"):
        assert word in proc.stdout


def test_list_names_every_bundled_scenario(capsys):
    from mjxdiff.input.scenario import bundled_scenarios

    assert main(["list"]) == 0
    out = capsys.readouterr().out
    for s in bundled_scenarios():
        assert s.name in out


def test_bad_inputs_are_reported_and_the_rest_still_runs(tmp_path, capsys):
    broken = tmp_path / "broken.xml"
    broken.write_text("<mujoco><worldbody><geom type='sphere'</worldbody></mujoco>")
    code = main(["sweep", "pendulm", str(broken), "pendulum", *SMALL, "--out", str(tmp_path / "o")])
    captured = capsys.readouterr()
    assert code == 2
    report = json.loads((tmp_path / "o" / "report.json").read_text())
    status = {s["name"]: s for s in report["scenarios"]}
    assert status["pendulm"]["status"] == "error" and "did you mean 'pendulum'" in status["pendulm"]["message"]
    assert status["broken"]["status"] == "error" and "cannot compile" in status["broken"]["message"]
    assert status["pendulum"]["status"] == "pass"
    assert "PASS   pendulum" in captured.out
    # input errors are named as such, not as a divergence
    summary_line = captured.out.strip().splitlines()[-1]
    assert "2 input error" in summary_line and "INPUT ERROR" in summary_line and "DIVERGENT" not in summary_line
    assert (report["summary"]["input_error"], report["summary"]["error"], report["summary"]["verdict"]) == (
        2, 0, "input-error")


def test_unsupported_feature_is_named_and_not_a_failure(capsys):
    code = main(["sweep", "energy_flag", "--no-adjust", *SMALL])
    out = capsys.readouterr().out
    assert code == 0
    assert "UNSUP" in out and "mjENBL_ENERGY" in out


def test_nan_scenario_reported_rest_continue(tmp_path, capsys):
    xml = tmp_path / "unstable.xml"
    xml.write_text(UNSTABLE_XML)
    code = main(["sweep", str(xml), "pendulum", *SMALL, "--format", "json"])
    report = json.loads(capsys.readouterr().out)
    unstable, pendulum = report["scenarios"]
    assert code == 1
    # C itself blows up: an unstable scenario, not an MJX divergence
    assert unstable["status"] == "error" and unstable["error_kind"] == "unstable"
    assert {d["engine"] for d in unstable["diverged_members"]} == {"c"}
    assert "MuJoCo C itself" in unstable["message"] and "step" in unstable["message"]
    assert "member" in unstable["message"]
    assert pendulum["status"] == "pass"


def test_report_schema_and_same_seed_same_report(tmp_path, capsys):
    args = ["sweep", "pendulum", "cartpole", *SMALL, "--seed", "3"]
    assert main([*args, "--out", str(tmp_path / "a")]) == 0
    assert main([*args, "--out", str(tmp_path / "b")]) == 0
    a = json.loads((tmp_path / "a" / "report.json").read_text())
    b = json.loads((tmp_path / "b" / "report.json").read_text())
    assert a["schema_version"] == 3 and report.validate(a, "sweep") == []
    assert {"jax", "mujoco", "mujoco-mjx", "mjxdiff"} <= a["versions"].keys()
    cache_a, cache_b = a["code"].pop("cache"), b["code"].pop("cache")  # what the cache held, not what was found
    assert a["code"] == b["code"] and len(a["code"]["mjx"]) == 64, "the tested MJX, named by content"
    assert {"dir", "loaded", "traced", "saved", "unsaved", "ambiguous", "removed"} <= cache_b.keys()
    assert cache_b["unsaved"] == [] == cache_a["ambiguous"]
    assert a["summary"]["verdict"] == "consistent" and a["summary"]["input_error"] == 0
    assert a["config"]["seed"] == 3 and a["config"]["batch"] == 2
    for sa, sb in zip(a["scenarios"], b["scenarios"]):
        for key in ("seconds", "cpu_seconds", "compile_seconds"):  # timings
            sa["info"].pop(key), sb["info"].pop(key)
        for key in ("mjx_compiles", "mjx_loaded", "checks_loaded"):  # what the caches held, not what was found
            sa["info"].pop(key, None), sb["info"].pop(key, None)
        assert sa == sb
    fields = a["scenarios"][0]["fields"]
    assert {"qpos", "qvel", "sensordata", "contacts"} <= fields.keys()
    assert {"max_error", "tolerance", "first_step"} <= fields["qpos"].keys()


def test_float32_precision_passes_with_its_tolerances():
    proc = _run("sweep", "pendulum", *SMALL, "--precision", "float32", "--format", "json")
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    report = json.loads(proc.stdout)
    (pendulum,) = report["scenarios"]
    assert pendulum["status"] == "pass"
    assert pendulum["tolerances"]["qpos"] >= 1e-3
