"""The gphoto2 driver against a fake gphoto2 executable (a script that writes a file as the real one does),
and without one."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import msgspec
import pytest

from benchctl.devices.camera.gphoto2 import Gphoto2Camera, gphoto2_error
from benchctl.devices.camera.hints import UDEV_RULE
from benchctl.devices.errors import DeviceBusy, DeviceError, DeviceTimeout
from benchctl.profiles import CameraConfig

RAW = bytes(range(256)) * 40

FAKE_GPHOTO2 = f"""#!{sys.executable}
import os, sys, time
args = sys.argv[1:]
with open(os.environ["FAKE_GPHOTO2_LOG"], "a") as log:
    log.write(" ".join(args) + "\\n")
mode = os.environ.get("FAKE_GPHOTO2_MODE", "ok")
if args == ["--summary"]:
    print("Camera summary:\\nManufacturer: Canon Inc.\\nModel: Canon EOS M10\\n  Version: 3-1.1.0\\n"
          "  Serial Number: 5a1c0ffee\\nVendor Extension ID: 0xb (1.0)")
    sys.exit(0)
if mode == "slow":
    time.sleep(10)
if mode == "error":
    sys.stderr.write(os.environ["FAKE_GPHOTO2_STDERR"])
    sys.exit(int(os.environ.get("FAKE_GPHOTO2_STATUS", "1")))
pattern = args[args.index("--filename") + 1]
for name, suffix in [("IMG_0042", "CR2")] if mode == "ok" else [("IMG_0042", "JPG")]:
    path = pattern.replace("%f", name).replace("%C", suffix.lower())
    with open(path, "wb") as out:
        out.write(bytes(range(256)) * 40)
    print("New file is in location /capt0000.cr2 on the camera")
    print("Saving file as " + path)
