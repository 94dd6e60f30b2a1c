"""sRGB transfer curve: reference values, round trip, clamping, extrapolation above 1, finite gradients."""

from __future__ import annotations

import torch

from benchctl.optics.colour import linear_to_srgb, srgb_to_linear


def test_reference_values() -> None:
    """Published values of the sRGB curve (IEC 61966-2-1): the knee at 0.04045 <-> 0.0031308, mid-level 0.5 ->
    0.2140, 8-bit 128 -> 0.2159, 18 % grey -> 0.4614, linear 0.5 -> 0.7354 (to the 4 digits they are quoted to)."""
    srgb = torch.tensor([0.0, 0.04045, 0.5, 128 / 255, 1.0], dtype=torch.float64)
    published = torch.tensor([0.0, 0.0031308, 0.2140, 0.2159, 1.0], dtype=torch.float64)
    torch.testing.assert_close(srgb_to_linear(srgb), published, atol=5e-5, rtol=0)
    linear = torch.tensor([0.0031308, 0.18, 0.5], dtype=torch.float64)
    torch.testing.assert_close(linear_to_srgb(linear), torch.tensor([0.04045, 0.4614, 0.7354], dtype=torch.float64),
                               atol=5e-5, rtol=0)


def test_round_trip_any_shape() -> None:
    x = torch.rand(2, 3, 5, 7, dtype=torch.float64)
    torch.testing.assert_close(linear_to_srgb(srgb_to_linear(x)), x)
    torch.testing.assert_close(srgb_to_linear(linear_to_srgb(x)), x)
    assert srgb_to_linear(x.float()).dtype == torch.float32


def test_curve_is_continuous_at_the_knee() -> None:
    eps = 1e-9
    knee = torch.tensor([0.04045 - eps, 0.04045 + eps], dtype=torch.float64)
    low, high = srgb_to_linear(knee)
    assert abs(high - low) < 1e-7


def test_negatives_clamp_to_zero_and_values_above_one_extrapolate() -> None:
    assert srgb_to_linear(torch.tensor([-0.5])).item() == 0.0
    assert linear_to_srgb(torch.tensor([-0.5])).item() == 0.0
    above = srgb_to_linear(torch.tensor([1.0, 1.2, 1.5]))
    assert (above.diff() > 0).all() and above[1] > 1.0
    torch.testing.assert_close(linear_to_srgb(above), torch.tensor([1.0, 1.2, 1.5]))


def test_gradients_finite_everywhere_including_zero() -> None:
    for fn in (srgb_to_linear, linear_to_srgb):
        x = torch.tensor([-1.0, 0.0, 1e-12, 0.0031308, 0.04045, 0.5, 1.0, 2.0], requires_grad=True)
        fn(x).sum().backward()
        assert torch.isfinite(x.grad).all(), fn.__name__
        assert x.grad[0] == 0.0  # clamped region
        assert (x.grad[1:] > 0).all()
