"""Power strings: every accepted form, every refusal a BadValueError naming the value, properties by hypothesis."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from benchctl.devices.power import format_power, parse_power
from benchctl.errors import BadValueError, BenchctlError


@pytest.mark.parametrize(("text", "watts"), [
    ("20mW", 0.02), ("20 mW", 0.02), ("0.02W", 0.02), (" 0.02 W ", 0.02), ("20uW", 2e-5), ("20 \u00b5W", 2e-5),
    ("5%", 0.002), ("5 %", 0.002), ("100%", 0.04), ("0mW", 0.0), ("2e-3 W", 0.002), ("+1.5mW", 0.0015),
])
def test_accepted_forms(text: str, watts: float) -> None:
    assert parse_power(text, max_mw=40) == pytest.approx(watts, rel=1e-12, abs=0)


@pytest.mark.parametrize(("value", "says"), [
    ("20", "no unit"), (20.0, "no unit"), (0.02, "no unit"), ("", "empty"), ("   ", "empty"), ("-1mW", "negative"),
    ("nan mW", "not a finite"), ("inf W", "not a finite"), ("mW", "cannot read"), ("twenty mW", "cannot read"),
    ("20 MW", "cannot read"), ("20 m W", "cannot read"), ("5%%", "cannot read"),
])
def test_refusals_name_the_value(value: str | float, says: str) -> None:
    with pytest.raises(BadValueError) as info:
        parse_power(value, max_mw=40)
    message = str(info.value)
    assert says in message and repr(value) in message and "\n" not in message
    if says == "no unit":
        assert '"20mW"' in message and '"5%"' in message  # examples of what to write instead


def test_format_picks_a_readable_unit() -> None:
    assert format_power(0.02) == "20 mW"
    assert format_power(1.5) == "1.5 W"
    assert format_power(2e-5) == "20 uW"
    assert format_power(0.0) == "0 mW"


@settings(max_examples=300, deadline=None)
@given(st.floats(min_value=0, max_value=1e4, allow_nan=False, allow_infinity=False))
def test_format_then_parse_round_trips(watts: float) -> None:
    assert parse_power(format_power(watts), max_mw=1) == pytest.approx(watts, rel=1e-5, abs=1e-300)


@settings(max_examples=300, deadline=None)
@given(st.floats(min_value=0, max_value=1000), st.floats(min_value=1e-3, max_value=1e5))
def test_percent_agrees_with_milliwatts(percent: float, max_mw: float) -> None:
    as_percent = parse_power(f"{percent!r}%", max_mw=max_mw)
    as_mw = parse_power(f"{percent * max_mw / 100!r} mW", max_mw=max_mw)
    assert as_percent == pytest.approx(as_mw, rel=1e-9, abs=1e-300)


@settings(max_examples=500, deadline=None)
@given(st.one_of(st.text(), st.text(alphabet="0123456789.-+eE %mWu\u00b5 nainf"), st.floats(), st.integers()))
def test_garbage_only_ever_raises_the_documented_error(value: str | float) -> None:
    try:
        watts = parse_power(value, max_mw=40)  # type: ignore[arg-type]
    except BadValueError as exc:
        assert isinstance(exc, BenchctlError) and "\n" not in str(exc)
    else:
        assert isinstance(value, str) and math.isfinite(watts) and watts >= 0
