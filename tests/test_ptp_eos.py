"""The ptp camera driver and the Canon EOS layer against the simulated EOS M10 body: the exact operation
sequence, the bytes delivered, chunked download, every fault mode, property writes, sessions and GetEvent
records."""

from __future__ import annotations

import dataclasses
import math
import struct
from pathlib import Path

import msgspec
import pytest

from benchctl.devices.camera.ptp.container import (
    CANON_VENDOR_ID,
    MTP_VENDOR_ID,
    Container,
    ContainerType,
    EventCode,
    MalformedContainer,
    ObjectFormat,
    OperationCode,
    ResponseCode,
)
from benchctl.devices.camera.ptp.eos import (
    PARTIAL_CHUNK,
    Eos,
    EosEventType,
    EosProperty,
    iso_code,
    object_record,
    pack_camera_status,
    pack_events,
    pack_object_record,
    parse_events,
    shutter_code,
)
from benchctl.devices.camera.ptp.session import PtpSession, ResponseBusy, ResponseError
from benchctl.devices.camera.ptp.transport import NO_BACKEND, Transport, UsbTransport
from benchctl.devices.camera.ptp_camera import EosTiming, PtpCamera, open_ptp_camera
from benchctl.devices.errors import DeviceBusy, DeviceError, DeviceTimeout
from benchctl.devices.sim.eos_usb import FIRST_HANDLE, SimEosTransport
from benchctl.errors import BadValueError
from benchctl.profiles import CameraConfig

FAST = EosTiming(settle_s=0.0, release_events_s=0.05, poll_interval_s=0.001, busy_retry_s=0.05)
Op = OperationCode
OPEN_SEQUENCE = [Op.OpenSession, Op.GetDeviceInfo, Op.EosSetRemoteMode, Op.EosSetEventMode, Op.EosGetEvent,
                 Op.EosGetEvent, Op.EosSetDevicePropValueEx, Op.EosPCHDDCapacity, Op.EosSetEventMode,
                 Op.EosSetDevicePropValueEx]


def raw_image(size: int, seed: int = 7) -> bytes:
    return bytes((seed + 31 * i) % 251 for i in range(size))


class Images:
    """An image_source handing out numbered RAW files, remembering what it produced."""

    def __init__(self, size: int = 5000, suffix: str = "DNG") -> None:
        self.size = size
        self.suffix = suffix
        self.produced: list[tuple[bytes, str]] = []

    def __call__(self) -> tuple[bytes, str]:
        n = len(self.produced) + 1
        self.produced.append((raw_image(self.size, n), f"IMG_{n:04d}.{self.suffix}"))
        return self.produced[-1]


def config(**changes: object) -> CameraConfig:
    return msgspec.structs.replace(CameraConfig(driver="ptp", transport="usb"), **changes)  # type: ignore[arg-type]


def camera(sim: SimEosTransport, **changes: object) -> PtpCamera:
    return open_ptp_camera(config(**changes), sim, FAST)


def capture_ops(sim: SimEosTransport, start: int) -> list[int]:
    return sim.operations[start:]


# -- the capture sequence ----------------------------------------------------------------------------------------

def test_exact_operation_sequence_and_transaction_ids(tmp_path: Path) -> None:
    images = Images(size=5000)
    sim = SimEosTransport(images)
    with camera(sim) as cam:
        assert sim.operations == OPEN_SEQUENCE
        frames = cam.capture(tmp_path, frames=1)
    assert sim.operations == OPEN_SEQUENCE + [
        Op.EosRemoteReleaseOn, Op.EosGetEvent, Op.EosRemoteReleaseOff, Op.EosGetEvent, Op.GetPartialObject,
        Op.EosTransferComplete, Op.CloseSession]
    assert [c.transaction_id for c in sim.commands] == list(range(len(sim.commands)))  # OpenSession is 0
    params = {Op(c.code): c.params for c in sim.commands}
    assert params[Op.OpenSession] == (1,)
    assert params[Op.EosSetRemoteMode] == (0x15,)
    assert params[Op.EosPCHDDCapacity] == (0x0FFFFFFF, 0x1000, 1)
    assert params[Op.EosRemoteReleaseOn] == (3, 0)
    assert params[Op.EosRemoteReleaseOff] == (3,)
    assert params[Op.GetPartialObject] == (FIRST_HANDLE, 0, 5000)
    assert params[Op.EosTransferComplete] == (FIRST_HANDLE,)
    assert [c.params for c in sim.commands if c.code == Op.EosSetEventMode] == [(1,), (2,)]
    assert sim.property_writes == [(EosProperty.CaptureDestination, (4,)), (EosProperty.EVFOutputDevice, (8,))]
    assert sim.closed
    frame = frames[0]
    assert frame.data == images.produced[0][0] and frame.file_name == "IMG_0001.DNG" and frame.format == "dng"
    assert frame.path is not None and frame.path.read_bytes() == images.produced[0][0]
    assert frame.metadata["camera"] == "Canon EOS M10" and frame.metadata["settings_written"] is False


