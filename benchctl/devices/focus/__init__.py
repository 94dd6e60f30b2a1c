"""The camera's focus: the `Focus` interface and its drivers (benchctl.drivers lists them), chosen by `driver` in the
profile's [focus] section.

    with open_focus(profile) as focus:
        focus.home()
        focus.move_to(1200, approach=+1, overshoot=400)   # arrive moving up, past the backlash
"""

from __future__ import annotations

from benchctl.devices.focus.base import Focus, FocusMove
from benchctl.drivers import driver_class
from benchctl.profiles import Profile

__all__ = ["Focus", "FocusMove", "focus_for", "open_focus"]


def focus_for(profile: Profile) -> Focus:
    """The profile's focus driver, not yet connected."""
    driver: type[Focus] = driver_class("focus", profile.section("focus").driver)
    return driver.for_profile(profile)


def open_focus(profile: Profile) -> Focus:
    """The profile's focus, opened (use it as a context manager so it is closed again)."""
    return focus_for(profile).open()
