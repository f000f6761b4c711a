"""The sweep's own commands: ``sweep``, ``replay``, ``merge``, ``list``, ``known``, ``history``,
``cache``: each a function adding its parser and one running it."""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time

from mjxdiff.cli.args import DESCRIPTION, DESCRIPTIONS, SHARED, selected, shared


_SWEEP_EPILOG = """\
examples:
  python -m mjxdiff sweep                       # every bundled scenario
  python -m mjxdiff sweep pendulum ant --quick  # two scenarios, small smoke run
  python -m mjxdiff sweep my_robot.xml          # your own MJCF, default randomization
  python -m mjxdiff sweep --out results --format json

statuses: PASS within tolerance; FAIL a field left its tolerance, or MJX went
non-finite where MuJoCo C did not (the line names field, object, step and time,
and the likely cause); UNSUP MJX refused the model (feature named; try
--drop-unsupported for collision pairs); ERROR an engine crashed, or MuJoCo C
itself blew up (an unstable scenario); INPUT the scenario could not be read.
A line ending in [adjusted: ...] ran a model mjxdiff changed so that MJX could
run it (e.g. the energy flag disabled); --no-adjust turns that off.

sharp checks (the indented 'checks:' line): every scenario is also stepped
once from C's own states with a converged solver in both engines (one-step),
bounded by C's rounding, so chaos cannot hide a bug; where your solver settings
do not converge (e.g. iterations=1) both engines also run converged (the
converged twin), judged sharply. 'weak' marks a pass whose bound exceeds 1% of
the field's own scale: it could not have seen a bug that small.
FAIL [known: solver-truncation]: your solver settings part MJX and C (the
rollouts differ beyond tolerance, covered only by C's own freedom under the same
settings), while the converged twin and the one-step check agree; it is not an
MJX bug, but the trajectories do differ by what the line says.

limits: before compiling, each scenario's MJX cost is estimated from its
collision pairs and solver ('MJX: compile ~3 min (...), ~300 MB per member');
the horizon, then the batch, shrink to fit --budget (600 s per scenario) and
the members stepped at once to fit --max-memory (85% of the memory available).
A scenario that still cannot fit, or runs past a limit (the sweep runs in a
watched child process: even an XLA compile is stopped), is an ERROR that says
how far it got and what to do; the report is written and the sweep goes on.

exit codes: 0 consistent; 1 a divergence (any FAIL, solver truncation included)
or an engine error; 2 bad usage or input. With --fail-on new, failures that an
accepted known entry explains (solver-truncation, or your --known entries with
accepted = true) and, with --baseline, failures the baseline already had, exit 0."""


def sweep_parser(sub) -> argparse.ArgumentParser:
    from mjxdiff.input import options

    sw = sub.add_parser("sweep", help="compare MJX with MuJoCo C on scenarios",
                        description=DESCRIPTION, epilog=_SWEEP_EPILOG,
                        formatter_class=argparse.RawDescriptionHelpFormatter)
    options.add_arguments(sw)  # one flag per field of SweepOptions, declared once
    return sw


def replay_parser(sub) -> argparse.ArgumentParser:
    rp = sub.add_parser("replay", help="re-run a saved reproducer of a failing scenario member",
                        description=DESCRIPTIONS["replay"])
    rp.add_argument("file", metavar="FILE", help="reproducer .json")
    shared(rp, "format", "cache_dir")
    return rp


def history_parser(sub) -> argparse.ArgumentParser:
    hi = sub.add_parser("history", help="query the run history sweeps append to (DuckDB over Parquet)",
                        description=DESCRIPTIONS["history"])
    hi.add_argument("--history", "--dir", dest="history", metavar="DIR", help=SHARED["history"][1]["help"] +
                    "; --dir is the older name")
    hi.add_argument("--scenario", metavar="S", help="only this scenario")
    hi.add_argument("--field", metavar="F", help="only this field (qpos, qvel, act, sensordata, contacts, ...)")
    hi.add_argument("--since", metavar="WHEN", type=_since,
                    help="only runs since WHEN: an ISO date or time (2026-11-01, 2026-11-01T12:00) or an age "
                         "(7d, 12h, 30m)")
    view = hi.add_mutually_exclusive_group()
    view.add_argument("--by-version", action="store_true", help="compare runs by MuJoCo/MJX version and code digest")
    view.add_argument("--runs", action="store_true", help="list the runs (id, time, versions, passes, failures)")
    shared(hi, "format")
    return hi


