"""Camera-in-the-loop (CITL) optimisation (Peng et al. 2020): per colour, start from a model hologram (DPAC or SGD),
then each iteration displays the phase, captures RAW frames, decodes them, registers the colour's CFA plane onto
the target's ROI with the stored registration, and takes one Adam step on the phase with the straight-through
gradient (cgh.citl): the loss is the captured amplitude's error, differentiated through the propagation model (the
fitted optical model from calibration/<profile>/ when there is one, as SGD uses it).

Each iteration is one resumable step. It reads the phase and the optimiser state the previous one saved
(state/<colour>/<k>.npz, float32 as optimised) and saves the next, so a resumed run continues bit for bit; the
state two iterations back is deleted. Each state file's SHA-256 is in the result of the step that wrote it and is
checked before use: a damaged one (missing, truncated, edited, of another shape, pickled) sends the run back to the
step that wrote it, which recomputes it from its own state (or, that one gone too, from further back).

Divergence stops the run: a phase that is no longer finite after a step, or a captured loss above DIVERGENCE times
iteration 0's. A resume then goes back one iteration and continues from the last good phase at half the learning
rate (each state file carries the rate's scale).

Disk: the RAW frames (and the displayed SLM frame) are kept for the first and last iterations and every
`keep_raw_every`-th; every iteration keeps its registered plane as a 16-bit PNG on the ROI
(images/citl/<colour>/<k>.png). Iteration k records the loss and captured PSNR of phase k (the one it displayed) and
the seconds spent per stage; the last (k = iterations) only captures the final phase.

The learning rate falls from `learning_rate` to 0 over the iterations (cosine; `schedule = "constant"` keeps it):
late gradients are mostly camera noise, and constant steps then walk the phase away from its best.

The model is only the gradient's: where the bench departs far from it (the aberrated simulated bench without a
fitted model) the gradient points elsewhere and the captured PSNR rises for a few iterations, then falls; run
model calibration first (README, "Camera in the loop").

With `exposure = "auto"` (default) one probe frame of the start hologram per colour sets the laser power that
puts its peak at `peak_goal` of full scale; every iteration and the baseline are captured at that power.

The gradient runs where `device` says: "auto" (default) takes a CUDA GPU when torch sees one, else the CPU. At
full size on a 2-core CPU the gradient (0.3-0.5 s, four FFTs of the ROI's padded grid) is most of an iteration's
software time, and the part a GPU speeds up; decoding and registering stay on the CPU. A run resumed on another
device continues from the saved state, equal to float32 rounding rather than bit for bit.

With `baseline` (default on), model-only SGD with the same number of Adam steps (start_iterations + iterations
for an SGD start) is captured the same way, so the report compares both at one budget.

A scene with depth (`target = "rgbd:..."`) is optimised on its focal stack: its planes chosen as focal-stack capture
chooses them (`planes`), the start hologram and the baseline made for those planes (layered DPAC, multi-plane SGD),
and every iteration captures the phase at every plane, the camera focused there through the focus calibration, each
plane's RAW frames in raw/<step>/plane-<k>/ and registered plane in images/citl/<colour>/<k>-plane-<j>.png; the loss
is the focal-stack loss of those captures (each plane where the scene is in focus there), its gradient through the
model's focal stack (cgh.citl.straight_through_stack_loss). The captured PSNR of an iteration is the mean over the
planes of the in-focus PSNR. A 2D target is captured at the target plane, focused there where the focus is calibrated.
"""

from __future__ import annotations

import hashlib
import io
import math
import time
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any, Literal, TypeAlias

import numpy as np
import torch
from msgspec import Meta

