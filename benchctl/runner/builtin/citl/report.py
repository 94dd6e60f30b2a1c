"""Camera in the loop's report: captured PSNR against iteration (per colour and merged), first and last captures,
model-only SGD at the same budget, seconds per iteration by stage, and the disk it took."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from benchctl.capture.colour_planes import capture_warnings, captured_amplitude, merge_capture, merge_colours
from benchctl.optics import colour_scores
from benchctl.optics.focal_stack import masked_colour_scores, mean_scores
from benchctl.runner.api import Context, Report, figure, line_plot, row, save_image, stepper, table

TIMING_NOTE = ("<p>display_s includes the SLM's settle time; exposure_s runs from shutter release to image ready "
               "without the simulator's rendering (render_s, 0 on a real camera); transfer_s is the image download "
               "where the driver reports it. The software part is decode + register + gradient (gradient_s averaged "
               "over the iterations that step).</p>")


def merged_scores(context: Context, planes: dict[int, np.ndarray], target_roi: torch.Tensor,
                  image: str | None) -> dict[str, Any]:
    """The merged colour image of one iteration's registered planes, scored as colour capture scores its merge:
    with `image` fully (SSIM, warnings) and saved as that image; without, its PSNR alone (a run of hundreds of
    iterations scores each of them)."""
    if image is None:
        merged = merge_colours({colour: captured_amplitude(plane) for colour, plane in planes.items()}, target_roi)
        scores = colour_scores(merged.linear, target_roi, with_ssim=False)
        return {"scores": {k: round(v, 4) for k, v in scores.items()}, "warnings": []}
    capture = merge_capture(planes, target_roi)
    return {"scores": {k: round(v, 4) for k, v in capture.merged_scores.items()}, "warnings": capture.warnings,
            "image": save_image(context, capture.merged.linear, "citl", image, srgb=True)}


def merged_stack_scores(context: Context, stacks: dict[int, np.ndarray], target_roi: torch.Tensor,
                        owner: torch.Tensor, image: str | None) -> dict[str, Any]:
    """The merged colour images of one iteration's focal stacks (colour -> (K, h, w) registered planes), plane k's
    colours balanced over its in-focus region (`owner == k`) and scored there (`masked_colour_scores`): the mean over
    the planes, each plane's, and with `image` each plane's image saved (<image>-plane-<k>.png) and the warnings."""
    planes = next(iter(stacks.values())).shape[0]
    scores, images, warnings = [], [], []
    for k in range(planes):
        region = owner == k
        merged = merge_colours({c: captured_amplitude(s[k]) for c, s in stacks.items()}, target_roi, region)
        scores.append(masked_colour_scores(merged.linear, target_roi, region))
        if image is not None:
            images.append(save_image(context, merged.linear, "citl", f"{image.removesuffix('.png')}-plane-{k + 1}.png",
                                     srgb=True))
            warnings += [f"plane {k + 1}: {w}" for w in capture_warnings({c: s[k] for c, s in stacks.items()},
                                                                         target_roi)]
    mean = {key: round(value, 4) for key, value in mean_scores(scores).items()}
    result: dict[str, Any] = {"scores": mean, "planes": scores, "warnings": warnings}
    return result | ({"files": images} if image is not None else {})


def citl_report(context: Context, summary: dict[str, Any]) -> dict[str, Any]:
    """Camera in the loop: captured PSNR against iteration (per colour and merged), first and last captures side by
    side (and model-only SGD's at the same budget), seconds per iteration by stage, and the disk it took."""
    iterations, merged, baseline = summary["iterations"], summary["merged"], summary["baseline"]
    count = len(merged) - 1
    steps = list(range(count + 1))
    series = {f"{name} (amplitude)": (steps, [r["psnr_amplitude_db"] for r in rows])
              for name, rows in iterations.items()}
    series["merged (sRGB)"] = (steps, [m["scores"]["psnr_srgb_db"] for m in merged])
    if baseline:
        series["model-only SGD, merged (sRGB)"] = ([0, count], [baseline["merged"]["scores"]["psnr_srgb_db"]] * 2)
    planes_mm = summary.get("planes_mm")
    if planes_mm is None:
        pictures = row(*_pictures(context, summary["target_image"], merged[0]["image"], merged[-1]["image"],
                                  baseline["merged"]["image"] if baseline else None, count, baseline))
    else:  # a focal stack: the same four pictures per plane, and a slider through depth
        pictures = stepper("citl", [(f"plane {k + 1} of {len(planes_mm)}: {depth:.2f} mm", row(*_pictures(
            context, summary["target_planes"][k], merged[0]["files"][k], merged[-1]["files"][k],
            baseline["merged"]["files"][k] if baseline else None, count, baseline)))
            for k, depth in enumerate(planes_mm)], "depth")
    colour_rows = []
    for name, rows in iterations.items():
        line = {"colour": name, "start": summary["start"][name]["method"],
                "start simulated PSNR dB": summary["start"][name]["simulated"].get("psnr_amplitude_db"),
                "first PSNR dB": rows[0]["psnr_amplitude_db"], "last PSNR dB": rows[-1]["psnr_amplitude_db"],
                "best PSNR dB": max(r["psnr_amplitude_db"] for r in rows)}
        if baseline:
            base = baseline["colours"][name]["psnr_amplitude_db"]
            line.update({"model-only SGD PSNR dB": base,
                         "CITL - SGD dB": round(rows[-1]["psnr_amplitude_db"] - base, 4)})
        colour_rows.append(line)
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
    csv_rows += [{"colour": "merged", "iteration": k, **{f"merged_{key}": value for key, value in m["scores"].items()}}
                 for k, m in enumerate(merged)]
    report = Report(f"Camera in the loop: {summary['target']}")
    report.warn(*slow, *[w for m in (merged[0], merged[-1]) for w in m["warnings"]])
    for name, rows in iterations.items():
        clipped = max(r["saturated_fraction"] for r in rows)
        if clipped > 0:
            report.warn(f"{name}: up to {clipped:.4%} of the sensor's pixels clipped in an iteration's capture "
                        "(the captured error reads low there): lower the setpoint")
    how = ("<p>Per colour: amplitude PSNR of the registered capture on the ROI, least-squares scaled; merged: the "
           "colour image merged and balanced as colour capture does. Iteration k captures the phase after k Adam "
           "steps on the captured error.</p>") if planes_mm is None else (
        f"<p>A focal stack ({summary['planes_reason']}): each iteration captures every plane, focused there. Per "
        "colour: the mean over the planes of the amplitude PSNR inside each plane's in-focus region, least-squares "
        "scaled; merged: per plane the colour image balanced over that region, its PSNR there, the mean over the "
        "planes. Iteration k captures the phase after k Adam steps on the captured focal-stack error.</p>")
    report.section("Captured PSNR against iteration", line_plot(series, "iteration", "captured PSNR (dB)"), how,
                   pictures)
    report.section("Per colour", table(colour_rows))
    report.section("Merged colour image", table(merged_rows))
    report.section("Seconds per iteration (mean)", table(timing_rows), TIMING_NOTE)
    report.section("Disk", table([{"what": k, "value": v} for k, v in disk.items()]))
    first, last = merged[0]["scores"]["psnr_srgb_db"], merged[-1]["scores"]["psnr_srgb_db"]
    where = "" if planes_mm is None else f" (mean in focus over {len(planes_mm)} planes)"
    headline = [f"{summary['target']}: merged capture PSNR {first:.2f} -> {last:.2f} dB sRGB{where} over {count} CITL "
                "iterations" + (f"; model-only SGD at {baseline['iterations']} iterations "
                                f"{baseline['merged']['scores']['psnr_srgb_db']:.2f} dB" if baseline else "")]
    return report.write(context, {"procedure": "citl", **summary}, csv_rows, list(iterations), headline + slow)


def _pictures(context: Context, target: str, first: str, last: str, baseline_image: str | None, count: int,
              baseline: dict[str, Any] | None) -> list[str]:
    """Target, first and last capture and (where captured) model-only SGD's, as figures."""
    pictures = [figure(context, target, "target (sRGB)"),
                figure(context, first, "first capture (iteration 0, the start hologram)"),
                figure(context, last, f"last capture (iteration {count})")]
    if baseline and baseline_image is not None:
        pictures.append(figure(context, baseline_image, f"model-only SGD, {baseline['iterations']} iterations"))
    return pictures
