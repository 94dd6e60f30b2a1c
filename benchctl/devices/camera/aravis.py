"""Aravis (the GenICam library: GigE Vision and USB3 Vision cameras) through GObject introspection, loaded on
first use, and the GenICam cameras it finds.

Aravis is an optional system library: without it (or without PyGObject) the genicam driver and `benchctl
devices` say in one line what to install. `$BENCHCTL_ARAVIS_INTERFACES` (comma-separated, e.g. "USB3Vision" or
"Fake") limits which Aravis interfaces are scanned: GigE Vision discovery broadcasts on every network interface,
which a lab may not want, and tests scan Aravis's in-process fake camera only.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from types import ModuleType

from benchctl.devices.errors import DeviceError

INTERFACES_ENV = "BENCHCTL_ARAVIS_INTERFACES"
INSTALL_HINT = ("sudo apt install gir1.2-aravis-0.8 libgirepository1.0-dev libcairo2-dev pkg-config, then "
                "pip install 'benchctl[genicam]'")


def aravis() -> ModuleType:
    """The Aravis 0.8 module (gi.repository.Aravis) with the interfaces $BENCHCTL_ARAVIS_INTERFACES names enabled
    (all of Aravis's defaults when unset); DeviceError saying what to install when it is missing."""
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis
    except (ImportError, ValueError) as exc:
        raise DeviceError(f"GenICam cameras need Aravis 0.8 through PyGObject ({exc}): {INSTALL_HINT}") from None
    wanted = os.environ.get(INTERFACES_ENV)
    if wanted is not None:
        names = {name.strip() for name in wanted.split(",") if name.strip()}
        known = {Aravis.get_interface_id(i) for i in range(Aravis.get_n_interfaces())}
        unknown = names - known
        if unknown:
            raise DeviceError(f"${INTERFACES_ENV}: unknown Aravis interface(s) {', '.join(sorted(unknown))} "
                              f"(known: {', '.join(sorted(known))})")
        for name in known:
            (Aravis.enable_interface if name in names else Aravis.disable_interface)(name)
    return Aravis


@dataclass(frozen=True)
class GenicamInfo:
    """A GenICam camera Aravis found, as the device list names it (no connection made)."""

    device_id: str
    vendor: str
    model: str
    serial: str
    protocol: str  # GigEVision, USB3Vision, Fake
    address: str


def genicam_cameras() -> list[GenicamInfo]:
    """The GenICam cameras Aravis finds now, on the interfaces enabled (see `aravis`)."""
    module = aravis()
    module.update_device_list()
    return [GenicamInfo(module.get_device_id(i), module.get_device_vendor(i) or "", module.get_device_model(i) or "",
                        module.get_device_serial_nbr(i) or "", module.get_device_protocol(i) or "",
                        module.get_device_address(i) or "")
            for i in range(module.get_n_devices())]
