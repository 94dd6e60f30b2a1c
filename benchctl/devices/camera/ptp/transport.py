"""Moving PTP containers over USB (Still Image class, interface class 6): bulk out, bulk in, interrupt in.

This layer knows bytes and endpoints, nothing of operations. It writes one container per bulk transfer and
follows it with a zero-length packet when its length is a multiple of the endpoint's wMaxPacketSize (else the
camera keeps waiting for the end of the transfer); it reads a container in chunks until the length in its
first u32 is complete, skipping a zero-length packet left over from the previous one.

`Transport` is what the protocol layer talks to, so a simulated camera can stand in for the USB one.
Transports raise pyusb's exceptions (USBError, USBTimeoutError) for USB failures; `usb_failure` turns one into
the one-line DeviceError the user sees, and is applied where transports are used (the session).
"""

from __future__ import annotations

import errno
import struct
from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import Any, Protocol

import usb.core
import usb.util

from benchctl.devices.camera.hints import NOT_FOUND_HINT, PERMISSION_HINT, USB_GRABBED_HINT
from benchctl.devices.errors import DeviceBusy, DeviceError, DeviceTimeout
from benchctl.errors import BadValueError

PTP_INTERFACE_CLASS = 6  # USB Still Image class
CHUNK_SIZE = 1 << 20  # bytes asked for per bulk-in read (a multiple of every wMaxPacketSize)
MAX_CONTAINER_BYTES = 512 << 20  # a container longer than this is garbage: the largest RAW files are ~100 MB
NO_BACKEND = "no libusb backend: install libusb-1.0 (Debian/Ubuntu: sudo apt install libusb-1.0-0)"
_NO_DEVICE = -4  # LIBUSB_ERROR_NO_DEVICE


class Endpoint(Protocol):
    """The part of a pyusb endpoint the transport uses (test doubles need only these)."""

    wMaxPacketSize: int

    def write(self, data: bytes, timeout: int | None = None) -> int: ...

    def read(self, size_or_buffer: int, timeout: int | None = None) -> Any: ...


class Transport(ABC):
    """Sends and receives whole PTP containers (as bytes); raises pyusb's exceptions on USB failures."""

    usb_vendor: int | None = None  # the USB vendor id of the device at the other end, where known

    @abstractmethod
    def send(self, container: bytes) -> None:
        """Write one container to the camera."""

    @abstractmethod
    def receive(self) -> bytes:
        """Read one container from the camera (raises USBTimeoutError when none comes)."""

    @abstractmethod
    def receive_event(self, timeout_s: float) -> bytes | None:
        """One event container from the interrupt endpoint, or None if none arrives within `timeout_s`."""

    @abstractmethod
    def close(self) -> None:
        """Release the device; never raises for a device that is already gone."""


def usb_failure(exc: usb.core.USBError, doing: str, timeout_s: float | None = None) -> DeviceError:
    """The DeviceError to show for a pyusb error raised while `doing` (e.g. 'GetPartialObject')."""
    waited = f" within {timeout_s:g} s" if timeout_s is not None else ""
    if isinstance(exc, usb.core.USBTimeoutError) or exc.errno == errno.ETIMEDOUT:
        return DeviceTimeout(f"camera did not answer {doing}{waited}: it stopped responding; power-cycle it "
                             f"and reconnect")
    if exc.errno == errno.ENODEV or exc.backend_error_code == _NO_DEVICE:
        return DeviceError(f"camera disconnected during {doing}: USB cable pulled or camera switched off; "
                           f"reconnect it and run again")
    if exc.errno in (errno.EACCES, errno.EPERM):
        return DeviceError(f"permission denied on the camera's USB device while {doing}: {PERMISSION_HINT}")
    if exc.errno == errno.EBUSY:
        return DeviceBusy(f"camera's USB interface is held by another program while {doing}: {USB_GRABBED_HINT}")
    return DeviceError(f"USB error during {doing}: {exc}")


def parse_usb_id(usb_id: str) -> tuple[int, int]:
    """'04a9:32a0' -> (0x04a9, 0x32a0)."""
    try:
        vendor, product = (int(part, 16) for part in usb_id.split(":"))
    except ValueError:
        raise BadValueError(f"camera usb_id {usb_id!r} is not vendor:product in hex, e.g. 04a9:32a0") from None
    return vendor, product


def ptp_interface(device: Any) -> Any | None:
    """The first Still Image (PTP) interface of `device`'s configurations, or None."""
    for configuration in device:
        for interface in configuration:
            if interface.bInterfaceClass == PTP_INTERFACE_CLASS:
                return interface
    return None


