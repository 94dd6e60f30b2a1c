"""The one place for image scores: ROI crop, least-squares scale, PSNR and SSIM, in torch.

Images are tensors shaped (..., H, W); every leading index (batch, colour channel) is scored on its own and
the result has shape (...). Callers pass data_range explicitly and say which domain they score in
(amplitude, linear intensity or sRGB). Nothing here returns NaN or inf, and everything is differentiable.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from benchctl.optics.colour import linear_to_srgb

PSNR_MSE_FLOOR = 1e-10
"""MSE floor as a fraction of data_range**2: PSNR never exceeds 100 dB (identical images score exactly 100)."""

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_K1 = 0.01
SSIM_K2 = 0.03


def centred_slices(shape: tuple[int, int], roi: tuple[int, int]) -> tuple[slice, slice]:
    """Row and column slices of a roi = (rows, cols) region centred in an (H, W) grid (extra pixel low)."""
    (h, w), (rows, cols) = shape, roi
    if not (0 < rows <= h and 0 < cols <= w):
        raise ValueError(f"ROI {rows}x{cols} does not fit in a {h}x{w} image")
    top, left = (h - rows) // 2, (w - cols) // 2
    return slice(top, top + rows), slice(left, left + cols)


def crop_roi(x: torch.Tensor, roi: tuple[int, int]) -> torch.Tensor:
    """Centred crop of (..., H, W) to roi = (rows, cols): the region that holds the target."""
    rows, cols = centred_slices((x.shape[-2], x.shape[-1]), roi)
    return x[..., rows, cols]


def _check_pair(pred: torch.Tensor, target: torch.Tensor, data_range: float) -> None:
    if pred.shape != target.shape:
        raise ValueError(f"shape mismatch: {tuple(pred.shape)} vs {tuple(target.shape)}")
    if pred.dim() < 2:
        raise ValueError(f"images must be shaped (..., H, W), got {tuple(pred.shape)}")
    if not data_range > 0:
        raise ValueError(f"data_range must be > 0, got {data_range!r}")


def lsq_scale(recon: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Per-image s minimising |s recon - target|^2, i.e. sum(r t) / sum(r^2), shaped (..., 1, 1).

    The shape broadcasts against the images, so `lsq_scale(r, t) * r` is the scaled reconstruction.
    An all-zero reconstruction has no best scale; it gets s = 1.
    """
    if recon.shape != target.shape:
        raise ValueError(f"shape mismatch: {tuple(recon.shape)} vs {tuple(target.shape)}")
    num = (recon * target).sum(dim=(-2, -1), keepdim=True)
    den = (recon * recon).sum(dim=(-2, -1), keepdim=True)
    nonzero = den > 0
    return torch.where(nonzero, num / torch.where(nonzero, den, torch.ones_like(den)), torch.ones_like(den))


def psnr(pred: torch.Tensor, target: torch.Tensor, data_range: float) -> torch.Tensor:
    """Peak signal-to-noise ratio in dB per image, shaped (...); capped at 100 dB (see PSNR_MSE_FLOOR)."""
    _check_pair(pred, target, data_range)
    return psnr_of_mse(((pred - target) ** 2).mean(dim=(-2, -1)), data_range)


def psnr_of_mse(mse: torch.Tensor, data_range: float) -> torch.Tensor:
    """PSNR in dB of a mean squared error (any shape), capped at 100 dB as `psnr` is."""
    return 10.0 * torch.log10(data_range**2 / mse.clamp(min=PSNR_MSE_FLOOR * data_range**2))


