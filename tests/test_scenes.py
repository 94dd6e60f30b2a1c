"""Scenes with depth: bundled RGB-D scenes on the bench's depth range, a user's scene files and what is wrong with
them, in-focus masks, the focal-stack loss and per-plane scores."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from benchctl.errors import BenchctlError
from benchctl.optics.focal_stack import (FocalStackTarget, focal_stack_loss, focal_stack_scores, in_focus_masks,
                                         masked_scores)
from benchctl.optics.metrics import lsq_scale, psnr, ssim
from benchctl.scenes import list_scenes, load_scene, prepare_scene

RANGE = (0.065, 0.075)


def test_bundled_scenes_lie_on_the_bench_depth_range():
    assert set(list_scenes()) >= {"rgbd:flat", "rgbd:two-planes", "rgbd:three-planes", "rgbd:tilted",
                                  "rgbd:occlusion", "rgbd:photo"}
    for spec in list_scenes():
        scene = load_scene(spec, (48, 64), RANGE)
        assert scene.srgb.dtype == np.float32 and scene.srgb.shape[2] == 3
        assert scene.depth_m.shape == scene.srgb.shape[:2]
        low, high = scene.depth_span_m
        assert RANGE[0] - 1e-12 <= low <= high <= RANGE[1] + 1e-12, spec
        assert "65 .. 75 mm" in scene.note
    assert np.unique(load_scene("rgbd:flat", (48, 64), RANGE).depth_m).tolist() == [0.07]
    two = load_scene("rgbd:two-planes", (48, 64), RANGE)
    assert np.unique(two.depth_m) == pytest.approx([0.066, 0.074])
    assert (two.depth_m[:, :32] == two.depth_m[0, 0]).all() and (two.depth_m[:, 32:] == two.depth_m[0, -1]).all()
    assert len(np.unique(load_scene("rgbd:three-planes", (48, 64), RANGE).depth_m)) == 3
    tilted = load_scene("rgbd:tilted", (48, 64), RANGE).depth_m
    assert (np.diff(tilted, axis=1) > 0).all() and tilted[:, 0] == pytest.approx(0.065)
    occlusion = load_scene("rgbd:occlusion", (48, 64), RANGE)
    assert occlusion.depth_m[24, 32] == pytest.approx(0.073) and occlusion.depth_m[0, 0] == pytest.approx(0.067)


def test_a_bench_without_a_depth_range_and_unknown_names_are_refused_in_one_line():
    with pytest.raises(BenchctlError, match="depth_range_mm") as error:
        load_scene("rgbd:two-planes", (48, 64), None)
    assert "\n" not in str(error.value)
    with pytest.raises(BenchctlError, match="did you mean 'rgbd:two-planes'"):
        load_scene("rgbd:two-plane", (48, 64), RANGE)


def _scene_file(folder: Path, depth_name: str, extra: str = "", image_shape: tuple[int, int] = (30, 40)) -> Path:
    image = np.zeros((*image_shape, 3), np.uint8)
    image[5:25, 10:30] = 200
    cv2.imwrite(str(folder / "image.png"), image)
    path = folder / "scene.toml"
    path.write_text(f'image = "image.png"\ndepth = "{depth_name}"\n{extra}')
    return path


def test_a_users_16_bit_depth_png_maps_0_and_65535_to_near_and_far(tmp_path):
    depth = np.zeros((30, 40), np.uint16)
    depth[:, 20:] = 65535
    cv2.imwrite(str(tmp_path / "depth.png"), depth)
    path = _scene_file(tmp_path, "depth.png", "near_mm = 66\nfar_mm = 72\n")
    scene = load_scene(f"rgbd:{path}", (1, 1), RANGE)
    assert scene.note is None and scene.srgb.shape == (30, 40, 3)
    assert scene.depth_m[0, 0] == pytest.approx(0.066) and scene.depth_m[0, -1] == pytest.approx(0.072)
    path.write_text('image = "image.png"\ndepth = "depth.png"\nnear_mm = 60\nfar_mm = 72\n')
    with pytest.raises(BenchctlError, match=r"60 \.\. 72 mm lies outside the bench's depth range 65 \.\. 75 mm") as err:
        load_scene(f"rgbd:{path}", (1, 1), RANGE)
    assert "--fit-depth" in str(err.value) and "\n" not in str(err.value)
    fitted = load_scene(f"rgbd:{path}", (1, 1), RANGE, fit_depth=True)
    assert fitted.depth_span_m == pytest.approx(RANGE) and "mapped onto" in fitted.note


@pytest.mark.parametrize("write, extra, message", [
    (lambda p: np.save(p / "d.npy", np.where(np.eye(30, 40) > 0, np.nan, 70.0)), "",
     r"d\.npy: 30 depth value\(s\) are NaN or infinite \(first at row 0, column 0: nan\)"),
    (lambda p: np.save(p / "d.npy", np.full((30, 40), 70.0) + (np.arange(40) == 7) * 30), "near_mm = 65\nfar_mm = 80\n",
     r"d\.npy: depth 100 mm at row 0, column 7 is outside 65 \.\. 80 mm \(30 value\(s\) are\)"),
    (lambda p: np.save(p / "d.npy", np.full((30, 40), -1.0)), "", r"d\.npy: depth -1 mm at row 0, column 0 is outside"),
    (lambda p: np.save(p / "d.npy", np.full((20, 40), 70.0)), "",
     r"d\.npy: depth map is 20x40, the image .*image\.png is 30x40: they must be the same size"),
    (lambda p: np.save(p / "d.npy", np.array(["a"])), "", r"d\.npy: a depth map must be 2-D numbers"),
    (lambda p: (p / "d.npy").write_bytes(b"not numpy"), "", r"d\.npy: not a readable \.npy depth map"),
    (lambda p: cv2.imwrite(str(p / "d.png"), np.zeros((30, 40), np.uint8)), "near_mm = 66\nfar_mm = 70\n",
     r"d\.png: a depth PNG must be 16-bit \(0 = near_mm, 65535 = far_mm\), got uint8"),
    (lambda p: cv2.imwrite(str(p / "d.png"), np.zeros((30, 40), np.uint16)), "",
     r"d\.png: a 16-bit depth map needs near_mm and far_mm"),
    (lambda p: cv2.imwrite(str(p / "d.png"), np.zeros((30, 40), np.uint16)), "near_mm = 70\nfar_mm = 66\n",
     r"scene\.toml: near_mm 70 must be less than far_mm 66"),
    (lambda p: cv2.imwrite(str(p / "d.png"), np.zeros((30, 40), np.uint16)), "near = 70\n", r"scene\.toml: near"),
])
def test_bad_depth_inputs_name_the_file_and_value_in_one_line(tmp_path, write, extra, message):
    write(tmp_path)
    name = "d.npy" if (tmp_path / "d.npy").exists() else "d.png"
    path = _scene_file(tmp_path, name, extra)
    with pytest.raises(BenchctlError, match=message) as error:
        load_scene(f"rgbd:{path}", (1, 1), (0.001, 1.0))
    assert "\n" not in str(error.value)


def test_prepared_scene_keeps_layer_depths_at_edges_and_continues_them_outside_the_roi():
    scene = load_scene("rgbd:two-planes", (30, 50), RANGE)
    amplitude, depth = prepare_scene(scene, (48, 64), (24, 40))
    assert amplitude.shape == (3, 48, 64) and depth.shape == (48, 64) and depth.dtype == torch.float64
    assert set(torch.unique(depth).tolist()) == set(np.unique(scene.depth_m).tolist())  # nothing in between
    assert bool((amplitude[:, :12] == 0).all())
    assert float(depth[0, 0]) == pytest.approx(0.066) and float(depth[-1, -1]) == pytest.approx(0.074)


def test_hard_masks_give_each_pixel_to_its_nearest_plane_and_soft_ones_sum_to_one():
    depth = torch.tensor([[1.0, 1.9, 2.0], [2.6, 3.0, 9.0]], dtype=torch.float64) * 1e-3
    masks = in_focus_masks(depth, (1e-3, 3e-3))
    assert masks.shape == (2, 2, 3)
    assert masks[0].tolist() == [[1, 1, 1], [0, 0, 0]]  # 2.0 mm is a tie: the plane nearer the SLM takes it
    soft = in_focus_masks(depth, (1e-3, 2e-3, 3e-3), softness_m=0.5e-3)
    torch.testing.assert_close(soft.sum(0), torch.ones(2, 3))
    assert float(soft[1, 0, 2]) == pytest.approx(1 / (1 + 2 * math.exp(-2)))
    assert float(soft[2, 1, 2]) > 0.999 and float(soft[2, 0, 1]) < float(soft[0, 0, 1]) < float(soft[1, 0, 1])
    with pytest.raises(ValueError, match="at least one plane"):
        in_focus_masks(depth, ())


def test_focal_stack_target_checks_its_maps_and_planes():
    amplitude, depth = torch.ones(4, 5), torch.full((4, 5), 0.07, dtype=torch.float64)
    target = FocalStackTarget(amplitude, depth, (0.066, 0.074))
    assert target.masks.shape == (2, 4, 5) and target.planes_m == (0.066, 0.074)
    with pytest.raises(ValueError, match="ascending"):
        FocalStackTarget(amplitude, depth, (0.074, 0.066))
    with pytest.raises(ValueError, match="finite and > 0"):
        FocalStackTarget(amplitude, depth * math.nan, (0.07,))
    with pytest.raises(ValueError, match="one shape"):
        FocalStackTarget(amplitude, depth[:3], (0.07,))


def test_focal_stack_loss_of_one_plane_is_the_2d_scaled_mse_and_masks_select_pixels():
    generator = torch.Generator().manual_seed(0)
    recon, target = torch.rand((1, 6, 7), generator=generator), torch.rand((6, 7), generator=generator)
    scaled = lsq_scale(recon[0], target) * recon[0]
    expected = torch.nn.functional.mse_loss(scaled, target)
    torch.testing.assert_close(focal_stack_loss(recon, target, torch.ones(1, 6, 7)), expected)
    # two planes, hard masks: changing a plane outside its mask changes nothing
    masks = torch.zeros(2, 6, 7)
    masks[0, :, :3], masks[1, :, 3:] = 1, 1
    stack = torch.rand((2, 6, 7), generator=generator)
    moved = stack.clone()
    moved[0, :, 3:] += 5
    torch.testing.assert_close(focal_stack_loss(stack, target, masks), focal_stack_loss(moved, target, masks))
    assert float(focal_stack_loss(target.expand(2, 6, 7) * 3, target, masks)) < 1e-12  # any brightness


def test_per_plane_scores_look_only_inside_each_planes_in_focus_region():
    generator = torch.Generator().manual_seed(1)
    target = torch.rand((32, 40), generator=generator)
    masks = in_focus_masks(torch.cat([torch.full((32, 20), 1.0), torch.full((32, 20), 2.0)], 1), (1.0, 2.0, 3.0))
    recon = torch.stack([target * 2, torch.rand((32, 40), generator=generator), target])
    recon[0, :, 20:] = 0  # wrong only outside plane 0's region
    recon[1, :, 20:] = target[:, 20:] * 0.5
    scores = focal_stack_scores(recon, target, masks, (1.0, 2.0, 3.0))
    assert scores.per_plane[0]["psnr_amplitude_db"] == pytest.approx(100.0)
    assert scores.per_plane[1]["psnr_amplitude_db"] == pytest.approx(100.0)
    assert scores.per_plane[0]["ssim_amplitude"] == pytest.approx(1.0) and scores.per_plane[2] is None
    assert scores.mean["psnr_amplitude_db"] == pytest.approx(100.0)
    noisy = target + 0.05 * torch.randn((32, 40), generator=generator)
    region = torch.ones(32, 40, dtype=torch.bool)
    whole = masked_scores(noisy, target, region)
    scale = lsq_scale(noisy, target)
    assert whole["psnr_amplitude_db"] == pytest.approx(float(psnr(scale * noisy, target, 1.0)), abs=1e-4)
    assert whole["ssim_amplitude"] == pytest.approx(float(ssim(scale * noisy, target, 1.0)), abs=1e-5)
