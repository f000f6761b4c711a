"""Where a sweep's units run: on this machine (``local``: :mod:`mjxdiff.runner.guard`'s watched child
processes, or in process) or on a Ray cluster (``ray``: one Ray task per unit).

A Ray task is self-contained (:class:`Payload`): the scenario, the bytes of every file in its
model's directory (includes, meshes), the judged pair's settings and the names of the MJX
modules the driver digested. The worker writes the files to a temporary directory, never reads
the driver's paths, sweeps the one scenario in its own process with ``K`` CPUs
(``--cpus-per-scenario``: XLA host devices, C threads and compile workers all come from it,
never from the node's core count), computes the digest of its own MJX code and returns the
verdict as JSON with the files still to write. Only the driver writes files.

Retries are the driver's, so that they are visible: a task whose worker or node died (Ray's
``WorkerCrashedError``, ``NodeDiedError``, ``ObjectLostError`` and the like) is submitted again,
up to :data:`RETRIES` times, and the journal records every attempt's failure. A task that
raised is not retried: that is the verdict's own ``error``. A worker whose MJX code differs
from the driver's gives an ``error`` (``worker``), never a verdict on other code.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import socket
import tempfile
import time
import warnings
from pathlib import Path
from typing import Any, Callable, Sequence

from mjxdiff.errors import one_line
from mjxdiff.compare.result import ScenarioResult

__all__ = ["EXECUTORS", "MAX_SHIPPED_BYTES", "RETRIES", "Payload", "payload", "ray_missing", "ray_sweep",
           "run_payload"]

EXECUTORS = ("local", "ray")
#: Submissions of one unit whose worker or node died before the unit counts as an error.
RETRIES = 3
#: The most bytes of model files one unit ships to a worker.
MAX_SHIPPED_BYTES = 64 << 20
#: Object store per Ray node started here (Ray's default reserves 30% of RAM).
OBJECT_STORE_BYTES = 200 << 20
#: Seconds a worker waits before sweeping (fault tests: time to remove its node); 0 by default.
_DELAY_ENV = "MJXDIFF_WORKER_DELAY"


def ray_missing() -> str | None:
    """Why ``--executor ray`` cannot run here (Ray not installed), or None."""
    try:
        import ray  # noqa: F401
    except ImportError:
        return "Ray is not installed: pip install 'mjxdiff[ray]'"
    return None


@dataclasses.dataclass(frozen=True)
class Payload:
    """One unit, self-contained: ``scenario`` with ``model`` relative to ``files`` (relative
    path -> bytes), the pair's ``config``, the driver's MJX module ``names`` (the worker digests
    the same ones), the worker's ``cpus`` and JAX ``cache_dir``."""

    scenario: Any
    files: dict[str, bytes]
    config: Any
    names: tuple[str, ...]
    cpus: int
    cache_dir: str | None


def payload(scenario, config, names: Sequence[str], cpus: int, cache_dir: str | None) -> Payload:
    """The :class:`Payload` of ``scenario``: every file under its model's directory.

    Raises:
      ScenarioError: the model file is missing, or the directory holds more than
        :data:`MAX_SHIPPED_BYTES`.
    """
    from mjxdiff.input.scenario import ScenarioError

    path = scenario.model_path
    if not path.is_file():
        raise ScenarioError(f"{scenario.name}: model file not found: {path}")
    root = path.parent
    files, size = {}, 0
    for f in sorted(root.rglob("*")):
        if f.is_file() and "__pycache__" not in f.parts:
            size += f.stat().st_size
            if size > MAX_SHIPPED_BYTES:
                raise ScenarioError(f"{scenario.name}: the model's directory {root} holds more than "
                                    f"{MAX_SHIPPED_BYTES >> 20} MiB: too much to ship to a Ray worker; move the "
                                    "model and its assets to a directory of their own")
            files[str(f.relative_to(root))] = f.read_bytes()
    shipped = dataclasses.replace(scenario, model=str(path.relative_to(root)), source=None)
    return Payload(shipped, files, dataclasses.replace(config, compile_workers=0), tuple(names), cpus, cache_dir)


