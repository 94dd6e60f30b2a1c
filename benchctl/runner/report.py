"""Run reports: a `Report` a procedure fills with sections and writes as the run's metrics (JSON and CSV) and a
self-contained HTML page (previews embedded as PNG data, full-resolution files linked beside it, plots as inline
SVG), so a user understands a run from the report alone; and the HTML helpers its sections are made of. Each
procedure writes its own report (the built-ins next to their plans).
"""

from __future__ import annotations

import base64
import html
import json
from collections.abc import Sequence
from typing import Any

import cv2
import numpy as np

from benchctl.calibration.acceptance import rejection_line
from benchctl.files import atomic_write_bytes, write_csv, write_json
from benchctl.images import read_image
from benchctl.runner import layout
from benchctl.runner.context import Context

PREVIEW_WIDTH = 480
# The page never scrolls sideways: figures share a row in equal columns that shrink with the window, wide tables
# scroll inside their own box, plots scale down.
STYLE = """body{font-family:system-ui,sans-serif;margin:2em auto;padding:0 2em;max-width:1200px;color:#222}
table{border-collapse:collapse;margin:.5em 0;font-size:.95em}
td,th{border:1px solid #ccc;padding:.2em .45em;text-align:right}
th{background:#f3f3f3}td:first-child,th:first-child{text-align:left}.scroll{overflow-x:auto;margin-bottom:1em}
figure{display:inline-block;margin:0 1em 1em 0;max-width:100%}figure img{max-width:100%;height:auto;display:block;
border:1px solid #888;box-sizing:border-box}.row{display:grid;grid-template-columns:repeat(var(--n),minmax(0,1fr));
gap:1em;margin:.5em 0 1em}.row figure{margin:0}.row figure img{width:100%}svg{max-width:100%;height:auto}
figcaption{font-size:.9em;color:#555}.warn{background:#fff4e0;border-left:4px solid #e69500;padding:.5em 1em}
.ok{color:#2a7a2a}code{background:#f3f3f3;padding:0 .2em}td.group{font-weight:600;vertical-align:top}
.text{text-align:left}.stepper{border:1px solid #ccc;padding:.5em 1em;margin:.5em 0 1em}
.stepper label{display:flex;gap:1em;align-items:center}.stepper input{flex:1;min-width:0}"""


def _esc(value: Any) -> str:
    return html.escape(str(value))


def readable(value: Any) -> str:
    """A value as people read it in a table: floats to 4 significant digits, yes / no, lists joined with commas,
    mappings as 'key: value' pairs, None (a default taken) as a dash."""
    if value is None:
        return "\u2013"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, (list, tuple)):
        return ", ".join(readable(item) for item in value) if value else "\u2013"
    if isinstance(value, dict):
        return "; ".join(f"{key}: {readable(item)}" for key, item in value.items()) if value else "\u2013"
    return str(value)


def table(rows: list[dict[str, Any]]) -> str:
    """An HTML table of dict rows, columns in first-seen order; floats to 4 significant digits (`readable`), in a
    box that scrolls sideways by itself when it is wider than the page."""
    if not rows:
        return "<p>(none)</p>"
    columns: list[str] = []
    for row in rows:
        columns.extend(key for key in row if key not in columns)

    def cell(value: Any) -> str:
        text = "" if value is None else _esc(readable(value))
        return f"<td class=text>{text}</td>" if isinstance(value, str) else f"<td>{text}</td>"  # numbers right

    head = "".join(f"<th>{_esc(c)}</th>" for c in columns)
    body = "".join("<tr>" + "".join(cell(row.get(c)) for c in columns) + "</tr>" for row in rows)
    return f"<div class='scroll'><table><tr>{head}</tr>{body}</table></div>"


def row(*figures: str, columns: int | None = None) -> str:
    """Figures side by side in equal columns (`columns`, default one per figure) that shrink with the window (never
    a sideways scroll)."""
    return f"<div class='row' style='--n:{columns or max(1, len(figures))}'>{''.join(figures)}</div>"


def figure(context: Context, relative: str, caption: str) -> str:
    """An embedded 8-bit preview of an image file of the run (`relative`, as a step result names it), linked to
    the full-resolution file."""
    image = read_image(context.verified(relative))
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


