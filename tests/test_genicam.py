"""The genicam camera driver against Aravis's in-process fake camera (Aravis's own GenICam feature tree and
image generator): formats, settings read back, DNGs that hold exactly the delivered values, CFA layouts, the
choice of camera, discovery and the command line; plus the pixel formats the fake camera does not deliver."""

from __future__ import annotations

import io
import math
import os
import subprocess
import sys
from pathlib import Path

import msgspec
import numpy as np
import pytest
import rawpy

from benchctl.capture.raw import decode_raw
from benchctl.cli import main
from benchctl.devices.camera import camera_for
from benchctl.devices.camera.aravis import aravis, genicam_cameras
from benchctl.devices.camera.genicam import GenicamCamera
from benchctl.devices.camera.pixel_formats import SUPPORTED, pixel_format
from benchctl.devices.errors import DeviceError
from benchctl.dng import dng_bytes
from benchctl.errors import BadValueError
from benchctl.profiles import CameraConfig, load_profile

WIDE = (0, 0, 256, 24)  # every ramp index (x + y + frame id) mod 255 appears in one frame (LibRaw: >= 22 rows)

pytestmark = pytest.mark.third_party


def config(**changes: object) -> CameraConfig:
    base = CameraConfig(driver="genicam", serial="1", region=(0, 0, 64, 48), image_timeout_s=5.0)
    return msgspec.structs.replace(base, **changes)  # type: ignore[arg-type]


REGION_CRASH = """
from benchctl.devices.camera.genicam import GenicamCamera
from benchctl.devices.errors import DeviceError
from benchctl.errors import BadValueError
from benchctl.profiles import CameraConfig

config = CameraConfig(driver="genicam", serial="1", region=(0, 0, 100000, 100000), image_timeout_s=5.0)
try:
    with GenicamCamera(config) as camera:
        camera.capture()
except (BadValueError, DeviceError) as exc:
    print(exc)
"""


def test_a_region_beyond_the_sensor_is_refused_before_it_is_written() -> None:
    """Aravis's fake camera takes a 100000 x 100000 region as written, and the process then died (SIGSEGV) in the
    buffer pop: in a subprocess, so that a crash fails this test instead of ending the suite."""
    done = subprocess.run([sys.executable, "-c", REGION_CRASH], capture_output=True, text=True, timeout=120,
                          env={**os.environ, "BENCHCTL_ARAVIS_INTERFACES": "Fake"})
    assert done.returncode == 0, (done.returncode, done.stderr[-2000:])
    assert done.stdout == ("Aravis Fake (serial 1): camera.region [0, 0, 100000, 100000] reaches column 100000 and "
                           "row 100000, beyond the camera's 2048 x 2048 (WidthMax x HeightMax): give a region inside "
                           "it\n")


