"""``state_ambiguity``: matched-pose garment distances, on scenes whose answer is known."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from garmentnerf.body.model import BodyModel
from garmentnerf.cli.main import main
from garmentnerf.data.garment_sequence import load_sequence, save_sequence
from garmentnerf.data.state_ambiguity import kabsch_to, state_ambiguity
from garmentnerf.data.synthetic import make_rigged_scene


def test_kabsch_recovers_a_rigid_motion():
    rng = np.random.default_rng(3)
    reference = rng.normal(size=(50, 3))
    reference -= reference.mean(axis=0)
    truth = Rotation.from_rotvec([0.3, -1.1, 0.5]).as_matrix()
    moved = reference @ truth + np.array([0.4, -2.0, 1.5])  # rows rotated by truth.T, then shifted
    rotation, centre = kabsch_to(moved, reference)
    np.testing.assert_allclose((moved - centre) @ rotation.T, reference, atol=1e-10)
    np.testing.assert_allclose(rotation, truth, atol=1e-10)


@pytest.fixture(scope="module")
def rigged(tmp_path_factory):
    """A walk whose skirt is rigidly skinned to the body: the garment IS a function of the pose."""
    return make_rigged_scene(tmp_path_factory.mktemp("rigged"), motion="walk,walk,walk", frames=80, views=2, size=16,
                             held_out_views=0, palette="none")


def test_a_skinned_garment_follows_its_pose(rigged):
    body = BodyModel.default()
    report = state_ambiguity(rigged, body)
    assert report.frames == 80 - 24
    # the walk cycle repeats, so every frame finds a close pose; a skinned skirt then sits as close
    matched = report.matched_garment_rms_m["pose"]
    assert report.matched_descriptor_rms_m["pose"] < 0.03
    assert matched < 1.5 * report.matched_descriptor_rms_m["pose"] + 1e-3
    assert report.random_garment_rms_m > 3 * matched


def test_a_garment_that_varies_apart_from_the_pose_is_measured(rigged, tmp_path):
    """The same scene with every frame's skirt shifted by a known, pose-independent offset: the
    matched garments are then about as far apart as the offsets of the matched frames."""
    import shutil

    from garmentnerf.data.scene import Scene

    root = tmp_path / "shifted"
    shutil.copytree(rigged.root, root)
    scene = Scene.load(root)
    seq = load_sequence(scene.garment_path("train"))
    frames = seq.vertices.shape[0]
    offsets = np.zeros((frames, 3), np.float32)
    offsets[::2, 0] = 0.10  # even frames 10 cm to the side: half the matched pairs differ by 10 cm
    save_sequence(scene.garment_path("train"), seq.vertices + offsets[:, None, :], seq.faces, color=seq.color,
                  kind=seq.kind, penetration_max_m=seq.penetration_max_m, fps=seq.fps, settings=seq.settings,
                  name=seq.name, motion=seq.motion, betas=seq.betas, uv=seq.uv)
    body = BodyModel.default()
    plain = state_ambiguity(rigged, body)
    shifted = state_ambiguity(scene, body)
    assert shifted.matched_descriptor_rms_m == plain.matched_descriptor_rms_m  # the bodies did not move
    assert shifted.matched_garment_rms_m["pose"] > plain.matched_garment_rms_m["pose"] + 0.02


def test_cli_prints_and_writes_json(rigged, tmp_path, capsys):
    out = tmp_path / "a.json"
    assert main(["data", "ambiguity", str(rigged.root), "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "pose+velocity" in printed and "random other frame" in printed
    data = json.loads(out.read_text())
    assert data["frames"] == 56 and set(data["matched_garment_rms_m"]) == {"pose", "pose+velocity",
                                                                             "pose+velocity+history"}
    assert main(["data", "ambiguity", str(rigged.root), "--json", str(out)]) == 2  # exists, no --overwrite
    assert "already exists" in capsys.readouterr().err
    assert main(["data", "ambiguity", str(rigged.root), "--min-gap", "0"]) == 2
