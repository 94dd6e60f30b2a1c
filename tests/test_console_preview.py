"""Live view for the console: the simulator's binned preview against its own full capture, the Camera preview hook
(simulated camera, default capture), and the EOS live view over PTP (GetViewFinderData) against the simulated
body, byte for byte."""

from __future__ import annotations

import struct
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from benchctl.calibration.calibrated import Calibrated
from benchctl.capture.raw import decode_raw
from benchctl.console import preview
from benchctl.devices.camera import open_camera
from benchctl.devices.camera.base import PreviewFrame
from benchctl.devices.camera.ptp.container import MalformedContainer, OperationCode, ResponseCode
from benchctl.devices.camera.ptp.eos import EVF_OUTPUT_PC, EosProperty, pack_viewfinder, viewfinder_jpeg
from benchctl.devices.camera.ptp_camera import EosTiming, open_ptp_camera
from benchctl.devices.errors import DeviceTimeout
from benchctl.devices.laser import open_laser
from benchctl.devices.sim import eos_usb, physics
from benchctl.devices.sim.eos_usb import SimEosTransport
from benchctl.devices.sim.slm import read_displayed
from benchctl.devices.sim.state import CAMERA_STATE, load_state
from benchctl.devices.slm import open_slm, slm_for
from benchctl.optics.setup import OpticalSetup
from benchctl.profiles import CameraConfig, Profile, load_profile

FAST = EosTiming(settle_s=0.0, release_events_s=0.05, poll_interval_s=0.001, busy_retry_s=0.05)
Op = OperationCode


def lit_bench(profile: Profile, channel: str = "green", power: str = "2mW") -> None:
    """Leave `channel` emitting at `power` (the simulated devices keep their state), a flat phase shown unless the
    SLM shows something already."""
    if read_displayed()[0] is None:
        show(profile, np.zeros(profile.slm.shape), channel)
    laser = open_laser(profile, leave_on=True)
    with laser:
        laser.set_power(channel, power)
        laser.set_emission(channel, True)


def show(profile: Profile, phase: np.ndarray, channel: str = "green") -> None:
    with open_slm(profile) as slm:
        slm.sleep = lambda s: None
        slm.show_phase(phase, channel)


SCENES = {"flat": lambda shape: np.zeros(shape),
          "speckle": lambda shape: np.random.default_rng(1).uniform(0, 2 * np.pi, shape),  # light at every frequency
          "grating": lambda shape: np.tile(np.arange(shape[1]) * (2 * np.pi / 6), (shape[0], 1))}
POWERS = {"flat": "2mW", "speckle": "20mW", "grating": "10mW"}  # bright, nowhere saturated


@pytest.mark.parametrize("scene", SCENES)
def test_binned_live_view_has_the_full_captures_signal(bench_profile_path: Path, scene: str) -> None:
    profile = load_profile(bench_profile_path)
    show(profile, SCENES[scene](profile.slm.shape))
    lit_bench(profile, power=POWERS[scene])
    captures = [decode_raw(physics.render_capture(profile).data) for _ in range(2)]
    view = physics.LiveView(profile)
    frames = [view.dng(100) for _ in range(2)]
    rows, cols = view.active_shape
    metadata = frames[0][1]
    assert metadata["window"] == [0, 0, rows, cols] and metadata["bin"] == pytest.approx(cols / 100, rel=0.02)
    assert metadata["bin"] / physics.sensor_pixels_per_slm_pixel(profile) > 2  # 2 x 2 target pixels per frame pixel
    frame = [decode_raw(data) for data, _ in frames]
    assert frame[0].mosaic.shape == (round(rows / metadata["bin"]) & ~1, 100)
    assert frame[0].layout == captures[0].layout
    # the same light on average (the preview bins, the capture does not), and the light where the capture has it
    capture = np.mean([c.mosaic for c in captures], axis=0)
    assert np.mean([f.mosaic.mean() for f in frame]) == pytest.approx(capture.mean(), rel=0.02)
    assert capture.mean() > 20 * np.abs(capture[:6]).mean() and not any(c.saturated.any() for c in captures)
    green = np.mean([f.planes()[1] for f in frame], axis=0)
    binned = np.mean([cv2.resize(c.planes()[1], green.shape[::-1], interpolation=cv2.INTER_AREA) for c in captures],
                     axis=0)
    assert np.corrcoef(binned.ravel(), green.ravel())[0, 1] > 0.93


