"""LapDEN: Laplacian-pyramid depth enhancement network (Jeon & Lee, ECCV 2018).

The network takes a raw depth image and its hole mask, encodes it down to 1/4
resolution with strided 4x4 convolutions, then predicts the enhanced depth coarse
to fine: at each level (1/4, 1/2, 1) a stack of residual blocks (3x3 conv,
LeakyReLU 0.2, 3x3 conv, identity skip) refines the features and a 3x3 convolution
(the level's head) predicts a residual depth map that is added to the level's base
(the Laplacian-pyramid scheme of LapSRN: LapDEN's levels predict residuals).
Features go up one level with a transposed 4x4 stride-2 convolution and are summed
with the encoder's features of that resolution (a parameter-free skip, our choice:
without it the full-resolution level only sees 1/4-resolution features and cannot
remove pixel-level noise from the input it starts from).

The bases are anchored on the input (our choice, for fast convergence on small
datasets; the paper does not pin them):

* 1/4 level: the valid-aware 4x4 average of the input
  (:func:`depthgt.depth_ops.masked_avg_pool`) with its holes filled smoothly
  (:func:`push_pull_fill`);
* 1/2 and full level: the valid-aware average of the input at that level where it
  has valid pixels, else the bilinearly upsampled output of the coarser level.

The heads are zero-initialised, so an untrained LapDEN returns the input on its
valid pixels and a smooth fill in its holes; training only learns the correction.

Size is configuration (:class:`LapDENConfig`), never a code fork:

* ``paper``: 64 channels, 10/20/40 convs in the decoder levels (the released
  model's blocks). The paper's text does not pin the encoder; 10 convs at full and
  10 at half resolution bring the count to ~3.6 M parameters, the released size.
* ``default``: 16 channels, 2/2/4 decoder convs, 2/0 encoder convs (~40 k
  parameters): 0.50-0.77 s per Adam step of 8 128x128 pairs on one or two threads of a
  2-core machine (docs/decisions.md "Threads per training on 2 cores";
  bench/bench_train_steps.py); 32 channels with 2/4/6 convs costs ~3x more.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
import torch.nn as nn
import torch.nn.functional as F

from depthgt.depth_ops import masked_avg_pool, valid_avg_pool
from depthgt.shapes import check_shape

__all__ = [
    "LapDENConfig",
    "LapDEN",
    "PRESETS",
    "lapden_from_preset",
    "build_lapden",
    "push_pull_fill",
    "count_parameters",
]


@dataclass(frozen=True)
class LapDENConfig:
    """Size of a LapDEN network.

    Attributes:
        channels: feature channels at every level.
        level_convs: number of 3x3 convs in the residual blocks of the decoder levels
            (1/4, 1/2, 1); each must be even (two convs per residual block).
        encoder_convs: number of 3x3 convs in the encoder at full and 1/2 resolution
            (before each strided down-convolution); even.
        negative_slope: LeakyReLU slope.
    """

    channels: int = 16
    level_convs: tuple[int, int, int] = (2, 2, 4)
    encoder_convs: tuple[int, int] = (2, 0)
    negative_slope: float = 0.2

    def __post_init__(self):
        if self.channels < 1:
            raise ValueError(f"LapDENConfig.channels must be >= 1, got {self.channels}")
        if len(self.level_convs) != 3 or len(self.encoder_convs) != 2:
            raise ValueError(
                f"LapDENConfig needs 3 level_convs and 2 encoder_convs, got {self.level_convs}, {self.encoder_convs}"
            )
        for name, convs in (("level_convs", self.level_convs), ("encoder_convs", self.encoder_convs)):
            if any(c < 0 or c % 2 for c in convs):
                raise ValueError(f"LapDENConfig.{name} must be even and >= 0 (2 convs per block), got {convs}")

    def to_dict(self) -> dict:
        return asdict(self)


PRESETS: dict[str, LapDENConfig] = {
    "paper": LapDENConfig(channels=64, level_convs=(10, 20, 40), encoder_convs=(10, 10)),
    "default": LapDENConfig(channels=16, level_convs=(2, 2, 4), encoder_convs=(2, 0)),
}


def lapden_from_preset(name: str, **overrides) -> LapDEN:
    """Build a LapDEN from a preset name (``paper`` or ``default``), with field overrides."""
    if name not in PRESETS:
        raise ValueError(f"unknown LapDEN preset {name!r}; known: {sorted(PRESETS)}")
    cfg = asdict(PRESETS[name])
    unknown = sorted(set(overrides) - set(cfg))
    if unknown:
        raise ValueError(f"unknown LapDEN model parameters {unknown}; known: preset, {', '.join(cfg)}")
    cfg.update(overrides)
    for key in ("level_convs", "encoder_convs"):
        cfg[key] = tuple(cfg[key])
    return LapDEN(LapDENConfig(**cfg))


def build_lapden(preset: str = "default", **overrides) -> LapDEN:
    """The registry's builder of ``lapden`` (:data:`depthgt.registry.MODELS`): the
    config's ``model_params`` (``preset`` and LapDENConfig overrides) as keywords."""
    return lapden_from_preset(preset, **overrides)


