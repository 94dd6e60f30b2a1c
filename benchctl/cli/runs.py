"""`benchctl runs`: list the run folders, compare their scores side by side, remove old ones."""

from __future__ import annotations

import argparse
from pathlib import Path

from benchctl.cli.args import print_lines
from benchctl.errors import BadValueError


def _folders(args: argparse.Namespace) -> list[Path]:
    """The runs named on the command line: a path, or a folder name under --out."""
    return [Path(name) if Path(name).is_dir() or Path(name).parent != Path(".") else args.out / name
            for name in args.runs]


def _cmd_runs(args: argparse.Namespace) -> int:
    from benchctl.runner import runs

    action = args.runs_command or "list"
    if action == "list":
        return print_lines(runs.list_lines(args.out))
    if action == "compare":
        return print_lines(runs.compare_lines(_folders(args)))
    if bool(args.runs) == (args.older_than is not None):
        raise BadValueError("name the runs to remove, or give --older-than DAYS (not both)")
    folders = _folders(args) if args.runs else runs.older_than(args.out, args.older_than)
    if not folders:
        return print_lines([f"no runs in {args.out} older than {args.older_than:g} days"])
    return print_lines(runs.remove_runs(folders, args.out, args.yes, args.force))


def _days(text: str) -> float:
    try:
        value = float(text.removesuffix("d"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of days such as 30 or 30d, got {text!r}") from None
    if not value >= 0:
        raise argparse.ArgumentTypeError(f"must be >= 0 days, got {text!r}")
    return value


def add_commands(sub: argparse._SubParsersAction) -> None:
    """Add this group's sub-commands to the `benchctl` sub-parsers (importing nothing heavy)."""
    runs = sub.add_parser("runs", help="run folders: list them, compare their scores, remove old ones",
                          description="The run folders under runs/ (or --out): procedure, profile, how each ended, "
                                      "size and headline; their scores (PSNR, SSIM, residuals, RMS errors from "
                                      "metrics.json) side by side; removing old ones. Listing and comparing change "
                                      "nothing.")
    runs.add_argument("--out", "-o", type=Path, default=Path("runs"), metavar="DIR",
                      help="where the run folders are (default: runs/)")
    runs.set_defaults(func=_cmd_runs, runs_command=None)
    actions = runs.add_subparsers(dest="runs_command", metavar="ACTION")
    listing = actions.add_parser("list", help="one line per run (the default)")
    compare = actions.add_parser("compare", help="the runs' scores side by side")
    compare.add_argument("runs", nargs="+", metavar="RUN", help="run folders (paths, or names under --out)")
    remove = actions.add_parser("remove", help="remove run folders (listed only, until --yes)")
    remove.add_argument("runs", nargs="*", metavar="RUN",
                        help="run folders directly under --out (paths, or their names); nothing else is removed")
    remove.add_argument("--older-than", type=_days, metavar="DAYS", help="every run that started more than DAYS ago")
    remove.add_argument("--yes", action="store_true", help="remove them (without it, only say what would go)")
    remove.add_argument("--force", action="store_true",
                        help="also runs without a stop record (one may still be running)")
    for parser in (listing, compare, remove):  # --out after the action too; SUPPRESS keeps one given before it
        parser.add_argument("--out", "-o", type=Path, default=argparse.SUPPRESS, metavar="DIR",
                            help="where the run folders are (default: runs/)")
        parser.set_defaults(func=_cmd_runs)
