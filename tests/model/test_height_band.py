"""The garment's height band (garmentnerf.model.height_band) against brute-force references, on the
skin faces where the skin-only and whole-body face numberings disagree."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from garmentnerf.model.height_band import HeightRange, dilate_vertex_values, measure_height_range
from garmentnerf.motion.library import load_motion


@pytest.fixture(scope="module")
def posed_skin(body):
    return load_motion("walk", body).slice(10, 11).pose(body).vertices[0].float()


@pytest.fixture(scope="module")
def tshirt_scene(tmp_path_factory, gl_context):
    from garmentnerf.data.synthetic import make_rigged_scene

    return make_rigged_scene(tmp_path_factory.mktemp("tshirt") / "scene", garment="tshirt", motion="walk",
                             frames=2, views=2, size=32, held_out_views=0, gl_context=gl_context)


def _closest_skin_faces(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray):
    """trimesh's closest skin face (a row of ``faces``) and barycentrics of each point."""
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    closest, _, tri = trimesh.proximity.closest_point(mesh, points)
    bary = trimesh.triangles.points_to_barycentric(mesh.triangles[tri], closest)
    return tri, bary


def test_numberings_differ_and_the_projection_answers_skin_face_ids(projector, posed_skin):
    F = projector.faces.shape[0]
    differ = torch.nonzero(projector.face_subset != torch.arange(F)).squeeze(1)
    # The skin table skips the eyes and teeth: the last 28 skin faces (front torso) are renumbered.
    assert differ.tolist() == list(range(F - 28, F)) and int(projector.face_subset[-1]) > F
    rng = np.random.default_rng(0)
    chosen = torch.cat([differ, torch.as_tensor(rng.choice(F - 28, 300, replace=False))])
    v, f = posed_skin.double(), projector.faces[chosen]
    bary = torch.as_tensor(rng.dirichlet([3.0, 3.0, 3.0], len(chosen)))
    on = (v[f] * bary.unsqueeze(-1)).sum(1)
    normal = torch.nn.functional.normalize(torch.linalg.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), dim=-1)
    points = (on + 0.002 * normal).float()
    got = projector.bind(posed_skin).project(points)
    tri, tbary = _closest_skin_faces(points.double().numpy(), posed_skin.double().numpy(), projector.faces.numpy())
    same = got.face.numpy() == tri
    assert same.mean() > 0.97  # the rest are ties on shared edges
    # trimesh is occasionally a little off inside its face (it is never nearer than ours)
    bary_ok = np.abs(got.bary.numpy()[same] - tbary[same]).max(1) < 1e-4
    assert bary_ok.mean() > 0.99
    assert (got.face.numpy() >= F - 28).sum() >= 20  # the faces the old numbering mixed up are reached
    torch.testing.assert_close(projector.body_face_ids(got.face), projector.face_subset[got.face])


def test_height_band_upper_bound_matches_brute_force_on_the_last_skin_faces(projector, posed_skin):
    F, V = projector.faces.shape[0], posed_skin.shape[0]
    rng = np.random.default_rng(1)
    values = torch.as_tensor(rng.uniform(0.02, 0.3, V), dtype=torch.float32)
    band = HeightRange(-0.05, 0.31, vertex_h_max=values)
    faces = projector.faces
    chosen = torch.arange(F - 28, F)
    v = posed_skin.double()
    bary = torch.as_tensor(rng.dirichlet([3.0, 3.0, 3.0], 28))
    f = faces[chosen]
    points = ((v[f] * bary.unsqueeze(-1)).sum(1) + torch.tensor([0.0, -0.01, 0.0], dtype=torch.float64)).float()
    got = projector.bind(posed_skin).project(points)
    bound = band.upper_bound(got.face, got.bary, faces)
    tri, tbary = _closest_skin_faces(points.double().numpy(), v.numpy(), faces.numpy())
    expected = (values.double().numpy()[faces.numpy()[tri]] * tbary).sum(1)
    np.testing.assert_allclose(bound.numpy(), expected, atol=2e-4)
    keep = band.sample_filter(faces).keep(got)
    h = got.signed_distance
    torch.testing.assert_close(keep, (h >= -0.05) & (h <= bound))


def test_tshirt_scene_band_matches_a_brute_force_measurement(tshirt_scene, body, projector):
    from garmentnerf.data.scene import read_garment_arrays

    band = measure_height_range(tshirt_scene, body, projector=projector, rings=1, margin_out=0.03)
    assert band.h_min < 0 < band.h_max < 0.4 and band.vertex_h_max is not None
    # Brute force: trimesh's closest skin triangle of every garment vertex raises its corners to h.
    faces = projector.faces.numpy()
    betas = body.betas(tshirt_scene.body.get("shape", "average"))
    vmax = np.zeros(body.asset.num_vertices)
    lo, hi = 0.0, 0.0
    for name in tshirt_scene.sequence_names("train"):
        garment = read_garment_arrays(tshirt_scene.garment_path(name))
        motion = tshirt_scene.load_motion(name)
        for t in range(garment.vertices.shape[0]):
            posed = motion.slice(t, t + 1).pose(body, betas).vertices[0].double().numpy()
            pts = garment.vertices[t].astype(np.float64)
            mesh = trimesh.Trimesh(posed, faces, process=False)
            _, dist, tri = trimesh.proximity.closest_point(mesh, pts)
            sign = np.where(trimesh.proximity.signed_distance(mesh, pts) > 0, -1.0, 1.0)  # trimesh: + inside
            h = sign * dist
            lo, hi = min(lo, h.min()), max(hi, h.max())
            np.maximum.at(vmax, faces[tri].reshape(-1), np.repeat(np.clip(h, 0, None), 3))
    assert band.h_min == pytest.approx(lo - 0.05, abs=1e-3) and band.h_max == pytest.approx(hi + 0.03, abs=1e-3)
    expected = (dilate_vertex_values(torch.as_tensor(vmax, dtype=torch.float32), projector.faces, 1) + 0.03
                ).clamp(max=band.h_max)
    # Where the garment raises the bound: the same values, but where a garment vertex is nearest to
    # a skin edge or vertex (ties: another adjacent face raises other corners).
    covered = (expected > 0.031) | (band.vertex_h_max > 0.031)
    diff = (band.vertex_h_max - expected).abs()[covered]
    assert covered.sum() > 500
    assert float(diff.median()) < 1e-4 and float((diff < 2e-3).float().mean()) > 0.9
    assert float(diff.quantile(0.99)) < 0.01
    # the garment reaches skin faces past the numbering the old measurement confused
    covered = torch.nonzero(band.vertex_h_max > 0.031).squeeze(1)
    last_corners = torch.unique(projector.faces[-28:].reshape(-1))
    assert bool(torch.isin(last_corners, covered).any())
