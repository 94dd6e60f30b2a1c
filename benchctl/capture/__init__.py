"""Turning captured RAW frames into measurements: RAW decode (`raw`), camera-SLM registration (`registration`),
SLM lookup-table calibration (`lut_calibration`), and registered, balanced, scored colour captures
(`colour_planes`). Imports `benchctl.optics` for metrics, nothing from devices, cgh or the runner."""

from benchctl.capture.colour_planes import (
    MergedCapture,
    merge_capture,
    registered_plane,
    registered_saturation,
    roi_saturation,
)
from benchctl.capture.lut_calibration import (
    CalibrationError,
    calibrate_lut,
    calibration_grays,
    grating_frame,
    lut_from_response,
    phase_response,
    zero_order_signal,
)
from benchctl.capture.raw import (
    RawImage,
    average_frames,
    decode_raw,
    linear_rgb,
    subtract_dark,
)
from benchctl.capture.registration import (
    DEFAULT_GRID,
    Registration,
    RegistrationError,
    apply_homography,
    cfa_planes,
    cfa_positions,
    dot_grid_target,
    dots_in_capture,
    find_dots,
    fit_registration,
    plane_homography,
    warp_to_roi,
)

__all__ = [
    "DEFAULT_GRID",
    "CalibrationError",
    "MergedCapture",
    "RawImage",
    "Registration",
    "RegistrationError",
    "apply_homography",
    "average_frames",
    "calibrate_lut",
    "calibration_grays",
    "cfa_planes",
    "cfa_positions",
    "decode_raw",
    "dot_grid_target",
    "dots_in_capture",
    "find_dots",
    "fit_registration",
    "grating_frame",
    "linear_rgb",
    "lut_from_response",
    "merge_capture",
    "phase_response",
    "plane_homography",
    "registered_plane",
    "registered_saturation",
    "roi_saturation",
    "subtract_dark",
    "warp_to_roi",
    "zero_order_signal",
]
