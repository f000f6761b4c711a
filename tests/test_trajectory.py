"""The engine interface: C, MJX and MuJoCo Warp through the protocol alone, on one comparison path."""

import dataclasses
import sys

import numpy as np
import pytest

from mjxdiff.input.inputs import make_inputs
from mjxdiff.input.precision import PRECISIONS
from mjxdiff.input.scenario import Tolerances, load_model, load_scenario
from mjxdiff.engine.trajectory import Engine, Trajectory, concat
from mjxdiff.compare.verdict import judge

#: Every member the protocol declares (attributes and methods).
_MEMBERS = ("name", "capabilities", "precision", "rollout", "stream", "resync", "batch_cap", "split", "compile_ahead")


def _engines() -> list[Engine]:
    from mjxdiff.engine.engines import CEngine, MJXEngine
    from mjxdiff.engine.mjwarp import MJWarpEngine

    return [CEngine(), MJXEngine(), MJWarpEngine()]


def _compare(reference: Engine, under_test: Engine, inputs, m) -> dict:
    """The shared path: whole rollouts judged, pieces joined, one-step resync judged; nothing
    but the protocol's members used."""
    traj_ref = reference.rollout(inputs)
    traj = under_test.rollout(inputs)
    pieces = concat(list(under_test.stream(inputs, 7)))
    local = under_test.resync(inputs, traj_ref, every=1)
    tol = Tolerances().for_precision(under_test.precision)
    under_test.compile_ahead(inputs, 7)
    return dict(whole=judge("pendulum", m, traj_ref, traj, tol), local=judge("pendulum", m, traj_ref, local, tol),
                pieces=pieces, traj=traj, cap=under_test.batch_cap(), split=under_test.split(inputs.batch))


def test_every_engine_runs_the_comparison_through_the_protocol_alone():
    """C against C, MJX and MuJoCo Warp on the pendulum: each declares every member of the
    protocol, passes, joins its pieces into its rollout bit for bit, and restarted from C every
    step stays within C's own rounding."""
    scenario = load_scenario("pendulum")
    m = load_model(scenario)
    inputs = make_inputs(scenario, m, seed=0, batch=3, steps=20)
    c = _engines()[0]
    for engine in _engines():
        assert all(hasattr(engine, k) for k in _MEMBERS), type(engine).__name__
        assert engine.precision in PRECISIONS and isinstance(engine.capabilities, frozenset)
        out = _compare(c, engine, inputs, m)
        assert out["whole"].status == "pass", (engine.name, out["whole"].message)
        assert out["local"].status == "pass", (engine.name, out["local"].message)
        for f in dataclasses.fields(Trajectory):
            assert np.array_equal(getattr(out["pieces"], f.name), getattr(out["traj"], f.name)), (engine.name, f.name)
        assert out["cap"] >= 1 and 1 <= out["split"] <= inputs.batch


def test_c_restarted_from_its_own_states_is_its_own_rollout():
    """C's resync from C's own trajectory, at any interval, gives that trajectory back (time
    included): the restart loses nothing a sweep compares."""
    from mjxdiff.engine.engines import CEngine

    scenario = load_scenario("cartpole")
    m = load_model(scenario)
    inputs = make_inputs(scenario, m, seed=1, batch=2, steps=25)
    c = CEngine()
    traj = c.rollout(inputs)
    for every in (1, 4, 25):
        again = c.resync(inputs, traj, every)
        for f in ("qpos", "qvel", "act", "sensordata", "ncon", "diverged_at"):
            assert np.array_equal(getattr(again, f), getattr(traj, f)), (every, f)
        assert np.allclose(again.time, traj.time, rtol=0, atol=1e-12)


def test_the_verdict_and_the_noise_floor_import_no_engine():
    """verdict, noise and trajectory read trajectories without importing MuJoCo's MJX."""
    import subprocess

    code = ("import sys, mjxdiff.compare.verdict, mjxdiff.compare.noise, mjxdiff.engine.trajectory; "
            "print(sorted(m for m in sys.modules if m in "
            "('mujoco.mjx', 'mjxdiff.engine.engines', 'mjxdiff.engine.mjwarp')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


@pytest.mark.parametrize("impl", ["mjx", "warp"])
def test_the_sweep_asks_the_engine_what_it_offers(impl):
    """The cost model and the host-interface check follow the engine's capabilities, not its name."""
    from mjxdiff.runner.sweep import SweepConfig, capable, engine_class

    config = SweepConfig(impl=impl)
    assert capable(config, "estimate") == capable(config, "transfer") == (impl == "mjx")
    assert engine_class(impl).name == impl


def test_the_import_graph_has_no_cycle():
    """No module of mjxdiff imports, at any depth and at any place in its code, one that imports
    it back (the pipeline's data flows one way)."""
    import ast
    from pathlib import Path

    root = Path(__file__).parent.parent / "mjxdiff"
    files = {".".join(p.relative_to(root).with_suffix("").parts): p for p in root.rglob("*.py")
             if p.stem not in ("__init__", "__main__")}
    mods = set(files)
    graph = {}
    for m, path in files.items():
        deps = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "mjxdiff":
                base = node.module.removeprefix("mjxdiff").lstrip(".")
                deps |= {f"{base}.{a.name}".lstrip(".") if f"{base}.{a.name}".lstrip(".") in mods else base
                         for a in node.names}
            elif isinstance(node, ast.Import):
                deps |= {a.name.removeprefix("mjxdiff.") for a in node.names if a.name.startswith("mjxdiff.")}
        graph[m] = (deps & mods) - {m}
    assert len(mods) > 40 and graph["runner.sweep"] >= {"engine.engines", "compare.verdict"}, graph

    def reaches_itself(start):
        seen, todo = set(), list(graph[start])
        while todo:
            m = todo.pop()
            if m == start:
                return True
            if m not in seen:
                seen.add(m)
                todo += graph[m]
        return False
    cycles = sorted(m for m in mods if reaches_itself(m))
    assert cycles == [], cycles
