"""Learned baselines of the paper's comparison (Sec. 4.3), reimplemented.

* :class:`DDRNetDenoise`: the denoising network of DDRNet (Yan et al., ECCV 2018), a
  convolutional encoder-decoder with skip connections that predicts a residual on
  the input depth. Its loss :func:`ddrnet_loss`: DDRNet trains the denoiser with a
  data term against a fused reference depth plus a shading term (the rendered
  shading of the predicted normals under spherical-harmonics lighting estimated
  from the colour image). Here the reference is depthgt's GT, and the shading term
  is replaced by an L1 term on the normals against the GT normals (single view, no
  lighting estimation): document it in the tables as "DDRNet (denoise, normal term
  for shading)".
* :class:`SDDUNet`: the partial-convolution U-Net of SDD (Sterzentsenko et al., ICCV
  2019; partial convolutions of Liu et al., ECCV 2018). SDD is self-supervised with a
  multi-view photometric term; :func:`sdd_loss` replaces it with single-view depth
  terms: an L1 depth term against the GT on valid GT pixels and SDD's edge-aware
  surface-normal smoothness prior (normals of neighbouring pixels should agree
  where the colour image has no edge).

Both take depth (B, 1, H, W) metres (0 = hole) and return ``[depth (B, 1, H, W)]``.
"""

from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

from depthgt.depth_ops import depth_normals
from depthgt.enhance.losses import depth_l1, normal_l1
from depthgt.shapes import check_shape

__all__ = ["DDRNetDenoise", "PartialConv2d", "SDDUNet", "ddrnet_loss", "sdd_loss", "normal_smoothness"]


class DDRNetDenoise(nn.Module):
    """DDRNet's denoising encoder-decoder.

    Encoder: per level two 3x3 convs (ReLU), then a stride-2 3x3 conv; decoder:
    transposed 4x4 stride-2 convs, concatenation with the encoder features of the
    same level, two 3x3 convs; a 3x3 conv predicts the residual added to the input.
    Depth is divided by its mean valid value on the way in and multiplied back on the
    way out. A denoiser: the input's holes stay holes (0) in the output, as in the
    paper's comparison where DDRNet "cannot cope with the missing depth values".

    Args:
        channels: width of the first level (doubles per level).
        levels: number of down-sampling steps; H and W must be multiples of 2**levels.
    """

    def __init__(self, channels: int = 16, levels: int = 3):
        super().__init__()
        if channels < 1 or levels < 1:
            raise ValueError(f"DDRNetDenoise needs channels >= 1 and levels >= 1, got {channels}, {levels}")
        self.size_multiple = 2**levels
        widths = [channels * 2**i for i in range(levels + 1)]
        self.inc = self._double(1, widths[0])
        self.downs = nn.ModuleList(
            [
                nn.Sequential(
                    nn.Conv2d(widths[i], widths[i + 1], 3, stride=2, padding=1),
                    nn.ReLU(inplace=True),
                    self._double(widths[i + 1], widths[i + 1]),
                )
                for i in range(levels)
            ]
        )
        self.ups = nn.ModuleList(
            [nn.ConvTranspose2d(widths[i + 1], widths[i], 4, stride=2, padding=1) for i in reversed(range(levels))]
        )
        self.decs = nn.ModuleList([self._double(2 * widths[i], widths[i]) for i in reversed(range(levels))])
        self.out = nn.Conv2d(widths[0], 1, 3, padding=1)

    @staticmethod
    def _double(cin: int, cout: int) -> nn.Sequential:
        return nn.Sequential(
            nn.Conv2d(cin, cout, 3, padding=1),
            nn.ReLU(inplace=True),
            nn.Conv2d(cout, cout, 3, padding=1),
            nn.ReLU(inplace=True),
        )

    def forward(self, depth_m: torch.Tensor) -> list[torch.Tensor]:
        _check_input(depth_m, self.size_multiple, "DDRNetDenoise")
        valid = depth_m > 0
        scale = _mean_valid_depth(depth_m, valid)
        d = depth_m / scale
        x = self.inc(d)
        skips = [x]
        for down in self.downs:
            x = down(x)
            skips.append(x)
        skips.pop()
        for up, dec in zip(self.ups, self.decs):
            x = dec(torch.cat([F.relu(up(x)), skips.pop()], dim=1))
        # a denoiser: holes of the input stay holes (0)
        return [torch.where(valid, (d + self.out(x)) * scale, torch.zeros_like(depth_m))]