def run_payload(p: Payload) -> dict[str, Any]:
    """Sweeps one :class:`Payload` in this (worker) process; returns the verdict
    (:func:`mjxdiff.output.report.result_dict`), the files still to write, the worker's MJX digest,
    host and pid."""
    t0 = time.perf_counter()
    delay = float(os.environ.get(_DELAY_ENV) or 0)
    if delay:
        time.sleep(delay)
    from mjxdiff.engine import engines
    from mjxdiff.engine.digest import code_digest
    from mjxdiff.output import report
    from mjxdiff.runner.sweep import sweep

    engines.configure_jax(p.config.precision, p.cache_dir, devices=p.cpus)
    with tempfile.TemporaryDirectory(prefix="mjxdiff-unit-") as tmp:
        for rel, data in p.files.items():
            target = Path(tmp, rel)
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(data)
        scenario = dataclasses.replace(p.scenario, model=str(Path(tmp, p.scenario.model)))
        [r] = sweep([scenario], p.config)
    return dict(result=report.result_dict(r), pending=[list(x) for x in r.pending],
                mjx=code_digest(names=list(p.names)), host=socket.gethostname(), pid=os.getpid(),
                wall=time.perf_counter() - t0 - delay)


def _lost(e: BaseException) -> bool:
    """Whether ``e`` says the worker or node went away (retry), not that the unit raised."""
    from ray import exceptions as rex

    lost = tuple(getattr(rex, n) for n in ("WorkerCrashedError", "NodeDiedError", "ObjectLostError",
                                           "OwnerDiedError", "ActorDiedError", "LocalRayletDiedError",
                                           "TaskUnschedulableError", "ObjectReconstructionFailedError")
                 if hasattr(rex, n))
    return isinstance(e, lost)


def _ray_init(address: str | None, cpus: int) -> None:
    """Connects to the Ray cluster at ``address``, or (None) starts a new Ray instance here with
    at least ``cpus`` CPUs; quiet (no dashboard, no worker logs)."""
    import ray

    with warnings.catch_warnings():
        # Ray starts its processes by fork + exec; JAX warns of any fork in its threaded process
        warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called", category=RuntimeWarning)
        if address:
            ray.init(address=address, include_dashboard=False, log_to_driver=False, logging_level=logging.ERROR)
        else:
            # "local": a new instance, never another one already running here (ray.init's default)
            ray.init(address="local", num_cpus=max(cpus, os.cpu_count() or 1),
                     object_store_memory=OBJECT_STORE_BYTES, include_dashboard=False, log_to_driver=False,
                     logging_level=logging.ERROR)


def _worker_env(cpus: int) -> dict[str, str]:
    """The environment variables a Ray task runs with: ``cpus`` cores and devices, and the
    driver's worker delay, cache and scenario directories where set."""
    env = {"MJXDIFF_CORES": str(cpus), "MJXDIFF_DEVICES": str(cpus)}
    for key in (_DELAY_ENV, "MJXDIFF_CACHE", "MJXDIFF_SCENARIOS"):
        if os.environ.get(key):
            env[key] = os.environ[key]
    return env


def _failed_result(name: str, lost: bool, failures: list[str]) -> ScenarioResult:
    """The ``error`` (``worker``) of a unit whose last attempt was lost (``lost``) or raised,
    naming how many attempts failed and the last one's ``failures`` entry."""
    why = "its worker was lost" if lost else "the worker raised"
    return ScenarioResult(name=name, status="error", error_kind="worker",
                          message=f"{why} on {len(failures)} attempt(s): {failures[-1]}")


