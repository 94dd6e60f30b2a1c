"""The SLM: a phase-only display. Public methods are fixed here; drivers implement three hooks.

`show_phase` turns radians into the gray levels the panel shows, in one place for every driver: add the
profile's phase offset and blazed grating carrier, encode through the channel's lookup table (the one
phase -> gray mapping, benchctl.optics.phase_encoding), mirror as the optics require, display, wait the
settle time. Drivers only open, close and put a finished gray frame on the panel (`_display`).
"""

from __future__ import annotations

import math
import sys
import time
from abc import abstractmethod
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import datetime, timedelta, timezone
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from benchctl.devices.connection import Connection
from benchctl.devices.errors import DeviceError
from benchctl.devices.lock import DeviceLock
from benchctl.devices.safety import wait
from benchctl.devices.slm.lut import lut_for
from benchctl.errors import BadValueError
from benchctl.optics.phase_encoding import PhaseLUT, gray_to_phase, phase_to_gray
from benchctl.profiles import Profile, SLMConfig

if TYPE_CHECKING:  # phases may come as tensors, but torch is never imported here: SLM commands stay light
    import torch

TWO_PI = 2.0 * math.pi


@dataclass(frozen=True)
class Showing:
    """What an SLM's panel shows now, as far as the device can tell: the gray frame as shown (None: it cannot
    tell), the device's id of that frame where it keeps one, who put it there (a program and its pid; None:
    unknown, e.g. a frame read back that this connection did not write) and when (UTC, ISO 8601), and the colour
    it was encoded for (None: raw gray levels, or unknown)."""

    frame: np.ndarray | None
    frame_id: int | None = None
    by: str | None = None
    at: str | None = None
    channel: str | None = None
# A table whose widest unshown phase interval exceeds this many ideal gray steps is worth optimising through: a
# red laser on a panel with 2 pi at 600 nm (gap 0.76 rad) gains 3.6 dB from SGD through it, while an 8-bit
# table covering 2 pi loses 0.1 dB (measured at 1088 x 1920, chart:bars, 70 iterations; docs/model_calibration.md).
GAP_STEPS = 4


