"""The one exception type that means "the user asked for something wrong" (shown as one line, no traceback), and
the hint such a line gives for a misspelt name."""

from __future__ import annotations

import difflib
from collections.abc import Callable, Iterable


class BenchctlError(Exception):
    """A user-facing error: bad file, key, value or device state. The message names what is wrong."""


class BadValueError(BenchctlError, ValueError):
    """A value a user chose (method name, iteration count, seed) is not acceptable; also a ValueError for APIs."""


def did_you_mean(name: str, known: Iterable[str], key: Callable[[str], str] = str) -> str:
    """" (did you mean 'dpac'?)" for the closest of `known` to a misspelt `name`, compared by `key` (e.g. without
    a prefix all share) with difflib's ratio >= 0.7, else ""."""
    choices = {key(choice): choice for choice in known}
    close = difflib.get_close_matches(key(str(name)), list(choices), n=1, cutoff=0.7)
    return f" (did you mean {choices[close[0]]!r}?)" if close else ""