def cache_parser(sub) -> argparse.ArgumentParser:
    ca = sub.add_parser("cache", help="check the cache of traced MJX rollouts against the code loaded now",
                        description=DESCRIPTIONS["cache"],
                        formatter_class=argparse.RawDescriptionHelpFormatter,
                        epilog="examples:\n  python -m mjxdiff cache check\n"
                               "  python -m mjxdiff cache check --fix --cache-dir .jax_cache")
    ca.add_argument("action", choices=("check",), help="what to do (check)")
    ca.add_argument("--fix", action="store_true",
                    help="remove what cannot be trusted: every artifact of an ambiguous key, unreadable ones, "
                         "orphaned files, older formats")
    shared(ca, "cache_dir", cache_dir="the cache to check (default $MJXDIFF_CACHE or ~/.cache/mjxdiff/jax, as sweep)")
    shared(ca, "format")
    return ca


def list_parser(sub) -> argparse.ArgumentParser:
    return sub.add_parser("list", help="list bundled scenarios and what each exercises",
                   description="List bundled scenarios with their model, size and what they exercise.")


def known_parser(sub) -> argparse.ArgumentParser:
    kn = sub.add_parser("known", help="list the known-divergence catalogue: each entry, its kind and its bug bundle",
                        description=DESCRIPTIONS["known"])
    kn.add_argument("--list", action="store_true", help="list every entry (what 'known' does; the flag says so)")
    kn.add_argument("--known", metavar="FILE", help="your own entries ([[known]] tables), listed first, as a sweep "
                                                  "tries them")
    return kn


def cmd_known(args: argparse.Namespace) -> int:
    from mjxdiff.compare import known

    try:
        entries = known.entries(args.known)
    except known.KnownError as e:
        print(f"mjxdiff known: error: {e}", file=sys.stderr)
        return 2
    for e in entries:
        print(f"{e.id:<42} {e.kind:<13} {e.title}")
        print(f"{'':<42} what to do: {known.advice(e)}")
        print(f"{'':<42} bundle: {e.bundle or 'none: not an MJX bug'}")
    kinds = [e.kind for e in entries]
    print(f"{len(entries)} entries: " + ", ".join(f"{kinds.count(k)} {k}" for k in dict.fromkeys(kinds)))
    return 0


def cmd_list(args: argparse.Namespace) -> int:
    scenarios = selected(())
    if scenarios is None:
        return 2
    for s in scenarios:
        print(f"{s.name:<28} batch {s.batch:>3} x {s.steps:>4} steps  {s.description}")
        if s.exercises:
            print(f"{'':<28} exercises: {', '.join(s.exercises)}")
    return 0


def cmd_sweep(args: argparse.Namespace) -> int:
    from mjxdiff.output import baseline, report
    from mjxdiff.compare import known
    from mjxdiff.runner import pipeline

    options = pipeline.SweepOptions(**{f.name: getattr(args, f.name) for f in dataclasses.fields(pipeline.SweepOptions)
                                       if f.name != "scenarios"}, scenarios=tuple(args.scenarios))
    text = args.format == "text"

    def show(r, entry) -> None:
        if text:
            print(report.format_line(r) + (f" [known: {entry.id}]\n{'':<6} {'':<28} what to do: {known.advice(entry)}"
                                           if entry else ""), flush=True)
    try:
        run = pipeline.compute(options, show)
    except pipeline.OptionsError as e:
        print(f"mjxdiff: error: {e}", file=sys.stderr)
        return 2
    for message in run.input_errors:
        print(f"mjxdiff: error: {message}", file=sys.stderr)
    if text:
        print(report.format_cache(run.doc["code"]["cache"]), file=sys.stderr)
        for a in run.anomalies:
            print(f"ANOMALY {a['message']}", flush=True)
        if run.changes is not None:
            print(baseline.format_text(run.changes, args.baseline))
    t = time.perf_counter()
    files = pipeline.write(run)
    written = time.perf_counter() - t
    for warning in run.warnings:
        print(f"mjxdiff: warning: {warning}", file=sys.stderr)
    for kind, name in (("report", "report"), ("page", "page")):
        if kind in files:
            print(f"{name} written to {files[kind]}", file=sys.stderr)
    if text:
        print(f"{report.format_timing(run.doc['timing'])}; writing {written:.1f} s", file=sys.stderr)
        print(report.format_text(run.results, args.threshold, run.seconds).splitlines()[-1])
    else:
        print(json.dumps(run.doc, indent=2))
    return run.exit_code


