"""Evaluation of runs (garmentnerf.eval.evaluate), the nearest-view baseline, ``garmentnerf eval`` and
``garmentnerf report`` on a small rigged scene with untrained / 2-step models."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from garmentnerf.cli.main import main
from garmentnerf.eval.evaluate import (
    DEFAULT_LIMITS,
    SPLITS,
    _middle_window,
    _frames_of,
    _Scores,
    _spread,
    evaluate_run,
    format_result_table,
    nearest_camera,
    select_views,
)
from garmentnerf.eval.metrics import PSNR_CAP_DB, psnr, ssim

FRAMES = 6  # tOF needs 6 frames (2 skipped at each end, then one pair)


@pytest.fixture(scope="module")
def scene(tmp_path_factory, gl_context):
    """Skirt on 6 walk frames + 6 run frames (unseen motion), 3 training cameras + 1 held out, 64 x 64."""
    from garmentnerf.data.synthetic import make_rigged_scene

    return make_rigged_scene(tmp_path_factory.mktemp("eval_scene") / "scene", frames=FRAMES, views=3, size=64,
                             held_out_views=1, test_motion="run", test_frames=FRAMES, gl_context=gl_context)


@pytest.fixture(scope="module")
def run_dir(scene, tmp_path_factory):
    from garmentnerf.model.config import ModelConfig
    from garmentnerf.runs import create_untrained_run

    return create_untrained_run(tmp_path_factory.mktemp("eval_run") / "untrained", scene.root, ModelConfig.tiny(), seed=0)


@pytest.fixture(scope="module")
def loaded(run_dir):
    from garmentnerf.runs import load_run

    return load_run(run_dir)


@pytest.fixture(scope="module")
def unseen_view_result(loaded, gl_context):
    return evaluate_run(loaded, "unseen_view", progress=False, baseline=True, gl_context=gl_context)


# ---- pure parts ----------------------------------------------------------------------------------
def test_perfect_prediction():
    rng = np.random.default_rng(0)
    img = rng.random((32, 32, 3))
    assert psnr(img, img) == math.inf
    assert ssim(img, img) == pytest.approx(1.0, abs=1e-12)
    scores = _Scores([])
    for f in range(3):
        scores.add("s", "c", f, img, img)
    part = scores.finish({"s": True}, tof=True)
    assert part["means"]["psnr"] == PSNR_CAP_DB  # +inf per frame, capped in the mean
    assert part["means"]["ssim"] == pytest.approx(1.0, abs=1e-12)
    assert "tof" in part["unavailable"]  # 3 frames are too few for TecoGAN's tOF
    from garmentnerf.eval.metrics import _encode_float

    text = json.dumps(_encode_float(part), allow_nan=False)
    assert json.loads(text)["per_frame"][0]["psnr"] == "inf"
    # a perfect sequence long enough for tOF scores 0
    scores = _Scores([])
    frames = [np.roll(img, k, axis=1) for k in range(FRAMES)]
    frames = [np.pad(f, ((8, 8), (8, 8), (0, 0))) for f in frames]  # 48 x 48: the smallest tOF frame
    for k, f in enumerate(frames):
        scores.add("s", "c", k, f, f)
    part = scores.finish({"s": True})
    assert part["means"]["tof"] == 0.0 and part["counts"]["tof_pairs"] == FRAMES - 5


def test_selection_helpers():
    assert _spread(list("abcdefgh"), 4) == list("aceg")
    assert _spread(list("abc"), 4) == list("abc")
    assert _middle_window(100, 30) == list(range(35, 65))
    assert _middle_window(6, 30) == list(range(6))
    # frame ranges are garmentnerf.ranges' (tests/test_ranges.py): a step selects every S-th frame
    assert _frames_of("2:5", 10, "s") == [2, 3, 4] and _frames_of("1:8:3", 10, "s") == [1, 4, 7]
    assert _frames_of(slice(2, None, 4), 10, "s") == [2, 6] and _frames_of(None, 3, "s") == [0, 1, 2]
    for bad in ("a:b", "0:4:0", "-1:2", "", "4:4", "8:12"):
        with pytest.raises(ValueError, match="frames"):
            _frames_of(bad, 10, "s")
    assert set(DEFAULT_LIMITS) == set(SPLITS)


def test_select_views(loaded, scene):
    sel = select_views(loaded, scene, "seen")
    assert sel["cameras"] == ["cam00", "cam01", "cam02"] and sel["sequences"] == {"train": list(range(FRAMES))}
    assert not sel["subsampled"]
    sel = select_views(loaded, scene, "unseen_motion", frames="1:4", cameras="cam01")
    assert sel["sequences"] == {"test": [1, 2, 3]} and sel["cameras"] == ["cam01"]
    with pytest.raises(ValueError, match="unknown split"):
        select_views(loaded, scene, "bogus")
    with pytest.raises(ValueError, match="not one of the unseen_view cameras"):
        select_views(loaded, scene, "unseen_view", cameras=["cam00"])
    with pytest.raises(ValueError, match="out of range"):
        select_views(loaded, scene, "seen", frames="0:99")


# ---- evaluate_run on an untrained run ---------------------------------------------------------------
def test_evaluate_run_untrained(unseen_view_result, scene):
    r = unseen_view_result
    assert r["format"] == "garmentnerf-eval" and r["split"] == "unseen_view" and r["method"] == "model"
    assert r["cameras"] == scene.camera_names("unseen_view") == ["held00"]
    assert r["sequences"] == {"train": list(range(FRAMES))}
    assert r["resolution_wh"] == [64, 64]
    assert r["counts"] == {"images": FRAMES, "tof_pairs": FRAMES - 5}
    assert len(r["per_frame"]) == FRAMES and [f["frame"] for f in r["per_frame"]] == list(range(FRAMES))
    for key in ("psnr", "ssim", "stlpips_alex", "tof"):
        assert isinstance(r["means"][key], float) and math.isfinite(r["means"][key]), key
    assert 0 < r["means"]["psnr"] < 60 and -1 <= r["means"]["ssim"] <= 1
    assert len(r["per_camera"]) == 1 and r["per_camera"][0]["tof"]["pairs"] == [[2, 3]]
    if "lpips_alex" not in r["means"]:
        assert "GARMENTNERF_LPIPS_ALEXNET" in r["unavailable"]["lpips_alex"]
    # strict JSON round trip
    text = json.dumps(r, allow_nan=False)
    assert json.loads(text) == r
    assert "psnr" in format_result_table(r) or "PSNR" in format_result_table(r)


def test_evaluate_matches_render_path(loaded, scene, gl_context, unseen_view_result):
    """The evaluated prediction is the RenderSession image: recompute one frame's PSNR directly."""
    ref = _direct_psnr(loaded, scene, gl_context, 3, "held00", preset="reference")  # eval's default
    row = next(f for f in unseen_view_result["per_frame"] if f["frame"] == 3)
    assert row["psnr"] == pytest.approx(ref, abs=1e-4)


