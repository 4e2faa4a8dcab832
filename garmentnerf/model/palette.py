"""Palette-based decomposition (paper Sec. 4.3, after PaletteNeRF): M_D, the palette, and the one
formula that turns the decomposed maps and a palette into an image.

M_D decodes the volume-rendered feature image F^zeta ``(B, 128, h, w)`` into maps at
``(4h, 4w)``: radiance r, per-color offsets o_i, per-color blend weights w_i and a mask m.
:func:`compose` then forms the image

    c = m * clamp(r * sum_i w_i (p_i + o_i), 0, 1) + (1 - m) * background

which for P = 2 (garment p_G, body/other p_B) and a black background is the paper's
``c = m r [w (p_G + o_G) + (1 - w)(p_B + o_B)]``.

One formula everywhere
    Training, rendering and recoloring all call :func:`compose`. The authors' code clips each
    palette term ``clip(r (p_i + o_i), 0, 1)`` before the weighted sum while training but clips
    after the sum when editing, so an edited image with the *original* palette differs from
    the trained one wherever a term leaves [0, 1]: recoloring would change pixels that should
    not change. Clamping once, after the sum, also keeps the formula linear in the palette
    inside [0, 1], so the change of a pixel under a new palette is exactly
    ``m r w_i (p_i' - p_i)`` (what the viewer's shader reproduces from the cached maps).

    The clamp's gradient is "restoring": zero only where it would push a value further out of
    [0, 1]. A plain clamp would give no gradient at all to a pixel stuck above 1 (softplus
    radiance is unbounded), so it could never come back.

The foreground is clamped, then alpha-composited: a convex combination of two colors in [0, 1]
needs no second clamp.

The hybrid composition (a rasterised body layer)
    With a body layer (``body_color``: the rasterised body's untinted colour ``a`` premultiplied by
    its coverage ``alpha_b``, :mod:`garmentnerf.render.body_layer`) the body is drawn, not decoded,
    and the network contributes the garment and its visibility only. The body is the palette's
    last color p_B (garment first, as :func:`palette_from_labels`); the garment is the rest:

        m_G = m (1 - w_B)                                   (the garment's visibility)
        c_G = clamp(r * sum_{i != B} w_i (p_i + o_i) / (1 - w_B), 0, 1)
        c   = m_G c_G + (1 - m_G) (clamp(p_B a, 0, 1) + (1 - alpha_b) background)

    which for P = 2 is ``c_G = clamp(r (p_G + o_G))``. A forearm in front of the skirt has a low
    garment weight (the NeRF's body density occludes the garment there), so the rasterised
    forearm shows; the skirt in front of the legs has m_G ~ 1 and hides them. Still linear in
    every palette color inside [0, 1], so recoloring stays exact.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from garmentnerf.model.config import BACKGROUND, BLEND_WEIGHT_FLOOR, OFFSET_SCALE

#: Makes softplus(0 + shift) = 1: the untrained radiance is 1, so the image starts at the palette.
_SOFTPLUS_ONE = math.log(math.e - 1.0)


class _RestoringClamp(torch.autograd.Function):
    """clamp(x, 0, 1) whose gradient passes wherever a descent step moves x towards [0, 1]."""

    @staticmethod
    def forward(ctx, x):
        ctx.save_for_backward(x)
        return x.clamp(0.0, 1.0)

    @staticmethod
    def backward(ctx, grad):
        (x,) = ctx.saved_tensors
        # Gradient descent moves x by -grad: above 1 that must decrease x (grad > 0), below 0
        # increase it (grad < 0).
        keep = ((x >= 0) & (x <= 1)) | ((x > 1) & (grad > 0)) | ((x < 0) & (grad < 0))
        return grad * keep


def restoring_clamp(x: torch.Tensor) -> torch.Tensor:
    """clamp(x, 0, 1) with a gradient that can bring out-of-range values back."""
    return _RestoringClamp.apply(x)


#: Smallest slope :func:`restoring_sigmoid` passes back towards the sigmoid's sensitive region.
RESTORING_SIGMOID_FLOOR = 0.02


class _RestoringSigmoid(torch.autograd.Function):
    """sigmoid(x) whose backward slope is at least ``floor`` where descent moves x towards 0."""

    @staticmethod
    def forward(ctx, x, floor):
        y = torch.sigmoid(x)
        ctx.save_for_backward(x, y)
        ctx.floor = floor
        return y

    @staticmethod
    def backward(ctx, grad):
        x, y = ctx.saved_tensors
        slope = y * (1.0 - y)
        # Descent moves x by -grad: towards 0 from below when grad < 0, from above when grad > 0.
        restoring = ((x < 0) & (grad < 0)) | ((x > 0) & (grad > 0))
        slope = torch.where(restoring, slope.clamp_min(ctx.floor), slope)
        return grad * slope, None


def restoring_sigmoid(x: torch.Tensor, floor: float = RESTORING_SIGMOID_FLOOR) -> torch.Tensor:
    """sigmoid(x), except that a saturated unit the loss wants back still gets a gradient.

    Why: with an L1 mask loss on mostly-background images the cheapest early descent is to push
    every mask logit far below 0; the plain sigmoid's slope there (~1e-7 at x = -16) then starves
    the foreground pixels, the features that feed the mask get no gradient, and training stays
    at an all-black image. Here a foreground pixel at x = -16 is pulled up with slope ``floor``,
    while a background pixel is never pushed further into saturation faster than the plain
    sigmoid would (no drift of the logits to -inf).
    """
    return _RestoringSigmoid.apply(x, float(floor))


def check_palette(palette: torch.Tensor) -> None:
    """Raise ValueError unless ``palette`` is (P, 3), finite and in [0, 1]."""
    if palette.ndim != 2 or palette.shape[-1] != 3:
        raise ValueError(f"palette must be (P, 3), got shape {tuple(palette.shape)}")
    if not bool(torch.isfinite(palette).all()):
        raise ValueError("palette contains NaN or Inf")
    if bool((palette < 0).any()) or bool((palette > 1).any()):
        raise ValueError(f"palette colors must lie in [0, 1], got min {float(palette.min()):.4g} "
                         f"max {float(palette.max()):.4g}")


def compose(radiance: torch.Tensor, offsets: torch.Tensor, weights: torch.Tensor, mask: torch.Tensor,
            palette: torch.Tensor, background: torch.Tensor | tuple[float, float, float] = (0.0, 0.0, 0.0),
            body_color: torch.Tensor | None = None, body_coverage: torch.Tensor | None = None) -> torch.Tensor:
    """The image from decomposed maps and a palette (see the module docstring).

    Args:
        radiance: (B, 3, H, W) or (B, 1, H, W) r >= 0 (grey radiance broadcasts over RGB).
        offsets: (B, P, 3, H, W) o_i.
        weights: (B, P, H, W) w_i >= 0 summing to 1 over P.
        mask: (B, 1, H, W) m in [0, 1].
        palette: (P, 3) p_i in [0, 1].
        background: RGB in [0, 1], tuple or (3,) tensor.
        body_color, body_coverage: (B, 3, H, W) and (B, 1, H, W), the rasterised body layer of the
            hybrid composition (module docstring); None: the network draws the body.
    Returns:
        (B, 3, H, W) image in [0, 1].
    Raises:
        ValueError on a palette outside [0, 1] or mismatched shapes.
    """
    check_palette(palette)
    B, P = weights.shape[:2]
    if P != palette.shape[0] or offsets.shape[:3] != (B, P, 3):
        raise ValueError(f"palette ({palette.shape[0]} colors), offsets {tuple(offsets.shape)} and weights "
                         f"{tuple(weights.shape)} disagree on the palette size")
    bg = torch.as_tensor(background, dtype=radiance.dtype, device=radiance.device)
    if bg.shape != (3,) or bool((bg < 0).any()) or bool((bg > 1).any()):
        raise ValueError(f"background must be 3 values in [0, 1], got {background}")
    colors = palette.to(radiance.dtype)[None, :, :, None, None] + offsets  # (B, P, 3, H, W)
    if (body_color is None) != (body_coverage is None):
        raise ValueError("give both body_color and body_coverage, or neither")
    if body_color is None:
        base = (weights.unsqueeze(2) * colors).sum(dim=1)  # (B, 3, H, W)
        foreground = restoring_clamp(radiance * base)
        return mask * foreground + (1.0 - mask) * bg.view(1, 3, 1, 1)
    if P < 2:
        raise ValueError("the hybrid composition needs a garment and a body palette color (P >= 2)")
    if body_color.shape != (B, 3, *mask.shape[-2:]) or body_coverage.shape != mask.shape:
        raise ValueError(f"body layer {tuple(body_color.shape)} / {tuple(body_coverage.shape)} does not match "
                         f"the maps {tuple(mask.shape)}")
    garment_share = 1.0 - weights[:, -1:]  # (B, 1, H, W)
    garment_base = (weights[:, :-1].unsqueeze(2) * colors[:, :-1]).sum(dim=1) / garment_share.clamp_min(1e-6)
    garment = restoring_clamp(radiance * garment_base)
    visible = mask * garment_share
    body = restoring_clamp(palette.to(radiance.dtype)[-1].view(1, 3, 1, 1) * body_color)
    behind = body + (1.0 - body_coverage) * bg.view(1, 3, 1, 1)
    return visible * garment + (1.0 - visible) * behind


def composite_alpha(mask: torch.Tensor, weights: torch.Tensor, body_coverage: torch.Tensor | None = None) -> torch.Tensor:
    """(B, 1, H, W) how much of each pixel :func:`compose` takes from the character rather than
    the background: ``m`` alone, or ``m_G + (1 - m_G) alpha_b`` with a body layer."""
    if body_coverage is None:
        return mask
    visible = mask * (1.0 - weights[:, -1:])
    return visible + (1.0 - visible) * body_coverage


@dataclass
class DecomposedMaps:
    """Output of M_D; cache it to recolor without re-running any network.

    Attributes:
        radiance: (B, 3 or 1, H, W) r >= 0.
        offsets: (B, P, 3, H, W) o_i.
        weights: (B, P, H, W) w_i, summing to 1 over P.
        mask: (B, 1, H, W) m in (0, 1).
        weights_head_only: (B, P, H, W) the same values as ``weights`` whose gradient reaches only
            the decoder's weight head, not the layers shared with the mask and radiance (set by
            :class:`PaletteDecoder` in training; what the label supervision of the weights uses).
        body_color: (B, 3, H, W) the rasterised body layer of the hybrid composition (untinted,
            premultiplied by coverage), or None when the network draws the body.
        body_coverage: (B, 1, H, W) its coverage, or None.
    """

    radiance: torch.Tensor
    offsets: torch.Tensor
    weights: torch.Tensor
    mask: torch.Tensor
    weights_head_only: torch.Tensor | None = None
    body_color: torch.Tensor | None = None
    body_coverage: torch.Tensor | None = None

    def compose(self, palette: torch.Tensor, background=BACKGROUND) -> torch.Tensor:
        """:func:`compose` with these maps (and their body layer, when they have one)."""
        return compose(self.radiance, self.offsets, self.weights, self.mask, palette, background,
                       self.body_color, self.body_coverage)

    @property
    def alpha(self) -> torch.Tensor:
        """(B, 1, H, W) :func:`composite_alpha`: the character's coverage in the composed image."""
        return composite_alpha(self.mask, self.weights, self.body_coverage)

    def _map(self, fn) -> "DecomposedMaps":
        """These maps with ``fn`` applied to every map and to the body layer (the head-only weights,
        a training-time view, are dropped)."""
        body = (None, None) if self.body_color is None else (fn(self.body_color), fn(self.body_coverage))
        return DecomposedMaps(fn(self.radiance), fn(self.offsets), fn(self.weights), fn(self.mask), None, *body)

    def with_body(self, color: torch.Tensor | None, coverage: torch.Tensor | None) -> "DecomposedMaps":
        """These maps with the body layer ``color`` (B, 3, H, W), ``coverage`` (B, 1, H, W)
        (None, None: without one)."""
        return DecomposedMaps(self.radiance, self.offsets, self.weights, self.mask, self.weights_head_only,
                              color, coverage)

    def detach(self) -> "DecomposedMaps":
        return self._map(torch.Tensor.detach)

    def to(self, *args, **kwargs) -> "DecomposedMaps":
        """Every map through ``Tensor.to(*args, **kwargs)``, made contiguous."""
        return self._map(lambda x: x.to(*args, **kwargs).contiguous())

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) of the maps."""
        return int(self.mask.shape[-1]), int(self.mask.shape[-2])

    def cropped(self, width: int, height: int) -> "DecomposedMaps":
        """The top-left ``width x height`` of every map (undoes padding on the right and bottom)."""
        return self._map(lambda x: x[..., :height, :width])

    def placed(self, x0: int, y0: int, width: int, height: int) -> "DecomposedMaps":
        """These maps put at ``(x0, y0)`` in maps of ``width x height`` that are empty elsewhere
        (mask 0, so :func:`compose` gives the background there; radiance and offsets 0, weights
        uniform; body coverage 0)."""
        h, w = self.mask.shape[-2:]
        if (x0, y0, w, h) == (0, 0, int(width), int(height)):
            return self

        def canvas(x, fill):
            out = x.new_full((*x.shape[:-2], int(height), int(width)), fill)
            out[..., y0:y0 + h, x0:x0 + w] = x
            return out

        P = self.weights.shape[1]
        body = (None, None) if self.body_color is None else (canvas(self.body_color, 0.0),
                                                               canvas(self.body_coverage, 0.0))
        return DecomposedMaps(canvas(self.radiance, 0.0), canvas(self.offsets, 0.0), canvas(self.weights, 1.0 / P),
                              canvas(self.mask, 0.0), None, *body)

    def resized(self, width: int, height: int) -> "DecomposedMaps":
        """Every map resampled to ``width x height``: averaged over each output pixel's area when
        both sides shrink (``F.interpolate``'s ``area``: for an integer factor, the box filter the
        ground truth's supersampled pixels are made with, :mod:`garmentnerf.data.render_gt`),
        bilinear otherwise (antialiased along a side that shrinks). Either is a convex
        combination, so the weights still sum to 1 after renormalising, the mask and coverage stay
        in [0, 1] and the radiance >= 0. The maps themselves when the size is already that.

        Why area: the antialiased bilinear filter spreads an output pixel over twice its width, a
        blur the truth does not have. The bundled skirt rendered at its trained density and shown at
        half (24 unseen views) scores 0.15 dB more foreground and 2.4 more body averaged by area
        than by that filter (``docs/lab/ledger.md``, "Rendering above the trained density, and shown
        smaller than rendered")."""
        if (int(width), int(height)) == self.size:
            return self
        w0, h0 = self.size
        shrink = int(width) <= w0 and int(height) <= h0

        def rs(x):
            shape = x.shape
            flat = x.reshape(shape[0], -1, shape[-2], shape[-1])
            if shrink:
                out = F.interpolate(flat, size=(int(height), int(width)), mode="area")
            else:
                out = F.interpolate(flat, size=(int(height), int(width)), mode="bilinear", align_corners=False,
                                    antialias=True)
            return out.reshape(*shape[:-2], int(height), int(width))

        weights = rs(self.weights)
        weights = weights / weights.sum(dim=1, keepdim=True)  # antialias filters are not exactly convex
        body = (None, None) if self.body_color is None else (rs(self.body_color).clamp_min(0.0),
                                                               rs(self.body_coverage).clamp(0.0, 1.0))
        return DecomposedMaps(rs(self.radiance).clamp_min(0.0), rs(self.offsets), weights,
                              rs(self.mask).clamp(0.0, 1.0), None, *body)


class PaletteDecoder(nn.Module):
    """M_D: feature image ``(B, C, h, w)`` -> :class:`DecomposedMaps` at ``(h, w) * 2**upsample_steps``.

    Layers: [nearest x2 -> conv3x3 -> LeakyReLU(0.2)] x
    upsample_steps (widths ``width``, ``width/2``, ... floored at ``min_width``), then
    ``extra_layers`` conv3x3 + LeakyReLU at full resolution, then a conv3x3 to the raw heads.

    Heads:
        radiance: softplus shifted so raw 0 -> 1 (it can exceed 1 where the pixel is brighter
            than its palette color, which a sigmoid could not).
        offsets: ``offset_scale * tanh``.
        weights: ``softplus + weight_floor``, normalised to sum 1 over the palette.
        mask: sigmoid.

    Args:
        in_channels: C (paper: 128).
        palette_size: P (paper: 2).
        width, min_width, upsample_steps, extra_layers: the conv stack.
        radiance_channels: 3 (paper) or 1.
        offset_scale, weight_floor: see the heads.
        head_only_weights: in training, also return the weights through the weight head alone
            (``DecomposedMaps.weights_head_only``, for the label supervision of the weights).
    """

    def __init__(self, in_channels: int = 128, palette_size: int = 2, width: int = 64, min_width: int = 32,
                 upsample_steps: int = 2, extra_layers: int = 2, radiance_channels: int = 3,
                 offset_scale: float = OFFSET_SCALE, weight_floor: float = BLEND_WEIGHT_FLOOR,
                 head_only_weights: bool = False):
        super().__init__()
        if radiance_channels not in (1, 3):
            raise ValueError(f"radiance_channels must be 1 or 3, got {radiance_channels}")
        self.palette_size = palette_size
        self.radiance_channels = radiance_channels
        self.offset_scale = offset_scale
        self.weight_floor = weight_floor
        self.head_only_weights = bool(head_only_weights)
        self.upsample_steps = upsample_steps
        layers: list[nn.Module] = []
        c = in_channels
        for step in range(upsample_steps):
            out = max(width // 2 ** step, min_width)
            layers += [nn.Upsample(scale_factor=2, mode="nearest"), nn.Conv2d(c, out, 3, padding=1),
                       nn.LeakyReLU(0.2, inplace=True)]
            c = out
        for _ in range(extra_layers):
            layers += [nn.Conv2d(c, c, 3, padding=1), nn.LeakyReLU(0.2, inplace=True)]
        self.body = nn.Sequential(*layers)
        self.head = nn.Conv2d(c, radiance_channels + 4 * palette_size + 1, 3, padding=1)

    @classmethod
    def from_config(cls, cfg) -> "PaletteDecoder":
        return cls(cfg.nerf.zeta_channels, cfg.decoder.palette_size, cfg.decoder.width, cfg.decoder.min_width,
                   cfg.decoder.upsample_steps, cfg.decoder.extra_layers, cfg.decoder.radiance_channels,
                   head_only_weights=cfg.loss.segmentation > 0 and cfg.loss.segmentation_head_only)

    def forward(self, features: torch.Tensor) -> DecomposedMaps:
        """(B, C, h, w) -> maps at (B, ., 4h, 4w) for two upsampling steps."""
        trunk = self.body(features)
        raw = self.head(trunk)
        B, _, H, W = raw.shape
        P, Cr = self.palette_size, self.radiance_channels
        rows = palette_head_rows(Cr, P)
        r_raw, o_raw, w_raw, m_raw = torch.split(raw, [len(r) for r in rows.values()], dim=1)
        radiance = F.softplus(r_raw + _SOFTPLUS_ONE)
        offsets = self.offset_scale * torch.tanh(o_raw).view(B, P, 3, H, W)
        head_only = None
        if self.head_only_weights and self.training and torch.is_grad_enabled():
            weight_rows = slice(rows["weights"].start, rows["weights"].stop)
            head_only = self._normalised_weights(F.conv2d(trunk.detach(), self.head.weight[weight_rows],
                                                          self.head.bias[weight_rows], padding=self.head.padding))
        return DecomposedMaps(radiance, offsets, self._normalised_weights(w_raw), restoring_sigmoid(m_raw), head_only)

    def _normalised_weights(self, w_raw: torch.Tensor) -> torch.Tensor:
        w = F.softplus(w_raw) + self.weight_floor
        return w / w.sum(dim=1, keepdim=True)


def palette_head_rows(radiance_channels: int, palette_size: int) -> dict[str, range]:
    """Rows of :class:`PaletteDecoder`'s raw head output, in order: ``radiance`` (``radiance_channels``),
    ``offsets`` (3 per colour, colour-major: colour c's at 3c, 3c + 1, 3c + 2), ``weights`` (one per
    colour) and ``mask`` (1)."""
    rows, start = {}, 0
    for name, count in (("radiance", radiance_channels), ("offsets", 3 * palette_size), ("weights", palette_size),
                        ("mask", 1)):
        rows[name] = range(start, start + count)
        start += count
    return rows


def palette_names(palette_size: int) -> list[str]:
    """What each palette color paints, in palette order: the garment's color (or one per layer of a
    layered garment, inner first), then the body's (always the last)."""
    if palette_size < 2:
        return ["Garment"][:palette_size]
    if palette_size == 2:
        return ["Garment", "Body / other"]
    layers = palette_size - 1
    return ([f"Garment layer {k + 1}" + (" (inner)" if k == 0 else " (outer)" if k == layers - 1 else "")
             for k in range(layers)] + ["Body / other"])


class Palette(nn.Module):
    """The learnable palette p ``(P, 3)`` and its initialisation p* (kept for L_p).

    The parameter may drift outside [0, 1] under gradient descent; :meth:`forward` clamps it so
    :func:`compose` always receives a valid palette, and L_p pulls it back towards p*.
    """

    def __init__(self, initial: torch.Tensor, learnable: bool = True):
        super().__init__()
        check_palette(initial)
        self.register_buffer("initial", initial.detach().clone().float())
        self.colors = nn.Parameter(initial.detach().clone().float(), requires_grad=learnable)

    def forward(self) -> torch.Tensor:
        """(P, 3) palette in [0, 1]."""
        return self.colors.clamp(0.0, 1.0)


def palette_from_labels(images: torch.Tensor, labels: torch.Tensor, classes=(2, 1)) -> torch.Tensor:
    """Mean color of each labelled region, the paper's p* (garment first, then body).

    Args:
        images: (N, 3, H, W) or (N, H, W, 3) RGB in [0, 1] (read as channels-first whenever
            dimension 1 has size 3).
        labels: (N, H, W) integer label maps (ground-truth renders: 0 background, 1 body,
            2 garment).
        classes: label value of each palette color, in palette order.
    Returns:
        (len(classes), 3) palette.
    Raises:
        ValueError if a class has no pixel.
    """
    if images.shape[-1] == 3 and images.shape[1] != 3:
        images = images.permute(0, 3, 1, 2)
    pixels = images.permute(0, 2, 3, 1).reshape(-1, 3).float()
    flat = labels.reshape(-1)
    out = []
    for c in classes:
        sel = flat == c
        if not bool(sel.any()):
            raise ValueError(f"no pixel has label {c}; cannot initialise its palette color")
        out.append(pixels[sel].mean(dim=0))
    return torch.stack(out).clamp(0.0, 1.0)
