"""``python -m mjxdiff``: sweep scenarios, replay a failure, fuzz, benchmark, list scenarios.

Exit codes: 0 every scenario consistent (unsupported ones are reported, not
failing), 1 at least one divergence (fail, solver truncation included, or a
non-finite rollout), 2 bad usage or input; ``sweep --fail-on new`` exits 0 on
failures an accepted known entry explains.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path
from typing import Any, Sequence

from mjxdiff.errors import one_line

__all__ = ["main"]

_DESCRIPTION = """\
mjxdiff: does MuJoCo MJX behave like MuJoCo C? It rolls out batches of
randomized variants of each scenario in both engines (MJX: jit+vmap+scan on
the CPU; C: mujoco.batch on all cores), compares qpos, qvel, act, sensors and
contact counts step by step, and prints one verdict per scenario."""

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


_BENCH_DEFAULT = ("pendulum", "cartpole", "ant")
#: The long descriptions of the subcommands (``--help``; argparse refills the lines).
_DESCRIPTIONS = {
    "scale": """\
Predict how a sweep would scale over more nodes, from the per-unit seconds its journal measured
(DIR/journal.jsonl of 'mjxdiff sweep --out DIR'; a Ray run measures each task on its worker):
units start longest first, each on the worker that frees first, node count x (CPUs per node //
CPUs per scenario) workers, plus --per-task seconds per unit and --fixed seconds once. No
schedule beats the longest unit: the table says which it is and where the speed-up levels off.""",
    "shrink": """\
Shrink a model that diverges to a minimal MJCF that still shows the same divergence, for a bug
report upstream can act on. The state: the first one of C's rollout (from --keyframe, or qpos0 at
rest, zero controls; or a reproducer's member with its controls) at which MJX's forward or one
converged step differs from C's, or C's contacts are lost through mjx.put_data and get_data.
Delta debugging then drops bodies, joints (welded where the state
holds them), geoms, sites, actuators, sensors, tendons, equality constraints, pairs, excludes and
keyframes, resets options and flags to MuJoCo's defaults and rounds the state, keeping each edit
only while C compiles the model and the same signature shows: the same check (forward, step or transfer),
first stage, first field and contact geom types. Deterministic; Ctrl-C or --budget stops it with
the best so far. Writes OUT/model.xml and OUT/state.json; --bundle adds repro.py (standalone:
mujoco and mujoco-mjx only), signature.json and README.md. Exit 0 when shrunk, 2 on bad input or
a model that shows no divergence.""",
    "known": """\
List the catalogue of known C/MJX divergences a sweep labels failures with ('known: ID'): each
entry's id, kind and title, and for an MJX bug its bundle, a minimal model with a standalone
repro.py made by 'mjxdiff shrink --bundle' (a directory of the mjxdiff repository). Kinds:
approximation (MJX computes it another way on purpose, or a setting such as a capped solver parts
the engines), bug (wrong in the MJX release measured), fixed (a bug of older releases only).""",
    "merge": """\
Join the --out directories of a sweep's shards ('mjxdiff sweep --shard I/N --out DIR'), or of
resumed runs, into one report: every unit's verdict from the directories' journal.jsonl, in the
sweep's order, then the known labels, history and exit code as one sweep decides them. The
result does not depend on the directories' order, and merging twice changes nothing. Exit 1 on
a divergence, on a unit no directory holds (missing), or on one whose records disagree
(nondeterministic: itself a finding); 2 when the directories are shards of different sweeps.""",
    "versions": """\
