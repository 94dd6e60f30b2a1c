"""PTP wire level: containers and datasets (pack/unpack, malformed input) and the USB transport's framing
(zero-length packets, chunked reads) against fake endpoints, and how USB failures read to the user."""

from __future__ import annotations

import errno
import struct
from collections.abc import Iterator

import pytest
import usb.core
from hypothesis import given
from hypothesis import strategies as st

from benchctl.devices.camera.hints import UDEV_RULE
from benchctl.devices.camera.ptp import transport as transport_module
from benchctl.devices.camera.ptp.container import (
    HEADER_SIZE,
    MAX_PARAMS,
    Container,
    ContainerType,
    MalformedContainer,
    OperationCode,
    code_name,
)
from benchctl.devices.camera.ptp.datasets import DeviceInfo, ObjectInfo
from benchctl.devices.camera.ptp.transport import NO_BACKEND, UsbTransport, parse_usb_id, usb_failure
from benchctl.devices.errors import DeviceBusy, DeviceError, DeviceTimeout
from benchctl.errors import BadValueError

u16 = st.integers(0, 0xFFFF)
u32 = st.integers(0, 0xFFFFFFFF)


@st.composite
def containers(draw: st.DrawFn) -> Container:
    kind = draw(st.sampled_from(list(ContainerType)))
    if kind == ContainerType.DATA:
        return Container(kind, draw(u16), draw(u32), payload=draw(st.binary(max_size=300)))
    params = draw(st.lists(u32, max_size=MAX_PARAMS[kind]))
    return Container(kind, draw(u16), draw(u32), tuple(params))


# -- containers --------------------------------------------------------------------------------------------------

@given(containers())
def test_pack_unpack_round_trip(container: Container) -> None:
    packed = container.pack()
    assert struct.unpack_from("<I", packed)[0] == len(packed)
    assert Container.unpack(packed) == container


@given(st.sampled_from([ContainerType.COMMAND, ContainerType.RESPONSE]), st.integers(0, 5), u16, u32)
def test_command_and_response_carry_zero_to_five_params(kind: ContainerType, count: int, code: int, tid: int) -> None:
    container = Container(kind, code, tid, tuple(range(count)))
    assert len(container.pack()) == HEADER_SIZE + 4 * count
    assert Container.unpack(container.pack()).params == tuple(range(count))


def test_exact_bytes_of_open_session() -> None:
    packed = Container(ContainerType.COMMAND, OperationCode.OpenSession, 0, (1,)).pack()
    assert packed == bytes.fromhex("10000000 0100 0210 00000000 01000000")


def test_events_carry_at_most_three_params() -> None:
    with pytest.raises(ValueError, match="at most 3"):
        Container(ContainerType.EVENT, 0x4002, 1, (1, 2, 3, 4))
    raw = struct.pack("<IHHI4I", 28, ContainerType.EVENT, 0x4002, 1, 1, 2, 3, 4)
    with pytest.raises(MalformedContainer, match="4 parameters, at most 3"):
        Container.unpack(raw)


@given(containers(), st.data())
def test_every_truncation_is_a_clear_error(container: Container, data: st.DataObject) -> None:
    packed = container.pack()
    cut = data.draw(st.integers(0, len(packed) - 1))
    with pytest.raises(MalformedContainer, match="truncated"):
        Container.unpack(packed[:cut])


@given(st.binary(max_size=64))
def test_arbitrary_bytes_parse_or_fail_clearly(raw: bytes) -> None:
    try:
        Container.unpack(raw)
    except MalformedContainer:
        pass


@pytest.mark.parametrize("raw, message", [
    (b"\x10\x00\x00\x00\x03\x00", "truncated PTP container: 6 bytes, the header alone is 12"),
    (struct.pack("<IHHI", 8, 3, 0x2001, 1), "length field 8 is less than the 12-byte header"),
    (struct.pack("<IHHI", 24, 3, 0x2001, 1) + b"\0" * 4,
     "truncated PTP container OK (0x2001): length field says 24 bytes, received 16"),
    (struct.pack("<IHHI", 12, 3, 0x2001, 1) + b"\0" * 4, "malformed PTP container OK (0x2001): length field says 12"),
    (struct.pack("<IHHI", 12, 7, 0x2001, 1), "type field 7 is not 1-4"),
    (struct.pack("<IHHI", 14, 3, 0x2001, 1) + b"\0\0", "2 parameter bytes is not a whole number"),
    (struct.pack("<IHHI6I", 36, 3, 0x2001, 1, *range(6)), "6 parameters, at most 5"),
])
def test_malformed_containers_name_the_field(raw: bytes, message: str) -> None:
    with pytest.raises(MalformedContainer, match=message.replace("(", r"\(").replace(")", r"\)")):
        Container.unpack(raw)


def test_code_names() -> None:
    assert code_name(0x9116) == "GetEvent (0x9116)"
    assert code_name(0x2019) == "DeviceBusy (0x2019)"
    assert code_name(0xA102) == "NotReady (0xA102)"  # Canon's, answered while no live-view frame is ready
    assert code_name(0xA1FE) == "0xA1FE"  # a code no table names


