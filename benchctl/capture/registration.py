"""Camera-SLM registration: where each target-plane pixel lands on the camera sensor.

The camera images the target plane through lenses (and perhaps mirrors), so one 3x3 homography H maps
target-plane pixel coordinates (x = column, y = row of the SLM grid, pixel centres at integers) to coordinates
in the sensor's ACTIVE AREA (the visible mosaic `decode_raw` returns; the frame of the simulator's
`camera_homography`). It is measured by displaying a hologram of a dot grid, finding the dots in the capture and
fitting H with RANSAC (`cv2.findHomography`), then used to sample captures onto the target's ROI (`warp_to_roi`).

The dot grid (`dot_grid_target`): grid = (rows, cols) dots, 12 x 21 by default (the reference project's
21 x 12), one antialiased disc at the centre of each cell of a regular division of the centred ROI. The dot of
the top-left cell (row 0, col 0) is left out: the MARKER. A full rectangular grid looks the same after a
180-degree turn and after either mirror (an SLM flip, a mirror in the relay), so its dots could be matched in
four ways; each of those maps the missing corner onto a different corner, so the marker leaves one. Target
points are listed row by row from the top, left to right, the marker skipped: point k is dot (row, col) with
k = row * cols + col - 1, N = rows * cols - 1 points.

Detection (`find_dots`) assumes nothing about scale, turn or mirror: the dot spacing is the distance of the
strongest off-centre peak of the image's autocorrelation; the image is smoothed at a tenth of that, dots are its
local maxima (one per spacing-sized window) at least a quarter as high as the typical dot, each refined to the
centroid of its upper half; the lattice's two step vectors come from the dots' nearest neighbours, every dot gets
integer lattice indices from an affine fit (refined twice; spots off the lattice are dropped), the rows x cols
window holding the most dots is the grid (either way round, so a quarter turn is recognised when rows != cols),
and the one empty corner says which corner is the marker. Dots not found come back as NaN.

Coordinates: a CFA plane of the mosaic, the 2x2 cell position (dy, dx), has plane pixel (i, j) at mosaic pixel
(2 i + dy, 2 j + dx); `plane_homography` turns H into the homography onto that plane.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import torch

from benchctl.capture.raw import MONO, RawImage
from benchctl.errors import BadValueError, BenchctlError
from benchctl.optics.metrics import centred_slices

DEFAULT_GRID = (12, 21)
"""(rows, cols) of the dot grid: the reference project's 21 x 12."""

RANSAC_TARGET_PX = 2.0
"""RANSAC inlier distance in target-plane pixels (times the camera's scale in sensor pixels)."""
MAX_RMS_TARGET_PX = 1.0
"""A fit whose RMS reprojection error (inliers) is above this many target-plane pixels is refused. Limits are
in target-plane pixels so that they hold at any magnification. Measured on the simulated bench: dot centres
scatter by 0.1-0.65 px around the true geometry with an uncalibrated SLM (its phase errors distort the dots'
images, most for DPAC in red and GS in blue), by 0.03-0.1 px with a calibrated one; a wrong match is off by about
a dot spacing (8 px on the test grids, 73 px on the default bench)."""
MIN_INLIER_FRACTION = 0.8
"""A fit explaining fewer of the points than this is refused."""
MIN_POINTS = 8
"""Fewest point pairs a fit is attempted with (a homography has 8 degrees of freedom)."""
MAX_ANISOTROPY = 1.5
"""Largest ratio of the two scales of H's linear part at the points' centre (a bench does not shear)."""
MAX_PERSPECTIVE = 1.2
"""Largest ratio of H's projective divisor w across the points (a bench is nearly affine)."""
MIN_FOUND_FRACTION = 0.75
"""find_dots needs at least this fraction of the grid's dots (missing ones come back as NaN)."""
ON_LATTICE = 0.25
"""A spot belongs to the lattice when both its fractional lattice indices are within this of integers."""
LATTICE_CONTRAST = 0.2
"""Autocorrelation peak at one dot spacing, relative to the centre, below which an image shows no grid (dot
grids on the simulated bench: 0.9; a dark frame: 0.03)."""


