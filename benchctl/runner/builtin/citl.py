"""Camera-in-the-loop (CITL) optimisation (Peng et al. 2020): per colour, start from a model hologram (DPAC or SGD),
then each iteration displays the phase, captures RAW frames, decodes them, registers the colour's CFA plane onto
the target's ROI with the stored registration, and takes one Adam step on the phase with the straight-through
gradient (cgh.citl): the loss is the captured amplitude's error, differentiated through the propagation model (the
fitted optical model from calibration/<profile>/ when there is one, as SGD uses it).

Each iteration is one resumable step. It reads the phase and the optimiser state the previous one saved
(state/<colour>/<k>.npz, float32 as optimised) and saves the next, so a resumed run continues bit for bit; the
state two iterations back is deleted. Disk: the RAW frames (and the displayed SLM frame) are kept for the first
and last iterations and every `keep_raw_every`-th; every iteration keeps its registered plane as a 16-bit PNG on
the ROI (images/citl/<colour>/<k>.png). Iteration k records the loss and captured PSNR of phase k (the one it
displayed) and the seconds spent per stage; the last (k = iterations) only captures the final phase.

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
"""

from __future__ import annotations

import io
import math
import time
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import torch
from msgspec import Meta

from benchctl.capture.colour_planes import merge_capture, registered_plane
from benchctl.capture.raw import RawImage, average_frames, decode_raw, subtract_dark
from benchctl.cgh.citl import straight_through_loss
from benchctl.devices.camera import RawFrame
from benchctl.devices.slm import slm_for
from benchctl.errors import BenchctlError
from benchctl.files import atomic_write_bytes, file_sha256
from benchctl.images import read_image, write_png
from benchctl.optics import crop_roi, linear_to_srgb, lsq_scale, psnr
from benchctl.optics.setup import OpticalSetup
from benchctl.profiles import LaserChannel, Positive
from benchctl.runner.builtin import registration
from benchctl.runner.hologram_cache import hologram
from benchctl.runner.holograms import optimised_setup, target_plane
from benchctl.runner.auto_exposure import Exposure, PeakGoal, probe_step, probed_power
from benchctl.runner.procedure import Context, Step
from benchctl.runner.record import set_aside
from benchctl.runner.report import citl_report
from benchctl.runner.steps import (
    DarkFrames,
    ExposureParameters,
    Frames,
    Registration,
    channels,
    displayed_frame,
    power_w,
    prepared_target,
    unknown_setpoints,
    write_linear16,
)
from benchctl.targets import active_channels

DESCRIPTION = "camera in the loop: per colour, display, capture, register and step the phase on the captured error"


class CitlParameters(ExposureParameters, kw_only=True):
    """What to optimise on the bench, how long, how fast, and what to keep on disk."""

    target: str = "chart:bars"
    frames: Frames = 1  # RAW frames averaged per iteration
    dark_frames: DarkFrames = 0  # per iteration (the decoder removes the black level)
    iterations: Annotated[int, Meta(ge=1, le=10_000)] = 50  # Adam steps on the captured error
    learning_rate: Positive = 0.05
    # "cosine": the learning rate falls from learning_rate to 0 over the iterations (late steps, whose gradient is
    # mostly camera noise, stay small); "constant"
    schedule: Literal["cosine", "constant"] = "cosine"
    start: Literal["dpac", "sgd"] = "dpac"  # the model hologram to start from
    start_iterations: Annotated[int, Meta(ge=1)] = 100  # model-only SGD steps of an SGD start
    # disk policy: RAW frames kept for the first and last iteration and every Nth (0: first and last only)
    keep_raw_every: Annotated[int, Meta(ge=0)] = 10
    baseline: bool = True  # capture model-only SGD at the same budget too
    registration: Registration = "auto"
    exposure: Exposure = "auto"  # "auto": a probe frame of the start hologram sets the power for every capture
    peak_goal: PeakGoal = 0.7  # fraction of full scale
    device: Literal["auto", "cpu", "cuda"] = "auto"  # where the gradient runs; "auto": a CUDA GPU if there is one


