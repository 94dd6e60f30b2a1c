"""What every command group shares: argument types, the --profile option, the epilog, line printing."""

from __future__ import annotations

import argparse
import math
import re
from collections.abc import Callable, Iterable
from typing import Any

import benchctl
from benchctl.limits import MAX_PIXELS_ENV, max_pixels

EPILOG = """targets: a bundled chart or photo (see `benchctl targets`) such as chart:siemens or photo:coffee, or an
image file.
profiles: a path to a TOML file or a name in hardware_profiles/ (default: simulated, or $BENCHCTL_PROFILE)."""


def grid_size(text: str) -> tuple[int, int]:
    """An `HxW` grid such as 1088x1920, as (rows, cols)."""
    try:
        rows, cols = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must look like 1088x1920 (rows x cols), got {text!r}") from None
    if rows < 1 or cols < 1:
        raise argparse.ArgumentTypeError(f"size must be positive, got {text!r}")
    limit = max_pixels()
    if rows * cols > limit:
        raise argparse.ArgumentTypeError(f"{text}: {rows * cols:,} pixels is above the limit of {limit:,} (set "
                                         f"${MAX_PIXELS_ENV} to raise it)")
    return rows, cols


def int_list(text: str) -> tuple[int, ...]:
    """Comma-separated iteration counts such as 10,50,200 (each >= 1)."""
    try:
        values = tuple(int(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers like 10,50,200, got {text!r}") from None
    if any(v < 1 for v in values):
        raise argparse.ArgumentTypeError(f"iteration counts must be >= 1, got {text!r}")
    return values


def name_list(text: str) -> list[str]:
    """Comma-separated names such as red,green (blanks dropped)."""
    return [v.strip() for v in text.split(",") if v.strip()]


def whole_number(minimum: int, maximum: int | None = None) -> Callable[[str], int]:
    """The argument type of a whole number >= `minimum` (and <= `maximum`)."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
        if value < minimum or (maximum is not None and value > maximum):
            bound = f"lie between {minimum} and {maximum}" if maximum is not None else f"be >= {minimum}"
            raise argparse.ArgumentTypeError(f"must {bound}, got {value}")
        return value

    return parse


def seconds(text: str) -> float:
    """The argument type of a time in seconds: a finite number above 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of seconds, got {text!r}") from None
    if not 0 < value < math.inf:
        raise argparse.ArgumentTypeError(f"must be a finite number of seconds above 0, got {text!r}")
    return value


def device_name(text: str) -> str:
    """The argument type of --device: auto, cpu, cuda or cuda:N (whether it is here is checked where it is used)."""
    from benchctl.errors import BadValueError
    from benchctl.training.device import check_device_text

    try:
        return check_device_text(text)
    except BadValueError as exc:
        raise argparse.ArgumentTypeError(str(exc).split(": ", 1)[1]) from None


def add_device(parser: argparse.ArgumentParser) -> None:
    """The --device option of the commands that train."""
    parser.add_argument("--device", type=device_name, default="cpu", metavar="DEVICE",
                        help="auto (the first GPU where there is one, else the CPU), cpu, cuda or cuda:N "
                             "(default: cpu)")


count = whole_number(0)
seed_number = whole_number(0, 2**32 - 1)  # numpy's generators take seeds in this range
positive_int = whole_number(1)
port = whole_number(0, 65535)


def plane_count(text: str) -> int | str:
    """The argument type of --planes: "auto" (the planes a scene's depth needs) or a whole number >= 1."""
    if text == "auto":
        return text
    try:
        return positive_int(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"expected 'auto' or a whole number of planes >= 1, got {text!r}") from None


class Parser(argparse.ArgumentParser):
    """benchctl's argument parser: a value that starts with '-' and a digit ('-5mW', '-3x4') is read as a value, so
    that its own check says what is wrong ("is negative") instead of argparse's "expected one argument" (argparse
    reads only plain negative numbers so; no benchctl option starts with '-' and a digit)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = re.compile(r"^-\.?\d")


class VersionAction(argparse.Action):
    """--version, reading the installed metadata only when asked (building the parser must stay cheap)."""

    def __call__(self, parser: argparse.ArgumentParser, *_: object) -> None:
        parser.exit(message=f"benchctl {benchctl.__version__}\n")


def add_profile(parser: argparse.ArgumentParser) -> None:
    """The --profile option every command that opens a bench takes."""
    parser.add_argument("--profile", "-p", metavar="P",
                        help="hardware profile: TOML path or name in hardware_profiles/ (default: simulated)")


def print_lines(lines: Iterable[str]) -> int:
    """Print `lines` one per line, each as it comes (a command may yield them as it works); exit code 0."""
    for line in lines:
        print(line, flush=True)
    return 0