def merge_parser(sub) -> argparse.ArgumentParser:
    mg = sub.add_parser("merge", help="join the --out directories of a sweep's shards (or resumed runs) into "
                                      "one report", description=DESCRIPTIONS["merge"])
    mg.add_argument("out", metavar="OUT", help="directory of the merged report.json, report.html and journal")
    mg.add_argument("dirs", nargs="+", metavar="DIR", help="--out directories of 'mjxdiff sweep --shard I/N' runs")
    shared(mg, "format")
    return mg


def cmd_merge(args: argparse.Namespace) -> int:
    from mjxdiff.runner import pipeline
    from mjxdiff.output import report

    try:
        run = pipeline.merge(args.out, args.dirs)
    except pipeline.OptionsError as e:
        print(f"mjxdiff: error: {e}", file=sys.stderr)
        return 2
    pipeline.write(run)
    book = run.doc["journal"]
    for name in book["nondeterministic"]:
        print(f"NONDETERMINISTIC {name}: its records disagree (status or worst errors)", flush=True)
    if book["missing"]:
        print(f"MISSING {len(book['missing'])} of {book['units']} units: no directory holds them "
              f"(canonical indices {book['missing'][:10]})", flush=True)
    for warning in run.warnings:
        print(f"mjxdiff: warning: {warning}", file=sys.stderr)
    if args.format == "json":
        print(json.dumps(run.doc, indent=2))
    else:
        for r in run.results:
            print(report.format_line(r))
        print(report.format_text(run.results, run.options.threshold, run.seconds).splitlines()[-1])
    return run.exit_code


def cmd_replay(args: argparse.Namespace) -> int:
    from mjxdiff.engine import engines
    from mjxdiff.output import report, reproducer
    from mjxdiff.input.scenario import ScenarioError
    from mjxdiff.runner.sweep import SweepConfig, exit_code, run_inputs

    try:
        rep = reproducer.load_any(args.file)  # checks everything replay reads below
    except ScenarioError as e:
        print(f"mjxdiff: error: {' '.join(str(e).split())}", file=sys.stderr)
        return 2
    if isinstance(rep, reproducer.GradReproducer):
        return _replay_grad(rep, args.format)
    saved = {k: v for k, v in rep.config.items() if k in SweepConfig.__dataclass_fields__}
    config = SweepConfig(**{**saved, "reproducers": None})
    engines.configure_jax(config.precision, args.cache_dir)
    result = run_inputs(rep.scenario, rep.model, rep.inputs, rep.tolerances, config)
    doc = report.result_dict(result)
    then = rep.verdict.get("first_divergence") or {}
    now = doc.get("first_divergence") or {}
    same = (doc["status"] == rep.verdict["status"]
            and all(then.get(k) == now.get(k) for k in ("field", "step", "object")))
    _print_replay(args.format, rep, doc, same,
                  f"replaying {rep.scenario} member {rep.member} (seed {rep.inputs.seed}, {config.precision}",
                  report.format_line(result), "same status, field, object and step as saved",
                  f"saved {rep.verdict['status']} {then}, now {doc['status']} {now}")
    return exit_code([result])


def _print_replay(fmt: str, rep, replayed: dict, same: bool, header: str, line: str, kept: str, lost: str) -> None:
    """Print a replay: the JSON document, or the header, the replayed verdict's line and whether
    it reproduced (``kept`` / ``lost`` say how)."""
    if fmt == "json":
        print(json.dumps(dict(reproduced=same, saved=rep.verdict, replayed=replayed), indent=2))
        return
    print(f"{header}, saved with mujoco {rep.versions.get('mujoco')}, mjx {rep.versions.get('mujoco-mjx')})")
    print(line)
    print(f"reproduced: {kept}" if same else f"NOT reproduced: {lost}")


def _replay_grad(rep, fmt: str) -> int:
    from mjxdiff.engine import engines
    from mjxdiff.tools import grad

    engines.configure_jax("float64", None)
    r, same = grad.replay(rep)
    _print_replay(fmt, rep, dataclasses.asdict(r), same,
                  f"replaying the Jacobians of {rep.scenario} at state {rep.index} (float64",
                  grad.format_state(r), "same status and worst entry as saved", f"saved {json.dumps(rep.verdict)}")
    return 1 if r.status == "fail" else 0


