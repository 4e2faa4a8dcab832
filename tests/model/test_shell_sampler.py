"""The shell sampler (garmentnerf.render.shell_sampler), the height band filter
(garmentnerf.model.height_band), early termination in the render, the render presets and
``garmentnerf bench --run``."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
import torch

from garmentnerf.conventions import Camera, camera_rays, intrinsics_from_fov, look_at, orbit_camera
from garmentnerf.geometry.winding import point_in_shell, winding_number
from garmentnerf.model.config import ModelConfig
from garmentnerf.model.field import Field
from garmentnerf.model.height_band import HeightRange, dilate_vertex_values, measure_height_range
from garmentnerf.model.pipeline import GarmentAnimationNeRF
from garmentnerf.model.samplers import BoxStratifiedSampler, body_aabb
from garmentnerf.render.shell_sampler import ShellSampler

PALETTE = {"garment": [0.8, 0.2, 0.2], "body": [0.7, 0.6, 0.5]}
BAND = HeightRange(-0.05, 0.10)
CAMERA = orbit_camera(30.0, 10.0, 3.0, width=64, height=64)


def tiny_config(changes: dict | None = None) -> ModelConfig:
    return ModelConfig.tiny().updated({"sampler.samples_per_ray": 32, **(changes or {})})


class Banded(Field):
    """Wraps the model's field: density zero wherever h is outside the band (and optionally scaled)."""

    def __init__(self, inner: Field, band: HeightRange, scale: float = 1.0):
        super().__init__()
        self.inner, self.band, self.scale, self.zeta_channels = inner, band, scale, inner.zeta_channels

    def evaluate(self, frame, points, *, clock, autocast):
        sigma, zeta = self.inner.evaluate(frame, points, clock=clock, autocast=autocast)
        distance = points.signed_distance.to(sigma.device)
        inside = (distance >= self.band.h_min) & (distance <= self.band.h_max)
        return sigma * inside.to(sigma.dtype) * self.scale, zeta


@pytest.fixture(scope="module")
def verts(walk_clip):
    """Frame 2 of the walk clip: the posed skin (V, 3) float32 the samplers bind to."""
    return walk_clip[0].vertices[2].float()


def banded_model(body, projector, scale=1.0, changes: dict | None = None):
    torch.manual_seed(0)
    model = GarmentAnimationNeRF(tiny_config(changes), body, PALETTE, projector=projector).eval()
    model.nerf = Banded(model.nerf, BAND, scale)
    return model


@pytest.fixture(scope="module")
def model_and_frame(body, projector, walk_inputs):
    model = banded_model(body, projector)
    with torch.no_grad():
        frame = model.prepare_frame(walk_inputs)
    return model, frame


def _surface_distance(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, within: float) -> np.ndarray:
    """Unsigned distance to the mesh with trimesh (inf where certainly farther than ``within``)."""
    import trimesh
    from scipy.spatial import cKDTree

    mesh = trimesh.Trimesh(vertices, faces, process=False)
    edge = float(np.linalg.norm(vertices[faces[:, 0]] - vertices[faces[:, 1]], axis=1).max())
    dv, _ = cKDTree(vertices[np.unique(faces)]).query(points)
    cand = np.flatnonzero(dv <= within + edge)  # nearest vertex - longest edge bounds the distance below
    out = np.full(len(points), np.inf)
    for i in range(0, len(cand), 4000):
        c = cand[i:i + 4000]
        _, d, _ = trimesh.proximity.closest_point(mesh, points[c])
        out[c] = d
    return out


class PosedFrame:
    """What a sampler's ``bind`` reads of a frame's features: the posed body and its box."""

    def __init__(self, vertices):
        self.posed_vertices = vertices
        self.aabb = body_aabb(vertices)


def _sample(sampler, verts, cam, training=False):
    """(bound sampler, samples of every pixel ray of ``cam``)."""
    bound = sampler.bind(PosedFrame(verts), cam)
    return bound, bound.sample(torch.arange(cam.width * cam.height), training=training)


