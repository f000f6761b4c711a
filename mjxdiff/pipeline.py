"""A whole sweep from one set of options, as ``python -m mjxdiff sweep`` runs it.

scenarios -> both engines (:func:`mjxdiff.sweep.sweep`, once per judged pair) -> verdicts ->
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

import dataclasses
import os
import time
from pathlib import Path
from typing import Any, Callable, Literal

from mjxdiff.errors import one_line
from mjxdiff import baseline, export_cache, known, report
from mjxdiff.verdict import ScenarioResult

__all__ = ["OptionsError", "SweepOptions", "SweepRun", "compute", "run", "write"]


class OptionsError(ValueError):
    """Options a sweep cannot run with; the message is one line."""


def _isolate_default() -> bool:
    return os.environ.get("MJXDIFF_ISOLATE", "1") != "0"


@dataclasses.dataclass(frozen=True)
class SweepOptions:
    """Everything ``mjxdiff sweep`` takes, by its flag's name (``--noise-floor`` is
    ``noise_floor``), with the same defaults; ``mjxdiff sweep --help`` says what each does."""

    scenarios: tuple[str, ...] = ()
    seed: int = 0
    batch: int | None = None
    steps: int | None = None
    precision: Literal["float64", "float32"] = "float64"
    threshold: float = 0.95
    envelope: bool = True
    noise_floor: Literal["on-demand", "always"] = "on-demand"
    diagnose: Literal["none", "basic", "full"] = "full"
    adjust: bool = True
    drop_unsupported: bool = False
    drop_costly_pairs: bool = False
    budget: float = 600.0
    sweep_budget: float | None = None
    max_memory: int | None = None
    isolate: bool = dataclasses.field(default_factory=_isolate_default)
    onestep: bool = True
    transfer: bool = True
    compile: Literal["auto", "fast", "optimized"] = "auto"
    compile_workers: int | None = None
    out: str | None = None
    impl: Literal["mjx", "warp", "both"] = "mjx"
    plots: Literal["failing", "all", "none"] = "failing"
    history: str | None = None
    no_history: bool = False
    history_keep: int = 500
    baseline: str | None = None
    fail_on: Literal["any", "new"] = "any"
    known: str | None = None
    format: Literal["text", "json"] = "text"
    quick: bool = False
    cache_dir: str | None = None
    progress: bool | None = None
    allow_untested_versions: bool = False

    def as_config(self) -> dict[str, Any]:
        """The options as ``report.json``'s ``config`` records them."""
        return dict(command="sweep", **dataclasses.asdict(self)) | dict(scenarios=list(self.scenarios))


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


def _entries(options: SweepOptions) -> tuple[known.Entry, ...]:
    return (known.load_entries(options.known) if options.known else ()) + known.CATALOGUE


def _scenarios(options: SweepOptions) -> tuple[list, list[ScenarioResult]]:
    """The scenarios the options name (every bundled one when none), and an ``error`` result
    for each that cannot be read."""
    from mjxdiff.scenario import ScenarioError, bundled_scenarios, load_scenario, no_bundled_scenarios_message

    try:
        refs = list(options.scenarios) or [s.name for s in bundled_scenarios()]
    except ScenarioError as e:
        raise OptionsError(str(e)) from e
    if not refs:  # never report "consistent" having swept nothing
        raise OptionsError(f"no scenarios selected ({no_bundled_scenarios_message()})")
    scenarios, bad = [], []
    for ref in refs:
        try:
            scenarios.append(load_scenario(ref))
        except ScenarioError as e:
            bad.append(ScenarioResult(name=str(ref), status="error", error_kind="input", message=str(e)))
    return scenarios, bad


def sweep_config(options: SweepOptions):
    """The :class:`mjxdiff.sweep.SweepConfig` of the options (reproducers under ``out``)."""
    from mjxdiff.sweep import SweepConfig

    o = options
    return SweepConfig(seed=o.seed, batch=o.batch, steps=o.steps, precision=o.precision,
                       reproducers=str(Path(o.out) / "reproducers") if o.out else None, quick=o.quick,
                       threshold=o.threshold, envelope=o.envelope, noise_floor=o.noise_floor, diagnose=o.diagnose,
                       adjust=o.adjust, drop_unsupported=o.drop_unsupported, compile=o.compile,
                       compile_workers=o.compile_workers, transfer=o.transfer, onestep=o.onestep,
                       drop_costly=o.drop_costly_pairs, budget=o.budget, max_memory=o.max_memory)


