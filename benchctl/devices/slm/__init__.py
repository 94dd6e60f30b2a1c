"""Phase SLMs: the `SLM` interface, its drivers (benchctl.drivers lists them) and lookup-table files.

`open_slm(profile)` builds the driver the profile's [slm] section names and opens it:

    with open_slm(profile) as slm:
        slm.show_phase(phase, "green")
"""

from __future__ import annotations

from benchctl.devices.slm.base import SLM, Showing
from benchctl.devices.slm.lut import load_lut, lut_for, save_lut
from benchctl.drivers import driver_class
from benchctl.profiles import Profile

__all__ = ["SLM", "Showing", "load_lut", "lut_for", "open_slm", "save_lut", "slm_for"]


def slm_for(profile: Profile) -> SLM:
    """The profile's SLM driver, not yet opened: enough to encode and decode frames without the panel."""
    driver: type[SLM] = driver_class("slm", profile.section("slm").driver)
    return driver.for_profile(profile)


def open_slm(profile: Profile) -> SLM:
    """The profile's SLM, opened (use it as a context manager so it is closed again)."""
    return slm_for(profile).open()
