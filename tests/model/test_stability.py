"""Numerical and resource stability: no NaN/Inf in outputs or gradients at the edges of the input
space (densities, intervals, cameras, poses, history, palettes, precision, long motions)."""

from __future__ import annotations

import math
import resource

import pytest
import torch

from garmentnerf.conventions import Camera, intrinsics_from_fov, look_at, orbit_camera
from garmentnerf.data.cameras import reference_cameras
from garmentnerf.model import volume_rendering as vr
from garmentnerf.model.config import ModelConfig
from garmentnerf.model.field import Field
from garmentnerf.model.height_band import HeightRange
from garmentnerf.model.palette import check_palette
from garmentnerf.model.pipeline import GarmentAnimationNeRF
from garmentnerf.motion.library import load_motion
from garmentnerf.motion.motion import Motion
from garmentnerf.render.frame_inputs import FrameInputBuilder
from garmentnerf.render.shell_sampler import ShellSampler

PALETTE = {"garment": [0.8, 0.2, 0.2], "body": [0.7, 0.6, 0.5]}
BAND = HeightRange(-0.05, 0.15)


def tiny_config(changes: dict | None = None) -> ModelConfig:
    return ModelConfig.tiny().updated({"decoder.image_resolution": 32, "decoder.feature_image_resolution": 8,
                                       "nerf.appearance_dim": 8, "nerf.mlp_width": 16, "decoder.width": 8,
                                       **(changes or {})})


class ForcedDensity(Field):
    """The model's field with its density replaced by a constant (gradients still reach zeta)."""

    def __init__(self, inner: Field, value: float):
        super().__init__()
        self.inner, self.value, self.zeta_channels = inner, value, inner.zeta_channels

    def evaluate(self, frame, points, *, clock, autocast):
        sigma, zeta = self.inner.evaluate(frame, points, clock=clock, autocast=autocast)
        return sigma * 0.0 + self.value, zeta


@pytest.fixture(scope="module")
def walk(body):
    return load_motion("walk", body)


@pytest.fixture(scope="module")
def builder(gl_context, body):
    with FrameInputBuilder(gl_context, body, reference_cameras(), tiny_config()) as b:
        yield b


@pytest.fixture(scope="module")
def model(body, projector):
    torch.manual_seed(0)
    return GarmentAnimationNeRF(tiny_config(), body, PALETTE, projector=projector).eval()


@pytest.fixture(scope="module")
def frame(model, builder, walk, body):
    posed = walk.slice(0, 3).pose(body)
    with torch.no_grad():
        return model.prepare_frame(builder.build(posed, 2, walk.fps))


def finite(*tensors) -> bool:
    return all(bool(torch.isfinite(t).all()) for t in tensors)


def culled_sampling(model, gl_context, samples=None, **sampler_kw) -> dict:
    """Render arguments of the culled sampling: the shell sampler and the height band filter."""
    faces = model.projector.faces
    sampler = ShellSampler(samples or model.cfg.sampler.samples_per_ray, faces, BAND, gl_context=gl_context, **sampler_kw)
    return {"sampler": sampler, "sample_filter": BAND.sample_filter(faces)}


def check_render(model, frame, camera, culled=False, gl_context=None, **kw):
    sampling = culled_sampling(model, gl_context) if culled else {}
    try:
        with torch.no_grad():
            out = model.render(frame, camera, **sampling, **kw)
    finally:
        if culled:
            sampling["sampler"].release()
    assert finite(out.image, out.opacity, out.depth, out.feature_image), "non-finite render"
    assert 0 <= float(out.image.min()) and float(out.image.max()) <= 1
    return out


# ---------------------------------------------------------------------------------------------
# volume rendering at the extremes
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("sigma", [0.0, 1e-8, 1.0, 1e8])
@pytest.mark.parametrize("delta", [0.0, 1e-9, 0.01, 1e6])
def test_volume_rendering_extremes(sigma, delta):
    for dtype in (torch.float32, torch.float64):
        s = torch.full((3, 5), sigma, dtype=dtype, requires_grad=True)
        d = torch.full((3, 5), delta, dtype=dtype, requires_grad=True)
        vals = torch.randn(3, 5, 4, dtype=dtype, requires_grad=True)
        w = vr.render_weights_from_density(s, d)
        out = vr.composite(w, vals).sum() + vr.expected_depth(w, d * 0, d, normalize=True).sum()
        out.backward()
        assert finite(w, s.grad, d.grad, vals.grad)
        assert float(w.detach().sum(-1).max()) <= 1 + 1e-6
        # Packed, with rays of 0 samples in between.
        ids = torch.tensor([0, 0, 2, 2, 2, 4])
        sp = torch.full((6,), sigma, dtype=dtype, requires_grad=True)
        dp = torch.full((6,), delta, dtype=dtype)
        wp = vr.render_weights_from_density_packed(sp, dp, ids, 6)
        feat = vr.composite_packed(wp, torch.ones(6, 2, dtype=dtype), ids, 6)
        feat.sum().backward()
        assert finite(wp, feat, sp.grad)
        assert float(vr.accumulate_opacity_packed(wp, ids, 6)[[1, 3, 5]].detach().abs().max()) == 0


