"""mjxdiff.runner.guard: a sweep in a watched child process; memory and time limits end a scenario with a
clean error, the report is written, and the next scenario runs."""

import dataclasses
import io
import json
import re
import subprocess
import sys
import threading

import pytest

from mjxdiff.runner import guard
from mjxdiff.input.scenario import load_scenario
from mjxdiff.runner.plan import out_of_memory
from mjxdiff.runner.sweep import SweepConfig, sweep

#: A humanoid stepping far longer than any budget of these tests.
LONG = """name = "long_humanoid"
model = "brax:humanoid.xml"
batch = 4
steps = 100000
"""
#: A humanoid with more members than fit the memory limit of these tests (preparing alone ~2 GB).
WIDE = """name = "wide_humanoid"
model = "brax:humanoid.xml"
batch = 4096
steps = 100
"""


def _sweep_cli(tmp_path, *args):
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, "-m", "mjxdiff", "sweep", *args, "--isolate", "--no-history",
                           "--out", str(out)], capture_output=True, text=True, timeout=600)
    doc = json.loads((out / "report.json").read_text())
    return proc, {s["name"]: s for s in doc["scenarios"]}


def test_a_horizon_past_the_budget_is_shortened_and_says_so(tmp_path):
    (tmp_path / "long.toml").write_text(LONG)
    proc, by_name = _sweep_cli(tmp_path, str(tmp_path / "long.toml"), "--budget", "20")
    long = by_name["long_humanoid"]
    planned = re.search(r"plan: steps 100000 -> (\d+) ", long["message"])
    assert planned and int(planned.group(1)) < 100000, long["message"]
    if long["status"] == "error":  # a loaded machine: the compile took the time the plan left for stepping
        assert long["error_kind"] == "budget" and long["message"].startswith("stopped at its budget of 20 s")
        return
    assert proc.returncode == 0 and long["status"] == "pass", long["message"]
    assert long["info"]["steps"] == int(planned.group(1)) == long["info"]["plan"]["steps"]


def test_a_scenario_past_its_budget_is_stopped_and_the_next_one_runs():
    """The child plans for a long budget (as an underestimate would), the guard holds 15 s."""
    scenarios = [load_scenario(str(_write(LONG))), load_scenario("pendulum")]
    long, pendulum = guard.sweep(scenarios, SweepConfig(budget=1e4), guard.Limits(8 * 2**30, budget=15))
    assert long.status == "error" and long.error_kind == "budget"
    assert long.message.startswith("stopped: its budget of 15 s (--budget) ran out while ")
    assert "MJX: compile ~" in long.message  # the estimate, for the user to judge
    assert long.info["guard"]["seconds"] >= 15
    assert pendulum.status == "pass"


def _write(text: str):
    import tempfile
    from pathlib import Path

    path = Path(tempfile.mkdtemp()) / "scenario.toml"
    path.write_text(text)
    return path


def test_a_scenario_past_the_memory_limit_is_stopped_and_the_next_one_runs(tmp_path):
    (tmp_path / "wide.toml").write_text(WIDE)
    proc, by_name = _sweep_cli(tmp_path, str(tmp_path / "wide.toml"), "pendulum", "--max-memory", "1.5G")
    assert proc.returncode == 1, proc.stderr
    wide = by_name["wide_humanoid"]
    assert wide["status"] == "error" and wide["error_kind"] == "memory", wide["message"]
    assert "limit 1.5 GB (--max-memory)" in wide["message"] and "Traceback" not in proc.stderr
    assert wide["info"]["guard"]["peak_rss_bytes"] > 1.5 * 2**30
    assert by_name["pendulum"]["status"] == "pass"
    assert "stopped by a limit" in proc.stdout.splitlines()[-1]


def test_a_compile_estimated_past_the_budget_stops_at_once():
    [r] = sweep([load_scenario("pendulum")], SweepConfig(quick=True, budget=0.5))
    assert r.status == "error" and r.error_kind == "budget"
    assert "the compile alone exceeds the scenario's budget" in r.message and "nothing was run" in r.message
    assert r.info["estimate"]["compile_s"] > 0.5 and "mjx_compiles" not in r.info


def test_mjx_patched_in_this_process_is_swept_here_not_in_a_child(monkeypatch, capsys, fresh_mjx):
    """The child would load the installed MJX: a patch made here must not be tested away."""
    from mujoco.mjx._src import smooth

    real = smooth.rne

    def rne(m, d, flg_acc=False):  # gravity and bias forces 1% too large
        d = real(m, d, flg_acc)
        return d.replace(qfrc_bias=d.qfrc_bias * 1.01)

    monkeypatch.setattr(smooth, "rne", rne)
    [r] = guard.sweep([load_scenario("pendulum")], SweepConfig(batch=2, steps=60, onestep=False, transfer=False,
                                                               diagnose="none"), guard.Limits(8 * 2**30))
    assert "differs from the one a new process loads" in capsys.readouterr().err
    assert r.status == "fail", r.message  # the patch was swept


