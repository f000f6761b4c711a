"""The Ray executor: the same verdicts as the local one, self-contained tasks, and lost workers
and nodes retried with the retry in the journal (a local Ray instance; a two-node cluster)."""

import json
import logging
import os
import signal
import threading
import time

import pytest

from mjxdiff.runner import journal, pipeline
from mjxdiff.cli import main

ray = pytest.importorskip("ray", reason="the ray extra (pip install 'mjxdiff[ray]') is part of the test extra")
# Ray starts its processes by fork + exec (a Cluster's too); JAX warns of any fork in its threaded process
pytestmark = [pytest.mark.filterwarnings(r"ignore:os\.fork\(\) was called:RuntimeWarning"),
              pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")]

SCENARIOS = ("pendulum", "cartpole", "actuators")
#: What differs between two runs of one unit: wall times, memory, compile or load counts, the worker.
_RUN_INFO = {"seconds", "cpu_seconds", "compile_seconds", "guard", "plan", "mjx_compiles", "mjx_loaded", "reproducer",
             "worker", "checks_loaded"}


def _verdicts(doc: dict) -> list[dict]:
    return [{**s, "info": {k: v for k, v in s["info"].items() if k not in _RUN_INFO}} for s in doc["scenarios"]]


def _options(out, **changes) -> pipeline.SweepOptions:
    return pipeline.SweepOptions(**dict(scenarios=SCENARIOS, quick=True, out=str(out), no_history=True,
                                        progress=False) | changes)


@pytest.fixture(scope="module")
def local(tmp_path_factory):
    return pipeline.run(_options(tmp_path_factory.mktemp("local"), isolate=False))


def _delay(monkeypatch) -> str:
    """Makes this test's Ray workers wait 4 s before sweeping (time to kill one), by a value of
    ``MJXDIFF_WORKER_DELAY`` no other test's workers have; returns it (see :func:`_workers`)."""
    value = f"4.{os.getpid()}{time.monotonic_ns() % 10**6:06d}"
    monkeypatch.setenv("MJXDIFF_WORKER_DELAY", value)
    return value


def _workers(delay: str) -> list[int]:
    """Pids of this test's Ray workers running a unit now: titled ``ray::run_payload`` meanwhile,
    with this test's :func:`_delay` in their environment (another test may run Ray beside it)."""
    pids = []
    for entry in os.listdir("/proc"):
        try:
            with open(f"/proc/{entry}/cmdline", "rb") as f:
                if not f.read().startswith(b"ray::run_payload"):
                    continue
            with open(f"/proc/{entry}/environ", "rb") as f:
                if f"MJXDIFF_WORKER_DELAY={delay}".encode() in f.read().split(b"\0"):
                    pids.append(int(entry))
        except (OSError, ValueError):
            continue
    return pids


def _in_thread(target) -> tuple[threading.Thread, dict]:
    box: dict = {}

    def run():
        try:
            box["run"] = target()
        except BaseException as e:  # noqa: BLE001 - re-raised by the test
            box["error"] = e
    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread, box


def test_ray_gives_the_local_verdicts_and_journals_each_unit(local, tmp_path):
    run = pipeline.run(_options(tmp_path, executor="ray"))
    assert _verdicts(run.doc) == _verdicts(local.doc)
    records = journal.read(tmp_path / journal.FILE).units
    assert sorted(r["index"] for r in records) == [0, 1, 2]
    assert all(r["attempts"] == 1 for r in records), [(r["unit"], r["lost"]) for r in records]
    assert all(s["info"]["worker"]["pid"] != os.getpid() for s in run.doc["scenarios"])  # run by Ray's workers
    # the cache line counts what the workers traced or loaded (this process traced nothing)
    cache = run.doc["code"]["cache"]
    assert cache["where"] == "Ray's workers" and cache["traced"] + cache["loaded"] >= len(SCENARIOS), cache


def test_a_worker_killed_on_its_first_attempt_is_retried(local, tmp_path, monkeypatch):
    delay = _delay(monkeypatch)  # time to find the worker and kill it
    ray.init(address="local", num_cpus=2, object_store_memory=100 << 20, include_dashboard=False,
             log_to_driver=False, logging_level=logging.ERROR)  # here: ray.init wants the main thread
    try:
        thread, box = _in_thread(lambda: pipeline.run(_options(tmp_path, executor="ray", scenarios=("pendulum",))))
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and not _workers(delay):
            time.sleep(0.1)
        victims = _workers(delay)
        assert victims, f"no Ray worker ever ran the unit: {box}"
        os.kill(victims[0], signal.SIGKILL)
        thread.join(600)
    finally:
        ray.shutdown()
    assert "error" not in box, box.get("error")
    run = box["run"]
    assert _verdicts(run.doc) == _verdicts(local.doc)[:1]
    [record] = journal.read(tmp_path / journal.FILE).units
    print(f"\nkilled worker {victims[0]}; journal: {record['unit']} attempts {record['attempts']}, "
          f"lost {record['lost']}")
    assert record["attempts"] == 2 and "WorkerCrashedError" in record["lost"][0], record["lost"]


def test_a_node_removed_mid_sweep_loses_no_verdict(local, tmp_path, monkeypatch):
    """A head and a worker node (one CPU each); the worker node is removed while both run a
    unit: every verdict still arrives, the lost one retried on the head, as the journal says."""
    from ray.cluster_utils import Cluster

    delay = _delay(monkeypatch)
    cluster = Cluster(initialize_head=True, head_node_args=dict(num_cpus=1, object_store_memory=100 << 20))
    node = cluster.add_node(num_cpus=1, object_store_memory=100 << 20)
    try:
        cluster.wait_for_nodes()
        ray.init(address=cluster.address, include_dashboard=False, log_to_driver=False, logging_level=logging.ERROR)
        thread, box = _in_thread(lambda: pipeline.run(_options(tmp_path, executor="ray")))
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and len(_workers(delay)) < 2:
            time.sleep(0.1)
        assert len(_workers(delay)) >= 2, "the two nodes never ran a unit each"
        cluster.remove_node(node)
        thread.join(600)
        assert "error" not in box, box.get("error")
        assert _verdicts(box["run"].doc) == _verdicts(local.doc)
        records = journal.read(tmp_path / journal.FILE).units
        print("\nnode removed; journal:" + "".join(f"\n  {r['unit']}: attempts {r['attempts']}, lost {r['lost']}"
                                                   for r in records))
        retried = [r for r in records if r["attempts"] > 1]
        assert retried and all(r["lost"] for r in retried), [(r["unit"], r["attempts"], r["lost"]) for r in records]
    finally:
        ray.shutdown()
        cluster.shutdown()


def test_ray_options_are_checked(tmp_path, monkeypatch, capsys):
    assert main(["sweep", "pendulum", "--no-history", "--address", "auto"]) == 2
    assert "--address and --cpus-per-scenario are for --executor ray" in capsys.readouterr().err
    import builtins

    real = builtins.__import__

    def no_ray(name, *args, **kwargs):
        if name == "ray" or name.startswith("ray."):
            raise ImportError("No module named 'ray'")
        return real(name, *args, **kwargs)
    monkeypatch.setattr(builtins, "__import__", no_ray)
    assert main(["sweep", "pendulum", "--no-history", "--executor", "ray"]) == 2
    err = capsys.readouterr().err
    assert "pip install 'mjxdiff[ray]'" in err and len(err.strip().splitlines()) == 1


def test_a_unit_ships_its_model_directory_and_nothing_else(tmp_path):
    from mjxdiff.runner.executors import payload
    from mjxdiff.input.scenario import load_scenario
    from mjxdiff.runner.sweep import SweepConfig

    (tmp_path / "assets").mkdir()
    (tmp_path / "assets" / "part.xml").write_text('<mujoco><worldbody><geom size=".1"/></worldbody></mujoco>')
    (tmp_path / "robot.xml").write_text('<mujoco><include file="assets/part.xml"/></mujoco>')
    p = payload(load_scenario(tmp_path / "robot.xml"), SweepConfig(), ["mujoco.mjx"], 1, None)
    assert set(p.files) == {"robot.xml", os.path.join("assets", "part.xml")}
    assert p.scenario.model == "robot.xml" and p.scenario.source is None and p.config.compile_workers == 0
    json.dumps({k: v.decode() for k, v in p.files.items()})  # plain bytes, nothing of the driver's paths