class RegistrationError(BenchctlError):
    """Dots not found, or a fit that is clearly wrong; the message gives the numbers that failed."""


# -- the pattern ------------------------------------------------------------------------------------------------


def _dot_spacing(roi: tuple[int, int], grid: tuple[int, int]) -> tuple[float, float]:
    """(rows, cols) pixels between neighbouring dot centres."""
    return roi[0] / grid[0], roi[1] / grid[1]


def dot_grid_target(shape: tuple[int, int], roi: tuple[int, int], grid: tuple[int, int] = DEFAULT_GRID,
                    radius_px: float | None = None) -> tuple[torch.Tensor, np.ndarray]:
    """The registration pattern: target amplitude (H, W) float32 (1 in the dots, 0 elsewhere and outside the
    centred ROI) and its dot centres (N, 2) float64 as (x = col, y = row), in the order of the module docstring.

    radius_px: dot radius in target-plane pixels; default a quarter of the smaller spacing, so dots are half a
    spacing apart (the hologram's blur and the camera's noise cannot join them).
    """
    rows, cols = int(grid[0]), int(grid[1])
    if rows < 3 or cols < 3:
        raise BadValueError(f"a dot grid needs at least 3 x 3 dots, got {rows} x {cols}")
    row_slice, col_slice = centred_slices(shape, roi)
    step_y, step_x = _dot_spacing(roi, (rows, cols))
    radius = 0.25 * min(step_y, step_x) if radius_px is None else float(radius_px)
    if not 0.5 <= radius <= 0.5 * min(step_y, step_x) - 1.0:
        raise BadValueError(f"dot radius {radius:.3g} px does not fit a {rows} x {cols} grid in a {roi[0]} x "
                            f"{roi[1]} ROI (spacing {step_y:.3g} x {step_x:.3g} px): it must lie in 0.5 .. "
                            f"{0.5 * min(step_y, step_x) - 1.0:.3g} px")
    top, left = row_slice.start - 0.5, col_slice.start - 0.5  # edges of the ROI's first pixel
    centre_y = top + (np.arange(rows) + 0.5) * step_y
    centre_x = left + (np.arange(cols) + 0.5) * step_x

    # Every pixel belongs to one cell and only that cell's dot can reach it (radius < half a spacing).
    y = np.arange(shape[0], dtype=np.float64)
    x = np.arange(shape[1], dtype=np.float64)
    cell_row = np.clip(np.floor((y - top) / step_y), 0, rows - 1).astype(int)
    cell_col = np.clip(np.floor((x - left) / step_x), 0, cols - 1).astype(int)
    distance = np.hypot((y - centre_y[cell_row])[:, None], (x - centre_x[cell_col])[None, :])
    amplitude = np.clip(radius + 0.5 - distance, 0.0, 1.0)  # antialiased edge, one pixel wide
    marker = np.zeros(amplitude.shape, dtype=bool)
    marker[np.ix_(cell_row == 0, cell_col == 0)] = True
    amplitude[marker] = 0.0
    outside = np.ones(amplitude.shape, dtype=bool)
    outside[row_slice, col_slice] = False
    amplitude[outside] = 0.0

    grid_x, grid_y = np.meshgrid(centre_x, centre_y)
    points = np.stack([grid_x.ravel(), grid_y.ravel()], axis=1)[1:]  # drop (row 0, col 0), the marker
    return torch.from_numpy(amplitude.astype(np.float32)), points


# -- finding the dots -------------------------------------------------------------------------------------------


