"""The world-space normal of what a feature image shows, from its rendered depth
(``ModelConfig.depth_normals``; not in the paper).

The scene's lights are fixed in the world, and inside the garment the ground truth is one colour
scaled by the shading of its folds (docs/quality.md, "What the error inside the garment is made
of"), so the decoder needs the orientation of the *cloth* under each pixel, which neither the
body-relative features nor the body's normal (``shading_normals``) give it. The field's density
carries as much of the sheet's shape as it has learned (the occupancy term fits it to the simulated
cloth); its expected depth along each ray gives a world point per pixel, and the cross product of
that point map's derivatives along the image rows and columns is the surface's normal there.
Measured: lit by the ground truth's rig, these normals follow the truth's shading better than the
body's normal does, but a decoder given them learned no better folds in a one-frame proxy
(docs/quality.md, "The garment against a flat colour").

Each derivative is the one-sided difference towards the neighbour whose depth is nearer the
pixel's own (the smaller jump): at an occlusion edge (the skirt in front of a leg) the other side
belongs to another surface and would tilt the normal by the depth jump. A neighbour counts only
where the ray's opacity reaches ``min_opacity``; a pixel without a counted neighbour along rows
or columns gets the zero vector, as do pixels under ``min_opacity`` themselves. Normals face the
camera (``n . d <= 0``): a cloth's inside, seen through an opening, is shaded from its visible side.
"""

from __future__ import annotations

import torch

__all__ = ["depth_normals"]


def _one_sided(points: torch.Tensor, depth: torch.Tensor, valid: torch.Tensor, dim: int) -> torch.Tensor:
    """(h, w, 3) derivative of ``points (h, w, 3)`` along ``dim`` (0: rows, 1: columns) in pixels:
    the difference to the forward or backward neighbour, whichever is valid and nearer in depth; 0
    where neither is valid."""
    size = depth.shape[dim]

    def shift(x: torch.Tensor, step: int, fill) -> torch.Tensor:
        # x shifted so that out[i] = x[i + step] along dim, ``fill`` past the edge
        out = torch.full_like(x, fill)
        src = [slice(None)] * x.ndim
        dst = [slice(None)] * x.ndim
        if step > 0:
            src[dim], dst[dim] = slice(step, size), slice(0, size - step)
        else:
            src[dim], dst[dim] = slice(0, size + step), slice(-step, size)
        out[tuple(dst)] = x[tuple(src)]
        return out

    fwd_valid = shift(valid, 1, False) & valid
    bwd_valid = shift(valid, -1, False) & valid
    fwd_jump = (shift(depth, 1, 0.0) - depth).abs()
    bwd_jump = (depth - shift(depth, -1, 0.0)).abs()
    use_fwd = fwd_valid & (~bwd_valid | (fwd_jump <= bwd_jump))
    use_bwd = bwd_valid & ~use_fwd
    fwd = shift(points, 1, 0.0) - points
    bwd = points - shift(points, -1, 0.0)
    return torch.where(use_fwd[..., None], fwd, torch.where(use_bwd[..., None], bwd, torch.zeros_like(fwd)))


def depth_normals(depth: torch.Tensor, opacity: torch.Tensor, origins: torch.Tensor, directions: torch.Tensor,
                  min_opacity: float = 0.5) -> torch.Tensor:
    """(3, h, w) unit world-space normals of the surface a depth map shows (module docstring).

    Args:
        depth: (h, w) distance along each pixel's ray (unit directions: metres from the origin).
        opacity: (h, w) the ray's accumulated opacity; pixels under ``min_opacity`` are not surface.
        origins, directions: (h, w, 3) each pixel's ray, ``directions`` of unit length.
        min_opacity: the opacity a pixel needs to count as surface.
    Returns:
        (3, h, w) normals facing the camera, 0 where there is no surface or no valid neighbour.
    """
    if depth.shape != opacity.shape or origins.shape != (*depth.shape, 3) or directions.shape != origins.shape:
        raise ValueError(f"depth {tuple(depth.shape)}, opacity {tuple(opacity.shape)}, origins "
                         f"{tuple(origins.shape)} and directions {tuple(directions.shape)} disagree")
    valid = opacity >= min_opacity
    points = origins + depth[..., None] * directions
    along_rows = _one_sided(points, depth, valid, 1)  # d/d(column)
    along_cols = _one_sided(points, depth, valid, 0)  # d/d(row)
    normal = torch.linalg.cross(along_rows, along_cols, dim=-1)
    normal = normal / normal.norm(dim=-1, keepdim=True).clamp_min(1e-20)  # a zero vector stays zero
    facing = (normal * directions).sum(dim=-1, keepdim=True) > 0
    normal = torch.where(facing, -normal, normal)
    return normal.permute(2, 0, 1)
