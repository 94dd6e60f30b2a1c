"""Automatic exposure as procedure steps: one probe frame of the hologram about to be captured, at the working
setpoint, decides the laser power that puts the colour's peak at a fraction of full scale
(`benchctl.capture.exposure.choose_power`), never above the procedure's `max_exposure_power` (else the channel's
max_power_mw): the bound the dry run states. The choice is the probe step's result, kept in the step log, so a
resumed run captures at the same power."""

from __future__ import annotations

from typing import Annotated, Any, Callable, Literal

import numpy as np
from msgspec import Meta

from benchctl.capture.exposure import PEAK_PERCENTILE, choose_power
from benchctl.capture.raw import RawImage
from benchctl.capture.registration import cfa_planes
from benchctl.devices.power import format_power
from benchctl.errors import BenchctlError
from benchctl.profiles import LaserChannel
from benchctl.runner.context import Context, Expose, Step
from benchctl.runner.steps import checked_power, focus_moves, measure, power_w, registered, unregistered
from benchctl.targets import target_plane

ExposureMode = Literal["auto", "fixed"]
""""auto": a probe frame per colour sets the laser power so the peak lands at peak_goal; "fixed": setpoints."""
PeakGoal = Annotated[float, Meta(gt=0.05, le=0.95)]
"""The fraction of full scale automatic exposure aims the peak at."""
ExposureCap = str | dict[str, str] | None
"""The most automatic exposure may set a colour to: one power for every colour ("5mW", "10%" of each channel's
max_power_mw) or one per colour ({ green = "5mW" }); None: each channel's max_power_mw."""


def exposure_cap_w(context: Context, channel: LaserChannel, cap: ExposureCap) -> float:
    """The power automatic exposure may reach on `channel` with the procedure's `max_exposure_power` = `cap`: at most
    the channel's max_power_mw, and not below the probe's power (the probe itself would pass it)."""
    text = cap.get(channel.name) if isinstance(cap, dict) else cap
    if text is None:
        return channel.max_power_mw * 1e-3
    key = f"max_exposure_power{'.' + channel.name if isinstance(cap, dict) else ''}"
    watts = checked_power(text, channel, key)
    probe = power_w(context, channel)
    if watts < probe * (1 - 1e-9):
        raise BenchctlError(f"parameters.{key}: {format_power(watts)} is below {channel.name}'s probe at "
                            f"{format_power(probe)} (its setpoint): lower the setpoint too")
    return watts


def unknown_caps(context: Context, cap: ExposureCap) -> None:
    """A cap for a colour the profile has no laser channel for is an error (a misspelt colour)."""
    names = {channel.name for channel in context.profile.require("laser").channels}
    for name in cap if isinstance(cap, dict) else ():
        if name not in names:
            raise BenchctlError(f"parameters.max_exposure_power.{name}: no laser channel {name!r} "
                                f"(known: {', '.join(sorted(names))})")


def signal_stats(context: Context, image: RawImage, channel: LaserChannel) -> dict[str, float]:
    """Mean, peak and saturated fraction of `channel`'s CFA plane on the ROI's image (or the whole frame)."""
    colour = target_plane(channel)
    saturated = float(np.mean([plane.mean() for plane, _ in cfa_planes(image.saturated, image.cfa, colour)]))
    if not unregistered(context, [channel]):
        values = registered(context, image, channel)
    else:
        values = np.concatenate([plane.ravel() for plane, _ in cfa_planes(image.mosaic, image.cfa, colour)])
    return {"mean": float(values.mean()), "peak": float(np.percentile(values, PEAK_PERCENTILE)),
            "saturated_fraction": saturated}


def probe_step(context: Context, key: str, channel: LaserChannel, frame: Callable[[Context], np.ndarray],
               description: str, peak_goal: float, max_w: float | None = None,
               depth_m: float | None = None) -> Step:
    """One frame of `frame` at the working setpoint, no dark, focused at `depth_m` (as `exposure_step` focuses); its
    result's "auto_exposure" holds the power chosen for the captures that follow (`probed_power`), at most `max_w`
    (`exposure_cap_w`; None: the channel's max_power_mw)."""
    power = power_w(context, channel)
    focus = focus_moves(context, channel, depth_m, required=depth_m is not None)
    limit_w = channel.max_power_mw * 1e-3 if max_w is None else max_w
    capped = limit_w < channel.max_power_mw * 1e-3

    def action(context: Context) -> dict[str, Any]:
        moved = {"focus": context.focus_at(focus[0])} if focus else {}
        # kept as a record: later steps use the power chosen, not the frame
        probe = measure(context, channel, power, frame(context), frames=1, dark_frames=0, read_later=False)
        stats = signal_stats(context, probe.image, channel)
        choice = choose_power(probe.record["setpoint_w"], stats["peak"], stats["saturated_fraction"] > 0, peak_goal,
                              limit_w)
        limit = ((" (the procedure's max_exposure_power)" if capped else " (the channel's max_power_mw)")
                 if choice.limited_by_max else "")
        context.say(f"      auto exposure {channel.name}: peak {stats['peak']:.1%} at {format_power(choice.probe_w)}"
                    f" -> {format_power(choice.power_w)}{limit}")
        return {**probe.record, "auto_exposure": choice.as_dict(), **moved}

    return Step(key, description, action, (Expose(channel.name, power, 1, 0),), focus)


def probed_power(probe_key: str) -> Callable[[Context], float]:
    """The power the probe step `probe_key` chose, read when the capture runs."""
    return lambda context: context.result(probe_key)["auto_exposure"]["power_w"]
