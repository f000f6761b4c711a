"""Edit to verdict: how long the default sweep takes after a one-line edit of one MJX function.

    python benchmarks/scripts/edit_to_verdict.py [CACHE_DIR] [-- SWEEP ARGS]

Runs the sweep three times in fresh processes on one cache directory: clean (cold unless the
cache is warm), with MJX's ``_sphere_sphere`` (collision_primitive.py) edited under its own file
name (the contact distance 0.1% short, as an in-place edit of site-packages would be), and clean
again. One JSON line each: wall seconds, rollouts traced and loaded, scenarios retraced,
verdict counts. Only the rollouts whose trace ran the edited function should be traced again.
"""

import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

EDIT = ("mujoco.mjx._src.collision_primitive", "dist = dist - (radius1 + radius2)",
        "dist = dist - (radius1 + radius2) * 1.001")

CLI = """
import importlib.abc, importlib.machinery, sys
MODULE, OLD, NEW = {edit!r}

class Loader(importlib.machinery.SourceFileLoader):
    def get_code(self, fullname):
        source = open(self.path).read()
        assert source.count(OLD) == 1, "the line to edit is not in this MJX"
        return compile(source.replace(OLD, NEW), self.path, "exec", dont_inherit=True)

class Finder(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name != MODULE:
            return None
        spec = importlib.machinery.PathFinder.find_spec(name, path)
        spec.loader = Loader(name, spec.origin)
        return spec

if sys.argv[1] == "edited":
    sys.meta_path.insert(0, Finder())
from mjxdiff.cli import main
sys.exit(main(sys.argv[2:]))
"""


def run(which: str, cache: Path, out: Path, extra: list[str]) -> dict:
    t = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", CLI.format(edit=EDIT), which, "sweep", "--cache-dir", str(cache),
                           "--out", str(out), "--diagnose", "none", *extra], capture_output=True, text=True)
    wall = time.perf_counter() - t
    report = json.loads((out / "report.json").read_text())
    retraced = [s["name"] for s in report["scenarios"] if s["info"].get("mjx_compiles")]
    return dict(run=which, rc=proc.returncode, wall_s=round(wall, 1), traced=report["summary"]["mjx_compiles"],
                loaded=report["summary"]["mjx_loaded"], retraced=retraced,
                failed=[s["name"] for s in report["scenarios"] if s["status"] == "fail"],
                summary={k: report["summary"][k] for k in ("pass", "fail", "unsupported", "error")})


def main() -> None:
    args = sys.argv[1:]
    extra = args[args.index("--") + 1:] if "--" in args else []
    args = args[:args.index("--")] if "--" in args else args
    with tempfile.TemporaryDirectory() as tmp:
        cache = Path(args[0]) if args else Path(tmp) / "cache"
        for i, which in enumerate(("clean", "edited", "clean")):
            print(json.dumps(run(which, cache, Path(tmp) / f"out{i}", extra)), flush=True)


if __name__ == "__main__":
    main()
