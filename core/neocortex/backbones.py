"""CNN backbones of the thesis's front-end comparison (notes §5), as plain ``torch.nn`` modules.

The module trees and parameter names are those of torchvision's ``shufflenet_v2_x1_0`` and ``alexnet``
(Ma et al. 2018; Krizhevsky 2014), so a torchvision ImageNet state dict loads with ``strict=True``.
The weights come only from a file the user names (``frontend_weights``): nothing is downloaded.

Taps (the thesis leaves the ShuffleNetV2 block open, notes §5): AlexNet conv3 + ReLU (``features[:8]``,
384×13×13 = 64,896 at 224², NeoSLAM's layer) and ShuffleNetV2 ``stage3`` (232×14×14 = 45,472 at 224²,
the mid-level block, by analogy with conv3).

Preprocessing (NeoSLAM's): grey images are repeated to RGB; resize the shorter side to 256 (bilinear),
centre crop 224, ImageNet mean/std.
"""

from __future__ import annotations

from pathlib import Path
from typing import cast

import numpy as np
import torch
from torch import nn
from torch.nn import functional

from core.arrays import UInt8Array
from core.config import ConfigError

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


class WeightsError(ConfigError):
    """A backbone weights file is missing, unreadable or does not fit the architecture (one-line message)."""