def _direct_psnr(loaded, scene, gl_context, frame: int, camera: str, **render_kwargs) -> float:
    """PSNR (scikit-image) of the RenderSession image of the training motion against the scene's
    ground truth, computed without the evaluation code."""
    from skimage.metrics import peak_signal_noise_ratio

    from garmentnerf.data.scene_images import SceneImages
    from garmentnerf.render.session import RenderSession

    with RenderSession(loaded, gl_context, "train") as s:
        pred = s.render_image(frame, scene.camera(camera).camera, **render_kwargs)
    images = SceneImages(scene)
    try:
        gt, _ = images.image("train", camera, frame)
    finally:
        images.close()
    return peak_signal_noise_ratio(gt.astype(np.float64), pred.astype(np.float64), data_range=1.0)


def test_quality_renders_at_that_density(loaded, scene, gl_context):
    """``quality`` replaces the preset's resolution: the evaluated image is the render at that
    quality (PSNR recomputed with scikit-image), and it differs from the default quality's."""
    half = evaluate_run(loaded, "unseen_view", frames="3:4", progress=False, gl_context=gl_context, quality=0.5,
                        tof=False)
    full = evaluate_run(loaded, "unseen_view", frames="3:4", progress=False, gl_context=gl_context, tof=False)
    assert half["quality"] == 0.5 and full["quality"] == 1.0
    ref = _direct_psnr(loaded, scene, gl_context, 3, "held00", quality=0.5, preset="reference")
    assert half["per_frame"][0]["psnr"] == pytest.approx(ref, abs=1e-4)
    assert half["per_frame"][0]["psnr"] != pytest.approx(full["per_frame"][0]["psnr"], abs=1e-3)
    with pytest.raises(ValueError, match="quality"):
        evaluate_run(loaded, "unseen_view", frames="3:4", progress=False, gl_context=gl_context, quality=0.0)


