"""The gphoto2 driver against libgphoto2's own virtual camera: the `vusb` io library python-gphoto2's wheel ships
(IOLIBS points libgphoto2 at it, VCAMERADIR at the files the virtual PTP camera serves): autodetect, the
configuration, capture and download, and the one-line errors."""

from __future__ import annotations

import re
from pathlib import Path

import msgspec
import numpy as np
import pytest

from benchctl.cli import main
from benchctl.devices.camera.gphoto2 import Gphoto2Camera, gphoto2, gphoto2_error
from benchctl.devices.errors import DeviceBusy, DeviceError, DeviceTimeout
from benchctl.dng import dng_bytes
from benchctl.profiles import CameraConfig

JPEG = bytes.fromhex("ffd8ffe000104a46494600010100000100010000ffd9")  # a minimal JPEG: what capture copies
DNG = dng_bytes(np.arange(24 * 32, dtype=np.uint16).reshape(24, 32), white_level=1023)


@pytest.fixture
def virtual_camera(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """libgphoto2's virtual camera serving a folder with a JPEG (capture returns a copy of the first JPEG it finds)
    and a DNG on its card."""
    store = tmp_path / "vcamera"
    (store / "DCIM" / "100BENCH").mkdir(parents=True)
    (store / "DCIM" / "100BENCH" / "IMG_0001.JPG").write_bytes(JPEG)
    (store / "DCIM" / "100BENCH" / "IMG_0002.DNG").write_bytes(DNG)
    monkeypatch.setenv("IOLIBS", str(Path(gphoto2().__file__).parent / "libgphoto2" / "vusb"))
    monkeypatch.setenv("VCAMERADIR", str(store))
    return store


def config(**changes: object) -> CameraConfig:
    return msgspec.structs.replace(CameraConfig(driver="gphoto2"), **changes)  # type: ignore[arg-type]


def test_autodetect_and_identity(virtual_camera: Path) -> None:
    with Gphoto2Camera(config()) as camera:
        identity = camera.identity()
    assert identity["driver"] == "gphoto2" and identity["detected_as"] == "Nikon DSC D750"
    assert identity["port"].startswith("usb:")
    assert (identity["manufacturer"], identity["model"]) == ("GP", "VC")  # what the virtual camera's PTP answers say


def test_configuration_read(virtual_camera: Path) -> None:
    with Gphoto2Camera(config(model="Nikon DSC D750")) as camera:
        settings = camera.settings()
    assert settings["capturetarget"] in ("Internal RAM", "Memory card")
    assert {"serialnumber", "manufacturer", "shutterspeed", "f-number"} <= set(settings)


def test_capture_downloads_what_the_camera_announced_and_refuses_a_jpeg(virtual_camera: Path) -> None:
    with Gphoto2Camera(config()) as camera:
        with pytest.raises(DeviceError, match=r"^the camera delivered GPH_\d{4}\.JPG \(22 bytes\), not a RAW file "
                                              r"\(\.dng, \.cr2, \.cr3\): set the image quality to RAW on the camera$"):
            camera.capture()
        assert camera.settings()["capturetarget"] == "Internal RAM"  # set by the capture: to the computer
        assert camera.download("/store_00010001/DCIM/100BENCH", "IMG_0002.DNG") == DNG
        assert camera.download("/store_00010001/DCIM/100BENCH", "IMG_0001.JPG") == JPEG


def test_camera_info_on_the_command_line(virtual_camera: Path, tmp_path: Path,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    profile = tmp_path / "gphoto2.toml"
    profile.write_text('[camera]\ndriver = "gphoto2"\nmodel = "Nikon DSC D750"\n')
    assert main(["camera", "info", "--profile", str(profile)]) == 0
    out = capsys.readouterr().out
    assert "driver: gphoto2\n" in out and "detected_as: Nikon DSC D750\n" in out and "model: VC\n" in out


def test_no_camera_or_another_model_is_one_line(virtual_camera: Path, tmp_path: Path,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(DeviceError, match=r"^libgphoto2 found no camera\(s\) for camera.model = 'Canon EOS M10' "
                                          r"\(found: Nikon DSC D750 on usb:\d+,\d+\): set camera.model"):
        Gphoto2Camera(config(model="Canon EOS M10")).open()
    monkeypatch.setenv("IOLIBS", str(tmp_path))  # no io library at all
    with pytest.raises(DeviceError, match=r"^libgphoto2 failed during autodetect: Error loading a library \(-4\)$"):
        Gphoto2Camera(config()).open()


def test_libgphoto2_results_become_one_line_errors() -> None:
    gp = gphoto2()
    cases = [(gp.GP_ERROR_CAMERA_BUSY, DeviceBusy, "camera busy during capture: it may still be saving"),
             (gp.GP_ERROR_IO_USB_CLAIM, DeviceBusy, "could not claim the camera's USB interface"),
             (gp.GP_ERROR_TIMEOUT, DeviceTimeout, "stopped answering during capture"),
             (gp.GP_ERROR_MODEL_NOT_FOUND, DeviceError, "libgphoto2 found no camera: is it on"),
             (gp.GP_ERROR_NOT_SUPPORTED, DeviceError, r"libgphoto2 failed during capture: Unsupported operation "
                                                      r"\(-6\)")]
    for code, cls, message in cases:
        error = gphoto2_error(code, "capture")
        assert type(error) is cls, (code, error)
        assert re.search(message, str(error)), (code, error)
        assert "\n" not in str(error)