# -- datasets ----------------------------------------------------------------------------------------------------

text = st.text(alphabet=st.characters(min_codepoint=1, max_codepoint=0xD7FF), max_size=40)
codes = st.lists(u16, max_size=20).map(tuple)


@given(st.builds(DeviceInfo, standard_version=u16, vendor_extension_id=u32, vendor_extension_version=u16,
                 vendor_extension_desc=text, functional_mode=u16, operations_supported=codes,
                 events_supported=codes, device_properties_supported=codes, capture_formats=codes,
                 image_formats=codes, manufacturer=text, model=text, device_version=text, serial_number=text))
def test_device_info_round_trip(info: DeviceInfo) -> None:
    assert DeviceInfo.unpack(info.pack()) == info


def test_ptp_string_layout() -> None:
    packed = ObjectInfo(filename="A.CR2").pack()
    # 52 bytes of fixed fields, then u8 count (chars + NUL) and UTF-16LE
    assert packed[52:52 + 13] == b"\x06" + "A.CR2\0".encode("utf-16-le")
    assert ObjectInfo.unpack(packed).filename == "A.CR2"


def test_truncated_dataset_names_the_field() -> None:
    packed = DeviceInfo(model="Canon EOS M10", serial_number="").pack()
    with pytest.raises(MalformedContainer, match=r"truncated DeviceInfo: field model at byte \d+ needs 3 more byte"):
        DeviceInfo.unpack(packed[:-5])


# -- USB transport framing ---------------------------------------------------------------------------------------

class FakeEndpoint:
    """A bulk/interrupt endpoint that records writes and replays queued transfers."""

    def __init__(self, max_packet: int = 512, transfers: list[bytes] | None = None) -> None:
        self.wMaxPacketSize = max_packet
        self.writes: list[bytes] = []
        self.reads: list[int] = []
        self.transfers = list(transfers or [])

    def write(self, data: bytes, timeout: int | None = None) -> int:
        self.writes.append(bytes(data))
        return len(data)

    def read(self, size: int, timeout: int | None = None) -> bytes:
        self.reads.append(size)
        if not self.transfers:
            raise usb.core.USBTimeoutError("Operation timed out", -7, errno.ETIMEDOUT)
        data = self.transfers.pop(0)
        assert len(data) <= size, "the device sent more than the host asked for (overflow)"
        return data


def data_container(payload_size: int) -> bytes:
    return Container(ContainerType.DATA, OperationCode.GetPartialObject, 5, payload=b"\xab" * payload_size).pack()


@pytest.mark.parametrize("payload, zlp", [(500, True), (1012, True), (501, False), (0, False), (20, False)])
def test_zero_length_packet_when_data_phase_fills_whole_packets(payload: int, zlp: bool) -> None:
    out = FakeEndpoint(max_packet=512)
    UsbTransport(out, FakeEndpoint(), usb_vendor=0x04A9).send(data_container(payload))
    assert out.writes == [data_container(payload)] + ([b""] if zlp else [])


def test_zero_length_packet_follows_full_speed_packet_size() -> None:
    out = FakeEndpoint(max_packet=64)
    UsbTransport(out, FakeEndpoint(), usb_vendor=0x04A9).send(data_container(52))  # 64 bytes
    assert out.writes[-1] == b""


def test_receive_reads_a_long_container_in_chunks() -> None:
    whole = data_container(3000)  # 3012 bytes
    chunks = [whole[:1024], whole[1024:2048], whole[2048:]]
    bulk_in = FakeEndpoint(max_packet=512, transfers=chunks)
    assert UsbTransport(FakeEndpoint(), bulk_in, chunk_size=1024, usb_vendor=0x04A9).receive() == whole
    assert bulk_in.reads == [1024, 1024, 1024]  # the last asks for 964 rounded up to whole packets


def test_receive_skips_the_zero_length_packet_of_the_previous_container() -> None:
    first = data_container(500)  # 512 bytes: the camera ends it with a zero-length packet
    response = Container(ContainerType.RESPONSE, 0x2001, 5).pack()
    bulk_in = FakeEndpoint(transfers=[first, b"", response])
    transport = UsbTransport(FakeEndpoint(), bulk_in, usb_vendor=0x04A9)
    assert transport.receive() == first
    assert transport.receive() == response


def test_receive_of_a_cut_off_transfer_is_reported_by_the_parser() -> None:
    whole = data_container(2000)
    transport = UsbTransport(FakeEndpoint(), FakeEndpoint(transfers=[whole[:1024], b""]), chunk_size=1024,
                             usb_vendor=0x04A9)
    with pytest.raises(MalformedContainer, match="length field says 2012 bytes, received 1024"):
        Container.unpack(transport.receive())