def test_nearest_view_baseline_matches_skimage(unseen_view_result, scene):
    from skimage.metrics import peak_signal_noise_ratio, structural_similarity

    from garmentnerf.data.scene_images import SceneImages

    b = unseen_view_result["baseline"]
    assert b["method"] == "nearest_view" and b["counts"]["images"] == FRAMES
    near = b["nearest_camera"]["held00"]
    assert near in scene.camera_names("train")
    # nearest by optical-axis angle, computed here independently
    axis = {c: np.asarray(scene.camera(c).camera.R)[2] for c in scene.camera_names()}
    angles = {c: math.degrees(math.acos(np.clip(axis["held00"] @ axis[c], -1, 1)))
              for c in scene.camera_names("train")}
    assert angles[near] <= min(angles.values()) + 1e-6
    assert nearest_camera(scene, "held00", scene.camera_names("train"))[0] == near
    images = SceneImages(scene)  # scene size 64 = the model's 64: no resize; black background
    try:
        for row in b["per_frame"]:
            gt = images.image("train", "held00", row["frame"])[0].astype(np.float64)
            pred = images.image("train", near, row["frame"])[0].astype(np.float64)
            assert row["psnr"] == pytest.approx(peak_signal_noise_ratio(gt, pred, data_range=1.0), abs=1e-6)
            ref_ssim = structural_similarity(gt, pred, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                             data_range=1.0, channel_axis=-1)
            assert row["ssim"] == pytest.approx(ref_ssim, abs=1e-5)
    finally:
        images.close()
    assert math.isfinite(b["means"]["tof"]) and math.isfinite(b["means"]["stlpips_alex"])


def test_baseline_only_on_unseen_view(loaded, gl_context):
    with pytest.raises(ValueError, match="unseen_view"):
        evaluate_run(loaded, "seen", baseline=True, progress=False, gl_context=gl_context)
    with pytest.raises(ValueError, match="unknown split"):
        evaluate_run(loaded, "bogus", progress=False, gl_context=gl_context)


