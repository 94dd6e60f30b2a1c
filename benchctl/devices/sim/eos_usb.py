"""A simulated Canon EOS M body (EOS M10 by default) behind a PTP/USB transport, answering container bytes.

It parses every container the host sends and answers with the containers a real body would: DeviceInfo with
Canon's vendor extension, sessions (SessionNotOpen outside one), remote and event modes, GetEvent records, the
remote release, capture to the computer, GetPartialObject, TransferComplete and GetObjectInfo. InitiateCapture
is not offered, as on the M10. Each shutter release takes one file from `image_source` (RAW bytes and the
camera's file name), so the simulated bench can plug in the DNG it rendered. With `live_view` (a callable giving
one JPEG) the body also has a live view: GetViewFinderData answers 0xA102 (not ready) while EVFOutputDevice 0xD1B0
is not 2 and once more just after it is set to 2 (the sensor starts), then a type-1 record holding a new JPEG.

With `lens` (the simulated bench's focus mechanism, benchctl.devices.sim.focus_mechanics) the body also drives its
lens: DriveLens (0x9155) Near / Far 1-3 moves it DRIVE_STEPS[size] of the mechanism's steps, only in live view (EVF
output 2); like a real body it answers OK to every valid drive, also one it ignored (not in live view, or the lens at
an end stop); `lens_drives` counts the drives that moved it. An invalid parameter is InvalidParameter.

What it does on a release: answered DeviceBusy unless the host declared capacity (PCHDDCapacity) for capture
to the computer; otherwise it shoots, reports CameraStatus 1 (shooting), and on RemoteReleaseOff announces the
image with RequestObjectTransfer (capture destination 4) or ObjectAddedEx (image kept on the card).

Faults (constructor arguments):
  busy_releases=N          the first N RemoteReleaseOn are answered DeviceBusy (0x2019)
  no_focus=True            autofocus fails: RemoteReleaseOn is answered OK with release result 1 (Canon's
                           "AF failed" code, as the EOS RemoteRelease result libgphoto2 reports as "Perhaps no
                           focus?" and the EDSDK as TAKE_PICTURE_AF_NG); the shutter does not fire
  no_transfer=True         the shutter fires but no RequestObjectTransfer ever comes (the host times out)
  unplug_after_bytes=N     the cable is pulled once N image bytes were sent: the GetPartialObject that would go
                           past them, and everything after, raises pyusb's USBError for a removed device (ENODEV)
  freeze_on_property_write the M10 quirk: after a SetDevicePropValueEx of an exposure setting (aperture,
                           shutter, ISO, image format) the body stops answering; every transfer times out
                           (USBTimeoutError) until it is power-cycled (a new instance)
  short_transfer_records   RequestObjectTransfer records end before the file name (the host asks GetObjectInfo)
"""

from __future__ import annotations

import errno
import struct
from collections import deque
from collections.abc import Callable
from pathlib import PurePath
from typing import TYPE_CHECKING

import usb.core

from benchctl.devices.camera.ptp.container import (
    CANON_USB_VENDOR,
    CANON_VENDOR_ID,
    RAW_OBJECT_FORMATS,
    Container,
    ContainerType,
    ObjectFormat,
    OperationCode,
    ResponseCode,
)
from benchctl.devices.camera.ptp.datasets import DeviceInfo, ObjectInfo
from benchctl.devices.camera.ptp.eos import (
    CAMERA_STATUS_SHOOTING,
    CAPTURE_TO_PC,
    EVF_OUTPUT_LIVE_VIEW,
    EXPOSURE_PROPERTIES,
    RELEASE_NO_FOCUS,
    EosEventType,
    EosProperty,
    pack_camera_status,
    pack_events,
    pack_object_record,
    pack_property_change,
    pack_viewfinder,
    parse_drive_lens,
)
from benchctl.devices.camera.ptp.transport import Transport

if TYPE_CHECKING:
    from benchctl.devices.sim.focus_mechanics import Mechanism

ImageSource = Callable[[], tuple[bytes, str]]
LiveViewSource = Callable[[], bytes]

FIRST_HANDLE = 0x90000001
# The mechanism steps one DriveLens moves, by size: a lens's small, medium and large steps (hidden from benchctl,
# which counts drives of the profile's one size; the calibration measures what a drive does).
DRIVE_STEPS = {1: 1.0, 2: 8.0, 3: 48.0}
_WITH_HOST_DATA = {OperationCode.SetDevicePropValue, OperationCode.EosSetDevicePropValueEx}
_OUTSIDE_SESSION = {OperationCode.GetDeviceInfo, OperationCode.OpenSession}
_FORMATS_BY_SUFFIX = {f".{name}": code for code, name in RAW_OBJECT_FORMATS.items()} | {
    ".jpg": ObjectFormat.JPEG, ".jpeg": ObjectFormat.JPEG}
