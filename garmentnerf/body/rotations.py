"""Rotation vectors to rotation matrices, in torch, without importing roma.

:func:`rotvec_to_rotmat` computes exactly what ``roma.rotvec_to_rotmat`` computes (the same
operations in the same order: Rodrigues' formula, and its first-order expansion below
``epsilon`` radians; ``tests/body/test_rotations.py`` holds the two equal, values and gradients).
It lives here because importing roma imports ``torch._dynamo`` (roma wraps two of its functions
with ``torch._dynamo.disable`` at import), which with sympy costs about 3 s of CPU: a third of what
``garmentnerf view`` imported before it could draw the body. Posing a body needs only this one
function; the motion modules that need more of roma import it when they run.
"""

from __future__ import annotations

import torch


def rotvec_to_rotmat(rotvec: torch.Tensor, epsilon: float = 1e-6) -> torch.Tensor:
    """(..., 3) rotation vectors -> (..., 3, 3) rotation matrices (differentiable)."""
    batch_shape = rotvec.shape[:-1]
    flat = rotvec.flatten(end_dim=-2) if len(batch_shape) > 0 else rotvec.unsqueeze(0)
    if flat.shape[-1] != 3:
        raise ValueError(f"rotation vectors must be (..., 3), got {tuple(rotvec.shape)}")
    theta = torch.norm(flat, dim=-1)
    is_angle_small = theta < epsilon
    # Rodrigues' formula; the clamp keeps small angles finite (torch.where would give nan gradients)
    axis = flat / torch.clamp_min(theta[..., None], epsilon)
    kx, ky, kz = axis[:, 0], axis[:, 1], axis[:, 2]
    sin_theta = torch.sin(theta)
    cos_theta = torch.cos(theta)
    one_minus_cos_theta = 1 - cos_theta
    xs = kx * sin_theta
    ys = ky * sin_theta
    zs = kz * sin_theta
    xyc = kx * ky * one_minus_cos_theta
    xzc = kx * kz * one_minus_cos_theta
    yzc = ky * kz * one_minus_cos_theta
    xxc = kx**2 * one_minus_cos_theta
    yyc = ky**2 * one_minus_cos_theta
    zzc = kz**2 * one_minus_cos_theta
    rodrigues = torch.stack([1 - yyc - zzc, xyc - zs, xzc + ys,
                             xyc + zs, 1 - xxc - zzc, -xs + yzc,
                             xzc - ys, xs + yzc, 1 - xxc - yyc], dim=-1).reshape(-1, 3, 3)
    # small angles: the first-order expansion
    xs, ys, zs = flat[:, 0], flat[:, 1], flat[:, 2]
    one = torch.ones_like(xs)
    first_order = torch.stack([one, -zs, ys,
                               zs, one, -xs,
                               -ys, xs, one], dim=-1).reshape(-1, 3, 3)
    R = torch.where(is_angle_small[:, None, None], first_order, rodrigues)
    return R.reshape(batch_shape + R.shape[1:]) if len(batch_shape) > 0 else R.squeeze(0)


__all__ = ["rotvec_to_rotmat"]
