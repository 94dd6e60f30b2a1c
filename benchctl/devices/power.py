"""Laser power as people write it ("20mW", "0.02 W", "5%") and as code keeps it (watts, a float).

A bare number is refused: "20" could be watts, milliwatts or percent, and guessing wrong with a laser is how
people get hurt. Every refusal is a BadValueError naming the value and showing the accepted forms.
"""

from __future__ import annotations

import math
import re

from benchctl.errors import BadValueError

EXAMPLES = '"20mW", "20 mW", "0.02W", "500uW" or "5%" (of the channel\'s max power)'
# Unit -> units per watt (dividing keeps "20uW" exactly 2e-05); "%" is relative to the channel's max power.
_PER_WATT = {"W": 1.0, "mW": 1e3, "uW": 1e6, "\N{MICRO SIGN}W": 1e6, "\N{GREEK SMALL LETTER MU}W": 1e6}
_VALUE = re.compile(r"\s*(?P<number>.*?)\s*(?P<unit>%|[m\N{MICRO SIGN}\N{GREEK SMALL LETTER MU}u]?W)\s*")


def parse_power(text: str | float, max_mw: float) -> float:
    """`text` as watts: "20mW", "20 mW", "0.02W", "20uW", or "5%" of `max_mw`.

    Raises BadValueError for a bare number (ambiguous), a negative, NaN or infinite value, an empty string,
    or anything else it cannot read. The limit itself is not checked here (Laser.set_power does that).
    """
    if not isinstance(text, str):
        raise BadValueError(f"power {text!r} has no unit: write it as {EXAMPLES}")
    if not text.strip():
        raise BadValueError(f"power {text!r} is empty: write it as {EXAMPLES}")
    match = _VALUE.fullmatch(text)
    if match is None:
        try:
            float(text)
        except ValueError:
            raise BadValueError(f"cannot read power {text!r}: write it as {EXAMPLES}") from None
        raise BadValueError(f"power {text!r} has no unit (W, mW or %?): write it as {EXAMPLES}")
    number, unit = match["number"], match["unit"]
    try:
        value = float(number) + 0.0  # + 0.0 turns -0.0 into 0.0
    except ValueError:
        raise BadValueError(f"cannot read power {text!r}: write it as {EXAMPLES}") from None
    if not math.isfinite(value):
        raise BadValueError(f"power {text!r} is not a finite number")
    if value < 0:
        raise BadValueError(f"power {text!r} is negative")
    if unit == "%":
        return value * max_mw / 1e5
    return value / _PER_WATT[unit]


def format_power(watts: float) -> str:
    """`watts` for people, in the unit that keeps the number readable: "1.5 W", "20 mW", "500 uW"."""
    magnitude = abs(watts)
    if magnitude >= 1.0 or not math.isfinite(watts):
        return f"{watts:.6g} W"
    if magnitude >= 1e-3 or magnitude == 0.0:
        return f"{watts * 1e3:.6g} mW"
    return f"{watts * 1e6:.6g} uW"
