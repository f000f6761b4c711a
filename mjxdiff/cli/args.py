"""What every command of ``python -m mjxdiff`` shares: the parser with one-line errors and
its hints, ``--version``, the options several commands take, the commands' descriptions, and
the scenarios a command names."""

from __future__ import annotations

import argparse
import sys
from typing import Any, Sequence



DESCRIPTION = """\
mjxdiff: does MuJoCo MJX behave like MuJoCo C? It rolls out batches of
randomized variants of each scenario in both engines (MJX: jit+vmap+scan on
the CPU; C: mujoco.batch on all cores), compares qpos, qvel, act, sensors and
contact counts step by step, and prints one verdict per scenario."""


#: The long descriptions of the subcommands (``--help``; argparse refills the lines).
DESCRIPTIONS = {
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


class Parser(argparse.ArgumentParser):
    """argparse with a one-line error and exit code 2, no usage dump; a mistyped flag gets the
    flag it most likely meant, and another command's flag says whose it is."""

    def parse_known_args(self, args=None, namespace=None):  # type: ignore[override]
        self._argv = list(sys.argv[1:] if args is None else args)
        return super().parse_known_args(args, namespace)

    def error(self, message: str) -> None:  # type: ignore[override]
        if message.startswith("unrecognized arguments: "):
            given = message.removeprefix("unrecognized arguments: ").split()
            command = self._command()
            message += did_you_mean(given, self._owners(), command, self._positional_args(command))
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


def did_you_mean(given: list[str], owners: dict[str, list[str]], command: str = "",
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


class Version(argparse.Action):
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


#: Options several commands share, each defined once (by dest); a command passes its own
#: help where the option means something more there (``shared(p, "out", out="write DIR/x.json")``).
SHARED: dict[str, tuple[tuple[str, ...], dict[str, Any]]] = {
    "scenarios": (("scenarios",), dict(nargs="*", metavar="SCENARIO", help="bundled scenario name, scenario .toml "
                                       "or MJCF .xml (default: every bundled scenario)")),
    "seed": (("--seed",), dict(type=int, default=0, help="seed of the randomized members (default 0)")),
    "out": (("--out",), dict(metavar="DIR", help="write the command's report under DIR")),
    "format": (("--format",), dict(choices=("text", "json"), default="text", help="stdout format (default text)")),
    "cache_dir": (("--cache-dir",), dict(metavar="DIR", help="JAX persistent compilation cache (see sweep --help)")),
    "history": (("--history",), dict(metavar="DIR", help="the run history's directory (default $MJXDIFF_HISTORY, "
                                     "else $XDG_DATA_HOME/mjxdiff/history or ~/.local/share/mjxdiff/history)")),
}


def shared(p: argparse.ArgumentParser, *dests: str, **helps: str) -> None:
    """Adds the shared options ``dests`` (:data:`SHARED`) to ``p``, with ``helps[dest]`` as
    the help text where given."""
    for dest in dests:
        flags, kw = SHARED[dest]
        p.add_argument(*flags, **{**kw, **({"help": helps[dest]} if dest in helps else {})})


def selected(refs: Sequence[str]) -> list | None:
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