@pytest.mark.parametrize("region, refused", [
    ((1024, 0, 1025, 64), "reaches column 2049 and row 64, beyond the camera's 2048 x 2048"),
    ((0, 2000, 64, 49), "reaches column 64 and row 2049, beyond the camera's 2048 x 2048"),
    ((0, 0, 2048, 2048), "2048 x 2048 = 4,194,304 pixels is above the limit of 1,000,000 (set $BENCHCTL_MAX_PIXELS"),
])
def test_a_region_outside_the_sensor_or_above_the_pixel_limit_is_one_line(
        region: tuple[int, int, int, int], refused: str, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("BENCHCTL_MAX_PIXELS", "1000000")
    with pytest.raises(BadValueError) as caught:
        GenicamCamera(config(region=region)).open()
    assert str(caught.value).startswith(f"Aravis Fake (serial 1): camera.region {list(region)}")
    assert refused in str(caught.value) and "\n" not in str(caught.value)


def fake_frame(fmt: str, region: tuple[int, int, int, int]) -> tuple[np.ndarray, int]:
    """One frame of the fake camera in `fmt` taken through Aravis directly (not the driver), and its frame id."""
    module = aravis()
    camera = module.Camera.new("Fake_1")
    camera.set_region(*region)
    camera.set_pixel_format_from_string(fmt)
    stream = camera.create_stream(None, None)
    stream.push_buffer(module.Buffer.new_allocate(camera.get_payload()))
    camera.start_acquisition()
    buffer = stream.timeout_pop_buffer(5_000_000)
    camera.stop_acquisition()
    assert buffer is not None and buffer.get_status() == module.BufferStatus.SUCCESS
    width, height = region[2], region[3]
    return np.frombuffer(buffer.get_image_data(), np.uint8).reshape(height, width, -1), buffer.get_frame_id()


def ramp_index(frame_id: int, height: int, width: int) -> np.ndarray:
    """The fake camera's diagonal ramp (at exposure 10 ms, gain 0): (x + y + frame id) mod 255."""
    y, x = np.mgrid[0:height, 0:width]
    return (x + y + frame_id) % 255


@pytest.mark.parametrize("fmt, expected", [
    ("Mono8", lambda step: step % 255),
    ("Mono16", lambda step: (256 * step) % 65535),
])
def test_mono_dng_holds_exactly_the_fake_cameras_ramp(fmt: str, expected: object) -> None:
    with GenicamCamera(config(pixel_format=fmt, exposure_s=0.01, gain=0.0)) as camera:
        frame = camera.capture()[0]
    y, x = np.mgrid[0:48, 0:64]
    with rawpy.imread(io.BytesIO(frame.data)) as raw:
        values, white, colours = raw.raw_image.copy(), raw.white_level, raw.num_colors
    assert np.array_equal(values, expected(x + y + frame.metadata["frame_id"]))  # type: ignore[operator]
    assert (white, colours) == (pixel_format(fmt).white_level, 1)


@pytest.mark.parametrize("fmt, layout", [("BayerRG8", "RGGB"), ("BayerGR8", "GRBG"), ("BayerGB8", "GBRG"),
                                         ("BayerBG8", "BGGR")])
def test_bayer_dng_layout_and_values(fmt: str, layout: str) -> None:
    """The DNG states the PFNC layout; decode_raw reads it; each site holds the fake camera's colour value there.

    Aravis 0.8.26's fake camera fills BayerRG8 with blue at (0, 0) and BayerBG8 with red there (checked against
    its own RGB8 frames: the two G-first layouts are filled as PFNC says, these two have red and blue swapped).
    benchctl follows PFNC, so for those two the sites hold the other colour; this test says so, and fails the day
    the fake camera changes."""
    rgb, rgb_id = fake_frame("RGB8", WIDE)
    jet = {int(i): rgb[y, x] for (y, x), i in np.ndenumerate(ramp_index(rgb_id, *rgb.shape[:2]))}
    with GenicamCamera(config(pixel_format=fmt, region=WIDE, exposure_s=0.01, gain=0.0)) as camera:
        frame = camera.capture()[0]
    decoded = decode_raw(frame.data)
    assert decoded.layout == layout and decoded.white_level == 255
    with rawpy.imread(io.BytesIO(frame.data)) as raw:
        values = raw.raw_image.copy()
    fake_layout = {"RGGB": "BGGR", "BGGR": "RGGB"}.get(layout, layout)
    index = ramp_index(frame.metadata["frame_id"], 24, 256)
    for (y, x), value in np.ndenumerate(values):
        colour = "RGB".index(fake_layout[2 * (y % 2) + x % 2])
        assert value == jet[int(index[y, x])][colour], (y, x)


def test_settings_are_written_and_read_back() -> None:
    with GenicamCamera(config(pixel_format="BayerGB8", exposure_s=0.0025, gain=3.0, region=(8, 4, 32, 24))) as cam:
        identity = cam.identity()
        frame = cam.capture()[0]
        device = cam._camera  # the Aravis camera: what it holds now, read independently of the driver
        assert (device.get_exposure_time(), device.get_gain(), device.get_pixel_format_as_string()) == \
            (2500.0, 3.0, "BayerGB8")
        assert (device.get_trigger_source(), device.get_string("TriggerMode")) == ("Software", "On")
    assert identity["manufacturer"] == "Aravis" and identity["model"] == "Fake" and identity["serial"] == "1"
    assert identity["pixel_format"] == "BayerGB8 (8 bit, GBRG)" and "Mono16" in identity["pixel_formats_offered"]
    assert identity["exposure_s"] == "0.0025" and identity["gain"] == "3" and identity["region"] == "[8, 4, 32, 24]"
    assert frame.metadata["exposure_s"] == 0.0025 and frame.metadata["gain"] == 3.0
    assert frame.metadata["incomplete_refused"] == []
    assert decode_raw(frame.data).mosaic.shape == (24, 32)


def test_frames_are_one_per_trigger_and_saved_as_they_come(tmp_path: Path) -> None:
    with GenicamCamera(config(pixel_format="Mono8")) as camera:
        frames = camera.capture(tmp_path, frames=3)
    ids = [frame.metadata["frame_id"] for frame in frames]
    assert len(set(ids)) == 3
    assert [frame.path.read_bytes() for frame in frames] == [frame.data for frame in frames]  # type: ignore[union-attr]


@pytest.mark.parametrize("changes, error, message", [
    ({"pixel_format": "BayerRG12"}, DeviceError, r"camera.pixel_format 'BayerRG12' is not offered \(offered: .*Mono16"),
    ({"pixel_format": "RGB8"}, DeviceError, r"pixel format 'RGB8' is not one benchctl keeps as RAW"),
    ({"exposure_s": 100.0}, BadValueError, r"exposure \(us\) 1e\+08 is outside the camera's 10 \.\. 1e\+07"),
    ({"gain": 11.0}, BadValueError, r"gain 11 is outside the camera's 0 \.\. 10"),
    ({"black_level": 4.0}, DeviceError, r"Aravis Fake \(serial 1\) has no BlackLevel feature"),
    ({"serial": "nope"}, DeviceError, r"^no GenICam camera match camera.serial = 'nope' \(found: Aravis Fake serial 1 "
                                      r"\(Fake_1\)\); `benchctl devices` lists them$"),
    ({"serial": None, "vendor": "Basler"}, DeviceError, r"no GenICam camera match camera.vendor = 'Basler'"),
    ({"serial": None, "user_id": "bench-left"}, DeviceError, r"no GenICam camera match camera.user_id"),
])
def test_refusals_are_one_line(changes: dict[str, object], error: type[Exception], message: str) -> None:
    camera = GenicamCamera(config(**changes))
    with pytest.raises(error, match=message) as caught:
        camera.open()
    assert "\n" not in str(caught.value) and not camera.is_open


def test_chosen_by_vendor_and_model_or_the_only_one() -> None:
    for changes in ({"serial": None, "vendor": "Aravis", "model": "Fake"}, {"serial": None}):
        with GenicamCamera(config(**changes)) as camera:
            assert camera.identity()["serial"] == "1"


@pytest.mark.parametrize("name", SUPPORTED)
def test_every_supported_format_round_trips_through_a_dng(name: str) -> None:
    """The formats the fake camera cannot deliver (10 / 12 / 16-bit Bayer, Mono10 / 12): little-endian words to
    a DNG with the format's CFA and white level, values unchanged."""
    fmt = pixel_format(name)
    rng = np.random.default_rng(3)
    values = rng.integers(0, fmt.white_level + 1, (24, 32), dtype=np.uint16)
    data = values.astype(np.uint8 if fmt.bits == 8 else "<u2").tobytes()
    frame = fmt.frame(data, 32, 24)
    with rawpy.imread(io.BytesIO(dng_bytes(frame, cfa=fmt.cfa, white_level=fmt.white_level))) as raw:
        assert np.array_equal(raw.raw_image, values) and raw.white_level == fmt.white_level
        assert raw.num_colors == (1 if fmt.cfa is None else 3)
    if fmt.cfa is not None:
        assert decode_raw(dng_bytes(frame, cfa=fmt.cfa, white_level=fmt.white_level)).layout == fmt.cfa


def test_pixel_format_refusals() -> None:
    with pytest.raises(DeviceError, match="BayerRG12p.*packed variants are not"):
        pixel_format("BayerRG12p")
    twelve = pixel_format("Mono12")
    with pytest.raises(DeviceError, match="holds the value 4096, above the 12-bit maximum 4095"):
        twelve.frame(np.array([1, 4096], "<u2").tobytes(), 2, 1)
    with pytest.raises(DeviceError, match="Mono12 frame of 2 x 2 holds 6 bytes, not 8: incomplete"):
        twelve.frame(bytes(6), 2, 2)
    assert twelve.frame(np.array([1, 4095], "<u2").tobytes(), 2, 1).tolist() == [[1, 4095]]
    assert math.isclose(pixel_format("BayerBG10").white_level, 1023)


def test_without_aravis_one_line_says_what_to_install(monkeypatch: pytest.MonkeyPatch) -> None:
    import gi

    def missing(namespace: str, version: str) -> None:
        raise ValueError(f"Namespace {namespace} not available")

    monkeypatch.setattr(gi, "require_version", missing)
    with pytest.raises(DeviceError, match=r"^GenICam cameras need Aravis 0.8 through PyGObject \(Namespace Aravis not "
                                          r"available\): sudo apt install gir1.2-aravis-0.8 .*benchctl\[genicam\]'$"):
        GenicamCamera(config()).open()


def test_discovery_and_the_command_line(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                        monkeypatch: pytest.MonkeyPatch) -> None:
    assert [(c.device_id, c.vendor, c.model, c.serial, c.protocol) for c in genicam_cameras()] == [
        ("Fake_1", "Aravis", "Fake", "1", "Fake")]
    assert main(["devices"]) == 0
    assert "GenICam cameras (Aravis):\n  Fake_1  Aravis Fake  serial 1  Fake" in capsys.readouterr().out
    profile = tmp_path / "genicam.toml"
    profile.write_text('[camera]\ndriver = "genicam"\nserial = "1"\npixel_format = "BayerGR8"\nexposure_s = 0.004\n'
                       'region = [0, 0, 64, 48]\n')
    assert isinstance(camera_for(load_profile(profile)), GenicamCamera)
    assert main(["profile", "check", str(profile)]) == 0
    assert "Camera        genicam: exposure 0.004 s, BayerGR8, gain as set on the camera, 1 frame(s) per capture" \
        in capsys.readouterr().out
    assert main(["camera", "info", "--profile", str(profile)]) == 0
    info = capsys.readouterr().out
    for line in ("driver: genicam", "model: Fake", "serial: 1", "pixel_format: BayerGR8 (8 bit, GRBG)",
                 "exposure_s: 0.004", "trigger: Software"):
        assert line in info, line
    assert main(["camera", "capture", "-o", str(tmp_path / "one.dng"), "--profile", str(profile)]) == 0
    assert decode_raw(tmp_path / "one.dng").layout == "GRBG"
    monkeypatch.setenv("BENCHCTL_ARAVIS_INTERFACES", "Firewire")
    assert main(["devices"]) == 0
    assert "cannot list: $BENCHCTL_ARAVIS_INTERFACES: unknown Aravis interface(s) Firewire" in capsys.readouterr().out


def test_iso_is_refused_in_a_genicam_profile(tmp_path: Path) -> None:
    profile = tmp_path / "iso.toml"
    profile.write_text('[camera]\ndriver = "genicam"\niso = 200\n')
    with pytest.raises(Exception, match=r"iso.toml: camera.iso: a GenICam camera has gain, not ISO"):
        load_profile(profile)


def test_the_benchmark_streams_and_counts_frames(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "genicam", "--size", "48x64", "--frames", "8", "--frame-rate", "200"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "fake camera 64 x 48 BayerRG8, 8 frames free running (camera frame rate 200 fps)"
    assert lines[1].startswith("  sustained into numpy: ") and lines[1].endswith(" fps, 0 dropped, 0 incomplete")
    assert "buffer -> numpy" in lines[2] and "numpy -> DNG bytes" in lines[2]