def _keys(ray_ids, t_starts):
    return set(zip(ray_ids.tolist(), np.round(t_starts.double().numpy() * 1e4).astype(np.int64).tolist()))


# ---------------------------------------------------------------------------------------------
def test_shell_contains_every_box_sample_near_the_body(gl_context, verts, projector):
    sampler = ShellSampler(64, projector.faces, BAND, gl_context=gl_context)
    cam = CAMERA.resized(40, 40)
    _, shell = _sample(sampler, verts, cam)
    _, box = _sample(BoxStratifiedSampler(64), verts, cam)
    # Independent: trimesh distances of the box samples to the posed skin; every sample within
    # h_max of the skin (inside or outside: a superset of the band) must be in the shell's set.
    dist = _surface_distance(box.positions.double().numpy(), verts.double().numpy(), projector.faces.numpy(),
                             BAND.h_max)
    near = dist <= BAND.h_max
    have = _keys(shell.ray_ids, shell.t_starts)
    box_keys = list(zip(box.ray_ids.tolist(), np.round(box.t_starts.double().numpy() * 1e4).astype(np.int64).tolist()))
    missing = [k for k, n in zip(box_keys, near) if n and k not in have]
    assert near.sum() > 1000 and not missing
    # Shell samples are the box's own samples (same intervals), and far fewer.
    assert have <= set(box_keys)
    assert shell.positions.shape[0] < 0.5 * box.positions.shape[0]
    # A subset of the rays gets exactly the samples those rays get in the whole image.
    bound = sampler.bind(PosedFrame(verts), cam)
    pixels = torch.arange(0, 1600, 7)
    part = bound.sample(pixels)
    whole = {(int(r), k) for r, k in _keys(shell.ray_ids, shell.t_starts) if r % 7 == 0}
    assert {(int(pixels[r]), k) for r, k in _keys(part.ray_ids, part.t_starts)} == whole
    # Per-ray bounds: every sample between its ray's near and far (up to one bin of the box).
    bin_len = float(box.deltas.max())
    assert bool((shell.t_mids >= shell.near[shell.ray_ids] - bin_len).all())
    assert bool((shell.t_mids <= shell.far[shell.ray_ids] + bin_len).all())
    sampler.release()


def test_rays_that_miss_get_nothing(gl_context, verts, projector):
    sampler = ShellSampler(16, projector.faces, BAND, gl_context=gl_context)
    cam = CAMERA.resized(32, 32)
    bound, out = _sample(sampler, verts, cam)
    bounds = bound.bounds
    hit_rays = torch.unique(out.ray_ids)
    assert 0 < hit_rays.numel() < 1024
    assert bounds.hit.reshape(-1)[hit_rays].all()  # only rays that cross the shell have samples
    assert (~out.hit[~bounds.hit.reshape(-1)]).all()
    # Samples lie between the shell's near and far (up to one bin).
    t = out.t_mids
    bin_len = (out.t_ends - out.t_starts).max()
    near, far = bounds.near.reshape(-1)[out.ray_ids], bounds.far.reshape(-1)[out.ray_ids]
    assert (t >= near - bin_len).all() and (t <= far + bin_len).all()
    # A camera looking away from the body: no samples at all.
    R, tvec = look_at((0.0, -3.0, 1.0), (0.0, -6.0, 1.0))
    away = Camera(intrinsics_from_fov(32, 32, 40.0), R, tvec, 32, 32)
    _, none = _sample(sampler, verts, away)
    assert none.positions.shape[0] == 0 and not none.hit.any()
    sampler.release()


