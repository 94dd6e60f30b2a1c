"""The `benchctl` command line: parses arguments and calls one function per command; no logic lives here.

One module per command group (`devices`, `profile`, `holograms`, `benchmarks`, `training`, `procedures`, `runs`,
`console`), each adding its sub-parsers with `add_commands`; a command imports what it uses only when it runs.
"""

from __future__ import annotations

import argparse
import sys
from typing import Sequence

from benchctl.cli import benchmarks, console, devices, holograms, procedures, profile, runs, training
from benchctl.cli.args import EPILOG, Parser, VersionAction
from benchctl.errors import BenchctlError


def build_parser() -> argparse.ArgumentParser:
    """The full argument parser (also used by the docs and tests).

    Building it imports nothing heavy (no torch, no networks): `benchctl laser off` must start instantly.
    Method names are therefore checked when a command runs, not by argparse `choices`.
    """
    parser = Parser(
        prog="benchctl",
        description="Holographic-display experiments on an optical bench, real or simulated.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action=VersionAction, nargs=0, help="show the version and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for group in (holograms, benchmarks, training, profile, procedures, runs, devices, console):
        group.add_commands(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the `benchctl` console script; returns the process exit code."""
    from benchctl.devices.lock import set_command
    from benchctl.devices.safety import TerminatedBySignal, signals_interrupt

    args = build_parser().parse_args(argv)
    action = getattr(args, f"{args.command}_command", None) or getattr(args, args.command, None)
    set_command(f"benchctl {args.command}" + (f" {action}" if isinstance(action, str) else ""))
    try:
        with signals_interrupt():
            return args.func(args)
    except BenchctlError as exc:
        print(f"benchctl: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        print(f"benchctl: interrupted{f' ({exc})' if str(exc) else ''}", file=sys.stderr)
        return 128 + exc.signum if isinstance(exc, TerminatedBySignal) else 130


if __name__ == "__main__":
    sys.exit(main())