def test_received_bytes_equal_the_image_source_for_every_frame() -> None:
    images = Images(size=3 * 1024 + 5, suffix="CR2")
    with camera(SimEosTransport(images)) as cam:
        frames = cam.capture(frames=3)
    assert [(f.data, f.file_name) for f in frames] == images.produced
    assert {f.format for f in frames} == {"cr2"}


def test_identity_from_device_info() -> None:
    with camera(SimEosTransport(Images())) as cam:
        assert cam.identity() == {"driver": "ptp", "manufacturer": "Canon Inc.", "model": "Canon EOS M10",
                                  "serial": "5a1c0ffee0ddba11deadbeef00c0ffee", "firmware": "3-1.1.0"}


@pytest.mark.parametrize("size", [1, PARTIAL_CHUNK - 1, PARTIAL_CHUNK, PARTIAL_CHUNK + 1, 2 * PARTIAL_CHUNK + 12345])
def test_download_in_1_mib_chunks(size: int) -> None:
    images = Images(size=size)
    sim = SimEosTransport(images)
    with camera(sim) as cam:
        frame = cam.capture()[0]
    partial = [c.params for c in sim.commands if c.code == Op.GetPartialObject]
    assert len(partial) == math.ceil(size / PARTIAL_CHUNK)
    assert [offset for _, offset, _ in partial] == [i * PARTIAL_CHUNK for i in range(len(partial))]
    assert sum(length for _, _, length in partial) == size
    assert frame.data == images.produced[0][0]


def test_name_from_object_info_when_the_record_has_none() -> None:
    sim = SimEosTransport(Images(), short_transfer_records=True)
    with camera(sim) as cam:
        start = len(sim.operations)
        frame = cam.capture()[0]
    assert Op.GetObjectInfo in capture_ops(sim, start)
    assert frame.file_name == "IMG_0001.DNG" and frame.format == "dng"


def test_a_jpeg_is_refused_with_what_to_do() -> None:
    with camera(SimEosTransport(Images(suffix="JPG"))) as cam:
        with pytest.raises(DeviceError, match="delivered IMG_0001.JPG, not a RAW file .*JPEG.*set the image "
                                              "quality to RAW on the camera"):
            cam.capture()


def test_an_eos_body_reporting_the_mtp_vendor_extension_is_a_canon() -> None:
    """Canon bodies on USB often report VendorExtensionID 6 (Microsoft / MTP), not Canon's 0x0B: the USB vendor
    0x04A9 and the EOS operations decide (as libgphoto2 does)."""
    images = Images()
    sim = SimEosTransport(images, vendor_extension_id=MTP_VENDOR_ID)
    with camera(sim) as cam:
        frame = cam.capture()[0]
    assert sim.operations[:len(OPEN_SEQUENCE)] == OPEN_SEQUENCE
    assert frame.data == images.produced[0][0]


class BodyOnUsb:
    """The simulated body behind bulk endpoints, as pyusb gives them: containers written whole, read back in the
    sizes the host asks for."""

    wMaxPacketSize = 512

    def __init__(self, body: SimEosTransport) -> None:
        self.body, self.pending = body, b""

    def write(self, data: bytes, timeout: int | None = None) -> int:
        if data:  # a zero-length packet only ends a transfer
            self.body.send(bytes(data))
        return len(data)

    def read(self, size: int, timeout: int | None = None) -> bytes:
        self.pending = self.pending or self.body.receive()
        data, self.pending = self.pending[:size], self.pending[size:]
        return data


