"""What procedures share: the parameter groups, the per-colour planning helpers, the step builders (hologram,
exposure, measurement) and the savers that place every file of a run folder (through `runner.layout`).

Every step writes its files into the run folder and returns a small JSON-ready result that later steps read.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import msgspec
import numpy as np
import torch
from msgspec import Meta

from benchctl.calibration.acceptance import AcceptMode
from benchctl.capture.colour_planes import registered_plane, roi_saturation
from benchctl.capture.focus import FocusMap
from benchctl.capture.raw import RawImage, average_frames, decode_raw, subtract_dark
from benchctl.cgh import DEFAULT_METHOD, Method
from benchctl.devices.power import format_power, parse_power
from benchctl.errors import BenchctlError
from benchctl.files import file_sha256
from benchctl.holograms.cache import Hologram, hologram
from benchctl.holograms.scene import resolve_method
from benchctl.images import read_image, write_png
from benchctl.optics import linear_to_srgb
from benchctl.optics.planes import PlaneChoice
from benchctl.profiles import LaserChannel, NonNegativeInt, Profile, SettleMs
from benchctl.runner import layout
from benchctl.runner.context import Context, Expose, FocusAt, P, Parameters, Step
from benchctl.runner.instruments import Exposure
from benchctl.targets import CHART_PREFIX, PHOTO_PREFIX, load_target, prepare_target, target_plane

Frames = Annotated[int, Meta(ge=1)]  # RAW frames averaged per exposure
DarkFrames = Annotated[int, Meta(ge=0)]  # with emission off, after each exposure
RegistrationMode = Literal["auto", "stored"]
""""auto": register first when no stored camera-SLM registration fits the geometry; "stored": require one."""


class ExposureParameters(Parameters, kw_only=True):
    """Which colours a procedure exposes, at what power, with how many frames: every procedure that exposes."""

    colours: tuple[str, ...] | None = None  # default: every laser channel of the profile
    setpoints: dict[str, str] = msgspec.field(default_factory=dict)  # colour -> "40mW" | "5%" (default: profile's)
    frames: Frames = 2
    dark_frames: DarkFrames = 1
    settle_ms: SettleMs | None = None  # after a new SLM frame (default: the profile's slm.settle_ms)
    # a calibration the procedure measures (registration, lookup tables, optical model) replaces the stored one only
    # if it passes its acceptance test ("tested"), or always ("always": said, and in the report)
    accept: AcceptMode = "tested"

    def applied_to(self, profile: Profile) -> Profile:
        """The profile with this procedure's SLM settle time, if it gives one."""
        if self.settle_ms is None or profile.slm is None:
            return profile
        return msgspec.structs.replace(profile, slm=msgspec.structs.replace(profile.slm, settle_ms=self.settle_ms))


class HologramParameters(ExposureParameters, kw_only=True):
    """The exposure parameters and how the holograms shown are computed. (Groups stack by derivation: a msgspec
    Struct has one base with fields.)"""

    method: str = DEFAULT_METHOD
    iterations: NonNegativeInt | None = None  # default: the method's own (0: its start)
    seed: NonNegativeInt = 0
    checkpoint: str | None = None  # a trained model for a learned method
    # "fitted": holograms computed through the optical model fitted for the bench (model calibration), if any;
    # "ideal": as if none had been fitted (the lookup tables still apply), to measure what the model buys
    optical_model: Literal["fitted", "ideal"] = "fitted"


# -- planning -------------------------------------------------------------------------------------------------------

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
    try:
        return [profile.channel(name) for name in names]
    except BenchctlError as exc:
        raise BenchctlError(f"parameters.colours: {exc}") from None


def power_w(context: Context, channel: LaserChannel) -> float:
    """The power a channel is exposed at: the procedure's setpoint for it, else the profile's; never above the
    channel's max_power_mw (checked here, at planning, and again by the laser driver)."""
    text = context.parameters(ExposureParameters).setpoints.get(channel.name)
    if text is None:
        return channel.setpoint_mw * 1e-3
    return checked_power(text, channel, f"setpoints.{channel.name}")


