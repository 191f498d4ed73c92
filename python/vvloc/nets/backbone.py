"""Small ResNet-like image backbone (GroupNorm) and a light FPN to C channels."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn


def _norm(channels: int) -> nn.GroupNorm:
    groups = 8 if channels % 8 == 0 else 1
    return nn.GroupNorm(groups, channels)


class BasicBlock(nn.Module):
    """ResNet basic block: two 3×3 convs with GroupNorm, projection shortcut when needed."""

    def __init__(self, c_in: int, c_out: int, stride: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(c_in, c_out, 3, stride, 1, bias=False)
        self.norm1 = _norm(c_out)
        self.conv2 = nn.Conv2d(c_out, c_out, 3, 1, 1, bias=False)
        self.norm2 = _norm(c_out)
        self.shortcut: nn.Module = nn.Identity()
        if stride != 1 or c_in != c_out:
            self.shortcut = nn.Sequential(
                nn.Conv2d(c_in, c_out, 1, stride, bias=False), _norm(c_out)
            )

    def forward(self, x: Tensor) -> Tensor:
        y = F.relu(self.norm1(self.conv1(x)))
        y = self.norm2(self.conv2(y))
        return F.relu(y + self.shortcut(x))


class ResNetBackbone(nn.Module):
    """Stem (stride 4) + 4 stages of basic blocks at strides 4, 8, 16, 32.

    ``forward`` maps images (N, 3, Hi, Wi) float to the four stage outputs (N, c_s, Hi/s, Wi/s).
    """

    def __init__(self, widths: tuple[int, ...], blocks: tuple[int, ...]) -> None:
        super().__init__()
        c0 = widths[0]
        self.stem = nn.Sequential(
            nn.Conv2d(3, c0, 5, 2, 2, bias=False),
            _norm(c0),
            nn.ReLU(inplace=True),
            nn.MaxPool2d(3, 2, 1),
        )
        stages = []
        c_in = c0
        for s, (c, n) in enumerate(zip(widths, blocks, strict=True)):
            layers = [BasicBlock(c_in, c, 1 if s == 0 else 2)]
            layers += [BasicBlock(c, c, 1) for _ in range(n - 1)]
            stages.append(nn.Sequential(*layers))
            c_in = c
        self.stages = nn.ModuleList(stages)

    def forward(self, x: Tensor) -> list[Tensor]:
        x = self.stem(x)
        outs = []
        for stage in self.stages:
            x = stage(x)
            outs.append(x)
        return outs


class FPN(nn.Module):
    """Light feature pyramid over the last ``num_levels`` stages: 1×1 laterals to C channels,
    top-down nearest upsampling + sum, 3×3 output convs. Returns levels finest first."""

    def __init__(self, in_widths: tuple[int, ...], channels: int, num_levels: int) -> None:
        super().__init__()
        self.num_levels = num_levels
        used = in_widths[len(in_widths) - num_levels :]
        self.lateral = nn.ModuleList(nn.Conv2d(c, channels, 1) for c in used)
        self.output = nn.ModuleList(nn.Conv2d(channels, channels, 3, 1, 1) for _ in used)

    def forward(self, feats: list[Tensor]) -> list[Tensor]:
        feats = feats[len(feats) - self.num_levels :]
        lat = [conv(f) for conv, f in zip(self.lateral, feats, strict=True)]
        for i in range(len(lat) - 2, -1, -1):
            lat[i] = lat[i] + F.interpolate(lat[i + 1], size=lat[i].shape[-2:], mode="nearest")
        return [conv(x) for conv, x in zip(self.output, lat, strict=True)]


IMAGENET_MEAN = torch.tensor([0.485, 0.456, 0.406])
IMAGENET_STD = torch.tensor([0.229, 0.224, 0.225])


def normalise_images(images: Tensor) -> Tensor:
    """uint8 [0, 255] or float [0, 1] images (..., 3, H, W) → float32, ImageNet-standardised."""
    x = images.float() / 255.0 if images.dtype == torch.uint8 else images.float()
    mean = IMAGENET_MEAN.to(x.device).view(3, 1, 1)
    std = IMAGENET_STD.to(x.device).view(3, 1, 1)
    return (x - mean) / std
