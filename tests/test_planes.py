"""Only the planes a scene needs: the axial resolution against its closed forms, the planes chosen for flat,
layered, tilted and partly dark scenes, and the sweep of a scene with continuous depth."""

from __future__ import annotations

import pytest
import torch

from benchctl.optics.geometry import Geometry
from benchctl.optics.planes import (MAX_PLANES, MAX_SWEEP_DEPTHS, SWEEP_STEP, DepthSweep, axial_resolution_m,
                                    choose_planes, even_planes, finest_resolution_m, numerical_aperture)


def test_axial_resolution_is_lambda_over_na_squared_with_the_iris_or_the_slm_extent_limiting_na():
    pitch, wavelength = 3.74e-6, 520e-9
    # the iris limits: NA = a lambda / (2 pitch), so lambda / NA^2 = 4 pitch^2 / (a^2 lambda)
    near = Geometry(wavelength, pitch, 4e-3, (272, 480), (220, 400), aperture=0.5)
    assert numerical_aperture(near) == pytest.approx((0.5 * wavelength / (2 * pitch),) * 2)
    assert axial_resolution_m(near) == pytest.approx(4 * pitch**2 / (0.25 * wavelength))
    # the SLM's extent limits: NA = N pitch / (2 z) on each axis, the wider axis (more columns) resolves finer
    far = Geometry(wavelength, pitch, 0.2, (1088, 1920), (880, 1600))
    assert numerical_aperture(far) == pytest.approx((1088 * pitch / 0.4, 1920 * pitch / 0.4))
    assert axial_resolution_m(far) == pytest.approx(wavelength / (1920 * pitch / 0.4) ** 2)
    red = Geometry(680e-9, pitch, 4e-3, (272, 480), (220, 400), aperture=0.5)
    assert finest_resolution_m([near, red]) == axial_resolution_m(red) < axial_resolution_m(near)


def _maps(*bands: tuple[float, float]) -> tuple[torch.Tensor, torch.Tensor]:
    """Vertical bands of (depth m, light), 10 columns each, 8 rows."""
    depth = torch.cat([torch.full((8, 10), z, dtype=torch.float64) for z, _ in bands], 1)
    light = torch.cat([torch.full((8, 10), a) for _, a in bands], 1)
    return depth, light


def test_a_flat_scene_gets_exactly_one_plane_at_its_depth():
    depth, light = _maps((0.07, 1.0), (0.07, 0.5))
    choice = choose_planes(depth, light, 0.4e-3)
    assert choice.planes_m == (0.07,) and "1 plane at 70.00 mm" in choice.reason


def test_separated_layers_get_one_plane_each_at_their_depths_and_dark_ones_none():
    depth, light = _maps((0.066, 1.0), (0.070, 0.8), (0.074, 0.6), (0.060, 0.0))
    assert choose_planes(depth, light, 0.4e-3).planes_m == pytest.approx((0.066, 0.070, 0.074))
    # layers closer than the resolution share one plane halfway
    depth, light = _maps((0.0700, 1.0), (0.0703, 1.0))
    assert choose_planes(depth, light, 0.4e-3).planes_m == pytest.approx((0.07015,))


def test_a_tilted_plane_gets_the_fewest_planes_that_keep_every_pixel_in_focus():
    depth = torch.linspace(0.065, 0.075, 200, dtype=torch.float64).repeat(4, 1)
    light, resolution = torch.ones_like(depth, dtype=torch.float32), 0.9e-3
    choice = choose_planes(depth, light, resolution)
    assert len(choice.planes_m) == 12  # ceil(10 mm / 0.9 mm)
    distance = (depth[..., None] - torch.tensor(choice.planes_m, dtype=torch.float64)).abs().amin(-1)
    assert float(distance.max()) <= resolution / 2 + 1e-12
    assert len(choose_planes(depth, light, 0.1e-3).planes_m) == MAX_PLANES  # 100 clusters: capped, evenly
    assert "more than 16" in choose_planes(depth, light, 0.1e-3).reason


def test_a_cluster_with_a_sliver_of_the_light_gets_no_plane():
    depth, light = _maps((0.066, 1.0), (0.074, 0.005))
    choice = choose_planes(depth, light, 0.4e-3)
    assert choice.planes_m == (0.066,) and "left to their neighbours" in choice.reason


