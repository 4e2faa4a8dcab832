"""The desktop previewer: pure logic (timeline, camera, shortcuts, export names, worker) without GL, and
the REAL window under Xvfb (screenshots vs a headless render, snapshots, resizes, random input).

Window tests start their own X server (``Xvfb -displayfd``, a free display number chosen by Xvfb)
and skip, naming the reason, only when Xvfb is not installed (.ci/run installs it). Comparisons
between the window and a headless EGL render rely on both being the same driver (Mesa llvmpipe in
CI); the tolerances below are stated where they are used.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import time

import numpy as np
import pytest
import torch

from garmentnerf.cli.view_cmd import NO_DISPLAY_MESSAGE, register
from garmentnerf.conventions import Camera
from garmentnerf.viewer import shortcuts as sc
from garmentnerf.viewer.camera import VIEW_DIRECTIONS, OrbitController
from garmentnerf.viewer.export_jobs import parse_size, snapshot_name, write_png
from garmentnerf.viewer.timeline import MAX_SPEED, MIN_SPEED, Timeline
from garmentnerf.viewer.worker import RenderWorker

WINDOW = (640, 480)


# ==== pure logic ========================================================================================
def test_timeline_loops_and_stops_at_end():
    tl = Timeline(num_frames=10, fps=10.0, loop=True, playing=True)
    assert tl.advance(0.55) and tl.frame == 5
    tl.advance(0.5)  # 10.5 frames: wraps
    assert tl.frame == 0 and tl.playing
    tl.loop = False
    tl.advance(2.0)
    assert tl.frame == 9 and not tl.playing and tl.at_end
    tl.play()  # from the end of a non-looping clip: restarts
    assert tl.frame == 0 and tl.playing
    assert not Timeline(num_frames=10, fps=10.0).advance(1.0)  # paused: nothing moves
    for bad in (float("nan"), -1.0, float("inf")):
        before = tl.frame
        assert not tl.advance(bad) and tl.frame == before


def test_timeline_speed_step_and_reset():
    tl = Timeline(num_frames=30, fps=30.0, playing=True)
    tl.set_speed(2.0)
    tl.advance(0.25)  # 0.25 s x 30 fps x 2 = 15 frames
    assert tl.frame == 15
    tl.set_speed(0.5)
    tl.advance(0.2)  # + 3 frames
    assert tl.frame == 18
    tl.set_speed(1e9)
    assert tl.speed == MAX_SPEED
    tl.set_speed(0.0)
    assert tl.speed == MIN_SPEED
    tl.step(1)
    assert not tl.playing and tl.frame == 19
    tl.set_frame(29)
    tl.step(1)  # looping: wraps
    assert tl.frame == 0
    tl.loop = False
    tl.step(-1)
    assert tl.frame == 0
    assert tl.set_frame(1000) and tl.frame == 29
    tl.reset(5, 60.0)
    assert (tl.frame, tl.num_frames, tl.fps) == (0, 5, 60.0)
    with pytest.raises(ValueError):
        tl.reset(0, 30.0)
    with pytest.raises(ValueError):
        tl.reset(3, 0.0)


def test_camera_orbit_keeps_distance_and_zoom_clamps():
    cam = OrbitController()
    target = cam.world_target.copy()
    rng = np.random.default_rng(0)
    for _ in range(200):
        cam.orbit(*rng.normal(0, 300, 2))
        c = cam.camera(320, 240)
        assert np.isclose(np.linalg.norm(c.center - target), cam.distance, atol=1e-9)
        assert -cam.max_elevation <= cam.elevation <= cam.max_elevation
        assert -180.0 < cam.azimuth <= 180.0
        # the world's up stays up on screen: image "down" has a negative world z component
        assert c.R[1, 2] < 0.0
    for _ in range(100):
        cam.zoom(5)
    assert cam.distance == cam.min_distance
    for _ in range(100):
        cam.zoom(-5)
    assert cam.distance == cam.max_distance
    cam.zoom(float("nan"))
    cam.orbit(float("inf"), 0)
    assert np.isfinite(cam.distance) and np.isfinite(cam.azimuth)


def test_camera_presets_reset_pan_and_follow():
    cam = OrbitController()
    for name, az in VIEW_DIRECTIONS.items():
        cam.preset(name)
        assert cam.azimuth == az
    cam.preset("front")
    c = cam.camera(100, 100)
    assert c.center[1] < cam.world_target[1] - 1.0  # front: on the -Y side, where the character faces
    cam.preset("left")
    assert cam.camera(100, 100).center[0] > cam.world_target[0] + 1.0  # the character's left is +X
    with pytest.raises(ValueError):
        cam.preset("top")
    # pan moves the target in the image plane, keeps the distance
    before = cam.world_target.copy()
    cam.pan(100, 0, 480)
    moved = cam.world_target - before
    assert np.linalg.norm(moved) > 0 and abs(moved[2]) < 1e-9  # horizontal drag, level camera
    cam.reset()
    assert np.allclose(cam.world_target, cam.home.target) and cam.azimuth == cam.home.azimuth
    # follow: switching on does not move the view; the camera then travels with the body
    cam.set_follow(True, (1.0, 2.0, 0.9))
    assert np.allclose(cam.world_target, cam.home.target)
    eye = cam.eye.copy()
    cam.update_anchor((1.5, 2.0, 0.9))
    assert np.allclose(cam.eye - eye, [0.5, 0.0, 0.0])
    cam.set_follow(False)
    assert np.allclose(cam.eye - eye, [0.5, 0.0, 0.0])
    cam.update_anchor((9.0, 9.0, 0.0))  # not following: ignored
    assert np.allclose(cam.eye - eye, [0.5, 0.0, 0.0])
    assert isinstance(cam.camera(64, 48), Camera)


def test_shortcuts_table():
    from garmentnerf.viewer.gui_libs import imgui

    keys = [k for s in sc.SHORTCUTS for k in s.keys]
    assert len(keys) == len(set(keys)), "a key is bound twice"
    assert len(sc.resolve(imgui)) == len(keys)  # every name is an imgui.Key
    rows = dict(sc.help_rows())
    assert rows["Space"] == "play / pause" and ", / Left" in rows and "H / F1" in rows
    required = {"space": "toggle_play", "comma": "step_back", "period": "step_forward", "f": "camera_front",
                "b": "camera_back", "r": "reset_camera", "s": "snapshot", "h": "toggle_help", "f1": "toggle_help",
                "escape": "quit"}
    for key, action in required.items():
        assert sc.action_for_key(key) == action
    assert sc.action_for_key("q") is None


def test_export_names_and_never_overwrite(tmp_path):
    assert parse_size("1280x800") == (1280, 800) and parse_size(" 64 X 48 ") == (64, 48)
    for bad in ("1280", "0x10", "axb", "99999x10"):
        with pytest.raises(ValueError):
            parse_size(bad)
    assert snapshot_name("walk,dance_a", 7) == "walk-dance_a_f0007.png"
    assert snapshot_name("/data/clip.npz", 0) == "clip_f0000.png"
    img = np.zeros((4, 5, 3), np.uint8)
    first = write_png(img, tmp_path / "a.png")
    data = first.read_bytes()
    second = write_png(img + 1, tmp_path / "a.png")
    assert first.name == "a.png" and second.name == "a_001.png"
    assert first.read_bytes() == data
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary files left


def test_render_worker_coalesces_requests():
    got = []
    started = []

    def render(request, generation):
        started.append(request)
        time.sleep(0.05)
        return request * 10

    worker = RenderWorker(render, lambda result, request, gen: got.append((request, result)))
    try:
        worker.request(1)
        time.sleep(0.01)  # 1 is rendering now
        for r in range(2, 8):
            worker.request(r)  # 2..6 are superseded before they start
        assert worker.wait_idle(5.0)
        assert started[0] == 1 and started[-1] == 7 and len(started) <= 3
        assert got[-1] == (7, 70)
        assert worker.stats.errors == 0
    finally:
        worker.stop()


def test_render_worker_shows_frames_while_requests_never_stop():
    """A camera moving every UI frame supersedes every render; after max_stale_s without a result
    the render in flight must still finish and be shown, or the layer would never update."""
    got = []

    def render(request, generation):
        for _ in range(10):  # 10 chunks of 10 ms, polling for cancellation like the real session
            time.sleep(0.01)
            if worker.should_cancel(generation):
                return None
        return request

    worker = RenderWorker(render, lambda result, request, gen: got.append(result), max_stale_s=0.15)
    try:
        deadline = time.monotonic() + 1.5
        r = 0
        while time.monotonic() < deadline:
            r += 1
            worker.request(r)  # a new request every 5 ms, faster than any render finishes
            time.sleep(0.005)
        assert worker.wait_idle(5.0)
        # without the guarantee only the very last request would ever be delivered
        assert len(got) >= 4, got
        assert got == sorted(got)  # results arrive in request order
    finally:
        worker.stop()


def test_view_without_display_prints_one_line(monkeypatch, capsys):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["view", "--motion", "walk"])
    assert args.func(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [NO_DISPLAY_MESSAGE]
    assert "no display available" in err[0] and "render headless instead: garmentnerf render" in err[0]


# ==== GL scene (headless) ==================================================================================
@pytest.fixture(scope="module")
def walk(body):
    from garmentnerf.viewer.sequence import BodySequence

    return BodySequence.load(body, body.betas("average"), "walk")


def _headless_scene(ctx, walk, frame, samples):
    from garmentnerf.viewer.scene_gl import SceneRenderer

    scene = SceneRenderer(ctx, samples=samples)
    scene.set_body(("ref", frame), walk.frame(frame), walk.faces, walk.centers[frame])
    return scene


def _flat_maps(H, W, mask=1.0):
    """Maps of a flat image: radiance 1, palette color 0 only, no offsets, the given mask."""
    from garmentnerf.viewer.palette_layer import pack_maps

    weights = np.zeros((2, H, W), np.float32)
    weights[0] = 1.0
    return pack_maps(np.ones((3, H, W), np.float32), np.zeros((2, 3, H, W), np.float32), weights,
                     np.full((H, W), mask, np.float32))


def test_palette_layer_composites_by_depth(gl_context, walk):
    """The network's image over the rasterised body by depth: in front it covers everything, behind it
    only the background; an empty mask leaves the scene untouched."""
    scene = _headless_scene(gl_context, walk, 0, samples=0)
    try:
        cam = OrbitController()
        cam.preset("front")
        camera = cam.camera(96, 128)
        layer = scene.palette_layer
        layer.visible = False
        base = scene.render_image(camera, samples=0)
        H, W = 128, 96
        layer.visible, layer.use_depth = True, True
        layer.set_palette([(0.0, 0.0, 1.0), (1.0, 1.0, 1.0)])  # color 0: pure blue
        near = np.full((H, W), 0.5, np.float32)  # in front of the body (the camera is ~3.6 m away)
        layer.submit(_flat_maps(H, W), near, (W, H))
        front = scene.render_image(camera, samples=0)
        assert (front == (0, 0, 255)).all()
        far = np.full((H, W), 50.0, np.float32)  # behind the body: only the background turns blue
        layer.submit(_flat_maps(H, W), far, (W, H))
        behind = scene.render_image(camera, samples=0)
        body_px = (np.abs(base.astype(int) - behind.astype(int)).sum(-1) == 0)
        assert 0.02 < body_px.mean() < 0.5  # the body (and nothing else) kept its pixels
        assert (behind[~body_px] == (0, 0, 255)).all()
        layer.submit(_flat_maps(H, W, mask=0.0), near, (W, H))  # mask 0 = empty: the layer shows nothing
        assert (scene.render_image(camera, samples=0) == base).all()
    finally:
        scene.release()


def test_palette_layer_side_by_side_fits_the_free_area(gl_context, walk):
    """Side by side: the network's image and the ground truth are fitted (aspect kept) into the two
    halves of the free area the window's panels leave, and nothing is drawn outside it."""
    from garmentnerf.viewer.scene_gl import read_image

    scene = _headless_scene(gl_context, walk, 0, samples=0)
    try:
        camera = OrbitController().camera(160, 120)
        layer = scene.palette_layer
        layer.side_by_side = True
        layer.set_palette([(0.0, 0.0, 1.0), (1.0, 1.0, 1.0)])  # the network's image: blue
        layer.submit(_flat_maps(40, 40), np.ones((40, 40), np.float32), (40, 40))
        layer.submit_ground_truth(np.full((40, 40, 3), (255, 0, 0), np.uint8))  # the ground truth: red
        target = scene.make_target(160, 120, samples=0)
        try:
            for area, (x0, x1, y0, y1) in (((-1.0, -1.0, 1.0, 1.0), (0, 160, 0, 120)),   # the whole view
                                           ((0.0, -0.5, 1.0, 1.0), (80, 160, 0, 90))):  # right of a panel, above a bar
                scene.render(target, camera, free_area=area)
                image = read_image(target.resolve_fbo, 160, 120)
                blue, red = [np.argwhere((image == c).all(-1)) for c in ((0, 0, 255), (255, 0, 0))]
                middle, size = (x0 + x1) // 2, min((x1 - x0) // 2, y1 - y0)  # each half: a square image
                for pixels, left in ((blue, x0), (red, middle)):
                    rows, cols = pixels[:, 0], pixels[:, 1]
                    assert len(pixels) == pytest.approx(size * size, rel=0.1), (area, len(pixels))
                    assert left <= cols.min() and cols.max() < left + (x1 - x0) // 2, area
                    assert y0 <= rows.min() and rows.max() < y1, area
        finally:
            target.release()
    finally:
        scene.release()


