"""The scenario the calling thread runs: its deadline and phase hook, and the clock and precision
every part of its run (plan, streamed verdict, follow-up checks) shares.

A sweep runs scenarios side by side on worker threads, so what belongs to one scenario is
thread-local: :data:`SCENARIO` (its deadline, phase hook and the estimated seconds of a rerun)
and JAX's ``jax_enable_x64`` (:func:`jax_precision`).
"""

from __future__ import annotations

import contextlib
import threading
import time
from typing import Any, Callable

from mjxdiff.compat import enable_x64
from mjxdiff.engine import export_cache
from mjxdiff.input.config import SweepConfig
from mjxdiff.input.precision import Precision

#: The scenario a worker thread runs: ``deadline`` (``time.monotonic()`` seconds, or None),
#: ``hook`` (its phase hook, or None) and ``rerun_s`` (seconds another compile and rollout of
#: it would take, estimated by :func:`mjxdiff.runner.plan.fit`, then measured by the verdict).
SCENARIO = threading.local()


@contextlib.contextmanager
def running(config: SweepConfig, hook: Callable[[str, dict], None] | None = None):
    """Sets this thread's scenario deadline (``config.budget`` seconds from now) and phase hook while it runs."""
    SCENARIO.deadline = time.monotonic() + config.budget if config.budget else None
    SCENARIO.hook, SCENARIO.rerun_s = hook, 0.0
    try:
        yield
    finally:
        SCENARIO.deadline = SCENARIO.hook = None


def phase(text: str, **detail) -> None:
    """Tells the phase hook (:func:`mjxdiff.runner.sweep.sweep`'s ``on_event``) what the scenario is doing now."""
    hook = getattr(SCENARIO, "hook", None)
    if hook is not None:
        hook(text, detail)


def out_of_time(rerun: bool = False) -> bool:
    """Whether the running scenario has spent its budget (``config.budget``); with ``rerun``,
    whether what is left is too short for another compile and rollout of it (``SCENARIO.rerun_s``
    seconds): a rerun started then would be stopped from outside and take the verdict with it."""
    deadline = getattr(SCENARIO, "deadline", None)
    need = getattr(SCENARIO, "rerun_s", 0.0) if rerun else 0.0
    return deadline is not None and time.monotonic() + need > deadline


class BudgetSpent(Exception):
    """The scenario's budget ran out before this part of it could run."""

    def __init__(self):
        super().__init__("the scenario's budget (--budget) ran out")


@contextlib.contextmanager
def clocked(seconds: dict[str, Any], key: str, cpu: dict[str, float] | None = None):
    """Adds the block's wall seconds less its compiling (:func:`export_cache.clock`) to ``seconds[key]``, so
    that a scenario's phases do not overlap; with ``cpu``, adds the process's CPU seconds over
    the block (compiling and other threads' work included) to ``cpu[key]``."""
    t, used = export_cache.clock(), time.process_time()
    try:
        yield
    finally:
        seconds[key] = seconds.get(key, 0.0) + max(export_cache.clock() - t, 0.0)
        if cpu is not None:
            cpu[key] = cpu.get(key, 0.0) + time.process_time() - used


def jax_precision(precision: Precision):
    """``jax_enable_x64`` as ``precision`` says, for the calling thread only (JAX's thread-local
    setting): scenarios a sweep runs at once on its workers never see each other's (a float32
    sweep's float64 ablation), and the process-wide setting is left as it was."""
    return enable_x64(precision == "float64")
