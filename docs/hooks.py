"""MkDocs hooks: the pages generated from the code at build time, so they cannot go stale.

- ``reference/cli.md``: every subcommand of ``python -m mjxdiff`` and every option, from the
  argparse parser (:func:`mjxdiff.cli.build_parser`).
- ``reference/known-divergences.md``: every entry of the known-divergence catalogue
  (:data:`mjxdiff.compare.support.CATALOGUE`), with its evidence and its bug bundle's reproducer.
- ``reference/json-schemas.md``: the envelope's keys and the kinds of JSON output
  (:data:`mjxdiff.output.report.ENVELOPE`, :data:`mjxdiff.output.report.KINDS`).
- ``index.md``: the margin of each bundled scenario's pass over many seeds, from
  ``docs/data/margins.json`` (written by ``benchmarks/scripts/margins.py``).

A page holds a marker (``<!-- mjxdiff:cli -->``, ``<!-- mjxdiff:catalogue -->``, ...) that
:func:`on_page_markdown` replaces. ``tests/test_docs.py`` imports this file and calls the same
functions, so a flag or an entry that the pages would miss fails a test.
"""

from __future__ import annotations

import argparse
import html
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

#: The public modules (``mjxdiff/__init__.py``'s curated names and the modules its users import
#: by path), each with a page ``reference/api/<name>.md``.
EXTRA_PUBLIC_MODULES = ("output.report", "tools.strategies", "testing")


def public_modules() -> list[str]:
    """The public modules' names under ``mjxdiff.`` (``metrics``, ``runner.pipeline``, ...): those that
    ``mjxdiff/__init__.py`` exports a name from or exports whole, plus
    :data:`EXTRA_PUBLIC_MODULES`; sorted."""
    import mjxdiff

    moved = mjxdiff._MOVED  # noqa: SLF001
    names = {(module or f"mjxdiff.{moved[name]}.{name}" if name in moved else module or f"mjxdiff.{name}")
             .removeprefix("mjxdiff.") for name, module in mjxdiff._PUBLIC.items()}  # noqa: SLF001
    return sorted(names | set(EXTRA_PUBLIC_MODULES))


# -- the CLI page ---------------------------------------------------------------------------------

def _cell(text: str) -> str:
    """``text`` safe inside a Markdown table cell: one line, pipes and angle brackets escaped."""
    return html.escape(" ".join(text.split())).replace("|", "\\|")


def _subcommands(parser: argparse.ArgumentParser) -> dict[str, tuple[str, argparse.ArgumentParser]]:
    """Subcommand name -> (its one-line help, its parser), in the parser's order."""
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))  # noqa: SLF001
    helps = {c.dest: c.help or "" for c in action._choices_actions}  # noqa: SLF001
    return {name: (helps.get(name, ""), sub) for name, sub in action.choices.items()}


def _option_row(parser: argparse.ArgumentParser, action: argparse.Action) -> str:
    """One table row: the option strings (or the positional's name), its value, default, help."""
    formatter = parser._get_formatter()  # noqa: SLF001
    names = ", ".join(f"`{s}`" for s in action.option_strings) or f"`{action.metavar or action.dest}`"
    if action.nargs == 0:
        value = ""
    else:
        metavar = formatter._format_args(action, action.dest.upper())  # noqa: SLF001
        value = f"`{metavar}`" if metavar else ""
    if action.choices is not None and not isinstance(action.choices, dict):
        value += " (one of " + ", ".join(f"`{c}`" for c in action.choices) + ")"
    default = action.default
    shown = "" if default in (None, False, argparse.SUPPRESS) or action.nargs == 0 else f"`{default}`"
    helptext = formatter._expand_help(action) if action.help else ""  # noqa: SLF001
    return f"| {names} | {value} | {shown} | {_cell(helptext)} |"


def cli_command_markdown(name: str, summary: str, sub: argparse.ArgumentParser) -> str:
    """The section of one subcommand: its summary, usage, every argument as a table row, and
    its description and examples as ``--help`` prints them."""
    rows = [_option_row(sub, a) for a in sub._actions if a.help != argparse.SUPPRESS]  # noqa: SLF001
    usage = sub.format_usage().removeprefix("usage: ").rstrip("\n")
    parts = [f"## `mjxdiff {name}`", "", f"{summary[:1].upper()}{summary[1:]}.", "",
             "```text", *usage.splitlines(), "```", "",
             "| argument | value | default | what it does |", "|---|---|---|---|", *rows, ""]
    text = "\n".join(x for x in (sub.description, sub.epilog) if x)
    if text:
        parts += ["??? note \"`--help` text\"", "", "    ```text",
                  *("    " + line for line in text.splitlines()), "    ```", ""]
    return "\n".join(parts)