def _since(text: str):
    import datetime as dt
    import re

    m = re.fullmatch(r"(\d+(?:\.\d+)?)([dhm])", text.strip())
    if m:
        unit = {"d": "days", "h": "hours", "m": "minutes"}[m.group(2)]
        return dt.datetime.now(dt.timezone.utc).replace(tzinfo=None) - dt.timedelta(**{unit: float(m.group(1))})
    try:
        return dt.datetime.fromisoformat(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a date, time or age: {text!r} (e.g. 2026-11-01 or 7d)") from None


def cmd_history(args: argparse.Namespace) -> int:
    from mjxdiff.output import history

    h = history.open_history(args.history)
    for name in h.skipped:
        print(f"mjxdiff history: warning: {name} cannot be read; skipped", file=sys.stderr)
    if args.runs:
        where, params = history._filters(args.scenario, args.field, args.since)  # noqa: SLF001
        rows = h.sql(f"""SELECT run_id, min(time) AS time, any_value(mujoco) AS mujoco, any_value(mjx) AS mjx,
                                any_value(mjx_digest) AS mjx_digest, any_value(seed) AS seed,
                                count(DISTINCT CASE WHEN status = 'pass' THEN scenario END) AS passed,
                                count(DISTINCT CASE WHEN status = 'fail' THEN scenario END) AS failed
                         FROM history {where} GROUP BY run_id ORDER BY time""", params)
    elif args.by_version:
        rows = h.by_version(args.scenario, args.field, args.since)
    else:
        rows = h.trends(args.scenario, args.field, args.since)
    if args.format == "json":
        print(json.dumps(dict(dir=str(h.directory), runs=h.runs, rows=rows), indent=2, default=str))
        return 0
    print(f"{h.runs} runs in {h.directory}")
    if rows:
        keys = list(rows[0])
        text = [[f"{v:.3g}" if isinstance(v, float) else str(v)[:19] for v in r.values()] for r in rows]
        widths = [max(len(k), *(len(t[i]) for t in text)) for i, k in enumerate(keys)]
        print("  ".join(k.ljust(w) for k, w in zip(keys, widths)))
        for t in text:
            print("  ".join(v.ljust(w) for v, w in zip(t, widths)))
    return 0


def cmd_cache(args: argparse.Namespace) -> int:
    from mjxdiff.engine import engines, export_cache

    if args.cache_dir == "":
        print("mjxdiff: error: --cache-dir '' means no cache: nothing to check", file=sys.stderr)
        return 2
    engines.configure_jax("float64", args.cache_dir)
    root = export_cache.export_dir()
    if root is None or not root.is_dir():
        print(f"mjxdiff: error: no saved MJX rollouts at {root} (a sweep with this --cache-dir makes them)",
              file=sys.stderr)
        return 2
    found = export_cache.check(root, fix=args.fix)
    untrusted = sum(len(found[k]) for k in ("ambiguous", "unreadable", "orphans", "old_format"))
    if args.format == "json":
        print(json.dumps(found, indent=2))
    else:
        print(f"cache {found['root']}: {found['artifacts']} artifacts of {found['structures']} model structures, "
              f"{found['bytes'] / 2**20:.1f} MiB")
        print(f"  {found['matching']} match the code loaded now, {found['other_code']} belong to other code (kept)")
        for kind, what in (("ambiguous", "ambiguous (several match one key: a sweep loads none)"),
                           ("unreadable", "unreadable"), ("orphans", "orphaned files (no pair, interrupted writes)"),
                           ("old_format", "directories of an older format")):
            print(f"  {len(found[kind])} {what}" + "".join(f"\n    {p}" for p in found[kind][:10]))
        for key, st in sorted(found["per_structure"].items(), key=lambda kv: -kv[1]["bytes"])[:10]:
            print(f"  {key[:16]}  {st['artifacts']} artifacts, {st['matching']} matching, "
                  f"{st['bytes'] / 2**20:.2f} MiB")
        if args.fix:
            print(f"removed {found['removed']} untrusted entries")
        elif untrusted:
            print("run 'mjxdiff cache check --fix' to remove what cannot be trusted")
    return 0 if args.fix or not untrusted else 1
