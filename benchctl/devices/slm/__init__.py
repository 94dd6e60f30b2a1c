"""Phase SLMs: the `SLM` interface, its drivers (simulated panel, Linux framebuffer) and lookup-table files.

`open_slm(profile)` builds the driver the profile's [slm] section names and opens it:

    with open_slm(profile) as slm:
        slm.show_phase(phase, "green")
"""

from __future__ import annotations

from benchctl.devices.slm.base import SLM
from benchctl.devices.slm.framebuffer import FramebufferGeometry, FramebufferSLM
from benchctl.devices.slm.lut import load_lut, lut_for, save_lut
from benchctl.devices.slm.sim import SimSLM, read_displayed
from benchctl.errors import BadValueError
from benchctl.profiles import Profile

DRIVERS: dict[str, type[SLM]] = {SimSLM.driver: SimSLM, FramebufferSLM.driver: FramebufferSLM}

__all__ = [
    "DRIVERS",
    "SLM",
    "FramebufferGeometry",
    "FramebufferSLM",
    "SimSLM",
    "load_lut",
    "lut_for",
    "open_slm",
    "read_displayed",
    "save_lut",
    "slm_for",
]


def slm_for(profile: Profile) -> SLM:
    """The profile's SLM driver, not yet opened: enough to encode and decode frames without the panel."""
    config = profile.require("slm").slm
    assert config is not None
    if config.driver not in DRIVERS:
        raise BadValueError(f"{profile.path}: slm.driver {config.driver!r} unknown (choose from {', '.join(DRIVERS)})")
    channels = [channel.name for channel in profile.channels]
    if config.driver == SimSLM.driver:
        return SimSLM(config, channels, profile.sim.slm)  # the simulated panel also knows its true response
    return DRIVERS[config.driver](config, channels)


def open_slm(profile: Profile) -> SLM:
    """The profile's SLM, opened (use it as a context manager so it is closed again)."""
    return slm_for(profile).open()
