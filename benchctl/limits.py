"""Size limits on what users hand in, so a bad file or value gets one line instead of exhausting memory.

One pixel limit covers decoded images (checked from the file's header before anything is decoded: benchctl.images
reads only formats whose header gives the size) and the SLM grid: 64 Mpx by default (an 8K grid, 4352 x 7680, is
33 Mpx). $BENCHCTL_MAX_PIXELS raises (or lowers) it.
"""

from __future__ import annotations

import os

from benchctl.errors import BadValueError

MAX_PIXELS_ENV = "BENCHCTL_MAX_PIXELS"
DEFAULT_MAX_PIXELS = 64 * 1024 * 1024


def max_pixels() -> int:
    """The pixel limit in effect ($BENCHCTL_MAX_PIXELS, else DEFAULT_MAX_PIXELS)."""
    text = os.environ.get(MAX_PIXELS_ENV)
    if not text:
        return DEFAULT_MAX_PIXELS
    if not text.isdigit() or int(text) < 1:
        raise BadValueError(f"${MAX_PIXELS_ENV} must be a whole number of pixels >= 1, got {text!r}")
    return int(text)


def check_pixels(what: str, height: int, width: int) -> None:
    """BadValueError naming `what` if height x width exceeds the pixel limit; says how to raise the limit."""
    limit = max_pixels()
    if height * width > limit:
        raise BadValueError(f"{what}: {height} x {width} = {height * width:,} pixels is above the limit of "
                            f"{limit:,} (set ${MAX_PIXELS_ENV} to raise it)")

