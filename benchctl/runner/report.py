"""Run reports: metrics.json, metrics.csv and a self-contained report.html (previews embedded as PNG data,
full-resolution files linked beside it, plots as inline SVG), so a user understands a run from the report alone.
"""

from __future__ import annotations

import base64
import html
import json
import statistics
from pathlib import Path
from collections.abc import Iterable
from typing import Any

import cv2
import numpy as np

from benchctl.files import atomic_write_bytes, write_csv, write_json
from benchctl.images import read_image
from benchctl.optics.metrics import pareto_front
from benchctl.runner.plots import front_plot, line_plot
from benchctl.runner.procedure import Context
from benchctl.runner.steps import HologramParameters

PREVIEW_WIDTH = 480
PEAK_PERCENTILE_TEXT = "99.9th percentile"
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


def figure(folder: Path, relative: str, caption: str) -> str:
    """An embedded 8-bit preview of an image file of the run (linked to the full-resolution file)."""
    image = read_image(folder / relative)
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
    devices_path = record.folder / "devices.json"
    devices = json.loads(devices_path.read_text()) if devices_path.is_file() else context.bench.identities
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


def write_report(context: Context, title: str, body: str, colours: list[str], warnings: list[str]) -> Path:
    """report.html: title, warnings first, the procedure's own sections, then the run's details."""
    record = context.record
    assert record is not None
    details, calibration_warnings = _run_section(context, colours)
    warnings = list(dict.fromkeys(warnings + calibration_warnings))
    box = ("<div class='warn'><b>Warnings</b><ul>" + "".join(f"<li>{_esc(w)}</li>" for w in warnings)
           + "</ul></div>") if warnings else "<p class='ok'>No warnings.</p>"
    page = (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{_esc(title)}</title><style>{STYLE}</style>"
            f"</head><body><h1>{_esc(title)}</h1>{box}{body}{details}</body></html>")
    return atomic_write_bytes(record.folder / "report.html", page.encode())


def _flat(prefix: str, scores: dict[str, Any]) -> dict[str, Any]:
    return {f"{prefix}{key}": value for key, value in scores.items()}