def test_alpha_path_extremes():
    alphas = torch.tensor([[0.0, 1.0, 1.0, 0.5], [1.0 - 1e-12, 0.0, 1.0, 1.0]], requires_grad=True)
    w = vr.render_weights(alphas)
    w.sum().backward()
    assert finite(w, alphas.grad) and float(w.detach().sum(-1).max()) <= 1 + 1e-6
    empty = vr.render_weights_from_density_packed(torch.zeros(0), torch.zeros(0), torch.zeros(0, dtype=torch.long), 3)
    assert empty.shape == (0,)


# ---------------------------------------------------------------------------------------------
# the model at the extremes
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("density", [0.0, 1e8])
@pytest.mark.parametrize("culled", [False, True])
def test_forced_densities_outputs_and_gradients(gl_context, body, projector, builder, walk, density, culled):
    torch.manual_seed(1)
    model = GarmentAnimationNeRF(tiny_config(), body, PALETTE, projector=projector).train()
    model.nerf = ForcedDensity(model.nerf, density)
    sampling = culled_sampling(model, gl_context, 8) if culled else {}
    posed = walk.slice(0, 3).pose(body)
    frame = model.prepare_frame(builder.build(posed, 2, walk.fps))
    try:
        out = model.render(frame, orbit_camera(30.0, 10.0, 3.0, width=32, height=32),
                           generator=torch.Generator().manual_seed(0), **sampling)
    finally:
        if culled:
            sampling["sampler"].release()
    loss = out.image.mean() + out.opacity.mean() + out.depth.mean() * 1e-3
    loss.backward()
    assert finite(out.image, out.opacity, out.depth)
    grads = [p.grad for p in model.parameters() if p.grad is not None]
    assert grads and all(finite(g) for g in grads)
    if density == 0:
        assert float(out.opacity.detach().max()) == 0
    else:
        assert float(out.opacity.detach().max()) > 0.99


def test_rays_that_miss_everything(gl_context, model, frame):
    R, t = look_at((0.0, -3.0, 1.0), (0.0, -6.0, 1.0))
    away = Camera(intrinsics_from_fov(32, 32, 40.0), R, t, 32, 32)
    for culled in (False, True):
        out = check_render(model, frame, away, culled, gl_context)
        assert out.points_evaluated == 0 and float(out.opacity.abs().max()) == 0


def test_extreme_cameras(gl_context, model, frame):
    verts = frame.posed_vertices
    normals = frame.vertex_normals
    i = int(torch.argmin(verts[:, 1]))  # the frontmost vertex (the body faces -y)
    p, n = verts[i].double().numpy(), normals[i].double().numpy()
    close = look_at(p + 0.01 * n, p)  # 1 cm off the skin, looking at it
    cams = {"1cm": Camera(intrinsics_from_fov(32, 32, 60.0), *close, 32, 32, near=0.001),
            "1km": orbit_camera(20.0, 5.0, 1000.0, width=32, height=32, far=2000.0),
            "1km_narrow": orbit_camera(20.0, 5.0, 1000.0, width=32, height=32, fov_y_deg=0.15, far=2000.0)}
    centre = verts.mean(0).double().numpy()
    inside = look_at(centre, centre + [0.0, -1.0, 0.0])
    cams["inside"] = Camera(intrinsics_from_fov(32, 32, 90.0), *inside, 32, 32, near=0.001)
    for name, cam in cams.items():
        for culled in (False, True):
            out = check_render(model, frame, cam, culled, gl_context)
            if name in ("1cm", "inside", "1km_narrow"):
                assert out.points_evaluated > 0, (name, culled)


def _extreme_motion(body, walk) -> Motion:
    """Frame 0: every joint at 170 degrees (past any joint limit); frame 1: arms folded into the
    torso and legs crossed (self-contact); frame 2: back to rest."""
    J = body.num_joints
    rot = torch.zeros(3, J, 3)
    axis = torch.nn.functional.normalize(torch.randn(J, 3, generator=torch.Generator().manual_seed(0)), dim=-1)
    rot[0, 1:] = axis[1:] * math.radians(170.0)
    names = list(body.joint_names)
    for k, name in enumerate(names):
        low = name.lower()
        if "arm" in low or "shoulder" in low:
            rot[1, k] = torch.tensor([0.0, 0.0, 1.6 if low.endswith("l") else -1.6])
        if "thigh" in low or "upperleg" in low:
            rot[1, k] = torch.tensor([0.0, 0.6 if low.endswith("l") else -0.6, 0.0])
    return Motion("extreme", names, rot, torch.zeros(3, 3), walk.fps, walk.skeleton)


