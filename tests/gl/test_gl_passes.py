"""The OpenGL passes against independent references (trimesh ray casting, exact geometry)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial import cKDTree
from trimesh.ray.ray_triangle import RayMeshIntersector

from garmentnerf.conventions import Camera, camera_rays, look_at, project_points
from garmentnerf.gl.camera_pass import CameraPass
from garmentnerf.gl.context import GLUnavailableError, create_context, make_current
from garmentnerf.gl.dilation import NearestTexelDilation
from garmentnerf.gl.shaders import shader_root, shader_source
from garmentnerf.gl.uv_raster import UVAttributeRasterizer
from garmentnerf.model.uv_maps import sample_uv_map, texel_centers_uv, uv_to_grid

EDGE_BARY = 1e-3  # a ray hit with a barycentric below this is "on an edge": either face may win


# ---------------------------------------------------------------------------------------------
# scenes


def _camera(width: int, height: int, skew: float = 0.0) -> Camera:
    """Off-centre principal point, non-square image, unequal focal lengths."""
    K = np.array([[1.05 * width, skew, 0.41 * width + 0.3], [0.0, 1.1 * width, 0.57 * height - 0.2],
                  [0.0, 0.0, 1.0]])
    R, t = look_at([0.7, -2.2, 0.9], [0.08, 0.05, -0.03])
    return Camera(K, R, t, width, height)


def _icosphere():
    return trimesh.creation.icosphere(subdivisions=3, radius=0.45)


def _box():
    rot = trimesh.transformations.euler_matrix(0.3, -0.5, 0.8)
    rot[:3, 3] = [0.05, 0.0, 0.02]
    return trimesh.creation.box(extents=[0.6, 0.45, 0.7], transform=rot)


def _ray_reference(mesh: trimesh.Trimesh, camera: Camera):
    """Nearest and farthest hits of the pixel-centre rays, by trimesh (float64)."""
    origins, dirs = camera_rays(camera, dtype=torch.float64)
    origins, dirs = origins.reshape(-1, 3).numpy(), dirs.reshape(-1, 3).numpy()
    tri, ray, loc = RayMeshIntersector(mesh).intersects_id(origins, dirs, multiple_hits=True,
                                                           return_locations=True)
    dist = np.einsum("ij,ij->i", loc - origins[ray], dirs[ray])
    n = len(origins)
    ref = {}
    for name, order in (("near", np.argsort(-dist)), ("far", np.argsort(dist))):
        face = np.full(n, -1)
        point = np.full((n, 3), np.nan)
        face[ray[order]] = tri[order]  # the last write per ray wins: nearest (or farthest)
        point[ray[order]] = loc[order]
        hit = face >= 0
        bary = np.zeros((n, 3))
        bary[hit] = trimesh.triangles.points_to_barycentric(mesh.triangles[face[hit]], point[hit])
        z = np.full(n, np.inf)
        z[hit] = (point[hit] @ camera.R.T + camera.t)[:, 2]
        ref[name] = dict(face=face, point=point, bary=bary, z=z, hit=hit,
                         interior=hit & (bary.min(axis=1) > EDGE_BARY))
    return ref


# ---------------------------------------------------------------------------------------------
# context and shader loading


def test_shader_files_found_and_defines_inserted():
    assert (shader_root() / "camera_pass.vert").is_file()
    src = shader_source("uv_attributes.frag", {"NUM_TARGETS": 3})
    lines = src.splitlines()
    assert lines[0].startswith("#version 330")
    assert lines[1] == "#define NUM_TARGETS 3"


def test_context_is_gl33_core(gl_context):
    assert gl_context.version_code >= 330


def test_context_failure_is_one_clear_line(monkeypatch):
    import moderngl

    def fail(*args, **kwargs):
        raise Exception("eglGetDisplay failed\nsecond line")

    monkeypatch.setattr(moderngl, "create_standalone_context", fail)
    with pytest.raises(GLUnavailableError) as info:
        create_context(headless=True)
    message = str(info.value)
    assert isinstance(info.value, RuntimeError)
    assert "\n" not in message
    assert "libegl1 libegl-mesa0 libgl1-mesa-dri" in message


# ---------------------------------------------------------------------------------------------
# camera pass


@pytest.mark.parametrize("mesh_fn, skew", [(_icosphere, 0.0), (_box, 3.0)])
def test_camera_pass_matches_ray_casting(gl_context, mesh_fn, skew):
    mesh = mesh_fn()
    camera = _camera(160, 120, skew)
    uv = mesh.vertices[:, [0, 2]] * 0.4 + 0.5  # affine in 3D, so exact on every triangle
    with CameraPass(gl_context) as cam_pass:
        out = cam_pass.render(mesh.vertices, mesh.faces, camera, uv=uv, uv_faces=mesh.faces,
                              depth_range=True)
        ranged = cam_pass.render_depth_range(mesh.vertices, mesh.faces, camera)
    ref = _ray_reference(mesh, camera)
    near, far = ref["near"], ref["far"]
    H, W = camera.height, camera.width
    assert out.depth.shape == (H, W) and out.depth.dtype == torch.float32
    assert out.face_id.shape == (H, W) and out.face_id.dtype == torch.int64
    assert out.bary.shape == (H, W, 3) and out.uv.shape == (H, W, 2)
    assert out.mask.dtype == torch.bool

    mask = out.mask.reshape(-1).numpy()
    face = out.face_id.reshape(-1).numpy()
    depth = out.depth.reshape(-1).numpy().astype(np.float64)
    bary = out.bary.reshape(-1, 3).numpy().astype(np.float64)
    assert near["hit"].sum() > 0.1 * H * W

    # Coverage: any disagreement only at a silhouette edge (ray grazing an edge).
    gl_only = mask & ~near["hit"]
    ray_only = near["hit"] & ~mask
    assert np.all(bary[gl_only].min(axis=1) < EDGE_BARY)
    assert np.all(near["bary"][ray_only].min(axis=1) < EDGE_BARY)
    assert gl_only.sum() + ray_only.sum() <= 0.002 * H * W
    assert np.all(face[~mask] == -1) and np.all(np.isinf(depth[~mask]))
    assert np.all(bary[~mask] == 0)

    # Depth is camera z (not ray length). The rasteriser snaps vertices to 1/256 pixel, which at
    # grazing angles moves depth by ~1e-4 relative; elsewhere it agrees to float32 precision.
    # Face ids equal off edges.
    both = mask & near["hit"]
    interior = near["interior"] & mask
    with np.errstate(invalid="ignore"):  # inf - inf off the body
        rel = np.abs(depth - near["z"]) / np.where(both, near["z"], 1.0)
    assert np.max(rel[both]) < 1e-3
    assert np.percentile(rel[interior], 99) < 1e-5
    assert interior.sum() > 0.9 * both.sum()
    # (at grazing silhouettes vertex snapping can hand a pixel to the neighbouring triangle)
    assert np.mean(face[interior] != near["face"][interior]) < 2e-3
    interior &= face == near["face"]

    # Barycentrics rebuild the ray hit point; the UV is the affine function of it.
    hit_points = np.einsum("nk,nkd->nd", bary[interior], mesh.vertices[mesh.faces[face[interior]]])
    np.testing.assert_allclose(hit_points, near["point"][interior], atol=2e-5)
    np.testing.assert_allclose(bary.sum(axis=1)[mask], 1.0, atol=1e-5)
    uv_img = out.uv.reshape(-1, 2).numpy()
    np.testing.assert_allclose(uv_img[interior], near["point"][interior][:, [0, 2]] * 0.4 + 0.5, atol=2e-5)

    # The point rebuilt at pixel (r, c) projects back to the pixel centre (c, r).
    all_points = np.einsum("nk,nkd->nd", bary[mask], mesh.vertices[mesh.faces[face[mask]]])
    pix, z = project_points(camera, torch.from_numpy(all_points))
    rows, cols = np.divmod(np.flatnonzero(mask), W)
    np.testing.assert_allclose(pix.numpy(), np.stack([cols, rows], -1), atol=2e-3)
    np.testing.assert_allclose(z.numpy(), depth[mask], rtol=1e-5)

    # Farthest surface (back faces included), and render_depth_range agrees with the flag.
    depth_far = out.depth_far.reshape(-1).numpy()
    far_ok = far["interior"] & mask
    assert far_ok.sum() > 0.8 * both.sum()
    assert np.max(np.abs(depth_far[far_ok] - far["z"][far_ok]) / far["z"][far_ok]) < 1e-4
    np.testing.assert_array_equal(out.face_id_far.reshape(-1).numpy()[far_ok], far["face"][far_ok])
    assert torch.all(out.depth_far[out.mask] >= out.depth[out.mask])
    assert torch.equal(ranged.mask, out.mask)
    assert torch.equal(ranged.near, out.depth) and torch.equal(ranged.far, out.depth_far)


@pytest.mark.parametrize("width, height", [(1024, 768), (512, 512), (37, 23)])
def test_projected_point_lands_in_its_pixel(gl_context, width, height):
    """Tiny fronto-parallel triangles around back-projected points: each covers exactly the pixel
    whose centre ``project_points`` puts its point nearest to, and nothing when the point sits at a
    pixel corner (a half-pixel convention error fails one or the other)."""
    rng = np.random.default_rng(1)
    camera = _camera(width, height, skew=1.5)
    n = 40
    flat = rng.choice(width * height, size=n, replace=False)
    rows, cols = np.divmod(flat, width)
    centre = np.stack([cols, rows], -1) + rng.uniform(-0.08, 0.08, (n, 2))
    corner = np.stack([cols, rows], -1) + 0.5 + rng.uniform(-0.03, 0.03, (n, 2))
    z = rng.uniform(0.5, 5.0, n)
    Kinv = np.linalg.inv(camera.K)

    def unproject(pix, radius):
        angles = rng.uniform(0, 2 * np.pi) + np.array([0, 2, 4]) * np.pi / 3
        tri_pix = pix[:, None, :] + radius * np.stack([np.cos(angles), np.sin(angles)], -1)
        hom = np.concatenate([tri_pix, np.ones((n, 3, 1))], -1)
        cam = (hom @ Kinv.T) * z[:, None, None]
        world = (cam - camera.t) @ camera.R  # R^T (x - t)
        return world.reshape(-1, 3)

    # Points: their projection is where we put them.
    points_cam = np.concatenate([centre, np.ones((n, 1))], -1) @ Kinv.T * z[:, None]
    points = (points_cam - camera.t) @ camera.R
    pix, depth = project_points(camera, torch.from_numpy(points))
    np.testing.assert_allclose(pix.numpy(), centre, atol=1e-6)

    verts = np.concatenate([unproject(centre, 0.3), unproject(corner, 0.1)])
    faces = np.arange(len(verts)).reshape(-1, 3)
    with CameraPass(gl_context) as cam_pass:
        out = cam_pass.render(verts, faces, camera)
    expected = torch.full((height, width), -1, dtype=torch.int64)
    expected[torch.from_numpy(rows), torch.from_numpy(cols)] = torch.arange(n)
    assert torch.equal(out.face_id, expected)
    np.testing.assert_allclose(out.depth[torch.from_numpy(rows), torch.from_numpy(cols)].numpy(), z, rtol=1e-5)


def test_camera_pass_depth_test_picks_closest_and_resizes(gl_context):
    """Two overlapping quads drawn far-first; the closer one wins. Several sizes on one pass."""
    quad = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], dtype=np.float64)
    faces = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    R = np.eye(3)
    with CameraPass(gl_context) as cam_pass:
        for size in ((64, 48), (33, 65), (64, 48)):
            K = np.array([[40.0, 0, size[0] / 2 - 0.5], [0, 40.0, size[1] / 2 - 0.5], [0, 0, 1]])
            camera = Camera(K, R, np.zeros(3), *size)
            verts = np.concatenate([quad * 3 + [0, 0, 3.0], quad * 2 + [0, 0, 2.0]])
            out = cam_pass.render(verts, faces, camera)
            assert out.mask.all()
            assert torch.all((out.face_id == 2) | (out.face_id == 3))
            torch.testing.assert_close(out.depth, torch.full(size[::-1], 2.0))
            ranged = cam_pass.render_depth_range(verts, faces, camera)
            torch.testing.assert_close(ranged.far, torch.full(size[::-1], 3.0))


# ---------------------------------------------------------------------------------------------
# UV raster


def _cube_with_charts(n: int = 12, margin: float = 0.05):
    """A unit cube, each face an n x n grid and its own UV chart; charts are rotated / mirrored
    and scaled differently inside the cells of a 3 x 2 atlas. One UV vertex per 3D vertex."""
    s = np.linspace(0.0, 1.0, n + 1)
    a, b = (x.ravel() for x in np.meshgrid(s, s, indexing="ij"))
    grid = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    q = np.stack([grid[:-1, :-1], grid[1:, :-1], grid[1:, 1:], grid[:-1, 1:]], -1).reshape(-1, 4)
    tris = np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
    verts, faces, uvs = [], [], []
    for k in range(6):
        axis, side = divmod(k, 2)
        p = np.zeros((len(a), 3))
        u_axis, v_axis = [i for i in range(3) if i != axis]
        p[:, u_axis], p[:, v_axis], p[:, axis] = a - 0.5, b - 0.5, side - 0.5
        local = np.stack([a, b], -1)
        if k % 2:  # rotate the chart by 90 degrees
            local = np.stack([1 - b, a], -1)
        if k == 4:  # mirror one
            local = local[:, ::-1]
        scale = 1.0 - 2 * margin - 0.1 * (k % 3) / 3
        cell = np.array([k % 3, k // 3], dtype=np.float64)
        uv = (cell + margin + local * scale) / np.array([3.0, 2.0])
        faces.append(tris + len(a) * k)
        verts.append(p)
        uvs.append(uv)
    return np.concatenate(verts), np.concatenate(faces), np.concatenate(uvs)


def _random_surface_points(faces, rng, count):
    face = rng.integers(0, len(faces), count)
    r1, r2 = rng.random(count), rng.random(count)
    s = np.sqrt(r1)
    bary = np.stack([1 - s, s * (1 - r2), s * r2], -1)
    return face, bary


def test_uv_to_grid_reads_the_texel_under_a_uv():
    """Row 0 is v = 0 and column 0 is u = 0: the texel whose square holds (u, v) is read."""
    H, W = 6, 10
    values = torch.arange(H * W, dtype=torch.float32).reshape(H, W, 1)
    centres = texel_centers_uv(H, W).reshape(-1, 2)
    np.testing.assert_allclose(centres[W + 2].numpy(), [2.5 / W, 1.5 / H])
    np.testing.assert_allclose(sample_uv_map(values, centres)[:, 0].numpy(), np.arange(H * W), atol=1e-5)
    uv = torch.tensor([[0.01, 0.02], [0.99, 0.98], [0.31, 0.72]])
    near = sample_uv_map(values, uv, mode="nearest")[:, 0]
    expected = torch.floor(uv[:, 1] * H) * W + torch.floor(uv[:, 0] * W)
    torch.testing.assert_close(near, expected)
    torch.testing.assert_close(uv_to_grid(torch.tensor([[0.0, 1.0], [0.5, 0.25]])),
                               torch.tensor([[-1.0, 1.0], [0.0, -0.5]]))


@pytest.mark.parametrize("method", ["gather", "draw"])
def test_uv_raster_position_lookup(gl_context, method):
    verts, faces, uv = _cube_with_charts()
    res = 128
    with UVAttributeRasterizer(gl_context, uv, faces, res, method=method) as raster:
        # 12 channels: the position, repeated with offsets so every render target is checked.
        attrs = np.concatenate([verts + 10.0 * i for i in range(4)], axis=1).astype(np.float32)
        values, mask = raster.render(torch.from_numpy(attrs))
        raw = raster.render_raw(torch.from_numpy(attrs))
    assert values.shape == (res, res, 12) and values.dtype == torch.float32
    assert mask.shape == (res, res) and mask.dtype == torch.bool

    rng = np.random.default_rng(0)
    face, bary = _random_surface_points(faces, rng, 40000)
    # Plus points on the chart borders themselves: on the boundary edges (used by one triangle).
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    _, inverse, counts = np.unique(edges, axis=0, return_inverse=True, return_counts=True)
    boundary = np.flatnonzero(counts[inverse.ravel()] == 1)  # rows of `edges`
    pick = rng.choice(boundary, 5000)
    edge_face, edge_k = pick % len(faces), pick // len(faces)  # edge k joins corners k, k+1
    t = rng.random(5000)
    edge_bary = np.zeros((5000, 3))
    edge_bary[np.arange(5000), edge_k] = 1 - t
    edge_bary[np.arange(5000), (edge_k + 1) % 3] = t
    face, bary = np.concatenate([face, edge_face]), np.concatenate([bary, edge_bary])
    true_pos = np.einsum("nk,nkd->nd", bary, verts[faces[face]])
    point_uv = torch.from_numpy(np.einsum("nk,nkd->nd", bary, uv[faces[face]]).astype(np.float32))
    looked_up = sample_uv_map(values, point_uv).numpy().astype(np.float64)
    for i in range(4):
        err = np.linalg.norm(looked_up[:, 3 * i:3 * i + 3] - 10.0 * i - true_pos, axis=1)
        # Interior points (all four bilinear taps covered): exact, the map is affine per chart.
        x = point_uv.numpy() * [res, res] - 0.5
        c0, r0 = np.floor(x[:, 0]).astype(int), np.floor(x[:, 1]).astype(int)
        taps = mask.numpy()[np.clip([r0, r0, r0 + 1, r0 + 1], 0, res - 1),
                            np.clip([c0, c0 + 1, c0, c0 + 1], 0, res - 1)]
        interior = taps.all(axis=0)
        assert (~interior).sum() > 5000  # plenty of points near chart borders
        assert err[interior].max() < 2e-5
        # Near borders, bilinear taps read gutter texels holding the value of a covered texel up to
        # ~1 texel away, so the error stays below one texel's footprint: the smallest chart spans
        # 0.833 * 128 / 3 = 35.6 texels of a 1 m face (2.8 cm per texel). Measured at 128^2: median
        # 3e-3 and max 1.1e-2 of the cube's diagonal over border points.
        texel_m = 1.0 / ((1 - 2 * 0.05 - 0.2 / 3) * res / 3)
        diagonal = np.sqrt(3.0)
        assert err.max() < texel_m
        assert err.max() / diagonal < 1.5e-2
        assert np.median(err[~interior]) / diagonal < 5e-3
    # Without the gutter, border lookups are pulled towards 0.
    raw_err = np.linalg.norm(sample_uv_map(raw, point_uv).numpy()[:, :3] - true_pos, axis=1)
    assert raw_err.max() > 10 * err.max()


@pytest.mark.parametrize("method", ["gather", "draw"])
def test_uv_raster_coverage_matches_point_in_triangle(gl_context, method):
    verts, faces, uv = _cube_with_charts(n=5)
    with UVAttributeRasterizer(gl_context, uv, faces, (48, 80), method=method) as raster:
        mask = raster.mask.numpy()
        values, mask2 = raster.render(np.ones((len(uv), 1), np.float32))
    assert mask.shape == (48, 80) and torch.equal(mask2, raster.mask)
    centres = texel_centers_uv(48, 80, dtype=torch.float64).reshape(-1, 2).numpy()
    inside = np.zeros(len(centres), bool)
    ambiguous = np.zeros(len(centres), bool)
    for tri in uv[faces]:
        e1, e2 = tri[1] - tri[0], tri[2] - tri[0]
        det = e1[0] * e2[1] - e1[1] * e2[0]
        d = centres - tri[0]
        b1 = (d[:, 0] * e2[1] - d[:, 1] * e2[0]) / det
        b2 = (e1[0] * d[:, 1] - e1[1] * d[:, 0]) / det
        b = np.stack([1 - b1 - b2, b1, b2], -1)
        inside |= b.min(axis=1) > 1e-6
        ambiguous |= np.abs(b.min(axis=1)) <= 1e-6
    sure = ~ambiguous
    np.testing.assert_array_equal(mask.reshape(-1)[sure], inside[sure])
    assert np.all(values[..., 0].numpy()[mask] == pytest.approx(1.0))


def test_dilation_fills_gutter_from_nearest_covered_texel(gl_context):
    verts, faces, uv = _cube_with_charts(n=4, margin=0.12)
    radius = 4.0
    with UVAttributeRasterizer(gl_context, uv, faces, 64, dilation_radius=radius) as raster:
        rng = np.random.default_rng(3)
        attrs = rng.standard_normal((len(uv), 5)).astype(np.float32)
        values, mask = raster.render(attrs)
        raw = raster.render_raw(attrs)
        assert torch.equal(mask, raster.mask)
    vals, raw, mask = values.numpy(), raw.numpy(), mask.numpy()
    np.testing.assert_array_equal(vals[mask], raw[mask])  # covered texels untouched

    covered = np.argwhere(mask)
    empty = np.argwhere(~mask)
    tree = cKDTree(covered)
    dist, _ = tree.query(empty)
    assert (dist <= radius).sum() > 100 and (dist > radius).sum() > 100  # both cases exercised
    for (r, c), d in zip(empty, dist):
        if d > radius:
            assert np.all(vals[r, c] == 0)
            continue
        nearest = covered[tree.query_ball_point([r, c], d + 1e-9)]  # all ties
        assert any(np.array_equal(vals[r, c], raw[rr, cc]) for rr, cc in nearest)


def test_dilation_on_a_random_mask():
    rng = np.random.default_rng(5)
    mask = rng.random((40, 30)) < 0.04
    values = torch.from_numpy(rng.standard_normal((40, 30, 2)).astype(np.float32))
    values[~torch.from_numpy(mask)] = 0
    dil = NearestTexelDilation(mask, radius=2.5)
    out = dil.apply(values)
    assert torch.equal(out[torch.from_numpy(mask)], values[torch.from_numpy(mask)])
    covered = np.argwhere(mask)
    tree = cKDTree(covered)
    for r, c in np.argwhere(~mask):
        d, _ = tree.query([r, c])
        if d <= 2.5:
            ties = covered[tree.query_ball_point([r, c], d + 1e-9)]
            assert any(torch.equal(out[r, c], values[rr, cc]) for rr, cc in ties)
        else:
            assert torch.all(out[r, c] == 0)


def test_uv_raster_gather_is_differentiable(gl_context):
    verts, faces, uv = _cube_with_charts(n=3)
    with UVAttributeRasterizer(gl_context, uv, faces, 32) as raster:
        attrs = torch.randn(len(uv), 7, requires_grad=True)
        values, _ = raster.render(attrs)
        values.sum().backward()
    assert attrs.grad is not None and attrs.grad.abs().sum() > 0


# ---------------------------------------------------------------------------------------------
# several contexts


def test_two_contexts_in_one_process(gl_context):
    try:
        other = create_context(headless=True)
    except GLUnavailableError as exc:
        pytest.skip(f"no second headless OpenGL context: {exc}")
    try:
        mesh = _icosphere()
        camera = _camera(80, 60)
        verts, faces, uv = _cube_with_charts(n=4)
        attrs = torch.from_numpy(np.concatenate([verts, verts], 1).astype(np.float32))
        passes = [CameraPass(gl_context), CameraPass(other)]
        rasters = [UVAttributeRasterizer(c, uv, faces, 32, method="draw") for c in (gl_context, other)]
        outs = []
        for _ in range(2):  # interleaved use
            for cam_pass, raster in zip(passes, rasters):
                outs.append((cam_pass.render(mesh.vertices, mesh.faces, camera),
                             raster.render(attrs)))
        reference = outs[0]
        for cam_out, uv_out in outs[1:]:
            assert torch.equal(cam_out.face_id, reference[0].face_id)
            assert torch.equal(cam_out.depth, reference[0].depth)
            assert torch.equal(uv_out.values, reference[1].values)
        assert reference[0].mask.sum() > 500 and reference[1].mask.sum() > 200
        # Releasing one context's objects and the context leaves the other working.
        passes[1].release()
        other.release()
        other = None
        rasters[1].release()  # after its context: a no-op, no error
        again = passes[0].render(mesh.vertices, mesh.faces, camera)
        assert torch.equal(again.face_id, reference[0].face_id)
        assert torch.equal(rasters[0].render(attrs).values, reference[1].values)
        # The context stays usable directly after the passes ran.
        make_current(gl_context)
        assert gl_context.texture((2, 2), 4, dtype="f4").glo > 0
        passes[0].release()
        rasters[0].release()
    finally:
        if other is not None:
            other.release()


def test_benchmark_runs(gl_context):
    from garmentnerf.perf.gl_bench import benchmark_gl_passes

    result = benchmark_gl_passes(gl_context, runs=2, warmup=1, image_size=64)
    for key in ("uv_raster_ms", "uv_raster_draw_ms", "camera_pass_ms", "depth_range_ms"):
        assert result[key] > 0
