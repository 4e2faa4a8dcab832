"""The window from its first frame (REAL window under Xvfb, see conftest.py): the posed body stands in
until the neural garment arrives, and the default camera keeps a character that walks away in frame.
"""

from __future__ import annotations

import shutil
import threading
import time

import numpy as np
import pytest
import torch

from garmentnerf.conventions import project_points
from garmentnerf.viewer.camera import OrbitController, follow_track

WINDOW = (320, 240)


def _projected(camera, points):
    """(N, 2) pixel coordinates and (N,) depths of world ``points`` (N, 3) seen by ``camera``."""
    uv, z = project_points(camera, torch.as_tensor(np.asarray(points), dtype=torch.float64))
    return uv.numpy(), z.numpy()


@pytest.fixture
def green_run(untrained_run, tiny_scene, tmp_path):
    """The untrained run with a learned body appearance of albedo (0, 3, 0) and no shading (S = 1):
    its body is drawn in clamp((0, 3 g, 0)), g the green of the body's palette colour, unlit, so its
    pixels can be told exactly."""
    from garmentnerf.model.body_appearance import BodyAppearance, save_body_appearance
    from garmentnerf.runs import load_run

    run_dir = tmp_path / "run"
    shutil.copytree(untrained_run, run_dir)
    green = BodyAppearance(texture_size=8)
    with torch.no_grad():
        green.albedo[0] = 0.0
        green.albedo[1] = 3.0
        green.albedo[2] = 0.0
    save_body_appearance(run_dir / "body_appearance.safetensors", green)
    return load_run(run_dir, scene=tiny_scene.root)


def test_the_body_is_drawn_from_the_first_frame_and_the_garment_joins_it_later(xvfb, green_run, tmp_path, monkeypatch):
    """Every neural render waits at a gate: the window's first frame already shows the posed body (in
    the run's learned appearance, depth tested) where it projects; while the gate is closed the body
    stays and the overlay says which frame the garment is rendering; once open, the garment arrives,
    composed over the body as before, and the stand-in goes."""
    from garmentnerf.render.session import RenderSession
    from garmentnerf.viewer.app import App
    from garmentnerf.viewer.panels import garment_status

    gate = threading.Event()
    slow_render = RenderSession.render

    def render(self, *args, **kwargs):
        gate.wait(300)  # the worker thread waits: the UI must not
        return slow_render(self, *args, **kwargs)

    monkeypatch.setattr(RenderSession, "render", render)
    try:
        with App(motion=None, run=green_run, size=WINDOW, samples=0, vsync=False, playing=False,
                 snapshot_dir=tmp_path, dynamic_scene=False) as viewer:
            view, layer, body = viewer.neural_view, viewer.scene.palette_layer, viewer.scene.body
            viewer.show_ui = False
            first = viewer.read_framebuffer()  # the window's first frame
            assert not view.has_image and body.standin and body.learned and not body.visible
            assert viewer.first_frames.body_s > 0 and viewer.first_frames.garment_s is None
            # the body's pixels: exactly its learned colour, unlit, inside the rectangle it projects to
            camera = viewer.view_camera(*viewer.window.framebuffer_size)
            frame = viewer.timeline.frame
            uv, z = _projected(camera, viewer.sequence.positions(frame))
            assert (z > 0).all()
            x0, y0 = np.floor(uv.min(axis=0)).astype(int)
            x1, y1 = np.ceil(uv.max(axis=0)).astype(int)
            assert 0 <= x0 < x1 < WINDOW[0] and 0 <= y0 < y1 < WINDOW[1]
            expected = np.clip(np.array([0.0, 3.0 * view.palette[-1][1], 0.0]), 0, 1) * 255
            is_body = np.abs(first.astype(float) - expected).max(axis=-1) <= 3
            inside = np.zeros_like(is_body)
            inside[y0:y1 + 1, x0:x1 + 1] = True
            assert is_body[inside].sum() > 150, is_body[inside].sum()
            assert is_body[inside].sum() > 0.2 * inside.sum()  # the silhouette fills its rectangle fairly
            assert not is_body[~inside].any()
            # a while later, no neural frame yet: the body is still there, the overlay names the frame
            start = time.monotonic()
            while time.monotonic() - start < 1.0:
                viewer.step()
            assert viewer.first_frames.garment_s is None
            assert not view.has_image and view.renderer.stats.renders == 0
            assert garment_status(view.renderer.activity) == f"garment: rendering frame {frame} ..."
            waiting = viewer.read_framebuffer()
            assert (np.abs(waiting.astype(float) - expected).max(axis=-1) <= 3)[inside].sum() > 150
            # the garment arrives: the neural image (with the body layer under the garment) replaces the stand-in
            gate.set()
            assert viewer.wait_for_neural(300), view.error()
            viewer.step()
            viewer.run_until(view.settled, 120)
            viewer.step()
            assert view.has_image and layer.has_body and not body.standin and not body.drawn
            assert viewer.first_frames.garment_s >= viewer.first_frames.body_s > 0
            composed = viewer.read_framebuffer()
            # never an empty stage: the neural image carries the body (the untrained garment veils it a little)
            c = composed.astype(int)
            green = (c[..., 1] > c[..., 0] + 100) & (c[..., 1] > c[..., 2] + 100)
            assert green[inside].sum() > 0.8 * is_body[inside].sum()
            assert viewer.stats()["first_frame"]["garment_s"] == viewer.first_frames.garment_s
    finally:
        gate.set()


