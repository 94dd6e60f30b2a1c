"""Focus calibration: per colour, where the camera's focus mechanism focuses in depth, its backlash and how well it
returns to a position (docs/focus.md).

Per colour, dot-grid holograms reconstructed at several depths around the profile's distance are shown in turn while
the focus is swept: a coarse sweep over the given range (every depth's hologram at every position), then per depth a
fine sweep around its coarse peak moving up and the same positions moving down. The sharpness of each capture
(benchctl.capture.focus.sharpness) peaks where the camera focuses on the dots; each sweep's peak is fitted. The
up-sweep peaks against their depths give the map steps -> depth (approached from below); up minus down peak is the
backlash. Then 20 round trips away from and back to a position on the flank of the middle depth's curve (approached
from below, past the backlash): the spread of the positions read back from their sharpness is the repeatability. On the
simulated bench each is shown beside the simulator's hidden mechanics.

The map is stored per profile in calibration/<profile>/focus.json if it passes its acceptance test
(calibration.acceptance): its peaks were found inside the sweeps, it is monotonic, its residual about the peaks is below
`max_residual_mm` and not above the stored map's on the same peaks.
"""

from __future__ import annotations

import functools
from typing import Annotated, Any

import numpy as np
from msgspec import Meta

from benchctl.capture.exposure import SATURATED_BACKOFF, brightest, clipped, kept_in_range
from benchctl.capture.focus import FLOOR, FocusMap, fit_peak, sharpness
from benchctl.capture.raw import RawImage
from benchctl.capture.registration import dot_grid_target
from benchctl.files import write_json
from benchctl.profiles import LaserChannel, Positive, PositiveInt
from benchctl.runner.api import (
    BenchctlError,
    Calibration,
    Context,
    DarkFrames,
    Expose,
    Frames,
    HologramParameters,
    Report,
    Step,
    Verdict,
    channels,
    compute_hologram,
    line_plot,
    load_image,
    measure,
    power_w,
    row,
    save_hologram,
    table,
    unknown_setpoints,
)

DESCRIPTION = "through-focus sweeps per colour: focus steps <-> depth, backlash and repeatability, stored per profile"
Points = Annotated[int, Meta(ge=5)]
RESTARTS = 3  # fine sweeps taken again at a quarter of the power when a frame clipped


class FocusCalibrationParameters(HologramParameters, kw_only=True):
    """Where and how finely to sweep; one frame per position, no dark (the sharpness takes the background out)."""

    frames: Frames = 1
    dark_frames: DarkFrames = 0
    method: str = "gs"  # phase-only dots at a depth without a carrier or an iris to clean them up
    depths_mm: Annotated[tuple[float, ...], Meta(min_length=3)] = (-1.0, 0.0, 1.0)  # from optics.distance_mm
    sweep_steps: tuple[int, int] = (0, 84000)  # the coarse sweep's first and last position, steps from home
    coarse_points: Points = 21
    fine_span_steps: PositiveInt = 3000  # half-width of each fine sweep; must exceed the backlash
    fine_points: Points = 11
    round_trips: Annotated[int, Meta(ge=2)] = 20
    round_trip_steps: PositiveInt = 5000  # how far each round trip goes away before it comes back
    grid: tuple[Annotated[int, Meta(ge=3)], Annotated[int, Meta(ge=3)]] = (5, 7)  # dots [rows, cols]
    dot_radius_px: Positive = 2.0  # small dots: their image grows as soon as the focus leaves them
    max_residual_mm: Positive = 0.05  # refuse a map whose peaks lie further (RMS) from it


PARAMETERS = FocusCalibrationParameters


