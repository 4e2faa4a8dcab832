"""Meshes as the GL passes upload them: numpy arrays of checked shapes and indices."""

from __future__ import annotations

import numpy as np
import torch

__all__ = ["as_numpy", "check_mesh_arrays"]


def as_numpy(array, dtype) -> np.ndarray:
    """A C-contiguous numpy array of ``dtype`` from a tensor (any device; detached) or array-like."""
    if isinstance(array, torch.Tensor):
        array = array.detach().cpu().numpy()
    return np.ascontiguousarray(array, dtype=dtype)


def check_mesh_arrays(vertices, faces, what: str = "") -> tuple[np.ndarray, np.ndarray]:
    """(V, 3) float32 vertices and (F, 3) int64 faces indexing them; ValueError (its message
    starting with ``what``, e.g. ``garment``) for another shape or an index out of range."""
    prefix = f"{what} " if what else ""
    verts = as_numpy(vertices, np.float32)
    tris = as_numpy(faces, np.int64)
    if verts.ndim != 2 or verts.shape[1] != 3:
        raise ValueError(f"{prefix}vertices must be (V, 3), got shape {verts.shape}")
    if tris.ndim != 2 or tris.shape[1] != 3:
        raise ValueError(f"{prefix}faces must be (F, 3), got shape {tris.shape}")
    if tris.size and (tris.min() < 0 or tris.max() >= len(verts)):
        raise ValueError(f"{prefix}faces index out of range [0, {len(verts)})")
    return verts, tris