def test_a_canon_reporting_the_mtp_extension_through_a_usb_transport_built_by_its_constructor() -> None:
    """UsbTransport(...) had no USB vendor unless UsbTransport.open made it, so a Canon answering VendorExtensionID 6
    through one built directly was refused: the vendor is now the constructor's."""
    images = Images()
    body = SimEosTransport(images, vendor_extension_id=MTP_VENDOR_ID)
    endpoints = BodyOnUsb(body)
    with open_ptp_camera(config(), UsbTransport(endpoints, endpoints, usb_vendor=0x04A9), FAST) as cam:
        frame = cam.capture()[0]
    assert frame.data == images.produced[0][0] and body.operations[:len(OPEN_SEQUENCE)] == OPEN_SEQUENCE


def test_the_mtp_vendor_extension_from_another_usb_vendor_is_not_a_canon() -> None:
    sim = SimEosTransport(Images(), vendor_extension_id=MTP_VENDOR_ID, usb_vendor=0x04B0)
    sim.device_info = dataclasses.replace(sim.device_info, model="Other")
    with pytest.raises(DeviceError, match=r"^Other \(04a9:32a0\) is not a Canon body \(USB vendor 0x04b0, PTP "
                                          r"vendor extension 6\): use camera driver 'gphoto2'$"):
        camera(sim)
    assert sim.closed and Op.EosSetRemoteMode not in sim.operations


@pytest.mark.parametrize("vendor_extension_id", [CANON_VENDOR_ID, MTP_VENDOR_ID])
def test_a_canon_without_the_eos_operations_is_refused(vendor_extension_id: int) -> None:
    """A PowerShot: Canon by USB vendor and extension, but no EOS remote release or event polling."""
    sim = SimEosTransport(Images(), vendor_extension_id=vendor_extension_id)
    without = {Op.EosRemoteReleaseOn, Op.EosGetEvent}
    sim.device_info = dataclasses.replace(sim.device_info, model="Canon PowerShot G7 X", operations_supported=tuple(
        code for code in sim.device_info.operations_supported if code not in without))
    with pytest.raises(DeviceError, match=r"Canon PowerShot G7 X \(04a9:32a0\) does not offer Canon EOS remote "
                                          r"release and events \(no RemoteReleaseOn \(0x9128\), GetEvent "
                                          r"\(0x9116\)\): use camera driver 'gphoto2'"):
        camera(sim)
    assert sim.closed


# -- fault modes -------------------------------------------------------------------------------------------------

def test_busy_releases_are_retried() -> None:
    sim = SimEosTransport(Images(), busy_releases=2)
    with open_ptp_camera(config(), sim, dataclasses.replace(FAST, busy_retry_s=5.0)) as cam:
        start = len(sim.operations)
        cam.capture()
    ops = capture_ops(sim, start)
    assert ops[:5] == [Op.EosRemoteReleaseOn, Op.EosGetEvent, Op.EosRemoteReleaseOn, Op.EosGetEvent,
                       Op.EosRemoteReleaseOn]
    assert ops.count(Op.EosRemoteReleaseOn) == 3


def test_camera_busy_for_too_long() -> None:
    with camera(SimEosTransport(Images(), busy_releases=10**6)) as cam:
        with pytest.raises(DeviceBusy, match=r"stayed busy for 0.05 s .*DeviceBusy 0x2019.*manual focus"):
            cam.capture()


def test_no_focus() -> None:
    sim = SimEosTransport(Images(), no_focus=True)
    with camera(sim) as cam:
        start = len(sim.operations)
        with pytest.raises(DeviceError, match="could not focus .*manual focus"):
            cam.capture()
    assert capture_ops(sim, start) == [Op.EosRemoteReleaseOn, Op.EosRemoteReleaseOff, Op.CloseSession]


