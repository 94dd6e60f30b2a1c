"""PTP codes and the container every PTP message travels in (PIMA 15740 over USB, little endian).

    u32 length (header included) | u16 type | u16 code | u32 transaction id | payload

Command, response and event containers carry up to 5 (events: 3) u32 parameters as their payload; a data
container carries the bytes of a data phase. `unpack` checks every field and says which one is wrong and by
how many bytes, so a garbled or cut-off reply is reported as such instead of being misread.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum

from benchctl.devices.errors import DeviceError

HEADER = struct.Struct("<IHHI")
HEADER_SIZE = HEADER.size  # 12


class ContainerType(IntEnum):
    COMMAND = 1
    DATA = 2
    RESPONSE = 3
    EVENT = 4


MAX_PARAMS = {ContainerType.COMMAND: 5, ContainerType.RESPONSE: 5, ContainerType.EVENT: 3}


class OperationCode(IntEnum):
    """Standard PTP operations and the Canon EOS extension's (one code space, so errors can name any of them)."""

    GetDeviceInfo = 0x1001
    OpenSession = 0x1002
    CloseSession = 0x1003
    GetStorageIDs = 0x1004
    GetObjectHandles = 0x1007
    GetObjectInfo = 0x1008
    GetObject = 0x1009
    DeleteObject = 0x100B
    InitiateCapture = 0x100E
    GetDevicePropValue = 0x1015
    SetDevicePropValue = 0x1016
    GetPartialObject = 0x101B
    # Canon EOS extension
    EosSetDevicePropValueEx = 0x9110
    EosSetRemoteMode = 0x9114
    EosSetEventMode = 0x9115
    EosGetEvent = 0x9116
    EosTransferComplete = 0x9117
    EosPCHDDCapacity = 0x911A
    EosKeepDeviceOn = 0x911D
    EosRemoteReleaseOn = 0x9128
    EosRemoteReleaseOff = 0x9129
    EosGetViewFinderData = 0x9153
    EosDriveLens = 0x9155


class ResponseCode(IntEnum):
    OK = 0x2001
    GeneralError = 0x2002
    SessionNotOpen = 0x2003
    InvalidTransactionID = 0x2004
    OperationNotSupported = 0x2005
    ParameterNotSupported = 0x2006
    InvalidObjectHandle = 0x2009
    DeviceBusy = 0x2019
    InvalidParameter = 0x201D
    SessionAlreadyOpen = 0x201E
    EosNotReady = 0xA102  # Canon: e.g. no live-view frame yet


class EventCode(IntEnum):
    ObjectAdded = 0x4002
    CaptureComplete = 0x400D


class ObjectFormat(IntEnum):
    Undefined = 0x3000
    JPEG = 0x3801
    DNG = 0x3811
    CR2 = 0xB103
    CR3 = 0xB108


# The RAW formats benchctl keeps, by the name RawFrame uses for them.
RAW_OBJECT_FORMATS: dict[int, str] = {ObjectFormat.DNG: "dng", ObjectFormat.CR2: "cr2", ObjectFormat.CR3: "cr3"}

CANON_VENDOR_ID = 0x0000000B  # DeviceInfo.VendorExtensionID Canon assigned itself
MTP_VENDOR_ID = 0x00000006  # Microsoft's (MTP) VendorExtensionID, which many Canon bodies report instead
CANON_USB_VENDOR = 0x04A9  # Canon's USB vendor id


def code_name(code: int) -> str:
    """'GetEvent (0x9116)', 'DeviceBusy (0x2019)', or just the hex for codes this module does not know."""
    for enum in (OperationCode, ResponseCode, EventCode, ObjectFormat):
        if code in enum._value2member_map_:
            return f"{enum(code).name.removeprefix('Eos')} (0x{code:04X})"
    return f"0x{code:04X}"


class MalformedContainer(DeviceError):
    """Bytes from the camera that are not a valid PTP container (truncated, garbled, wrong field)."""


@dataclass(frozen=True)
class Container:
    """One PTP container: `params` for command/response/event containers, `payload` for data containers."""

    type: ContainerType
    code: int
    transaction_id: int
    params: tuple[int, ...] = ()
    payload: bytes = b""

    def __post_init__(self) -> None:
        if self.type == ContainerType.DATA:
            if self.params:
                raise ValueError("a data container has a payload, not parameters")
        else:
            if self.payload:
                raise ValueError(f"a {self.type.name.lower()} container has parameters, not a payload")
            if len(self.params) > MAX_PARAMS[self.type]:
                raise ValueError(f"a {self.type.name.lower()} container has at most {MAX_PARAMS[self.type]} "
                                 f"parameters, got {len(self.params)}")

    def pack(self) -> bytes:
        body = self.payload if self.type == ContainerType.DATA else struct.pack(f"<{len(self.params)}I", *self.params)
        return HEADER.pack(HEADER_SIZE + len(body), self.type, self.code, self.transaction_id) + body

    @classmethod
    def unpack(cls, data: bytes) -> Container:
        """Parse exactly one container; MalformedContainer names the field that is wrong."""
        if len(data) < HEADER_SIZE:
            raise MalformedContainer(f"truncated PTP container: {len(data)} bytes, the header alone is {HEADER_SIZE}")
        length, kind, code, transaction_id = HEADER.unpack_from(data)
        if length < HEADER_SIZE:
            raise MalformedContainer(f"malformed PTP container: length field {length} is less than the "
                                     f"{HEADER_SIZE}-byte header")
        if length != len(data):
            what = "truncated" if length > len(data) else "malformed"
            raise MalformedContainer(f"{what} PTP container {code_name(code)}: length field says {length} bytes, "
                                     f"received {len(data)}")
        try:
            ctype = ContainerType(kind)
        except ValueError:
            raise MalformedContainer(f"malformed PTP container: type field {kind} is not 1-4 "
                                     f"(command, data, response, event)") from None
        body = bytes(data[HEADER_SIZE:])
        if ctype == ContainerType.DATA:
            return cls(ctype, code, transaction_id, payload=body)
        if len(body) % 4:
            raise MalformedContainer(f"malformed PTP {ctype.name.lower()} {code_name(code)}: {len(body)} parameter "
                                     f"bytes is not a whole number of u32 parameters")
        count = len(body) // 4
        if count > MAX_PARAMS[ctype]:
            raise MalformedContainer(f"malformed PTP {ctype.name.lower()} {code_name(code)}: {count} parameters, "
                                     f"at most {MAX_PARAMS[ctype]} allowed")
        return cls(ctype, code, transaction_id, params=struct.unpack(f"<{count}I", body))
