"""The console's SLM panel: what to show, computed and displayed through the SLM driver's own encoding.

Patterns: blank (gray 0), a flat phase, a blazed grating (period, angle), the registration dot grid, and the
hologram of a target (a bundled chart or photo, or an uploaded image) by a method for one colour. Zernike terms in
waves (defocus, astigmatism, coma, spherical) are added to any phase pattern: the quick way to correct a bench by
hand. Every phase goes through `SLM.show_phase` (the colour's lookup table, phase offset, carrier, flips); the
holograms are the ones a run displays (`holograms.cache.hologram`: the same method, calibration, fitted model
and cache), computed in the console's hologram worker process. The request is a typed model, so a bad value is
refused with its name before anything is computed.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Annotated, Any, Literal

import cv2
import msgspec
import numpy as np

from benchctl.console.devices import Held
from benchctl.console.holograms import HologramWorker, Request
from benchctl.console.uploads import Uploads
from benchctl.devices.errors import DeviceError
from benchctl.devices.slm import SLM, open_slm
from benchctl.errors import BadValueError, BenchctlError
from benchctl.profiles import Profile

PatternKind = Literal["blank", "flat", "grating", "dots", "hologram"]
ZernikeName = Literal["defocus", "astigmatism_vertical", "astigmatism_oblique", "coma_vertical", "coma_horizontal",
                      "spherical"]
Waves = Annotated[float, msgspec.Meta(ge=-20, le=20)]
THUMBNAIL_WIDTH = 320


class Pattern(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
    """What the SLM panel asks for (the page's form, as JSON)."""

    kind: PatternKind
    channel: str | None = None  # the colour whose lookup table encodes the phase (default: the first channel)
    phase_rad: Annotated[float, msgspec.Meta(ge=-100, le=100)] = 0.0  # flat
    period_px: Annotated[float, msgspec.Meta(ge=2, le=100000)] = 16.0  # grating
    angle_deg: Annotated[float, msgspec.Meta(ge=-360, le=360)] = 0.0  # grating, 0 = phase rising along columns
    zernike: dict[ZernikeName, Waves] = msgspec.field(default_factory=dict)
    target: str = "chart:bars"  # hologram: chart:<name>, photo:<name> or upload:<id>
    method: str = "dpac"
    iterations: Annotated[int, msgspec.Meta(ge=1, le=5000)] | None = None
    checkpoint: str | None = None  # a learned method's checkpoint: a name the console lists, never a path
    seed: Annotated[int, msgspec.Meta(ge=0)] = 0


def parse_pattern(data: Any) -> Pattern:
    """The page's JSON as a Pattern; BadValueError naming the key that is wrong."""
    try:
        return msgspec.convert(data, Pattern)
    except msgspec.ValidationError as exc:
        raise BadValueError(f"SLM pattern: {exc}") from None


class SlmControl:
    """The profile's SLM held by the console (lookup tables and fitted model as calibrated for the profile), and
    what it shows now."""

    def __init__(self, profile: Profile, uploads: Uploads, checkpoints: dict[str, str]) -> None:
        self.profile = profile
        self.uploads = uploads
        self.checkpoints = checkpoints  # name the page may choose -> checkpoint file
        self.worker = HologramWorker()
        self.held: Held[SLM] = Held("SLM", lambda: open_slm(profile), SLM.close)
        self.shown: dict[str, Any] = {"kind": None}  # the pattern, or (kind None) what the device says it shows
        self.frame: np.ndarray | None = None
        self.last_hologram: dict[str, Any] | None = None  # how the last hologram was made: seconds, cache, scores

    @property
    def channels(self) -> list[str]:
        return [channel.name for channel in self.profile.channels]

    def phase(self, pattern: Pattern, progress: Any = None) -> np.ndarray | None:
        """The phase (radians, (H, W)) `pattern` shows, before encoding; None for blank. Holograms take long (in
        the hologram worker; `progress(label, done, total)` as they go): call this off the server's event loop."""
        if pattern.kind == "blank":
            return None
        slm = self.profile.section("slm")
        rows, cols = slm.shape
        if pattern.kind == "flat":
            phase = np.full((rows, cols), pattern.phase_rad)
        elif pattern.kind == "grating":
            angle = math.radians(pattern.angle_deg)
            y, x = np.arange(rows)[:, None], np.arange(cols)[None, :]
            phase = (2 * math.pi / pattern.period_px) * (x * math.cos(angle) + y * math.sin(angle))
        else:
            phase = self._hologram(pattern, progress)
        if pattern.zernike:
            from benchctl.optics.aberration import wavefront_phase

            waves: dict[str, float] = {term: value for term, value in pattern.zernike.items()}
            phase = phase + wavefront_phase((rows, cols), slm.pitch_m, waves).numpy()
        return phase

    def _hologram(self, pattern: Pattern, progress: Any) -> np.ndarray:
        """The hologram a run would display for this target, method and colour (computed in the hologram worker),
        decoded back to its phase."""
        from benchctl.targets import active_channels, load_target, prepare_target, target_plane

        channel = self._channel(pattern)
        slm, optics = self.profile.section("slm"), self.profile.section("optics")
        if pattern.kind == "dots":
            from benchctl.capture.registration import dot_grid_target

            dots, _ = dot_grid_target(slm.shape, optics.roi)
            amplitude, method, iterations, checkpoint = dots.expand(3, -1, -1).clone(), "dpac", None, None
            label = "registration dot grid"
        else:
            srgb = load_target(self._target(pattern.target), size=optics.roi)
            amplitude = prepare_target(srgb, slm.shape, optics.roi)
            method, iterations = pattern.method, pattern.iterations
            checkpoint = self._checkpoint(pattern.checkpoint)
            label = pattern.target
        if not active_channels(amplitude)[target_plane(self.profile.channel(channel))]:
            raise BadValueError(f"{label} is black in {channel}: nothing to show in that colour")
        result = self.worker.compute(Request(self.profile, amplitude, channel, method, iterations, pattern.seed,
                                             checkpoint), progress)
        self.last_hologram = {"seconds": round(result.seconds, 3), "cached": result.cached,
                              "scores": {k: round(v, 3) for k, v in result.scores.items()}}
        with self.device() as device:
            return device.decode(result.gray, channel).astype(np.float64)

    @contextmanager
    def device(self) -> Iterator[SLM]:
        """The open SLM for one block. A driver's error other than a refused value (the X server of a display SLM
        died, a framebuffer went away) means the SLM is lost: it is let go, the page says why in one line and offers
        to connect again, and the request gets that line (a DeviceError), never a traceback."""
        with self.held.use() as device:
            try:
                yield device
            except BadValueError:
                raise
            except Exception as exc:  # noqa: BLE001 - any failure of the driver is said, not a 500
                reason = str(exc) if isinstance(exc, BenchctlError) else f"{device.label}: {type(exc).__name__}: {exc}"
                self.held.lost(f"{reason} (connect again when it is back)")
                raise DeviceError(reason) from None

    def read_device(self) -> str | None:
        """What the SLM shows now, from the device itself (at connect, and when the console takes the SLM back from
        a procedure): its frame, who put it there and when. Returns a line saying so when that is not what the
        console last showed (None when it is, or the SLM is not connected)."""
        if not self.held.connected:
            return None
        with self.device() as device:
            showing = device.showing()
        if showing.frame_id is not None and showing.frame_id == self.shown.get("frame") and \
                showing.by == self.shown.get("by"):
            return None  # still the console's own frame
        known = self.shown.get("frame") is not None
        self.frame = showing.frame
        self.shown = {"kind": None, "frame": showing.frame_id, "by": showing.by, "at": showing.at,
                      "channel": showing.channel}
        if showing.frame is None:  # nothing shown yet, or a panel that cannot be read back
            return "the SLM cannot say what it shows now" if known else None
        who = f" by {showing.by}" if showing.by else " by a program unknown to the SLM"
        return f"the SLM shows frame {showing.frame_id}, put there{who}" + (f" at {showing.at}" if showing.at else "")

    def show(self, pattern: Pattern, phase: np.ndarray | None) -> dict[str, Any]:
        """Display `phase` (from `phase(pattern)`) through the driver and remember what is shown."""
        with self.device() as device:
            if phase is None:
                self.frame = device.blank()
            else:
                self.frame = device.show_phase(phase, self._channel(pattern))
            frame_id, by = device.shown_frame, device.holder()
        self.shown = {**msgspec.to_builtins(pattern), "channel": None if phase is None else self._channel(pattern),
                      "frame": frame_id, "by": by, "at": device.presented_at}
        if pattern.kind in ("hologram", "dots"):
            self.shown["hologram"] = self.last_hologram
        return self.shown

    def thumbnail(self) -> bytes:
        """What the panel shows now, THUMBNAIL_WIDTH pixels wide, as PNG (gray 0 before anything was shown)."""
        slm = self.profile.section("slm")
        frame = self.frame if self.frame is not None else np.zeros(slm.shape, np.uint8)
        if frame.dtype != np.uint8:
            frame = (frame >> (slm.bit_depth - 8)).astype(np.uint8)
        width = min(THUMBNAIL_WIDTH, frame.shape[1])
        small = cv2.resize(frame, (width, max(1, round(frame.shape[0] * width / frame.shape[1]))),
                           interpolation=cv2.INTER_AREA)
        ok, png = cv2.imencode(".png", small)
        if not ok:
            raise BenchctlError("SLM thumbnail could not be encoded")
        return png.tobytes()

    def _channel(self, pattern: Pattern) -> str:
        channel = pattern.channel or self.channels[0]
        if channel not in self.channels:
            raise BadValueError(f"SLM pattern: no channel {channel!r} (known: {', '.join(self.channels)})")
        return channel

    def _target(self, spec: str) -> str:
        """A bundled target spec as it is, an upload's private file for `upload:<id>`; nothing else (no paths)."""
        if spec.startswith(("chart:", "photo:")):
            return spec
        if spec.startswith("upload:"):
            return str(self.uploads.path(spec.removeprefix("upload:")))
        raise BadValueError(f"target {spec!r}: choose chart:<name>, photo:<name> or an uploaded image")

    def _checkpoint(self, name: str | None) -> str | None:
        if name is None:
            return None
        if name not in self.checkpoints:
            raise BadValueError(f"checkpoint {name!r} is not one the console offers (known: "
                                f"{', '.join(self.checkpoints) or 'none'})")
        return self.checkpoints[name]