def _worker_result(got: dict[str, Any], scenario, digest: str) -> ScenarioResult:
    """The verdict a worker returned (:func:`run_payload`'s ``got``) on the driver: its pending
    files, the worker's host and pid, the driver's model path; an ``error`` (``worker``) instead
    where the worker's MJX digest is not the driver's ``digest``."""
    from mjxdiff.output import report

    r = report.result_from_dict(got["result"])
    info = {**r.info, "worker": dict(host=got["host"], pid=got["pid"])}
    if "model" in info:
        info["model"] = str(scenario.model)  # the driver's name for it, not the worker's copy
    r = dataclasses.replace(r, pending=tuple(tuple(x) for x in got["pending"]), info=info)
    if got["mjx"] != digest:
        r = ScenarioResult(name=r.name, status="error", error_kind="worker",
                           message=f"the worker on {got['host']} runs other MJX code (digest "
                                   f"{got['mjx'][:12]}, the driver's {digest[:12]}): not a verdict on "
                                   "the tested code; install the same MJX on every node")
    return r


def ray_sweep(jobs: list[tuple[Any, Any, Any]], arrived: Callable[[Any, ScenarioResult, list[str], float | None], None],
              address: str | None, cpus: int, cache_dir: str | None,
              say: Callable[[str], None] | None = None) -> dict[int, ScenarioResult]:
    """Runs ``jobs`` (unit, its scenario, its pair's SweepConfig) as Ray tasks of ``cpus`` CPUs
    each on the cluster at ``address`` (None: a Ray instance started here), at most twice the
    cluster's CPUs / ``cpus`` in flight. ``arrived(unit, result, failures, seconds)`` is called
    in completion order (``failures``: why earlier attempts were lost; ``seconds``: the task's
    wall time on its worker, None where it never ran); returns the results by unit index (the
    caller orders them)."""
    import ray

    from mjxdiff.engine.digest import code_digest, loaded_modules
    from mjxdiff.input.scenario import ScenarioError

    names = loaded_modules()
    digest = code_digest(names=names)
    started_here = not ray.is_initialized()
    if started_here:
        _ray_init(address, cpus)
    task = ray.remote(run_payload).options(num_cpus=cpus, max_retries=0,
                                           runtime_env={"env_vars": _worker_env(cpus)})
    results: dict[int, ScenarioResult] = {}
    try:
        capacity = max(1, int(2 * ray.cluster_resources().get("CPU", cpus) // cpus))
        queue = list(jobs)
        failures: dict[int, list[str]] = {}
        flying: dict[Any, tuple[Any, Any, Any, Payload]] = {}

        def finish(unit, result: ScenarioResult, seconds: float | None = None) -> None:
            results[unit.index] = result
            arrived(unit, result, failures.get(unit.index, []), seconds)

        def submit(unit, scenario, config, p: Payload | None = None) -> None:
            if p is None:
                try:
                    p = payload(scenario, config, names, cpus, cache_dir)
                except ScenarioError as e:
                    finish(unit, ScenarioResult(name=scenario.name, status="error", error_kind="input",
                                                message=str(e)))
                    return
            flying[task.remote(p)] = (unit, scenario, config, p)

        while queue or flying:
            while queue and len(flying) < capacity:
                submit(*queue.pop(0))
            if not flying:
                continue
            [ref], _ = ray.wait(list(flying), num_returns=1)
            unit, scenario, config, p = flying.pop(ref)
            try:
                got = ray.get(ref)
            except Exception as e:  # noqa: BLE001 - a lost worker is retried, a raising unit is its verdict
                lost = _lost(e)
                failures.setdefault(unit.index, []).append(f"{type(e).__name__}: {one_line(e)}"[:300])
                if lost and len(failures[unit.index]) < RETRIES:
                    if say:
                        say(f"{scenario.name}: worker lost ({type(e).__name__}); submitted again")
                    submit(unit, scenario, config, p)
                else:
                    finish(unit, _failed_result(scenario.name, lost, failures[unit.index]))
                continue
            finish(unit, _worker_result(got, scenario, digest), got["wall"])
    finally:
        if started_here:
            ray.shutdown()
    return results