def test_without_a_learned_appearance_the_stand_in_is_the_studio_body(xvfb, untrained_run, tmp_path, monkeypatch):
    """A run without a body appearance (the network draws the body): the stand-in is the studio
    material until the first neural image."""
    from garmentnerf.render.session import RenderSession
    from garmentnerf.viewer.app import App

    gate = threading.Event()
    slow_render = RenderSession.render
    monkeypatch.setattr(RenderSession, "render", lambda self, *a, **k: (gate.wait(300), slow_render(self, *a, **k))[1])
    try:
        with App(motion=None, run=untrained_run, size=WINDOW, samples=0, vsync=False, playing=False,
                 snapshot_dir=tmp_path, dynamic_scene=False) as viewer:
            viewer.show_ui = False
            shot = viewer.read_framebuffer()
            body = viewer.scene.body
            assert body.standin and not body.learned and not body.has_appearance and body.drawn
            camera = viewer.view_camera(*viewer.window.framebuffer_size)
            uv, _ = _projected(camera, viewer.sequence.positions(viewer.timeline.frame))
            x0, y0 = np.floor(uv.min(axis=0)).astype(int)
            x1, y1 = np.ceil(uv.max(axis=0)).astype(int)
            patch = shot[y0:y1 + 1, x0:x1 + 1].astype(int)
            skin = (patch[..., 0] > patch[..., 2] + 25) & (patch[..., 0] > 90)  # the studio skin tone: red over blue
            assert skin.sum() > 150
            gate.set()
            assert viewer.wait_for_neural(300), viewer.neural_view.error()
            viewer.step()
            assert not body.standin and not body.drawn
    finally:
        gate.set()


# ==== the default camera ======================================================================================
def _walking_away(body, frames: int = 60, metres: float = 6.0, heading: float = 0.0):
    """A clip of the posed rest body gliding ``metres`` along the ground direction ``heading`` (degrees
    from +Y, the direction away from the home camera) over ``frames`` frames at 30 fps."""
    from garmentnerf.viewer.sequence import BodySequence

    rest = body.template_vertices.detach().double().numpy()
    direction = np.array([np.sin(np.radians(heading)), np.cos(np.radians(heading)), 0.0])
    steps = np.linspace(0.0, metres, frames)[:, None, None] * direction
    return BodySequence.from_vertices("away", 30.0, rest[None] + steps, body.faces)


def _inside(camera, points, margin: float = 0.0) -> bool:
    uv, z = _projected(camera, points)
    return bool((z > 0).all() and (uv[:, 0] >= margin).all() and (uv[:, 0] <= camera.width - margin).all()
                and (uv[:, 1] >= margin).all() and (uv[:, 1] <= camera.height - margin).all())


