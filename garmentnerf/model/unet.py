"""The U-Net shared by the dynamic feature encoder E and the detail feature encoder G_en.

Paper, "Implementation details": conv3x3 to 32 channels, four stride-2 conv blocks to
64/128/256/512 (128 x 128 -> 8 x 8 for E; 512 -> 32 for G_en), four bilinear x2 upsamplings, each
followed by concatenation with the encoder feature of the same resolution and a conv3x3 back to
256/128/64/32, a last conv3x3 to the output channels and tanh. Instance normalisation and
LeakyReLU after every conv but the last.

Widths are ``round(base_width * width_scale) * 2**level``; ``depth`` is the number of stride-2
blocks, so ``UNet(..., width_scale=0.5, depth=3)`` is a cheaper network of the same shape.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from garmentnerf.model.config import DETAIL_FEATURE_DIM, DYNAMIC_FEATURE_DIM, UNET_BASE_WIDTH, UNET_DEPTH

#: pix2pix's slope; the paper only says "leakyReLU".
LEAKY_SLOPE = 0.2


def conv_norm_act(in_channels: int, out_channels: int, stride: int = 1) -> nn.Sequential:
    """conv3x3 -> InstanceNorm -> LeakyReLU(0.2)."""
    return nn.Sequential(
        # No conv bias: the instance norm removes any per-channel constant right after it.
        nn.Conv2d(in_channels, out_channels, 3, stride=stride, padding=1, bias=False),
        nn.InstanceNorm2d(out_channels, affine=True),
        nn.LeakyReLU(LEAKY_SLOPE, inplace=True),
    )


def unet_widths(base_width: int = 32, depth: int = 4, width_scale: float = 1.0) -> list[int]:
    """Encoder widths from the input conv to the bottleneck (paper: [32, 64, 128, 256, 512])."""
    base = max(1, round(base_width * width_scale))
    return [base * 2 ** level for level in range(depth + 1)]


class UNet(nn.Module):
    """U-Net with skip concatenation, ``(B, C_in, H, W) -> (B, C_out, H, W)`` in (-1, 1).

    Args:
        in_channels, out_channels: C_in, C_out.
        base_width: width of the first conv (paper: 32).
        depth: number of stride-2 blocks (paper: 4). H and W must be divisible by 2**depth.
        width_scale: multiplies every width.
        out_activation: ``"tanh"`` (paper), ``"sigmoid"`` (images in [0, 1]) or ``"none"``.
    """

    def __init__(self, in_channels: int, out_channels: int, base_width: int = 32, depth: int = 4,
                 width_scale: float = 1.0, out_activation: str = "tanh"):
        super().__init__()
        if depth < 1:
            raise ValueError(f"UNet depth must be >= 1, got {depth}")
        if out_activation not in ("tanh", "sigmoid", "none"):
            raise ValueError(f"UNet out_activation must be 'tanh', 'sigmoid' or 'none', got {out_activation!r}")
        self.depth = depth
        self.out_activation = out_activation
        self.widths = widths = unet_widths(base_width, depth, width_scale)
        self.stem = conv_norm_act(in_channels, widths[0])
        self.down = nn.ModuleList(conv_norm_act(widths[i], widths[i + 1], stride=2) for i in range(depth))
        # Up block i takes the upsampled level-(i+1) feature concatenated with the level-i skip.
        self.up = nn.ModuleList(conv_norm_act(widths[i + 1] + widths[i], widths[i]) for i in reversed(range(depth)))
        self.head = nn.Conv2d(widths[0], out_channels, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C_in, H, W) -> (B, C_out, H, W)."""
        if x.ndim != 4:
            raise ValueError(f"UNet input must be (B, C, H, W), got shape {tuple(x.shape)}")
        H, W = x.shape[-2:]
        step = 2 ** self.depth
        if H % step or W % step or H // step < 2 or W // step < 2:
            # InstanceNorm needs more than one value per channel at the bottleneck.
            raise ValueError(f"UNet input size {H}x{W} must be divisible by 2^depth = {step} "
                             f"with a bottleneck of at least 2x2")
        skips = [self.stem(x)]
        for block in self.down:
            skips.append(block(skips[-1]))
        y = skips.pop()
        for block in self.up:
            skip = skips.pop()
            y = F.interpolate(y, size=skip.shape[-2:], mode="bilinear", align_corners=False)
            y = block(torch.cat([y, skip], dim=1))
        y = self.head(y)
        if self.out_activation == "tanh":
            return torch.tanh(y)
        if self.out_activation == "sigmoid":
            return torch.sigmoid(y)
        return y


class DynamicFeatureEncoder(UNet):
    """E: info maps [N_t, V_t] ``(B, 3 (k + 1), R, R)`` -> dynamic feature map F^s_t ``(B, 8, R, R)``
    (``EncoderConfig.in_channels`` inputs)."""

    def __init__(self, in_channels: int = 9, out_channels: int = 8, base_width: int = 32, depth: int = 4,
                 width_scale: float = 1.0):
        super().__init__(in_channels, out_channels, base_width, depth, width_scale, "tanh")

    @classmethod
    def from_config(cls, cfg) -> "DynamicFeatureEncoder":
        return cls(cfg.encoder.in_channels, DYNAMIC_FEATURE_DIM, UNET_BASE_WIDTH, UNET_DEPTH, cfg.encoder.width_scale)


class DetailEncoder(UNet):
    """G_en: reference image ``(B, 3, S, S)`` in [0, 1] -> detail feature map F^d_t ``(B, 8, S, S)``."""

    def __init__(self, out_channels: int = 8, base_width: int = 32, depth: int = 4, width_scale: float = 1.0):
        super().__init__(3, out_channels, base_width, depth, width_scale, "tanh")

    @classmethod
    def from_config(cls, cfg) -> "DetailEncoder":
        return cls(DETAIL_FEATURE_DIM, UNET_BASE_WIDTH, UNET_DEPTH, cfg.encoder.width_scale)
