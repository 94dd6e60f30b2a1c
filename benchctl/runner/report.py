"""Run reports: a `Report` a procedure fills with sections and writes as the run's metrics (JSON and CSV) and a
self-contained HTML page (previews embedded as PNG data, full-resolution files linked beside it, plots as inline
SVG), so a user understands a run from the report alone; and the HTML helpers its sections are made of. Each
procedure writes its own report (the built-ins next to their plans).
"""

from __future__ import annotations

import base64
import html
import json
from typing import Any

import cv2
import numpy as np

from benchctl.files import atomic_write_bytes, write_csv, write_json
from benchctl.images import read_image
from benchctl.runner import layout
from benchctl.runner.context import Context

PREVIEW_WIDTH = 480
STYLE = """body{font-family:system-ui,sans-serif;margin:2em;max-width:1200px;color:#222}
table{border-collapse:collapse;margin:.5em 0 1.5em}td,th{border:1px solid #ccc;padding:.25em .6em;text-align:right}
th{background:#f3f3f3}td:first-child,th:first-child{text-align:left}figure{display:inline-block;margin:0 1em 1em 0}
figcaption{font-size:.9em;color:#555}.warn{background:#fff4e0;border-left:4px solid #e69500;padding:.5em 1em}
.ok{color:#2a7a2a}code{background:#f3f3f3;padding:0 .2em}"""


def _esc(value: Any) -> str:
    return html.escape(str(value))


def table(rows: list[dict[str, Any]]) -> str:
    """An HTML table of dict rows, columns in first-seen order; floats to 4 significant digits."""
    if not rows:
        return "<p>(none)</p>"
    columns: list[str] = []
    for row in rows:
        columns.extend(key for key in row if key not in columns)

    def cell(value: Any) -> str:
        if isinstance(value, float):
            return f"{value:.4g}"
        return _esc("" if value is None else value)

    head = "".join(f"<th>{_esc(c)}</th>" for c in columns)
    body = "".join("<tr>" + "".join(f"<td>{cell(row.get(c))}</td>" for c in columns) + "</tr>" for row in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def figure(context: Context, relative: str, caption: str) -> str:
    """An embedded 8-bit preview of an image file of the run (`relative`, as a step result names it), linked to
    the full-resolution file."""
    image = read_image(context.path(relative))
    if image.dtype == np.uint16:
        image = (image / 257).round().astype(np.uint8)
    if image.shape[1] > PREVIEW_WIDTH:
        height = max(1, round(image.shape[0] * PREVIEW_WIDTH / image.shape[1]))
        image = cv2.resize(image, (PREVIEW_WIDTH, height), interpolation=cv2.INTER_AREA)
    if image.ndim == 3:
        image = image[:, :, ::-1]  # OpenCV encodes BGR
    ok, png = cv2.imencode(".png", np.ascontiguousarray(image))
    data = base64.b64encode(png.tobytes()).decode() if ok else ""
    return (f'<figure><a href="{_esc(relative)}"><img src="data:image/png;base64,{data}" alt="{_esc(caption)}">'
            f"</a><figcaption>{_esc(caption)}</figcaption></figure>")


def _run_section(context: Context, colours: list[str]) -> tuple[str, list[str]]:
    """The header every report starts with: what ran where, versions, devices, calibration, step timings."""
    record = context.record
    assert record is not None
    info = record.info()
    rows, warnings = context.calibration.state(colours)
    devices_path = record.folder / layout.DEVICES
    devices = json.loads(devices_path.read_text()) if devices_path.is_file() else context.instruments.identities
    timings: dict[str, float] = {}
    for event in record.events():
        if event.get("event") == "done":
            group = event["step"].split("/")[0]
            timings[group] = timings.get(group, 0.0) + float(event.get("seconds", 0.0))
    parts = [
        f"<p>Run <code>{_esc(record.name)}</code>: procedure <b>{_esc(info.get('procedure'))}</b> on profile "
        f"<b>{_esc(info.get('profile'))}</b>, started {_esc(info.get('start'))}"
        + (f", resumed {len(info['resumed'])} time(s)" if info.get("resumed") else "") + ".</p>",
        "<h2>Parameters</h2>"
        + table([{"parameter": k, "value": json.dumps(v)} for k, v in info["parameters"].items()]),
        "<h2>Calibration used</h2>" + table(rows),
        "<h2>Devices</h2>" + table([{"device": k, "identity": json.dumps(v, default=str)} for k, v in devices.items()]),
        "<h2>Time per kind of step</h2>" + table([{"steps": k, "seconds": round(v, 3)} for k, v in timings.items()]),
        "<h2>Versions</h2>" + table([{"package": k, "version": v} for k, v in info["versions"].items()]),
    ]
    return "".join(parts), warnings


class Report:
    """A run's report as a procedure builds it: a title, sections of HTML (from the helpers here) and warnings;
    `write` stores it with the run's metrics."""

    def __init__(self, title: str) -> None:
        self.title = title
        self.sections: list[str] = []
        self.warnings: list[str] = []

    def section(self, heading: str, *parts: str, level: int = 2) -> None:
        """A section: its heading (h2; `level` 3 for a sub-section) and its parts (tables, figures, plots, text)."""
        self.sections.append(f"<h{level}>{_esc(heading)}</h{level}>" + "".join(parts))

    def warn(self, *lines: str) -> None:
        """Warnings, shown first in the report (each once)."""
        self.warnings += lines

    def write(self, context: Context, metrics: dict[str, Any], rows: list[dict[str, Any]], colours: list[str],
              headline: list[str]) -> dict[str, Any]:
        """Write metrics.json (`metrics`), metrics.csv (`rows`) and report.html: the title, the warnings (this
        report's and the calibration's for `colours`), the sections, then the run's details. Returns the report
        step's result: the `headline` the run ends by printing, and the warnings."""
        write_json(context.path(layout.METRICS_JSON), metrics)
        write_csv(context.path(layout.METRICS_CSV), rows)
        details, calibration_warnings = _run_section(context, colours)
        warnings = list(dict.fromkeys(self.warnings + calibration_warnings))
        box = ("<div class='warn'><b>Warnings</b><ul>" + "".join(f"<li>{_esc(w)}</li>" for w in warnings)
               + "</ul></div>") if warnings else "<p class='ok'>No warnings.</p>"
        page = (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{_esc(self.title)}</title>"
                f"<style>{STYLE}</style></head><body><h1>{_esc(self.title)}</h1>{box}{''.join(self.sections)}"
                f"{details}</body></html>")
        atomic_write_bytes(context.path(layout.REPORT), page.encode())
        return {"headline": headline, "warnings": list(dict.fromkeys(self.warnings))}
