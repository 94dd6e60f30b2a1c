"""The camera: captures RAW frames exactly as the camera delivers them. Public methods here; drivers do hooks.

A captured file is written to its destination (atomically) before anything else touches it, so a crash
after the shutter never loses a frame; only then may the driver let the camera drop its own copy (`_saved`).
Decoding and averaging happen later, in `benchctl.capture`.
"""

from __future__ import annotations

from abc import abstractmethod
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

from benchctl.devices.connection import Connection
from benchctl.devices.errors import DeviceError
from benchctl.devices.lock import DeviceLock
from benchctl.errors import BadValueError
from benchctl.files import atomic_write_bytes, ensure_dir
from benchctl.profiles import CameraConfig, Profile

if TYPE_CHECKING:
    import numpy as np

# The RAW files LibRaw (rawpy) decodes, by their usual file suffix: Adobe DNG; Canon CR2, CR3, CRW; Nikon NEF, NRW;
# Sony ARW, SRF, SR2; Fujifilm RAF; Olympus ORF; Panasonic RW2, RAW; Leica RWL; Pentax PEF, PTX; Samsung SRW;
# Hasselblad 3FR, FFF; Phase One IIQ; Leaf MOS; Mamiya MEF; Minolta MRW; Sigma X3F; Epson ERF; Kodak KDC, DCR, K25.
RAW_FORMATS = {name: f".{name}" for name in (
    "dng", "cr2", "cr3", "crw", "nef", "nrw", "arw", "srf", "sr2", "raf", "orf", "rw2", "raw", "rwl", "pef", "ptx",
    "srw", "3fr", "fff", "iiq", "mos", "mef", "mrw", "x3f", "erf", "kdc", "dcr", "k25")}
# A real body, when the profile says nothing of its own: shutter to file ready (an EOS M10 takes about 1 s), and the
# RAW file over USB 2.
READOUT_S = 1.0
TRANSFER_BYTES_PER_S = 30e6
DNG_BYTES_PER_PX = 2  # benchctl's DNGs (and a bound for a camera's RAW): 16 bits a pixel, uncompressed
PREVIEW_WIDTH = 960  # pixels across a live-view frame unless the caller asks for another size
Window = tuple[int, int, int, int]  # (top, left, rows, cols) of the sensor's active area


@dataclass(frozen=True)
class RawFrame:
    """One RAW file as the camera delivered it, never modified, plus what is known about the capture."""

    data: bytes
    format: str  # "dng" | "cr2" | "cr3"
    file_name: str  # the camera's own name for it, e.g. IMG_0042.DNG
    metadata: dict[str, Any] = field(default_factory=dict)  # exposure_s, iso, captured_at, camera, ...
    path: Path | None = None  # where it was saved, once it was

    @property
    def suffix(self) -> str:
        return RAW_FORMATS.get(self.format, ".raw")


@dataclass(frozen=True)
class FrameSize:
    """One RAW frame of a profile's camera as its driver expects it before any camera is opened (estimates of a
    run's time, disk and memory): its pixels, its file's bytes and the seconds one capture takes."""

    rows: int
    cols: int
    file_bytes: int
    seconds: float  # shutter release to the file saved: exposure, readout, transfer (the simulator's rendering)
    what: str  # what the figures rest on, for people


@dataclass(frozen=True)
class PreviewFrame:
    """One live-view frame, for watching the bench (alignment, focus, exposure), never saved as a measurement.

    data: an image file as the camera gives it: a JPEG (`format` "jpeg": a body's processed live view, sRGB) or a
    RAW file (a format of RAW_FORMATS, decoded like a capture). window: the part of the sensor's active area it
    shows, (top, left, rows, cols); None: all of it. full_shape: (rows, cols) of the active area where the camera
    knows it, so that overlays in sensor coordinates can be placed on the frame.
    """

    data: bytes
    format: str
    window: Window | None = None
    full_shape: tuple[int, int] | None = None
    metadata: dict[str, Any] = field(default_factory=dict)


def real_frame(profile: Profile, rows: int, cols: int, readout_s: float, pixels_per_s: float, what: str) -> FrameSize:
    """A camera's frame of rows x cols pixels, captured in the profile's exposure (else its [sim.sensor]'s) plus
    `readout_s` plus its transfer at `pixels_per_s`, saved as a 16-bit DNG (a bound for a camera's own RAW)."""
    exposure = (profile.camera.exposure_s if profile.camera else None) or profile.sim.sensor.exposure_s
    return FrameSize(rows, cols, DNG_BYTES_PER_PX * rows * cols, exposure + readout_s + rows * cols / pixels_per_s,
                     what)


