"""`benchctl bench genicam`: frames per second into numpy from Aravis's in-process fake camera, free running, and
what the genicam driver adds per frame.

Sustained: the fake camera streams at its fastest frame rate into a ring of buffers; every buffer is turned into
a numpy frame (the driver's `PixelFormat.frame`) and given back. Frame ids must run without a gap: a gap is a
dropped frame, and is counted. Overhead: per frame, the driver's own work after a buffer arrived: copying the
image out of it into numpy, and writing the DNG (what `camera capture` adds), timed apart.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from statistics import median

from benchctl.devices.camera.aravis import aravis
from benchctl.devices.camera.pixel_formats import pixel_format
from benchctl.dng import dng_bytes
from benchctl.errors import BenchctlError

BUFFERS = 16


@dataclass(frozen=True)
class GenicamBench:
    width: int
    height: int
    pixel_format: str
    frames: int
    dropped: int
    incomplete: int
    fps: float
    camera_fps: float  # the fake camera's own AcquisitionFrameRate (the ceiling)
    to_numpy_ms: float  # median per frame
    dng_ms: float  # median per frame

    def lines(self) -> list[str]:
        return [
            f"fake camera {self.width} x {self.height} {self.pixel_format}, {self.frames} frames free running "
            f"(camera frame rate {self.camera_fps:g} fps)",
            f"  sustained into numpy: {self.fps:.1f} fps, {self.dropped} dropped, {self.incomplete} incomplete",
            f"  driver overhead per frame (median): buffer -> numpy {self.to_numpy_ms:.2f} ms, "
            f"numpy -> DNG bytes {self.dng_ms:.2f} ms",
            f"  = {100 * self.to_numpy_ms * self.fps / 1000:.1f} % of the frame interval to numpy "
            f"({100 * (self.to_numpy_ms + self.dng_ms) * self.fps / 1000:.1f} % with the DNG)",
        ]


def run_genicam_bench(width: int = 2048, height: int = 2048, fmt: str = "BayerRG8", frames: int = 100,
                      frame_rate: float | None = None) -> GenicamBench:
    """Stream `frames` frames from the in-process fake camera (see module docstring)."""
    module = aravis()
    module.enable_interface("Fake")
    camera = module.Camera.new("Fake_1")
    camera.set_region(0, 0, width, height)
    camera.set_pixel_format_from_string(fmt)
    if frame_rate is not None:
        camera.set_frame_rate(frame_rate)
    camera.set_acquisition_mode(module.AcquisitionMode.CONTINUOUS)
    layout = pixel_format(camera.get_pixel_format_as_string())
    stream = camera.create_stream(None, None)
    for _ in range(BUFFERS):
        stream.push_buffer(module.Buffer.new_allocate(camera.get_payload()))
    numpy_s: list[float] = []
    dng_s: list[float] = []
    ids: list[int] = []
    incomplete = 0
    camera.start_acquisition()
    try:
        started = None
        while len(ids) < frames:
            buffer = stream.timeout_pop_buffer(5_000_000)
            if buffer is None:
                raise BenchctlError("the fake camera delivered no frame within 5 s")
            if buffer.get_status() != module.BufferStatus.SUCCESS:
                incomplete += 1
                stream.push_buffer(buffer)
                continue
            start = time.perf_counter()
            frame = layout.frame(buffer.get_image_data(), width, height)
            numpy_s.append(time.perf_counter() - start)
            ids.append(buffer.get_frame_id())
            stream.push_buffer(buffer)
            if started is None:
                started = time.perf_counter()  # fps counts from the first frame's arrival
            if len(ids) <= 10:  # DNG writing timed on a few frames: it is not part of the stream
                start = time.perf_counter()
                dng_bytes(frame, cfa=layout.cfa, white_level=layout.white_level)
                dng_s.append(time.perf_counter() - start)
        elapsed = time.perf_counter() - started if started is not None else 0.0
    finally:
        camera.stop_acquisition()
    dropped = sum((b - a) % 65535 - 1 for a, b in zip(ids, ids[1:]))  # ids run 1 .. 65535, then 1 again
    return GenicamBench(width, height, layout.name, len(ids), dropped, incomplete,
                        (len(ids) - 1) / elapsed if elapsed > 0 else 0.0, camera.get_frame_rate(),
                        1e3 * median(numpy_s), 1e3 * median(dng_s))