# ==== the real window under Xvfb =============================================================================
@pytest.fixture(scope="module")
def app(xvfb, body, walk, tmp_path_factory):
    from garmentnerf.viewer.app import App

    snapshots = tmp_path_factory.mktemp("snapshots")
    # the scene at full size in every frame (the tests compare a frame right after a change with a
    # headless render); the smaller scene while moving has its own test, which switches it on
    viewer = App(sequence=walk, motion="walk", body=body, size=WINDOW, samples=0, vsync=False, playing=False,
                 snapshot_dir=snapshots, snapshot_size=(320, 240), dynamic_scene=False)
    for _ in range(3):
        viewer.step()
    yield viewer
    viewer.close()


def _background_and_body(app, gl_context, walk, frame):
    """Headless renders of the app's current view: with the body and without it."""
    scene = _headless_scene(gl_context, walk, frame, samples=app.scene.samples)
    try:
        camera = app.controller.camera(*app.window.framebuffer_size)
        with_body = scene.render_image(camera)
        scene.body.visible = False
        without = scene.render_image(camera)
        return camera, with_body, without
    finally:
        scene.release()


def test_window_shows_upright_shaded_body_matching_headless_render(app, gl_context, walk):
    import torch

    from garmentnerf.conventions import project_points

    frame = 12
    app.set_frame(frame)
    app.show_ui = False
    shot = app.read_framebuffer()
    app.show_ui = True
    assert shot.shape == (WINDOW[1], WINDOW[0], 3)
    camera, reference, background = _background_and_body(app, gl_context, walk, frame)
    # the window shows exactly what the headless renderer draws for the same camera and frame
    # (same driver; tolerance: at most 2/255 per channel, mean below 0.05/255)
    diff = np.abs(shot.astype(int) - reference.astype(int))
    assert diff.max() <= 2 and diff.mean() < 0.05, (diff.max(), diff.mean())
    # the body is visible where its vertices project (vertices on the silhouette may round onto a
    # background pixel: 90% of all vertices must land on changed pixels)
    uv, z = project_points(camera, torch.as_tensor(walk.positions(frame), dtype=torch.float64))
    uv = uv.numpy()
    assert (z.numpy() > 0).all()
    cols, rows = np.rint(uv[:, 0]).astype(int), np.rint(uv[:, 1]).astype(int)
    inside = (cols >= 0) & (cols < WINDOW[0]) & (rows >= 0) & (rows < WINDOW[1])
    assert inside.mean() > 0.99
    changed = np.abs(shot.astype(int) - background.astype(int)).sum(-1) > 12
    assert changed[rows[inside], cols[inside]].mean() > 0.9
    ys, xs = np.nonzero(changed)
    assert abs(xs.min() - uv[:, 0].min()) < 4 and abs(xs.max() - uv[:, 0].max()) < 4
    assert abs(ys.min() - uv[:, 1].min()) < 4 and abs(ys.max() - uv[:, 1].max()) < 4
    # upright: the head (highest vertex) is near the top of the body's image region, the feet at its bottom
    head, foot = np.argmax(walk.positions(frame)[:, 2]), np.argmin(walk.positions(frame)[:, 2])
    assert uv[head, 1] < ys.min() + 6 and uv[foot, 1] > ys.max() - 25
    # shaded, not flat: the body's pixels span a range of brightness
    lum = shot[changed].mean(-1)
    assert lum.std() > 12 and lum.max() - lum.min() > 80


