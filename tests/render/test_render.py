"""The one render path (garmentnerf.render): the headless ``garmentnerf render`` command on the tiny
scene with an untrained run, the palette composition, and the viewer's palette shader against
:func:`garmentnerf.model.palette.compose`."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from garmentnerf.cli.main import main
from garmentnerf.model.config import ModelConfig
from garmentnerf.model.palette import compose
from garmentnerf.render.cameras import fit_size, orbit_view, parse_camera_spec, turntable
from garmentnerf.render.colors import build_palette, parse_hex_color, to_hex
from garmentnerf.render.video import FrameWriter, VideoWriter, count_video_frames


@pytest.fixture(scope="module")
def scene_dir(request, tmp_path_factory):
    try:
        scene = request.getfixturevalue("tiny_scene")
        return scene.root if hasattr(scene, "root") else scene
    except pytest.FixtureLookupError:
        from garmentnerf.data.synthetic import make_rigged_scene

        gl = request.getfixturevalue("gl_context")
        root = tmp_path_factory.mktemp("scene") / "tiny"
        return make_rigged_scene(root, frames=4, views=4, size=64, gl_context=gl).root


@pytest.fixture(scope="module")
def run_dir(scene_dir, tmp_path_factory):
    from garmentnerf.runs import create_untrained_run

    return create_untrained_run(tmp_path_factory.mktemp("run") / "untrained", scene_dir, ModelConfig.tiny(), seed=0)


@pytest.fixture(scope="module")
def session(run_dir, gl_context):
    from garmentnerf.render.session import RenderSession
    from garmentnerf.runs import load_run

    s = RenderSession(load_run(run_dir), gl_context)
    yield s
    s.close()


# ---- pure parts ---------------------------------------------------------------------------------
def test_colors_and_palette_parsing():
    assert parse_hex_color("#c03030") == pytest.approx((192 / 255, 48 / 255, 48 / 255))
    assert parse_hex_color("fff") == (1.0, 1.0, 1.0)
    assert to_hex((0.752941, 0.188235, 0.188235)) == "#c03030"
    for bad in ("#12345", "red", "#gg0000", ""):
        with pytest.raises(ValueError, match="not a hex color"):
            parse_hex_color(bad)
    learned = torch.tensor([[0.1, 0.2, 0.3], [0.4, 0.5, 0.6]])
    pal = build_palette(learned, "#ff0000")
    assert pal[0].tolist() == [1.0, 0.0, 0.0] and torch.equal(pal[1], learned[1])
    pal = build_palette(learned, "-,#00ff00", body="#0000ff")
    assert torch.equal(pal[0], learned[0]) and pal[1].tolist() == [0.0, 0.0, 1.0]
    with pytest.raises(ValueError, match="3 colors"):
        build_palette(learned, "#000,#111,#222")
    layered = torch.tensor([[0.1, 0.2, 0.3], [0.4, 0.5, 0.6], [0.7, 0.8, 0.9]])
    pal = build_palette(layered, "-,#00ff00", body="#0000ff")  # the body is the last color
    assert torch.equal(pal[0], layered[0]) and pal[1].tolist() == [0.0, 1.0, 0.0] and pal[2].tolist() == [0, 0, 1.0]


def test_cameras():
    assert parse_camera_spec("orbit").kind == "turntable"
    spec = parse_camera_spec("orbit:90:10")
    assert (spec.kind, spec.azimuth, spec.elevation) == ("orbit", 90.0, 10.0)
    with pytest.raises(ValueError, match="unknown camera 'cam99'"):
        parse_camera_spec("cam99")
    with pytest.raises(ValueError, match="needs a scene"):
        parse_camera_spec("3")
    cams = turntable(4, 32, 32)
    centres = np.array([c.center for c in cams])
    assert np.allclose(np.linalg.norm(centres[:, :2], axis=1), np.linalg.norm(centres[0, :2]))
    assert cams[0].center[1] < 0  # azimuth 0: in front of the character (-Y)
    wide = fit_size(orbit_view(0, width=200, height=100), 64)
    assert (wide.width, wide.height) == (64, 32)


def test_frame_and_video_writers_never_overwrite(tmp_path):
    w = FrameWriter(tmp_path / "out")
    img = np.zeros((9, 7, 3), np.uint8)
    w.write(3, img)
    with pytest.raises(FileExistsError):
        w.write(3, img + 1)
    with pytest.raises(FileExistsError, match="frame_0003.png"):
        w.check([2, 3])
    with VideoWriter(tmp_path / "v.mp4", 10) as v:
        for i in range(3):
            v.append(np.full((9, 7, 3), 40 * i, np.uint8))  # odd sizes are padded
    assert count_video_frames(tmp_path / "v.mp4") == 3
    with pytest.raises(FileExistsError):
        VideoWriter(tmp_path / "v.mp4", 10)
    assert not [p for p in tmp_path.rglob(".*")]  # no temporary files left


def test_a_video_that_does_not_check_out_is_removed_and_named(tmp_path, monkeypatch):
    """A video is checked before it is said to be written: an encoder that dies mid-way (a broken pipe)
    or a file holding other than the frames appended is a one-line VideoError, and no file stays."""
    import imageio_ffmpeg

    from garmentnerf.render import video as video_module
    from garmentnerf.budgets import VIDEO_FPS
    from garmentnerf.render.video import VideoError

    for fps in (1e-300, 1e308, float("nan"), 0.0):
        with pytest.raises(ValueError, match=f"video fps must be in {VIDEO_FPS.low:g}..{VIDEO_FPS.high:g}"):
            VideoWriter(tmp_path / "x.mp4", fps)
    frame = np.zeros((8, 8, 3), np.uint8)
    monkeypatch.setattr(video_module, "count_video_frames", lambda path: 2)  # one frame lost on the way
    v = VideoWriter(tmp_path / "short.mp4", 10)
    for _ in range(3):
        v.append(frame)
    with pytest.raises(VideoError, match=r"short.mp4: the video written holds 2 frame\(s\), not the 3 rendered"):
        v.close()
    monkeypatch.undo()

    def dying_encoder(*args, **kwargs):  # takes the first frame, then its ffmpeg is gone
        yield
        yield
        raise BrokenPipeError(32, "Broken pipe")

    monkeypatch.setattr(imageio_ffmpeg, "write_frames", dying_encoder)
    v = VideoWriter(tmp_path / "broken.mp4", 10)
    v.append(frame)
    with pytest.raises(VideoError, match=r"broken.mp4: the video encoder failed at frame 2 \(.*Broken pipe\)"):
        v.append(frame)
    assert not list(tmp_path.iterdir())  # neither video, nor a temporary


# ---- the session ------------------------------------------------------------------------------------
def test_session_caches_frames_and_scales(session):
    cam = orbit_view(30.0, width=96, height=96)
    first = session.render(1, cam, preset="reference")
    again = session.render(1, orbit_view(60.0, width=96, height=96), preset="reference")
    assert not first.cached_frame and again.cached_frame
    assert first.render_size == (64, 64)  # the frame at training density: 64 px for the 64 px model
    low = session.render(1, cam, quality=0.5, preset="reference")
    assert low.render_size == (32, 32)
    img = low.composite()
    assert img.shape == (96, 96, 3) and img.dtype == np.float32 and 0 <= img.min() and img.max() <= 1
    assert first.depth.shape == (64, 64) and (first.depth >= 0).all()
    with pytest.raises(ValueError, match="out of range"):
        session.render(99, cam)


def test_a_scene_of_another_body_shape_is_posed_with_that_shape(run_dir, gl_context):
    """Scoring a run on a scene of a held-out body shape: the session poses the scene's shape (what its
    ground truth shows), not the one the run was trained on."""
    from garmentnerf.render.session import RenderSession
    from garmentnerf.runs import load_run

    run = load_run(run_dir)
    body = run.model.body
    assert run.scene.body["shape"] == "average"
    with RenderSession(run, gl_context) as same:
        assert torch.equal(same.betas, body.betas("average"))
        average = same.posed.vertices[0].clone()
    run.scene.body = {**run.scene.body, "shape": "thin"}
    with RenderSession(run, gl_context) as thin:
        assert torch.equal(thin.betas, body.betas("thin"))
        assert float((thin.posed.vertices[0] - average).norm(dim=-1).max()) > 0.01  # posed with it


def test_culled_presets_render_the_character_at_its_training_density(session):
    """Near or far, the character's sampling box spans as many rendered pixels as it spans in the
    median training view at the model's resolution (measured here with trimesh-free geometry:
    the projected corners' extent), within a pixel of rounding."""
    from garmentnerf.conventions import project_points

    features, _ = session.frame_features(1)
    box = session.sampling_box(features).numpy()
    corners = torch.tensor([[x, y, z] for x in box[:, 0] for y in box[:, 1] for z in box[:, 2]], dtype=torch.float64)

    def extent(camera):
        uv, _ = project_points(camera, corners)
        return float((uv.max(0).values - uv.min(0).values).max())

    trained = float(np.median([extent(c) for c in session.training_views]))
    assert session.training_views and all(c.width == c.height == 64 for c in session.training_views)
    for radius, size in ((2.5, (320, 200)), (7.0, (200, 200))):
        cam = orbit_view(45.0, width=size[0], height=size[1], radius=radius)
        nf = session.render(1, cam, preset="full")
        assert extent(cam.scaled(nf.scale)) == pytest.approx(trained, abs=1.5)
        half = session.render(1, cam, quality=0.5, preset="full")
        assert half.scale == pytest.approx(nf.scale / 2)


