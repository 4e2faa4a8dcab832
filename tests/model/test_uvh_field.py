"""The UV-h field (``model/uvh_field.py``): its reads against scipy's interpolation, its tangent
frames against analytic and trimesh values, and the field inside the assembled model."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh
from scipy.interpolate import RegularGridInterpolator

from garmentnerf.model.config import ModelConfig
from garmentnerf.model.losses import garment_losses, plane_total_variation
from garmentnerf.model.palette import DecomposedMaps
from garmentnerf.model.pipeline import GarmentAnimationNeRF
from garmentnerf.gl.uv_raster import sample_uv_map
from garmentnerf.model.uvh_field import (SHEET_UNIT, UVHField, face_tangent_frames, local_offset_direction,
                                         normalised_height, read_triplane, read_uvh_volume)
from garmentnerf.conventions import camera_rays, orbit_camera
from garmentnerf.model.depth_normals import depth_normals
from garmentnerf.train.settings import tiny_config
from garmentnerf.train.trainer import param_groups

PALETTE = {"garment": [0.8, 0.2, 0.2], "body": [0.7, 0.6, 0.5]}


def texel_axis(n: int) -> np.ndarray:
    """Grid coordinates in [-1, 1] of n texel centres (``grid_sample``, ``align_corners=False``)."""
    return (np.arange(n) + 0.5) / n * 2.0 - 1.0


def test_volume_read_is_scipys_trilinear_interpolation():
    g = torch.Generator().manual_seed(0)
    C, K, R = 3, 5, 7
    volume = torch.randn(C, K, R, R, generator=g, dtype=torch.float64)
    # Inside the texel centres, where border clamping plays no part.
    uv = 0.08 + 0.84 * torch.rand(50, 2, generator=g, dtype=torch.float64)
    height = -0.75 + 1.5 * torch.rand(50, generator=g, dtype=torch.float64)
    got = read_uvh_volume(volume, uv, height)
    axes = (texel_axis(K), texel_axis(R), texel_axis(R))  # (h, v, u)
    query = np.stack([height.numpy(), uv[:, 1].numpy() * 2 - 1, uv[:, 0].numpy() * 2 - 1], -1)
    for c in range(C):
        want = RegularGridInterpolator(axes, volume[c].numpy())(query)
        np.testing.assert_allclose(got[:, c].numpy(), want, atol=1e-10)


def test_triplane_reads_are_scipys_bilinear_interpolation():
    g = torch.Generator().manual_seed(1)
    C, R, K = 2, 9, 4
    planes = torch.nn.ParameterList([torch.nn.Parameter(torch.randn(1, C, rows, R, generator=g, dtype=torch.float64))
                                     for rows in (R, K, K)])
    uv = 0.06 + 0.88 * torch.rand(40, 2, generator=g, dtype=torch.float64)
    height = -0.7 + 1.4 * torch.rand(40, generator=g, dtype=torch.float64)
    got = read_triplane(planes, uv, height).detach().numpy()
    u, v, h = uv[:, 0].numpy() * 2 - 1, uv[:, 1].numpy() * 2 - 1, height.numpy()
    for k, (rows_axis, rows_q, cols_q) in enumerate(((texel_axis(R), v, u), (texel_axis(K), h, u),
                                                     (texel_axis(K), h, v))):
        for c in range(C):
            plane = planes[k][0, c].detach().numpy()
            want = RegularGridInterpolator((rows_axis, texel_axis(R)), plane)(np.stack([rows_q, cols_q], -1))
            np.testing.assert_allclose(got[:, k * C + c], want, atol=1e-10)


def test_normalised_height_maps_the_band_to_the_grid():
    h = torch.tensor([-0.1, 0.15, 0.4, 0.65])
    assert torch.allclose(normalised_height(h, (-0.1, 0.4)), torch.tensor([-1.0, 0.0, 1.0, 2.0]))


def test_tangent_frames_follow_the_atlas_and_the_face_normal():
    # A triangle in the plane z = 1 whose atlas is its (x, y) coordinates, and the same triangle
    # with the atlas mirrored in u (a flipped atlas island): T follows +u both times.
    vertices = torch.tensor([[0.0, 0.0, 1.0], [2.0, 0.0, 1.0], [0.0, 3.0, 1.0]], dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2]])
    uv = torch.tensor([[0.0, 0.0], [0.2, 0.0], [0.0, 0.3], [0.2, 0.0], [0.0, 0.0], [0.2, 0.3]], dtype=torch.float64)
    frames = face_tangent_frames(vertices, faces.repeat(2, 1), uv, torch.tensor([[0, 1, 2], [3, 4, 5]]))
    assert torch.allclose(frames[0], torch.eye(3, dtype=torch.float64))
    assert torch.allclose(frames[1, 0], torch.tensor([-1.0, 0.0, 0.0], dtype=torch.float64))  # u grows to -x
    assert torch.allclose(frames[1, 2], torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))


def test_tangent_frames_on_the_body_are_orthonormal_with_trimeshs_normals(body, projector):
    verts = body.template_vertices.double()
    frames = face_tangent_frames(verts, projector.faces, body.uv, projector.uv_faces)
    eye = torch.eye(3, dtype=torch.float64).expand_as(frames)
    assert torch.allclose(frames @ frames.transpose(1, 2), eye, atol=1e-9)
    assert torch.allclose(torch.linalg.det(frames), torch.ones(len(frames), dtype=torch.float64), atol=1e-9)
    mesh = trimesh.Trimesh(verts.numpy(), projector.faces.numpy(), process=False)
    area = torch.tensor(mesh.area_faces)
    good = area > 1e-10  # trimesh gives degenerate faces a zero normal
    np.testing.assert_allclose(frames[good, 2].numpy(), mesh.face_normals[good.numpy()], atol=1e-7)


def test_local_offset_direction_is_the_normal_above_a_face_and_tilts_past_an_edge():
    frames = torch.eye(3).expand(3, 3, 3)
    closest = torch.zeros(3, 3)
    positions = torch.tensor([[0.0, 0.0, 0.5], [0.3, 0.0, 0.4], [0.0, 0.0, 0.0]])
    got = local_offset_direction(positions, closest, frames)
    assert torch.allclose(got, torch.tensor([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, 0.0, 0.0]]))


def uvh_config(**changes) -> ModelConfig:
    return tiny_config().replace(field="uvh", mlp_depth=2, mlp_width=16, uvh_plane_resolution=32,
                                 uvh_plane_height=8, uvh_slices=4, **changes)


def test_config_checks_and_round_trip():
    cfg = uvh_config()
    assert cfg.dynamic_encoder_channels == cfg.dynamic_feature_dim * 4
    assert ModelConfig.from_dict(cfg.to_dict()) == cfg
    with pytest.raises(ValueError, match="field"):
        uvh_config().replace(field="hash")
    with pytest.raises(ValueError, match="uvh_height_range"):
        uvh_config(uvh_height_range=(0.3, 0.1))
    with pytest.raises(ValueError, match="'paper' field"):
        uvh_config(positional_encoding_freqs=2)
    with pytest.raises(ValueError, match="uvh_canonical_freqs belongs to the 'uvh' field"):
        tiny_config().replace(uvh_canonical_freqs=2)
    with pytest.raises(ValueError, match="uvh_canonical_freqs must be >= 0"):
        uvh_config(uvh_canonical_freqs=-1)
    assert uvh_config(uvh_sheet_layers=2).dynamic_encoder_channels == cfg.dynamic_feature_dim * 4 + 2
    with pytest.raises(ValueError, match="uvh_sheet_layers belongs to the 'uvh' field"):
        tiny_config().replace(uvh_sheet_layers=1)
    with pytest.raises(ValueError, match="uvh_sheet_layers must be >= 0"):
        uvh_config(uvh_sheet_layers=-1)


def test_a_model_with_a_sheet_height_trains_it_through_the_encoder(body, projector, walk_inputs):
    torch.manual_seed(0)
    cfg = uvh_config(uvh_sheet_layers=1, uvh_sheet_freqs=3)
    model = GarmentAnimationNeRF(cfg, body, PALETTE, projector=projector)
    frame = model.prepare_frame(walk_inputs)
    assert frame.dynamic_features.shape == (cfg.dynamic_feature_dim * 4 + 1, 32, 32)
    out = model.render(frame, orbit_camera(30.0, 10.0, 3.0, width=64, height=64), training=True,
                       generator=torch.Generator().manual_seed(0))
    out.image.mean().backward()
    assert model.encoder.head.weight.grad[-1].abs().sum() > 0  # E's sheet-height channel learns


def test_sheet_heights_are_read_bilinearly_and_enter_the_field_as_h_minus_g():
    """E's sheet-height channels (``uvh_sheet_layers``) are read like scipy's bilinear interpolation,
    and the field sees them only as h - g: with the volume's, the planes' and the plain height
    encoding's inputs taken out, moving the samples and the sheet up by 10 cm changes no zeta; the
    sheet height gets gradient from the output."""
    g = torch.Generator().manual_seed(2)
    maps = torch.randn(2, 9, 9, generator=g, dtype=torch.float64)
    uv = 0.06 + 0.88 * torch.rand(30, 2, generator=g, dtype=torch.float64)
    got = sample_uv_map(maps.permute(1, 2, 0), uv)  # how the field reads them
    for c in range(2):
        want = RegularGridInterpolator((texel_axis(9), texel_axis(9)), maps[c].numpy())(
            np.stack([uv[:, 1].numpy() * 2 - 1, uv[:, 0].numpy() * 2 - 1], -1))
        np.testing.assert_allclose(got[:, c].numpy(), want, atol=1e-10)
    torch.manual_seed(0)
    field = UVHField(dynamic_dim=2, slices=3, detail_dim=0, appearance_dim=4, plane_channels=2, plane_resolution=8,
                     plane_height=4, depth=2, width=16, sheet_layers=1, sheet_freqs=3)
    plain = UVHField(dynamic_dim=2, slices=3, detail_dim=0, appearance_dim=4, plane_channels=2, plane_resolution=8,
                     plane_height=4, depth=2, width=16)
    assert field.input_dim == plain.input_dim + 7
    volume = torch.randn(7, 8, 8)
    volume[6] = 0.5  # the sheet 5 cm above the skin everywhere
    uv, direction = torch.full((3, 2), 0.4), torch.tensor([[0.0, 0.0, 1.0]] * 3)
    h = torch.tensor([0.05, 0.06, 0.30])
    with torch.no_grad():
        for plane in field.planes:
            plane.zero_()  # no tri-plane reads
        field.trunk[0].weight[:, 18:27] = 0.0  # nor the plain encoding of h: [volume 2, h - g 7, planes 6, direction 3, PE(h) 9]
        flat = volume.clone()
        flat[:6] = 0.0  # nor the volume's: zeta depends on h only through h - g
        base = field(flat, uv, h, direction)[1]
        raised = flat.clone()
        raised[6] += 0.1 / SHEET_UNIT  # the sheet 10 cm higher, and the samples with it
        moved = field(raised, uv, h + 0.1, direction)[1]
        torch.testing.assert_close(moved, base, atol=1e-5, rtol=0)
        assert (base[0] - base[2]).abs().max() > 1e-3  # 25 cm off the sheet is not on it
    volume.requires_grad_(True)
    sigma, zeta = field(volume, uv, h, direction)
    (sigma.sum() + zeta.sum()).backward()
    assert volume.grad[6].abs().sum() > 0  # the sheet height learns from the image


def test_the_field_tells_apart_points_that_share_their_closest_body_point():
    torch.manual_seed(0)
    field = UVHField(dynamic_dim=2, slices=3, detail_dim=0, appearance_dim=4, plane_channels=2,
                     plane_resolution=8, plane_height=4, depth=2, width=16)
    volume = torch.randn(6, 8, 8)
    uv, h = torch.full((2, 2), 0.4), torch.full((2,), 0.1)
    direction = torch.tensor([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]])
    sigma, zeta = field(volume, uv, h, direction)
    assert sigma.shape == (2,) and zeta.shape == (2, 4) and (sigma >= 0).all()
    assert not torch.allclose(zeta[0], zeta[1])


@pytest.mark.parametrize("canonical_freqs", [0, 2])
def test_a_uvh_model_renders_and_trains_its_grids_and_encoder(body, projector, walk_inputs, canonical_freqs):
    torch.manual_seed(0)
    cfg = uvh_config(uvh_canonical_freqs=canonical_freqs)
    assert GarmentAnimationNeRF(cfg, body, PALETTE, projector=projector).nerf.input_dim == (
        GarmentAnimationNeRF(uvh_config(), body, PALETTE, projector=projector).nerf.input_dim
        + (3 * (1 + 2 * canonical_freqs) if canonical_freqs else 0))
    model = GarmentAnimationNeRF(cfg, body, PALETTE, projector=projector)
    frame = model.prepare_frame(walk_inputs)
    assert frame.dynamic_features.shape == (cfg.dynamic_feature_dim * 4, 32, 32)
    out = model.render(frame, orbit_camera(30.0, 10.0, 3.0, width=64, height=64), training=True,
                       generator=torch.Generator().manual_seed(0))
    assert out.points_evaluated > 0
    out.image.mean().backward()
    assert model.nerf.planes[0].grad.abs().sum() > 0
    assert model.encoder.head.weight.grad.abs().sum() > 0
    groups = param_groups(model, [p for p in model.parameters() if p.requires_grad], cfg)
    planes = [g for g in groups if any(p is model.nerf.planes[0] for p in g["params"])]
    assert len(planes) == 1 and planes[0]["lr_scale"] == cfg.uvh_plane_lr_scale
    assert len(planes[0]["params"]) == 3


def test_canonical_positions_undo_a_rigid_motion_of_the_body(body, projector):
    """Moved rigidly, the body takes its samples with it: a sample's canonical position is the motion
    undone, R^T (x - t), wherever its closest point lies (inside a face, on an edge or a corner;
    inside or outside the body), here mapped from the model's box to [-1, 1]."""
    from types import SimpleNamespace

    from scipy.spatial.transform import Rotation

    model = GarmentAnimationNeRF(uvh_config(uvh_canonical_freqs=2), body, PALETTE, projector=projector)
    R = torch.tensor(Rotation.from_rotvec([0.3, -1.1, 0.4]).as_matrix(), dtype=torch.float32)
    t = torch.tensor([0.2, -0.1, 0.5])
    template = projector.canonical_vertices.float()
    posed = template @ R.T + t
    mesh = trimesh.Trimesh(template.double().numpy(), projector.faces.numpy(), process=False)
    rng = np.random.default_rng(3)
    on_skin, face_ids = trimesh.sample.sample_surface(mesh, 2000, seed=3)
    canonical = (on_skin + rng.uniform(-0.02, 0.25, size=(2000, 1)) * mesh.face_normals[face_ids]
                 + rng.normal(scale=0.03, size=(2000, 3)))
    canonical = torch.tensor(canonical, dtype=torch.float32)
    positions = canonical @ R.T + t
    frame = SimpleNamespace(posed_vertices=posed, surface=model.bind_body(posed))
    points = model.sample_geometry(frame, positions)
    got = model.canonical_inputs(points, positions, model.offset_direction(frame, points, positions))
    lo, hi = model._canonical_box
    assert (lo < canonical.min(0).values).all() and (canonical.max(0).values < hi).all()
    want = (canonical - lo) * (2.0 / (hi - lo)) - 1.0
    torch.testing.assert_close(got, want, rtol=0, atol=2e-5)
    # not the identity: the closest points are spread over the body and the motion is large
    assert (positions - canonical).norm(dim=-1).min() > 0.1