from benchctl.cgh.citl import straight_through_loss, straight_through_stack_loss
from benchctl.files import atomic_write_bytes
from benchctl.optics import crop_roi, lsq_scale, psnr
from benchctl.optics.focal_stack import focal_stack_loss, focal_stack_scores
from benchctl.optics.planes import MAX_PLANES
from benchctl.profiles import LaserChannel
from benchctl.runner.api import (
    BenchctlError,
    Context,
    DarkFrames,
    Expose,
    ExposureCap,
    ExposureMode,
    ExposureParameters,
    FocusAt,
    Frames,
    HologramParameters,
    PeakGoal,
    RegistrationMode,
    Step,
    StepRedo,
    channels,
    compute_hologram,
    exposure_cap_w,
    focus_moves,
    load_image,
    measure,
    power_w,
    prepared_target,
    probe_step,
    probed_power,
    registered,
    save_hologram,
    save_image,
    shown,
    state_path,
    target_plane,
    unknown_caps,
    unknown_setpoints,
)
from benchctl.runner.builtin import focal_stack, registration
from benchctl.runner.builtin.citl.report import citl_report, merged_scores, merged_stack_scores
from benchctl.scenes import is_scene
from benchctl.targets import active_channels

DESCRIPTION = "camera in the loop: per colour, display, capture, register and step the phase on the captured error"


class CitlParameters(ExposureParameters, kw_only=True):
    """What to optimise on the bench, how long, how fast, and what to keep on disk."""

    target: str = "chart:bars"  # a 2D target, or a scene with depth (rgbd:...): optimised on its focal stack
    # a scene with depth: "auto" (the planes its depth and the bench's axial resolution need) or a count
    planes: Literal["auto"] | Annotated[int, Meta(ge=1, le=MAX_PLANES)] = "auto"
    frames: Frames = 1  # RAW frames averaged per iteration
    dark_frames: DarkFrames = 0  # per iteration (the decoder removes the black level)
    iterations: Annotated[int, Meta(ge=1, le=10_000)] = 50  # Adam steps on the captured error
    # Adam moves each phase value by about this (radians) per step: above 1 a step scrambles the hologram
    learning_rate: Annotated[float, Meta(gt=0, le=1)] = 0.05
    # "cosine": the learning rate falls from learning_rate to 0 over the iterations (late steps, whose gradient is
    # mostly camera noise, stay small); "constant"
    schedule: Literal["cosine", "constant"] = "cosine"
    start: Literal["dpac", "sgd"] = "dpac"  # the model hologram to start from
    start_iterations: Annotated[int, Meta(ge=1)] = 100  # model-only SGD steps of an SGD start
    # disk policy: RAW frames kept for the first and last iteration and every Nth (0: first and last only)
    keep_raw_every: Annotated[int, Meta(ge=0)] = 10
    baseline: bool = True  # capture model-only SGD at the same budget too
    registration: RegistrationMode = "auto"
    exposure: ExposureMode = "auto"  # "auto": a probe frame of the start hologram sets the power for every capture
    peak_goal: PeakGoal = 0.7  # fraction of full scale
    max_exposure_power: ExposureCap = None  # the most "auto" may set: "5mW", "10%" or per colour; default max_power_mw
    device: Literal["auto", "cpu", "cuda"] = "auto"  # where the gradient runs; "auto": a CUDA GPU if there is one


PARAMETERS = CitlParameters
DIVERGENCE = 4.0  # a captured loss above this many times iteration 0's: the phase diverged
MIN_SCALE = 1 / 64  # the learning rate is halved on divergence at most down to this fraction

TIMING_KEYS = ("display_s", "exposure_s", "transfer_s", "decode_s", "register_s", "gradient_s", "laser_s",
               "save_s", "render_s", "total_s")
"""Seconds per iteration: display_s (SLM frame shown, settle included), exposure_s (shutter release to image
ready, all frames, the simulator's rendering excluded), transfer_s (image download, where the driver reports it),
decode_s, register_s, gradient_s (model forward, backward, Adam step), laser_s (setpoint, emission on/off and
read-backs), save_s (images, state), render_s (the simulated camera's rendering: 0 on a real camera), total_s."""


