"""`benchctl train`: training the learned hologram methods: one model per colour, Adam, loss on the ROI, DDP.

What one step does, per colour (laser channel): the image's plane for that colour, prepared like every
target (`prepare_target`: sRGB -> linear -> resized to the ROI -> amplitude -> zero-padded to the grid),
scaled to peak 1 as `Method` scales targets at inference, goes through the network to an SLM phase; the
phase is propagated to the target plane (`OpticalSetup.reconstruct`); the loss compares the reconstruction
on the ROI, after the least-squares scale that every score here uses, with the target on the ROI:
MSE, or MSE + 0.025 x the VGG19 perceptual term (`--loss l2-perceptual`, the paper's 1080p loss).
Images are flipped horizontally and vertically at random (seeded per epoch and position, so a resumed run
sees the same flips). All colours' models train side by side on the same images.

A network for scenes with depth (`DEPTH_METHODS`) trains the same way on scenes (`procedural-rgbd:N`, or pictures
on a ground plane; `training.data`), the depth map prepared like `benchctl generate` prepares a scene's
(`scenes.prepare_scene`) over the bench's depth range, flipped with its image; its loss is the focal-stack loss
(`optics.focal_stack`: the reconstruction at each scene's focal planes, `data.loss_planes`, at most `--planes`,
moved at random within their bins while training, one multi-plane propagation each, every plane scored where the
scene is in focus there) and its validation scores are the mean in-focus PSNR / SSIM over the planes, beside 2D
DPAC of the image at the middle of the depth range (the one-shot hologram that ignores depth).
`--fresnel-scaled` trains on a smaller `--size` with the distance and depth range scaled so that the Fresnel number
is the full bench's (as `bench reproduce` does); without it the distance is kept, as the paper trains.

Under `torchrun` (WORLD_SIZE > 1 in the environment) every process trains on its share of each batch and
the models are wrapped in DistributedDataParallel (gloo on CPU, nccl on CUDA), so the gradients and hence
the weights stay identical; only rank 0 validates, prints and writes checkpoints.
"""

from __future__ import annotations

import dataclasses
import math
import os
import shlex
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import numpy as np
import torch
import torch.distributed as dist
import torch.nn.functional as F
from msgspec.structs import replace
from torch import nn

from benchctl.calibration.files import fitted_model_entry
from benchctl.calibration.geometry import grid_profile
from benchctl.calibration.setups import optical_setups
from benchctl.calibration.store import Calibration, validity
from benchctl.cgh.learned.models import DEPTH_METHODS, LEARNED_METHODS, VARIANTS, build_model
from benchctl.cgh.learned.vgg import PERCEPTUAL_WEIGHT, PerceptualLoss, load_vgg19
from benchctl.cgh.method import get_method
from benchctl.errors import BadValueError, BenchctlError
from benchctl.files import ensure_dir
from benchctl.holograms.checkpoints import RESUME_SUFFIX, WEIGHT_DTYPES, Checkpoint, read_checkpoint
from benchctl.memory import Estimate, check_training_memory, size_text, training_estimate
from benchctl.optics.focal_stack import FocalStackScores, focal_stack_loss, focal_stack_scores, in_focus_masks
from benchctl.optics.metrics import amplitude_scores, centred_slices, crop_roi, lsq_scale, psnr, psnr_of_mse
from benchctl.optics.planes import MAX_PLANES
from benchctl.optics.setup import OpticalSetup
from benchctl.profiles import Profile
from benchctl.scenes import Scene, prepare_scene
from benchctl.targets import prepare_target, target_plane
from benchctl.terminal import ProgressLine
from benchctl.training.averaging import WeightAverage
from benchctl.training.data import ImageSource, describe_sources, image_sources, loss_planes, split_sources
from benchctl.training.device import check_device_text, resolve_device
from benchctl.training.health import StepStats, TrainingHealth, clamped_fraction, gradient_norm
from benchctl.training.schedule import Schedule

LOSSES = ("mse", "l2-perceptual")
MAX_LR = 0.1  # Adam on these networks diverges far below this; above it a value is a typo
BACKEND_ENV = "BENCHCTL_DDP_BACKEND"


