"""A smooth field of body normals in world space: what the decoder's shading reads when the normal at a
sample's closest body point would be the wrong one (``ModelConfig.shading_normal_blur``).

The closest point's normal is the normal of the cloth only where the cloth follows the skin. Where it
spans a gap, the skirt across the legs, the closest point is an inner thigh and its normal points
sideways while the cloth faces forward (docs/quality.md, "The lights": LN1's dark blotch between the
legs). Blurring the body's normals over a few centimetres fixes that: the normals of two surfaces that
face each other across a gap cancel, and the fronts of the legs win.

The field is ``N(q) = sum_f a_f G_sigma(q - c_f)`` over the posed body's faces f (area vector a_f: the
face's normal times its area; centroid c_f; G an isotropic Gaussian), normalised where it is read. It
is computed once per frame on a grid (:func:`blurred_normal_grid`: the area vectors splatted
trilinearly into cells of ``sigma / 2`` over the body's box, then blurred by a separable Gaussian) and
read trilinearly per sample (:func:`read_normal_grid`); :func:`blurred_normals_direct` is the plain sum
over faces, the reference the grid is tested against.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

__all__ = ["NormalGrid", "KERNEL_SIGMAS", "blurred_normal_grid", "read_normal_grid", "blurred_normals_direct"]

#: Cells per sigma of the grid (the splat and the read each blur by about half a cell more).
CELLS_PER_SIGMA = 2
#: The Gaussian's kernel reaches this many sigmas.
KERNEL_SIGMAS = 3.0
#: A field shorter than this fraction of the grid's longest vector has no direction worth reading.
WEAK_FIELD = 1e-3


@dataclass
class NormalGrid:
    """The blurred area vectors of one posed frame on a regular grid.

    Attributes:
        values: (3, D, H, W) float32, the summed area vectors (not normalised) at the cell centres;
            axis D is z, H is y, W is x.
        origin: (3,) world position of cell (0, 0, 0)'s centre.
        cell: the cell's edge (metres).
        weak: lengths under this have no direction worth reading (:data:`WEAK_FIELD` times the
            grid's longest vector).
    """

    values: torch.Tensor
    origin: torch.Tensor
    cell: float
    weak: float


def _face_area_vectors(vertices: torch.Tensor, faces: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(F, 3) centroids and (F, 3) area vectors (normal times area) of the faces."""
    tri = vertices[faces]  # (F, 3, 3)
    centroids = tri.mean(dim=1)
    area = 0.5 * torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    return centroids, area


def blurred_normal_grid(vertices: torch.Tensor, faces: torch.Tensor, sigma: float, reach: float) -> NormalGrid:
    """The field of the module docstring on a grid covering the body's box grown by ``reach``.

    Args:
        vertices: (V, 3) posed body (world, metres); faces: (F, 3) long.
        sigma: the Gaussian's standard deviation (metres, > 0).
        reach: how far beyond the body's box the field is stored (metres): samples further out read
            the border's values.
    """
    if sigma <= 0:
        raise ValueError(f"sigma must be > 0, got {sigma}")
    vertices = vertices.detach().to("cpu", torch.float32)
    centroids, area = _face_area_vectors(vertices, faces.to("cpu"))
    cell = sigma / CELLS_PER_SIGMA
    lo = vertices.min(dim=0).values - reach
    hi = vertices.max(dim=0).values + reach
    size = torch.ceil((hi - lo) / cell).long() + 1  # (x, y, z) cell counts
    nx, ny, nz = (int(s) for s in size)
    grid = torch.zeros(3, nz * ny * nx)
    f = (centroids - lo) / cell  # continuous cell coordinates
    base = f.floor().long()
    frac = f - base
    for corner in range(8):
        offs = torch.tensor([(corner >> k) & 1 for k in range(3)])
        idx = base + offs
        w = torch.where(offs.bool(), frac, 1.0 - frac).prod(dim=1)
        inside = ((idx >= 0) & (idx < size)).all(dim=1)
        flat = (idx[:, 2] * ny + idx[:, 1]) * nx + idx[:, 0]
        grid.index_add_(1, flat[inside], (area[inside] * w[inside, None]).T)
    grid = grid.view(3, nz, ny, nx)
    radius = math.ceil(KERNEL_SIGMAS * CELLS_PER_SIGMA)
    taps = torch.arange(-radius, radius + 1, dtype=torch.float32)
    kernel = torch.exp(-0.5 * (taps / CELLS_PER_SIGMA) ** 2)
    kernel = (kernel / kernel.sum()).view(1, 1, -1)
    for axis in (1, 2, 3):  # separable: z, y, x, each as a batch of 1-D convolutions along the last axis
        moved = grid.movedim(axis, -1)
        rows = F.conv1d(moved.reshape(-1, 1, moved.shape[-1]), kernel, padding=radius)
        grid = rows.view(moved.shape).movedim(-1, axis)
    grid = grid.contiguous()
    return NormalGrid(grid, lo, cell, WEAK_FIELD * float(grid.norm(dim=0).max()))


def read_normal_grid(grid: NormalGrid, positions: torch.Tensor, fallback: torch.Tensor) -> torch.Tensor:
    """(n, 3) unit normals of the field at world ``positions (n, 3)`` (trilinear; outside the grid the
    border's value). Where the field is too weak to have a direction (further than the kernel's
    reach from every face: its length under ``grid.weak``), the unit
    ``fallback (n, 3)`` instead (e.g. the closest point's normal)."""
    values = grid.values.to(positions.device)
    size = torch.tensor([values.shape[3], values.shape[2], values.shape[1]], device=positions.device)
    cells = (positions.float() - grid.origin.to(positions.device)) / grid.cell
    coords = cells / (size - 1).clamp_min(1) * 2.0 - 1.0  # align_corners=True: -1 and 1 are the end cells
    sampled = F.grid_sample(values[None], coords.view(1, -1, 1, 1, 3), mode="bilinear", padding_mode="border",
                            align_corners=True).view(3, -1).T
    length = sampled.norm(dim=-1, keepdim=True)
    strong = length > grid.weak
    return torch.where(strong, sampled / length.clamp_min(1e-30), fallback.to(sampled))


def blurred_normals_direct(vertices: torch.Tensor, faces: torch.Tensor, sigma: float,
                           positions: torch.Tensor) -> torch.Tensor:
    """(n, 3) the field of the module docstring at ``positions``, summed over every face (float64; the
    plain reference of :func:`blurred_normal_grid` and :func:`read_normal_grid`)."""
    centroids, area = _face_area_vectors(vertices.double(), faces)
    d2 = torch.cdist(positions.double(), centroids).square()
    return F.normalize(torch.exp(-0.5 * d2 / sigma ** 2) @ area, dim=-1)