_INITIAL_PROPERTIES: dict[int, tuple[int, ...]] = {
    EosProperty.Aperture: (0x28,), EosProperty.ShutterSpeed: (0x68,), EosProperty.ISO: (0x48,),
    EosProperty.CaptureDestination: (1,), EosProperty.ImageFormat: (1, 0x10, 6, 0, 4),
    EosProperty.EVFOutputDevice: (0,)}

Reply = tuple[int, tuple[int, ...], bytes | None]  # response code, response parameters, data phase


def _removed_device() -> usb.core.USBError:
    return usb.core.USBError("No such device (it may have been disconnected)", -4, errno.ENODEV)


def _timed_out() -> usb.core.USBTimeoutError:
    return usb.core.USBTimeoutError("Operation timed out", -7, errno.ETIMEDOUT)


class SimEosTransport(Transport):
    """A Transport whose other end is a simulated EOS M body. It records what it received: `commands` (every
    command container), `data_phases` (the host's data phases, as sent) and `property_writes` (property, value)."""

    def __init__(self, image_source: ImageSource, *, model: str = "Canon EOS M10",
                 serial: str = "5a1c0ffee0ddba11deadbeef00c0ffee", firmware: str = "3-1.1.0",
                 busy_releases: int = 0, no_focus: bool = False, no_transfer: bool = False,
                 unplug_after_bytes: int | None = None, freeze_on_property_write: bool = False,
                 short_transfer_records: bool = False, live_view: LiveViewSource | None = None,
                 lens: Mechanism | None = None,
                 vendor_extension_id: int = CANON_VENDOR_ID, usb_vendor: int = CANON_USB_VENDOR) -> None:
        """`vendor_extension_id`: what DeviceInfo reports (Canon's 0x0B, or 6 (MTP) as many EOS bodies do);
        `live_view`: what GetViewFinderData delivers (without one the body does not offer the operation)."""
        self.image_source = image_source
        self.live_view = live_view
        self.lens = lens
        self.lens_drives = 0
        self.usb_vendor = usb_vendor
        operations = set(_HANDLERS) - (set() if live_view else {OperationCode.EosGetViewFinderData}) \
            - (set() if lens else {OperationCode.EosDriveLens})
        self.device_info = DeviceInfo(
            standard_version=100, vendor_extension_id=vendor_extension_id, vendor_extension_version=100,
            operations_supported=tuple(sorted(operations)),
            events_supported=(EosEventType.ObjectAddedEx, EosEventType.RequestObjectTransfer,
                              EosEventType.PropValueChanged, EosEventType.CameraStatus),
            device_properties_supported=tuple(EosProperty), image_formats=(ObjectFormat.JPEG, ObjectFormat.CR2),
            manufacturer="Canon Inc.", model=model, device_version=firmware, serial_number=serial)
        self.busy_releases = busy_releases
        self.no_focus = no_focus
        self.no_transfer = no_transfer
        self.unplug_after_bytes = unplug_after_bytes
        self.freeze_on_property_write = freeze_on_property_write
        self.short_transfer_records = short_transfer_records
        self.commands: list[Container] = []
        self.data_phases: list[bytes] = []
        self.property_writes: list[tuple[int, tuple[int, ...]]] = []
        self.properties: dict[int, tuple[int, ...]] = dict(_INITIAL_PROPERTIES)
        self.remote_mode = 0
        self.event_mode = 0
        self.host_capacity = False
        self.frozen = False
        self.unplugged = False
        self.closed = False
        self.object_bytes_sent = 0
        self.live_view_frames = 0
        self._sensor_started = False  # the live view has run since EVF output went to the computer
        self._session: int | None = None
        self._outbox: deque[bytes] = deque()
        self._events: list[bytes] = []
        self._objects: dict[int, tuple[bytes, str, int]] = {}
        self._shot: int | None = None  # handle of the image taken by the current press, announced on release
        self._next_handle = FIRST_HANDLE
        self._awaiting_data: Container | None = None

    @property
    def operations(self) -> list[int]:
        """The operation codes received, in order."""
        return [command.code for command in self.commands]

    # -- Transport ---------------------------------------------------------------------------------------------

    def send(self, container: bytes) -> None:
        self.closed = False
        if self.unplugged:
            raise _removed_device()
        if self.frozen:
            raise _timed_out()
        received = Container.unpack(container)
        if received.type == ContainerType.COMMAND:
            self.commands.append(received)
            if received.code in _WITH_HOST_DATA:
                self._awaiting_data = received
            else:
                self._answer(received, None)
        elif received.type == ContainerType.DATA and self._awaiting_data is not None \
                and received.transaction_id == self._awaiting_data.transaction_id:
            command, self._awaiting_data = self._awaiting_data, None
            self.data_phases.append(received.payload)
            self._answer(command, received.payload)
        else:
            raise AssertionError(f"simulated EOS body: unexpected container from the host {received}")

    def receive(self) -> bytes:
        if self.unplugged:
            raise _removed_device()
        if not self._outbox:
            raise _timed_out()
        return self._outbox.popleft()

    def receive_event(self, timeout_s: float) -> bytes | None:
        if self.unplugged:
            raise _removed_device()
        return None  # EOS bodies report through GetEvent

    def close(self) -> None:
        self.closed = True
        self._outbox.clear()

    # -- the body ----------------------------------------------------------------------------------------------

    def _answer(self, command: Container, data: bytes | None) -> None:
        handler = _HANDLERS.get(command.code)
        reply: Reply
        if handler is None:
            reply = ResponseCode.OperationNotSupported, (), None
        elif self._session is None and command.code not in _OUTSIDE_SESSION:
            reply = ResponseCode.SessionNotOpen, (), None
        else:
            reply = handler(self, command, data)
        code, params, out = reply
        if self.frozen or self.unplugged:
            return  # no answer ever comes
        tid = command.transaction_id
        if out is not None:
            self._outbox.append(Container(ContainerType.DATA, command.code, tid, payload=out).pack())
        self._outbox.append(Container(ContainerType.RESPONSE, code, tid, params).pack())

    def _get_device_info(self, command: Container, data: bytes | None) -> Reply:
        return ResponseCode.OK, (), self.device_info.pack()

    def _open_session(self, command: Container, data: bytes | None) -> Reply:
        if command.transaction_id != 0:
            return ResponseCode.InvalidTransactionID, (), None
        if self._session is not None:
            return ResponseCode.SessionAlreadyOpen, (self._session,), None
        if not command.params or command.params[0] == 0:
            return ResponseCode.InvalidParameter, (), None
        self._session = command.params[0]
        return ResponseCode.OK, (), None

    def _close_session(self, command: Container, data: bytes | None) -> Reply:
        self._session = None
        self.remote_mode = self.event_mode = 0
        self._events.clear()
        return ResponseCode.OK, (), None

    def _set_remote_mode(self, command: Container, data: bytes | None) -> Reply:
        self.remote_mode = command.params[0]
        return ResponseCode.OK, (), None

    def _set_event_mode(self, command: Container, data: bytes | None) -> Reply:
        """Turning events on queues the first bulk of property values, as a body does on connect."""
        if self.event_mode == 0 and command.params[0]:
            self._events += [pack_property_change(prop, value) for prop, value in self.properties.items()]
        self.event_mode = command.params[0]
        return ResponseCode.OK, (), None

    def _get_event(self, command: Container, data: bytes | None) -> Reply:
        records, self._events = self._events, []
        return ResponseCode.OK, (), pack_events(records)

    def _set_property(self, command: Container, data: bytes | None) -> Reply:
        if data is None or len(data) < 12 or len(data) % 4 or struct.unpack_from("<I", data)[0] != len(data):
            return ResponseCode.InvalidParameter, (), None
        prop, *values = struct.unpack(f"<{len(data) // 4 - 1}I", data[4:])
        self.properties[prop] = tuple(values)
        self.property_writes.append((prop, tuple(values)))
        self._events.append(pack_property_change(prop, values))
        if prop == EosProperty.EVFOutputDevice:
            self._sensor_started = False
        if self.freeze_on_property_write and prop in EXPOSURE_PROPERTIES:
            self.frozen = True
        return ResponseCode.OK, (), None

    def _pc_hdd_capacity(self, command: Container, data: bytes | None) -> Reply:
        self.host_capacity = True
        return ResponseCode.OK, (), None

    def _to_computer(self) -> bool:
        return self.properties[EosProperty.CaptureDestination] == (CAPTURE_TO_PC,)

    def _release_on(self, command: Container, data: bytes | None) -> Reply:
        if self.busy_releases > 0:
            self.busy_releases -= 1
            return ResponseCode.DeviceBusy, (), None
        if self._to_computer() and not self.host_capacity:
            return ResponseCode.DeviceBusy, (), None  # the body thinks the computer has no room
        if self.no_focus:
            return ResponseCode.OK, (RELEASE_NO_FOCUS,), None
        image, name = self.image_source()
        handle, self._next_handle = self._next_handle, self._next_handle + 1
        fmt = _FORMATS_BY_SUFFIX.get(PurePath(name).suffix.lower(), ObjectFormat.Undefined)
        self._objects[handle] = (bytes(image), name, fmt)
        self._shot = handle
        self._events.append(pack_camera_status(CAMERA_STATUS_SHOOTING))
        return ResponseCode.OK, (), None

    def _release_off(self, command: Container, data: bytes | None) -> Reply:
        if self._shot is not None:
            image, name, fmt = self._objects[self._shot]
            if not self._to_computer():
                self._events.append(pack_object_record(EosEventType.ObjectAddedEx, self._shot, len(image), fmt, name))
            elif not self.no_transfer:
                record = pack_object_record(EosEventType.RequestObjectTransfer, self._shot, len(image), fmt, name)
                if self.short_transfer_records:
                    record = struct.pack("<I", 0x1C) + record[4:0x1C]
                self._events.append(record)
            self._events.append(pack_camera_status(0))
            self._shot = None
        return ResponseCode.OK, (), None

    def _get_partial_object(self, command: Container, data: bytes | None) -> Reply:
        handle, offset, size = command.params
        if handle not in self._objects:
            return ResponseCode.InvalidObjectHandle, (), None
        part = self._objects[handle][0][offset:offset + size]
        if self.unplug_after_bytes is not None and self.object_bytes_sent + len(part) > self.unplug_after_bytes:
            self.unplugged = True
        self.object_bytes_sent += len(part)
        return ResponseCode.OK, (len(part),), part

    def _get_object_info(self, command: Container, data: bytes | None) -> Reply:
        if command.params[0] not in self._objects:
            return ResponseCode.InvalidObjectHandle, (), None
        image, name, fmt = self._objects[command.params[0]]
        info = ObjectInfo(storage_id=0, object_format=fmt, compressed_size=len(image), filename=name)
        return ResponseCode.OK, (), info.pack()

    def _get_viewfinder_data(self, command: Container, data: bytes | None) -> Reply:
        if self.live_view is None:
            return ResponseCode.OperationNotSupported, (), None
        if self.properties[EosProperty.EVFOutputDevice] != (EVF_OUTPUT_LIVE_VIEW,) or not self._sensor_started:
            self._sensor_started = self.properties[EosProperty.EVFOutputDevice] == (EVF_OUTPUT_LIVE_VIEW,)
            return ResponseCode.EosNotReady, (), None
        self.live_view_frames += 1
        return ResponseCode.OK, (), pack_viewfinder(self.live_view())

    def _drive_lens(self, command: Container, data: bytes | None) -> Reply:
        if self.lens is None:
            return ResponseCode.OperationNotSupported, (), None
        drive = parse_drive_lens(command.params[0]) if command.params else None
        if drive is None:
            return ResponseCode.InvalidParameter, (), None
        far, size = drive
        if self.properties[EosProperty.EVFOutputDevice] == (EVF_OUTPUT_LIVE_VIEW,):
            moved = self.lens.drive(DRIVE_STEPS[size] * (1 if far else -1))
            self.lens_drives += bool(moved)
        return ResponseCode.OK, (), None  # also when ignored: Canon's body says OK either way

    def _transfer_complete(self, command: Container, data: bytes | None) -> Reply:
        if self._objects.pop(command.params[0], None) is None:
            return ResponseCode.InvalidObjectHandle, (), None
        return ResponseCode.OK, (), None