@dataclass(frozen=True)
class TrainSettings:
    """What `benchctl train` was asked to do (everything but the profile, output folder and resume file)."""

    method: str
    data: str
    size: tuple[int, int] | None = None
    colours: tuple[str, ...] | None = None
    epochs: int = 10
    lr: float = 5e-4
    loss: str = "mse"
    vgg_weights: Path | None = None
    batch_size: int = 1
    seed: int = 42
    val_fraction: float = 0.1
    max_steps: int | None = None
    weights_dtype: str = "float32"
    model_calibration: str | None = None  # "stored" or an optical-model.json: train through that fitted model
    ema: float | None = None  # decay of a weight average (averaging.py) that validation and the checkpoint use
    warmup: int = 0  # steps of linear learning-rate warm-up (schedule.py)
    decay: str = "none"  # learning-rate decay after the warm-up: none or cosine (to zero at the last step)
    device: str = "cpu"  # --device: auto, cpu, cuda or cuda:N (device.py)
    planes: int = 5  # scenes with depth: at most this many focal planes per scene in the loss
    fresnel_scaled: bool = False  # with `size`: distance and depth range scaled to keep the Fresnel number

    @property
    def depth(self) -> bool:
        """Whether the method reads depth (a scene's focal stack is its loss)."""
        return self.method in DEPTH_METHODS

    def validate(self) -> None:
        """BadValueError naming the flag for every setting a user can get wrong."""
        if self.method not in LEARNED_METHODS:
            raise BadValueError(f"--method {self.method!r} is not a learned method; "
                                f"known: {', '.join(LEARNED_METHODS)}")
        if self.loss not in LOSSES:
            raise BadValueError(f"--loss {self.loss!r}: expected one of {', '.join(LOSSES)}")
        if self.depth and self.loss != "mse":
            raise BadValueError(f"--loss {self.loss}: {self.method} trains on the focal-stack loss (the in-focus MSE "
                                "of every plane); use --loss mse")
        if not 1 <= self.planes <= MAX_PLANES:
            raise BadValueError(f"--planes must lie between 1 and {MAX_PLANES}, got {self.planes}")
        if self.fresnel_scaled and self.size is None:
            raise BadValueError("--fresnel-scaled scales the bench to a smaller grid: give the grid with --size HxW")
        if self.loss == "l2-perceptual" and self.vgg_weights is None:
            raise BadValueError("--loss l2-perceptual needs VGG19 weights: pass --vgg-weights FILE (a torchvision "
                                "vgg19 state dict saved with torch.save); benchctl never downloads them")
        for flag, value in (("--epochs", self.epochs), ("--batch-size", self.batch_size)):
            if value < 1:
                raise BadValueError(f"{flag} must be >= 1, got {value}")
        if self.max_steps is not None and self.max_steps < 1:
            raise BadValueError(f"--max-steps must be >= 1, got {self.max_steps}")
        if not (math.isfinite(self.lr) and 0 < self.lr <= MAX_LR):
            raise BadValueError(f"--lr must lie in (0, {MAX_LR:g}] (the paper's is 5e-4), got {self.lr:g}")
        if self.ema is not None and not 0 < self.ema < 1:
            raise BadValueError(f"--ema must lie between 0 and 1 (e.g. 0.99), got {self.ema}")
        if not 0 <= self.seed < 2**32:
            raise BadValueError(f"--seed must lie between 0 and {2**32 - 1}, got {self.seed}")
        check_device_text(self.device)
        Schedule(self.lr, self.warmup, self.decay, None if self.decay == "none" else 1 << 62)
        if self.weights_dtype not in WEIGHT_DTYPES:
            raise BadValueError(f"--weights-dtype {self.weights_dtype!r}: expected one of {', '.join(WEIGHT_DTYPES)}")

    def command(self, profile: Profile, out_dir: Path) -> str:
        """The `benchctl train` command line that asks for exactly these settings."""
        words = ["benchctl", "train", "--method", self.method, "--data", self.data, "--profile", profile.name,
                 "--epochs", str(self.epochs), "--lr", f"{self.lr:g}", "--loss", self.loss,
                 "--batch-size", str(self.batch_size), "--seed", str(self.seed),
                 "--val-fraction", f"{self.val_fraction:g}"]
        if self.size:
            words += ["--size", f"{self.size[0]}x{self.size[1]}"]
        if self.colours:
            words += ["--colours", ",".join(self.colours)]
        if self.vgg_weights:
            words += ["--vgg-weights", str(self.vgg_weights)]
        if self.max_steps:
            words += ["--max-steps", str(self.max_steps)]
        if self.weights_dtype != "float32":
            words += ["--weights-dtype", self.weights_dtype]
        if self.model_calibration:
            words += ["--model-calibration", self.model_calibration]
        if self.ema is not None:
            words += ["--ema", f"{self.ema:g}"]
        if self.warmup:
            words += ["--warmup", str(self.warmup)]
        if self.decay != "none":
            words += ["--decay", self.decay]
        if self.device != "cpu":
            words += ["--device", self.device]
        if self.depth:
            words += ["--planes", str(self.planes)]
        if self.fresnel_scaled:
            words += ["--fresnel-scaled"]
        return shlex.join(words + ["--out", str(out_dir)])


@dataclass
class TrainResult:
    """What a training run produced (on every rank; `checkpoint` only on rank 0)."""

    models: dict[str, nn.Module]  # colour -> trained network (unwrapped from DDP)
    steps: int
    epochs_done: int
    metrics: dict[str, dict[str, float]]
    checkpoint: Path | None = None
    rank: int = 0
    world_size: int = 1


@dataclass
class Distributed:
    """This process's place in a torchrun job (rank 0 of 1 outside one) and the device it trains on."""

    rank: int = 0
    world_size: int = 1
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))
    owns_group: bool = False

    @classmethod
    def from_env(cls, device_text: str = "cpu") -> Distributed:
        """Join the process group torchrun describes (RANK, WORLD_SIZE, LOCAL_RANK, MASTER_ADDR/PORT) on the device
        `--device` names: on GPUs, each process on GPU LOCAL_RANK (modulo the GPUs here) unless one is named.
        Backend: nccl on GPUs, gloo on CPU, or $BENCHCTL_DDP_BACKEND (gloo lets several processes share a GPU,
        which nccl refuses)."""
        world = int(os.environ.get("WORLD_SIZE", "1"))
        local_rank = int(os.environ.get("LOCAL_RANK", "0"))
        device = resolve_device(device_text, local_rank)
        if world <= 1:
            return cls(device=device)
        owns = not dist.is_initialized()
        if owns:
            backend = os.environ.get(BACKEND_ENV) or ("nccl" if device.type == "cuda" else "gloo")
            if backend not in ("nccl", "gloo"):
                raise BadValueError(f"${BACKEND_ENV}={backend!r}: expected nccl or gloo")
            if device.type == "cuda":
                torch.cuda.set_device(device)
            dist.init_process_group(backend)
        return cls(rank=dist.get_rank(), world_size=dist.get_world_size(), device=device, owns_group=owns)

    @property
    def main(self) -> bool:
        return self.rank == 0

    def wrap(self, model: nn.Module) -> nn.Module:
        if self.world_size == 1:
            return model
        ids = [self.device.index] if self.device.type == "cuda" else None  # DDP's rule for one GPU per process
        return nn.parallel.DistributedDataParallel(model, device_ids=ids)

    def mean(self, values: Sequence[float]) -> list[float]:
        """The mean over all processes of each value (the values themselves outside a job)."""
        if self.world_size == 1:
            return list(values)
        tensor = torch.tensor(list(values), dtype=torch.float64, device=self.device)
        dist.all_reduce(tensor)
        return (tensor / self.world_size).tolist()

    def barrier(self) -> None:
        if self.world_size > 1:
            dist.barrier()

    def close(self) -> None:
        if self.owns_group and dist.is_initialized():
            dist.destroy_process_group()