def test_panels_render_and_help_toggles(app):
    app.show_ui = False
    bare = app.read_framebuffer()
    app.show_ui = True
    with_ui = app.read_framebuffer()
    assert with_ui.shape == bare.shape
    differs = np.abs(with_ui.astype(int) - bare.astype(int)).sum(-1) > 0
    assert differs[:40, :150].mean() > 0.3  # the controls window at the top left
    assert differs[-20:, :].mean() > 0.3    # the timeline bar along the bottom
    app.handle_key("h")
    with_help = app.read_framebuffer()
    assert app.show_help
    assert np.abs(with_help.astype(int) - with_ui.astype(int)).sum() > 0
    app.handle_key("f1")
    assert not app.show_help


def test_playback_uploads_only_changed_frames(app):
    app.timeline.pause()
    app.set_frame(3)
    app.step()
    uploads = app.scene.body.uploads
    for _ in range(3):
        app.step()
    assert app.scene.body.uploads == uploads  # a still frame uploads nothing
    app.handle_key("period")
    app.step()
    assert app.timeline.frame == 4 and app.scene.body.uploads == uploads + 1
    app.handle_key("comma")
    app.handle_key("comma")
    assert app.timeline.frame == 2
    # the same through imgui's input queue (what the GLFW backend feeds): press and release '.'
    from garmentnerf.viewer.gui_libs import imgui

    imgui.get_io().add_key_event(imgui.Key.period, True)
    app.step()
    imgui.get_io().add_key_event(imgui.Key.period, False)
    app.step()
    assert app.timeline.frame == 3
    app.set_frame(2)
    app.fixed_dt = 1.0 / 30.0
    try:
        app.handle_key("space")
        assert app.timeline.playing
        for _ in range(5):
            app.step()
        assert app.timeline.frame == 7  # 5 UI frames x (1/30 s x 30 fps) = 5 motion frames
        app.handle_key("space")
        assert not app.timeline.playing
    finally:
        app.fixed_dt = None


