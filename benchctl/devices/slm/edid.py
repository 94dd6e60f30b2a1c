"""EDID (VESA E-EDID 1.3 / 1.4 base block): what a monitor says it is, to find the SLM among the desktop's outputs.

Output names (HDMI-A-1, DP-2) change with ports and drivers; the EDID a monitor sends does not. Read from the base
block (128 bytes): header 00 ff ff ff ff ff ff 00, the packed manufacturer id (bytes 8-9, three 5-bit letters),
product code (10-11, little endian), serial number (12-15), and the four 18-byte descriptors at 54, 72, 90 and
108: a detailed timing (pixel clock not 0; the first is the preferred mode), or a display descriptor whose tag
(byte 3) is 0xFC (monitor name) or 0xFF (serial number as text), text ending at a line feed. Every byte of the
block sums to 0 modulo 256.
"""

from __future__ import annotations

from dataclasses import dataclass

from benchctl.devices.errors import DeviceError

HEADER = bytes.fromhex("00ffffffffffff00")
BLOCK = 128
_DESCRIPTORS = (54, 72, 90, 108)
_NAME, _SERIAL_TEXT = 0xFC, 0xFF


@dataclass(frozen=True)
class Edid:
    """The parts of an EDID benchctl uses to recognise a monitor."""

    manufacturer: str  # three letters, e.g. DEL
    product_code: int
    serial_number: int  # 0: not given
    name: str  # monitor name descriptor ("" if none)
    serial_text: str  # serial number descriptor ("" if none)
    preferred_mode: tuple[int, int] | None  # (width, height) of the first detailed timing

    @property
    def serial(self) -> str:
        """The serial as a lab would quote it: the text descriptor, else the number (empty when neither)."""
        return self.serial_text or (str(self.serial_number) if self.serial_number else "")


def parse_edid(data: bytes) -> Edid:
    """Parse an EDID's base block; DeviceError for a blob that is not one (short, bad header or checksum)."""
    if len(data) < BLOCK or data[:8] != HEADER:
        raise DeviceError(f"not an EDID: {len(data)} bytes, header {data[:8].hex()} (expected {HEADER.hex()})")
    if sum(data[:BLOCK]) % 256:
        raise DeviceError(f"EDID checksum wrong: the base block sums to {sum(data[:BLOCK]) % 256} modulo 256, not 0")
    packed = int.from_bytes(data[8:10], "big")
    manufacturer = "".join(chr(ord("A") - 1 + (packed >> shift & 0x1F)) for shift in (10, 5, 0))
    texts: dict[int, str] = {}
    preferred = None
    for offset in _DESCRIPTORS:
        descriptor = data[offset:offset + 18]
        if descriptor[0] or descriptor[1]:  # a detailed timing: pixel clock not zero
            if preferred is None:
                width = descriptor[2] | (descriptor[4] & 0xF0) << 4
                height = descriptor[5] | (descriptor[7] & 0xF0) << 4
                preferred = (width, height)
        elif descriptor[3] in (_NAME, _SERIAL_TEXT):
            texts.setdefault(descriptor[3], descriptor[5:18].split(b"\n", 1)[0].decode("ascii", "replace").strip())
    return Edid(manufacturer, int.from_bytes(data[10:12], "little"), int.from_bytes(data[12:16], "little"),
                texts.get(_NAME, ""), texts.get(_SERIAL_TEXT, ""), preferred)
