"""Training losses (paper Sec. 4.4) of the NeRF (:func:`garment_losses`) and of G_img's
pre-training (:func:`generator_losses`).

The NeRF's:

    L = lambda_1 L_img + lambda_2 L_vgg + lambda_3 L_sp + lambda_4 L_off + lambda_5 L_p

with L_img = |I - I*|_1 + |M - M*|_1 (the two parts weighted separately here, both 1 in the
paper), L_sp the blend-weight sparsity, L_off = |O|^2, L_p = |p - p*|^2 and lambda = (1, 0.1,
2e-4, 0.03, 1e-3). Plain L1 as in the paper (the authors' code uses a pseudo-Huber).

Normalisation: L1 terms are means over all elements; L_sp and L_off are per-pixel values
(summed over palette colors and channels) averaged over pixels, as in PaletteNeRF whose weights
the paper adopts; L_p is the sum over the palette's 3P values.

Two terms are not in the paper (weight 0 gives its objective; the cpu_small preset turns both
on, see :class:`~garmentnerf.model.config.LossConfig`): ``opacity`` holds the feature rays'
opacity to the ground-truth mask, ``segmentation`` holds the garment blend weight to the label
maps' garment share.

G_img's pre-training (DNG's recipe, without its adversarial terms): ``image L1 + perceptual
perceptual`` between the generated and the ground-truth reference images.

The perceptual network is not defined here: pass any ``callable(pred, target) -> scalar`` (for
example a VGG or shift-tolerant LPIPS module). Without one the ``perceptual`` term is absent
from the result (not replaced by anything).
"""

from __future__ import annotations

from typing import Callable

import torch
import torch.nn.functional as F

from garmentnerf.model.config import LossConfig
from garmentnerf.model.palette import DecomposedMaps


