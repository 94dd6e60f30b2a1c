"""The "sim" camera driver: a Canon-like body on the simulated bench, recording what the simulated SLM and
lasers produce (benchctl.devices.sim.physics) as a DNG; and the simulated EOS body that the `ptp` driver talks to
when the profile says camera.transport = "sim", delivering the same frames over PTP."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import numpy as np

from benchctl.devices.camera.base import DNG_BYTES_PER_PX, Camera, FrameSize, PreviewFrame, RawFrame, Window
from benchctl.devices.errors import DeviceError
from benchctl.devices.lock import DeviceLock
from benchctl.devices.safety import wait
from benchctl.devices.sim.eos_usb import SimEosTransport
from benchctl.devices.sim.state import CAMERA_STATE, load_state, sim_lock, state_dir
from benchctl.files import ensure_dir
from benchctl.profiles import CameraConfig, Profile

if TYPE_CHECKING:
    from benchctl.devices.sim.physics import LiveView

# The simulator's work per frame (render, DNG, file, laser): 3 s per 18.6 Mpx frame on the project's shared 2-core
# machine.
SIM_SECONDS_PER_MPX = 0.16


def unplug_frame(fault: str) -> int:
    """N of the simulated camera's fault `unplug_at=N`; DeviceError for anything else."""
    name, _, value = fault.partition("=")
    if name != "unplug_at" or not value.isdigit():
        raise DeviceError(f"simulated camera: unknown fault {fault!r} (known: unplug_at=N)")
    return int(value)


class SimCamera(Camera):
    """The simulated camera of `profile` (its [sim] physics); exposure and ISO come from the [camera] section,
    else from the simulated body's own settings ([sim.sensor])."""

    driver = "sim"
    windowed_preview = True

    def __init__(self, config: CameraConfig, profile: Profile) -> None:
        super().__init__(config)
        self.profile = profile
        self._live_view: LiveView | None = None

    @classmethod
    def for_profile(cls, profile: Profile) -> SimCamera:
        config = profile.require("camera").camera
        assert config is not None
        return cls(config, profile)

    @classmethod
    def frame_size(cls, profile: Profile) -> FrameSize:
        return simulated_frame(profile, "the simulated camera")

    def _device_lock(self) -> DeviceLock:
        return sim_lock(CAMERA_STATE, "camera (sim)")

    def _open(self) -> None:
        """Nothing to connect to; fail now, not at the first frame, if the state folder is not writable."""
        ensure_dir(state_dir())

    def _close(self) -> None:
        pass

    def _identity(self) -> dict[str, str]:
        return {"manufacturer": "benchctl", "model": self.profile.sim.sensor.model, "serial_number": "sim"}

    def _check_cable(self) -> None:
        """Fault `unplug_at=N` (benchctl sim fault sim-camera unplug_at=N): the cable is pulled just before
        frame N, so that shutter release fails and the frame counter stays at N - 1."""
        state = load_state(CAMERA_STATE)
        for fault in state.get("faults", []):
            if int(state.get("frame", 0)) + 1 >= unplug_frame(fault):
                raise DeviceError(f"simulated camera: USB cable pulled before frame {state.get('frame', 0) + 1}")

    def _apply_settings(self, exposure_s: float | None, iso: int | None) -> None:
        """Accepted: every capture already uses the profile's exposure and ISO."""

    def ground_truth_homography(self) -> np.ndarray:
        """The simulated bench's own imaging geometry ([sim.imaging], [sim.sensor])."""
        from benchctl.devices.sim.physics import camera_homography

        return camera_homography(self.profile)

    def _capture_one(self) -> RawFrame:
        """Render the frame, then wait the exposure and the body's readout time as a real camera would."""
        from benchctl.devices.sim.physics import render_capture  # torch physics: only a capture needs it

        self._check_cable()
        start = time.perf_counter()
        frame = render_capture(self.profile, exposure_s=self.config.exposure_s, iso=self.config.iso)
        frame.metadata["render_s"] = round(time.perf_counter() - start, 6)  # the simulator's own work, not a camera's
        wait(frame.metadata["exposure_s"] + self.profile.sim.sensor.readout_s)
        return frame

    def _preview(self, width: int, window: Window | None) -> PreviewFrame:
        """A binned readout of `window` from the simulator's live view (`LiveView`): the light is computed once per
        SLM frame and laser state, so a steady scene costs only resampling and noise per frame."""
        from benchctl.devices.sim.physics import LiveView

        self._check_cable()
        if self._live_view is None:
            self._live_view = LiveView(self.profile)
        start = time.perf_counter()
        data, metadata = self._live_view.dng(width, window, exposure_s=self.config.exposure_s, iso=self.config.iso)
        metadata["render_s"] = round(time.perf_counter() - start, 6)
        return PreviewFrame(data, "dng", tuple(metadata["window"]), self._live_view.active_shape, metadata)

def simulated_frame(profile: Profile, who: str) -> FrameSize:
    """A frame the simulated bench renders for `profile` ([sim.sensor]): the rendering, the exposure and the body's
    readout time, each waited as a real camera would."""
    sensor = profile.sim.sensor
    rows, cols = sensor.shape
    exposure = (profile.camera.exposure_s if profile.camera else None) or sensor.exposure_s
    return FrameSize(rows, cols, DNG_BYTES_PER_PX * rows * cols,
                     SIM_SECONDS_PER_MPX * rows * cols / 1e6 + exposure + sensor.readout_s,
                     f"{who}'s {rows * cols / 1e6:.3g} Mpx")


def eos_transport(profile: Profile) -> SimEosTransport:
    """A simulated EOS body on `profile`'s simulated bench: each shutter release delivers the DNG the bench
    renders, and its live view the simulator's preview as JPEG, with the exposure and ISO of the profile's
    [camera] section; with [focus] driver "eos" its lens is the bench's focus mechanism ([sim.focus])."""
    from benchctl.devices.camera.base import PREVIEW_WIDTH
    from benchctl.devices.sim.physics import LiveView, render_capture  # torch physics: only a capture needs it

    config = profile.require("camera").camera
    assert config is not None

    def image_source() -> tuple[bytes, str]:
        frame = render_capture(profile, exposure_s=config.exposure_s, iso=config.iso)
        return frame.data, frame.file_name

    view = LiveView(profile)
    lens = None
    if profile.focus is not None and profile.focus.driver == "eos":
        from benchctl.devices.sim.focus_mechanics import Mechanism, bind

        bind(profile.sim.focus)
        lens = Mechanism(profile.sim.focus, profile.optics.distance_mm if profile.optics else None)
    return SimEosTransport(image_source, live_view=lambda: view.jpeg(PREVIEW_WIDTH, exposure_s=config.exposure_s,
                                                                     iso=config.iso), lens=lens)