def test_character_rect_render_equals_the_whole_frame_inside_it(session):
    """A culled preset casts rays and decodes only in the character's rectangle: inside it (less the
    decoder's margin) the maps equal a whole-frame render's, outside it they are empty, and fewer
    rays are cast."""
    import dataclasses

    from garmentnerf.render.presets import CHARACTER_RECT_MARGIN, RENDER_PRESETS

    cam = orbit_view(20.0, width=256, height=192, radius=6.0)  # far: the character is small
    cropped_preset = RENDER_PRESETS["full"]
    assert cropped_preset.character_rect
    whole_preset = dataclasses.replace(cropped_preset, name="full_whole_frame", character_rect=False)
    whole = session.render(1, cam, scale=0.5, preset=whole_preset)  # the same density for both
    cropped = session.render(1, cam, scale=0.5, preset=cropped_preset)
    assert whole.render_size == cropped.render_size == (128, 96)
    up = 2 ** session.config.decoder.upsample_steps
    assert whole.counts["rays_total"] == cropped.counts["rays_frame"] == (128 // up) * (96 // up)
    assert 0 < cropped.counts["rays_total"] < 0.6 * whole.counts["rays_total"]
    from garmentnerf.render.session import padded_render_camera

    padded, _, _ = padded_render_camera(cam, cropped.scale, up)
    features, _ = session.frame_features(1)
    rect = session.character_rect(features, padded, up)
    m = CHARACTER_RECT_MARGIN * up
    inner = (slice(rect.y0 + m, rect.y1 - m), slice(rect.x0 + m, rect.x1 - m))
    for a, b in zip((whole.maps.radiance, whole.maps.weights, whole.maps.mask),
                    (cropped.maps.radiance, cropped.maps.weights, cropped.maps.mask)):
        assert torch.allclose(a[..., inner[0], inner[1]], b[..., inner[0], inner[1]], atol=1e-5)
    outside = np.ones(cropped.maps.mask.shape[-2:], bool)
    outside[rect.slices()] = False
    assert outside.any() and float(cropped.maps.mask[0, 0].numpy()[outside].max()) == 0.0
    # the rays the whole frame cast outside the rectangle met no sample: its mask there is the
    # decoder's empty-space output, not the character
    assert whole.counts["points_evaluated"] == cropped.counts["points_evaluated"]


def test_palette_change_only_moves_garment_weighted_pixels(session):
    nf = session.render(2, orbit_view(0.0, width=64, height=64))
    learned = nf.palette
    new = learned.clone()
    new[0] = torch.tensor([0.9, 0.1, 0.1])
    a, b = nf.composite(learned), nf.composite(new)
    maps = nf.maps_at()
    # the change is m * r * w_0 * (p0' - p0) wherever the foreground is not clamped (compose is
    # linear in the palette inside [0, 1])
    base_old = (maps.weights.unsqueeze(2) * (learned[None, :, :, None, None] + maps.offsets)).sum(1)
    base_new = (maps.weights.unsqueeze(2) * (new[None, :, :, None, None] + maps.offsets)).sum(1)
    inside = ((maps.radiance * base_old).clamp(0, 1) == maps.radiance * base_old) & \
             ((maps.radiance * base_new).clamp(0, 1) == maps.radiance * base_new)
    predicted = (maps.mask * maps.radiance * maps.weights[:, :1] * (new[0] - learned[0]).view(1, 3, 1, 1))[0]
    diff = torch.from_numpy(b - a).permute(2, 0, 1)
    sel = inside[0]
    assert sel.float().mean() > 0.5
    assert torch.allclose(diff[sel], predicted[sel], atol=1e-5)
    # the same palette gives the same image: recoloring with the learned palette changes nothing
    assert np.array_equal(nf.composite(learned.clone()), a)
    # and compose() on the maps is what composite() returns
    ref = compose(maps.radiance, maps.offsets, maps.weights, maps.mask, new, nf.background)[0].permute(1, 2, 0)
    assert np.allclose(ref.numpy(), b, atol=1e-6)


# ---- the command --------------------------------------------------------------------------------
def test_render_command_writes_frames_and_video(run_dir, tmp_path, capsys):
    out = tmp_path / "out"
    argv = ["render", "--run", str(run_dir), "--motion", "train", "--camera", "orbit", "--frames", "0:3",
            "--size", "48", "--out", str(out), "--video", "--no-progress"]
    assert main(argv) == 0
    pngs = sorted(out.glob("*.png"))
    assert [p.name for p in pngs] == ["frame_0000.png", "frame_0001.png", "frame_0002.png"]
    from PIL import Image

    assert all(Image.open(p).size == (48, 48) for p in pngs)
    videos = list(out.glob("*.mp4"))
    assert len(videos) == 1 and count_video_frames(videos[0]) == 3
    stamp = [p.stat().st_mtime_ns for p in pngs]
    capsys.readouterr()
    assert main(argv) == 2  # never overwrites
    assert "already exists" in capsys.readouterr().err
    assert [p.stat().st_mtime_ns for p in pngs] == stamp


def test_render_command_palette_and_scene_camera(run_dir, tmp_path, session):
    a, b = tmp_path / "a", tmp_path / "b"
    common = ["render", "--run", str(run_dir), "--motion", "train", "--frames", "2", "--camera", "0",
              "--size", "64", "--no-progress"]
    assert main(common + ["--out", str(a)]) == 0
    assert main(common + ["--out", str(b), "--palette", "#c03030"]) == 0
    from PIL import Image

    ia = np.asarray(Image.open(a / "frame_0002.png")).astype(float) / 255
    ib = np.asarray(Image.open(b / "frame_0002.png")).astype(float) / 255
    # the same render through the session: the command's images are composite() of its maps
    cam = session.scene.camera(session.scene.camera_names()[0]).camera
    nf = session.render(2, cam)
    new = nf.palette.clone()
    new[0] = torch.tensor(parse_hex_color("#c03030"))
    assert np.abs(ia - nf.composite()).max() <= 1 / 255 + 1e-6
    assert np.abs(ib - nf.composite(new)).max() <= 1 / 255 + 1e-6
    # each pixel moved by m * r * w_garment * (p_new - p_old), up to the 8-bit rounding of both files
    m = nf.maps
    predicted = (m.mask * m.radiance * m.weights[:, :1] * (new[0] - nf.palette[0]).view(1, 3, 1, 1))[0]
    unclamped = (nf.composite(new) < 1) & (nf.composite(new) > 0) & (nf.composite() < 1) & (nf.composite() > 0)
    err = np.abs((ib - ia) - predicted.permute(1, 2, 0).numpy())[unclamped]
    drawn = m.mask[0, 0].numpy() > 0  # outside the character's rectangle the maps are empty: background
    assert unclamped[drawn].mean() > 0.9 and err.max() <= 1 / 255 + 1e-6


def test_the_preset_bench_measures_another_run_taking_turns(run_dir, tmp_path, gl_context):
    """``bench --run A --against B``: B's presets are rendered on the same views, taking turns with
    A's; a copy of the same model renders the same images (the same PSNR to the last bit, the same
    points), and the speed-up is the ratio of the two rows' ms per frame."""
    import shutil

    from garmentnerf.perf.preset_bench import preset_benchmark

    other = tmp_path / "other_run"
    shutil.copytree(run_dir, other)
    bench = preset_benchmark(run_dir, ["interactive"], frames=1, views=1, repeats=1, gl_context=gl_context,
                             log=lambda *a: None, playback_frames=1, against=[other])
    (theirs,) = bench["against"]
    assert theirs["run"] == str(other) and [r["preset"] for r in theirs["presets"]] == ["reference", "interactive"]
    for ours, row in zip(bench["presets"], theirs["presets"]):
        assert row["views"][0]["camera"] == ours["views"][0]["camera"] and row["points_per_frame"] == ours["points_per_frame"]
        assert row["psnr"] == ours["psnr"] and bench["psnr_vs_against_db"][str(other)][ours["preset"]] == 0.0
        assert bench["speedup_vs_against"][str(other)][ours["preset"]] == pytest.approx(
            row["ms_per_frame"] / ours["ms_per_frame"])


def test_interactive_preset_is_the_bench_row_in_render_and_in_the_viewer(run_dir, tmp_path, session, gl_context):
    """``render --preset interactive``, the previewer's lowest quality level and the bench row
    ``interactive`` render the same thing: same points, same size, same image."""
    from PIL import Image

    from garmentnerf.perf.preset_bench import preset_benchmark
    from garmentnerf.render.presets import RENDER_PRESETS, VIEWER_LEVELS
    from garmentnerf.runs import load_run
    from garmentnerf.viewer.playback_bench import render_ahead_benchmark
    from garmentnerf.viewer.quality import QualityController
    from garmentnerf.viewer.worker import NeuralRenderer, NeuralRequest

    bench = preset_benchmark(run_dir, ["interactive"], frames=1, views=1, repeats=1, gl_context=gl_context,
                             log=lambda *a: None, render_ahead=render_ahead_benchmark)
    row = next(r for r in bench["presets"] if r["preset"] == "interactive")
    # render-ahead: the previewer's worker rendered the tiny clip's 3 frames once each for
    # the still camera while it played (none abandoned), then played them back at the clip's rate
    ahead = bench["playback"]["render_ahead"]
    assert ahead["frames"] == 3 and ahead["camera"] == [1280, 800] and set(ahead["presets"]) == {"reference",
                                                                                                  "interactive"}
    for name, r in ahead["presets"].items():
        assert r["renders"] == r["started"] == 3 and r["completed_share"] == 1.0, (name, r)
        assert r["seconds_for_clip"] > 0 and 0 <= r["max_lag_frames"] < 3, (name, r)
        assert r["frames_shown"] == 6 and 0 < r["fps_after"] <= 1.05 * ahead["fps"], (name, r)
    assert bench["playback"]["completed_share"] == 1.0
    # the previewer-view figures: the whole frame casts every ray, the rectangle only some, with the
    # same samples at the same density; the character density is the session's rule
    for view in bench["previewer_view"]["views"]:
        whole, rect, char = (view["rows"][k] for k in ("whole frame, window density",
                                                       "character rectangle, window density",
                                                       "character rectangle, character density"))
        assert whole["rays"] == whole["rays_frame"] == rect["rays_frame"] and 0 < rect["rays"] < whole["rays"]
        assert rect["points"] == whole["points"] and rect["rendered"] == whole["rendered"]
        cam = orbit_view(25.0, width=1280, height=800, radius=view["distance"])
        features, _ = session.frame_features(bench["previewer_view"]["frame"])
        assert char["scale"] == pytest.approx(session.render_scale(cam, 1.0, features))
    entry = row["views"][0]
    frame, cam_name = entry["frame"], entry["camera"]
    cam = session.scene.camera(cam_name).camera
    assert row["settings"] == RENDER_PRESETS["interactive"].to_dict()
    # The previewer's lowest level (dynamic resolution off) asks the worker for exactly that preset.
    level = QualityController(preset=VIEWER_LEVELS[0], dynamic=False)
    results = []
    renderer = NeuralRenderer(load_run(run_dir), lambda result, request: results.append(result), motion=session.sequence)
    try:
        renderer.request(NeuralRequest(frame, cam, level.quality(0.0), session.sequence, None, level.preset))
        assert renderer.worker.wait_idle(120.0)
    finally:
        renderer.stop()
    assert len(results) == 1 and results[0].preset == "interactive"
    assert results[0].counts["points_evaluated"] == entry["points"] > 0
    assert results[0].counts["samples_placed"] == entry["samples_candidate"]
    # The command line renders the same image.
    out = tmp_path / "interactive"
    assert main(["render", "--run", str(run_dir), "--motion", session.sequence, "--frames", str(frame), "--camera",
                 cam_name, "--size", str(cam.width), "--preset", "interactive", "--no-progress", "--out", str(out)]) == 0
    image = np.asarray(Image.open(out / f"frame_{frame:04d}.png")).astype(float) / 255
    nf = session.render(frame, cam, preset="interactive")
    assert nf.render_size == tuple(results[0].render_size) and nf.counts["points_evaluated"] == entry["points"]
    assert np.abs(image - nf.composite()).max() <= 1 / 255 + 1e-6
    reference = session.render(frame, cam, preset="reference")  # another preset is another render
    assert reference.preset == "reference" and reference.render_size != nf.render_size
    assert reference.counts["points_evaluated"] > 2 * nf.counts["points_evaluated"]


@pytest.mark.parametrize("args, message", [
    (["--palette", "#zz0000"], "not a hex color"),
    (["--body-color", "blue"], "not a hex color"),
    (["--camera", "nope"], "unknown camera 'nope'"),
    (["--camera", "42"], "camera index 42 is out of range"),
    (["--frames", "2:99"], "out of range"),
    (["--frames", "x"], "--frames must look like"),
    (["--motion", "no_such_motion"], "no_such_motion"),
])
def test_render_command_errors_are_one_line(run_dir, tmp_path, capsys, args, message):
    code = main(["render", "--run", str(run_dir), "--out", str(tmp_path / "o"), "--no-progress"] + args)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and message in err[0]
    assert not (tmp_path / "o").exists() or not list((tmp_path / "o").iterdir())


def _write_path(file, frames=(0, 2), size=(40, 30)):
    from garmentnerf.render.camera_path import CameraPath, Keyframe, save_camera_path

    keys = tuple(Keyframe.from_camera(orbit_view(az, 10.0, (0.0, 0.0), 64, 64), f)
                 for az, f in zip((20.0, 110.0, 200.0), frames))
    return save_camera_path(CameraPath(keys, *size, fps=12.0), file)


def test_render_command_follows_a_camera_path(run_dir, tmp_path, session):
    from PIL import Image

    from garmentnerf.render.camera_path import load_camera_path

    path_file = _write_path(tmp_path / "dolly.json")
    out = tmp_path / "path"
    assert main(["render", "--run", str(run_dir), "--motion", session.sequence, "--camera-path", str(path_file),
                 "--out", str(out), "--video", "--no-progress"]) == 0
    pngs = sorted(out.glob("*.png"))
    assert [p.name for p in pngs] == [f"frame_{f:04d}.png" for f in range(3)]  # the path's span, frames 0..2
    videos = list(out.glob("*.mp4"))
    assert [v.name for v in videos] == [f"{session.sequence}_dolly.mp4"] and count_video_frames(videos[0]) == 3
    path = load_camera_path(path_file)
    for f, png in enumerate(pngs):
        image = np.asarray(Image.open(png)).astype(float) / 255
        assert image.shape == (30, 40, 3)  # the path's size
        reference = session.render(f, path.camera_at(f, 40, 30)).composite()
        assert np.abs(image - reference).max() <= 1 / 255 + 1e-6
    # --frames picks frames inside the motion; --size N keeps the path's aspect
    out2 = tmp_path / "path2"
    assert main(["render", "--run", str(run_dir), "--motion", session.sequence, "--camera-path", str(path_file),
                 "--frames", "1:3", "--size", "80", "--out", str(out2), "--no-progress"]) == 0
    assert [p.name for p in sorted(out2.glob("*.png"))] == ["frame_0001.png", "frame_0002.png"]
    assert Image.open(out2 / "frame_0001.png").size == (80, 60)


@pytest.mark.parametrize("content, message", [
    ("not json at all", "not valid JSON"),
    ("between frames", "span no whole motion frame"),
    ('{"format": "garmentnerf-camera-path", "keyframes": []}', "no keyframes"),
    ('{"format": "garmentnerf-camera-path", "keyframes": [{"frame": 0, "fov_y": 40, '
     '"camera_to_world": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 3, 0], [0, 0, 0, 1]]}]}', "not rigid"),
    ("frame 999", "outside motion"),
    ("--camera too", "--camera and --camera-path"),
])
def test_render_command_camera_path_errors_are_one_line(run_dir, tmp_path, capsys, session, content, message):
    file = tmp_path / "bad.json"
    extra = []
    if content == "frame 999":
        _write_path(file, frames=(0, 2, 999))
    elif content == "between frames":
        _write_path(file, frames=(0.2, 0.8))
    elif content == "--camera too":
        _write_path(file)
        extra = ["--camera", "orbit"]
    else:
        file.write_text(content)
    code = main(["render", "--run", str(run_dir), "--motion", session.sequence, "--camera-path", str(file),
                 "--out", str(tmp_path / "o"), "--no-progress"] + extra)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and message in err[0], err
    assert not (tmp_path / "o").exists() or not list((tmp_path / "o").iterdir())


# ---- the viewer's palette shader == compose() -----------------------------------------------------
def _gl_compose(ctx, maps, palette, background, body=None, camera=None):
    """The palette layer's image of ``maps`` (W x H, drawn over a whole W x H view); ``body``:
    (body model, appearance, vertices, normals) of a body layer it draws itself, seen by ``camera``."""
    import moderngl

    from garmentnerf.gl.context import current
    from garmentnerf.viewer import palette_layer, scene_gl

    B, P, H, W = maps["weights"].shape
    layers = scene_gl.pack_maps(maps["radiance"][0].numpy(), maps["offsets"][0].numpy(),
                                maps["weights"][0].numpy(), maps["mask"][0].numpy())
    view = scene_gl.ViewParams.of(camera if camera is not None else orbit_view(0.0, width=W, height=H))
    with current(ctx):
        layer = scene_gl.PaletteLayer(ctx)
        tex = ctx.texture((W, H), 4, dtype="f4")
        fbo = ctx.framebuffer(color_attachments=[tex])
        try:
            body_view = None
            if body is not None:
                body_model, appearance, vertices, normals = body
                layer.set_body_model(body_model, appearance)
                body_view = palette_layer.BodyView(vertices.numpy(), normals.numpy(), camera)
            layer.submit(layers, np.zeros((H, W), np.float32), (W, H), body=body_view)
            layer.prepare(view)
            assert layer.has_body == (body is not None)
            layer.set_palette(palette.numpy())
            layer.opaque = True
            layer.background = background
            fbo.use()
            ctx.viewport = (0, 0, W, H)
            ctx.enable_only(moderngl.NOTHING)
            fbo.clear(0.0, 0.0, 0.0, 0.0)
            layer.draw(view)
            data = np.frombuffer(fbo.read(components=4, dtype="f4"), dtype=np.float32).reshape(H, W, 4)
            return data[::-1, :, :3].copy()  # GL rows bottom-first -> image rows top-first
        finally:
            fbo.release()
            tex.release()
            layer.release()


@pytest.mark.parametrize("radiance_channels", [3, 1])
def test_palette_shader_matches_compose(gl_context, radiance_channels):
    g = torch.Generator().manual_seed(0)
    H, W, P = 24, 40, 2
    maps = {"radiance": torch.rand(1, radiance_channels, H, W, generator=g) * 1.6,  # some foregrounds clamp
            "offsets": (torch.rand(1, P, 3, H, W, generator=g) - 0.5) * 0.6,
            "weights": torch.softmax(torch.randn(1, P, H, W, generator=g) * 2, dim=1),
            "mask": torch.rand(1, 1, H, W, generator=g)}
    maps["mask"][..., :4, :] = 0.0  # some pure background rows
    palette = torch.tensor([[0.75, 0.19, 0.19], [0.8, 0.63, 0.53]])
    background = (0.1, 0.2, 0.3)
    ref = compose(maps["radiance"], maps["offsets"], maps["weights"], maps["mask"], palette, background)[0]
    ref = ref.permute(1, 2, 0).numpy()
    got = _gl_compose(gl_context, maps, palette, background)
    assert np.abs(got - ref).max() < 2 / 255
    # recolor: only the uniform changes
    new = palette.clone()
    new[0] = torch.tensor([0.1, 0.8, 0.2])
    ref2 = compose(maps["radiance"], maps["offsets"], maps["weights"], maps["mask"], new, background)[0]
    got2 = _gl_compose(gl_context, maps, new, background)
    assert np.abs(got2 - ref2.permute(1, 2, 0).numpy()).max() < 2 / 255


@pytest.mark.parametrize("P", [2, 3])
def test_palette_shader_matches_compose_with_a_body_layer(gl_context, body, walk_clip, P):
    """The raster_body composition: the layer draws the body itself (GL-shaded, at the size it is
    shown at); against compose() with the torch reference's body layer of the same camera, and with
    a new body color (only the uniform changes)."""
    from garmentnerf.body.surface import vertex_normals
    from garmentnerf.data.cameras import ring_camera
    from garmentnerf.gl.camera_pass import CameraPass
    from garmentnerf.model.body_appearance import BodyAppearance
    from garmentnerf.render.body_layer import render_body_layer

    g = torch.Generator().manual_seed(1)
    H, W = 36, 40
    vertices = walk_clip[0].vertices[0].detach().float()
    normals = vertex_normals(vertices, body.faces)
    centre = vertices.double().mean(dim=0).numpy()
    camera = ring_camera(20.0, 2.4, float(centre[2]), centre, W, H)
    appearance = BodyAppearance(texture_size=16)
    with torch.no_grad():
        appearance.albedo.uniform_(0.3, 1.4, generator=g)
        appearance.shading[1:].normal_(0.0, 0.3, generator=g)
    with CameraPass(gl_context) as camera_pass, torch.no_grad():
        body_color, coverage = render_body_layer(camera_pass, body, vertices, camera, appearance, normals=normals)
    assert 0.05 < coverage.mean() < 0.6 and (coverage == 0).any()
    maps = {"radiance": torch.rand(1, 3, H, W, generator=g) * 1.6,
            "offsets": (torch.rand(1, P, 3, H, W, generator=g) - 0.5) * 0.6,
            "weights": torch.softmax(torch.randn(1, P, H, W, generator=g) * 2, dim=1),
            "mask": torch.rand(1, 1, H, W, generator=g)}
    palette = torch.tensor([[0.75, 0.19, 0.19], [0.2, 0.5, 0.3], [0.8, 0.63, 0.53]])[-P:]
    background = (0.1, 0.2, 0.3)
    for pal in (palette, torch.cat([palette[:-1], torch.tensor([[0.3, 0.9, 0.1]])])):
        ref = compose(maps["radiance"], maps["offsets"], maps["weights"], maps["mask"], pal, background,
                      body_color, coverage)[0].permute(1, 2, 0).numpy()
        got = _gl_compose(gl_context, maps, pal, background, (body, appearance, vertices, normals), camera)
        assert np.abs(got - ref).max() < 2 / 255


def test_palette_shader_matches_session_composite(gl_context, session):
    nf = session.render(0, orbit_view(45.0, width=64, height=64))
    m = nf.maps
    maps = {"radiance": m.radiance, "offsets": m.offsets, "weights": m.weights, "mask": m.mask}
    pal = nf.palette.clone()
    pal[0] = torch.tensor([0.2, 0.3, 0.9])
    got = _gl_compose(gl_context, maps, pal, (0.0, 0.0, 0.0))
    assert np.abs(got - nf.composite(pal, (0.0, 0.0, 0.0), size=nf.render_size)).max() < 2 / 255


def test_palette_layer_draws_the_body_at_the_size_it_shows_it(gl_context, body, walk_clip):
    """The body layer follows the shown size (not the maps'), and is drawn again only when the body
    or that size changes."""
    from garmentnerf.body.surface import vertex_normals
    from garmentnerf.data.cameras import ring_camera
    from garmentnerf.gl.context import current
    from garmentnerf.model.body_appearance import BodyAppearance
    from garmentnerf.viewer import palette_layer, scene_gl

    vertices = walk_clip[0].vertices[0].detach().float()
    normals = vertex_normals(vertices, body.faces)
    centre = vertices.double().mean(dim=0).numpy()
    camera = ring_camera(0.0, 2.4, float(centre[2]), centre, 64, 48)  # the result's camera, 4:3
    maps = scene_gl.pack_maps(np.ones((3, 12, 16), np.float32), np.zeros((2, 3, 12, 16), np.float32),
                              np.full((2, 12, 16), 0.5, np.float32), np.ones((12, 16), np.float32))
    with current(gl_context):
        layer = scene_gl.PaletteLayer(gl_context)
        try:
            layer.set_body_model(body, BodyAppearance(texture_size=4))
            layer.submit(maps, np.zeros((12, 16), np.float32), (64, 48),
                         body=palette_layer.BodyView(vertices.numpy(), normals.numpy(), camera))
            big = scene_gl.ViewParams.of(ring_camera(0.0, 2.4, 1.0, centre, 400, 300))
            layer.prepare(big)
            assert layer.has_body and layer.body_draws == 1 and layer._body_tex.size == (400, 300)
            layer.prepare(big)  # nothing changed: no draw
            assert layer.body_draws == 1
            wide = scene_gl.ViewParams.of(ring_camera(0.0, 2.4, 1.0, centre, 600, 200))  # fitted: 267 x 200
            layer.prepare(wide)
            assert layer.body_draws == 2 and layer._body_tex.size == (267, 200)
            layer.submit(maps, np.zeros((12, 16), np.float32), (64, 48))  # a result without a body
            layer.prepare(wide)
            assert not layer.has_body and layer.body_draws == 2
        finally:
            layer.release()