def test_foreground_figures_match_a_direct_computation(loaded, scene, gl_context, unseen_view_result):
    """fg / body / garment PSNR (scikit-image on the region's pixels), IoU and sharpness of one view,
    recomputed here from the render path's image and mask and the scene's labels; the margin."""
    from scipy import ndimage
    from scipy.stats import pearsonr
    from skimage.metrics import peak_signal_noise_ratio

    from garmentnerf.data.scene_images import SceneImages
    from garmentnerf.render.session import RenderSession

    with RenderSession(loaded, gl_context, "train") as s:
        nf = s.render(2, scene.camera("held00").camera, preset="reference")
        pred, pred_sil = nf.composite().astype(np.float64), nf.alpha() > 0.5
    images = SceneImages(scene)
    try:
        gt, labels = images.image("train", "held00", 2)
        near = unseen_view_result["baseline"]["nearest_camera"]["held00"]
        near_img, near_labels = images.image("train", near, 2)
    finally:
        images.close()
    gt = gt.astype(np.float64)
    row = next(f for f in unseen_view_result["per_frame"] if f["frame"] == 2)
    truth = labels != 0
    for key, region in (("fg_psnr", truth | pred_sil), ("body_psnr", labels == 1), ("garment_psnr", labels == 2)):
        assert region.any(), key
        ref = peak_signal_noise_ratio(gt[region], pred[region], data_range=1.0)
        assert row[key] == pytest.approx(ref, abs=1e-4), key
    assert row["silhouette_iou"] == pytest.approx((truth & pred_sil).sum() / (truth | pred_sil).sum(), abs=1e-12)
    inside = ndimage.binary_erosion(labels == 2, structure=np.ones((3, 3), bool), border_value=0)  # 1 px at 64

    def energy(img):
        luma = img @ np.array([0.299, 0.587, 0.114])
        return float(np.sum((ndimage.sobel(luma, axis=1) ** 2 + ndimage.sobel(luma, axis=0) ** 2)[inside]))

    if inside.any() and energy(gt) > 0:  # away from the image border, where the two Sobels agree
        assert row["sharpness"] == pytest.approx(energy(pred) / energy(gt), rel=1e-3)
    # the garment away from its outline (OUTLINE_BAND, 1 px at 64) and the outline band's share of its error
    assert inside.any()
    assert row["garment_inner_psnr"] == pytest.approx(peak_signal_noise_ratio(gt[inside], pred[inside], data_range=1.0),
                                                      abs=1e-4)
    sq = ((pred - gt) ** 2).sum(axis=-1)
    band = (labels == 2) & ~inside
    assert band.any()
    assert row["garment_outline_share"] == pytest.approx(sq[band].sum() / sq[labels == 2].sum(), rel=1e-9)
    luma = np.array([0.2126, 0.7152, 0.0722])
    assert row["garment_luma"] == pytest.approx(float((pred[inside] @ luma).mean()), rel=1e-9)
    assert row["garment_luma_truth"] == pytest.approx(float((gt[inside] @ luma).mean()), rel=1e-9)
    assert row["fold_correlation"] == pytest.approx(pearsonr(pred[inside] @ luma, gt[inside] @ luma)[0], abs=1e-9)
    garment = gt[labels == 2]
    flat = np.broadcast_to(garment.mean(axis=0), garment.shape)
    assert row["garment_flat_psnr"] == pytest.approx(peak_signal_noise_ratio(garment, flat, data_range=1.0), abs=1e-6)
    views = [f for f in unseen_view_result["per_frame"] if "garment_luma" in f]
    p, t = np.array([f["garment_luma"] for f in views]), np.array([f["garment_luma_truth"] for f in views])
    assert len(views) >= 3 and t.std() > 0
    assert unseen_view_result["means"]["shading_contrast"] == pytest.approx(p.std() / t.std(), rel=1e-9)
    assert unseen_view_result["means"]["shading_correlation"] == pytest.approx(np.corrcoef(p, t)[0, 1], rel=1e-9)
    # the baseline's silhouette is its own ground-truth labels
    base_row = next(f for f in unseen_view_result["baseline"]["per_frame"] if f["frame"] == 2)
    near_sil = near_labels != 0
    ref = peak_signal_noise_ratio(gt[truth | near_sil], near_img.astype(np.float64)[truth | near_sil], data_range=1.0)
    assert base_row["fg_psnr"] == pytest.approx(ref, abs=1e-6)
    r = unseen_view_result
    assert r["resolution"] == "native"
    assert r["margin_db"]["psnr"] == pytest.approx(r["means"]["psnr"] - r["baseline"]["means"]["psnr"])
    assert r["margin_db"]["fg_psnr"] == pytest.approx(r["means"]["fg_psnr"] - r["baseline"]["means"]["fg_psnr"])
    table = format_result_table(r)
    assert "fg PSNR" in table and "margin over the nearest view" in table


# ---- CLI ------------------------------------------------------------------------------------------
def _one_line_error(capsys, argv, match):
    rc = main(argv)
    err = capsys.readouterr().err.strip()
    assert rc == 2, err
    assert len(err.splitlines()) == 1 and err.startswith("garmentnerf: error:") and match in err, err


