"""`benchctl devices` discovery: USB PTP cameras (or why USB cannot be scanned), serial ports, framebuffers."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import pytest
import serial.tools.list_ports
import usb.core

from benchctl.devices.camera.ptp.transport import NO_BACKEND
from benchctl.devices.discovery import (
    FramebufferInfo,
    UsbCameraInfo,
    discover,
    framebuffers,
    serial_ports,
    usb_cameras,
)


def test_discovery_on_this_machine_does_not_crash() -> None:
    found = discover()
    assert found.usb_error in (None, NO_BACKEND)  # no libusb here: the reason instead of an exception
    if found.usb_error is not None:
        assert found.cameras == []


def test_no_libusb_backend_is_reported() -> None:
    def no_backend(**_: object) -> list[object]:
        raise usb.core.NoBackendError("No backend available")

    cameras, error = usb_cameras(no_backend)
    assert cameras == [] and error == "no libusb backend: install libusb-1.0 (Debian/Ubuntu: sudo apt install " \
                                      "libusb-1.0-0)"


@dataclass
class FakeDevice:
    """Enough of a pyusb Device: ids, bus/address, interface classes, string descriptors (None: unreadable)."""

    idVendor: int
    idProduct: int
    classes: tuple[int, ...]
    names: tuple[str, str, str] | None = None
    bus: int = 1
    address: int = 7

    def __iter__(self) -> Iterator[list[SimpleNamespace]]:
        return iter([[SimpleNamespace(bInterfaceClass=c) for c in self.classes]])

    def _name(self, index: int) -> str:
        if self.names is None:
            raise ValueError("The device has no langid (permission issue, no string descriptors supported or "
                             "device error)")
        return self.names[index]

    manufacturer = property(lambda self: self._name(0))
    product = property(lambda self: self._name(1))
    serial_number = property(lambda self: self._name(2))


def test_ptp_cameras_are_found_by_interface_class() -> None:
    devices = [FakeDevice(0x04A9, 0x32A0, (6,), ("Canon Inc.", "Canon Digital Camera", "5A1C")),
               FakeDevice(0x0403, 0x6001, (0xFF,)),  # a USB-serial adapter
               FakeDevice(0x04A9, 0x3218, (6,), None, bus=2, address=3)]  # no permission to read its names
    cameras, error = usb_cameras(lambda **_: devices)
    assert error is None
    assert cameras == [UsbCameraInfo("04a9:32a0", 1, 7, "Canon Inc.", "Canon Digital Camera", "5A1C"),
                       UsbCameraInfo("04a9:3218", 2, 3, None, None, None)]


def test_usb_scan_error_is_reported() -> None:
    def failing(**_: object) -> list[object]:
        raise usb.core.USBError("Input/output error", -1, 5)

    assert usb_cameras(failing) == ([], "cannot scan USB: [Errno 5] Input/output error")


def make_fb(root: Path, name: str, size: str | None, bpp: str | None = "32", driver: str = "simple") -> None:
    folder = root / "class" / "graphics" / name
    folder.mkdir(parents=True)
    if size is not None:
        (folder / "virtual_size").write_text(size + "\n")
    if bpp is not None:
        (folder / "bits_per_pixel").write_text(bpp + "\n")
    (folder / "name").write_text(driver + "\n")


def test_framebuffers_from_a_fake_sys_root(tmp_path: Path) -> None:
    make_fb(tmp_path, "fb0", "3840,2160", driver="simpledrmdrmfb")
    make_fb(tmp_path, "fb10", "1920,1080", "16")
    make_fb(tmp_path, "fb2", None, None)
    (tmp_path / "class" / "graphics" / "fbcon").mkdir()  # the console, not a framebuffer
    assert framebuffers(tmp_path, Path("/dev")) == [
        FramebufferInfo("/dev/fb0", "simpledrmdrmfb", 3840, 2160, 32),
        FramebufferInfo("/dev/fb2", "simple", None, None, None),
        FramebufferInfo("/dev/fb10", "simple", 1920, 1080, 16)]


def test_no_graphics_class_means_no_framebuffers(tmp_path: Path) -> None:
    assert framebuffers(tmp_path) == []


def test_serial_ports_and_full_discovery(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    port = SimpleNamespace(device="/dev/ttyUSB0", description="FT232R USB UART", hwid="USB VID:PID=0403:6001")
    monkeypatch.setattr(serial.tools.list_ports, "comports", lambda: [port])
    make_fb(tmp_path, "fb1", "1920,1080")
    found = discover(tmp_path, Path("/dev"), lambda **_: [FakeDevice(0x04A9, 0x32A0, (6,))])
    assert [p.device for p in serial_ports()] == ["/dev/ttyUSB0"]
    assert [p.device for p in found.serial_ports] == ["/dev/ttyUSB0"]
    assert [c.usb_id for c in found.cameras] == ["04a9:32a0"] and found.usb_error is None
    assert [f.device for f in found.framebuffers] == ["/dev/fb1"]
