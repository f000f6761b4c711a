"""How a sweep would scale over more nodes: a list-scheduling model over the per-unit seconds a
journal measured (:mod:`mjxdiff.runner.journal`).

The model: ``nodes x slots`` identical workers (``slots`` = a node's CPUs // the CPUs per unit);
units start longest first, each on the worker that frees first (LPT list scheduling, within
4/3 of the best schedule); every unit costs ``per_task`` seconds more (submission, shipping the
model, the result back); the whole run ``fixed`` seconds more (starting or joining Ray, workers
importing JAX and MuJoCo). Predicted wall time::

    wall(nodes) = fixed + makespan(LPT(units + per_task, nodes * slots))

No schedule beats the longest unit: ``wall >= fixed + max(unit) + per_task``, which is where the
speed-up levels off; :func:`predict` names that unit.
"""

from __future__ import annotations

import dataclasses
import heapq
from typing import Sequence

__all__ = ["NODES", "Prediction", "makespan", "predict", "format_table"]

#: Node counts :func:`predict` reports by default.
NODES = (1, 2, 4, 8, 16, 32, 64)


def makespan(seconds: Sequence[float], workers: int) -> float:
    """Seconds until the last of ``seconds`` finishes on ``workers`` workers, longest first,
    each on the worker that frees first."""
    if workers < 1:
        raise ValueError(f"workers must be positive, got {workers}")
    free = [0.0] * min(workers, max(len(seconds), 1))
    for s in sorted(seconds, reverse=True):
        heapq.heappush(free, heapq.heappop(free) + s)
    return max(free)


@dataclasses.dataclass(frozen=True)
class Prediction:
    """The predicted wall time (s) of a sweep on ``nodes`` nodes, its ``speedup`` over one node,
    and the lower bound every schedule has: ``fixed`` + the ``longest`` unit (its name)."""

    nodes: int
    wall: float
    speedup: float
    bound: float
    longest: str


def predict(units: Sequence[tuple[str, float]], nodes: Sequence[int] = NODES, slots: int = 1,
            fixed: float = 0.0, per_task: float = 0.0) -> list[Prediction]:
    """Wall time of the sweep whose units took ``units`` (name, seconds) on each of ``nodes``.

    Args:
      slots: units a node runs at once (its CPUs // ``--cpus-per-scenario``).
      fixed: seconds the run costs once (Ray's start, workers' imports).
      per_task: seconds each unit costs on top of its own.
    """
    if not units:
        raise ValueError("no units to schedule: the journal holds no finished unit")
    seconds = [s + per_task for _, s in units]
    name, longest = max(units, key=lambda u: u[1])
    one = fixed + makespan(seconds, slots)
    out = []
    for n in nodes:
        wall = fixed + makespan(seconds, n * slots)
        out.append(Prediction(n, wall, one / wall, fixed + longest + per_task, name))
    return out


def format_table(predictions: Sequence[Prediction]) -> str:
    """The predictions as a text table, one row per node count."""
    rows = ["nodes  predicted wall (s)  speed-up  bound (s)"]
    rows += [f"{p.nodes:5d}  {p.wall:18.1f}  {p.speedup:8.2f}  {p.bound:9.1f}" for p in predictions]
    rows.append(f"bound: the longest unit, {predictions[0].longest}, plus the fixed and per-task costs")
    return "\n".join(rows)
