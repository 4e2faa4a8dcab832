"""The bundled body: asset integrity, skinning against an independent numpy reference."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from garmentnerf.body.asset import BodyAsset, BodyAssetError, default_asset_path
from garmentnerf.body.model import BodyModel, BodyShapeError
from garmentnerf.body.surface import solve3x3, vertex_normals


@pytest.fixture(scope="module")
def body() -> BodyModel:
    return BodyModel.default(dtype=torch.float64)


def reference_lbs(asset: BodyAsset, betas: np.ndarray, rotvecs: np.ndarray, trans: np.ndarray) -> np.ndarray:
    """Straightforward per-joint loop in numpy/scipy (no shared code with garmentnerf.body.skinning)."""
    v = asset.template_vertices.astype(np.float64) + np.einsum("s,svc->vc", betas, asset.shape_dirs)
    j = asset.template_joints.astype(np.float64) + np.einsum("s,sjc->jc", betas, asset.joint_shape_dirs)
    J = len(asset.parents)
    G = [None] * J
    order = sorted(range(J), key=lambda k: _depth(asset.parents, k))
    for k in order:
        local = np.eye(4)
        local[:3, :3] = Rotation.from_rotvec(rotvecs[k]).as_matrix()
        p = asset.parents[k]
        local[:3, 3] = j[k] - (j[p] if p >= 0 else 0.0)
        G[k] = local if p < 0 else G[p] @ local
    out = np.zeros_like(v)
    for k in range(J):
        A = G[k].copy()
        A[:3, 3] -= A[:3, :3] @ j[k]
        w = np.zeros(len(v))
        for slot in range(asset.skin_indices.shape[1]):
            w += np.where(asset.skin_indices[:, slot] == k, asset.skin_weights[:, slot], 0.0)
        out += w[:, None] * (v @ A[:3, :3].T + A[:3, 3])
    return out + trans


def _depth(parents, k):
    d = 0
    while parents[k] >= 0:
        k = parents[k]
        d += 1
    return d


def test_asset_is_consistent_and_small():
    path = default_asset_path()
    assert path.stat().st_size < 8 * 2**20
    asset = BodyAsset.load(path)
    assert asset.num_vertices == 13718 and asset.faces.shape == (27420, 3)
    assert asset.uv.shape[0] > asset.num_vertices  # seams split vertices in the atlas
    assert {"average", "round", "thin"} <= set(asset.named_shapes)
    assert "CC0" in asset.license and "MakeHuman" in asset.license


def test_rest_pose_skinning_is_identity(body):
    for shape in ("average", "round", "thin"):
        betas = body.betas(shape)
        posed = body.pose(body.zero_pose(3), betas=betas)
        rest, _ = body.rest(betas)
        assert torch.allclose(posed.vertices, rest.expand_as(posed.vertices), atol=1e-12)


def test_skinning_matches_reference(body):
    rng = np.random.default_rng(0)
    betas = rng.normal(size=body.asset.num_shape_coeffs) * 0.5
    rotvecs = rng.normal(size=(body.num_joints, 3)) * 0.4
    trans = np.array([0.3, -0.2, 0.1])
    expected = reference_lbs(body.asset, betas, rotvecs, trans)
    posed = body.pose(torch.tensor(rotvecs)[None], torch.tensor(trans)[None], torch.tensor(betas))
    np.testing.assert_allclose(posed.vertices[0].numpy(), expected, atol=1e-9)


def test_whole_clip_in_one_call_matches_per_frame(body):
    rot = torch.randn(5, body.num_joints, 3, dtype=torch.float64) * 0.3
    clip = body.pose(rot).vertices
    for t in range(5):
        assert torch.allclose(clip[t], body.pose(rot[t:t + 1]).vertices[0], atol=1e-12)


def test_shapes_differ_as_named(body):
    def girth(shape):  # front-to-back depth of the torso at 55-65% of the height, and the height
        v, _ = body.rest(body.betas(shape))
        height = float(v[:, 2].max())
        band = v[(v[:, 2] > 0.55 * height) & (v[:, 2] < 0.65 * height) & (v[:, 0].abs() < 0.1)]
        return float(band[:, 1].max() - band[:, 1].min()), height

    avg, rnd, thin = girth("average"), girth("round"), girth("thin")
    assert rnd[0] > avg[0] * 1.1 > thin[0] * 1.1
    tall, short = girth("tall")[1], girth("short")[1]
    assert tall > avg[1] > short
    for shape in ("average", "round", "thin", "tall"):
        v, _ = body.rest(body.betas(shape))
        assert abs(float(v[:, 2].min())) < 2e-3  # every preset stands on the floor


def test_bad_shapes_are_rejected(body):
    with pytest.raises(BodyShapeError, match="unknown body shape 'chubby'"):
        body.betas("chubby")
    with pytest.raises(BodyShapeError, match="at most"):
        body.betas(np.zeros(100))
    with pytest.raises(BodyShapeError, match="NaN"):
        body.betas([float("nan")])
    with pytest.raises(ValueError, match="NaN"):
        rot = body.zero_pose(1)
        rot[0, 3, 0] = float("nan")
        body.pose(rot)


def test_corrupt_and_truncated_assets_are_rejected(tmp_path):
    src = default_asset_path().read_bytes()
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(src[: len(src) // 2])
    with pytest.raises(BodyAssetError, match="truncated.npz"):
        BodyAsset.load(truncated)
    garbage = tmp_path / "garbage.npz"
    garbage.write_bytes(b"not a zip at all")
    with pytest.raises(BodyAssetError, match="garbage.npz"):
        BodyAsset.load(garbage)
    with pytest.raises(BodyAssetError, match="not found"):
        BodyAsset.load(tmp_path / "missing.npz")
    asset = BodyAsset.load(default_asset_path())
    asset.faces = asset.faces.copy()
    asset.faces[0, 0] = 10**7
    bad = tmp_path / "bad_faces.npz"
    asset.save(bad)
    with pytest.raises(BodyAssetError, match="bad_faces.npz: field 'faces'"):
        BodyAsset.load(bad)


def test_asset_round_trip(tmp_path):
    asset = BodyAsset.load(default_asset_path())
    out = tmp_path / "copy.npz"
    asset.save(out)
    again = BodyAsset.load(out)
    np.testing.assert_array_equal(again.template_vertices, asset.template_vertices)
    np.testing.assert_array_equal(again.faces, asset.faces)
    assert again.joint_names == asset.joint_names
    assert again.named_shapes.keys() == asset.named_shapes.keys()


def test_vertex_normals_match_trimesh(body):
    import trimesh

    v = body.pose(torch.randn(1, body.num_joints, 3, dtype=torch.float64) * 0.2).vertices[0]
    mesh = trimesh.Trimesh(v.numpy(), body.faces.numpy(), process=False)
    # Area-weighted vertex normals from trimesh's face normals and areas.
    area_weighted = np.zeros_like(mesh.vertices)
    for corner in range(3):
        np.add.at(area_weighted, mesh.faces[:, corner], mesh.face_normals * mesh.area_faces[:, None])
    area_weighted /= np.linalg.norm(area_weighted, axis=1, keepdims=True)
    ours = vertex_normals(v, body.faces).numpy()
    np.testing.assert_allclose(ours, area_weighted, atol=1e-9)
    # and they point outwards: compare with trimesh's angle-weighted normals loosely
    assert np.mean(np.sum(ours * mesh.vertex_normals, axis=1)) > 0.99


def test_solve3x3_matches_lapack():
    m = torch.randn(500, 3, 3, dtype=torch.float64)
    b = torch.randn(500, 3, dtype=torch.float64)
    np.testing.assert_allclose(solve3x3(m, b).numpy(), np.linalg.solve(m.numpy(), b.numpy()[..., None])[..., 0], atol=1e-9)
    singular = torch.zeros(1, 3, 3, dtype=torch.float64)
    assert torch.all(solve3x3(singular, torch.ones(1, 3, dtype=torch.float64)) == 0)
