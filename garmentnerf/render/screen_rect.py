"""Where the character is on screen: the pixel rectangle a box in the world covers.

Rays outside the projection of the samplers' box meet no sample (the box sampler places none
outside it, the shell sampler's shell lies inside it), so their features are zero: rendering only
the rectangle, aligned to the decoder's feature grid and grown by a margin of feature pixels so
that the decoder's receptive field sees the same zeros, gives the same maps inside it as rendering
the whole frame, in a fraction of the rays. :func:`box_rect` computes that rectangle.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from garmentnerf.conventions import Camera, project_points

__all__ = ["PixelRect", "box_rect", "box_extent"]


@dataclass(frozen=True)
class PixelRect:
    """Pixels ``[x0, x0 + width) x [y0, y0 + height)`` of an image."""

    x0: int
    y0: int
    width: int
    height: int

    @property
    def x1(self) -> int:
        return self.x0 + self.width

    @property
    def y1(self) -> int:
        return self.y0 + self.height

    @property
    def area(self) -> int:
        return self.width * self.height

    def scaled(self, factor: int) -> "PixelRect":
        """The same rectangle on a grid ``factor`` times finer (a feature rectangle -> pixels)."""
        f = int(factor)
        return PixelRect(self.x0 * f, self.y0 * f, self.width * f, self.height * f)

    def slices(self) -> tuple[slice, slice]:
        """(rows, columns) slices of an (H, W, ...) array."""
        return slice(self.y0, self.y1), slice(self.x0, self.x1)


def _projected_corners(camera: Camera, box) -> np.ndarray | None:
    """(8, 2) pixel coordinates of the box's corners; None when the projection is unbounded (the
    camera inside the box, or a corner behind the camera)."""
    lo, hi = np.asarray(torch.as_tensor(box, dtype=torch.float64).cpu(), dtype=np.float64)
    centre = camera.center
    if np.all(centre >= lo) and np.all(centre <= hi):
        return None
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    uv, depth = project_points(camera, torch.as_tensor(corners, dtype=torch.float64))
    if bool((depth <= camera.near * 1e-3).any()):
        return None
    return uv.numpy()


def box_extent(camera: Camera, box: np.ndarray | torch.Tensor) -> float | None:
    """The larger side, in ``camera``'s pixels, of the box's projection (not clipped to the image):
    how large the box looks. None when the projection is unbounded."""
    uv = _projected_corners(camera, box)
    if uv is None:
        return None
    return float(np.max(uv.max(axis=0) - uv.min(axis=0)))


def box_rect(camera: Camera, box: np.ndarray | torch.Tensor, *, cell: int = 1, margin_cells: int = 0
             ) -> PixelRect | None:
    """The rectangle of ``camera``'s pixels that can see into an axis-aligned box.

    Args:
        camera: the camera; its image is ``camera.width x camera.height`` pixels, read as a grid of
            ``cell x cell`` cells (the image size must be a multiple of ``cell``).
        box: (2, 3) world-space [min, max] corners.
        cell: the grid the rectangle is aligned to (the decoder's upsampling factor).
        margin_cells: cells added on every side (the decoder's receptive field).
    Returns:
        The smallest cell-aligned rectangle holding the projection of the box's 8 corners, grown by
        the margin and clipped to the image; the whole image when the camera is inside the box or a
        corner lies behind it (the projection is then unbounded); None when the box is entirely
        outside the view.
    """
    cell = int(cell)
    if camera.width % cell or camera.height % cell:
        raise ValueError(f"the image ({camera.width}x{camera.height}) is not a multiple of the cell ({cell})")
    whole = PixelRect(0, 0, camera.width, camera.height)
    uv = _projected_corners(camera, box)
    if uv is None:
        return whole
    # pixel (c, r) covers [c - 0.5, c + 0.5): the cells touched by the corners' hull
    u0, v0 = np.floor((uv.min(axis=0) + 0.5) / cell).astype(int) - margin_cells
    u1, v1 = np.floor((uv.max(axis=0) + 0.5) / cell).astype(int) + 1 + margin_cells
    cols, rows = camera.width // cell, camera.height // cell
    u0, v0 = max(int(u0), 0), max(int(v0), 0)
    u1, v1 = min(int(u1), cols), min(int(v1), rows)
    if u1 <= u0 or v1 <= v0:
        return None
    return PixelRect(u0, v0, u1 - u0, v1 - v0).scaled(cell)
