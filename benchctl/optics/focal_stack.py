"""Scenes with depth as holograms see them: the focal-stack target of one colour, in-focus masks, the focal-stack
loss and per-plane scores (torch).

Depth is the distance from the SLM along the optical axis, in metres, per pixel. A focal stack is the
reconstruction at K planes (`OpticalSetup.reconstruct_planes`). Following Neural 3D Holography (Choi et al. 2021)
each plane is judged only where the scene is in focus there: each pixel belongs to the plane nearest its depth
(or, with a softness, to every plane with a Gaussian weight of its distance to it). The loss takes one
least-squares scale for the whole stack (a hologram sends the same light to every plane); scores take one per plane,
as 2D scores take one per image. A target with a sweep (`DepthSweep`) has its planes moved from one iteration of an
optimiser to the next (`FocalStackTarget.swept`): each plane then scores only the pixels whose depth lies near it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import torch

from benchctl.optics.colour import linear_to_srgb
from benchctl.optics.metrics import lsq_scale, perceptual_scores, psnr, psnr_of_mse, ssim_map
from benchctl.optics.planes import DepthSweep


def in_focus_masks(depth_m: torch.Tensor, planes_m: Sequence[float], softness_m: float = 0.0) -> torch.Tensor:
    """Per plane, where the scene is in focus there: (K, ...) float32 for a depth map (...).

    Hard (`softness_m` 0): 1 at the plane nearest each pixel's depth (the nearer plane to the SLM on a tie), 0 at
    the others. Soft: weights exp(-(d - z_k)^2 / (2 softness^2)) normalised over the planes. Either way the weights
    of a pixel sum to 1 over the planes.
    """
    if not planes_m:
        raise ValueError("a focal stack needs at least one plane")
    if not softness_m >= 0:
        raise ValueError(f"softness_m must be >= 0, got {softness_m!r}")
    planes = torch.tensor([float(z) for z in planes_m], dtype=torch.float64, device=depth_m.device)
    offset = depth_m.to(torch.float64).unsqueeze(0) - planes.view(-1, *([1] * depth_m.dim()))
    if softness_m == 0:
        nearest = offset.abs().argmin(dim=0)
        return torch.nn.functional.one_hot(nearest, len(planes)).movedim(-1, 0).to(torch.float32)
    return torch.softmax(-offset.square() / (2 * softness_m**2), dim=0).to(torch.float32)


def nearest_plane(depth_m: torch.Tensor, planes_m: Sequence[float]) -> torch.Tensor:
    """Per pixel, the index of the plane (ascending `planes_m`) nearest its depth, the nearer to the SLM on a tie
    (`in_focus_masks`' hard rule, without its K maps); float32 depths, which resolve nanometres at these distances."""
    planes = torch.tensor([float(z) for z in planes_m], dtype=torch.float32, device=depth_m.device)
    return torch.searchsorted((planes[1:] + planes[:-1]) / 2, depth_m.to(torch.float32).contiguous())


@dataclass(frozen=True, eq=False)
class FocalStackTarget:
    """What a hologram of a scene with depth aims for in one colour: the amplitude (H, W) on the SLM grid (zero
    outside the ROI, as a 2D target), the depth (H, W) in metres from the SLM, the planes (metres, ascending) it is
    shown at, and per plane the in-focus mask (K, H, W) that `in_focus_masks` gives; with a `sweep`, the depths an
    optimiser moves its planes through instead (`swept`)."""

    amplitude: torch.Tensor
    depth_m: torch.Tensor
    planes_m: tuple[float, ...]
    softness_m: float = 0.0
    sweep: DepthSweep | None = None
    masks: torch.Tensor = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if not isinstance(self.amplitude, torch.Tensor) or not isinstance(self.depth_m, torch.Tensor):
            raise TypeError("a focal-stack target's amplitude and depth must be torch tensors")
        if self.amplitude.dim() != 2 or self.depth_m.shape != self.amplitude.shape:
            raise ValueError(f"amplitude {tuple(self.amplitude.shape)} and depth {tuple(self.depth_m.shape)} must be "
                             "two maps (H, W) of one shape")
        if not bool(torch.isfinite(self.depth_m).all()) or not bool((self.depth_m > 0).all()):
            raise ValueError("depth must be finite and > 0 (metres from the SLM) everywhere")
        planes = tuple(float(z) for z in self.planes_m)
        if not planes or any(not (math.isfinite(z) and z > 0) for z in planes) or list(planes) != sorted(set(planes)):
            raise ValueError(f"planes_m must be distinct distances > 0 in ascending order, got {self.planes_m!r}")
        if self.sweep is not None and len(self.sweep.depths_m) != len(planes):
            raise ValueError(f"a sweep of {len(self.sweep.depths_m)} planes for {len(planes)} planes")
        object.__setattr__(self, "planes_m", planes)
        object.__setattr__(self, "masks", in_focus_masks(self.depth_m, planes, self.softness_m))

    def with_amplitude(self, amplitude: torch.Tensor) -> FocalStackTarget:
        """The same depth, planes and masks for another amplitude (a checked or scaled one)."""
        twin = FocalStackTarget.__new__(FocalStackTarget)
        for name, value in (("amplitude", amplitude), ("depth_m", self.depth_m), ("planes_m", self.planes_m),
                            ("softness_m", self.softness_m), ("sweep", self.sweep), ("masks", self.masks)):
            object.__setattr__(twin, name, value)
        return twin

    def swept(self, iteration: int, region: tuple[slice, slice] | None = None) -> tuple[list[int], torch.Tensor]:
        """Where the sweep's planes stand at `iteration` (`DepthSweep.at`: their indices into `sweep.all_m`) and their
        masks (K, ...) on `region` (rows, cols) of the depth map (None: all of it): each pixel scored at the plane
        nearest its depth if that lies within `sweep.reach_m` (farther from every plane: left out of this
        iteration). Hard masks whatever the softness: a sweep scores only near each plane."""
        if self.sweep is None:
            raise ValueError("this focal-stack target has no sweep")
        picks, planes = self.sweep.at(iteration)
        depth = (self.depth_m if region is None else self.depth_m[region]).to(torch.float32)
        nearest = nearest_plane(depth, planes)
        at = torch.tensor(planes, dtype=torch.float32, device=depth.device)
        nearest = torch.where((depth - at[nearest]).abs() <= self.sweep.reach_m, nearest, len(planes))
        index = torch.arange(len(planes), device=depth.device).view(-1, *[1] * depth.dim())
        return picks, (nearest.unsqueeze(0) == index).to(torch.float32)


def focal_stack_loss(recon: torch.Tensor, target: torch.Tensor, masks: torch.Tensor) -> torch.Tensor:
    """Masked MSE of a focal stack: sum over planes and pixels of mask * (s recon - target)^2, divided by the pixels
    of one plane; `recon` (..., K, h, w), `target` (h, w), `masks` (K, h, w). s is the least-squares scale of the
    whole stack, held constant for autograd (exact at the optimum, as for `sgd.roi_loss`). With one plane and a
    mask of ones it is that plane's MSE after `lsq_scale`."""
    scale = stack_scale(recon.detach(), target, masks)
    error = (masks * (scale * recon - target).square()).sum(dim=(-3, -2, -1))
    return (error / (target.shape[-2] * target.shape[-1])).mean()


def stack_scale(recon: torch.Tensor, target: torch.Tensor, masks: torch.Tensor) -> torch.Tensor:
    """The least-squares scale of a focal stack (..., K, h, w) against `target` (h, w) over the in-focus `masks`
    (K, h, w): sum(m r t) / sum(m r^2), shaped (..., 1, 1, 1); 1 where the stack is dark."""
    weighted = masks * recon
    numerator = (weighted * target).sum(dim=(-3, -2, -1), keepdim=True)
    denominator = (weighted * recon).sum(dim=(-3, -2, -1), keepdim=True)
    return torch.where(denominator > 0, numerator / torch.where(denominator > 0, denominator, 1.0), 1.0)


def masked_scores(recon: torch.Tensor, target: torch.Tensor, region: torch.Tensor, *,
                  perceptual: bool = False) -> dict[str, float] | None:
    """Amplitude PSNR and SSIM of `recon` against `target` (h, w) inside `region` (h, w, bool), after the
    least-squares scale over the region; None for an empty region. SSIM: the mean over the windows that lie wholly
    inside the region, or where the region holds no whole window, over those centred inside it. `perceptual` adds
    FLIP and speckle contrast inside the region (`perceptual_scores`)."""
    if not bool(region.any()):
        return None
    inside = region.to(recon.dtype)
    scaled = lsq_scale(recon * inside, target * inside) * recon
    mse = ((scaled - target).square() * inside).sum() / inside.sum()
    scores = {"psnr_amplitude_db": float(psnr_of_mse(mse, data_range=1.0))}
    local = ssim_map(scaled, target, data_range=1.0)
    size = (region.shape[-2] - local.shape[-2] + 1, region.shape[-1] - local.shape[-1] + 1)
    outside = (~region).to(torch.float32)[None, None]
    whole = torch.nn.functional.max_pool2d(outside, size, stride=1)[0, 0] == 0
    top, left = size[0] // 2, size[1] // 2
    centred = region[top:top + local.shape[-2], left:left + local.shape[-1]]
    windows = whole if bool(whole.any()) else centred
    scores["ssim_amplitude"] = float(local[windows].mean() if bool(windows.any()) else local.mean())
    if perceptual:
        scores |= perceptual_scores(scaled, target, region)
    return scores


def masked_colour_scores(merged_linear: torch.Tensor, target: torch.Tensor,
                         region: torch.Tensor) -> dict[str, float] | None:
    """PSNR of a merged colour image (3, h, w, linear intensity, balanced as `merge_colours` balances it) against the
    target amplitude (3, h, w) inside `region` (h, w, bool), in linear intensity and in sRGB, over the three colours
    together (as `colour_scores` over the whole image); None for an empty region."""
    if not bool(region.any()):
        return None
    inside = region.to(merged_linear.dtype)
    wanted = target.square().clamp(0, 1)

    def db(image: torch.Tensor, reference: torch.Tensor) -> float:
        mse = ((image - reference).square() * inside).sum() / (image.shape[0] * inside.sum())
        return float(psnr_of_mse(mse, data_range=1.0))

    return {"psnr_linear_db": db(merged_linear, wanted),
            "psnr_srgb_db": db(linear_to_srgb(merged_linear.clamp(0, 1)), linear_to_srgb(wanted))}


@dataclass
class FocalStackScores:
    """Scores of a focal stack: per plane (None where no pixel is in focus there) and their mean over the planes
    that have some."""

    planes_m: tuple[float, ...]
    per_plane: list[dict[str, float] | None]
    mean: dict[str, float]


def focal_stack_scores(recon: torch.Tensor, target: torch.Tensor, masks: torch.Tensor,
                       planes_m: Sequence[float], *, perceptual: bool = False) -> FocalStackScores:
    """Each plane of `recon` (K, h, w) scored inside its in-focus region (where its mask is the largest of the
    pixel's weights) against `target` (h, w), by `masked_scores`; the mean over the planes with a region (a score
    that only some planes have, such as speckle contrast, over those)."""
    if recon.dim() != 3 or masks.shape != recon.shape or target.shape != recon.shape[-2:]:
        raise ValueError(f"focal stack {tuple(recon.shape)}, masks {tuple(masks.shape)} and target "
                         f"{tuple(target.shape)} must be (K, h, w), (K, h, w) and (h, w)")
    owner = masks.argmax(dim=0)
    per_plane = [masked_scores(recon[k], target, owner == k, perceptual=perceptual) for k in range(len(recon))]
    return FocalStackScores(tuple(float(z) for z in planes_m), per_plane, mean_scores(per_plane))


def all_in_focus_psnr(stack: torch.Tensor, target: torch.Tensor, owner: torch.Tensor) -> float:
    """Amplitude PSNR of the all-in-focus image of a focal stack (K, h, w): each pixel from the plane `owner` (h, w)
    names (the plane nearest its depth, `nearest_plane`), one least-squares scale against `target` (h, w). What a
    viewer sees focusing on each point in turn, at the planes of the stack."""
    return scaled_psnr(stack.gather(0, owner.to(stack.device)[None])[0], target)


def scaled_psnr(image: torch.Tensor, target: torch.Tensor) -> float:
    """Amplitude PSNR of `image` against `target` (h, w) after one least-squares scale."""
    wanted = target.to(image.device)
    return float(psnr(lsq_scale(image, wanted) * image, wanted, data_range=1.0))


def mean_scores(scores: Sequence[dict[str, float] | None]) -> dict[str, float]:
    """Key by key, the mean over the score dicts that have the key (None entries left out); {} for none."""
    present = [s for s in scores if s is not None]
    keys = dict.fromkeys(key for s in present for key in s)
    return {key: sum(s[key] for s in present if key in s) / sum(key in s for s in present) for key in keys}