def test_inside_the_shell_and_far_away(gl_context, verts, projector):
    faces = projector.faces
    centre = verts[faces.reshape(-1)].mean(0)
    torso = torch.tensor([float(centre[0]), float(centre[1]), 1.2])
    assert winding_number(torso, verts, faces) > 0.9
    assert winding_number(torso + torch.tensor([0.0, 0.0, 5.0]), verts, faces) < 0.1
    assert point_in_shell(torso, verts, faces, 0.1)
    sampler = ShellSampler(16, faces, BAND, gl_context=gl_context)
    R, t = look_at(torso.numpy(), (torso + torch.tensor([0.0, -1.0, 0.0])).numpy())
    inside = Camera(intrinsics_from_fov(16, 16, 90.0), R, t, 16, 16)
    bound, out = _sample(sampler, verts, inside)
    assert bound.bounds.hit.all() and (bound.bounds.near == 0).all()
    assert out.hit.all() and (out.t_starts.reshape(-1)[:1] == 0).all()
    far_cam = orbit_camera(0.0, 0.0, 1000.0, width=16, height=16, fov_y_deg=0.1, far=2000.0)
    _, out = _sample(sampler, verts, far_cam)
    assert out.positions.shape[0] > 0 and torch.isfinite(out.positions).all()
    sampler.release()


# ---------------------------------------------------------------------------------------------
def test_culled_render_equals_reference(gl_context, model_and_frame):
    model, frame = model_and_frame
    with torch.no_grad():
        ref = model.render(frame, CAMERA)
    sampler = ShellSampler(model.cfg.sampler.samples_per_ray, model.projector.faces, BAND, gl_context=gl_context)
    culled = {"sampler": sampler, "sample_filter": BAND.sample_filter(model.projector.faces)}
    try:
        with torch.no_grad():
            out = model.render(frame, CAMERA, **culled)
        assert 0 < out.points_evaluated < 0.5 * ref.points_evaluated
        assert out.points_evaluated < out.points_projected == out.samples_placed < ref.samples_placed
        torch.testing.assert_close(out.feature_image, ref.feature_image, atol=1e-5, rtol=0)
        torch.testing.assert_close(out.opacity, ref.opacity, atol=1e-6, rtol=0)
        torch.testing.assert_close(out.image, ref.image, atol=1e-5, rtol=0)
        # A subset of rays renders as the same rays of the full image.
        mask = torch.zeros(16, 16, dtype=torch.bool)
        mask[3:13, 5:11] = True
        with torch.no_grad():
            sub = model.render_features(frame, CAMERA, mask, **culled)
        torch.testing.assert_close(sub["feature_image"][:, mask], out.feature_image[:, mask], atol=1e-6, rtol=0)
        # Training draws jittered samples through the same interface, with gradients.
        model.train()
        trained = model.render(frame, CAMERA, training=True, generator=torch.Generator().manual_seed(0), **culled)
        trained.image.sum().backward()
        assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in model.decoder.parameters())
    finally:
        model.eval()
        model.zero_grad(set_to_none=True)
        sampler.release()


def test_height_band_drop_does_not_change_the_image(model_and_frame):
    """Same (box) samples with and without the band: a model with zero density outside it renders
    the same image, while evaluating fewer points."""
    model, frame = model_and_frame
    wide = HeightRange(-10.0, 10.0)
    faces = model.projector.faces
    with torch.no_grad():
        everything = model.render(frame, CAMERA, sample_filter=wide.sample_filter(faces))
        banded = model.render(frame, CAMERA, sample_filter=BAND.sample_filter(faces))
    assert banded.points_evaluated < 0.5 * everything.points_evaluated
    assert banded.points_projected == everything.points_projected == everything.points_evaluated
    torch.testing.assert_close(banded.feature_image, everything.feature_image, atol=1e-6, rtol=0)
    torch.testing.assert_close(banded.opacity, everything.opacity, atol=1e-6, rtol=0)
    torch.testing.assert_close(banded.image, everything.image, atol=1e-5, rtol=0)