def count_parameters(model: nn.Module) -> int:
    """Number of trainable parameters (shared tensors counted once)."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)


def push_pull_fill(depth_m: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Smooth hole filling by a pyramid of valid-aware 2x2 averages (push-pull).

    The image is averaged down (valid pixels only, :func:`depthgt.depth_ops.valid_avg_pool`
    over 2x2 blocks, odd sizes rounded up) until the coarsest level is one pixel; then,
    coarse to fine, each level's holes take the bilinearly upsampled filled coarser
    level. Valid pixels are returned unchanged. The levels below the first without holes
    change nothing (it keeps all its pixels), so there is no data-dependent stop: the same
    ops for every batch, no host read of the mask, one graph for torch.compile. Written by hand: OpenCV's inpainting
    is per-image numpy (no batch, no device), and this is ~log2(H) tensor ops.

    Args:
        depth_m: (B, 1, H, W) metres.
        valid: (B, 1, H, W) bool or {0, 1} float.

    Returns:
        (B, 1, H, W) metres; holes filled, 0 only in images with no valid pixel.
    """
    check_shape(valid, "B 1 H W", "valid", check_shape(depth_m, "B 1 H W", "depth_m"))
    w = valid.to(depth_m.dtype)
    levels = [(depth_m * w, w)]
    while min(levels[-1][0].shape[-2:]) > 1:
        d, w = levels[-1]
        d_c, ok = valid_avg_pool(d, w, 2, ceil_mode=True)
        levels.append((d_c, ok.to(d.dtype)))
    filled = levels[-1][0]
    for d, w in reversed(levels[:-1]):
        up = F.interpolate(filled, size=tuple(d.shape[-2:]), mode="bilinear", align_corners=False)
        filled = torch.where(w > 0, d, up)
    return filled


class _ResBlock(nn.Module):
    def __init__(self, channels: int, slope: float):
        super().__init__()
        self.conv1 = nn.Conv2d(channels, channels, 3, padding=1)
        self.conv2 = nn.Conv2d(channels, channels, 3, padding=1)
        self.slope = slope

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        # in place on tensors nothing else reads (a convolution's output, a fresh sum):
        # the same values and gradients (LeakyReLU's backward reads the sign of its output
        # instead of its input's, the same for a positive slope), one allocation less
        y = self.conv2(F.leaky_relu(self.conv1(x), self.slope, inplace=True))
        return F.leaky_relu(x + y, self.slope, inplace=True)


def _blocks(channels: int, convs: int, slope: float) -> nn.Sequential:
    return nn.Sequential(*[_ResBlock(channels, slope) for _ in range(convs // 2)])


class LapDEN(nn.Module):
    """Laplacian-pyramid depth enhancement network.

    ``forward(depth_m)`` takes (B, 1, H, W) metres (0 = hole; H, W divisible by 4),
    builds the input (B, 2, H, W) = (depth, hole mask) and returns the multi-scale
    outputs ``[(B,1,H/4,W/4), (B,1,H/2,W/2), (B,1,H,W)]`` in metres, finest last:
    each is its level's base (see the module docstring) plus the predicted residual.
    """

    def __init__(self, config: LapDENConfig = LapDENConfig()):
        super().__init__()
        self.config = config
        c, s = config.channels, config.negative_slope
        self.conv_in = nn.Conv2d(2, c, 3, padding=1)
        self.enc = nn.ModuleList([_blocks(c, n, s) for n in config.encoder_convs])
        self.down = nn.ModuleList([nn.Conv2d(c, c, 4, stride=2, padding=1) for _ in range(2)])
        self.levels = nn.ModuleList([_blocks(c, n, s) for n in config.level_convs])
        self.up = nn.ModuleList([nn.ConvTranspose2d(c, c, 4, stride=2, padding=1) for _ in range(2)])
        self.heads = nn.ModuleList([nn.Conv2d(c, 1, 3, padding=1) for _ in range(3)])
        for head in self.heads:  # start at the base: identity on valid pixels, smooth fill in holes
            nn.init.zeros_(head.weight)
            nn.init.zeros_(head.bias)

    def forward(self, depth_m: torch.Tensor) -> list[torch.Tensor]:
        check_shape(depth_m, "B 1 H W", "LapDEN: depth_m")
        if depth_m.shape[-1] % 4 or depth_m.shape[-2] % 4:
            raise ValueError(f"LapDEN needs H and W divisible by 4, got {tuple(depth_m.shape)}")
        s = self.config.negative_slope
        valid = depth_m > 0
        hole = (~valid).to(depth_m.dtype)
        x = F.leaky_relu(self.conv_in(torch.cat([depth_m, hole], dim=1)), s, inplace=True)
        skips = []  # encoder features at full and 1/2 resolution
        for enc, down in zip(self.enc, self.down):
            x = enc(x)
            skips.append(x)
            x = F.leaky_relu(down(x), s, inplace=True)
        outputs = []
        for level in range(3):
            d_l, v_l = masked_avg_pool(depth_m, valid, 4 >> level)
            if level == 0:
                base = push_pull_fill(d_l, v_l)
            else:
                x = F.leaky_relu(self.up[level - 1](x), s, inplace=True) + skips[2 - level]
                up = F.interpolate(outputs[-1], scale_factor=2.0, mode="bilinear", align_corners=False)
                base = torch.where(v_l, d_l, up)
            x = self.levels[level](x)
            outputs.append(base + self.heads[level](x))
        return outputs
