"""From decoded captures to a scored colour image: each colour's CFA plane registered onto the target's ROI,
the colours balanced and merged, and scored against the target like the simulated reconstruction.

Each colour is exposed alone, so a capture of colour c is read from the sensor pixels with colour-c filters
only: one CFA position for red and blue, two for green. Every position is warped onto the ROI with its own
plane homography (`registration.plane_homography`), so the two greens, half a pixel apart diagonally, land
where they belong and are then averaged.

Captured and simulated colours are merged the same way (`merge_colours`, which the simulated reconstruction of
`holograms.scene.compute_scene` uses too): each colour's amplitude (captured: sqrt of the linear signal) scaled
by least squares against that colour's target amplitude (the colour balance the paper sets with laser powers,
here measured: each plane's gain is recorded), the merged linear image being the scaled amplitudes squared,
clipped to 0..1 (colours not present stay 0); then `amplitude_scores` per colour and `colour_scores` merged.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
import torch

from benchctl.capture.exposure import PEAK_PERCENTILE
from benchctl.capture.raw import RawImage
from benchctl.capture.registration import cfa_planes, plane_homography, warp_to_roi
from benchctl.errors import BenchctlError
from benchctl.optics import amplitude_scores, colour_scores, lsq_scale

COLOUR_NAMES = ("red", "green", "blue")
LOW_SIGNAL = 0.05
"""A plane whose 99.9th-percentile signal on the ROI is below this fraction of full scale is under-exposed:
its amplitude carries visible shot and read noise (warned about, not refused)."""


def registered_plane(raw: RawImage, colour: int, homography: np.ndarray, shape: tuple[int, int],
                     roi: tuple[int, int]) -> np.ndarray:
    """(roi_h, roi_w) float32 linear signal of `colour`'s CFA plane(s) (0 R, 1 G, 2 B) sampled at every pixel of
    the centred ROI of a target plane of `shape`; `homography` maps target pixels to active-area mosaic pixels."""
    warped = [warp_to_roi(plane, plane_homography(homography, offset), shape, roi)
              for plane, offset in cfa_planes(raw.mosaic, raw.cfa, colour)]
    return np.stack(warped).mean(axis=0, dtype=np.float32) if len(warped) > 1 else warped[0]


def registered_saturation(raw: RawImage, colour: int, homography: np.ndarray, shape: tuple[int, int],
                          roi: tuple[int, int]) -> np.ndarray:
    """(roi_h, roi_w) bool: ROI pixels whose registered `colour` value draws on a saturated sensor pixel."""
    touched = [warp_to_roi(clipped, plane_homography(homography, offset), shape, roi) > 0
               for clipped, offset in cfa_planes(raw.saturated.astype(np.float32), raw.cfa, colour)]
    return np.logical_or.reduce(touched)


def roi_saturation(raw: RawImage, colour: int, homography: np.ndarray, shape: tuple[int, int],
                   roi: tuple[int, int]) -> float:
    """Fraction of the ROI whose registered `colour` value draws on a saturated sensor pixel (for merge_capture)."""
    return float(registered_saturation(raw, colour, homography, shape, roi).mean())


def captured_amplitude(signal: np.ndarray) -> torch.Tensor:
    """The amplitude of a registered plane's linear signal: its square root, the noise below 0 clipped."""
    return torch.from_numpy(np.sqrt(np.clip(np.asarray(signal, dtype=np.float32), 0.0, None)))


@dataclass
class MergedColours:
    """Colours balanced and merged (keys are plane indices 0 R, 1 G, 2 B): amplitude (3, h, w), each colour scaled
    by its least-squares gain against the target (0 for the colours not given); linear: its square clipped to
    0..1, the merged image; gains: each colour's amplitude gain (intensity gain = gain^2)."""

    amplitude: torch.Tensor
    linear: torch.Tensor
    gains: dict[int, float]