def test_snapshot_matches_offscreen_render_and_never_overwrites(app, gl_context, walk):
    from PIL import Image

    from garmentnerf.viewer.scene_gl import SceneRenderer

    app.set_frame(20)
    app.handle_key("b")  # back view
    app.step()
    first = app.snapshot(320, 240)
    data = first.read_bytes()
    second = app.snapshot(320, 240)
    assert first != second and first.parent == second.parent
    assert first.read_bytes() == data
    saved = np.asarray(Image.open(first).convert("RGB"))
    assert saved.shape == (240, 320, 3)
    scene = SceneRenderer(gl_context, samples=0)
    try:
        scene.set_body("ref", walk.frame(20), walk.faces, walk.centers[20])
        reference = scene.render_image(app.controller.camera(320, 240), samples=app.scene.snapshot_samples)
    finally:
        scene.release()
    # same state, same renderer: at most 2/255 per channel apart, mean below 0.05/255
    diff = np.abs(saved.astype(int) - reference.astype(int))
    assert diff.max() <= 2 and diff.mean() < 0.05, (diff.max(), diff.mean())
    # the 'S' shortcut takes one at the snapshot size after the frame
    before = set(first.parent.iterdir())
    app.handle_key("s")
    app.step()
    new = set(first.parent.iterdir()) - before
    assert len(new) == 1 and Image.open(new.pop()).size == (320, 240)
    app.handle_key("r")


def test_resize_to_zero_and_back(app, monkeypatch):
    from garmentnerf.viewer.gui_libs import glfw

    glfw.set_window_size(app.window.handle, 0, 0)  # X11 makes this 1 x 1
    for _ in range(3):
        assert app.step()
    tiny = app.read_framebuffer()
    assert tiny.shape[0] <= 1 or tiny.shape[1] <= 1 or tiny.size == 0
    with monkeypatch.context() as m:  # minimised (what Windows reports): a 0 x 0 framebuffer
        m.setattr(glfw, "get_framebuffer_size", lambda window: (0, 0))
        m.setattr(glfw, "get_window_size", lambda window: (0, 0))
        for _ in range(3):
            assert app.step()
        assert app.window.minimized
        assert app.read_framebuffer().shape == (0, 0, 3)
        app.snapshot(32, 24)  # snapshots do not need the window
    glfw.set_window_size(app.window.handle, *WINDOW)
    deadline = time.monotonic() + 5
    while app.window.framebuffer_size != WINDOW and time.monotonic() < deadline:
        app.step()
        time.sleep(0.01)
    assert not app.window.minimized
    assert app.read_framebuffer().shape == (WINDOW[1], WINDOW[0], 3)


def _drive_random_input(app, seed: int, count: int, sizes) -> int:
    """Feed ``count`` seeded random UI events (keys of the shortcuts table and a few others through
    imgui's input queue, mouse moves / buttons (drags) / wheel, window resizes, direct shortcut calls),
    stepping a frame every 15 events; returns the number of frames stepped. Restores the view after."""
    from garmentnerf.viewer.gui_libs import glfw, imgui

    rng = np.random.default_rng(seed)
    io = imgui.get_io()
    # imgui normally trickles queued input (one change per key/button per frame); 15 random events per
    # frame would then back up into the next tests. Off here: every queued event lands in the next frame.
    trickle = io.config_input_trickle_event_queue
    io.config_input_trickle_event_queue = False
    keys = [(name, getattr(imgui.Key, name)) for s in sc.SHORTCUTS for name in s.keys if s.action != "quit"]
    keys += [("a", imgui.Key.a), ("q", imgui.Key.q), ("enter", imgui.Key.enter), ("left_shift", imgui.Key.left_shift)]
    down_keys: set = set()
    events = 0
    steps = 0
    try:
        while events < count:
            kind = rng.integers(0, 10)
            if kind < 3:
                name, key = keys[rng.integers(len(keys))]
                down = key not in down_keys
                io.add_key_event(key, down)
                (down_keys.add if down else down_keys.discard)(key)
            elif kind < 6:
                w, h = app.window.window_size
                io.add_mouse_pos_event(float(rng.uniform(-20, w + 20)), float(rng.uniform(-20, h + 20)))
            elif kind < 8:
                io.add_mouse_button_event(int(rng.integers(0, 3)), bool(rng.integers(0, 2)))
            elif kind < 9:
                io.add_mouse_wheel_event(0.0, float(rng.normal(0, 2)))
            elif rng.random() < 0.1:
                glfw.set_window_size(app.window.handle, *sizes[rng.integers(len(sizes))])
            else:
                app.handle_key(str(rng.choice([k for k, _ in keys])))
            events += 1
            if events % 15 == 0:
                assert app.step(), "the window closed during random input"
                steps += 1
        for key in down_keys:
            io.add_key_event(key, False)
        for button in range(3):
            io.add_mouse_button_event(button, False)
        app.step()
    finally:
        io.config_input_trickle_event_queue = trickle
        glfw.set_window_size(app.window.handle, *sizes[-1])
        app.show_help = False
        app.show_ui = True
        app.timeline.pause()
        app.controller.follow = False
        app.controller.anchor[:] = 0.0
        app.controller.reset()
        app.clear_keyframes()  # K added some, P may look through them
        for _ in range(3):
            app.step()
    cam = app.controller
    assert np.isfinite([cam.azimuth, cam.elevation, cam.distance, *cam.target]).all()
    assert 0 <= app.timeline.frame < app.timeline.num_frames
    return steps