def plan(context: Context) -> list[Step]:
    unknown_setpoints(context)
    context.profile.require("focus", "camera", "slm", "optics", "laser")
    params = context.parameters(FocusCalibrationParameters)
    low, high = params.sweep_steps
    if not 0 <= low < high:
        raise BenchctlError(f"parameters.sweep_steps: {list(params.sweep_steps)} must be two positions from home, "
                            f"the first below the second")
    _depths_m(context)  # every depth in front of the SLM, said before anything runs
    used = channels(context)
    steps: list[Step] = []
    for channel in used:
        watts = power_w(context, channel)
        name = channel.name
        expose = functools.partial(_exposures, name, watts, params)
        depths = len(params.depths_mm)
        steps.append(Step(f"focus/{name}/holograms", f"dot holograms at {depths} depths ({name})",
                          _holograms(channel)))
        steps.append(Step(f"focus/{name}/coarse", f"coarse sweep {low}..{high} ({name})",
                          _coarse(channel, watts), expose(params.coarse_points * depths)))
        for k in range(depths):
            steps.append(Step(f"focus/{name}/fine/{k}", f"fine sweep up and down, depth {k + 1} ({name})",
                              _fine(channel, k), expose(2 * params.fine_points)))
        steps.append(Step(f"focus/{name}/repeat", f"{params.round_trips} round trips ({name})",
                          _round_trips(channel), expose(params.round_trips)))
        steps.append(Step(f"focus/{name}/fit", f"steps <-> depth, backlash, repeatability ({name})", _fitter(channel)))
    return steps + [Step("report", "focus calibration report", _reporter(used))]


def _exposures(colour: str, watts: float, params: FocusCalibrationParameters, times: int) -> tuple[Expose, ...]:
    """A sweep's exposures: `times` captures of `colour`, not kept (only their sharpness is)."""
    return (Expose(colour, watts, params.frames, params.dark_frames, keep=False, times=times),)


def _depths_m(context: Context) -> list[float]:
    params = context.parameters(FocusCalibrationParameters)
    distance = context.profile.section("optics").distance_mm
    depths = [distance + offset for offset in params.depths_mm]
    if min(depths) <= 0:
        raise BenchctlError(f"parameters.depths_mm: {min(params.depths_mm):g} mm puts a depth behind the SLM")
    return [depth * 1e-3 for depth in depths]


def _holograms(channel: LaserChannel):
    def action(context: Context) -> dict[str, Any]:
        params = context.parameters(FocusCalibrationParameters)
        profile = context.profile
        slm, optics = profile.section("slm"), profile.section("optics")
        dots, _ = dot_grid_target(slm.shape, optics.roi, params.grid, params.dot_radius_px)
        target = dots.expand(3, -1, -1).contiguous()
        files = []
        for k, depth in enumerate(_depths_m(context)):
            result = compute_hologram(context, target, channel, params, distance_m=depth)
            files.append(save_hologram(context, result.gray, f"focus-{channel.name}-{k}.png"))
        return {"files": files, "depths_mm": [round(d * 1e3, 6) for d in _depths_m(context)]}

    return action


def _capture(context: Context, channel: LaserChannel, power: float, frame: np.ndarray) -> RawImage:
    params = context.parameters(FocusCalibrationParameters)
    return measure(context, channel, power, frame, frames=params.frames, dark_frames=params.dark_frames,
                   keep=False).image


def _comparable_sharpness(context: Context, channel: LaserChannel, power: float,
                          frame: np.ndarray) -> tuple[float, float]:
    """The coarse sweep's sharpness of `frame` at the focus where it stands (floored: comparable across powers), and
    the power it was taken at: starting at `power`, retaken lower or higher (never above the declared setpoint) until
    it neither clips nor drowns in noise."""
    def take(watts: float) -> tuple[float, bool, float]:
        image = _capture(context, channel, watts, frame)
        return brightest(image.mosaic), clipped(image.saturated), sharpness(image.mosaic, floor=FLOOR)

    return kept_in_range(take, power, power_w(context, channel))


def _at_power(context: Context, channel: LaserChannel, power: float, frame: np.ndarray) -> tuple[float, bool]:
    """The sharpness of `frame` at one power, unfloored (the finest measure where every frame of a curve shares
    its exposure), and whether it clipped."""
    image = _capture(context, channel, power, frame)
    return sharpness(image.mosaic), clipped(image.saturated)


def _frames(context: Context, channel: LaserChannel) -> list[np.ndarray]:
    return [load_image(context, name) for name in context.result(f"focus/{channel.name}/holograms")["files"]]


