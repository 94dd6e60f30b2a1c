"""VGG19 feature layers for the perceptual loss, built here in plain torch and loaded from a local file.

The paper trains at 1080p with L2 + perceptual loss (VGG19 features, weight 0.025). torchvision is not a
dependency of benchctl and nothing is ever downloaded: the user passes a file holding a torchvision-format
VGG19 state dict (`torchvision.models.vgg19(weights=...).state_dict()` saved with `torch.save`, or the
`vgg19-dcbb9e9d.pth` file torchvision itself caches). Only the `features.N.weight` / `features.N.bias`
entries are used; the classifier is ignored.

The perceptual term: the reconstructed and target amplitudes (ROI, gray) are repeated to three channels,
normalised with the ImageNet mean and standard deviation the VGG weights expect, and compared by MSE at
relu1_2, relu2_2, relu3_4, relu4_4 and relu5_4 (mean over the layers).
"""

from __future__ import annotations

from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from benchctl.errors import BenchctlError

VGG19_LAYOUT: tuple[int | str, ...] = (64, 64, "M", 128, 128, "M", 256, 256, 256, 256, "M",
                                       512, 512, 512, 512, "M", 512, 512, 512, 512, "M")
"""torchvision's VGG19 `features`: 3x3 convs (each followed by a ReLU) and 2x2 max pools ("M")."""

FEATURE_LAYERS = {"relu1_2": 3, "relu2_2": 8, "relu3_4": 17, "relu4_4": 26, "relu5_4": 35}
"""Index in `features` of each ReLU whose output the perceptual loss compares."""

PERCEPTUAL_WEIGHT = 0.025
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def _features(last: int) -> nn.Sequential:
    """torchvision's VGG19 `features` up to and including index `last`, with the same indices."""
    layers: list[nn.Module] = []
    channels = 3
    for item in VGG19_LAYOUT:
        if item == "M":
            layers.append(nn.MaxPool2d(2, 2))
        else:
            assert isinstance(item, int)
            layers += [nn.Conv2d(channels, item, 3, padding=1), nn.ReLU()]
            channels = item
    return nn.Sequential(*layers[:last + 1])


class VGG19Features(nn.Module):
    """Frozen VGG19 feature extractor: (B, 3, H, W) normalised images -> activations at `FEATURE_LAYERS`."""

    def __init__(self) -> None:
        super().__init__()
        self.taps = sorted(FEATURE_LAYERS.values())
        self.features = _features(self.taps[-1])
        self.requires_grad_(False)
        self.eval()

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        out = []
        for index, layer in enumerate(self.features):
            x = layer(x)
            if index in self.taps:
                out.append(x)
        return out


def load_vgg19(path: Path) -> VGG19Features:
    """VGG19 features with the weights from a torchvision-format state dict file (read with weights_only)."""
    path = Path(path)
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise BenchctlError(f"--vgg-weights {path}: no such file") from None
    except Exception as exc:  # noqa: BLE001  (pickle, zip and torch errors: not a state dict we can read)
        first_line = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise BenchctlError(f"--vgg-weights {path}: cannot read a torch state dict from it ({first_line})") from None
    if isinstance(state, dict) and "state_dict" in state and isinstance(state["state_dict"], dict):
        state = state["state_dict"]
    if not isinstance(state, dict):
        raise BenchctlError(f"--vgg-weights {path}: expected a state dict, found {type(state).__name__}")
    model = VGG19Features()
    wanted = model.state_dict()
    missing = [key for key in wanted if key not in state]
    if missing:
        raise BenchctlError(f"--vgg-weights {path}: not a torchvision VGG19 state dict, missing "
                            f"{', '.join(missing[:4])}{' ...' if len(missing) > 4 else ''}")
    for key, tensor in wanted.items():
        if not isinstance(state[key], torch.Tensor) or tuple(state[key].shape) != tuple(tensor.shape):
            found = tuple(state[key].shape) if isinstance(state[key], torch.Tensor) else type(state[key]).__name__
            raise BenchctlError(f"--vgg-weights {path}: {key} is {found}, VGG19 needs {tuple(tensor.shape)}")
    model.load_state_dict({key: state[key].float() for key in wanted})
    return model


class PerceptualLoss(nn.Module):
    """Mean over `FEATURE_LAYERS` of the MSE between VGG19 features of two gray (B, 1, H, W) images."""

    mean: torch.Tensor  # buffers, registered in __init__
    std: torch.Tensor

    def __init__(self, features: VGG19Features) -> None:
        super().__init__()
        self.features = features
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

    def _normalised(self, gray: torch.Tensor) -> torch.Tensor:
        return (gray.expand(-1, 3, -1, -1) - self.mean) / self.std

    def forward(self, recon: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            target_features = self.features(self._normalised(target))
        recon_features = self.features(self._normalised(recon))
        losses = [F.mse_loss(a, b) for a, b in zip(recon_features, target_features)]
        return torch.stack(losses).mean()