def checked_power(text: str, channel: LaserChannel, key: str) -> float:
    """A power the procedure's parameter `key` gives for `channel` ("20mW", "5%" of its max_power_mw), in watts,
    never above the channel's max_power_mw; a BenchctlError naming the key otherwise."""
    try:
        watts = parse_power(text, channel.max_power_mw)
    except BenchctlError as exc:
        raise BenchctlError(f"parameters.{key}: {exc}") from None
    if watts > channel.max_power_mw * 1e-3 * (1 + 1e-9):
        raise BenchctlError(f"parameters.{key}: {format_power(watts)} is above the channel's max_power_mw "
                            f"{channel.max_power_mw:g} mW")
    return watts


def unknown_setpoints(context: Context) -> None:
    """A setpoint for a colour the profile has no laser channel for is an error (a misspelt colour)."""
    names = {channel.name for channel in context.profile.require("laser").channels}
    for name in context.parameters(ExposureParameters).setpoints:
        if name not in names:
            raise BenchctlError(f"parameters.setpoints.{name}: no laser channel {name!r} "
                                f"(known: {', '.join(sorted(names))})")


def unregistered(context: Context, used: list[LaserChannel]) -> list[LaserChannel]:
    """The channels of `used` without a stored camera-SLM registration that fits the geometry."""
    stored = context.calibration.registrations()
    return [channel for channel in used if channel.name not in stored]


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


def prepared_target(profile: Profile, spec: str, key: str | None = None) -> torch.Tensor:
    """(3, H, W) target amplitude on the SLM grid, prepared as the paper prepares targets; an unknown or unreadable
    target is an error naming the parameter `key` it came from (e.g. "parameters.targets")."""
    profile.require("slm", "optics")
    assert profile.slm is not None and profile.optics is not None
    try:
        return prepare_target(load_target(spec, size=profile.optics.roi), profile.slm.shape, profile.optics.roi)
    except BenchctlError as exc:
        if key is None:
            raise
        raise BenchctlError(f"{key}: {exc}") from None


# -- holograms ------------------------------------------------------------------------------------------------------

def compute_hologram(context: Context, target: torch.Tensor, channel: LaserChannel,
                     options: HologramParameters, *, distance_m: float | None = None,
                     depth_m: torch.Tensor | None = None, planes: PlaneChoice | None = None) -> Hologram:
    """`channel`'s hologram of `target` (3, H, W amplitude on the SLM grid) as `options` say: its frame as
    displayed, simulated reconstruction and scores; from the hologram cache when it was computed before.
    `distance_m`: reconstructed at that depth instead of the profile's distance (the focus calibration's). A scene
    with depth gives its `depth_m` (H, W) and the planes it is shown at: the reconstruction is its focal stack."""
    bench = context.bench if options.optical_model == "fitted" else context.bench.without_model()
    bench = bench if distance_m is None else bench.at_distance(distance_m)
    return hologram(bench, target, channel.name, options.method, iterations=options.iterations,
                    seed=options.seed, checkpoint=options.checkpoint, progress=context.progress, depth_m=depth_m,
                    planes=planes)


def hologram_step(key: str, label: str, target: torch.Tensor, channel: LaserChannel,
                  options: HologramParameters | None = None) -> Step:
    """Compute (or take from the cache) `channel`'s hologram of `target` with `options` (default: the procedure's
    parameters) and keep the frame as displayed and the simulated reconstruction."""
    def action(context: Context) -> dict[str, Any]:
        how = options or context.parameters(HologramParameters)
        result = compute_hologram(context, target, channel, how)
        cached = "cached" if result.cached else f"{result.seconds:.2f} s"
        context.say(f"      {how.method} {channel.name}: {cached}, simulated PSNR "
                    f"{result.scores['psnr_amplitude_db']:.2f} dB amplitude")
        return {"file": save_hologram(context, result.gray, f"{label}-{channel.name}.png"),
                "seconds": round(result.seconds, 4), "cached": result.cached,
                "scores": {k: round(v, 4) for k, v in result.scores.items()},
                "simulated": save_array(context, result.reconstruction, label, f"simulated-{channel.name}.npy")}

    method = options.method if options is not None else "the procedure's method"
    return Step(key, f"hologram {label} {channel.name} ({method})", action)


def displayed_frame(context: Context, hologram_key: str) -> np.ndarray:
    """The SLM frame a hologram step kept, exactly as it is to be displayed."""
    return load_image(context, context.result(hologram_key)["file"])


def shown(hologram_key: str) -> Callable[[Context], np.ndarray]:
    """The frame function of an exposure that shows what hologram step `hologram_key` kept."""
    return lambda context: displayed_frame(context, hologram_key)


