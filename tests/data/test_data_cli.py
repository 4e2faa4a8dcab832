"""``garmentnerf data info|render|preview`` on a small scene written by the test."""

from __future__ import annotations

import json

import imageio.v3 as iio
import numpy as np
from support.scenes import build_scene

from garmentnerf.cli.main import main
from garmentnerf.data.scene import Scene
from garmentnerf.data.scene_images import SceneImages


def test_info_render_preview(tmp_path, capsys):
    scene = build_scene(tmp_path / "scene")
    assert main(["data", "info", str(scene.root), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["sequences"]["train"]["frames"] == 3 and info["sequences"]["test_run"]["split"] == "unseen_motion"
    assert info["cameras"]["reference"] == ["ref_front", "ref_back"]

    assert main(["data", "render", str(scene.root), "--split", "reference", "--sequence", "train"]) == 0
    out = capsys.readouterr().out
    assert "6 images rendered" in out
    assert main(["data", "render", str(scene.root), "--split", "reference", "--sequence", "train"]) == 0
    assert "0 images rendered, 6 already cached" in capsys.readouterr().out
    # the cached image is the renderer's image of that frame
    loaded = Scene.load(scene.root)
    with SceneImages(loaded, use_cache=False) as images:
        rgb, labels = images.render("train", "ref_back", 2)
    cached = iio.imread(loaded.image_path("train", "ref_back", 2))
    np.testing.assert_array_equal(cached, np.round(np.clip(rgb, 0, 1) * 255).astype(np.uint8))
    assert (labels == 2).sum() > 0 and (labels == 1).sum() > 0

    sheet = tmp_path / "sheet.png"
    assert main(["data", "preview", str(scene.root), "--out", str(sheet)]) == 0
    image = iio.imread(sheet)
    assert image.ndim == 3 and image.shape[0] > 48 and image.std() > 5


def test_unknown_sequence_and_missing_scene_are_one_line_errors(tmp_path, capsys):
    scene = build_scene(tmp_path / "scene")
    assert main(["data", "render", str(scene.root), "--sequence", "nope"]) == 2
    err = capsys.readouterr().err
    assert "nope" in err and err.count("\n") == 1
    assert main(["data", "info", str(tmp_path / "missing")]) == 2
    err = capsys.readouterr().err
    assert "missing" in err and err.count("\n") == 1