class ReconstructionLoss(nn.Module):
    """MSE between ROI amplitudes (+ PERCEPTUAL_WEIGHT x VGG19 perceptual term when given a perceptual loss)."""

    def __init__(self, perceptual: PerceptualLoss | None = None) -> None:
        super().__init__()
        self.perceptual = perceptual

    def forward(self, recon: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        loss = F.mse_loss(recon, target)
        if self.perceptual is not None:
            loss = loss + PERCEPTUAL_WEIGHT * self.perceptual(recon, target)
        return loss


def step_estimate(settings: TrainSettings, grid: tuple[int, int]) -> Estimate:
    """The estimated peak memory of one training step of `settings` on `grid` (benchctl.memory)."""
    variant = VARIANTS[settings.method]
    return training_estimate(settings.method, variant.family, variant.factor, grid, settings.batch_size)


def make_loss(kind: str, vgg_weights: Path | None = None) -> ReconstructionLoss:
    """The loss `--loss kind` names; l2-perceptual loads VGG19 from `vgg_weights` (required)."""
    if kind == "mse":
        return ReconstructionLoss()
    if kind == "l2-perceptual":
        if vgg_weights is None:
            raise BadValueError("--loss l2-perceptual needs VGG19 weights: pass --vgg-weights FILE")
        return ReconstructionLoss(PerceptualLoss(load_vgg19(vgg_weights)))
    raise BadValueError(f"--loss {kind!r}: expected one of {', '.join(LOSSES)}")


def scaled_reconstruction(model: nn.Module, setup: OpticalSetup,
                          amplitude: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(reconstruction, target) on the ROI, (B, 1, h, w), the reconstruction least-squares scaled to the target.

    `amplitude` is the target on the SLM grid (B, 1, H, W). The scale stays in the graph: the loss is then the
    error at the best brightness, which is what a phase-only hologram can be asked for. With a fitted optical
    model the network's phase is displayed without the model's wavefront, as at inference.
    """
    return _scaled(model(amplitude), setup, amplitude)


def _scaled(phase: torch.Tensor, setup: OpticalSetup, amplitude: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    recon = setup.reconstruct_roi(setup.without_wavefront(phase))
    target = crop_roi(amplitude, setup.roi)
    return recon * lsq_scale(recon, target), target


@dataclass(frozen=True)
class SceneDepth:
    """The depth of a batch of scenes: the depth maps (B, 1, H, W) in metres from the SLM on the grid, and each
    scene's focal planes (metres, ascending)."""

    depth_m: torch.Tensor
    planes_m: tuple[tuple[float, ...], ...]

    def to(self, device: torch.device) -> SceneDepth:
        return SceneDepth(self.depth_m.to(device), self.planes_m)


def focal_stack_error(phase: torch.Tensor, setup: OpticalSetup, amplitude: torch.Tensor,
                      scenes: SceneDepth) -> tuple[torch.Tensor, torch.Tensor]:
    """The focal-stack loss (`focal_stack_loss` on the ROI) of each SLM phase of a batch (B, 1, H, W) against its
    scene, and its PSNR (each scene's loss is its in-focus MSE: the masks of a pixel sum to one); both (B,). With
    a fitted optical model the phase is displayed without the model's wavefront, as at inference."""
    rows, cols = setup.roi_slices
    losses = []
    for b, planes in enumerate(scenes.planes_m):
        recon = setup.reconstruct_planes_roi(setup.without_wavefront(phase[b, 0]), planes)
        masks = in_focus_masks(scenes.depth_m[b, 0, rows, cols], planes).to(recon.device)
        losses.append(focal_stack_loss(recon, amplitude[b, 0, rows, cols], masks))
    loss = torch.stack(losses)
    return loss, psnr_of_mse(loss.detach(), data_range=1.0)


def training_step(model: nn.Module, optimiser: torch.optim.Optimizer, setup: OpticalSetup,
                  amplitude: torch.Tensor, loss_fn: nn.Module, scenes: SceneDepth | None = None) -> StepStats:
    """One Adam step on a batch of targets (B, 1, H, W), with what it measured (`health.StepStats`); with
    `scenes`, on the focal stacks of scenes with depth (`loss_fn` unused).

    A step whose gradient is not finite changes no weight (the optimiser is not stepped), so the
    state before it stays the one to resume from."""
    model.train()
    optimiser.zero_grad(set_to_none=True)
    if scenes is None:
        phase = model(amplitude)
        recon, target = _scaled(phase, setup, amplitude)
        loss = loss_fn(recon, target)
        psnr_db = psnr(recon.detach(), target, data_range=1.0)
    else:
        phase = model(amplitude, scenes.depth_m)
        losses, psnr_db = focal_stack_error(phase, setup, amplitude, scenes)
        loss = losses.mean()
    loss.backward()
    stats = StepStats(float(loss.detach()), float(psnr_db.mean()), gradient_norm(model), clamped_fraction(phase))
    if math.isfinite(stats.grad_norm):  # the same on every rank of a DDP job: all step or none
        optimiser.step()
    return stats


def peak_normalised(planes: torch.Tensor) -> torch.Tensor:
    """Each image of (B, 1, H, W) scaled to peak 1 (all-zero images stay zero), as `Method` scales targets."""
    peak = planes.amax(dim=(-2, -1), keepdim=True)
    return planes / torch.where(peak > 0, peak, torch.ones_like(peak))


def load_targets(sources: Sequence[ImageSource], grid: tuple[int, int], roi: tuple[int, int],
                 flips: Sequence[tuple[bool, bool]] | None = None) -> torch.Tensor:
    """Targets (B, 3, H, W) on the grid from images, each optionally flipped (horizontal, vertical) first."""
    targets = []
    for i, source in enumerate(sources):
        srgb = source.load(roi)
        if flips is not None:
            horizontal, vertical = flips[i]
            srgb = srgb[:, ::-1] if horizontal else srgb
            srgb = srgb[::-1] if vertical else srgb
        targets.append(prepare_target(np.ascontiguousarray(srgb), grid, roi))
    return torch.stack(targets)


@dataclass(frozen=True)
class TargetLoader:
    """Training images as targets on the grid (`load_targets`); for a network that reads depth (`depth_range_m`
    given), as scenes with their depth over that range and at most `planes` focal planes each."""

    grid: tuple[int, int]
    roi: tuple[int, int]
    depth_range_m: tuple[float, float] | None = None
    planes: int = 1

    def __call__(self, sources: Sequence[ImageSource], flips: Sequence[tuple[bool, bool]] | None = None,
                 jitters: Sequence[float] | None = None) -> tuple[torch.Tensor, SceneDepth | None]:
        """Targets (B, 3, H, W) and, for scenes, their depth; flips as `load_targets`; `jitters` (-0.5 .. 0.5 per
        image) move the focal planes within their bins (`loss_planes`)."""
        if self.depth_range_m is None:
            return load_targets(sources, self.grid, self.roi, flips), None
        near, far = self.depth_range_m
        targets, depths, planes = [], [], []
        rows, cols = centred_slices(self.grid, self.roi)
        for i, source in enumerate(sources):
            srgb, relative = source.load_scene(self.roi)
            if flips is not None:
                axes = [axis for axis, flip in zip((1, 0), flips[i]) if flip]
                srgb, relative = np.flip(srgb, tuple(axes)), np.flip(relative, tuple(axes))
            amplitude, depth = prepare_scene(Scene(source.name, np.ascontiguousarray(srgb),
                                                   near + (far - near) * np.ascontiguousarray(relative)),
                                             self.grid, self.roi)
            targets.append(amplitude)
            depths.append(depth)
            planes.append(loss_planes(depth[rows, cols].numpy(), self.planes, jitters[i] if jitters else 0.0))
        return torch.stack(targets), SceneDepth(torch.stack(depths)[:, None], tuple(planes))


def epoch_jitters(seed: int, epoch: int, positions: Sequence[int]) -> list[float]:
    """Random moves of the focal planes within their bins (-0.5 .. 0.5), fixed by (seed, epoch, position)."""
    return [float(np.random.default_rng([seed, epoch, p, 3]).uniform(-0.5, 0.5)) for p in positions]


def epoch_flips(seed: int, epoch: int, positions: Sequence[int]) -> list[tuple[bool, bool]]:
    """Random (horizontal, vertical) flips, fixed by (seed, epoch, position in the epoch)."""
    flips = (np.random.default_rng([seed, epoch, p]).random(2) < 0.5 for p in positions)
    return [(bool(horizontal), bool(vertical)) for horizontal, vertical in flips]


def epoch_order(n: int, seed: int, epoch: int, length: int) -> np.ndarray:
    """A seeded permutation of range(n), repeated from its start up to `length` entries (so ranks get equal
    shares)."""
    order = np.random.default_rng([seed, epoch, 7]).permutation(n)
    return np.resize(order, length)


Score = Callable[[str, torch.Tensor, "SceneDepth | None"], dict[str, float]]
"""score(colour, peak-normalised target plane (1, 1, H, W), its scene's depth or None) -> scores."""


def phase_stack_scores(phase: torch.Tensor, setup: OpticalSetup, amplitude: torch.Tensor, depth_m: torch.Tensor,
                       planes: Sequence[float]) -> tuple[float, FocalStackScores]:
    """The focal-stack loss and scores (`focal_stack_scores`: per plane in focus, and their mean) of one SLM phase
    (H, W) against a scene: its amplitude and depth (H, W) on the grid, and its planes."""
    rows, cols = setup.roi_slices
    with torch.no_grad():
        recon = setup.reconstruct_planes_roi(setup.without_wavefront(phase), planes).cpu()
    target = amplitude[rows, cols].cpu()
    masks = in_focus_masks(depth_m[rows, cols].cpu(), planes)
    return float(focal_stack_loss(recon, target, masks)), focal_stack_scores(recon, target, masks, planes)


def stack_scores(phase: torch.Tensor, setup: OpticalSetup, amplitude: torch.Tensor,
                 scenes: SceneDepth) -> dict[str, float]:
    """The focal-stack loss and the mean in-focus amplitude PSNR / SSIM over the planes of one SLM phase
    (1, 1, H, W) against its scene (`phase_stack_scores`)."""
    loss, scores = phase_stack_scores(phase[0, 0], setup, amplitude[0, 0], scenes.depth_m[0, 0], scenes.planes_m[0])
    return {"loss": loss} | scores.mean


def evaluate(models: Mapping[str, nn.Module], setups: Mapping[str, OpticalSetup], planes: Mapping[str, int],
             sources: Sequence[ImageSource], loss_fn: nn.Module, device: torch.device,
             loader: TargetLoader | None = None) -> dict[str, dict[str, float]]:
    """Per colour, the mean loss and amplitude scores (`amplitude_scores`; for scenes with depth `stack_scores`)
    over `sources` (unquantised phase); `loader` makes the targets (default: 2D targets on the setups' grid)."""
    def score(colour: str, amplitude: torch.Tensor, scenes: SceneDepth | None) -> dict[str, float]:
        model = models[colour]
        model.eval()
        with torch.no_grad():
            if scenes is not None:
                return stack_scores(model(amplitude.to(device), scenes.depth_m.to(device)), setups[colour],
                                    amplitude.to(device), scenes)
            recon, target = scaled_reconstruction(model, setups[colour], amplitude.to(device))
            return {"loss": float(loss_fn(recon, target))} | amplitude_scores(recon[0, 0].cpu(), target[0, 0].cpu())

    return _mean_scores(setups, planes, sources, score, loader)


def dpac_reference(setups: Mapping[str, OpticalSetup], planes: Mapping[str, int], sources: Sequence[ImageSource],
                   loader: TargetLoader | None = None) -> dict[str, dict[str, float]]:
    """Per colour, DPAC's mean amplitude scores over `sources`, scored as `evaluate` scores a network: the one-shot
    classical hologram a trained model has to beat to be worth its training. Scenes with depth: DPAC of the image
    at the middle of the depth range, scored on the scene's focal stack."""
    dpac = get_method("dpac")

    def score(colour: str, amplitude: torch.Tensor, scenes: SceneDepth | None) -> dict[str, float]:
        setup = setups[colour]
        if scenes is not None:
            assert loader is not None and loader.depth_range_m is not None
            middle = sum(loader.depth_range_m) / 2
            phase = dpac(amplitude[0, 0], setup.at_distance(middle))[None, None]
            return {k: v for k, v in stack_scores(phase, setup, amplitude, scenes).items() if k != "loss"}
        recon = setup.reconstruct_roi(dpac(amplitude[0, 0], setup))
        target = crop_roi(amplitude[0, 0], setup.roi)
        return amplitude_scores(recon * lsq_scale(recon, target), target)

    return _mean_scores(setups, planes, sources, score, loader)


def _mean_scores(setups: Mapping[str, OpticalSetup], planes: Mapping[str, int], sources: Sequence[ImageSource],
                 score: Score, loader: TargetLoader | None = None) -> dict[str, dict[str, float]]:
    """Per colour, the mean over `sources` of `score(colour, peak-normalised target plane (1, 1, H, W), depth)`."""
    if not sources:
        return {}
    some = next(iter(setups.values()))
    load = loader or TargetLoader(some.shape, some.roi)
    sums: dict[str, dict[str, float]] = {c: {} for c in setups}
    for source in sources:
        targets, scenes = load([source])
        for colour in setups:
            amplitude = peak_normalised(targets[:, planes[colour]:planes[colour] + 1])
            for key, value in score(colour, amplitude, scenes).items():
                sums[colour][key] = sums[colour].get(key, 0.0) + value
    return {c: {k: round(v / len(sources), 5) for k, v in s.items()} for c, s in sums.items()}


def training_bench(profile: Profile, size: tuple[int, int] | None, fresnel_scaled: bool = False) -> Profile:
    """The bench trained for: the profile, on grid `size` if given (pitch kept, ROI scaled with the grid; the
    distance kept, as the paper trains at 1080p, 4K and 8K, or with `fresnel_scaled` scaled with the depth range so
    that the Fresnel number is the profile's: `calibration.geometry.grid_profile`)."""
    return (grid_profile(profile, size, scale_distance=fresnel_scaled) if size
            else profile.require("slm", "optics"))


def training_setups(profile: Profile, size: tuple[int, int] | None, colours: Sequence[str] | None,
                    fresnel_scaled: bool = False) -> dict[str, OpticalSetup]:
    """The setup per trained colour on the bench `training_bench` gives."""
    bench = training_bench(profile, size, fresnel_scaled)
    names = list(colours) if colours else [c.name for c in profile.require("laser").channels]
    return optical_setups(bench, [profile.channel(name).name for name in names])


def training_depth_range(profile: Profile, settings: TrainSettings) -> tuple[float, float] | None:
    """The depth range (near, far) metres a network for scenes with depth trains over: the profile's
    `optics.depth_range_mm` on the training bench; None for a 2D network."""
    if not settings.depth:
        return None
    depth_range = training_bench(profile, settings.size, settings.fresnel_scaled).section("optics").depth_range_m
    if depth_range is None:
        raise BenchctlError(f"--method {settings.method} trains on scenes with depth: profile {profile.name!r} shows "
                            "one plane only; set optics.depth_range_mm = [near, far] in it")
    return depth_range


def _geometry_note(profile: Profile, size: tuple[int, int] | None, fresnel_scaled: bool = False) -> str:
    return f"profile {profile.name!r}" + (f" at --size {size[0]}x{size[1]}" if size else "") + \
        (" --fresnel-scaled" if fresnel_scaled else "")


def train(profile: Profile, settings: TrainSettings, out_dir: Path, planes: Mapping[str, int], *,
          resume: Path | None = None, out: Callable[[str], None] = print,
          progress_stream: TextIO | None = None) -> TrainResult:
    """Train `settings.method` for each colour of `profile` (or `settings.colours`); checkpoints go to
    `out_dir/<method>.pt` (+ .json, + .resume.pt) after every epoch and at the end. `planes` maps each laser
    channel to the RGB plane of the images it displays. Joins a torchrun job when the environment has one.
    """
    settings.validate()
    loss_fn = make_loss(settings.loss, settings.vgg_weights)
    setups = training_setups(profile, settings.size, settings.colours, settings.fresnel_scaled)
    geometry = next(iter(setups.values()))
    loader = TargetLoader(geometry.shape, geometry.roi, training_depth_range(profile, settings), settings.planes)
    train_set, val_set = split_sources(image_sources(settings.data), settings.val_fraction, settings.seed)
    job = Distributed.from_env(settings.device)
    if job.device.type == "cpu":  # the estimate is of CPU memory; on a GPU its allocator's refusal is caught below
        check_training_memory(step_estimate(settings, geometry.shape))
    try:
        return _train(profile, settings, Path(out_dir), planes, setups, loader, train_set, val_set, loss_fn, job,
                      resume, out if job.main else (lambda _: None), progress_stream)
    except torch.cuda.OutOfMemoryError:
        free, total = torch.cuda.mem_get_info(job.device)
        grid = geometry.shape
        raise BenchctlError(f"one training step of {settings.method} on {grid[0]} x {grid[1]} with --batch-size "
                            f"{settings.batch_size} does not fit in {job.device}'s memory ({size_text(total)}, "
                            f"{size_text(free)} free now): use a smaller --size or --batch-size, or a DCM "
                            "variant") from None
    finally:
        job.close()


def _train(profile: Profile, settings: TrainSettings, out_dir: Path, planes: Mapping[str, int],
           setups: dict[str, OpticalSetup], loader: TargetLoader, train_set: list[ImageSource],
           val_set: list[ImageSource], loss_fn: ReconstructionLoss, job: Distributed, resume: Path | None,
           out: Callable[[str], None], progress_stream: TextIO | None) -> TrainResult:
    device = job.device
    loss_fn = loss_fn.to(device)
    if job.main:
        ensure_dir(out_dir)
    models: dict[str, nn.Module] = {}
    for colour, setup in setups.items():
        torch.manual_seed(settings.seed)  # every colour, and every process, starts from the same weights
        models[colour] = build_model(settings.method, setup, loader.depth_range_m).to(device)
    optimisers = {c: torch.optim.Adam(m.parameters(), lr=settings.lr, betas=(0.9, 0.999)) for c, m in models.items()}
    averages = {c: WeightAverage(m, settings.ema) for c, m in models.items()} if settings.ema else {}
    position = {"epoch": 0, "batch": 0, "step": 0}
    history: list[dict[str, Any]] = []
    if resume is not None:
        position, history = _resume(resume, settings, profile, setups, models, optimisers, averages, out)
    wrapped = {c: job.wrap(m) for c, m in models.items()}

    per_step = settings.batch_size * job.world_size
    steps_per_epoch = math.ceil(len(train_set) / per_step)
    total = settings.epochs * steps_per_epoch
    if settings.max_steps is not None:
        total = min(total, settings.max_steps)
    schedule = Schedule(settings.lr, settings.warmup, settings.decay, total)
    geometry = next(iter(setups.values()))
    out(f"training {settings.method} for {', '.join(setups)} on {geometry.shape[0]}x{geometry.shape[1]} "
        f"(ROI {geometry.roi[0]}x{geometry.roi[1]}), {len(train_set)} training / {len(val_set)} validation images "
        f"from {settings.data}, {settings.epochs} epoch(s) of {steps_per_epoch} step(s) "
        f"(batch {settings.batch_size} x {job.world_size} process(es)), {total} step(s) in all, on {device}, "
        f"{schedule.describe()}"
        + (f", about {size_text(step_estimate(settings, geometry.shape).peak)} per step" if device.type == "cpu"
           else ""))
    meta = {
        "loss": settings.loss, "lr": settings.lr, "warmup": settings.warmup, "decay": settings.decay,
        "epochs": settings.epochs, "batch_size": settings.batch_size,
        "seed": settings.seed, "val_fraction": settings.val_fraction, "max_steps": settings.max_steps,
        "processes": job.world_size, "device": str(device), "size": list(settings.size) if settings.size else None,
        "profile": profile.name, "data": describe_sources(settings.data, train_set, val_set),
        "command": settings.command(profile, out_dir), "resumed_from": str(resume) if resume else None,
        "optimiser": "Adam(betas=(0.9, 0.999))", "flips": "random horizontal and vertical",
        "loss_region": "ROI, least-squares scaled", "perceptual_weight": PERCEPTUAL_WEIGHT
        if settings.loss == "l2-perceptual" else None,
        "optical_model": {c: s.field_model.to_dict() for c, s in setups.items() if s.field_model is not None} or None,
        "fresnel_scaled": settings.fresnel_scaled,
        **({"planes": settings.planes, "depth_range_mm": [z * 1e3 for z in loader.depth_range_m],
            "loss_region": "ROI, focal stack at each scene's planes (at most --planes, moved within their bins at "
                           "random), in-focus masks, one least-squares scale per stack"}
           if loader.depth_range_m is not None else {}),
        "weight_average": {"decay": settings.ema, "kind": "exponential, bias-corrected"} if settings.ema else None,
    }
    reference = dpac_reference(setups, planes, val_set, loader) if job.main else {}
    progress = ProgressLine(settings.method, stream=progress_stream) if job.main else None
    health = {c: TrainingHealth() for c in setups}
    started = time.perf_counter()
    metrics: dict[str, dict[str, float]] = {}
    saved: Path | None = None
    step = position["step"]
    epoch = position["epoch"]
    while epoch < settings.epochs and step < total:
        order = epoch_order(len(train_set), settings.seed, epoch, steps_per_epoch * per_step)
        sums = {c: [0.0, 0.0] for c in setups}
        batches = 0
        batch = position["batch"] if epoch == position["epoch"] else 0
        while batch < steps_per_epoch and step < total:
            first = batch * per_step + job.rank * settings.batch_size
            positions = list(range(first, first + settings.batch_size))
            targets, scenes = loader([train_set[order[p]] for p in positions],
                                     epoch_flips(settings.seed, epoch, positions),
                                     epoch_jitters(settings.seed, epoch, positions))
            targets, scenes = targets.to(device), scenes.to(device) if scenes is not None else None
            for colour, model in wrapped.items():
                amplitude = peak_normalised(targets[:, planes[colour]:planes[colour] + 1])
                schedule.apply(optimisers[colour], step)
                stats = training_step(model, optimisers[colour], setups[colour], amplitude, loss_fn, scenes)
                verdict = health[colour].update(StepStats(*job.mean(
                    [stats.loss, stats.psnr_db, stats.grad_norm, stats.clamped])))
                if verdict is not None:
                    raise BenchctlError(f"training {settings.method} for {colour} {verdict}. "
                                        + _last_good(out_dir, settings.method, step))
                if averages:
                    averages[colour].update(models[colour])
                sums[colour][0] += stats.loss
                sums[colour][1] += stats.psnr_db
            batch += 1
            batches += 1
            step += 1
            if progress is not None:
                loss_now = sum(s[0] for s in sums.values()) / (len(sums) * batches)
                psnr_now = sum(s[1] for s in sums.values()) / (len(sums) * batches)
                progress.label = (f"{settings.method} epoch {epoch + 1}/{settings.epochs} loss {loss_now:.5f} "
                                  f"PSNR {psnr_now:5.2f} dB")
                progress(step, total)
        epoch_done = batch >= steps_per_epoch
        means = job.mean([v / max(batches, 1) for c in setups for v in sums[c]])
        train_stats = {c: {"train_loss": round(means[2 * i], 6), "train_psnr_amplitude_db": round(means[2 * i + 1], 3)}
                       for i, c in enumerate(setups)}
        position = {"epoch": epoch + 1 if epoch_done else epoch, "batch": 0 if epoch_done else batch, "step": step}
        if job.main:
            kept = {c: averages[c].averaged(m) for c, m in models.items()} if averages else models
            scores = evaluate(kept, setups, planes, val_set, loss_fn, device, loader)
            metrics = {c: train_stats[c] | {f"val_{k}": v for k, v in scores.get(c, {}).items()}
                       | {f"val_dpac_{k}": v for k, v in reference.get(c, {}).items()} for c in setups}
            history.append({"epoch": epoch + 1, "step": step, "complete": epoch_done,
                            "seconds": round(time.perf_counter() - started, 1), "metrics": metrics})
            checkpoint = Checkpoint(
                method=settings.method, geometry={c: s.geometry for c, s in setups.items()},
                weights={c: m.state_dict() for c, m in kept.items()},
                training=meta | {"steps": step, "epochs_done": position["epoch"], "history": history,
                                 "seconds": round(time.perf_counter() - started, 1)},
                metrics=metrics, weights_dtype=settings.weights_dtype)
            saved = checkpoint.save(out_dir / f"{settings.method}.pt", settings.weights_dtype)
            # the resume state carries the weights that train on, and the averages to continue
            resume_state = dataclasses.replace(
                checkpoint, weights={c: m.state_dict() for c, m in models.items()},
                optimisers={c: o.state_dict() for c, o in optimisers.items()}, position=position,
                averages={c: a.to_state() for c, a in averages.items()} or None)
            resume_state.save_resume(out_dir / f"{settings.method}{RESUME_SUFFIX}")
            out(_epoch_line(epoch, settings.epochs, epoch_done, step, metrics, saved))
        job.barrier()
        epoch = position["epoch"]
        if not epoch_done:
            break
    if averages:
        models = {c: averages[c].averaged(m) for c, m in models.items()}
    return TrainResult(models=models, steps=step, epochs_done=position["epoch"], metrics=metrics,
                       checkpoint=saved, rank=job.rank, world_size=job.world_size)


def _last_good(out_dir: Path, method: str, step: int) -> str:
    """Where a stopped run's last good state is (nothing of the failing epoch is written)."""
    resume = out_dir / f"{method}{RESUME_SUFFIX}"
    if not resume.is_file():
        return f"Nothing was written (it stopped in the first epoch, at step {step + 1})."
    position = read_checkpoint(resume).position or {}
    return (f"The last good state is {resume} (step {position.get('step', '?')}): continue from it with "
            "--resume and a lower --lr.")


def _epoch_line(epoch: int, epochs: int, complete: bool, step: int, metrics: Mapping[str, Mapping[str, float]],
                path: Path) -> str:
    state = "" if complete else " (stopped by --max-steps)"
    parts = []
    for colour, m in metrics.items():
        val = (f", val PSNR {m['val_psnr_amplitude_db']:.2f} dB (DPAC {m['val_dpac_psnr_amplitude_db']:.2f})"
               if "val_psnr_amplitude_db" in m else "")
        parts.append(f"{colour} loss {m['train_loss']:.5f}{val}")
    return f"epoch {epoch + 1}/{epochs}{state}, step {step}: {'; '.join(parts)}; wrote {path}"


def _resume(path: Path, settings: TrainSettings, profile: Profile, setups: Mapping[str, OpticalSetup],
            models: Mapping[str, nn.Module], optimisers: Mapping[str, torch.optim.Optimizer],
            averages: Mapping[str, WeightAverage], out: Callable[[str], None]) -> tuple[dict[str, int],
                                                                                    list[dict[str, Any]]]:
    """Load weights (and, from a .resume.pt file, Adam's state, the weight averages and the position) into this
    run."""
    checkpoint = read_checkpoint(path)
    if checkpoint.method != settings.method:
        raise BadValueError(f"--resume {path} holds a {checkpoint.method} model, not --method {settings.method}")
    checkpoint.check(setups, _geometry_note(profile, settings.size, settings.fresnel_scaled))
    extra = [c for c in checkpoint.colours if c not in setups]
    if extra:
        raise BenchctlError(f"--resume {path} also holds {', '.join(extra)}; train the same colours "
                            f"({', '.join(checkpoint.colours)})")
    for colour, model in models.items():
        model.load_state_dict(checkpoint.weights[colour])
    history = list(checkpoint.training.get("history", []))
    if checkpoint.optimisers is None or checkpoint.position is None:
        out(f"{path} holds weights only: continuing from them with a fresh Adam, from step 0 "
            f"(resume from {path.with_suffix('').name}{RESUME_SUFFIX} to continue exactly)")
        return {"epoch": 0, "batch": 0, "step": 0}, history
    _refuse_changes(path, checkpoint.training, settings, setups)
    for colour, optimiser in optimisers.items():
        optimiser.load_state_dict(checkpoint.optimisers[colour])  # its lr is replaced by the schedule's at each step
    saved_lr = {checkpoint.training.get("lr", settings.lr)}
    position = {k: int(v) for k, v in checkpoint.position.items()}
    if averages and checkpoint.averages:
        for colour, average in averages.items():
            average.load_state(checkpoint.averages[colour])
    elif averages:
        out(f"{path} holds no weight average: --ema {settings.ema:g} averages from this step on")
    elif checkpoint.averages:
        out(f"{path} holds a weight average; without --ema this run continues the weights alone")
    changed = f"; learning rate {settings.lr:g} (was {', '.join(f'{lr:g}' for lr in sorted(saved_lr))})" \
        if saved_lr != {settings.lr} else ""
    out(f"resuming from {path}: epoch {position['epoch'] + 1}, step {position['step']}{changed}")
    return position, history


def _refuse_changes(path: Path, recorded: Mapping[str, Any], settings: TrainSettings,
                    setups: Mapping[str, OpticalSetup]) -> None:
    """An exact resume continues the same run: refuse (naming both values) data, seed, batch size, loss, fitted
    optical model or (scenes with depth) planes that differ from the recorded ones (start from the weights alone, a
    .pt file, to change them)."""
    model = {c: s.field_model.to_dict() for c, s in setups.items() if s.field_model is not None} or None
    asked = {"--data": settings.data, "--seed": settings.seed, "--batch-size": settings.batch_size,
             "--loss": settings.loss, "--model-calibration (the fitted optical model)": model}
    recorded_values = {"--data": (recorded.get("data") or {}).get("spec"), "--seed": recorded.get("seed"),
                       "--batch-size": recorded.get("batch_size"), "--loss": recorded.get("loss"),
                       "--model-calibration (the fitted optical model)": recorded.get("optical_model")}
    if settings.depth:
        asked["--planes"], recorded_values["--planes"] = settings.planes, recorded.get("planes")
    changed = [f"{flag} {_shown(asked[flag])} (the run used {_shown(recorded_values[flag])})"
               for flag in asked if recorded_values[flag] != asked[flag]]
    if changed:
        raise BadValueError(f"--resume {path} continues a run exactly, but " + "; ".join(changed) + ": give the "
                            f"run's values, or start from its weights alone (--resume {path.with_suffix('').name}"
                            ".pt) to train differently")


def _shown(value: Any) -> str:
    return "none" if value is None else "a fitted model" if isinstance(value, dict) else str(value)


def run_train(profile: Profile, settings: TrainSettings, out_dir: Path, *, resume: Path | None = None,
              out: Callable[[str], None] = print) -> TrainResult:
    """Train one model per colour of `profile` (each on the image plane its laser displays, as in
    `benchctl generate`), write checkpoints to `out_dir` and print where they are and what they reach."""
    profile = with_model_calibration(profile.require("slm", "optics", "laser"), settings)
    planes = {channel.name: target_plane(channel) for channel in profile.channels}
    result = train(profile, settings, out_dir, planes, resume=resume, out=out)
    if result.rank != 0:
        return result
    if result.checkpoint is None:
        out(f"nothing to train: the run already stands at {settings.epochs} epoch(s) / its --max-steps")
        return result
    for colour, metrics in result.metrics.items():
        scores = (f"validation PSNR {metrics['val_psnr_amplitude_db']:.2f} dB amplitude, SSIM "
                  f"{metrics['val_ssim_amplitude']:.3f} (DPAC on the same images: "
                  f"{metrics['val_dpac_psnr_amplitude_db']:.2f} dB, {metrics['val_dpac_ssim_amplitude']:.3f})"
                  if "val_psnr_amplitude_db" in metrics else "no validation images")
        out(f"{colour:>6}: {scores} (training loss {metrics['train_loss']:.5f})")
    out(f"{result.steps} step(s), {result.epochs_done} complete epoch(s); checkpoint {result.checkpoint}")
    return result


def with_model_calibration(profile: Profile, settings: TrainSettings) -> Profile:
    """`profile` carrying the fitted optical model `--model-calibration` names ("stored": the profile's, from model
    calibration; else an optical-model.json), checked to hold a model for every colour trained, on the profile's
    own grid; `profile` itself without the option."""
    how = settings.model_calibration
    if how is None:
        return profile
    flag = f"--model-calibration {how}"
    if settings.size is not None:
        slm = profile.section("slm")
        raise BadValueError(f"{flag}: the model was fitted on the profile's {slm.height}x{slm.width} "
                            "grid; train on that grid (leave out --size)")
    optics = profile.section("optics")
    if how == "stored":
        calibrated = Calibration.store(profile).with_model(replace(profile, optics=replace(optics, model=None)))
        if calibrated.section("optics").model is None:
            raise BenchctlError(f"{flag}: no fitted optical model is stored for profile {profile.name!r}; run "
                                "procedures/model_calibration.toml first, or name an optical-model.json")
    else:
        path = Path(how).expanduser()
        if not path.is_file():
            raise BadValueError(f"{flag}: no such file")
        calibrated = replace(profile, optics=replace(optics, model=path.resolve()))
    model = calibrated.section("optics").model
    for name in settings.colours or [channel.name for channel in profile.channels]:
        entry = fitted_model_entry(calibrated, profile.channel(name).name)  # a bad file: one line naming key and value
        if entry is None:
            raise BadValueError(f"{flag}: {model} has no fitted model for {name!r}")
        fitted_for, here = entry.get("geometry"), validity(profile, name)
        if fitted_for is not None and fitted_for != here:
            raise BadValueError(f"{flag}: {model} was fitted for another geometry than profile "
                                f"{profile.name!r} ({_geometry_change(fitted_for, here)})")
    return calibrated


def _geometry_change(fitted: Mapping[str, Any], now: Mapping[str, Any]) -> str:
    return "; ".join(f"{key} {fitted.get(key)} there, {now.get(key)} here" for key in sorted(set(fitted) | set(now))
                     if fitted.get(key) != now.get(key))