def _spacing(image: np.ndarray) -> tuple[float, float]:
    """Distance between neighbouring dots, from the strongest peak of the image's autocorrelation away from the
    centre, and that peak's height relative to the centre's (near 0 where the image shows no lattice)."""
    factor = max(1, math.ceil(max(image.shape) / 1024))  # enough resolution for the dots, at FFT cost ~1 M px
    small = image if factor == 1 else cv2.resize(image, (image.shape[1] // factor, image.shape[0] // factor),
                                                 interpolation=cv2.INTER_AREA)
    small = small - np.float32(np.median(small))
    spectrum = np.fft.rfft2(small)
    correlation = np.fft.fftshift(np.fft.irfft2(np.abs(spectrum) ** 2, s=small.shape)).astype(np.float32)
    centre = np.array(small.shape) // 2
    peaks = correlation == cv2.dilate(correlation, np.ones((3, 3), np.uint8))
    rows, cols = np.nonzero(peaks)
    away = np.hypot(rows - centre[0], cols - centre[1]) >= 2
    if not away.any() or correlation[tuple(centre)] <= 0:
        return math.nan, 0.0
    best = np.argmax(np.where(away, correlation[rows, cols], -np.inf))
    distance = math.hypot(rows[best] - centre[0], cols[best] - centre[1]) * factor
    return distance, float(correlation[rows[best], cols[best]] / correlation[tuple(centre)])


def _noise(image: np.ndarray) -> float:
    """Pixel noise (standard deviation) from the median absolute difference of horizontal neighbours."""
    return 1.4826 * float(np.median(np.abs(np.diff(image, axis=1)))) / math.sqrt(2.0)


def _dot_centres(image: np.ndarray, spacing: float, limit: int) -> tuple[np.ndarray, float, float]:
    """Up to `limit` candidate dot centres (M, 2) as (x, y): local maxima of the image smoothed at the dots' scale,
    at least a quarter of the typical dot's height, refined to the centroid of each dot's upper half; and the
    typical height and the smoothed noise (for messages)."""
    sigma = max(0.7, 0.12 * spacing)
    smooth = cv2.GaussianBlur(image - np.float32(np.median(image)), (0, 0), sigmaX=sigma, sigmaY=sigma,
                              borderType=cv2.BORDER_REPLICATE)
    noise = _noise(image) / (2.0 * math.sqrt(math.pi) * sigma)  # white noise after the Gaussian
    size = max(3, 2 * round(0.3 * spacing) + 1)
    dilated = cv2.dilate(smooth, np.ones((size, size), np.uint8))  # a square window: OpenCV's fast path
    _, _, _, seeds = cv2.connectedComponentsWithStats(((smooth == dilated) & (smooth > 6 * noise)).astype(np.uint8))
    seeds = np.rint(seeds[1:]).astype(int)  # a flat top (clipped dot) is one component: one seed
    if not len(seeds):
        return np.zeros((0, 2)), 0.0, noise
    height = smooth[seeds[:, 1], seeds[:, 0]]
    order = np.argsort(height)[::-1][:limit]
    typical = float(np.median(height[order[: max(1, limit // 4)]]))
    seeds, height = seeds[order], height[order]
    keep = height >= 0.25 * typical
    seeds, height = seeds[keep], height[keep]
    reach = max(1, math.ceil(0.3 * spacing))
    dy, dx = np.mgrid[-reach:reach + 1, -reach:reach + 1]
    disc = np.hypot(dy, dx) <= reach
    padded = np.pad(smooth, reach)
    centres = np.empty((len(seeds), 2))
    for k, ((x, y), top) in enumerate(zip(seeds, height)):
        window = padded[y:y + 2 * reach + 1, x:x + 2 * reach + 1]
        weight = np.where(disc, np.clip(window - 0.5 * top, 0.0, None), 0.0)
        total = weight.sum()
        centres[k] = (x + (weight * dx).sum() / total, y + (weight * dy).sum() / total)
    return _merge_close(centres, 0.25 * spacing), typical, noise


def _merge_close(points: np.ndarray, distance: float) -> np.ndarray:
    """`points` with each group closer than `distance` (two seeds on one dot) replaced by its first member."""
    keep = np.ones(len(points), dtype=bool)
    for k in range(len(points)):
        if keep[k]:
            close = np.hypot(*(points[k + 1:] - points[k]).T) < distance
            keep[k + 1:] &= ~close
    return points[keep]


def _neighbour_vectors(points: np.ndarray, k: int = 4) -> np.ndarray:
    """Vectors from each point to its k nearest neighbours, (M * k, 2)."""
    difference = points[None, :, :] - points[:, None, :]
    distance = np.hypot(difference[..., 0], difference[..., 1])
    np.fill_diagonal(distance, np.inf)
    nearest = np.argsort(distance, axis=1)[:, :k]
    return difference[np.arange(len(points))[:, None], nearest].reshape(-1, 2)


def _lattice_steps(points: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The lattice's two step vectors (a nearer the image's x axis, b nearer y) from nearest-neighbour vectors;
    None where the points show no lattice."""
    vectors = _neighbour_vectors(points, k=min(4, len(points) - 1))
    length = np.hypot(vectors[:, 0], vectors[:, 1])
    nearest = np.median(np.sort(length.reshape(len(points), -1), axis=1)[:, 0])
    vectors = vectors[length < 1.4 * nearest]  # the four direct neighbours, not the diagonals
    angle = np.arctan2(vectors[:, 1], vectors[:, 0])
    turn = math.atan2(np.sin(4 * angle).mean(), np.cos(4 * angle).mean()) / 4  # lattice orientation mod 90 deg
    c, s = math.cos(turn), math.sin(turn)
    upright = vectors @ np.array([[c, -s], [s, c]])  # vectors turned back by `turn`
    along_x = np.abs(upright[:, 0]) > np.abs(upright[:, 1])
    if along_x.sum() < 3 or (~along_x).sum() < 3:
        return None
    # Each direction's vectors with their sign made consistent (pointing to +x, resp. +y, once turned back).
    a = np.median(vectors[along_x] * np.sign(upright[along_x, 0])[:, None], axis=0)
    b = np.median(vectors[~along_x] * np.sign(upright[~along_x, 1])[:, None], axis=0)
    if abs(a[0] * b[1] - a[1] * b[0]) < 0.25 * np.hypot(*a) * np.hypot(*b):
        return None
    return a, b


def _lattice_indices(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Integer lattice indices (M, 2) of every point and its distance from its lattice point (the larger
    fractional-index deviation, in steps), from a map index -> position refined on the points near the lattice:
    the step vectors first, then homographies (which absorb perspective across the grid)."""
    origin = points[np.argmin(np.hypot(*(points - np.median(points, axis=0)).T))]
    fractional = (points - origin) @ np.linalg.inv(np.stack([a, b], axis=1)).T
    for _ in range(3):
        index = np.rint(fractional)
        near = np.abs(fractional - index).max(axis=1) < ON_LATTICE
        if near.sum() < 4:
            break
        homography, _ = cv2.findHomography(index[near], points[near], 0)  # least squares
        if homography is None:
            break
        fractional = apply_homography(np.linalg.inv(homography), points)
    index = np.rint(fractional)
    return index.astype(int), np.abs(fractional - index).max(axis=1)


def _placements(index: np.ndarray, quality: np.ndarray,
                size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every placement of a size = (u, v) window on the lattice: its first index (K, 2), its score (the summed
    quality of the spots it holds, the best per cell), how many cells hold a spot, and how many of its four
    corners are empty (each (K,))."""
    low = index.min(axis=0) - np.array(size)
    weight = np.zeros(index.max(axis=0) - low + 1 + np.array(size))
    np.maximum.at(weight, (index[:, 0] - low[0], index[:, 1] - low[1]), quality)
    du, dv = size

    def window_sums(cells: np.ndarray) -> np.ndarray:
        table = np.pad(cells.cumsum(0).cumsum(1), ((1, 0), (1, 0)))  # summed-area table: any window in O(1)
        return table[du:, dv:] - table[:-du, dv:] - table[du:, :-dv] + table[:-du, :-dv]

    filled = (weight > 0).astype(np.int64)
    score, count = window_sums(weight), window_sums(filled)
    n_u, n_v = score.shape
    corners = np.sum([filled[i:i + n_u, j:j + n_v] for i in (0, du - 1) for j in (0, dv - 1)], axis=0)
    starts = np.stack(np.meshgrid(np.arange(n_u), np.arange(n_v), indexing="ij"), axis=-1).reshape(-1, 2) + low
    return starts, score.ravel(), count.ravel(), 4 - corners.ravel()


def find_dots(image: np.ndarray, grid: tuple[int, int] = DEFAULT_GRID) -> np.ndarray:
    """Centres (N, 2) as (x = col, y = row) in `image`'s pixel coordinates of the dots of `dot_grid_target`'s
    pattern, in the target's point order; rows of dots not found (at most 1 - MIN_FOUND_FRACTION of them) are
    NaN. Works at any scale, turn or mirror (module docstring); raises RegistrationError when it cannot.
    """
    image = np.asarray(image, dtype=np.float32)
    if image.ndim != 2 or min(image.shape) < 8:
        raise RegistrationError(f"find_dots needs a 2-D image, got shape {image.shape}")
    if not np.isfinite(image).all():
        raise RegistrationError("find_dots: the image contains NaN or infinite values")
    rows, cols = int(grid[0]), int(grid[1])
    expected = rows * cols - 1

    def fail(found: int, why: str) -> RegistrationError:
        return RegistrationError(f"found {found} of the {expected} dots of a {rows} x {cols} dot grid: {why}")

    spacing, contrast = _spacing(image)
    if not spacing >= 3.0 or contrast < LATTICE_CONTRAST:
        raise fail(0, f"the image shows no regular pattern (autocorrelation peak {contrast:.2g} of its centre, "
                      f"{spacing:.3g} px out; needs {LATTICE_CONTRAST:g} at >= 3 px): no light, or no grid in view")
    candidates, typical, noise = _dot_centres(image, spacing, 4 * expected)
    if len(candidates) < MIN_FOUND_FRACTION * expected:
        raise fail(len(candidates), f"only {len(candidates)} bright spots (typical height {typical:.3g}, noise "
                                    f"{noise:.2g}, spacing {spacing:.3g} px): the pattern is not fully in view")
    steps = _lattice_steps(candidates)
    if steps is None:
        raise fail(0, f"the {len(candidates)} bright spots form no regular lattice")
    index, offset = _lattice_indices(candidates, *steps)
    on = offset < ON_LATTICE
    index, candidates, offset = index[on], candidates[on], offset[on]
    if rows == cols:  # a square grid: the step nearer the image's x axis runs along the target's rows
        options = [(cols, rows, False)]
    else:
        options = [(cols, rows, False), (rows, cols, True)]  # (u extent, v extent, u counts target rows)
    # The grid is the placement with exactly one empty corner (the marker) whose spots sit best on the lattice:
    # a dot lies within a few hundredths of a step of its lattice point, a speckle maximum (light a hologram
    # sends outside the ROI) anywhere within the quarter step, so a window shifted onto such light scores less.
    quality = 1.0 - offset / ON_LATTICE
    placements = [(start, score, count, empty, transposed) for du, dv, transposed in options
                  for start, score, count, empty in zip(*_placements(index, quality, (du, dv)))]
    marked = sorted((p for p in placements if p[3] == 1), key=lambda p: p[1], reverse=True)
    needed = math.ceil(MIN_FOUND_FRACTION * expected)
    if not marked:
        fullest = max(placements, key=lambda p: p[2])
        raise RegistrationError(
            f"no {rows} x {cols} part of the {len(candidates)} spots on the lattice shows the marker (exactly one "
            f"empty corner): the fullest holds {fullest[2]} spots (the grid has {expected}) with {fullest[3]} corners "
            "empty, so the grid's orientation is unknown")
    (u0, v0), score, count, _, transposed = marked[0]
    if count < needed:
        raise fail(count, f"too few in the best {rows} x {cols} part of the lattice with the marker (needs {needed}; "
                          f"{len(candidates)} spots on the lattice in all)")
    if len(marked) > 1 and marked[1][1] > score - 1e-6:
        raise fail(count, "two placements of the grid on the lattice fit equally well")
    du, dv = (rows, cols) if transposed else (cols, rows)
    inside = (index[:, 0] >= u0) & (index[:, 0] < u0 + du) & (index[:, 1] >= v0) & (index[:, 1] < v0 + dv)
    local = index[inside] - [u0, v0]
    found = candidates[inside]
    if transposed:
        local = local[:, ::-1]  # now (col, row) of the image's own grid
    col, row = local[:, 0], local[:, 1]
    marker_col, marker_row = next((c, r) for r in (0, rows - 1) for c in (0, cols - 1)
                                  if not np.any((col == c) & (row == r)))
    target_col = col if marker_col == 0 else cols - 1 - col
    target_row = row if marker_row == 0 else rows - 1 - row
    order = target_row * cols + target_col - 1
    # A dot may have been found twice (split in two): keep the spot nearest its lattice point.
    points = np.full((expected, 2), np.nan)
    best = np.full(expected, np.inf)
    for k, point, error in zip(order, found, offset[inside]):
        if error < best[k]:
            points[k], best[k] = point, error
    return points


def cfa_positions(cfa: np.ndarray, colour: int) -> list[tuple[int, int]]:
    """(dy, dx) cell positions of `colour` (0 R, 1 G, 2 B) in a (2, 2) CFA layout: one for R and B, two for G, all
    four on a monochrome sensor (each warped on its own and averaged, so every pixel counts)."""
    cells = np.asarray(cfa)
    positions = [(int(dy), int(dx)) for dy, dx in np.argwhere((cells == colour) | (cells == MONO))]
    if not positions:
        raise BenchctlError(f"colour {colour} does not occur in the CFA layout {np.asarray(cfa).tolist()}")
    return positions


def cfa_planes(mosaic: np.ndarray, cfa: np.ndarray, colour: int) -> list[tuple[np.ndarray, tuple[int, int]]]:
    """The planes (views, even-sized like RawImage.planes) of `colour`'s CFA positions in a mosaic (or in any
    array laid out like it, e.g. the saturation mask), each with its (dy, dx) cell position."""
    rows, cols = (n - n % 2 for n in mosaic.shape)
    return [(mosaic[dy:rows:2, dx:cols:2], (dy, dx)) for dy, dx in cfa_positions(cfa, colour)]


def dots_in_capture(raw: RawImage, colour: int, grid: tuple[int, int] = DEFAULT_GRID) -> np.ndarray:
    """`find_dots` on the CFA plane of `colour` (its positions averaged), as active-area mosaic coordinates."""
    planes = cfa_planes(raw.mosaic, raw.cfa, colour)
    offset = np.mean([position for _, position in planes], axis=0)  # (dy, dx) of the averaged samples
    return 2.0 * find_dots(np.mean([plane for plane, _ in planes], axis=0), grid) + offset[::-1]


# -- fitting and using the homography ---------------------------------------------------------------------------


def apply_homography(homography: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points (N, 2) as (x, y) mapped through a 3x3 homography."""
    points = np.asarray(points, dtype=np.float64)
    mapped = np.column_stack([points, np.ones(len(points))]) @ np.asarray(homography, dtype=np.float64).T
    return mapped[:, :2] / mapped[:, 2:]


@dataclass(frozen=True, eq=False)
class Registration:
    """A fitted camera-SLM registration: `homography` maps target-plane pixels to active-area mosaic coordinates.

    rms_px / max_px: reprojection error of the inliers in sensor pixels; inliers of `points` point pairs.
    """

    homography: np.ndarray
    rms_px: float
    max_px: float
    inliers: int
    points: int

    @property
    def scale(self) -> float:
        """Sensor pixels per target-plane pixel at the target grid's origin (sqrt of the Jacobian's |det|)."""
        return math.sqrt(abs(np.linalg.det(_jacobian(self.homography, np.zeros(2)))))

    @property
    def rms_target_px(self) -> float:
        """The RMS error in target-plane pixels (rms_px / scale), comparable across magnifications."""
        return self.rms_px / self.scale

    @property
    def mirrored(self) -> bool:
        """True when the camera sees the target plane mirrored (the homography reverses orientation)."""
        return bool(np.linalg.det(_jacobian(self.homography, np.zeros(2))) < 0)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form, read back by `from_dict`."""
        return {"homography": [[float(v) for v in row] for row in self.homography], "rms_px": self.rms_px,
                "max_px": self.max_px, "inliers": self.inliers, "points": self.points}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Registration:
        """A registration from `to_dict`'s form; a damaged record is a RegistrationError naming the key."""
        try:
            homography = np.array(data["homography"], dtype=np.float64)
            values = {key: float(data[key]) for key in ("rms_px", "max_px")}
            counts = {key: int(data[key]) for key in ("inliers", "points")}
        except KeyError as exc:
            raise RegistrationError(f"stored registration lacks the key {exc.args[0]!r}") from None
        except (TypeError, ValueError) as exc:
            raise RegistrationError(f"stored registration has a malformed value: {exc}") from None
        if homography.shape != (3, 3) or not np.isfinite(homography).all():
            raise RegistrationError(f"stored registration: 'homography' must be 3 x 3 finite numbers, got shape "
                                    f"{homography.shape}")
        return cls(homography, values["rms_px"], values["max_px"], counts["inliers"], counts["points"])


def _jacobian(homography: np.ndarray, point: np.ndarray) -> np.ndarray:
    """2x2 derivative of the homography's mapping at `point` (x, y)."""
    h = np.asarray(homography, dtype=np.float64)
    x, y = point
    w = h[2, 0] * x + h[2, 1] * y + h[2, 2]
    mapped = apply_homography(h, np.array([[x, y]]))[0]
    return (h[:2, :2] - np.outer(mapped, h[2, :2])) / w


def fit_registration(target_points: np.ndarray, image_points: np.ndarray, *,
                     ransac_target_px: float = RANSAC_TARGET_PX, max_rms_target_px: float = MAX_RMS_TARGET_PX,
                     min_inlier_fraction: float = MIN_INLIER_FRACTION) -> Registration:
    """RANSAC homography target-plane points -> image points (both (N, 2) as (x, y); rows with NaN, dots not
    found, are left out), refined on the inliers. Refuses (RegistrationError, with the numbers) a fit with too
    few inliers, an RMS error above `max_rms_target_px`, or a degenerate or implausible homography.

    Both limits are in target-plane pixels, so they hold at any magnification: the camera's
    scale (sensor pixels per target pixel) converts them, estimated from the point clouds' spreads for RANSAC
    and taken from the fit for the RMS check. The Registration reports errors in sensor pixels.
    """
    source = np.asarray(target_points, dtype=np.float64)
    destination = np.asarray(image_points, dtype=np.float64)
    if source.shape != destination.shape or source.ndim != 2 or source.shape[1] != 2:
        raise RegistrationError(f"point lists must both be (N, 2), got {source.shape} and {destination.shape}")
    usable = np.isfinite(source).all(axis=1) & np.isfinite(destination).all(axis=1)
    source, destination = source[usable], destination[usable]
    count = len(source)
    if count < MIN_POINTS:
        raise RegistrationError(f"a homography needs at least {MIN_POINTS} point pairs, got {count}")
    spread = np.linalg.det(np.cov(destination.T)) / max(np.linalg.det(np.cov(source.T)), 1e-300)
    ransac_px = ransac_target_px * max(spread, 0.0) ** 0.25  # det of a covariance scales as scale^4
    homography, mask = cv2.findHomography(source.reshape(-1, 1, 2), destination.reshape(-1, 1, 2), cv2.RANSAC,
                                          ransacReprojThreshold=float(max(ransac_px, 0.5)), maxIters=2000,
                                          confidence=0.999)
    if homography is None or mask is None:
        raise RegistrationError(f"no homography fits the {count} point pairs (degenerate layout?)")
    homography = homography / homography[2, 2]
    inlier = mask.ravel().astype(bool)
    errors = np.hypot(*(apply_homography(homography, source) - destination).T)
    inliers = int(inlier.sum())
    rms = float(np.sqrt(np.mean(errors[inlier] ** 2))) if inliers else math.inf
    worst = float(errors[inlier].max()) if inliers else math.inf
    summary = (f"{inliers} of {count} points within {ransac_px:.3g} px, RMS {rms:.3g} px, max {worst:.3g} px "
               "(sensor pixels)")
    if inliers < min_inlier_fraction * count:
        raise RegistrationError(f"registration refused: only {summary} (needs {min_inlier_fraction:.0%} inliers)")
    _check_plausible(homography, source[inlier], summary)
    registration = Registration(homography, rms, worst, inliers, count)
    if registration.rms_target_px > max_rms_target_px:
        raise RegistrationError(f"registration refused: {summary}; the RMS is {registration.rms_target_px:.3g} "
                                f"target-plane pixels, above the {max_rms_target_px:g} px limit")
    return registration


def _check_plausible(homography: np.ndarray, points: np.ndarray, summary: str) -> None:
    """Refuse a homography no bench produces: singular, strongly sheared or anisotropic, or strongly projective."""
    centre = points.mean(axis=0)
    singular = np.linalg.svd(_jacobian(homography, centre), compute_uv=False)
    if not singular[1] > 1e-6 * singular[0] or not singular[1] > 0:
        raise RegistrationError(f"registration refused: degenerate homography (scales {singular[0]:.3g} and "
                                f"{singular[1]:.3g}); {summary}")
    if singular[0] / singular[1] > MAX_ANISOTROPY:
        raise RegistrationError(f"registration refused: the homography stretches one direction "
                                f"{singular[0] / singular[1]:.3g} x more than the other (limit {MAX_ANISOTROPY:g}); "
                                f"{summary}")
    w = np.column_stack([points, np.ones(len(points))]) @ homography[2]
    if not (w > 0).all() or w.max() / w.min() > MAX_PERSPECTIVE:
        raise RegistrationError(f"registration refused: perspective divisor ranges {w.min():.3g} .. {w.max():.3g} "
                                f"across the points (limit ratio {MAX_PERSPECTIVE:g}); {summary}")


def plane_homography(homography: np.ndarray, offset: tuple[float, float]) -> np.ndarray:
    """The homography onto a CFA plane whose pixel (i, j) is mosaic pixel (2 i + dy, 2 j + dx), offset = (dy, dx)."""
    dy, dx = offset
    to_plane = np.array([[0.5, 0.0, -0.5 * dx], [0.0, 0.5, -0.5 * dy], [0.0, 0.0, 1.0]])
    return to_plane @ np.asarray(homography, dtype=np.float64)


def warp_to_roi(image: np.ndarray, homography: np.ndarray, shape: tuple[int, int], roi: tuple[int, int]) -> np.ndarray:
    """(roi_h, roi_w) float32: `image` sampled (bilinear, 0 outside it) where `homography` maps each pixel of the
    centred ROI of a target plane of `shape`: pixel (r, c) of the result is target pixel (top + r, left + c)."""
    rows, cols = centred_slices(shape, roi)
    from_roi = np.array([[1.0, 0.0, cols.start], [0.0, 1.0, rows.start], [0.0, 0.0, 1.0]])
    source = np.ascontiguousarray(image, dtype=np.float32)
    return cv2.warpPerspective(source, np.asarray(homography, dtype=np.float64) @ from_roi, (int(roi[1]), int(roi[0])),
                               flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_CONSTANT,
                               borderValue=0.0)
