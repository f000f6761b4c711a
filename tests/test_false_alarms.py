"""Unmodified MJX never makes the default sweep exit 1, on seeds nobody tuned against.

The seeds are drawn from the date (a new set each day, far from the seeds 0-60 the bundled
scenarios' margins were measured on), swept with the ``--quick`` settings; a failure names the
seed and the command that reproduces it."""

import datetime
import json

import pytest

from mjxdiff.cli import main

#: Seeds swept per run; the first costs the compiles, the others only stepping.
SEEDS_PER_RUN = 2


def seeds_of(day: datetime.date) -> list[int]:
    """``SEEDS_PER_RUN`` seeds for ``day``: 1000 + SEEDS_PER_RUN x (days since 2026-01-01) onwards, so no two
    days share one and none falls in 0-999."""
    first = 1000 + SEEDS_PER_RUN * (day - datetime.date(2026, 1, 1)).days
    return list(range(first, first + SEEDS_PER_RUN))


def test_the_seeds_of_a_day_are_its_own_and_outside_the_tuned_range():
    today, tomorrow = datetime.date(2026, 11, 27), datetime.date(2026, 11, 28)
    assert min(seeds_of(today)) >= 1000 and not set(seeds_of(today)) & set(seeds_of(tomorrow))


@pytest.mark.slow
def test_unmodified_mjx_passes_the_quick_default_sweep_on_seeds_drawn_from_the_date(tmp_path):
    for seed in seeds_of(datetime.date.today()):
        out = tmp_path / str(seed)
        code = main(["sweep", "--quick", "--seed", str(seed), "--no-history", "--no-progress", "--out", str(out)])
        doc = json.loads((out / "report.json").read_text())
        bad = [f"{s['name']}: {s['status']}: {s['message'][:300]}" for s in doc["scenarios"]
               if s["status"] not in ("pass", "unsupported")]
        assert code == 0 and not bad, (f"unmodified MJX, seed {seed}: exit {code}; reproduce with "
                                       f"`python -m mjxdiff sweep --quick --seed {seed}`:\n" + "\n".join(bad))