def test_events_from_the_interrupt_endpoint() -> None:
    event = Container(ContainerType.EVENT, 0x4002, 3, (0x1234,)).pack()
    transport = UsbTransport(FakeEndpoint(), FakeEndpoint(), FakeEndpoint(max_packet=64, transfers=[event]),
                             usb_vendor=0x04A9)
    assert transport.receive_event(0.01) == event
    assert transport.receive_event(0.01) is None  # timed out: no event
    no_interrupt = UsbTransport(FakeEndpoint(), FakeEndpoint(), usb_vendor=0x04A9)
    assert no_interrupt.receive_event(0.01) is None


def test_close_runs_once_and_ignores_a_vanished_device() -> None:
    calls = []

    def release() -> None:
        calls.append(1)
        raise usb.core.USBError("No such device (it may have been disconnected)", -4, errno.ENODEV)

    transport = UsbTransport(FakeEndpoint(), FakeEndpoint(), on_close=release, usb_vendor=0x04A9)
    transport.close()
    transport.close()
    assert calls == [1]


# -- USB errors as the user reads them ---------------------------------------------------------------------------

def test_usb_failures_become_one_line_errors() -> None:
    timeout = usb_failure(usb.core.USBTimeoutError("Operation timed out", -7, errno.ETIMEDOUT), "GetEvent", 10)
    assert isinstance(timeout, DeviceTimeout) and "did not answer GetEvent within 10 s" in str(timeout)
    gone = usb_failure(usb.core.USBError("No such device (it may have been disconnected)", -4, errno.ENODEV),
                       "GetPartialObject")
    assert "disconnected during GetPartialObject" in str(gone) and "cable" in str(gone)
    denied = usb_failure(usb.core.USBError("Access denied (insufficient permissions)", -3, errno.EACCES), "x")
    assert "permission denied" in str(denied) and UDEV_RULE in str(denied)
    busy = usb_failure(usb.core.USBError("Resource busy", -6, errno.EBUSY), "x")
    assert isinstance(busy, DeviceBusy) and "gvfs-gphoto2-volume-monitor" in str(busy)
    for error in (timeout, gone, denied, busy):
        assert "\n" not in str(error)


class FakeInterface:
    bInterfaceClass = 6


class FakeUsbDevice:
    """Enough of a pyusb Device (one configuration, one PTP interface) for UsbTransport.open to fail the way a
    real one does; `error` is raised when it is first touched."""

    def __init__(self, error: usb.core.USBError | None = None) -> None:
        self.error = error

    def get_active_configuration(self) -> None:
        if self.error is not None:
            raise self.error

    def __iter__(self) -> Iterator[list[FakeInterface]]:
        return iter([[FakeInterface()]])


@pytest.fixture
def released(monkeypatch: pytest.MonkeyPatch) -> list[object]:
    disposed: list[object] = []
    monkeypatch.setattr(transport_module.usb.util, "dispose_resources", disposed.append)
    return disposed


def test_open_without_libusb(monkeypatch: pytest.MonkeyPatch) -> None:
    def no_backend(**_: object) -> None:
        raise usb.core.NoBackendError("No backend available")

    monkeypatch.setattr(usb.core, "find", no_backend)
    with pytest.raises(DeviceError, match="^no libusb backend: install libusb-1.0") as caught:
        UsbTransport.open("04a9:32a0")
    assert str(caught.value) == NO_BACKEND


def test_open_camera_not_found(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(usb.core, "find", lambda **_: None)
    with pytest.raises(DeviceError, match=r"camera 04a9:32a0 not found on USB: is it on, in PTP mode, not grabbed "
                                          r"by a desktop daemon \(gvfs-gphoto2-volume-monitor\)\?"):
        UsbTransport.open("04a9:32a0")


def test_open_permission_denied_points_to_the_udev_rule(monkeypatch: pytest.MonkeyPatch,
                                                         released: list[object]) -> None:
    device = FakeUsbDevice(usb.core.USBError("Access denied (insufficient permissions)", -3, errno.EACCES))
    monkeypatch.setattr(usb.core, "find", lambda **_: device)
    with pytest.raises(DeviceError, match=f"permission denied .*{UDEV_RULE}"):
        UsbTransport.open("04a9:32a0")
    assert released == [device]


def test_open_interface_held_by_a_daemon(monkeypatch: pytest.MonkeyPatch, released: list[object]) -> None:
    def claimed_elsewhere(device: object, interface: object) -> None:
        raise usb.core.USBError("Resource busy", -6, errno.EBUSY)

    monkeypatch.setattr(usb.core, "find", lambda **_: FakeUsbDevice())
    monkeypatch.setattr(transport_module.usb.util, "claim_interface", claimed_elsewhere)
    with pytest.raises(DeviceBusy, match="held by another program.*gvfs-gphoto2-volume-monitor"):
        UsbTransport.open("04a9:32a0")
    assert len(released) == 1


def test_usb_id_must_be_hex_pair() -> None:
    assert parse_usb_id("04a9:32a0") == (0x04A9, 0x32A0)
    with pytest.raises(BadValueError, match="vendor:product"):
        parse_usb_id("canon")
