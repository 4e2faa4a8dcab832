"""Baked frames: the median depth against an analytic slab, exact recolouring of the attribute layers,
the view mesh and its GL draw against the view's own layers, the angle weights, and the bake files."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from garmentnerf.bake.settings import BakeSettings
from garmentnerf.bake.store import BakeFileError, BakeFolder, frame_bytes, read_frame_file
from garmentnerf.bake.views import (BakedFrame, BakedView, filled_depth, garment_layers, maps_from_layers,
                                    nearest_views, ring_cameras, view_mesh)
from garmentnerf.conventions import Camera, look_at
from garmentnerf.model.palette import DecomposedMaps
from garmentnerf.model.volume_rendering import median_depth_packed, render_packed_segmented


def test_median_depth_of_a_slab_is_where_half_the_light_is_stopped():
    # one ray through a slab of density s starting at t0: opacity 1 - exp(-s (t - t0)) reaches 1/2 at
    # t0 + ln 2 / s; samples of 1 cm, the crossing inside one of them
    s, t0 = 40.0, 1.3
    t_starts = torch.arange(0.0, 3.0, 0.01)
    t_ends = t_starts + 0.01
    sigmas = torch.where(t_starts >= t0 - 1e-6, torch.tensor(s), torch.tensor(0.0))
    ids = torch.zeros(len(t_starts), dtype=torch.long)
    expected = t0 + math.log(2.0) / s
    assert float(median_depth_packed(sigmas, t_starts, t_ends, ids, 1)[0]) == pytest.approx(expected, abs=1e-4)
    march = render_packed_segmented(lambda i: (sigmas[i], torch.zeros(len(i), 1)), t_starts, t_ends, ids, 1, 1,
                                    chunk_points=7, termination_eps=1e-4)
    assert float(march.median_depth[0]) == pytest.approx(expected, abs=1e-4)
    # a ray that never reaches one half has none
    faint = torch.full_like(t_starts, 0.1)
    assert float(median_depth_packed(faint, t_starts, t_ends, ids, 1)[0]) == 0.0


def _random_maps(P: int, H: int = 6, W: int = 5, seed: int = 0) -> DecomposedMaps:
    g = torch.Generator().manual_seed(seed)
    w = torch.rand(1, P, H, W, generator=g) + 0.05
    return DecomposedMaps(torch.rand(1, 1, H, W, generator=g) * 1.5, (torch.rand(1, P, 3, H, W, generator=g) - 0.5) * 0.4,
                          w / w.sum(1, keepdim=True), torch.rand(1, 1, H, W, generator=g))


@pytest.mark.parametrize("P", [2, 3, 4])
def test_garment_layers_recolour_exactly_over_the_body(P):
    maps = _random_maps(P, seed=P)
    g = torch.Generator().manual_seed(10 + P)
    body = (torch.rand(1, 3, 6, 5, generator=g), torch.rand(1, 1, 6, 5, generator=g))
    baked = maps_from_layers(garment_layers(maps))
    for k in range(3):
        palette = torch.rand(P, 3, generator=g)
        want = maps.with_body(*body).compose(palette, (0.1, 0.2, 0.3))
        got = baked.with_body(*body).compose(palette, (0.1, 0.2, 0.3))
        assert torch.allclose(got, want, atol=1e-5), k


def test_a_palette_without_a_body_colour_cannot_be_baked():
    with pytest.raises(ValueError, match="garment and a body"):
        garment_layers(_random_maps(1))


def _plane_view(size=(48, 40), depth=2.0, cell=4, seed=0) -> BakedView:
    """A view of a plane facing its camera at ``depth``, random attributes, visibility 1."""
    W, H = size
    K = np.array([[60.0, 0, (W - 1) / 2], [0, 60.0, (H - 1) / 2], [0, 0, 1]])
    R, t = look_at([0.0, -3.0, 1.0], [0.0, 0.0, 1.0])
    rng = np.random.default_rng(seed)
    layers = rng.uniform(0.1, 0.9, (3, H, W, 4)).astype(np.float32)
    layers[0, ..., 3] = 1.0
    return BakedView.from_values(Camera(K, R, t, W, H), layers, np.full((H // cell, W // cell), depth, np.float32), cell)


def test_view_mesh_lies_on_the_depth_and_projects_to_its_pixels():
    view = _plane_view()
    mesh = view_mesh(view)
    cam = view.camera
    xc = mesh.positions.astype(np.float64) @ cam.R.T + cam.t
    assert np.allclose(xc[:, 2], 2.0, atol=1e-5)
    uv = xc @ cam.K.T
    pix = uv[:, :2] / uv[:, 2:]
    assert np.allclose((pix + 0.5) / [cam.width, cam.height], mesh.texcoords, atol=1e-5)
    # a full grid: two triangles per cell of pixel centres
    assert len(mesh.faces) == 2 * (cam.width - 1) * (cam.height - 1)


def test_filled_depth_grows_by_neighbour_means():
    z = torch.zeros(5, 5, dtype=torch.float64)
    z[2, 2] = 3.0
    once = filled_depth(z, rays=1)
    assert torch.all(once[1:4, 1:4] == 3.0) and once[0, 0] == 0.0
    assert torch.all(filled_depth(z, rays=2) == 3.0)


def test_gl_draw_of_a_view_from_its_own_camera_returns_its_layers(gl_context):
    from garmentnerf.bake.draw import BakeDrawer

    view = _plane_view()
    drawer = BakeDrawer(gl_context, draw_views=1)
    try:
        layers = drawer.read_layers(BakedFrame(0, (view,)), view.camera)
    finally:
        drawer.release()
    inner = (slice(1, -1), slice(1, -1))  # pixel centres inside the mesh (the border pixels are its edge)
    for j in range(3):
        want = view.layers[j][inner].copy()
        if j == 1:
            want[..., 3] = 1.0  # layer 1's fourth channel: the view covers the pixel
        assert np.allclose(layers[j][inner], want, atol=1e-3), j  # the slots are half floats


def test_gl_body_hides_the_bake_only_beyond_the_margin(gl_context):
    from garmentnerf.bake.draw import BakeDrawer

    view = _plane_view(depth=2.0)
    cam = view.camera
    corners = np.array([[-5, -5], [5, -5], [5, 5], [-5, 5]], np.float64)
    drawer = BakeDrawer(gl_context, draw_views=1, body_margin=0.04)
    try:
        covered = {}
        for body_z in (1.98, 1.9):  # a wall 2 cm and 10 cm in front of the plane
            world = (np.c_[corners, np.full(4, body_z)] - cam.t) @ cam.R
            drawer.set_body(body_z, world.astype(np.float32), np.array([[0, 1, 2], [0, 2, 3]], np.uint32))
            covered[body_z] = float(drawer.read_layers(BakedFrame(0, (view,)), cam)[1, ..., 3].mean())
    finally:
        drawer.release()
    assert covered[1.98] > 0.9 and covered[1.9] == 0.0


def test_nearest_views_weights_follow_the_angle():
    centers = np.array([[math.cos(a), math.sin(a), 0.0] for a in np.deg2rad([0, 90, 180, 270])]) * 3
    eye = np.array([math.cos(math.radians(30)), math.sin(math.radians(30)), 0.0]) * 5
    chosen = nearest_views(centers, np.zeros(3), eye, 2)
    assert [i for i, _ in chosen] == [0, 1]
    # angles 30 and 60 degrees, cut-off at the third nearest (120): weights 1 - 30/120, 1 - 60/120, normalised
    w0, w1 = 0.75, 0.5
    assert chosen[0][1] == pytest.approx(w0 / (w0 + w1)) and chosen[1][1] == pytest.approx(w1 / (w0 + w1))
    assert nearest_views(centers, np.zeros(3), eye, 1) == [(0, 1.0)]


def test_ring_cameras_stand_on_the_training_ring():
    K = np.array([[700.0, 0, 255.5], [0, 700.0, 255.5], [0, 0, 1]])
    training = []
    for a in np.deg2rad(np.arange(0, 360, 45)):
        R, t = look_at([3 * math.sin(a), -3 * math.cos(a), 1.0], [0, 0, 0.9])
        training.append(Camera(K, R, t, 512, 512))
    ring = ring_cameras(training, (0.5, -0.2), 16)
    centers = np.stack([c.center for c in ring])
    assert np.allclose(np.linalg.norm(centers[:, :2] - [0.5, -0.2], axis=1), 3.0)
    assert np.allclose(centers[:, 2], 1.0)
    forward = np.stack([c.R[2] for c in ring])  # same tilt as the training cameras: looking at z 0.9 from 3 m
    assert np.allclose(forward[:, 2] / np.linalg.norm(forward[:, :2], axis=1), -0.1 / 3.0)


def test_a_view_quantises_each_channel_to_within_half_a_step():
    rng = np.random.default_rng(3)
    values = rng.normal(0.0, 2.0, (3, 9, 7, 4)).astype(np.float32)
    view = BakedView.from_values(_plane_view().camera, values, np.ones((2, 1), np.float32), 4)
    span = values.max(axis=(1, 2)) - values.min(axis=(1, 2))
    assert np.all(np.abs(view.layers - values) <= span[:, None, None, :] / 510 + 1e-6)
    assert np.allclose(view.visibility, view.layers[0, ..., 3])


def test_bake_files_round_trip(tmp_path):
    views = (_plane_view(seed=1), _plane_view(size=(32, 24), depth=1.5, seed=2))
    baked = BakedFrame(7, views)
    path = tmp_path / "f.npz"
    path.write_bytes(frame_bytes(baked))
    back = read_frame_file(path, 7)
    for a, b in zip(baked.views, back.views):
        assert np.array_equal(a.codes, b.codes) and np.array_equal(a.low, b.low) and np.array_equal(a.high, b.high)
        assert np.allclose(a.depth, b.depth, rtol=1e-3)
        assert np.allclose(a.camera.K, b.camera.K) and a.camera.width == b.camera.width
    with pytest.raises(BakeFileError, match="holds frame 7, not 8"):
        read_frame_file(path, 8)
    path.write_bytes(frame_bytes(baked)[:100])
    with pytest.raises(BakeFileError, match="not a readable bake frame"):
        read_frame_file(path, 7)


def test_a_bake_folder_names_what_it_was_made_for(tmp_path):
    settings = BakeSettings("custom", views=8, quality=0.5)
    manifest = BakeFolder.manifest_for("m" * 32, "w" * 32, "walk", settings, 10)
    folder = BakeFolder.create(tmp_path / "b", manifest)
    again = BakeFolder.open(tmp_path / "b")
    assert again.mismatch(manifest) is None and again.num_frames == 10
    other = BakeFolder.manifest_for("x" * 32, "w" * 32, "walk", settings, 10)
    assert "another model" in again.mismatch(other)
    finer = BakeFolder.manifest_for("m" * 32, "w" * 32, "walk", BakeSettings("custom", views=16, quality=0.5), 10)
    assert "other bake settings" in again.mismatch(finer)
    folder.save_frame(BakedFrame(3, (_plane_view(),)))
    assert folder.baked_frames() == {3} and folder.load_frame(4) is None
    assert folder.load_frame(3).frame == 3
    with pytest.raises(ValueError, match="not a bake folder"):
        BakeFolder.open(tmp_path)