PARAMETERS = CitlParameters

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
    target = prepared_target(context.profile, params.target)
    present = active_channels(target)
    used = [c for c in channels(context) if present[target_plane(c)]]
    if not used:
        raise BenchctlError(f"parameters.target: {params.target!r} has none of the colours "
                            f"{[c.name for c in channels(context)]}")
    steps = registration.registration_first(context, used, params, params.registration)
    count = params.iterations
    devices = ("laser", "slm", "camera")
    for channel in used:
        name = channel.name
        steps.append(Step(f"citl/{name}/start", f"start hologram {name} ({params.start})",
                          _starter(target, channel)))
        if params.exposure == "auto":
            steps.append(probe_step(context, f"citl/{name}/probe", ("citl", name, "probe"), channel,
                                    lambda ctx, key=f"citl/{name}/start": displayed_frame(ctx, key),
                                    "probe exposure of the start hologram", params.peak_goal))
        for k in range(count + 1):
            what = "capture the final phase" if k == count else "capture, register, step the phase"
            steps.append(Step(f"citl/{name}/{k:04d}", f"CITL {name} iteration {k}/{count}: {what}",
                              _iteration(target, channel, k), devices))
        if params.baseline:
            steps.append(Step(f"citl/{name}/baseline", f"model-only SGD {name} at {_budget(params)} iterations, "
                              "captured", _baseline(target, channel), devices))
    steps.append(Step("report", "metrics.json, metrics.csv and report.html", _reporter(target, used)))
    return steps


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


def _setup(context: Context, channel: LaserChannel) -> OpticalSetup:
    return optimised_setup(context.profile, channel.name, slm_for(context.profile))


def _target_roi(context: Context, target: torch.Tensor, channel: LaserChannel) -> torch.Tensor:
    assert context.profile.optics is not None
    return crop_roi(target[target_plane(channel)], context.profile.optics.roi)


# -- the optimiser state ----------------------------------------------------------------------------------------

def _state_file(context: Context, channel: LaserChannel, k: int) -> Path:
    return context.path("state", channel.name, f"{k:04d}.npz")


def _save_state(path: Path, phase: torch.Tensor, optimiser: torch.optim.Adam | None) -> None:
    """The phase and Adam's moments and step count, exactly (float32), written atomically."""
    arrays: dict[str, np.ndarray] = {"phase": phase.detach().cpu().numpy(), "step": np.zeros((), np.float32)}
    state = optimiser.state.get(optimiser.param_groups[0]["params"][0]) if optimiser else None
    if state:
        arrays.update({key: state[key].cpu().numpy() for key in ("step", "exp_avg", "exp_avg_sq")})
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    atomic_write_bytes(path, buffer.getvalue())


def _load_state(path: Path, learning_rate: float,
                device: torch.device | str = "cpu") -> tuple[torch.Tensor, torch.optim.Adam]:
    """The phase (a leaf to optimise, on `device`) and its Adam optimiser as `_save_state` left them."""
    if not path.is_file():
        raise BenchctlError(f"{path}: the CITL state this iteration starts from is missing (a run keeps only the "
                            "last two): start a new run")
    with np.load(path, allow_pickle=False) as data:
        phase = torch.from_numpy(data["phase"].copy()).to(device).requires_grad_()
        optimiser = torch.optim.Adam([phase], lr=learning_rate)
        if float(data["step"]) > 0:  # Adam keeps its step count on the CPU, its moments beside the parameter
            optimiser.state[phase] = {"step": torch.from_numpy(data["step"].copy()),
                                      "exp_avg": torch.from_numpy(data["exp_avg"].copy()).to(device),
                                      "exp_avg_sq": torch.from_numpy(data["exp_avg_sq"].copy()).to(device)}
    return phase, optimiser


# -- one capture, decoded and registered --------------------------------------------------------------------------

