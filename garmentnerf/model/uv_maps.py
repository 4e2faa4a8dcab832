"""Reading UV-space maps: the torch side of the maps :mod:`garmentnerf.gl.uv_raster` bakes.

Layout of the maps
    A map is a tensor ``(H, W, C)``. Texel (row r, column c) covers u in [c/W, (c+1)/W] and
    v in [r/H, (r+1)/H]; its centre is at ``((c + 0.5) / W, (r + 0.5) / H)``. So **row 0 is v = 0**
    (the bottom of the texture in the usual picture with v up): the same layout as GL texture
    memory.

    ``torch.nn.functional.grid_sample(..., align_corners=False)`` reads the same texel for
    ``grid = uv_to_grid(uv) = 2 * uv - 1`` (grid x follows the columns, grid y the rows);
    :func:`sample_uv_map` wraps this.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

__all__ = ["uv_to_grid", "texel_centers_uv", "sample_uv_map"]


def uv_to_grid(uv: torch.Tensor) -> torch.Tensor:
    """Texture coordinates (N, 2) in [0, 1] (u right, v up) -> ``grid_sample`` coordinates in [-1, 1]
    for maps of the layout above, with ``align_corners=False``."""
    return uv * 2.0 - 1.0


def texel_centers_uv(height: int, width: int, dtype=torch.float32, device=None) -> torch.Tensor:
    """(H, W, 2) texture coordinates (u, v) of every texel centre of a map."""
    v = (torch.arange(height, dtype=dtype, device=device) + 0.5) / height
    u = (torch.arange(width, dtype=dtype, device=device) + 0.5) / width
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    return torch.stack([uu, vv], dim=-1)


def sample_uv_map(values: torch.Tensor, uv: torch.Tensor, mode: str = "bilinear") -> torch.Tensor:
    """Look up a map ``(H, W, C)`` at texture coordinates ``uv (N, 2)`` -> ``(N, C)``.

    Bilinear by default, clamped at the map border (``padding_mode="border"``).
    """
    if values.ndim != 3:
        raise ValueError(f"values must be (H, W, C), got shape {tuple(values.shape)}")
    image = values.permute(2, 0, 1).unsqueeze(0)  # (1, C, H, W)
    grid = uv_to_grid(uv.to(values.dtype)).reshape(1, 1, -1, 2)
    out = F.grid_sample(image, grid, mode=mode, padding_mode="border", align_corners=False)
    return out[0, :, 0].T