def test_cli_errors(run_dir, tmp_path, capsys, scene):
    _one_line_error(capsys, ["eval", "--run", str(run_dir), "--split", "bogus"], "unknown split 'bogus'")
    _one_line_error(capsys, ["eval", "--run", str(run_dir), "--split", "seen", "--baseline"], "unseen_view only")
    _one_line_error(capsys, ["eval", "--run", str(tmp_path / "nope"), "--split", "seen"], "no such run folder")
    _one_line_error(capsys, ["eval", "--run", str(run_dir), "--split", "seen", "--frames", "x:y"], "A:B")
    # a run whose scene folder is gone
    import shutil

    moved = tmp_path / "moved_run"
    shutil.copytree(run_dir, moved)
    info = json.loads((moved / "run.json").read_text())
    info["scene"] = str(tmp_path / "gone_scene")
    (moved / "run.json").write_text(json.dumps(info))
    _one_line_error(capsys, ["eval", "--run", str(moved), "--split", "seen"], "pass --scene")
    _one_line_error(capsys, ["report", "--scene", str(tmp_path / "none"), "--out", str(tmp_path / "r.md")],
                    "scene.json")
    _one_line_error(capsys, ["report", "--scene", str(scene.root), "--out", str(tmp_path / "r.md"),
                             "--variants", "bogus"], "unknown variant")


def test_raster_body_composition(run_dir, scene, gl_context, tmp_path, capsys, unseen_view_result):
    """``garmentnerf body fit-appearance`` on a copy of the run, then both compositions: the rasterised
    body wins over the (untrained) network's by far on the body, ``auto`` picks it, and ``nerf`` on the
    copy scores exactly what the run without an appearance does."""
    import shutil

    from garmentnerf.runs import load_run

    copy = tmp_path / "with_body"
    shutil.copytree(run_dir, copy)
    argv = ["body", "fit-appearance", "--run", str(copy), "--scene", str(scene.root), "--steps", "200",
            "--frame-stride", "2", "--no-progress"]
    assert main(argv) == 0
    assert "PSNR over them" in capsys.readouterr().out
    assert (copy / "body_appearance.safetensors").is_file()
    _one_line_error(capsys, argv, "already exists")
    _one_line_error(capsys, ["eval", "--run", str(run_dir), "--split", "seen", "--composition", "raster_body"],
                    "fit-appearance")
    _one_line_error(capsys, ["eval", "--run", str(run_dir), "--split", "seen", "--composition", "x"],
                    "unknown composition")
    loaded = load_run(copy, scene=scene.root)
    assert loaded.body_appearance is not None
    hybrid = evaluate_run(loaded, "unseen_view", progress=False, baseline=True, gl_context=gl_context)
    plain = evaluate_run(loaded, "unseen_view", progress=False, baseline=True, gl_context=gl_context,
                         composition="nerf")
    assert hybrid["composition"] == "raster_body" and plain["composition"] == "nerf"
    assert hybrid["means"]["body_psnr"] > plain["means"]["body_psnr"] + 5
    assert hybrid["means"]["silhouette_iou"] > plain["means"]["silhouette_iou"]
    assert plain["means"] == unseen_view_result["means"]
    # a session leaves the body layer to a caller that draws it itself (the previewer), handing over the
    # frame's posed body: the same layer drawn from it is the one the session attaches
    from garmentnerf.render.session import RenderSession

    camera = scene.camera("held00").camera
    with RenderSession(loaded, gl_context) as session:
        attached = session.render(0, camera)
        bare = session.render(0, camera, body_layer=False)
        feats, _ = session.frame_features(0)
        assert attached.maps.body_color is not None and bare.maps.body_color is None
        vertices, normals = bare.body
        assert vertices.dtype == normals.dtype == torch.float32 and vertices.device.type == "cpu"
        torch.testing.assert_close(vertices, feats.posed_vertices.float().cpu())
        color, coverage = session.body_layer(feats, camera.resized(*bare.render_size))
        assert torch.equal(color, attached.maps.body_color) and torch.equal(coverage, attached.maps.body_coverage)


