"""G_img: the reference-image generator (paper Sec. 4.2, after DNG), pre-trained then frozen.

A learnable neural texture on the body's UV atlas is read at the per-pixel body UVs of a
reference camera (front or back), giving the neural image Q_t; an encoder-decoder turns Q_t into
the reference image I^_t(c) in [0, 1].

Neural texture (DNG / Deferred Neural Rendering)
    ``levels`` textures of ``channels`` channels at resolutions ``R, R/2, ..., R/2^(levels-1)``
    (DNG: 4 x 16 channels at 512/256/128/64). Q_t is the *sum* of the bilinear reads of all
    levels: coarse levels give every texel a gradient even where the fine level is rarely seen,
    which is the purpose of the pyramid. Pixels outside the body mask get 0.

Generator
    The project's U-Net (``model/unet.py``) with a sigmoid output; the body mask is appended to
    Q_t as one extra input channel so that "no body" is never confused with a texture that
    happens to be 0.

Left out on purpose: DNG's SPADE block conditioned on the previous frame and its patch-GAN and
feature-matching losses. L1 plus a perceptual loss (``model/losses.py``) train this generator;
the adversarial terms sharpen textures but need a discriminator, a second optimiser and far
more iterations than a CPU budget allows.

UV layout: as :mod:`garmentnerf.gl.uv_raster` (row 0 of a texture is v = 0), read with
``grid_sample(align_corners=False)`` at ``2 uv - 1``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from garmentnerf.model.config import NEURAL_TEXTURE_CHANNELS, NEURAL_TEXTURE_LEVELS, UNET_BASE_WIDTH, UNET_DEPTH
from garmentnerf.model.unet import UNet


class NeuralTexture(nn.Module):
    """Multi-resolution learnable texture.

    Args:
        channels: channels per level (DNG: 16).
        levels: number of levels (DNG: 4).
        resolution: side of the finest level (DNG: 512); level l has side ``resolution / 2**l``.
        init_std: standard deviation of the random initialisation.
    """

    def __init__(self, channels: int = 16, levels: int = 4, resolution: int = 512, init_std: float = 0.01):
        super().__init__()
        if resolution // 2 ** (levels - 1) < 1:
            raise ValueError(f"NeuralTexture: {levels} levels do not fit a {resolution} texture")
        self.channels = channels
        self.textures = nn.ParameterList(
            nn.Parameter(init_std * torch.randn(1, channels, resolution // 2 ** l, resolution // 2 ** l))
            for l in range(levels))

    def forward(self, uv: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        """Render the neural image Q_t.

        Args:
            uv: (B, H, W, 2) atlas coordinates of the body point seen at each pixel, in [0, 1].
            mask: (B, H, W) bool or {0, 1}, pixels that see the body; None: all.
        Returns:
            (B, C, H, W) summed bilinear reads of all levels, 0 outside the mask.
        """
        if uv.ndim != 4 or uv.shape[-1] != 2:
            raise ValueError(f"uv must be (B, H, W, 2), got shape {tuple(uv.shape)}")
        grid = uv.to(self.textures[0].dtype) * 2.0 - 1.0
        B = uv.shape[0]
        out = 0.0
        for tex in self.textures:
            out = out + F.grid_sample(tex.expand(B, -1, -1, -1), grid, mode="bilinear", padding_mode="border",
                                      align_corners=False)
        if mask is not None:
            out = out * mask.to(out.dtype).unsqueeze(1)
        return out


class ImageGenerator(nn.Module):
    """G_img: body UVs at a reference camera -> reference image ``(B, 3, H, W)`` in [0, 1].

    Args:
        texture_channels, texture_levels, texture_resolution: the :class:`NeuralTexture`.
        base_width, depth, width_scale: the encoder-decoder (a :class:`UNet`).
    """

    def __init__(self, texture_channels: int = 16, texture_levels: int = 4, texture_resolution: int = 512,
                 base_width: int = 32, depth: int = 4, width_scale: float = 1.0):
        super().__init__()
        self.texture = NeuralTexture(texture_channels, texture_levels, texture_resolution)
        self.generator = UNet(texture_channels + 1, 3, base_width, depth, width_scale, out_activation="sigmoid")

    @classmethod
    def from_config(cls, cfg) -> "ImageGenerator":
        return cls(NEURAL_TEXTURE_CHANNELS, NEURAL_TEXTURE_LEVELS, cfg.encoder.neural_texture_resolution,
                   UNET_BASE_WIDTH, UNET_DEPTH, cfg.encoder.width_scale)

    def neural_image(self, uv: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """Q_t ``(B, C, H, W)`` from uv (B, H, W, 2) and mask (B, H, W)."""
        return self.texture(uv, mask)

    def forward(self, uv: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """Reference image ``(B, 3, H, W)`` in [0, 1] from uv (B, H, W, 2) and mask (B, H, W)."""
        q = self.texture(uv, mask)
        return self.generator(torch.cat([q, mask.to(q.dtype).unsqueeze(1)], dim=1))

    def freeze(self) -> "ImageGenerator":
        """Stop training G_img (after pre-training): no gradients, eval mode. Returns self."""
        freeze(self)
        return self


def freeze(module: nn.Module) -> nn.Module:
    """Turn off gradients of every parameter of ``module`` and put it in eval mode; returns it.

    ``train()`` on a parent would switch the module back to train mode, which only matters for
    layers that behave differently (none here: instance norm keeps no running statistics).
    """
    for p in module.parameters():
        p.requires_grad_(False)
    return module.eval()
