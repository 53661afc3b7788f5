"""The R&R RGB feature encoder and the lifting of pixels to feature-carrying 3D points.

Encoder (UnsupervisedR&R, CVPR 2021): 3x3 conv to ``channels`` + BN + ReLU, then
``n_blocks`` ResNet-18 BasicBlocks at full resolution (each with its own weights),
then a 1x1 conv to ``feat_dim`` + BN. ResNet-18's first stage is two 64-channel
BasicBlocks at stride 1, the default here.
"""

from __future__ import annotations

import torch
from torch import nn

from depthgt.geometry import backproject
from depthgt.shapes import check_shape

__all__ = ["BasicBlock", "RGBEncoder", "build_encoder", "candidate_points"]


class BasicBlock(nn.Module):
    """ResNet BasicBlock at stride 1 with identity shortcut: relu(x + bn(conv(relu(bn(conv(x)))))).

    Written here (a few lines) because torchvision, which ships it, is not a
    dependency of the project.
    """

    def __init__(self, channels: int):
        super().__init__()
        self.conv1 = nn.Conv2d(channels, channels, 3, padding=1, bias=False)
        self.bn1 = nn.BatchNorm2d(channels)
        self.conv2 = nn.Conv2d(channels, channels, 3, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(channels)
        self.relu = nn.ReLU(inplace=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.relu(self.bn1(self.conv1(x)))
        y = self.bn2(self.conv2(y))
        return self.relu(x + y)


class RGBEncoder(nn.Module):
    """Full-resolution RGB encoder: (B, 3, H, W) in [0, 1] -> (B, feat_dim, H, W)."""

    def __init__(self, n_blocks: int = 2, channels: int = 64, feat_dim: int = 32):
        super().__init__()
        if n_blocks < 0 or channels < 1 or feat_dim < 1:
            raise ValueError(f"invalid encoder size n_blocks={n_blocks}, channels={channels}, feat_dim={feat_dim}")
        self.stem = nn.Sequential(
            nn.Conv2d(3, channels, 3, padding=1, bias=False), nn.BatchNorm2d(channels), nn.ReLU(inplace=True)
        )
        # One new module per block: no layer is registered twice.
        self.blocks = nn.Sequential(*[BasicBlock(channels) for _ in range(n_blocks)])
        self.head = nn.Sequential(nn.Conv2d(channels, feat_dim, 1, bias=False), nn.BatchNorm2d(feat_dim))

    def forward(self, rgb: torch.Tensor) -> torch.Tensor:
        check_shape(rgb, "B 3 H W", "rgb")
        return self.head(self.blocks(self.stem(rgb)))


def build_encoder(n_blocks: int = 2, channels: int = 64, feat_dim: int = 32, seed: int | None = None) -> RGBEncoder:
    """New encoder; with ``seed`` its initial weights are deterministic."""
    if seed is None:
        return RGBEncoder(n_blocks, channels, feat_dim)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return RGBEncoder(n_blocks, channels, feat_dim)


def candidate_points(depth_m: torch.Tensor, K: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """(B, N, 3) camera-frame points (metres) of the pixels ``index`` (B, N) (flat,
    row-major) of ``depth_m`` (B, 1, H, W) with intrinsics ``K`` (B, 3, 3); their features
    come from :func:`depthgt.registration.overfit.encode_at`."""
    check_shape(index, "B N", "index", check_shape(depth_m, "B 1 H W", "depth_m"))
    return torch.gather(backproject(depth_m, K), 1, index[..., None].expand(-1, -1, 3))
