"""SLM gray -> phase calibration from the camera: binary gratings and their zero order.

Method. The SLM shows a binary grating of period 2 px: columns alternate gray 0 and gray g. Its field is
periodic with two values, so it diffracts into a zero order (the mean field) and first orders at +-Nyquist
(the half-difference of the two values). The relay's Fourier iris (radius 0.5 x Nyquist in the default
profile) blocks +-Nyquist; without an iris they leave at sin(theta) = lambda / (2 pitch), far outside the central
target region. What reaches the target plane is the zero order: the SLM's aperture lit with amplitude
|mean field|, one fixed pattern whose brightness follows |m|^2.

With the pixel model field = (1 - f) e^{i phase} + f (f: unmodulated light from the pixel gaps) and phase(0) = 0
(the table's reference, as a measured table defines it), write d = phase(g) - phase(0). The mean field is
    m = (1 - f) (1 + e^{i d}) / 2 + f = e^{i d/2} (1 - f) cos(d/2) + f,
    |m|^2 = (1 - f)^2 cos^2(d/2) + 2 f (1 - f) cos(d/2) Re e^{i d/2} + f^2
          = ((1 - f)^2 + 2 f (1 - f)) cos^2(d/2) + f^2 = (1 - f^2) cos^2(d/2) + f^2
          = (1 + f^2)/2 + (1 - f^2)/2 cos d,
so the signal is exactly I(g) = a + b cos d(g) for any leakage f (with gray 0 at phase 0; were gray 0's phase
p0 != 0 relative to the gap light, a term 2 f (1 - f) cos(d/2) (cos(p0 + d/2) - cos(d/2)) of order f would
remain: f = 0.02 would bend the curve by up to ~4 % of its span). Camera offsets (black level residue, stray
light) only change a.

Inversion. I(0) is the top of the curve (d = 0) and its first minimum is d = pi, so
    cos d = (2 I - I(0) - I(pi)) / (I(0) - I(pi)).
The minimum is located and its value refined by a parabola through the three samples around it (the sampled
minimum lies up to half a step beyond the true one). acos gives d modulo the branch; phase(g) is increasing, so
every extremum of I passed marks one more multiple of pi: on branch k (k extrema passed), d = k pi + acos(c) for
even k, (k + 1) pi - acos(c) for odd k. Extrema are found with hysteresis (a turn counts once the signal has
come back by TURN_HYSTERESIS of the curve's span), each split at its parabola's vertex. A panel whose depth is
below pi never reaches the minimum, so the curve cannot be normalised: that is an error, not a guess.

Only a subset of gray levels is measured (`calibration_grays`: every 8th and the last); `lut_from_response`
makes the phases non-decreasing (isotonic regression: noise near the flat extrema can reverse neighbours) and
interpolates them to every level with a monotone cubic (PCHIP), phase(0) = 0.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from benchctl.capture.colour_planes import registered_plane, registered_saturation
from benchctl.capture.raw import RawImage
from benchctl.capture.registration import cfa_planes
from benchctl.errors import BenchctlError
from benchctl.optics import PhaseLUT
from benchctl.optics.metrics import centred_slices

DEFAULT_STEP = 8
"""Gray levels between measured gratings (plus the last level)."""
CENTRAL_FRACTION = 0.5
"""Sides of the central region whose mean is the zero-order signal, as a fraction of the SLM grid's sides (or
of the sensor's): away from the edges of the SLM's image."""
TURN_HYSTERESIS = 0.05
"""A turn of the curve counts once the normalised signal (span -1..1) has come back this far from its extreme."""
EXTREMUM_MARGIN = 0.2
"""A turn is an extremum only within this of -1 (minimum) or +1 (maximum) in the normalised signal."""
MIN_CONTRAST = 0.5
"""(I(0) - min I) / I(0) below this: the gratings barely modulate the zero order (first orders not blocked, or
no light), so no phase can be read."""


class CalibrationError(BenchctlError):
    """A lookup-table calibration that cannot be made from the measurements; the message says why, with numbers."""


def calibration_grays(bit_depth: int = 8, step: int = DEFAULT_STEP) -> list[int]:
    """Gray levels to measure: 0, step, 2 step, ... and the last level 2^bit_depth - 1."""
    if not 1 <= bit_depth <= 16 or step < 1:
        raise CalibrationError(f"calibration grays need bit depth 1..16 and step >= 1, got {bit_depth} and {step}")
    last = (1 << bit_depth) - 1
    grays = list(range(0, last + 1, step))
    return grays if grays[-1] == last else grays + [last]


def grating_frame(shape: tuple[int, int], gray: int, period_px: int = 2, bit_depth: int = 8) -> np.ndarray:
    """The gray frame to display: vertical stripes, each period's first half at gray 0 and second half at `gray`
    (period 2: even columns 0, odd columns gray). uint8 up to 8 bit, uint16 above (the SLM's gray dtype).

    Its first orders leave at (2 / period_px) x Nyquist: the iris must block them (period 2 with an iris below
    1 x Nyquist), or the central region sees them too.
    """
    levels = 1 << bit_depth
    if not 0 <= gray < levels:
        raise CalibrationError(f"gray {gray} is outside 0..{levels - 1} for a {bit_depth}-bit SLM")
    if period_px < 2 or period_px % 2:
        raise CalibrationError(f"grating period must be an even number of pixels >= 2, got {period_px}")
    frame = np.zeros(shape, dtype=np.uint8 if bit_depth <= 8 else np.uint16)
    lit = (np.arange(shape[1]) % period_px) >= period_px // 2
    frame[:, lit] = gray
    return frame


def zero_order_signal(raw: RawImage, colour: int, homography: np.ndarray | None = None,
                      shape: tuple[int, int] | None = None, fraction: float = CENTRAL_FRACTION) -> float:
    """Mean linear signal of `colour`'s CFA plane(s) over the central `fraction` (per side) of the lit area.

    With a registration (`homography`, target plane -> active-area mosaic, and the SLM grid's `shape`): the
    central part of the SLM's image. Without one: the central part of the sensor's active area, which works
    wherever the camera is aimed at the SLM's image: the zero order lights the whole image of the SLM with one
    fixed pattern times |mean field|^2, so any region's mean follows a + b cos d, and unlit pixels only add
    noise to a. Saturated pixels in the region are an error: they read low.
    """
    if homography is not None:
        if shape is None:
            raise CalibrationError("zero_order_signal: a homography needs the SLM grid's shape")
        inner = (max(1, round(shape[0] * fraction)), max(1, round(shape[1] * fraction)))
        signal = registered_plane(raw, colour, homography, shape, inner)
        clipped = registered_saturation(raw, colour, homography, shape, inner)
    else:
        planes = cfa_planes(raw.mosaic, raw.cfa, colour)
        masks = cfa_planes(raw.saturated, raw.cfa, colour)
        h, w = planes[0][0].shape
        central = centred_slices((h, w), (max(1, round(h * fraction)), max(1, round(w * fraction))))
        signal = np.stack([plane[central] for plane, _ in planes])
        clipped = np.stack([mask[central] for mask, _ in masks])
    if clipped.any():
        raise CalibrationError(f"{_name(raw)}: {clipped.mean():.1%} of the measured region is saturated; lower "
                               "the exposure or the laser power (the gray-0 grating is the brightest)")
    return float(signal.mean())


def _name(raw: RawImage) -> str:
    """Short name of a capture for messages."""
    return raw.source if len(raw.source) < 60 else raw.source[:57] + "..."


def _checked_grays(grays: ArrayLike, values: ArrayLike, what: str) -> tuple[np.ndarray, np.ndarray]:
    g = np.asarray(grays, dtype=np.float64)
    v = np.asarray(values, dtype=np.float64)
    if g.ndim != 1 or g.shape != v.shape or len(g) < 3:
        raise CalibrationError(f"need matching 1-D lists of at least 3 grays and {what}, got {g.shape} and {v.shape}")
    if g[0] != 0 or (np.diff(g) <= 0).any():
        raise CalibrationError(f"grays must start at 0 (the reference) and increase, got {list(map(int, g[:5]))}...")
    if not np.isfinite(v).all():
        raise CalibrationError(f"{what} contain NaN or infinite values")
    return g, v


def _vertex(x: np.ndarray, y: np.ndarray, k: int) -> tuple[float, float]:
    """(position, value) of the parabola through samples k - 1, k, k + 1; sample k itself where that fails."""
    if k == 0 or k == len(x) - 1:
        return float(x[k]), float(y[k])
    a, b, c = np.polyfit(x[k - 1:k + 2] - x[k], y[k - 1:k + 2], 2)
    if a == 0:
        return float(x[k]), float(y[k])
    offset = -b / (2 * a)
    if not x[k - 1] - x[k] <= offset <= x[k + 1] - x[k]:
        return float(x[k]), float(y[k])
    return float(x[k] + offset), float(c - b * b / (4 * a))


def _turns(c: np.ndarray) -> list[int]:
    """Sample indices where a curve starting downwards turns (minima, maxima, alternately), with hysteresis."""
    turns, direction, best = [], -1, 0
    for k in range(1, len(c)):
        if direction * (c[k] - c[best]) > 0:
            best = k
        elif direction * (c[best] - c[k]) > TURN_HYSTERESIS:
            turns.append(best)
            direction, best = -direction, k
    return turns


def phase_response(grays: ArrayLike, signals: ArrayLike) -> np.ndarray:
    """Phase difference d(g) = phase(g) - phase(0) in radians at the measured grays (which start at 0 and
    increase), from their gratings' zero-order signals, unwrapped (module docstring)."""
    g, signal = _checked_grays(grays, signals, "signals")
    top, bottom = signal[0], signal.min()
    if not top > 0 or (top - bottom) / top < MIN_CONTRAST:
        raise CalibrationError(
            f"the zero-order signal barely changes with gray level ({top:.4g} at gray 0, minimum {bottom:.4g}; "
            f"contrast {(top - bottom) / top if top > 0 else 0:.2f} < {MIN_CONTRAST}): no light, or the grating's "
            "first orders reach the measured region (is the Fourier iris in place?)")
    normalised = (2 * signal - top - bottom) / (top - bottom)
    turns = _turns(normalised)
    if not turns:
        raise CalibrationError(
            f"the zero-order signal falls from {top:.4g} at gray 0 to {signal[-1]:.4g} at gray {int(g[-1])} without "
            "reaching a minimum: the phase depth is below pi at this wavelength, so the curve cannot be normalised "
            "(measure up to the last gray level, or use a shorter wavelength)")
    for number, k in enumerate(turns):
        expected = -1.0 if number % 2 == 0 else 1.0
        if normalised[k] * expected < 1 - EXTREMUM_MARGIN:
            kind = "minimum" if expected < 0 else "maximum"
            raise CalibrationError(
                f"the zero-order signal turns at gray {int(g[k])} at {normalised[k]:+.2f} of its span, too far from "
                f"its {kind} ({expected:+.0f}) to be a multiple of pi: noisy signal or a non-monotonic response")
    vertices = [_vertex(g, signal, k) for k in turns]
    low = float(np.mean([value for number, (_, value) in enumerate(vertices) if number % 2 == 0]))
    cosine = np.clip((2 * signal - top - low) / (top - low), -1.0, 1.0)
    base = np.arccos(cosine)
    branch = np.searchsorted([position for position, _ in vertices], g, side="right")
    return np.where(branch % 2 == 0, branch * math.pi + base, (branch + 1) * math.pi - base)


def _isotonic(values: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Least-squares non-decreasing fit (pool adjacent violators)."""
    weights = np.ones(len(values)) if weights is None else weights
    means, sizes, counts = [], [], []
    for value, weight in zip(values, weights):
        means.append(float(value))
        sizes.append(float(weight))
        counts.append(1)
        while len(means) > 1 and means[-2] > means[-1]:
            total = sizes[-2] + sizes[-1]
            means[-2] = (means[-2] * sizes[-2] + means[-1] * sizes[-1]) / total
            sizes[-2], counts[-2] = total, counts[-2] + counts[-1]
            del means[-1], sizes[-1], counts[-1]
    return np.repeat(means, counts)


def _pchip(x: np.ndarray, y: np.ndarray, at: np.ndarray) -> np.ndarray:
    """Monotone piecewise-cubic Hermite interpolation (Fritsch-Carlson slopes, as scipy's PchipInterpolator)."""
    h = np.diff(x)
    delta = np.diff(y) / h
    slope = np.zeros(len(x))
    w1, w2 = 2 * h[1:] + h[:-1], h[1:] + 2 * h[:-1]
    same = delta[:-1] * delta[1:] > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        harmonic = (w1 + w2) / (w1 / delta[:-1] + w2 / delta[1:])
    slope[1:-1] = np.where(same, harmonic, 0.0)
    for end, (h0, h1, d0, d1) in ((0, (h[0], h[1], delta[0], delta[1])), (-1, (h[-1], h[-2], delta[-1], delta[-2]))):
        s = ((2 * h0 + h1) * d0 - h0 * d1) / (h0 + h1) if len(h) > 1 else d0
        if np.sign(s) != np.sign(d0):
            s = 0.0
        elif np.sign(d0) != np.sign(d1) and abs(s) > 3 * abs(d0):
            s = 3 * d0
        slope[end] = s
    k = np.clip(np.searchsorted(x, at, side="right") - 1, 0, len(x) - 2)
    t = (at - x[k]) / h[k]
    return ((2 * t**3 - 3 * t**2 + 1) * y[k] + (t**3 - 2 * t**2 + t) * h[k] * slope[k]
            + (-2 * t**3 + 3 * t**2) * y[k + 1] + (t**3 - t**2) * h[k] * slope[k + 1])


def lut_from_response(grays: ArrayLike, phases: ArrayLike, bit_depth: int) -> PhaseLUT:
    """The full lookup table (every level of a `bit_depth`-bit SLM) from phases measured at `grays` (from 0 to
    the last level): shifted so phase(0) = 0, made non-decreasing, interpolated monotonically (PCHIP)."""
    g, phase = _checked_grays(grays, phases, "phases")
    last = (1 << bit_depth) - 1
    if g[-1] != last:
        raise CalibrationError(f"measured grays end at {int(g[-1])}; a {bit_depth}-bit table needs gray {last} "
                               "measured (no extrapolation)")
    monotone = _isotonic(phase - phase[0])
    table = _pchip(g, monotone, np.arange(last + 1, dtype=np.float64))
    table = np.maximum.accumulate(table - table[0])  # rounding only: PCHIP of monotone data is monotone
    return PhaseLUT(table)


def calibrate_lut(grays: ArrayLike, signals: ArrayLike, bit_depth: int) -> PhaseLUT:
    """The lookup table measured by gratings at `grays` with these zero-order signals (phase_response, then
    lut_from_response)."""
    return lut_from_response(grays, phase_response(grays, signals), bit_depth)