def _coarse(channel: LaserChannel, watts: float):
    def action(context: Context) -> dict[str, Any]:
        params = context.parameters(FocusCalibrationParameters)
        focus, frames = context.instruments.focus, _frames(context, channel)
        positions = [round(p) for p in np.linspace(*params.sweep_steps, params.coarse_points)]
        values: list[list[float]] = [[] for _ in frames]
        powers: list[list[float]] = [[] for _ in frames]
        focus.home()
        for position in positions:
            focus.move_to(position, approach=1, overshoot=params.fine_span_steps)
            for k, frame in enumerate(frames):
                value, power = _comparable_sharpness(context, channel, powers[k][-1] if powers[k] else watts, frame)
                values[k].append(value)
                powers[k].append(power)
        peaks = [_coarse_peak(positions, v) for v in values]
        context.say(f"      {channel.name}: coarse peaks at {', '.join(str(p) for p in peaks)} {focus.unit}(s)")
        return {"positions": positions, "sharpness": values, "peaks": peaks, "power_w": powers}

    return action


def _coarse_peak(positions: list[int], values: list[float]) -> int:
    """Where a coarse sweep peaks: its fitted vertex (the top of a broad peak is flat, and its sharpest point may lie
    a spacing or two from the middle), or its sharpest position where that is at an end of the sweep."""
    try:
        return round(fit_peak(positions, values))
    except BenchctlError:
        return positions[int(np.argmax(values))]


def _fine(channel: LaserChannel, k: int):
    def action(context: Context) -> dict[str, Any]:
        params = context.parameters(FocusCalibrationParameters)
        focus, frame = context.instruments.focus, _frames(context, channel)[k]
        coarse = context.result(f"focus/{channel.name}/coarse")
        centre = coarse["peaks"][k]
        nearest = int(np.argmin(np.abs(np.asarray(coarse["positions"]) - centre)))
        span = params.fine_span_steps
        low, high = params.sweep_steps  # the window stays inside the range the coarse sweep showed reachable
        positions = [round(p) for p in np.linspace(max(centre - span, low), min(centre + span, high),
                                                   params.fine_points)]
        focus.move_to(centre, approach=1, overshoot=span)
        # the power that keeps the brightest frame (the peak's) in range, from the coarse sweep's there
        _, power = _comparable_sharpness(context, channel, coarse["power_w"][k][nearest], frame)
        for _ in range(RESTARTS):
            result: dict[str, Any] = {"positions": positions, "power_w": power}
            any_clipped = False
            for direction, label, order in ((1, "up", positions), (-1, "down", positions[::-1])):
                values = []
                for position in order:
                    focus.move_to(position, approach=direction, overshoot=span)
                    value, saturated = _at_power(context, channel, power, frame)
                    values.append(value)
                    any_clipped |= saturated
                result[label] = values = values if direction > 0 else values[::-1]
                try:
                    result[f"peak_{label}"] = fit_peak(positions, values)
                except BenchctlError as exc:
                    result[f"peak_{label}"], result["problem"] = None, str(exc)
            if not any_clipped:
                return result
            power *= SATURATED_BACKOFF
        return {**result, "problem": f"frames still clip at {power / SATURATED_BACKOFF * 1e3:.3g} mW after "
                                     f"{RESTARTS} sweeps"}

    return action


def _flank(positions: list[int], values: list[float]) -> tuple[list[float], list[float]]:
    """The rising flank of an up-sweep's curve (positions below its best one): (sharpness, position) pairs in
    increasing sharpness, for reading a position back from a sharpness."""
    best = int(np.argmax(values))
    start = int(np.argmin(values[:best + 1]))
    flank_s, flank_p = [values[start]], [float(positions[start])]
    for i in range(start + 1, best + 1):
        if values[i] > flank_s[-1]:  # keep it increasing, so that it can be inverted
            flank_s.append(values[i])
            flank_p.append(float(positions[i]))
    return flank_s, flank_p


def _away(position: int, distance: int, swept: tuple[int, int]) -> int | None:
    """Where a round trip from `position` goes: `distance` above it, or below it where that would pass the swept
    range's end (the focus's travel may end there); None where neither stays inside."""
    low, high = swept
    for away in (position + distance, position - distance):
        if low <= away <= high:
            return away
    return None