class SLM(Connection):
    """A phase SLM built from the profile's [slm] section; a context manager (open on enter, close on exit)."""

    driver: ClassVar[str]

    def __init__(self, config: SLMConfig, channels: Sequence[str] = ()) -> None:
        """`channels`: the profile's laser channel names, the valid `channel` arguments (with any in slm.lut)."""
        self.config = config
        self.channels: tuple[str, ...] = tuple(dict.fromkeys([*channels, *config.lut]))
        self.sleep: Callable[[float], None] = wait  # the settle wait; tests replace it
        self._luts: dict[str, PhaseLUT] = {}
        self._current: np.ndarray | None = None
        self._current_channel: str | None = None
        self._frames_shown = 0
        self.shown_frame: int | None = None  # displayed_frame() right after this object's last frame went up
        # When the last frame was presented (UTC, ISO 8601 to the microsecond): the time the platform reports
        # (the display driver's vblank), else when `_display` returned; the settle time counts from here.
        self.presented_at: str | None = None

    @classmethod
    def for_profile(cls, profile: Profile) -> SLM:
        """This driver for `profile`'s [slm] section and laser channels, not yet opened; drivers that need more
        of the profile override it."""
        config = profile.require("slm").slm
        assert config is not None
        return cls(config, [channel.name for channel in profile.channels])

    # -- hooks ------------------------------------------------------------------------------------------

    @abstractmethod
    def _open(self) -> None:
        """Connect to the panel."""

    @abstractmethod
    def _close(self) -> None:
        """Release the panel; what it shows stays (a display keeps its last frame)."""

    @abstractmethod
    def _display(self, gray: np.ndarray, channel: str | None) -> float | None:
        """Put `gray` ((H, W), gray_dtype, read-only) on the panel; `channel` is None for raw gray frames. Returns
        when the panel showed it, on time.monotonic()'s clock, where the platform says; None: on return."""

    def _device_lock(self) -> DeviceLock:
        return DeviceLock(f"slm:{self.driver}:{self.config.device}", self.label)

    # -- description --------------------------------------------------------------------------------------

    @property
    def label(self) -> str:
        """How messages name this SLM, e.g. "SLM (framebuffer /dev/fb1)"."""
        where = f" {self.config.device}" if self.config.device else ""
        return f"SLM ({self.driver}{where})"

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) = (rows, cols): the shape of phases and gray frames."""
        return self.config.shape

    @property
    def pitch_m(self) -> float:
        """Pixel pitch in metres."""
        return self.config.pitch_m

    @property
    def bit_depth(self) -> int:
        """Bits per gray level; the panel shows 0 .. 2^bit_depth - 1."""
        return self.config.bit_depth

    @property
    def gray_dtype(self) -> type[np.unsignedinteger]:
        """dtype of gray frames: uint8 up to 8 bit, uint16 above."""
        return np.uint8 if self.bit_depth <= 8 else np.uint16

    @property
    def settle_s(self) -> float:
        """Wait after each new frame before the panel is trusted (liquid crystal response)."""
        return self.config.settle_ms * 1e-3

    def info(self) -> dict[str, Any]:
        """What this SLM is and how it encodes, for `benchctl slm info` and run records (JSON-ready)."""
        linear = f"linear, 2 pi = gray {self.config.two_pi_gray or (1 << self.bit_depth):g}"
        return {
            "driver": self.driver,
            "device": self.config.device,
            "shape": list(self.shape),
            "pitch_um": self.config.pitch_um,
            "bit_depth": self.bit_depth,
            "settle_ms": self.config.settle_ms,
            "flip_x": self.config.flip_x,
            "flip_y": self.config.flip_y,
            "phase_offset_rad": self.config.phase_offset_rad,
            "grating_period_px": list(self.config.grating_period_px),
            "luts": {ch: str(self.config.lut[ch]) if ch in self.config.lut else linear for ch in self.channels},
        }

    def lut(self, channel: str) -> PhaseLUT:
        """The gray -> phase table used for `channel` (loaded once)."""
        if channel not in self._luts:
            if channel not in self.channels:
                known = ", ".join(self.channels) or "none (the profile has no [laser] channels or [slm.lut])"
                raise BadValueError(f"{self.label}: no channel {channel!r}; known channels: {known}")
            self._luts[channel] = lut_for(self.config, channel)
        return self._luts[channel]

    def ground_truth_lut(self, wavelength_m: float) -> np.ndarray | None:
        """The panel's true gray -> phase response at `wavelength_m` (radians, one per gray level), as far as
        the device knows: a simulated panel knows what LUT calibration should measure; a real one does not
        (None), since only calibration can measure it."""
        return None

    def displayed_frame(self) -> int | None:
        """Id of the frame the panel shows now, as the device reports it. Drivers whose panel cannot say
        report the count of frames this object displayed (the device lock keeps other commands off the panel)."""
        return self._frames_shown

    def current(self) -> np.ndarray | None:
        """The last frame this object displayed (read-only), None before the first."""
        return self._current

    def showing(self) -> Showing:
        """What the panel shows now and who put it there: the frame this connection displayed last, unless the
        panel, read back where the driver can (`_read_panel`), holds another one (then `by` is unknown). Drivers
        that know more (the simulated panel records every program's frames) override it."""
        panel = self._read_panel()
        own = self._current
        if own is not None and (panel is None or np.array_equal(panel, own)):
            return Showing(own, self.displayed_frame(), self.holder(), self.presented_at, self._current_channel)
        return Showing(panel)

    def _read_panel(self) -> np.ndarray | None:
        """The gray frame on the panel as the device reads it back; None where it cannot (the default)."""
        return None

    def holder(self) -> str | None:
        """The program holding this SLM (its lock's holder: command and pid), while it is open."""
        holder = self._hold.holder() if self._hold is not None else None
        return None if holder is None else f"`{holder.command}` (pid {holder.pid})"

    # -- showing ----------------------------------------------------------------------------------------------

    def _added_phase(self) -> np.ndarray:
        """Phase offset plus blazed carrier (float64, broadcastable to (H, W)) added before encoding."""
        total = np.full((1, 1), self.config.phase_offset_rad, dtype=np.float64)
        for axis, period in enumerate(self.config.grating_period_px):
            if period:
                ramp = np.arange(self.shape[axis], dtype=np.float64) * (TWO_PI / period)
                total = total + (ramp[:, None] if axis == 0 else ramp)
        return total

    def _flipped(self, frame: np.ndarray) -> np.ndarray:
        """`frame` mirrored as the optics require (flip_y: rows, flip_x: columns); a view."""
        return np.flip(frame, tuple(axis for axis, on in ((0, self.config.flip_y), (1, self.config.flip_x)) if on))

    def encode(self, phase: np.ndarray | torch.Tensor, channel: str) -> np.ndarray:
        """The gray frame `show_phase` would display for `phase` ((H, W) radians), without displaying it."""
        phase = self._checked_phase(phase).astype(np.float64, copy=False)
        gray = phase_to_gray(phase + self._added_phase(), self.lut(channel))
        return np.ascontiguousarray(self._flipped(gray), dtype=self.gray_dtype)

    def decode(self, gray: np.ndarray, channel: str) -> np.ndarray:
        """The hologram phase a displayed frame carries: undo flips, look up `channel`'s table, remove the
        offset and carrier (the optics compensate those). Float32 (H, W) radians in [-pi, pi)."""
        return (np.remainder(self._driven(gray, channel) + math.pi, TWO_PI) - math.pi).astype(np.float32)

    def driven(self, gray: np.ndarray, channel: str) -> np.ndarray:
        """`decode` without the wrap into [-pi, pi): the table's phases (offset and carrier removed), which jump
        where the gray levels wrap, as the panel's do. Pixel crosstalk blurs these jumps (`FittedOptics`)."""
        return self._driven(gray, channel).astype(np.float32)

    def _driven(self, gray: np.ndarray, channel: str) -> np.ndarray:
        table_phase = gray_to_phase(self._flipped(np.asarray(gray)), self.lut(channel)).astype(np.float64)
        return table_phase - self._added_phase()

    def display_model(self, channel: str, always: bool = False) -> Callable[[torch.Tensor], torch.Tensor] | None:
        """What the panel drives for a hologram phase at `channel` (encoded, then `driven`: torch in, torch out),
        for optimisers to see through. Unless `always` (a model with crosstalk needs the driven phase's jumps),
        None when the table leaves no phase more than GAP_STEPS gray steps away: there rounding to a level is
        noise that a straight-through gradient only blurs."""
        lut = self.lut(channel)
        if not always and lut.widest_gap <= GAP_STEPS * TWO_PI / lut.levels:
            return None

        def shown(phase: torch.Tensor) -> torch.Tensor:
            return phase.new_tensor(self.driven(self.encode(phase.detach(), channel), channel))

        return shown

    def show_phase(self, phase: np.ndarray | torch.Tensor, channel: str) -> np.ndarray:
        """Display `phase` ((H, W) radians) encoded for `channel`'s wavelength; returns the frame as displayed."""
        return self._show(self.encode(phase, channel), channel)

    def show_gray(self, gray: np.ndarray | torch.Tensor) -> np.ndarray:
        """Display raw gray levels as they are (no offset, carrier, table or flip); returns the frame displayed."""
        gray = _as_numpy(gray)
        if gray.shape != self.shape:
            raise BadValueError(
                f"{self.label}: gray frame has shape {gray.shape}, expected (H, W) = {self.shape} "
                f"(profile slm.height x slm.width)"
            )
        expected = np.dtype(self.gray_dtype)
        if gray.dtype != expected:
            raise BadValueError(
                f"{self.label}: gray frame has dtype {gray.dtype}, expected {expected} for a {self.bit_depth}-bit SLM"
            )
        top = int(gray.max())
        if top >= 1 << self.bit_depth:
            raise BadValueError(
                f"{self.label}: gray level {top} out of range 0..{(1 << self.bit_depth) - 1} ({self.bit_depth}-bit SLM)"
            )
        return self._show(gray.copy(), None)

    def blank(self) -> np.ndarray:
        """Display gray 0 everywhere; returns the frame."""
        return self.show_gray(np.zeros(self.shape, self.gray_dtype))

    def _show(self, frame: np.ndarray, channel: str | None) -> np.ndarray:
        if not self._open_now:
            raise DeviceError(f"{self.label} is not open (use `with open_slm(profile) as slm:`)")
        frame.flags.writeable = False
        presented = self._display(frame, channel)
        since = 0.0 if presented is None else max(0.0, time.monotonic() - presented)
        self.presented_at = (datetime.now(timezone.utc) - timedelta(seconds=since)).isoformat(timespec="microseconds")
        self._current, self._current_channel = frame, channel
        self._frames_shown += 1
        self.shown_frame = self.displayed_frame()
        self.sleep(max(0.0, self.settle_s - since))
        return frame

    def _checked_phase(self, phase: np.ndarray | torch.Tensor) -> np.ndarray:
        """`phase` as a numpy array, refused unless it is real floating point, (H, W) and finite."""
        array = _as_numpy(phase)
        if array.dtype.kind != "f":
            raise BadValueError(
                f"{self.label}: phase must be real radians (float), got {array.dtype}; "
                f"use show_gray for gray levels"
            )
        if array.shape != self.shape:
            raise BadValueError(
                f"{self.label}: phase has shape {array.shape}, expected (H, W) = {self.shape} "
                f"(profile slm.height x slm.width)"
            )
        bad = int(np.count_nonzero(~np.isfinite(array)))
        if bad:
            raise BadValueError(f"{self.label}: phase has {bad} NaN or infinite values of {array.size}")
        return array


def _as_numpy(array: np.ndarray | torch.Tensor) -> np.ndarray:
    """`array` as numpy; a tensor is detached and brought to the CPU (displaying needs no gradient)."""
    torch = sys.modules.get("torch")  # a tensor can only exist once torch is imported
    if torch is not None and isinstance(array, torch.Tensor):
        return array.detach().cpu().numpy()
    return np.asarray(array)
