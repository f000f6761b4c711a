"""The sweep's plumbing: C streamed from a background thread, an engine crash contained to its scenario."""

import threading
import time

import pytest

from mjxdiff.engines import CEngine
from mjxdiff.inputs import make_inputs
from mjxdiff.scenario import load_model, load_scenario
from mjxdiff.sweep import SweepConfig, _ahead, run_inputs


def test_ahead_yields_every_item_in_order():
    assert list(_ahead(iter(range(7)), depth=2)) == list(range(7))
    assert list(_ahead(iter([]))) == []


def test_ahead_raises_the_producers_error_after_the_items_before_it():
    def items():
        yield 1
        yield 2
        raise RuntimeError("C crashed")

    got = []
    with pytest.raises(RuntimeError, match="C crashed"):
        for x in _ahead(items()):
            got.append(x)
    assert got == [1, 2]


def test_closing_ahead_stops_its_thread():
    produced = []

    def items():
        for i in range(1000):
            produced.append(i)
            yield i

    before = threading.active_count()
    stream = _ahead(items(), depth=1)
    assert next(stream) == 0
    stream.close()
    time.sleep(0.1)
    assert threading.active_count() == before
    assert len(produced) <= 3, "the producer ran on after the consumer stopped"


def test_a_c_crash_mid_stream_is_that_scenarios_engine_error(monkeypatch):
    scenario = load_scenario("pendulum")
    m = load_model(scenario)
    inputs = make_inputs(scenario, m, seed=0, batch=2, steps=100)
    real = CEngine.stream

    def crashing(self, inputs, chunk):
        pieces = real(self, inputs, chunk)
        yield next(pieces)  # a real first piece, then the crash
        raise RuntimeError("mj_step: simulated crash")

    monkeypatch.setattr(CEngine, "stream", crashing)
    result = run_inputs("pendulum", m, inputs, scenario.tolerance, SweepConfig(diagnose="none", piece_steps=50))
    assert (result.status, result.error_kind) == ("error", "engine")
    assert result.message == "MuJoCo C failed: RuntimeError: mj_step: simulated crash"
