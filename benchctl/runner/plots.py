"""Plots for run reports: inline SVG of named curves and of a speed-against-error front on a log time axis, and the
raster pictures a report shows as images (an error map, a registration's dots over what the camera saw).

SVG keeps report.html self-contained and readable without matplotlib (an optional extra).
"""

from __future__ import annotations

import html
import math
from collections.abc import Callable, Mapping, Sequence

import cv2
import numpy as np
import torch

from benchctl.optics import linear_to_srgb

COLOURS = ("#d62728", "#2ca02c", "#1f77b4", "#9467bd", "#ff7f0e", "#8c564b")
LEFT, BOTTOM, PAD = 60, 40, 10


def _axes(x_range: tuple[float, float], y_range: tuple[float, float], labels: tuple[str, str, str, str],
          xlabel: str, ylabel: str, width: int, height: int) -> tuple[list[str], Callable[[float, float], str]]:
    """The frame, the four range labels and the axis titles; and the map from data to "x,y" pixel text."""
    (x0, x1), (y0, y1) = x_range, y_range

    def px(x: float, y: float) -> str:
        return (f"{LEFT + (x - x0) / (x1 - x0) * (width - LEFT - PAD):.1f},"
                f"{height - BOTTOM - (y - y0) / (y1 - y0) * (height - BOTTOM - PAD):.1f}")

    low_x, high_x, low_y, high_y = (html.escape(text) for text in labels)
    parts = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" '
             f'viewBox="0 0 {width} {height}" font-size="11">',  # the viewBox scales it down whole where it must
             f'<rect x="{LEFT}" y="{PAD}" width="{width - LEFT - PAD}" height="{height - BOTTOM - PAD}" '
             'fill="none" stroke="#999"/>',
             f'<text x="{LEFT}" y="{height - 22}">{low_x}</text>',
             f'<text x="{width - PAD}" y="{height - 22}" text-anchor="end">{high_x}</text>',
             f'<text x="{LEFT - 4}" y="{height - BOTTOM}" text-anchor="end">{low_y}</text>',
             f'<text x="{LEFT - 4}" y="{PAD + 10}" text-anchor="end">{high_y}</text>',
             f'<text x="{(width + LEFT) / 2}" y="{height - 6}" text-anchor="middle">{html.escape(xlabel)}</text>',
             f'<text x="12" y="{(height - BOTTOM) / 2}" transform="rotate(-90 12 {(height - BOTTOM) / 2})" '
             f'text-anchor="middle">{html.escape(ylabel)}</text>']
    return parts, px


def _span(values: Sequence[float], floor: float | None = None) -> tuple[float, float]:
    low = min(values) if floor is None else min(floor, min(values))
    return low, max(values) if max(values) > low else low + 1.0


def line_plot(series: Mapping[str, tuple[Sequence[float], Sequence[float]]], xlabel: str, ylabel: str,
              width: int = 520, height: int = 300) -> str:
    """An inline SVG plot of named (x, y) series, with axis ranges and labels (the y axis starts at 0 or below)."""
    xs = [x for x_values, _ in series.values() for x in x_values]
    ys = [y for _, y_values in series.values() for y in y_values]
    if not xs:
        return "<p>(no data)</p>"
    (x0, x1), (y0, y1) = _span(xs), _span(ys, floor=0.0)
    parts, px = _axes((x0, x1), (y0, y1), (f"{x0:.4g}", f"{x1:.4g}", f"{y0:.4g}", f"{y1:.4g}"), xlabel, ylabel,
                      width, height)
    for n, (name, (x_values, y_values)) in enumerate(series.items()):
        colour = COLOURS[n % len(COLOURS)]
        points = " ".join(px(x, y) for x, y in zip(x_values, y_values))
        parts.append(f'<polyline points="{points}" fill="none" stroke="{colour}" stroke-width="1.5"/>')
        parts.append(f'<text x="{LEFT + 8}" y="{PAD + 14 + 13 * n}" fill="{colour}">{html.escape(name)}</text>')
    parts.append("</svg>")
    return "".join(parts)


