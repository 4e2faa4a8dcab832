"""The assembled Garment Animation NeRF forward pass on a tiny model and the bundled body."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from garmentnerf.body.surface import vertex_normals
from garmentnerf.conventions import Camera, camera_rays, intrinsics_from_fov, look_at, orbit_camera, project_points
from garmentnerf.data.cameras import reference_cameras
from garmentnerf.model.config import BBOX_PADDING, ModelConfig
from garmentnerf.model.detail_features import read_detail_features, reference_visibility, sample_image_features
from garmentnerf.model.palette import compose
from garmentnerf.model.pipeline import (
    FRAME_STAGES,
    RENDER_STAGES,
    GarmentAnimationNeRF,
    RenderCancelled,
    palette_initial_colors,
)
from garmentnerf.model.samplers import ray_aabb_intersect
from garmentnerf.render.frame_inputs import FrameInputBuilder, resolve_reference_cameras

PALETTE = {"garment": [0.8, 0.2, 0.2], "body": [0.7, 0.6, 0.5]}


def tiny_config(changes: dict | None = None) -> ModelConfig:
    return ModelConfig.tiny().updated(changes or {})


def make_model(body, projector, seed=0, changes: dict | None = None) -> GarmentAnimationNeRF:
    torch.manual_seed(seed)
    return GarmentAnimationNeRF(tiny_config(changes), body, PALETTE, projector=projector).eval()


@pytest.fixture(scope="module")
def model(body, projector):
    return make_model(body, projector)


@pytest.fixture(scope="module")
def frame(model, walk_inputs):
    with torch.no_grad():
        return model.prepare_frame(walk_inputs)


CAMERA = orbit_camera(30.0, 10.0, 3.0, width=64, height=64)


# ---------------------------------------------------------------------------------------- inputs
def test_frame_inputs(gl_context, body, walk_clip, walk_inputs):
    cfg = tiny_config()
    assert walk_inputs.info_maps.shape == (9, 32, 32)
    assert walk_inputs.reference_uv.shape == (2, 32, 32, 2)
    assert (walk_inputs.reference_mask.shape == walk_inputs.reference_depth.shape
            == walk_inputs.reference_face.shape == (2, 32, 32))
    for i in range(2):
        m = walk_inputs.reference_mask[i]
        assert 0.05 < m.float().mean() < 0.6  # the body fills part of each reference view
        depth = walk_inputs.reference_depth[i]
        assert torch.isfinite(depth[m]).all() and torch.isinf(depth[~m]).all()
        assert (walk_inputs.reference_face[i][m] >= 0).all()
    assert set(walk_inputs.timings) == {"info_maps", "reference_passes"}
    # A single frame equals the same frame of the whole clip (velocity history included).
    posed, fps = walk_clip
    with FrameInputBuilder(gl_context, body, reference_cameras(), cfg) as builder:
        whole = builder.build_clip(posed, fps)
    assert len(whole) == 3
    torch.testing.assert_close(whole[2].info_maps, walk_inputs.info_maps, atol=1e-5, rtol=0)
    # each frame holds its own vertices, not a row of the clip that would keep the whole clip alive
    own_bytes = posed.vertices.shape[1] * 3 * 4
    for inputs in (walk_inputs, *whole):
        assert inputs.posed_vertices.untyped_storage().nbytes() == own_bytes
    torch.testing.assert_close(walk_inputs.posed_vertices, posed.vertices[2], atol=0, rtol=0)
    assert walk_inputs.info_maps[3:].abs().max() > 0  # the body moves
    with pytest.raises(ValueError, match="info_maps"):
        walk_inputs.validate(cfg.updated({"encoder.history": 1}))


def test_resolve_reference_cameras():
    front, back = reference_cameras()
    got = resolve_reference_cameras([back, front])  # by name
    assert got[0] is front.camera and got[1] is back.camera
    got = resolve_reference_cameras([back.camera, front.camera])  # plain cameras: by order
    assert got[0] is back.camera and got[1] is front.camera
    with pytest.raises(ValueError):
        resolve_reference_cameras([front.camera])


def test_palette_init():
    p = palette_initial_colors(PALETTE)
    torch.testing.assert_close(p, torch.tensor([PALETTE["garment"], PALETTE["body"]]))
    assert palette_initial_colors(None, 3).shape == (3, 3)
    with pytest.raises(ValueError):
        palette_initial_colors(torch.zeros(3, 3), 2)
    with pytest.raises(ValueError):
        palette_initial_colors([[1.5, 0, 0], [0, 0, 0]], 2)
    # a layered garment: its layers' colors, inner first, then the body's (always the last)
    layered = {**PALETTE, "garment_layers": [[0.9, 0.6, 0.1], [0.7, 0.5, 0.2]]}
    torch.testing.assert_close(palette_initial_colors(layered, 3),
                               torch.tensor([[0.9, 0.6, 0.1], [0.7, 0.5, 0.2], PALETTE["body"]]))
    torch.testing.assert_close(palette_initial_colors(layered, 2), p)
    with pytest.raises(ValueError, match="needs 2 garment layer colors"):
        palette_initial_colors(PALETTE, 3)


# ---------------------------------------------------------------------------------------- render
def test_shapes_and_timings(model, frame):
    assert frame.dynamic_features.shape == (8, 32, 32)
    assert frame.reference_images.shape == (2, 3, 32, 32)
    assert frame.detail_features.shape == (2, 8, 32, 32)
    assert frame.aabb.shape == (2, 3)
    with torch.no_grad():
        out = model.render(frame, CAMERA)
    assert out.image.shape == (3, 64, 64)
    assert out.maps.radiance.shape == (1, model.cfg.decoder.radiance_channels, 64, 64)
    assert out.maps.offsets.shape == (1, 2, 3, 64, 64)
    assert out.maps.weights.shape == (1, 2, 64, 64)
    assert out.maps.mask.shape == (1, 1, 64, 64)
    assert out.opacity.shape == out.depth.shape == (16, 16)
    assert out.feature_image.shape == (16, 16, 16)
    assert out.image.min() >= 0 and out.image.max() <= 1 and torch.isfinite(out.image).all()
    assert 0 < out.points_evaluated == out.rays_evaluated * 8 and out.rays_total == 256
    assert set(FRAME_STAGES) | set(RENDER_STAGES) | {"frame_total", "render_total"} == set(out.timings)
    assert all(v >= 0 for v in out.timings.values())
    hit = out.opacity > 0
    near, far = np.linalg.norm(CAMERA.center) - 1.0, np.linalg.norm(CAMERA.center) + 1.0
    assert ((out.depth[hit] > near) & (out.depth[hit] < far)).all() and (out.depth[~hit] == 0).all()


def test_missed_rays_are_not_evaluated(model, frame):
    calls = []
    hook = model.nerf.register_forward_hook(lambda m, args, out: calls.append(args[0].shape[0]))
    try:
        with torch.no_grad():
            out = model.render(frame, CAMERA)
        # Independent count: rays of the feature image that enter the padded body box.
        origins, dirs = camera_rays(CAMERA.resized(16, 16))
        pad = torch.tensor([[-1.0], [1.0]]) * BBOX_PADDING
        _, _, hit = ray_aabb_intersect(origins.reshape(-1, 3), dirs.reshape(-1, 3), frame.aabb + pad)
        assert 0 < int(hit.sum()) < 256  # some rays miss the box, some hit it
        assert sum(calls) == out.points_evaluated == int(hit.sum()) * model.cfg.sampler.samples_per_ray
        opacity = out.opacity.reshape(-1)
        assert (opacity[~hit] == 0).all() and (opacity[hit] > 0).all()
        # A camera looking away from the body evaluates nothing.
        calls.clear()
        R, t = look_at((0.0, -3.0, 1.0), (0.0, -6.0, 1.0))
        away = Camera(intrinsics_from_fov(64, 64, 40.0), R, t, 64, 64)
        with torch.no_grad():
            out = model.render(frame, away)
        assert out.points_evaluated == 0 and out.rays_evaluated == 0 and sum(calls) == 0
        assert (out.opacity == 0).all() and out.image.shape == (3, 64, 64)
    finally:
        hook.remove()


def test_gradients_reach_every_trainable_module(body, projector, walk_inputs):
    model = make_model(body, projector, seed=1).train()
    frame = model.prepare_frame(walk_inputs)
    out = model.render(frame, CAMERA, generator=torch.Generator().manual_seed(0))
    target = torch.rand(out.image.shape, generator=torch.Generator().manual_seed(1))
    loss = (out.image - target).abs().mean()
    loss.backward()
    modules = model.trainable_modules()
    assert set(modules) == {"encoder", "detail_encoder", "nerf", "decoder", "palette"}
    for name, module in modules.items():
        grads = [p.grad for p in module.parameters()]
        assert all(g is not None and torch.isfinite(g).all() for g in grads), name
        assert sum(float(g.abs().sum()) for g in grads) > 0, name
    for head in (model.nerf.density_head, model.nerf.appearance_head):
        assert head.weight.grad.abs().sum() > 0
    assert model.palette.colors.grad.abs().sum() > 0
    # G_img is frozen: no gradient, and its output is not part of the graph.
    assert model.image_generator_frozen
    assert all(p.grad is None and not p.requires_grad for p in model.image_generator.parameters())
    assert not frame.reference_images.requires_grad and frame.detail_features.requires_grad
    assert model.image_generator.training is False  # train() keeps the frozen G_img in eval mode


def test_unfrozen_image_generator_gets_gradient(body, projector, walk_inputs):
    model = make_model(body, projector, seed=2).train()
    model.set_image_generator_frozen(False)
    assert "image_generator" in model.trainable_modules()
    out = model.render(model.prepare_frame(walk_inputs), CAMERA)
    out.image.mean().backward()
    assert sum(float(p.grad.abs().sum()) for p in model.image_generator.parameters()) > 0


def test_recoloring_equals_rerendering(model, frame):
    new = torch.tensor([[0.1, 0.3, 0.9], [0.2, 0.8, 0.3]])
    with torch.no_grad():
        out = model.render(frame, CAMERA)
        again = model.render(frame, CAMERA, palette=new, background=(1.0, 1.0, 1.0))
    maps = out.maps
    recolored = compose(maps.radiance, maps.offsets, maps.weights, maps.mask, new, (1.0, 1.0, 1.0))[0]
    torch.testing.assert_close(recolored, again.image, atol=1e-6, rtol=0)
    torch.testing.assert_close(out.recolor(new, (1.0, 1.0, 1.0)), again.image, atol=1e-6, rtol=0)
    assert (recolored - out.image).abs().max() > 1e-3  # the palette does change the image


def test_cancellation(model, frame):
    with torch.no_grad():
        full = model.render(frame, CAMERA, chunk_points=64)
    asked = []

    def cancel_third():
        asked.append(1)
        return len(asked) >= 3

    with pytest.raises(RenderCancelled) as info:
        with torch.no_grad():
            model.render(frame, CAMERA, chunk_points=64, should_cancel=cancel_third)
    assert 0 < info.value.points_evaluated < full.points_evaluated
    assert len(asked) == 3
    with torch.no_grad():  # nothing left behind: the next render is the same as before
        again = model.render(frame, CAMERA, chunk_points=64, should_cancel=lambda: False)
        big_chunks = model.render(frame, CAMERA)
    torch.testing.assert_close(again.image, full.image, atol=0, rtol=0)
    torch.testing.assert_close(big_chunks.image, full.image, atol=1e-5, rtol=0)  # chunking changes nothing


def test_a_renders_samples_are_projected_in_calls_that_change_nothing(model, frame, monkeypatch):
    """The render projects its samples onto the body before the march, PROJECTION_CHUNK_POINTS per
    call: in calls of 100 samples the image is the same to the last bit, and a cancel asked between
    two calls stops the render before any sample reaches the field."""
    from garmentnerf.model import pipeline

    with torch.no_grad():
        whole = model.render(frame, CAMERA, chunk_points=64)
        calls = []
        original = type(model).sample_geometry
        monkeypatch.setattr(type(model), "sample_geometry",
                            lambda self, f, positions: calls.append(positions.shape[0]) or original(self, f, positions))
        monkeypatch.setattr(pipeline, "PROJECTION_CHUNK_POINTS", 100)
        split = model.render(frame, CAMERA, chunk_points=64)
        assert len(calls) > 2 and max(calls) == 100 and sum(calls) == split.points_projected
        torch.testing.assert_close(split.image, whole.image, atol=0, rtol=0)
        with pytest.raises(RenderCancelled) as info:
            model.render(frame, CAMERA, chunk_points=64, should_cancel=lambda: True)
        assert info.value.points_evaluated == 0


def test_ray_subset(model, frame):
    mask = torch.zeros(16, 16, dtype=torch.bool)
    mask[4:12, 6:10] = True
    with torch.no_grad():
        full = model.render(frame, CAMERA)
        part = model.render(frame, CAMERA, rays=mask)
        idx = model.render(frame, CAMERA, rays=mask.reshape(-1).nonzero().squeeze(1))
    torch.testing.assert_close(part.feature_image[:, mask], full.feature_image[:, mask], atol=1e-6, rtol=0)
    assert (part.feature_image[:, ~mask] == 0).all() and (part.opacity[~mask] == 0).all()
    assert part.rays_total == 32 and part.points_evaluated < full.points_evaluated
    torch.testing.assert_close(idx.image, part.image, atol=0, rtol=0)
    with pytest.raises(ValueError, match="unique"):
        model.render(frame, CAMERA, rays=torch.tensor([3, 3]))


def test_any_resolution_by_padding_the_camera_and_cropping_the_maps(model, frame):
    from garmentnerf.render.session import padded_render_camera

    cam = orbit_camera(-60.0, 5.0, 3.0, width=70, height=50)
    padded, (fw, fh), (wr, hr) = padded_render_camera(cam, 1.0, 4)
    assert (fw, fh) == (18, 13) and (wr, hr) == (70, 50) and (padded.width, padded.height) == (72, 52)
    # Padding extends the image to the right and bottom: the pixel centres of the camera stay put.
    _, d_cam = camera_rays(cam, torch.float64)
    _, d_pad = camera_rays(padded, torch.float64)
    torch.testing.assert_close(d_pad[:50, :70], d_cam, atol=1e-12, rtol=0)
    half, (hw, hh), (w2, h2) = padded_render_camera(cam, 0.5, 4)
    assert (w2, h2) == (35, 25) and (hw, hh) == (9, 7) and (half.width, half.height) == (36, 28)
    with torch.no_grad():
        out = model.render(frame, padded, feature_size=(fw, fh))
        square = model.render(frame, padded_render_camera(CAMERA, 1.0, 4)[0], feature_size=(16, 16))
        direct = model.render(frame, CAMERA)
    maps = out.maps.cropped(wr, hr)
    assert maps.size == (70, 50) and maps.mask.shape == (1, 1, 50, 70)
    torch.testing.assert_close(maps.mask, out.maps.mask[..., :50, :70], atol=0, rtol=0)
    small = maps.resized(35, 25)
    assert small.size == (35, 25) and maps.resized(70, 50) is maps
    torch.testing.assert_close(small.weights.sum(1), torch.ones(1, 25, 35))
    assert float(small.mask.min()) >= 0 and float(small.mask.max()) <= 1 and float(small.radiance.min()) >= 0
    # A 2x downsampling averages: the mean of every map is kept to within the filter's edge effects.
    torch.testing.assert_close(small.mask.mean(), maps.mask.mean(), atol=0.02, rtol=0)
    # A camera at the model's resolution renders exactly as render() does.
    torch.testing.assert_close(square.image, direct.image, atol=1e-6, rtol=0)


def test_visibility_selects_front_for_front_and_back_for_back(model, frame, projector):
    skin = torch.unique(projector.faces.reshape(-1))
    verts = frame.posed_vertices[skin]
    normals = vertex_normals(frame.posed_vertices, model.body.faces)[skin]
    # The torso below the chin (the hands and face hold most vertices, with thin or self-hidden parts).
    torso = (verts[:, 0].abs() < 0.1) & (verts[:, 2] > 0.9) & (verts[:, 2] < 1.35)
    front, back = (normals[:, 1] < -0.9) & torso, (normals[:, 1] > 0.9) & torso
    front_pts, back_pts = verts[front], verts[back]
    assert len(front_pts) > 100 and len(back_pts) > 100
    maps, cams, depth = frame.detail_features, frame.reference_cameras, frame.reference_depth
    _, w_front = read_detail_features(maps, cams, depth, front_pts)
    _, w_back = read_detail_features(maps, cams, depth, back_pts)
    assert w_front.float().mean() > 0.97 and w_back.float().mean() < 0.03
    # The same through the public test; a visible point gets exactly the front read.
    assert reference_visibility(back_pts, cams[1], depth[1]).float().mean() > 0.97
    assert reference_visibility(front_pts, cams[1], depth[1]).float().mean() < 0.03
    feats, sel = read_detail_features(maps, cams, depth, front_pts)
    pix, _ = project_points(cams[0], front_pts)
    front_read = sample_image_features(frame.detail_features[0], pix)
    torch.testing.assert_close(feats[sel], front_read[sel])


@pytest.mark.parametrize("changes", [{"encoder.detail_feature": False}, {"encoder.dynamic_feature": False},
                                     {"encoder.detail_feature": False, "encoder.dynamic_feature": False},
                                     {"nerf.shading_normals": True}])
def test_ablations_and_modes(body, projector, walk_inputs, changes):
    model = make_model(body, projector, changes=changes).train()
    frame = model.prepare_frame(walk_inputs)
    cfg = model.cfg
    assert (model.encoder is None) == (frame.dynamic_features is None) == (not cfg.encoder.dynamic_feature)
    assert (model.detail_encoder is None) == (frame.detail_features is None) == (not cfg.encoder.detail_feature)
    assert model.nerf.input_dim == cfg.mlp_input_dim
    out = model.render(frame, CAMERA)
    assert out.image.shape == (3, 64, 64) and out.points_evaluated > 0
    out.image.mean().backward()
    for name, module in model.trainable_modules().items():
        assert sum(float(p.grad.abs().sum()) for p in module.parameters()) > 0, name


def test_evaluate_samples_reuses_a_projection_it_is_given(model, frame):
    """Handing evaluate_samples the positions' own projection gives the same field, bit for bit."""
    g = torch.Generator().manual_seed(5)
    lo, hi = frame.aabb[0], frame.aabb[1]
    positions = lo + (hi - lo) * torch.rand(500, 3, generator=g)
    with torch.no_grad():
        sigma, zeta, n = model.evaluate_samples(frame, positions)
        again = model.evaluate_samples(frame, positions, points=model.sample_geometry(frame, positions))
    assert n == again[2] == 500
    assert torch.equal(sigma, again[0]) and torch.equal(zeta, again[1])
    assert float(sigma.max()) > 0
