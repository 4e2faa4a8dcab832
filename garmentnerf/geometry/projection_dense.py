"""Closest points on a triangle mesh by brute force, in pure torch: the GPU twin of projection.py.

:class:`SurfaceProjector` (:mod:`garmentnerf.geometry.projection`) answers the same queries with a
native tree search on the CPU, under a microsecond per point; with a million NeRF samples per training step that
CPU search, not the network, would bound the step time. :class:`DenseSurfaceProjector` has the
same ``bind`` / ``project`` interface and returns the same :class:`SurfaceProjection`, but runs
only dense tensor operations on the device of its inputs (CUDA, CPU, any other), with no host
round trip except one small ``any()`` per chunk for the certificate below.

Usage::

    projector = DenseSurfaceProjector(faces, num_vertices)   # once per topology
    surface = projector.bind(posed_vertices.cuda())          # once per frame (on its device)
    proj = surface.project(points_on_cuda)                   # SurfaceProjection on the same device

Algorithm
---------
1. *Brute-force k nearest vertices.* Each chunk of points is scored against every vertex the
   faces use, ``s(q, u) = |u|^2 - L_u - 2 q . u`` (coordinates centred on the mesh; the
   ``|q|^2`` term does not change the order), as three fused multiply-adds rather than a matmul
   (a float32 matmul may silently run in TF32 on a GPU, ~1e-3 relative error: useless at the
   centimetre scale of a body mesh; one ``addmm`` where float32 matmuls are known to be IEEE:
   CUDA with TF32 off, or float64), then ``topk`` keeps the k smallest. With the default
   ``ranking="power"``, ``L_u = R_u^2`` is the squared *reach* of the vertex (the largest
   enclosing-circle radius of its faces) and ``|q - u|^2 - R_u^2`` is the power distance of
   the witness lemma below; with ``ranking="distance"`` ``L_u = 0`` and these are the plain k
   nearest vertices.
2. *One-ring faces.* The faces around those k vertices (a padded (V, max valence) table, -1
   padding) are tested with the exact point-triangle distance (in each face's orthonormal frame,
   as projection.py does; duplicates are harmless) and the nearest is kept. The winner alone is
   re-solved with :func:`closest_point_on_triangles` in float64 (float32 on devices without
   float64) for the closest point, the barycentrics and the sign.
3. *Sign.* The angle-weighted pseudo-normal of the feature (face, edge, corner) holding the
   closest point, exactly as in projection.py: right for every point off a closed,
   consistently wound mesh.

When it can differ from the exact projector, and the certificate
----------------------------------------------------------------
The search is exact when the face holding the true closest point has a corner among the k
fetched vertices. It can miss where that face has none: a point whose k nearest vertices all
belong to other parts of the mesh (big triangles next to small ones, points far from the
surface whose nearest vertices sit around a face's corners while the foot point lies inside a
large face, points near the medial axis such as between the legs or arms where several sheets
are almost equidistant). The miss is then a neighbouring face, so the distance error is small,
but the foot point, the face and the barycentrics can be off.

*Witness lemma.* Let p* be the closest point of face f to a query q, at distance h. Every point
of a triangle lies within r_f of one of its corners, r_f being the radius of the triangle's
smallest enclosing circle (the circumradius, or half the longest edge if the triangle is obtuse;
the face's *reach*, :func:`face_reach`). Take as witness the corner nearest to p* within the
smallest feature holding p*: the face, an edge or the corner itself. q - p* is orthogonal to that
feature, hence ``|q - u|^2 = h^2 + |p* - u|^2 <= h^2 + r_f^2``: the closest face has a corner u
with ``|q - u|^2 - r_f^2 <= h^2`` (r_f <= R_u, the largest reach of u's faces). Hence, with
``best`` the distance found, the answer is *certified* exact when the k-th least power exceeds
``best^2`` (power ranking) or the k-th least squared vertex distance exceeds ``best^2 + max
R^2`` (distance ranking), rounding slack included. With ``certify=True`` (default) points that
fail are searched again with 8x more vertices until they pass (at most every face), so the
result equals the exact projector's up to rounding and ties; with ``certify=False`` they keep
the first answer. :func:`garmentnerf.perf.projection_bench.measure_dense_mismatch` measures
both on the bundled body; on a posed walk frame of the bundled body (points in a padded box and
in a shell ``|h| < 0.15 m``) the uncertified first pass with power ranking differs from the
exact distance by more than 1e-5 m for 0.05 % / 0.002 % / 0 of the shell points with k = 4 / 8
/ 16 (max 1.7 mm / 1.9e-5 m / 0), the plain k nearest vertices for 0.066 % / 0.006 % / 0 (max
4.6 mm / 0.6 mm / 0); none in the box, no sign flips (see that function's docstring).

Memory: each chunk holds a (M, V) score matrix and (M, k * valence) point-face pairs; the chunk
size M is derived from ``memory_budget`` (default 256 MB; at most 32 MB on the CPU, where small
chunks run faster) unless ``chunk_size`` is given. The brute force costs O(V) per point: on a
CPU it is far slower than projection.py's tree search (use that there); it is meant for GPUs.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from garmentnerf.geometry.projection import SurfaceProjection, SurfaceProjector, check_search_dtype
from garmentnerf.geometry.triangles import (FEATURE_TOL, check_points, closest_point_on_triangles, dot_rows,
                                            face_frame_distance2, face_frame_table, face_reach, pseudo_normals)

__all__ = [
    "DenseSurfaceProjector",
    "DensePosedSurface",
    "RANKINGS",
    "DEFAULT_DENSE_NEIGHBOURS",
    "DEFAULT_MEMORY_BUDGET",
]

#: k, vertices fetched per point in the first pass.
DEFAULT_DENSE_NEIGHBOURS = 8
#: Bytes one chunk may hold (score matrix plus point-face pairs), roughly.
DEFAULT_MEMORY_BUDGET = 256 << 20
#: On the CPU smaller chunks run faster (the score matrix stays in cache, no fresh pages).
_CPU_MEMORY_CAP = 32 << 20
#: Factor by which a failed certificate grows k for the retry.
_RETRY_GROWTH = 8
#: How the first pass picks its k vertices: least power, or nearest.
RANKINGS = ("power", "distance")


def _solve_dtype(device: torch.device) -> torch.dtype:
    """float64 for the winner's re-solve and the normals, where the device has it."""
    return torch.float32 if device.type == "mps" else torch.float64