@pytest.mark.parametrize("sim", [
    {},
    {"beam": {"waist_mm": 0.6, "offset_mm": [0.1, -0.2], "tilt_mrad": [0.5, -1.0]},
     "aberration": {"green": {"defocus": 0.3, "coma_vertical": -0.2}}, "imaging": {"stray_light": 0.01}},
    {"slm": {"crosstalk_px": 0.8}},
])
@pytest.mark.parametrize("iris", [0.5, None])
def test_the_live_views_light_is_the_captures(make_bench_profile, sim: dict, iris: float | None) -> None:
    """The live view computes the light its own, faster way (table lookup, pruned FFTs): the same numbers."""
    profile = make_bench_profile(sim=sim, optics={"iris_fraction": iris})
    gray = np.random.default_rng(2).integers(0, 256, profile.slm.shape).astype(np.uint8)
    for channel in profile.channels:
        capture = physics._target_irradiance(profile, channel, gray)
        live = physics._live_irradiance(profile, channel, gray)
        assert live.dtype == torch.float32 and live.shape == capture.shape
        assert torch.allclose(live.double(), capture, rtol=0, atol=2e-6 * float(capture.max()))
    propagator = physics._pruned_propagator(OpticalSetup.of(profile.geometry("green")))
    ph, pw = propagator.padded_shape
    band = (propagator.low_y + propagator.high_y) * (propagator.low_x + propagator.high_x)
    assert band < 0.3 * ph * pw if iris else band > 0.6 * ph * pw  # what the iris lets through, and skips


def test_a_bin_with_one_saturated_pixel_is_marked(bench_profile_path: Path) -> None:
    """Speckle bright enough that its brightest grains saturate sensor pixels while their bins' means do not: the
    binned frame marks exactly the bins that hold a saturated sensor pixel; the console shows them."""
    profile = load_profile(bench_profile_path)
    show(profile, SCENES["speckle"](profile.slm.shape))
    lit_bench(profile, power="20mW")
    sensor = profile.sim.sensor
    full = (sensor.white_level - sensor.black_level) / physics.dn_per_electron(sensor, sensor.iso)
    gray, powers = read_displayed()[0], physics.emitting_channels(profile)
    brightest = physics._mean_electrons(profile, gray, powers, sensor.exposure_s)[1].max()
    exposure_s = 1.5 * sensor.exposure_s * full / brightest  # the brightest sensor pixels at 1.5 x the white level
    (top, bottom, left, right), mean = physics._mean_electrons(profile, gray, powers, exposure_s)
    data, metadata = physics.LiveView(profile).dng(100, exposure_s=exposure_s)
    frame = decode_raw(data)

    def bins_with(hot: np.ndarray) -> np.ndarray:
        """The frame pixels whose bins hold a sensor pixel of `hot` (in the lit box)."""
        rows, cols = (np.floor((np.arange(a, b) + 0.5) / metadata["bin"]).astype(int) for a, b in
                      ((top, bottom), (left, right)))
        y, x = np.nonzero(hot)
        keep = (rows[y] < frame.mosaic.shape[0]) & (cols[x] < frame.mosaic.shape[1])
        marked = np.zeros(frame.mosaic.shape, bool)
        marked[rows[y[keep]], cols[x[keep]]] = True
        return marked

    surely, maybe = bins_with(mean >= 1.001 * full), bins_with(mean >= 0.999 * full)  # interpolation's rounding
    marks = metadata["saturated_bins"]
    assert marks.shape == frame.mosaic.shape and surely.sum() >= 5
    assert (surely & ~frame.saturated).sum() >= 3  # bins whose mean stays below the white level: only marks say it
    assert not (surely & ~marks).any() and not (marks & ~maybe).any()  # exactly the bins with a saturated pixel
    shown = preview.decode(PreviewFrame(data, "dng", metadata=metadata))
    assert not (surely & ~shown.saturated).any()


def test_a_bins_noise_has_the_shot_and_read_noise_of_its_electrons() -> None:
    rng = np.random.default_rng(3)
    for expected, read_variance in ((3.0, 0.0), (40.0, 64.0), (2000.0, 64.0), (2000.0, 0.0)):
        counts = physics._binned_electrons(rng, np.full(200_000, expected, np.float32), read_variance)
        assert counts.dtype == np.float32
        assert counts.mean() == pytest.approx(expected, rel=0.01)
        assert counts.var() == pytest.approx(expected + read_variance, rel=0.02)
    few = physics._binned_electrons(rng, np.full(1000, 3.0, np.float32), 0.0)
    assert np.array_equal(few, np.round(few)) and few.min() >= 0  # Poisson's whole electrons where they are few