def test_real_x_key_event_reaches_shortcuts(app):
    # before the random input below: after some random sequences (seed 1234 with the current shortcuts
    # table) the window stops receiving xdotool's key events, not root-caused (see the 2026-11-26 note)
    exe = shutil.which("xdotool")
    if exe is None:
        pytest.skip("xdotool is not installed (optional: sends real X key events)")
    from garmentnerf.viewer.gui_libs import glfw

    app.timeline.pause()
    app.step()
    xid = glfw.get_x11_window(app.window.handle)
    subprocess.run([exe, "key", "--window", str(xid), "space"], check=True, timeout=10)
    deadline = time.monotonic() + 5
    while not app.timeline.playing and time.monotonic() < deadline:
        app.step()
    assert app.timeline.playing
    app.timeline.pause()


def test_random_ui_events_raise_nothing(app):
    steps = _drive_random_input(app, 1234, 3000, [(320, 240), (200, 150), (1, 1), (480, 320), WINDOW])
    assert steps >= 200


def test_motion_switch_in_background(app):
    app.timeline.pause()
    app.load_motion("sway")
    deadline = time.monotonic() + 30
    while app.motion_name != "sway" and time.monotonic() < deadline:
        app.step()
        time.sleep(0.01)
    assert app.motion_name == "sway" and app.sequence.name == "sway"
    assert app.timeline.num_frames == app.sequence.num_frames and app.timeline.frame == 0
    app.load_motion("no_such_motion")
    deadline = time.monotonic() + 10
    while app.motions.loading and time.monotonic() < deadline:
        app.step()
        time.sleep(0.01)
    app.step()
    assert "cannot load motion" in app.status.message() and app.motion_name == "sway"


def test_run_frame_limit_and_quit(xvfb, body, walk, monkeypatch, tmp_path):
    from garmentnerf.viewer.app import ENV_FRAMES, App

    monkeypatch.setenv(ENV_FRAMES, "4")
    with App(sequence=walk, body=body, size=(160, 120), samples=0, vsync=False, snapshot_dir=tmp_path) as viewer:
        assert viewer.run() == 4
        assert viewer.timer.frames == 4
        viewer.handle_key("escape")
        assert viewer.run(max_frames=10) == 0  # quit: the loop ends at once
    assert not list(tmp_path.iterdir())
    assert not os.path.exists("imgui.ini")


# ==== dynamic resolution (pure logic) =========================================================================
def test_quality_controller_moving_still_floor_and_hysteresis():
    from garmentnerf.render.presets import RENDER_PRESETS
    from garmentnerf.viewer.quality import QualityController

    q = QualityController(preset="full", target_ms=100.0, floor=0.125, settle_seconds=0.3)
    assert q.quality(0.0) == 1.0  # nothing changed yet: still, full quality
    q.view_changed("a", 1.0)
    assert q.moving(1.1) and not q.moving(1.31)
    q.observe(1.0, 400.0)  # 400 ms at full quality: sqrt(100 / 400) = 0.5 while moving
    assert q.quality(1.1) == 0.5
    assert q.quality(1.4) == 1.0  # still again: full
    q.observe(0.5, 110.0)  # within +-20 %: the moving quality stays put (no flicker)
    q.view_changed("b", 2.0)
    assert q.quality(2.05) == 0.5
    for _ in range(30):
        q.observe(1.0, 1e6)  # hopeless machine: never below the floor
    assert q.quality(2.1) == q.floor
    before = q.unit_ms
    q.observe(1.0, 1.0)  # one absurdly fast sample moves the estimate by at most max_jump
    assert q.unit_ms >= before / q.max_jump * (1 - q.smoothing)
    q.set_preset("interactive")  # the levels are render presets: the still quality is the preset's resolution
    low = RENDER_PRESETS["interactive"].resolution_scale
    assert q.full == low and q.quality(10.0) == low
    assert q.unit_ms is None  # another preset costs another amount per ray: measured anew
    assert q.quality(2.1) <= low
    fixed = QualityController(preset="balanced", dynamic=False)
    fixed.view_changed("x", 0.0)
    assert fixed.quality(0.01) == RENDER_PRESETS["balanced"].resolution_scale
    with pytest.raises(ValueError):
        q.set_preset("reference")  # a render preset, but not a viewer level
    with pytest.raises(ValueError):
        q.set_preset("ultra")


# ==== the neural layer in the window (untrained run on the tiny scene) ========================================
def _settle(app, seconds=60.0):
    """Step until the worker is idle, the view is still and the newest result is on the GPU (the first
    step sends the request for a view just changed)."""
    app.step()
    app.run_until(app.neural_view.settled, seconds)
    app.step()


