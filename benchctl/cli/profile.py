"""`benchctl profile check`: validate a hardware profile and print what it describes."""

from __future__ import annotations

import argparse


def _cmd_profile_check(args: argparse.Namespace) -> int:
    from benchctl.calibration.calibrated import Calibrated
    from benchctl.calibration.files import check_calibration
    from benchctl.calibration.geometry import describe_plans
    from benchctl.calibration.store import FOCUS_FILE, REGISTRATION_FILE, Calibration
    from benchctl.profiles import load_profile

    profile = load_profile(args.path)
    print(profile.describe())
    print(describe_plans(profile))
    registration, store = None, Calibration.store(profile)
    if profile.slm is not None and profile.optics is not None:  # what calibration/<profile>/ holds for its geometry
        profile, registration = Calibrated(profile, store).profile, store.folder / REGISTRATION_FILE
    for line in check_calibration(profile, registration, store.folder / FOCUS_FILE):
        print(line)
    print(f"{profile.path}: OK")
    return 0


def add_commands(sub: argparse._SubParsersAction) -> None:
    """Add this group's sub-commands to the `benchctl` sub-parsers (importing nothing heavy)."""
    profile = sub.add_parser("profile", help="hardware profiles").add_subparsers(
        dest="profile_command", metavar="ACTION", required=True)
    check = profile.add_parser("check", help="validate a profile and the calibration files it uses; print what it "
                                             "describes")
    check.add_argument("path", nargs="?", help="profile TOML path or name (default: simulated)")
    check.set_defaults(func=_cmd_profile_check)