def plan(context: Context) -> list[Step]:
    """Registration if needed; per colour: the start hologram, iterations + 1 captures, the baseline; the report."""
    params = context.parameters(CitlParameters)
    gradient_device(params.device)
    unknown_setpoints(context)
    unknown_caps(context, params.max_exposure_power)
    scene = None
    if is_scene(params.target):
        scene = focal_stack.stack_scene(context, params.target, focal_stack.scene_label(params.target, set()),
                                        None if params.planes == "auto" else params.planes, False, channels(context),
                                        "parameters.target")
        target, used = scene.amplitude, list(scene.lit)
    else:
        target = prepared_target(context.profile, params.target, "parameters.target")
        present = active_channels(target)
        used = [c for c in channels(context) if present[target_plane(c)]]
    if not used:
        raise BenchctlError(f"parameters.target: {params.target!r} has none of the colours "
                            f"{[c.name for c in channels(context)]}")
    count = params.iterations
    views = {c.name: _views(context, c, scene) for c in used}  # the focus calibration checked before registering
    steps = registration.registration_first(context, used, params, params.registration)
    for channel in used:
        name, focus = channel.name, views[channel.name]
        steps.append(Step(f"citl/{name}/start", f"start hologram {name} ({params.start})",
                          _starter(target, channel, scene), memory=scene.memory if scene is not None else None))
        cap = exposure_cap_w(context, channel, params.max_exposure_power)
        power: Any = None if params.exposure == "auto" else power_w(context, channel)
        if params.exposure == "auto" and scene is None:
            steps.append(probe_step(context, f"citl/{name}/probe", channel, shown(f"citl/{name}/start"),
                                    "probe exposure of the start hologram", params.peak_goal, cap))
            power = probed_power(f"citl/{name}/probe")
        elif params.exposure == "auto":
            assert scene is not None
            probes, power = focal_stack.plane_probes(context, f"citl/{name}/probe", channel,
                                                     shown(f"citl/{name}/start"), scene.planes.planes_m,
                                                     params.peak_goal, "probe exposure of the start hologram", cap)
            steps += probes
        declared = None if callable(power) else power
        for k in range(count + 1):
            what = "capture the final phase" if k == count else "capture, register, step the phase"
            steps.append(Step(f"citl/{name}/{k:04d}", f"CITL {name} iteration {k}/{count}: {what}",
                              _iteration(target, channel, k, scene, focus, power),
                              (Expose(name, declared, params.frames, params.dark_frames,
                                      keeps_raw(k, count, params.keep_raw_every), times=len(focus), max_w=cap),),
                              tuple(at for at in focus if at is not None)))
        if params.baseline:
            steps.append(Step(f"citl/{name}/baseline", f"model-only SGD {name} at {_budget(params)} iterations, "
                              "captured", _baseline(target, channel, scene, focus, power),
                              (Expose(name, declared, params.frames, params.dark_frames, times=len(focus),
                                      max_w=cap),),
                              tuple(at for at in focus if at is not None)))
    steps.append(Step("report", "metrics.json, metrics.csv and report.html", _reporter(target, used, scene)))
    return steps


def _views(context: Context, channel: LaserChannel, scene: focal_stack.StackScene | None) -> list[FocusAt | None]:
    """Where each capture of an iteration focuses: a 2D target once, at the target plane where the focus is
    calibrated (else wherever it is: None); a scene with depth at each of its planes (which needs the calibration)."""
    if scene is None:
        return list(focus_moves(context, channel)) or [None]
    return [focus_moves(context, channel, depth, required=True)[0] for depth in scene.planes.planes_m]


def _budget(params: CitlParameters) -> int:
    """Adam steps CITL's final phase has had: the SGD start's (if any) plus its own."""
    return params.iterations + (params.start_iterations if params.start == "sgd" else 0)


def gradient_device(choice: str) -> torch.device:
    """The device of parameters.device ("auto": CUDA when torch sees a GPU, else the CPU)."""
    if choice == "auto":
        choice = "cuda" if torch.cuda.is_available() else "cpu"
    elif choice == "cuda" and not torch.cuda.is_available():
        raise BenchctlError(f"parameters.device: 'cuda', but torch {torch.__version__} sees no CUDA GPU "
                            "(use 'auto' or 'cpu')")
    return torch.device(choice)


