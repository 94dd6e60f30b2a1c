"""What `benchctl focus` does: open the profile's focus, act, report (lines to print). Loads no torch.

`go` needs the focus calibration (calibration/<profile>/focus.json, `procedures/focus_calibration.toml`): it turns a
depth into steps for one colour and arrives there from the side the calibration says, past the backlash.
"""

from __future__ import annotations

from benchctl.calibration.store import Calibration
from benchctl.capture.focus import FocusMap, parse_depth
from benchctl.devices.focus import Focus, FocusMove, open_focus
from benchctl.errors import BenchctlError
from benchctl.profiles import Profile


def _maps(profile: Profile) -> dict[str, FocusMap]:
    return {colour: FocusMap.from_dict(entry) for colour, entry in Calibration.store(profile).focus_maps().items()}


def _where(focus: Focus, maps: dict[str, FocusMap]) -> list[str]:
    """Where the focus is, in steps and, per calibrated colour, in depth."""
    status = focus.status()
    position = status["position"]
    lines = [f"position: {'unknown (not homed since connecting)' if position is None else position} {focus.unit}(s)"
             + ("" if status["reported"] is None else f" (the device reports {status['reported']})")]
    if position is not None:
        for colour, found in maps.items():
            lines.append(f"  {colour}: focused at {found.depth_mm(position):.4g} mm from the SLM (calibrated)")
    return lines


def focus_status(profile: Profile) -> list[str]:
    """Identity, believed position and, where calibrated, the depth it focuses at per colour."""
    maps = _maps(profile)
    with open_focus(profile) as focus:
        identity = ", ".join(f"{k} {v}" for k, v in focus.identity().items())
        lines = [f"focus: {identity}", *_where(focus, maps)]
    if not maps:
        lines.append("not calibrated: `benchctl run procedures/focus_calibration.toml` relates steps to depth")
    return lines


def focus_home(profile: Profile) -> list[str]:
    """Drive to the home end stop: position 0 from then on."""
    with open_focus(profile) as focus:
        return [_line(focus, focus.home())]


def focus_move(profile: Profile, steps: int) -> list[str]:
    """Move `steps` (signed) from where the focus is."""
    with open_focus(profile) as focus:
        return [_line(focus, focus.move(steps))]


def focus_go(profile: Profile, depth: str, channel: str | None) -> list[str]:
    """Focus at `depth` ('70.2mm', '14.3D') for `channel` (default: the only calibrated colour, else green if
    calibrated), from the calibrated side, past the backlash; homes first if the position is not known."""
    target_m = parse_depth(depth)
    maps = _maps(profile)
    if not maps:
        raise BenchctlError(f"{profile.name}: no focus calibration for this profile and focus device; run "
                            f"`benchctl run procedures/focus_calibration.toml --profile {profile.name}` first")
    if channel is None:
        channel = next(iter(maps)) if len(maps) == 1 else "green" if "green" in maps else None
        if channel is None:
            raise BenchctlError(f"focus go: choose a colour with --channel ({', '.join(maps)})")
    if channel not in maps:
        raise BenchctlError(f"focus go: colour {channel!r} is not focus-calibrated (calibrated: {', '.join(maps)})")
    found = maps[channel]
    steps = found.steps_for(target_m)
    with open_focus(profile) as focus:
        move = focus.move_to(steps, approach=found.approach, overshoot=found.overshoot_steps)
        side = "below" if found.approach > 0 else "above"
        return [f"{channel}: {target_m * 1e3:.4g} mm from the SLM is {steps} {focus.unit}(s) (approached from "
                f"{side}, {found.overshoot_steps} past the backlash first where needed)", _line(focus, move)]


def _line(focus: Focus, move: FocusMove) -> str:
    return f"focus: {move.describe(focus.unit)}"
