"""PTP datasets carried in data phases: DeviceInfo and ObjectInfo, with PTP strings and arrays.

A PTP string is a u8 character count (terminating NUL included, 0 for the empty string) then UTF-16LE
characters; an array is a u32 count then its elements. Both directions live here: the driver unpacks what
the camera sends and the simulated body packs it. A dataset cut short is a MalformedContainer naming the
dataset, the field and how many bytes were missing.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, fields
from typing import ClassVar, TypeVar

from benchctl.devices.camera.ptp.container import MalformedContainer

_INT = {"u8": struct.Struct("<B"), "u16": struct.Struct("<H"), "u32": struct.Struct("<I")}


class _Reader:
    """Reads typed fields from a dataset in order; a short read names the dataset and the field."""

    def __init__(self, data: bytes, dataset: str) -> None:
        self.data = data
        self.dataset = dataset
        self.offset = 0

    def _take(self, size: int, name: str) -> bytes:
        if self.offset + size > len(self.data):
            missing = self.offset + size - len(self.data)
            raise MalformedContainer(f"truncated {self.dataset}: field {name} at byte {self.offset} needs "
                                     f"{missing} more byte(s) (dataset is {len(self.data)} bytes)")
        chunk = self.data[self.offset:self.offset + size]
        self.offset += size
        return chunk

    def number(self, kind: str, name: str) -> int:
        return int(_INT[kind].unpack(self._take(_INT[kind].size, name))[0])

    def array(self, kind: str, name: str) -> tuple[int, ...]:
        count = self.number("u32", f"{name} count")
        size = _INT[kind].size
        return struct.unpack(f"<{count}{_INT[kind].format[-1]}", self._take(count * size, name))

    def string(self, name: str) -> str:
        count = self.number("u8", f"{name} length")
        text = self._take(2 * count, name).decode("utf-16-le", errors="replace")
        return text[:-1] if text.endswith("\0") else text


def _pack_int(kind: str, value: int) -> bytes:
    return _INT[kind].pack(value)


def _pack_array(kind: str, values: tuple[int, ...]) -> bytes:
    return _pack_int("u32", len(values)) + struct.pack(f"<{len(values)}{_INT[kind].format[-1]}", *values)


def _pack_string(text: str) -> bytes:
    if not text:
        return b"\0"
    encoded = (text + "\0").encode("utf-16-le")
    return _pack_int("u8", len(encoded) // 2) + encoded


_D = TypeVar("_D", bound="_Dataset")


@dataclass(frozen=True)
class _Dataset:
    """A dataclass packed field by field in declaration order; KINDS gives each field's PTP kind
    (u8, u16, u32, str, or u16[] for an array)."""

    KINDS: ClassVar[str]

    @classmethod
    def _layout(cls) -> list[tuple[str, str]]:
        names, kinds = [f.name for f in fields(cls)], cls.KINDS.split()
        assert len(names) == len(kinds), f"{cls.__name__}: KINDS does not match the fields"
        return list(zip(names, kinds))

    def pack(self) -> bytes:
        out = bytearray()
        for name, kind in self._layout():
            value = getattr(self, name)
            if kind == "str":
                out += _pack_string(value)
            elif kind.endswith("[]"):
                out += _pack_array(kind[:-2], tuple(value))
            else:
                out += _pack_int(kind, value)
        return bytes(out)

    @classmethod
    def unpack(cls: type[_D], data: bytes) -> _D:
        reader = _Reader(bytes(data), cls.__name__)
        values: dict[str, object] = {}
        for name, kind in cls._layout():
            if kind == "str":
                values[name] = reader.string(name)
            elif kind.endswith("[]"):
                values[name] = reader.array(kind[:-2], name)
            else:
                values[name] = reader.number(kind, name)
        return cls(**values)


@dataclass(frozen=True)
class DeviceInfo(_Dataset):
    """What GetDeviceInfo returns: vendor extension, supported operations and events, identity."""

    KINDS: ClassVar[str] = "u16 u32 u16 str u16 u16[] u16[] u16[] u16[] u16[] str str str str"

    standard_version: int = 100
    vendor_extension_id: int = 0
    vendor_extension_version: int = 0
    vendor_extension_desc: str = ""
    functional_mode: int = 0
    operations_supported: tuple[int, ...] = ()
    events_supported: tuple[int, ...] = ()
    device_properties_supported: tuple[int, ...] = ()
    capture_formats: tuple[int, ...] = ()
    image_formats: tuple[int, ...] = ()
    manufacturer: str = ""
    model: str = ""
    device_version: str = ""
    serial_number: str = ""


@dataclass(frozen=True)
class ObjectInfo(_Dataset):
    """What GetObjectInfo returns for one object (an image in the camera's memory or on its card)."""

    KINDS: ClassVar[str] = "u32 u16 u16 u32 u16 u32 u32 u32 u32 u32 u32 u32 u16 u32 u32 str str str str"

    storage_id: int = 0
    object_format: int = 0
    protection_status: int = 0
    compressed_size: int = 0
    thumb_format: int = 0
    thumb_compressed_size: int = 0
    thumb_width: int = 0
    thumb_height: int = 0
    image_width: int = 0
    image_height: int = 0
    image_bit_depth: int = 0
    parent_object: int = 0
    association_type: int = 0
    association_desc: int = 0
    sequence_number: int = 0
    filename: str = ""
    capture_date: str = ""
    modification_date: str = ""
    keywords: str = ""
