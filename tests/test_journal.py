"""The journal: every finished unit on disk at once, a killed sweep resumed without recomputing
what was recorded, shards merged into the report one run gives, and disagreement flagged."""

import dataclasses
import json
import os
import signal
import subprocess
import sys
import time

import pytest

from mjxdiff.runner import journal, pipeline
from mjxdiff.output import report
from mjxdiff.runner.sweep import SweepConfig

SCENARIOS = ("pendulum", "cartpole", "actuators")
#: What differs between two runs of one unit: wall times, memory, compile or load counts.
_RUN_INFO = {"seconds", "cpu_seconds", "compile_seconds", "guard", "plan", "mjx_compiles", "mjx_loaded",
             "reproducer", "checks_loaded"}


def _verdicts(doc: dict) -> list[dict]:
    return [{**s, "info": {k: v for k, v in s["info"].items() if k not in _RUN_INFO}} for s in doc["scenarios"]]


def _options(out, **changes) -> pipeline.SweepOptions:
    return pipeline.SweepOptions(scenarios=SCENARIOS, quick=True, out=str(out), no_history=True, isolate=False,
                                 progress=False, **changes)


@pytest.fixture(scope="module")
def whole(tmp_path_factory):
    """One quick sweep of :data:`SCENARIOS` with a journal."""
    out = tmp_path_factory.mktemp("whole")
    return pipeline.run(_options(out)), out


# --- the file ---------------------------------------------------------------------


def test_a_torn_last_line_and_bad_lines_are_skipped(tmp_path):
    path = tmp_path / journal.FILE
    with journal.Journal(path) as j:
        j.write(dict(type="header", units=2))
        j.unit("k1", {}, 0, dict(name="a", status="pass", info={"seconds": {"c": 1.0, "mjx": 2.0}}))
    with open(path, "ab") as f:
        f.write(b"not json\n")
        f.write(b'{"type":"unit","key":"k2","ind')  # a write cut short by a kill
    got = journal.read(path)
    assert got.header == dict(type="header", units=2)
    assert [r["key"] for r in got.units] == ["k1"] and got.units[0]["seconds"] == 3.0
    assert got.torn and got.bad == [3]
    with journal.Journal(path, append=True) as j:  # appending after a torn line: the torn bytes stay one bad line
        j.write(dict(type="unit", key="k3", index=1, unit="b", result={}))
    assert [r["key"] for r in journal.read(path).units] == ["k1"]
    assert journal.read(tmp_path / "absent.jsonl").units == []


def test_the_key_holds_what_decides_a_verdict_and_nothing_else():
    config = SweepConfig(seed=0, batch=4)
    base = journal.config_digest(config)
    for change in (dict(seed=1), dict(batch=8), dict(precision="float32"), dict(onestep=False)):
        assert journal.config_digest(dataclasses.replace(config, **change)) != base, change
    for field in journal.RESOURCE_FIELDS:  # where files go, how much of the machine: not the verdict
        value = {"reproducers": "elsewhere", "compile_workers": 7, "budget": 5.0, "max_memory": 10}[field]
        assert journal.config_digest(dataclasses.replace(config, **{field: value})) == base, field

    def key(**changes):
        args = dict(scenario_hash="s", suffix="", config=config, mjx="mjx", own="own", versions={"mujoco": "4.0.0"})
        return journal.unit_key(**(args | changes))

    first, parts = key()
    assert set(parts) == {"scenario", "pair", "seed", "config", "mjx", "mjxdiff", "versions"}
    for change in (dict(scenario_hash="t"), dict(suffix="@warp"), dict(mjx="edited MJX"), dict(own="edited mjxdiff"),
                   dict(versions={"mujoco": "3.9.0"}), dict(config=dataclasses.replace(config, seed=1))):
        assert key(**change)[0] != first, change


def test_only_settled_verdicts_are_reused():
    def record(status, kind=""):
        return dict(result=dict(status=status, error_kind=kind))
    assert all(journal.reusable(record(s)) for s in ("pass", "fail", "unsupported"))
    assert journal.reusable(record("error", "input"))
    assert not any(journal.reusable(record("error", k)) for k in ("engine", "worker", "budget", "memory"))
    assert journal.reusable(record("pass"), "failed") and not journal.reusable(record("fail"), "failed")


# --- sweeps -----------------------------------------------------------------------


def test_every_verdict_round_trips_through_its_record(whole):
    run, out = whole
    records = journal.read(out / journal.FILE)
    assert records.header["config"]["scenarios"] == list(SCENARIOS) and records.header["units"] == 3
    assert [r["unit"] for r in records.units] == list(SCENARIOS) and [r["index"] for r in records.units] == [0, 1, 2]
    for r, record in zip(run.results, records.units):
        assert report.result_dict(report.result_from_dict(record["result"])) == report.result_dict(r)
    assert run.doc["journal"]["file"] == str(out / journal.FILE)


def test_shards_merged_give_the_report_of_one_run_in_any_order(whole, tmp_path):
    run, _ = whole
    shards = []
    for i in (1, 2, 3):
        shard = pipeline.run(_options(tmp_path / f"shard{i}", shard=f"{i}/3"))
        assert [r.name for r in shard.results] == [SCENARIOS[i - 1]]
        shards.append(str(tmp_path / f"shard{i}"))
    merged = pipeline.merge(str(tmp_path / "merged"), shards[::-1])
    assert merged.exit_code == 0 and merged.doc["journal"]["missing"] == []
    assert _verdicts(merged.doc) == _verdicts(run.doc)
    again = pipeline.merge(str(tmp_path / "again"), shards + shards[:1])  # idempotent: a directory twice
    assert _verdicts(again.doc) == _verdicts(run.doc) and again.doc["journal"]["nondeterministic"] == []
    partial = pipeline.merge(str(tmp_path / "partial"), shards[:2])
    assert partial.exit_code == 1 and partial.doc["journal"]["missing"] == [2]


