"""Run history: every sweep appends one row per scenario x field to a Parquet dataset.

Layout: ``DIR/run-<UTC time>-<run id>.parquet``, one file per run, written by DuckDB to a
hidden temporary name in ``DIR`` and renamed into place (``os.replace``, atomic on one file
system): a write interrupted at any point leaves at most a ``.tmp`` file that readers never
see, and every earlier run intact. Readers take the ``run-*.parquet`` files; one that cannot
be read (a disk that lost it) is skipped with its name in :attr:`History.skipped`.

Bounded: after each append only the newest ``keep`` runs are kept (:data:`KEEP`); older
files are deleted.

:func:`anomalies` flags a scenario x field whose error, for the same seed and configuration,
moves outside the spread of its own history (see :data:`ANOMALY_DECADES`).
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import math
import os
import uuid
from pathlib import Path
from typing import Any, Iterable

from mjxdiff.files import atomic_write

__all__ = ["default_dir", "rows", "append", "History", "open_history", "anomalies", "config_key", "KEEP",
           "ANOMALY_RUNS", "ANOMALY_DECADES", "ANOMALY_RELEVANT", "COLUMNS"]

#: Runs kept in a history directory; older run files are deleted after each append.
KEEP = 500
#: Anomaly check: the last this many runs of the same scenario, field, seed and configuration.
ANOMALY_RUNS = 20
#: ... flag when |log10(error) - median of log10(history)| exceeds max(3 x 1.4826 x MAD, this)
#: (MAD: median absolute deviation of the history's log10 errors; 1.4826 x MAD estimates a
#: standard deviation robustly; the minimum width, a factor of 5, keeps a history of
#: identical numbers from flagging every rounding change of a new MJX build).
ANOMALY_DECADES = math.log10(5.0)
#: ... and only where the error or the history's median is at least this fraction of the
#: field's tolerance (changes deep in rounding say nothing).
ANOMALY_RELEVANT = 1e-6
#: ... with at least this many earlier runs.
ANOMALY_MIN_RUNS = 3

#: (column, DuckDB type) of every row.
COLUMNS: tuple[tuple[str, str], ...] = (
    ("run_id", "VARCHAR"), ("time", "TIMESTAMP"), ("mjxdiff", "VARCHAR"), ("jax", "VARCHAR"),
    ("mujoco", "VARCHAR"), ("mjx", "VARCHAR"), ("mjx_digest", "VARCHAR"), ("seed", "BIGINT"),
    ("config", "VARCHAR"), ("config_key", "VARCHAR"), ("scenario", "VARCHAR"), ("status", "VARCHAR"),
    ("field", "VARCHAR"), ("max_error", "DOUBLE"), ("tolerance", "DOUBLE"), ("ratio", "DOUBLE"),
    ("first_step", "BIGINT"), ("envelope", "DOUBLE"), ("seconds", "DOUBLE"), ("compile_seconds", "DOUBLE"),
)
#: Configuration keys that change a scenario's numbers (what "the same configuration" means).
_NUMERIC_CONFIG = ("seed", "batch", "steps", "precision", "quick", "threshold", "envelope", "noise_floor", "adjust")


def default_dir() -> Path:
    """``$MJXDIFF_HISTORY``, else ``$XDG_DATA_HOME/mjxdiff/history``, else
    ``~/.local/share/mjxdiff/history``."""
    if os.environ.get("MJXDIFF_HISTORY"):
        return Path(os.environ["MJXDIFF_HISTORY"]).expanduser()
    base = os.environ.get("XDG_DATA_HOME") or Path.home() / ".local" / "share"
    return Path(base) / "mjxdiff" / "history"


def config_key(config: dict[str, Any]) -> str:
    """A short digest of the configuration settings that change the numbers."""
    picked = {k: config.get(k) for k in _NUMERIC_CONFIG}
    return hashlib.sha256(json.dumps(picked, sort_keys=True, default=str).encode()).hexdigest()[:12]


def _float(x: Any) -> float | None:
    try:
        return float(x)  # "nan"/"inf" strings of the JSON report read back as floats
    except (TypeError, ValueError):
        return None


def rows(doc: dict[str, Any], run_id: str | None = None, time: _dt.datetime | None = None) -> list[dict[str, Any]]:
    """One row per scenario x compared field of a sweep report (``report.to_json``); a scenario
    without fields (unsupported, an input error) gives one row with an empty field."""
    run_id = run_id or uuid.uuid4().hex[:12]
    time = time or _dt.datetime.now(_dt.timezone.utc).replace(tzinfo=None)
    v, config = doc.get("versions", {}), doc.get("config", {})
    common = dict(run_id=run_id, time=time, mjxdiff=v.get("mjxdiff"), jax=v.get("jax"), mujoco=v.get("mujoco"),
                  mjx=v.get("mujoco-mjx"), mjx_digest=doc.get("code", {}).get("mjx"), seed=config.get("seed"),
                  config=json.dumps({k: config.get(k) for k in _NUMERIC_CONFIG}, sort_keys=True, default=str),
                  config_key=config_key(config))
    out = []
    for s in doc.get("scenarios", []):
        seconds = s.get("info", {}).get("seconds", {})
        total = sum(v for k, v in seconds.items() if k != "compiled_ahead" and isinstance(v, (int, float)))
        base = dict(common, scenario=s["name"], status=s["status"], seconds=float(total),
                    compile_seconds=_float(seconds.get("compile")))
        fields = s.get("fields") or {}
        if not fields:
            out.append(dict(base, field="", max_error=None, tolerance=None, ratio=None, first_step=None,
                            envelope=None))
        for name, f in fields.items():
            out.append(dict(base, field=name, max_error=_float(f.get("max_error")),
                            tolerance=_float(f.get("tolerance")), ratio=_float(f.get("ratio")),
                            first_step=f.get("first_step"),
                            envelope=_float(f.get("envelope"))))
    return out


def append(directory: str | Path, doc: dict[str, Any], keep: int = KEEP) -> Path:
    """Appends a sweep report's rows as one run file; keeps the newest ``keep`` runs.

    Returns the run file's path."""
    import duckdb

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    now = _dt.datetime.now(_dt.timezone.utc).replace(tzinfo=None)
    run_id = uuid.uuid4().hex[:12]
    final = directory / f"run-{now:%Y%m%dT%H%M%S%f}-{run_id}.parquet"
    con = duckdb.connect()
    try:
        con.execute("CREATE TABLE r (" + ", ".join(f'"{c}" {t}' for c, t in COLUMNS) + ")")
        data = rows(doc, run_id, now)
        if data:
            con.executemany(f"INSERT INTO r VALUES ({', '.join('?' * len(COLUMNS))})",
                            [[row[c] for c, _ in COLUMNS] for row in data])
        atomic_write(final, lambda tmp: con.execute(f"COPY r TO '{_sql_path(tmp)}' (FORMAT parquet)"))
    finally:
        con.close()
    for old in sorted(directory.glob("run-*.parquet"))[:-keep] if keep > 0 else []:
        old.unlink(missing_ok=True)
    return final


