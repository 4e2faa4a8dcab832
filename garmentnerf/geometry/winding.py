"""Inside or outside a closed triangle mesh: generalised winding numbers (Jacobson et al. 2013)."""

from __future__ import annotations

import math

import numpy as np
import torch


def winding_number(point, vertices: torch.Tensor, faces: torch.Tensor) -> float:
    """Generalised winding number of ``point (3,)`` w.r.t. the triangle mesh (about 1 inside a
    closed outward-oriented surface, 0 outside; Jacobson et al. 2013, solid angles by
    Van Oosterom and Strackee)."""
    v = vertices.detach().to("cpu", torch.float64) - torch.as_tensor(np.asarray(point, dtype=np.float64))
    f = faces.detach().cpu().long()
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    la, lb, lc = a.norm(dim=-1), b.norm(dim=-1), c.norm(dim=-1)
    num = (a * torch.linalg.cross(b, c, dim=-1)).sum(-1)
    den = la * lb * lc + (a * b).sum(-1) * lc + (b * c).sum(-1) * la + (c * a).sum(-1) * lb
    return float(2.0 * torch.atan2(num, den).sum() / (4.0 * math.pi))


def point_in_shell(point, vertices: torch.Tensor, faces: torch.Tensor, margin: float) -> bool:
    """Whether ``point`` may lie inside the body inflated by ``margin`` (conservative: inside the
    body by winding number, or within ``margin`` + the longest edge of a vertex). A point outside
    the box of the faces' vertices grown by ``margin`` is outside at once (the common case: a
    camera looking at the body from a distance)."""
    v = vertices.detach().to("cpu", torch.float64)
    f = faces.detach().cpu().long()
    p = torch.as_tensor(np.asarray(point, dtype=np.float64))
    corners = v[f.reshape(-1)] if len(f) else v[:0]
    if not len(corners) or bool((p < corners.amin(0) - margin).any() or (p > corners.amax(0) + margin).any()):
        return False
    edge = float((v[f[:, 0]] - v[f[:, 1]]).norm(dim=-1).max()) if len(f) else 0.0
    used = torch.unique(f.reshape(-1))
    if float((v[used] - p).norm(dim=-1).min()) <= margin + edge:
        return True
    return winding_number(p, v, f) > 0.5


__all__ = ["winding_number", "point_in_shell"]