def _measure(context: Context, key: str, channel: LaserChannel, gray: np.ndarray,
             keep: tuple[str, ...] | None) -> tuple[np.ndarray, dict[str, Any], dict[str, float]]:
    """Display `gray`, expose it (RAW saved under raw/<keep> when given, else only in memory), decode and register
    the colour's plane: (ROI linear signal, JSON-ready record, seconds per stage)."""
    params, profile = context.parameters(CitlParameters), context.profile
    assert profile.slm is not None and profile.optics is not None
    where = context.path("raw", *keep) if keep else None
    attempt = context.record.attempts.get(key, 1) if context.record else 1
    if where is not None and attempt > 1:
        set_aside(where, attempt - 1)
    power = (probed_power(f"citl/{channel.name}/probe")(context) if params.exposure == "auto"
             else power_w(context, channel))
    exposure = context.bench.expose_frames(where, channel.name, power, gray,
                                           frames=params.frames, dark_frames=params.dark_frames)
    clock = time.perf_counter
    start = clock()
    image = _decoded(exposure.frames)
    if exposure.darks:
        image = subtract_dark(image, _decoded(exposure.darks))
    decoded = clock()
    homography = np.asarray(context.calibration.registrations()[channel.name]["homography"], dtype=np.float64)
    plane = registered_plane(image, target_plane(channel), homography, profile.slm.shape, profile.optics.roi)
    registered = clock()
    metadata = [frame.metadata for frame in (*exposure.frames, *exposure.darks)]
    render = sum(float(m.get("render_s", 0.0)) for m in metadata)
    transfer = sum(float(m.get("transfer_s", 0.0)) for m in metadata)
    timing = {"display_s": exposure.timing["display_s"], "laser_s": exposure.timing["laser_s"],
              "exposure_s": exposure.timing["capture_s"] - render - transfer, "transfer_s": transfer,
              "render_s": render, "decode_s": decoded - start, "register_s": registered - decoded}
    record: dict[str, Any] = {"setpoint_w": exposure.result["setpoint_w"], "slm_frame": exposure.result["slm_frame"],
                              "saturated_fraction": round(float(image.saturation_fraction), 6)}
    if where is not None:
        names = [*exposure.result["frames"], *exposure.result["darks"]]
        record["raw"] = str(Path("raw", *keep))
        record["archived"] = {str(Path("raw", *keep, name)): file_sha256(where / name) for name in names}
    return plane, record, timing


def _decoded(frames: list[RawFrame]) -> RawImage:
    return average_frames(decode_raw(frame.data) for frame in frames)


def _amplitude_error(plane: np.ndarray, target_roi: torch.Tensor) -> tuple[torch.Tensor, float, float]:
    """The captured amplitude (sqrt of the signal, negatives clipped), its MSE and PSNR against the target after
    least-squares scaling."""
    captured = torch.from_numpy(np.sqrt(np.clip(plane, 0.0, None)))
    scaled = lsq_scale(captured, target_roi) * captured
    loss = torch.nn.functional.mse_loss(scaled, target_roi)
    return captured, float(loss), float(psnr(scaled, target_roi, data_range=1.0))


def _save_plane(context: Context, channel: LaserChannel, name: str, plane: np.ndarray) -> dict[str, Any]:
    """The registered plane as a 16-bit PNG on the ROI, scaled by its maximum (recorded to undo the scaling)."""
    peak = float(max(plane.max(), 1e-12))
    file = Path("images", "citl", channel.name, f"{name}.png")
    write_linear16(context.path(str(file)), np.clip(plane, 0, None) / peak)
    return {"file": str(file), "full_scale": peak}


# -- the steps ------------------------------------------------------------------------------------------------------

def _starter(target: torch.Tensor, channel: LaserChannel):
    def action(context: Context) -> dict[str, Any]:
        params = context.parameters(CitlParameters)
        iterations = params.start_iterations if params.start == "sgd" else None
        result = hologram(context.profile, target, channel.name, params.start, iterations=iterations, seed=0,
                          checkpoint=None, progress=context.progress)
        file = Path("holograms", "citl", channel.name, "start.png")
        write_png(context.path(str(file)), result.gray)
        phase = torch.from_numpy(slm_for(context.profile).decode(result.gray, channel.name))
        _save_state(_state_file(context, channel, 0), phase, None)
        return {"file": str(file), "method": params.start, "iterations": iterations,
                "seconds": round(result.seconds, 4), "simulated": {k: round(v, 4) for k, v in result.scores.items()}}

    return action