def cli_markdown() -> str:
    """The whole CLI reference: an overview table, then one section per subcommand."""
    from mjxdiff.cli import build_parser

    parser = build_parser()
    commands = _subcommands(parser)
    overview = ["| command | what it does |", "|---|---|",
                *(f"| [`{name}`](#mjxdiff-{name}) | {_cell(summary)} |" for name, (summary, _) in commands.items())]
    sections = [cli_command_markdown(name, summary, sub) for name, (summary, sub) in commands.items()]
    return "\n".join(overview) + "\n\n" + "\n".join(sections)


# -- the catalogue page ---------------------------------------------------------------------------

#: The heading of each kind of entry.
KIND_HEADINGS = {"approximation": "Approximations", "bug": "MJX bugs", "fixed": "Bugs of older releases (fixed)"}

def _matching(entry) -> str:
    """What a failing scenario must show to get the entry's label, as one sentence."""
    rules = [f"{label} `{value}`" for label, value in (
        ("first stage", entry.stage), ("first field", entry.field), ("contact pair", entry.pair),
        ("contacts differ in", entry.part), ("first element", entry.element), ("message matches", entry.pattern),
        ("cause", entry.cause), ("scenario matches", entry.scenario)) if value]
    if entry.integrator:
        rules.append("integrator " + " or ".join(f"`{i}`" for i in entry.integrator))
    if entry.only_on:
        rules.append("MJX release " + ", ".join(f"`{v}*`" for v in entry.only_on))
    if getattr(entry, "impl", ()):
        rules.append("implementation under test " + " or ".join(f"`{i}`" for i in entry.impl))
    if getattr(entry, "feature", None):
        rules.append(f"the model has `{entry.feature}`")
    return "; ".join(rules) or "never by itself"


def _bundle_markdown(entry) -> list[str]:
    """The entry's bug bundle: where it is, how to run it, its model and repro.py inline (the
    reader can copy both and run them with only ``mujoco`` and ``mujoco-mjx``)."""
    if not entry.bundle.startswith("tests/"):
        return [f"- **Reproducer**: {entry.bundle or 'none'}"]
    if "::" in entry.bundle:  # a MuJoCo Warp bug: its reproducer is a strict xfail of the suite
        return [f"- **Reproducer**: the test `{entry.bundle}` (a strict xfail while MuJoCo Warp and C differ; "
                f"`pytest {entry.bundle}`)"]
    directory = ROOT / entry.bundle
    lines = [f"- **Reproducer**: the bundle `{entry.bundle}/` (`python {entry.bundle}/repro.py` exits 1 while "
             "MJX and C differ)", ""]
    for name, lang in (("README.md", "markdown"), ("model.xml", "xml"), ("repro.py", "python")):
        path = directory / name
        if path.is_file():
            body = path.read_text().rstrip("\n").splitlines()
            lines += [f"??? example \"{name}\"", "", f"    ```{lang}", *("    " + b for b in body), "    ```", ""]
    return lines


def catalogue_entry_markdown(entry) -> str:
    """One catalogue entry: its id as a heading (the anchor users link to), title, kind,
    releases, matching rule, evidence, what to do and reproducer."""
    from mjxdiff.compare.known import advice

    accepted = " (accepted: `--fail-on new` lets it pass)" if entry.accepted else ""
    return "\n".join([
        f"#### `{entry.id}`", "", f"**{_cell(entry.title)}**", "",
        f"- **Kind**: {entry.kind}{accepted}",
        "- **Seen in MJX**: " + ", ".join(entry.versions),
        f"- **Matched when**: {_matching(entry) if getattr(entry, 'labels', True) else 'never: it labels no report'}",
        f"- **Evidence**: {_cell(entry.evidence)}",
        f"- **What to do**: {_cell(advice(entry))}",
        *_bundle_markdown(entry), ""])


