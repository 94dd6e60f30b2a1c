"""The `gphoto2` camera driver: any camera libgphoto2 drives, through its maintained Python binding (python-gphoto2,
whose wheel bundles libgphoto2, so no system package is needed).

Open: autodetect, take the camera the profile's `model` names (else the only one found), connect. Capture: set
the capture target to the camera's RAM where it has that setting (the image goes to the computer, not the card),
release, and download the file the camera announces, which must be a RAW file LibRaw reads (by its suffix:
RAW_FORMATS, NEF, ARW, RAF, ORF, RW2, PEF ... included); the camera's copy is deleted only once the file is saved
(`_saved`), and a file that is not RAW (a JPEG) is left on the camera. libgphoto2's errors arrive as numbered
results, each turned into the same one-line error the ptp driver gives, with what libgphoto2 said about it (a card
that ran full says so). Exposure and ISO are not written (Camera's default): set them on the body.
"""

from __future__ import annotations

from collections.abc import Sequence
from datetime import datetime, timezone
from pathlib import PurePath
from types import ModuleType
from typing import Any

from benchctl.devices.camera.base import RAW_FORMATS, Camera, RawFrame
from benchctl.devices.camera.hints import BUSY_HINT, NOT_FOUND_HINT, PERMISSION_HINT, RAW_HINT, USB_GRABBED_HINT
from benchctl.devices.errors import DeviceBusy, DeviceError, DeviceTimeout
from benchctl.profiles import CameraConfig

INSTALL_HINT = "pip install 'benchctl[gphoto2]'"
_IDENTITY = {"manufacturer": "manufacturer", "model": "cameramodel", "serial": "serialnumber",
             "firmware": "deviceversion"}
_TO_RAM = ("Internal RAM", "RAM", "sdram")  # capture target names meaning "to the computer", by libgphoto2 driver


def gphoto2() -> ModuleType:
    """python-gphoto2; DeviceError saying what to install when it is missing."""
    try:
        import gphoto2 as module
    except ImportError:
        raise DeviceError(f"the gphoto2 camera driver needs python-gphoto2: {INSTALL_HINT}") from None
    return module


def gphoto2_error(code: int, doing: str, said: Sequence[str] = ()) -> DeviceError:
    """The DeviceError for libgphoto2's result `code` while `doing` (e.g. 'capture'); `said`: the error messages
    libgphoto2 gave its context meanwhile (they tell a full card from a lack of memory here)."""
    gp = gphoto2()
    told = f" (libgphoto2: {' '.join(said)})" if said else ""
    if code in (gp.GP_ERROR_NO_SPACE, gp.GP_ERROR_NO_MEMORY) and (
            code == gp.GP_ERROR_NO_SPACE or any("full" in text.lower() for text in said)):
        return DeviceError(f"the camera's card is full{told}: free space on it (download and delete its files, or "
                           f"format it) and capture again")
    known: dict[int, tuple[type[DeviceError], str]] = {
        gp.GP_ERROR_MODEL_NOT_FOUND: (DeviceError, f"libgphoto2 found no camera: {NOT_FOUND_HINT}"),
        gp.GP_ERROR_IO_USB_FIND: (DeviceError, f"libgphoto2 found no camera: {NOT_FOUND_HINT}"),
        gp.GP_ERROR_IO_USB_CLAIM: (DeviceBusy, f"libgphoto2 could not claim the camera's USB interface: "
                                               f"{USB_GRABBED_HINT}; or no permission: {PERMISSION_HINT}"),
        gp.GP_ERROR_CAMERA_BUSY: (DeviceBusy, f"camera busy during {doing}: {BUSY_HINT}"),
        gp.GP_ERROR_TIMEOUT: (DeviceTimeout, f"the camera stopped answering during {doing}: power-cycle it and "
                                             f"reconnect"),
    }
    cls, message = known.get(code, (DeviceError, f"libgphoto2 failed during {doing}: "
                                                 f"{gp.gp_result_as_string(code)} ({code}){told}"))
    return cls(message)


