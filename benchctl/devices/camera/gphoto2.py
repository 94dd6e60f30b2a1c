"""The `gphoto2` camera driver: captures through the gphoto2 command-line tool, the widely installed fallback.

One capture is one gphoto2 run: `--set-config capturetarget=0 --capture-image-and-download --filename F`
into a fresh temporary folder (capturetarget 0: the image goes to the computer, not the card); the RAW file it
wrote is read back and the folder removed. gphoto2 reports failures as text, sometimes with exit status 0, so
its output is searched for the errors it prints and each becomes the same one-line error the ptp driver gives.
Exposure and ISO are not written (Camera's default): set them on the body.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import tempfile
from datetime import datetime, timezone
from pathlib import Path

from benchctl.devices.camera.base import RAW_FORMATS, Camera, RawFrame
from benchctl.devices.camera.hints import (
    BUSY_HINT,
    NO_FOCUS_HINT,
    NOT_FOUND_HINT,
    PERMISSION_HINT,
    RAW_HINT,
    USB_GRABBED_HINT,
)
from benchctl.devices.errors import DeviceBusy, DeviceError, DeviceTimeout
from benchctl.profiles import CameraConfig

FILENAME_PATTERN = "%f.%C"  # the camera's own file name and suffix, e.g. IMG_0042.CR2
_SUMMARY_KEYS = {"manufacturer": "Manufacturer", "model": "Model", "firmware": "Version", "serial": "Serial Number"}
_ERROR_MARKERS = ("*** Error", "ERROR:")
# (texts gphoto2 prints, error class, message): the first entry with a text in the output wins
_KNOWN_ERRORS: list[tuple[tuple[str, ...], type[DeviceError], str]] = [
    (("Perhaps no focus",), DeviceError, NO_FOCUS_HINT),
    (("Permission denied", "Access denied"), DeviceError, f"no permission to use the camera: {PERMISSION_HINT}"),
    (("Could not claim the USB device", "Could not claim interface"), DeviceBusy,
     f"gphoto2 could not claim the camera's USB interface: {USB_GRABBED_HINT}"),
    (("PTP Device Busy", "0x2019", "I/O in progress"), DeviceBusy, f"camera busy (PTP DeviceBusy): {BUSY_HINT}"),
    (("No camera found", "Could not detect any camera"), DeviceError, f"gphoto2 found no camera: {NOT_FOUND_HINT}"),
    (("Timeout reading from or writing to the port", "PTP Timeout"), DeviceTimeout,
     "the camera stopped answering gphoto2: power-cycle it and reconnect"),
]


def gphoto2_error(output: str, returncode: int) -> DeviceError:
    """The DeviceError for a failed gphoto2 run, from what it printed."""
    for texts, cls, message in _KNOWN_ERRORS:
        if any(text in output for text in texts):
            return cls(message)
    lines = [line.strip().strip("*").strip() for line in output.splitlines()]
    detail = next((line for line in lines if line and line != "Error"), "no message")
    return DeviceError(f"gphoto2 failed (exit status {returncode}): {detail}")


class Gphoto2Camera(Camera):
    """A camera driven through the gphoto2 executable (camera.gphoto2_path)."""

    driver = "gphoto2"

    def __init__(self, config: CameraConfig) -> None:
        super().__init__(config)
        self._executable = ""
        self._summary: dict[str, str] = {}

    def _open(self) -> None:
        found = shutil.which(self.config.gphoto2_path)
        if found is None:
            raise DeviceError(f"gphoto2 not found (camera.gphoto2_path = {self.config.gphoto2_path!r}): install it "
                              f"(sudo apt install gphoto2), set camera.gphoto2_path to its full path, or use camera "
                              f"driver 'ptp'")
        self._executable = found
        summary = self._run("--summary")
        self._summary = {key: match.group(1).strip() for key, label in _SUMMARY_KEYS.items()
                         if (match := re.search(rf"^\s*{label}:\s*(.+)$", summary, re.MULTILINE))}

    def _close(self) -> None:
        """Nothing held: each gphoto2 run connects and disconnects by itself."""

    def _identity(self) -> dict[str, str]:
        return dict(self._summary)

    def _run(self, *args: str) -> str:
        """Run gphoto2 with `args`; its standard output, or the DeviceError its output describes."""
        try:
            done = subprocess.run([self._executable, *args], capture_output=True, text=True,
                                  timeout=self.config.image_timeout_s)
        except subprocess.TimeoutExpired:
            raise DeviceTimeout(f"gphoto2 {args[0]} did not finish within {self.config.image_timeout_s:g} s "
                                f"(camera.image_timeout_s): is the camera on and awake?") from None
        except OSError as exc:
            raise DeviceError(f"cannot run gphoto2 ({self._executable}): {exc.strerror or exc}") from None
        output = done.stdout + done.stderr
        if done.returncode != 0 or any(marker in output for marker in _ERROR_MARKERS):
            raise gphoto2_error(output, done.returncode)
        return done.stdout

    def _capture_one(self) -> RawFrame:
        with tempfile.TemporaryDirectory(prefix="benchctl-gphoto2-") as folder:
            self._run("--set-config", "capturetarget=0", "--capture-image-and-download",
                      "--filename", str(Path(folder) / FILENAME_PATTERN))
            written = sorted(Path(folder).iterdir())
            raws = [path for path in written if path.suffix.lower().lstrip(".") in RAW_FORMATS]
            if not raws:
                names = ", ".join(path.name for path in written) or "nothing"
                raise DeviceError(f"gphoto2 downloaded {names} but no RAW file (.dng, .cr2, .cr3): {RAW_HINT}")
            data = raws[0].read_bytes()
        metadata = {"captured_at": datetime.now(timezone.utc).isoformat(timespec="milliseconds"),
                    "camera": self._summary.get("model", ""), "serial": self._summary.get("serial", "")}
        return RawFrame(data, raws[0].suffix.lower().lstrip("."), raws[0].name, metadata)
