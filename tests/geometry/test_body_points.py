"""Body-aware sample coordinates: b_t, h, b_o and uv against trimesh and analytic cases."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from garmentnerf.body.model import BodyModel
from garmentnerf.body.surface import vertex_normals
from garmentnerf.geometry.body_points import BodyPointProjector, main_component_faces


@pytest.fixture(scope="module")
def setup():
    body = BodyModel.default(dtype=torch.float64)
    rot = torch.randn(1, body.num_joints, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 0.2
    posed = body.pose(rot, torch.tensor([[0.2, -0.1, 0.05]], dtype=torch.float64))
    return body, posed.vertices[0], BodyPointProjector(body)


def test_skin_excludes_eyes_and_teeth(setup):
    body, _, projector = setup
    faces = main_component_faces(body.asset.faces)
    assert 26000 < len(faces) < body.asset.faces.shape[0]
    mesh = trimesh.Trimesh(body.asset.template_vertices, body.asset.faces[faces], process=False)
    assert mesh.is_watertight


def test_points_on_the_surface_map_to_the_canonical_body(setup):
    body, verts, projector = setup
    rng = np.random.default_rng(1)
    faces = projector.faces.numpy()
    f = rng.integers(0, len(faces), 500)
    bary = rng.dirichlet([2.0, 2.0, 2.0], 500)
    points = np.einsum("nk,nkc->nc", bary, verts.numpy()[faces[f]])
    out = projector.project(torch.as_tensor(points), verts)
    np.testing.assert_allclose(out.signed_distance.numpy(), 0.0, atol=1e-9)
    expected_bo = np.einsum("nk,nkc->nc", bary, body.asset.template_vertices.astype(np.float64)[faces[f]])
    np.testing.assert_allclose(out.canonical.numpy(), expected_bo, atol=1e-6)
    uv_faces = projector.uv_faces.numpy()
    expected_uv = np.einsum("nk,nkc->nc", bary, body.asset.uv.astype(np.float64)[uv_faces[f]])
    np.testing.assert_allclose(out.uv.numpy(), expected_uv, atol=1e-6)


def test_offset_points_have_the_right_signed_height(setup):
    body, verts, projector = setup
    normals = vertex_normals(verts, body.faces)
    skin = np.unique(projector.faces.numpy())
    rng = np.random.default_rng(2)
    idx = torch.as_tensor(rng.choice(skin, 300, replace=False))
    # Tiny offsets along the normal: the sign is the offset's, |h| <= offset (a neighbouring face
    # can be nearer where the surface curves towards the point), and on convex spots h = offset.
    for eps in (1e-4, -1e-4):
        out = projector.project(verts[idx] + eps * normals[idx], verts)
        h = out.signed_distance.numpy()
        assert np.all(np.sign(h) == np.sign(eps))
        assert np.all(np.abs(h) <= abs(eps) + 1e-9)
        assert np.mean(np.abs(h - eps) < 2e-6) > 0.6
        np.testing.assert_allclose(out.canonical.numpy(), body.template_vertices[idx].numpy(), atol=5e-3)


def test_distances_match_trimesh_for_near_and_far_points(setup):
    body, verts, projector = setup
    rng = np.random.default_rng(3)
    skin_mesh = trimesh.Trimesh(verts.numpy(), projector.faces.numpy(), process=False)
    near = skin_mesh.sample(600, seed=4) + rng.normal(scale=0.05, size=(600, 3))
    far = rng.normal(size=(100, 3)) * 2.0 + [0, 0, 1]
    points = np.concatenate([near, far])
    out = projector.project(torch.as_tensor(points), verts)
    _, dist, _ = trimesh.proximity.closest_point(skin_mesh, points)
    # trimesh is occasionally a neighbouring face off; ours must never be farther
    assert np.all(out.signed_distance.abs().numpy() <= dist + 1e-9)
    np.testing.assert_allclose(out.signed_distance.abs().numpy(), dist, atol=1e-5)
    inside = trimesh.proximity.signed_distance(skin_mesh, points) > 1e-3  # trimesh: positive inside
    assert np.all(out.signed_distance.numpy()[inside] < 0)


def brute_force_nearest(points: torch.Tensor, verts: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """(N,) float64 distance from every point to its nearest face, every face tested."""
    from garmentnerf.geometry.triangles import closest_point_on_triangles

    a, b, c = (verts[faces[:, i]] for i in range(3))
    out = []
    for p in points:
        cp, _ = closest_point_on_triangles(p.expand(len(faces), 3), a, b, c)
        out.append((cp - p).norm(dim=1).min())
    return torch.stack(out)


def test_exact_search_matches_brute_force_on_a_posed_body(setup):
    # The fast search (tree order from the template, bounds refit to the posed frame) against
    # every face: points near the skin, up to 0.5 m away, far away, and between the legs / at
    # the armpits where two parts of the body are about equally near (the medial axis).
    body, verts, projector = setup
    faces = projector.faces
    g = torch.Generator().manual_seed(3)
    skin = torch.unique(faces)
    normals = vertex_normals(verts, body.faces)
    idx = skin[torch.randint(0, len(skin), (300,), generator=g)]
    near = verts[idx] + normals[idx] * (torch.rand(300, 1, generator=g, dtype=torch.float64) * 0.1 - 0.05)
    lo, hi = verts.amin(0) - 0.5, verts.amax(0) + 0.5
    box = lo + (hi - lo) * torch.rand(200, 3, generator=g, dtype=torch.float64)
    far = torch.randn(20, 3, generator=g, dtype=torch.float64) * 5.0
    # Midpoints of random pairs of skin vertices a few cm to 40 cm apart: on or near the medial axis.
    i, j = skin[torch.randint(0, len(skin), (4000,), generator=g)], skin[torch.randint(0, len(skin), (4000,), generator=g)]
    gap = (verts[i] - verts[j]).norm(dim=1)
    keep = ((gap > 0.03) & (gap < 0.4)).nonzero().squeeze(1)[:150]
    medial = 0.5 * (verts[i[keep]] + verts[j[keep]])
    points = torch.cat([near, box, far, medial])
    for dtype in (torch.float64, torch.float32):
        surface = projector.exact_projector.bind(verts, dtype)
        stats: dict = {}
        proj = surface.project(points.to(dtype), stats=stats)
        q = points.to(dtype).double()  # the points the search saw
        ref = brute_force_nearest(q, verts, faces)
        # The returned face is a nearest face: its float64 distance equals the brute-force minimum.
        a, b, c = (verts[faces[proj.face, k]] for k in range(3))
        from garmentnerf.geometry.triangles import closest_point_on_triangles
        cp, _ = closest_point_on_triangles(q, a, b, c)
        torch.testing.assert_close((cp - q).norm(dim=1), ref, rtol=0, atol=1e-12)
        tol = 1e-12 if dtype == torch.float64 else 1e-6
        torch.testing.assert_close(proj.distance.double(), ref, rtol=0, atol=tol)
    assert stats["pairs"] < 200 * len(points)  # the walk stays local
