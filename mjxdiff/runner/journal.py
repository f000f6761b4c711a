"""A crash-safe record of a sweep's finished units, so that no finished work is lost: resume,
shards and merge read it.

A *unit* is one scenario judged by one pair of engines (``NAME``, ``NAME@warp``, ...). As each
unit's verdict arrives, the driver appends one JSON line to ``OUT/journal.jsonl``: the whole
line in one ``os.write`` on an ``O_APPEND`` descriptor, then ``fsync``, so a killed sweep
leaves every finished unit on disk and at most a torn last line, which :func:`read` ignores.

Each unit record carries its *key* (:func:`unit_key`): the digests of the scenario (its
settings and compiled model), the sweep's settings that decide verdicts (:func:`config_digest`:
seed, batch, steps, precision, checks; not where files go, how many workers or devices),
the MJX code loaded (:func:`mjxdiff.engine.digest.code_digest`), mjxdiff's own source
(:func:`mjxdiff_digest`) and the versions of MuJoCo, MJX and JAX. A record is reused only
under the same key; one whose key no current unit has is *stale* (listed, never merged).

Record types (``type``): ``header`` (``format``, the options as ``report.json``'s ``config``,
``units``: how many units the whole sweep has, ``shard``) and ``unit`` (``key``, ``parts``,
``index`` in the whole sweep's canonical order, ``unit`` name, ``result``:
:func:`mjxdiff.output.report.result_dict`, ``pending``: files the driver has still to write,
``attempts`` and ``lost``: why earlier attempts' workers were lost, ``seconds``: the unit's
wall time on a Ray worker, else :func:`unit_seconds`, ``host``, ``pid``, ``time``).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import socket
import time
from pathlib import Path
from typing import Any, Iterable

__all__ = ["FILE", "FORMAT", "Journal", "Records", "config_digest", "mjxdiff_digest", "read", "reusable",
           "scenario_digest", "unit_key", "unit_seconds"]

FILE = "journal.jsonl"
FORMAT = "mjxdiff-journal/1"

#: SweepConfig fields that say where files go or how much of the machine to use, not what is
#: judged: left out of :func:`config_digest` (a shard on a 64-core node and one on a laptop agree).
RESOURCE_FIELDS = ("reproducers", "compile_workers", "budget", "max_memory")


def _sha(*parts: Any) -> str:
    h = hashlib.sha256()
    for p in parts:
        h.update(p if isinstance(p, bytes) else json.dumps(p, sort_keys=True, default=str).encode())
        h.update(b"\0")
    return h.hexdigest()


def mjxdiff_digest() -> str:
    """Hex SHA-256 of mjxdiff's own source: every ``.py`` file of the package, by relative path."""
    root = Path(__file__).parents[1]  # the package, not this stage
    files = sorted(p for p in root.rglob("*.py") if "__pycache__" not in p.parts)
    return _sha(*[x for p in files for x in (str(p.relative_to(root)), p.read_bytes())])


def config_digest(config: Any) -> str:
    """Hex SHA-256 of a :class:`mjxdiff.runner.sweep.SweepConfig` without :data:`RESOURCE_FIELDS`."""
    fields = {k: v for k, v in dataclasses.asdict(config).items() if k not in RESOURCE_FIELDS}
    return _sha(fields)


def scenario_digest(scenario: Any) -> str:
    """Hex SHA-256 of a scenario: its settings (the model's path aside) and its model as MuJoCo
    compiles it (``mj_saveModel``'s bytes: the XML, its includes and assets), or the model
    file's bytes and the compile error where it does not compile."""
    import mujoco
    import numpy as np

    from mjxdiff.input.scenario import ScenarioError, load_model

    settings = {k: v for k, v in dataclasses.asdict(scenario).items() if k not in ("model", "source")}
    try:
        m = load_model(scenario)
        model = np.zeros(mujoco.mj_sizeModel(m), np.uint8)
        mujoco.mj_saveModel(m, None, model)
        return _sha(settings, model.tobytes())
    except ScenarioError as e:
        path = scenario.model_path
        return _sha(settings, path.read_bytes() if path.is_file() else str(path), str(e))