def _round_trips(channel: LaserChannel):
    def action(context: Context) -> dict[str, Any]:
        params = context.parameters(FocusCalibrationParameters)
        focus = context.instruments.focus
        middle = int(np.argmin(np.abs(np.asarray(params.depths_mm))))
        fine = context.result(f"focus/{channel.name}/fine/{middle}")
        frame = _frames(context, channel)[middle]
        flank_s, flank_p = _flank(fine["positions"], fine["up"])
        if len(flank_s) < 2:
            return {"problem": "the middle depth's up-sweep has no rising flank to read positions from"}
        half = (flank_s[0] + flank_s[-1]) / 2
        target = round(float(np.interp(half, flank_s, flank_p)))
        power = fine["power_w"]
        span = params.fine_span_steps
        away = _away(target, params.round_trip_steps, params.sweep_steps)
        if away is None:
            return {"problem": f"no round trip of {params.round_trip_steps} steps from {target} stays inside the "
                               f"swept range {list(params.sweep_steps)}: lower round_trip_steps"}
        read, truth = [], []
        for _ in range(params.round_trips):
            focus.move_to(away, approach=1, overshoot=span)
            focus.move_to(target, approach=1, overshoot=span)
            value, _ = _at_power(context, channel, power, frame)
            read.append(float(np.interp(value, flank_s, flank_p)) - target)
            known = focus.ground_truth()
            if known is not None:
                truth.append(known["true_steps"])
        result: dict[str, Any] = {"position": target, "read_steps": read,
                                  "repeatability_steps": float(np.std(read, ddof=1))}
        if truth:
            result["true_offsets_steps"] = [t - float(np.mean(truth)) for t in truth]
            result["true_repeatability_steps"] = float(np.std(truth, ddof=1))
        context.say(f"      {channel.name}: repeatability {result['repeatability_steps']:.3g} {focus.unit}(s) (std of "
                    f"{params.round_trips} returns)" + (f", the simulator's {result['true_repeatability_steps']:.3g}"
                                                        if truth else ""))
        return result

    return action


def _fitter(channel: LaserChannel):
    def action(context: Context) -> dict[str, Any]:
        params = context.parameters(FocusCalibrationParameters)
        name = channel.name
        depths_mm = context.result(f"focus/{name}/holograms")["depths_mm"]
        fines = [context.result(f"focus/{name}/fine/{k}") for k in range(len(depths_mm))]
        repeat = context.result(f"focus/{name}/repeat")
        problems = [f"depth {d:g} mm: {f['problem']}" for d, f in zip(depths_mm, fines) if f.get("problem")]
        problems += [repeat["problem"]] if repeat.get("problem") else []
        verdict = Verdict("focus calibration", name, "residual mm", None, None)
        if problems:
            verdict.check(False, "; ".join(problems))
            return {"problems": problems, "calibration": context.store_calibration(verdict, lambda c: None, {})}
        ups = [f["peak_up"] for f in fines]
        backlash = float(np.median([f["peak_up"] - f["peak_down"] for f in fines]))
        positions = [p for f in fines for p in f["positions"]] + context.result(f"focus/{name}/coarse")["positions"]
        found = FocusMap.fit(list(zip(ups, depths_mm)), approach=1, backlash_steps=backlash,
                             repeatability_steps=repeat["repeatability_steps"],
                             range_steps=(float(min(positions)), float(max(positions))))
        stored = context.calibration.focus_maps().get(name)
        old = None
        if stored is not None:
            before = FocusMap.from_dict(stored)
            old = float(np.sqrt(np.mean([(before.depth_mm(s) - z) ** 2 for s, z in zip(ups, depths_mm)])))
        verdict = Verdict("focus calibration", name, "residual mm", round(found.residual_mm, 6),
                          None if old is None else round(old, 6),
                          details={"backlash_steps": round(backlash, 2),
                                   "repeatability_steps": round(repeat["repeatability_steps"], 3)})
        grid = np.linspace(*found.range_steps, 257)
        slopes = np.diff([found.depth_mm(s) for s in grid])
        verdict.check(bool(np.all(slopes > 0) or np.all(slopes < 0)),
                      "the map is not monotonic over the swept range (a depth would have two positions)")
        verdict.check(found.residual_mm <= params.max_residual_mm, f"residual {found.residual_mm:.4g} mm above the "
                                                                   f"bound {params.max_residual_mm:g} mm")
        verdict.no_worse()
        unit = context.instruments.focus.unit
        run = context.record.name if context.record else None
        entry = {**found.to_dict(), "run": run}
        record = context.store_calibration(verdict, lambda calibration: _store(calibration, name, entry, unit),
                                           {f"focus-{name}.json": lambda path: write_json(path, entry)})
        result: dict[str, Any] = {"map": found.to_dict(), "calibration": record, "unit": unit,
                                  "peaks_down": [f["peak_down"] for f in fines]}
        known = context.instruments.focus.ground_truth()
        if known is not None:
            result["simulator"] = {"backlash_steps": known["backlash_steps"],
                                   "repeatability_steps": repeat.get("true_repeatability_steps")}
        context.say(f"      {name}: backlash {backlash:.1f} {unit}(s)"
                    + (f" (simulator {known['backlash_steps']:g})" if known else "")
                    + f", residual {found.residual_mm * 1e3:.2f} um")
        return result

    return action