def _ieee_fp32_matmul(device: torch.device) -> bool:
    """Whether a float32 matmul on ``device`` is plain IEEE float32 (CUDA, TF32 off)."""
    if device.type != "cuda":
        return False  # CPU: the fused multiply-adds are as fast; other devices: unknown precision
    try:
        if torch.get_float32_matmul_precision() != "highest" or torch.backends.cuda.matmul.allow_tf32:
            return False
        return getattr(torch.backends.cuda.matmul, "fp32_precision", "none") in ("none", "ieee")
    except (AttributeError, RuntimeError):
        return False


class DenseSurfaceProjector(SurfaceProjector):
    """Brute-force closest-point queries against a triangle mesh, on any torch device.

    Same interface and results as :class:`SurfaceProjector` (see the module docstring for the
    algorithm and when the results can differ); the topology tables are copied to each device
    once, on first use.

    Args:
        faces: (F, 3) integer vertex indices (counter-clockwise seen from outside).
        num_vertices: V, the number of vertices of the posed meshes.
        neighbours: k, vertices fetched per point in the first pass.
        ranking: "power" (vertices of least ``|q - u|^2 - R_u^2``; default) or "distance" (the
            plain k nearest vertices).
        certify: retry points whose result is not certified exact (default True).
        memory_budget: bytes a chunk may hold; sets the chunk size.
        chunk_size: points per chunk; overrides ``memory_budget`` for the first pass.
    """

    def __init__(self, faces: torch.Tensor | np.ndarray, num_vertices: int, *,
                 neighbours: int = DEFAULT_DENSE_NEIGHBOURS, ranking: str = "power", certify: bool = True,
                 memory_budget: int = DEFAULT_MEMORY_BUDGET, chunk_size: int | None = None):
        if ranking not in RANKINGS:
            raise ValueError(f"ranking must be one of {RANKINGS}, got {ranking!r}")
        if memory_budget < 1:
            raise ValueError(f"memory_budget must be positive, got {memory_budget}")
        if neighbours < 1:
            raise ValueError(f"neighbours must be positive, got {neighbours}")
        super().__init__(faces, num_vertices, chunk_size=chunk_size or 1)
        self.neighbours = int(neighbours)
        self.chunk_size = None if chunk_size is None else int(chunk_size)
        self.ranking = ranking
        self.certify = bool(certify)
        self.memory_budget = int(memory_budget)
        # Padded one-ring table: ring_table[u, j] = j-th face around compact vertex u, or -1.
        count = self._ring_count
        self.max_valence = int(count.max())
        n = self._ring_faces.shape[0]
        row = torch.repeat_interleave(torch.arange(count.shape[0]), count)
        col = torch.arange(n) - torch.repeat_interleave(self._ring_start, count)
        table = torch.full((count.shape[0], self.max_valence), -1, dtype=torch.long)
        table[row, col] = self._ring_faces
        self._ring_table = table
        self._device_tables: dict[str, dict[str, torch.Tensor]] = {}

    def _tables(self, device: torch.device) -> dict[str, torch.Tensor]:
        """The topology tables on ``device`` (cached)."""
        key = str(device)
        if key not in self._device_tables:
            self._device_tables[key] = {
                "faces": self.faces.to(device),
                "compact_faces": self._compact_faces.to(device),
                "used_vertices": self.used_vertices.to(device),
                "ring_table": self._ring_table.to(device),
                "face_edges": self._face_edges.to(device),
            }
        return self._device_tables[key]

    def bind(self, vertices: torch.Tensor, dtype: torch.dtype | None = None,
             device: torch.device | str | None = None) -> "DensePosedSurface":
        """Prepare one posed frame on ``device`` (default: that of ``vertices``)."""
        return DensePosedSurface(self, vertices, dtype, device)

    def project(self, points: torch.Tensor, vertices: torch.Tensor) -> SurfaceProjection:
        """Closest points of ``points`` (N, 3) on the mesh posed at ``vertices`` (V, 3).

        Runs on the device of ``points``; bind once and reuse the result when a frame is queried
        in several batches.
        """
        check_points("points", points)
        dtype = points.dtype if points.dtype in (torch.float32, torch.float64) else torch.float32
        return self.bind(vertices, dtype, points.device).project(points)