def unit_key(scenario_hash: str, suffix: str, config: Any, mjx: str, own: str,
             versions: dict[str, str]) -> tuple[str, dict[str, Any]]:
    """The key of one unit and the parts it hashes (shown for a stale record)."""
    parts = dict(scenario=scenario_hash, pair=suffix, seed=config.seed, config=config_digest(config), mjx=mjx,
                 mjxdiff=own, versions=versions)
    return _sha(parts), parts


def unit_seconds(result: dict[str, Any]) -> float:
    """A unit's seconds from its verdict: inputs, compile, both engines, verdict, diagnosis and
    the checks summed (``compiled_ahead`` overlaps the rest and is left out)."""
    spent = ((result.get("info") or {}).get("seconds") or {}).items()
    return float(sum(v for k, v in spent if isinstance(v, (int, float)) and k != "compiled_ahead"))


class Journal:
    """Appends records to ``path`` (created; emptied first unless ``append``). Each
    :meth:`write` is one ``os.write`` of one whole line, then ``fsync``."""

    def __init__(self, path: str | Path, append: bool = False):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        flags = os.O_WRONLY | os.O_CREAT | os.O_APPEND | (0 if append else os.O_TRUNC)
        self._fd = os.open(self.path, flags, 0o644)

    def write(self, record: dict[str, Any]) -> None:
        line = (json.dumps(record, separators=(",", ":"), allow_nan=False) + "\n").encode()
        written = os.write(self._fd, line)
        if written != len(line):  # O_APPEND writes of a regular file are whole; say so if not
            raise OSError(f"journal {self.path}: wrote {written} of {len(line)} bytes")
        os.fsync(self._fd)

    def unit(self, key: str, parts: dict[str, Any], index: int, result: dict[str, Any],
             pending: Iterable[tuple[str, str, dict[str, Any]]] = (), lost: Iterable[str] = (),
             seconds: float | None = None) -> None:
        """Records a finished unit (``result``: :func:`mjxdiff.output.report.result_dict`; ``lost``:
        why earlier attempts' workers were lost, each retried; ``seconds``: its wall time where
        the executor measured it, else :func:`unit_seconds`)."""
        lost = list(lost)
        self.write(dict(type="unit", key=key, parts=parts, index=index, unit=result["name"], result=result,
                        pending=[list(p) for p in pending], attempts=len(lost) + 1, lost=lost,
                        seconds=unit_seconds(result) if seconds is None else seconds,
                        host=socket.gethostname(), pid=os.getpid(), time=time.time()))

    def close(self) -> None:
        os.close(self._fd)

    def __enter__(self) -> "Journal":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


@dataclasses.dataclass
class Records:
    """What :func:`read` found: the ``header`` (the last one), the ``units`` in file order,
    whether the last line was ``torn`` (an interrupted write, ignored) and the numbers of
    ``bad`` lines elsewhere (skipped)."""

    header: dict[str, Any] | None
    units: list[dict[str, Any]]
    torn: bool = False
    bad: list[int] = dataclasses.field(default_factory=list)


def read(path: str | Path) -> Records:
    """The records of a journal file; an absent file has none."""
    path = Path(path)
    if not path.is_file():
        return Records(None, [])
    raw = path.read_bytes()
    lines = raw.split(b"\n")
    torn = bool(lines[-1])  # a last line without its newline never finished its write
    out = Records(None, [], torn=torn)
    for number, line in enumerate(lines[:-1], 1):
        try:
            record = json.loads(line)
        except ValueError:
            out.bad.append(number)
            continue
        if record.get("type") == "header":
            out.header = record
        elif record.get("type") == "unit":
            out.units.append(record)
    return out


#: Statuses a journal's record settles: a verdict on MJX, or input it could not read. The rest
#: (a worker that died, a limit, an engine crash) are rerun on resume.
SETTLED = ("pass", "fail", "unsupported")


def reusable(record: dict[str, Any], rerun: str = "errors") -> bool:
    """Whether a resumed sweep keeps ``record``'s verdict: a settled status
    (:data:`SETTLED`, or an input error) unless ``rerun="failed"`` (then failures and errors
    are rerun too, as pytest's ``--lf``)."""
    r = record["result"]
    settled = r["status"] in SETTLED or (r["status"] == "error" and r.get("error_kind") == "input")
    return settled and not (rerun == "failed" and r["status"] in ("fail", "error"))