def test_extreme_poses(gl_context, body, builder, model, walk):
    motion = _extreme_motion(body, walk)
    posed = motion.pose(body)
    assert finite(posed.vertices)
    for f in range(3):
        inputs = builder.build(posed, f, motion.fps)
        assert finite(inputs.info_maps)
        with torch.no_grad():
            frame = model.prepare_frame(inputs)
        assert finite(frame.dynamic_features, frame.detail_features)
        for culled in (False, True):
            check_render(model, frame, orbit_camera(45.0 * f, 10.0, 3.0, width=32, height=32), culled, gl_context)


def test_first_frames_and_single_frame_motion(builder, body, walk, model):
    posed = walk.slice(0, 5).pose(body)
    first = builder.build(posed, 0, walk.fps)  # no history at all
    assert finite(first.info_maps) and float(first.info_maps[3:].abs().max()) == 0  # velocities are 0
    second = builder.build(posed, 1, walk.fps)  # one frame of history of the two
    assert finite(second.info_maps)
    single = walk.slice(3, 4)
    assert single.num_frames == 1
    one = builder.build(single.pose(body), 0, single.fps)
    assert finite(one.info_maps) and float(one.info_maps[3:].abs().max()) == 0
    with torch.no_grad():
        frame = model.prepare_frame(one)
    assert finite(frame.dynamic_features)
    whole = builder.build_clip(single.pose(body), single.fps)
    assert len(whole) == 1 and finite(whole[0].info_maps)


def test_palette_edges(model, frame):
    cam = orbit_camera(30.0, 10.0, 3.0, width=32, height=32)
    for value in (0.0, 1.0):
        out = check_render(model, frame, cam, palette=torch.full((2, 3), value))
        assert finite(out.recolor(torch.full((2, 3), 1.0 - value)))
    for bad, message in ((torch.tensor([[1.5, 0.0, 0.0], [0.0, 0.0, 0.0]]), "in \\[0, 1\\]"),
                         (torch.tensor([[-0.1, 0.0, 0.0], [0.0, 0.0, 0.0]]), "in \\[0, 1\\]"),
                         (torch.tensor([[float("nan"), 0.0, 0.0], [0.0, 0.0, 0.0]]), "NaN"),
                         (torch.zeros(2, 4), "\\(P, 3\\)")):
        with pytest.raises(ValueError, match=message):
            check_palette(bad)
    with pytest.raises(ValueError, match="in \\[0, 1\\]"):
        out = check_render(model, frame, cam)
        out.recolor(torch.tensor([[2.0, 0.0, 0.0], [0.0, 0.0, 0.0]]))


def test_half_precision(gl_context, model, frame):
    cam = orbit_camera(30.0, 10.0, 3.0, width=32, height=32)
    for precision in ("bfloat16", "float16"):
        sampling = culled_sampling(model, gl_context, 8)
        try:
            try:
                with torch.no_grad():
                    out = model.render(frame, cam, precision=precision, **sampling)
            except RuntimeError as exc:  # an op without a half kernel on this device
                if precision == "float16":
                    pytest.skip(f"float16 autocast unavailable here: {exc}")
                raise
        finally:
            sampling["sampler"].release()
        assert finite(out.image, out.feature_image) and out.points_evaluated > 0
    # Volume rendering itself in half precision.
    for dtype in (torch.float16, torch.bfloat16):
        w = vr.render_weights_from_density(torch.full((2, 8), 1e4, dtype=dtype), torch.full((2, 8), 0.1, dtype=dtype))
        assert finite(w.float()) and float(w.float().sum(-1).max()) <= 1.01


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def test_long_motion_streams_in_bounded_memory(builder, body, walk):
    """Info maps of a 2000-frame motion, computed frame by frame from a window of k + 1 posed
    frames: nothing of size T is ever materialised but the (T, J, 3) rotations."""
    reps = math.ceil(2000 / walk.num_frames)
    long = Motion("long", walk.joint_names, walk.rotations.repeat(reps, 1, 1)[:2000],
                  walk.translation.repeat(reps, 1)[:2000], walk.fps, walk.skeleton)
    assert long.num_frames == 2000
    k = builder.cfg.encoder.history

    def streamed(f):
        window = long.slice(max(0, f - k), f + 1).pose(body)
        return builder.build(window, window.vertices.shape[0] - 1, long.fps).info_maps

    streamed(0)
    before = _rss_mb()
    checks = {}
    for f in range(0, 2000, 25):  # every 25th frame across the whole motion
        maps = streamed(f)
        assert finite(maps)
        if f in (0, 1000, 1975):
            checks[f] = maps
    grown = _rss_mb() - before
    assert grown < 150, f"memory grew by {grown:.0f} MB while streaming"
    # The streamed maps equal the maps built from the whole (short) clip around the frame.
    for f, maps in checks.items():
        lo = max(0, f - 5)
        clip = long.slice(lo, f + 1).pose(body)
        full = builder.build(clip, f - lo, long.fps).info_maps
        torch.testing.assert_close(maps, full, atol=1e-4, rtol=0)