def _synchronised(device: torch.device) -> None:
    """Wait for `device`'s queued work, so a clock read afterwards times it (CUDA runs asynchronously)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def learning_rate(params: CitlParameters, k: int) -> float:
    """The learning rate of iteration k's Adam step (k = 0 .. iterations - 1)."""
    if params.schedule == "constant":
        return params.learning_rate
    return params.learning_rate * 0.5 * (1 + math.cos(math.pi * k / params.iterations))


def keeps_raw(k: int, iterations: int, every: int) -> bool:
    """Whether iteration k keeps its RAW frames: the first, the last, and every `every`-th (0: none between)."""
    return k in (0, iterations) or (every > 0 and k % every == 0)


def _target_roi(context: Context, target: torch.Tensor, channel: LaserChannel) -> torch.Tensor:
    assert context.profile.optics is not None
    return crop_roi(target[target_plane(channel)], context.profile.optics.roi)


# -- the optimiser state ----------------------------------------------------------------------------------------

def _state_file(context: Context, channel: LaserChannel, k: int) -> Path:
    return state_path(context, channel.name, f"{k:04d}.npz")


class StateDamaged(ValueError):
    """A state file that cannot be used as saved: missing, changed since saved, unreadable or inconsistent."""


def _save_state(path: Path, phase: torch.Tensor, optimiser: torch.optim.Adam | None, lr_scale: float = 1.0) -> str:
    """The phase, Adam's moments and step count, exactly (float32), and the learning rate's scale, written atomically;
    returns the file's SHA-256, which the step's result keeps."""
    arrays: dict[str, np.ndarray] = {"phase": phase.detach().cpu().numpy(), "step": np.zeros((), np.float32),
                                     "lr_scale": np.array(lr_scale, np.float64)}
    state = optimiser.state.get(optimiser.param_groups[0]["params"][0]) if optimiser else None
    if state:
        arrays.update({key: state[key].cpu().numpy() for key in ("step", "exp_avg", "exp_avg_sq")})
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)  # type: ignore[arg-type]  # numpy's stub: a key could be its bool allow_pickle
    atomic_write_bytes(path, buffer.getvalue())
    return hashlib.sha256(buffer.getvalue()).hexdigest()


def _read_state(path: Path, sha256: str | None) -> dict[str, np.ndarray]:
    """The arrays of a state file, checked against the SHA-256 recorded when it was saved (if given), read without
    pickles, their shapes consistent; StateDamaged says what is wrong."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise StateDamaged(f"{path.name}: {exc.strerror or exc}") from None
    if sha256 is not None and (actual := hashlib.sha256(data).hexdigest()) != sha256:
        raise StateDamaged(f"{path.name} changed since it was saved (SHA-256 {actual[:12]}..., saved {sha256[:12]}...)")
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as archive:
            arrays = {name: archive[name] for name in archive.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise StateDamaged(f"{path.name} cannot be read as a saved state: {exc}") from None
    phase = arrays.get("phase")
    moments = [arrays.get(name) for name in ("exp_avg", "exp_avg_sq")] if float(arrays.get("step", 0)) > 0 else []
    if (phase is None or phase.ndim != 2 or phase.dtype != np.float32
            or any(m is None or m.shape != phase.shape for m in moments) or not np.isfinite(phase).all()):
        raise StateDamaged(f"{path.name} does not hold a finite float32 phase (with Adam's moments of its shape)")
    return arrays


def _load_state(path: Path, learning_rate: float, device: torch.device | str = "cpu",
                sha256: str | None = None) -> tuple[torch.Tensor, torch.optim.Adam, float]:
    """The phase (a leaf to optimise, on `device`), its Adam optimiser and the learning rate's scale as `_save_state`
    left them (StateDamaged if the file is not as saved)."""
    data = _read_state(path, sha256)
    phase = torch.from_numpy(data["phase"].copy()).to(device).requires_grad_()
    optimiser = torch.optim.Adam([phase], lr=learning_rate)
    if float(data["step"]) > 0:  # Adam keeps its step count on the CPU, its moments beside the parameter
        optimiser.state[phase] = {"step": torch.from_numpy(data["step"].copy()),
                                  "exp_avg": torch.from_numpy(data["exp_avg"].copy()).to(device),
                                  "exp_avg_sq": torch.from_numpy(data["exp_avg_sq"].copy()).to(device)}
    return phase, optimiser, float(data.get("lr_scale", 1.0))


def _writer(channel: LaserChannel, k: int) -> str:
    """The step that saves iteration k's state: the start for k = 0, else iteration k - 1."""
    return f"citl/{channel.name}/start" if k == 0 else f"citl/{channel.name}/{k - 1:04d}"


