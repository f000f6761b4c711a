"""XLA in an mjxdiff process: its configuration (CPU devices, thread pool, precision, caches), the
options a rollout is compiled with, and telemetry of what the process compiled.

:func:`configure_jax` sets XLA up before JAX's backend starts (the CLI calls it first; importing
mjxdiff changes nothing); :func:`xla_options` chooses how hard XLA optimises a rollout;
:func:`compile_count`, :func:`compile_seconds` and :func:`xla_compiles` count the traces and
compiles, from JAX's own compile events. Re-exported by :mod:`mjxdiff.engine.engines`.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

# Load-bearing, the XLA CPU thread pool: jax's batched LAPACK kernels (the Newton solver's
# Cholesky) split a large enough batch into tasks on XLA's intra-op pool and block their own
# thread until those finish. If every pool thread is blocked that way, nothing runs the tasks
# and the rollout never returns (0% CPU; gdb: two threads in CholeskyFactorization::Kernel,
# the rest idle). The pool has one thread per core by default, so two concurrent kernels
# deadlock a 2-core machine: two devices of a split batch (humanoid, 64 members per device,
# 3/3 hangs), or two kernels one device runs side by side (the concurrency-optimised
# scheduler; 56-dof primitive_pairs). PJRT_NPROC sizes the pool: with more threads than
# kernels that can block at once (one per device; pool = cores + devices) it cannot
# deadlock (3/3 passes). The scheduler and the multithreaded Eigen pool (PyAutoFit #1528)
# stay off as well.
# All of this is read once, when JAX's backend starts, so it is set by configure_jax (the
# CLI calls it first), never by importing mjxdiff: a research process that imports the
# metrics keeps its own XLA settings.
#
# Host devices to split MJX's batch over: configure_jax(devices=N), MJXDIFF_DEVICES, default
# one per core. A single XLA CPU device runs a vmapped MJX rollout on about one core; split
# over devices, each runs its share on its own thread. MJXEngine splits only batches big
# enough to gain from it.
#: CPUs this process may use: ``MJXDIFF_CORES`` (what a cluster task was given, see
#: :mod:`mjxdiff.runner.executors`), else the machine's. Host devices, C threads and compile workers follow it.
CORES = int(os.environ.get("MJXDIFF_CORES") or 0) or os.cpu_count() or 1
#: XLA flags that keep a blocking LAPACK kernel from starving the pool (see above).
SAFETY_FLAGS = ("--xla_cpu_enable_concurrency_optimized_scheduler=false", "--xla_cpu_multi_thread_eigen=false")
_DEVICE_FLAG = "--xla_force_host_platform_device_count"

import jax  # noqa: E402

from mjxdiff.compat import BALANCED_COMPILE, FAST_COMPILE, fast_compile_validated, jaxlib_validated  # noqa: E402
from mjxdiff.engine import export_cache  # noqa: E402
from mjxdiff.engine.digest import untraced  # noqa: E402
from mjxdiff.input.options import COMPILE_MODES  # noqa: E402 - the values of MJXEngine's ``compile``
from mjxdiff.input.precision import Precision  # noqa: E402

__all__ = ["CORES", "COMPILE_MODES", "SAFETY_FLAGS", "compile_count", "compile_seconds", "configure_jax",
           "device_count", "xla_compiles", "xla_options"]


def _backend_started() -> bool:
    from jax._src import xla_bridge

    return xla_bridge.backends_are_initialized()


def _flag_value(flags: str, name: str) -> str | None:
    values = [f.split("=", 1)[1] for f in flags.split() if f.startswith(name + "=")]
    return values[-1] if values else None


def _xla_settings(devices: int | None) -> tuple[str, str, int]:
    """(XLA_FLAGS, PJRT_NPROC, devices) mjxdiff wants: the safety flags, and ``devices`` host
    devices (None: an inherited device-count flag, else ``MJXDIFF_DEVICES``, else one per core)."""
    flags = os.environ.get("XLA_FLAGS", "")
    if devices is None and os.environ.get("MJXDIFF_DEVICES"):
        devices = int(os.environ["MJXDIFF_DEVICES"])
    if devices is None:
        devices = int(_flag_value(flags, _DEVICE_FLAG) or CORES)
    kept = [f for f in flags.split() if not f.startswith(_DEVICE_FLAG)]
    wanted = kept + [f for f in SAFETY_FLAGS if f.split("=")[0] not in flags] + [f"{_DEVICE_FLAG}={devices}"]
    return " ".join(wanted), os.environ.get("PJRT_NPROC") or str(CORES + devices), devices


_CONFIGURED = untraced({"done": False})


def configure_jax(precision: Precision = "float64", cache_dir: str | os.PathLike | None = None,
                  devices: int | None = None) -> None:
    """Sets up JAX for mjxdiff in this process: XLA's CPU devices and thread pool, precision,
    persistent compilation cache. The CLI calls it first; importing mjxdiff changes nothing.

    XLA reads its flags once, when JAX's backend starts (the first computation). Before
    that, this sets ``XLA_FLAGS`` (``devices`` host devices and :data:`SAFETY_FLAGS`) and
    ``PJRT_NPROC`` (cores + devices: a pool a blocking kernel per device cannot starve).
    After that it changes neither and says so in one line on stderr if the running backend
    differs (MJX then splits its batch over the devices there are).

    Args:
      precision: ``float64`` (``jax_enable_x64``, the default: algorithmic
        differences are not drowned by rounding) or ``float32``.
      cache_dir: persistent compilation cache directory; ``None`` uses
        ``$MJXDIFF_CACHE`` or ``~/.cache/mjxdiff/jax``; ``""`` disables it.
      devices: host CPU devices; None: ``MJXDIFF_DEVICES``, else an inherited
        ``--xla_force_host_platform_device_count``, else one per core.
    """
    if precision not in ("float32", "float64"):
        raise ValueError(f"precision must be float32 or float64, got {precision!r}")
    if devices is not None and devices < 1:
        raise ValueError(f"devices must be positive, got {devices!r}")
    flags, nproc, want = _xla_settings(devices)
    if not _backend_started():
        os.environ["XLA_FLAGS"], os.environ["PJRT_NPROC"] = flags, nproc
    elif device_count() != want or not all(f in os.environ.get("XLA_FLAGS", "") for f in SAFETY_FLAGS):
        import sys

        print(f"mjxdiff: JAX's backend had already started ({device_count()} CPU device(s), XLA_FLAGS="
              f"{os.environ.get('XLA_FLAGS', '')!r}); mjxdiff's settings ({want} device(s), {' '.join(SAFETY_FLAGS)}) "
              "take effect only if configure_jax runs before the first JAX computation", file=sys.stderr)
    _CONFIGURED["done"] = True
    jax.config.update("jax_enable_x64", precision == "float64")
    if cache_dir is None:
        cache_dir = os.environ.get("MJXDIFF_CACHE", Path.home() / ".cache" / "mjxdiff" / "jax")
    if not jaxlib_validated():
        cache_dir = ""  # a loaded rollout crashes some jaxlib releases (mjxdiff.compat.VALIDATED_JAXLIB)
    if cache_dir:
        # XLA's executables per CPU type (export_cache.cpu_type), mjxdiff's portable artifacts beside them
        xla_dir = Path(cache_dir).expanduser() / f"{export_cache.XLA_PREFIX}{export_cache.cpu_type()}"
        jax.config.update("jax_compilation_cache_dir", str(xla_dir))
        # every compile, however small: a sweep's many small eager ops (stacking leaves,
        # casts, metrics of each shape) otherwise recompile in every new process
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)


def _ensure_safe_backend() -> None:
    """Before MJX's first computation in a process that never called :func:`configure_jax`:
    the :data:`SAFETY_FLAGS` (nothing else), if JAX has not started yet; without them a
    vmapped Newton solver can hang XLA's CPU pool. Called when an engine is used, not on import."""
    if _CONFIGURED["done"]:
        return
    _CONFIGURED["done"] = True
    if not _backend_started():
        flags = os.environ.get("XLA_FLAGS", "")
        os.environ["XLA_FLAGS"] = " ".join([flags] + [f for f in SAFETY_FLAGS if f.split("=")[0] not in flags]).strip()


