"""garment_reach (garmentnerf.model.garment_reach) and ``garmentnerf data reach``, against numpy and
trimesh on a scene whose garment is moved by a known amount."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch
import trimesh

from garmentnerf.cli.main import main
from garmentnerf.data.garment_sequence import load_sequence, save_sequence
from garmentnerf.data.scene import Scene
from garmentnerf.model.garment_reach import box_excess, garment_reach

SHIFT = 0.5  # metres: frame 1's skirt moved sideways, far out of the box


def test_box_excess_is_the_padding_that_takes_a_point_in():
    box = torch.tensor([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]])
    points = torch.tensor([[0.5, 1.0, 1.0], [1.2, 1.0, 1.0], [-0.1, 2.5, 1.0], [1.0, 2.0, 3.0], [2.0, -3.0, 4.0]])
    expected = np.array([0.0, 0.2, 0.5, 0.0, 3.0])  # the largest axis excess of each point
    np.testing.assert_allclose(box_excess(points, box).numpy(), expected, atol=1e-6)


@pytest.fixture(scope="module")
def shifted_scene(tmp_path_factory):
    from garmentnerf.data.synthetic import make_rigged_scene

    root = tmp_path_factory.mktemp("reach")
    rigged = make_rigged_scene(root / "rigged", motion="walk", frames=3, views=1, size=16, held_out_views=0,
                               palette="none")
    shutil.copytree(rigged.root, root / "shifted")
    scene = Scene.load(root / "shifted")
    seq = load_sequence(scene.garment_path("train"))
    vertices = np.array(seq.vertices, dtype=np.float32)
    vertices[1, :, 0] += SHIFT
    save_sequence(scene.garment_path("train"), vertices, seq.faces, color=seq.color, kind=seq.kind,
                  penetration_max_m=seq.penetration_max_m, fps=seq.fps, settings=seq.settings, name=seq.name,
                  motion=seq.motion, betas=seq.betas, uv=seq.uv)
    return scene, vertices


def test_reach_against_numpy_and_trimesh(shifted_scene, body, projector):
    scene, garment = shifted_scene
    padding, width = 0.05, 0.15
    (r,) = garment_reach(scene, body, padding, width, projector=projector)
    posed = scene.load_motion("train").pose(body, body.betas("average")).vertices.detach().double().numpy()
    assert r.frames == 3

    # The box: numpy per frame, the largest axis excess over the padded body box.
    excess, share = [], []
    for f in range(3):
        lo, hi = posed[f].min(axis=0) - padding, posed[f].max(axis=0) + padding
        e = np.maximum(lo - garment[f], garment[f] - hi).clip(min=0).max(axis=1)
        excess.append(e.max())
        share.append((e > 0).mean())
    assert excess[1] > 0.2 and r.worst_outside_frame == 1
    assert r.frames_outside_box == sum(e > 0 for e in excess)
    assert r.farthest_outside_m == pytest.approx(max(excess), abs=1e-5)
    assert r.worst_outside_share == pytest.approx(max(share), abs=1e-6)

    # The heights: trimesh's distance to the posed skin for the shifted frame, whose skirt hangs in the
    # air beside the body (every vertex outside: the signed height is the plain distance).
    skin = trimesh.Trimesh(posed[1], projector.faces.numpy(), process=False)
    _, distance, _ = trimesh.proximity.closest_point(skin, garment[1].astype(np.float64))
    assert r.h_max_frame == 1
    assert r.h_max_m == pytest.approx(distance.max(), abs=1e-5)
    beyond_1 = (distance > width).mean()
    assert beyond_1 > 0.5  # moved half a metre out: most of it is beyond the prior's zero
    assert r.worst_beyond_prior_zero_share >= beyond_1 - 1e-3 and r.worst_beyond_prior_zero_frame == 1


def test_cli_prints_writes_json_and_refuses_bad_flags(shifted_scene, tmp_path, capsys):
    scene, _ = shifted_scene
    out = tmp_path / "reach.json"
    assert main(["data", "reach", str(scene.root), "--padding", "0.05", "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "outside the body box + 0.05 m" in printed and "beyond the prior's zero (0.15 m)" in printed
    (data,) = json.loads(out.read_text())
    assert data["sequence"] == "train" and data["worst_outside_frame"] == 1
    assert main(["data", "reach", str(scene.root), "--json", str(out)]) == 2  # exists, no --overwrite
    assert "already exists" in capsys.readouterr().err
    assert main(["data", "reach", str(scene.root), "--prior-width", "0"]) == 2
    assert "--prior-width" in capsys.readouterr().err
    assert main(["data", "reach", str(scene.root), "--sequence", "nope"]) == 2