def _diverged(channel: LaserChannel, k: int, what: str, rate: float, scale: float, redo: str) -> BenchctlError:
    """The error that stops a diverged run; a resume goes back to `redo` at half the learning rate's `scale`."""
    halved = f" x {scale:g} after earlier divergences" if scale != 1 else ""
    where = f"CITL {channel.name} diverged at iteration {k}: {what} (learning_rate {rate:g}{halved})"
    if scale / 2 < MIN_SCALE:
        return BenchctlError(f"{where}, already halved down to {MIN_SCALE:g}: start a new run with a lower "
                             "learning_rate")
    back = "this iteration's start" if redo.endswith(f"{k:04d}") else f"iteration {k - 1}'s phase"
    return StepRedo(f"{where}: the run stops; a resume continues from {back} at half that rate, or start a new run "
                    "with a lower learning_rate", redo, stop=True, diverged=True)


# -- one capture, decoded and registered --------------------------------------------------------------------------

Power: TypeAlias = "float | Callable[[Context], float]"  # the captures' laser power, or how to read it when they run


def _capture(context: Context, channel: LaserChannel, gray: np.ndarray, keep: bool, views: list[FocusAt | None],
             power: Power) -> tuple[np.ndarray, dict[str, Any], dict[str, float]]:
    """Display `gray`, expose it once per view (focused there, where a view says: a scene's planes), RAW files kept
    with `keep` (each plane's in its own sub-folder), else only in memory; decode and register the colour's plane:
    (ROI linear signal (h, w), or (K, h, w) for K planes; JSON-ready record; seconds per stage, summed over views)."""
    params = context.parameters(CitlParameters)
    watts = power(context) if callable(power) else power
    clock = time.perf_counter
    planes, records = [], []
    timing: dict[str, float] = {}
    for j, view in enumerate(views):
        within = f"plane-{j + 1}" if len(views) > 1 else None
        moved = context.focus_at(view) if view is not None else None
        measured = measure(context, channel, watts, gray, frames=params.frames, dark_frames=params.dark_frames,
                           keep=keep, read_later=False, within=within)
        start = clock()
        image = measured.image
        decoded = clock()
        planes.append(registered(context, image, channel))
        registered_at = clock()
        exposure = measured.exposure
        metadata = [frame.metadata for frame in (*exposure.frames, *exposure.darks)]
        render = sum(float(m.get("render_s", 0.0)) for m in metadata)
        transfer = sum(float(m.get("transfer_s", 0.0)) for m in metadata)
        for key, value in {"display_s": exposure.timing["display_s"], "laser_s": exposure.timing["laser_s"],
                           "exposure_s": exposure.timing["capture_s"] - render - transfer, "transfer_s": transfer,
                           "render_s": render, "decode_s": decoded - start,
                           "register_s": registered_at - decoded}.items():
            timing[key] = timing.get(key, 0.0) + value
        record = {key: value for key, value in measured.record.items()
                  if key in ("setpoint_w", "slm_frame", "folder", "archived")}
        record["saturated_fraction"] = round(float(image.saturation_fraction), 6)
        records.append({**record, **({"focus": moved} if moved is not None else {})})
    if len(views) == 1:
        return planes[0], records[0], timing
    archived = {name: digest for r in records for name, digest in r.get("archived", {}).items()}
    record = {"setpoint_w": records[0]["setpoint_w"], "slm_frame": records[0]["slm_frame"],
              "saturated_fraction": max(r["saturated_fraction"] for r in records),
              "views": [{k: v for k, v in r.items() if k != "archived"} for r in records],
              **({"archived": archived, "folder": records[0]["folder"].rsplit("/", 1)[0]} if keep else {})}
    return np.stack(planes), record, timing