def stepper(key: str, frames: list[tuple[str, str]], what: str) -> str:
    """A series of frames (caption, HTML such as a `row` of figures) one below the other, with above them a viewer
    and a slider (`what` names it: "depth") that shows one frame at a time: a way to step through a focal stack,
    self-contained (a few lines of script, the frames' own images), and without script the frames are still all
    there. `key` makes the ids unique in the page."""
    slug = "".join(c if c.isalnum() else "-" for c in key)
    blocks = "".join(f"<div class='frame' data-caption='{_esc(caption)}'><h4>{_esc(caption)}</h4>{body}</div>"
                     for caption, body in frames)
    first = _esc(frames[0][0]) if frames else ""
    script = ("<script>(function(){const box=document.getElementById('stepper-%s');"
              "const frames=box.querySelectorAll('.frame'),view=box.querySelector('.view'),"
              "slider=box.querySelector('input'),out=box.querySelector('output');"
              "function show(k){const f=frames[k];view.innerHTML=f.querySelector('.row').outerHTML;"
              "out.textContent=f.dataset.caption;}"
              "slider.addEventListener('input',()=>show(+slider.value));if(frames.length)show(0);})();</script>"
              % slug)
    return (f"<div id='stepper-{slug}'><div class='stepper'><label>{_esc(what)} <input type='range' min='0' "
            f"max='{max(len(frames) - 1, 0)}' value='0' step='1' aria-label='{_esc(what)}'><output>{first}</output>"
            f"</label><div class='view'></div></div><div class='frames'>{blocks}</div></div>{script}")


def _grouped(groups: dict[str, dict[str, Any]], headings: tuple[str, str, str]) -> str:
    """A table of named groups of properties (a device's identity, the versions): one row per property, the group's
    name on its first row."""
    rows = "".join(
        f"<tr>{f'<td class=group rowspan={len(items)}>{_esc(name)}</td>' if n == 0 else ''}<td class=text>"
        f"{_esc(key)}</td><td class=text>{_esc(readable(value))}</td></tr>"
        for name, items in groups.items() for n, (key, value) in enumerate(items.items()))
    head = "".join(f"<th class=text>{_esc(heading)}</th>" for heading in headings)
    return f"<div class='scroll'><table><tr>{head}</tr>{rows}</table></div>"