#: The judged pairs of each ``impl``: (name suffix, changes to the sweep's config).
_PAIRS: dict[str, tuple[tuple[str, dict[str, Any]], ...]] = {
    "mjx": (("", {}),),
    "warp": (("", dict(impl="warp")),),
    # MJWarp against MJX: C's envelope as the floor
    "both": (("", {}), ("@warp", dict(impl="warp")),
             ("@mjx-warp", dict(impl="warp", reference="mjx", diagnose="none", reproducers=None))),
}


def compute(options: SweepOptions, on_result: Callable[[ScenarioResult, known.Entry | None], None] | None = None,
            ) -> SweepRun:
    """Sweeps, then labels known divergences, reads the history's anomalies and the baseline's
    changes, and decides the exit code: 1 on any ``fail`` or ``error`` (with ``fail_on="new"``,
    only on failures no accepted known entry explains and, with a baseline, that it did not
    have), else 0. Writes nothing: the reproducers of failures are carried (``pending``) for
    :func:`write`.

    ``on_result(result, known_entry)`` is called as each scenario's verdict arrives (the
    results of ``impl="both"``'s other pairs renamed ``NAME@warp``, ``NAME@mjx-warp``)."""
    from mjxdiff import compat, engines, guard
    from mjxdiff.sweep import exit_code, sweep

    why = compat.gate(options.allow_untested_versions)
    if why:
        raise OptionsError(why)

    try:
        entries = _entries(options)
        base = (baseline.load(options.baseline, None if options.no_history else options.history)
                if options.baseline else None)
    except (known.KnownError, baseline.BaselineError) as e:
        raise OptionsError(str(e)) from e
    if options.impl in ("warp", "both"):
        from mjxdiff import mjwarp

        why = mjwarp.available()
        if why:
            raise OptionsError(f"--impl {options.impl}: {why}")
    engines.configure_jax(options.precision, options.cache_dir)
    config = sweep_config(options)
    limits = guard.Limits(options.max_memory or guard.default_memory(), options.budget, options.sweep_budget)
    scenarios, bad = _scenarios(options)

    t0 = time.perf_counter()
    cache_before = export_cache.events()
    results = list(bad)
    for suffix, change in _PAIRS[options.impl]:
        if change.get("impl") == "warp" and "reproducers" not in change and config.reproducers:
            change = dict(change, reproducers=str(Path(config.reproducers) / "warp"))
        pair_config = dataclasses.replace(config, **change)

        def arrived(r: ScenarioResult, suffix: str = suffix) -> None:
            if on_result is not None:
                r = dataclasses.replace(r, name=r.name + suffix)
                on_result(r, known.match(report.result_dict(r), entries))
        if options.isolate:
            swept = guard.sweep(scenarios, pair_config, limits, options.progress, arrived, options.cache_dir)
        else:
            swept = sweep(scenarios, pair_config, options.progress, arrived)
        # a scenario's name seeds its inputs: the pair's results are renamed after the sweep
        results += [dataclasses.replace(r, name=r.name + suffix) for r in swept]
    seconds = time.perf_counter() - t0

    doc = report.to_json(results, dict(options.as_config(), seconds=seconds, mjx_compiles=engines.compile_count()))
    doc["code"]["cache"] = export_cache.events_since(cache_before)
    accepted = set()
    for sc in doc["scenarios"]:
        entry = known.match(sc, entries)
        if entry:
            sc["known"] = dataclasses.asdict(entry)
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
    from mjxdiff import history

    return Path(options.history) if options.history else history.default_dir()


def _read_history(out: SweepRun) -> None:
    """Flags the run's anomalies against the history (``doc["history"]``). A history that cannot
    be read is a warning: the verdicts stand."""
    if out.options.no_history:
        return
    from mjxdiff import history

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
    from mjxdiff import history

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
            from mjxdiff import html_report

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