def test_cli_eval_gallery(run_dir, scene, tmp_path, capsys):
    """--gallery: one strip per kept view, ground truth | render | error | nearest view | error, the
    ground-truth tile the scene's image."""
    import imageio.v3 as iio

    from garmentnerf.data.scene_images import SceneImages
    from garmentnerf.eval.gallery import CAPTION_PX

    out = tmp_path / "gallery.png"
    argv = ["eval", "--run", str(run_dir), "--split", "unseen_view", "--frames", "1:4", "--baseline",
            "--gallery", str(out), "--gallery-views", "2", "--no-progress"]
    assert main(argv) == 0
    assert "wrote" in capsys.readouterr().out
    sheet = iio.imread(out)
    images = SceneImages(scene)
    try:
        gt, labels = images.image("train", "held00", 1)  # the first view is always kept
    finally:
        images.close()
    # the row is cropped to the character: the ground truth's labels and the render's mask, + 16 px
    rows, cols = np.nonzero(labels)
    assert sheet.shape[0] <= 2 * (CAPTION_PX + 64) and sheet.shape[1] % 5 == 0
    h, w = sheet.shape[0] // 2 - CAPTION_PX, sheet.shape[1] // 5  # a square 64-pixel scene: same each row
    assert h >= min(rows.max() - rows.min() + 1, 64) and w >= min(cols.max() - cols.min() + 1, 64)
    tile = sheet[CAPTION_PX:CAPTION_PX + h, :w]
    gt8 = np.round(gt * 255).astype(np.uint8)
    # the tile is a window of the ground truth that holds every labelled pixel (the render's
    # silhouette may widen it)
    windows = [(y0, x0) for y0 in range(0, 64 - h + 1) for x0 in range(0, 64 - w + 1)
               if np.array_equal(gt8[y0:y0 + h, x0:x0 + w], tile)]
    assert any(y0 <= rows.min() and rows.max() < y0 + h and x0 <= cols.min() and cols.max() < x0 + w
               for y0, x0 in windows), windows
    # asking again without --overwrite refuses, the file untouched
    before = out.read_bytes()
    _one_line_error(capsys, argv, "already exists")
    assert out.read_bytes() == before
    _one_line_error(capsys, argv[:-3] + ["--gallery-views", "0"], "--gallery-views")
    _one_line_error(capsys, ["eval", "--run", str(run_dir), "--split", "seen", "--resolution", "huge"],
                    "--resolution")
    _one_line_error(capsys, ["eval", "--run", str(run_dir), "--split", "seen", "--quality", "0"], "--quality")


def test_cli_eval_json(run_dir, tmp_path, capsys):
    out = tmp_path / "eval.json"
    rc = main(["eval", "--run", str(run_dir), "--split", "unseen_motion", "--frames", "0:2", "--cameras", "cam01",
               "--json", str(out), "--no-progress"])
    printed = capsys.readouterr().out
    assert rc == 0
    assert "PSNR" in printed and "unseen_motion" in printed
    data = json.loads(out.read_text())
    assert data["sequences"] == {"test": [0, 1]} and data["cameras"] == ["cam01"]
    assert len(data["per_frame"]) == 2 and "tof" in data["unavailable"]  # 2 frames: no tOF


# ---- report --------------------------------------------------------------------------------------
def test_render_markdown_shape():
    from garmentnerf.eval.report import Variant, render_markdown

    def res(p):
        return {"means": {"psnr": p, "ssim": 0.9, "stlpips_alex": 0.1, "tof": 0.5}, "sequences": {"train": [0, 1]},
                "cameras": ["c"], "unavailable": {"lpips_alex": "no weights"}, "step": 2}

    variants = [Variant("full"), Variant("no_detail", {"encoder.detail_feature": False}), Variant("k0", {"encoder.history": 0}),
                Variant("views_4", views=4, cameras=("a", "b", "c", "d")), Variant("views_16", views=16, note="few")]
    results = {v.name: {"seen": res(20.0 + i), "unseen_view": res(18.0 + i)} for i, v in enumerate(variants[:4])}
    meta = {"scene": "s", "preset": "tiny", "iterations": 2, "generator_iterations": 1, "seed": 0, "history": 2,
            "train_cameras": 8, "runs_dir": "r", "seconds": 1.0}
    md = render_markdown(meta, variants, results, {**res(15.0), "nearest_camera": {"h": "c"}}, ["seen", "unseen_view"])
    assert "| nearest view | - | - | - | - | 15.00 | 0.900 | 0.100 | 0.500 |" in md
    assert "| ours (full) | 20.00 |" in md
    assert "| ✓ | ✓ | 20.00 |" in md and "|  | ✓ | 21.00 |" in md
    assert "| 4 | 23.00 |" in md and "| 8 (full) | 20.00 |" in md
    assert "| 0 | 22.00 |" in md and "| 2 (full) | 20.00 |" in md
    assert "ST-LPIPS↓" in md and "not the paper's LPIPS" in md and "no weights" in md
    assert "skipped: few" in md


