"""Metrics: ROI crop, least-squares scale, PSNR by hand, SSIM against an independent float64 reference."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from numpy.lib.stride_tricks import sliding_window_view

from benchctl.optics.metrics import crop_roi, lsq_scale, psnr, ssim


def reference_ssim(a: np.ndarray, b: np.ndarray, data_range: float) -> float:
    """Textbook SSIM in float64: explicit 2-D Gaussian window slid over the valid region (no padding)."""
    size = min(11, *(n if n % 2 else n - 1 for n in a.shape))
    offsets = np.arange(size) - (size - 1) / 2
    g = np.exp(-(offsets**2) / (2 * 1.5**2))
    window = np.outer(g, g) / np.outer(g, g).sum()

    def local_mean(img: np.ndarray) -> np.ndarray:
        return np.einsum("ijkl,kl->ij", sliding_window_view(img, (size, size)), window)

    a, b = a.astype(np.float64), b.astype(np.float64)
    mu_a, mu_b = local_mean(a), local_mean(b)
    var_a = local_mean(a**2) - mu_a**2
    var_b = local_mean(b**2) - mu_b**2
    cov = local_mean(a * b) - mu_a * mu_b
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    s = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2))
    return float(s.mean())


def _structured_pair(rng: np.random.Generator, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    y, x = np.mgrid[0:h, 0:w]
    clean = 0.5 + 0.4 * np.sin(x / 3.0) * np.cos(y / 5.0)
    clean[h // 3 : h // 2, w // 4 : w // 2] = 1.0  # a sharp-edged block
    noisy = np.clip(0.8 * clean + 0.05 * rng.standard_normal((h, w)), 0, 1)
    return clean, noisy


@pytest.mark.parametrize("shape", [(64, 64), (48, 80), (9, 30), (8, 12), (5, 5), (1, 17)])
def test_ssim_matches_reference(shape: tuple[int, int]) -> None:
    rng = np.random.default_rng(sum(shape))
    pairs = [(rng.random(shape), rng.random(shape)), _structured_pair(rng, *shape)]
    for data_range, scale in ((1.0, 1.0), (255.0, 255.0)):
        for a, b in pairs:
            got = ssim(torch.tensor(a * scale, dtype=torch.float32), torch.tensor(b * scale, dtype=torch.float32),
                       data_range=data_range)
            assert abs(got.item() - reference_ssim(a * scale, b * scale, data_range)) < 1e-3


def test_ssim_is_batched_over_leading_dims() -> None:
    rng = np.random.default_rng(0)
    a, b = rng.random((2, 3, 32, 40)), rng.random((2, 3, 32, 40))
    got = ssim(torch.tensor(a), torch.tensor(b), data_range=1.0)
    assert got.shape == (2, 3)
    for i in range(2):
        for c in range(3):
            assert abs(got[i, c].item() - reference_ssim(a[i, c], b[i, c], 1.0)) < 1e-6


def test_psnr_known_values() -> None:
    target = torch.zeros(2, 16, 16)
    pred = torch.full((2, 16, 16), 0.1)
    pred[1] = 0.0
    pred[1, :8, :8] = 0.5  # a quarter of the pixels off by 0.5: mse = 0.0625
    got = psnr(pred, target, data_range=1.0)
    torch.testing.assert_close(got, torch.tensor([20.0, 10 * math.log10(16.0)]))
    off_by_one = psnr(torch.full((8, 8), 101.0), torch.full((8, 8), 100.0), data_range=255.0)
    assert off_by_one.shape == ()
    assert off_by_one.item() == pytest.approx(20 * math.log10(255.0), abs=1e-4)


@pytest.mark.parametrize("fill", [0.0, 0.3, 1.0])
def test_identical_constant_and_black_images_are_finite(fill: float) -> None:
    img = torch.full((3, 20, 20), fill)
    torch.testing.assert_close(psnr(img, img.clone(), data_range=1.0), torch.full((3,), 100.0))
    torch.testing.assert_close(ssim(img, img.clone(), data_range=1.0), torch.ones(3))
    other = torch.full((3, 20, 20), 1.0 - fill)
    assert torch.isfinite(psnr(img, other, data_range=1.0)).all()
    assert torch.isfinite(ssim(img, other, data_range=1.0)).all()


def test_metrics_validate_arguments() -> None:
    a = torch.rand(16, 16)
    with pytest.raises(ValueError, match="data_range"):
        psnr(a, a, data_range=0)
    with pytest.raises(ValueError, match="shape mismatch"):
        ssim(a, torch.rand(16, 15), data_range=1.0)


def test_gradients_are_finite_even_for_identical_constant_images() -> None:
    for pred_value in (torch.full((2, 16, 16), 0.5), torch.rand(2, 16, 16)):
        target = torch.full((2, 16, 16), 0.5)
        pred = pred_value.clone().requires_grad_(True)
        (psnr(pred, target, 1.0).sum() + ssim(pred, target, 1.0).sum()).backward()
        assert torch.isfinite(pred.grad).all()


def test_lsq_scale_recovers_a_known_scale_and_handles_zero() -> None:
    target = torch.rand(3, 24, 24) + 0.1
    recon = target / 2.5
    recon[2] = 0.0
    s = lsq_scale(recon, target)
    assert s.shape == (3, 1, 1)
    torch.testing.assert_close(s[:2].flatten(), torch.full((2,), 2.5))
    assert s[2].item() == 1.0
    torch.testing.assert_close((s * recon)[:2], target[:2])
    recon.requires_grad_(True)
    lsq_scale(recon, target).sum().backward()
    assert torch.isfinite(recon.grad).all()


def test_crop_roi_is_centred() -> None:
    x = torch.arange(8 * 10).reshape(1, 8, 10)
    crop = crop_roi(x, (4, 6))
    assert crop.shape == (1, 4, 6)
    assert crop[0, 0, 0].item() == x[0, 2, 2].item()
    assert crop_roi(x, (8, 10)).equal(x)
    with pytest.raises(ValueError, match="ROI 9x10 does not fit in a 8x10 image"):
        crop_roi(x, (9, 10))


@pytest.mark.parametrize("shape", [(64, 80), (31, 120)])
def test_ssim_and_psnr_match_scikit_image(shape: tuple[int, int]) -> None:
    """An independent oracle: scikit-image's structural_similarity with the paper's settings (Gaussian weights,
    sigma 1.5, population statistics) and peak_signal_noise_ratio, on a photograph-like pair."""
    from skimage.metrics import peak_signal_noise_ratio, structural_similarity

    rng = np.random.default_rng(7)
    a = rng.random(shape)
    b = np.clip(a + 0.3 * rng.standard_normal(shape), 0, 1) * 0.8
    expected_ssim = structural_similarity(a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                          data_range=1.0)
    got = ssim(torch.tensor(b), torch.tensor(a), data_range=1.0).item()
    assert got == pytest.approx(expected_ssim, abs=1e-9)
    assert 0.1 < expected_ssim < 0.9  # a pair that exercises both terms, not a trivial 0 or 1
    assert psnr(torch.tensor(b), torch.tensor(a), data_range=1.0).item() == pytest.approx(
        peak_signal_noise_ratio(a, b, data_range=1.0), abs=1e-9)
