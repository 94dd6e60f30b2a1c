"""Canon EOS PTP extension: remote mode, event polling (GetEvent records), remote release, capture to the
computer, chunked download and the live view.

GetEvent returns a run of records, each `u32 size | u32 type | body`, ending with the record size 8 type 0.
Offsets below count from the start of a record (size field included) and are those libgphoto2 parses
(camlibs/ptp2/ptp.c, `ptp_canon_eos_getevent`). RequestObjectTransfer: handle at 8, format (u16) at 0x0c,
size at 0x14, NUL-terminated file name at 0x1c. ObjectAddedEx: handle at 8, storage 0x0c, format 0x10,
size 0x1c, parent 0x20, name 0x28. CameraStatus: status at 8 (1 = busy shooting). PropValueChanged: property
at 8, value from 0x0c. Both directions are here: the driver parses, the simulated body packs.

Live view (libgphoto2's sequence): EVFOutputDevice 0xD1B0 = 2 sends the viewfinder to the computer; then each
GetViewFinderData (0x9153, parameter 0x00100000, data to the host) returns records of the same `u32 size |
u32 type | body` form, the image a type-1 record whose body is a JPEG; the body answers 0xA102 (not ready) or
DeviceBusy until it has a frame. Setting 0xD1B0 back ends it.

Focus (libgphoto2's `manualfocusdrive`, Canon's EDSDK DriveLens): operation 0x9155 with one parameter, 0x0001 /
0x0002 / 0x0003 = Near 1 / 2 / 3 (small / medium / large step) and 0x8001 / 0x8002 / 0x8003 = Far 1 / 2 / 3. The lens
moves only in live view (0xD1B0 = 2), and the body answers OK even when it ignored a drive (at an end stop, a busy
lens): no drive says where the lens is.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from enum import IntEnum

from benchctl.devices.camera.ptp.container import (
    CANON_USB_VENDOR,
    CANON_VENDOR_ID,
    MalformedContainer,
    OperationCode,
    ResponseCode,
    code_name,
)
from benchctl.devices.camera.ptp.datasets import DeviceInfo
from benchctl.devices.camera.ptp.session import PtpSession, response_error
from benchctl.devices.errors import DeviceError
from benchctl.errors import BadValueError

RECORD_HEADER = struct.Struct("<II")
TERMINATOR = RECORD_HEADER.pack(8, 0)
PARTIAL_CHUNK = 1 << 20  # GetPartialObject asks for 1 MiB at a time

REMOTE_MODE_EOS_M = 0x15
EVENT_MODE = 1
EVENT_MODE_EOS_M = 2
CAPTURE_TO_PC = 4
EVF_OUTPUT_PC = 8
EVF_OUTPUT_LIVE_VIEW = 2  # the viewfinder's frames go to the computer (GetViewFinderData)
VIEWFINDER_PARAMETER = 0x00100000
VIEWFINDER_IMAGE = 1  # record type of the live-view JPEG
JPEG_START = b"\xff\xd8"
PC_HDD_CAPACITY = (0x0FFFFFFF, 0x1000, 1)  # (free clusters, bytes per cluster, 1): "plenty of room"
RAW_ONLY = (1, 0x10, 6, 0, 4)  # image format value: one entry of 0x10 bytes, type RAW, size L, quality RAW
DRIVE_NEAR = 0x0000  # DriveLens parameter: the direction bit clear is Near, set (0x8000) is Far; size 1-3 below it
DRIVE_FAR = 0x8000
DRIVE_SIZES = (1, 2, 3)
FULL_PRESS = 3  # RemoteReleaseOn button: half + full press in one go
AF_ON = 0  # RemoteReleaseOn second parameter

# The first response parameter of RemoteReleaseOn: Canon's release result (as for EOS RemoteRelease 0x910F).
RELEASE_OK = 0
RELEASE_NO_FOCUS = 1
RELEASE_NO_CARD_SPACE = 7
CAMERA_STATUS_SHOOTING = 1


# The operations the EOS capture sequence needs beyond standard PTP: remote release and event polling.
EOS_OPERATIONS = (OperationCode.EosRemoteReleaseOn, OperationCode.EosRemoteReleaseOff,
                  OperationCode.EosSetEventMode, OperationCode.EosGetEvent)


def is_canon(info: DeviceInfo, usb_vendor: int | None) -> bool:
    """Whether the body is a Canon: Canon's own VendorExtensionID, or any (EOS bodies report 6, Microsoft / MTP)
    from Canon's USB vendor id, as libgphoto2 decides it."""
    return info.vendor_extension_id == CANON_VENDOR_ID or usb_vendor == CANON_USB_VENDOR


