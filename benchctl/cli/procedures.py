"""`benchctl run`: run, dry-run or resume a procedure."""

from __future__ import annotations

import argparse
from pathlib import Path

from benchctl.cli.args import add_profile
from benchctl.errors import BenchctlError


def _cmd_run(args: argparse.Namespace) -> int:
    from benchctl.runner.engine import run_procedure
    from benchctl.runner.events import EventStream

    if args.procedure is None and args.resume is None:
        raise BenchctlError("give a procedure file (e.g. procedures/colour_capture.toml) or --resume RUN_DIR")
    if args.procedure is not None and args.resume is not None:
        raise BenchctlError("give either a procedure file or --resume RUN_DIR, not both (a resumed run uses its own "
                            "copy of the procedure)")
    run_procedure(args.procedure, profile=args.profile, out=args.out, dry_run=args.dry_run, resume=args.resume,
                  allow_code=args.allow_code, events=EventStream(args.events) if args.events is not None else None)
    return 0


def add_commands(sub: argparse._SubParsersAction) -> None:
    """Add this group's sub-commands to the `benchctl` sub-parsers (importing nothing heavy)."""
    run = sub.add_parser(
        "run", help="run a procedure: colour-capture, focal-stack, registration, model-calibration, lut-calibration, "
                    "citl, focus-calibration, power-sweep (procedures/*.toml) or a Python one",
        description="Run a procedure file on the bench the profile describes. Every run writes a new folder "
                    "OUT/<timestamp>-<name>/ with the profile and procedure as used, versions, device identities, a "
                    "step log, holograms as displayed, RAW frames as captured, images, metrics and report.html. An "
                    "interrupted run leaves emission off and keeps what it captured; --resume finishes it.",
        epilog="procedures: files in procedures/ (TOML, or a Python file with PARAMETERS and plan(); see README). "
               "A .py procedure is code: running, dry-running or resuming it executes it with your rights; run "
               "only procedure files you trust. A TOML file is data: the Python file it names (in its own folder "
               "only) runs only with --allow-code, and so does the Python code of a run resumed.")
    run.add_argument("procedure", nargs="?", type=Path, help="procedure file (.toml or .py)")
    add_profile(run)
    run.add_argument("--out", "-o", type=Path, default=Path("runs"), metavar="DIR",
                     help="where run folders are created (default: runs/)")
    run.add_argument("--dry-run", action="store_true",
                     help="check the procedure and profile and print every step; benchctl touches no device and "
                          "writes nothing (a .py procedure's own code still runs)")
    run.add_argument("--resume", type=Path, metavar="RUN_DIR",
                     help="finish an interrupted run without repeating its finished steps")
    run.add_argument("--allow-code", action="store_true",
                     help="let the Python file a TOML procedure names (in its own folder), or the Python procedure of "
                          "the run resumed, run with your rights (a .py given as PROCEDURE needs no flag)")
    run.add_argument("--events", type=int, metavar="FD",
                     help="also write the run's events as JSON lines to open file descriptor FD (its folder once "
                          "created, each step's start and end as the step log has them, how it stopped), for a "
                          "program that follows the run (README: following a run)")
    run.set_defaults(func=_cmd_run)