def test_timeout_waiting_for_the_image_says_how_long() -> None:
    sim = SimEosTransport(Images(), no_transfer=True)
    with camera(sim, image_timeout_s=0.05) as cam:
        with pytest.raises(DeviceTimeout, match=r"sent no image within 0.05 s .*RequestObjectTransfer"):
            cam.capture()
    assert Op.GetPartialObject not in sim.operations


def test_cable_pulled_mid_transfer() -> None:
    sim = SimEosTransport(Images(size=3 * PARTIAL_CHUNK), unplug_after_bytes=PARTIAL_CHUNK)
    cam = camera(sim)
    with pytest.raises(DeviceError, match=r"camera disconnected during GetPartialObject \(0x101B\): USB cable "
                                          r"pulled or camera switched off; reconnect"):
        cam.capture()
    assert [c.params[1] for c in sim.commands if c.code == Op.GetPartialObject] == [0, PARTIAL_CHUNK]
    cam.close()  # the device is gone: closing must not raise
    assert sim.closed


def test_property_write_freezes_the_m10() -> None:
    sim = SimEosTransport(Images(), freeze_on_property_write=True)
    with pytest.raises(DeviceTimeout, match=r"stopped answering after writing image format RAW .*freezes on "
                                            r"property writes.*write_properties = false"):
        open_ptp_camera(config(write_properties=True, exposure_s=0.01), sim, FAST)
    assert sim.frozen and sim.closed


def test_freeze_does_not_happen_without_property_writes() -> None:
    sim = SimEosTransport(Images(), freeze_on_property_write=True)
    with camera(sim, exposure_s=0.01, iso=200) as cam:  # settings in the profile, writes off (the default)
        frame = cam.capture()[0]
    assert not sim.frozen and "exposure_s" not in frame.metadata


# -- property writes ---------------------------------------------------------------------------------------------

def test_no_exposure_property_writes_by_default() -> None:
    sim = SimEosTransport(Images())
    with camera(sim, exposure_s=0.01, iso=400) as cam:
        cam.capture()
    written = {prop for prop, _ in sim.property_writes}
    assert written == {EosProperty.CaptureDestination, EosProperty.EVFOutputDevice}  # capture set-up only
    assert not written & {EosProperty.ShutterSpeed, EosProperty.ISO, EosProperty.ImageFormat}


def test_property_writes_when_configured() -> None:
    sim = SimEosTransport(Images())
    with camera(sim, write_properties=True, exposure_s=1 / 125, iso=400) as cam:
        assert sim.operations == OPEN_SEQUENCE + [Op.EosSetDevicePropValueEx] * 3
        frame = cam.capture()[0]
    assert sim.property_writes[2:] == [(EosProperty.ImageFormat, (1, 0x10, 6, 0, 4)),
                                       (EosProperty.ShutterSpeed, (0x70,)), (EosProperty.ISO, (0x58,))]
    assert sim.data_phases[-1] == struct.pack("<III", 12, EosProperty.ISO, 0x58)  # u32 size, property, value
    assert sim.data_phases[2] == struct.pack("<7I", 28, EosProperty.ImageFormat, 1, 0x10, 6, 0, 4)
    assert frame.metadata["exposure_s"] == 1 / 125 and frame.metadata["iso"] == 400
    assert frame.metadata["settings_written"] is True


def test_exposure_codes() -> None:
    assert [iso_code(iso) for iso in (100, 125, 160, 200, 400, 800, 12800)] == [
        0x48, 0x4B, 0x4D, 0x50, 0x58, 0x60, 0x80]
    assert [shutter_code(t) for t in (30, 25, 1, 0.5, 0.3, 1 / 4, 1 / 60, 1 / 125, 1 / 4000)] == [
        0x10, 0x13, 0x38, 0x40, 0x45, 0x48, 0x68, 0x70, 0x98]
    with pytest.raises(BadValueError, match="ISO 50"):
        iso_code(50)
    with pytest.raises(BadValueError, match="exposure 60 s"):
        shutter_code(60)


# -- connecting --------------------------------------------------------------------------------------------------

def test_real_usb_without_libusb(monkeypatch: pytest.MonkeyPatch) -> None:
    import usb.core

    def no_backend(**_: object) -> None:
        raise usb.core.NoBackendError("No backend available")

    monkeypatch.setattr(usb.core, "find", no_backend)
    with pytest.raises(DeviceError, match="^" + NO_BACKEND.replace("(", r"\(").replace(")", r"\)") + "$"):
        open_ptp_camera(config())


