"""Gutter filling for UV-space maps: each empty texel near a chart takes its nearest covered texel.

Bilinear lookups near a UV seam read texels whose centres lie outside the chart; without filling,
they would pull values towards the background. The nearest covered texel of every empty texel is
found once per (coverage mask, radius) with a Euclidean distance transform, so filling a frame is a
single gather.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy import ndimage


class NearestTexelDilation:
    """Precomputed nearest-covered-texel fill for one coverage mask.

    Args:
        mask: (H, W) bool, True where a texel is covered.
        radius: empty texels whose Euclidean distance (in texels, centre to centre) to the nearest
            covered texel is <= radius are filled; farther ones are left as they are.

    Attributes:
        mask: (H, W) bool tensor, the coverage given.
        fill_mask: (H, W) bool tensor, the empty texels that get filled.
        dst, src: (G,) int64 flat texel indices: texel ``dst[i]`` takes the value of ``src[i]``.
    """

    def __init__(self, mask: np.ndarray | torch.Tensor, radius: float = 4.0) -> None:
        mask_np = mask.cpu().numpy() if isinstance(mask, torch.Tensor) else np.asarray(mask)
        mask_np = mask_np.astype(bool)
        if mask_np.ndim != 2:
            raise ValueError(f"mask must be (H, W), got shape {mask_np.shape}")
        if radius < 0:
            raise ValueError(f"dilation radius must be >= 0, got {radius}")
        self.height, self.width = mask_np.shape
        self.radius = float(radius)
        self.mask = torch.from_numpy(mask_np.copy())
        if mask_np.any() and not mask_np.all():
            # Distance from every nonzero (empty) texel to the nearest zero (covered) texel.
            dist, (iy, ix) = ndimage.distance_transform_edt(~mask_np, return_indices=True)
            fill = (~mask_np) & (dist <= self.radius)
            dst = np.flatnonzero(fill)
            src = (iy * self.width + ix).ravel()[dst]
        else:
            fill = np.zeros_like(mask_np)
            dst = src = np.zeros(0, dtype=np.int64)
        self.fill_mask = torch.from_numpy(fill)
        self.dst = torch.from_numpy(dst.astype(np.int64))
        self.src = torch.from_numpy(src.astype(np.int64))

    def apply_(self, values: torch.Tensor) -> torch.Tensor:
        """Fill ``values`` (H, W, C) in place and return it."""
        if values.shape[:2] != (self.height, self.width):
            raise ValueError(f"values must be ({self.height}, {self.width}, C), got {tuple(values.shape)}")
        if not values.is_contiguous():
            raise ValueError("values must be contiguous to be filled in place")
        if self.dst.numel():
            flat = values.view(self.height * self.width, -1)
            dst, src = self.dst.to(values.device), self.src.to(values.device)
            flat[dst] = flat.index_select(0, src)
        return values

    def apply(self, values: torch.Tensor) -> torch.Tensor:
        """A filled copy of ``values`` (H, W, C); texels beyond the radius are left unchanged."""
        return self.apply_(values.clone(memory_format=torch.contiguous_format))
