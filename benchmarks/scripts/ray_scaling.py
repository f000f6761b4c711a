"""Ray against local on one machine, and the scaling model checked at 1 and 2 nodes.

    python benchmarks/scripts/ray_scaling.py [SCENARIO ...] [--quick]

1. Ray's fixed cost: ``ray.init`` + ``ray.shutdown`` of a local instance, and a Ray sweep of no
   unit's worth (one trivial task), in seconds.
2. The same sweep three ways, each from a warm compile cache (a Ray run first, unmeasured: a
   task's single XLA device keys its rollouts apart from the local sweep's): local (this
   machine's executor), Ray on one node (a ``ray.cluster_utils.Cluster`` head of 1 CPU) and Ray
   on two nodes (1 CPU each); wall seconds of each, and Ray's per-unit cost: (Ray 1-node wall - fixed - sum of the
   units' worker seconds) / units.
3. The model (:mod:`mjxdiff.runner.scaling`) fed the 1-node run's journal, the fixed and per-unit costs,
   predicting the 1- and 2-node walls; printed beside the measured ones, then 1-64 nodes.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
import time
import warnings
from pathlib import Path

warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called")


def _sweep(out: Path, scenarios, quick: bool, **changes) -> float:
    from mjxdiff.runner import pipeline

    t0 = time.perf_counter()
    run = pipeline.run(pipeline.SweepOptions(scenarios=tuple(scenarios), quick=quick, out=str(out), no_history=True,
                                             progress=False, **changes))
    wall = time.perf_counter() - t0
    statuses = sorted({r.status for r in run.results})
    print(f"  {out.name}: {wall:.1f} s, statuses {statuses}", flush=True)
    return wall


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scenarios", nargs="*", default=["pendulum", "cartpole", "actuators", "tendons", "ball_joint",
                                                           "double_pendulum", "imu_sensors", "lidar"])
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args()
    import ray
    from ray.cluster_utils import Cluster

    from mjxdiff.runner import journal, scaling

    from ray_overhead import ray_fixed_cost  # this script's directory is on sys.path

    quiet = dict(include_dashboard=False, log_to_driver=False, logging_level=logging.ERROR)
    fixed = ray_fixed_cost()

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        _sweep(tmp / "warmup", args.scenarios, args.quick, isolate=False)  # the compile cache, warm
        local = _sweep(tmp / "local", args.scenarios, args.quick)
        walls = {}
        # a Ray task runs on K=1 XLA device, the local sweep on one per core, and a traced rollout's
        # key includes the device count: the first Ray run is cold whatever the local cache holds
        for nodes in (0, 1, 2):  # 0: the warm-up, one node, not measured
            cluster = Cluster(initialize_head=True, head_node_args=dict(num_cpus=1, object_store_memory=100 << 20))
            for _ in range(max(nodes, 1) - 1):
                cluster.add_node(num_cpus=1, object_store_memory=100 << 20)
            cluster.wait_for_nodes()
            ray.init(address=cluster.address, **quiet)
            try:
                walls[nodes] = _sweep(tmp / f"ray{nodes}", args.scenarios, args.quick, executor="ray")
            finally:
                ray.shutdown()
                cluster.shutdown()
        units = [(r["unit"], float(r["seconds"])) for r in journal.read(tmp / "ray1" / journal.FILE).units]
        work = sum(s for _, s in units)
        per_task = max(0.0, (walls[1] - fixed - work) / len(units))
        print(f"local {local:.1f} s; Ray 1 node {walls[1]:.1f} s, 2 nodes {walls[2]:.1f} s; units' worker seconds "
              f"{work:.1f}; Ray per unit {per_task:.2f} s", flush=True)
        predicted = scaling.predict(units, nodes=(1, 2), slots=1, fixed=fixed, per_task=per_task)
        for p in predicted:
            print(f"  {p.nodes} node(s): predicted {p.wall:.1f} s, measured {walls[p.nodes]:.1f} s "
                  f"({(p.wall - walls[p.nodes]) / walls[p.nodes]:+.0%})")
        table = scaling.predict(units, slots=1, fixed=fixed, per_task=per_task)
        print(scaling.format_table(table))
        print(json.dumps(dict(fixed=fixed, per_task=per_task, local=local, ray=walls, work=work,
                              predicted={p.nodes: p.wall for p in table})))
    return 0


if __name__ == "__main__":
    sys.exit(main())