def _iteration(target: torch.Tensor, channel: LaserChannel, k: int):
    def action(context: Context) -> dict[str, Any]:
        params, clock = context.parameters(CitlParameters), time.perf_counter
        begin = clock()
        count, device = params.iterations, gradient_device(params.device)
        phase, optimiser = _load_state(_state_file(context, channel, k), params.learning_rate, device)
        gray = slm_for(context.profile).encode(phase.detach(), channel.name)
        keep = keeps_raw(k, count, params.keep_raw_every)
        key = f"citl/{channel.name}/{k:04d}"
        plane, record, timing = _measure(context, key, channel, gray,
                                         ("citl", channel.name, f"{k:04d}") if keep else None)
        target_roi = _target_roi(context, target, channel)
        start = clock()
        captured, loss, score = _amplitude_error(plane, target_roi)
        if k < count:
            with torch.enable_grad():
                optimiser.param_groups[0]["lr"] = learning_rate(params, k)
                optimiser.zero_grad(set_to_none=True)
                setup = _setup(context, channel)
                straight_through_loss(phase, captured.to(device), target_roi.to(device), setup).backward()
                optimiser.step()
                with torch.no_grad():
                    phase.copy_(setup.within_reach(phase))
            _synchronised(device)
        timing["gradient_s"] = clock() - start
        start = clock()
        record.update(_save_plane(context, channel, f"{k:04d}", plane))
        if keep:
            frame = Path("holograms", "citl", channel.name, f"{k:04d}.png")
            write_png(context.path(str(frame)), gray)
            record["hologram"] = str(frame)
        if k < count:
            _save_state(_state_file(context, channel, k + 1), phase, optimiser)
        if k > 0:
            _state_file(context, channel, k - 1).unlink(missing_ok=True)  # iteration k - 1 finished: not needed
        timing["save_s"] = clock() - start
        timing["total_s"] = clock() - begin
        context.say(f"      {channel.name} {k}/{count}: captured PSNR {score:.2f} dB amplitude, loss {loss:.3e}")
        return {"iteration": k, "loss": loss, "psnr_amplitude_db": round(score, 4), **record, "device": str(device),
                "timing": {name: round(timing[name], 6) for name in TIMING_KEYS}}

    return action


def _baseline(target: torch.Tensor, channel: LaserChannel):
    def action(context: Context) -> dict[str, Any]:
        budget = _budget(context.parameters(CitlParameters))
        result = hologram(context.profile, target, channel.name, "sgd", iterations=budget, seed=0, checkpoint=None,
                          progress=context.progress)
        key = f"citl/{channel.name}/baseline"
        plane, record, _ = _measure(context, key, channel, result.gray, ("citl", channel.name, "baseline"))
        _, loss, score = _amplitude_error(plane, _target_roi(context, target, channel))
        frame = Path("holograms", "citl", channel.name, "baseline.png")
        write_png(context.path(str(frame)), result.gray)
        context.say(f"      {channel.name}: model-only SGD ({budget} iterations) captured PSNR {score:.2f} dB")
        return {"iterations": budget, "loss": loss, "psnr_amplitude_db": round(score, 4), **record,
                **_save_plane(context, channel, "baseline", plane), "hologram": str(frame),
                "simulated": {k: round(v, 4) for k, v in result.scores.items()}}

    return action