def test_early_termination(gl_context, body, projector, walk_inputs):
    """An opaque model: rays stop once T < eps; the result moves by at most about eps."""
    model = banded_model(body, projector, scale=200.0)
    with torch.no_grad():
        frame = model.prepare_frame(walk_inputs)
        ref = model.render(frame, CAMERA)
    assert ref.opacity.max() > 0.999
    eps = 1e-3
    sampler = ShellSampler(model.cfg.sampler.samples_per_ray, model.projector.faces, BAND, gl_context=gl_context)
    try:
        with torch.no_grad():
            out = model.render(frame, CAMERA, chunk_points=512, sampler=sampler, termination_eps=eps,
                               sample_filter=BAND.sample_filter(model.projector.faces))
        assert out.rays_terminated > 0 and out.points_projected < out.samples_placed
        zmax = float(ref.feature_image.abs().max())
        assert (out.opacity - ref.opacity).abs().max() <= eps + 1e-6
        assert (out.feature_image - ref.feature_image).abs().max() <= eps * max(zmax, 1.0) * 20
        assert torch.isfinite(out.image).all()
    finally:
        sampler.release()


def test_measure_height_range(tiny_scene, body, projector):
    band = measure_height_range(tiny_scene, body, projector=projector)
    assert band.h_min < 0 < band.h_max < 0.6
    assert "train" in band.source
    assert HeightRange.from_dict(band.to_dict()) == band
    with pytest.raises(ValueError):
        HeightRange(0.2, 0.1)


def test_per_vertex_band_is_tight_where_the_garment_never_goes(tiny_scene, body, projector):
    import trimesh

    band = measure_height_range(tiny_scene, body, projector=projector, rings=2)
    v = band.vertex_h_max
    assert v is not None and v.shape == (projector.canonical_vertices.shape[0],)
    assert float(v.min()) == pytest.approx(0.03, abs=1e-6)  # bare skin: just the margin
    assert float(v.max()) == pytest.approx(band.h_max, abs=1e-6)
    assert float((v > 0.05).float().mean()) < 0.5  # the tiny scene's garment covers a minority
    # every garment vertex lies under its face's interpolated bound (what the cull relies on)
    from garmentnerf.data.scene import read_garment_arrays

    g = read_garment_arrays(tiny_scene.garment_path("train"))
    motion = tiny_scene.load_motion("train")
    posed = motion.slice(1, 2).pose(body, body.betas("average")).vertices[0].float()
    proj = projector.bind(posed).project(torch.from_numpy(g.vertices[1]).float())
    bound = band.upper_bound(proj.face, proj.bary, projector.faces)
    assert bool((proj.signed_distance <= bound + 1e-6).all())
    # dilation: the value spreads exactly over the mesh's k-ring (graph distance from trimesh)
    faces = projector.faces.cpu().numpy()
    mesh = trimesh.Trimesh(projector.canonical_vertices.cpu().numpy(), faces, process=False)
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import shortest_path

    e = mesh.edges_unique
    graph = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(len(mesh.vertices),) * 2)
    seed = int(faces[0, 0])
    hops = shortest_path(graph, directed=False, unweighted=True, indices=seed)
    rings = np.flatnonzero(hops <= 3).tolist()
    one = torch.zeros(mesh.vertices.shape[0])
    one[seed] = 1.0
    got = set(torch.nonzero(dilate_vertex_values(one, projector.faces, 3)).squeeze(1).tolist())
    assert got == set(rings)