class DensePosedSurface:
    """A :class:`DenseSurfaceProjector` bound to one posed frame on one device.

    Attributes:
        projector: the topology it was built from.
        dtype: precision of the search and of the results (float32 or float64).
        device: where it computes.
        reach_sq_max: the largest squared reach of a vertex (m^2).
    """

    def __init__(self, projector: DenseSurfaceProjector, vertices: torch.Tensor, dtype: torch.dtype | None = None,
                 device: torch.device | str | None = None):
        dtype = check_search_dtype(vertices, projector.num_vertices, dtype)
        device = torch.device(device) if device is not None else vertices.device
        self.projector = projector
        self.dtype = dtype
        self.device = device
        self.solve_dtype = _solve_dtype(device) if dtype == torch.float32 else torch.float64
        T = projector._tables(device)
        self._faces = T["faces"]
        self._ring_table = T["ring_table"]
        self._face_edges = T["face_edges"]
        sd = self.solve_dtype
        with torch.no_grad():
            v = vertices.detach().to(device, sd)
            self._vertices = v
            F = self._faces
            tiny = torch.finfo(sd).tiny
            # Reach of every face (projection.py's formula) and of every vertex.
            r_face, cross, twice_area = face_reach(v[F[:, 0]], v[F[:, 1]], v[F[:, 2]], tiny)
            n_used = T["used_vertices"].shape[0]
            reach = torch.zeros(n_used, dtype=sd, device=device).scatter_reduce(
                0, T["compact_faces"].reshape(-1), r_face.repeat_interleave(3), "amax")
            reach_sq = reach * reach
            self.reach_sq_max = float(reach_sq.max())
            self._num_used = n_used

            # Centred coordinates keep |q|, |u| (and the rounding of the score) small.
            used = v[T["used_vertices"]]
            self._center = used.mean(dim=0)
            u = used - self._center
            lift = reach_sq if projector.ranking == "power" else torch.zeros_like(reach_sq)
            # Certificate: k-th computed power minus this offset must exceed best^2.
            self._cert_offset = 0.0 if projector.ranking == "power" else self.reach_sq_max
            self._score_bias = (dot_rows(u, u) - lift).to(dtype).contiguous()  # (U,)
            self._score_w = (-2.0 * u).T.to(dtype).contiguous()  # (3, U)
            self._vmax2 = float(dot_rows(u, u).max())
            self._lift_max = float(lift.max())

            table, self._degenerate = face_frame_table(v - self._center, F, tiny)  # projection.py's pair table
            self._pair_table = table.to(self.dtype).contiguous()
            self._has_degenerate = bool(self._degenerate.any())
            self._face_normals, self._edge_normals, self._vertex_normals = pseudo_normals(
                v, F, self._face_edges, projector.num_edges, cross, twice_area, tiny)

    # -- queries --------------------------------------------------------------------------------

    def _chunk_for(self, k: int) -> int:
        """Points per chunk for k fetched vertices, from the memory budget."""
        es = torch.finfo(self.dtype).bits // 8
        budget = self.projector.memory_budget
        if self.device.type == "cpu":
            budget = min(budget, _CPU_MEMORY_CAP)
        pairs = min(k * self.projector.max_valence, self.projector.num_faces)
        per_point = 2 * self._num_used * es + k * (es + 8) + pairs * (32 * es + 24)
        return max(1, budget // per_point)

    def project(self, points: torch.Tensor, *, stats: dict | None = None) -> SurfaceProjection:
        """Closest points on this posed surface.

        Args:
            points: (N, 3) query points on any device (moved to this surface's device).
            stats: if given, filled with counters: ``points``, ``pairs`` (point-face tests,
                padding included), ``retried`` (points whose first-pass certificate failed; with
                ``certify=False`` they are counted but keep the first answer), ``retry_passes``.
        Returns:
            :class:`SurfaceProjection` in the search dtype on the device of ``points``; no
            gradient flows through it.
        """
        check_points("points", points)
        out_device = points.device
        N = points.shape[0]
        if stats is not None:
            stats.update(points=N, pairs=0, retried=0, retry_passes=0)
        dev, dt = self.device, self.dtype
        face = torch.empty(N, dtype=torch.long, device=dev)
        bary = torch.empty(N, 3, dtype=dt, device=dev)
        closest = torch.empty(N, 3, dtype=dt, device=dev)
        dist = torch.empty(N, dtype=dt, device=dev)
        signed = torch.empty(N, dtype=dt, device=dev)
        P = self.projector
        k0 = min(P.neighbours, self._num_used)
        chunk = P.chunk_size or self._chunk_for(k0)
        with torch.no_grad():
            q_all = points.detach().to(dev)
            for s in range(0, N, chunk):
                q = q_all[s:s + chunk]
                qc = (q.to(self.solve_dtype) - self._center).to(dt)
                f = self._nearest_faces(qc, k0, stats)
                # The winner alone, in full and in the solve precision (picks the sign's feature).
                qs = q.to(self.solve_dtype)
                corners = self._faces[f]
                v = self._vertices
                cp, bc = closest_point_on_triangles(qs, v[corners[:, 0]], v[corners[:, 1]], v[corners[:, 2]])
                offset = qs - cp
                d = offset.norm(dim=1)
                face[s:s + chunk] = f
                bary[s:s + chunk] = bc.to(dt)
                closest[s:s + chunk] = cp.to(dt)
                dist[s:s + chunk] = d.to(dt)
                signed[s:s + chunk] = (d * self._sign(offset, f, bc)).to(dt)
        out = SurfaceProjection(face, bary, closest, dist, signed)
        return out if out_device == dev else out.to(out_device)

    def _sign(self, offset: torch.Tensor, face: torch.Tensor, bary: torch.Tensor) -> torch.Tensor:
        """(M,) +1 outside / -1 inside from the pseudo-normal of the closest feature (no host sync)."""
        zero = bary <= FEATURE_TOL
        nzero = zero.sum(dim=1)
        normal = self._face_normals[face]
        # Edge: the zero coordinate names the opposite corner, i.e. the edge's slot in face_edges.
        edge_slot = zero.to(torch.uint8).argmax(dim=1)
        edge_n = self._edge_normals[self._face_edges[face, edge_slot]]
        corner_n = self._vertex_normals[self._faces[face, bary.argmax(dim=1)]]
        normal = torch.where((nzero == 1).unsqueeze(1), edge_n, normal)
        normal = torch.where((nzero >= 2).unsqueeze(1), corner_n, normal)
        dot = dot_rows(offset, normal.to(offset.dtype))
        return torch.where(dot < 0, -1.0, 1.0).to(offset.dtype)

    def _nearest_faces(self, qc: torch.Tensor, k: int, stats: dict | None) -> torch.Tensor:
        """(M,) a face at minimal distance from each centred point of ``qc`` (M, 3)."""
        face, ok = self._search(qc, k, stats)
        if k >= self._num_used:
            return face
        pending = (~ok).nonzero().squeeze(1)
        if stats is not None:
            stats["retried"] += int(pending.shape[0])
        if not self.projector.certify:
            return face
        while pending.numel():
            k = min(k * _RETRY_GROWTH, self._num_used)
            if stats is not None:
                stats["retry_passes"] += 1
            step = self._chunk_for(k)
            still = []
            for s in range(0, pending.shape[0], step):
                rows = pending[s:s + step]
                f2, ok2 = self._search(qc[rows], k, stats)
                face[rows] = f2
                still.append(rows[~ok2])
            pending = torch.cat(still)
        return face

    def _search(self, qc: torch.Tensor, k: int, stats: dict | None) -> tuple[torch.Tensor, torch.Tensor]:
        """One pass with k vertices: best face (M,) among their one-rings and certified flags (M,)."""
        M = qc.shape[0]
        P = self.projector
        if self.dtype == torch.float64 or _ieee_fp32_matmul(qc.device):
            score = torch.addmm(self._score_bias.unsqueeze(0), qc, self._score_w)  # one pass over (M, U)
        else:
            # Fused multiply-adds: a float32 matmul may run in TF32 (~1e-3 relative error).
            qx, qy, qz = (qc[:, i].contiguous().unsqueeze(1) for i in range(3))
            wx, wy, wz = self._score_w
            score = torch.addcmul(self._score_bias.unsqueeze(0), qx, wx.unsqueeze(0))
            score.addcmul_(qy, wy.unsqueeze(0)).addcmul_(qz, wz.unsqueeze(0))
        if k >= self._num_used:
            kth = score.max(dim=1).values
            idx = None
        else:
            vals, idx = torch.topk(score, k, dim=1, largest=False, sorted=False)
            kth = vals.max(dim=1).values
        del score
        if idx is None or k * P.max_valence >= P.num_faces:
            cand = torch.arange(P.num_faces, device=qc.device).expand(M, -1)
        else:
            cand = self._ring_table[idx].reshape(M, -1)
        if stats is not None:
            stats["pairs"] += int(cand.numel())
        d2 = self._pair_distance2(qc, cand)
        best2, arg = d2.min(dim=1)
        face = cand.gather(1, arg.unsqueeze(1)).squeeze(1)
        if k >= self._num_used:
            return face, torch.ones(M, dtype=torch.bool, device=qc.device)
        qq = dot_rows(qc, qc)
        eps = torch.finfo(self.dtype).eps
        rel = 64.0 * eps
        # Rounding of the score (|q|^2 + 2 |q||u| + |u|^2 + L terms) and of the pair kernel.
        err = 8.0 * eps * (qq + self._vmax2 + self._lift_max) + rel * 4.0 * self.reach_sq_max
        ok = kth + qq - self._cert_offset - err > best2 * (1.0 + rel)
        return face, ok

    def _pair_distance2(self, qc: torch.Tensor, cand: torch.Tensor) -> torch.Tensor:
        """(M, C) squared distance from qc[i] to face cand[i, j] (inf for -1 padding).

        :func:`~garmentnerf.geometry.triangles.face_frame_distance2` on the pair table.
        """
        M, C = cand.shape
        flat = cand.reshape(-1).clamp_min(0)
        t = torch.index_select(self._pair_table, 1, flat).view(19, M, C)
        ax, ay, az, *frame = t.unbind(0)
        d2 = face_frame_distance2(qc[:, 0:1] - ax, qc[:, 1:2] - ay, qc[:, 2:3] - az, frame)
        del t, frame
        if self._has_degenerate:
            bad = self._degenerate[flat].view(M, C).nonzero()
            if bad.numel():
                fb = self._faces[cand[bad[:, 0], bad[:, 1]]]
                v = self._vertices - self._center
                qb = qc[bad[:, 0]].to(v.dtype)
                cp, _ = closest_point_on_triangles(qb, v[fb[:, 0]], v[fb[:, 1]], v[fb[:, 2]])
                d2[bad[:, 0], bad[:, 1]] = ((qb - cp) ** 2).sum(1).to(d2.dtype)
        return d2.masked_fill_(cand < 0, math.inf)
