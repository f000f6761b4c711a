"""``python -m mjxdiff``: sweep scenarios, replay a failure, fuzz, benchmark, list scenarios.

Exit codes: 0 every scenario consistent (unsupported ones are reported, not
failing), 1 at least one divergence (fail, solver truncation included, or a
non-finite rollout), 2 bad usage or input; ``sweep --fail-on new`` exits 0 on
failures an accepted known entry explains.
"""

from __future__ import annotations

import argparse
import sys
from typing import Sequence

from mjxdiff.cli import commands, tools
from mjxdiff.cli.args import DESCRIPTION, Parser, Version

__all__ = ["build_parser", "main"]


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="mjxdiff", description=DESCRIPTION,
                    formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action=Version)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=Parser)
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


#: Every command: the function that adds its parser, the function that runs it.
_COMMANDS = (
    (commands.sweep_parser, commands.cmd_sweep), (commands.replay_parser, commands.cmd_replay),
    (tools.fuzz_parser, tools.cmd_fuzz), (tools.bench_parser, tools.cmd_bench),
    (tools.policy_parser, tools.cmd_policy), (tools.coverage_parser, tools.cmd_coverage),
    (tools.grad_parser, tools.cmd_grad), (commands.history_parser, commands.cmd_history),
    (commands.cache_parser, commands.cmd_cache), (tools.versions_parser, tools.cmd_versions),
    (commands.merge_parser, commands.cmd_merge), (tools.scale_parser, tools.cmd_scale),
    (tools.shrink_parser, tools.cmd_shrink), (commands.known_parser, commands.cmd_known),
    (commands.list_parser, commands.cmd_list))


#: Commands that run neither MuJoCo nor MJX: no version check.
# versions: each environment is gated by its own range
_UNGATED = (commands.cmd_history, commands.cmd_list, tools.cmd_versions, tools.cmd_scale, commands.cmd_known)


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    why = _untested_versions(args)
    if why:
        print(f"mjxdiff {args.command}: error: {why}", file=sys.stderr)
        return 2
    return args.func(args)