def channel_shuffle(x: torch.Tensor, groups: int) -> torch.Tensor:
    """Return ``x`` with its channels shuffled across ``groups`` (ShuffleNet's channel shuffle)."""
    b, c, h, w = x.shape
    return x.view(b, groups, c // groups, h, w).transpose(1, 2).contiguous().view(b, c, h, w)


class InvertedResidual(nn.Module):
    """ShuffleNetV2 unit: split (stride 1) or two branches (stride 2), concatenate, shuffle."""

    def __init__(self, inp: int, oup: int, stride: int) -> None:
        super().__init__()
        self.stride = stride
        branch = oup // 2
        if stride > 1:
            self.branch1 = nn.Sequential(
                nn.Conv2d(inp, inp, 3, stride, 1, bias=False, groups=inp), nn.BatchNorm2d(inp),
                nn.Conv2d(inp, branch, 1, 1, 0, bias=False), nn.BatchNorm2d(branch), nn.ReLU(inplace=True),
            )
        else:
            self.branch1 = nn.Sequential()
        self.branch2 = nn.Sequential(
            nn.Conv2d(inp if stride > 1 else branch, branch, 1, 1, 0, bias=False), nn.BatchNorm2d(branch),
            nn.ReLU(inplace=True),
            nn.Conv2d(branch, branch, 3, stride, 1, bias=False, groups=branch), nn.BatchNorm2d(branch),
            nn.Conv2d(branch, branch, 1, 1, 0, bias=False), nn.BatchNorm2d(branch), nn.ReLU(inplace=True),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Apply the unit."""
        if self.stride == 1:
            x1, x2 = x.chunk(2, dim=1)
            out = torch.cat((x1, self.branch2(x2)), dim=1)
        else:
            out = torch.cat((self.branch1(x), self.branch2(x)), dim=1)
        return channel_shuffle(out, 2)


class ShuffleNetV2(nn.Module):
    """ShuffleNetV2 x1.0 (stage repeats 4, 8, 4; channels 24, 116, 232, 464, 1024)."""

    stage2: nn.Sequential
    stage3: nn.Sequential
    stage4: nn.Sequential

    def __init__(
        self, repeats: tuple[int, ...] = (4, 8, 4), channels: tuple[int, ...] = (24, 116, 232, 464, 1024)
    ) -> None:
        super().__init__()
        self.conv1 = nn.Sequential(nn.Conv2d(3, channels[0], 3, 2, 1, bias=False), nn.BatchNorm2d(channels[0]),
                                   nn.ReLU(inplace=True))
        self.maxpool = nn.MaxPool2d(kernel_size=3, stride=2, padding=1)
        inp = channels[0]
        for name, count, oup in zip(("stage2", "stage3", "stage4"), repeats, channels[1:4], strict=True):
            units = [InvertedResidual(inp, oup, 2)] + [InvertedResidual(oup, oup, 1) for _ in range(count - 1)]
            setattr(self, name, nn.Sequential(*units))
            inp = oup
        self.conv5 = nn.Sequential(nn.Conv2d(inp, channels[-1], 1, 1, 0, bias=False), nn.BatchNorm2d(channels[-1]),
                                   nn.ReLU(inplace=True))
        self.fc = nn.Linear(channels[-1], 1000)

    def embed(self, x: torch.Tensor) -> torch.Tensor:
        """Return the flattened ``stage3`` features (B, 232·h·w)."""
        x = self.maxpool(self.conv1(x))
        return torch.flatten(self.stage3(self.stage2(x)), 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Return the ImageNet logits (the full torchvision forward)."""
        x = self.conv5(self.stage4(self.stage3(self.stage2(self.maxpool(self.conv1(x))))))
        return cast(torch.Tensor, self.fc(x.mean([2, 3])))


class AlexNet(nn.Module):
    """AlexNet as torchvision's (``features``, ``avgpool``, ``classifier``)."""

    def __init__(self) -> None:
        super().__init__()
        self.features = nn.Sequential(
            nn.Conv2d(3, 64, 11, 4, 2), nn.ReLU(inplace=True), nn.MaxPool2d(3, 2),
            nn.Conv2d(64, 192, 5, padding=2), nn.ReLU(inplace=True), nn.MaxPool2d(3, 2),
            nn.Conv2d(192, 384, 3, padding=1), nn.ReLU(inplace=True),
            nn.Conv2d(384, 256, 3, padding=1), nn.ReLU(inplace=True),
            nn.Conv2d(256, 256, 3, padding=1), nn.ReLU(inplace=True), nn.MaxPool2d(3, 2),
        )
        self.avgpool = nn.AdaptiveAvgPool2d((6, 6))
        self.classifier = nn.Sequential(
            nn.Dropout(0.5), nn.Linear(256 * 36, 4096), nn.ReLU(inplace=True),
            nn.Dropout(0.5), nn.Linear(4096, 4096), nn.ReLU(inplace=True), nn.Linear(4096, 1000),
        )

    def embed(self, x: torch.Tensor) -> torch.Tensor:
        """Return the flattened conv3 + ReLU features (B, 384·h·w)."""
        return torch.flatten(self.features[:8](x), 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Return the ImageNet logits (the full torchvision forward)."""
        return cast(torch.Tensor, self.classifier(torch.flatten(self.avgpool(self.features(x)), 1)))


ARCHITECTURES: dict[str, type[ShuffleNetV2] | type[AlexNet]] = {"shufflenetv2": ShuffleNetV2, "alexnet": AlexNet}


def build_backbone(name: str, weights: str | Path, device: torch.device) -> ShuffleNetV2 | AlexNet:
    """Return backbone ``name`` in eval mode on ``device`` with the state dict of file ``weights``.

    Accepts a plain state dict or one under ``"state_dict"`` (tensors only; ``weights_only`` loading).

    Raises:
        WeightsError: no file given, unreadable file, or keys/shapes that do not fit the architecture.
    """
    if name not in ARCHITECTURES:
        msg = f"unknown backbone {name!r} (valid: {', '.join(ARCHITECTURES)})"
        raise WeightsError(msg)
    if not str(weights):
        msg = f"backbone {name!r} needs a weights file (frontend_weights / --weights PATH); nothing is downloaded"
        raise WeightsError(msg)
    path = Path(weights)
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except (OSError, RuntimeError, ValueError, EOFError) as err:
        msg = f"cannot read backbone weights {str(path)!r}: {str(err).splitlines()[0] if str(err) else err}"
        raise WeightsError(msg) from err
    if isinstance(state, dict) and isinstance(state.get("state_dict"), dict):
        state = state["state_dict"]
    if not isinstance(state, dict):
        msg = f"backbone weights {str(path)!r} hold no state dict"
        raise WeightsError(msg)
    model = ARCHITECTURES[name]()
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as err:
        lines = str(err).splitlines()
        detail = lines[1].strip() if len(lines) > 1 else str(err)
        msg = f"backbone weights {str(path)!r} do not fit {name}: {detail}"
        raise WeightsError(msg) from err
    return model.eval().to(device)


def preprocess(image: UInt8Array, device: torch.device, size: int = 224, resize: int = 256) -> torch.Tensor:
    """Return the (1, 3, size, size) ImageNet-normalised tensor of a uint8 (H, W) or (H, W, 3) image."""
    pixels = torch.from_numpy(np.array(image, dtype=np.float32)) / 255.0
    if pixels.ndim == 2:
        pixels = pixels[..., None].expand(-1, -1, 3)
    x = pixels[..., :3].permute(2, 0, 1)[None].to(device)
    h, w = x.shape[-2:]
    scale = resize / min(h, w)
    x = functional.interpolate(x, size=(max(size, round(h * scale)), max(size, round(w * scale))), mode="bilinear",
                      align_corners=False)
    top, left = (x.shape[-2] - size) // 2, (x.shape[-1] - size) // 2
    x = x[..., top : top + size, left : left + size]
    mean = torch.tensor(IMAGENET_MEAN, device=device)[None, :, None, None]
    std = torch.tensor(IMAGENET_STD, device=device)[None, :, None, None]
    return (x - mean) / std
