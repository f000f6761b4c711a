"""The scaling model: LPT list scheduling over a journal's per-unit seconds."""

import json

import pytest

from mjxdiff.runner import journal, scaling
from mjxdiff.cli import main


def test_makespan_is_longest_first_list_scheduling():
    assert scaling.makespan([3, 3, 2, 2, 2], 2) == 7  # LPT: 3 | 3, then 2 -> 5 | 3 -> 5 | 5 -> 7 | 5
    assert scaling.makespan([5, 4, 3, 3, 3], 2) == 10  # 5 | 4, then 3 -> 5 | 7, 3 -> 8 | 7, 3 -> 8 | 10
    assert scaling.makespan([1.0] * 8, 4) == 2 and scaling.makespan([7, 1], 64) == 7
    with pytest.raises(ValueError):
        scaling.makespan([1], 0)


def test_the_prediction_levels_off_at_the_longest_unit():
    units = [("ant", 40.0)] + [(f"s{i}", 5.0) for i in range(20)]
    got = scaling.predict(units, nodes=(1, 2, 4, 64), slots=2, fixed=6.0, per_task=0.5)
    assert [p.nodes for p in got] == [1, 2, 4, 64] and got[0].speedup == 1.0
    assert all(a.wall >= b.wall for a, b in zip(got, got[1:]))
    assert got[-1].wall == got[-1].bound == 6.0 + 40.0 + 0.5 and got[-1].longest == "ant"
    assert got[0].wall == 6.0 + scaling.makespan([40.5] + [5.5] * 20, 2)


def test_scale_reads_journals(tmp_path, capsys):
    with journal.Journal(tmp_path / journal.FILE) as j:
        for i, s in enumerate((10.0, 20.0, 30.0)):
            j.unit(f"k{i}", {}, i, dict(name=f"u{i}", status="pass", info={}), seconds=s)
    assert main(["scale", str(tmp_path), "--nodes", "1", "3", "--cpus-per-node", "1", "--format", "json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [(r["nodes"], r["wall"], r["longest"]) for r in rows] == [(1, 60.0, "u2"), (3, 30.0, "u2")]
    assert main(["scale", str(tmp_path / "empty")]) == 2
