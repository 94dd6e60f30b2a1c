"""Live view for the console: the simulator's binned preview against its own full capture, the Camera preview hook
(simulated camera, default capture), and the EOS live view over PTP (GetViewFinderData) against the simulated
body, byte for byte."""

from __future__ import annotations

import struct
from pathlib import Path

import cv2
import numpy as np
import pytest

from benchctl.capture.raw import decode_raw
from benchctl.devices.camera import open_camera
from benchctl.devices.camera.ptp.container import MalformedContainer, OperationCode, ResponseCode
from benchctl.devices.camera.ptp.eos import EVF_OUTPUT_PC, EosProperty, pack_viewfinder, viewfinder_jpeg
from benchctl.devices.camera.ptp_camera import EosTiming, open_ptp_camera
from benchctl.devices.errors import DeviceTimeout
from benchctl.devices.laser import open_laser
from benchctl.devices.sim import bench, eos_usb
from benchctl.devices.sim.eos_usb import SimEosTransport
from benchctl.devices.sim.state import CAMERA_STATE, load_state
from benchctl.devices.slm import open_slm
from benchctl.profiles import CameraConfig, Profile, load_profile

FAST = EosTiming(settle_s=0.0, release_events_s=0.05, poll_interval_s=0.001, busy_retry_s=0.05)
Op = OperationCode


def lit_bench(profile: Profile, channel: str = "green", power: str = "2mW") -> None:
    """Show a grating-free flat phase and leave `channel` emitting (the simulated devices keep their state)."""
    with open_slm(profile) as slm:
        slm.sleep = lambda s: None
        slm.show_phase(np.zeros(profile.slm.shape), channel)
    laser = open_laser(profile, leave_on=True)
    with laser:
        laser.set_power(channel, power)
        laser.set_emission(channel, True)


def test_binned_live_view_has_the_full_captures_signal(bench_profile_path: Path) -> None:
    profile = load_profile(bench_profile_path)
    lit_bench(profile)
    capture = decode_raw(bench.render_capture(profile).data)
    view = bench.LiveView(profile)
    data, metadata = view.dng(110)
    frame = decode_raw(data)
    rows, cols = view.active_shape
    assert metadata["window"] == [0, 0, rows, cols] and metadata["bin"] == pytest.approx(cols / 110, rel=0.02)
    assert frame.mosaic.shape == (round(rows / metadata["bin"]) & ~1, 110) and frame.layout == capture.layout
    # the same light on average (the preview bins, the capture does not), and the light where the capture has it
    assert frame.mosaic.mean() == pytest.approx(capture.mosaic.mean(), rel=0.03)
    assert capture.mosaic.mean() > 20 * np.abs(capture.mosaic[:6]).mean()  # there is light to compare
    green = frame.planes()[1]
    small = cv2.resize(capture.planes()[1], green.shape[::-1], interpolation=cv2.INTER_AREA)
    assert np.corrcoef(small.ravel(), green.ravel())[0, 1] > 0.9


def test_a_native_window_is_the_sensor_at_one_to_one(bench_profile_path: Path) -> None:
    profile = load_profile(bench_profile_path)
    lit_bench(profile)
    capture = decode_raw(bench.render_capture(profile).data)
    data, metadata = bench.LiveView(profile).dng(64, (101, 151, 64, 64))  # corner moved onto a CFA cell
    assert metadata["window"] == [100, 150, 64, 64] and metadata["bin"] == 1.0
    zoom = decode_raw(data)
    region = capture.mosaic[100:164, 150:214]
    assert zoom.mosaic.shape == (64, 64) and zoom.layout == capture.layout
    assert zoom.mosaic.mean() == pytest.approx(region.mean(), rel=0.05)
    assert np.corrcoef(zoom.mosaic.ravel(), region.ravel())[0, 1] > 0.8  # pixel for pixel the same scene


