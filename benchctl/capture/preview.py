"""A RAW frame at a glance (`benchctl camera show FRAME`): its size, CFA layout, black and white levels, and per
colour the peak (as everywhere in benchctl: the brightest 0.1 % of the pixels, PEAK_PERCENTILE), the brightest pixel
and the saturated fraction, plus a preview PNG, without writing Python.

The preview is the half-size colour planes (no interpolation) as amplitude, the square root of the linear signal
scaled so that the frame's brightest pixel is white: dim speckle and stray light stay visible next to a bright image,
as in the amplitude pictures of reconstructions. Numpy and OpenCV only: camera commands load no torch.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from benchctl.capture.exposure import PEAK_PERCENTILE
from benchctl.capture.raw import MONO, RawImage, decode_raw
from benchctl.images import write_png

COLOURS = ("red", "green", "blue")


def frame_lines(image: RawImage) -> list[str]:
    """What a frame holds, for people: size, layout, levels, then per colour its peak (the brightest 0.1 %) and
    brightest pixel (of full scale, 1 = the white level) and the fraction of its pixels at the clip level."""
    rows, cols = image.mosaic.shape
    black = ", ".join(f"{level:g}" for level in image.black_levels.ravel())
    lines = [f"{image.source}: {cols} x {rows} px visible (width x height), "
             + ("monochrome (every colour reads every pixel)" if image.monochrome else f"{image.layout} Bayer"),
             f"black level {black} (per CFA position, {image.layout}), white level {image.white_level:g}"]
    for index, colour in enumerate(COLOURS):
        cells = [(i, j) for i in range(2) for j in range(2) if image.cfa[i, j] in (index, MONO)]
        signal = [image.mosaic[i::2, j::2] for i, j in cells]
        pixels = sum(plane.size for plane in signal)
        clipped = sum(int(image.saturated[i::2, j::2].sum()) for i, j in cells)
        mean = sum(float(plane.sum(dtype=np.float64)) for plane in signal) / pixels
        peak = float(np.percentile(np.concatenate([plane.ravel() for plane in signal]), PEAK_PERCENTILE))
        lines.append(f"{colour:>5}: peak {peak:.1%} of full scale (brightest 0.1 %), brightest pixel "
                     f"{max(float(plane.max()) for plane in signal):.1%}, mean {mean:.2%}, saturated "
                     f"{clipped / pixels:.3%} ({clipped} of {pixels} px)")
    return lines


def preview(image: RawImage) -> np.ndarray:
    """(H/2, W/2, 3) uint8 RGB: the colour planes as amplitude, sqrt(signal / brightest), the brightest pixel white."""
    planes = np.clip(image.planes(), 0.0, None)
    brightest = float(planes.max())
    amplitude = np.sqrt(planes / brightest) if brightest > 0 else planes
    return np.rint(np.moveaxis(amplitude, 0, -1) * 255).astype(np.uint8)


def show_frame(frame: Path, output: Path | None = None) -> list[str]:
    """Decode `frame`, describe it and write its preview (default: <frame name>.preview.png in the current
    folder; never next to the RAW files of a run)."""
    image = decode_raw(frame)
    output = Path(output) if output is not None else Path(f"{Path(frame).name}.preview.png")
    write_png(output, preview(image))
    rows, cols = image.mosaic.shape
    return frame_lines(image) + [f"preview: {output} ({cols // 2} x {rows // 2} px, amplitude: square root of the "
                                 "signal, the frame's brightest pixel white)"]
