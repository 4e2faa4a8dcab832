"""The previewer's camera path: the editor's keyframes (pure), the turntable taking a keyframe's view,
the drawn frusta (projected with the conventions' own projection), and in the window: the path drawn
and looked through, and a path export equal to ``garmentnerf render --camera-path`` of the saved file.

Window tests use the Xvfb server and the tiny untrained run of this folder's ``conftest.py``.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from support.viewer_app import small_neural_app

from garmentnerf.conventions import orbit_camera, project_points
from garmentnerf.render.camera_path import CameraPath, Keyframe
from garmentnerf.viewer.camera import OrbitController
from garmentnerf.viewer.export_jobs import ExportSettings, plan_path
from garmentnerf.viewer.path_editor import PATH_COLOR, PathEditor, frustum_lines, path_lines

SIZE = (48, 32)


def _view(azimuth, elevation=10.0, distance=3.0, fov=40.0, size=(320, 200)):
    return orbit_camera(azimuth, elevation, distance, (0.0, 0.0, 0.9), size[0], size[1], fov)


# ==== pure logic =========================================================================================
def test_the_editor_keeps_one_keyframe_per_frame_in_order(tmp_path):
    editor = PathEditor()
    assert editor.path(SIZE, 30.0) is None
    assert editor.add(_view(0), 10) == 0
    assert editor.add(_view(90), 2) == 0  # sorted by frame: the new one comes first
    assert [k.frame for k in editor.keyframes] == [2.0, 10.0]
    editor.add(_view(45), 10)  # the same frame: replaced
    assert len(editor.keyframes) == 2
    np.testing.assert_allclose(editor.keyframes[1].camera(320, 200).R, _view(45).R, atol=1e-12)
    path = editor.path(SIZE, 30.0)
    assert editor.path(SIZE, 30.0) is path  # made once per change
    with pytest.raises(ValueError, match="already at frame 10"):
        editor.move(0, 10)
    editor.move(0, 20)
    assert [k.frame for k in editor.keyframes] == [10.0, 20.0] and editor.path(SIZE, 30.0) is not path
    file = editor.save(SIZE, 24.0, file=tmp_path / "p.json")
    with pytest.raises(FileExistsError):
        editor.save(SIZE, 24.0, file=file)
    other = PathEditor()
    other.add(_view(10), 0)
    with pytest.raises(ValueError, match="outside walk"):
        other.load(file, num_frames=15, motion="walk")  # keyframe at 20 in a 15-frame clip
    assert [k.frame for k in other.keyframes] == [0.0]  # unchanged by a refused load
    loaded = other.load(file, num_frames=30)
    assert (loaded.width, loaded.height, loaded.fps) == (*SIZE, 24.0)
    assert [k.frame for k in other.keyframes] == [10.0, 20.0]
    editor.look_through = True
    editor.clear()
    assert editor.keyframes == [] and not editor.look_through


@pytest.mark.parametrize("follow", [False, True])
def test_the_turntable_takes_a_keyframes_view(follow):
    key = Keyframe.from_camera(_view(-130.0, 25.0, 2.2, 33.0), 5)
    cam = OrbitController()
    cam.distance = 2.2
    if follow:
        cam.set_follow(True, (0.4, -0.3, 0.9))
    cam.look_from(key.position, key.camera_to_world[:3, 2], key.fov_y)
    got, want = cam.camera(320, 200), key.camera(320, 200)
    np.testing.assert_allclose(got.R, want.R, atol=1e-9)
    np.testing.assert_allclose(got.center, want.center, atol=1e-9)
    np.testing.assert_allclose(got.K, want.K, atol=1e-9)


def test_a_drawn_frustum_ends_at_the_image_corners():
    camera = _view(60.0, 15.0, fov=35.0, size=(320, 200))
    key = Keyframe.from_camera(camera, 0)
    points = frustum_lines(key.camera_to_world, key.fov_y, 320 / 200)
    np.testing.assert_allclose(points[0], camera.center, atol=1e-12)  # the apex
    uv, depth = project_points(camera, torch.tensor(points[[1, 3, 5, 7]]))
    np.testing.assert_allclose(uv.numpy(), [[-0.5, -0.5], [319.5, -0.5], [319.5, 199.5], [-0.5, 199.5]], atol=1e-9)
    tick_uv, _ = project_points(camera, torch.tensor(points[[-2]]))  # the tick's peak
    assert tick_uv[0, 1] < -0.5  # the tick sits above the image: up is up


def test_path_lines_and_plan_follow_the_path():
    path = CameraPath((Keyframe.from_camera(_view(0), 1), Keyframe.from_camera(_view(120), 4)), *SIZE)
    positions, colors = path_lines(path, SIZE[0] / SIZE[1], current_frame=2)
    assert positions.shape == colors.shape and len(positions) % 2 == 0
    on_path = np.all(colors == PATH_COLOR, axis=1)
    np.testing.assert_allclose(positions[on_path][0], path.keyframes[0].position, atol=1e-12)
    np.testing.assert_allclose(positions[on_path][-1], path.keyframes[1].position, atol=1e-12)
    plan = plan_path(path, SIZE, num_frames=6)
    assert [f for f, _ in plan] == [1, 2, 3, 4]
    for (f, cam), ref in zip(plan, path.cameras([1, 2, 3, 4])):
        np.testing.assert_array_equal(cam.R, ref.R)
        assert (cam.width, cam.height) == SIZE
    with pytest.raises(ValueError, match="outside"):
        plan_path(path, SIZE, num_frames=4)


# ==== the window with a tiny untrained run ================================================================
@pytest.fixture(scope="module")
def run(untrained_run, tmp_path_factory):  # noqa: F811
    """A copy of the tiny untrained run with its decoder's weights scaled by 5 and saved, so that its
    image has structure (as in test_viewer_export.py) and the headless command renders the same model."""
    import shutil

    from garmentnerf.runs import load_run, save_weights

    folder = tmp_path_factory.mktemp("scaled_run") / "run"
    shutil.copytree(untrained_run, folder)
    loaded = load_run(folder)
    with torch.no_grad():
        for p in loaded.model.decoder.parameters():
            p.mul_(5.0)
    save_weights(folder / "model.safetensors", loaded.model)
    return load_run(folder)


@pytest.fixture(scope="module")
def app(xvfb, run, tmp_path_factory):  # noqa: F811
    with small_neural_app(run, tmp_path_factory.mktemp("path_exports"), SIZE) as viewer:
        yield viewer


def _path_pixels(image: np.ndarray) -> int:
    target = np.round(np.array(PATH_COLOR) * 255)
    return int((np.abs(image.astype(int) - target).max(axis=-1) <= 2).sum())


def test_keyframes_from_the_window_are_drawn_and_looked_through(app):
    app.neural_view.set_mode("body")
    app.controller.reset()
    app.controller.distance = 6.0
    app.set_frame(0)
    app.controller.azimuth = 0.0
    app.do("add_keyframe")
    app.set_frame(2)
    app.controller.azimuth = 90.0
    app.handle_key("k")
    assert [k.frame for k in app.path_editor.keyframes] == [0.0, 2.0]
    app.controller.azimuth, app.controller.distance = 45.0, 12.0  # step back to see the path
    app.set_frame(1)
    app.show_ui = False  # the panels would cover most of this small window
    app.scene_scale.dynamic = False  # drawn at full size: the lines keep their exact colour
    seen = app.read_framebuffer()
    assert _path_pixels(seen) > 20  # the path's polyline is drawn
    app.handle_key("p")  # view through the path
    assert app.path_editor.look_through
    w, h = app.window.framebuffer_size
    through = app.view_camera(w, h)
    expected = app.camera_path().camera_at(1, w, h)
    np.testing.assert_array_equal(through.R, expected.R)
    assert _path_pixels(app.read_framebuffer()) == 0  # not drawn while looking through it
    app.set_frame(2)
    np.testing.assert_allclose(app.view_camera(w, h).center, app.path_editor.keyframes[1].position, atol=1e-9)
    app.handle_key("p")
    app.go_to_keyframe(0)
    assert app.timeline.frame == 0
    np.testing.assert_allclose(app.controller.camera(w, h).R, app.path_editor.keyframes[0].camera(w, h).R,
                               atol=1e-9)
    app.clear_keyframes()
    app.handle_key("p")  # nothing to look through: refused, said on the status line
    assert not app.path_editor.look_through and "add a keyframe" in app.status.message()
    app.show_ui, app.scene_scale.dynamic = True, True


def test_a_path_export_equals_the_headless_render_of_the_saved_path(app, tmp_path):
    import imageio.v2 as iio

    from garmentnerf.cli.main import main

    app.neural_view.set_mode("neural")
    app.clear_keyframes()
    for frame, azimuth in ((0, -30.0), (2, 60.0)):
        app.set_frame(frame)
        app.controller.azimuth = azimuth
        app.add_keyframe()
    settings = ExportSettings(mode="path", size=SIZE, quality=1.0)
    app.exports.settings.size = SIZE
    job = app.exports.start_video(settings, directory=tmp_path / "window")
    exported = app.wait_export(job, timeout=300)
    app.path_editor.file = str(tmp_path / "dolly.json")
    saved = app.save_camera_path()
    assert saved is not None and saved.is_file()
    assert app.save_camera_path() is None and "exists" in app.path_error  # never overwritten
    out = tmp_path / "headless"
    assert main(["render", "--run", str(app.neural_view.run.root), "--camera-path", str(saved), "--quality", "1",
                 "--video", "--out", str(out), "--no-progress"]) == 0
    [headless] = list(out.glob("*.mp4"))
    with iio.get_reader(str(exported), format="FFMPEG") as a, iio.get_reader(str(headless), format="FFMPEG") as b:
        window_frames = [np.asarray(f)[..., :3].astype(int) for f in a]
        headless_frames = [np.asarray(f)[..., :3].astype(int) for f in b]
    assert len(window_frames) == len(headless_frames) == 3
    for x, y in zip(window_frames, headless_frames):
        assert x.std() > 3.0  # an image with structure: the comparison means something
        diff = np.abs(x - y)
        assert diff.mean() <= 1.0 and diff.max() <= 8, (diff.mean(), diff.max())
    # and the frames differ from one another: the camera moved along the path
    assert np.abs(window_frames[0] - window_frames[2]).mean() > 2.0


def test_playing_along_a_path_renders_each_frame_from_its_own_camera_and_ahead(gl_context, untrained_run,
                                                                                monkeypatch):
    """Looking through a path, the worker renders each frame with the path's camera at that frame,
    and renders the clip ahead along it as for a still camera: played back, no new render."""
    import time

    from garmentnerf.render.session import RenderSession
    from garmentnerf.runs import load_run
    from garmentnerf.viewer.neural_view import NeuralView
    from garmentnerf.viewer.scene_gl import SceneRenderer
    from garmentnerf.viewer.timeline import Timeline

    real = RenderSession.render
    calls = []

    def render(self, frame, camera, *args, **kwargs):
        calls.append((int(frame), camera))
        return real(self, frame, camera, *args, **kwargs)

    monkeypatch.setattr(RenderSession, "render", render)
    path = CameraPath((Keyframe.from_camera(_view(-40.0), 0), Keyframe.from_camera(_view(70.0), 2)), 64, 48)
    scene = SceneRenderer(gl_context, samples=0)
    view = NeuralView(scene, load_run(untrained_run), None, lambda text: None, time.perf_counter)
    view.quality.dynamic = False
    view.quality.set_preset("interactive")
    try:
        timeline = Timeline(num_frames=3, fps=30.0, playing=True)
        window_camera = _view(0.0, size=(64, 48))  # the orbit camera: not what is rendered
        deadline = time.monotonic() + 180
        view.update(window_camera, timeline, camera_path=path)
        while not view.settled() and time.monotonic() < deadline:
            time.sleep(0.01)
            view.update(window_camera, timeline, camera_path=path)
        assert view.settled(), view.error()
        assert sorted(f for f, _ in calls) == [0, 1, 2]
        for frame, camera in calls:
            expected = path.camera_at(frame, 64, 48)
            np.testing.assert_array_equal(camera.R, expected.R)
            np.testing.assert_array_equal(camera.t, expected.t)
        for _ in range(6):  # playing on along the path: every frame shown from the frames rendered ahead
            timeline.advance(1.0 / 30.0)
            view.update(window_camera, timeline, camera_path=path)
            assert view.shown_frame == timeline.frame
        assert len(calls) == 3
    finally:
        view.stop()
        scene.release()
