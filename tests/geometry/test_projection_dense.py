"""Brute-force torch projector: against the exact KD-tree projector, trimesh, signs, chunking."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from garmentnerf.geometry.projection import SurfaceProjector
from garmentnerf.geometry.projection_dense import DensePosedSurface, DenseSurfaceProjector
from garmentnerf.perf.projection_bench import _sample_points, benchmark_dense_projection

cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")


def _mesh_points(mesh: trimesh.Trimesh, n_near: int, n_far: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    near = mesh.sample(n_near, seed=seed) + rng.normal(scale=0.05, size=(n_near, 3))
    far = rng.uniform(mesh.bounds[0] - 1.0, mesh.bounds[1] + 1.0, size=(n_far, 3))
    return np.concatenate([near, far])


@pytest.fixture(scope="module")
def body_frame():
    from garmentnerf.body.model import BodyModel
    from garmentnerf.geometry.body_points import main_component_faces

    body = BodyModel.default(dtype=torch.float64)
    rot = torch.randn(1, body.num_joints, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 0.2
    verts = body.pose(rot, torch.tensor([[0.2, -0.1, 0.05]], dtype=torch.float64)).vertices[0]
    faces = body.faces[torch.as_tensor(main_component_faces(body.asset.faces))]
    return body, faces, verts


@pytest.mark.parametrize("ranking", ["power", "distance"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_matches_exact_projector_near_the_body(body_frame, ranking, dtype):
    body, faces, verts = body_frame
    V = body.asset.num_vertices
    box, shell = _sample_points(verts, faces, 500, 2500, 0.15, 0.3, seed=1)
    points = torch.cat([box, shell]).to(dtype)
    exact = SurfaceProjector(faces, V).project(points, verts.to(dtype))
    stats = {}
    dense = DenseSurfaceProjector(faces, V, ranking=ranking).bind(verts, dtype).project(points, stats=stats)
    tol = 1e-6 if dtype == torch.float32 else 1e-9
    np.testing.assert_allclose(dense.distance.numpy(), exact.distance.numpy(), atol=tol)
    np.testing.assert_allclose(dense.signed_distance.numpy(), exact.signed_distance.numpy(), atol=tol)
    # Same foot point (the face may differ at a shared edge / corner).
    foot_tol = 1e-4 if dtype == torch.float32 else 1e-6
    np.testing.assert_allclose(dense.closest.numpy(), exact.closest.numpy(), atol=foot_tol)
    assert dense.face.dtype == torch.long and dense.bary.dtype == dtype
    recon = torch.einsum("nk,nkc->nc", dense.bary.double(), verts[faces[dense.face]])
    np.testing.assert_allclose(recon.numpy(), dense.closest.double().numpy(), atol=1e-5)
    assert stats["points"] == points.shape[0] and stats["pairs"] > 0


def test_uncertified_first_pass_is_close_and_certificate_catches_misses(body_frame):
    body, faces, verts = body_frame
    V = body.asset.num_vertices
    box, shell = _sample_points(verts, faces, 1000, 1000, 0.15, 0.3, seed=2)
    points = torch.cat([box, shell])
    exact = SurfaceProjector(faces, V).project(points, verts)
    stats = {}
    first = DenseSurfaceProjector(faces, V, neighbours=2, certify=False).bind(verts).project(points, stats=stats)
    diff = (first.distance - exact.distance).abs()
    assert torch.all(first.distance >= exact.distance - 1e-9)  # never nearer than the truth
    assert stats["retried"] > 0
    assert float(diff.max()) < 0.05


def test_matches_trimesh_on_small_meshes():
    for mesh in (trimesh.creation.icosphere(subdivisions=2, radius=0.7), trimesh.creation.box(extents=(1.0, 0.5, 2.0))):
        points = _mesh_points(mesh, 400, 100, seed=3)
        projector = DenseSurfaceProjector(torch.as_tensor(mesh.faces), len(mesh.vertices), neighbours=4)
        out = projector.project(torch.as_tensor(points), torch.as_tensor(mesh.vertices))
        closest, dist, _ = trimesh.proximity.closest_point(mesh, points)
        assert np.all(out.distance.numpy() <= dist + 1e-9)
        np.testing.assert_allclose(out.distance.numpy(), dist, atol=1e-7)
        np.testing.assert_allclose(out.closest.numpy(), closest, atol=1e-6)
        inside = mesh.contains(points)
        assert np.all(out.signed_distance.numpy()[inside] < 0)
        assert np.all(out.signed_distance.numpy()[~inside & (dist > 1e-9)] > 0)


def test_sign_at_faces_edges_and_corners_of_a_box():
    mesh = trimesh.creation.box(extents=(2.0, 2.0, 2.0))  # big faces: the far-from-corner case
    projector = DenseSurfaceProjector(torch.as_tensor(mesh.faces), len(mesh.vertices), neighbours=1)
    points = torch.tensor([
        [0.0, 0.0, 0.5], [0.1, -0.2, 0.9], [0.0, 0.0, 3.0], [0.3, 0.2, 1.5],  # face interior
        [1.5, 0.0, 1.5], [0.9, 0.0, 0.95], [2.0, 2.0, 2.0], [0.95, 0.95, 0.95],  # edge / corner
    ], dtype=torch.float64)
    out = projector.project(points, torch.as_tensor(mesh.vertices))
    expected = np.array([-0.5, -0.1, 2.0, 0.5, np.sqrt(0.5), -0.05, np.sqrt(3.0), -0.05])
    np.testing.assert_allclose(out.signed_distance.numpy(), expected, atol=1e-12)


def test_chunking_gives_identical_results(body_frame):
    body, faces, verts = body_frame
    V = body.asset.num_vertices
    box, shell = _sample_points(verts, faces, 300, 700, 0.15, 0.3, seed=4)
    points = torch.cat([box, shell]).float()
    whole = DenseSurfaceProjector(faces, V, chunk_size=10**6).bind(verts.float()).project(points)
    for projector in (DenseSurfaceProjector(faces, V, chunk_size=37),
                      DenseSurfaceProjector(faces, V, memory_budget=1)):  # one point per chunk
        part = projector.bind(verts.float()).project(points)
        for name in ("face", "bary", "closest", "distance", "signed_distance"):
            assert torch.equal(getattr(whole, name), getattr(part, name)), name


def test_empty_input_and_validation():
    mesh = trimesh.creation.icosphere(subdivisions=1)
    projector = DenseSurfaceProjector(torch.as_tensor(mesh.faces), len(mesh.vertices))
    surface = projector.bind(torch.as_tensor(mesh.vertices, dtype=torch.float32))
    assert isinstance(surface, DensePosedSurface)
    out = surface.project(torch.empty(0, 3))
    assert len(out) == 0 and out.bary.shape == (0, 3) and out.closest.shape == (0, 3)
    assert out.signed_distance.shape == (0,) and out.face.dtype == torch.long
    with pytest.raises(ValueError):
        surface.project(torch.zeros(4, 2))
    with pytest.raises(ValueError):
        surface.project(torch.tensor([[0.0, float("nan"), 0.0]]))
    with pytest.raises(ValueError):
        DenseSurfaceProjector(torch.as_tensor(mesh.faces), len(mesh.vertices), ranking="nearest")


def test_unused_vertices_are_ignored():
    mesh = trimesh.creation.icosphere(subdivisions=2)
    verts = np.concatenate([mesh.vertices, [[0.0, 0.0, 3.0]]])  # a stray vertex no face uses
    projector = DenseSurfaceProjector(torch.as_tensor(mesh.faces), len(verts), neighbours=1)
    out = projector.project(torch.tensor([[0.0, 0.0, 2.9]], dtype=torch.float64), torch.as_tensor(verts))
    np.testing.assert_allclose(out.distance.numpy(), [1.9], atol=1e-2)


def test_body_point_projector_dense_method_matches_exact(body_frame):
    from garmentnerf.geometry.body_points import BodyPointProjector

    body, faces, verts = body_frame
    box, shell = _sample_points(verts, faces, 200, 800, 0.1, 0.2, seed=5)
    points = torch.cat([box, shell])
    exact = BodyPointProjector(body).project(points, verts)
    dense = BodyPointProjector(body, method="dense").project(points, verts)
    np.testing.assert_allclose(dense.signed_distance.numpy(), exact.signed_distance.numpy(), atol=1e-9)
    np.testing.assert_allclose(dense.closest.numpy(), exact.closest.numpy(), atol=1e-6)
    np.testing.assert_allclose(dense.canonical.numpy(), exact.canonical.numpy(), atol=1e-3)
    with pytest.raises(ValueError):
        BodyPointProjector(body, method="fast")


def test_benchmark_runs_on_cpu():
    stats = {}
    pps = benchmark_dense_projection(256, "cpu", repeats=1, stats=stats)
    assert pps > 0 and stats["n_points"] == 256 and stats["device"] == "cpu"


@cuda
def test_cuda_matches_cpu(body_frame):
    body, faces, verts = body_frame
    V = body.asset.num_vertices
    box, shell = _sample_points(verts, faces, 2000, 8000, 0.15, 0.3, seed=6)
    points = torch.cat([box, shell]).float()
    exact = SurfaceProjector(faces, V).project(points, verts.float())
    projector = DenseSurfaceProjector(faces, V)
    out = projector.project(points.cuda(), verts.float().cuda())
    assert out.face.device.type == "cuda" and out.signed_distance.device.type == "cuda"
    np.testing.assert_allclose(out.distance.cpu().numpy(), exact.distance.numpy(), atol=1e-6)
    np.testing.assert_allclose(out.signed_distance.cpu().numpy(), exact.signed_distance.numpy(), atol=1e-6)
    assert len(projector.project(torch.empty(0, 3, device="cuda"), verts.float().cuda())) == 0


@cuda
def test_cuda_body_point_projector_keeps_outputs_on_device(body_frame):
    from garmentnerf.geometry.body_points import BodyPointProjector

    body, faces, verts = body_frame
    box, shell = _sample_points(verts, faces, 100, 900, 0.1, 0.2, seed=7)
    points = torch.cat([box, shell]).float()
    projector = BodyPointProjector(body)
    cpu = projector.project(points, verts.float())
    gpu = projector.project(points.cuda(), verts.float().cuda())
    for name in ("face", "bary", "closest", "signed_distance", "canonical", "uv"):
        assert getattr(gpu, name).device.type == "cuda", name
    np.testing.assert_allclose(gpu.signed_distance.cpu().numpy(), cpu.signed_distance.numpy(), atol=1e-6)
    np.testing.assert_allclose(gpu.canonical.cpu().numpy(), cpu.canonical.numpy(), atol=1e-3)


@cuda
def test_cuda_benchmark():
    assert benchmark_dense_projection(4096, "cuda", repeats=1) > 0
