"""Exact closest points on a triangle mesh: the body-aware geometry of every NeRF sample.

For a sample point x the paper needs the closest point on the posed body surface, the face and
barycentric coordinates of that point (to find the same point on the canonical body, or in UV
space, with :func:`interpolate`) and the signed distance to the body. :class:`SurfaceProjector`
computes these *exactly* (the true closest point of the mesh, not of its nearest vertex) for
hundreds of thousands of points per frame on the CPU.

Usage::

    projector = SurfaceProjector(faces, num_vertices)      # once per topology
    surface = projector.bind(posed_vertices)                # once per frame
    proj = surface.project(points)                          # any number of point batches
    canonical = projector.interpolate(template_vertices, proj.face, proj.bary)
    uv = interpolate(uv_coords, uv_faces, proj.face, proj.bary)

or, with values per face corner given once (``SurfaceProjector(..., corner_values=...)``),
``proj.values`` holds them interpolated by the search kernel itself.

How the exact search stays cheap
--------------------------------
Each posed frame gets a bounding-volume hierarchy over its faces (:mod:`~garmentnerf.geometry.face_bvh`):
a complete binary tree of median splits down to leaves of two or three faces, every node bounded
by a box oriented along its faces' mean normal and their principal directions across it (and,
where that is tighter, high in the tree, its axis-aligned box). A native kernel (warp, on the
CPU) walks it for every point and skips a node when its box is farther than the best face found:
the answer is the exact nearest face (in float64), with nothing to certify or retry. Oriented
boxes hug a patch of skin, so a point tens of centimetres off the body opens only the nodes
around its foot point, where an axis-aligned box (the scipy KD-tree of vertices this replaced)
sticks out of the surface by its own size and lets the point's distance ball reach far more of
them. The points are walked in Morton order, each starting at the leaf of the face of the point
before it and walking up (samples along a ray share their neighbourhood); the kernel writes every
answer to its point's own row, with the projector's ``corner_values`` (the body's canonical
position and UV) interpolated there too; ``stats`` counts the bounds and faces tested.

The tree's face order is computed once per topology when a reference pose is given
(``reference_vertices``, the body's template), else on every :meth:`SurfaceProjector.bind`;
either way :meth:`~SurfaceProjector.bind` refits the node bounds to the frame (exact for that
frame, so any order gives the same answers, up to ties between equidistant faces).

Only the winning face of each point is then solved in full, in the same kernel and in float64:
closest point and barycentrics as :func:`~garmentnerf.geometry.triangles.closest_point_on_triangles`
computes them (the same candidates in the same order), and the sign below.

Sign
----
The sign is that of ``(x - closest) . n`` with n the angle-weighted pseudo-normal (Baerentzen &
Aanaes, 2005) of the feature holding the closest point: the face normal inside a face, the sum
of the two face normals on an edge, the angle-weighted normal at a corner. Unlike an
interpolated vertex normal it is provably right for every point off a closed, consistently
wound (counter-clockwise seen from outside) mesh, edges and corners included. Near a hole of an
open mesh it gives the side of the face the point projects onto.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
import torch

from garmentnerf.geometry.face_bvh import DEFAULT_CHUNK_SIZE, FaceBVH, morton_order, tree_order
from garmentnerf.geometry.triangles import check_points, interpolate, pseudo_normals

__all__ = [
    "check_search_dtype",
    "SurfaceProjection",
    "SurfaceProjector",
    "PosedSurface",
    "DEFAULT_CHUNK_SIZE",
]


def check_search_dtype(vertices: torch.Tensor, num_vertices: int, dtype: torch.dtype | None) -> torch.dtype:
    """The search precision of a posed frame: ``dtype``, else that of ``vertices`` (float32 for
    other float types). Raises when ``vertices`` is not (num_vertices, 3) finite floats or the
    precision is not float32/float64."""
    check_points("vertices", vertices)
    if vertices.shape[0] != num_vertices:
        raise ValueError(f"vertices has {vertices.shape[0]} rows, the projector was built for {num_vertices}")
    if dtype is None:
        dtype = vertices.dtype if vertices.dtype in (torch.float32, torch.float64) else torch.float32
    if dtype not in (torch.float32, torch.float64):
        raise TypeError(f"search precision must be float32 or float64, got {dtype}")
    return dtype


@dataclass
class SurfaceProjection:
    """Closest points on the surface for N query points.

    Attributes:
        face: (N,) long index of the face holding the closest point.
        bary: (N, 3) its barycentric coordinates w.r.t. that face's corners (in ``faces`` order).
        closest: (N, 3) the closest point.
        distance: (N,) unsigned distance ``|x - closest|``.
        signed_distance: (N,) the same distance, negative inside the surface, positive outside.
        values: (N, C) the projector's ``corner_values`` interpolated at the closest point (None
            without them).
    """

    face: torch.Tensor
    bary: torch.Tensor
    closest: torch.Tensor
    distance: torch.Tensor
    signed_distance: torch.Tensor
    values: torch.Tensor | None = None

    def __len__(self) -> int:
        return int(self.face.shape[0])

    def to(self, device) -> "SurfaceProjection":
        return SurfaceProjection(*(None if getattr(self, f) is None else getattr(self, f).to(device) for f in
                                   ("face", "bary", "closest", "distance", "signed_distance", "values")))


class SurfaceProjector:
    """Exact closest-point queries against a triangle mesh of fixed topology.

    Built once per topology (the vertex -> incident-face table, the edge table, the search
    tree's face order if ``reference_vertices`` is given); :meth:`bind` then prepares one posed
    frame and :meth:`project` answers queries. See the module docstring for the algorithm and for
    the sign convention (pseudo-normals; faces wound counter-clockwise seen from outside).

    Vertices that no face references are ignored (never returned as a closest point).

    Args:
        faces: (F, 3) integer vertex indices.
        num_vertices: V, the number of vertices of the posed meshes.
        chunk_size: points processed at once.
        reference_vertices: (V, 3) a pose to compute the search tree's face order on once (e.g.
            the template); None: each :meth:`bind` computes it on its own frame (a few tens of
            ms more per frame, a slightly tighter tree).
        threads: kernel launches run at once per query (default: torch's thread count).
        corner_values: (F, 3, C) values at every face's corners that do not change with the pose
            (e.g. canonical positions, UVs): every projection also returns them interpolated at
            the closest point (``SurfaceProjection.values``, in float64 in the search kernel:
            what :func:`interpolate` gives, without its gathers).
    """

    def __init__(self, faces: torch.Tensor | np.ndarray, num_vertices: int, *, chunk_size: int = DEFAULT_CHUNK_SIZE,
                 reference_vertices: torch.Tensor | None = None, threads: int | None = None,
                 corner_values: torch.Tensor | None = None):
        if not isinstance(faces, torch.Tensor):
            faces = np.asarray(faces)
            if faces.dtype.kind not in "iu":
                raise TypeError(f"faces must be integer indices, got {faces.dtype}")
            faces = torch.from_numpy(faces.astype(np.int64))
        if faces.ndim != 2 or faces.shape[1] != 3:
            raise ValueError(f"faces must have shape (F, 3), got {tuple(faces.shape)}")
        if faces.is_floating_point() or faces.is_complex() or faces.dtype == torch.bool:
            raise TypeError(f"faces must be integer indices, got {faces.dtype}")
        if faces.shape[0] == 0:
            raise ValueError("faces is empty: a surface needs at least one triangle")
        faces = faces.detach().to("cpu", torch.long).contiguous()
        if int(faces.min()) < 0 or int(faces.max()) >= num_vertices:
            raise ValueError(f"face indices must lie in [0, {num_vertices}), "
                             f"got [{int(faces.min())}, {int(faces.max())}]")
        if chunk_size < 1:
            raise ValueError(f"chunk_size must be positive, got {chunk_size}")
        if threads is not None and threads < 1:
            raise ValueError(f"threads must be positive, got {threads}")
        if corner_values is not None and (corner_values.ndim != 3 or corner_values.shape[:2] != (faces.shape[0], 3)):
            raise ValueError(f"corner_values must be (F={faces.shape[0]}, 3, C), got {tuple(corner_values.shape)}")
        self.faces = faces
        self.num_vertices = int(num_vertices)
        self.corner_values = None if corner_values is None else corner_values.detach().to("cpu", torch.float64)
        self.chunk_size = int(chunk_size)
        self.threads = threads
        self.tree_order = None
        if reference_vertices is not None:
            check_search_dtype(reference_vertices, self.num_vertices, None)
            self.tree_order = tree_order(reference_vertices, faces)

        # The KD-tree holds only referenced vertices, under compact ids.
        used = torch.zeros(num_vertices, dtype=torch.bool)
        used[faces.reshape(-1)] = True
        self.used_vertices = used.nonzero().squeeze(1)  # compact id -> vertex id
        compact = torch.full((num_vertices,), -1, dtype=torch.long)
        compact[self.used_vertices] = torch.arange(self.used_vertices.shape[0])
        self._compact_faces = compact[faces]  # (F, 3)

        # Incident faces of each compact vertex, CSR: ring_faces[ring_start[u] : ring_start[u] + ring_count[u]].
        corner_vertex = self._compact_faces.reshape(-1)
        order = torch.argsort(corner_vertex, stable=True)
        self._ring_faces = (order // 3).contiguous()
        self._ring_count = torch.bincount(corner_vertex, minlength=self.used_vertices.shape[0])
        self._ring_start = torch.cumsum(self._ring_count, 0) - self._ring_count

        # Edge j of a face is the one opposite corner j; shared edges get one id (pseudo-normals).
        e = torch.stack([faces[:, [1, 2]], faces[:, [2, 0]], faces[:, [0, 1]]], dim=1)  # (F, 3, 2)
        e = torch.sort(e, dim=-1).values.reshape(-1, 2)
        _, self._face_edges = torch.unique(e, dim=0, return_inverse=True)
        self._face_edges = self._face_edges.reshape(-1, 3)
        self.num_edges = int(self._face_edges.max()) + 1

    def search_threads(self) -> int:
        """Threads the search runs on: ``threads``, else torch's thread count (at most the CPUs)."""
        return self.threads or min(torch.get_num_threads(), os.cpu_count() or 1)

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])

    def bind(self, vertices: torch.Tensor, dtype: torch.dtype | None = None) -> "PosedSurface":
        """Prepare one posed frame for queries.

        Args:
            vertices: (V, 3) posed vertex positions.
            dtype: precision of the search and results (float32 or float64); default: that of
                ``vertices`` (float32 for half precisions).
        """
        return PosedSurface(self, vertices, dtype)

    def project(self, points: torch.Tensor, vertices: torch.Tensor) -> SurfaceProjection:
        """Closest points of ``points`` (N, 3) on the mesh posed at ``vertices`` (V, 3).

        Shorthand for ``bind(vertices, points.dtype).project(points)`` (float32 for half
        precisions); bind once and reuse the result when a frame is queried in several batches.
        """
        dtype = points.dtype if points.dtype in (torch.float32, torch.float64) else torch.float32
        return self.bind(vertices, dtype).project(points)

    def interpolate(self, values: torch.Tensor, face: torch.Tensor, bary: torch.Tensor,
                    faces: torch.Tensor | None = None) -> torch.Tensor:
        """Interpolate per-vertex ``values`` (V, C) at (face (N,), bary (N, 3)) -> (N, C).

        ``faces`` defaults to this mesh's faces; pass ``uv_faces`` to interpolate UVs.
        """
        return interpolate(values, self.faces if faces is None else faces, face, bary)


