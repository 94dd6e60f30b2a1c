"""Every device driver benchctl has, by device kind and name: the one list a profile's `driver` key is checked
against (benchctl.profiles) and the one place a driver class is found by that name (`driver_class`).

A driver is named by its module and class, not imported here: a command imports only the driver its profile
chooses, so `benchctl laser off` never loads a camera library, and a driver whose optional library is missing
(Aravis, python-gphoto2, python-xlib) fails only where it is chosen. Adding a driver is one line here.
"""

from __future__ import annotations

import importlib
from typing import Literal

Kind = Literal["laser", "slm", "camera", "focus"]

DRIVERS: dict[str, dict[str, str]] = {
    "laser": {
        "template": "benchctl.devices.laser.template:TemplateLaser",
        "cobolt": "benchctl.devices.laser.cobolt:CoboltLaser",
        "obis": "benchctl.devices.laser.obis:ObisLaser",
        "sapphire": "benchctl.devices.laser.sapphire:SapphireLaser",
        "deepstar": "benchctl.devices.laser.deepstar:DeepstarLaser",
    },
    "slm": {
        "sim": "benchctl.devices.sim.slm:SimSLM",
        "framebuffer": "benchctl.devices.slm.framebuffer:FramebufferSLM",
        "display": "benchctl.devices.slm.display:DisplaySLM",
    },
    "camera": {
        "sim": "benchctl.devices.sim.camera:SimCamera",
        "ptp": "benchctl.devices.camera.ptp_camera:PtpCamera",
        "gphoto2": "benchctl.devices.camera.gphoto2:Gphoto2Camera",
        "genicam": "benchctl.devices.camera.genicam:GenicamCamera",
    },
    "focus": {
        "zaber": "benchctl.devices.focus.zaber:ZaberFocus",
        "eos": "benchctl.devices.focus.eos:EosFocus",
    },
}


def driver_names(kind: Kind) -> tuple[str, ...]:
    """The driver names a profile may give for `kind`, in the order listed above."""
    return tuple(DRIVERS[kind])


def driver_class(kind: Kind, name: str) -> type:
    """The class of driver `name` for `kind`, imported now. Profiles are checked against DRIVERS when they load,
    so an unknown name here is a programming error (KeyError)."""
    module, _, attribute = DRIVERS[kind][name].partition(":")
    found: type = getattr(importlib.import_module(module), attribute)
    return found