def test_per_vertex_shell_culls_samples_near_bare_skin(gl_context, verts, projector):
    V = verts.shape[0]
    reach = 0.03
    thin = HeightRange(-0.05, 0.30, vertex_h_max=torch.full((V,), reach))
    wide = HeightRange(-0.05, 0.30)
    cam = CAMERA.resized(40, 40)
    kept = {}
    for name, band in (("thin", thin), ("wide", wide)):
        s = ShellSampler(64, projector.faces, band, gl_context=gl_context)
        kept[name] = _sample(s, verts, cam)[1]
        s.release()
    # Conservative: every box sample within the thin reach of the skin (trimesh) is kept ...
    _, box = _sample(BoxStratifiedSampler(64), verts, cam)
    dist = _surface_distance(box.positions.double().numpy(), verts.double().numpy(), projector.faces.numpy(), reach)
    near = dist <= reach
    have = _keys(kept["thin"].ray_ids, kept["thin"].t_starts)
    box_keys = list(zip(box.ray_ids.tolist(), np.round(box.t_starts.double().numpy() * 1e4).astype(np.int64).tolist()))
    assert near.sum() > 500 and not [k for k, n in zip(box_keys, near) if n and k not in have]
    # ... and far fewer samples than the uniform shell keeps.
    assert kept["thin"].positions.shape[0] < 0.6 * kept["wide"].positions.shape[0], (
        kept["thin"].positions.shape[0], kept["wide"].positions.shape[0])
    # The per-sample bound interpolates the vertex values: constant here.
    proj = projector.project(kept["thin"].positions.float(), verts)
    bound = thin.upper_bound(proj.face, proj.bary, projector.faces)
    assert torch.allclose(bound, torch.full_like(bound, reach))


def test_occlusion_cuts_rays_behind_the_skin(gl_context, verts, projector):
    import trimesh

    cam = CAMERA.resized(32, 32)
    origins, dirs = (x.reshape(-1, 3) for x in camera_rays(cam))
    margin = 0.05
    out = {}
    for occ in (False, True):
        s = ShellSampler(64, projector.faces, BAND, gl_context=gl_context, occlusion=occ, occlusion_margin=margin)
        out[occ] = _sample(s, verts, cam)[1]
        s.release()
    kept, full = _keys(out[True].ray_ids, out[True].t_starts), _keys(out[False].ray_ids, out[False].t_starts)
    assert kept < full and len(kept) < 0.9 * len(full)
    # Independent first skin hit per ray (trimesh ray casting): every sample of the uncut set that
    # starts before hit + margin is kept; none starts beyond hit + margin + one bin.
    mesh = trimesh.Trimesh(verts.double().numpy(), projector.faces.numpy(), process=False)
    o, d = origins.double().numpy(), dirs.double().numpy()
    locs, ray_idx, _ = mesh.ray.intersects_location(o, d, multiple_hits=True)
    first = np.full(len(o), np.inf)
    np.minimum.at(first, ray_idx, np.linalg.norm(locs - o[ray_idx], axis=1))
    rid, ts = out[False].ray_ids.numpy(), out[False].t_starts.double().numpy()
    te = out[False].t_ends.double().numpy()
    key = np.round(ts * 1e4).astype(np.int64)
    must = te <= first[rid] + margin - 1e-3  # the whole bin lies in front of the cut
    assert must.sum() > 500
    assert all((int(r), int(k)) in kept for r, k in zip(rid[must], key[must]))
    rid2, ts2 = out[True].ray_ids.numpy(), out[True].t_starts.double().numpy()
    assert (ts2 <= first[rid2] + margin + 1e-3).all()


def test_presets_render_through_their_sampling_plans(gl_context, model_and_frame):
    from garmentnerf.render.presets import RENDER_PRESETS, VIEWER_LEVELS, get_render_preset
    from garmentnerf.render.session import padded_render_camera

    model, frame = model_and_frame
    points, images = {}, {}
    for name in ("reference", "full", "balanced", "interactive"):
        preset = get_render_preset(name)
        plan = preset.sampling(model, BAND, gl_context)
        assert isinstance(plan.sampler, BoxStratifiedSampler if name == "reference" else ShellSampler)
        assert (plan.sample_filter is None) == (name == "reference")
        assert plan.termination_eps == preset.termination_eps and plan.precision == preset.precision
        padded, size, (w, h) = padded_render_camera(CAMERA, preset.resolution_scale, 4)
        with torch.no_grad():
            out = model.render(frame, padded, feature_size=size, **plan.render_kwargs())
        plan.release()
        images[name] = out.maps.cropped(w, h).resized(64, 64).compose(out.palette, out.background)[0]
        assert torch.isfinite(images[name]).all()
        points[name] = out.points_evaluated
    assert points["reference"] > points["full"] > points["balanced"] > points["interactive"] > 0
    # The model has no density outside the band, so the full preset differs from the reference only
    # by what its skin occlusion cuts (this untrained model is far from opaque behind the skin).
    diff = (images["full"] - images["reference"]).abs()
    assert float(diff.max()) < 0.01 and float(diff.mean()) < 1e-3
    assert float((images["interactive"] - images["reference"]).abs().mean()) > float(diff.mean())
    assert set(RENDER_PRESETS) == {"reference", "full", "balanced", "interactive"}
    assert set(VIEWER_LEVELS) <= set(RENDER_PRESETS) and VIEWER_LEVELS[0] == "interactive"
    with pytest.raises(ValueError, match="unknown render preset"):
        get_render_preset("warp")


