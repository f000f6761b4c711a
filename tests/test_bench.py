"""``mjxdiff bench``: real timings of both engines, their ratio, and advice derived from them."""

import json

import pytest

from mjxdiff.output import report
from mjxdiff.tools.bench import measure, recommendations
from mjxdiff.cli import main


def test_bench_measures_both_engines(tmp_path, capsys):
    code = main(["bench", "pendulum", "--batch", "2", "4", "--steps", "20", "--repeats", "1",
                 "--out", str(tmp_path), "--format", "json"])
    assert code == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc == json.loads((tmp_path / "bench.json").read_text())
    assert report.validate(doc, "bench") == []
    assert doc["versions"]["mujoco"] and doc["machine"]["jax_cpu_devices"] >= 1
    (r,) = doc["scenarios"]
    assert [p["batch"] for p in r["curve"]] == [2, 4]
    for p in r["curve"]:
        assert p["c_steps_per_s"] > 0 and p["mjx_steps_per_s"] > 0
        assert p["mjx_over_c"] == pytest.approx(p["mjx_steps_per_s"] / p["c_steps_per_s"])
        assert 0 < p["c_cpu"] <= 1.05 and 0 < p["mjx_cpu"] <= 1.05
        assert p["first_call"] in ("compiled", "loaded", "warm")
    assert r["best"] in r["curve"]
    assert r["tester"]["engines_s"] > 0 and r["tester"]["verify_s"] > 0
    assert r["tester"]["engines_cpu_s"] > 0 and r["tester"]["cpu_ratio"] > 0
    assert r["tester"]["always_ratio"] > 0
    assert (r["tester"]["noise_floor_members"], r["tester"]["members"]) == (0, r["best"]["batch"]), "calm: no rerun"
    assert any("bottleneck" in text for text in r["recommendations"])


def test_bench_unknown_scenario_exits_2(capsys):
    assert main(["bench", "no_such_scenario"]) == 2
    assert "no_such_scenario" in capsys.readouterr().err


def test_measure_sees_memory_and_time():
    import time

    import numpy as np

    def hold():  # 64 MiB, held while the sampler (every 5 ms) looks: a busy machine may not schedule it sooner
        x = np.ones(64 * 2**20 // 8)
        time.sleep(0.2)
        return x.sum()

    out, m = measure(hold)
    assert out == 64 * 2**20 // 8
    assert m.seconds > 0 and m.peak_mib > 30


def _result(mjx, c, compile_s=0.1, speedup=2.0, ratio=0.9):
    curve = [dict(batch=b, steps=100, mjx_steps_per_s=s, c_steps_per_s=c, mjx_over_c=s / c, compile_s=compile_s)
             for b, s in mjx]
    best = max(curve, key=lambda p: p["mjx_steps_per_s"])
    return dict(curve=curve, best=best, split=dict(devices=2, speedup=speedup),
                tester=dict(throughput_ratio=ratio, cpu_ratio=ratio))


def test_recommendations_follow_the_numbers():
    text = "\n".join(recommendations(_result([(8, 1000), (32, 4000), (128, 2000)], c=100_000)))
    assert "best batch size for MJX here: 32" in text
    assert "split big sweeps into batches of 32" in text
    assert "bottleneck: MJX (25.0x slower than C" in text
    assert "2.00x one device (keep it)" in text
    slow_split = "\n".join(recommendations(_result([(8, 1000)], c=100_000, compile_s=60, speedup=0.8, ratio=0.5)))
    assert "does not pay" in slow_split and "persistent compilation cache" in slow_split
    assert "noticeable cost" in slow_split
    loaded = _result([(8, 1000)], c=100_000, compile_s=60)
    loaded["best"]["first_call"] = "loaded"
    assert "persistent compilation cache" not in "\n".join(recommendations(loaded)), "loading is not compiling"