def _sql_path(p: Path) -> str:
    return str(p).replace("'", "''")


class History:
    """The rows of a history directory as a DuckDB view ``history``; :meth:`sql` queries it."""

    def __init__(self, directory: str | Path):
        import duckdb

        self.directory = Path(directory)
        self.con = duckdb.connect()
        self.skipped: list[str] = []
        files = []
        for f in sorted(self.directory.glob("run-*.parquet")):
            try:
                self.con.execute(f"SELECT count(*) FROM read_parquet('{_sql_path(f)}')").fetchone()
                files.append(f)
            except duckdb.Error:
                self.skipped.append(f.name)
        if files:
            listed = ", ".join(f"'{_sql_path(f)}'" for f in files)
            self.con.execute(f"CREATE VIEW history AS SELECT * FROM read_parquet([{listed}], union_by_name=true)")
        else:
            self.con.execute("CREATE VIEW history AS SELECT * FROM (SELECT " + ", ".join(
                f'CAST(NULL AS {t}) AS "{c}"' for c, t in COLUMNS) + ") WHERE false")
        self.runs = len(files)

    def sql(self, query: str, params: Iterable[Any] = ()) -> list[dict[str, Any]]:
        cur = self.con.execute(query, list(params))
        names = [d[0] for d in cur.description]
        return [dict(zip(names, r)) for r in cur.fetchall()]

    def trends(self, scenario: str | None = None, field: str | None = None,
               since: _dt.datetime | None = None) -> list[dict[str, Any]]:
        """Per scenario x field: runs, first and last time, pass count, median / min / max
        error, and the last run's status, error and ratio."""
        where, params = _filters(scenario, field, since)
        return self.sql(f"""
            SELECT scenario, field, count(*) AS runs, min(time) AS first, max(time) AS last,
                   sum(CAST(status = 'pass' AS INTEGER)) AS passed,
                   median(max_error) AS median_error, min(max_error) AS min_error, max(max_error) AS max_error,
                   arg_max(status, time) AS last_status, arg_max(max_error, time) AS last_error,
                   arg_max(ratio, time) AS last_ratio
            FROM history {where} GROUP BY scenario, field ORDER BY scenario, field""", params)

    def by_version(self, scenario: str | None = None, field: str | None = None,
                   since: _dt.datetime | None = None) -> list[dict[str, Any]]:
        """Runs compared by version: per mujoco / mujoco-mjx version and MJX code digest, the
        runs, scenarios passed and failed, and the median ratio to bound."""
        where, params = _filters(scenario, field, since)
        return self.sql(f"""
            SELECT mujoco, mjx, mjx_digest, count(DISTINCT run_id) AS runs, min(time) AS first, max(time) AS last,
                   count(DISTINCT CASE WHEN status = 'pass' THEN run_id || scenario END) AS scenario_passes,
                   count(DISTINCT CASE WHEN status = 'fail' THEN run_id || scenario END) AS scenario_failures,
                   median(ratio) AS median_ratio
            FROM history {where} GROUP BY mujoco, mjx, mjx_digest ORDER BY last""", params)


