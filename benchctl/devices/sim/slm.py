"""The simulated SLM: keeps exactly what the panel would show, in the simulated bench's state folder, and knows
its own liquid crystal's phase response (`true_lut`), which calibration has to find.

Each displayed frame becomes a PNG (8- or 16-bit, gray levels as shown) named by a frame counter, and the
state file `slm.json` says which frame is current, its shape, bit depth, channel and time. Other programs
(the simulated camera) read it with `read_displayed`; like every device, the SLM is held by one command at a time.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from datetime import datetime, timezone
from typing import Any

import numpy as np

from benchctl.devices.errors import DeviceError
from benchctl.devices.lock import DeviceLock
from benchctl.devices.sim.state import device_file, load_state, save_state, sim_lock, state_dir
from benchctl.devices.slm.base import SLM, Showing
from benchctl.errors import BenchctlError
from benchctl.files import ensure_dir
from benchctl.optics.phase_encoding import PhaseLUT
from benchctl.profiles import Profile, SimSLMConfig, SLMConfig

STATE_NAME = "slm"
_READ_ATTEMPTS = 5


@functools.lru_cache(maxsize=8)
def true_lut(wavelength_m: float, bit_depth: int, response: SimSLMConfig) -> PhaseLUT:
    """The simulated panel's real gray -> phase table at one wavelength (what calibration should measure):
    2 pi (two_pi_nm / wavelength) (g / 2^bit_depth)^gamma."""
    depth = 2 * math.pi * response.two_pi_nm * 1e-9 / wavelength_m
    levels = np.arange(1 << bit_depth, dtype=np.float64) / (1 << bit_depth)
    return PhaseLUT(depth * levels**response.gamma)


def read_displayed() -> tuple[np.ndarray | None, dict[str, Any]]:
    """The frame the simulated SLM shows now and its metadata; (None, {}) if it has shown nothing yet."""
    from benchctl.images import read_image  # OpenCV: only where a frame file is read, so `slm info` stays light

    for _ in range(_READ_ATTEMPTS):
        state = load_state(STATE_NAME)
        if not state:
            return None, {}
        if "file" not in state or "frame" not in state:
            raise DeviceError(f"simulated SLM: state {state_dir()}/{STATE_NAME}.json is incomplete; "
                              f"`benchctl sim reset` clears it")
        try:
            return read_image(state_dir() / state["file"]), state
        except BenchctlError:
            if load_state(STATE_NAME).get("frame") == state["frame"]:
                raise
            # A newer frame replaced this one while it was being read: read the new one.
    raise DeviceError("simulated SLM: the frame changed on every attempt to read it")


class SimSLM(SLM):
    """An SLM whose panel is a PNG plus metadata in the simulated bench state (see module docstring)."""

    driver = "sim"
    read_displayed = staticmethod(read_displayed)

    def __init__(self, config: SLMConfig, channels: Sequence[str] = (), response: SimSLMConfig | None = None) -> None:
        """`response`: the simulated panel's true phase response (the profile's [sim.slm]; default: its defaults)."""
        super().__init__(config, channels)
        self.response = response if response is not None else SimSLMConfig()

    @classmethod
    def for_profile(cls, profile: Profile) -> SimSLM:
        """The simulated panel of `profile`, with its true phase response ([sim.slm])."""
        config = profile.require("slm").slm
        assert config is not None
        return cls(config, [channel.name for channel in profile.channels], profile.sim.slm)

    def ground_truth_lut(self, wavelength_m: float) -> np.ndarray:
        """The simulated panel's own response ([sim.slm]) at `wavelength_m`."""
        return true_lut(wavelength_m, self.bit_depth, self.response).phases

    def _device_lock(self) -> DeviceLock:
        return sim_lock(STATE_NAME, self.label)

    def _open(self) -> None:
        """Nothing to connect to; fail now, not at the first frame, if the state folder is not writable."""
        ensure_dir(state_dir())

    def _close(self) -> None:
        pass

    def _display(self, gray: np.ndarray, channel: str | None) -> None:
        """Write the frame file first, then the state naming it, then drop older frame files."""
        from benchctl.images import write_png

        frame = int(load_state(STATE_NAME).get("frame", 0)) + 1
        name = f"{STATE_NAME}-{frame}.png"
        write_png(device_file(name), gray)
        save_state(STATE_NAME, {
            "frame": frame,
            "file": name,
            "shape": list(gray.shape),
            "bit_depth": self.bit_depth,
            "channel": channel,
            "time": datetime.now(timezone.utc).isoformat(timespec="milliseconds"),
            "by": self.holder(),
        })
        for old in state_dir().glob(f"{STATE_NAME}-*.png"):
            if old.name != name:
                old.unlink(missing_ok=True)

    def displayed_frame(self) -> int | None:
        """The simulated panel's frame counter (None before its first frame)."""
        frame = load_state(STATE_NAME).get("frame")
        return None if frame is None else int(frame)

    def showing(self) -> Showing:
        """The simulated panel's frame and its record: which program displayed it, when, for which colour."""
        gray, state = read_displayed()
        frame = state.get("frame")
        return Showing(gray, None if frame is None else int(frame), state.get("by"), state.get("time"),
                       state.get("channel"))

    def info(self) -> dict[str, Any]:
        """The base description plus where the simulated panel lives and what it shows now."""
        return {**super().info(), "device": str(state_dir()), "displayed": load_state(STATE_NAME)}