def colour_capture_report(context: Context, results: list[dict[str, Any]], colours: list[str]) -> dict[str, Any]:
    """Per target: target / simulation / capture side by side, per-colour and merged scores, generation time
    against error; metrics.json and metrics.csv (one row per target and colour, plus the merged row)."""
    record = context.record
    assert record is not None
    rows, body, warnings = [], [], []
    for result in results:
        label = result["label"]
        for name, colour in result["colours"].items():
            rows.append({"target": result["target"], "label": label, "colour": name,
                         "generation_s": colour["generation_s"], "cached": colour["cached"], "gain": colour["gain"],
                         "saturated_fraction": colour["saturated_fraction"], "power_w": colour["power_w"],
                         "peak": colour["peak"],
                         **_flat("simulated_", colour["simulated"]), **_flat("capture_", colour["capture"])})
        rows.append({"target": result["target"], "label": label, "colour": "merged",
                     **_flat("simulated_", result["merged"]["simulated"]),
                     **_flat("capture_", result["merged"]["capture"])})
        warnings += [f"{label}: {w}" for w in result["warnings"]]
        folder = result["folder"]
        pictures = "".join(figure(record.folder, f"{folder}/{result['files'][key]}", caption) for key, caption in (
            ("target", "target (sRGB)"), ("simulated", "simulated reconstruction"), ("capture", "merged capture")))
        score_rows = [{"colour": name, "generation s": c["generation_s"],
                       "simulated PSNR dB (amplitude)": c["simulated"]["psnr_amplitude_db"],
                       "capture PSNR dB (amplitude)": c["capture"]["psnr_amplitude_db"],
                       "simulated SSIM (sRGB)": c["simulated"]["ssim_srgb"],
                       "capture SSIM (sRGB)": c["capture"]["ssim_srgb"], "gain": c["gain"],
                       "laser mW": c["power_w"] * 1e3, "peak": c["peak"], "saturated": c["saturated_fraction"]}
                      for name, c in result["colours"].items()]
        merged = result["merged"]
        merged_rows = [{"image": kind, "PSNR dB linear": s["psnr_linear_db"], "PSNR dB sRGB": s["psnr_srgb_db"],
                        "SSIM sRGB": s["ssim_srgb"]} for kind, s in merged.items()]
        body.append(f"<h2>Target {_esc(result['target'])} ({_esc(label)})</h2>{pictures}"
                    f"<h3>Per colour (ROI, least-squares scaled)</h3>{table(score_rows)}"
                    f"<h3>Merged colour image</h3>{table(merged_rows)}")
    speed = [{"label": r["label"], "colour": r["colour"], "generation s": r["generation_s"],
              "simulated PSNR dB": r.get("simulated_psnr_amplitude_db"),
              "capture PSNR dB": r.get("capture_psnr_amplitude_db")} for r in rows if r["colour"] != "merged"]
    method = context.parameters(HologramParameters).method
    methods = method if isinstance(method, str) else ", ".join(method)
    body.append(f"<h2>Generation time against error ({_esc(methods)})</h2>{table(speed)}"
                "<p>Generation time is the time it took to compute the hologram (for a cached hologram, when it was "
                "computed). PSNR in amplitude on the ROI after least-squares scaling.</p>")
    front = method_front(results)
    if len(front) > 1:
        points = [(r["method"], r["seconds per frame"], r["capture PSNR dB sRGB"], r["on front"]) for r in front]
        body.append("<h2>Speed against error across methods</h2>"
                    + front_plot(points, "seconds per frame (every colour)", "merged capture PSNR dB (sRGB)")
                    + table(front) + "<p>Per method, means over the targets: the time to compute one frame of "
                    "every colour in the target, and the merged capture's PSNR. Filled markers are on the Pareto "
                    "front: no other method is both at least as fast and at least as good.</p>")
    write_json(record.folder / "metrics.json", {"procedure": "colour-capture", "method": method, "targets": results,
                                                "front": front})
    write_csv(record.folder / "metrics.csv", rows)
    write_report(context, f"Colour capture: {', '.join(r['label'] for r in results)}", "".join(body), colours,
                 warnings)
    headline = [f"{r['label']}: merged capture PSNR {r['merged']['capture']['psnr_srgb_db']:.2f} dB sRGB, SSIM "
                f"{r['merged']['capture']['ssim_srgb']:.3f} (simulated {r['merged']['simulated']['psnr_srgb_db']:.2f} "
                f"dB, {r['merged']['simulated']['ssim_srgb']:.3f}); generation "
                + ", ".join(f"{n} {c['generation_s']:.2f} s" for n, c in r["colours"].items()) for r in results]
    return {"headline": headline, "warnings": warnings}


