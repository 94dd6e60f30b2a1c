"""Lasers: the Laser API (base.py) and its drivers, chosen by `driver` in the profile's [laser] section.

    with open_laser(profile) as laser:      # connected; emission off on every channel
        laser.set_power("green", "2mW")     # refused above the channel's max_power_mw; read back
        laser.set_emission("green", True)   # interlock and faults checked first
    # leaving the block (also by an exception or Ctrl-C) turns emission off on every channel
"""

from __future__ import annotations

from benchctl.devices.laser.base import UNKNOWN_EMISSION, ChannelStatus, Laser, PortFactory
from benchctl.devices.laser.cobolt import CoboltLaser
from benchctl.devices.laser.obis import ObisLaser
from benchctl.devices.laser.template import TemplateLaser
from benchctl.drivers import driver_class
from benchctl.profiles import LaserConfig, Profile

__all__ = ["UNKNOWN_EMISSION", "ChannelStatus", "CoboltLaser", "Laser", "ObisLaser", "TemplateLaser", "open_laser"]


def open_laser(profile_or_config: Profile | LaserConfig, *, leave_on: bool = False, observe: bool = False,
               port_factory: PortFactory | None = None) -> Laser:
    """The profile's laser, connected and made safe (see Laser.open; `observe`: connected to read only);
    use it in a `with` block."""
    if isinstance(profile_or_config, Profile):
        config = profile_or_config.require("laser").laser
        assert config is not None
    else:
        config = profile_or_config
    driver: type[Laser] = driver_class("laser", config.driver)
    laser = driver(config, leave_on=leave_on, observe=observe, port_factory=port_factory)
    return laser.open()
