"""Per-vertex surface quantities of a posed body clip: normals, canonical-frame velocities."""

from __future__ import annotations

import torch

#: Velocity-map scale: map value = velocity in m/s x VELOCITY_SCALE. It equals the authors'
#: "per-frame displacement x 5" at 30 fps, but does not change with the motion's frame rate.
VELOCITY_SCALE = 5.0 / 30.0


def vertex_normals(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Area-weighted unit vertex normals.

    Args:
        vertices: (T, V, 3) or (V, 3).
        faces: (F, 3) long, counter-clockwise seen from outside.
    Returns:
        normals with the shape of ``vertices``; vertices with no (non-degenerate) face get (0, 0, 0).
    """
    squeeze = vertices.ndim == 2
    v = vertices.unsqueeze(0) if squeeze else vertices
    a, b, c = (v[:, faces[:, i]] for i in range(3))
    face_n = torch.cross(b - a, c - a, dim=-1)  # length = 2 x area: area weighting for free
    n = torch.zeros_like(v)
    for i in range(3):
        n.index_add_(1, faces[:, i], face_n)
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-20)
    return n[0] if squeeze else n


def root_relative_normals(normals: torch.Tensor, root_rotation: torch.Tensor) -> torch.Tensor:
    """Remove the root's global rotation from normals: ``R_root^T n``.

    Args:
        normals: (T, V, 3).
        root_rotation: (T, 3, 3) global rotation of the root joint.
    """
    return torch.einsum("tji,tvj->tvi", root_rotation, normals)


def canonical_velocities(vertices: torch.Tensor, vertex_linear: torch.Tensor, fps: float, history: int) -> torch.Tensor:
    """Velocity history of every vertex, in the canonical (rest-pose) frame.

    For frame t and i = 1..k the displacement ``d = x(t-i+1) - x(t-i)`` is mapped back to rest
    space by the inverse of that vertex's skinning matrix at frame ``t-i+1``
    (``x' = L x + b`` so a rest-space displacement ``dx`` shows as ``L dx``). The inverse of the
    blended matrix is used rather than its rotation part: it is the exact rest-space
    displacement, and a closed-form 3x3 solve is far cheaper than the SVD a polar rotation needs.
    Then it is converted to m/s and scaled by :data:`VELOCITY_SCALE`.

    Frames before the start of the motion are defined as the first frame held still, so the
    first ``i`` frames have zero velocity in slot i.

    Args:
        vertices: (T, V, 3) posed vertices of consecutive frames.
        vertex_linear: (T, V, 3, 3) linear part of each vertex's skinning transform.
        fps: frames per second of the clip.
        history: k, the number of velocity slots.
    Returns:
        (T, V, 3 k): slot i-1 in channels [3 (i-1), 3 i).
    """
    T = vertices.shape[0]
    local = canonical_frame_velocities(vertices, vertex_linear, fps)
    slots = []
    for i in range(1, history + 1):
        # slot i at frame t holds local[t - i + 1]; before the start it is zero.
        shifted = torch.zeros_like(local)
        if T - (i - 1) > 0:
            shifted[i - 1:] = local[: T - (i - 1)]
        slots.append(shifted)
    return torch.cat(slots, dim=-1)


def canonical_frame_velocities(vertices: torch.Tensor, vertex_linear: torch.Tensor, fps: float) -> torch.Tensor:
    """(T, V, 3) each vertex's velocity between frame t - 1 and t in the canonical frame (zero at t = 0),
    scaled by :data:`VELOCITY_SCALE`: slot 1 of :func:`canonical_velocities`."""
    disp = torch.zeros_like(vertices)
    disp[1:] = vertices[1:] - vertices[:-1]  # disp[s] = x(s) - x(s-1); zero at s = 0
    return solve3x3(vertex_linear, disp) * (fps * VELOCITY_SCALE)


def solve3x3(matrices: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:
    """Solve ``M x = b`` for many 3x3 systems with Cramer's rule (elementwise, no LAPACK calls).

    Args:
        matrices: (..., 3, 3); rhs: (..., 3).
    Returns:
        (..., 3). A singular matrix (|det| < 1e-12) gives x = 0 rather than Inf.
    """
    m = matrices
    c0 = torch.cross(m[..., 1, :], m[..., 2, :], dim=-1)  # rows of the adjugate's transpose
    c1 = torch.cross(m[..., 2, :], m[..., 0, :], dim=-1)
    c2 = torch.cross(m[..., 0, :], m[..., 1, :], dim=-1)
    det = (m[..., 0, :] * c0).sum(-1, keepdim=True)
    # inverse = [c0 c1 c2] / det (columns), so x = (c0 b0 + c1 b1 + c2 b2) / det
    x = c0 * rhs[..., 0:1] + c1 * rhs[..., 1:2] + c2 * rhs[..., 2:3]
    safe = det.abs() > 1e-12
    return torch.where(safe, x / torch.where(safe, det, torch.ones_like(det)), torch.zeros_like(x))