def _amplitude_error(plane: np.ndarray, target_roi: torch.Tensor,
                     scene: focal_stack.StackScene | None) -> tuple[torch.Tensor, float, float]:
    """The captured amplitude (sqrt of the signal, negatives clipped), its MSE and PSNR against the target after
    least-squares scaling; of a focal stack (K, h, w), the focal-stack loss and the mean over the planes of the
    in-focus PSNR."""
    captured = torch.from_numpy(np.sqrt(np.clip(plane, 0.0, None)))
    if scene is not None:
        masks = _masks(scene)
        scores = focal_stack_scores(captured, target_roi, masks, scene.planes.planes_m)
        return captured, float(focal_stack_loss(captured, target_roi, masks)), scores.mean["psnr_amplitude_db"]
    scaled = lsq_scale(captured, target_roi) * captured
    loss = torch.nn.functional.mse_loss(scaled, target_roi)
    return captured, float(loss), float(psnr(scaled, target_roi, data_range=1.0))


def _masks(scene: focal_stack.StackScene) -> torch.Tensor:
    """The scene's in-focus masks (K, h, w) on the ROI: each pixel belongs to the plane nearest its depth."""
    planes = len(scene.planes.planes_m)
    return torch.nn.functional.one_hot(scene.owner, planes).movedim(-1, 0).to(torch.float32)


def _save_plane(context: Context, channel: LaserChannel, name: str, plane: np.ndarray) -> dict[str, Any]:
    """The registered plane as a 16-bit PNG on the ROI, scaled by its maximum (recorded to undo the scaling); a
    focal stack (K, h, w) as one such PNG per plane (`planes`)."""
    if plane.ndim == 3:
        return {"planes": [_save_plane(context, channel, f"{name}-plane-{j + 1}", p) for j, p in enumerate(plane)]}
    peak = float(max(plane.max(), 1e-12))
    file = save_image(context, np.clip(plane, 0, None) / peak, "citl", channel.name, f"{name}.png")
    return {"file": file, "full_scale": peak}


# -- the steps ------------------------------------------------------------------------------------------------------

def _hologram(context: Context, target: torch.Tensor, channel: LaserChannel, scene: focal_stack.StackScene | None,
              method: str, iterations: int | None) -> Any:
    """The model hologram of `target` (of a scene with depth: for its planes) by `method`."""
    options = HologramParameters(method=method, iterations=iterations)
    if scene is None:
        return compute_hologram(context, target, channel, options)
    return compute_hologram(context, target, channel, options, depth_m=scene.depth_m, planes=scene.planes)


def _starter(target: torch.Tensor, channel: LaserChannel, scene: focal_stack.StackScene | None):
    def action(context: Context) -> dict[str, Any]:
        params = context.parameters(CitlParameters)
        iterations = params.start_iterations if params.start == "sgd" else None
        result = _hologram(context, target, channel, scene, params.start, iterations)
        file = save_hologram(context, result.gray, "citl", channel.name, "start.png")
        phase = torch.from_numpy(context.decode(result.gray, channel.name))
        digest = _save_state(_state_file(context, channel, 0), phase, None)
        return {"file": file, "method": params.start, "iterations": iterations, "state_sha256": digest,
                "seconds": round(result.seconds, 4), "simulated": {k: round(v, 4) for k, v in result.scores.items()}}

    return action


