"""The memory and time plan of a scenario's run: what fits its budget and memory (MJX's cost
estimate against ``--budget`` and ``--max-memory``), the member groups and pieces the verdict
streams in, what to say when memory or time ran out, and when a sweep lets go of its compiled
functions.
"""

from __future__ import annotations

import dataclasses
import re
import warnings

import jax
import mujoco
import numpy as np
from mujoco import mjx

from mjxdiff.engine import engines
from mjxdiff.engine.trajectory import Engine
from mjxdiff.input import cost
from mjxdiff.input.config import SweepConfig
from mjxdiff.input.inputs import BatchedInputs
from mjxdiff.runner.current import SCENARIO, phase

#: Seconds of MJX stepping a piece may take (estimated) when a member-step takes at least
#: SLOW_STEP_S: the budget is checked between pieces.
PIECE_SECONDS = 10.0
SLOW_STEP_S = 0.01

#: Budget for the memory one piece of a rollout holds (records of C, C's perturbed rerun and
#: MJX, with XLA's scan buffers and the errors and bounds computed from them), MiB.
PIECE_BUDGET_MIB = 32
#: Shortest piece, steps: shorter ones spend more time in per-call overhead than they save.
MIN_PIECE_STEPS = 50
#: Budget for MJX's working set while it steps one group of members, MiB.
GROUP_BUDGET_MIB = 4096

#: Share of the kernel's memory-map limit (``vm.max_map_count``) a sweep's process may hold
#: before it lets go of its compiled functions.
MAP_BUDGET = 0.5


@dataclasses.dataclass(frozen=True)
class Fit:
    """The run that fits a scenario's limits (:func:`fit`): ``batch`` members, ``steps`` steps,
    ``config`` (the sweep's, with the plan's member group and steps per piece), or ``stop``: the
    error kind (``budget`` or ``memory``) and message of a plan that cannot fit."""

    batch: int
    steps: int
    config: SweepConfig
    stop: tuple[str, str] | None = None