class PartialConv2d(nn.Module):
    """Partial convolution (Liu et al. 2018): convolve only valid inputs, renormalise
    by the valid fraction of the window, propagate the mask (valid if any input was).

    ``forward(x (B, C, H, W), mask (B, 1, H, W) {0,1}, masked=False) -> (y, new_mask)``;
    ``y`` is 0 outside ``new_mask``. ``masked=True`` says that ``x`` is 0 outside ``mask``
    already (a partial convolution's output through an activation with f(0) = 0, or such
    outputs concatenated under the union of their masks), so that multiplying it by the
    mask would change nothing: the multiplication and its backward are skipped (the
    weights' gradients are the same to the bit: the next layer's ``new_mask`` zeroes
    what the skipped product would have).
    """

    def __init__(self, cin: int, cout: int, kernel_size: int, stride: int = 1):
        super().__init__()
        self.conv = nn.Conv2d(cin, cout, kernel_size, stride=stride, padding=kernel_size // 2, bias=True)
        self.register_buffer("ones", torch.ones(1, 1, kernel_size, kernel_size), persistent=False)
        self.window = float(kernel_size * kernel_size)

    def forward(self, x: torch.Tensor, mask: torch.Tensor, masked: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        with torch.no_grad():
            count = F.conv2d(mask, self.ones, stride=self.conv.stride, padding=self.conv.padding)
            new_mask = (count > 0).to(x.dtype)
            ratio = self.window / count.clamp_min(1.0) * new_mask
        raw = F.conv2d(x if masked else x * mask, self.conv.weight, None, self.conv.stride, self.conv.padding)
        bias = self.conv.bias.view(1, -1, 1, 1)
        return (raw * ratio + bias) * new_mask, new_mask


class SDDUNet(nn.Module):
    """SDD's partial-convolution U-Net.

    Encoder: partial convs (kernel 5 then 3) with stride 2 per level; decoder: nearest
    up-sampling, concatenation with the encoder level (features and masks), partial
    3x3 conv; ELU activations as in SDD. The output is absolute depth (holes filled
    where the propagated mask reaches); the network sees depth divided by its mean
    valid value and its output is multiplied back.

    Args:
        channels: width of the first level (doubles per level, capped at 8x).
        levels: number of down-sampling steps; H, W multiples of 2**levels.
    """

    def __init__(self, channels: int = 16, levels: int = 3):
        super().__init__()
        if channels < 1 or levels < 1:
            raise ValueError(f"SDDUNet needs channels >= 1 and levels >= 1, got {channels}, {levels}")
        self.size_multiple = 2**levels
        widths = [channels * min(2**i, 8) for i in range(levels + 1)]
        self.inc = PartialConv2d(1, widths[0], 5)
        self.downs = nn.ModuleList([PartialConv2d(widths[i], widths[i + 1], 3, stride=2) for i in range(levels)])
        self.decs = nn.ModuleList(
            [PartialConv2d(widths[i + 1] + widths[i], widths[i], 3) for i in reversed(range(levels))]
        )
        self.out = nn.Conv2d(widths[0], 1, 3, padding=1)
        with torch.no_grad():  # start at the mean depth (1 in the normalised units)
            self.out.bias.fill_(1.0)

    def forward(self, depth_m: torch.Tensor) -> list[torch.Tensor]:
        _check_input(depth_m, self.size_multiple, "SDDUNet")
        mask = (depth_m > 0).to(depth_m.dtype)
        scale = _mean_valid_depth(depth_m, mask > 0)
        x, m = self.inc(depth_m / scale, mask)
        x = F.elu(x)
        skips = [(x, m)]
        for down in self.downs:
            x, m = down(x, m, masked=True)  # elu(0) = 0: x is 0 outside m
            x = F.elu(x)
            skips.append((x, m))
        skips.pop()
        for dec in self.decs:
            sx, sm = skips.pop()
            x = F.interpolate(x, scale_factor=2.0, mode="nearest")
            m = F.interpolate(m, scale_factor=2.0, mode="nearest")
            # a concatenated channel group keeps its own mask: take their union
            x, m = dec(torch.cat([x, sx], dim=1), torch.maximum(m, sm), masked=True)
            x = F.elu(x)
        return [self.out(x) * scale]


def _mean_valid_depth(depth_m: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """(B, 1, 1, 1) mean valid depth per image (1 m for an empty image): the networks
    see depth divided by it, so that they work at any metric scale."""
    w = valid.to(depth_m.dtype)
    mean = (depth_m * w).sum(dim=(1, 2, 3), keepdim=True) / w.sum(dim=(1, 2, 3), keepdim=True).clamp_min(1.0)
    return torch.where(mean > 0, mean, torch.ones_like(mean))


def _float_terms(*terms: tuple[str, torch.Tensor]) -> dict[str, float]:
    """The loss log's floats of scalar tensors, read in one go (one host read, and no
    break in a graph torch.compile traces before the read)."""
    values = torch.stack([t for _, t in terms]).detach().tolist()
    return {name: v for (name, _), v in zip(terms, values)}


def _check_input(depth_m: torch.Tensor, multiple: int, who: str) -> None:
    check_shape(depth_m, "B 1 H W", f"{who}: depth_m")
    if depth_m.shape[-1] % multiple or depth_m.shape[-2] % multiple:
        raise ValueError(f"{who} needs H and W divisible by {multiple}, got {tuple(depth_m.shape)}")


def ddrnet_loss(outputs, batch: dict, w_depth: float = 1.0, w_normal: float = 1.0):
    """DDRNet denoising loss with the normal term standing in for shading.

    Args:
        outputs: [pred (B, 1, H, W)] metres; batch: ``gt`` (B, 1, H, W), ``K`` (B, 3, 3).

    Returns:
        (total, {"depth", "normal", "total"}).
    """
    pred = outputs[-1] if isinstance(outputs, (list, tuple)) else outputs
    gt = batch["gt"]
    valid = gt > 0
    t_d = depth_l1(pred, gt, valid)
    t_n = normal_l1(pred, gt, valid, batch["K"])
    total = w_depth * t_d + w_normal * t_n
    return total, _float_terms(("depth", t_d), ("normal", t_n), ("total", total))


def normal_smoothness(depth_m: torch.Tensor, K: torch.Tensor, rgb: torch.Tensor | None, alpha: float = 10.0):
    """Edge-aware normal smoothness: mean of w * (1 - n_p . n_q) over right and lower
    neighbours q, w = exp(-alpha * |I_p - I_q|) (mean over colour channels; 1 without rgb).

    Args:
        depth_m: (B, 1, H, W); K: (B, 3, 3); rgb: (B, 3, H, W) in [0, 1] or None.
    """
    n = depth_normals(depth_m, K.to(depth_m.dtype))
    terms = []
    for dim in (-1, -2):
        a, b = n.narrow(dim, 1, n.shape[dim] - 1), n.narrow(dim, 0, n.shape[dim] - 1)
        cos = (a * b).sum(dim=1, keepdim=True)
        if rgb is not None:
            ia, ib = rgb.narrow(dim, 1, rgb.shape[dim] - 1), rgb.narrow(dim, 0, rgb.shape[dim] - 1)
            w = torch.exp(-alpha * (ia - ib).abs().mean(dim=1, keepdim=True))
        else:
            w = torch.ones_like(cos)
        terms.append((w * (1.0 - cos)).mean())
    return terms[0] + terms[1]


def sdd_loss(outputs, batch: dict, w_depth: float = 1.0, w_smooth: float = 0.1, alpha: float = 10.0):
    """SDD's single-view loss: L1 depth against the GT + edge-aware normal smoothness.

    Args:
        outputs: [pred (B, 1, H, W)]; batch: ``gt``, ``K``, optional ``rgb`` (B, 3, H, W).

    Returns:
        (total, {"depth", "smooth", "total"}).
    """
    pred = outputs[-1] if isinstance(outputs, (list, tuple)) else outputs
    gt = batch["gt"]
    t_d = depth_l1(pred, gt, gt > 0)
    t_s = normal_smoothness(pred, batch["K"], batch.get("rgb"), alpha)
    total = w_depth * t_d + w_smooth * t_s
    return total, _float_terms(("depth", t_d), ("smooth", t_s), ("total", total))
