"""UV-space info maps against trimesh normals and finite-difference velocities."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from garmentnerf.body.model import BodyModel
from garmentnerf.body.surface import VELOCITY_SCALE, canonical_velocities
from garmentnerf.gl.info_maps import InfoMapRenderer
from garmentnerf.model.uv_maps import sample_uv_map

FPS = 30.0


@pytest.fixture(scope="module")
def renderer(gl_context, body):
    r = InfoMapRenderer(gl_context, body, resolution=128, history=2)
    yield r
    r.release()


def smooth_motion(body, frames=4, seed=0):
    """Rotations varying smoothly over time, including a turning root."""
    g = torch.Generator().manual_seed(seed)
    base = torch.randn(body.num_joints, 3, generator=g) * 0.15
    speed = torch.randn(body.num_joints, 3, generator=g) * 0.05
    t = torch.arange(frames, dtype=torch.float32)[:, None, None]
    rot = base + t * speed
    rot[:, 0] = torch.tensor([0.1, -0.2, 0.0]) + t[:, 0] * torch.tensor([0.0, 0.0, 0.3])
    trans = torch.stack([torch.zeros(frames), -0.04 * torch.arange(frames, dtype=torch.float32), torch.zeros(frames)], 1)
    return rot, trans


def surface_samples(mesh: trimesh.Trimesh, faces_uv: np.ndarray, uv: np.ndarray, count: int, seed: int = 0):
    """Random surface points: (face index, barycentrics, uv)."""
    points, face_idx = trimesh.sample.sample_surface(mesh, count, seed=seed)
    bary = trimesh.triangles.points_to_barycentric(mesh.triangles[face_idx], points)
    point_uv = np.einsum("nk,nkc->nc", bary, uv[faces_uv[face_idx]])
    return face_idx, bary, point_uv


def test_normal_map_matches_trimesh_normals(renderer, body):
    rot, trans = smooth_motion(body)
    posed = body.pose(rot, trans)
    maps = renderer.render_clip(posed, FPS)
    t = 2
    mesh = trimesh.Trimesh(posed.vertices[t].double().numpy(), body.faces.numpy(), process=False)
    face_idx, bary, point_uv = surface_samples(mesh, body.asset.uv_faces, body.asset.uv, 4000)
    root_rot = posed.joint_transforms[t, 0, :, :3].double().numpy()
    expected = np.einsum("nk,nkc->nc", bary, mesh.vertex_normals[mesh.faces[face_idx]])
    expected = expected @ root_rot  # R^T n for row vectors
    expected /= np.linalg.norm(expected, axis=1, keepdims=True)
    got = sample_uv_map(maps[t].normal, torch.as_tensor(point_uv, dtype=torch.float32)).double().numpy()
    got /= np.linalg.norm(got, axis=1, keepdims=True)
    angle = np.degrees(np.arccos(np.clip(np.sum(got * expected, axis=1), -1, 1)))
    # 128x128 texels for 27k triangles: the map is a low-pass version of the surface normals.
    # Measured at 128: median 0.9 deg, 90th percentile 4.5 deg (99th: 48 deg, on fingers and
    # ears where a texel spans several triangles; at 512 the 99th percentile drops to 9 deg).
    assert np.median(angle) < 2.0
    assert np.percentile(angle, 90) < 8.0
    # the root rotation really is removed: without it the error would be the root's 0.22 rad turn
    raw = np.einsum("nk,nkc->nc", bary, mesh.vertex_normals[mesh.faces[face_idx]])
    raw /= np.linalg.norm(raw, axis=1, keepdims=True)
    raw_angle = np.degrees(np.arccos(np.clip(np.sum(got * raw, axis=1), -1, 1)))
    assert np.median(raw_angle) > np.median(angle) + 5.0


def test_velocities_match_finite_differences(body):
    rot, trans = smooth_motion(body, frames=5)
    posed = body.pose(rot.double(), trans.double())
    body64 = BodyModel(body.asset, dtype=torch.float64)
    posed = body64.pose(rot.double(), trans.double())
    x = posed.vertices.numpy()
    W = body64.weights.numpy()
    A = posed.joint_transforms.numpy()  # (T, J, 3, 4)
    vel = canonical_velocities(posed.vertices, body64.vertex_transforms(posed.joint_transforms)[..., :3], FPS, 2).numpy()
    for t in range(5):
        for slot in (1, 2):
            s = t - slot + 1
            if s <= 0:
                expected = np.zeros_like(x[0])
            else:
                L = np.einsum("vj,jab->vab", W, A[s, :, :, :3])
                expected = np.linalg.solve(L, (x[s] - x[s - 1])[..., None])[..., 0] * FPS * VELOCITY_SCALE
            np.testing.assert_allclose(vel[t, :, 3 * (slot - 1):3 * slot], expected, atol=1e-9)


def test_rigid_translation_gives_uniform_velocity_map(renderer, body):
    frames = 3
    rot = body.zero_pose(frames)
    step = torch.tensor([0.02, -0.05, 0.01])
    trans = torch.arange(frames, dtype=torch.float32)[:, None] * step
    maps = renderer.render_clip(body.pose(rot, trans), FPS)
    expected = (step * FPS * VELOCITY_SCALE).numpy()
    mask = maps[2].mask.numpy()
    vel = maps[2].velocity.numpy()
    np.testing.assert_allclose(vel[mask][:, :3], np.broadcast_to(expected, (mask.sum(), 3)), atol=1e-5)
    np.testing.assert_allclose(vel[mask][:, 3:], np.broadcast_to(expected, (mask.sum(), 3)), atol=1e-5)
    # frame 0 has no history: the motion is preceded by its first frame held still
    assert np.abs(maps[0].velocity.numpy()).max() == 0.0
    # frame 1: slot 1 moves, slot 2 (before the start) is still
    np.testing.assert_allclose(maps[1].velocity.numpy()[mask][:, :3], np.broadcast_to(expected, (mask.sum(), 3)), atol=1e-5)
    assert np.abs(maps[1].velocity.numpy()[..., 3:]).max() == 0.0


def test_velocity_map_lookup_matches_vertex_velocities(renderer, body):
    rot, trans = smooth_motion(body, frames=3, seed=1)
    posed = body.pose(rot, trans)
    attrs = renderer.vertex_attributes(posed, FPS)
    maps = renderer.render_attributes(attrs[2])
    mesh = trimesh.Trimesh(posed.vertices[2].double().numpy(), body.faces.numpy(), process=False)
    face_idx, bary, point_uv = surface_samples(mesh, body.asset.uv_faces, body.asset.uv, 4000, seed=3)
    expected = np.einsum("nk,nkc->nc", bary, attrs[2, :, 3:].numpy()[body.asset.faces[face_idx]])
    got = sample_uv_map(maps.velocity, torch.as_tensor(point_uv, dtype=torch.float32)).numpy()
    err = np.linalg.norm(got - expected, axis=1)
    scale = np.linalg.norm(expected, axis=1).mean()
    assert np.median(err) < 0.05 * scale
    assert np.percentile(err, 90) < 0.25 * scale


def test_maps_have_the_documented_shapes(renderer, body):
    maps = renderer.render_clip(body.pose(body.zero_pose(2)), FPS)[1]
    assert maps.normal.shape == (128, 128, 3) and maps.velocity.shape == (128, 128, 6)
    assert maps.mask.dtype == torch.bool and 0.4 < float(maps.mask.float().mean()) < 0.9
    assert maps.stacked().shape == (9, 128, 128)
    assert torch.isfinite(maps.stacked()).all()


def test_frame_inputs_built_alone_equal_the_clip_ones(gl_context, body):
    """A frame built alone reaches back far enough for its velocity history: it equals the clip's frame."""
    from garmentnerf.model.config import ModelConfig
    from garmentnerf.render.frame_inputs import FrameInputBuilder

    rot, trans = smooth_motion(body, frames=24, seed=4)
    posed = body.pose(rot, trans)
    cfg = ModelConfig.cpu_small().updated({"encoder.reference_resolution": 32, "encoder.info_map_resolution": 32})
    assert cfg.encoder.in_channels == 3 * (2 + 1)
    from garmentnerf.conventions import orbit_camera

    cams = (orbit_camera(0.0, 0.0, 3.0, width=32, height=32), orbit_camera(180.0, 0.0, 3.0, width=32, height=32))
    with FrameInputBuilder(gl_context, body, cams, cfg) as builder:
        clip = builder.build_clip(posed, FPS, frames=[20])[0]
        alone = builder.build(posed, 20, FPS)
        short = builder.build(posed, 2, FPS)
    assert alone.info_maps.shape == (cfg.encoder.in_channels, 32, 32)
    torch.testing.assert_close(alone.info_maps, clip.info_maps, rtol=0, atol=1e-6)
    # the velocity slots reach back k = 2 frames, so frame 20's are not frame 2's
    assert not torch.allclose(alone.info_maps[-3:], short.info_maps[-3:])
    assert builder.info_map_renderer.frames_back(FPS) == 2
