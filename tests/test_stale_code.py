"""A verdict names the code it ran: an MJX edited under its installed file name is traced, never
served from an artifact of other code; unchanged code reuses its artifacts and XLA's cache."""

import os
import json
import subprocess
import sys
from pathlib import Path


#: Runs the CLI, with MJX's forward.py replaced by an edited copy compiled under its own file
#: name (as an in-place edit of site-packages, a patched wheel or a nightly build would be).
EDITED_CLI = """
import importlib.abc, importlib.machinery, sys
OLD = "d = d.replace(qvel=d.qvel + qacc * m.opt.timestep)"
NEW = "d = d.replace(qvel=d.qvel + qacc * m.opt.timestep * 1.001)"

class Loader(importlib.machinery.SourceFileLoader):
    def get_code(self, fullname):
        source = open(self.path).read()
        assert source.count(OLD) == 1, "the line to edit is not in this MJX"
        return compile(source.replace(OLD, NEW), self.path, "exec", dont_inherit=True)

class Finder(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name != "mujoco.mjx._src.forward":
            return None
        spec = importlib.machinery.PathFinder.find_spec(name, path)
        spec.loader = Loader(name, spec.origin)
        return spec

if sys.argv[1] == "edited":
    sys.meta_path.insert(0, Finder())
from mjxdiff.cli import main
sys.exit(main(sys.argv[2:]))
"""


def _sweep(tmp_path, which: str, cache) -> dict:
    out = tmp_path / which
    args = ["sweep", "pendulum", "--quick", "--diagnose", "none", "--out", str(out), "--cache-dir", str(cache)]
    proc = subprocess.run([sys.executable, "-c", EDITED_CLI, which.rstrip("0123456789"), *args],
                          capture_output=True, text=True, timeout=600)
    assert "Traceback" not in proc.stderr, proc.stderr[-3000:]
    report = json.loads((out / "report.json").read_text())
    report["exit"] = proc.returncode
    return report


def test_an_edited_mjx_is_traced_and_fails_although_artifacts_of_the_clean_one_exist(tmp_path, repo_root):
    cache = Path(os.environ["MJXDIFF_CACHE"])  # the run's: the clean rollout is usually warm already
    clean = _sweep(tmp_path, "clean", cache)
    assert clean["exit"] == 0 and clean["summary"]["pass"] == 1
    assert list((cache / "mjxdiff-exports").rglob("*.jaxexport")), "the clean run left its artifact"
    edited = _sweep(tmp_path, "edited", cache)
    [scenario] = edited["scenarios"]
    assert edited["exit"] == 1 and scenario["status"] == "fail", scenario["message"]
    assert scenario["first_divergence"]["field"] in ("qvel", "qpos")
    assert scenario["info"]["mjx_compiles"] >= 1 or scenario["info"]["mjx_loaded"] >= 1
    assert edited["code"]["mjx"] != clean["code"]["mjx"], "the report names the code that was tested"
    again = _sweep(tmp_path, "clean2", cache)
    assert again["exit"] == 0 and again["code"]["mjx"] == clean["code"]["mjx"]
    info = again["scenarios"][0]["info"]
    assert info["mjx_compiles"] == 0 and info["mjx_loaded"] >= 1, "the clean code's artifact is loaded again"


EXPORT_TWICE = """
import hashlib, pickle, shutil, sys
import jax
from mjxdiff.engine import engines, export_cache
from mjxdiff.input.inputs import make_inputs
from mjxdiff.input.scenario import load_model, load_scenario
engines.configure_jax("float64", sys.argv[1], devices=1)
events = {"hits": 0, "misses": 0}
jax.monitoring.register_event_listener(
    lambda e, **_: events.__setitem__(e.rsplit("_", 1)[-1], events.get(e.rsplit("_", 1)[-1], 0) + 1))
shutil.rmtree(export_cache.export_dir(), ignore_errors=True)  # the artifact is made anew in every process
scenario = load_scenario("pendulum")
inputs = make_inputs(scenario, load_model(scenario), seed=0, batch=2, steps=20)
engines.MJXEngine().rollout(inputs)
[path] = export_cache.export_dir().rglob("*.jaxexport")
blob = pickle.loads(path.read_bytes())[1]
print(hashlib.sha256(blob).hexdigest(), events["hits"], events["misses"])
"""


def test_a_regenerated_artifact_is_the_same_module_and_hits_xlas_cache(tmp_path):
    """jax.export of unchanged code gives the same StableHLO in every process, so remaking an
    artifact (evicted, or after an edit that was undone) costs a trace but no XLA compile."""
    runs = []
    for _ in range(2):
        proc = subprocess.run([sys.executable, "-c", EXPORT_TWICE, str(tmp_path / "cache")],
                              capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, proc.stderr[-3000:]
        digest, hits, misses = proc.stdout.split()
        runs.append((digest, int(hits), int(misses)))
    (first, _, cold_misses), (second, hits, misses) = runs
    assert first == second, "the exported module differs between processes: XLA's cache would miss"
    assert cold_misses > 0 and misses == 0 and hits > 0, runs