_HANDLERS: dict[int, Callable[[SimEosTransport, Container, bytes | None], Reply]] = {
    OperationCode.GetDeviceInfo: SimEosTransport._get_device_info,
    OperationCode.OpenSession: SimEosTransport._open_session,
    OperationCode.CloseSession: SimEosTransport._close_session,
    OperationCode.GetObjectInfo: SimEosTransport._get_object_info,
    OperationCode.GetPartialObject: SimEosTransport._get_partial_object,
    OperationCode.EosSetDevicePropValueEx: SimEosTransport._set_property,
    OperationCode.EosSetRemoteMode: SimEosTransport._set_remote_mode,
    OperationCode.EosSetEventMode: SimEosTransport._set_event_mode,
    OperationCode.EosGetEvent: SimEosTransport._get_event,
    OperationCode.EosTransferComplete: SimEosTransport._transfer_complete,
    OperationCode.EosPCHDDCapacity: SimEosTransport._pc_hdd_capacity,
    OperationCode.EosRemoteReleaseOn: SimEosTransport._release_on,
    OperationCode.EosRemoteReleaseOff: SimEosTransport._release_off,
    OperationCode.EosGetViewFinderData: SimEosTransport._get_viewfinder_data,
    OperationCode.EosDriveLens: SimEosTransport._drive_lens,
}