def test_neural_viewer_palette_is_a_uniform_and_modes_switch(xvfb, untrained_run, tmp_path):
    from garmentnerf.viewer.app import App
    from garmentnerf.viewer.renderables import FULL_VIEW

    with App(motion=None, run=untrained_run, size=(320, 240), samples=0, vsync=False, playing=False,
             snapshot_dir=tmp_path) as viewer:
        view = viewer.neural_view
        assert viewer.motion_name == "train" and view.ground_truth_available()
        assert viewer.wait_for_neural(180), view.error()
        _settle(viewer)
        viewer.show_ui = False
        layer = viewer.scene.palette_layer
        assert view.mode == "neural" and not viewer.scene.body.visible
        before = viewer.read_framebuffer()
        uploads, renders = layer.uploads, view.renderer.stats.renders
        view.set_palette_color(0, (1.0, 0.0, 0.0))
        recolored = viewer.read_framebuffer()
        assert layer.uploads == uploads and view.renderer.stats.renders == renders  # no re-render, no upload
        diff = np.abs(recolored.astype(int) - before.astype(int))
        assert diff.max() > 10 and diff[..., 0].sum() > diff[..., 2].sum()  # more red
        view.reset_palette()
        assert np.abs(viewer.read_framebuffer().astype(int) - before.astype(int)).max() <= 1
        for mode in ("side_by_side", "difference", "maps", "ground_truth"):
            view.set_mode(mode)
            _settle(viewer)
            assert layer.has_ground_truth
            assert viewer.read_framebuffer().shape == before.shape
        # side by side beside the control panel: the free area starts at the panel's right edge
        view.set_mode("side_by_side")
        assert viewer.free_area == FULL_VIEW  # panels hidden: the whole window
        viewer.show_ui = True
        viewer.step()
        x0, y0, x1, y1 = viewer.free_area
        assert -1.0 < x0 < x1 == 1.0 and -1.0 < y0 < y1 == 1.0  # right of the panel, above the timeline bar
        view.set_mode("body")
        assert viewer.scene.body.visible and not layer.visible
        stats = viewer.stats()["neural"]
        assert stats["renders"] >= 2 and stats["errors"] == 0 and stats["timings"]["render_total"] > 0


def test_ui_frames_do_not_wait_for_a_slow_neural_render(xvfb, untrained_run, tmp_path, monkeypatch):
    """Every neural render takes at least 0.6 s (slowed on purpose) while the camera orbits every
    UI frame: the UI thread never waits for it, so its frame time stays far below a render's
    (measured here; bound loose for a loaded CI machine)."""
    from garmentnerf.render.session import RenderSession
    from garmentnerf.viewer.app import App

    slow_render = RenderSession.render

    def render(self, *args, **kwargs):
        time.sleep(0.6)  # the worker thread sleeps: a UI frame that waited for it would take as long
        return slow_render(self, *args, **kwargs)

    monkeypatch.setattr(RenderSession, "render", render)
    with App(motion=None, run=untrained_run, size=(320, 240), samples=0, vsync=False, playing=False,
             snapshot_dir=tmp_path) as viewer:
        assert viewer.wait_for_neural(180), viewer.neural_view.error()
        renders = viewer.neural_view.renderer.stats.renders
        intervals = []
        start = last = time.perf_counter()
        while time.perf_counter() - start < 2.5:
            viewer.controller.orbit(2.0, 0.0)  # a new view every frame: the worker is never idle
            viewer.step()
            now = time.perf_counter()
            intervals.append(now - last)
            last = now
        busy = viewer.neural_view.renderer.stats.renders - renders
    assert busy <= 5  # the renders really were slow (at most 2.5 s / 0.6 s of them finished) ...
    assert len(intervals) >= 10 and float(np.median(intervals)) < 0.25, np.median(intervals)  # ... the UI was not


def test_view_command_with_run_renders_a_neural_frame(xvfb, untrained_run, tmp_path):
    import json
    import sys

    stats = tmp_path / "stats.json"
    env = dict(os.environ, GARMENTNERF_VIEWER_FRAMES="5", GARMENTNERF_VIEWER_STATS=str(stats))
    proc = subprocess.run([sys.executable, "-m", "garmentnerf.cli.main", "view", "--run", str(untrained_run),
                           "--size", "240x180", "--no-vsync", "--paused", "--snapshot-dir", str(tmp_path / "s")],
                          env=env, capture_output=True, text=True, timeout=400)
    assert proc.returncode == 0, proc.stderr[-2000:]
    data = json.loads(stats.read_text())
    assert data["view_mode"] == "neural" and data["motion"] == "train"
    assert data["neural"]["renders"] >= 1 and data["neural"]["layer_has_image"], data
    assert data["neural"]["errors"] == 0
    assert "neural frame(s)" in proc.stdout


