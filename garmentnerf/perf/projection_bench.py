"""Measurements of the surface projectors (:mod:`garmentnerf.geometry.projection`, the exact tree
search, and :mod:`garmentnerf.geometry.projection_dense`, the brute force): their speed on a sphere
or the bundled body, the dense search's mismatch against the exact one, and the point sets they use.
"""

from __future__ import annotations

import math
import time

import numpy as np
import torch

from garmentnerf.body.model import BodyModel
from garmentnerf.geometry.body_points import main_component_faces
from garmentnerf.geometry.projection import DEFAULT_CHUNK_SIZE, SurfaceProjector
from garmentnerf.geometry.projection_dense import (DEFAULT_DENSE_NEIGHBOURS, DEFAULT_MEMORY_BUDGET, RANKINGS,
                                                   DenseSurfaceProjector)
from garmentnerf.motion.library import load_motion

__all__ = ["benchmark_projection", "benchmark_dense_projection", "measure_dense_mismatch", "near_surface_points"]


def near_surface_points(vertices: torch.Tensor, normals: torch.Tensor, count: int, spread: float, seed: int = 0) -> torch.Tensor:
    """(count, 3) points offset from random vertices along their normals by U(-spread, spread)
    plus isotropic jitter: the distribution NeRF samples around a body have."""
    g = torch.Generator().manual_seed(seed)
    idx = torch.randint(0, vertices.shape[0], (count,), generator=g)
    offset = (torch.rand(count, 1, generator=g) * 2 - 1) * spread
    jitter = torch.randn(count, 3, generator=g) * spread * 0.3
    return vertices[idx] + normals[idx] * offset + jitter


def benchmark_projection(n_points: int = 262144, *, vertices: torch.Tensor | np.ndarray | None = None,
                         faces: torch.Tensor | np.ndarray | None = None, band: float = 0.1,
                         far_fraction: float = 0.05, far: float = 3.0, repeats: int = 3, seed: int = 0,
                         chunk_size: int = DEFAULT_CHUNK_SIZE) -> dict:
    """Time :meth:`PosedSurface.project <garmentnerf.geometry.projection.PosedSurface.project>` on float32 points around a mesh.

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
    # local: only here: the rest of the module (foundation_bench's near_surface_points) needs no mesh
    # library, and trimesh costs 0.8 s
    import trimesh

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

    projector = SurfaceProjector(torch.as_tensor(np.asarray(mesh.faces)), verts.shape[0], chunk_size=chunk_size)
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
        "us_per_point": seconds / n_points * 1e6,
        "points_per_second": n_points / seconds if seconds > 0 else math.inf,
        "bounds_per_point": stats["bounds"] / n_points,
        "pairs_per_point": stats["pairs"] / n_points,
        "torch_threads": torch.get_num_threads(),
    }


def _body_frame(frame: int = 10):
    """(faces (F, 3) long of the skin, posed vertices (V, 3) float64, V) of the bundled body walking."""
    body = BodyModel.default()
    posed = load_motion("walk", body).pose(body)
    verts = posed.vertices[min(frame, posed.vertices.shape[0] - 1)].to(torch.float64)
    faces = body.faces[torch.as_tensor(main_component_faces(body.asset.faces))]
    return faces, verts, body.asset.num_vertices


def _sample_points(verts: torch.Tensor, faces: torch.Tensor, n_box: int, n_shell: int, shell: float, pad: float,
                   seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(box points, shell points) float64: uniform in the padded bounding box; surface samples
    moved along the face normal by a uniform offset in (-shell, shell)."""
    g = torch.Generator().manual_seed(seed)
    lo, hi = verts.min(dim=0).values - pad, verts.max(dim=0).values + pad
    box = lo + (hi - lo) * torch.rand(n_box, 3, generator=g, dtype=torch.float64)
    a, b, c = (verts[faces[:, i]] for i in range(3))
    n = torch.cross(b - a, c - a, dim=1)
    area = n.norm(dim=1)
    f = torch.multinomial(area, n_shell, replacement=True, generator=g)
    r = torch.rand(n_shell, 2, generator=g, dtype=torch.float64)
    flip = r.sum(1) > 1
    r[flip] = 1.0 - r[flip]
    p = a[f] + r[:, :1] * (b[f] - a[f]) + r[:, 1:] * (c[f] - a[f])
    h = (torch.rand(n_shell, 1, generator=g, dtype=torch.float64) * 2.0 - 1.0) * shell
    return box, p + h * n[f] / area[f].unsqueeze(1)


