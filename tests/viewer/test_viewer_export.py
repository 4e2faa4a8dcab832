"""Viewer exports (:mod:`garmentnerf.viewer.exporting`): neural snapshots and mp4 videos rendered on the
exporter's thread through the headless command's path, compared with
:meth:`garmentnerf.render.session.RenderSession.render_image` on a headless EGL context; cancel,
never-overwrite, and the window drawing on meanwhile. Pure planning/progress logic first.

Window tests use the Xvfb server and the tiny untrained run that ``test_viewer.py`` uses too (fixtures of
this folder's ``conftest.py``). Sizes are tiny (48 x 32, 3 video frames) so each test takes seconds on one core.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
from support.viewer_app import small_neural_app

from garmentnerf.render.video import count_video_frames, to_uint8
from garmentnerf.viewer.camera import OrbitController
from garmentnerf.viewer.export_jobs import (
    ExportJob,
    ExportSettings,
    format_seconds,
    plan_range,
    plan_turntable,
    video_name,
)

SIZE = (48, 32)


def _files(folder):
    """Every entry of ``folder``, hidden temporary files included."""
    return sorted(p.name for p in folder.iterdir())


# ==== pure logic =========================================================================================
def test_plans_follow_the_view():
    cam = OrbitController()
    cam.azimuth, cam.elevation, cam.distance = 30.0, 10.0, 3.0
    centers = np.zeros((5, 3))
    plan = plan_turntable(cam, SIZE, 4, start_frame=3, num_frames=5, plays=True, centers=centers)
    assert [f for f, _ in plan] == [3, 4, 0, 1]  # plays on from the current frame, wrapping
    target = cam.world_target
    for i, (_, c) in enumerate(plan):
        assert (c.width, c.height) == SIZE
        assert np.isclose(np.linalg.norm(c.center - target), 3.0)  # the current distance
        offset = c.center - target
        assert np.isclose(np.degrees(np.arcsin(offset[2] / 3.0)), 10.0)  # the current elevation
        az = np.degrees(np.arctan2(offset[0], -offset[1]))
        assert np.isclose((az - 30.0 - 90.0 * i + 180.0) % 360.0 - 180.0, 0.0, atol=1e-6)  # a quarter turn each
    held = plan_turntable(cam, SIZE, 3, start_frame=2, num_frames=5, plays=False, centers=centers)
    assert [f for f, _ in held] == [2, 2, 2]
    assert cam.azimuth == 30.0  # the window's controller is untouched
    # a range: the current camera on every frame; a following controller moves with the body
    cam.set_follow(True, (0.0, 0.0, 0.9))
    centers[:, 0] = np.arange(5) * 0.1
    rng = plan_range(cam, SIZE, 1, 3, centers)
    assert [f for f, _ in rng] == [1, 2, 3]
    xs = [c.center[0] for _, c in rng]
    assert np.allclose(np.diff(xs), 0.1)
    s = ExportSettings(mode="range", range_first=2, range_last=1)
    with pytest.raises(ValueError, match="frame range"):
        s.check(5)
    with pytest.raises(ValueError, match="quality"):
        ExportSettings(quality=0.0).check(5)
    assert video_name("walk,dance", "f0001-0003") == "walk-dance_f0001-0003.mp4"


def test_job_progress_eta_and_cancel():
    now = [100.0]
    job = ExportJob("video", [(0, None)] * 4, "x.mp4", source="body", clock=lambda: now[0])
    assert job.progress().state == "queued" and not job.finished
    job._start(now[0])
    assert job.progress().fraction == 0.0 and job.progress().eta_s is None
    now[0] += 2.0
    job._frame_done(now[0])
    now[0] += 0.5
    p = job.progress()
    assert (p.done, p.total, p.fraction) == (1, 4, 0.25)
    assert p.eta_s == pytest.approx(2.0 * 3 - 0.5) and p.elapsed_s == pytest.approx(2.5)
    assert "1/4 frames" in job.status_line() and "ETA 6 s" in job.status_line()
    job.cancel()
    assert job.cancel_requested()
    job._finish("cancelled")
    assert job.finished and job.status_line() == "export: cancelled"
    single = ExportJob("snapshot", [(0, None)], "x.png", source="body", clock=lambda: now[0])
    single._start(now[0])
    assert single.progress().fraction is None  # one frame in flight: indeterminate
    assert "rendering..." in single.status_line()
    assert format_seconds(95) == "1:35" and format_seconds(None) == "--"


# ==== the window with a tiny untrained run ================================================================
@pytest.fixture(scope="module")
def run(untrained_run):  # noqa: F811
    """The tiny untrained run, loaded, with its decoder's weights scaled by 5: untrained, its image is
    one flat color (mask ~0.51 everywhere), which no comparison could tell from a wrong camera or
    quality; scaled, the image has structure (per-channel std ~12-31/255, and quality 0.25 differs
    from quality 1 by ~19/255 on average). The app and the headless session share this object."""
    import torch

    from garmentnerf.runs import load_run

    loaded = load_run(untrained_run)
    with torch.no_grad():
        for p in loaded.model.decoder.parameters():
            p.mul_(5.0)
    return loaded


@pytest.fixture(scope="module")
def headless(run, gl_context):
    """The headless command's session (its first training sequence, as the app's)."""
    from garmentnerf.render.session import RenderSession

    session = RenderSession(run, gl_context)
    yield session
    session.close()


@pytest.fixture(scope="module")
def neural_app(xvfb, run, tmp_path_factory):  # noqa: F811
    with small_neural_app(run, tmp_path_factory.mktemp("exports"), SIZE) as viewer:
        yield viewer


def test_neural_snapshot_equals_headless_render(neural_app, headless):
    from PIL import Image

    app = neural_app
    app.neural_view.set_mode("neural")
    app.neural_view.quality.set_preset("interactive")  # the preview renders that preset (half resolution); the snapshot must not
    app.set_frame(1)
    app.controller.preset("left")
    app.neural_view.set_palette_color(0, (0.9, 0.2, 0.1))
    frames = app.timer.frames
    job = app.exports.start_snapshot(*SIZE)
    assert job.source == "neural" and job.quality >= 1.0
    assert not job.finished  # off the UI thread
    path = app.wait_export(job, timeout=300)
    assert app.timer.frames > frames  # the window kept drawing while it rendered
    assert app.exports.last_snapshot == path and "saved" in app.status.message()
    saved = np.asarray(Image.open(path).convert("RGB"))
    assert saved.shape == (SIZE[1], SIZE[0], 3)
    camera = app.controller.camera(*SIZE)
    reference = to_uint8(headless.render_image(1, camera, app.neural_view.palette, quality=1.0))
    assert reference.reshape(-1, 3).std(axis=0).max() > 5.0  # not a flat image: the comparison means something
    # the same path on another GL context and thread: mean abs diff <= 1/255, max <= 3/255 (uint8)
    diff = np.abs(saved.astype(int) - reference.astype(int))
    assert diff.mean() <= 1.0 and diff.max() <= 3, (diff.mean(), diff.max())
    preview = to_uint8(headless.render_image(1, camera, app.neural_view.palette, preset="interactive"))
    # not the preview's quality: far further from the preview than from the headless full-quality render
    assert np.abs(saved.astype(int) - preview.astype(int)).mean() > max(2.0, 4 * diff.mean())
    app.neural_view.quality.set_preset("full")
    app.neural_view.reset_palette()


def test_neural_snapshot_never_overwrites(neural_app):
    app = neural_app
    app.neural_view.set_mode("neural")
    app.set_frame(2)
    folder = app.exports.directory / "never"
    folder.mkdir()
    taken = folder / "train_f0002.png"
    taken.write_bytes(b"someone else's file")
    first = app.snapshot(*SIZE, directory=folder)
    second = app.snapshot(*SIZE, directory=folder)
    assert taken.read_bytes() == b"someone else's file"
    assert (first.name, second.name) == ("train_f0002_001.png", "train_f0002_002.png")
    assert _files(folder) == ["train_f0002.png", "train_f0002_001.png", "train_f0002_002.png"]  # no temporaries


def test_range_video_export_matches_headless_render(neural_app, headless, tmp_path):
    import imageio.v2 as iio

    app = neural_app
    app.neural_view.set_mode("neural")
    app.controller.preset("front")
    settings = ExportSettings(mode="range", range_first=0, range_last=2, size=SIZE, quality=1.0)
    job = app.exports.start_video(settings, directory=tmp_path)
    path = app.wait_export(job, timeout=300)
    assert path == tmp_path / "train_f0000-0002.mp4" and app.exports.last_export == path
    assert count_video_frames(path) == 3
    with iio.get_reader(str(path), format="FFMPEG") as reader:
        first = np.asarray(reader.get_data(0))[..., :3]
    reference = to_uint8(headless.render_image(0, app.controller.camera(*SIZE), app.neural_view.palette, quality=1.0))
    assert first.shape == reference.shape
    # H.264 (yuv420p, chroma at half resolution): mean abs diff below 8/255
    diff = np.abs(first.astype(int) - reference.astype(int))
    assert diff.mean() < 8.0, diff.mean()
    # a second export of the same range never replaces the first
    again = app.wait_export(app.exports.start_video(settings, directory=tmp_path), timeout=300)
    assert again.name == "train_f0000-0002_001.mp4" and count_video_frames(path) == 3
    assert _files(tmp_path) == ["train_f0000-0002.mp4", "train_f0000-0002_001.mp4"]


def test_cancel_export_leaves_no_file_and_ui_keeps_running(neural_app, tmp_path, monkeypatch):
    from garmentnerf.viewer.gui_libs import imgui

    app = neural_app
    app.neural_view.set_mode("neural")
    # every panel section open, so the Snapshot and Export sections (progress bars) draw meanwhile
    monkeypatch.setattr(imgui, "collapsing_header", lambda *args, **kwargs: True)
    settings = ExportSettings(mode="turntable", turntable_frames=200, size=SIZE, quality=1.0)
    frames = app.timer.frames
    job = app.exports.start_video(settings, directory=tmp_path)
    with pytest.raises(RuntimeError, match="still running"):
        app.exports.start_snapshot(*SIZE)  # one export at a time
    deadline = time.monotonic() + 300
    while job.progress().done < 1 and not job.finished and time.monotonic() < deadline:
        assert app.step()
        time.sleep(0.01)
    assert not job.finished and job.progress().done >= 1
    assert app.timer.frames > frames + 1  # the UI loop ran while the export was in progress
    assert any(name.endswith(".tmp") for name in _files(tmp_path))  # a partial video is being written
    app.exports.cancel()
    deadline = time.monotonic() + 60
    while not job.finished and time.monotonic() < deadline:
        assert app.step()
        time.sleep(0.01)
    assert job.state == "cancelled" and job.written is None
    app.step()
    assert "cancelled" in app.status.message()
    assert _files(tmp_path) == []  # the partial file is gone
    assert app.stats()["export"]["state"] == "cancelled"


# ==== body only (no run): a GL video on the export thread ================================================
def test_body_only_video_and_errors_in_the_window(xvfb, tmp_path):  # noqa: F811
    from garmentnerf.body.model import BodyModel
    from garmentnerf.viewer.app import App
    from garmentnerf.viewer.sequence import BodySequence

    body = BodyModel.default()
    walk = BodySequence.load(body, body.betas("average"), "walk")
    with App(sequence=walk, body=body, size=(160, 120), samples=0, vsync=False, playing=False,
             snapshot_dir=tmp_path) as app:
        app.step()
        assert app.exports.source() == "body"
        job = app.exports.start_video(ExportSettings(mode="range", range_first=5, range_last=7, size=SIZE))
        path = app.wait_export(job, timeout=120)
        assert count_video_frames(path) == 3 and path.name == "walk_f0005-0007.mp4"
        # an export that fails shows its error and the window goes on
        blocked = tmp_path / "not_a_folder"
        blocked.write_text("x")
        job = app.exports.start_video(ExportSettings(mode="turntable", turntable_frames=2, size=SIZE),
                                     directory=blocked)
        assert job.wait(60)
        assert app.step()
        assert job.state == "failed" and "export failed" in app.status.message()
        app.exports.settings.range_first, app.exports.settings.range_last = 3, 1  # bad settings: status, no raise
        app.exports.settings.mode = "range"
        app.exports.start_video_with_status()
        assert "frame range" in app.status.message() and app.step()