def test_view_bench_writes_finite_figures(xvfb, untrained_run, tmp_path):
    """``garmentnerf view --bench`` with a tiny run for ~2 s: every figure is present and finite, a
    palette change shows within the frame budget without a new neural render, the body is shown no
    later than the garment (``first_frame``)."""
    import json
    import math
    import sys

    from garmentnerf.render.presets import RENDER_PRESETS, VIEWER_LEVELS

    out = tmp_path / "view_bench.json"
    env = dict(os.environ)
    env.pop("GARMENTNERF_VIEWER_FRAMES", None)
    proc = subprocess.run([sys.executable, "-m", "garmentnerf.cli.main", "view", "--bench", "--run", str(untrained_run),
                           "--size", "240x180", "--bench-seconds", "2", "--bench-repeats", "1", "--json", str(out),
                           "--snapshot-dir", str(tmp_path / "s")],
                          env=env, capture_output=True, text=True, timeout=500)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "UI while worker busy" in proc.stdout and "recolor latency" in proc.stdout
    data = json.loads(out.read_text())

    def finite(x):
        return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)

    ui = data["ui_busy"]
    for key in ("fps", "frame_ms_median", "frame_ms_p95", "frame_ms_max", "worker_busy_fraction", "seconds"):
        assert finite(ui[key]), (key, ui)
    assert ui["fps"] > 0 and ui["frames"] >= 2 and 1.5 < ui["seconds"] < 60
    rc = data["recolor"]
    assert rc["available"] and finite(rc["latency_frames"]) and 1 <= rc["latency_frames"] <= 10, rc
    assert rc["worker_renders"] == 0 and rc["layer_uploads"] == 0, rc  # a uniform, not a re-render
    assert list(data["presets"]) == list(VIEWER_LEVELS)
    for name, p in data["presets"].items():
        assert finite(p["render_ms_median"]) and p["render_ms_median"] > 0, (name, p)
        # each level rendered its render preset: the bench row of that name
        assert p["preset"] == [name] and p["quality"] == RENDER_PRESETS[name].resolution_scale, (name, p)
        assert len(p["render_size"]) == 2
    sizes = [data["presets"][n]["render_size"][0] for n in VIEWER_LEVELS]
    assert sizes[0] < sizes[1] < sizes[2]  # higher presets render more pixels
    assert data["worker"]["errors"] == 0
    # the first frame through the real window: the body, then the garment, seconds from the command's start
    first = data["first_frame"]
    assert finite(first["body_s"]) and finite(first["garment_s"]), first
    assert 0 < first["body_s"] <= first["garment_s"] < 500, first
    assert "first frame: body" in proc.stdout
    # other processes' load meanwhile (the X server's included), printed and kept beside the figures
    others = data["other_processes_cores"]
    assert others is None or 0.0 <= others <= os.cpu_count(), others
    assert "other processes" in proc.stdout


def test_neural_viewer_survives_random_input_and_zero_size(xvfb, untrained_run, tmp_path, monkeypatch):
    """The neural window under seeded random input (view modes cycle with V, the worker renders and is
    superseded meanwhile), then minimised to 0 x 0 and back: nothing raises, the worker reports no
    error, and the neural layer shows a frame again afterwards."""
    from garmentnerf.viewer.app import App
    from garmentnerf.viewer.gui_libs import glfw

    size = (320, 240)
    with App(motion=None, run=untrained_run, size=size, samples=0, vsync=False, playing=False,
             snapshot_dir=tmp_path) as viewer:
        assert viewer.wait_for_neural(180), viewer.neural_view.error()
        steps = _drive_random_input(viewer, 4321, 1500, [(160, 120), (1, 1), (400, 300), size])
        assert steps >= 100
        with monkeypatch.context() as m:  # minimised: a 0 x 0 framebuffer
            m.setattr(glfw, "get_framebuffer_size", lambda window: (0, 0))
            m.setattr(glfw, "get_window_size", lambda window: (0, 0))
            for _ in range(3):
                assert viewer.step()
            assert viewer.window.minimized and viewer.read_framebuffer().shape == (0, 0, 3)
        deadline = time.monotonic() + 5
        while viewer.window.framebuffer_size != size and time.monotonic() < deadline:
            viewer.step()
            time.sleep(0.01)
        viewer.neural_view.set_mode("neural")
        _settle(viewer)
        assert viewer.neural_view.renderer.stats.errors == 0, viewer.neural_view.error()
        assert viewer.scene.palette_layer.has_image
        assert viewer.read_framebuffer().shape == (size[1], size[0], 3)
    from PIL import Image

    for path in tmp_path.iterdir():  # snapshots the random S presses took: whole PNGs, no temporary files left
        assert path.suffix == ".png" and Image.open(path).format == "PNG", path


def test_the_scene_is_redrawn_only_when_something_it_shows_changes(app):
    """A still view reuses the last image (panels keep the display rate while the worker computes);
    the camera, the body frame and a display setting each trigger a redraw (two when an upload
    was pending: the draw that consumes it, then one of the consumed state), then none."""
    import numpy as np

    stats = app.scene.stats

    def scene_image():  # the 3D scene the window shows (the panels on top change every frame)
        return app.scene.read(app.scene.window_target(*app.scene.render_size(app.window.framebuffer_size)))

    def redraws_after(change) -> int:
        change()
        before = stats.draws
        for _ in range(3):
            app.step()
        settled = stats.draws
        for _ in range(4):
            app.step()
        assert stats.draws == settled, "the scene kept redrawing a still view"
        return settled - before

    for _ in range(3):
        app.step()
    draws, skipped = stats.draws, stats.skipped
    still = scene_image()
    for _ in range(5):
        app.step()
    assert stats.draws == draws and stats.skipped >= skipped + 5
    np.testing.assert_array_equal(scene_image(), still)
    assert redraws_after(lambda: app.controller.orbit(5.0, 0.0)) == 1
    assert 1 <= redraws_after(lambda: app.set_frame((app.timeline.frame + 7) % app.timeline.num_frames)) <= 2
    before = scene_image()
    floor = app.scene.floor
    assert redraws_after(lambda: setattr(floor, "show_lines", not floor.show_lines)) == 1
    changed = scene_image()
    assert redraws_after(lambda: setattr(floor, "show_lines", not floor.show_lines)) == 1
    assert np.abs(changed.astype(int) - before.astype(int)).max() > 0
    np.testing.assert_array_equal(scene_image(), before)


