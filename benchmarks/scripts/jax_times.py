"""Where the test suite's time goes, per file and per test: wall seconds against JAX's own
tracing, lowering and XLA compile seconds (and what JAX's persistent cache saved).

Run the suite with ``MJXDIFF_TEST_JAX_TIMES=DIR`` (tests/conftest.py records per test), then::

    python benchmarks/scripts/jax_times.py DIR [--tests 40]

A test whose compile is most of its wall time is one to share compiled work with another, or
to compile for compile time (``mjxdiff.compat.jit_for_few_calls``); one whose trace is most of
it, one to serve from an artifact (``mjxdiff.engine.export_cache``)."""

import argparse
import json
from collections import defaultdict
from pathlib import Path

COLUMNS = ("wall", "trace", "lower", "compile", "cache_saved")


def load(directory: Path) -> dict[str, dict[str, float]]:
    """Per test id, its seconds (:data:`COLUMNS`), summed over the processes' files."""
    rows: dict[str, dict[str, float]] = defaultdict(lambda: defaultdict(float))
    for path in sorted(directory.glob("jax-times.*.json")):
        for test, row in json.loads(path.read_text()).items():
            for k, v in row.items():
                rows[test][k] += v
    return rows


def table(rows: dict[str, dict[str, float]], title: str, limit: int | None = None) -> str:
    ordered = sorted(rows.items(), key=lambda kv: -kv[1].get("wall", 0.0))[:limit]
    lines = [f"| {title} | " + " | ".join(COLUMNS) + " |", "|---" * (len(COLUMNS) + 1) + "|"]
    lines += [f"| {name} | " + " | ".join(f"{row.get(c, 0.0):.1f}" for c in COLUMNS) + " |" for name, row in ordered]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("directory", type=Path)
    parser.add_argument("--tests", type=int, default=40, help="the slowest tests to list (default 40)")
    args = parser.parse_args()
    rows = load(args.directory)
    files: dict[str, dict[str, float]] = defaultdict(lambda: defaultdict(float))
    for test, row in rows.items():
        for k, v in row.items():
            files[test.split("::")[0]][k] += v
    total = {c: sum(r.get(c, 0.0) for r in rows.values()) for c in COLUMNS}
    print("total seconds: " + ", ".join(f"{c} {v:.0f}" for c, v in total.items()) + "\n")
    print(table(files, "file") + "\n")
    print(table(rows, "test", args.tests))


if __name__ == "__main__":
    main()