def missing_eos_operations(info: DeviceInfo) -> list[int]:
    """The EOS_OPERATIONS the body does not offer (none for an EOS body)."""
    return [code for code in EOS_OPERATIONS if code not in info.operations_supported]


class EosEventType(IntEnum):
    Terminator = 0
    ObjectAddedEx = 0xC181
    RequestObjectTransfer = 0xC186
    PropValueChanged = 0xC189
    CameraStatus = 0xC18B


class EosProperty(IntEnum):
    Aperture = 0xD101
    ShutterSpeed = 0xD102
    ISO = 0xD103
    CaptureDestination = 0xD11C
    ImageFormat = 0xD120
    EVFOutputDevice = 0xD1B0


# Properties whose writes freeze the EOS M10 while capture keeps working (user reports against libgphoto2:
# https://github.com/gphoto/libgphoto2/issues/734, https://github.com/gphoto/gphoto2/issues/159):
# the exposure settings and the image format.
EXPOSURE_PROPERTIES = frozenset({EosProperty.Aperture, EosProperty.ShutterSpeed, EosProperty.ISO,
                                 EosProperty.ImageFormat})

# Object record layouts: type -> (minimum length, handle, format (u16), size, name) offsets
_OBJECT_LAYOUT = {
    EosEventType.RequestObjectTransfer: (0x18, 0x08, 0x0C, 0x14, 0x1C),
    EosEventType.ObjectAddedEx: (0x20, 0x08, 0x10, 0x1C, 0x28),
}


@dataclass(frozen=True)
class EosEvent:
    """One GetEvent record, kept whole (header included) so documented offsets apply directly."""

    type: int
    record: bytes

    def u32(self, offset: int) -> int:
        if offset + 4 > len(self.record):
            raise MalformedContainer(f"truncated GetEvent record 0x{self.type:04X}: {len(self.record)} bytes, a field "
                                     f"at byte {offset} needs {offset + 4}")
        return int(struct.unpack_from("<I", self.record, offset)[0])


@dataclass(frozen=True)
class ObjectRecord:
    """An image announced by ObjectAddedEx or RequestObjectTransfer."""

    handle: int
    size: int
    format: int
    name: str | None  # None when the record ends before the name


def parse_events(data: bytes) -> list[EosEvent]:
    """The records of a GetEvent data phase, up to (not including) the terminator."""
    events: list[EosEvent] = []
    offset = 0
    while True:
        if len(data) - offset < RECORD_HEADER.size:
            raise MalformedContainer(f"truncated GetEvent data: it ends at byte {len(data)} without the terminator "
                                     f"record (size 8, type 0)")
        size, kind = RECORD_HEADER.unpack_from(data, offset)
        if size == 8 and kind == EosEventType.Terminator:
            return events
        if size < RECORD_HEADER.size:
            raise MalformedContainer(f"malformed GetEvent record at byte {offset}: size field {size} is less than "
                                     f"its 8-byte header")
        if offset + size > len(data):
            raise MalformedContainer(f"truncated GetEvent record 0x{kind:04X} at byte {offset}: size field says "
                                     f"{size} bytes, only {len(data) - offset} remain")
        events.append(EosEvent(kind, bytes(data[offset:offset + size])))
        offset += size


def object_record(event: EosEvent) -> ObjectRecord:
    """Handle, size, format and name of an ObjectAddedEx / RequestObjectTransfer record."""
    minimum, handle, fmt, size, name = _OBJECT_LAYOUT[EosEventType(event.type)]
    if len(event.record) < minimum:
        raise MalformedContainer(f"truncated {EosEventType(event.type).name} record: {len(event.record)} bytes, "
                                 f"its object size field ends at byte {minimum}")
    raw_name = event.record[name:].split(b"\0", 1)[0] if len(event.record) > name else b""
    return ObjectRecord(event.u32(handle), event.u32(size), int(struct.unpack_from("<H", event.record, fmt)[0]),
                        raw_name.decode("ascii", errors="replace") or None)


