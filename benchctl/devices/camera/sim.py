"""The "sim" camera driver: a Canon-like body on the simulated bench, recording what the simulated SLM and
lasers produce (benchctl.devices.sim.bench) as a DNG."""

from __future__ import annotations

from benchctl.devices.camera.base import Camera, RawFrame
from benchctl.devices.sim.bench import render_capture
from benchctl.devices.sim.state import state_dir
from benchctl.files import ensure_dir
from benchctl.profiles import CameraConfig, Profile


class SimCamera(Camera):
    """The simulated camera of `profile` (its [sim] physics); exposure and ISO come from the [camera] section,
    else from the simulated body's own settings ([sim.sensor])."""

    driver = "sim"

    def __init__(self, config: CameraConfig, profile: Profile) -> None:
        super().__init__(config)
        self.profile = profile

    def _open(self) -> None:
        """Nothing to connect to; fail now, not at the first frame, if the state folder is not writable."""
        ensure_dir(state_dir())

    def _close(self) -> None:
        pass

    def _identity(self) -> dict[str, str]:
        return {"manufacturer": "benchctl", "model": self.profile.sim.sensor.model, "serial_number": "sim"}

    def _apply_settings(self, exposure_s: float | None, iso: int | None) -> None:
        """Accepted: every capture already uses the profile's exposure and ISO."""

    def _capture_one(self) -> RawFrame:
        return render_capture(self.profile, exposure_s=self.config.exposure_s, iso=self.config.iso)