def measure_dense_mismatch(ks=(4, 8, 16), n_box: int = 100_000, n_shell: int = 100_000, *, shell: float = 0.15,
                           pad: float = 0.3, tol: float = 1e-5, frame: int = 10, seed: int = 0,
                           device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32) -> list[dict]:
    """How often the uncertified dense search differs from the exact projector on the bundled body.

    Body: :meth:`BodyModel.default` posed by frame ``frame`` of the "walk" motion, skin only.
    Points: ``n_box`` uniform in the bounding box grown by ``pad`` m and ``n_shell`` at signed
    heights uniform in (-shell, shell) m over uniform surface samples. For each k and ranking
    ("distance": the k nearest vertices; "power": the k vertices of least power) the first pass
    alone (``certify=False``) is compared with :class:`SurfaceProjector` in float64.

    Measured (walk frame 10, 50k box points with pad 0.3 m, 50k shell points, float32 search):
    fraction of points whose distance is off by > 1e-5 m / max |difference| / fraction failing
    the certificate, first pass only:

    ========  ===  ==================================  =====================================
    ranking    k   box                                 shell |h| < 0.15 m
    ========  ===  ==================================  =====================================
    power      4   0       / 8e-8 m   / 0.4 %          0.05 %  / 1.7 mm   / 8.0 %
    power      8   0       / 8e-8 m   / 0.004 %        0.002 % / 1.9e-5 m / 0.45 %
    power     16   0       / 8e-8 m   / 0              0       / 6e-8 m   / 0.014 %
    distance   4   0.002 % / 8.1e-5 m / 48 %           0.066 % / 4.6 mm   / 88 %
    distance   8   0       / 8e-8 m   / 21 %           0.006 % / 0.6 mm   / 49 %
    distance  16   0       / 8e-8 m   / 7 %            0       / 6e-8 m   / 21 %
    ========  ===  ==================================  =====================================

    No sign differed; with ``certify=True`` every case matched to 8e-8 m (float32 rounding).

    Returns:
        one dict per (ranking, k, set): ``ranking``, ``k``, ``set`` ("box" / "shell"),
        ``mismatch_fraction``, ``max_abs_diff`` (m), ``uncertified_fraction`` (points the
        certificate sends to a retry), ``sign_flips`` (points whose sign differs and whose
        exact |h| > tol), and ``certified_max_abs_diff`` (with retries).
    """
    faces, verts, V = _body_frame(frame)
    box, shell_pts = _sample_points(verts, faces, n_box, n_shell, shell, pad, seed)
    exact = SurfaceProjector(faces, V).bind(verts, torch.float64)
    reference = {name: exact.project(pts) for name, pts in (("box", box), ("shell", shell_pts))}
    rows = []
    for ranking in RANKINGS:
        for k in ks:
            projector = DenseSurfaceProjector(faces, V, neighbours=k, ranking=ranking, certify=False)
            surface = projector.bind(verts.to(device), dtype)
            certified = DenseSurfaceProjector(faces, V, neighbours=k, ranking=ranking).bind(verts.to(device), dtype)
            for name, pts in (("box", box), ("shell", shell_pts)):
                ref = reference[name]
                stats = {}
                out = surface.project(pts.to(device, dtype), stats=stats)
                diff = (out.distance.double().cpu() - ref.distance).abs()
                flips = ((torch.sign(out.signed_distance.double().cpu()) != torch.sign(ref.signed_distance))
                         & (ref.distance > tol))
                cert = certified.project(pts.to(device, dtype))
                cdiff = (cert.distance.double().cpu() - ref.distance).abs()
                rows.append({
                    "ranking": ranking, "k": k, "set": name,
                    "mismatch_fraction": float((diff > tol).double().mean()),
                    "max_abs_diff": float(diff.max()),
                    "uncertified_fraction": stats["retried"] / max(1, pts.shape[0]),
                    "sign_flips": int(flips.sum()),
                    "certified_max_abs_diff": float(cdiff.max()),
                })
    return rows


def benchmark_dense_projection(n_points: int = 262144, device: torch.device | str = "cpu", *, repeats: int = 3,
                               neighbours: int = DEFAULT_DENSE_NEIGHBOURS, ranking: str = "power",
                               certify: bool = True, memory_budget: int = DEFAULT_MEMORY_BUDGET,
                               far_fraction: float = 0.05, band: float = 0.1, seed: int = 0,
                               stats: dict | None = None) -> float:
    """Points per second of :meth:`DensePosedSurface.project <garmentnerf.geometry.projection_dense.DensePosedSurface.project>` on the bundled body (walk frame).

    Points (float32): ``1 - far_fraction`` of them at heights uniform in +-``band`` m over the
    skin, the rest uniform in the bounding box grown by 1 m. Best of ``repeats`` timed runs after
    one warm-up (CUDA is synchronised around each run).

    Args:
        stats: if given, filled with ``seconds``, ``bind_seconds``, ``n_points``, ``device``,
            ``retried_fraction``, ``pairs_per_point`` and ``torch_threads``.
    """
    if n_points < 1:
        raise ValueError(f"n_points must be positive, got {n_points}")
    device = torch.device(device)
    faces, verts, V = _body_frame()
    n_far = int(round(n_points * far_fraction))
    box, near = _sample_points(verts, faces, n_far, n_points - n_far, band, 1.0, seed)
    pts = torch.cat([near, box])[torch.randperm(n_points, generator=torch.Generator().manual_seed(seed))]
    pts = pts.to(device, torch.float32)
    projector = DenseSurfaceProjector(faces, V, neighbours=neighbours, ranking=ranking, certify=certify,
                                      memory_budget=memory_budget)

    def sync():
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    vd = verts.to(device, torch.float32)
    projector.bind(vd)  # copies the topology tables to the device
    sync()
    t0 = time.perf_counter()
    surface = projector.bind(vd)
    sync()
    bind_seconds = time.perf_counter() - t0
    run_stats: dict = {}
    surface.project(pts, stats=run_stats)  # warm-up
    times = []
    for _ in range(max(1, repeats)):
        sync()
        t0 = time.perf_counter()
        surface.project(pts)
        sync()
        times.append(time.perf_counter() - t0)
    seconds = min(times)
    if stats is not None:
        stats.update(seconds=seconds, bind_seconds=bind_seconds, n_points=n_points, device=str(device),
                     retried_fraction=run_stats["retried"] / n_points,
                     pairs_per_point=run_stats["pairs"] / n_points, torch_threads=torch.get_num_threads())
    return n_points / seconds if seconds > 0 else math.inf
