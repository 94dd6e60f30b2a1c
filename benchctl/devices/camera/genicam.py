"""The `genicam` camera driver: a machine-vision camera (GigE Vision, USB3 Vision) through Aravis.

Open: find the one camera the profile's keys match (device_id, serial, user_id, vendor / model), set and read
back region, pixel format, exposure (us), gain and black level (a value the camera does not take as written is
an error), set the software trigger, and start acquiring into a few pushed buffers. Each capture: software
trigger, wait for the buffer, and keep it only when Aravis reports it complete and its size, geometry and pixel
format are those set; an incomplete or missing one (lost packets) is re-triggered up to `frame_retries` times,
then the capture fails: a frame is kept whole or not at all. The frame becomes a DNG holding exactly the delivered
values, with the CFA layout and white level of its pixel format (benchctl.devices.camera.pixel_formats).
"""

from __future__ import annotations

import math
import time
from datetime import datetime, timezone
from typing import Any, Callable

from benchctl.devices.camera.aravis import aravis
from benchctl.devices.camera.base import Camera, FrameSize, RawFrame, real_frame
from benchctl.devices.camera.pixel_formats import PixelFormat, pixel_format
from benchctl.devices.errors import DeviceError, DeviceTimeout
from benchctl.devices.lock import DeviceLock
from benchctl.dng import dng_bytes
from benchctl.errors import BadValueError
from benchctl.limits import check_pixels
from benchctl.profiles import CameraConfig, Profile

BUFFERS = 4  # pushed to the stream: a frame can arrive while the previous one is converted
LINK_BYTES_PER_S = 100e6  # GigE Vision's 1 Gb/s link: the slower of the two (USB3 Vision carries about 400 MB/s)
_RELATIVE = 0.01  # a read-back setting within 1 % (cameras round to their increments) is taken as written
_ABSOLUTE = 0.05