# -- exposures ------------------------------------------------------------------------------------------------------

@dataclass
class Measurement:
    """One exposure: what `Instruments.expose` reported, the JSON-ready record a step keeps (with, where the RAW
    frames were kept, their folder and checksums), and the decoded image (lit frames' mean minus the darks')."""

    exposure: Exposure
    record: dict[str, Any]

    @functools.cached_property
    def image(self) -> RawImage:
        """Decoded from the frames' bytes on first use (a step that only keeps the files never decodes)."""
        lit = average_frames(decode_raw(frame.data) for frame in self.exposure.frames)
        if not self.exposure.darks:
            return lit
        return subtract_dark(lit, average_frames(decode_raw(frame.data) for frame in self.exposure.darks))


def measure(context: Context, channel: LaserChannel, power: float, frame: np.ndarray, *, frames: int,
            dark_frames: int, keep: bool = True, read_later: bool = True, within: str | None = None) -> Measurement:
    """Show `frame`, expose it with `channel` alone at `power`, capture `frames` RAW frames and `dark_frames`
    dark ones: an exposure the running step declared. With `keep` the RAW files are kept in the step's raw folder
    (its sub-folder `within`, for one of several exposures of the step) and the record holds each file's checksum,
    which a resumed run verifies: under "checksums" for files later steps read (a changed one is captured again),
    under "archived" with `read_later=False` for a record no later step reads (a changed one is reported)."""
    exposure = context.expose(channel.name, power, frame, frames=frames, dark_frames=dark_frames, keep=keep,
                              within=within)
    record = dict(exposure.result)
    if keep:
        assert context.step is not None
        folder = layout.raw_folder(context.step.key, within)
        names = [*exposure.result["frames"], *exposure.result["darks"]]
        record["folder"] = folder
        record["checksums" if read_later else "archived"] = {
            f"{folder}/{name}": file_sha256(context.path(f"{folder}/{name}")) for name in names}
    return Measurement(exposure, record)


def focus_moves(context: Context, channel: LaserChannel, depth_m: float | None = None, *,
                required: bool = False) -> tuple[FocusAt, ...]:
    """The focus move that focuses the camera at `depth_m` from the SLM (None: the profile's target plane) for
    `channel`, through its stored focus calibration (positions, approach side and overshoot past the backlash); checked
    when planning. None where the profile has no [focus], or no focus calibration for the colour unless `required`
    (then an error saying to calibrate first): a capture at the target plane leaves an uncalibrated focus where it
    is."""
    profile = context.profile
    if profile.focus is None:
        if required:
            profile.require("focus")
        return ()
    entry = context.calibration.focus_maps().get(channel.name)
    if entry is None:
        if not required:
            return ()
        raise BenchctlError(f"no focus calibration for {channel.name} on profile {profile.name!r} with its [focus] "
                            f"device ({context.calibration.focus_device()}): run procedures/focus_calibration.toml "
                            "first")
    depth = profile.section("optics").distance_mm * 1e-3 if depth_m is None else depth_m
    found = FocusMap.from_dict(entry)
    try:
        steps = found.steps_for(depth)
    except BenchctlError as exc:
        raise BenchctlError(f"{channel.name}: {exc}") from None
    return (FocusAt(channel.name, depth, steps, found.approach, found.overshoot_steps),)


def exposure_step(context: Context, key: str, channel: LaserChannel, watts: float | Callable[[Context], float],
                  frame: Callable[[Context], np.ndarray], description: str, *, frames: int | None = None,
                  dark_frames: int | None = None, read_later: bool = True, max_w: float | None = None,
                  depth_m: float | None = None) -> Step:
    """A step that shows `frame(context)` and exposes it with `channel` alone at `watts` (a number, or a function
    of the context that decides when the step runs, as automatic exposure does: `max_w` bounds what it may choose,
    else the channel's max_power_mw), keeping the RAW frames and dark frames (counts: as given, else the procedure's
    `frames` / `dark_frames`) for later steps (`load_exposure`). The camera focuses first at `depth_m` from the SLM
    (which needs the focus calibration), or by default at the target plane where the focus is calibrated
    (`focus_moves`). A retried step first moves what its unfinished
    attempt left aside (kept, never deleted)."""
    params = context.parameters(ExposureParameters)
    count = params.frames if frames is None else frames
    darks = params.dark_frames if dark_frames is None else dark_frames
    focus = focus_moves(context, channel, depth_m, required=depth_m is not None)

    def action(context: Context) -> dict[str, Any]:
        power = watts(context) if callable(watts) else watts
        moved = [context.focus_at(at) for at in focus]
        record = measure(context, channel, power, frame(context), frames=count, dark_frames=darks,
                         read_later=read_later).record
        return {**record, "focus": moved[0]} if moved else record

    declared = Expose(channel.name, None if callable(watts) else watts, count, darks,
                      max_w=max_w if callable(watts) else None)
    return Step(key, description, action, (declared,), focus)


