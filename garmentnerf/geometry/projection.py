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

How the exact search stays cheap
--------------------------------
*Witness lemma.* Let p* be the closest point of face f to a query q, at distance h. Every point
of a triangle lies within r_f of one of its corners, r_f being the radius of the triangle's
smallest enclosing circle (the circumradius, or half the longest edge if the triangle is obtuse).
Take as witness the corner nearest to p* within the smallest feature holding p*: the face
(|p* - v| <= r_f), an edge (half its length <= r_f) or the corner itself. q - p* is orthogonal to
that feature, hence ``|q - v|^2 = h^2 + |p* - v|^2 <= h^2 + r_f^2``. This quadratic bound keeps
the search local: it looks a lateral distance r_f around the foot point however far q is (the
linear bound ``h + r_f`` would grow a cap of radius ``sqrt(2 h r_f)``).

*Lifted KD-tree.* Give every vertex the reach R_u = max r_f over its faces and put it in a 4-D
KD-tree at ``(u, sqrt(C - R_u^2))``, C = max R_u^2. For the query ``(q, 0)`` the squared 4-D
distance minus C is the power ``|q - u|^2 - R_u^2``, and by the lemma the face holding the
closest point has a corner of power <= best^2. So: fetch the k vertices of least power, search
the faces of those whose power is <= best^2, and the answer is *certified* when the k-th power
exceeds best^2 (no vertex left out can be a witness). Big triangles widen the search only near
themselves, not everywhere as one global radius would. Points that fail the certificate (near
the medial axis, where many vertices are almost equidistant) are retried with 8x more
neighbours until they pass or every vertex is in; :func:`benchmark_projection` reports the
fraction retried.

*Refinement.* The faces around each point's nearest vertex are tested first: the classic guess,
right for most points, it gives a tight ``best``. Then only the fetched vertices of power <=
best^2 are expanded, and from each only the faces it can witness (``|q - u|^2 - r_f^2 <=
best^2``), about a dozen point-face tests per point on a body mesh. The tests run on flat pairs,
component-wise on contiguous 1-D tensors (strided ``(P, 3)`` slices are several times slower on
the CPU), in each face's own orthonormal frame so that rounding stays at eps |q - a| (the
shorter ``|q - a|^2 - |projection|^2`` forms lose every digit near a big face). Only the
winning face of each point is re-solved, with :func:`closest_point_on_triangles` in float64.

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

import math
import time
from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree

from garmentnerf.geometry.triangles import (FEATURE_TOL, check_points, closest_point_on_triangles, dot_rows,
                                            face_frame_distance2, face_frame_table, face_reach, interpolate,
                                            pseudo_normals)
from garmentnerf.interrupts import deferred_interrupts

__all__ = [
    "check_search_dtype",
    "SurfaceProjection",
    "SurfaceProjector",
    "PosedSurface",
    "benchmark_projection",
    "DEFAULT_CHUNK_SIZE",
    "DEFAULT_NEIGHBOURS",
]