class Camera(Connection):
    """A camera built from the profile's [camera] section; a context manager (open on enter, close on exit)."""

    driver: str
    windowed_preview: ClassVar[bool] = False
    """Whether `preview` gives the window and size it is asked for; else it gives the whole frame at the size the
    camera has, and the caller crops and scales it."""

    def __init__(self, config: CameraConfig) -> None:
        self.config = config

    @classmethod
    def for_profile(cls, profile: Profile) -> Camera:
        """This driver for `profile`'s [camera] section, not yet connected; drivers that need more of the profile
        (the simulated bench) override it."""
        config = profile.require("camera").camera
        assert config is not None
        return cls(config)

    @classmethod
    def frame_size(cls, profile: Profile) -> FrameSize:
        """One RAW frame of this driver's camera as `profile` describes it, without the camera. Default, for a body
        whose sensor the profile's [camera] section does not give: the sensor [sim.sensor] describes (an EOS M10's
        unless set), 16 bits a pixel, the profile's exposure plus READOUT_S plus the file over USB 2; drivers whose
        section says more override it."""
        rows, cols = profile.sim.sensor.shape
        return real_frame(profile, rows, cols, READOUT_S, TRANSFER_BYTES_PER_S / DNG_BYTES_PER_PX,
                          f"camera {cls.driver}'s {rows * cols / 1e6:.3g} Mpx (its sensor as [sim.sensor] shape "
                          f"says)")

    def _device_lock(self) -> DeviceLock:
        return DeviceLock(f"camera:{self.driver}:{self.config.usb_id}", f"camera ({self.driver} {self.config.usb_id})")

    @abstractmethod
    def _open(self) -> None:
        """Connect (find the device, open a session)."""

    @abstractmethod
    def _close(self) -> None:
        """Disconnect; must not raise for a device that is already gone."""

    def ground_truth_homography(self) -> np.ndarray | None:
        """Where the bench truly images the SLM grid on the sensor (3x3, target-plane pixels -> sensor pixels),
        as far as the device knows: a simulated camera knows what registration should find; a real one does
        not (None), since only registration can measure it."""
        return None

    @abstractmethod
    def _identity(self) -> dict[str, str]:
        """Manufacturer, model, serial number, firmware as far as the camera tells."""

    @abstractmethod
    def _capture_one(self) -> RawFrame:
        """Release the shutter once and return the RAW file the camera produced (the camera keeps its own copy until
        `_saved`)."""

    def _saved(self, frame: RawFrame) -> None:  # noqa: B027 (an optional hook, not abstract)
        """`frame` is safe on disk (or, for a preview, not wanted): the camera may drop its own copy now. Default:
        nothing to drop."""

    def _preview(self, width: int, window: Window | None) -> PreviewFrame:
        """One live-view frame. Default, for cameras without a live view: a RAW capture of the whole frame, which
        the caller decodes and reduces (slow, but every camera can do it), not kept on the camera either (a preview
        is not a measurement); drivers with a faster view override."""
        frame = self._capture_one()
        self._saved(frame)
        return PreviewFrame(frame.data, frame.format, metadata=frame.metadata)

    def _apply_settings(self, exposure_s: float | None, iso: int | None) -> None:
        """Write exposure time / ISO to the camera; drivers that can override this."""
        raise BadValueError(f"the {self.driver} camera driver cannot set exposure or ISO; set them on the camera")

    def open(self) -> Camera:
        """Connect (no-op if open); returns self. Applies exposure / ISO only where the profile allows it."""
        if self.is_open:
            return self
        super().open()
        wanted = (self.config.exposure_s, self.config.iso)
        if self.config.write_properties and any(v is not None for v in wanted):
            try:
                self._apply_settings(*wanted)
            except BaseException:
                self.close()  # no `with` block owns the camera yet
                raise
        return self

    def identity(self) -> dict[str, str]:
        """What the camera says it is, plus the driver name."""
        self._require_open()
        return {"driver": self.driver, **self._identity()}

    def preview(self, width: int = PREVIEW_WIDTH, window: Window | None = None) -> PreviewFrame:
        """One live-view frame about `width` pixels wide, of `window` of the active area (None: the whole frame)
        where the driver can (`windowed_preview`). Nothing is saved; call it again for the next frame."""
        self._require_open()
        if width < 1:
            raise BadValueError(f"preview width must be >= 1 pixel, got {width}")
        return self._preview(width, window)

    def capture(self, destination: Path | None = None, frames: int | None = None,
                stem: str = "frame") -> list[RawFrame]:
        """Capture `frames` RAW frames (default: the profile's `frames`), each saved to `destination` (a folder)
        as `<stem>-<n>.<ext>` the moment it arrives, before the next shutter release. An existing file of that
        name is never replaced (BenchctlError naming it). With no destination the frames are only in memory, and
        the camera keeps its own copy of each."""
        return list(self.captures(destination, frames, stem))

    def captures(self, destination: Path | None = None, frames: int | None = None,
                 stem: str = "frame") -> Iterator[RawFrame]:
        """`capture`, one frame at a time: each is saved (and the camera's copy dropped) before it is yielded, so
        a caller that keeps only what it needs of each holds one frame in memory however many it captures."""
        self._require_open()
        count = self.config.frames if frames is None else frames
        if count < 1:
            raise BadValueError(f"frames must be >= 1, got {count}")
        if destination is not None:
            ensure_dir(Path(destination))
        for index in range(count):
            frame = self._capture_one()
            if destination is not None:
                path = atomic_write_bytes(Path(destination) / f"{stem}-{index:03d}{frame.suffix}", frame.data,
                                          overwrite=False)
                frame = RawFrame(frame.data, frame.format, frame.file_name, frame.metadata, path)
                self._saved(frame)
            yield frame

    def _require_open(self) -> None:
        if not self._open_now:
            raise DeviceError(f"{self.driver} camera is not open")