@pytest.mark.parametrize("heading", [0.0, 90.0, 180.0, -135.0])
def test_the_default_camera_keeps_a_body_that_walks_away_in_frame(body, heading):
    """Analytic, with the camera matrices: the previewer's default camera (home view, following the
    body's smoothed ground track) sees every vertex of every frame of a clip that travels 6 m, in
    any direction, inside the window; the old default (home view aimed at the clip's middle, not
    following) loses it."""
    clip = _walking_away(body, heading=heading)
    cam = OrbitController()
    cam.aim_home(clip.centers)
    cam.reset()
    cam.set_follow(True, clip.track[0])
    cam.reset()
    fixed = OrbitController()
    fixed.aim_home(clip.centers)
    fixed.reset()
    lost = 0
    for frame in range(clip.num_frames):
        cam.update_anchor(clip.track[frame])
        assert _inside(cam.camera(1280, 800), clip.positions(frame), margin=20), frame
        lost += not _inside(fixed.camera(1280, 800), clip.positions(frame))
    assert lost > 0


def test_the_follow_track_is_smooth_and_does_not_lag():
    """The anchor averages the centre over 0.5 s either side: a constant velocity is followed exactly
    (ends included), a sway in place is damped."""
    t = np.arange(90, dtype=np.float64)
    walking = np.stack([0.05 * t, -0.02 * t, np.full_like(t, 0.9)], axis=1)
    np.testing.assert_allclose(follow_track(walking, 30.0)[:, :2], walking[:, :2], atol=1e-12)
    assert (follow_track(walking, 30.0)[:, 2] == 0).all()  # on the ground
    sway = np.stack([0.3 * np.sin(2 * np.pi * t / 30.0), np.zeros_like(t), np.ones_like(t)], axis=1)
    assert np.abs(follow_track(sway, 30.0)[20:70, 0]).max() < 0.02  # a 1 s sway of +-0.3 m, averaged out


def test_the_window_follows_by_default_and_follow_and_orbit_mean_what_they_say(xvfb, body, tmp_path):
    """The window's default camera keeps the walking clip inside the window, frame after frame (the
    window's own camera, after each UI frame); orbiting while following still follows; switching
    "Follow the body (T)" off leaves the camera where it is while the body walks on."""
    from garmentnerf.viewer.app import App

    clip = _walking_away(body, heading=30.0)
    with App(sequence=clip, motion="away", body=body, size=WINDOW, samples=0, vsync=False, playing=False,
             snapshot_dir=tmp_path) as viewer:
        assert viewer.controller.follow
        size = viewer.window.framebuffer_size
        for frame in range(0, clip.num_frames, 5):
            viewer.set_frame(frame)
            viewer.step()
            assert _inside(viewer.view_camera(*size), clip.positions(frame)), frame
        # the user's orbit: the view turns, and keeps following
        azimuth = viewer.controller.azimuth
        viewer.controller.orbit(150.0, -40.0)
        assert viewer.controller.azimuth != azimuth
        for frame in (0, clip.num_frames // 2, clip.num_frames - 1):
            viewer.set_frame(frame)
            viewer.step()
            assert _inside(viewer.view_camera(*size), clip.positions(frame)), frame
        # T: follow off; the camera stays put in the world while the body walks on
        viewer.handle_key("t")
        assert not viewer.controller.follow
        here = viewer.view_camera(*size)
        viewer.set_frame(0)
        viewer.step()
        there = viewer.view_camera(*size)
        assert np.array_equal(here.R, there.R) and np.array_equal(here.t, there.t)
        viewer.handle_key("t")
        assert viewer.controller.follow
        # the neural worker is handed the same camera for each frame (FollowView: render-ahead keeps working)
        view = viewer.controller.follow_view(clip.track, clip.track_key)
        for frame in (3, 40):
            viewer.set_frame(frame)
            viewer.step()
            mine, its = viewer.view_camera(*size), view.camera_at(frame, *size)
            assert np.array_equal(mine.R, its.R) and np.array_equal(mine.t, its.t) and np.array_equal(mine.K, its.K)