def test_plane_total_variation_against_numpy_and_analytic_planes():
    ramp = torch.arange(6.0).mul(0.25).view(1, 1, 6, 1).expand(1, 3, 6, 5)  # slope 0.25 per texel along rows
    assert float(plane_total_variation([ramp])) == pytest.approx(0.0625)
    checker = torch.tensor([[(-1.0) ** (i + j) for j in range(4)] for i in range(3)]).mul(0.5).view(1, 1, 3, 4)
    assert float(plane_total_variation([checker])) == pytest.approx(2.0)  # differences of 1 along both axes
    assert float(plane_total_variation([torch.full((1, 2, 4, 4), 3.0)])) == 0.0
    rng = np.random.default_rng(0)
    planes = [rng.normal(size=(1, 4, 8, 16)), rng.normal(size=(1, 4, 3, 16))]
    expected = np.mean([np.mean(np.diff(p, axis=2) ** 2) + np.mean(np.diff(p, axis=3) ** 2) for p in planes])
    tensors = [torch.tensor(p, requires_grad=True) for p in planes]
    assert plane_total_variation(tensors).item() == pytest.approx(expected, rel=1e-12)
    assert torch.autograd.gradcheck(lambda a, b: plane_total_variation([a, b]), tuple(tensors))


def test_the_plane_term_enters_the_loss_only_with_its_weight():
    image = torch.rand(1, 3, 8, 8)
    maps = DecomposedMaps(torch.rand(1, 1, 8, 8), torch.zeros(1, 2, 3, 8, 8),
                          torch.softmax(torch.rand(1, 2, 8, 8), dim=1), torch.rand(1, 1, 8, 8))
    palette = torch.rand(2, 3)
    planes = [torch.rand(1, 2, 4, 4)]
    common = dict(image=image, target_image=torch.rand(1, 3, 8, 8), maps=maps, target_mask=torch.ones(1, 1, 8, 8),
                  palette=palette, palette_initial=palette, planes=planes)
    off = garment_losses(cfg=ModelConfig(w_plane_tv=0.0), **common)
    on = garment_losses(cfg=ModelConfig(w_plane_tv=0.5), **common)
    assert "plane_tv" not in off and float(on["plane_tv"]) == pytest.approx(float(plane_total_variation(planes)))
    assert float(on["total"] - off["total"]) == pytest.approx(0.5 * float(on["plane_tv"]), rel=1e-5)
    with pytest.raises(ValueError, match="w_plane_tv"):
        ModelConfig(w_plane_tv=-1.0)


