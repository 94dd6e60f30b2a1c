"""The instruments a run uses: the profile's laser, SLM, camera and focus, each opened the first time a step needs it
and all closed together (emission off first, then the profile's setpoints back) however the run ends.

`expose` is the one way a run puts light on the camera: frame on the SLM, only the wanted channel at its
setpoint, the settle time, RAW frames saved the moment they arrive, emission off again, then dark frames with
every channel off. Laser safety (off at connect, off on any exit, limits, read-back) lives in the driver.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from benchctl.devices.camera import Camera, RawFrame, open_camera
from benchctl.devices.errors import DeviceError
from benchctl.devices.focus import Focus
from benchctl.devices.laser import Laser, open_laser
from benchctl.devices.slm import SLM, open_slm
from benchctl.profiles import Profile

DEVICES = ("laser", "slm", "camera", "focus")


class Instruments:
    """The lazily opened devices of one profile; use as a context manager."""

    def __init__(self, profile: Profile, say: Callable[[str], None] = print) -> None:
        self.profile = profile
        self.say = say
        self._stack = ExitStack()
        self._open: dict[str, Any] = {}
        self.identities: dict[str, Any] = {}

    def __enter__(self) -> Instruments:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Close every opened device, the laser first: emission off, every channel's setpoint back to the profile's
        (automatic exposure and power sweeps choose others; the next `laser on` must not surprise), then its ports
        (closing switches emission off again)."""
        laser = self._open.pop("laser", None)
        try:
            if laser is not None:
                try:
                    laser.all_off()
                    for line in laser.restore_setpoints("the run"):  # the run's own error, if any, stays raised
                        self.say(f"laser: {line}")
                finally:
                    laser.close()
        finally:
            self._open.clear()
            self._stack.close()

    def _device(self, name: str, opener: Callable[[], Any], identify: Callable[[Any], Any]) -> Any:
        """The device called `name`, opened (and its identity noted) on first use."""
        if name not in self._open:
            device = opener()
            if name != "laser":  # the laser is closed first, by close(), not by the stack
                self._stack.enter_context(device)
            self._open[name] = device
            self.identities[name] = identify(device)
        return self._open[name]

    @property
    def laser(self) -> Laser:
        return self._device("laser", lambda: open_laser(self.profile), self._laser_identity)

    def _laser_identity(self, laser: Laser) -> Any:
        """The laser's identity; channels it found emitting at connect are said and recorded (devices.json)."""
        found = laser.connect_report()
        for line in found:
            self.say(f"laser: {line}")
        if found:
            self.identities["laser_found_emitting"] = found
        return laser.identity()

    @property
    def slm(self) -> SLM:
        return self._device("slm", lambda: open_slm(self.profile.require("slm")), lambda slm: slm.info())

    @property
    def camera(self) -> Camera:
        return self._device("camera", lambda: open_camera(self.profile), lambda camera: camera.identity())

    @property
    def focus(self) -> Focus:
        """The camera's focus; the EOS lens is driven through this run's camera (which it opens first)."""
        def opener() -> Focus:
            from benchctl.devices.camera.ptp_camera import PtpCamera
            from benchctl.devices.focus import open_focus
            from benchctl.devices.focus.eos import EosFocus

            config = self.profile.section("focus")
            camera = self.camera if config.driver == "eos" else None
            if isinstance(camera, PtpCamera):
                return EosFocus.on_camera(config, camera).open()
            return open_focus(self.profile)

        return self._device("focus", opener, lambda focus: focus.identity())

    def expose(self, folder: Path | None, channel: str, power_w: float, frame: np.ndarray, *, frames: int,
               dark_frames: int) -> Exposure:
        """Show `frame` (gray levels as displayed), light it with `channel` alone at `power_w`, capture `frames`
        RAW frames, then with emission off `dark_frames`, saved into `folder` as they arrive (frame-000...,
        dark-000...; with `folder` None kept in memory only).

        A lit frame that saw another SLM frame than the one shown is a DeviceError.
        """
        laser, slm, camera = self.laser, self.slm, self.camera
        clock = time.perf_counter
        start = clock()
        laser.all_off()
        shown_at = clock()
        slm.show_gray(frame)  # waits the settle time while dark
        display_s = clock() - shown_at
        shown = slm.shown_frame
        setpoint = laser.set_power(channel, power_w)
        start_emission = clock()
        capture_s = 0.0
        try:
            laser.set_emission(channel, True)
            measured = laser.measured_w(channel)
            captured_at = clock()
            lit = camera.capture(folder, frames, stem="frame")
            capture_s += clock() - captured_at
        finally:
            laser.set_emission(channel, False)
        exposed_s = clock() - start_emission
        seen = [_slm_frame_seen(frame_, slm) for frame_ in lit]
        wrong = [(frame_, id_) for frame_, id_ in zip(lit, seen) if id_ != shown]
        if wrong:
            frame_, id_ = wrong[0]
            raise DeviceError(f"{frame_.path or frame_.file_name}: captured while the SLM showed frame {id_}, not "
                              f"frame {shown} that this step displayed (did another program change the SLM?)")
        captured_at = clock()
        darks = camera.capture(folder, dark_frames, stem="dark") if dark_frames else []
        capture_s += clock() - captured_at
        result = {
            "channel": channel, "slm_frame": shown, "slm_presented_at": slm.presented_at, "slm_frames_seen": seen,
            "setpoint_w": setpoint,
            "measured_w": measured, "emission_s": round(exposed_s, 3),
            "frames": [frame_.path.name for frame_ in lit if frame_.path],
            "darks": [frame_.path.name for frame_ in darks if frame_.path],
            "camera": [frame_.metadata for frame_ in lit][:1],
        }
        timing = {"display_s": display_s, "capture_s": capture_s,
                  "laser_s": clock() - start - display_s - capture_s}
        return Exposure(result, lit, darks, timing)


@dataclass
class Exposure:
    """What one `expose` did: a JSON-ready result (file names, the read-back setpoint, the measured power, the SLM
    frame shown and the one each lit frame saw, the camera's metadata), the lit and dark frames (their bytes, and
    their paths when saved), and seconds spent: display_s (showing the frame, settle included), capture_s
    (shutter release to file received, every frame), laser_s (the rest: setpoint, emission on and off,
    read-backs)."""

    result: dict[str, Any]
    frames: list[RawFrame]
    darks: list[RawFrame]
    timing: dict[str, float]


def _slm_frame_seen(frame: RawFrame, slm: SLM) -> int | None:
    """Which SLM frame a captured frame saw: what the camera reports where it can tell (the simulated one
    does), else what the SLM reports it shows right after the capture."""
    seen = frame.metadata.get("slm_frame")
    return slm.displayed_frame() if seen is None else int(seen)
