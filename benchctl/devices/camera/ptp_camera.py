"""The `ptp` camera driver: a Canon EOS M body (the bench's EOS M10) captured over PTP/USB, RAW to the computer.

The M10 has no InitiateCapture, so this follows the EOS M capture sequence of libgphoto2
(camlibs/ptp2/library.c, the Canon EOS capture path; https://github.com/gphoto/libgphoto2):

    open:     OpenSession(1) [transaction 0], GetDeviceInfo, SetRemoteMode(0x15), SetEventMode(1),
              GetEvent until empty, SetDevicePropValueEx(capture destination 0xD11C = 4, to the computer),
              PCHDDCapacity(0x0fffffff, 0x1000, 1), SetEventMode(2), SetDevicePropValueEx(0xD1B0 = 8), wait 1 s
              [write_properties only: image format RAW, then shutter and ISO, each a SetDevicePropValueEx]
    capture:  RemoteReleaseOn(3, 0) (answered DeviceBusy: GetEvent, retry), GetEvent until the body reports it is
              shooting (<= 2 s), RemoteReleaseOff(3), GetEvent until RequestObjectTransfer (<= image_timeout_s),
              GetPartialObject in 1 MiB chunks, TransferComplete(handle)
    preview:  SetDevicePropValueEx(0xD1B0 = 2) once, then GetViewFinderData(0x00100000) per frame (answered 0xA102
              or DeviceBusy while no frame is ready: GetEvent, retry); a capture or close sets 0xD1B0 back to 8 first
    focus:    SetDevicePropValueEx(0xD1B0 = 2) if the live view is off, then DriveLens(0x9155, Near/Far 1-3) per step
              (answered OK even when the lens ignored it: benchctl.devices.focus.eos counts from an end stop)
    close:    CloseSession

Capture destination and EVF output are part of the capture set-up and always written; the exposure settings
(format, shutter, ISO) are written only with `write_properties = true`, because such writes freeze the M10.
The object's name and format come from the RequestObjectTransfer record; GetObjectInfo is asked only when the
record ends before the name.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import PurePath

from benchctl.devices.camera.base import Camera, FrameSize, PreviewFrame, RawFrame, Window
from benchctl.devices.camera.hints import BUSY_HINT, NO_FOCUS_HINT, RAW_HINT
from benchctl.devices.camera.ptp.container import RAW_OBJECT_FORMATS, OperationCode, code_name
from benchctl.devices.camera.ptp.datasets import DeviceInfo
from benchctl.devices.camera.ptp.eos import (
    CAMERA_STATUS_SHOOTING,
    CAPTURE_TO_PC,
    EVENT_MODE,
    EVENT_MODE_EOS_M,
    EVF_OUTPUT_LIVE_VIEW,
    EVF_OUTPUT_PC,
    RAW_ONLY,
    RELEASE_NO_CARD_SPACE,
    RELEASE_NO_FOCUS,
    RELEASE_OK,
    REMOTE_MODE_EOS_M,
    Eos,
    EosEvent,
    EosEventType,
    EosProperty,
    ObjectRecord,
    is_canon,
    iso_code,
    missing_eos_operations,
    object_record,
    shutter_code,
)
from benchctl.devices.camera.ptp.session import PtpSession, ResponseBusy
from benchctl.devices.camera.ptp.transport import Transport, UsbTransport
from benchctl.devices.errors import DeviceBusy, DeviceError, DeviceTimeout
from benchctl.devices.safety import wait
from benchctl.profiles import CameraConfig, Profile


@dataclass(frozen=True)
class EosTiming:
    """The waits of the capture sequence (defaults from the reference implementation; tests shrink them)."""

    settle_s: float = 1.0  # after the EOS M EVF-output write
    release_events_s: float = 2.0  # GetEvent after RemoteReleaseOn, until the body says it is shooting
    poll_interval_s: float = 0.05  # between GetEvent polls that found nothing
    busy_retry_s: float = 5.0  # keep retrying a release the body answers DeviceBusy
    usb_timeout_s: float = 10.0  # one USB transfer (real USB only)
    live_view_s: float = 3.0  # GetViewFinderData answered "not ready" this long: the live view failed


class PtpCamera(Camera):
    """A Canon EOS M body over PTP; see the module docstring for the exact operations."""

    driver = "ptp"

    def __init__(self, config: CameraConfig, transport: Transport | None = None,
                 timing: EosTiming = EosTiming()) -> None:
        super().__init__(config)
        self._given_transport = transport
        self.timing = timing
        self._transport: Transport | None = None
        self._session: PtpSession | None = None
        self._eos: Eos | None = None
        self._info = DeviceInfo()
        self._written: dict[str, float | int] = {}
        self._live = False  # the live view is on (EVF output to the computer)

    @classmethod
    def for_profile(cls, profile: Profile) -> PtpCamera:
        """The body on USB, or with camera.transport = "sim" the simulated EOS body on the simulated bench."""
        config = profile.require("camera").camera
        assert config is not None
        if config.transport != "sim":
            return cls(config)
        from benchctl.devices.sim.camera import eos_transport

        return cls(config, eos_transport(profile))

    @classmethod
    def frame_size(cls, profile: Profile) -> FrameSize:
        """The body's sensor as [sim.sensor] gives it (an EOS M10's by default); the simulated body renders it."""
        if profile.section("camera").transport != "sim":
            return super().frame_size(profile)
        from benchctl.devices.sim.camera import simulated_frame

        return simulated_frame(profile, "the simulated EOS body")

    # -- connection --------------------------------------------------------------------------------------------

    def _open(self) -> None:
        if self._given_transport is None and self.config.transport == "sim":
            raise DeviceError("camera.transport = 'sim' needs the simulated EOS body: open the camera through "
                              "the simulated bench, not on its own")
        self._transport = self._given_transport or UsbTransport.open(self.config.usb_id, self.timing.usb_timeout_s)
        self._session = PtpSession(self._transport, self.timing.usb_timeout_s)
        self._eos = Eos(self._session)
        try:
            self._prepare()
        except BaseException:
            self._shutdown()  # no CloseSession: the body may be frozen or gone; a later OpenSession recovers
            raise

    def _prepare(self) -> None:
        session, eos = self._require_session()
        session.open()
        self._info = session.get_device_info()
        usb_vendor = self._transport.usb_vendor if self._transport is not None else None
        if not is_canon(self._info, usb_vendor):
            vendor = "unknown" if usb_vendor is None else f"0x{usb_vendor:04x}"
            raise DeviceError(f"{self._describe()} is not a Canon body (USB vendor {vendor}, PTP vendor extension "
                              f"{self._info.vendor_extension_id}): use camera driver 'gphoto2'")
        missing = missing_eos_operations(self._info)
        if missing:
            raise DeviceError(f"{self._describe()} does not offer Canon EOS remote release and events (no "
                              f"{', '.join(code_name(code) for code in missing)}): use camera driver 'gphoto2'")
        eos.set_remote_mode(REMOTE_MODE_EOS_M)
        eos.set_event_mode(EVENT_MODE)
        eos.drain_events()
        eos.set_property(EosProperty.CaptureDestination, CAPTURE_TO_PC)
        eos.pc_hdd_capacity()
        eos.set_event_mode(EVENT_MODE_EOS_M)
        eos.set_property(EosProperty.EVFOutputDevice, EVF_OUTPUT_PC)
        wait(self.timing.settle_s)
        if self.config.write_properties:
            self._write(EosProperty.ImageFormat, RAW_ONLY, "image format RAW")

    def _close(self) -> None:
        if self._session is not None and self._session.is_open:
            try:
                self._end_live_view()
                self._session.close()
            except DeviceError:
                pass  # the camera is gone or frozen: nothing left to close on its side
        self._shutdown()

    def _shutdown(self) -> None:
        """Release the transport (also after a failed open); never raises."""
        if self._transport is not None:
            self._transport.close()
        self._transport = self._session = self._eos = None
        self._live = False

    def _require_session(self) -> tuple[PtpSession, Eos]:
        if self._session is None or self._eos is None:
            raise DeviceError("ptp camera is not connected")
        return self._session, self._eos

    def _describe(self) -> str:
        return f"{self._info.model or 'camera'} ({self.config.usb_id})"

    def _identity(self) -> dict[str, str]:
        return {"manufacturer": self._info.manufacturer, "model": self._info.model,
                "serial": self._info.serial_number, "firmware": self._info.device_version}

    # -- settings ----------------------------------------------------------------------------------------------

    def _write(self, prop: EosProperty, value: int | tuple[int, ...], what: str) -> None:
        _, eos = self._require_session()
        try:
            eos.set_property(prop, value)
        except DeviceTimeout:
            raise DeviceTimeout(f"{self._describe()} stopped answering after writing {what} "
                                f"(SetDevicePropValueEx): the EOS M10 freezes on property writes; power-cycle it, "
                                f"set exposure, ISO and RAW on the body and set camera.write_properties = false") \
                from None

    def _apply_settings(self, exposure_s: float | None, iso: int | None) -> None:
        try:
            if exposure_s is not None:
                self._write(EosProperty.ShutterSpeed, shutter_code(exposure_s), f"shutter {exposure_s:g} s")
                self._written["exposure_s"] = exposure_s
            if iso is not None:
                self._write(EosProperty.ISO, iso_code(iso), f"ISO {iso}")
                self._written["iso"] = iso
        except BaseException:
            self._shutdown()  # Camera.open() raises from here, so no `with` block will close us
            raise

    # -- capture -----------------------------------------------------------------------------------------------

    # -- live view ---------------------------------------------------------------------------------------------

    def _preview(self, width: int, window: Window | None) -> PreviewFrame:
        """The body's own live view (a JPEG of the whole frame at the body's size); a body without
        GetViewFinderData gives a RAW capture instead (the default)."""
        if OperationCode.EosGetViewFinderData not in self._info.operations_supported:
            return super()._preview(width, window)
        _, eos = self._require_session()
        if not self._live:
            eos.set_property(EosProperty.EVFOutputDevice, EVF_OUTPUT_LIVE_VIEW)
            self._live = True
        started = time.monotonic()
        while (jpeg := eos.viewfinder_frame()) is None:
            if time.monotonic() - started >= self.timing.live_view_s:
                raise DeviceTimeout(f"{self._describe()} gave no live-view frame within {self.timing.live_view_s:g} "
                                    f"s (GetViewFinderData answered not ready): is it in movie mode or asleep?")
            eos.get_events()
            wait(self.timing.poll_interval_s)
        return PreviewFrame(jpeg, "jpeg", metadata={"camera": self._info.model,
                                                    "waited_s": round(time.monotonic() - started, 6)})

    def drive_lens(self, far: bool, size: int) -> None:
        """One DriveLens step Near or Far of `size` (1-3), in live view (started here if it is off: the lens moves
        only then). The body answers OK whether or not the lens moved (an end stop): the caller counts."""
        if OperationCode.EosDriveLens not in self._info.operations_supported:
            raise DeviceError(f"{self._describe()} does not offer DriveLens (0x9155): it cannot drive its lens's focus")
        _, eos = self._require_session()
        if not self._live:
            eos.set_property(EosProperty.EVFOutputDevice, EVF_OUTPUT_LIVE_VIEW)
            self._live = True
        eos.drive_lens(far, size)

    def _end_live_view(self) -> None:
        """EVF output back to the capture set-up's value (the live view holds the sensor otherwise)."""
        if self._live:
            _, eos = self._require_session()
            self._live = False
            eos.set_property(EosProperty.EVFOutputDevice, EVF_OUTPUT_PC)

    def _capture_one(self) -> RawFrame:
        session, eos = self._require_session()
        self._end_live_view()
        result = self._release(eos)
        seen = self._poll(eos, self.timing.release_events_s, _shooting) if result == RELEASE_OK else []
        eos.remote_release_off()
        if result == RELEASE_NO_FOCUS:
            raise DeviceError(f"{self._describe()}: {NO_FOCUS_HINT}")
        if result == RELEASE_NO_CARD_SPACE:
            raise DeviceError(f"{self._describe()} refused the release: no room for the image (release result 7); "
                              f"check the capture destination and the card")
        if result != RELEASE_OK:
            raise DeviceError(f"{self._describe()} refused the release with result {result}")
        requests = [event for event in seen if _transfer_request(event)] or [
            event for event in self._poll(eos, self.config.image_timeout_s, _transfer_request)
            if _transfer_request(event)]
        if not requests:
            raise DeviceTimeout(f"{self._describe()} sent no image within {self.config.image_timeout_s:g} s of the "
                                f"shutter release (no RequestObjectTransfer event): check that it released, that "
                                f"the exposure is shorter than camera.image_timeout_s, and that it is not in "
                                f"movie mode")
        record = object_record(requests[0])
        name, fmt = self._name_and_format(session, record)
        if fmt not in RAW_OBJECT_FORMATS:
            raise DeviceError(f"{self._describe()} delivered {name}, not a RAW file (format {code_name(fmt)}): "
                              f"{RAW_HINT}")
        started = time.perf_counter()
        data = eos.read_object(record.handle, record.size)
        eos.transfer_complete(record.handle)
        metadata = {"transfer_s": round(time.perf_counter() - started, 6),
                    "captured_at": datetime.now(timezone.utc).isoformat(timespec="milliseconds"),
                    "camera": self._info.model, "serial": self._info.serial_number,
                    "object_handle": record.handle, "settings_written": bool(self._written), **self._written}
        return RawFrame(data, RAW_OBJECT_FORMATS[fmt], name, metadata)

    def _release(self, eos: Eos) -> int:
        """RemoteReleaseOn, retried while the body answers DeviceBusy (events drained in between)."""
        deadline = time.monotonic() + self.timing.busy_retry_s
        while True:
            try:
                return eos.remote_release_on()
            except ResponseBusy:
                if time.monotonic() >= deadline:
                    raise DeviceBusy(f"{self._describe()} stayed busy for {self.timing.busy_retry_s:g} s and "
                                     f"refused the shutter release (PTP DeviceBusy 0x2019): {BUSY_HINT}") from None
            eos.get_events()
            wait(self.timing.poll_interval_s)

    def _poll(self, eos: Eos, within_s: float, wanted: Callable[[EosEvent], bool]) -> list[EosEvent]:
        """GetEvent until a batch holds a record satisfying `wanted` or `within_s` passes; all records seen."""
        seen: list[EosEvent] = []
        deadline = time.monotonic() + within_s
        while True:
            events = eos.get_events()
            seen += events
            if any(wanted(event) for event in events) or time.monotonic() >= deadline:
                return seen
            if not events:
                wait(self.timing.poll_interval_s)

    def _name_and_format(self, session: PtpSession, record: ObjectRecord) -> tuple[str, int]:
        if record.name is not None:
            return record.name, record.format
        info = session.get_object_info(record.handle)
        return PurePath(info.filename).name or f"IMG_{record.handle:08X}", info.object_format


def _shooting(event: EosEvent) -> bool:
    """The body reports it took the picture: status 'shooting', or the image already announced."""
    return (event.type == EosEventType.CameraStatus and event.u32(8) == CAMERA_STATUS_SHOOTING) \
        or _transfer_request(event)


def _transfer_request(event: EosEvent) -> bool:
    return event.type == EosEventType.RequestObjectTransfer


def open_ptp_camera(config: CameraConfig, transport: Transport | None = None,
                    timing: EosTiming = EosTiming()) -> PtpCamera:
    """The `ptp` camera, connected (capture set-up done); use it in a `with` block. `transport`: None for the
    real camera over USB (pyusb), else e.g. `SimEosTransport(image_source=...)`; `timing`: shorter waits for tests."""
    camera = PtpCamera(config, transport, timing)
    camera.open()
    return camera