def _filters(scenario, field, since) -> tuple[str, list[Any]]:
    clauses, params = [], []
    for column, value in (("scenario", scenario), ("field", field)):
        if value is not None:
            clauses.append(f"{column} = ?")
            params.append(value)
    if since is not None:
        clauses.append("time >= ?")
        params.append(since)
    return ("WHERE " + " AND ".join(clauses)) if clauses else "", params


def open_history(directory: str | Path | None = None) -> History:
    return History(default_dir() if directory is None else directory)


def anomalies(history: History, doc: dict[str, Any], runs: int = ANOMALY_RUNS) -> list[dict[str, Any]]:
    """Scenario x field pairs of ``doc`` (a sweep report not yet appended) whose max error
    moves outside the spread of the last ``runs`` runs with the same seed and configuration:
    |log10 e - median| > max(3 x 1.4826 x MAD, :data:`ANOMALY_DECADES`), over logs of the
    history's errors, when e or the median is at least :data:`ANOMALY_RELEVANT` x the
    tolerance and the history has :data:`ANOMALY_MIN_RUNS` runs or more. Flags passing
    scenarios too: the error need not exceed its bound to have moved."""
    key = config_key(doc.get("config", {}))
    recent: dict[tuple[str, str], list[float]] = {}
    for r in history.sql(  # one scan of the history: the last `runs` errors of every scenario x field
            "SELECT scenario, field, max_error FROM history WHERE config_key = ? AND max_error IS NOT NULL "
            "AND isfinite(max_error) QUALIFY row_number() OVER (PARTITION BY scenario, field ORDER BY time DESC) <= ?",
            (key, runs)):
        recent.setdefault((r["scenario"], r["field"]), []).append(r["max_error"])
    out = []
    for row in rows(doc):
        e, tol = row["max_error"], row["tolerance"]
        if not row["field"] or e is None or tol is None or not math.isfinite(e):
            continue
        past = recent.get((row["scenario"], row["field"]), [])
        if len(past) < ANOMALY_MIN_RUNS:
            continue
        logs = sorted(math.log10(max(x, 1e-300)) for x in past)
        median = _median(logs)
        mad = _median(sorted(abs(x - median) for x in logs))
        width = max(3 * 1.4826 * mad, ANOMALY_DECADES)
        moved = math.log10(max(e, 1e-300)) - median
        relevant = max(e, 10 ** median) >= ANOMALY_RELEVANT * tol
        if abs(moved) > width and relevant:
            out.append(dict(scenario=row["scenario"], field=row["field"], status=row["status"], max_error=e,
                            history_median=10 ** median, decades=moved, width_decades=width, runs=len(past),
                            message=f"{row['scenario']} {row['field']}: max error {e:.3g} is {10 ** abs(moved):.3g}x "
                                    f"{'above' if moved > 0 else 'below'} its history's median {10 ** median:.3g} "
                                    f"({len(past)} runs, same seed and configuration; spread ±{10 ** width:.3g}x)"))
    return out


def _median(xs: list[float]) -> float:
    n = len(xs)
    return xs[n // 2] if n % 2 else 0.5 * (xs[n // 2 - 1] + xs[n // 2])
