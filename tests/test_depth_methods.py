"""Hologram methods for scenes with depth: a flat scene is exactly 2D, multi-plane SGD reaches each plane's 2D
quality through the fitted model, layered anti-aliased DPAC; FLIP (against NVIDIA's evaluator reading files) and
speckle contrast (against its analytic value)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch

from benchctl.benchmarks.depth import all_in_focus_psnr
from benchctl.cgh import get_method
from benchctl.cgh.dpac import anti_aliased, layered_field
from benchctl.errors import BadValueError
from benchctl.optics.colour import linear_to_srgb
from benchctl.optics.fitted import FittedOptics
from benchctl.optics.focal_stack import FocalStackTarget, focal_stack_scores, in_focus_masks, nearest_plane
from benchctl.optics.metrics import flip_map, perceptual_scores, speckle_contrast
from benchctl.optics.planes import DepthSweep, axial_resolution_m, choose_planes, even_planes
from benchctl.optics.propagation import propagate
from benchctl.optics.setup import OpticalSetup
from benchctl.scenes import load_scene, prepare_scene

SHAPE, ROI, RANGE = (64, 96), (48, 80), (0.016, 0.024)
PLANES = (0.0168, 0.0232)  # the two-plane scene's layers at 10 % and 90 % of RANGE


def _setup(**changes) -> OpticalSetup:
    return OpticalSetup(520e-9, 8e-6, 0.02, SHAPE, ROI, **changes)


def _target(name: str, planes: tuple[float, ...]) -> FocalStackTarget:
    amplitude, depth = prepare_scene(load_scene(f"rgbd:{name}", ROI, RANGE), SHAPE, ROI)
    return FocalStackTarget(amplitude[1], depth, planes)


def _plane_psnrs(setup: OpticalSetup, phase: torch.Tensor, target: FocalStackTarget) -> list[float]:
    rows, cols = setup.roi_slices
    recon = setup.reconstruct_planes_roi(phase, target.planes_m)
    scores = focal_stack_scores(recon, target.amplitude[rows, cols], target.masks[:, rows, cols], target.planes_m)
    return [s["psnr_amplitude_db"] for s in scores.per_plane if s is not None]


@pytest.mark.slow
@pytest.mark.parametrize("method, iterations", [("dpac", None), ("sgd", 15), ("gs", 10)])
def test_a_flat_scene_gets_exactly_the_2d_hologram_at_its_plane(method, iterations):
    target = _target("flat", (0.02,))
    assert bool((target.masks == 1).all())
    setup = _setup()
    flat = get_method(method)(target, setup, iterations=iterations)
    torch.testing.assert_close(flat, get_method(method)(target.amplitude, setup, iterations=iterations), rtol=0, atol=0)
    elsewhere = _target("flat", (0.021,))  # a plane away from the setup's distance: the setup moved there
    torch.testing.assert_close(get_method(method)(elsewhere, setup, iterations=iterations),
                               get_method(method)(target.amplitude, setup.at_distance(0.021), iterations=iterations),
                               rtol=0, atol=0)


def test_a_2d_only_method_refuses_a_scene_on_several_planes_naming_those_that_can():
    with pytest.raises(BadValueError, match=r"method 'gs' makes holograms of one plane; a scene on 2 planes needs "
                                            r"one of: dpac, sgd"):
        get_method("gs")(_target("two-planes", PLANES), _setup(), iterations=3)


@pytest.mark.slow
def test_multiplane_sgd_reaches_each_planes_2d_quality_on_the_two_plane_scene():
    setup, target, iterations = _setup(), _target("two-planes", PLANES), 40
    phase = get_method("sgd")(target, setup, iterations=iterations)
    assert phase.shape == SHAPE and phase.dtype == torch.float32
    stack = _plane_psnrs(setup, phase, target)
    start = _plane_psnrs(setup, get_method("dpac")(target, setup), target)
    for k, plane in enumerate(PLANES):
        alone = get_method("sgd")(target.amplitude * target.masks[k], setup.at_distance(plane), iterations=iterations)
        assert stack[k] > _plane_psnrs(setup, alone, target)[k] - 2.0, k
        assert stack[k] > start[k] + 1.5  # it optimised the focal stack, not just kept its layered-DPAC start


@pytest.mark.slow
def test_multiplane_sgd_optimises_through_the_fitted_model_and_the_display():
    model = FittedOptics((("defocus", 0.4), ("astigmatism_vertical", 0.3)), waist_m=300e-6, zero_order=0.04)

    def display(phase: torch.Tensor) -> torch.Tensor:  # 16 levels
        return torch.round(phase / (2 * math.pi / 16)) * (2 * math.pi / 16)

    measured = OpticalSetup.of(_setup(), model).with_display(display)
    target = _target("two-planes", PLANES)
    aware = get_method("sgd")(target, measured, iterations=40)
    naive = get_method("sgd")(target, _setup(), iterations=40)
    # scored on the measured bench, as shown by its panel
    assert np.mean(_plane_psnrs(measured, display(aware), target)) > np.mean(
        _plane_psnrs(measured, display(naive), target)) + 1.0


def test_a_swept_target_scores_each_plane_near_its_depth_only():
    target = _target("tilted", PLANES)
    sweep = DepthSweep(((0.0165, 0.0170, 0.0175), (0.0225, 0.0230, 0.0235)), reach_m=0.0004)
    swept = FocalStackTarget(target.amplitude, target.depth_m, PLANES, sweep=sweep)
    picks, masks = swept.swept(1)
    assert picks == [1, 5] and masks.shape == (2, *SHAPE)  # the second plane half a cycle on
    near = [(target.depth_m - z).abs() <= 0.0004 for z in (0.0170, 0.0235)]
    for k in range(2):
        assert bool((masks[k].bool() == near[k]).all()), k  # no tilted pixel lies within reach of both planes
    assert 0 < float(masks.sum()) < masks[0].numel()
    with pytest.raises(ValueError, match="a sweep of 2 planes for 3 planes"):
        FocalStackTarget(target.amplitude, target.depth_m, (0.017, 0.02, 0.023), sweep=sweep)
    with pytest.raises(ValueError, match="no sweep"):
        target.swept(0)


def test_the_nearest_plane_is_the_hard_in_focus_masks_owner_ties_included():
    planes = (4 / 256, 5 / 256, 5.5 / 256, 6 / 256)  # binary fractions: halfway between two is exactly a tie
    depth = torch.rand((40, 50), generator=torch.Generator().manual_seed(3), dtype=torch.float64) * 0.01 + 0.014
    depth[0, :3] = torch.tensor([4.5 / 256, 5.25 / 256, 0.0001])  # two ties, and far nearer than every plane
    owner = nearest_plane(depth, planes)
    assert torch.equal(owner, in_focus_masks(depth, planes).argmax(dim=0))
    assert owner[0, :3].tolist() == [0, 1, 0]


@pytest.mark.slow
def test_sweeping_the_planes_of_a_tilted_scene_shows_it_in_focus_at_every_depth():
    setup, iterations = _setup(), 40
    rows, cols = setup.roi_slices
    scene = _target("tilted", PLANES)
    light = scene.amplitude[rows, cols].square()
    choice = choose_planes(scene.depth_m[rows, cols], light, axial_resolution_m(setup.geometry))
    assert choice.sweep is not None and len(choice.planes_m) == 6
    judge = FocalStackTarget(scene.amplitude, scene.depth_m, even_planes(scene.depth_m[rows, cols], light, 64).planes_m)

    def all_in_focus(planes: tuple[float, ...], sweep: DepthSweep | None) -> float:
        phase = get_method("sgd")(FocalStackTarget(scene.amplitude, scene.depth_m, planes, sweep=sweep), setup,
                                  iterations=iterations)
        return all_in_focus_psnr(setup, phase, judge)

    fixed, swept = all_in_focus(choice.planes_m, None), all_in_focus(choice.planes_m, choice.sweep)
    sixteen = all_in_focus(even_planes(scene.depth_m[rows, cols], light, 16).planes_m, None)
    assert swept > fixed + 2.0 and swept > sixteen - 0.5, (fixed, swept, sixteen)


def test_layered_field_lets_a_farther_layer_hide_what_lies_behind_it():
    target = _target("occlusion", PLANES)
    setup = _setup()
    far = target.masks[1] > 0.5  # the disc, nearer the camera
    at_last = layered_field(target, setup, PLANES[1])
    torch.testing.assert_close(at_last[far], target.amplitude[far].to(torch.complex64))  # nothing from behind
    behind = propagate((target.amplitude * target.masks[0]).to(torch.complex64), PLANES[1] - PLANES[0],
                       setup.wavelength_m, setup.pitch_m)
    torch.testing.assert_close(at_last[~far], behind[~far], rtol=0, atol=1e-5)


def test_anti_aliasing_is_a_gaussian_of_the_given_width():
    checkerboard = ((torch.arange(8)[:, None] + torch.arange(8)[None, :]) % 2 * 2 - 1).to(torch.complex64)
    sigma = 0.6  # a checkerboard sits at the Nyquist corner: (1/2, 1/2) cycles per pixel
    torch.testing.assert_close(anti_aliased(checkerboard, sigma), checkerboard * math.exp(-math.pi**2 * sigma**2))
    assert anti_aliased(checkerboard, 0.0) is checkerboard


def test_layered_dpac_shows_each_layer_better_than_2d_dpac_of_the_whole_image_at_the_mid_plane():
    setup, target = _setup(aperture=0.5), _target("two-planes", PLANES)
    layered = _plane_psnrs(setup, get_method("dpac")(target, setup), target)
    flat = get_method("dpac")(target.amplitude, setup.at_distance(sum(PLANES) / 2))
    assert np.mean(layered) > np.mean(_plane_psnrs(setup, flat, target)) + 1.0


def test_flip_matches_nvidias_evaluator_reading_the_images_from_files(tmp_path):
    import flip_evaluator

    generator = torch.Generator().manual_seed(0)
    target = torch.zeros(48, 64)
    target[8:40, 8:56] = 0.9
    recon = (target + 0.15 * torch.rand(48, 64, generator=generator)).clamp(0, 1)
    assert float(flip_map(target, target).max()) == 0.0
    paths = []
    for name, image in (("reference", target), ("test", recon)):
        srgb = (linear_to_srgb(image.square()).numpy() * 255).round().astype(np.uint8)
        paths.append(str(tmp_path / f"{name}.png"))
        cv2.imwrite(paths[-1], np.repeat(srgb[:, :, None], 3, axis=2))
    _, mean, _ = flip_evaluator.evaluate(paths[0], paths[1], "LDR")
    assert float(flip_map(recon, target).mean()) == pytest.approx(mean, abs=5e-3)
    assert mean > 0.02


def test_speckle_contrast_of_a_known_speckle_on_the_flat_part_only():
    generator = torch.Generator().manual_seed(3)
    target = torch.zeros(96, 96)
    target[16:80, 16:48] = 0.8
    target[16:80, 48:80] = 0.4  # two flat levels
    a = 0.1
    recon = target * (1 + a * torch.randn(96, 96, generator=generator))
    expected = math.sqrt(4 * a**2 + 2 * a**4) / (1 + a**2)  # std / mean of (1 + a n)^2, n standard normal
    assert speckle_contrast(recon, target) == pytest.approx(expected, rel=0.05)
    assert speckle_contrast(target * 3, target) == pytest.approx(0.0, abs=1e-12)
    edges = torch.zeros(96, 96, dtype=torch.bool)
    edges[:, 46:50] = True  # where the two levels meet: no flat neighbourhood
    assert speckle_contrast(recon, target, edges) is None
    assert set(perceptual_scores(recon, target)) == {"flip", "speckle_contrast"}
    assert set(perceptual_scores(recon, target, edges)) == {"flip"}
