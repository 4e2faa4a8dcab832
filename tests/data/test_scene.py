"""Scene folders: camera rigs against OpenCV, scene.json round trip and validation, the image cache,
contact sheets."""

from __future__ import annotations

import json
import os
import shutil

import cv2
import numpy as np
import pytest
import torch
from support.scenes import SIZE, _motion, _write_garment, build_scene

from garmentnerf.conventions import project_points
from garmentnerf.data.cameras import CAMERA_SPLITS, circle_rig, default_rig, held_out_rig, reference_cameras
from garmentnerf.data.preview import contact_sheet, label_edges, scene_contact_sheet
from garmentnerf.data.render_gt import GroundTruthRenderer, to_uint8
from garmentnerf.data.scene import GarmentArrays, Scene, SceneError
from garmentnerf.data.scene_images import SceneImages, palette_from_images
from garmentnerf.motion.motion import Motion


def _read_garment(path) -> GarmentArrays:
    with np.load(path) as npz:
        return GarmentArrays(npz["vertices"], npz["faces"])


# ---- rigs -----------------------------------------------------------------------------------------
def test_rig_layout():
    circle = circle_rig(16)
    assert [c.name for c in circle] == [f"cam{i:02d}" for i in range(16)]
    assert all(c.split == "train" for c in circle)
    # cam00 in front of the character (-Y side), cam04 on +X (the character's left).
    np.testing.assert_allclose(circle[0].camera.center, [0.0, -3.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(circle[4].camera.center, [3.0, 0.0, 1.0], atol=1e-12)
    held = held_out_rig(4, 16)
    assert [c.name for c in held] == ["held00", "held01", "held02", "held03"]
    assert all(c.split == "unseen_view" for c in held)
    centers = np.array([c.camera.center for c in circle])
    for cam in held:
        d = np.sort(np.linalg.norm(centers - cam.camera.center, axis=1))
        assert abs(d[0] - d[1]) < 1e-9 and d[1] < d[2] - 1e-3  # exactly halfway between two neighbours
    assert sorted(round(c.azimuth_deg, 6) for c in held) == [11.25, 101.25, 191.25, 281.25]
    ref = reference_cameras()
    assert [c.name for c in ref] == ["ref_front", "ref_back"] and {c.split for c in ref} == {"reference"}
    np.testing.assert_allclose(ref[0].camera.R, circle[0].camera.R, atol=1e-12)
    np.testing.assert_allclose(ref[1].camera.R, circle[8].camera.R, atol=1e-12)
    assert {c.split for c in default_rig()} == set(CAMERA_SPLITS)
    with pytest.raises(ValueError):
        held_out_rig(5, 4)


@pytest.mark.parametrize("target", [(0.0, 0.0, 0.9), (0.2, -0.1, 1.1)])
def test_rig_projects_like_opencv(target):
    rng = np.random.default_rng(0)
    cams = default_rig(look_at=target) + circle_rig(5, radius=2.5, height=1.6, look_at=target, width=640,
                                                    height_px=480, fov_y_deg=55, prefix="wide")
    pts = rng.uniform(-0.6, 0.6, (50, 3)) + np.array(target)
    for nc in cams:
        cam = nc.camera
        uv, z = project_points(cam, torch.as_tensor(np.vstack([target, pts]), dtype=torch.float64))
        uv = uv.numpy()
        assert (z.numpy() > 0).all()
        # The look-at target lands on the principal point.
        np.testing.assert_allclose(uv[0], cam.K[:2, 2], atol=1e-9)
        # A point above the target is higher in the image (smaller row), same column.
        up = project_points(cam, torch.tensor([[target[0], target[1], target[2] + 0.3]], dtype=torch.float64))[0][0]
        assert up[1] < uv[0][1] - 5 and abs(up[0] - uv[0][0]) < 1e-6
        expected, _ = cv2.projectPoints(pts, cv2.Rodrigues(cam.R)[0], cam.t, cam.K, None)
        np.testing.assert_allclose(uv[1:], expected.reshape(-1, 2), atol=1e-7)
    # cam00 looks at the character's front: its left (+X) is on the image's right.
    front = cams[0].camera
    left = project_points(front, torch.tensor([[target[0] + 0.3, target[1], target[2]]], dtype=torch.float64))[0][0]
    assert left[0] > front.K[0, 2] + 5


# ---- scene.json ------------------------------------------------------------------------------------
def test_round_trip(tmp_path):
    scene = build_scene(tmp_path / "skirt")
    loaded = Scene.load(tmp_path / "skirt")
    assert loaded.to_json() == scene.to_json()
    assert Scene.load(tmp_path / "skirt" / "scene.json").to_json() == scene.to_json()
    for a, b in zip(scene.rig, loaded.rig):
        assert a.name == b.name and a.split == b.split
        for field in ("K", "R", "t"):
            assert np.array_equal(getattr(a.camera, field), getattr(b.camera, field))
    data = json.loads((tmp_path / "skirt" / "scene.json").read_text())
    assert data["format"] == "garmentnerf-scene" and data["version"] == 1 and data["image_size"] == [SIZE, SIZE]
    assert data["sequences"]["train"] == {"motion": "walk,dance_a", "frames": 3, "split": "train"}
    assert data["body"] == {"model": "anny", "shape": "average"}
    assert loaded.sequence_names("train") == ["train"] and loaded.sequence_names("unseen_motion") == ["test_run"]
    assert loaded.camera_names("unseen_view") == ["held00", "held01"]
    assert loaded.camera_names("reference") == ["ref_front", "ref_back"]
    assert len(loaded.cameras("train")) == 8 and len(loaded.cameras()) == 12
    assert loaded.num_frames("train") == 3 and loaded.load_motion("train").num_frames == 3
    assert loaded.garment_path("train") == tmp_path / "skirt" / "sequences" / "train" / "garment.npz"
    assert loaded.simulation["train"]["seconds_per_frame"] == 2.1
    p = loaded.image_path("train", "cam03", 2)
    assert p.parent.parent.parent == tmp_path / "skirt" / "cache" / "train" and p.name == "00002.png"
    with pytest.raises(SceneError, match="out of range"):
        loaded.image_path("train", "cam03", 3)
    with pytest.raises(SceneError, match="no camera 'cam99'"):
        loaded.camera("cam99")
    with pytest.raises(SceneError, match="unknown camera split"):
        loaded.cameras("test")
    # Saving is atomic and leaves no temporary file behind.
    loaded.save()
    assert sorted(x.name for x in (tmp_path / "skirt").iterdir()) == ["scene.json", "sequences"]


def _edit(key_path, value):
    def apply(d):
        node = d
        for k in key_path[:-1]:
            node = node[k]
        if value is _DELETE:
            del node[key_path[-1]]
        else:
            node[key_path[-1]] = value(node[key_path[-1]]) if callable(value) else value
        return d
    return apply


_DELETE = object()


def _scaled_row(R):
    R = [list(r) for r in R]
    R[0] = [1.1 * x for x in R[0]]
    return R


MALFORMED = {
    "missing field": (_edit(["fps"], _DELETE), "fps is missing"),
    "missing camera field": (_edit(["cameras", 2, "t"], _DELETE), "cameras[2].t is missing"),
    "K 2x2": (_edit(["cameras", 3, "K"], [[100.0, 0.0], [0.0, 100.0]]), "cameras[3].K must be 3x3"),
    "K bottom row": (_edit(["cameras", 3, "K"], lambda K: K[:2] + [[0.0, 0.0, 2.0]]), "cameras[3].K must be upper"),
    "R not orthonormal": (_edit(["cameras", 2, "R"], _scaled_row), "cameras[2].R must be a rotation"),
    "R reflection": (_edit(["cameras", 1, "R"], lambda R: [[-x for x in R[0]]] + R[1:]), "cameras[1].R must be a rot"),
    "t length": (_edit(["cameras", 0, "t"], [0.0, 1.0]), "cameras[0].t must be a list of 3 numbers"),
    "width type": (_edit(["cameras", 0, "width"], "48"), "cameras[0].width must be an integer"),
    "size mismatch": (_edit(["image_size"], [64, 48]), "cameras[0] is 48x48"),
    "unknown camera split": (_edit(["cameras", 1, "split"], "test"), "cameras[1].split must be one of"),
    "unknown camera key": (_edit(["cameras", 0, "D"], [0.1, 0, 0, 0, 0]), "cameras[0] has unknown key(s) D"),
    "duplicate camera": (_edit(["cameras", 1, "name"], "cam00"), "cameras[1].name 'cam00' is used"),
    "unknown sequence split": (_edit(["sequences", "train", "split"], "val"), "sequences.train.split must be one of"),
    "frames mismatch": (_edit(["sequences", "train", "frames"], 5), "sequences.train.frames is 5 but"),
    "frames type": (_edit(["sequences", "train", "frames"], 2.5), "sequences.train.frames must be an integer"),
    "garment color": (_edit(["garment", "color"], [0.2, 1.4, 0.1]), "garment.color must hold 3 numbers in [0, 1]"),
    "body shape": (_edit(["body", "shape"], {"a": 1}), "body.shape must be a shape name or a list"),
    "format": (_edit(["format"], "nerf"), "format must be 'garmentnerf-scene'"),
    "version": (_edit(["version"], 2), "version 2 is newer"),
    "fps": (_edit(["fps"], -30), "fps must be > 0"),
    "palette": (_edit(["palette_init", "body"], _DELETE), "palette_init.body is missing"),
    "simulation": (_edit(["simulation", "nope"], {}), "simulation.nope names no sequence"),
    "not an object": (lambda d: [d], "must be an object, got a list"),
}


@pytest.mark.parametrize("case", list(MALFORMED), ids=list(MALFORMED))
def test_malformed_scene_json(tmp_path, case):
    build_scene(tmp_path / "s")
    file = tmp_path / "s" / "scene.json"
    mutate, expected = MALFORMED[case]
    file.write_text(json.dumps(mutate(json.loads(file.read_text()))))
    with pytest.raises(SceneError) as info:
        Scene.load(tmp_path / "s")
    msg = str(info.value)
    assert msg.startswith(f"{file}: ") and expected in msg and "\n" not in msg, msg


def test_bad_json_and_missing_files(tmp_path):
    build_scene(tmp_path / "s")
    file = tmp_path / "s" / "scene.json"
    text = file.read_text()

    def expect(fragment):
        with pytest.raises(SceneError) as info:
            Scene.load(tmp_path / "s")
        msg = str(info.value)
        assert msg.startswith(f"{file}: ") and fragment in msg and "\n" not in msg, msg

    file.write_text(text.replace('"fps":', '"fps"', 1))
    expect("not valid JSON (")
    file.write_text(text.replace('"fps": ', '"fps": NaN, "x": ', 1))
    expect("fps: NaN is not a finite number")
    file.write_text(text)
    garment = tmp_path / "s" / "sequences" / "train" / "garment.npz"
    garment.rename(garment.with_suffix(".bak"))
    expect("sequences.train is missing its file")
    garment.with_suffix(".bak").rename(garment)
    _write_garment(garment, 4)
    expect("sequences.train.frames is 3 but")
    _write_garment(garment, 3)
    np.savez(garment, positions=np.zeros((3, 5, 3)))
    expect("has no (T, Vg, 3) 'vertices' or 'vertices_q' array")
    _write_garment(garment, 3)
    shutil.rmtree(tmp_path / "s" / "sequences" / "test_run")
    expect("sequences.test_run has no folder")
    assert Scene.load(tmp_path / "s", check_files=False).sequence_names() == ["train", "test_run"]
    with pytest.raises(SceneError, match="no such file"):
        Scene.load(tmp_path / "nowhere")


def test_fps_mismatch_rejected(tmp_path):
    scene = build_scene(tmp_path / "s")
    with pytest.raises(SceneError, match="fps"):
        scene.add_sequence("other", Motion("o", ["root"], torch.zeros(2, 1, 3), torch.zeros(2, 3), 60.0), "train")
    with pytest.raises(SceneError, match="split"):
        scene.add_sequence("other", _motion("o", 2), "validation")


# ---- images on demand -------------------------------------------------------------------------------
def test_images_are_cached_and_keyed(tmp_path, gl_context, monkeypatch):
    scene = build_scene(tmp_path / "s")
    renderer = GroundTruthRenderer(gl_context)
    images = SceneImages(scene, renderer, garment_loader=_read_garment)
    rgb, labels = images.image("train", "cam00", 1)
    rgb_path, label_path = images.paths("train", "cam00", 1)
    assert rgb_path.is_file() and label_path.is_file()
    assert rgb.shape == (SIZE, SIZE, 3) and rgb.dtype == np.float32 and labels.dtype == np.uint8
    assert {1, 2} <= set(np.unique(labels).tolist())
    fresh_rgb, fresh_labels = images.render("train", "cam00", 1)
    assert np.array_equal(rgb, to_uint8(fresh_rgb).astype(np.float32) / 255.0)
    assert np.array_equal(labels, fresh_labels)

    def boom(*args, **kwargs):
        raise AssertionError("rendered although cached")

    monkeypatch.setattr(images, "render", boom)
    rgb2, labels2 = images.image("train", "cam00", 1)
    assert np.array_equal(rgb2, rgb) and np.array_equal(labels2, labels)
    monkeypatch.undo()

    # Other renderer settings -> another key; a changed garment file -> another key.
    other = GroundTruthRenderer(gl_context, supersample=1)
    assert SceneImages(scene, other).paths("train", "cam00", 1)[0] != rgb_path
    other.release()
    key = scene.cache_key("train", "cam00", renderer.settings())
    garment = scene.garment_path("train")
    _write_garment(garment, 3, sway=0.05)
    st = garment.stat()
    os.utime(garment, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    assert scene.cache_key("train", "cam00", renderer.settings()) != key
    images = SceneImages(scene, renderer, garment_loader=_read_garment)
    assert images.ensure("train", ["cam00", "held01"], [0, 1]) == 4
    assert images.ensure("train", ["cam00", "held01"], [0, 1]) == 0
    assert scene.clear_cache(stale_only=True, renderer_settings=renderer.settings()) == 1
    assert images.paths("train", "cam00", 1)[0].is_file()
    # A copied scene (new modification times) keeps its cache: keys hash the files' content.
    shutil.copytree(scene.root, tmp_path / "copy", copy_function=shutil.copy)
    copy = Scene.load(tmp_path / "copy")
    rel = images.paths("train", "held01", 0)[0].relative_to(scene.root)
    assert copy.image_path("train", "held01", 0, renderer.settings()) == tmp_path / "copy" / rel
    assert (tmp_path / "copy" / rel).is_file()
    renderer.release()


def test_palette_from_images():
    rgb = np.zeros((20, 20, 3), dtype=np.float32)
    labels = np.zeros((20, 20), dtype=np.uint8)
    rgb[2:9, 2:9], labels[2:9, 2:9] = (0.2, 0.3, 0.9), 2
    rgb[11:18, 11:18], labels[11:18, 11:18] = (0.8, 0.6, 0.5), 1
    rgb[2:9, 8] = (0.1, 0.15, 0.45)  # a darker anti-aliased edge column, removed by the erosion
    out = palette_from_images([(rgb, labels)])
    np.testing.assert_allclose(out["garment"], [0.2, 0.3, 0.9], atol=1e-6)
    np.testing.assert_allclose(out["body"], [0.8, 0.6, 0.5], atol=1e-6)
    assert "garment_layers" not in out
    # a layered garment: each layer's mean, and "garment" the mean of all its pixels
    rgb[2:9, 11:18], labels[2:9, 11:18] = (0.6, 0.3, 0.1), 3
    out = palette_from_images([(rgb, labels)])
    np.testing.assert_allclose(out["garment_layers"], [[0.2, 0.3, 0.9], [0.6, 0.3, 0.1]], atol=1e-6)
    np.testing.assert_allclose(out["garment"], [0.4, 0.3, 0.5], atol=1e-6)  # equal eroded areas


def test_contact_sheets(tmp_path, gl_context):
    grid = [[np.zeros((30, 40, 3), np.float32), np.full((30, 40), 200, np.uint8)],
            [np.ones((20, 40, 3), np.float32)]]
    sheet = contact_sheet(grid, row_titles=["a", "bb"], col_titles=["f0", "f1"], gap=2)
    assert sheet.dtype == np.uint8 and sheet.ndim == 3
    assert sheet.shape[0] > 2 * 30 + 3 * 2 and sheet.shape[1] > 2 * 40 + 3 * 2
    with pytest.raises(ValueError, match="titles"):
        contact_sheet(grid, row_titles=["a"])
    g, b = label_edges(np.pad(np.full((4, 4), 2, np.uint8), 2))
    assert g.sum() == 12 and b.sum() == 0

    scene = build_scene(tmp_path / "s")
    with GroundTruthRenderer(gl_context) as renderer:
        images = SceneImages(scene, renderer, garment_loader=_read_garment)
        sheet = scene_contact_sheet(scene, images, "train", cameras=["cam00", "held01"], frames=[0, 2],
                                    show_labels=True, cell_scale=1.0)
    assert sheet.shape[0] >= 2 * SIZE and sheet.shape[1] >= 2 * SIZE
    assert np.any(np.all(sheet == (255, 220, 0), axis=-1))  # garment borders drawn
