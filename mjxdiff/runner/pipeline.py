"""A whole sweep from one set of options, as ``python -m mjxdiff sweep`` runs it.

scenarios -> both engines (:func:`mjxdiff.runner.sweep.sweep`, once per judged pair) -> verdicts ->
the known-divergence catalogue, the history's anomalies, the baseline's changes and the exit
code (:func:`compute`) -> ``report.json``, ``report.html`` and the history row
(:func:`write`). :func:`run` does both; the CLI only parses and prints::

    import mjxdiff

    run = mjxdiff.run(scenarios=["pendulum", "cartpole"], batch=4, steps=100, out="sweep-out")
    print(run.exit_code)                      # 0 consistent, 1 a divergence (as the CLI exits)
    for r in run.results:                     # mjxdiff.ScenarioResult, in the order swept
        print(r.name, r.status, r.worst_ratio)
    run.doc["summary"]                        # report.json's content, known labels included
    run.files                                 # {"report": ..., "page": ..., "history": ...}

Options that cannot be used (an unreadable ``known`` file or baseline, MJWarp not installed,
no scenario selected) raise :class:`OptionsError`, whose message is one line (the CLI exits 2
with it). A scenario that cannot be read is an ``error`` result, and the others still run.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import time
from pathlib import Path
from typing import Any, Callable, Sequence

from mjxdiff.errors import one_line
from mjxdiff.input.options import PAIRS, WARP_IMPLS, SweepOptions, config_values
from mjxdiff.output import baseline, report
from mjxdiff.runner import journal
from mjxdiff.compare import known
from mjxdiff.compare.result import ScenarioResult

__all__ = ["OptionsError", "SweepOptions", "SweepRun", "Unit", "compute", "merge", "run", "write"]


class OptionsError(ValueError):
    """Options a sweep cannot run with; the message is one line."""


@dataclasses.dataclass
class SweepRun:
    """What a sweep found: its ``results`` (one per scenario and judged pair), the report
    ``doc`` (``report.json``'s content), ``exit_code`` (0, 1; see :func:`compute`), the
    ``warnings`` that left the verdicts standing, and ``files`` written by :func:`write`."""

    options: SweepOptions
    results: list[ScenarioResult]
    doc: dict[str, Any]
    exit_code: int
    seconds: float
    input_errors: list[str] = dataclasses.field(default_factory=list)
    warnings: list[str] = dataclasses.field(default_factory=list)
    files: dict[str, str] = dataclasses.field(default_factory=dict)

    @property
    def anomalies(self) -> list[dict[str, Any]]:
        """Errors that moved outside their own history (``doc["history"]["anomalies"]``)."""
        return (self.doc.get("history") or {}).get("anomalies", [])

    @property
    def changes(self) -> list[dict[str, Any]] | None:
        """The baseline's classes per scenario, or None without a baseline."""
        return (self.doc.get("baseline") or {}).get("changes")


def _scenarios(options: SweepOptions) -> tuple[list, list[ScenarioResult]]:
    """The scenarios the options name (every bundled one when none), and an ``error`` result
    for each that cannot be read."""
    from mjxdiff.input.scenario import (LaterFeatureError, ScenarioError, bundled_scenarios, load_model, load_scenario,
                                  no_bundled_scenarios_message)

    try:
        refs = list(options.scenarios) or [s.name for s in bundled_scenarios()]
    except ScenarioError as e:
        raise OptionsError(str(e)) from e
    if not refs:  # never report "consistent" having swept nothing
        raise OptionsError(f"no scenarios selected ({no_bundled_scenarios_message()})")
    scenarios, bad = [], []
    for ref in refs:
        name = str(ref)
        try:
            scenario = load_scenario(ref)
            name = scenario.name
            if options.scenarios:  # the user's: an MJCF MuJoCo cannot compile is said now, before MJX's import
                with contextlib.suppress(LaterFeatureError):  # a newer MuJoCo's feature: the sweep's unsupported
                    load_model(scenario)
            scenarios.append(scenario)
        except ScenarioError as e:
            bad.append(ScenarioResult(name=name, status="error", error_kind="input", message=str(e)))
    return scenarios, bad


def sweep_config(options: SweepOptions):
    """The :class:`mjxdiff.runner.sweep.SweepConfig` of the options (reproducers under ``out``):
    the fields :class:`SweepOptions` declares with ``config`` (:func:`~mjxdiff.input.options.config_values`)."""
    from mjxdiff.runner.sweep import SweepConfig

    return SweepConfig(**config_values(options),
                       reproducers=str(Path(options.out) / "reproducers") if options.out else None)


#: Every pair's name suffix, longest first (``@mjx-warp`` before ``@warp``).
_SUFFIXES = sorted({suffix for pairs in PAIRS.values() for suffix, _ in pairs if suffix}, key=len, reverse=True)


def _pair_configs(config, impl: str) -> list[tuple[str, Any]]:
    """(name suffix, SweepConfig) of each judged pair of ``impl``."""
    out = []
    for suffix, change in PAIRS[impl]:
        if change.get("impl") in WARP_IMPLS and "reproducers" not in change and config.reproducers:
            change = dict(change, reproducers=str(Path(config.reproducers) / change["impl"]))
        out.append((suffix, dataclasses.replace(config, **change)))
    return out


@dataclasses.dataclass(frozen=True)
class Unit:
    """One scenario judged by one pair: its ``index`` in the whole sweep's canonical order
    (pairs, then scenarios as given), and its journal ``key`` and ``parts``
    (:func:`mjxdiff.runner.journal.unit_key`; empty when nothing is journaled)."""

    index: int
    suffix: str
    scenario: Any
    key: str = ""
    parts: dict[str, Any] = dataclasses.field(default_factory=dict)


def _units(config, scenarios: list, impl: str, journaled: bool) -> list[Unit]:
    """The canonical unit list, keyed where a journal is written or read."""
    units = []
    if journaled:
        from mjxdiff import compat
        from mjxdiff.engine.digest import code_digest

        mjx, own, versions = code_digest(), journal.mjxdiff_digest(), compat.installed()
        digests = [journal.scenario_digest(s) for s in scenarios]
    for p, (suffix, pair_config) in enumerate(_pair_configs(config, impl)):
        for i, s in enumerate(scenarios):
            key, parts = (journal.unit_key(digests[i], suffix, pair_config, mjx, own, versions) if journaled
                          else ("", {}))
            units.append(Unit(p * len(scenarios) + i, suffix, s, key, parts))
    return units


def _deliver(u: Unit, r: ScenarioResult, done: dict[int, ScenarioResult], writer: journal.Journal | None,
             on_result, entries, lost: Sequence[str] = (), seconds: float | None = None) -> None:
    """One unit's verdict as it arrives, from either executor: renamed for its pair, kept in
    ``done``, journaled, passed to ``on_result`` with its known entry."""
    r = dataclasses.replace(r, name=r.name + u.suffix)
    done[u.index] = r
    if writer is None and on_result is None:
        return
    as_dict = report.result_dict(r)
    if writer is not None:
        writer.unit(u.key, u.parts, u.index, as_dict, r.pending, list(lost), seconds)
    if on_result is not None:
        on_result(r, known.match(as_dict, entries))


def _ray(options: SweepOptions, config, units: list[Unit], done: dict[int, ScenarioResult],
         writer: journal.Journal | None, on_result, entries) -> None:
    """The units not ``done`` as Ray tasks (:func:`mjxdiff.runner.executors.ray_sweep`), each result
    journaled and passed on as it arrives; ``done`` gains them."""
    import sys

    from mjxdiff.runner import executors

    configs = dict(_pair_configs(config, options.impl))
    jobs = [(u, u.scenario, configs[u.suffix]) for u in units if u.index not in done]

    def arrived(u: Unit, r: ScenarioResult, lost: list[str], seconds: float | None) -> None:
        _deliver(u, r, done, writer, on_result, entries, lost, seconds)

    progress = sys.stderr.isatty() if options.progress is None else options.progress
    say = (lambda text: print(f"... {text}", file=sys.stderr, flush=True)) if progress else None
    executors.ray_sweep(jobs, arrived, options.address, options.cpus_per_scenario or 1, options.cache_dir, say)


def _shard(text: str | None) -> tuple[int, int] | None:
    """``"I/N"`` -> (I, N), 1 <= I <= N; OptionsError otherwise."""
    if text is None:
        return None
    try:
        i, n = (int(x) for x in str(text).split("/"))
    except ValueError:
        i = n = 0
    if not 1 <= i <= n:
        raise OptionsError(f"--shard {text}: expected I/N with 1 <= I <= N, e.g. 2/3")
    return i, n


def _resumed(options: SweepOptions, units: list[Unit]) -> tuple[dict[int, ScenarioResult], dict[str, Any] | None]:
    """The verdicts a resumed sweep keeps (by unit index) and what the journal said: ``reused``
    units, ``stale`` records (a key no current unit has: other code, seed, settings or model),
    ``torn`` (an interrupted last line) and ``bad`` lines. Without ``resume``: nothing kept, and
    the journal's file where ``out`` is given (else None)."""
    if not options.resume:
        return {}, ({"file": str(Path(options.out) / journal.FILE)} if options.out else None)
    records = journal.read(Path(options.resume) / journal.FILE)
    latest = {r["key"]: r for r in records.units}  # a key recorded twice (a rerun): the later record
    current = {u.key for u in units}
    done = {}
    for u in units:
        record = latest.get(u.key)
        if record is not None and journal.reusable(record, options.rerun):
            r = report.result_from_dict(record["result"])
            done[u.index] = dataclasses.replace(r, pending=tuple(tuple(p) for p in record.get("pending", ())))
    stale = sorted({r["unit"] for r in records.units if r["key"] not in current})
    out_dir = options.out or options.resume
    return done, dict(file=str(Path(out_dir) / journal.FILE), resumed_from=str(options.resume), reused=len(done),
                      stale=stale, torn=records.torn, bad_lines=records.bad)


def _open_journal(options: SweepOptions, total: int, done: dict[int, ScenarioResult]) -> journal.Journal | None:
    """The journal this sweep appends to (under ``out``, or the resumed directory): a resumed
    one in place keeps its records; a fresh one begins with a header (and, resumed elsewhere,
    the reused records, so that it stands alone)."""
    out_dir = options.out or options.resume
    if not out_dir:
        return None
    in_place = bool(options.resume) and Path(options.resume).resolve() == Path(out_dir).resolve()
    writer = journal.Journal(Path(out_dir) / journal.FILE, append=in_place)
    writer.write(dict(type="header", format=journal.FORMAT, config=options.as_config(), units=total,
                      shard=options.shard))
    if options.resume and not in_place:
        records = {r["key"]: r for r in journal.read(Path(options.resume) / journal.FILE).units}
        for r in records.values():
            if r["index"] in done and report.result_dict(done[r["index"]]) == r["result"]:
                writer.write(r)
    return writer


def _checked(options: SweepOptions) -> tuple[SweepOptions, tuple[known.Entry, ...], Any, tuple[int, int] | None]:
    """``options`` checked before anything runs (resumed in place where ``resume`` has no
    ``out``), the known entries, the baseline (None without one) and the shard (None without
    one). Raises :class:`OptionsError` on untested versions, an unreadable known file or
    baseline, MJWarp or Ray missing, Ray's options without Ray, or a ``resume`` without journal."""
    from mjxdiff import compat

    why = compat.gate(options.allow_untested_versions)
    if why:
        raise OptionsError(why)
    if options.resume and not options.out:  # resumed in place
        options = dataclasses.replace(options, out=options.resume)

    try:
        entries = known.entries(options.known)
        base = (baseline.load(options.baseline, None if options.no_history else options.history)
                if options.baseline else None)
    except (known.KnownError, baseline.BaselineError) as e:
        raise OptionsError(str(e)) from e
    if options.impl != "mjx":
        from mjxdiff.engine import mjwarp

        why = mjwarp.available()
        if why:
            raise OptionsError(f"--impl {options.impl}: {why}")
    shard = _shard(options.shard)
    if options.executor == "ray":
        from mjxdiff.runner import executors

        why = executors.ray_missing()
        if why:
            raise OptionsError(f"--executor ray: {why}")
    elif options.address or options.cpus_per_scenario:
        raise OptionsError("--address and --cpus-per-scenario are for --executor ray")
    if options.resume and not (Path(options.resume) / journal.FILE).is_file():
        raise OptionsError(f"--resume {options.resume}: no {journal.FILE} there (a sweep run with --out "
                           f"{options.resume} writes one)")
    return options, entries, base, shard


def _sweep_local(options: SweepOptions, config, limits, units: list[Unit], done: dict[int, ScenarioResult],
                 writer: journal.Journal | None, on_result, entries: tuple[known.Entry, ...]) -> None:
    """Sweeps the ``units`` not yet ``done`` on this machine, pair by pair (in the guard's child
    processes held to ``limits`` with ``options.isolate``), delivering each verdict as it arrives
    (:func:`_deliver`); ``done`` gets them by unit index, renamed after their pair."""
    from mjxdiff.runner import guard
    from mjxdiff.runner.sweep import sweep

    for suffix, pair_config in _pair_configs(config, options.impl):
        todo = [u for u in units if u.suffix == suffix and u.index not in done]
        arriving = iter(todo)

        def arrived(r: ScenarioResult) -> None:
            _deliver(next(arriving), r, done, writer, on_result, entries)
        picked = [u.scenario for u in todo]
        if not picked:
            continue
        if options.isolate:
            swept = guard.sweep(picked, pair_config, limits, options.progress, arrived, options.cache_dir)
        else:
            swept = sweep(picked, pair_config, options.progress, arrived)
        # a scenario's name seeds its inputs: the pair's results are renamed after the sweep
        done.update({u.index: dataclasses.replace(r, name=r.name + suffix) for u, r in zip(todo, swept)})


def _process_timing(entered: tuple[float, float], started: tuple[float, float],
                    swept: tuple[float, float]) -> dict[str, dict[str, float]]:
    """The process's (wall, CPU) seconds by phase: ``startup`` (the interpreter and the imports,
    once per process: zero for a later run in it), ``prepare`` (from ``entered`` to
    ``started``), ``sweep`` (to ``swept``) and ``finish`` (to now)."""
    import mjxdiff

    # start-up: the interpreter and the imports, once per process (a later run in it has none)
    startup = (dict(wall=entered[0] - mjxdiff._IMPORTED_AT, cpu=entered[1])  # noqa: SLF001
               if not _STARTED.get("done") else dict(wall=0.0, cpu=0.0))
    _STARTED["done"] = True
    return dict(startup=startup, prepare=_between(entered, started), sweep=_between(started, swept),
                finish=_between(swept, _clocks()))


def compute(options: SweepOptions, on_result: Callable[[ScenarioResult, known.Entry | None], None] | None = None,
            ) -> SweepRun:
    """Sweeps, then labels known divergences, reads the history's anomalies and the baseline's
    changes, and decides the exit code: 1 on any ``fail`` or ``error`` (with ``fail_on="new"``,
    only on failures no accepted known entry explains and, with a baseline, that it did not
    have), else 0. Writes nothing: the reproducers of failures are carried (``pending``) for
    :func:`write`.

    ``on_result(result, known_entry)`` is called as each scenario's verdict arrives (the
    results of ``impl="both"``'s other pairs renamed ``NAME@warp``, ``NAME@mjx-warp``)."""
    entered = _clocks()
    options, entries, base, shard = _checked(options)
    scenarios, bad = _scenarios(options)
    if bad and not scenarios and not options.resume:  # nothing to run: said in a second, MJX never imported
        raise OptionsError("; ".join(r.message for r in bad))
    from mjxdiff.engine import engines, export_cache  # JAX and MJX: imported once there is something to run
    from mjxdiff.runner import guard

    engines.configure_jax(options.precision, options.cache_dir)
    config = sweep_config(options)
    limits = guard.Limits(options.max_memory or guard.default_memory(), options.budget, options.sweep_budget)
    units = [u for u in _units(config, scenarios, options.impl, journaled=bool(options.out or options.resume))
             if shard is None or u.index % shard[1] == shard[0] - 1]

    t0 = time.perf_counter()
    started = _clocks()
    cache_before = export_cache.events()
    done, book = _resumed(options, units)
    resumed = set(done)
    writer = _open_journal(options, len(scenarios) * len(PAIRS[options.impl]), done)
    try:
        if options.executor == "ray":
            _ray(options, config, units, done, writer, on_result, entries)
        if options.executor == "local":
            _sweep_local(options, config, limits, units, done, writer, on_result, entries)
    finally:
        if writer is not None:
            writer.close()
    results = list(bad) + [done[i] for i in sorted(done)]
    if options.impl in ("both", "all"):
        results = _c_outliers(results)
    seconds = time.perf_counter() - t0
    swept = _clocks()

    doc = report.to_json(results, dict(options.as_config(), seconds=seconds, mjx_compiles=engines.compile_count()))
    doc["code"]["cache"] = cache = export_cache.events_since(cache_before)
    if options.executor == "ray":  # Ray's workers traced and loaded, not this process
        fresh = [done[i].info for i in done if i not in resumed]
        cache.update(loaded=sum(i.get("mjx_loaded", 0) for i in fresh),
                     traced=sum(i.get("mjx_compiles", 0) for i in fresh), where="Ray's workers")
    if book is not None:
        doc["journal"] = book
    out = _finish(options, results, bad, seconds, doc, entries, base)
    doc["timing"] = report.timing(doc["scenarios"], _process_timing(entered, started, swept))
    return out


_STARTED: dict[str, bool] = {}


def _c_outliers(results: list[ScenarioResult]) -> list[ScenarioResult]:
    """``impl="both"``'s verdicts, where C is the odd one out of a scenario's three
    (:func:`mjxdiff.compare.reference.c_outlier`) its two failures against C saying so
    (``info["reference_outlier"]``), instead of blaming MJX and MuJoCo Warp alone."""
    from mjxdiff.compare import reference

    status: dict[str, dict[str, str]] = {}
    for r in results:
        base, suffix = _pair_of(r.name)
        status.setdefault(base, {})[suffix] = r.status
    out = []
    for r in results:
        base, suffix = _pair_of(r.name)
        if suffix in ("", "@warp") and reference.c_outlier(status[base]):
            r = dataclasses.replace(r, message=f"{r.message}; {reference.outlier_clause(base)}",
                                    info=dict(r.info, reference_outlier=True))
        out.append(r)
    return out


def _pair_of(name: str) -> tuple[str, str]:
    """(scenario, pair suffix) of a result's name under ``impl="both"`` (:data:`PAIRS`)."""
    for suffix in _SUFFIXES:
        if name.endswith(suffix):
            return name[:-len(suffix)], suffix
    return name, ""


def _clocks() -> tuple[float, float]:
    """(wall seconds, CPU seconds of this process and of its children waited for so far: a
    guard's child process counts once it has ended)."""
    try:
        import resource
    except ImportError:  # not on Windows: this process alone
        return time.perf_counter(), time.process_time()
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.perf_counter(), own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def _between(a: tuple[float, float], b: tuple[float, float]) -> dict[str, float]:
    return dict(wall=b[0] - a[0], cpu=b[1] - a[1])


def _finish(options: SweepOptions, results: list[ScenarioResult], bad: list[ScenarioResult], seconds: float,
            doc: dict[str, Any], entries: tuple[known.Entry, ...], base: Any) -> SweepRun:
    """Labels known divergences, reads the history's anomalies and the baseline's changes, and
    decides the exit code (:func:`compute`)."""
    from mjxdiff.runner.sweep import exit_code

    accepted = set()
    for sc in doc["scenarios"]:
        entry = known.match(sc, entries)
        if entry:
            sc["known"] = dict(dataclasses.asdict(entry), advice=known.advice(entry))
            if entry.accepted:
                accepted.add(sc["name"])
    out = SweepRun(options, results, doc, 0, seconds, input_errors=[r.message for r in bad])
    _read_history(out)
    changes = None if base is None else baseline.compare(base, doc)
    if changes is not None:
        doc["baseline"] = dict(ref=options.baseline, changes=changes)
    code = exit_code(results)
    if options.fail_on == "new" and code == 1:
        failing = (baseline.new_failures(changes) if changes is not None else
                   [s["name"] for s in doc["scenarios"] if s["status"] in ("fail", "error")])
        code = 1 if [n for n in failing if n not in accepted] else 0
    out.exit_code = code
    return out


def _history_dir(options: SweepOptions) -> Path:
    from mjxdiff.output import history

    return Path(options.history) if options.history else history.default_dir()


def _read_history(out: SweepRun) -> None:
    """Flags the run's anomalies against the history (``doc["history"]``). A history that cannot
    be read is a warning: the verdicts stand."""
    if out.options.no_history:
        return
    from mjxdiff.output import history

    directory = _history_dir(out.options)
    try:
        out.doc["history"] = dict(dir=str(directory), anomalies=history.anomalies(history.open_history(directory),
                                                                                  out.doc))
    except Exception as e:  # noqa: BLE001 - never lose the verdicts to the history
        out.warnings.append(f"history {directory}: {one_line(e)}")


def write(out: SweepRun) -> dict[str, str]:
    """Writes the failures' reproducers (under ``out/reproducers``), appends the run to the
    history (where it was read), then writes ``report.json`` and ``report.html`` under the
    options' ``out``; returns the files written (``out.files``). A reproducer that cannot be
    written is a part of its verdict's message; a history or page, a warning (``out.warnings``)."""
    from mjxdiff.output import history

    options, doc = out.options, out.doc
    for i, r in enumerate(out.results):  # doc["scenarios"] holds the results in order
        if r.pending:
            out.results[i] = written = report.write_pending(r)
            sc = doc["scenarios"][i]
            sc["message"] = written.message
            sc["info"].update({key: written.info[key] for key, *_ in r.pending})
    if "history" in doc:
        directory = _history_dir(options)
        try:
            out.files["history"] = doc["history"]["run_file"] = str(
                history.append(directory, doc, keep=options.history_keep))
        except Exception as e:  # noqa: BLE001 - never lose the verdicts to the history
            out.warnings.append(f"history {directory}: {one_line(e)}")
    if options.out:
        out.files["report"] = str(report.write_report(options.out, doc))
        try:
            from mjxdiff.output import html_report

            out.files["page"] = str(html_report.write(options.out, doc, options.plots))
        except Exception as e:  # noqa: BLE001 - the verdicts stand without their page
            out.warnings.append(f"report.html not written: {one_line(e)}")
    return out.files


def run(options: SweepOptions | None = None, /, on_result=None, **changes: Any) -> SweepRun:
    """:func:`compute` then :func:`write`: everything ``mjxdiff sweep`` does but print. Options
    come as a :class:`SweepOptions` or by name (``run(scenarios=["pendulum"], batch=4)``; a
    single scenario name may be a string)."""
    if isinstance(changes.get("scenarios"), (str, os.PathLike)):
        changes["scenarios"] = (changes["scenarios"],)
    if "scenarios" in changes:
        changes["scenarios"] = tuple(str(s) for s in changes["scenarios"])
    try:
        options = dataclasses.replace(options or SweepOptions(), **changes)
    except TypeError as e:
        raise OptionsError(str(e)) from e
    out = compute(options, on_result)
    write(out)
    return out


#: Options that may differ between shards of one sweep (where each ran, what it printed).
_PER_SHARD = ("shard", "out", "resume", "rerun", "progress", "format", "cache_dir", "compile_workers", "budget",
              "sweep_budget", "max_memory", "isolate", "history", "no_history", "seconds", "mjx_compiles", "command",
              "executor", "address", "cpus_per_scenario")


def _verdict(result: dict[str, Any]) -> tuple:
    """What two runs of one unit must agree on: the status and each field's worst error, first
    step out and member (timings, compile counts and file paths aside)."""
    fields = result.get("fields") or {}
    return (result["status"], result.get("error_kind", ""),
            tuple(sorted((k, str(f["max_error"]), f["first_step"], f["member"]) for k, f in fields.items())))


def merge(out: str | None, dirs: list[str], **changes: Any) -> SweepRun:
    """One report from the journals of shard outputs (``mjxdiff merge OUT DIR...``): the units
    of every directory, in the sweep's canonical order, then the known labels, history and exit
    code as one sweep decides them. Order-independent and idempotent: a unit recorded twice
    (two shards, a resumed run) counts once. Records of one unit with other verdicts are
    ``nondeterministic`` (a finding: exit 1); units no directory has are ``missing`` (exit 1).

    Raises:
      OptionsError: a directory without a journal, or shards of different sweeps (other
        scenarios, seed or settings).
    """
    headers, records = [], []
    for d in dirs:
        found = journal.read(Path(d) / journal.FILE)
        if found.header is None:
            raise OptionsError(f"{d}: no {journal.FILE} with a header (a sweep run with --out {d} writes one)")
        headers.append(found.header)
        records += found.units
    configs = [{k: v for k, v in h["config"].items() if k not in _PER_SHARD} for h in headers]
    if any(c != configs[0] for c in configs[1:]):
        differ = sorted({k for c in configs[1:] for k in c if c[k] != configs[0].get(k)})
        raise OptionsError(f"the directories hold shards of different sweeps: {', '.join(differ)} differ")
    fields = {f.name for f in dataclasses.fields(SweepOptions)}
    config = {k: v for k, v in headers[0]["config"].items() if k in fields}
    options = SweepOptions(**{**config, "scenarios": tuple(config.get("scenarios") or ()), "out": out, "shard": None,
                              "resume": None, **changes})
    entries = known.entries(options.known)
    base = (baseline.load(options.baseline, None if options.no_history else options.history)
            if options.baseline else None)
    _, bad = _scenarios(options)
    by_index: dict[int, list[dict[str, Any]]] = {}
    for r in records:
        by_index.setdefault(r["index"], []).append(r)
    total = max(h["units"] for h in headers)
    nondeterministic = sorted(group[0]["unit"] for group in by_index.values()
                              if len({_verdict(r["result"]) for r in group}) > 1)
    missing = [i for i in range(total) if i not in by_index]
    results = list(bad)
    for i in sorted(by_index):
        first = by_index[i][0]
        r = report.result_from_dict(first["result"])
        results.append(dataclasses.replace(r, pending=tuple(tuple(p) for p in first.get("pending", ()))))
    seconds = sum(float(r.get("seconds") or 0.0) for r in records)
    doc = report.to_json(results, dict(options.as_config(), seconds=seconds))
    doc["journal"] = dict(merged=[str(d) for d in dirs], units=total, records=len(records), missing=missing,
                          nondeterministic=nondeterministic)
    run = _finish(options, results, bad, seconds, doc, entries, base)
    if missing or nondeterministic:
        run.exit_code = 1
    return run