"""

NO_FOCUS = """
*** Error ***
Canon EOS Capture failed to release: Perhaps no focus?
ERROR: Could not capture image.
ERROR: Could not capture.
"""
BUSY = """
*** Error ***
Canon EOS M Full-Press failed (0x2019: PTP Device Busy)
ERROR: Could not capture image.
ERROR: Could not capture.
*** Error (-110: 'I/O in progress') ***
"""
CLAIMED = """
*** Error ***
An error occurred in the io-library ('Could not claim the USB device'): Could not claim interface 0 (Device or
resource busy). Make sure no other program (gvfs-gphoto2-volume-monitor) or kernel module (such as sdc2xx, stv680,
spca50x) is using the device and you have read/write access to the device.
*** Error (-53: 'Could not claim the USB device') ***
"""
NO_CAMERA = "\n*** Error: No camera found. ***\n\n"
DENIED = "\n*** Error ***\nCould not open USB device (Permission denied)\n"
TIMEOUT = "\n*** Error (-10: 'Timeout reading from or writing to the port') ***\n"
OTHER = "\n*** Error ***\nSomething unexpected happened\n*** Error (-1: 'Unspecified error') ***\n"


@pytest.fixture
def fake_gphoto2(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A fake gphoto2 on PATH; returns its log of argument lines."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    script = bin_dir / "gphoto2"
    script.write_text(FAKE_GPHOTO2)
    script.chmod(0o755)
    log = tmp_path / "gphoto2.log"
    monkeypatch.setenv("PATH", f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '')}")
    monkeypatch.setenv("FAKE_GPHOTO2_LOG", str(log))
    return log


def config(**changes: object) -> CameraConfig:
    return msgspec.structs.replace(CameraConfig(driver="gphoto2"), **changes)  # type: ignore[arg-type]


def test_capture_downloads_the_raw_file(fake_gphoto2: Path, tmp_path: Path) -> None:
    with Gphoto2Camera(config()) as cam:
        assert cam.identity() == {"driver": "gphoto2", "manufacturer": "Canon Inc.", "model": "Canon EOS M10",
                                  "firmware": "3-1.1.0", "serial": "5a1c0ffee"}
        frame = cam.capture(tmp_path / "out")[0]
    assert frame.data == RAW and frame.format == "cr2" and frame.file_name == "IMG_0042.cr2"
    assert frame.path == tmp_path / "out" / "frame-000.cr2" and frame.path.read_bytes() == RAW
    calls = fake_gphoto2.read_text().splitlines()
    assert calls[0] == "--summary"
    assert calls[1].startswith("--set-config capturetarget=0 --capture-image-and-download --filename ")
    assert calls[1].endswith("/%f.%C")
    temp_folder = Path(calls[1].split("--filename ")[1]).parent
    assert not temp_folder.exists()  # removed after reading the file back


def test_explicit_gphoto2_path(fake_gphoto2: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("PATH", "")
    with Gphoto2Camera(config(gphoto2_path=str(tmp_path / "bin" / "gphoto2"))) as cam:
        assert cam.capture()[0].data == RAW


def test_gphoto2_not_installed(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("PATH", str(tmp_path))
    with pytest.raises(DeviceError, match=r"gphoto2 not found \(camera.gphoto2_path = 'gphoto2'\): install it "
                                          r"\(sudo apt install gphoto2\).*driver 'ptp'"):
        Gphoto2Camera(config()).open()
    with pytest.raises(DeviceError, match="gphoto2 not found"):
        Gphoto2Camera(config(gphoto2_path=str(tmp_path / "nowhere" / "gphoto2"))).open()


def test_no_raw_file(fake_gphoto2: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("FAKE_GPHOTO2_MODE", "jpeg")
    with Gphoto2Camera(config()) as cam:
        with pytest.raises(DeviceError, match="downloaded IMG_0042.jpg but no RAW file.*set the image quality to RAW"):
            cam.capture()


@pytest.mark.parametrize("stderr, status, error, message", [
    (NO_FOCUS, 1, DeviceError, "could not focus .*manual focus"),
    (BUSY, 1, DeviceBusy, r"camera busy \(PTP DeviceBusy\)"),
    (BUSY, 0, DeviceBusy, "camera busy"),  # gphoto2 sometimes exits 0 after an error
    (CLAIMED, 1, DeviceBusy, "could not claim the camera's USB interface: .*gvfs-gphoto2-volume-monitor"),
    (NO_CAMERA, 1, DeviceError, r"gphoto2 found no camera: is it on, .*PTP mode"),
    (DENIED, 1, DeviceError, f"no permission to use the camera: install {UDEV_RULE}"),
    (TIMEOUT, 1, DeviceTimeout, "stopped answering gphoto2"),
    (OTHER, 1, DeviceError, r"^gphoto2 failed \(exit status 1\): Something unexpected happened$"),
])
def test_gphoto2_errors(fake_gphoto2: Path, monkeypatch: pytest.MonkeyPatch, stderr: str, status: int,
                        error: type[DeviceError], message: str) -> None:
    with Gphoto2Camera(config()) as cam:
        monkeypatch.setenv("FAKE_GPHOTO2_MODE", "error")
        monkeypatch.setenv("FAKE_GPHOTO2_STDERR", stderr)
        monkeypatch.setenv("FAKE_GPHOTO2_STATUS", str(status))
        with pytest.raises(error, match=message) as caught:
            cam.capture()
    assert "\n" not in str(caught.value)


def test_gphoto2_error_without_text() -> None:
    assert str(gphoto2_error("", 2)) == "gphoto2 failed (exit status 2): no message"


def test_gphoto2_that_hangs(fake_gphoto2: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    with Gphoto2Camera(config()) as cam:  # opening runs gphoto2 too: a loaded machine may take over 0.3 s
        cam.config = config(image_timeout_s=0.3)
        monkeypatch.setenv("FAKE_GPHOTO2_MODE", "slow")
        with pytest.raises(DeviceTimeout, match=r"did not finish within 0.3 s \(camera.image_timeout_s\)"):
            cam.capture()