_COMPILES = untraced({"count": 0, "seconds": 0.0, "xla": 0})
# JAX's own timings of tracing, lowering and XLA compilation (a persistent-cache hit is
# timed as the load that replaces compilation), by the compile phase each counts in.
_COMPILE_EVENTS = {"/jax/core/compile/jaxpr_trace_duration": "trace",
                   "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
                   "/jax/core/compile/backend_compile_duration": "xla"}
# the part of a backend compile that was a persistent-cache hit's load (timed inside it)
_CACHE_RETRIEVAL = "/jax/compilation_cache/cache_retrieval_time_sec"


def _on_duration(event: str, duration_secs: float, **_) -> None:
    kind = _COMPILE_EVENTS.get(event)
    if kind is not None:
        _COMPILES["seconds"] += duration_secs
        export_cache.count("seconds", duration_secs)
        export_cache.count(kind, duration_secs)
    elif event == _CACHE_RETRIEVAL:
        export_cache.count("xla", -duration_secs)
        export_cache.count("cache_load", duration_secs)
    if kind == "xla":
        _COMPILES["xla"] += 1


def _traced() -> None:
    _COMPILES["count"] += 1
    export_cache.count("traced")


# JAX calls it during a trace; it counts, and emits nothing the trace records
jax.monitoring.register_event_duration_secs_listener(untraced(_on_duration))