def test_sim_transport_in_the_profile_needs_the_simulated_bench() -> None:
    with pytest.raises(DeviceError, match="needs the simulated EOS body"):
        open_ptp_camera(config(transport="sim"))


# -- sessions and transactions -----------------------------------------------------------------------------------

def test_session_not_open() -> None:
    session = PtpSession(SimEosTransport(Images()))
    assert session.get_device_info().model == "Canon EOS M10"  # allowed outside a session
    with pytest.raises(ResponseError, match=r"camera refused GetEvent \(0x9116\): SessionNotOpen \(0x2003\)"):
        Eos(session).get_events()


def test_session_left_open_by_a_dead_program_is_reopened() -> None:
    sim = SimEosTransport(Images())
    PtpSession(sim).open()  # never closed
    session = PtpSession(sim)
    session.open()
    assert session.is_open
    assert [(Op(c.code), c.transaction_id) for c in sim.commands] == [
        (Op.OpenSession, 0), (Op.OpenSession, 0), (Op.CloseSession, 1), (Op.OpenSession, 0)]


def test_initiate_capture_is_not_offered() -> None:
    session = PtpSession(SimEosTransport(Images()))
    session.open()
    assert Op.InitiateCapture not in session.get_device_info().operations_supported
    with pytest.raises(ResponseError, match="OperationNotSupported") as caught:
        session.request(Op.InitiateCapture)
    assert caught.value.response == ResponseCode.OperationNotSupported


def test_device_busy_response_is_a_device_busy_error() -> None:
    session = PtpSession(SimEosTransport(Images(), busy_releases=1))
    session.open()
    Eos(session).pc_hdd_capacity()
    with pytest.raises(ResponseBusy) as caught:
        Eos(session).remote_release_on()
    assert isinstance(caught.value, DeviceBusy)


class ScriptedTransport(Transport):
    """Answers each send with the next scripted reply (a list of raw containers)."""

    def __init__(self, replies: list[list[bytes]]) -> None:
        self.replies = replies
        self.pending: list[bytes] = []

    def send(self, container: bytes) -> None:
        if Container.unpack(container).type == ContainerType.COMMAND:
            self.pending = self.replies.pop(0)

    def receive(self) -> bytes:
        return self.pending.pop(0)

    def receive_event(self, timeout_s: float) -> bytes | None:
        return None

    def close(self) -> None:
        pass


def test_truncated_response_from_the_camera() -> None:
    response = Container(ContainerType.RESPONSE, ResponseCode.OK, 0).pack()
    session = PtpSession(ScriptedTransport([[response[:-2] + b"\x00"]]))
    with pytest.raises(MalformedContainer, match="truncated PTP container: 11 bytes"):
        session.open()


def test_response_out_of_step() -> None:
    stale = Container(ContainerType.RESPONSE, ResponseCode.OK, 41).pack()
    with pytest.raises(DeviceError, match="answered transaction 41 while OpenSession \\(0x1002\\) was transaction 0"):
        PtpSession(ScriptedTransport([[stale]])).open()


def test_data_phase_in_both_directions() -> None:
    info = Container(ContainerType.DATA, Op.GetDeviceInfo, 0, payload=b"\x01\x02").pack()
    ok = Container(ContainerType.RESPONSE, ResponseCode.OK, 0, (9,)).pack()
    response = PtpSession(ScriptedTransport([[info, ok]])).transact(Op.GetDeviceInfo)
    assert (response.code, response.params, response.data) == (ResponseCode.OK, (9,), b"\x01\x02")


def test_transaction_ids_wrap_past_0xfffffffe() -> None:
    session = PtpSession(ScriptedTransport([]))
    session._next_id = 0xFFFFFFFE
    assert [session._take_id() for _ in range(3)] == [0xFFFFFFFE, 1, 2]


# -- GetEvent records --------------------------------------------------------------------------------------------