def merge_colours(amplitudes: Mapping[int, torch.Tensor], target_roi: torch.Tensor,
                  region: torch.Tensor | None = None) -> MergedColours:
    """Balance and merge amplitudes (colour -> (h, w)) against the target amplitude on the ROI (3, h, w); with
    `region` ((h, w) bool: a focal-stack plane's in-focus region) each gain is fitted there only, where the
    capture is meant to match the target."""
    amplitude = torch.zeros_like(target_roi)
    gains: dict[int, float] = {}
    inside = None if region is None else region.to(target_roi.dtype)
    for colour, measured in sorted(amplitudes.items()):
        gain = (lsq_scale(measured, target_roi[colour]) if inside is None
                else lsq_scale(measured * inside, target_roi[colour] * inside))
        amplitude[colour] = measured * gain
        gains[colour] = float(gain)
    return MergedColours(amplitude, amplitude.square().clamp(0, 1), gains)


@dataclass
class MergedCapture:
    """Captured colours registered, balanced, merged (`merged`) and scored: each captured colour's
    `amplitude_scores` (scores), `colour_scores` of the merged image (merged_scores), and warnings (lines)."""

    merged: MergedColours
    scores: dict[int, dict[str, float]]
    merged_scores: dict[str, float]
    warnings: list[str] = field(default_factory=list)


def capture_warnings(planes: Mapping[int, np.ndarray], target_roi: torch.Tensor,
                     saturation: Mapping[int, float] | None = None, *, low_signal: float = LOW_SIGNAL) -> list[str]:
    """What is wrong with registered planes (colour -> (h, w) linear signal) as a capture of the target amplitude
    (3, h, w): a colour under-exposed or saturated (`roi_saturation`), a colour of the target not captured; a plane
    of the wrong colour index or shape is an error."""
    if target_roi.dim() != 3 or target_roi.shape[0] != 3:
        raise BenchctlError(f"target ROI must be (3, h, w) amplitude, got shape {tuple(target_roi.shape)}")
    warnings: list[str] = []
    for colour, signal in sorted(planes.items()):
        if colour not in (0, 1, 2):
            raise BenchctlError(f"colour plane {colour} is not 0 (red), 1 (green) or 2 (blue)")
        name = COLOUR_NAMES[colour]
        if np.shape(signal) != tuple(target_roi.shape[1:]):
            raise BenchctlError(f"{name} plane is {np.shape(signal)}, the target ROI is {tuple(target_roi.shape[1:])}")
        peak = float(np.percentile(signal, PEAK_PERCENTILE))
        if peak < low_signal:
            warnings.append(f"{name}: low signal, peak {peak:.1%} of full scale (below {low_signal:.0%}): "
                            "expose longer or raise the laser power")
        clipped = (saturation or {}).get(colour, 0.0)
        if clipped > 0:
            warnings.append(f"{name}: {clipped:.2%} of the ROI is saturated; that colour reads low there")
    missing = [COLOUR_NAMES[c] for c in range(3) if c not in planes and float(target_roi[c].max()) > 0]
    if missing:
        warnings.append(f"not captured: {', '.join(missing)} (present in the target; scored as black)")
    return warnings


def merge_capture(planes: Mapping[int, np.ndarray], target_roi: torch.Tensor,
                  saturation: Mapping[int, float] | None = None, *, low_signal: float = LOW_SIGNAL) -> MergedCapture:
    """Balance, merge and score registered planes (colour -> (h, w) linear signal, full scale 1) against the
    target amplitude on the ROI (3, h, w). saturation: per colour, the fraction of ROI pixels touched by clipped
    sensor pixels (`roi_saturation`), warned about when above 0."""
    target = torch.as_tensor(target_roi, dtype=torch.float32)
    warnings = capture_warnings(planes, target, saturation, low_signal=low_signal)
    amplitudes = {colour: captured_amplitude(signal) for colour, signal in sorted(planes.items())}
    merged = merge_colours(amplitudes, target)
    scores = {colour: amplitude_scores(merged.amplitude[colour], target[colour]) for colour in amplitudes}
    return MergedCapture(merged, scores, colour_scores(merged.linear, target), warnings)