def l1(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean absolute error over all elements."""
    return (pred - target).abs().mean()


def sparsity_loss(weights: torch.Tensor) -> torch.Tensor:
    """Blend-weight sparsity ``mean(1 / sum_i w_i^2 - 1)`` over pixels; weights (B, P, H, W).

    For P = 2 with w_B = 1 - w_G this is the paper's ``1 / (w^2 + (1 - w)^2) - 1``. In general
    1 / sum w_i^2 is the effective number of colors a pixel mixes (1 for a one-hot pixel, P
    for a uniform mix), so the loss is 0 exactly at one-hot weights and at most P - 1.
    """
    return (1.0 / weights.square().sum(dim=1) - 1.0).mean()


def offset_loss(offsets: torch.Tensor) -> torch.Tensor:
    """``mean over pixels of sum_i |o_i|^2``; offsets (B, P, 3, H, W)."""
    return offsets.square().sum(dim=(1, 2)).mean()


def palette_loss(palette: torch.Tensor, initial: torch.Tensor) -> torch.Tensor:
    """``|p - p*|^2`` summed over the (P, 3) palette values."""
    return (palette - initial).square().sum()


def opacity_loss(opacity: torch.Tensor, target_mask: torch.Tensor) -> torch.Tensor:
    """L1 between opacity (B, h, w) and the mask (B, 1, H, W) area-averaged to (h, w)."""
    if target_mask.ndim == 3:
        target_mask = target_mask.unsqueeze(1)
    if opacity.ndim == 2:
        opacity = opacity.unsqueeze(0)
    target = F.adaptive_avg_pool2d(target_mask.to(opacity.dtype), tuple(opacity.shape[-2:]))[:, 0]
    return (opacity - target).abs().mean()


def segmentation_loss(weights: torch.Tensor, target_garment: torch.Tensor, target_mask: torch.Tensor,
                      eps: float = 1e-3) -> torch.Tensor:
    """Total-variation distance between each foreground pixel's blend weights and its label shares.

    Args:
        weights: (B, P, H, W) blend weights; colors 0..K-1 are the garment's (its layers), the last
            the body's.
        target_garment: (B, K, H, W) ground-truth coverage in [0, 1] of each garment layer (K = 1:
            the whole garment), K < P.
        target_mask: (B, 1, H, W) ground-truth foreground (body + garment) coverage in [0, 1].
    Returns:
        ``sum(m* TV(w, t)) / sum(m*)`` with ``TV(w, t) = sum_p |w_p - t_p| / 2`` and the target
        ``t = (g_0*/m*, ..., g_{K-1}*/m*, 0, ..., 1 - sum_k g_k*/m*)`` (the body's share last):
        background pixels, whose weights compose to nothing, carry no weight; a border pixel half
        garment, half body asks for w_G = 0.5. For P = 2 it is ``|w_G - g*/m*|``. Every color is
        held, the body's too: a head that cannot tell two layers apart gains nothing by moving a
        layer pixel's weight to the body (with the layers alone held, it would: the dress's first
        model leaked a quarter of its garment weight to the body that way, docs/lab/ledger.md).
    """
    B, P, H, W = weights.shape
    K = target_garment.shape[1]
    if K >= P:
        raise ValueError(f"{K} garment layer targets need a palette of more than {K} colors, got {P}")
    share = (target_garment / target_mask.clamp_min(eps)).clamp(0.0, 1.0)
    body = (1.0 - share.sum(dim=1, keepdim=True)).clamp_min(0.0)
    target = torch.cat([share, share.new_zeros(B, P - K - 1, H, W), body], dim=1)
    per_pixel = 0.5 * (weights - target).abs().sum(dim=1, keepdim=True) * target_mask
    return per_pixel.sum() / target_mask.sum().clamp_min(eps)


def garment_losses(image: torch.Tensor, target_image: torch.Tensor, maps: DecomposedMaps,
                   target_mask: torch.Tensor, palette: torch.Tensor, palette_initial: torch.Tensor,
                   weights: LossConfig, perceptual: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None,
                   opacity: torch.Tensor | None = None,
                   target_garment: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """All loss terms of one batch.

    Args:
        image: (B, 3, H, W) composed prediction (:func:`~garmentnerf.model.palette.compose`).
        target_image: (B, 3, H, W) ground truth on the same background.
        maps: the decoder's maps (mask, weights, offsets are regularised).
        target_mask: (B, 1, H, W) or (B, H, W) ground-truth mask of body + garment in {0, 1}.
        palette: (P, 3) the palette *parameter* (unclamped, so L_p can pull it back into range).
        palette_initial: (P, 3) p*.
        weights: the terms' weights.
        perceptual: optional ``(pred, target) -> scalar``; its term is left out when None. It sees both
            images area-averaged by ``weights.perceptual_downsample`` (when > 1).
        opacity: optional (B, h, w) accumulated opacity of the feature rays; with ``weights.opacity``
            > 0 it is held to the target mask area-averaged to (h, w) (:func:`opacity_loss`).
        target_garment: optional (B, K, H, W) or (B, H, W) ground-truth coverage of the garment (K = 1)
            or of each of its layers; with ``weights.segmentation`` > 0 the garment blend weights are held
            to it (:func:`segmentation_loss`), through the weight head alone when
            ``weights.segmentation_head_only`` and the maps carry ``weights_head_only``.
    Returns:
        dict of the unweighted terms ``image, mask, [perceptual,] sparsity, offset, palette, [opacity,]
        [segmentation]`` and ``total``, the weighted sum.
    """
    if target_mask.ndim == 3:
        target_mask = target_mask.unsqueeze(1)
    terms = {
        "image": l1(image, target_image),
        "mask": l1(maps.mask, target_mask.to(maps.mask.dtype)),
    }
    if perceptual is not None:
        factor = int(weights.perceptual_downsample)
        if factor > 1:
            terms["perceptual"] = perceptual(F.avg_pool2d(image, factor), F.avg_pool2d(target_image, factor))
        else:
            terms["perceptual"] = perceptual(image, target_image)
    terms["sparsity"] = sparsity_loss(maps.weights)
    terms["offset"] = offset_loss(maps.offsets)
    terms["palette"] = palette_loss(palette, palette_initial)
    if opacity is not None and weights.opacity > 0:
        terms["opacity"] = opacity_loss(opacity, target_mask)
    if target_garment is not None and weights.segmentation > 0:
        if target_garment.ndim == 3:
            target_garment = target_garment.unsqueeze(1)
        head_only = weights.segmentation_head_only and maps.weights_head_only is not None
        supervised = maps.weights_head_only if head_only else maps.weights
        terms["segmentation"] = segmentation_loss(supervised, target_garment.to(maps.weights.dtype),
                                                  target_mask.to(maps.weights.dtype))
    terms["total"] = sum(getattr(weights, name) * value for name, value in terms.items())
    return terms


def generator_losses(pred: torch.Tensor, target: torch.Tensor, weights: LossConfig,
                     perceptual: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None
                     ) -> dict[str, torch.Tensor]:
    """The loss terms of one G_img pre-training step.

    Args:
        pred: (B, 3, H, W) G_img's reference images (front and back: B = 2).
        target: (B, 3, H, W) the ground-truth reference images.
        weights: the terms' weights (``image`` and ``perceptual``).
        perceptual: optional ``(pred, target) -> scalar``; its term is left out when None.
    Returns:
        dict of the unweighted terms ``image, [perceptual]`` and ``total``, the weighted sum.
    """
    terms = {"image": l1(pred, target)}
    total = weights.image * terms["image"]
    if perceptual is not None:
        terms["perceptual"] = perceptual(pred, target)
        total = total + weights.perceptual * terms["perceptual"]
    terms["total"] = total
    return terms
