"""``garmentnerf bake``: a real one-frame bake of the bundled skirt that resumes, rebuilds a damaged frame with a
notice, and refuses bad input in one line (exit 2) before overwriting anything. The bakes take a minute: slow."""

from __future__ import annotations

import json

import numpy as np
import pytest

from garmentnerf.cli.main import main


def _bake(out, *extra) -> int:
    return main(["bake", "--demo", "skirt", "--frames", "3", "--preset", "draft", "--workers", "1", "--no-progress",
                 "--out", str(out), *extra])


@pytest.fixture(scope="module")
def one_frame(tmp_path_factory):
    out = tmp_path_factory.mktemp("bake") / "skirt"
    assert _bake(out) == 0
    return out


@pytest.mark.slow
def test_a_bake_folder_holds_the_frame_its_manifest_and_the_body(one_frame):
    from garmentnerf.bake.store import BakeFolder

    folder = BakeFolder.open(one_frame)
    assert folder.baked_frames() == {3} and folder.num_frames == 170
    baked = folder.load_frame(3)
    assert len(baked.views) == 8  # the draft preset's ring
    faces = folder.body_faces()
    assert baked.body_vertices.shape[1] == 3 and faces.max() == len(baked.body_vertices) - 1
    manifest = json.loads((one_frame / "bake.json").read_text())
    assert manifest["capture"] == {"views": 8, "quality": 0.5, "preset": "full"} and len(manifest["palette"]) == 2


@pytest.mark.slow
def test_baking_again_makes_nothing_and_a_damaged_frame_is_baked_again(one_frame, capfd):
    path = one_frame / "frames" / "00003.npz"
    before = path.read_bytes()
    assert _bake(one_frame) == 0
    out, err = capfd.readouterr()
    assert "1 of 1 frames of train already baked" in err and "nothing to do" in out
    path.write_bytes(before[:200])
    assert _bake(one_frame) == 0
    out, err = capfd.readouterr()
    assert "not a readable bake frame" in err and "baking it again" in err
    from garmentnerf.bake.store import read_frame_file

    again = read_frame_file(path, 3)
    first = read_frame_file_from_bytes(before, path.parent / "first.npz")
    assert np.array_equal(again.views[0].codes, first.views[0].codes)  # the same frame, made again


def read_frame_file_from_bytes(data: bytes, path):
    from garmentnerf.bake.store import read_frame_file

    path.write_bytes(data)
    try:
        return read_frame_file(path, 3)
    finally:
        path.unlink()


@pytest.mark.slow
def test_a_bake_of_other_settings_is_refused_unless_overwritten(one_frame, capfd):
    manifest = (one_frame / "bake.json").read_bytes()
    assert main(["bake", "--demo", "skirt", "--frames", "3", "--preset", "balanced", "--out", str(one_frame),
                 "--no-progress"]) == 2
    err = capfd.readouterr().err.strip()
    assert err.count("\n") == 0 and "other bake settings" in err and "--overwrite" in err
    assert (one_frame / "bake.json").read_bytes() == manifest and (one_frame / "frames" / "00003.npz").is_file()


@pytest.mark.parametrize("args, message", [
    pytest.param(["--frames", "400:420"], "400:420", marks=pytest.mark.slow),  # after the model loads
    (["--preset", "huge"], "invalid choice"),
    (["--workers", "0"], "--workers must be in 1..64"),
])
def test_bad_bake_arguments_are_refused_in_one_line(tmp_path, capfd, args, message):
    out = tmp_path / "b"
    code = None
    try:
        code = main(["bake", "--demo", "skirt", "--out", str(out), "--no-progress", *args])
    except SystemExit as exc:  # argparse's own refusals exit 2 too
        code = exc.code
    err = capfd.readouterr().err.strip().splitlines()
    assert code == 2 and message in err[-1] and "Traceback" not in "\n".join(err)
    assert not (out / "bake.json").exists()


@pytest.mark.slow
def test_a_folder_of_other_files_is_not_baked_into(tmp_path, capfd):
    (tmp_path / "notes.txt").write_text("mine")
    assert _bake(tmp_path) == 2
    err = capfd.readouterr().err.strip()
    assert "not empty and not a bake folder" in err and (tmp_path / "notes.txt").read_text() == "mine"
