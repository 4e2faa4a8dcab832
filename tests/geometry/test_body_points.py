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
