"""The drill-down's ``mjx.forward`` on the sensing scenario (the bundled model with the most
stages to compare): traced and compiled afresh, against loaded from its artifact by a later run
(:meth:`mjxdiff.engine.engines.MJXEngine.forward` binds it through :func:`mjxdiff.engine.export_cache.bind`).

Run: ``python -m pytest benchmarks/test_drill_down.py --benchmark-only``. Each round forgets the
process's compiled functions, as a new run would; XLA's persistent cache stays as the user has it
(a traced round still traces and lowers; its XLA compile may be a cache hit).
"""

import mujoco
import pytest

from mjxdiff.engine import engines, export_cache
from mjxdiff.compare.diagnose import STAGES
from mjxdiff.output.report import versions
from mjxdiff.input.scenario import load_model, load_scenario

FIELDS = tuple(f for _, fs in STAGES for f in fs if f not in ("qM", "contact"))


@pytest.fixture(scope="module")
def state():
    m = load_model(load_scenario("sensing"))
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    return m, d


@pytest.mark.parametrize("artifact", ["traced", "loaded"])
def test_drill_down_forward(benchmark, state, artifact, tmp_path, monkeypatch):
    m, d = state
    directory = tmp_path if artifact == "loaded" else None
    monkeypatch.setattr(export_cache, "export_dir", lambda: directory)

    def forward():
        engines.clear_compiled()
        return engines.MJXEngine().forward(m, d, FIELDS)

    if artifact == "loaded":
        forward()  # saved once: every round loads it
    benchmark.pedantic(forward, rounds=3, iterations=1)
    benchmark.extra_info.update(versions())
    benchmark.extra_info.update(function="mjx.forward", scenario="sensing", artifact=artifact)
