"""What is plugged in, for `benchctl devices`: serial ports, PTP cameras on USB, GenICam cameras (Aravis),
framebuffers and desktop outputs (SLM candidates).

Each part is looked up on its own and a part that cannot be scanned says why (no libusb backend, no
permission) instead of failing the whole listing. Returns plain data; the command line formats it.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import serial.tools.list_ports
import usb.core

from benchctl.devices.camera.aravis import GenicamInfo, genicam_cameras
from benchctl.devices.camera.ptp.transport import NO_BACKEND, ptp_interface
from benchctl.devices.errors import DeviceError
from benchctl.devices.slm.desktop import DesktopOutput, connect, desktop_outputs


@dataclass(frozen=True)
class SerialPortInfo:
    device: str  # e.g. /dev/ttyUSB0
    description: str
    hwid: str


@dataclass(frozen=True)
class UsbCameraInfo:
    """A USB device with a Still Image (PTP) interface; names are None where the device cannot be read."""

    usb_id: str  # vendor:product, as camera.usb_id takes it
    bus: int | None
    address: int | None
    manufacturer: str | None = None
    product: str | None = None
    serial: str | None = None


@dataclass(frozen=True)
class FramebufferInfo:
    device: str  # /dev/fbN
    name: str | None  # the driver's name for it (sysfs `name`)
    width: int | None
    height: int | None
    bits_per_pixel: int | None


@dataclass(frozen=True)
class Discovery:
    """Everything found; `usb_error` says why USB could not be scanned (then `cameras` is empty)."""

    serial_ports: list[SerialPortInfo] = field(default_factory=list)
    cameras: list[UsbCameraInfo] = field(default_factory=list)
    usb_error: str | None = None
    framebuffers: list[FramebufferInfo] = field(default_factory=list)
    genicam: list[GenicamInfo] = field(default_factory=list)
    genicam_error: str | None = None  # why GenICam cameras could not be listed (then `genicam` is empty)
    outputs: list[DesktopOutput] = field(default_factory=list)  # monitors of the X11 desktop ($DISPLAY)
    outputs_error: str | None = None


def serial_ports() -> list[SerialPortInfo]:
    return [SerialPortInfo(port.device, port.description, port.hwid) for port in serial.tools.list_ports.comports()]


def _read_string(device: Any, attribute: str) -> str | None:
    """A USB string descriptor, or None (reading needs access to the device)."""
    try:
        value = getattr(device, attribute)
    except (usb.core.USBError, ValueError, NotImplementedError):
        return None
    return None if value is None else str(value)


def usb_cameras(find: Callable[..., Iterable[Any]] = usb.core.find) -> tuple[list[UsbCameraInfo], str | None]:
    """PTP devices on USB (interface class 6), and None; or [] and the reason USB cannot be scanned."""
    try:
        devices = list(find(find_all=True))
    except usb.core.NoBackendError:
        return [], NO_BACKEND
    except usb.core.USBError as exc:
        return [], f"cannot scan USB: {exc}"
    cameras = []
    for device in devices:
        try:
            if ptp_interface(device) is None:
                continue
        except usb.core.USBError:
            continue  # descriptors unreadable: not something we could drive either
        cameras.append(UsbCameraInfo(f"{device.idVendor:04x}:{device.idProduct:04x}", device.bus, device.address,
                                     _read_string(device, "manufacturer"), _read_string(device, "product"),
                                     _read_string(device, "serial_number")))
    return cameras, None


def _read_int(path: Path) -> int | None:
    try:
        return int(path.read_text().strip())
    except (OSError, ValueError):
        return None


def framebuffers(sys_root: Path = Path("/sys"), dev_root: Path = Path("/dev")) -> list[FramebufferInfo]:
    """Framebuffer devices from sysfs (class/graphics/fbN), with their virtual size and depth."""
    found = []
    graphics = sys_root / "class" / "graphics"
    entries = [p for p in graphics.glob("fb*") if re.fullmatch(r"fb\d+", p.name)] if graphics.is_dir() else []
    for entry in sorted(entries, key=lambda p: int(p.name[2:])):
        width = height = None
        try:
            width, height = (int(v) for v in (entry / "virtual_size").read_text().strip().split(","))
        except (OSError, ValueError):
            pass
        try:
            name: str | None = (entry / "name").read_text().strip() or None
        except OSError:
            name = None
        found.append(FramebufferInfo(str(dev_root / entry.name), name, width, height,
                                     _read_int(entry / "bits_per_pixel")))
    return found


def genicam() -> tuple[list[GenicamInfo], str | None]:
    """GenICam cameras and None; or [] and why they cannot be listed (Aravis missing)."""
    try:
        return genicam_cameras(), None
    except DeviceError as exc:
        return [], str(exc)


def desktop() -> tuple[list[DesktopOutput], str | None]:
    """The outputs of the X11 desktop ($DISPLAY) and None; or [] and why they cannot be read."""
    try:
        display = connect(None)
    except DeviceError as exc:
        return [], str(exc)
    try:
        return desktop_outputs(display), None
    except DeviceError as exc:
        return [], str(exc)
    finally:
        display.close()


def discover(sys_root: Path = Path("/sys"), dev_root: Path = Path("/dev"),
             find_usb: Callable[..., Iterable[Any]] = usb.core.find) -> Discovery:
    """Serial ports, USB PTP cameras (or why USB cannot be scanned), GenICam cameras and framebuffers."""
    cameras, usb_error = usb_cameras(find_usb)
    found_genicam, genicam_error = genicam()
    outputs, outputs_error = desktop()
    return Discovery(serial_ports(), cameras, usb_error, framebuffers(sys_root, dev_root), found_genicam,
                     genicam_error, outputs, outputs_error)