def test_light_is_computed_once_per_slm_frame_and_laser_state(bench_profile_path: Path,
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    profile = load_profile(bench_profile_path)
    lit_bench(profile)
    calls = []
    original = bench._electron_planes
    monkeypatch.setattr(bench, "_electron_planes", lambda *a: calls.append(a[2]) or original(*a))
    view = bench.LiveView(profile)
    first = [view.render(64)[0] for _ in range(3)]
    assert len(calls) == 1 and not np.array_equal(first[0], first[1])  # new noise, same light
    lit_bench(profile, "green", "4mW")
    brighter, metadata = view.render(64)
    assert len(calls) == 2 and calls[-1] == {"green": pytest.approx(0.004)}
    assert metadata["lasers_on_w"] == {"green": pytest.approx(0.004)}
    black = profile.sim.sensor.black_level
    assert (brighter.astype(float) - black).mean() == pytest.approx(2 * (first[0].astype(float) - black).mean(),
                                                                      rel=0.05)
    with open_slm(profile) as slm:
        slm.sleep = lambda s: None
        slm.blank()
        shown = slm.shown_frame
    assert view.render(64)[1]["slm_frame"] == shown and len(calls) == 3


def test_the_simulated_camera_previews_without_taking_a_capture_number(bench_profile_path: Path) -> None:
    profile = load_profile(bench_profile_path)
    lit_bench(profile)
    with open_camera(profile) as camera:
        assert camera.windowed_preview
        frame = camera.preview(width=100)
        zoom = camera.preview(32, (40, 60, 32, 32))
        captured = camera.capture()[0]
    assert frame.format == "dng" and frame.full_shape == bench.LiveView(profile).active_shape
    assert frame.metadata["lasers_on_w"] == {"green": pytest.approx(0.002)}
    assert decode_raw(frame.data).mosaic.shape[1] == 100
    assert zoom.window == (40, 60, 32, 32) and decode_raw(zoom.data).mosaic.shape == (32, 32)
    assert captured.metadata["frame"] == 1 and load_state(CAMERA_STATE)["frame"] == 1


class Images:
    def __init__(self) -> None:
        self.count = 0

    def __call__(self) -> tuple[bytes, str]:
        self.count += 1
        return bytes(range(200)) * 10, f"IMG_{self.count:04d}.DNG"


def jpeg(level: int) -> bytes:
    ok, data = cv2.imencode(".jpg", np.full((24, 36, 3), level, np.uint8))
    assert ok
    return data.tobytes()


def ptp_config() -> CameraConfig:
    return CameraConfig(driver="ptp", transport="usb")


def test_eos_live_view_over_ptp_byte_for_byte() -> None:
    frames = [jpeg(40), jpeg(200)]
    sim = SimEosTransport(Images(), live_view=lambda: frames[sim.live_view_frames - 1])
    with open_ptp_camera(ptp_config(), sim, FAST) as camera:
        start = len(sim.commands)
        first = camera.preview()
        assert sim.operations[start:] == [Op.EosSetDevicePropValueEx, Op.EosGetViewFinderData, Op.EosGetEvent,
                                          Op.EosGetViewFinderData]
        second = camera.preview()
        assert sim.operations[-1] == Op.EosGetViewFinderData and sim.operations.count(Op.EosSetDevicePropValueEx) == 3
        params = [c.params for c in sim.commands if c.code == Op.EosGetViewFinderData]
        assert set(params) == {(0x00100000,)}
        camera.capture()
        assert sim.property_writes[-2:] == [(EosProperty.EVFOutputDevice, (2,)),
                                            (EosProperty.EVFOutputDevice, (EVF_OUTPUT_PC,))]
        assert sim.operations.index(Op.EosRemoteReleaseOn) > len(sim.operations) - 10
    assert (first.format, first.data) == ("jpeg", frames[0]) and second.data == frames[1]
    assert not camera.windowed_preview


def test_a_body_without_live_view_previews_by_capturing() -> None:
    images = Images()
    sim = SimEosTransport(images)
    with open_ptp_camera(ptp_config(), sim, FAST) as camera:
        frame = camera.preview()
    assert frame.format == "dng" and frame.data == bytes(range(200)) * 10 and images.count == 1
    assert Op.EosGetViewFinderData not in sim.operations and Op.EosRemoteReleaseOn in sim.operations


def test_live_view_records() -> None:
    image = jpeg(90)
    assert viewfinder_jpeg(pack_viewfinder(image)) == image
    other = struct.pack("<II", 12, 0x0B) + b"\0\0\0\0"
    assert viewfinder_jpeg(other + pack_viewfinder(image)) == image  # metadata records before the image
    with pytest.raises(MalformedContainer, match="no image record"):
        viewfinder_jpeg(other)
    with pytest.raises(MalformedContainer, match="not a JPEG"):
        viewfinder_jpeg(struct.pack("<II", 12, 1) + b"abcd")
    with pytest.raises(MalformedContainer, match="size field 4000"):
        viewfinder_jpeg(struct.pack("<II", 4000, 1) + image)


def test_live_view_that_never_comes_is_a_timeout(monkeypatch: pytest.MonkeyPatch) -> None:
    never = lambda body, command, data: (ResponseCode.EosNotReady, (), None)  # noqa: E731
    monkeypatch.setitem(eos_usb._HANDLERS, Op.EosGetViewFinderData, never)
    sim = SimEosTransport(Images(), live_view=lambda: jpeg(1))
    with open_ptp_camera(ptp_config(), sim, EosTiming(settle_s=0, poll_interval_s=0.001, live_view_s=0.05)) as cam:
        with pytest.raises(DeviceTimeout, match="no live-view frame within 0.05 s"):
            cam.preview()


def test_the_simulated_eos_body_shows_the_bench_in_its_live_view(make_bench_profile) -> None:
    profile = make_bench_profile(camera={"driver": "ptp", "transport": "sim"})
    with open_camera(profile) as camera:
        dark = cv2.imdecode(np.frombuffer(camera.preview().data, np.uint8), cv2.IMREAD_COLOR)
    lit_bench(profile)
    with open_camera(profile) as camera:
        lit = cv2.imdecode(np.frombuffer(camera.preview().data, np.uint8), cv2.IMREAD_COLOR)
    assert lit.shape == dark.shape and lit.shape[1] == min(960, bench.LiveView(profile).active_shape[1])
    green = lit[:, :, 1].astype(float)  # OpenCV's BGR: green is in the middle either way
    assert green.max() > 50 > dark.max() + 30 and green.mean() > 3 * lit[:, :, 2].mean()