def load_exposure(context: Context, key: str) -> tuple[RawImage, RawImage | None]:
    """The averaged RAW frames of an exposure step, dark-subtracted, and its averaged dark (None if none)."""
    result = context.result(key)
    folder = result["folder"]
    # decoded one at a time, each checked against its checksum first
    lit = average_frames(decode_raw(context.verified(f"{folder}/{name}")) for name in result["frames"])
    if not result["darks"]:
        return lit, None
    dark = average_frames(decode_raw(context.verified(f"{folder}/{name}")) for name in result["darks"])
    return subtract_dark(lit, dark), dark


def _registration(context: Context, channel: LaserChannel) -> tuple[int, np.ndarray, tuple[int, int],
                                                                          tuple[int, int]]:
    profile = context.profile
    assert profile.slm is not None and profile.optics is not None
    stored = context.calibration.registrations().get(channel.name)
    if stored is None:
        raise BenchctlError(f"no stored camera-SLM registration for {channel.name} on profile {profile.name!r}: run "
                            "procedures/registration.toml first")
    homography = np.asarray(stored["homography"], dtype=np.float64)
    return target_plane(channel), homography, profile.slm.shape, profile.optics.roi


def registered(context: Context, image: RawImage, channel: LaserChannel) -> np.ndarray:
    """`channel`'s CFA plane of `image` on the target plane's ROI (linear, full scale 1), through the stored
    camera-SLM registration."""
    return registered_plane(image, *_registration(context, channel))


def registered_saturation(context: Context, image: RawImage, channel: LaserChannel) -> float:
    """The fraction of the ROI whose registered value draws on a saturated sensor pixel."""
    return roi_saturation(image, *_registration(context, channel))


# -- files ----------------------------------------------------------------------------------------------------------

def save_hologram(context: Context, gray: np.ndarray, *name: str, read_later: bool = True) -> str:
    """An SLM frame exactly as displayed (8-bit PNG) under the run's holograms; returns its run-relative path. Its
    checksum joins the step's result (`Context.wrote`; `read_later=False`: a record no later step reads)."""
    relative = layout.hologram_file(*name)
    write_png(context.path(relative), gray)
    return context.wrote(relative, read_later=read_later)


def save_image(context: Context, linear: np.ndarray | torch.Tensor, *name: str, srgb: bool = False) -> str:
    """A linear image in [0, 1] ((h, w) or (3, h, w)) as a 16-bit PNG under the run's images, optionally
    sRGB-encoded for viewing; returns its run-relative path (checksum in the step's result, `Context.wrote`)."""
    image = torch.as_tensor(np.asarray(linear, dtype=np.float32)).clamp(0, 1)
    if srgb:
        image = linear_to_srgb(image)
    if image.dim() == 3:
        image = image.permute(1, 2, 0)
    relative = layout.image_file(*name)
    write_png(context.path(relative), (image.numpy() * 65535).round().astype(np.uint16))
    return context.wrote(relative)


def save_array(context: Context, array: np.ndarray | torch.Tensor, *name: str) -> str:
    """An array (.npy) under the run's images; returns its run-relative path (checksum in the step's result)."""
    relative = layout.image_file(*name)
    np.save(context.path(relative), np.asarray(array))
    return context.wrote(relative)


def load_image(context: Context, relative: str) -> np.ndarray:
    """An image a finished step saved (as a step result names it), checked against its checksum first: a damaged
    one sends the run back to the step that saved it (`Context.verified`)."""
    return read_image(context.verified(relative))


def load_array(context: Context, relative: str) -> np.ndarray:
    """An array a finished step saved (`save_array`), checked as `load_image` checks images."""
    return np.load(context.verified(relative), allow_pickle=False)


def state_path(context: Context, *name: str) -> Path:
    """A file (or folder) of the run's resumable state."""
    return context.path(layout.state_file(*name))