def test_mjx_and_xla_alarms_become_one_line_of_the_scenario():
    watch = guard._Watch(1)
    watch.flying[0] = guard._Flight(0.0)
    stream = io.BytesIO(
        b'/x/mesh.py:141: UserWarning: Mesh "link1_c" has a coplanar face with more than 20 vertices. This may\n'
        b"  warnings.warn(\n"
        b'/x/mesh.py:141: UserWarning: Mesh "link1_c" has a coplanar face with more than 20 vertices. This may\n'
        b"2026-11-26 E0000 slow_operation_alarm.cc:73] ****\nVery slow compile? If you want to file a bug\n"
        b"an ordinary line\n")
    err = io.StringIO()
    old, sys.stderr = sys.stderr, err
    try:
        guard._read_stderr(stream, watch, threading.Lock())
    finally:
        sys.stderr = old
    assert watch.alarms[0] == ["MJX: mesh link1_c has a coplanar face with more than 20 vertices: decimate it",
                               "XLA: very slow compile (XLA's own alarm); see the estimate"]
    assert "an ordinary line" in err.getvalue() and "coplanar" not in err.getvalue()


def test_an_xla_allocation_failure_names_the_batch_that_fits():
    inputs = type("I", (), {"batch": 8})()
    line = out_of_memory("RESOURCE_EXHAUSTED: Out of memory allocating 105414900936 bytes.", inputs,
                         dict(plan=dict(group=8, max_memory=20 * 2**30)))
    assert line.startswith("out of memory: MJX's stepping of 8 member(s)")
    assert "98.2 GB" in line and "per member" in line and ("a batch of" in line or "not even one member" in line)


@pytest.mark.parametrize("text, size", [("12G", 12 * 2**30), ("800M", 800 * 2**20), ("1.5GB", int(1.5 * 2**30)),
                                        ("4096", 4096)])
def test_parse_size(text, size):
    assert guard.parse_size(text) == size


def test_in_process_a_scenario_stops_itself_at_its_budget_between_pieces(monkeypatch):
    """Without the guard (the API's sweep), the budget still holds between pieces of stepping:
    here the estimate is made to say the long horizon fits, as an underestimate would."""
    from mjxdiff.input import cost

    real = cost.estimate
    monkeypatch.setattr(cost, "estimate", lambda m: dataclasses.replace(real(m), compile_s=0.0, step_s=1e-9))
    long, pendulum = sweep([load_scenario(str(_write(LONG))), load_scenario("pendulum")],
                           SweepConfig(budget=5.0, compile_workers=0))
    assert long.status == "error" and long.error_kind == "budget"
    assert long.message.startswith("stopped at its budget of 5 s: stepped ") and " of 100000 steps" in long.message
    assert pendulum.status == "pass"


def test_the_child_stops_when_the_guard_is_killed(tmp_path):
    """A guard killed outright (SIGKILL) leaves no child compiling or stepping on its own."""
    import os
    import signal
    import time

    (tmp_path / "long.toml").write_text(LONG)
    parent = subprocess.Popen([sys.executable, "-m", "mjxdiff", "sweep", str(tmp_path / "long.toml"), "--isolate",
                               "--no-history", "--budget", "10000"], stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL)

    def children() -> list[int]:
        found = []
        for pid in filter(str.isdigit, os.listdir("/proc")):
            try:
                with open(f"/proc/{pid}/stat") as f:
                    ours = int(f.read().rsplit(")", 1)[1].split()[1]) == parent.pid
                with open(f"/proc/{pid}/cmdline", "rb") as f:
                    if ours and b"mjxdiff.runner.guard" in f.read():
                        found.append(int(pid))
            except (OSError, ValueError, IndexError):
                pass
        return found

    deadline = time.monotonic() + 60
    while not children() and time.monotonic() < deadline:
        time.sleep(0.2)
    [child] = children()
    time.sleep(20)  # the child is stepping by now: a long phase that sends nothing
    assert os.path.exists(f"/proc/{child}")
    os.kill(parent.pid, signal.SIGKILL)
    parent.wait()
    deadline = time.monotonic() + 10

    def running() -> bool:  # exists and is not a zombie
        try:
            with open(f"/proc/{child}/stat") as f:
                return f.read().rsplit(")", 1)[1].split()[0] != "Z"
        except OSError:
            return False

    while running() and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not running()


def test_a_scenario_stopped_after_its_rollout_keeps_the_rollouts_verdict():
    """Killed in the checks after the rollout (a rerun's compile), the rollout's verdict stands."""
    from mjxdiff.compare.verdict import ScenarioResult

    flight = guard._Flight(0.0, phase="diagnosing")
    flight.verdict = ScenarioResult(name="arm", status="fail", message="qpos of joint 'j5' leaves the envelope",
                                    info=dict(batch=8))
    r = guard._stopped("arm", "budget", "its budget of 600 s (--budget) ran out", flight, guard.Limits(2**30, 600), 0)
    assert r.status == "fail" and r.info["batch"] == 8 and r.info["guard"]["phase"] == "diagnosing"
    assert r.message.startswith("qpos of joint 'j5' leaves the envelope; its budget of 600 s (--budget) ran out "
                                "while diagnosing")
    assert r.message.endswith("the checks after the rollout did not finish")
    flight.verdict = None
    assert guard._stopped("arm", "budget", "x", flight, guard.Limits(2**30, 600), 0).status == "error"