class Gphoto2Camera(Camera):
    """A camera driven through libgphoto2 (python-gphoto2); see the module docstring."""

    driver = "gphoto2"

    def __init__(self, config: CameraConfig) -> None:
        super().__init__(config)
        self._camera: Any = None
        self._found: dict[str, str] = {}
        self._said: list[str] = []  # error messages libgphoto2 gave self._context since the last call
        self._context: Any = None
        self._context_hook: Any = None  # keeps the error callback registered

    def _call(self, doing: str, function: Any, *args: Any) -> Any:
        """`function(*args)`, a libgphoto2 error becoming a one-line DeviceError (with what libgphoto2 said)."""
        gp = gphoto2()
        self._said.clear()
        try:
            return function(*args)
        except gp.GPhoto2Error as exc:
            raise gphoto2_error(exc.code, doing, list(self._said)) from None

    def _hear(self, context: Any, text: Any, data: Any) -> None:
        self._said.append(text.decode(errors="replace") if isinstance(text, bytes) else str(text))

    def _open(self) -> None:
        gp = gphoto2()
        cameras = self._call("autodetect", gp.Camera.autodetect)
        detected = [(cameras.get_name(i), cameras.get_value(i)) for i in range(cameras.count())]
        chosen = [(name, port) for name, port in detected if not self.config.model or name == self.config.model]
        if len(chosen) != 1:
            found = ", ".join(f"{name} on {port}" for name, port in detected) or "none"
            wanted = f"camera.model = {self.config.model!r}" if self.config.model else "one camera"
            hint = NOT_FOUND_HINT if not detected else "set camera.model to one of them"
            raise DeviceError(f"libgphoto2 found {len(chosen) or 'no'} camera(s) for {wanted} (found: {found}): {hint}")
        name, port = chosen[0]
        self._context = gp.Context()
        self._context_hook = self._context.set_error_func(self._hear, None)
        abilities, ports = gp.CameraAbilitiesList(), gp.PortInfoList()
        self._call("loading camera drivers", abilities.load)
        self._call("loading ports", ports.load)
        camera = gp.Camera()
        camera.set_abilities(abilities[self._call("looking up the model", abilities.lookup_model, name)])
        camera.set_port_info(ports[self._call("looking up the port", ports.lookup_path, port)])
        self._call("connecting", camera.init, self._context)
        self._camera = camera
        self._found = {"detected_as": name, "port": port, **{key: self._setting(widget) or ""
                                                             for key, widget in _IDENTITY.items()}}

    def _close(self) -> None:
        if self._camera is not None:
            try:
                self._camera.exit()
            except gphoto2().GPhoto2Error:
                pass  # the camera is gone: nothing left to close on its side
            self._camera = None

    def _setting(self, name: str) -> str | None:
        """A configuration value of the camera as text; None where it has no such setting."""
        gp = gphoto2()
        try:
            return str(self._camera.get_single_config(name).get_value())
        except gp.GPhoto2Error:
            return None

    def settings(self) -> dict[str, str]:
        """Every configuration value the camera reports, by name (sections flattened)."""
        self._require_open()
        gp = gphoto2()
        found: dict[str, str] = {}
        pending = [self._call("reading the configuration", self._camera.get_config)]
        while pending:
            widget = pending.pop()
            pending += [widget.get_child(i) for i in range(widget.count_children())]
            if widget.get_type() not in (gp.GP_WIDGET_WINDOW, gp.GP_WIDGET_SECTION, gp.GP_WIDGET_BUTTON):
                found[widget.get_name()] = str(widget.get_value())
        return found

    def _identity(self) -> dict[str, str]:
        return {key: value for key, value in self._found.items() if value}

    def _to_computer(self) -> None:
        """Capture target RAM where the camera has the setting (not every body does)."""
        gp = gphoto2()
        try:
            target = self._camera.get_single_config("capturetarget")
        except gp.GPhoto2Error:
            return
        choices = [target.get_choice(i) for i in range(target.count_choices())]
        ram = next((choice for choice in choices if choice in _TO_RAM), None)
        if ram is not None and target.get_value() != ram:
            target.set_value(ram)
            self._call("setting the capture target", self._camera.set_single_config, "capturetarget", target)

    def download(self, folder: str, name: str) -> bytes:
        """The file `name` in the camera's `folder`, as the camera holds it."""
        gp = gphoto2()
        file = self._call(f"downloading {name}", self._camera.file_get, folder, name, gp.GP_FILE_TYPE_NORMAL)
        return bytes(memoryview(file.get_data_and_size()))

    def _capture_one(self) -> RawFrame:
        gp = gphoto2()
        self._to_computer()
        where = self._call("capture", self._camera.capture, gp.GP_CAPTURE_IMAGE, self._context)
        folder, name = str(where.folder), str(where.name)
        suffix = PurePath(name).suffix.lower().lstrip(".")
        if suffix not in RAW_FORMATS:
            raise DeviceError(f"the camera delivered {name}, not a RAW file (.dng, .nef, .arw, .cr2, ...: what LibRaw "
                              f"reads); left on the camera as {folder}/{name}: {RAW_HINT}")
        data = self.download(folder, name)
        metadata = {"captured_at": datetime.now(timezone.utc).isoformat(timespec="milliseconds"),
                    "camera": self._found.get("model") or self._found["detected_as"],
                    "serial": self._found.get("serial", ""), "camera_path": f"{folder}/{name}"}
        return RawFrame(data, suffix, name, metadata)

    def _saved(self, frame: RawFrame) -> None:
        """Delete the camera's copy (in its RAM, or on the card where it has no RAM target) now that it is saved."""
        folder, _, name = frame.metadata["camera_path"].rpartition("/")
        try:
            self._camera.file_delete(folder, name)
        except gphoto2().GPhoto2Error:
            pass  # a body that keeps it (on the card) is fine: the file is saved
