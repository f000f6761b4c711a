"""Sweeps public MJX-ready robots (fetched by ``fetch_robots.py``) one by one with default
settings, as a user would, and prints one JSON line per robot: the verdict, the as-configured gap
and its cause, the converged twin's and the one-step check's verdicts and ratios, weak fields,
and the wall time of the ``python -m mjxdiff sweep`` process.

    python benchmarks/scripts/sweep_robots.py [DEST] [--robots anymal_c,h1] [-- SWEEP ARGS]

``DEST`` is fetch_robots.py's destination (its ``robots.json`` lists the scenes); reports go to
``DEST/sweeps/<robot>/``.
"""

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path


def row(name: str, kind: str, doc: dict, wall: float, rc: int) -> dict:
    sc = doc["scenarios"][0]
    info = sc.get("info") or {}
    one, twin, floor = info.get("onestep") or {}, info.get("twin") or {}, info.get("solver_floor") or {}
    fields = sc.get("fields") or {}
    return dict(
        robot=name, kind=kind, rc=rc, wall_s=round(wall, 1), status=sc["status"],
        cause=(sc.get("diagnosis") or {}).get("cause", {}).get("cause"),
        known=(sc.get("known") or {}).get("id"),
        gap={k: floor["gap"][k] for k in ("field", "object", "error", "steps")} if floor.get("gap") else None,
        worst={k: dict(max_error=v.get("max_error"), ratio=v.get("ratio"), bound_scale=v.get("bound_scale"))
               for k, v in fields.items() if k in ("qpos", "qvel")},
        weak=sc.get("weak"),
        onestep=dict(status=one.get("status"), field=one.get("field"), ratio=one.get("ratio"),
                     converged=(one.get("solver") or {}).get("converged"),
                     truncation=(one.get("solver") or {}).get("ratio"),
                     as_configured=(one.get("as_configured") or {}).get("ratio"),
                     weak=one.get("weak")) if one else None,
        twin=dict(status=twin.get("status"), worst=twin.get("worst"), weak=twin.get("weak")) if twin else None,
        message=sc["message"][:400], batch=info.get("batch"), steps=info.get("steps"),
        error_kind=sc.get("error_kind") or None, estimate=(info.get("estimate") or {}).get("line"),
        estimate_compile_s=(info.get("estimate") or {}).get("compile_s"),
        measured_compile_s=(info.get("seconds") or {}).get("compile"),
        plan=(info.get("plan") or {}).get("changed"), alarms=info.get("alarms"),
        peak_rss_gb=round((info.get("guard") or {}).get("peak_rss_bytes", 0) / 2**30, 2))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dest", nargs="?", default=str(Path.home() / ".cache" / "mjxdiff" / "robots"))
    parser.add_argument("--robots", default="")
    parser.add_argument("--timeout", type=float, default=1200, help="seconds per robot before it is killed")
    parser.add_argument("sweep_args", nargs="*")
    args, extra = parser.parse_known_args()
    args.sweep_args += [x for x in extra if x != "--"]
    dest = Path(args.dest)
    wanted = set(filter(None, args.robots.split(",")))
    for robot in json.loads((dest / "robots.json").read_text()):
        if robot.get("status") != "ok" or (wanted and robot["name"] not in wanted):
            continue
        out = dest / "sweeps" / robot["name"]
        (out / "report.json").unlink(missing_ok=True)
        t = time.perf_counter()
        try:
            proc = subprocess.run([sys.executable, "-m", "mjxdiff", "sweep", robot["scene"], "--no-history",
                                   "--out", str(out), *args.sweep_args], capture_output=True, text=True,
                                  timeout=args.timeout)
        except subprocess.TimeoutExpired as e:
            proc = subprocess.CompletedProcess(e.cmd, -9, "", f"no verdict after {args.timeout} s")
        wall = time.perf_counter() - t
        try:
            doc = json.loads((out / "report.json").read_text())
            print(json.dumps(row(robot["name"], robot["kind"], doc, wall, proc.returncode)), flush=True)
        except (OSError, ValueError, IndexError, KeyError) as e:
            print(json.dumps(dict(robot=robot["name"], rc=proc.returncode, wall_s=round(wall, 1),
                                  error=f"{type(e).__name__}: {e}", stderr=proc.stderr[-400:])), flush=True)


if __name__ == "__main__":
    main()
