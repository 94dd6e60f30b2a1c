"""Building blocks the procedures share: targets, per-colour holograms, exposures, loading what was captured,
saving images. Every step writes its files into the run folder and returns a small JSON-ready result.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any, Literal

import msgspec
import numpy as np
import torch
from msgspec import Meta

from benchctl.capture.raw import RawImage, average_frames, decode_raw, subtract_dark
from benchctl.cgh import Method
from benchctl.devices.power import format_power, parse_power
from benchctl.errors import BenchctlError
from benchctl.files import file_sha256
from benchctl.images import read_image, write_png
from benchctl.optics import linear_to_srgb
from benchctl.profiles import LaserChannel, NonNegative, NonNegativeInt, Profile
from benchctl.runner.hologram_cache import hologram
from benchctl.runner.holograms import resolve_method
from benchctl.runner.procedure import Context, P, Parameters, Step
from benchctl.runner.record import set_aside
from benchctl.targets import CHART_PREFIX, PHOTO_PREFIX, load_target, prepare_target

Frames = Annotated[int, Meta(ge=1)]  # RAW frames averaged per exposure
DarkFrames = Annotated[int, Meta(ge=0)]  # with emission off, after each exposure
Registration = Literal["auto", "stored"]  # "auto": register first when no stored registration fits; "stored": require


class ExposureParameters(Parameters, kw_only=True):
    """Which colours a procedure exposes, at what power, with how many frames: every procedure that exposes."""

    colours: tuple[str, ...] | None = None  # default: every laser channel of the profile
    setpoints: dict[str, str] = msgspec.field(default_factory=dict)  # colour -> "40mW" | "5%" (default: profile's)
    frames: Frames = 2
    dark_frames: DarkFrames = 1
    settle_ms: NonNegative | None = None  # after a new SLM frame (default: the profile's slm.settle_ms)

    def applied_to(self, profile: Profile) -> Profile:
        """The profile with this procedure's SLM settle time, if it gives one."""
        if self.settle_ms is None or profile.slm is None:
            return profile
        return msgspec.structs.replace(profile, slm=msgspec.structs.replace(profile.slm, settle_ms=self.settle_ms))


class HologramParameters(ExposureParameters, kw_only=True):
    """The exposure parameters and how the holograms shown are computed. (Groups stack by derivation: a msgspec
    Struct has one base with fields.)"""

    method: str = "dpac"
    iterations: NonNegativeInt | None = None  # default: the method's own
    seed: NonNegativeInt = 0
    checkpoint: str | None = None  # a trained model for a learned method


def carried(params: Parameters, kind: type[P]) -> P:
    """Another procedure's parameters (`kind`: registration's, when colour capture registers first) with the values
    these parameters share with it, and its own defaults for the rest."""
    shared = set(kind.__struct_fields__) & set(params.__struct_fields__)
    return kind(**{name: getattr(params, name) for name in shared})


def check_method(context: Context, used: list[LaserChannel], params: HologramParameters | None = None) -> Method:
    """The hologram method of `params` (default: the procedure's) and its checkpoint (the file and the geometry it
    was trained for), checked when planning, so a dry run reports what the run would otherwise fail on at its
    first hologram."""
    params = params or context.parameters(HologramParameters)
    try:
        return resolve_method(params.method, context.profile, params.checkpoint,
                              [channel.name for channel in used])[0]
    except BenchctlError as exc:
        raise BenchctlError(f"parameters.method / checkpoint: {exc}") from None


def channels(context: Context) -> list[LaserChannel]:
    """The laser channels a procedure uses: `colours` if given (each must exist), else all of the profile's."""
    profile = context.profile.require("laser")
    names = context.parameters(ExposureParameters).colours or [channel.name for channel in profile.channels]
    return [profile.channel(name) for name in names]


def power_w(context: Context, channel: LaserChannel) -> float:
    """The power a channel is exposed at: the procedure's setpoint for it, else the profile's; never above the
    channel's max_power_mw (checked here, at planning, and again by the laser driver)."""
    text = context.parameters(ExposureParameters).setpoints.get(channel.name)
    watts = channel.setpoint_mw * 1e-3 if text is None else parse_power(text, channel.max_power_mw)
    if watts > channel.max_power_mw * 1e-3 * (1 + 1e-9):
        raise BenchctlError(f"parameters.setpoints.{channel.name}: {format_power(watts)} is above the channel's "
                            f"max_power_mw {channel.max_power_mw:g} mW")
    return watts


def unknown_setpoints(context: Context) -> None:
    """A setpoint for a colour the profile has no laser channel for is an error (a misspelt colour)."""
    names = {channel.name for channel in context.profile.require("laser").channels}
    for name in context.parameters(ExposureParameters).setpoints:
        if name not in names:
            raise BenchctlError(f"parameters.setpoints.{name}: no laser channel {name!r} "
                                f"(known: {', '.join(sorted(names))})")