def test_shading_normals_are_trimeshs_normals_at_the_closest_point_after_the_same_zeta(body, projector, walk_inputs):
    """With ``shading_normals`` every sample carries the posed body's normal at its closest point (the
    vertex normals interpolated there: trimesh's closest point and vertex normals, independently)
    after zeta, which is unchanged; the decoder takes the 3 more channels and the view renders."""
    torch.manual_seed(0)
    plain = GarmentAnimationNeRF(uvh_config(), body, PALETTE, projector=projector)
    torch.manual_seed(0)
    cfg = uvh_config(shading_normals=True)
    shaded = GarmentAnimationNeRF(cfg, body, PALETTE, projector=projector)
    assert cfg.feature_image_channels == cfg.appearance_dim + 3
    assert shaded.decoder.body[1].in_channels == cfg.appearance_dim + 3
    frame_plain, frame = plain.prepare_frame(walk_inputs), shaded.prepare_frame(walk_inputs)
    verts = frame.posed_vertices.double().numpy()
    mesh = trimesh.Trimesh(verts, projector.faces.numpy(), process=False)
    rng = np.random.default_rng(0)
    on_skin, face_ids = trimesh.sample.sample_surface(mesh, 600, seed=1)
    offset = rng.uniform(0.005, 0.05, size=(600, 1))
    positions = torch.tensor(on_skin + offset * mesh.face_normals[face_ids], dtype=torch.float32)
    with torch.no_grad():
        _, zeta_plain, _ = plain.evaluate_samples(frame_plain, positions)
        sigma, zeta, _ = shaded.evaluate_samples(frame, positions)
    assert zeta.shape == (600, cfg.appearance_dim + 3)
    torch.testing.assert_close(zeta[:, :cfg.appearance_dim], zeta_plain)
    closest, _, tri = trimesh.proximity.closest_point(mesh, positions.double().numpy())
    bary = trimesh.triangles.points_to_barycentric(mesh.triangles[tri], closest)
    want = np.einsum("nk,nkc->nc", bary, mesh.vertex_normals[mesh.faces[tri]])
    want /= np.linalg.norm(want, axis=1, keepdims=True)
    got = zeta[:, cfg.appearance_dim:].double().numpy()
    angle = np.degrees(np.arccos(np.clip((got * want).sum(1), -1, 1)))
    assert np.median(angle) < 1.0 and np.percentile(angle, 95) < 5.0
    out = shaded.render(frame, orbit_camera(30.0, 10.0, 3.0, width=64, height=64))
    assert out.feature_image.shape[0] == cfg.appearance_dim + 3 and out.points_evaluated > 0
    assert torch.isfinite(out.image).all()