@pytest.mark.slow
def test_report_tiny(scene, tmp_path):
    """Two variants x 2 NeRF steps (+1 G_img step), every split; a second call reuses everything."""
    from garmentnerf.eval.report import build_report

    out = tmp_path / "report.md"
    kw = dict(iterations=2, generator_iterations=1, preset="tiny", runs_dir=tmp_path / "runs",
              variants=["full", "no_detail"], views=(), histories=(), perceptual="none", frames="0:6",
              progress=False, log=lambda m: None)
    build_report(scene.root, out, **kw)
    md = out.read_text()
    assert "| nearest view |" in md and "| ours (full) |" in md
    assert "|  | ✓ |" in md and "| ✓ | ✓ |" in md  # no_detail and full rows of the features table
    assert "seen PSNR↑" in md and "unseen view PSNR↑" in md and "unseen motion PSNR↑" in md
    for v in ("full", "no_detail"):
        info = json.loads((tmp_path / "runs" / v / "run.json").read_text())
        assert info["step"] == (3 if v == "full" else 2)
        assert all((tmp_path / "runs" / v / "eval" / f"{s}.json").is_file() for s in SPLITS)
    stamp = (tmp_path / "runs" / "full" / "eval" / "seen.json").stat().st_mtime_ns
    messages = []
    with pytest.raises(FileExistsError, match="already exists"):  # the report itself is never replaced unasked
        build_report(scene.root, out, **kw)
    build_report(scene.root, out, **{**kw, "log": messages.append, "overwrite": True})
    assert "full: skipped" in messages and "no_detail: skipped" in messages
    assert (tmp_path / "runs" / "full" / "eval" / "seen.json").stat().st_mtime_ns == stamp
    assert "| full | - | all | 3 | skipped |" in out.read_text()
    # other settings in the same runs folder: refused
    with pytest.raises(ValueError, match="other settings"):
        build_report(scene.root, out, **{**kw, "iterations": 3, "overwrite": True})


def test_train_variant_resumes_and_skips(scene, gl_context, tmp_path):
    """An unfinished run is resumed from its checkpoint, a finished one is left alone."""
    from garmentnerf.eval.report import train_variant
    from garmentnerf.model.config import ModelConfig
    from garmentnerf.train.settings import TrainConfig
    from garmentnerf.train.trainer import Trainer

    cfg = ModelConfig.tiny().updated({"encoder.detail_feature": False, "encoder.dynamic_feature": False})  # no G_img: cheapest
    run = tmp_path / "runs" / "no_features"
    tc = TrainConfig(scene=scene.root, out=run, model_config=cfg, iterations=2, stop_after=1, perceptual="none",
                     progress=False, image_every=0, cameras=("cam00",))
    with Trainer(tc, gl_context, log=lambda m: None) as t:
        t.train()
    assert json.loads((run / "run.json").read_text())["step"] == 1
    kw = dict(iterations=2, perceptual="none", progress=False, gl_context=gl_context, log=lambda m: None)
    assert train_variant(scene.root, run, cfg, ("cam00",), **kw) == "resumed"
    assert json.loads((run / "run.json").read_text())["step"] == 2
    assert train_variant(scene.root, run, cfg, ("cam00",), **kw) == "skipped"
    with pytest.raises(ValueError, match="training cameras"):
        train_variant(scene.root, run, cfg, ("cam01",), **kw)
    (tmp_path / "runs" / "junk").mkdir()
    (tmp_path / "runs" / "junk" / "file.txt").write_text("x")
    with pytest.raises(ValueError, match="not a run folder"):
        train_variant(scene.root, tmp_path / "runs" / "junk", cfg, None, **kw)