Answer "is it safe to upgrade MJX?" and "since which release does this divergence exist?": for
each MJX release given, make (or reuse) an isolated environment, a venv with that MJX, its MuJoCo
and a JAX, installed by pip from the package index, with this mjxdiff linked in; run the same
sweep in each; print one table, scenario x version, with status, worst ratio to the bound, first
step out and known-divergence label, each cell marked where it changed since the previous
version. Each version's report.json, and its run in one history (see 'mjxdiff history
--by-version'), stay under --out. A version that cannot be installed or swept is one error line;
the others still run. A target with +coreC changes only the reference: the same MJX judged
against another MuJoCo C (3.17.0 3.17.0+core4.0.1: a verdict that changes between them was C's).
Exit 0 when every version ran and no scenario failed outside the known divergences, else 1; 2
bad input.""",
    "replay": """\
Re-run a reproducer file (written under DIR/reproducers/ by 'sweep --out DIR' for each failing
scenario, or by 'grad --out DIR' for a state whose Jacobians disagree) and print its diagnosis. Exit
1 if it still diverges, 0 if it now passes, 2 if the file is bad.""",
    "fuzz": """\
Generate MJX-supported models, initial states and controls with Hypothesis, compare MJX with MuJoCo
C on each (as 'sweep' does), and shrink a divergence to a minimal MJCF. The shrunk model is printed
and, with --out, saved as a reproducer for 'mjxdiff replay'. Found failures are kept in Hypothesis's
example database and tried first next time. Exit 0 none found, 1 found, 2 the harness itself failed
(traceback shown and, with --out, in DIR/fuzz-report.json).""",
    "policy": """\
Drive the same environment with the same policy, initial states and policy keys on MJX (vmapped
episodes, the policy inside the scan), on MuJoCo C (a mujoco.batch.Batch, the policy jitted over the
batch of C observations each control step) and on C again from initial states moved by a few units
of roundoff (C's own closed-loop floor; also with a converged solver where the model has
constraints), all in float64, streamed 50 control steps at a time. Episodes are compared paired:
return, length, termination and behaviour statistics (mean |action|, |Δaction|, |qvel|, the
environment's metrics); FAIL when the 95%% bootstrap CI of a mean gap lies outside C's own band,
lengths differ more often than C against itself, or the states separate beyond 10x C's own
separation. Names the first such control step, the stage that differs first there and its cause (one
control step from C's state under ablations). Exit 0 pass, 1 fail, 2 bad input.""",
    "coverage": """\
Trace MJX (put_model, make_data, one mjx.step) for every scenario under coverage.py and report line
and branch coverage of mujoco/mjx/_src per module, the functions never traced, which floating-point
model fields and options some member of some scenario moves away from MuJoCo's default, and which
pairs of the conditions MJX branches on (options and flags, actuator, sensor, tendon, equality and
limit attributes, controls outside their range, limits and deadbands reached;
mjxdiff.tools.interactions.GROUPS) some member holds together, with the pairs not covered and those no
model can hold (and why). MuJoCo C steps the members for the state-dependent conditions; MJX is
traced, not compiled. 'mjxdiff fuzz' reports the same pairs for what it generated. --out DIR writes
DIR/coverage.json.""",
    "grad": """\
At states sampled from each scenario (initial states and states along C rollouts), compare the
transition Jacobians of one step, A = dx'/dx and B = dx'/du (x: qpos in the tangent space, qvel,
act), and the sensors' C = ds/dx and D = ds/du, from jax.jacfwd of mjx.step in float64 with
mujoco.mjd_transitionFD (centred, at 1e-6 and 1e-7). Each entry is judged against the finite
differences' own error floor (3x their change between the two steps, at least their row's, plus
roundoff) plus 1e-4 of its size. States where the constraint set changes inside the stencil, or
where MJX's own forward jumps there, are reported as non-smooth, not judged (a scenario with no
smooth state is NONSM: nothing judged). Models with constraints use a converged solver on both
sides. A failure names the worst entry (d output / d input: joints, actuators, sensors), whether it
sits in the smooth dynamics or the constraint part, and its kind from MJX's own finite differences:
'derivative only' (a gradient bug: MJX's forward agrees with C) or 'forward dynamics' (MJX's forward
has another slope). Exit 0 pass, 1 fail, 2 bad input.""",
    "history": """\
Trends per scenario and field over the runs the sweeps appended (runs, passes, median/min/max error,
the last status and ratio to bound), runs compared by MuJoCo/MJX version and MJX code digest
(--by-version), or the runs themselves (--runs). The history is a directory of Parquet files, one
per run; any DuckDB or Parquet reader can read it too.""",
    "cache": """\
Verifies every saved MJX rollout (DIR/mjxdiff-exports) against the MJX and mjxdiff code loaded now:
which artifacts this code may load, which belong to other code (kept: valid for that code), keys
where more than one matches (ambiguous: a sweep loads none of them), unreadable artifacts, files
left without their pair, directories of an older format, and bytes per model structure. Exit 0 when
everything can be trusted (or --fix removed what could not), 1 when something cannot.""",
}


_VERSIONS_EPILOG = """\
examples:
  python -m mjxdiff versions 3.9.0/0.7.2 3.17.0 --quick           # a playground pin against the newest
  python -m mjxdiff versions 3.3.5/0.7.0 3.9.0/0.7.2 3.17.0 --scenarios pendulum humanoid
  python -m mjxdiff versions 3.12.0 3.17.0 --scenarios my_robot.toml --out upgrade-check
  python -m mjxdiff versions 3.17.0 3.17.0+core4.0.1 --quick   # the same MJX against C 4.0.0 and 4.0.1

The first run of a version installs it (a minute or two, about 1 GB per environment); later runs
reuse it while mjxdiff's requirements are unchanged."""
_BENCH_DESCRIPTION = """\
Measure both platforms on the same batch, horizon and cores: steps/s of MJX and
of MuJoCo C for several batch sizes (MJX's best batch size is model-specific),
their ratio, MJX compile seconds, peak memory and CPU utilisation of each side,
the speedup of splitting MJX's batch over host devices, and how much the
verification itself (noise floor, metrics, verdict) costs on top of the two
engines. Ends with plain-language recommendations. float64 throughout."""
_BENCH_EPILOG = """\
examples:
  python -m mjxdiff bench                         # pendulum, cartpole, ant
  python -m mjxdiff bench humanoid --batch 16 64  # one scenario, two batch sizes
  python -m mjxdiff bench ant --out bench-results --format json

steps/s counts member-steps (batch x steps) per wall second, best of --repeats
warm runs. MJX splits a batch over the host CPU devices (one per core) when each
gets at least 16 members; bench then adds a one-device comparison at the best
batch. MJXDIFF_DEVICES=N (in the environment) sets the number of devices."""


class _Parser(argparse.ArgumentParser):
    """argparse with a one-line error and exit code 2, no usage dump; a mistyped flag gets the
    flag it most likely meant, and another command's flag says whose it is."""

    def parse_known_args(self, args=None, namespace=None):  # type: ignore[override]
        self._argv = list(sys.argv[1:] if args is None else args)
        return super().parse_known_args(args, namespace)

    def error(self, message: str) -> None:  # type: ignore[override]
        if message.startswith("unrecognized arguments: "):
            given = message.removeprefix("unrecognized arguments: ").split()
            command = self._command()
            message += _did_you_mean(given, self._owners(), command, self._positional_args(command))
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")

    def _commands(self) -> dict[str, argparse.ArgumentParser]:
        # argparse keeps no public list of a parser's actions
        return {name: p for a in self._actions if isinstance(a, argparse._SubParsersAction)  # noqa: SLF001
                for name, p in a.choices.items()}

    def _command(self) -> str:
        """The command this parse was for ('' for none): the first argument that names one."""
        commands = self._commands()
        return next((word for word in getattr(self, "_argv", []) if word in commands), "")

    def _owners(self) -> dict[str, list[str]]:
        """Every option string of this parser ('' as owner) and of its commands' parsers -> who has it."""
        owners: dict[str, list[str]] = {}
        for name, p in [("", self), *self._commands().items()]:
            for a in p._actions:  # noqa: SLF001
                for flag in a.option_strings:
                    owners.setdefault(flag, []).append(name)
        return owners

    def _positional_args(self, command: str) -> dict[str, str]:
        """``command``'s positional arguments: dest -> metavar."""
        p = self._commands().get(command)
        return {a.dest: str(a.metavar or a.dest) for a in (p._actions if p else [])  # noqa: SLF001
                if not a.option_strings}


def _did_you_mean(given: list[str], owners: dict[str, list[str]], command: str = "",
                  positionals: dict[str, str] | None = None) -> str:
    """A hint for the first unrecognized flag: where ``command`` takes it as a positional argument, how
    (``"; 'mjxdiff sweep' takes SCENARIO ... as arguments, without a flag"``); else ``command``'s flag
    closest to it (``"; did you mean --quick?"``); else, for another command's flag, whose it is
    (``"; --scenarios is a flag of 'mjxdiff versions'"``); else the closest flag of any command; else ''."""
    import difflib

    own = [flag for flag, who in owners.items() if command in who or "" in who]
    for word in given:
        if not word.startswith("--"):
            continue
        name = word.split("=")[0]
        dest = name.lstrip("-").replace("-", "_")
        positional = next((positionals[d] for d in (dest, dest + "s") if positionals and d in positionals), "")
        if positional:
            return f"; 'mjxdiff {command}' takes {positional} ... as arguments, without a flag"
        close = difflib.get_close_matches(name, own, n=1, cutoff=0.7)
        if close:
            return f"; did you mean {close[0]}?"
        if name in owners:
            return "; {} is a flag of {}".format(name, " and ".join(f"'mjxdiff {c}'" for c in owners[name] if c))
        close = difflib.get_close_matches(name, list(owners), n=1, cutoff=0.7)
        if close:
            return f"; did you mean {close[0]}?"
    return ""


class _Version(argparse.Action):
    """``--version``: mjxdiff's version and those of the MuJoCo, MJX and JAX installed (read from
    the installed packages' metadata: nothing is imported)."""

    def __init__(self, option_strings, dest, **kwargs):
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS,
                         help="print mjxdiff's, MuJoCo's, MJX's and JAX's versions")

    def __call__(self, parser, namespace, values, option_string=None):
        from importlib import metadata

        from mjxdiff import __version__

        def version(dist: str) -> str:
            try:
                return metadata.version(dist)
            except metadata.PackageNotFoundError:
                return "not installed"

        print(f"mjxdiff {__version__}; " + ", ".join(
            f"{dist} {version(dist)}" for dist in ("mujoco", "mujoco-mjx", "jax", "jaxlib")))
        parser.exit(0)


def _integer(text: str, least: int, kind: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a {kind} integer, got {text!r}") from None
    if value < least:
        raise argparse.ArgumentTypeError(f"expected a {kind} integer, got {text!r}")
    return value


def _positive(text: str) -> int:
    return _integer(text, 1, "positive")


def _non_negative(text: str) -> int:
    return _integer(text, 0, "non-negative")


def _fraction(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number in [0, 1], got {text!r}") from None
    if not 0 <= value <= 1:
        raise argparse.ArgumentTypeError(f"expected a number in [0, 1], got {text!r}")
    return value


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected seconds (a positive number), got {text!r}") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"expected seconds (a positive number), got {text!r}")
    return value


def _size(text: str) -> int:
    from mjxdiff.runner.guard import parse_size

    try:
        value = parse_size(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None
    if value <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive size (e.g. 12G, 800M), got {text!r}")
    return value


#: Options several commands share, each defined once (by dest); a command passes its own
#: help where the option means something more there (``_shared(p, "out", out="write DIR/x.json")``).
_SHARED: dict[str, tuple[tuple[str, ...], dict[str, Any]]] = {
    "scenarios": (("scenarios",), dict(nargs="*", metavar="SCENARIO", help="bundled scenario name, scenario .toml "
                                       "or MJCF .xml (default: every bundled scenario)")),
    "seed": (("--seed",), dict(type=int, default=0, help="seed of the randomized members (default 0)")),
    "out": (("--out",), dict(metavar="DIR", help="write the command's report under DIR")),
    "format": (("--format",), dict(choices=("text", "json"), default="text", help="stdout format (default text)")),
    "cache_dir": (("--cache-dir",), dict(metavar="DIR", help="JAX persistent compilation cache (see sweep --help)")),
    "history": (("--history",), dict(metavar="DIR", help="the run history's directory (default $MJXDIFF_HISTORY, "
                                     "else $XDG_DATA_HOME/mjxdiff/history or ~/.local/share/mjxdiff/history)")),
}


def _shared(p: argparse.ArgumentParser, *dests: str, **helps: str) -> None:
    """Adds the shared options ``dests`` (:data:`_SHARED`) to ``p``, with ``helps[dest]`` as
    the help text where given."""
    for dest in dests:
        flags, kw = _SHARED[dest]
        p.add_argument(*flags, **{**kw, **({"help": helps[dest]} if dest in helps else {})})


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="mjxdiff", description=_DESCRIPTION,
                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action=_Version)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True
    for add, handler in _COMMANDS:
        command = add(sub)
        command.set_defaults(func=handler)
        if handler not in _UNGATED:
            command.add_argument("--allow-untested-versions", action="store_true",
                                 help="run with a MuJoCo, MJX or JAX outside the supported range "
                                      f"({_supported_range()}; see 'mjxdiff versions')")
    return parser


def _supported_range() -> str:
    from mjxdiff.compat import SUPPORTED

    return ", ".join(f"{dist} {lo} to {hi}" for dist, (lo, hi) in SUPPORTED.items())


def _untested_versions(args: argparse.Namespace) -> str | None:
    """Why the installed MuJoCo, MJX or JAX may not run this command (None: it may): outside
    :data:`mjxdiff.compat.SUPPORTED` without ``--allow-untested-versions``
    (or ``MJXDIFF_ALLOW_UNTESTED_VERSIONS=1``)."""
    from mjxdiff.compat import gate

    return None if args.func in _UNGATED else gate(args.allow_untested_versions)


def _sweep_parser(sub) -> argparse.ArgumentParser:
    sw = sub.add_parser("sweep", help="compare MJX with MuJoCo C on scenarios",
                        description=_DESCRIPTION, epilog=_SWEEP_EPILOG,
                        formatter_class=argparse.RawDescriptionHelpFormatter)
    _shared(sw, "scenarios", "seed", scenarios="bundled scenario name, path to a scenario .toml, or path to any MJCF "
            ".xml (default: every bundled scenario; see 'mjxdiff list')", seed="master seed of all randomization "
            "(default 0)")
    sw.add_argument("--batch", type=_positive, help="batch members per scenario (default: the scenario's)")
    sw.add_argument("--steps", type=_positive, help="steps per rollout (default: the scenario's)")
    sw.add_argument("--precision", choices=("float64", "float32"), default="float64",
                    help="MJX precision; float64 (default) keeps rounding far below algorithmic "
                         "differences; float32 (as most users train) uses looser tolerance floors and judges "
                         "MJX against C's float32 shadow (C rounded at every step), so a landing that "
                         "rounding decides passes, said to be weak")
    sw.add_argument("--threshold", type=_fraction, default=0.95,
                    help="least fraction of batch members within tolerance for a scenario to pass (default 0.95)")
    sw.add_argument("--envelope", action=argparse.BooleanOptionalAction, default=True,
                    help="judge errors against the chaos envelope measured from C's own divergence under "
                         "rounding-level perturbations (default); --no-envelope uses fixed tolerances only")
    sw.add_argument("--noise-floor", choices=("on-demand", "always"), default="on-demand",
                    help="when C's perturbed rerun (the envelope's source) runs: on-demand (default) only for "
                         "members whose errors exceed the fixed tolerances, the only ones the envelope can "
                         "change; always: for every member, so that every report gives the envelope and noise_rate")
    sw.add_argument("--diagnose", choices=("none", "basic", "full"), default="full",
                    help="for failing scenarios: basic = re-synchronised one-step error and the first "
                         "pipeline stage that differs; full (default) = also the likely cause, from reruns "
                         "with a converged solver, no contacts, a smaller timestep, another integrator")
    sw.add_argument("--adjust", action=argparse.BooleanOptionalAction, default=True,
                    help="set aside settings MJX refuses that change nothing compared (the energy and fwdinv "
                         "flags) and mark the result 'adjusted' (default); --no-adjust reports such models "
                         "unsupported")
    sw.add_argument("--drop-unsupported", action="store_true",
                    help="remove geom pairs MJX cannot collide (e.g. cylinder-box) from the model both engines "
                         "step and test the rest; changes the dynamics, so it is never the default and every "
                         "dropped pair is listed in the result")
    sw.add_argument("--drop-costly-pairs", action="store_true",
                    help="remove the mesh-mesh and box-mesh geom pairs (MJX's dense separating-axis test: minutes "
                         "of compile, GBs per member on robots' plain models) from the model both engines step; "
                         "changes the dynamics, so never the default; every dropped pair is listed")
    sw.add_argument("--budget", type=_seconds, default=600.0, metavar="SECONDS",
                    help="wall time per scenario (default 600). A compile estimated past it stops the scenario "
                         "at once, with the estimate and what to do; a scenario that runs past it ends as an "
                         "ERROR saying how far it got, and the sweep goes on")
    sw.add_argument("--sweep-budget", type=_seconds, metavar="SECONDS",
                    help="wall time for the whole sweep (default: none); scenarios left when it runs out are "
                         "reported as not run")
    sw.add_argument("--max-memory", type=_size, metavar="SIZE",
                    help="resident memory the sweep may hold, e.g. 12G (default: 85%% of what the machine has "
                         "available at the start). MJX steps fewer members at once to fit; a scenario that would "
                         "still exceed it ends as an ERROR naming the cause, before the kernel would kill it")
    sw.add_argument("--isolate", action=argparse.BooleanOptionalAction,
                    default=os.environ.get("MJXDIFF_ISOLATE", "1") != "0",
                    help="run the sweep in a child process watched for --max-memory and --budget, which can "
                         "stop even an XLA compile (default; MJXDIFF_ISOLATE=0 changes the default); "
                         "--no-isolate runs it in this process, where only the plan and the checks between "
                         "pieces hold the limits")
    sw.add_argument("--onestep", action=argparse.BooleanOptionalAction, default=True,
                    help="check every scenario one step at a time from C's states with a converged solver in "
                         "both engines, bounded by C's own rounding (sharp where chaos or a truncated solver make "
                         "the rollout's bound wide); it can fail the scenario on its own (default on)")
    sw.add_argument("--transfer", action=argparse.BooleanOptionalAction, default=True,
                    help="also check MJX's host interface against C at two C states of each scenario "
                         "(default): get_data(put_data(d)) gives C's fields and penetrating contacts back, "
                         "get_state/set_state/state_size match mj_getState/mj_stateSize, id2name/name2id and "
                         "Model.bind/Data.bind read what C holds; a mismatch fails the scenario as field "
                         "'transfer'; state elements MJX refuses are listed, not failed")
    sw.add_argument("--compile", choices=("auto", "fast", "optimized"), default="auto",
                    help="how hard XLA optimises each MJX rollout: auto (default) compiles quickly (about "
                         "60%% less compile time than XLA's defaults, 3x slower stepping) when the rollout steps "
                         "too little for that to matter, as a sweep's do, and for stepping otherwise (40%% less "
                         "compile time, about the same speed); fast forces the first, optimized XLA's defaults; "
                         "results agree to rounding whichever is used")
    sw.add_argument("--compile-workers", type=_non_negative, metavar="N",
                    help="scenarios run side by side, each on its own thread from compile to verdict; results "
                         "are reported in order (default: one per core, at most 4; 0: one after another)")
    _shared(sw, "out", out="write DIR/report.json (versions, config, per-scenario metrics) "
                                                  "and DIR/report.html (one self-contained page with plots); "
                                                  "each scenario's verdict is also appended to DIR/journal.jsonl "
                                                  "as it arrives, so an interrupted sweep loses nothing (--resume)")
    sw.add_argument("--resume", metavar="DIR",
                    help="finish an interrupted sweep: reuse the verdicts DIR/journal.jsonl holds for the same "
                         "scenario, model, seed, settings, MJX and mjxdiff code and versions, run the rest "
                         "(and units whose worker or engine failed), and write the report to DIR (or --out); "
                         "records of other code or settings are listed as stale, never reused")
    sw.add_argument("--rerun", choices=("errors", "failed"), default="errors",
                    help="with --resume: rerun only units that did not settle (errors, the default: a worker "
                         "or engine failed, a limit ran out), or also the failures (failed, as pytest's --lf)")
    sw.add_argument("--executor", choices=("local", "ray"), default="local",
                    help="where the units run: on this machine (local, the default) or as one Ray task per "
                         "unit on a Ray cluster (ray; pip install 'mjxdiff[ray]'): self-contained tasks (the "
                         "model's files shipped), retried when a worker or node is lost, results journaled as "
                         "they arrive and reported in the sweep's order")
    sw.add_argument("--address", metavar="ADDR",
                    help="with --executor ray: the cluster to join (ray.init's address, e.g. 'auto' or "
                         "'ray://head:10001'; default: start a Ray instance on this machine)")
    sw.add_argument("--cpus-per-scenario", type=_positive, metavar="K",
                    help="with --executor ray: CPUs each unit's task asks for, and all it uses (XLA host "
                         "devices, C threads; default 1)")
    sw.add_argument("--shard", metavar="I/N",
                    help="run only the I-th of N deterministic slices of the sweep's units (scenario x judged "
                         "pair, every N-th from the I-th); 'mjxdiff merge' joins the shards' --out directories "
                         "into one report (a CI matrix: one job per shard)")
    sw.add_argument("--impl", choices=("mjx", "warp", "mjx.warp", "both", "all"), default="mjx",
                    help="what is judged against MuJoCo C: MJX (default), MuJoCo Warp on Warp's CPU device "
                         "(float32, so float32 tolerance floors; needs pip install 'mjxdiff[warp]'; kernels "
                         "compile on first use, ~30 s, then load from the cache), mjx.warp: MJX's own warp "
                         "implementation (mjx.put_model(m, impl='warp'), MJX's vendored MuJoCo Warp through JAX; "
                         "float32, needs the warp extra too), or both: one verdict per "
                         "pair, MJX vs C ('NAME'), MJWarp vs C ('NAME@warp') and MJWarp vs MJX ('NAME@mjx-warp', "
                         "float32, C's envelope as the floor); all: both, and MJX's warp implementation vs C "
                         "('NAME@mjx.warp')")
    sw.add_argument("--plots", choices=("failing", "all", "none"), default="failing",
                    help="report.html's error-vs-time plots: of failing scenarios (default), of all, or none")
    _shared(sw, "history", history=
            "append this run (one row per scenario x field) to the Parquet history in DIR and flag "
            "errors that moved outside their own history (default $MJXDIFF_HISTORY, else "
            "$XDG_DATA_HOME/mjxdiff/history or ~/.local/share/mjxdiff/history; see 'mjxdiff history')")
    sw.add_argument("--no-history", action="store_true", help="do not read or append the run history")
    sw.add_argument("--history-keep", type=_positive, default=500, metavar="N",
                    help="runs kept in the history; older ones are deleted (default 500)")
    sw.add_argument("--baseline", metavar="REF",
                    help="compare with a trusted run: a report.json, a directory holding one, or a history run "
                         "id; each scenario is 'same', 'new failure', 'fixed', 'error grew' or 'error shrank'")
    sw.add_argument("--fail-on", choices=("any", "new"), default="any",
                    help="exit 1 on any divergence (default), or only on new ones: failures that no accepted "
                         "known entry explains (e.g. 'solver-truncation': your solver settings, not MJX, part the "
                         "engines) and, with --baseline, that the baseline did not already have")
    sw.add_argument("--known", metavar="FILE",
                    help="your own known divergences ([[known]] tables, see mjxdiff.compare.known), tried before the "
                         "catalogue shipped with mjxdiff")
    _shared(sw, "format")
    sw.add_argument("--quick", action="store_true",
                    help="smoke run: batch <= 4, steps <= 50, and none of the checks that compile on their own "
                         "(the converged twin, the ablations that name a likely cause): each verdict says what it "
                         "skipped; it steps the full run's compiled code, so either run warms the cache for the "
                         "other")
    _shared(sw, "cache_dir", cache_dir=
            "JAX persistent compilation cache, plus traced MJX rollouts in DIR/mjxdiff-exports "
            "so a second run skips tracing mjx.step (default $MJXDIFF_CACHE or "
            "~/.cache/mjxdiff/jax; '' disables both)")
    sw.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None,
                    help="progress lines on stderr (default: when stderr is a terminal)")
    return sw


def _replay_parser(sub) -> argparse.ArgumentParser:
    rp = sub.add_parser("replay", help="re-run a saved reproducer of a failing scenario member",
                        description=_DESCRIPTIONS["replay"])
    rp.add_argument("file", metavar="FILE", help="reproducer .json")
    _shared(rp, "format", "cache_dir")
    return rp


def _fuzz_parser(sub) -> argparse.ArgumentParser:
    fz = sub.add_parser("fuzz", help="hunt for divergences with generated models (Hypothesis), shrink what is found",
                        description=_DESCRIPTIONS["fuzz"],
                        formatter_class=argparse.RawDescriptionHelpFormatter)
    fz.add_argument("--max-examples", type=_positive, default=300,
                    help="most generated models (structures) to try (default 300); each is judged on "
                         "64 variants of its parameters, initial state and controls, compiled once")
    _shared(fz, "seed", seed="Hypothesis seed (default 0)")
    fz.add_argument("--budget", type=float, default=None, metavar="SECONDS",
                    help="seconds of generation (default 60); shrinking a find may take longer")
    _shared(fz, "out", out="save the reproducer and the example database under DIR")
    fz.add_argument("--include-known", action="store_true",
                    help="also generate features with known, documented C/MJX divergences "
                         "(connect/weld, RK4/implicitfast, box and mesh geoms, tendon wrap sidesites) and report "
                         "the contact differences known by their signature (plane-cylinder far cap, capsule contact "
                         "frames)")
    _shared(fz, "cache_dir")
    return fz


def _bench_parser(sub) -> argparse.ArgumentParser:
    bn = sub.add_parser("bench", help="measure MJX and MuJoCo C throughput, compile time and memory per scenario",
                        description=_BENCH_DESCRIPTION, epilog=_BENCH_EPILOG,
                        formatter_class=argparse.RawDescriptionHelpFormatter)
    _shared(bn, "scenarios", scenarios=
            f"bundled scenario name, scenario .toml or MJCF .xml (default: {' '.join(_BENCH_DEFAULT)}, "
            "a small, a medium and an ant-class model)")
    bn.add_argument("--batch", type=_positive, nargs="+", metavar="B",
                    help="batch sizes of the throughput curve (default 8 32 128)")
    bn.add_argument("--steps", type=_positive, default=200, help="steps per rollout (default 200)")
    bn.add_argument("--repeats", type=_positive, default=2, help="warm runs per measurement, best kept (default 2)")
    _shared(bn, "seed", "out", "format", "cache_dir", out="write DIR/bench.json (versions, machine, every number)")
    return bn


def _policy_parser(sub) -> argparse.ArgumentParser:
    po = sub.add_parser("policy", help="run a policy in closed loop on MJX and on MuJoCo C and compare episodes",
                        description=_DESCRIPTIONS["policy"])
    po.add_argument("target", metavar="MODEL_OR_ENV", nargs="?",
                    help="a brax environment name (MJX backend, e.g. inverted_pendulum), a bundled scenario, "
                         "a scenario .toml or an MJCF .xml (observations qpos, qvel, sensordata; actions in "
                         "[-1, 1] onto ctrlrange; no reward: compare states)")
    po.add_argument("--replay", metavar="FILE",
                    help="re-run the one episode a failing run saved (DIR/policy-reproducer.json, written "
                         "with --out): same target, policy, seed and keys")
    po.add_argument("--policy", metavar="SPEC",
                    help="a brax PPO checkpoint directory, PARAMS_FILE::module:factory (brax.io.model.save_params "
                         "and a make_ppo_networks-like factory), or module:function (a policy(obs, key), or a "
                         "factory of the observation and action sizes returning one)")
    po.add_argument("--episodes", type=_positive, default=16, help="episodes per engine (default 16)")
    po.add_argument("--steps", type=_positive, default=200, help="control steps per episode (default 200)")
    po.add_argument("--n-frames", type=_positive, default=1,
                    help="substeps per control step for an MJCF (brax environments bring their own)")
    _shared(po, "seed", "out", "format", seed="seed of resets and policy keys (default 0)",
            out="write DIR/policy-report.json")
    return po


def _coverage_parser(sub) -> argparse.ArgumentParser:
    cv = sub.add_parser("coverage", help="measure which MJX code and which model parameters the scenarios exercise",
                        description=_DESCRIPTIONS["coverage"])
    _shared(cv, "scenarios", "seed", "out", "format", out="write DIR/coverage.json")
    return cv


def _grad_parser(sub) -> argparse.ArgumentParser:
    gr = sub.add_parser("grad", help="compare MJX's one-step Jacobians (jax.jacfwd) with C's finite differences",
                        description=_DESCRIPTIONS["grad"])
    _shared(gr, "scenarios", scenarios=
            "bundled scenario name, scenario .toml or MJCF .xml (default: the smooth ones: pendulum, "
            "double_pendulum, cartpole, actuators, gravcomp_arm)")
    gr.add_argument("--states", type=_positive, default=8, help="states sampled per scenario (default 8)")
    _shared(gr, "seed", "out", "format", out="write DIR/grad-report.json, DIR/grad-report.html (a heat map of each "
            "failing scenario's worst state) and, per failing scenario, its worst state as "
            "DIR/reproducers/NAME-grad-stateI.json for 'mjxdiff replay'")
    return gr


def _history_parser(sub) -> argparse.ArgumentParser:
    hi = sub.add_parser("history", help="query the run history sweeps append to (DuckDB over Parquet)",
                        description=_DESCRIPTIONS["history"])
    hi.add_argument("--history", "--dir", dest="history", metavar="DIR", help=_SHARED["history"][1]["help"] +
                    "; --dir is the older name")
    hi.add_argument("--scenario", metavar="S", help="only this scenario")
    hi.add_argument("--field", metavar="F", help="only this field (qpos, qvel, act, sensordata, contacts, ...)")
    hi.add_argument("--since", metavar="WHEN", type=_since,
                    help="only runs since WHEN: an ISO date or time (2026-11-01, 2026-11-01T12:00) or an age "
                         "(7d, 12h, 30m)")
    view = hi.add_mutually_exclusive_group()
    view.add_argument("--by-version", action="store_true", help="compare runs by MuJoCo/MJX version and code digest")
    view.add_argument("--runs", action="store_true", help="list the runs (id, time, versions, passes, failures)")
    _shared(hi, "format")
    return hi


def _cache_parser(sub) -> argparse.ArgumentParser:
    ca = sub.add_parser("cache", help="check the cache of traced MJX rollouts against the code loaded now",
                        description=_DESCRIPTIONS["cache"],
                        formatter_class=argparse.RawDescriptionHelpFormatter,
                        epilog="examples:\n  python -m mjxdiff cache check\n"
                               "  python -m mjxdiff cache check --fix --cache-dir .jax_cache")
    ca.add_argument("action", choices=("check",), help="what to do (check)")
    ca.add_argument("--fix", action="store_true",
                    help="remove what cannot be trusted: every artifact of an ambiguous key, unreadable ones, "
                         "orphaned files, older formats")
    _shared(ca, "cache_dir", cache_dir="the cache to check (default $MJXDIFF_CACHE or ~/.cache/mjxdiff/jax, as sweep)")
    _shared(ca, "format")
    return ca


def _list_parser(sub) -> argparse.ArgumentParser:
    return sub.add_parser("list", help="list bundled scenarios and what each exercises",
                   description="List bundled scenarios with their model, size and what they exercise.")


def _known_parser(sub) -> argparse.ArgumentParser:
    kn = sub.add_parser("known", help="list the known-divergence catalogue: each entry, its kind and its bug bundle",
                        description=_DESCRIPTIONS["known"])
    kn.add_argument("--list", action="store_true", help="list every entry (what 'known' does; the flag says so)")
    kn.add_argument("--known", metavar="FILE", help="your own entries ([[known]] tables), listed first, as a sweep "
                                                  "tries them")
    return kn


def _cmd_known(args: argparse.Namespace) -> int:
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


def _versions_parser(sub) -> argparse.ArgumentParser:
    ve = sub.add_parser("versions", help="run the same sweep on several MJX releases and tabulate the verdicts",
                        description=_DESCRIPTIONS["versions"], epilog=_VERSIONS_EPILOG,
                        formatter_class=argparse.RawDescriptionHelpFormatter)
    ve.add_argument("targets", nargs="+", metavar="MJX[/JAX][+coreC]", type=_target,
                    help="an MJX release (3.9.0; its MuJoCo is installed with it, 4.0 for MJX 3.17), optionally with "
                         "the JAX to pair it with (3.9.0/0.7.2; default: the newest pip finds within mjxdiff's range) "
                         "and the MuJoCo C to judge it against (3.17.0+core4.0.1: mujoco-core 4.0.1 over the pinned "
                         "4.0.0, MJX unchanged, to see whether C is the one that moved)")
    ve.add_argument("--scenarios", nargs="+", default=[], metavar="SCENARIO",
                    help="bundled scenario names, scenario .toml or MJCF .xml files to sweep on every version "
                         "(default: every bundled scenario)")
    ve.add_argument("--quick", action="store_true", help="sweep --quick on every version")
    _shared(ve, "seed", "out", out="write OUT/versions.json, each version's report under OUT/<version>/ and their runs "
                            "to the history OUT/history (default mjxdiff-versions)")
    ve.add_argument("--envs", metavar="DIR", help="where the environments are kept and reused (default "
                                                  "$XDG_CACHE_HOME/mjxdiff/versions or ~/.cache/mjxdiff/versions)")
    ve.add_argument("--extras", nargs="*", default=[], metavar="EXTRA",
                    help="mjxdiff extras installed in every environment too (test: to run the suite there)")
    _shared(ve, "format")
    return ve


def _target(text: str):
    from mjxdiff.tools.versions import parse_target

    try:
        return parse_target(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def _cmd_versions(args: argparse.Namespace) -> int:
    from mjxdiff.tools import versions

    scenarios = [str(Path(x).resolve()) if Path(x).suffix else x for x in args.scenarios]  # files: for the child
    sweep_args = [*scenarios, "--seed", str(args.seed), *(["--quick"] if args.quick else [])]
    cache = Path(args.envs) if args.envs else Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / \
        "mjxdiff" / "versions"
    say = (lambda line: print(line, file=sys.stderr)) if args.format == "json" else print
    doc = versions.run(args.targets, sweep_args, Path(args.out or "mjxdiff-versions"), cache, args.extras, say)
    if args.format == "json":
        print(json.dumps(doc, indent=2))
    else:
        print(versions.format_table(doc["table"]))
    cells = [c for row in doc["table"]["rows"].values() for c in row.values()]
    return 1 if doc["table"]["errors"] or any(c["status"] in ("fail", "error") and not c["known"] for c in cells) else 0


def _selected(refs: Sequence[str]) -> list | None:
    """The scenarios ``refs`` name (every bundled one when empty); None, after one error line on
    stderr, when one cannot be read or none is selected."""
    from mjxdiff.input.scenario import ScenarioError, bundled_scenarios, load_scenario, no_bundled_scenarios_message

    try:
        scenarios = [load_scenario(ref) for ref in refs] if refs else bundled_scenarios()
    except ScenarioError as e:
        print(f"mjxdiff: error: {e}", file=sys.stderr)
        return None
    if not scenarios:
        print(f"mjxdiff: error: no scenarios selected ({no_bundled_scenarios_message()})", file=sys.stderr)
        return None
    return scenarios


def _cmd_list(args: argparse.Namespace) -> int:
    scenarios = _selected(())
    if scenarios is None:
        return 2
    for s in scenarios:
        print(f"{s.name:<28} batch {s.batch:>3} x {s.steps:>4} steps  {s.description}")
        if s.exercises:
            print(f"{'':<28} exercises: {', '.join(s.exercises)}")
    return 0


def _cmd_sweep(args: argparse.Namespace) -> int:
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


def _merge_parser(sub) -> argparse.ArgumentParser:
    mg = sub.add_parser("merge", help="join the --out directories of a sweep's shards (or resumed runs) into "
                                      "one report", description=_DESCRIPTIONS["merge"])
    mg.add_argument("out", metavar="OUT", help="directory of the merged report.json, report.html and journal")
    mg.add_argument("dirs", nargs="+", metavar="DIR", help="--out directories of 'mjxdiff sweep --shard I/N' runs")
    _shared(mg, "format")
    return mg


def _cmd_merge(args: argparse.Namespace) -> int:
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


def _shrink_parser(sub) -> argparse.ArgumentParser:
    sh = sub.add_parser("shrink", help="shrink a diverging model to a minimal MJCF with the same divergence",
                        description=_DESCRIPTIONS["shrink"])
    sh.add_argument("model", metavar="MODEL", help="an MJCF file, or a reproducer .json ('sweep --out' writes them)")
    sh.add_argument("--out", metavar="DIR", default="mjxdiff-out/shrink", help="where to write (default %(default)s)")
    sh.add_argument("--bundle", action="store_true",
                    help="write a bug bundle: repro.py, signature.json and README.md beside the model")
    sh.add_argument("--keyframe", type=int, metavar="K", help="start C's rollout from keyframe K (default qpos0)")
    sh.add_argument("--steps", type=_positive, default=200, metavar="N",
                    help="states of C's rollout searched for the divergence (default 200)")
    sh.add_argument("--budget", type=_seconds, default=600.0, metavar="SECONDS",
                    help="stop shrinking after this long with the best so far (default 600)")
    return sh


def _shrink_input(path: str, keyframe: int | None, steps: int):
    """(spec, state, signature, step, source directory) of a model file or a reproducer."""
    import mujoco
    import numpy as np

    from mjxdiff.output import reproducer
    from mjxdiff.tools import shrink

    ctrl = None
    if path.endswith(".json"):
        rep = reproducer.load(path)
        spec = shrink.named(mujoco.MjSpec.from_string(rep.model_xml))
        m = spec.compile()
        controls = np.asarray(rep.inputs.ctrl[0])
        ctrl = (lambda k: controls[min(k, len(controls) - 1)]) if controls.size else None
        start = (rep.inputs.qpos[0], rep.inputs.qvel[0], rep.inputs.act[0])
        source = None
    else:
        spec = shrink.named(mujoco.MjSpec.from_file(path))
        m, start, source = spec.compile(), None, Path(path).resolve().parent
    if keyframe is not None and not 0 <= keyframe < m.nkey:
        raise ValueError(f"--keyframe {keyframe}: the model has {m.nkey} keyframes")
    found = shrink.find_state(m, steps, keyframe, ctrl, start)
    return spec, found, source


def _cmd_shrink(args: argparse.Namespace) -> int:
    from mjxdiff.tools import bundle, shrink
    from mjxdiff.engine import engines
    from mjxdiff.input.scenario import ScenarioError

    engines.configure_jax("float64")
    try:
        spec, found, source = _shrink_input(args.model, args.keyframe, args.steps)
    except NotImplementedError as e:
        print(f"mjxdiff shrink: error: unsupported by MJX, nothing to compare: {one_line(e)}", file=sys.stderr)
        return 2
    except (ScenarioError, ValueError, OSError) as e:
        print(f"mjxdiff shrink: error: {one_line(e)}", file=sys.stderr)
        return 2
    if found is None:
        print(f"mjxdiff shrink: error: no divergence in the first {args.steps} states of C's rollout: nothing to "
              "shrink (a sweep's reproducer starts from the failing member's state)", file=sys.stderr)
        return 2
    state, signature, step = found
    print(f"shrink: {signature.describe()} at step {step}", file=sys.stderr)
    shrunk = shrink.shrink(spec, state, signature, args.budget, lambda line: print(line, file=sys.stderr),
                           steps_before=step + 1)
    out = Path(args.out)
    if args.bundle:
        bundle.write(shrunk, out, source, origin=args.model)
    else:
        out.mkdir(parents=True, exist_ok=True)
        bundle.write_model(shrunk, out, source)
    print(f"{signature.describe()}\nbefore: {shrunk.before}\nafter:  {shrunk.after}\n"
          f"{shrunk.candidates} candidates, {shrunk.compiles} XLA compiles, {shrunk.seconds:.0f} s"
          + ("" if shrunk.complete else " (stopped early: the best so far)") + f"\nwritten to {out}")
    return 0


def _scale_parser(sub) -> argparse.ArgumentParser:
    sc = sub.add_parser("scale", help="predict a sweep's wall time on 1-64 nodes from its journal",
                        description=_DESCRIPTIONS["scale"])
    sc.add_argument("dirs", nargs="+", metavar="DIR", help="--out directories whose journal.jsonl measured the units")
    sc.add_argument("--nodes", type=_positive, nargs="+", metavar="N", help="node counts (default 1 2 4 ... 64)")
    sc.add_argument("--cpus-per-node", type=_positive, default=2, metavar="C", help="CPUs of a node (default 2)")
    sc.add_argument("--cpus-per-scenario", type=_positive, default=1, metavar="K",
                    help="CPUs each unit's task asks for (default 1)")
    sc.add_argument("--fixed", type=float, default=0.0, metavar="SECONDS",
                    help="seconds the run costs once: starting or joining Ray, the workers' imports (default 0)")
    sc.add_argument("--per-task", type=float, default=0.0, metavar="SECONDS",
                    help="seconds each unit costs on top of its own (default 0)")
    _shared(sc, "format")
    return sc


def _cmd_scale(args: argparse.Namespace) -> int:
    from mjxdiff.runner import journal, scaling

    units = {}
    for d in args.dirs:
        for r in journal.read(Path(d) / journal.FILE).units:
            units[r["key"]] = (r["unit"], float(r.get("seconds") or 0.0))  # a unit recorded twice: the later
    if not units:
        print(f"mjxdiff: error: no finished unit in {', '.join(args.dirs)} (a sweep run with --out DIR journals "
              "them)", file=sys.stderr)
        return 2
    predictions = scaling.predict(list(units.values()), args.nodes or scaling.NODES,
                                  max(1, args.cpus_per_node // args.cpus_per_scenario), args.fixed, args.per_task)
    if args.format == "json":
        print(json.dumps([dataclasses.asdict(p) for p in predictions], indent=2))
    else:
        print(f"{len(units)} units, {sum(s for _, s in units.values()):.1f} s of work")
        print(scaling.format_table(predictions))
    return 0


def _cmd_replay(args: argparse.Namespace) -> int:
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


def _cmd_bench(args: argparse.Namespace) -> int:
    from mjxdiff.tools import bench
    from mjxdiff.engine import engines
    from mjxdiff.output import report
    from mjxdiff.input.scenario import ScenarioError, load_scenario

    engines.configure_jax("float64", args.cache_dir)
    try:
        scenarios = [load_scenario(ref) for ref in args.scenarios or _BENCH_DEFAULT]
    except ScenarioError as e:
        print(f"mjxdiff: error: {e}", file=sys.stderr)
        return 2
    say = (lambda text: print(f"... {text}", file=sys.stderr, flush=True)) if sys.stderr.isatty() else None
    results = []
    for scenario in scenarios:
        try:
            results.append(bench.bench_scenario(scenario, args.batch or bench.DEFAULT_BATCHES, args.steps,
                                                args.seed, args.repeats, say))
        except engines.UnsupportedError as e:
            print(f"mjxdiff: {scenario.name}: skipped, MJX does not support: {e.feature}", file=sys.stderr)
            continue
        if args.format == "text":
            print(bench.format_text(results[-1:]), flush=True)
    doc = report.envelope("bench", dict(scenarios=args.scenarios, batch=args.batch, steps=args.steps, seed=args.seed,
                                        repeats=args.repeats), steps=args.steps, scenarios=results)
    if args.out:
        path = report.write_report(args.out, doc, "bench.json")
        print(f"bench written to {path}", file=sys.stderr)
    if args.format == "json":
        print(json.dumps(doc, indent=2))
    return 0 if results else 1


def _cmd_fuzz(args: argparse.Namespace) -> int:
    from mjxdiff.engine import engines
    from mjxdiff.output import report
    from mjxdiff.tools.fuzz import DEFAULT_BUDGET, fuzz

    engines.configure_jax("float64", args.cache_dir)
    budget = DEFAULT_BUDGET if args.budget is None else args.budget
    if budget <= 0:
        print("mjxdiff: error: --budget must be positive (see 'mjxdiff fuzz --help')", file=sys.stderr)
        return 2
    result = fuzz(max_examples=args.max_examples, seed=args.seed, budget=budget, out=args.out,
                  include_known=args.include_known, progress=sys.stderr.isatty())
    written = None
    if args.out:
        doc = report.envelope("fuzz", dict(max_examples=args.max_examples, seed=args.seed, budget=budget,
                                           include_known=args.include_known),
                   examples=result.examples, structures=result.structures, seconds=result.seconds,
                   **result.rates(), failure=result.failure,
                   harness_error=result.harness_error, traceback=result.harness_traceback,
                   harness_example=result.harness_example, interactions=result.interactions,
                   set_aside=result.set_aside)
        written = report.write_report(args.out, doc, "fuzz-report.json")
    if result.harness_error is not None:
        # the run proves nothing: not "no divergence", whatever was tried before
        print(f"mjxdiff: error: fuzz harness failed: {result.harness_error}", file=sys.stderr)
        assert result.harness_traceback is not None  # recorded with the harness error
        print(result.harness_traceback.rstrip("\n"), file=sys.stderr)
        if written:
            print(f"fuzz report written to {written}", file=sys.stderr)
        if result.failure is not None:
            print(f"(a divergence was found before the harness failed: {result.failure['message']})")
        return 2
    if written:
        print(f"fuzz report written to {written}", file=sys.stderr)
    rates = result.rates()
    tried = (f"{result.examples} examples ({result.structures} generated models x "
             f"{result.examples // max(1, result.structures)} variants; {rates['examples_per_minute']:.0f} examples, "
             f"{rates['structures_per_minute']:.1f} models per minute)")
    notes = []  # printed after the verdict
    if result.set_aside:  # models judged that count neither way, each with why
        notes.append("set aside, neither a pass nor a find: " + ", ".join(
            f"{n} ({why})" for why, n in sorted(result.set_aside.items())))
    if result.interactions:
        from mjxdiff.tools import interactions
        line = interactions.format_text(result.interactions, "interaction pairs generated", "fuzz-report.json")
        notes.append(f"{line.splitlines()[0]}; {result.interactions['pairs_per_minute']:.0f} per minute")
    if result.failure is None:
        print(f"no divergence in {tried}, {result.seconds:.0f} s")
        if notes:
            print("\n".join(notes))
        return 0
    f = result.failure
    print(f"DIVERGENCE ({f['status']}) after {tried}, {result.seconds:.0f} s: {f['message']}")
    print(f"shrunk to {f['nbody']} bodies, {f['ngeom']} geoms; features: {', '.join(f['features']) or 'none'}")
    if f["reproducer"]:
        print(f"reproducer: {f['reproducer']} (python -m mjxdiff replay {f['reproducer']})")
    print(f["xml"])
    if notes:
        print("\n".join(notes))
    return 1


def _cmd_policy(args: argparse.Namespace) -> int:
    from mjxdiff.tools import closedloop
    from mjxdiff.engine import engines
    from mjxdiff.output import report

    only = None
    if args.replay:
        try:
            saved = json.loads(Path(args.replay).read_text())
            if saved.get("kind", "policy-reproducer") != "policy-reproducer":
                raise ValueError(f"a {saved['kind']} output")
            args.target, args.policy, only = saved["target"], saved["policy"], [int(saved["episode"])]
            config = saved["config"] if "kind" in saved else saved  # before the envelope: at the top level
            args.episodes, args.steps, args.seed, args.n_frames = (int(config[k]) for k in
                                                                   ("episodes", "steps", "seed", "n_frames"))
        except (OSError, ValueError, KeyError, TypeError) as e:
            print(f"mjxdiff policy: {args.replay}: not a policy reproducer ({one_line(e)})", file=sys.stderr)
            return 2
    if not args.target or not args.policy:
        print("mjxdiff policy: give MODEL_OR_ENV and --policy SPEC, or --replay FILE", file=sys.stderr)
        return 2
    engines.configure_jax("float64", None)
    try:
        env = closedloop.resolve_env(args.target, args.n_frames)
        policy = closedloop.load_policy(args.policy, env)
    except closedloop.PolicyError as e:
        print(f"mjxdiff policy: {e}", file=sys.stderr)
        return 2
    comparison = closedloop.run(env, policy, args.episodes, args.steps, args.seed, only=only)
    n_frames = int(env._n_frames)  # noqa: SLF001 - brax's substeps per control step
    result = closedloop.judge(closedloop.c_model(env), comparison, seed=args.seed, n_frames=n_frames)
    config = dict(episodes=args.episodes, steps=args.steps, seed=args.seed, n_frames=args.n_frames)
    doc = report.envelope("policy", dict(config, only=only), target=args.target, policy=args.policy, **result)
    if args.out:
        path = report.write_report(args.out, doc, "policy-report.json")
        print(f"report written to {path}", file=sys.stderr)
        if result["status"] == "fail" and only is None:
            worst = result["first_separation"]["episode"] if result["first_separation"] else result["worst_episode"]
            rep = report.envelope("policy-reproducer", config, target=args.target, policy=args.policy,
                                  episode=worst, message=result["message"])
            path = report.write_report(args.out, rep, "policy-reproducer.json")
            print(f"reproducer of episode {worst} written to {path} (mjxdiff policy --replay {path})",
                  file=sys.stderr)
    print(json.dumps(doc, indent=2) if args.format == "json" else f"{result['status'].upper():6} {args.target}  "
          f"{result['message']}")
    return 0 if result["status"] == "pass" else 1


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


def _cmd_history(args: argparse.Namespace) -> int:
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


def _cmd_grad(args: argparse.Namespace) -> int:
    from mjxdiff.engine import engines
    from mjxdiff.tools import grad
    from mjxdiff.output import report

    scenarios = _selected(args.scenarios or list(grad.SMOOTH))
    if scenarios is None:
        return 2
    engines.configure_jax("float64", None)
    rows = []
    for scenario in scenarios:
        rows.append(grad.check_scenario(scenario, args.states, args.seed,
                                        Path(args.out) / "reproducers" if args.out else None))
        if args.format == "text":
            print(grad.format_text(rows[-1:]), flush=True)
    doc = report.envelope("grad", dict(scenarios=args.scenarios, states=args.states, seed=args.seed, eps=grad.EPS),
                          scenarios=rows)
    if args.out:
        from mjxdiff.output import html_report

        print(f"report written to {report.write_report(args.out, doc, 'grad-report.json')} and "
              f"{html_report.write_grad(args.out, doc)}", file=sys.stderr)
    if args.format == "json":
        print(json.dumps(doc, indent=2))
    if any(r["status"] == "error" for r in rows):
        return 2
    return 1 if any(r["status"] == "fail" for r in rows) else 0


def _cmd_coverage(args: argparse.Namespace) -> int:
    from mjxdiff.tools import coverage
    from mjxdiff.engine import engines
    from mjxdiff.output import report

    scenarios = _selected(args.scenarios)
    if scenarios is None:
        return 2
    engines.configure_jax("float64", "")
    measured = coverage.measure(scenarios, args.seed)
    # "code" of the envelope names the MJX code tested: its line and branch coverage is "code_coverage"
    body = {("code_coverage" if k == "code" else k): v for k, v in measured.items()}
    doc = report.envelope("coverage", dict(scenarios=args.scenarios, seed=args.seed), **body)
    if args.out:
        path = report.write_report(args.out, doc, "coverage.json")
        print(f"coverage written to {path}", file=sys.stderr)
    print(json.dumps(doc, indent=2) if args.format == "json" else coverage.format_text(measured))
    return 0


def _cmd_cache(args: argparse.Namespace) -> int:
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


#: Every command: the function that adds its parser, the function that runs it.
_COMMANDS = ((_sweep_parser, _cmd_sweep), (_replay_parser, _cmd_replay), (_fuzz_parser, _cmd_fuzz),
             (_bench_parser, _cmd_bench), (_policy_parser, _cmd_policy), (_coverage_parser, _cmd_coverage),
             (_grad_parser, _cmd_grad), (_history_parser, _cmd_history), (_cache_parser, _cmd_cache),
             (_versions_parser, _cmd_versions), (_merge_parser, _cmd_merge), (_scale_parser, _cmd_scale),
             (_shrink_parser, _cmd_shrink), (_known_parser, _cmd_known), (_list_parser, _cmd_list))


#: Commands that run neither MuJoCo nor MJX: no version check.
# versions: each environment is gated by its own range
_UNGATED = (_cmd_history, _cmd_list, _cmd_versions, _cmd_scale, _cmd_known)


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    why = _untested_versions(args)
    if why:
        print(f"mjxdiff {args.command}: error: {why}", file=sys.stderr)
        return 2
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