def test_depth_normals_follow_the_rendered_zeta_and_are_the_depths(body, projector, walk_inputs):
    """With ``depth_normals`` the feature image is the plain model's rendered zeta, then the normals of the
    depth it rendered beside it (:func:`depth_normals` of that depth and opacity on the camera's rays)."""
    torch.manual_seed(0)
    plain = GarmentAnimationNeRF(uvh_config(), body, PALETTE, projector=projector)
    torch.manual_seed(0)
    cfg = uvh_config(depth_normals=True)
    model = GarmentAnimationNeRF(cfg, body, PALETTE, projector=projector)
    assert cfg.feature_image_channels == cfg.zeta_channels + 3 == cfg.appearance_dim + 3
    camera = orbit_camera(30.0, 10.0, 3.0, width=64, height=64)
    with torch.no_grad():
        want = plain.render(plain.prepare_frame(walk_inputs), camera, training=False)
        out = model.render(model.prepare_frame(walk_inputs), camera, training=False)
    torch.testing.assert_close(out.feature_image[:cfg.appearance_dim], want.feature_image)
    size = cfg.feature_image_resolution
    origins, directions = camera_rays(camera.resized(size, size))
    normals = depth_normals(out.depth, out.opacity, origins, directions)
    torch.testing.assert_close(out.feature_image[cfg.appearance_dim:], normals)
    assert int((normals.norm(dim=0) > 0.999).sum()) >= 20  # the body prior's skin is opaque in an untrained model
    assert torch.isfinite(out.image).all()