def _iteration(target: torch.Tensor, channel: LaserChannel, k: int, scene: focal_stack.StackScene | None,
               views: list[FocusAt | None], power: Power):
    def action(context: Context) -> dict[str, Any]:
        params, clock = context.parameters(CitlParameters), time.perf_counter
        begin = clock()
        count, device = params.iterations, gradient_device(params.device)
        key, writer = f"citl/{channel.name}/{k:04d}", _writer(channel, k)
        try:
            phase, optimiser, scale = _load_state(_state_file(context, channel, k), params.learning_rate, device,
                                                  context.result(writer).get("state_sha256"))
        except StateDamaged as exc:
            raise StepRedo(f"CITL {channel.name} iteration {k}: its state {exc}", writer) from None
        scale *= 0.5 ** context.divergences(key)
        gray = context.encode(phase.detach(), channel.name)
        keep = keeps_raw(k, count, params.keep_raw_every)
        plane, record, timing = _capture(context, channel, gray, keep, views, power)
        target_roi = _target_roi(context, target, channel)
        start = clock()
        captured, loss, score = _amplitude_error(plane, target_roi, scene)
        if k > 0:
            first = context.result(f"citl/{channel.name}/0000")["loss"]
            if not math.isfinite(loss) or loss > DIVERGENCE * first:
                raise _diverged(channel, k, f"captured loss {loss:.3g}, {loss / first:.1f} x iteration 0's "
                                f"{first:.3g}", params.learning_rate, scale, writer)
        rate = learning_rate(params, k) * scale if k < count else 0.0
        if k < count:
            with torch.enable_grad():
                optimiser.param_groups[0]["lr"] = rate
                optimiser.zero_grad(set_to_none=True)
                setup = context.setup(channel.name, as_displayed=True)
                if scene is None:
                    loss_of = straight_through_loss(phase, captured.to(device), target_roi.to(device), setup)
                else:
                    loss_of = straight_through_stack_loss(phase, captured.to(device), target_roi.to(device),
                                                          _masks(scene).to(device), scene.planes.planes_m, setup)
                loss_of.backward()
                optimiser.step()
                with torch.no_grad():
                    phase.copy_(setup.within_reach(phase))
            _synchronised(device)
            if not bool(torch.isfinite(phase).all()):
                raise _diverged(channel, k, "the phase is no longer finite after its step",
                                params.learning_rate, scale, key)
        timing["gradient_s"] = clock() - start
        start = clock()
        record.update(_save_plane(context, channel, f"{k:04d}", plane))
        if keep:
            record["hologram"] = save_hologram(context, gray, "citl", channel.name, f"{k:04d}.png", read_later=False)
        if k < count:
            record["state_sha256"] = _save_state(_state_file(context, channel, k + 1), phase, optimiser, scale)
        if k > 0:
            _state_file(context, channel, k - 1).unlink(missing_ok=True)  # iteration k - 1 finished: not needed
        timing["save_s"] = clock() - start
        timing["total_s"] = clock() - begin
        context.say(f"      {channel.name} {k}/{count}: captured PSNR {score:.2f} dB amplitude, loss {loss:.3e}")
        return {"iteration": k, "loss": loss, "psnr_amplitude_db": round(score, 4), **record, "device": str(device),
                "learning_rate": rate, "timing": {name: round(timing[name], 6) for name in TIMING_KEYS}}

    return action


def _baseline(target: torch.Tensor, channel: LaserChannel, scene: focal_stack.StackScene | None,
              views: list[FocusAt | None], power: Power):
    def action(context: Context) -> dict[str, Any]:
        budget = _budget(context.parameters(CitlParameters))
        result = _hologram(context, target, channel, scene, "sgd", budget)
        plane, record, _ = _capture(context, channel, result.gray, True, views, power)
        _, loss, score = _amplitude_error(plane, _target_roi(context, target, channel), scene)
        frame = save_hologram(context, result.gray, "citl", channel.name, "baseline.png")
        context.say(f"      {channel.name}: model-only SGD ({budget} iterations) captured PSNR {score:.2f} dB")
        return {"iterations": budget, "loss": loss, "psnr_amplitude_db": round(score, 4), **record,
                **_save_plane(context, channel, "baseline", plane), "hologram": frame,
                "simulated": {k: round(v, 4) for k, v in result.scores.items()}}

    return action