def _store(calibration: Calibration, colour: str, entry: dict[str, Any], unit: str) -> None:
    calibration.save_focus(colour, {**entry, "unit": unit})


def _reporter(used: list[LaserChannel]):
    def action(context: Context) -> dict[str, Any]:
        report = Report("Focus calibration")
        fits = {c.name: context.result(f"focus/{c.name}/fit") for c in used}
        report.calibrations([fit["calibration"] for fit in fits.values()])
        rows: list[dict[str, Any]] = []
        headline: list[str] = []
        for channel in used:
            name, fit = channel.name, fits[channel.name]
            if "map" not in fit:
                rows.append({"colour": name, "problem": "; ".join(fit["problems"])})
                headline.append(f"{name}: not calibrated ({'; '.join(fit['problems'])})")
                continue
            found, truth = fit["map"], fit.get("simulator") or {}
            repeat = context.result(f"focus/{name}/repeat")
            rows.append({"colour": name, "unit": fit["unit"], "backlash": round(found["backlash_steps"], 2),
                         "backlash (simulator)": truth.get("backlash_steps"),
                         "repeatability": round(found["repeatability_steps"], 3),
                         "repeatability (simulator)": None if truth.get("repeatability_steps") is None
                         else round(truth["repeatability_steps"], 3),
                         "residual um": round(found["residual_mm"] * 1e3, 3),
                         "mm per 1000 steps": round((found["coefficients"][1]) * 1e3, 5),
                         "stored": fit["calibration"]["stored"]})
            headline.append(f"{name}: backlash {found['backlash_steps']:.1f}"
                            + (f" (simulator {truth['backlash_steps']:g})" if truth else "")
                            + f", repeatability {found['repeatability_steps']:.3g} {fit['unit']}(s)"
                            + ("" if fit["calibration"]["stored"] else "; NOT stored"))
            holograms = context.result(f"focus/{name}/holograms")
            coarse = context.result(f"focus/{name}/coarse")
            sweeps = {f"{depth:g} mm": ([float(p) for p in coarse["positions"]], values)
                      for depth, values in zip(holograms["depths_mm"], coarse["sharpness"])}
            depths = np.asarray(holograms["depths_mm"])
            middle = int(np.argmin(np.abs(depths - float(np.median(depths)))))
            fine = context.result(f"focus/{name}/fine/{middle}")
            lowest = min(fine["up"] + fine["down"])
            sides = {f"{holograms['depths_mm'][middle]:g} mm, approached {label}": (
                [float(p) for p in fine["positions"]], [v - lowest for v in fine[key]])
                for key, label in (("up", "from below"), ("down", "from above"))}
            read = repeat.get("read_steps", [])
            trips = [float(t) for t in range(1, len(read) + 1)]
            returns = {"read back from sharpness": (trips, [r - float(np.mean(read)) for r in read])}
            if "true_offsets_steps" in repeat:
                returns["simulator's true position"] = (trips, repeat["true_offsets_steps"])
            unit = f"{fit['unit']}s"
            report.section(f"{name}", row(
                line_plot(sweeps, f"focus position ({unit} from home)", "sharpness (coarse sweep)"),
                line_plot(sides, f"focus position ({unit} from home)", "sharpness above the fine sweep's lowest"),
                line_plot(returns, "round trip", f"position - mean ({unit})")), level=3)
        report.section("Focus calibration", table(rows),
                       "<p>Steps are the focus driver's own; the map relates positions approached from below to "
                       "depth from the SLM. Backlash: the up-sweep's peak minus the down-sweep's. Repeatability: the "
                       "standard deviation of positions read back from the sharpness after each round trip.</p>")
        return report.write(context, {"procedure": "focus-calibration", "colours": fits}, rows, [c.name for c in used],
                            headline)

    return action