class UsbTransport(Transport):
    """PTP over a USB device's bulk and interrupt endpoints (pyusb). `usb_vendor`: the device's USB vendor id, which
    the protocol layer needs (a Canon body is known by it where it reports another PTP vendor extension)."""

    def __init__(self, bulk_out: Endpoint, bulk_in: Endpoint, interrupt_in: Endpoint | None = None, *,
                 usb_vendor: int, timeout_s: float = 10.0, chunk_size: int = CHUNK_SIZE,
                 on_close: Callable[[], None] | None = None) -> None:
        self.usb_vendor = usb_vendor
        self.bulk_out = bulk_out
        self.bulk_in = bulk_in
        self.interrupt_in = interrupt_in
        self.timeout_s = timeout_s
        self.chunk_size = chunk_size
        self._on_close = on_close

    @classmethod
    def open(cls, usb_id: str, timeout_s: float = 10.0) -> UsbTransport:
        """Find the camera `usb_id` ('vendor:product'), claim its PTP interface and pick its endpoints."""
        vendor, product = parse_usb_id(usb_id)
        try:
            device = usb.core.find(idVendor=vendor, idProduct=product)
        except usb.core.NoBackendError:
            raise DeviceError(NO_BACKEND) from None
        if device is None:
            raise DeviceError(f"camera {usb_id} not found on USB: {NOT_FOUND_HINT}")
        try:
            try:
                device.get_active_configuration()
            except usb.core.USBError as exc:
                if exc.errno in (errno.EACCES, errno.EPERM):
                    raise
                device.set_configuration()  # not configured yet
            interface = ptp_interface(device)
            if interface is None:
                raise DeviceError(f"USB device {usb_id} has no PTP (still image) interface: switch the camera's "
                                  f"USB mode to PTP")
            usb.util.claim_interface(device, interface)
        except (usb.core.USBError, DeviceError) as exc:
            usb.util.dispose_resources(device)
            if isinstance(exc, DeviceError):
                raise
            raise usb_failure(exc, f"opening USB device {usb_id}") from exc

        def endpoint(direction: int, kind: int) -> Any:
            return usb.util.find_descriptor(interface, custom_match=lambda e: (
                usb.util.endpoint_direction(e.bEndpointAddress) == direction
                and usb.util.endpoint_type(e.bmAttributes) == kind))

        bulk_out = endpoint(usb.util.ENDPOINT_OUT, usb.util.ENDPOINT_TYPE_BULK)
        bulk_in = endpoint(usb.util.ENDPOINT_IN, usb.util.ENDPOINT_TYPE_BULK)
        if bulk_out is None or bulk_in is None:
            usb.util.dispose_resources(device)
            raise DeviceError(f"USB device {usb_id}: its PTP interface lacks bulk endpoints")

        def release() -> None:
            usb.util.release_interface(device, interface)
            usb.util.dispose_resources(device)

        return cls(bulk_out, bulk_in, endpoint(usb.util.ENDPOINT_IN, usb.util.ENDPOINT_TYPE_INTR), usb_vendor=vendor,
                   timeout_s=timeout_s, on_close=release)

    @property
    def _timeout_ms(self) -> int:
        return max(1, round(self.timeout_s * 1000))

    def send(self, container: bytes) -> None:
        self.bulk_out.write(container, self._timeout_ms)
        if len(container) % self.bulk_out.wMaxPacketSize == 0:
            self.bulk_out.write(b"", self._timeout_ms)  # zero-length packet: the transfer ends here

    def _read(self, size: int) -> bytes:
        packet = self.bulk_in.wMaxPacketSize
        return bytes(self.bulk_in.read(-(-size // packet) * packet, self._timeout_ms))

    def receive(self) -> bytes:
        data = self._read(self.chunk_size)
        if not data:  # the zero-length packet that ended the previous container
            data = self._read(self.chunk_size)
        if len(data) < 4:
            return data  # too short to hold a length; the container parser reports it
        (length,) = struct.unpack_from("<I", data)
        if length > MAX_CONTAINER_BYTES:
            raise DeviceError(f"camera announced a PTP container of {length:,} bytes, above the limit of "
                              f"{MAX_CONTAINER_BYTES:,}: garbled, or not a camera")
        buffer = bytearray(data)
        while len(buffer) < length:
            part = self._read(min(self.chunk_size, length - len(buffer)))
            if not part:
                break  # the camera ended the transfer early; the parser reports the missing bytes
            buffer += part
        return bytes(buffer)

    def receive_event(self, timeout_s: float) -> bytes | None:
        if self.interrupt_in is None:
            return None
        try:
            return bytes(self.interrupt_in.read(self.interrupt_in.wMaxPacketSize, max(1, round(timeout_s * 1000))))
        except usb.core.USBTimeoutError:
            return None

    def close(self) -> None:
        if self._on_close is not None:
            try:
                self._on_close()
            except usb.core.USBError:
                pass  # already gone
            self._on_close = None