def _reporter(target: torch.Tensor, used: list[LaserChannel]):
    def action(context: Context) -> dict[str, Any]:
        assert context.profile.optics is not None
        count, folder = context.parameters(CitlParameters).iterations, context.path()
        target_roi = crop_roi(target, context.profile.optics.roi)
        iterations = {c.name: [context.result(f"citl/{c.name}/{k:04d}") for k in range(count + 1)] for c in used}
        baseline = ({c.name: context.result(f"citl/{c.name}/baseline") for c in used}
                    if context.parameters(CitlParameters).baseline else {})

        def planes(results: dict[str, dict[str, Any]]) -> dict[int, np.ndarray]:
            return {target_plane(c): read_image(folder / results[c.name]["file"]) / 65535.0
                    * results[c.name]["full_scale"] for c in used}

        def merged(results: dict[str, dict[str, Any]], image: str) -> dict[str, Any]:
            merge = merge_capture(planes(results), target_roi)
            write_linear16(context.path("images", "citl", image), merge.merged_linear, srgb=True)
            return {"scores": {k: round(v, 4) for k, v in merge.merged_scores.items()}, "warnings": merge.warnings,
                    "image": f"images/citl/{image}"}

        # Every iteration's merged PSNR; the full scoring (SSIM, warnings, the image) for the first and the last.
        per_k: list[dict[str, Any]] = [
            {"scores": merged_psnr(planes({name: rows[k] for name, rows in iterations.items()}), target_roi),
             "warnings": []} for k in range(count + 1)]
        for k, image in ((0, "merged-first.png"), (count, "merged-last.png")):
            per_k[k] = merged({name: rows[k] for name, rows in iterations.items()}, image)
        write_linear16(context.path("images", "citl", "target.png"), target_roi.square(), srgb=True)
        disk = _disk(folder, iterations, used)
        return citl_report(context, {
            "target": context.parameters(CitlParameters).target, "iterations": iterations, "merged": per_k,
            "baseline": {"colours": baseline, "merged": merged(baseline, "merged-baseline.png"),
                         "iterations": _budget(context.parameters(CitlParameters))} if baseline else None,
            "start": {c.name: context.result(f"citl/{c.name}/start") for c in used},
            "timing_keys": list(TIMING_KEYS), "disk": disk, "target_image": "images/citl/target.png"})

    return action


def merged_psnr(planes: dict[int, np.ndarray], target_roi: torch.Tensor) -> dict[str, float]:
    """The merged colour image's PSNR, linear and sRGB, as `merge_capture` balances and scores it (the same
    numbers, without its SSIM: a run of hundreds of iterations scores each of them)."""
    merged = torch.zeros_like(target_roi)
    for colour, signal in planes.items():
        measured = torch.from_numpy(np.sqrt(np.clip(np.asarray(signal, dtype=np.float32), 0.0, None)))
        merged[colour] = (lsq_scale(measured, target_roi[colour]) * measured).square().clamp(0, 1)
    rows = (3 * target_roi.shape[-2], target_roi.shape[-1])
    linear = target_roi.square().clamp(0, 1)
    return {"psnr_linear_db": round(float(psnr(merged.reshape(rows), linear.reshape(rows), 1.0)), 4),
            "psnr_srgb_db": round(float(psnr(linear_to_srgb(merged).reshape(rows),
                                             linear_to_srgb(linear).reshape(rows), 1.0)), 4)}


def _disk(folder: Path, iterations: dict[str, list[dict[str, Any]]], used: list[LaserChannel]) -> dict[str, Any]:
    """Bytes the run keeps per iteration: registered planes (every iteration), RAW and displayed frames (the kept
    iterations), and the optimiser state (two iterations' worth at a time, one left at the end)."""
    def size(relative: str) -> int:
        path = folder / relative
        return path.stat().st_size if path.is_file() else 0

    rows = [row for rows in iterations.values() for row in rows]
    kept = [row for row in rows if "raw" in row]
    raw = sum(size(name) for row in kept for name in row["archived"])
    frames = sum(size(row["hologram"]) for row in kept)
    planes = sum(size(row["file"]) for row in rows)
    states = [p.stat().st_size for c in used for p in (folder / "state" / c.name).glob("*.npz")]
    return {"iterations": len(rows), "kept_raw_iterations": len(kept),
            "registered_bytes_per_iteration": round(planes / len(rows)),
            "raw_bytes_per_kept_iteration": round(raw / len(kept)) if kept else 0,
            "hologram_bytes_per_kept_iteration": round(frames / len(kept)) if kept else 0,
            "state_bytes": max(states, default=0), "citl_bytes": raw + frames + planes + sum(states)}