def fit(m: mujoco.MjModel, config: SweepConfig, info: dict, batch: int, steps: int) -> Fit:
    """MJX's estimated cost of ``m`` (``info['estimate']``, :func:`mjxdiff.input.cost.estimate`) and
    the plan of ``batch`` members over ``steps`` steps that fits the config's budget (seconds) and
    memory (bytes) (``info['plan']``, :func:`mjxdiff.input.cost.plan`); sets the running scenario's
    rerun estimate (``SCENARIO.rerun_s``, seconds)."""
    est = cost.estimate(m)
    info["estimate"] = est.as_dict()
    group = min(config.group_size or batch, batch)
    planned = cost.plan(est, batch, steps, group, config.budget, config.max_memory, cost.resident_bytes())
    phase("estimated", line=est.line(), compile_s=est.compile_s, member_bytes=est.member_bytes,
          stepping_s=est.step_s * planned.batch * planned.steps)
    SCENARIO.rerun_s = est.compile_s + est.step_s * planned.batch * planned.steps
    info["plan"] = dict(batch=planned.batch, steps=planned.steps, group=planned.group, changed=list(planned.changed),
                        budget=config.budget, max_memory=config.max_memory)
    if planned.stop and _refused_by_mjx(m):  # unsupported is the verdict, whatever it would cost
        return Fit(batch, steps, config)
    if planned.stop:
        return Fit(planned.batch, planned.steps, config, (planned.kind, planned.stop))
    fitted = config
    if planned.group < planned.batch:
        fitted = dataclasses.replace(fitted, group_size=planned.group)
    # slow stepping (hull-hull pairs) in short pieces: the budget is checked between pieces
    piece = max(1, int(PIECE_SECONDS // (est.step_s * planned.group)))
    if est.step_s >= SLOW_STEP_S and piece < planned.steps and config.piece_steps is None:
        fitted = dataclasses.replace(fitted, piece_steps=piece)
        info["plan"]["piece_steps"] = piece
    return Fit(planned.batch, planned.steps, fitted)


def _refused_by_mjx(m) -> bool:
    """Whether MJX's ``put_model`` refuses ``m`` (the sweep then reports it ``unsupported``)."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            mjx.put_model(m)
    except NotImplementedError:
        return True
    except Exception:  # noqa: BLE001 - any other trouble is the sweep's to report
        return False
    return False


def piece_steps(m, batch: int, steps: int, budget_mib: float = PIECE_BUDGET_MIB) -> int:
    """Steps per piece of a streamed comparison: equal pieces that fit ``budget_mib``.

    A member-step records ``nq + nv + na + nsensordata + 4`` numbers; measured
    on the ant (batch 64, 625-step pieces), a piece holds about 24 float64
    copies of them at its peak (both C rollouts, MJX's records on the device
    and on the host, the next MJX piece already running, the error and bound
    arrays), so K steps of B members take about
    ``192 (nq + nv + na + nsensordata + 4) B K`` bytes.
    """
    width = 192 * (m.nq + m.nv + m.na + m.nsensordata + 4)
    most = max(MIN_PIECE_STEPS, int(budget_mib * 2**20 // (width * batch)))
    pieces = -(-steps // most)
    return -(-steps // pieces)


def group_size(m, batch: int, budget_mib: float = GROUP_BUDGET_MIB) -> int:
    """Members MJX steps at once: all of them, unless their working set exceeds ``budget_mib``
    (:func:`mjxdiff.engine.engines.member_bytes` per member)."""
    per_member = cost.member_bytes(m)
    return max(1, min(batch, int(budget_mib * 2**20 // per_member))) if per_member else batch


def member_groups(batch: int, most: int) -> list[np.ndarray]:
    """Member indices in equal groups of at most ``most``, in order; the last group is padded
    with repeats of the last member, so that every group runs the same compiled function."""
    n = -(-batch // most)
    size = -(-batch // n)
    idx = np.minimum(np.arange(n * size), batch - 1)
    return [idx[i * size:(i + 1) * size] for i in range(n)]


def layout(m, inputs: BatchedInputs, config: SweepConfig, under_test: Engine,
           plan_for: tuple[int, int] | None = None) -> tuple[list[np.ndarray], int]:
    """How the verdict steps ``inputs``: member groups (:func:`member_groups`, each a (group,)
    array of member indices) and steps per piece.

    ``plan_for`` (batch, steps): the sizes to plan for instead of the inputs' own, larger ones (a
    ``--quick`` run plans for the full sweep's): the one group of ``inputs`` is padded to the
    group those sizes would have and stepped in their pieces, so that both runs step one compiled
    piece (the quick run's horizon a run-time trip count of it) and a quick run after a full one,
    or before it, compiles nothing the other has not."""
    batch, steps = plan_for or (inputs.batch, inputs.steps)
    size = config.group_size or min(group_size(m, batch), under_test.batch_cap())
    groups = member_groups(inputs.batch, size)
    if plan_for is not None and len(groups) == 1:
        groups = [np.minimum(np.arange(size), inputs.batch - 1)]
    return groups, config.piece_steps or piece_steps(m, len(groups[0]), steps)


OUT_OF_MEMORY = re.compile(r"RESOURCE_EXHAUSTED|[Oo]ut of memory")


def out_of_memory(error: str, inputs: BatchedInputs, info: dict) -> str:
    """The one-line error of an XLA allocation MJX's stepping could not make, with the batch that fits."""
    found = re.search(r"allocating (\d+) bytes", error)
    group = info.get("plan", {}).get("group") or inputs.batch
    line = f"out of memory: MJX's stepping of {group} member(s) at once"
    if found:
        per = int(found.group(1)) / group
        limit = info.get("plan", {}).get("max_memory") or cost.available_bytes()
        fits = int(max(limit - cost.resident_bytes(), 0) // max(per, 1))
        line += f" asked XLA for {cost.human_bytes(int(found.group(1)))} (~{cost.human_bytes(per)} per member)"
        line += (f"; a batch of {fits} would fit (--batch {fits})" if fits else
                 "; not even one member fits: --drop-costly-pairs, or primitive collision geoms")
    return line + f" [{' '.join(error.split())[:160]}]"


def stopped(info: dict, clock: dict[str, float]) -> str:
    """The one-line error of a scenario stopped by its budget: how far it got, and the estimate."""
    done = clock.get("progress", "MJX's first piece of stepping had not come back")
    est = info.get("estimate", {}).get("line", "")
    return f"stopped at its budget of {info.get('plan', {}).get('budget'):g} s: {done}" + (f"; {est}" if est else "")


def _memory_maps() -> tuple[int, int]:
    """(memory maps this process holds, the kernel's limit); (0, 0) where /proc cannot tell."""
    try:
        with open("/proc/self/maps", "rb") as f:
            held = sum(1 for _ in f)
        with open("/proc/sys/vm/max_map_count") as f:
            return held, int(f.read())
    except (OSError, ValueError):
        return 0, 0


def release_compiled_if_crowded(budget: float = MAP_BUDGET) -> bool:
    """Drops every compiled function (JAX's in-memory caches and MJX's rollouts) once the process
    holds more than ``budget`` of the kernel's memory-map limit, and says whether it did.

    Each XLA CPU executable maps ~500-1,000 regions (measured: 981 -> 4,056 maps after four
    small scenarios, 1,082 after clearing); a sweep whose failing scenarios each compile their
    ablations reaches Linux's default limit of 65,530 within about fifteen of them, and LLVM
    then fails to allocate ('Cannot allocate memory') and the process segfaults (seen: an edited
    MJX failing every scenario). The persistent caches keep what is dropped a load away.
    """
    held, limit = _memory_maps()
    if not limit or held <= budget * limit:
        return False
    engines.clear_compiled()
    jax.clear_caches()
    import gc

    gc.collect()
    return True