def test_the_scene_is_drawn_smaller_while_the_view_moves_and_sharp_once_still(app):
    """While the camera moves the scene is drawn at the scale whose measured cost fits the budget
    and stretched to the window (what OpenCV's bilinear upsampling of a headless half-size render
    shows); once still it is drawn again at full size, the image a fixed-scale window shows."""
    import cv2

    clock = [1000.0]
    app.clock = lambda: clock[0]
    app.show_ui = False
    scale = app.scene_scale
    scale.dynamic = True
    scale.forget()
    try:
        for _ in range(2):
            clock[0] += 1.0
            app.step()
        assert app.scene_draw_scale == 1.0  # still: full size
        scale.unit_ms = 4.0 * scale.target_ms  # a scene that costs 4x the budget at full size
        app.controller.orbit(5.0, 0.0)
        clock[0] += 0.01
        moving = app.read_framebuffer()
        assert app.scene_draw_scale == 0.5  # sqrt(1 / 4)
        W, H = app.window.framebuffer_size
        camera = app.controller.camera(W, H)
        half = app.scene.render_image(camera.resized(W // 2, H // 2))
        stretched = cv2.resize(half, (W, H), interpolation=cv2.INTER_LINEAR).astype(int)
        full = app.scene.render_image(camera).astype(int)
        assert np.abs(moving.astype(int) - stretched).mean() < 0.5 * np.abs(moving.astype(int) - full).mean()
        clock[0] += 0.01 + scale.settle_seconds
        sharp = app.read_framebuffer()
        assert app.scene_draw_scale == 1.0
        np.testing.assert_array_equal(sharp, full.astype(np.uint8))
        scale.dynamic = False  # a window that never scales shows the same
        clock[0] += 1.0
        np.testing.assert_array_equal(app.read_framebuffer(), sharp)
    finally:
        app.clock = time.perf_counter
        app.show_ui = True
        scale.dynamic = False


def test_scene_scale_fits_the_budget_while_moving():
    from garmentnerf.viewer.quality import SceneScale

    s = SceneScale(target_ms=10.0, floor=0.35, settle_seconds=0.2)
    assert s.scale(0.0) == 1.0  # nothing shown yet: still
    s.view_changed("a", 1.0)
    assert s.scale(1.1) == 0.5  # moving, nothing measured: half
    s.observe(0.5, 22.5)  # 22.5 ms at half size: 90 ms at full, sqrt(10 / 90) = 1/3 -> the floor 0.35,
    s.view_changed("b", 1.15)  # quantised to 6/16
    assert s.moving(1.3) and s.scale(1.3) == 6 / 16
    assert not s.moving(1.36) and s.scale(1.36) == 1.0  # still for settle_seconds: full size
    s.forget()
    s.observe(1.0, 12.0)  # 12 ms at full size: 0.91 -> quantised to 15/16
    s.view_changed("c", 2.0)
    assert s.scale(2.05) == 15 / 16
    s.dynamic = False
    assert s.scale(2.05) == 1.0


def test_playback_meter_counts_shown_and_neural_frames_per_second():
    from garmentnerf.viewer.timeline import PlaybackMeter

    meter = PlaybackMeter(window=1.0)
    for i in range(60):  # a UI at 60 fps playing a 30 fps motion: each frame shown twice
        now = i / 60.0
        meter.frame_shown(i // 2, now)
        if i % 6 == 0:  # the worker delivers a neural frame every 100 ms
            meter.neural_received(i // 2, now)
    motion, neural = meter.rates(59 / 60.0)
    assert motion == pytest.approx(30.0, abs=1.0) and neural == pytest.approx(10.0, abs=1.0)
    meter.neural_received(29, 1.0)  # the same frame again counts once
    assert meter.rates(1.0)[1] == pytest.approx(neural, abs=1.0)
    assert meter.rates(5.0) == (0.0, 0.0)  # older than the window
    meter.frame_shown(3, 5.0)
    meter.reset()
    assert meter.rates(5.0) == (0.0, 0.0)


def test_neural_viewer_draws_the_rasterised_body_and_switches_composition(xvfb, untrained_run, tiny_scene, tmp_path):
    """A run with a body appearance: the viewer's maps carry the body layer, the window shows the body
    where the untrained network alone shows almost nothing, and switching the composition off
    re-renders without it."""
    import shutil

    from garmentnerf.model.body_appearance import BodyAppearance, save_body_appearance
    from garmentnerf.runs import load_run
    from garmentnerf.viewer.app import App

    run_dir = tmp_path / "run"
    shutil.copytree(untrained_run, run_dir)
    green = BodyAppearance(texture_size=8)
    with torch.no_grad():
        green.albedo[0] = 0.0  # a green body: albedo (0, 3, 0) x the body's palette color
        green.albedo[1] = 3.0
        green.albedo[2] = 0.0
    save_body_appearance(run_dir / "body_appearance.safetensors", green)
    run = load_run(run_dir, scene=tiny_scene.root)
    with App(motion=None, run=run, size=(320, 240), samples=0, vsync=False, playing=False,
             snapshot_dir=tmp_path) as viewer:
        view, layer = viewer.neural_view, viewer.scene.palette_layer
        assert view.can_rasterise_body and view.composition == "raster_body"
        assert viewer.wait_for_neural(180), view.error()
        _settle(viewer)
        viewer.show_ui = False
        assert layer.has_body and layer.palette_size == 2
        with_body = viewer.read_framebuffer().astype(int)
        uploads = layer.uploads
        view.set_composition("nerf")
        _settle(viewer)
        assert layer.uploads > uploads and not layer.has_body
        without = viewer.read_framebuffer().astype(int)
        def green_pixels(image):
            return int(((image[..., 1] > image[..., 0] + 40) & (image[..., 1] > image[..., 2] + 40)).sum())

        assert green_pixels(with_body) > 300 and green_pixels(without) == 0
        # a snapshot is composed as the window shows it
        from PIL import Image

        shots = []
        for composition in ("nerf", "raster_body"):
            view.set_composition(composition)
            job = viewer.exports.start_snapshot(96, 72)
            assert job.composition == composition
            shots.append(np.asarray(Image.open(viewer.wait_export(job, timeout=300)).convert("RGB")).astype(int))
        assert green_pixels(shots[0]) == 0 and green_pixels(shots[1]) > 20
        with pytest.raises(ValueError, match="not available"):
            view.set_composition("bogus")