def _device_groups(devices: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Each device's identity as properties; the SLM's lookup tables are left to 'Calibration used' (the device
    reports those it opened with, before a run measures its own)."""
    groups: dict[str, dict[str, Any]] = {}
    for name, identity in devices.items():
        if isinstance(identity, dict):
            groups[name] = {key: value for key, value in identity.items()
                            if key != "luts" and value not in ({}, [], None, "")}
        elif isinstance(identity, list):
            groups[name] = {"note": identity}
        else:
            groups[name] = {"identity": identity}
    return groups


def _version_groups(versions: dict[str, Any]) -> dict[str, dict[str, Any]]:
    code = versions.get("benchctl_code")
    packages = {name: version for name, version in versions.items() if name != "benchctl_code"}
    groups = {"packages": packages}
    if isinstance(code, dict):
        groups["benchctl code"] = {"version": code.get("version"), "source SHA-256": code.get("source_sha256"),
                                   "git commit": code.get("git_commit"),
                                   "uncommitted changes": code.get("git_dirty")}
    return groups


def _run_section(context: Context, colours: list[str]) -> tuple[str, list[str]]:
    """The header every report ends with: what ran where, parameters, calibration, devices, step timings, versions."""
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
        f"<h2>Run</h2><p><code>{_esc(record.name)}</code>: procedure <b>{_esc(info.get('procedure'))}</b> on profile "
        f"<b>{_esc(info.get('profile'))}</b>, started {_esc(info.get('start'))}"
        + (f", resumed {len(info['resumed'])} time(s)" if info.get("resumed") else "") + ".</p>",
        "<h2>Parameters</h2>" + table([{"parameter": k, "value": "default" if v in (None, {}, []) else v}
                                       for k, v in info["parameters"].items()]),
        "<h2>Calibration used</h2>" + table(rows),
        "<h2>Devices</h2>" + _grouped(_device_groups(devices), ("device", "property", "value")),
        "<h2>Time per kind of step</h2>" + table([{"steps": k, "seconds": round(v, 3)} for k, v in timings.items()]),
        "<h2>Versions</h2>" + _grouped(_version_groups(info["versions"]), ("", "name", "version")),
    ]
    return "".join(parts), warnings


class Report:
    """A run's report as a procedure builds it: a title, sections of HTML (from the helpers here) and warnings;
    `write` stores it with the run's metrics."""

    def __init__(self, title: str) -> None:
        self.title = title
        self.sections: list[str] = []
        self.warnings: list[str] = []
        self.verdicts: list[dict[str, Any]] = []

    def section(self, heading: str, *parts: str, level: int = 2) -> None:
        """A section: its heading (h2; `level` 3 for a sub-section) and its parts (tables, figures, plots, text)."""
        self.sections.append(f"<h{level}>{_esc(heading)}</h{level}>" + "".join(parts))

    def warn(self, *lines: str) -> None:
        """Warnings, shown first in the report (each once)."""
        self.warnings += lines

    def calibrations(self, records: list[dict[str, Any]]) -> None:
        """The calibrations the run measured (`Verdict.record`s), shown in one section after the warnings: per colour
        whether each replaced the previous one, its residual beside the previous one's on the same captures, and why
        one was not stored; a warning for each one not stored or stored by force."""
        self.verdicts += records
        for record in records:
            if not record["stored"]:
                self.warn(rejection_line(record))
            elif record["forced"]:
                self.warn(f"{record['colour']}: new {record['kind']} stored although it failed its acceptance test "
                          f"(accept = \"always\"): {'; '.join(record['failures'])}")

    def _acceptance(self) -> str:
        if not self.verdicts:
            return ""
        rows = [{"colour": r["colour"], "calibration": r["kind"], "measure": r["measure"], "new": r["new"],
                 "compared with": r.get("replaces", "stored one") if r["old"] is not None else "nothing",
                 "its value on the same captures": r["old"],
                 "stored": "yes, forced" if r["forced"] else "yes" if r["stored"] else "no",
                 "failed checks": "; ".join(r["failures"]) or "none"} for r in self.verdicts]
        return ("<h2>New calibration: stored only if it passes its acceptance test</h2>" + table(rows) +
                "<p>A new calibration replaces the one in use (the stored one, else the default: linear lookup "
                "table, ideal optical model) only if light reached the camera, its fit improved on its start, and "
                "on captures it was not fitted to (an optical model's held-out patterns, a lookup table's held-out "
                "gray levels) its residual is below the bound and not above that of the one in use. One that fails "
                "is kept for inspection in <code>rejected/</code> beside the store and in this run's "
                "<code>calibration/</code>; <code>accept = \"always\"</code> stores it anyway.</p>")

    def write(self, context: Context, metrics: dict[str, Any], rows: Sequence[dict[str, Any]] = (),
              colours: Sequence[str] | None = None, headline: Sequence[str] = ()) -> dict[str, Any]:
        """Write metrics.json (`metrics`), metrics.csv (`rows`: one dict per row) and report.html: the title, the
        warnings (this report's and the calibration's for `colours`, default every laser channel of the profile),
        the sections, then the run's details. Returns the report step's result: the `headline` lines the run ends by
        printing, and the warnings."""
        write_json(context.path(layout.METRICS_JSON), metrics)
        write_csv(context.path(layout.METRICS_CSV), rows)
        used = [c.name for c in context.profile.channels] if colours is None else list(colours)
        details, calibration_warnings = _run_section(context, used)
        warnings = list(dict.fromkeys(self.warnings + calibration_warnings))
        box = ("<div class='warn'><b>Warnings</b><ul>" + "".join(f"<li>{_esc(w)}</li>" for w in warnings)
               + "</ul></div>") if warnings else "<p class='ok'>No warnings.</p>"
        page = (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{_esc(self.title)}</title>"
                f"<style>{STYLE}</style></head><body><h1>{_esc(self.title)}</h1>{box}{self._acceptance()}"
                f"{''.join(self.sections)}"
                f"{details}</body></html>")
        atomic_write_bytes(context.path(layout.REPORT), page.encode())
        return {"headline": list(headline), "warnings": list(dict.fromkeys(self.warnings))}