class GenicamCamera(Camera):
    """A GenICam camera through Aravis; see the module docstring."""

    driver = "genicam"

    def __init__(self, config: CameraConfig) -> None:
        super().__init__(config)
        self._camera: Any = None
        self._stream: Any = None
        self._format: PixelFormat | None = None
        self._region: tuple[int, int, int, int] = (0, 0, 0, 0)
        self._settings: dict[str, Any] = {}
        self._identity_found: dict[str, str] = {}

    @classmethod
    def frame_size(cls, profile: Profile) -> FrameSize:
        """The profile's camera.region in its pixel_format (16 bits a sample where none is given), read out over
        GigE Vision after the exposure; without a region, Camera's default ([sim.sensor] shape), said so."""
        config = profile.section("camera")
        if config.region is None:
            return super().frame_size(profile)
        width, height = config.region[2], config.region[3]
        sample_bytes = pixel_format(config.pixel_format).bytes_per_sample if config.pixel_format else 2
        return real_frame(profile, height, width, 0.0, LINK_BYTES_PER_S / sample_bytes,
                          f"camera genicam's {width * height / 1e6:.3g} Mpx region ({width} x {height} "
                          f"{config.pixel_format or '16-bit'})")

    # -- finding the camera -------------------------------------------------------------------------------------

    def _wanted(self) -> dict[str, str]:
        """The profile's keys that choose the camera, by name."""
        keys = {"device_id": self.config.device_id, "serial": self.config.serial, "user_id": self.config.user_id,
                "vendor": self.config.vendor, "model": self.config.model or None}
        return {key: value for key, value in keys.items() if value is not None}

    def _device_lock(self) -> DeviceLock:
        wanted = ",".join(f"{key}={value}" for key, value in self._wanted().items()) or "any"
        return DeviceLock(f"camera:genicam:{wanted}", f"camera (genicam {wanted})")

    def _find(self, module: Any) -> Any:
        """The Aravis camera the profile's keys choose; DeviceError naming what was found otherwise."""
        wanted = self._wanted()
        if self.config.device_id is not None:
            return self._connect(module, self.config.device_id)
        module.update_device_list()
        found = [(module.get_device_id(i), module.get_device_serial_nbr(i) or "", module.get_device_vendor(i) or "",
                  module.get_device_model(i) or "") for i in range(module.get_n_devices())]
        candidates = [device_id for device_id, serial, vendor, model in found
                      if wanted.get("serial", serial) == serial and wanted.get("vendor", vendor) == vendor
                      and wanted.get("model", model) == model]
        chosen = [camera for camera in (self._connect(module, device_id) for device_id in candidates)
                  if self.config.user_id is None or _user_id(camera) == self.config.user_id]
        described = ", ".join(f"{vendor} {model} serial {serial} ({device_id})"
                              for device_id, serial, vendor, model in found) or "none"
        asked = ", ".join(f"camera.{key} = {value!r}" for key, value in wanted.items()) or "no camera keys"
        if len(chosen) != 1:
            many = "no GenICam camera" if not chosen else f"{len(chosen)} GenICam cameras"
            raise DeviceError(f"{many} match {asked} (found: {described}); `benchctl devices` lists them")
        return chosen[0]

    def _connect(self, module: Any, device_id: str) -> Any:
        try:
            return module.Camera.new(device_id)
        except _glib_error() as exc:
            raise DeviceError(f"cannot open GenICam camera {device_id!r}: {exc.message}") from None

    # -- connection -------------------------------------------------------------------------------------------------

    def _open(self) -> None:
        module = aravis()
        self._camera = self._find(module)
        try:
            self._identity_found = self._read_identity()
            self._configure()
            self._start(module)
        except _glib_error() as exc:
            self._shutdown()
            raise DeviceError(f"{self._label()}: {exc.message}") from None
        except BaseException:
            self._shutdown()
            raise

    def _configure(self) -> None:
        """Write every setting the profile gives and read each back; then check the pixel format."""
        camera, config = self._camera, self.config
        if config.region is not None:
            x, y, width, height = config.region
            self._check_region(x, y, width, height)
            camera.set_region(x, y, width, height)
            got = camera.get_region()
            if (got.x, got.y, got.width, got.height) != (x, y, width, height):
                raise DeviceError(f"{self._label()}: camera.region {list(config.region)} written, the camera reads "
                                  f"back {[got.x, got.y, got.width, got.height]} (increments or sensor size)")
        if config.pixel_format is not None:
            available = list(camera.dup_available_pixel_formats_as_strings() or [])
            if config.pixel_format not in available:
                raise DeviceError(f"{self._label()}: camera.pixel_format {config.pixel_format!r} is not offered "
                                  f"(offered: {', '.join(available)})")
            camera.set_pixel_format_from_string(config.pixel_format)
        self._format = pixel_format(camera.get_pixel_format_as_string())
        if config.pixel_format is not None and self._format.name != config.pixel_format:
            raise DeviceError(f"{self._label()}: pixel format {config.pixel_format} written, the camera reads back "
                              f"{self._format.name}")
        region = camera.get_region()
        self._region = (region.x, region.y, region.width, region.height)
        if config.exposure_s is not None:
            self._set("exposure (us)", config.exposure_s * 1e6, camera.get_exposure_time_bounds(),
                      camera.set_exposure_time, camera.get_exposure_time)
        if config.gain is not None:
            self._set("gain", config.gain, camera.get_gain_bounds(), camera.set_gain, camera.get_gain)
        if config.black_level is not None:
            if not camera.is_black_level_available():
                raise DeviceError(f"{self._label()} has no BlackLevel feature: remove camera.black_level")
            self._set("black level", config.black_level, camera.get_black_level_bounds(), camera.set_black_level,
                      camera.get_black_level)
        camera.set_trigger("Software")
        self._settings = {"pixel_format": self._format.name, "region": list(self._region),
                          "exposure_s": camera.get_exposure_time() * 1e-6, "gain": camera.get_gain(),
                          "trigger": "Software"}
        if camera.is_black_level_available():
            self._settings["black_level"] = camera.get_black_level()

    def _check_region(self, x: int, y: int, width: int, height: int) -> None:
        """Refuse a region outside the sensor (WidthMax x HeightMax, else the sensor's size) or above benchctl's pixel
        limit before it is written: a camera may take one and then fail in native code (Aravis's fake camera took
        100000 x 100000 and the process died in the buffer pop), or fill the disk with one frame."""
        camera = self._camera
        sensor = camera.get_sensor_size()
        columns, rows = (camera.get_integer(name) if camera.is_feature_available(name) else fallback
                         for name, fallback in (("WidthMax", sensor.width), ("HeightMax", sensor.height)))
        where = f"{self._label()}: camera.region {[x, y, width, height]}"
        if x + width > columns or y + height > rows:
            raise BadValueError(f"{where} reaches column {x + width} and row {y + height}, beyond the camera's "
                                f"{columns} x {rows} (WidthMax x HeightMax): give a region inside it")
        check_pixels(where, height, width)

    def _set(self, name: str, value: float, bounds: Any, write: Callable[[float], None],
             read: Callable[[], float]) -> None:
        """Write `value` and read it back; refused outside the camera's bounds or when it reads back otherwise."""
        low, high = bounds
        if not low <= value <= high:
            raise BadValueError(f"{self._label()}: {name} {value:g} is outside the camera's {low:g} .. {high:g}")
        write(value)
        got = read()
        if not math.isclose(got, value, rel_tol=_RELATIVE, abs_tol=_ABSOLUTE):
            raise DeviceError(f"{self._label()}: {name} {value:g} written, the camera reads back {got:g}")

    def _start(self, module: Any) -> None:
        """A stream with BUFFERS buffers of the payload size, acquisition started (frames come on triggers)."""
        self._stream = self._camera.create_stream(None, None)
        if self._stream is None:
            raise DeviceError(f"{self._label()}: Aravis could not create a stream")
        payload = self._camera.get_payload()
        for _ in range(BUFFERS):
            self._stream.push_buffer(module.Buffer.new_allocate(payload))
        self._camera.start_acquisition()

    def _close(self) -> None:
        if self._camera is not None:
            try:
                self._camera.stop_acquisition()
            except _glib_error():
                pass  # the camera is gone: nothing to stop on its side
        self._shutdown()

    def _shutdown(self) -> None:
        """Drop the stream and the camera (Aravis closes the connection when they are freed); never raises."""
        self._stream = self._camera = None
        self._identity_found = {}

    def _label(self) -> str:
        """How messages name the camera (read at open: a camera that stopped answering cannot say its name)."""
        found = self._identity_found
        if not found:
            return "GenICam camera"
        return f"{found['manufacturer']} {found['model']} (serial {found['serial']})"

    def _read_identity(self) -> dict[str, str]:
        camera = self._camera
        identity = {"manufacturer": camera.get_vendor_name() or "", "model": camera.get_model_name() or "",
                    "serial": camera.get_device_serial_number() or "", "device_id": camera.get_device_id() or ""}
        user_id = _user_id(camera)
        if user_id:
            identity["user_id"] = user_id
        return identity

    def _identity(self) -> dict[str, str]:
        assert self._format is not None
        offered = ", ".join(self._camera.dup_available_pixel_formats_as_strings() or [])
        features = {key: f"{value:g}" if isinstance(value, float) else str(value)
                    for key, value in self._settings.items() if key != "pixel_format"}
        return {**self._identity_found, "pixel_format": f"{self._format.name} ({self._format.bits} bit, "
                f"{self._format.cfa or 'mono'})", "pixel_formats_offered": offered, **features}

    def _apply_settings(self, exposure_s: float | None, iso: int | None) -> None:
        """Exposure was written at open (every GenICam camera takes it); ISO is not a GenICam setting."""
        if iso is not None:
            raise BadValueError("a GenICam camera has gain, not ISO: set camera.gain and remove camera.iso")

    # -- capture ---------------------------------------------------------------------------------------------------

    def _capture_one(self) -> RawFrame:
        assert self._format is not None and self._stream is not None
        module = aravis()
        timeout_s = self._settings["exposure_s"] + self.config.image_timeout_s
        refused = []
        for _ in range(1 + self.config.frame_retries):
            self._drain()
            started = time.perf_counter()
            try:
                self._camera.software_trigger()
            except _glib_error() as exc:
                raise DeviceError(f"{self._label()}: software trigger failed: {exc.message}") from None
            buffer = self._stream.timeout_pop_buffer(round(timeout_s * 1e6))
            if buffer is None:  # nothing arrived (its leader lost, or the camera gone): trigger again
                refused.append("nothing")
                continue
            try:
                status = buffer.get_status()
                if status != module.BufferStatus.SUCCESS:
                    refused.append(status.value_nick)
                    continue
                frame, received = self._checked(buffer), time.perf_counter()
                frame_id, timestamp_ns = buffer.get_frame_id(), buffer.get_timestamp()
            finally:
                self._stream.push_buffer(buffer)
            data = dng_bytes(frame, cfa=self._format.cfa, white_level=self._format.white_level,
                             camera_model=self._identity_found["model"], exposure_s=self._settings["exposure_s"])
            metadata = {"captured_at": datetime.now(timezone.utc).isoformat(timespec="milliseconds"),
                        "camera": self._identity_found["model"], "serial": self._identity_found["serial"],
                        "frame_id": frame_id, "timestamp_ns": timestamp_ns, "incomplete_refused": refused,
                        "trigger_to_frame_s": round(received - started, 6), **self._settings}
            return RawFrame(data, "dng", f"frame-{frame_id:08d}.dng", metadata)
        if set(refused) == {"nothing"}:
            raise DeviceTimeout(f"{self._label()} delivered no frame within {timeout_s:g} s of each of {len(refused)} "
                                f"software triggers: camera off, cable pulled or network down (camera.image_timeout_s)")
        raise DeviceError(f"{self._label()}: no complete frame in {len(refused)} software triggers (buffers: "
                          f"{', '.join(refused)}): packets lost; use a dedicated network port, jumbo frames or a "
                          f"lower frame rate")

    def _checked(self, buffer: Any) -> Any:
        """The buffer's frame as a uint16 array; DeviceError unless geometry and format are those set."""
        assert self._format is not None
        width, height = self._region[2], self._region[3]
        got = (buffer.get_image_width(), buffer.get_image_height(), buffer.get_image_pixel_format())
        expected = (width, height, self._camera.get_pixel_format())
        if got != expected:
            raise DeviceError(f"{self._label()} delivered a {got[0]} x {got[1]} frame of pixel format 0x{got[2]:08x}, "
                              f"not the {width} x {height} {self._format.name} set")
        return self._format.frame(buffer.get_image_data(), width, height)

    def _drain(self) -> None:
        """Give back buffers that arrived without a trigger of ours (a late frame), so each capture is its own."""
        while (stale := self._stream.try_pop_buffer()) is not None:
            self._stream.push_buffer(stale)


def _user_id(camera: Any) -> str | None:
    """The camera's DeviceUserID, or None where it has none."""
    try:
        return camera.get_string("DeviceUserID") if camera.is_feature_available("DeviceUserID") else None
    except _glib_error():
        return None


def _glib_error() -> type[Any]:
    """GLib.Error, the exception Aravis calls raise (gi is loaded once `aravis()` ran)."""
    from gi.repository import GLib

    error: type[Any] = GLib.Error  # untyped (PyGObject has no stubs): its instances carry .message
    return error