def test_the_reference_preset_samples_in_the_box_and_the_culled_ones_in_the_shell(gl_context, body, projector):
    from garmentnerf.render.presets import RENDER_PRESETS

    model = GarmentAnimationNeRF(tiny_config({"sampler.samples_per_ray": 16}), body, PALETTE, projector=projector)
    for name, preset in RENDER_PRESETS.items():
        plan = preset.sampling(model, BAND, gl_context)
        assert preset.uses_shell() == (name != "reference")
        assert isinstance(plan.sampler, ShellSampler if preset.uses_shell() else BoxStratifiedSampler)
        assert plan.sampler.num_samples == preset.samples_per_ray(model.cfg)
        plan.release()


def test_bench_cli_with_run(tmp_path, tiny_scene):
    from garmentnerf.cli.main import main
    from garmentnerf.runs import create_untrained_run

    run = create_untrained_run(tmp_path / "run", tiny_scene.root, tiny_config({"sampler.samples_per_ray": 8}))
    out_json, out_png = tmp_path / "bench.json", tmp_path / "bench.png"
    rc = main(["bench", "--run", str(run), "--json", str(out_json), "--plot", str(out_png), "--frames", "1",
               "--views", "1", "--repeats", "1", "--presets", "full,interactive"])
    assert rc in (0, None)
    data = json.loads(out_json.read_text())
    names = [p["preset"] for p in data["presets"]]
    assert names == ["reference", "full", "interactive"]  # reference always measured alongside
    for p in data["presets"]:
        assert p["ms_per_frame"] > 0 and p["points_per_frame"] >= 0 and np.isfinite(p["psnr"])
        assert set(p["stages_ms"]) == {"info_maps", "reference_images", "encoders", "projection", "mlp",
                                       "compositing", "decoder", "body_layer"}
        assert p["stages_ms"]["body_layer"] == 0.0  # an untrained run has no body appearance
    assert data["presets"][0]["speedup_vs_reference"] == 1.0
    pb = data["playback"]
    assert pb["precomputed"] == len(pb["frames"]) == 3 and pb["precompute_ms_per_frame"] > 0  # the tiny clip
    assert set(pb["presets"]) == set(names) and all(r["fps"] > 0 for r in pb["presets"].values())
    assert pb["scrub_ready_ms"] > 0 and pb["scrub_cold_ms"] is None  # every frame of the clip was ready
    ahead = pb["render_ahead"]  # per preset, the clip rendered ahead by the previewer's worker
    assert set(ahead["presets"]) == set(names) and 0 < pb["completed_share"] <= 1
    for row in ahead["presets"].values():
        assert {"seconds_for_clip", "fps_after", "max_lag_frames"} <= set(row) and row["seconds_for_clip"] > 0
    assert all(0 <= p["rays_missing_share"] < 1 for p in data["presets"])
    assert out_png.stat().st_size > 1000
    # other processes' load over the benchmark, beside its figures (garmentnerf.cpu_load; None off Linux)
    others = data["machine"]["other_processes_cores"]
    assert others is None or 0.0 <= others <= os.cpu_count()