def _gaussian_window(size: int, sigma: float, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return (g / g.sum()).to(dtype=dtype, device=device)


def ssim(pred: torch.Tensor, target: torch.Tensor, data_range: float) -> torch.Tensor:
    """Structural similarity (Wang et al. 2004) per image, shaped (...): `ssim_map` averaged over its pixels."""
    return ssim_map(pred, target, data_range).mean(dim=(-2, -1))


def ssim_map(pred: torch.Tensor, target: torch.Tensor, data_range: float) -> torch.Tensor:
    """The local structural similarity (Wang et al. 2004) of each window position, (..., H - s + 1, W - s + 1).

    Gaussian s x s window, s = 11, sigma 1.5, K1 = 0.01, K2 = 0.03, population (not sample) statistics, on the
    valid region (no padding): entry (i, j) is the window centred on pixel (i + s // 2, j + s // 2). Images
    narrower than 11 px in either direction use the largest odd window that fits, with the same sigma (the
    Gaussian is truncated and renormalised). Two identical images score 1, constant and black ones included,
    because C1 and C2 keep both fractions away from 0 / 0.
    """
    _check_pair(pred, target, data_range)
    if not pred.is_floating_point():
        pred, target = pred.float(), target.float()
    *lead, h, w = pred.shape
    size = min(SSIM_WINDOW, h - (1 - h % 2), w - (1 - w % 2))
    g = _gaussian_window(size, SSIM_SIGMA, pred.dtype, pred.device)
    kernel_rows, kernel_cols = g.view(1, 1, size, 1), g.view(1, 1, 1, size)

    def blur(x: torch.Tensor) -> torch.Tensor:
        return F.conv2d(F.conv2d(x, kernel_rows), kernel_cols)

    x = pred.reshape(-1, 1, h, w)
    y = target.reshape(-1, 1, h, w)
    mu_x, mu_y = blur(x), blur(y)
    var_x = blur(x * x) - mu_x**2
    var_y = blur(y * y) - mu_y**2
    cov = blur(x * y) - mu_x * mu_y
    c1 = (SSIM_K1 * data_range) ** 2
    c2 = (SSIM_K2 * data_range) ** 2
    luminance = (2 * mu_x * mu_y + c1) / (mu_x**2 + mu_y**2 + c1)
    structure = (2 * cov + c2) / (var_x + var_y + c2)
    values = luminance * structure
    return values.reshape(*lead, *values.shape[-2:])


def amplitude_scores(recon: torch.Tensor, target: torch.Tensor, *, perceptual: bool = False) -> dict[str, float]:
    """PSNR / SSIM of an amplitude image against the target amplitude (same shape, already scaled), in amplitude,
    linear intensity and sRGB: the one scoring of a colour, for simulated reconstructions and captures alike.
    `perceptual` adds the mean FLIP error (`flip_map`) and, where the target holds flat regions, the speckle
    contrast there (`speckle_contrast`)."""
    lin_r, lin_t = recon.square().clamp(0, 1), target.square().clamp(0, 1)
    srgb_r, srgb_t = linear_to_srgb(lin_r), linear_to_srgb(lin_t)
    scores = {
        "psnr_amplitude_db": float(psnr(recon, target, data_range=1.0).mean()),
        "ssim_amplitude": float(ssim(recon, target, data_range=1.0).mean()),
        "psnr_linear_db": float(psnr(lin_r, lin_t, data_range=1.0).mean()),
        "psnr_srgb_db": float(psnr(srgb_r, srgb_t, data_range=1.0).mean()),
        "ssim_srgb": float(ssim(srgb_r, srgb_t, data_range=1.0).mean()),
    }
    if perceptual:
        scores |= perceptual_scores(recon, target)
    return scores


def perceptual_scores(recon: torch.Tensor, target: torch.Tensor,
                      region: torch.Tensor | None = None) -> dict[str, float]:
    """Mean FLIP error of an amplitude image (h, w) against its target (already scaled), over `region` (bool (h, w);
    all pixels if None), and the speckle contrast on the flat part of the region, where it has one."""
    region = torch.ones(recon.shape[-2:], dtype=torch.bool) if region is None else region.cpu()
    scores = {"flip": float(flip_map(recon, target)[region].mean())}
    contrast = speckle_contrast(recon, target, region)
    if contrast is not None:
        scores["speckle_contrast"] = contrast
    return scores


def colour_scores(merged_linear: torch.Tensor, target_roi: torch.Tensor, *,
                  with_ssim: bool = True, perceptual: bool = False) -> dict[str, float]:
    """Scores of a merged colour image (3, h, w) in linear intensity against the target amplitude (3, h, w): PSNR
    over all planes at once, in linear and sRGB, (`with_ssim`) SSIM in sRGB averaged over planes and (`perceptual`)
    the mean FLIP error of the colour image."""
    h, w = merged_linear.shape[-2:]
    lin_t = target_roi.square().clamp(0, 1)
    srgb_r, srgb_t = linear_to_srgb(merged_linear), linear_to_srgb(lin_t)
    scores = {
        "psnr_linear_db": float(psnr(merged_linear.reshape(3 * h, w), lin_t.reshape(3 * h, w), data_range=1.0)),
        "psnr_srgb_db": float(psnr(srgb_r.reshape(3 * h, w), srgb_t.reshape(3 * h, w), data_range=1.0)),
    }
    if with_ssim:
        scores["ssim_srgb"] = float(ssim(srgb_r, srgb_t, data_range=1.0).mean())
    if perceptual:
        scores["flip"] = float(_flip(srgb_r, srgb_t).mean())
    return scores


def _flip(srgb: torch.Tensor, reference_srgb: torch.Tensor) -> torch.Tensor:
    """LDR-FLIP error map (h, w) of an sRGB image (3, h, w) against a reference one, 67 pixels per degree."""
    import flip_evaluator  # a compiled extension: loaded only where perceptual scores are asked for

    def hwc(image: torch.Tensor) -> np.ndarray:
        return np.ascontiguousarray(image.detach().float().clamp(0, 1).permute(1, 2, 0).cpu().numpy())

    error, _, _ = flip_evaluator.evaluate(hwc(reference_srgb), hwc(srgb), "LDR", inputsRGB=True, applyMagma=False,
                                          computeMeanError=False)
    return torch.from_numpy(np.asarray(error, dtype=np.float32).reshape(srgb.shape[-2:]))


def flip_map(recon: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """The FLIP error map (h, w), in [0, 1], of an amplitude image (h, w) against its target amplitude: NVIDIA's
    LDR-FLIP (Andersson et al. 2020, PyPI flip-evaluator) on the intensities in sRGB, gray as three equal channels,
    at its default viewing condition (67 pixels per degree). Not differentiable."""
    srgb_r, srgb_t = (linear_to_srgb(x.detach().square().clamp(0, 1)).expand(3, *x.shape[-2:]) for x in (recon, target))
    return _flip(srgb_r, srgb_t)


FLAT_WINDOW = 7
"""Side (pixels) of the neighbourhood in which a target must hold flat for its speckle to be measured."""
FLAT_TOLERANCE = 0.02
"""Largest amplitude spread (of a peak of 1) within that neighbourhood that counts as flat."""
FLAT_FLOOR = 0.1
"""Smallest target amplitude where speckle is measured: dark regions hold no light whose spread could be told."""
MIN_FLAT_PIXELS = 64


def flat_regions(target: torch.Tensor) -> torch.Tensor:
    """Where the target amplitude (h, w) is lit (>= FLAT_FLOOR) and varies by at most FLAT_TOLERANCE over the
    FLAT_WINDOW x FLAT_WINDOW pixels around: bool (h, w)."""
    image = target.detach().float()[None, None]
    pad = FLAT_WINDOW // 2
    highest = F.max_pool2d(F.pad(image, (pad,) * 4, mode="replicate"), FLAT_WINDOW, stride=1)
    lowest = -F.max_pool2d(F.pad(-image, (pad,) * 4, mode="replicate"), FLAT_WINDOW, stride=1)
    return ((highest - lowest <= FLAT_TOLERANCE) & (image >= FLAT_FLOOR))[0, 0]


def speckle_contrast(recon: torch.Tensor, target: torch.Tensor, region: torch.Tensor | None = None) -> float | None:
    """Speckle contrast std / mean of the reconstructed intensity over the target's intensity, on the pixels of
    `region` (default all) where the target holds flat (`flat_regions`): 0 for a reconstruction without speckle,
    whatever the level of each flat region. None where fewer than MIN_FLAT_PIXELS such pixels exist."""
    flat = flat_regions(target)
    if region is not None:
        flat &= region.to(flat.device)
    if int(flat.sum()) < MIN_FLAT_PIXELS:
        return None
    ratio = (recon.detach().double().square()[flat] / target.detach().double().square()[flat])
    mean = ratio.mean()
    return float(ratio.std(unbiased=False) / mean) if float(mean) > 0 else None


def pareto_front(points: Sequence[tuple[float, float]]) -> list[bool]:
    """For each (seconds, psnr) point, whether no other point is at least as fast and as good and better in one.

    Ties (the same point twice) are both on the front.
    """
    return [not any(t2 <= t1 and p2 >= p1 and (t2 < t1 or p2 > p1) for t2, p2 in points) for t1, p1 in points]