def test_event_records_at_the_documented_offsets() -> None:
    transfer = pack_object_record(EosEventType.RequestObjectTransfer, 0x90ABCDEF, 0x01234567, ObjectFormat.CR2,
                                  "IMG_0042.CR2")
    assert struct.unpack_from("<III", transfer, 0)[1:] == (EosEventType.RequestObjectTransfer, 0x90ABCDEF)
    assert struct.unpack_from("<I", transfer, 0x14)[0] == 0x01234567
    added = pack_object_record(EosEventType.ObjectAddedEx, 0x90000002, 777, ObjectFormat.DNG, "IMG_0043.DNG")
    assert struct.unpack_from("<I", added, 8)[0] == 0x90000002
    events = parse_events(pack_events([pack_camera_status(1), transfer, added]))
    assert [e.type for e in events] == [EosEventType.CameraStatus, EosEventType.RequestObjectTransfer,
                                        EosEventType.ObjectAddedEx]
    assert events[0].u32(8) == 1
    first, second = object_record(events[1]), object_record(events[2])
    assert (first.handle, first.size, first.format, first.name) == (0x90ABCDEF, 0x01234567, ObjectFormat.CR2,
                                                                    "IMG_0042.CR2")
    assert (second.handle, second.size, second.format, second.name) == (0x90000002, 777, ObjectFormat.DNG,
                                                                        "IMG_0043.DNG")


def test_empty_event_list_is_just_the_terminator() -> None:
    assert pack_events([]) == struct.pack("<II", 8, 0)
    assert parse_events(pack_events([])) == []


@pytest.mark.parametrize("data, message", [
    (pack_camera_status(1), "ends at byte 12 without the terminator"),
    (struct.pack("<II", 4, 0xC18B) + pack_events([]), "record at byte 0: size field 4 is less than its 8-byte"),
    (struct.pack("<II", 40, 0xC18B) + b"\0" * 4, "record 0xC18B at byte 0: size field says 40 bytes, only 12"),
])
def test_malformed_event_data(data: bytes, message: str) -> None:
    with pytest.raises(MalformedContainer, match=message):
        parse_events(data)


def test_truncated_object_record() -> None:
    record = pack_object_record(EosEventType.RequestObjectTransfer, 1, 2, ObjectFormat.CR2, "A")[:0x10]
    events = parse_events(struct.pack("<I", 0x10) + record[4:] + pack_events([]))
    with pytest.raises(MalformedContainer, match="RequestObjectTransfer record: 16 bytes"):
        object_record(events[0])


def test_image_kept_on_the_card_is_announced_with_object_added() -> None:
    sim = SimEosTransport(Images())
    session = PtpSession(sim)
    session.open()
    eos = Eos(session)
    eos.remote_release_on()  # capture destination still the card
    eos.remote_release_off()
    records = [e for e in eos.get_events() if e.type == EosEventType.ObjectAddedEx]
    assert object_record(records[0]).handle == FIRST_HANDLE
    assert session.get_object_info(FIRST_HANDLE).filename == "IMG_0001.DNG"


def test_short_camera_status_record() -> None:
    events = parse_events(struct.pack("<II", 10, EosEventType.CameraStatus) + b"\0\0" + pack_events([]))
    with pytest.raises(MalformedContainer, match="record 0xC18B: 10 bytes, a field at byte 8 needs 12"):
        events[0].u32(8)


def test_standard_events_from_the_interrupt_endpoint() -> None:
    class EventTransport(ScriptedTransport):
        def __init__(self, events: list[bytes | None]) -> None:
            super().__init__([])
            self.events = events

        def receive_event(self, timeout_s: float) -> bytes | None:
            return self.events.pop(0)

    added = Container(ContainerType.EVENT, EventCode.ObjectAdded, 4, (0x90000001,)).pack()
    session = PtpSession(EventTransport([added, None]))
    event = session.poll_event(0.01)
    assert event is not None and (event.code, event.params) == (EventCode.ObjectAdded, (0x90000001,))
    assert session.poll_event(0.01) is None
    unplugged = SimEosTransport(Images())
    unplugged.unplugged = True
    with pytest.raises(DeviceError, match="camera disconnected during an event wait"):
        PtpSession(unplugged).poll_event(0.01)