def method_front(results: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per hologram method of a colour capture: mean seconds per frame (all colours of a target), mean
    merged PSNR / SSIM captured and simulated, and whether it is on the Pareto front of time against captured
    PSNR."""
    groups: dict[str, list[dict[str, Any]]] = {}
    for result in results:
        groups.setdefault(result["method"], []).append(result)
    rows = []
    for method, group in groups.items():
        rows.append({
            "method": method, "targets": len(group),
            "seconds per frame": _mean(sum(c["generation_s"] for c in r["colours"].values()) for r in group),
            "capture PSNR dB sRGB": _mean(r["merged"]["capture"]["psnr_srgb_db"] for r in group),
            "capture SSIM sRGB": _mean(r["merged"]["capture"]["ssim_srgb"] for r in group),
            "simulated PSNR dB sRGB": _mean(r["merged"]["simulated"]["psnr_srgb_db"] for r in group),
        })
    on_front = pareto_front([(r["seconds per frame"], r["capture PSNR dB sRGB"]) for r in rows])
    return [row | {"on front": flag} for row, flag in zip(rows, on_front)]


def _mean(values: Iterable[float]) -> float:
    return round(statistics.fmean(values), 4)


def registration_report(context: Context, fits: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """Per colour: dots used, reprojection error, scale, and (simulated bench) the error against the truth."""
    record = context.record
    assert record is not None
    rows = [{"colour": name, "inliers": f["inliers"], "points": f["points"], "rms px": f["rms_px"],
             "max px": f["max_px"], "sensor px per SLM px": f["scale"], "mirrored": f["mirrored"],
             "ROI corners vs simulator, max px": (f["simulator"] or {}).get("corner_error_max_px")}
            for name, f in fits.items()]
    pictures = "".join(figure(record.folder, context.result(f"registration/hologram/{name}")["file"],
                              f"dot-grid hologram {name}") for name in fits)
    write_json(record.folder / "metrics.json", {"procedure": "registration", "colours": fits})
    write_csv(record.folder / "metrics.csv", rows)
    write_report(context, "Camera-SLM registration", f"<h2>Fits</h2>{table(rows)}{pictures}", list(fits), [])
    return {"headline": [f"{r['colour']}: RMS {r['rms px']:.3f} px over {r['inliers']}/{r['points']} dots"
                         for r in rows]}


def power_sweep_report(context: Context, analyses: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """Signal against setpoint per colour (plot and table), linearity, and the exposure advice."""
    record = context.record
    assert record is not None
    rows, summary, warnings = [], [], []
    for name, analysis in analyses.items():
        for point in analysis["points"]:
            rows.append({"colour": name, "setpoint_mw": point["setpoint_w"] * 1e3,
                         "measured_mw": None if point["measured_w"] is None else point["measured_w"] * 1e3,
                         "mean": point["mean"], "peak": point["peak"],
                         "saturated_fraction": point["saturated_fraction"],
                         "exposure_s": point["exposure_s"]})
        if "warning" in analysis:
            warnings.append(analysis["warning"])
            continue
        fit = analysis["mean_fit"]
        summary.append({"colour": name, "R^2": fit["r2"], "max deviation": fit["max_deviation"],
                        "mean per mW": fit["slope"] * 1e-3, "offset": fit["offset"],
                        "working setpoint mW": analysis["working_setpoint_w"] * 1e3,
                        "peak at working setpoint": analysis["peak_at_working"],
                        "recommended exposure s": analysis.get("recommended_exposure_s")})
        if analysis["saturated_levels"]:
            warnings.append(f"{name}: {analysis['saturated_levels']} level(s) saturated (left out of the fits)")
        if analysis["peak_at_working"] >= 1.0:
            warnings.append(f"{name}: the working setpoint saturates the sensor at this exposure")
    series = {name: ([p["setpoint_w"] * 1e3 for p in a["points"]], [p["mean"] for p in a["points"]])
              for name, a in analyses.items()}
    body = (f"<h2>Signal against setpoint</h2>{line_plot(series, 'setpoint (mW)', 'mean signal (full scale = 1)')}"
            f"<h2>Linearity and exposure</h2>{table(summary)}<p>Fits use the unsaturated levels. The recommended "
            f"exposure puts the peak ({PEAK_PERCENTILE_TEXT}) at 80 % of full scale at the working setpoint.</p>"
            f"<h2>Measurements</h2>{table(rows)}")
    write_json(record.folder / "metrics.json", {"procedure": "power-sweep", "colours": analyses})
    write_csv(record.folder / "metrics.csv", rows)
    write_report(context, "Laser power sweep", body, list(analyses), warnings)
    return {"headline": [f"{s['colour']}: R^2 {s['R^2']:.5f}, recommended exposure "
                         + (f"{s['recommended exposure s']:.4g} s" if s["recommended exposure s"] else "n/a")
                         for s in summary] + warnings}


def lut_report(context: Context, fits: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """Measured gray -> phase per colour (plot), depth, and on the simulated bench the error against the truth."""
    record = context.record
    assert record is not None
    series = {name: ([float(g) for g in fit["grays"]], fit["phases"]) for name, fit in fits.items()}
    rows = [{"colour": name, "grays measured": len(fit["grays"]), "phase depth rad": fit["depth_rad"],
             "RMS vs simulator rad": (fit.get("simulator") or {}).get("rms_rad"),
             "max vs simulator rad": (fit.get("simulator") or {}).get("max_rad"), "table": fit["file"]}
            for name, fit in fits.items()]
    signals = {name: ([float(g) for g in fit["grays"]], fit["signals"]) for name, fit in fits.items()}
    body = (f"<h2>Measured phase response</h2>{line_plot(series, 'gray level', 'phase - phase(0) (rad)')}"
            f"<h2>Zero-order signal</h2>{line_plot(signals, 'gray level', 'signal (full scale = 1)')}"
            f"<h2>Tables</h2>{table(rows)}<p>The tables are stored per profile and used by later runs for every "
            "channel whose table the profile does not name ([slm.lut]).</p>")
    write_json(record.folder / "metrics.json", {"procedure": "lut-calibration", "colours": fits})
    write_csv(record.folder / "metrics.csv", rows)
    write_report(context, "SLM lookup-table calibration", body, list(fits), [])
    return {"headline": [f"{r['colour']}: depth {r['phase depth rad']:.3f} rad"
                         + (f", RMS {r['RMS vs simulator rad']:.4f} rad vs the simulator"
                            if r["RMS vs simulator rad"] is not None else "") for r in rows]}


def model_calibration_report(context: Context, fits: dict[str, dict[str, Any]], terms: list[str],
                             warnings: list[str]) -> dict[str, Any]:
    """Per colour: fitted Zernike coefficients (waves), beam, crosstalk, zero order, residual before and after; the
    fit's loss curves."""
    record = context.record
    assert record is not None
    rows = [{"colour": name, **{f"{t} (waves)": f["zernike_waves"].get(t) for t in terms},
             "waist mm": round(f["waist_mm"], 4), "offset mm": [round(v, 4) for v in f["offset_mm"]],
             "crosstalk px": f.get("crosstalk_px", 0.0),
             **({"crosstalk px, this colour's fit": f["crosstalk_fitted_px"]} if "crosstalk_fitted_px" in f else {}),
             "zero order": f.get("zero_order", 0.0),
             "camera blur px": f.get("camera_blur_px", 0.0),
             "residual before": f["initial_residual"], "residual after": f["residual"],
             "patterns": f"{f['patterns']}{' + flat' if f.get('flat') else ''}",
             "fit s": f["seconds"],
             "registered through a model": "yes" if f.get("registration_through_model") else "no"}
            for name, f in fits.items()]
    by_quantity = [{"": key, **{row["colour"]: row[key] for row in rows}} for key in rows[0] if key != "colour"]
    curves = {name: (list(range(1, len(f["losses"]) + 1)), f["losses"]) for name, f in fits.items()}
    body = (f"<h2>Fitted model</h2>{table(by_quantity)}<p>Wavefront error at the SLM: ANSI/OSA Zernike terms, "
            "RMS-normalised over the disc circumscribing the panel. Residual: RMS misfit of the registered captures "
            "relative to their RMS, after the best gain and offset (gain alone for the flat pattern), with the ideal "
            "model (before) and the fitted one (after). Crosstalk: one value for the panel where several colours "
            "were fitted (the median of their fits: the liquid crystal's fringing is the same in pixels at every "
            "wavelength; the residuals are those of each colour's own fit). Camera blur: the blur of the registered "
            "captures (camera optics, sampling, resampling), fitted so that it is not taken for the bench's; "
            "holograms do not use it. The model is stored per profile and used by generation, SGD and the "
            "simulated scores of later runs.</p>"
            f"<h2>Fit</h2>{line_plot(curves, 'Adam step', 'relative residual (first half blurred)')}")
    write_json(record.folder / "metrics.json", {"procedure": "model-calibration", "colours": fits})
    write_csv(record.folder / "metrics.csv", rows)
    write_report(context, "Model calibration", body, list(fits), warnings)
    return {"headline": [f"{r['colour']}: residual {r['residual before']:.3f} -> {r['residual after']:.3f}"
                         for r in rows]}


def citl_report(context: Context, summary: dict[str, Any]) -> dict[str, Any]:
    """Camera in the loop: captured PSNR against iteration (per colour and merged), first and last captures side by
    side (and model-only SGD's at the same budget), seconds per iteration by stage, and the disk it took."""
    record = context.record
    assert record is not None
    iterations, merged, baseline = summary["iterations"], summary["merged"], summary["baseline"]
    count = len(merged) - 1
    steps = list(range(count + 1))
    series = {f"{name} (amplitude)": (steps, [r["psnr_amplitude_db"] for r in rows])
              for name, rows in iterations.items()}
    series["merged (sRGB)"] = (steps, [m["scores"]["psnr_srgb_db"] for m in merged])
    if baseline:
        series["model-only SGD, merged (sRGB)"] = ([0, count], [baseline["merged"]["scores"]["psnr_srgb_db"]] * 2)
    pictures = figure(record.folder, summary["target_image"], "target (sRGB)")
    pictures += figure(record.folder, merged[0]["image"], "first capture (iteration 0, the start hologram)")
    pictures += figure(record.folder, merged[-1]["image"], f"last capture (iteration {count})")
    if baseline:
        pictures += figure(record.folder, baseline["merged"]["image"],
                           f"model-only SGD, {baseline['iterations']} iterations")
    colour_rows = []
    for name, rows in iterations.items():
        row = {"colour": name, "start": summary["start"][name]["method"],
               "start simulated PSNR dB": summary["start"][name]["simulated"].get("psnr_amplitude_db"),
               "first PSNR dB": rows[0]["psnr_amplitude_db"], "last PSNR dB": rows[-1]["psnr_amplitude_db"],
               "best PSNR dB": max(r["psnr_amplitude_db"] for r in rows)}
        if baseline:
            base = baseline["colours"][name]["psnr_amplitude_db"]
            row.update({"model-only SGD PSNR dB": base,
                        "CITL - SGD dB": round(rows[-1]["psnr_amplitude_db"] - base, 4)})
        colour_rows.append(row)
    merged_rows = [{"image": "first (iteration 0)", **merged[0]["scores"]},
                   {"image": f"last (iteration {count})", **merged[-1]["scores"]}]
    if baseline:
        merged_rows.append({"image": f"model-only SGD ({baseline['iterations']} iterations)",
                            **baseline["merged"]["scores"]})
    keys = summary["timing_keys"]
    timing_rows, slow = [], []
    for name, rows in iterations.items():
        mean = {key: sum(r["timing"][key] for r in rows) / len(rows) for key in keys}
        stepped = rows[:-1] or rows  # the last iteration only captures: no gradient to average in
        mean["gradient_s"] = sum(r["timing"]["gradient_s"] for r in stepped) / len(stepped)
        software = mean["decode_s"] + mean["register_s"] + mean["gradient_s"]
        hardware = mean["display_s"] + mean["exposure_s"]
        device = rows[0].get("device", "cpu")
        timing_rows.append({"colour": name, "gradient on": device, **{key: round(v, 4) for key, v in mean.items()},
                            "software (decode+register+gradient)": round(software, 4),
                            "display/settle + exposure": round(hardware, 4)})
        if software > hardware:
            slow.append(f"{name}: software {software:.3f} s per iteration exceeds display/settle + exposure "
                        f"{hardware:.3f} s" + (" (the gradient ran on the CPU: parameters.device = 'auto' takes a "
                                               "CUDA GPU when there is one)" if device == "cpu" else ""))
    disk = summary["disk"]
    csv_rows = [{"colour": name, "iteration": r["iteration"], "loss": r["loss"],
                 "psnr_amplitude_db": r["psnr_amplitude_db"], **r["timing"]}
                for name, rows in iterations.items() for r in rows]
    csv_rows += [{"colour": "merged", "iteration": k, **_flat("merged_", m["scores"])} for k, m in enumerate(merged)]
    body = (f"<h2>Captured PSNR against iteration</h2>{line_plot(series, 'iteration', 'captured PSNR (dB)')}"
            f"<p>Per colour: amplitude PSNR of the registered capture on the ROI, least-squares scaled; merged: the "
            f"colour image merged and balanced as colour capture does. Iteration k captures the phase after k Adam "
            f"steps on the captured error.</p>{pictures}"
            f"<h2>Per colour</h2>{table(colour_rows)}<h2>Merged colour image</h2>{table(merged_rows)}"
            f"<h2>Seconds per iteration (mean)</h2>{table(timing_rows)}<p>display_s includes the SLM's settle time; "
            "exposure_s runs from shutter release to image ready without the simulator's rendering (render_s, 0 "
            "on a real camera); transfer_s is the image download where the driver reports it. The software part is "
            "decode + register + gradient (gradient_s averaged over the iterations that step).</p>"
            f"<h2>Disk</h2>{table([{'what': k, 'value': v} for k, v in disk.items()])}")
    warnings = slow + [w for m in (merged[0], merged[-1]) for w in m["warnings"]]
    for name, rows in iterations.items():
        clipped = max(r["saturated_fraction"] for r in rows)
        if clipped > 0:
            warnings.append(f"{name}: up to {clipped:.4%} of the sensor's pixels clipped in an iteration's capture "
                            "(the captured error reads low there): lower the setpoint")
    write_json(record.folder / "metrics.json", {"procedure": "citl", **summary})
    write_csv(record.folder / "metrics.csv", csv_rows)
    write_report(context, f"Camera in the loop: {summary['target']}", body, list(iterations), warnings)
    first, last = merged[0]["scores"]["psnr_srgb_db"], merged[-1]["scores"]["psnr_srgb_db"]
    headline = [f"{summary['target']}: merged capture PSNR {first:.2f} -> {last:.2f} dB sRGB over {count} CITL "
                "iterations" + (f"; model-only SGD at {baseline['iterations']} iterations "
                                f"{baseline['merged']['scores']['psnr_srgb_db']:.2f} dB" if baseline else "")]
    return {"headline": headline + slow, "warnings": warnings}
