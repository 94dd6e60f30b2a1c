"""The bench a procedure runs on: the profile's laser, SLM and camera, each opened the first time a step needs
it and all closed together (emission off first) however the run ends.

`expose` is the one way procedures put light on the camera: frame on the SLM, only the wanted channel at its
setpoint, the settle time, RAW frames saved the moment they arrive, emission off again, then dark frames with
every channel off. Laser safety (off at connect, off on any exit, limits, read-back) lives in the driver.
"""

from __future__ import annotations

import time
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import numpy as np

from benchctl.devices.camera import Camera, open_camera
from benchctl.devices.laser import Laser, open_laser
from benchctl.devices.slm import SLM, open_slm
from benchctl.profiles import Profile

DEVICES = ("laser", "slm", "camera")


class Bench:
    """Lazily opened devices of one profile; use as a context manager."""

    def __init__(self, profile: Profile) -> None:
        self.profile = profile
        self._stack = ExitStack()
        self._open: dict[str, Any] = {}
        self.identities: dict[str, Any] = {}

    def __enter__(self) -> Bench:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Close every opened device, the laser first (its close switches emission off)."""
        laser = self._open.pop("laser", None)
        try:
            if laser is not None:
                laser.close()
        finally:
            self._open.clear()
            self._stack.close()

    @property
    def laser(self) -> Laser:
        if "laser" not in self._open:
            laser = open_laser(self.profile)
            self._open["laser"] = laser
            self.identities["laser"] = laser.identity()
        return self._open["laser"]

    @property
    def slm(self) -> SLM:
        if "slm" not in self._open:
            slm = self._stack.enter_context(open_slm(self.profile.require("slm")))
            self._open["slm"] = slm
            self.identities["slm"] = slm.info()
        return self._open["slm"]

    @property
    def camera(self) -> Camera:
        if "camera" not in self._open:
            camera = self._stack.enter_context(open_camera(self.profile))
            self._open["camera"] = camera
            self.identities["camera"] = camera.identity()
        return self._open["camera"]

    def expose(self, folder: Path, channel: str, power_w: float, frame: np.ndarray, *, frames: int,
               dark_frames: int) -> dict[str, Any]:
        """Show `frame` (gray levels as displayed), light it with `channel` alone at `power_w`, capture
        `frames` RAW frames into `folder` (frame-000...), then with emission off `dark_frames` (dark-000...).

        Returns what happened: file names, the read-back setpoint, the measured power, timings.
        """
        laser, slm, camera = self.laser, self.slm, self.camera
        laser.all_off()
        slm.show_gray(frame)  # waits the settle time while dark
        setpoint = laser.set_power(channel, power_w)
        start = time.perf_counter()
        try:
            laser.set_emission(channel, True)
            measured = laser.measured_w(channel)
            lit = camera.capture(folder, frames, stem="frame")
        finally:
            laser.set_emission(channel, False)
        exposed_s = time.perf_counter() - start
        darks = camera.capture(folder, dark_frames, stem="dark") if dark_frames else []
        return {
            "channel": channel, "setpoint_w": setpoint, "measured_w": measured, "emission_s": round(exposed_s, 3),
            "frames": [frame_.path.name for frame_ in lit if frame_.path],
            "darks": [frame_.path.name for frame_ in darks if frame_.path],
            "camera": [frame_.metadata for frame_ in lit][:1],
        }