class PosedSurface:
    """A :class:`SurfaceProjector` bound to one posed frame; see :meth:`SurfaceProjector.bind`.

    Holds the frame's search tree (:class:`~garmentnerf.geometry.face_bvh.FaceBVH`: per-face
    and per-node tables, ~6 MB for a body mesh) and pseudo-normals. Queries do not modify it.

    Attributes:
        projector: the topology it was built from.
        dtype: precision of the results (float32 or float64; the search itself runs in float64).
    """

    def __init__(self, projector: SurfaceProjector, vertices: torch.Tensor, dtype: torch.dtype | None = None):
        self.projector = projector
        self.dtype = check_search_dtype(vertices, projector.num_vertices, dtype)
        P = projector
        v64 = vertices.detach().to("cpu", torch.float64)
        self._vertices64 = v64
        F = P.faces
        a, b, c = v64[F[:, 0]], v64[F[:, 1]], v64[F[:, 2]]
        cross = torch.cross(b - a, c - a, dim=1)
        self._face_normals, self._edge_normals, self._vertex_normals = pseudo_normals(
            v64, F, P._face_edges, P.num_edges, cross, cross.norm(dim=1))
        self._tree = FaceBVH(v64, F, P.tree_order, (self._face_normals, self._edge_normals, self._vertex_normals,
                                                    P._face_edges), P.corner_values, P.search_threads())

    # -- queries ------------------------------------------------------------------------------

    def project(self, points: torch.Tensor, *, stats: dict | None = None) -> SurfaceProjection:
        """Closest points on this posed surface.

        Args:
            points: (N, 3) query points (any device; the search runs on the CPU).
            stats: if given, filled with counters: ``points``, ``bounds`` (node bounds tested)
                and ``pairs`` (point-face distances computed).
        Returns:
            :class:`SurfaceProjection` in the dtype of the search and on the device of ``points``;
            no gradient flows through it.
        """
        check_points("points", points)
        device = points.device
        N = points.shape[0]
        if stats is not None:
            stats.update(points=N, pairs=0, bounds=0)
        q_all = points.detach().to("cpu", torch.float64)
        threads = self.projector.search_threads()
        with torch.no_grad():
            # Nearby queries in a row: each starts from its predecessor's face, and the tree walk
            # and the table reads stay in cache. The kernel solves the winner in full, in float64
            # (closest_point_on_triangles and _sign, ported), and writes every point's own row.
            found = self._tree.query(q_all, threads, walk_order=morton_order(q_all),
                                     chunk_size=self.projector.chunk_size)
            if stats is not None:
                totals = found.work.sum(dim=0, dtype=torch.int64)
                stats["bounds"] += int(totals[0])
                stats["pairs"] += int(totals[1])
            bary, closest, dist, signed = (found.geom[:, cols].to(self.dtype, copy=True)
                                           for cols in (slice(0, 3), slice(3, 6), 6, 7))
            values = None if found.values is None else found.values.to(self.dtype)
        out = SurfaceProjection(found.face, bary, closest, dist, signed, values)
        return out if device.type == "cpu" else out.to(device)
