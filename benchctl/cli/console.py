"""`benchctl console`: the live bench console, a local web page (needs the `console` extra)."""

from __future__ import annotations

import argparse
from pathlib import Path

from benchctl.cli.args import add_profile, port, seconds
from benchctl.errors import BenchctlError

DEFAULT_PORT = 8765


def deadman(text: str) -> float:
    """The argument type of --deadman: seconds above 0, at most the console's MAX_DEADMAN_S (minutes)."""
    from benchctl.console.laser import MAX_DEADMAN_S

    value = seconds(text)
    if value > MAX_DEADMAN_S:
        raise argparse.ArgumentTypeError(f"must be at most {MAX_DEADMAN_S:g} seconds (a dead-man switch that waits "
                                         f"longer guards nothing), got {text!r}")
    return value


def _cmd_console(args: argparse.Namespace) -> int:
    try:
        from benchctl.console.server import serve
    except ImportError as exc:
        raise BenchctlError(f"the console needs its extra ({exc.name} is missing): pip install 'benchctl[console]'")\
            from None
    from benchctl.profiles import load_profile

    procedures = args.procedures if args.procedures is not None else Path("procedures")
    serve(load_profile(args.profile), port=args.port, bind=args.bind, out=args.out,
          procedures=procedures if procedures.is_dir() else None, deadman_s=args.deadman)
    return 0


def add_commands(sub: argparse._SubParsersAction) -> None:
    """Add this group's sub-commands to the `benchctl` sub-parsers (importing nothing heavy)."""
    console = sub.add_parser(
        "console", help="live bench console in the browser: camera view, laser, SLM, capture, procedures",
        description="Start a local web server holding the profile's laser, SLM and camera, and print the URL of its "
                    "page (with a token made for this start). The page shows the camera's live view and controls "
                    "the laser, the SLM, RAW captures and procedures. Emission stays on only while a page is open "
                    "(dead-man switch) and is off when the console stops. `benchctl laser off` in another shell "
                    "stops the console with emission off.",
        epilog="security: only this computer can connect unless --bind says otherwise; every request needs the "
               "token; requests from other sites (CSRF, DNS rebinding) are refused by their Host and Origin.")
    add_profile(console)
    console.add_argument("--port", type=port, default=DEFAULT_PORT, metavar="N",
                         help=f"TCP port (default {DEFAULT_PORT}; 0 picks a free one)")
    console.add_argument("--bind", default="127.0.0.1", metavar="ADDRESS",
                         help="address to listen on (default 127.0.0.1, this computer only); another address lets "
                              "other computers reach the console and prints a warning")
    console.add_argument("--out", type=Path, default=Path("runs"), metavar="DIR",
                         help="where captures and procedure runs are written (default: runs/)")
    console.add_argument("--procedures", type=Path, metavar="DIR",
                         help="folder of procedure files the page offers (default: procedures/ if it exists)")
    console.add_argument("--deadman", type=deadman, default=3.0, metavar="SECONDS",
                         help="emission off when no page has been heard from for this long (default 3, at most "
                              "300)")
    console.set_defaults(func=_cmd_console)
