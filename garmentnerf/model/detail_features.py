"""Reading a sample's detail feature f^d from the front and back detail maps F^d(c^fr), F^d(c^ba).

A sample's body point b_t is projected into each reference camera
(:func:`garmentnerf.conventions.project_points`) and the map is read there
(:func:`sample_image_features`). The two reads are merged by :func:`select_detail_features`:

``"visibility"`` (paper)
    The front read where b_t is visible from the front reference camera, else the back read
    (visibility comes from a depth or face-id pass of the body at that camera; the authors' code
    does the same and uses the back map for points seen by neither).
``"soft_normal"`` (authors' code)
    ``w = (cos + 1) / 2`` per camera, cos between the body normal at b_t and the direction from
    b_t to that camera; the pair (w_fr, w_ba) L2-normalised (so w_fr^2 + w_ba^2 = 1, not
    w_fr + w_ba = 1: their choice, kept for comparability) and the reads blended with it.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


def sample_image_features(feature_map: torch.Tensor, pixels: torch.Tensor, mode: str = "bilinear") -> torch.Tensor:
    """Read an image-space map at continuous pixel coordinates.

    Args:
        feature_map: (C, H, W).
        pixels: (N, 2) (u, v) pixel coordinates, centre of pixel (column c, row r) at (c, r)
            (:mod:`garmentnerf.conventions`).
        mode: ``"bilinear"`` or ``"nearest"`` (authors' code).
    Returns:
        (N, C); points outside the image read the border pixel.
    """
    C, H, W = feature_map.shape
    scale = torch.tensor([2.0 / W, 2.0 / H], dtype=feature_map.dtype, device=feature_map.device)
    grid = (pixels.to(feature_map.dtype) + 0.5) * scale - 1.0  # align_corners=False pixel edges at -1, 1
    out = F.grid_sample(feature_map.unsqueeze(0), grid.view(1, 1, -1, 2), mode=mode, padding_mode="border",
                        align_corners=False)
    return out[0, :, 0].T


def soft_normal_weights(cos_front: torch.Tensor, cos_back: torch.Tensor) -> torch.Tensor:
    """(N, 2) the ``soft_normal`` blend weights of the front and back reads: ``(cos + 1) / 2`` per
    reference camera, normalised to unit L2 norm (the authors' code); ``cos_*`` (N,)."""
    return F.normalize(torch.stack([cos_front, cos_back], dim=-1).add(1.0).mul(0.5), p=2, dim=-1)


def select_detail_features(front: torch.Tensor, back: torch.Tensor, mode: str = "visibility", *,
                           front_visible: torch.Tensor | None = None, cos_front: torch.Tensor | None = None,
                           cos_back: torch.Tensor | None = None) -> torch.Tensor:
    """Merge the front and back detail reads of N samples.

    Args:
        front, back: (N, D) reads of F^d(c^fr) and F^d(c^ba).
        mode: ``"visibility"`` (needs ``front_visible``) or ``"soft_normal"`` (needs ``cos_front``
            and ``cos_back``).
        front_visible: (N,) bool, b_t visible from the front reference camera.
        cos_front, cos_back: (N,) cosine between the body normal at b_t and the direction to each
            reference camera.
    Returns:
        (N, D) f^d.
    """
    if mode == "visibility":
        if front_visible is None:
            raise ValueError("detail selection 'visibility' needs front_visible")
        return torch.where(front_visible.unsqueeze(-1), front, back)
    if mode == "soft_normal":
        if cos_front is None or cos_back is None:
            raise ValueError("detail selection 'soft_normal' needs cos_front and cos_back")
        w = soft_normal_weights(cos_front, cos_back)
        return w[:, :1] * front + w[:, 1:] * back
    raise ValueError(f"unknown detail selection {mode!r} (known: 'visibility', 'soft_normal')")