def _loaded(context: Context, result: dict[str, Any]) -> np.ndarray:
    """A registered plane a step saved (`_save_plane`), at its recorded scale; a focal stack's planes (K, h, w)."""
    if "planes" in result:
        return np.stack([_loaded(context, plane) for plane in result["planes"]])
    return load_image(context, result["file"]) / 65535.0 * result["full_scale"]


def _reporter(target: torch.Tensor, used: list[LaserChannel], scene: focal_stack.StackScene | None):
    def action(context: Context) -> dict[str, Any]:
        assert context.profile.optics is not None
        params = context.parameters(CitlParameters)
        count = params.iterations
        target_roi = crop_roi(target, context.profile.optics.roi)
        iterations = {c.name: [context.result(f"citl/{c.name}/{k:04d}") for k in range(count + 1)] for c in used}
        baseline = {c.name: context.result(f"citl/{c.name}/baseline") for c in used} if params.baseline else {}

        def merged(results: dict[str, dict[str, Any]], image: str | None = None) -> dict[str, Any]:
            """The merged capture's scores (with SSIM, warnings and the image where `image` names it); of focal
            stacks, per plane in its in-focus region and their mean."""
            planes = {target_plane(c): _loaded(context, results[c.name]) for c in used}
            if scene is None:
                return merged_scores(context, planes, target_roi, image)
            return merged_stack_scores(context, planes, target_roi, scene.owner, image)

        per_k = [merged({name: rows[k] for name, rows in iterations.items()},
                        "merged-first.png" if k == 0 else "merged-last.png" if k == count else None)
                 for k in range(count + 1)]
        return citl_report(context, {
            "target": params.target, "iterations": iterations, "merged": per_k,
            "planes_mm": [round(z * 1e3, 6) for z in scene.planes.planes_m] if scene is not None else None,
            "planes_reason": scene.planes.reason if scene is not None else None,
            "baseline": {"colours": baseline, "merged": merged(baseline, "merged-baseline.png"),
                         "iterations": _budget(params)} if baseline else None,
            "start": {c.name: context.result(f"citl/{c.name}/start") for c in used},
            "timing_keys": list(TIMING_KEYS), "disk": _disk(context, iterations, used),
            "target_image": save_image(context, target_roi.square(), "citl", "target.png", srgb=True),
            "target_planes": [save_image(context, target_roi.square() * torch.where(scene.region(j), 1.0,
                                                                                     focal_stack.OUT_OF_FOCUS_SHADE),
                                         "citl", f"target-plane-{j + 1}.png", srgb=True)
                              for j in range(len(scene.planes.planes_m))] if scene is not None else None})

    return action


def _disk(context: Context, iterations: dict[str, list[dict[str, Any]]], used: list[LaserChannel]) -> dict[str, Any]:
    """Bytes the run keeps per iteration: registered planes (every iteration), RAW and displayed frames (the kept
    iterations), and the optimiser state (two iterations' worth at a time, one left at the end)."""
    def size(relative: str) -> int:
        path = context.path(relative)
        return path.stat().st_size if path.is_file() else 0

    rows = [row for rows in iterations.values() for row in rows]
    kept = [row for row in rows if "folder" in row]
    raw = sum(size(name) for row in kept for name in row["archived"])
    frames = sum(size(row["hologram"]) for row in kept)
    planes = sum(size(plane["file"]) for row in rows for plane in row.get("planes", [row]))
    states = [p.stat().st_size for c in used for p in state_path(context, c.name).glob("*.npz")]
    return {"iterations": len(rows), "kept_raw_iterations": len(kept),
            "registered_bytes_per_iteration": round(planes / len(rows)),
            "raw_bytes_per_kept_iteration": round(raw / len(kept)) if kept else 0,
            "hologram_bytes_per_kept_iteration": round(frames / len(kept)) if kept else 0,
            "state_bytes": max(states, default=0), "citl_bytes": raw + frames + planes + sum(states)}