def _lines(out) -> list[str]:
    return (out / journal.FILE).read_text().splitlines()


def _journal_dir(path, records: list) -> str:
    """A directory whose journal holds ``records`` (JSON lines or dicts)."""
    path.mkdir()
    (path / journal.FILE).write_text("".join((r if isinstance(r, str) else json.dumps(r)) + "\n" for r in records))
    return str(path)


def test_disagreeing_records_of_one_unit_are_nondeterminism(whole, tmp_path):
    _, out = whole
    lines = _lines(out)
    record = json.loads(lines[2])
    record["result"]["fields"]["qpos"]["max_error"] *= 3  # the same unit, another number
    other = _journal_dir(tmp_path / "other", [lines[0], record])
    merged = pipeline.merge(str(tmp_path / "merged"), [str(out), other])
    assert merged.doc["journal"]["nondeterministic"] == [record["unit"]] and merged.exit_code == 1


def test_shards_of_different_sweeps_are_refused(whole, tmp_path):
    _, out = whole
    header = json.loads(_lines(out)[0])
    header["config"]["seed"] = 1
    other = _journal_dir(tmp_path / "seed1", [header])
    with pytest.raises(pipeline.OptionsError, match="different sweeps: seed differ"):
        pipeline.merge(str(tmp_path / "m"), [str(out), other])


def test_resume_reuses_settled_units_reruns_the_rest_and_lists_stale_ones(whole, tmp_path):
    run, out = whole
    lines = _lines(out)
    crashed = json.loads(lines[2])
    crashed["result"].update(status="error", error_kind="worker", message="worker died")
    failed = json.loads(lines[3])
    failed["result"]["status"] = "fail"
    stale = json.loads(lines[1])
    stale.update(key="0" * 64, unit="renamed")  # recorded by other code or settings
    resumed_dir = tmp_path / "resumed"
    _journal_dir(resumed_dir, [lines[0], lines[1], crashed, failed, stale])
    arrived = []
    again = pipeline.run(_options(resumed_dir, resume=str(resumed_dir)), on_result=lambda r, e: arrived.append(r.name))
    assert arrived == ["cartpole"]  # only the crashed unit ran; the others came from the journal
    book = again.doc["journal"]
    assert book["reused"] == 2 and book["stale"] == ["renamed"]
    assert [s["status"] for s in again.doc["scenarios"]] == ["pass", "pass", "fail"]  # the recorded fail stands
    arrived.clear()
    rerun = pipeline.run(_options(resumed_dir, resume=str(resumed_dir), rerun="failed"),
                         on_result=lambda r, e: arrived.append(r.name))
    assert arrived == ["actuators"] and _verdicts(rerun.doc) == _verdicts(run.doc)
    other_seed = pipeline.run(_options(tmp_path / "seed1", resume=str(resumed_dir), seed=1),
                              on_result=lambda r, e: None)
    assert other_seed.doc["journal"]["reused"] == 0 and set(other_seed.doc["journal"]["stale"]) >= set(SCENARIOS)


def test_a_sweep_killed_after_its_first_record_resumes_without_recomputing_it(whole, tmp_path):
    """SIGKILL of the whole process group once the journal holds a unit; --resume then gives
    the uninterrupted run's verdicts, and sweeps only the units the journal lacked."""
    run, _ = whole
    out = tmp_path / "killed"
    cmd = [sys.executable, "-m", "mjxdiff", "sweep", *SCENARIOS, "--quick", "--out", str(out), "--no-history",
           "--compile-workers", "0"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and proc.poll() is None:
        if len(journal.read(out / journal.FILE).units) >= 1:
            os.killpg(proc.pid, signal.SIGKILL)
            break
        time.sleep(0.05)
    proc.wait()
    before = journal.read(out / journal.FILE).units
    assert proc.returncode == -signal.SIGKILL and 1 <= len(before) < len(SCENARIOS), (proc.returncode, len(before))
    assert not (out / "report.json").exists()
    done = subprocess.run([sys.executable, "-m", "mjxdiff", "sweep", *SCENARIOS, "--quick", "--resume", str(out),
                           "--no-history", "--format", "json"], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    doc = json.loads(done.stdout)
    assert _verdicts(doc) == _verdicts(run.doc)
    after = journal.read(out / journal.FILE).units
    rollouts = {s["name"]: s["info"].get("mjx_compiles", 0) + s["info"].get("mjx_loaded", 0) for s in doc["scenarios"]}
    print(f"\nSIGKILL after {[r['unit'] for r in before]} was journaled; --resume reused {doc['journal']['reused']}, "
          f"swept {[r['unit'] for r in after[len(before):]]} (MJX rollouts traced or loaded: {rollouts})")
    assert doc["journal"]["reused"] == len(before)
    assert [r["unit"] for r in after[len(before):]] == [s for s in SCENARIOS if s not in {r["unit"] for r in before}]
    assert json.loads((out / "report.json").read_text())["summary"]["total"] == len(SCENARIOS)


def test_bad_shard_and_resume_options_are_one_line_errors(tmp_path):
    from mjxdiff.cli import main

    for args, words in ((["--shard", "4/3"], "--shard 4/3: expected I/N"), (["--shard", "x"], "expected I/N"),
                        (["--resume", str(tmp_path)], "no journal.jsonl there")):
        with pytest.raises(pipeline.OptionsError, match=words):
            pipeline.compute(dataclasses.replace(_options(tmp_path), **{a.lstrip("-"): v for a, v in [args]}))
        assert main(["sweep", "pendulum", "--no-history", *args]) == 2