def catalogue_markdown() -> str:
    """Every catalogue entry, grouped by kind, then the features the fuzzer leaves out."""
    from mjxdiff.compare.support import CATALOGUE, KNOWN_DIVERGENCES

    kinds = list(dict.fromkeys(e.kind for e in CATALOGUE))
    summary = ["| id | kind | title |", "|---|---|---|",
               *(f"| [`{e.id}`](#{e.id.replace('.', '')}) | {e.kind} | {_cell(e.title)} |" for e in CATALOGUE)]
    parts = ["\n".join(summary), ""]
    for kind in kinds:
        parts += [f"### {KIND_HEADINGS.get(kind, kind)}", ""]
        parts += [catalogue_entry_markdown(e) for e in CATALOGUE if e.kind == kind]
    parts += ["### Left out of generated models", "",
              "`mjxdiff fuzz` leaves these features out unless `--include-known` "
              "(`mjxdiff.compare.support.KNOWN_DIVERGENCES`):", "",
              "| feature | why |", "|---|---|",
              *(f"| {_cell(k)} | {_cell(v)} |" for k, v in KNOWN_DIVERGENCES.items()), ""]
    return "\n".join(parts)


# -- the JSON envelope ---------------------------------------------------------------------------

def envelope_markdown() -> str:
    """The keys every JSON output begins with (:data:`mjxdiff.output.report.ENVELOPE`) and the kinds
    of output with their files (:data:`mjxdiff.output.report.KINDS`), from the code."""
    from mjxdiff.output.report import ENVELOPE, KINDS, SCHEMA_VERSION

    what = {"kind": "the kind of output, below",
            "schema_version": f"{SCHEMA_VERSION} (bumped when a key changes meaning or disappears)",
            "versions": "python, mjxdiff, jax, jaxlib, mujoco, mujoco-mjx, numpy",
            "code": "SHA-256 digests of the MJX code tested (`mjx`) and of everything a compiled rollout depends "
                    "on (`rollout`)",
            "machine": "cores and the host devices MJX's batch is split over",
            "config": "what the run was asked (a sweep: every flag)",
            "seed": "the config's seed (null where there is none)"}
    rows = ["| key | what |", "|---|---|", *(f"| `{k}` | {what.get(k, '')} |" for k in ENVELOPE), "",
            "| kind | written to |", "|---|---|", *(f"| `{k}` | `{v}` |" for k, v in KINDS.items())]
    return "\n".join(rows) + "\n"


# -- the margin of each pass over seeds ----------------------------------------------------------

def margins_markdown() -> str:
    """The table of ``docs/data/margins.json`` (``benchmarks/scripts/margins.py``): per bundled
    scenario and check, the worst ratio to its bound over the seeds swept."""
    import json

    data = json.loads((ROOT / "docs" / "data" / "margins.json").read_text())
    first, end = data["seeds"]
    rows = [f"Unmodified MJX, seeds {first} to {end - 1}{' (--quick)' if data['quick'] else ''}: "
            f"{len(data['failures'])} failure(s); per-sweep false-alarm estimate "
            f"{data['per_sweep_false_alarm']:.1e}.", "",
            "| scenario | check | seeds | differing | median | 99th percentile | max | P(ratio >= 1) per draw |",
            "|---|---|---|---|---|---|---|---|"]
    for key, r in sorted(data["rows"].items()):
        name, check = key.rsplit(" ", 1)
        rows.append(f"| {name} | {check} | {r['seeds']} | {r.get('differing', '')} | {r['median']:.2g} "
                    f"| {r['p99']:.2g} | {r['max']:.2g} | {r['p_exceed']:.1e} |")
    rows += ["", *(f"Measured: {run}" for run in data.get("runs", []))]
    return "\n".join(rows) + "\n"


# -- the hook -------------------------------------------------------------------------------------

MARKERS = {"<!-- mjxdiff:cli -->": cli_markdown, "<!-- mjxdiff:catalogue -->": catalogue_markdown,
           "<!-- mjxdiff:envelope -->": envelope_markdown, "<!-- mjxdiff:margins -->": margins_markdown}


def on_page_markdown(markdown: str, **_) -> str:
    """MkDocs hook: replaces each marker in a page by its generated Markdown."""
    for marker, generate in MARKERS.items():
        if marker in markdown:
            markdown = markdown.replace(marker, generate())
    return markdown