def target_label(spec: str, taken: set[str]) -> str:
    """A short file-name label for a target: chart:bars -> bars, photo:coffee -> coffee, photos/cat.png -> cat
    (unique in `taken`)."""
    prefix = next((p for p in (CHART_PREFIX, PHOTO_PREFIX) if spec.startswith(p)), None)
    base = spec[len(prefix):] if prefix else Path(spec).stem
    base = "".join(c if c.isalnum() or c in "-_" else "-" for c in base) or "target"
    label, n = base, 2
    while label in taken:
        label, n = f"{base}-{n}", n + 1
    taken.add(label)
    return label


def prepared_target(profile: Profile, spec: str) -> torch.Tensor:
    """(3, H, W) target amplitude on the SLM grid, prepared as the paper prepares targets."""
    profile.require("slm", "optics")
    assert profile.slm is not None and profile.optics is not None
    return prepare_target(load_target(spec, size=profile.optics.roi), profile.slm.shape, profile.optics.roi)


def hologram_step(key: str, label: str, target: torch.Tensor, channel: LaserChannel,
                  options: HologramParameters) -> Step:
    """Compute (or take from the cache) `channel`'s hologram of `target` and keep the frame as displayed."""
    def action(context: Context) -> dict[str, Any]:
        result = hologram(context.profile, target, channel.name, options.method, iterations=options.iterations,
                          seed=options.seed, checkpoint=options.checkpoint, progress=context.progress)
        file = Path("holograms") / f"{label}-{channel.name}.png"
        write_png(context.path(str(file)), result.gray)
        np.save(context.path("images", label, f"simulated-{channel.name}.npy"), result.reconstruction)
        how = "cached" if result.cached else f"{result.seconds:.2f} s"
        context.say(f"      {options.method} {channel.name}: {how}, simulated PSNR "
                    f"{result.scores['psnr_amplitude_db']:.2f} dB amplitude")
        return {"file": str(file), "seconds": round(result.seconds, 4), "cached": result.cached,
                "scores": {k: round(v, 4) for k, v in result.scores.items()},
                "simulated": f"images/{label}/simulated-{channel.name}.npy"}

    return Step(key, f"hologram {label} {channel.name} ({options.method})", action)


def displayed_frame(context: Context, hologram_key: str) -> np.ndarray:
    """The SLM frame a hologram step kept, exactly as it is to be displayed."""
    return read_image(context.path(context.result(hologram_key)["file"]))


def exposure_step(context: Context, key: str, folder: tuple[str, ...], channel: LaserChannel,
                  watts: float | Callable[[Context], float], frame: Callable[[Context], np.ndarray],
                  description: str, *, frames: int | None = None, dark_frames: int | None = None,
                  read_later: bool = True) -> Step:
    """Show a frame, expose it with `channel` alone at `watts` (a number, or a function of the context that
    decides when the step runs, as automatic exposure does), keep the RAW frames and the dark frames in
    raw/<folder>/ (counts: as given, else the procedure's `frames` / `dark_frames`). A retried step first moves
    what its unfinished attempt left aside (kept, never deleted). The result records each file's checksum, which
    a resumed run verifies: under "checksums" for files later steps read (a changed one is captured again), under
    "archived" with `read_later=False` for a record no later step reads (a changed one is reported)."""
    def action(context: Context) -> dict[str, Any]:
        where = context.path("raw", *folder)
        attempt = context.record.attempts.get(key, 1) if context.record else 1
        if attempt > 1:
            set_aside(where, attempt - 1)
        power = watts(context) if callable(watts) else watts
        result = context.bench.expose(where, channel.name, power, frame(context), frames=frames,
                                      dark_frames=darks)
        checksums = {str(Path("raw", *folder, name)): file_sha256(where / name)
                     for name in [*result["frames"], *result["darks"]]}
        return {**result, "folder": str(Path("raw", *folder)), "checksums" if read_later else "archived": checksums}

    params = context.parameters(ExposureParameters)
    frames = params.frames if frames is None else frames
    darks = params.dark_frames if dark_frames is None else dark_frames
    power_text = "the power automatic exposure chooses" if callable(watts) else format_power(watts)
    return Step(key, f"{description}: {channel.name} alone at {power_text}, {frames} frame(s) + {darks} dark",
                action, ("laser", "slm", "camera"))


def load_exposure(context: Context, key: str) -> tuple[RawImage, RawImage | None]:
    """The averaged RAW frames of an exposure step, dark-subtracted, and its averaged dark (None if none)."""
    result = context.result(key)
    folder = context.path(result["folder"])
    lit = average_frames(decode_raw(folder / name) for name in result["frames"])  # decoded one at a time
    if not result["darks"]:
        return lit, None
    dark = average_frames(decode_raw(folder / name) for name in result["darks"])
    return subtract_dark(lit, dark), dark


def write_linear16(path: Path, linear: np.ndarray | torch.Tensor, *, srgb: bool = False) -> str:
    """A linear image in [0, 1] ((h, w) or (3, h, w)) as a 16-bit PNG, optionally sRGB-encoded for viewing."""
    image = torch.as_tensor(np.asarray(linear, dtype=np.float32)).clamp(0, 1)
    if srgb:
        image = linear_to_srgb(image)
    if image.dim() == 3:
        image = image.permute(1, 2, 0)
    write_png(path, (image.numpy() * 65535).round().astype(np.uint16))
    return path.name
