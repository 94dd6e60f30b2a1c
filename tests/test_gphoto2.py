"""The gphoto2 driver against libgphoto2's own virtual camera: the `vusb` io library python-gphoto2's wheel ships
(IOLIBS points libgphoto2 at it, VCAMERADIR at the files the virtual PTP camera serves): autodetect, the
configuration, capture and download, and the one-line errors."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import msgspec
import numpy as np
import pytest

from benchctl.capture.raw import decode_raw
from benchctl.cli import main
from benchctl.devices.camera.gphoto2 import Gphoto2Camera, gphoto2, gphoto2_error
from benchctl.devices.errors import DeviceBusy, DeviceError, DeviceTimeout
from benchctl.dng import dng_bytes
from benchctl.errors import BenchctlError
from benchctl.profiles import CameraConfig

JPEG = bytes.fromhex("ffd8ffe000104a46494600010100000100010000ffd9")  # a minimal JPEG: what capture copies
DNG = dng_bytes(np.arange(24 * 32, dtype=np.uint16).reshape(24, 32), white_level=1023)

pytestmark = pytest.mark.third_party


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


def test_a_jpeg_is_refused_and_left_on_the_camera(virtual_camera: Path, tmp_path: Path) -> None:
    with Gphoto2Camera(config()) as camera:
        with pytest.raises(DeviceError) as caught:
            camera.capture(tmp_path / "frames")
        match = re.fullmatch(r"the camera delivered (GPH_\d{4}\.JPG), not a RAW file \(\.dng, \.nef, \.arw, \.cr2, "
                             r"\.\.\.: what LibRaw reads\); left on the camera as (/store_00010001/DCIM/\d{3}GPHOT)/"
                             r"GPH_\d{4}\.JPG: set the image quality to RAW on the camera", str(caught.value))
        assert match is not None, str(caught.value)
        assert camera.settings()["capturetarget"] == "Internal RAM"  # set by the capture: to the computer
        assert camera.download(match[2], match[1]) == JPEG  # still there
        assert camera.download("/store_00010001/DCIM/100BENCH", "IMG_0002.DNG") == DNG
    assert not list((tmp_path / "frames").iterdir())


class Announcing:
    """libgphoto2's camera object, whose capture announces the file `name` of the card's DCIM/100BENCH: the virtual
    camera takes its picture as ever (it serves a copy of a JPEG under a .JPG name, whatever the settings), and the
    file announced is the RAW a body set to RAW makes. Everything else goes to libgphoto2 as it is."""

    def __init__(self, camera: object, name: str) -> None:
        self._camera, self._name = camera, name

    def capture(self, kind: int, *context: object) -> object:
        self._camera.capture(kind, *context)  # type: ignore[attr-defined]
        return SimpleNamespace(folder="/store_00010001/DCIM/100BENCH", name=self._name)  # a CameraFilePath's fields

    def __getattr__(self, name: str) -> object:
        return getattr(self._camera, name)


# The virtual camera types a file by the extensions its name contains, and serves any other as "undefined" with no
# thumbnail, which libgphoto2 will not download (a real Nikon's NEF carries a JPEG thumbnail); so each RAW name here
# holds ".DNG" before its own suffix, which is the one the driver goes by.
@pytest.mark.parametrize("name", ["DSC_0001.DNG.NEF", "DSC00001.DNG.ARW", "DSCF0001.DNG.RAF", "P1010001.DNG.ORF",
                                  "P1000001.DNG.RW2", "IMGP0001.DNG.PEF", "IMG_0002.DNG"])
def test_every_raw_libraw_reads_is_saved_before_the_camera_copy_is_deleted(
        virtual_camera: Path, tmp_path: Path, name: str) -> None:
    """A Nikon, Sony, Fujifilm, Olympus, Panasonic or Pentax RAW was refused after it had been deleted from the camera:
    each is now saved under its own suffix, then deleted from the camera. Where the file cannot be saved (a frame of
    that name exists), the camera keeps it."""
    (virtual_camera / "DCIM" / "100BENCH" / name).write_bytes(DNG)
    suffix = name.rsplit(".", 1)[1].lower()
    folder = tmp_path / "frames"
    folder.mkdir()
    (folder / f"frame-000.{suffix}").write_bytes(b"an earlier frame")
    with Gphoto2Camera(config()) as camera:
        camera._camera = Announcing(camera._camera, name)
        with pytest.raises(BenchctlError, match=f"frame-000.{suffix}"):
            camera.capture(folder)
        assert camera.download("/store_00010001/DCIM/100BENCH", name) == DNG  # not saved: kept on the camera
        (frame,) = camera.capture(tmp_path / "saved")
        assert frame.path == tmp_path / "saved" / f"frame-000.{suffix}" and frame.path.read_bytes() == DNG
        assert (frame.format, frame.file_name) == (suffix, name)
        with pytest.raises(DeviceError, match=f"downloading {name}"):
            camera.download("/store_00010001/DCIM/100BENCH", name)  # saved: deleted from the camera
    assert decode_raw(frame.path).mosaic.shape == (24, 32)
    assert (folder / f"frame-000.{suffix}").read_bytes() == b"an earlier frame"


FULL_CARD = """
import json, sys
from benchctl.devices.camera.gphoto2 import Gphoto2Camera
from benchctl.devices.errors import DeviceError
from benchctl.profiles import CameraConfig
errors = []
with Gphoto2Camera(CameraConfig(driver="gphoto2")) as camera:
    for _ in range(40):
        try:
            camera.capture()
        except DeviceError as exc:
            if "not a RAW file" not in str(exc):
                errors.append(str(exc))
                break
print(json.dumps(errors))
"""


def test_a_full_card_says_the_card_is_full(virtual_camera: Path) -> None:
    """libgphoto2's virtual camera declares its store full after 26 pictures (its count lives in the process, hence the
    subprocess): libgphoto2 reports "Out of memory (-3)", and says in its context that the memory card ran full."""
    done = subprocess.run([sys.executable, "-c", FULL_CARD], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert json.loads(done.stdout) == ["the camera's card is full (libgphoto2: Camera memorycard ran full during "
                                       "capture.): free space on it (download and delete its files, or format it) "
                                       "and capture again"]


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