def test_even_planes_and_the_planes_option():
    import argparse

    from benchctl.cli.args import plane_count

    depth, light = _maps((0.066, 1.0), (0.074, 1.0), (0.050, 0.0))
    assert even_planes(depth, light, 3).planes_m == pytest.approx((0.066, 0.070, 0.074))
    assert even_planes(depth, light, 1).planes_m == pytest.approx((0.070,))
    assert plane_count("auto") == "auto" and plane_count("4") == 4
    for bad in ("0", "-2", "two", ""):
        with pytest.raises(argparse.ArgumentTypeError, match="'auto' or a whole number"):
            plane_count(bad)


def test_a_tilted_plane_is_swept_plane_by_plane_and_layers_are_not():
    depth = torch.linspace(0.065, 0.075, 200, dtype=torch.float64).repeat(4, 1)
    resolution = 0.9e-3
    choice = choose_planes(depth, torch.ones_like(depth, dtype=torch.float32), resolution)
    sweep = choice.sweep
    # 11 clusters of 0.85 mm at 0.225 mm steps, 5 depths each, and the last of 0.05 mm, 2
    assert sweep is not None and [len(d) for d in sweep.depths_m] == [5] * 11 + [2]
    assert sweep.reach_m == pytest.approx(SWEEP_STEP * resolution)
    assert len(sweep.depths_m) == len(choice.planes_m)
    assert "each swept over its cluster (57 depths, at most 0.225 mm apart)" in choice.reason
    for plane, depths in zip(choice.planes_m, sweep.depths_m):
        steps = torch.tensor(depths).diff()
        assert bool((steps > 0).all()) and float(steps.max()) <= sweep.reach_m + 1e-12
        assert depths[0] < plane < depths[-1] and plane == pytest.approx(0.5 * (depths[0] + depths[-1]))
    # every pixel lies within reach of some depth of the sweep: over a cycle each is scored near its own depth
    every = torch.tensor(sweep.all_m, dtype=torch.float64)
    assert float((depth[..., None] - every).abs().amin(-1).max()) <= sweep.reach_m
    # a shallower scene keeps the SWEEP_STEP: 3 clusters, 5 depths each
    shallow = depth.clamp(max=0.0677)
    few = choose_planes(shallow, torch.ones_like(shallow, dtype=torch.float32), resolution).sweep
    assert few is not None and few.reach_m == pytest.approx(SWEEP_STEP * resolution)
    assert [len(d) for d in few.depths_m] == [5, 5, 5]
    # the deepest content, capped at MAX_PLANES even planes, is swept over each plane's share of the depth
    capped = choose_planes(depth, torch.ones_like(depth, dtype=torch.float32), 0.1e-3).sweep
    # 16 planes 0.625 mm apart at 25 micrometre steps would be 416 depths: the steps widen to keep MAX_SWEEP_DEPTHS
    assert capped is not None and len(capped.depths_m) == MAX_PLANES and len(capped.all_m) <= MAX_SWEEP_DEPTHS < 416
    assert SWEEP_STEP * 0.1e-3 < capped.reach_m < 0.625e-3 / 3
    assert f"({len(capped.all_m)} depths, at most {capped.reach_m * 1e3:.3g} mm apart, wider than 0.25 resolution to " \
        f"keep {MAX_SWEEP_DEPTHS} depths at most)" in choose_planes(depth, torch.ones_like(depth), 0.1e-3).reason
    assert capped.depths_m[0][0] == pytest.approx(0.065) and capped.depths_m[-1][-1] == pytest.approx(0.075)
    assert float((depth[..., None] - torch.tensor(capped.all_m, dtype=torch.float64)).abs().amin(-1).max()) <= \
        capped.reach_m
    layers, light = _maps((0.066, 1.0), (0.070, 0.8), (0.074, 0.6))
    assert choose_planes(layers, light, 0.4e-3).sweep is None
    assert even_planes(depth, torch.ones_like(depth), 4).sweep is None  # planes asked for by count stay put


def test_a_sweep_steps_each_plane_through_its_depths_half_a_cycle_out_of_step_with_the_last():
    sweep = DepthSweep(((1.0, 2.0, 3.0, 4.0), (5.0, 6.0, 7.0, 8.0), (9.0,)), reach_m=0.5)
    assert sweep.all_m == (1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0)
    assert sweep.at(0) == ([0, 6, 8], (1.0, 7.0, 9.0))
    assert sweep.at(1) == ([1, 7, 8], (2.0, 8.0, 9.0))
    assert sweep.at(3) == ([3, 5, 8], (4.0, 6.0, 9.0))
    assert sweep.at(4) == sweep.at(0)
    seen = [sweep.at(t)[1] for t in range(4)]
    assert sorted(z for planes in seen for z in planes[:2]) == [float(z) for z in range(1, 9)]
    assert len({planes[1] - planes[0] for planes in seen}) == 2  # the gap between neighbours changes