#: Points processed at once; bounds the memory of the flat point-face pairs (~12 per point).
DEFAULT_CHUNK_SIZE = 65536
#: Vertices of least power fetched per point in the first pass (see the module docstring). Fewer
#: make the KD-tree query cheaper and more points retry: on a render's samples (57k points, 0 to
#: 35 cm from the body) 4 took 2.6 us per point (1.2 % retried) against 2.7 for 3 (7 %), 2.6 for 5
#: and 3.0 for 8 (0.02 %); on the icosphere benchmark 1.74 against 1.90 for 8.
DEFAULT_NEIGHBOURS = 4
#: Factor by which a failed certificate grows the neighbour count for the retry.
_RETRY_GROWTH = 8
#: Most (point, neighbour) entries a retry pass holds at once.
_RETRY_BUDGET = 1 << 22
#: Most point-face pairs evaluated at once (~100 bytes each).
_PAIR_BUDGET = 1 << 21


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
    """

    face: torch.Tensor
    bary: torch.Tensor
    closest: torch.Tensor
    distance: torch.Tensor
    signed_distance: torch.Tensor

    def __len__(self) -> int:
        return int(self.face.shape[0])

    def to(self, device) -> "SurfaceProjection":
        return SurfaceProjection(*(getattr(self, f).to(device) for f in
                                   ("face", "bary", "closest", "distance", "signed_distance")))


class SurfaceProjector:
    """Exact closest-point queries against a triangle mesh of fixed topology.

    Built once per topology (the vertex -> incident-face table, the edge table); :meth:`bind`
    then prepares one posed frame and :meth:`project` answers queries. See the module docstring
    for the algorithm and for the sign convention (pseudo-normals; faces wound counter-clockwise
    seen from outside).

    Vertices that no face references are ignored (never returned as a closest point).

    Args:
        faces: (F, 3) integer vertex indices.
        num_vertices: V, the number of vertices of the posed meshes.
        neighbours: k of the first pass; more makes fewer points retry but each costlier.
        chunk_size: points processed at once.
    """

    def __init__(self, faces: torch.Tensor | np.ndarray, num_vertices: int, *, neighbours: int = DEFAULT_NEIGHBOURS,
                 chunk_size: int = DEFAULT_CHUNK_SIZE):
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
        if neighbours < 1 or chunk_size < 1:
            raise ValueError(f"neighbours and chunk_size must be positive, got {neighbours}, {chunk_size}")
        self.faces = faces
        self.num_vertices = int(num_vertices)
        self.neighbours = int(neighbours)
        self.chunk_size = int(chunk_size)

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

    Holds the frame's KD-tree, per-face constants and pseudo-normals (a few MB for a body
    mesh; building them takes milliseconds). Queries do not modify it.

    Attributes:
        projector: the topology it was built from.
        dtype: precision of the search and of the results (float32 or float64).
        reach_sq_max: C, the largest squared reach of a vertex (m^2).
    """

    def __init__(self, projector: SurfaceProjector, vertices: torch.Tensor, dtype: torch.dtype | None = None):
        self.projector = projector
        self.dtype = check_search_dtype(vertices, projector.num_vertices, dtype)
        P = projector
        v64 = vertices.detach().to("cpu", torch.float64)
        self._vertices64 = v64
        F = P.faces
        r_face, cross, twice_area = face_reach(v64[F[:, 0]], v64[F[:, 1]], v64[F[:, 2]])
        reach = torch.zeros(P.used_vertices.shape[0], dtype=torch.float64)
        reach = reach.scatter_reduce(0, P._compact_faces.reshape(-1), r_face.repeat_interleave(3), "amax")
        self.reach_sq_max = float((reach * reach).max())
        self._face_reach_sq = r_face * r_face
        lift = torch.sqrt((self.reach_sq_max - reach * reach).clamp_min(0.0))
        self._lift_sq = (lift * lift).numpy()
        pts4 = torch.cat([v64[P.used_vertices], lift.unsqueeze(1)], dim=1).numpy()
        self._tree = cKDTree(pts4, leafsize=32)  # a little faster than 16 (measured with k = 8)
        self._num_tree = pts4.shape[0]

        table, self._degenerate = face_frame_table(v64, F)
        self._pair_table = table.to(self.dtype).contiguous()
        self._has_degenerate = bool(self._degenerate.any())
        self._face_normals, self._edge_normals, self._vertex_normals = pseudo_normals(
            v64, F, P._face_edges, P.num_edges, cross, twice_area)

    # -- queries ------------------------------------------------------------------------------

    def project(self, points: torch.Tensor, *, stats: dict | None = None) -> SurfaceProjection:
        """Closest points on this posed surface.

        Args:
            points: (N, 3) query points (any device; the search runs on the CPU).
            stats: if given, filled with counters: ``points``, ``pairs`` (point-face tests),
                ``retried`` (points whose first-pass certificate failed), ``retry_passes``.
        Returns:
            :class:`SurfaceProjection` in the dtype of the search and on the device of ``points``;
            no gradient flows through it.
        """
        check_points("points", points)
        device = points.device
        N = points.shape[0]
        if stats is not None:
            stats.update(points=N, pairs=0, retried=0, retry_passes=0)
        q_all = points.detach().to("cpu", self.dtype)
        # Nearby queries in a row keep the KD-tree walk and the face-table gathers in cache.
        order = _spatial_order(q_all)
        q_all = q_all[order]
        face = torch.empty(N, dtype=torch.long)
        bary = torch.empty(N, 3, dtype=self.dtype)
        closest = torch.empty(N, 3, dtype=self.dtype)
        dist = torch.empty(N, dtype=self.dtype)
        signed = torch.empty(N, dtype=self.dtype)
        F = self.projector.faces
        v = self._vertices64
        chunk = self.projector.chunk_size
        with torch.no_grad():
            for s in range(0, N, chunk):
                q = q_all[s:s + chunk]
                rows = order[s:s + chunk]
                f = self._nearest_faces(q, stats)
                # Only the winner is solved in full, in float64: its barycentrics must be exact
                # enough to pick the sign's feature (face / edge / corner).
                q64 = q.to(torch.float64)
                corners = F[f]
                cp, bc = closest_point_on_triangles(q64, v[corners[:, 0]], v[corners[:, 1]], v[corners[:, 2]])
                offset = q64 - cp
                d = offset.norm(dim=1)
                face[rows] = f
                bary[rows] = bc.to(self.dtype)
                closest[rows] = cp.to(self.dtype)
                dist[rows] = d.to(self.dtype)
                signed[rows] = (d * self._sign(offset, f, bc)).to(self.dtype)
        out = SurfaceProjection(face, bary, closest, dist, signed)
        return out if device.type == "cpu" else out.to(device)

    def _sign(self, offset: torch.Tensor, face: torch.Tensor, bary: torch.Tensor) -> torch.Tensor:
        """(N,) +1 outside / -1 inside from the pseudo-normal of the closest feature."""
        zero = bary <= FEATURE_TOL
        nzero = zero.sum(dim=1)
        normal = self._face_normals[face]
        # Edge: the zero coordinate names the opposite corner, i.e. the edge's slot in face_edges.
        on_edge = nzero == 1
        if bool(on_edge.any()):
            slot = zero[on_edge].to(torch.uint8).argmax(dim=1)
            normal[on_edge] = self._edge_normals[self.projector._face_edges[face[on_edge], slot]]
        on_corner = nzero >= 2
        if bool(on_corner.any()):
            slot = bary[on_corner].argmax(dim=1)
            normal[on_corner] = self._vertex_normals[self.projector.faces[face[on_corner], slot]]
        dot = dot_rows(offset, normal)
        return torch.where(dot < 0, -1.0, 1.0).to(offset.dtype)

    def _nearest_faces(self, q: torch.Tensor, stats: dict | None) -> torch.Tensor:
        """(M,) index of a face at minimal distance from each point of ``q`` (M, 3), certified."""
        M = q.shape[0]
        if M == 0:
            return torch.empty(0, dtype=torch.long)
        q4 = np.zeros((M, 4))
        q4[:, :3] = q.numpy()
        k = min(self.projector.neighbours, self._num_tree)
        face, best2, ok = self._search(q, q4, k, torch.full((M,), -1, dtype=torch.long), np.full(M, np.inf), stats)
        pending = np.flatnonzero(~ok)
        if stats is not None:
            stats["retried"] += int(pending.shape[0])
        while pending.size:
            k = min(k * _RETRY_GROWTH, self._num_tree)
            if stats is not None:
                stats["retry_passes"] += 1
            step = max(1, _RETRY_BUDGET // k)
            still = []
            for s in range(0, pending.shape[0], step):
                idx = pending[s:s + step]
                rows = torch.from_numpy(idx)
                f2, b2, ok2 = self._search(q[rows], q4[idx], k, face[rows], best2[idx], stats)
                face[rows] = f2
                best2[idx] = b2
                still.append(idx[~ok2])
            pending = np.concatenate(still)
        return face

    def _search(self, q: torch.Tensor, q4: np.ndarray, k: int, face: torch.Tensor, best2: np.ndarray,
                stats: dict | None):
        """One certified pass with the k vertices of least power.

        Args:
            q: (M, 3) points; q4: (M, 4) the same lifted to the KD-tree's space (w = 0).
            k: neighbours to fetch.
            face, best2: (M,) best face known so far (-1 if none) and its squared distance
                (inf if none); a retry starts from the previous pass's answer.
        Returns:
            face (M,) tensor, best squared distance (M,) float64 numpy, certified (M,) bool numpy.
        """
        M = len(q4)
        with deferred_interrupts():  # scipy's threads must finish before a Ctrl-C acts
            D, I = self._tree.query(q4, k=k, workers=-1)
        D2 = (D * D).reshape(M, k)
        I = I.reshape(M, k)
        power = D2 - self.reach_sq_max  # |q - u|^2 - R_u^2
        d2_vertex = D2 - self._lift_sq[I]  # |q - u|^2
        rel = 64.0 * float(torch.finfo(self.dtype).eps)  # rounding slack of the pair kernel
        slack = rel * 4.0 * self.reach_sq_max
        rows = np.arange(M)

        def merge(face_new, best2_new):
            nonlocal face, best2
            better = best2_new.numpy().astype(np.float64) < best2
            face = torch.where(torch.from_numpy(better), face_new, face)
            best2 = np.where(better, best2_new.numpy().astype(np.float64), best2)

        # Stage 1: the faces around the nearest vertex (the classic guess, right for most
        # points) give a tight upper bound of the distance ...
        nearest = d2_vertex.argmin(axis=1)
        merge(*self._refine(q, torch.from_numpy(rows), torch.from_numpy(I[rows, nearest]), M, stats))
        # ... so only the vertices that may still be witnesses for it are expanded.
        select = power <= (best2 * (1.0 + rel) + slack)[:, None]
        select[rows, nearest] = False
        pt, slot = np.nonzero(select)
        if pt.size:
            # A face is only needed from a vertex that can be its witness.
            bound = torch.from_numpy(d2_vertex[pt, slot] - best2[pt] * (1.0 + rel) - slack)
            merge(*self._refine(q, torch.from_numpy(pt), torch.from_numpy(I[pt, slot]), M, stats, bound))
        if k >= self._num_tree:
            ok = np.ones(M, dtype=bool)
        else:
            ok = power[:, -1] > best2 * (1.0 + rel) + slack
        return face, best2, ok

    def _refine(self, q: torch.Tensor, pt: torch.Tensor, u: torch.Tensor, M: int, stats: dict | None,
                bound: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Exact search over the faces incident to vertex u[i] for point pt[i] (compact ids).

        Args:
            q: (M, 3) points.
            pt, u: (E,) entries: point index and compact vertex id.
            bound: optional (E,) value that a face's squared reach must reach for the face to be
                tested from that entry (``|q - u|^2 - best^2``: the vertex must be able to be the
                face's witness).
        Returns:
            the winning face (M,) (-1 for points without entries) and its squared distance (M,)
            in the search dtype (inf for points without entries).
        """
        count = self.projector._ring_count[u]
        total = int(count.sum())
        if total <= _PAIR_BUDGET:
            return self._refine_entries(q, pt, u, count, M, stats, bound)
        # Deep retries (a point near the medial axis may list every vertex) go in slices.
        cuts = torch.searchsorted(torch.cumsum(count, 0), torch.arange(_PAIR_BUDGET, total, _PAIR_BUDGET))
        edges = [0, *torch.unique(cuts).tolist(), len(u)]
        face = torch.full((M,), -1, dtype=torch.long)
        best2 = torch.full((M,), math.inf, dtype=self.dtype)
        for s0, s1 in zip(edges[:-1], edges[1:]):
            if s1 <= s0:
                continue
            f, b = self._refine_entries(q, pt[s0:s1], u[s0:s1], count[s0:s1], M, stats,
                                        None if bound is None else bound[s0:s1])
            better = b < best2
            face, best2 = torch.where(better, f, face), torch.where(better, b, best2)
        return face, best2

    def _refine_entries(self, q: torch.Tensor, pt: torch.Tensor, u: torch.Tensor, count: torch.Tensor, M: int,
                        stats: dict | None, bound: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`_refine` for entries whose rings (``count`` faces each) fit in memory at once."""
        P = self.projector
        rep = torch.repeat_interleave(count)
        n_pairs = rep.shape[0]
        base = P._ring_start[u] - (torch.cumsum(count, 0) - count)
        face = P._ring_faces[base[rep] + torch.arange(n_pairs)]
        pid = pt[rep]
        if bound is not None:
            keep = (bound[rep] <= self._face_reach_sq[face]).nonzero().squeeze(1)
            face, pid = face[keep], pid[keep]
            n_pairs = face.shape[0]
        if stats is not None:
            stats["pairs"] += n_pairs
        d2 = self._pair_distance2(q, pid, face)
        if self._has_degenerate:
            bad = self._degenerate[face].nonzero().squeeze(1)
            if bad.numel():
                fb, qb = P.faces[face[bad]], q[pid[bad]].to(torch.float64)
                v = self._vertices64
                cp, _ = closest_point_on_triangles(qb, v[fb[:, 0]], v[fb[:, 1]], v[fb[:, 2]])
                d2[bad] = ((qb - cp) ** 2).sum(1).to(d2.dtype)
        best2 = torch.full((M,), math.inf, dtype=d2.dtype).scatter_reduce_(0, pid, d2, "amin")
        pair_id = torch.where(d2 <= best2[pid], torch.arange(n_pairs), n_pairs)
        win = torch.full((M,), n_pairs, dtype=torch.long).scatter_reduce_(0, pid, pair_id, "amin")
        face = torch.cat([face, torch.full((1,), -1, dtype=torch.long)])
        return face[win], best2

    def _pair_distance2(self, q: torch.Tensor, pid: torch.Tensor, face: torch.Tensor) -> torch.Tensor:
        """(P,) squared distance from q[pid] to each face, on contiguous 1-D tensors.

        In the face's frame (see :meth:`_face_constants`) the squared distance is the squared
        height over the plane plus the squared 2-D distance to the triangle: zero inside it,
        else the least distance to its three edges (segments, so corners are covered).
        Degenerate faces come out wrong here and are redone by the caller.
        """
        qx, qy, qz = (torch.index_select(q[:, i].contiguous(), 0, pid) for i in range(3))
        ax, ay, az, *frame = torch.index_select(self._pair_table, 1, face).unbind(0)
        return face_frame_distance2(qx - ax, qy - ay, qz - az, frame)


def _spatial_order(points: torch.Tensor) -> torch.Tensor:
    """(N,) permutation putting points (N, 3) in Morton (Z-curve) order over their bounding box."""
    N = points.shape[0]
    if N < 1024:
        return torch.arange(N)
    lo, hi = points.min(dim=0).values, points.max(dim=0).values
    cells = ((points - lo) * (1023.0 / (hi - lo).clamp_min(1e-12))).to(torch.int64)  # 10 bits per axis

    def spread(v):  # bit i of v -> bit 3 i
        v = (v | (v << 16)) & 0x030000FF
        v = (v | (v << 8)) & 0x0300F00F
        v = (v | (v << 4)) & 0x030C30C3
        return (v | (v << 2)) & 0x09249249

    code = spread(cells[:, 0]) | (spread(cells[:, 1]) << 1) | (spread(cells[:, 2]) << 2)
    return torch.argsort(code)


def benchmark_projection(n_points: int = 262144, *, vertices: torch.Tensor | np.ndarray | None = None,
                         faces: torch.Tensor | np.ndarray | None = None, band: float = 0.1,
                         far_fraction: float = 0.05, far: float = 3.0, repeats: int = 3, seed: int = 0,
                         neighbours: int = DEFAULT_NEIGHBOURS, chunk_size: int = DEFAULT_CHUNK_SIZE) -> dict:
    """Time :meth:`PosedSurface.project` on float32 points around a mesh.

    Default mesh: an icosphere of radius 0.5 m with 20,480 faces (edges ~1.9 cm, close to a body
    mesh's). Points: ``1 - far_fraction`` of them on random surface points offset along the
    normal uniformly within +-``band`` m, the rest uniform in the bounding box grown by ``far`` m.

    Returns:
        dict with ``seconds`` (best of ``repeats`` projections: the CPU is often shared, and
        the best run is the least disturbed one), ``median_seconds``, ``first_seconds`` (the
        first call pays one-off warm-up), ``bind_seconds`` (preparing the frame),
        ``points_per_second`` (from ``seconds``), ``fallback_fraction`` (points whose first-pass
        certificate failed and were retried), ``pairs_per_point`` (point-face tests) and the
        problem size.
    """
    import trimesh  # only here: the module itself needs no mesh library

    if n_points < 1:
        raise ValueError(f"n_points must be positive, got {n_points}")

    if vertices is None or faces is None:
        mesh = trimesh.creation.icosphere(subdivisions=5, radius=0.5)
    else:
        mesh = trimesh.Trimesh(np.asarray(vertices, dtype=np.float64), np.asarray(faces), process=False)
    rng = np.random.default_rng(seed)
    n_far = int(round(n_points * far_fraction))
    n_near = n_points - n_far
    samples, fid = trimesh.sample.sample_surface(mesh, n_near, seed=seed)
    near = samples + mesh.face_normals[fid] * rng.uniform(-band, band, size=(n_near, 1))
    lo, hi = mesh.bounds[0] - far, mesh.bounds[1] + far
    pts = np.concatenate([near, rng.uniform(lo, hi, size=(n_far, 3))])[rng.permutation(n_points)]
    points = torch.as_tensor(pts, dtype=torch.float32)
    verts = torch.as_tensor(np.asarray(mesh.vertices), dtype=torch.float32)

    projector = SurfaceProjector(torch.as_tensor(np.asarray(mesh.faces)), verts.shape[0], neighbours=neighbours,
                                 chunk_size=chunk_size)
    t0 = time.perf_counter()
    surface = projector.bind(verts)
    bind_seconds = time.perf_counter() - t0
    times, stats = [], {}
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        surface.project(points, stats=stats)
        times.append(time.perf_counter() - t0)
    seconds = min(times)
    return {
        "n_points": n_points,
        "n_vertices": int(verts.shape[0]),
        "n_faces": int(mesh.faces.shape[0]),
        "seconds": seconds,
        "median_seconds": float(np.median(times)),
        "first_seconds": times[0],
        "bind_seconds": bind_seconds,
        "points_per_second": n_points / seconds if seconds > 0 else math.inf,
        "fallback_fraction": stats["retried"] / max(1, n_points),
        "pairs_per_point": stats["pairs"] / max(1, n_points),
        "torch_threads": torch.get_num_threads(),
    }