def pack_record(kind: int, body: bytes) -> bytes:
    return RECORD_HEADER.pack(RECORD_HEADER.size + len(body), kind) + body


def pack_events(records: Iterable[bytes]) -> bytes:
    """A GetEvent data phase: the packed records, then the terminator."""
    return b"".join(records) + TERMINATOR


def pack_object_record(kind: EosEventType, handle: int, size: int, fmt: int, name: str) -> bytes:
    """An ObjectAddedEx / RequestObjectTransfer record laid out as `object_record` reads it."""
    _, at_handle, at_format, at_size, at_name = _OBJECT_LAYOUT[kind]
    record = bytearray(at_name)
    struct.pack_into("<II", record, 0, 0, kind)
    struct.pack_into("<I", record, at_handle, handle)
    struct.pack_into("<H", record, at_format, fmt)
    struct.pack_into("<I", record, at_size, size)
    record += name.encode("ascii") + b"\0"
    record += bytes(-len(record) % 4)
    struct.pack_into("<I", record, 0, len(record))
    return bytes(record)


def pack_property_change(prop: int, values: Sequence[int]) -> bytes:
    return pack_record(EosEventType.PropValueChanged, struct.pack(f"<{len(values) + 1}I", prop, *values))


def pack_camera_status(status: int) -> bytes:
    return pack_record(EosEventType.CameraStatus, struct.pack("<I", status))


def viewfinder_jpeg(data: bytes) -> bytes:
    """The JPEG of a GetViewFinderData data phase: the body of its first type-1 record (the records need no
    terminator: the data phase ends after the last one)."""
    offset = 0
    while len(data) - offset >= RECORD_HEADER.size:
        size, kind = RECORD_HEADER.unpack_from(data, offset)
        if size < RECORD_HEADER.size or offset + size > len(data):
            raise MalformedContainer(f"malformed live-view record at byte {offset}: size field {size}, "
                                     f"{len(data) - offset} bytes left")
        body = data[offset + RECORD_HEADER.size:offset + size]
        if kind == VIEWFINDER_IMAGE:
            if not body.startswith(JPEG_START):
                raise MalformedContainer(f"live-view image record at byte {offset} is not a JPEG (starts "
                                         f"{body[:2].hex() or 'empty'}, not ffd8)")
            return bytes(body)
        offset += size
    raise MalformedContainer(f"live-view data of {len(data)} bytes holds no image record (type {VIEWFINDER_IMAGE})")


def pack_viewfinder(jpeg: bytes) -> bytes:
    """A GetViewFinderData data phase holding `jpeg`, as `viewfinder_jpeg` reads it."""
    return pack_record(VIEWFINDER_IMAGE, jpeg)


def drive_lens_code(far: bool, size: int) -> int:
    """DriveLens's parameter: Near / Far and the step size 1 (small), 2 or 3 (large)."""
    if size not in DRIVE_SIZES:
        raise BadValueError(f"DriveLens step size must be 1, 2 or 3, got {size!r}")
    return (DRIVE_FAR if far else DRIVE_NEAR) | size


def parse_drive_lens(code: int) -> tuple[bool, int] | None:
    """(far, size) of a DriveLens parameter, or None if it is not one of the six codes."""
    far, size = bool(code & DRIVE_FAR), code & ~DRIVE_FAR
    return (far, size) if size in DRIVE_SIZES and code & 0xFFFF == code else None


def _third_stop_code(stops: float, base: int) -> int:
    """Canon's 1/8-EV code for a value `stops` whole stops from the one coded `base`, rounded to 1/3 stop
    (thirds are coded +3 and +5 eighths)."""
    thirds = round(3 * stops)
    whole, third = divmod(thirds, 3)
    return base + 8 * whole + (0, 3, 5)[third]


