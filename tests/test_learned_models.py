"""Learned architectures: HoloNet, CCNN-CGH, their DCM variants, LFMN and the pyramid (shapes, counts, wiring)."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from benchctl.cgh import OpticalSetup
from benchctl.cgh.learned import (
    GRN,
    LEARNED_METHODS,
    LFMN,
    PAPER_PARAMETERS,
    PYRAMID_GROUPS,
    ComplexConv2d,
    ComplexConvTranspose2d,
    ComplexReLU,
    Divided,
    PyramidMerger,
    build_model,
    build_networks,
    count_parameters,
    model_info,
    sublattice_groups,
    tier,
)
from benchctl.cgh.learned.lfmn import ECCM, LFM
from benchctl.optics import Propagator

FACTORS = {"holonet": 1, "holonet-dcm2": 2, "holonet-dcm4": 4, "holonet-pyramid": 4, "ccnn": 1, "ccnn-dcm4": 4,
           "holonet-ps2": 2, "holonet-ps4": 4, "holonet-lowdef2": 2, "holonet-dcm2-nolfm": 2,
           "holonet-dcm2-noeccm": 2, "holonet-dcm2-nogrn": 2}
MERGERS = {"holonet-pyramid": "pyramid", "holonet-ps2": "pixel-shuffle", "holonet-ps4": "pixel-shuffle"}


def tiny_setup(shape: tuple[int, int] = (32, 64)) -> OpticalSetup:
    return OpticalSetup(wavelength_m=520e-9, pitch_m=8e-6, distance_m=10e-3, shape=shape, roi=shape)


def amplitude(shape: tuple[int, int], batch: int = 2) -> torch.Tensor:
    return torch.rand(batch, 1, *shape, generator=torch.Generator().manual_seed(1))


def test_catalogue_names() -> None:
    assert LEARNED_METHODS == ("holonet", "holonet-dcm2", "holonet-dcm4", "holonet-pyramid", "ccnn", "ccnn-dcm4",
                               "holonet-ps2", "holonet-ps4", "holonet-lowdef2", "holonet-dcm2-nolfm",
                               "holonet-dcm2-noeccm", "holonet-dcm2-nogrn")
    with pytest.raises(ValueError, match="unknown learned method"):
        model_info("holonet-dcm3", (32, 64))


@pytest.mark.parametrize("name", LEARNED_METHODS)
@pytest.mark.parametrize("shape", [(32, 64), (30, 50)])
def test_forward_shape_and_range(name: str, shape: tuple[int, int]) -> None:
    """Any grid works, including sizes the U-Net depth or r does not divide (padded and cropped)."""
    torch.manual_seed(0)
    model = build_model(name, tiny_setup(shape)).eval()
    with torch.no_grad():
        phase = model(amplitude(shape))
    assert phase.shape == (2, 1, *shape)
    assert phase.dtype == torch.float32
    assert torch.isfinite(phase).all()
    assert phase.abs().max() <= math.pi


@pytest.mark.parametrize("name", LEARNED_METHODS)
def test_gradient_reaches_every_parameter(name: str) -> None:
    torch.manual_seed(0)
    model = build_model(name, tiny_setup())
    model(amplitude((32, 64))).square().mean().backward()
    for key, parameter in model.named_parameters():
        assert parameter.grad is not None, key
        assert torch.isfinite(parameter.grad).all(), key
        assert parameter.grad.abs().sum() > 0, key


@pytest.mark.parametrize("name", [n for n in LEARNED_METHODS if n != "holonet-lowdef2"])
def test_subnetworks_run_on_sub_images_and_propagation_on_the_full_grid(name: str, monkeypatch) -> None:
    shape, r = (64, 128), FACTORS[name]
    model = build_model(name, tiny_setup(shape))
    seen: dict[str, torch.Size] = {}
    for part in ("generator", "encoder"):
        subnet = getattr(model, part).subnet
        subnet.register_forward_pre_hook(lambda _m, args, part=part: seen.__setitem__(part, args[0].shape))
    propagated = []
    original_call = Propagator.__call__

    def recording_call(self: Propagator, field: torch.Tensor) -> torch.Tensor:
        propagated.append(tuple(field.shape))
        return original_call(self, field)

    monkeypatch.setattr(Propagator, "__call__", recording_call)
    with torch.no_grad():
        model.eval()(amplitude(shape, batch=1))
    sub = (shape[0] // r, shape[1] // r)
    assert seen["generator"] == (1, r * r, *sub)
    assert seen["encoder"] == (1, r * r, *sub)  # complex SLM field, unshuffled (HoloNet splits it into 2 r^2)
    assert propagated == [(1, 1, *shape)]  # one propagation, at full definition


def test_holonet_encoder_sees_amplitude_then_phase_sub_images() -> None:
    generator, encoder = build_networks("holonet-dcm2", (32, 64))
    seen = []
    encoder.subnet[1].register_forward_pre_hook(lambda _m, args: seen.append(args[0]))
    field = torch.polar(torch.rand(1, 1, 32, 64), torch.rand(1, 1, 32, 64) * 6 - 3)
    with torch.no_grad():
        encoder.eval()(field)
    expected = F.pixel_unshuffle(torch.cat([field.abs(), field.angle()], dim=1), 2)
    assert seen[0].shape == (1, 8, 16, 32)
    torch.testing.assert_close(seen[0], expected)
    assert isinstance(generator.merge, nn.PixelShuffle) and isinstance(encoder.merge, LFMN)


@pytest.mark.parametrize("shape", [(8, 12), (30, 50)])
@pytest.mark.parametrize("factor", [1, 2, 4])
@pytest.mark.parametrize("dtype", [torch.float32, torch.complex64])
def test_pixel_unshuffle_shuffle_round_trip(shape: tuple[int, int], factor: int, dtype: torch.dtype) -> None:
    x = torch.randn(2, 1, *shape, dtype=dtype)
    assert torch.equal(Divided(nn.Identity(), factor, nn.PixelShuffle(factor))(x), x)


def test_pyramid_groups_are_the_2x2_sub_lattices_of_the_4x4_unshuffle() -> None:
    paper_one_based = ((1, 3, 9, 11), (2, 4, 10, 12), (5, 7, 13, 15), (6, 8, 14, 16))
    assert PYRAMID_GROUPS == tuple(tuple(c - 1 for c in group) for group in paper_one_based)
    assert PYRAMID_GROUPS == sublattice_groups(4, 2)
    image = torch.randn(1, 1, 8, 12)
    sub = F.pixel_unshuffle(image, 4)
    halves = [F.pixel_shuffle(sub[:, list(group)], 2) for group in PYRAMID_GROUPS]
    for (p, q), half in zip([(0, 0), (0, 1), (1, 0), (1, 1)], halves):
        assert torch.equal(half[0, 0], image[0, 0, p::2, q::2])  # one 2x2 sub-lattice of the image
    assert torch.equal(F.pixel_shuffle(torch.cat(halves, dim=1), 2), image)  # recursion: x4 = x2 of x2


def test_pyramid_shares_stage_one_and_clamps_only_at_the_end() -> None:
    torch.manual_seed(0)
    pyramid = PyramidMerger((8, 10), blocks=1).eval()
    assert isinstance(pyramid.stage1.clamp, nn.Identity)
    assert isinstance(pyramid.stage2.clamp, nn.Hardtanh)
    assert pyramid.stage1.grn.gamma.shape[1] == 8 and pyramid.stage2.grn.gamma.shape[1] == 10
    x = torch.randn(2, 16, 4, 6) * 3
    expected = pyramid.stage2(torch.cat([pyramid.stage1(x[:, list(group)]) for group in PYRAMID_GROUPS], dim=1))
    torch.testing.assert_close(pyramid(x), expected)
    assert pyramid(x).shape == (2, 1, 16, 24)


def test_grn_is_identity_at_init() -> None:
    grn = GRN(6)
    assert torch.equal(grn.gamma, torch.zeros(1, 6, 1, 1)) and torch.equal(grn.beta, torch.zeros(1, 6, 1, 1))
    x = torch.randn(2, 6, 5, 7)
    assert torch.equal(grn(x), x)
    with torch.no_grad():
        grn.gamma.fill_(1.0)
    g = torch.linalg.vector_norm(x, dim=(-2, -1), keepdim=True)
    torch.testing.assert_close(grn(x), x * g / (g.mean(dim=1, keepdim=True) + 1e-6) + x)


def test_lfmn_layers_and_global_residual() -> None:
    lfm, eccm = LFM(40), ECCM(40)
    assert [m.out_channels for m in lfm.gate if isinstance(m, nn.Conv2d)] == [20, 20, 40]
    assert isinstance(lfm.gate[-1], nn.Sigmoid)
    assert [m.out_channels for m in eccm if isinstance(m, nn.Conv2d)] == [50, 40]  # 1.25 expansion
    slopes = {m.negative_slope for m in [*lfm.modules(), *eccm.modules()] if isinstance(m, nn.LeakyReLU)}
    assert slopes == {0.1}
    lfmn = LFMN(2, dim=8, blocks=2)
    assert len(lfmn.body) == 2
    with torch.no_grad():  # silence the body: what is left is the global residual, the shuffle and the clamp
        lfmn.tail.weight.zero_()
        lfmn.tail.bias.zero_()
    x = torch.randn(1, 4, 3, 5) * 4
    assert torch.equal(lfmn(x), F.pixel_shuffle(x, 2).clamp(-math.pi, math.pi))


def test_complex_layers_match_complex_arithmetic() -> None:
    torch.manual_seed(0)
    x = torch.randn(1, 2, 6, 6, dtype=torch.complex64)
    for layer, op, kwargs in ((ComplexConv2d(2, 3, 3, stride=2, padding=1), F.conv2d, {}),
                              (ComplexConvTranspose2d(2, 3, 4, stride=2, padding=1), F.conv_transpose2d, {})):
        weight = torch.complex(layer.real.weight, layer.imag.weight)
        bias = torch.complex(layer.real.bias - layer.imag.bias, layer.real.bias + layer.imag.bias)
        expected = op(x, weight, bias, stride=2, padding=1, **kwargs)
        torch.testing.assert_close(layer(x), expected, rtol=1e-5, atol=1e-5)
    relu = ComplexReLU()(x)
    assert torch.equal(relu.real, x.real.clamp(min=0)) and torch.equal(relu.imag, x.imag.clamp(min=0))


# Exact counts this implementation gives (regression pins); the paper's figures are checked to 3 % below.
EXACT_PARAMETERS = {
    ("holonet", (1088, 1920)): 2_868_466,
    ("holonet-dcm2", (1088, 1920)): 3_012_684,
    ("holonet-dcm4", (1088, 1920)): 3_111_952,
    ("holonet-pyramid", (1088, 1920)): 3_165_992,  # both stages dim 32 (ECCM hidden 40), as the paper's code
    ("ccnn", (2176, 3840)): 42_260,
    ("ccnn-dcm4", (1088, 1920)): 97_476,  # LFMN dim 24, 2 blocks at every size below 8K
    ("ccnn-dcm4", (2176, 3840)): 97_476,  # published 112.7 K is the dim-28 (8K) model
    ("ccnn-dcm4", (4352, 7680)): 112_714,
}

# Sub-module counts at 1088 x 1920 (the paper's public code, layer by layer): generator U-Net, encoder U-Net,
# encoder merger.
SUBMODULE_PARAMETERS = {
    "holonet-dcm2": (1_435_460, 1_436_036, 141_188),
    "holonet-dcm4": (1_440_656, 1_442_960, 228_336),
    "ccnn-dcm4": (25_696, 25_696, 46_084),
}


@pytest.mark.parametrize("name", sorted(PAPER_PARAMETERS))
def test_parameter_counts_match_the_paper(name: str) -> None:
    shape, published = PAPER_PARAMETERS[name]
    counted = model_info(name, shape)["parameters"]
    assert abs(counted - published) / published < 0.03, (name, counted, published)


@pytest.mark.parametrize("key", sorted(EXACT_PARAMETERS))
def test_parameter_counts_exact(key: tuple[str, tuple[int, int]]) -> None:
    assert model_info(*key)["parameters"] == EXACT_PARAMETERS[key]


@pytest.mark.parametrize("name", sorted(SUBMODULE_PARAMETERS))
def test_submodule_counts(name: str) -> None:
    generator, encoder = build_networks(name, (1088, 1920))
    counted = (count_parameters(generator.subnet), count_parameters(encoder.subnet), count_parameters(encoder.merge))
    assert counted == SUBMODULE_PARAMETERS[name]


def test_pyramid_stage_two_counts() -> None:
    stage2 = build_networks("holonet-pyramid", (1088, 1920))[1].merge.stage2
    assert [count_parameters(m) for m in (stage2.head, stage2.grn, stage2.tail)] == [1_184, 64, 1_156]
    assert sum(count_parameters(block.lfm) for block in stage2.body) == 46_336
    assert sum(count_parameters(block.eccm) for block in stage2.body) == 92_448


def test_tiers_choose_blocks_and_dims() -> None:
    assert [tier(s) for s in [(32, 64), (1080, 1920), (1088, 1920), (2160, 3840), (2176, 3840), (4352, 7680)]] \
        == ["1080p", "1080p", "1080p", "4k", "4k", "8k"]
    assert model_info("holonet-dcm4", (1088, 1920))["lfmn_blocks"] == 4
    assert model_info("holonet-dcm4", (2176, 3840))["lfmn_blocks"] == 2
    assert model_info("holonet-pyramid", (1088, 1920))["lfmn_dims"] == (32, 32)
    assert model_info("holonet-pyramid", (2176, 3840))["lfmn_dims"] == (24, 24)
    assert model_info("ccnn-dcm4", (1088, 1920))["lfmn_blocks"] == 2
    assert model_info("ccnn-dcm4", (1088, 1920))["lfmn_dims"] == (24,)
    assert model_info("ccnn-dcm4", (4352, 7680))["lfmn_dims"] == (28,)
    _, encoder = build_networks("holonet-dcm2", (2176, 3840))
    assert len(encoder.merge.body) == 2 and encoder.merge.grn.gamma.shape[1] == 24


@pytest.mark.parametrize("name", LEARNED_METHODS)
def test_model_info(name: str, monkeypatch) -> None:
    def no_kernels(*_args: object) -> None:
        raise AssertionError("model_info must not build propagation kernels")

    monkeypatch.setattr(Propagator, "kernel", no_kernels)
    info = model_info(name, (32, 64))
    assert info["name"] == name
    assert info["family"] == name.split("-")[0]
    assert info["factor"] == FACTORS[name]
    assert info["merger"] == MERGERS.get(name, "lfmn" if FACTORS[name] > 1 else "pixel-shuffle")
    assert info["parameters"] == info["generator_parameters"] + info["encoder_parameters"]
    assert info["parameters"] == count_parameters(build_model(name, tiny_setup()))


def test_model_rejects_inputs_off_the_slm_grid() -> None:
    model = build_model("ccnn", tiny_setup())
    with pytest.raises(ValueError, match="SLM grid"):
        model(torch.rand(1, 1, 32, 32))
    with pytest.raises(ValueError, match=r"\(B, 1, H, W\)"):
        model(torch.rand(1, 2, 32, 64))


def test_dcm_encoder_output_reaches_lfmn_unclamped() -> None:
    """The paper's code: the DCM encoder's U-Net has no Hardtanh; LFMN reads values beyond pi, clamps at its end."""
    torch.manual_seed(0)
    model = build_model("holonet-dcm2", tiny_setup()).eval()
    with torch.no_grad():
        model.encoder.subnet[1].out[1].bias.fill_(10.0)  # push the U-Net's output far above pi
    seen: list[torch.Tensor] = []
    model.encoder.merge.register_forward_pre_hook(lambda _m, args: seen.append(args[0]))
    with torch.no_grad():
        phase = model(amplitude((32, 64)))
    assert seen[0].max() > math.pi + 1
    assert phase.abs().max() <= math.pi
    # Merged by a plain PixelShuffle ("SR -> None"), the encoder keeps its Hardtanh: the phase must be in range.
    assert isinstance(build_model("holonet-ps2", tiny_setup()).encoder.subnet[1].out[-1], nn.Hardtanh)


@pytest.mark.parametrize(("ablation", "part"), [("holonet-dcm2-nolfm", "lfm"), ("holonet-dcm2-noeccm", "eccm"),
                                                 ("holonet-dcm2-nogrn", "grn")])
def test_lfmn_ablations_remove_exactly_one_part(ablation: str, part: str) -> None:
    full = build_networks("holonet-dcm2", (1088, 1920))[1].merge
    reduced = build_networks(ablation, (1088, 1920))[1].merge
    removed = (count_parameters(full.grn) if part == "grn"
               else sum(count_parameters(getattr(block, part)) for block in full.body))
    assert count_parameters(full) - count_parameters(reduced) == removed > 0
    assert model_info("holonet-dcm2", (1088, 1920))["parameters"] - model_info(ablation, (1088, 1920))["parameters"] \
        == removed
    if part == "grn":
        assert isinstance(reduced.grn, nn.Identity)
    else:
        assert all(getattr(block, part) is None for block in reduced.body)
    with pytest.raises(ValueError, match="unknown LFMN part"):
        LFMN(2, 8, 1, without=("safm",))


@pytest.mark.parametrize(("name", "full"), [("holonet-ps2", "holonet-dcm2"), ("holonet-ps4", "holonet-dcm4")])
def test_pixel_shuffle_ablation_is_dcm_without_lfmn(name: str, full: str) -> None:
    merger = build_networks(full, (1088, 1920))[1].merge
    assert isinstance(build_networks(name, (1088, 1920))[1].merge, nn.PixelShuffle)
    assert model_info(full, (1088, 1920))["parameters"] - model_info(name, (1088, 1920))["parameters"] \
        == count_parameters(merger)


def test_low_definition_ablation_propagates_sub_images_at_pitch_times_r(monkeypatch) -> None:
    shape = (32, 64)
    setup = OpticalSetup(wavelength_m=520e-9, pitch_m=8e-6, distance_m=10e-3, shape=shape, roi=(24, 48),
                         aperture=0.4)
    model = build_model("holonet-lowdef2", setup).eval()
    low = model.low_setup
    assert low.pitch_m == (16e-6, 16e-6) and low.shape == (16, 32) and low.distance_m == setup.distance_m
    assert low.wavelength_m == setup.wavelength_m and low.aperture == pytest.approx(0.8)  # same physical iris
    assert model_info("holonet-lowdef2", shape)["parameters"] == model_info("holonet-dcm2", shape)["parameters"]
    propagated = []
    original_call = Propagator.__call__

    def recording_call(self: Propagator, field: torch.Tensor) -> torch.Tensor:
        propagated.append((tuple(field.shape), self.plan.pitch_m))
        return original_call(self, field)

    monkeypatch.setattr(Propagator, "__call__", recording_call)
    x = amplitude(shape, batch=1)
    with torch.no_grad():
        phase = model(x)
        sub = F.pixel_unshuffle(x, 2)
        expected_fields = low.slm_propagator()(torch.polar(sub, model.generator.subnet(sub)))
        expected = model.encoder.merge(model.encoder.subnet(expected_fields))
    assert propagated[0] == ((1, 4, 16, 32), (16e-6, 16e-6))  # the r^2 sub-fields, each at low definition
    torch.testing.assert_close(phase, expected)


def test_complex_convolutions_as_one_block_convolution_equal_the_four_real_ones() -> None:
    """ComplexConv2d / ComplexConvTranspose2d run one real convolution with the block weight [[Wr, -Wi], [Wi, Wr]]:
    the same complex product (float64) as the pair's four convolutions, with the pair's own parameters."""
    from benchctl.cgh.learned.complex_layers import ComplexConv2d, ComplexConvTranspose2d, ComplexPair

    torch.manual_seed(0)
    x = torch.randn(2, 3, 16, 20, dtype=torch.complex128)
    for layer in (ComplexConv2d(3, 5, 3, stride=2, padding=1), ComplexConvTranspose2d(3, 5, 4, stride=2, padding=1)):
        layer = layer.double()
        expected = ComplexPair.forward(layer, x)  # (Wr re - Wi im) + i (Wr im + Wi re), four real layers
        assert layer(x).shape == expected.shape
        assert torch.allclose(layer(x), expected, rtol=0, atol=1e-12)
        assert sorted(name for name, _ in layer.named_parameters()) == ["imag.bias", "imag.weight", "real.bias",
                                                                        "real.weight"]