def compile_count() -> int:
    """How many times the MJX rollout has been traced (compiled) in this process.

    A rollout loaded from a saved artifact (:mod:`mjxdiff.engine.export_cache`) is not
    traced and not counted here: see :func:`export_cache.loaded_count`.
    """
    return _COMPILES["count"]


def xla_compiles() -> int:
    """XLA compiles of any JAX function in this process so far (a persistent-cache hit counts too)."""
    return _COMPILES["xla"]


def compile_seconds() -> float:
    """Seconds this process has spent compiling JAX functions (trace, lower, XLA compile or cache load)."""
    return _COMPILES["seconds"]


def device_count() -> int:
    """Host CPU devices JAX has (see :func:`configure_jax`)."""
    return len(jax.devices("cpu"))


#: Seconds per flop (XLA's cost analysis of one step of the batch) that :data:`FAST_COMPILE`
#: adds to stepping over :data:`BALANCED_COMPILE`: the largest measured, with a margin (ant
#: 3.7e-9, humanoid 2.8e-9, box_stack 0.8e-9, primitive_pairs 0.5e-9).
FAST_SECONDS_PER_FLOP = 4e-9
#: Stepping seconds ``auto`` may add to save compile time: :data:`FAST_COMPILE` saved
#: 1.3-2.2 s over :data:`BALANCED_COMPILE` (ant, humanoid, box_stack, primitive_pairs).
FAST_BUDGET_SECONDS = 1.0


def xla_options(mode: str, steps: int) -> export_cache.Options:
    """Chooses how hard XLA optimises a rollout from the stepping it will do.

    A sweep's rollout (8 members x 300 steps) steps for well under a second and
    compiles for 2-11 s, so its compile time decides how long the answer takes;
    a long soak run is the opposite. ``auto`` compiles with :data:`FAST_COMPILE` when
    the stepping that costs, estimated as ``FAST_SECONDS_PER_FLOP x flops x steps``
    (``flops``: XLA's cost analysis of one step of the whole batch), stays below
    :data:`FAST_BUDGET_SECONDS`, else with :data:`BALANCED_COMPILE`; ``fast`` always
    with :data:`FAST_COMPILE`; ``optimized`` with XLA's defaults. All compile the
    same StableHLO: results agree to rounding (the emitters and LLVM levels vectorise
    and contract differently), which the verdict's envelope covers
    (``tests/test_compile_options.py``); measured in ``benchmarks/scripts/xla_options.py``.

    Returns:
      ``options(lowered) -> (XLA options, choice)``, the choice being what the report records:
      ``level`` (``fast``, ``balanced`` or ``optimized``), ``mode``, and for ``auto``
      ``flops_per_step`` and ``fast_extra_seconds`` (the estimate).
    """
    def choose(lowered):
        choice: dict[str, Any] = dict(mode=mode)
        level = mode
        if mode == "auto":
            try:
                flops = float(lowered.cost_analysis().get("flops", 0.0))
            except Exception:  # noqa: BLE001 - no estimate: compile for stepping
                flops = float("inf")
            extra = FAST_SECONDS_PER_FLOP * flops * steps
            choice.update(flops_per_step=flops, fast_extra_seconds=round(extra, 3))
            level = "fast" if extra < FAST_BUDGET_SECONDS else "balanced"
        if level == "fast" and not fast_compile_validated():
            level = "balanced"  # LLVM level 0 miscompiles MJX on some jaxlib and MJX releases (mjxdiff.compat)
        choice["level"] = level
        options = {"fast": FAST_COMPILE, "balanced": BALANCED_COMPILE}.get(level, {})
        return dict(options), choice

    return choose