def front_plot(points: Sequence[tuple[str, float, float, bool]], xlabel: str, ylabel: str,
               width: int = 560, height: int = 320) -> str:
    """An inline SVG scatter of named (seconds, score, on_front) points on a log10 time axis, each point a
    labelled marker, the Pareto front joined by a staircase (faster points first)."""
    points = [p for p in points if p[1] > 0 and math.isfinite(p[1]) and math.isfinite(p[2])]
    if not points:
        return "<p>(no data)</p>"
    logs = [math.log10(p[1]) for p in points]
    (x0, x1), (y0, y1) = _span(logs), _span([p[2] for p in points])
    margin_x, margin_y = 0.08 * (x1 - x0), 0.1 * (y1 - y0)
    x0, x1, y0, y1 = x0 - margin_x, x1 + margin_x, y0 - margin_y, y1 + margin_y
    parts, px = _axes((x0, x1), (y0, y1), (f"{10 ** x0:.3g}", f"{10 ** x1:.3g}", f"{y0:.4g}", f"{y1:.4g}"),
                      xlabel + " (log scale)", ylabel, width, height)
    front = sorted((math.log10(p[1]), p[2]) for p in points if p[3])
    steps: list[str] = []
    for n, (x, y) in enumerate(front):
        if n:
            steps.append(px(x, front[n - 1][1]))
        steps.append(px(x, y))
    if steps:
        parts.append(f'<polyline points="{" ".join(steps)}" fill="none" stroke="#888" stroke-dasharray="4 3"/>')
    for n, (name, seconds, score, on_front) in enumerate(points):
        colour = COLOURS[n % len(COLOURS)]
        x, y = (float(v) for v in px(math.log10(seconds), score).split(","))
        fill = colour if on_front else "white"
        # a label right of its marker, or left of it in the right half, so that it stays inside the frame
        label_x, anchor = (x - 8, ' text-anchor="end"') if x > (LEFT + width) / 2 else (x + 8, "")
        parts.append(f'<circle cx="{x:.1f}" cy="{y:.1f}" r="5" fill="{fill}" stroke="{colour}" stroke-width="2"/>'
                     f'<text x="{label_x:.1f}" y="{y - 6:.1f}" fill="{colour}"{anchor}>{html.escape(name)}</text>')
    parts.append("</svg>")
    return "".join(parts)


ERROR_FULL_SCALE = 0.25
"""An error map's colour scale ends at this sRGB error (of 1): brighter is worse."""


def _heat(values: np.ndarray) -> np.ndarray:
    """(h, w) values in [0, 1] through OpenCV's inferno colour map: (3, h, w) RGB in [0, 1]."""
    gray = np.round(np.clip(values, 0, 1) * 255).astype(np.uint8)
    return cv2.applyColorMap(gray, cv2.COLORMAP_INFERNO)[:, :, ::-1].transpose(2, 0, 1).astype(np.float32) / 255


def error_map(linear: torch.Tensor, target_linear: torch.Tensor) -> np.ndarray:
    """Where an image (3, h, w, linear) departs from its target: per pixel the RMS over colours of the sRGB difference,
    as a heat map (3, h, w) RGB in [0, 1] whose scale ends at ERROR_FULL_SCALE."""
    difference = linear_to_srgb(linear.clamp(0, 1)) - linear_to_srgb(target_linear.clamp(0, 1))
    return _heat(difference.square().mean(0).sqrt().numpy() / ERROR_FULL_SCALE)


def dots_over(plane: np.ndarray, dots: np.ndarray, radius_px: float) -> np.ndarray:
    """A registered capture of a dot grid (h, w, linear) in gray, with a red ring of `radius_px` where each dot
    (N, 2) as (x, y) was meant to land: (3, h, w) RGB in [0, 1]. A good registration puts every dot in its ring."""
    gray = np.clip(plane / max(float(np.percentile(plane, 99.9)), 1e-12), 0, 1)
    scale = 4 if max(plane.shape) < 800 else 1  # rings drawn finer than a small ROI's pixels
    picture = cv2.resize(np.round(np.repeat(gray[:, :, None], 3, axis=2) * 255).astype(np.uint8),
                         (plane.shape[1] * scale, plane.shape[0] * scale), interpolation=cv2.INTER_NEAREST)
    radius = max(2, round(radius_px * scale))
    for x, y in dots:
        cv2.circle(picture, (round((x + 0.5) * scale - 0.5), round((y + 0.5) * scale - 0.5)), radius, (255, 40, 40),
                   1, cv2.LINE_AA)
    return picture.transpose(2, 0, 1).astype(np.float32) / 255