def iso_code(iso: int) -> int:
    """ISO speed -> EOS ISO property value (100 = 0x48, 200 = 0x50, ..., 1/3 stops in between)."""
    if not 100 <= iso <= 25600:
        raise BadValueError(f"ISO {iso} is outside the EOS M10's 100-25600")
    return _third_stop_code(math.log2(iso / 100), 0x48)


def shutter_code(exposure_s: float) -> int:
    """Exposure time -> EOS shutter property value (1 s = 0x38, 1/2 s = 0x40, ..., 1/3 stops in between)."""
    if not 1 / 4000 <= exposure_s <= 30:
        raise BadValueError(f"exposure {exposure_s:g} s is outside the EOS M10's 1/4000 s to 30 s")
    return _third_stop_code(-math.log2(exposure_s), 0x38)


class Eos:
    """The Canon EOS operations, on an open PTP session."""

    def __init__(self, session: PtpSession) -> None:
        self.session = session

    def set_remote_mode(self, mode: int) -> None:
        self.session.request(OperationCode.EosSetRemoteMode, mode)

    def set_event_mode(self, mode: int) -> None:
        self.session.request(OperationCode.EosSetEventMode, mode)

    def get_events(self) -> list[EosEvent]:
        return parse_events(self.session.request(OperationCode.EosGetEvent).data)

    def drain_events(self, max_polls: int = 100) -> None:
        """GetEvent until a call returns no records (bounded: a chatty body cannot hold us here)."""
        for _ in range(max_polls):
            if not self.get_events():
                return

    def set_property(self, prop: int, value: int | Sequence[int]) -> None:
        """SetDevicePropValueEx: data is u32 size, u32 property, then the value as u32s."""
        values = (value,) if isinstance(value, int) else tuple(value)
        data = struct.pack(f"<{len(values) + 2}I", 8 + 4 * len(values), prop, *values)
        self.session.request(OperationCode.EosSetDevicePropValueEx, data=data)

    def pc_hdd_capacity(self) -> None:
        """Tell the body the computer has room for its images (needed before capture to the computer)."""
        self.session.request(OperationCode.EosPCHDDCapacity, *PC_HDD_CAPACITY)

    def remote_release_on(self, button: int = FULL_PRESS, af: int = AF_ON) -> int:
        """Press the shutter button; returns the body's release result (RELEASE_OK, RELEASE_NO_FOCUS, ...)."""
        response = self.session.request(OperationCode.EosRemoteReleaseOn, button, af)
        return response.params[0] if response.params else RELEASE_OK

    def remote_release_off(self, button: int = FULL_PRESS) -> None:
        self.session.request(OperationCode.EosRemoteReleaseOff, button)

    def read_object(self, handle: int, size: int, chunk: int = PARTIAL_CHUNK) -> bytes:
        """The object's bytes via GetPartialObject, `chunk` bytes per call: ceil(size / chunk) calls."""
        data = bytearray()
        while len(data) < size:
            part = self.session.request(OperationCode.GetPartialObject, handle, len(data),
                                        min(chunk, size - len(data))).data
            if not part:
                raise DeviceError(f"camera sent no data for image 0x{handle:08X} at byte {len(data)} of {size} "
                                  f"({code_name(OperationCode.GetPartialObject)})")
            data += part
        return bytes(data[:size])

    def viewfinder_frame(self) -> bytes | None:
        """One GetViewFinderData: the live-view JPEG, or None while the body has no frame (0xA102 or DeviceBusy)."""
        response = self.session.transact(OperationCode.EosGetViewFinderData, VIEWFINDER_PARAMETER)
        if response.code in (ResponseCode.EosNotReady, ResponseCode.DeviceBusy):
            return None
        if response.code != ResponseCode.OK:
            raise response_error(OperationCode.EosGetViewFinderData, response.code, response.params)
        return viewfinder_jpeg(response.data)

    def drive_lens(self, far: bool, size: int) -> None:
        """One DriveLens: the lens moves Near or Far by one step of `size` (only in live view; OK says nothing about
        whether it moved)."""
        self.session.request(OperationCode.EosDriveLens, drive_lens_code(far, size))

    def transfer_complete(self, handle: int) -> None:
        """Tell the body the image arrived, so it frees its buffer."""
        self.session.request(OperationCode.EosTransferComplete, handle)