def test_a_native_window_is_the_sensor_at_one_to_one(bench_profile_path: Path) -> None:
    profile = load_profile(bench_profile_path)
    lit_bench(profile)
    capture = decode_raw(physics.render_capture(profile).data)
    data, metadata = physics.LiveView(profile).dng(64, (101, 151, 64, 64))  # corner moved onto a CFA cell
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
    original = physics._electron_planes
    monkeypatch.setattr(physics, "_electron_planes", lambda *a: calls.append(a[2]) or original(*a))
    view = physics.LiveView(profile, progressive=False)
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


def test_a_change_is_shown_at_once_in_coarse_light_then_refined(bench_profile_path: Path,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    """Progressive preview: the first frame after an SLM or laser change shows the light computed on a grid twice
    as coarse (a quarter of the work), the next one the full light, and later ones reuse it."""
    profile = load_profile(bench_profile_path)
    lit_bench(profile)
    coarse_calls = []
    original = physics._live_irradiance
    monkeypatch.setattr(physics, "_live_irradiance", lambda *a, coarse=1: coarse_calls.append(coarse)
                        or original(*a, coarse=coarse))
    view = physics.LiveView(profile)
    assert view.render(64)[1]["coarse"] is False  # the first light of all: no frame to show meanwhile
    show(profile, SCENES["grating"](profile.slm.shape))
    frames = [view.render(64)[1] for _ in range(3)]
    shown = read_displayed()[1]["frame"]
    assert [(m["slm_frame"], m["coarse"]) for m in frames] == [(shown, True), (shown, False), (shown, False)]
    assert coarse_calls == [1, 2, 1] and frames[2]["light_s"] < frames[1]["light_s"]
    steady = physics.LiveView(profile, progressive=False)
    steady.render(64)
    assert np.array_equal(view._planes, steady._planes)  # refined: exactly the light without progression


@pytest.mark.parametrize("scene", ["flat", "grating", "dpac"])
def test_the_coarse_light_is_the_light_at_a_previews_resolution(bench_profile_path: Path, scene: str) -> None:
    """The coarse light against the full light, both averaged over 4 x 4 target pixels (a preview frame pixel spans
    more): the same power and the same picture for what the iris passes (flat, a 6-pixel grating, a DPAC hologram).
    A field with light at every frequency (uniform random phase) is the worst case: its coarse frame's power is
    about 1.3 times the full one's, correlation 0.81 (docs/console.md)."""
    from benchctl.holograms.cache import hologram
    from benchctl.targets import load_target, prepare_target

    profile = load_profile(bench_profile_path)
    channel = profile.channel("green")
    if scene == "dpac":
        target = prepare_target(load_target("chart:bars", profile.optics.roi), profile.slm.shape, profile.optics.roi)
        gray = hologram(Calibrated(profile), target, "green", "dpac", iterations=None, seed=0, checkpoint=None).gray
    else:
        gray = slm_for(profile).encode(SCENES[scene](profile.slm.shape), "green")
    full = physics._live_irradiance(profile, channel, gray).numpy()
    coarse = physics._live_irradiance(profile, channel, gray, coarse=2).numpy()
    assert coarse.shape == full.shape and coarse.sum() == pytest.approx(full.sum(), rel=0.06)
    rows, cols = (n // 4 for n in full.shape)
    binned = [cv2.resize(light, (cols, rows), interpolation=cv2.INTER_AREA) for light in (full, coarse)]
    assert np.corrcoef(binned[0].ravel(), binned[1].ravel())[0, 1] > 0.96


def test_the_simulated_camera_previews_without_taking_a_capture_number(bench_profile_path: Path) -> None:
    profile = load_profile(bench_profile_path)
    lit_bench(profile)
    with open_camera(profile) as camera:
        assert camera.windowed_preview
        frame = camera.preview(width=100)
        zoom = camera.preview(32, (40, 60, 32, 32))
        captured = camera.capture()[0]
    assert frame.format == "dng" and frame.full_shape == physics.LiveView(profile).active_shape
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
    assert lit.shape == dark.shape and lit.shape[1] == min(960, physics.LiveView(profile).active_shape[1])
    green = lit[:, :, 1].astype(float)  # OpenCV's BGR: green is in the middle either way
    assert green.max() > 50 > dark.max() + 30 and green.mean() > 3 * lit[:, :, 2].mean()
