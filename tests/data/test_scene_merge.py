"""``import_sequence`` / ``garmentnerf data add-sequence``: a sequence simulated for one scene trains another."""

from __future__ import annotations

import filecmp

import numpy as np
import pytest
from support.scenes import build_scene

from garmentnerf.cli.main import main
from garmentnerf.data.garment_sequence import penetration_summary, recorded_penetration, save_sequence
from garmentnerf.data.scene import Scene, SceneError
from garmentnerf.data.scene_merge import import_sequence


def _same_files(a, b) -> bool:
    names = sorted(p.name for p in a.iterdir())
    return names == sorted(p.name for p in b.iterdir()) and all(filecmp.cmp(a / n, b / n, shallow=False)
                                                                 for n in names)


def test_imported_sequence_is_the_source_files_and_trains(tmp_path):
    target = build_scene(tmp_path / "target", train_frames=3)
    source = build_scene(tmp_path / "source", train_frames=5)
    before = {n: (i.frames, i.split) for n, i in target.sequences.items()}

    info = import_sequence(target, source, "train", as_name="train_more")

    loaded = Scene.load(target.root)  # checks the files against the recorded frame counts
    assert loaded.sequence_names("train") == ["train", "train_more"]
    assert {n: (i.frames, i.split) for n, i in loaded.sequences.items() if n != "train_more"} == before
    assert (info.frames, info.split, info.motion) == (5, "train", source.sequence("train").motion)
    assert loaded.sequence("train_more").extra["copied_from"].endswith(":train")
    assert loaded.simulation["train_more"] == source.simulation["train"]
    assert _same_files(loaded.sequence_dir("train_more"), source.sequence_dir("train"))
    copied, original = loaded.load_motion("train_more"), source.load_motion("train")
    np.testing.assert_array_equal(copied.rotations.numpy(), original.rotations.numpy())
    np.testing.assert_array_equal(copied.translation.numpy(), original.translation.numpy())
    assert not any(p.name.endswith(".partial") for p in (target.root / "sequences").iterdir())

    # a held-out motion can come in under another split
    import_sequence(loaded, source, "test_run", as_name="train_run", split="train")
    assert Scene.load(target.root).sequence_names("train") == ["train", "train_more", "train_run"]


def _mutate(scene: Scene, what: str) -> None:
    if what == "garment":
        scene.garment["kind"] = "tshirt"
    elif what == "shape":
        scene.body["shape"] = "thin"
    elif what == "fps":
        scene.fps = scene.fps * 2


@pytest.mark.parametrize("what, message", [("garment", "garment is a tshirt"), ("shape", "body shape"),
                                           ("fps", "fps"), ("taken", "already exists"), ("unknown", "no sequence"),
                                           ("topology", "garment mesh")])
def test_refusals_leave_the_scene_as_it_was(tmp_path, what, message):
    target = build_scene(tmp_path / "target")
    source = build_scene(tmp_path / "source")
    _mutate(source, what)
    if what == "topology":  # a garment with one face fewer
        path = source.garment_path("train")
        with np.load(path, allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
        arrays["faces"] = arrays["faces"][:-1]
        np.savez(path, **arrays)
    text = target.scene_file.read_text()
    folders = sorted(p.name for p in (target.root / "sequences").iterdir())
    name = {"taken": None, "unknown": "nope"}.get(what, "train")
    as_name = None if what == "taken" else "train_more"
    with pytest.raises(SceneError, match=message):
        import_sequence(target, source, name or "train", as_name=as_name)
    assert target.scene_file.read_text() == text
    assert sorted(p.name for p in (target.root / "sequences").iterdir()) == folders


def test_failed_save_removes_the_copied_folder(tmp_path, monkeypatch):
    target = build_scene(tmp_path / "target")
    source = build_scene(tmp_path / "source")
    text = target.scene_file.read_text()

    def refuse(*_args, **_kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(target, "save", refuse)
    with pytest.raises(OSError, match="disk full"):
        import_sequence(target, source, "train", as_name="train_more")
    assert "train_more" not in target.sequences and "train_more" not in target.simulation
    assert not (target.root / "sequences" / "train_more").exists()
    assert target.scene_file.read_text() == text


def test_cli(tmp_path, capsys):
    target = build_scene(tmp_path / "target")
    source = build_scene(tmp_path / "source", train_frames=4)
    assert main(["data", "add-sequence", str(target.root), "--from", str(source.root), "--as", "train_more"]) == 0
    assert "train_more: 4 frames (train" in capsys.readouterr().out
    assert Scene.load(target.root).sequence_names("train") == ["train", "train_more"]
    # the same name again: one line, exit 2, nothing changed
    text = target.scene_file.read_text()
    assert main(["data", "add-sequence", str(target.root), "--from", str(source.root), "--as", "train_more"]) == 2
    err = capsys.readouterr().err
    assert "already exists" in err and err.count("\n") == 1
    assert target.scene_file.read_text() == text


def test_a_scene_another_process_writes_is_refused_naming_its_pid(tmp_path, capsys):
    """add-sequence holds the receiving scene's writer lock, as data make does: while another process holds
    it, the import is refused at once in one line naming that process, and the scene is left as it was."""
    import subprocess
    import sys
    import textwrap

    from garmentnerf.folder_lock import LOCK_FILE

    target = build_scene(tmp_path / "target")
    source = build_scene(tmp_path / "source", train_frames=4)
    holder = subprocess.Popen([sys.executable, "-c", textwrap.dedent("""
        import sys, time
        from garmentnerf.folder_lock import lock_folder
        lock = lock_folder(sys.argv[1], "garmentnerf data make", what="scene")
        print("held", flush=True)
        time.sleep(600)
    """), str(target.root)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        text = target.scene_file.read_text()
        assert main(["data", "add-sequence", str(target.root), "--from", str(source.root), "--as", "train_more"]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "Traceback" not in err
        assert f"{target.root}: another process is writing this scene (PID {holder.pid}, 'garmentnerf data make')" in err
        assert target.scene_file.read_text() == text and not (target.root / "sequences" / "train_more").exists()
    finally:
        holder.kill()
        holder.wait()
    assert main(["data", "add-sequence", str(target.root), "--from", str(source.root), "--as", "train_more"]) == 0
    assert Scene.load(target.root).sequence_names("train") == ["train", "train_more"]
    assert not (target.root / LOCK_FILE).exists()  # released, and its file gone
    # a folder without a scene is refused as such, and the lock makes no folder for it
    assert main(["data", "add-sequence", str(tmp_path / "typo"), "--from", str(source.root)]) == 2
    assert "typo" in capsys.readouterr().err and not (tmp_path / "typo").exists()


def test_penetration_summary_counts_the_frames_over_the_bound():
    assert penetration_summary(np.array([0.0, 0.004, 0.0099]), 0.010) == "max penetration 9.9 mm"
    line = penetration_summary(np.array([0.0, 0.02, 0.005, 0.0931, 0.011]), 0.010)
    assert line == ("max penetration 93.1 mm, 3 of 5 frames over the 10 mm bound, the first at frame 1 "
                    "(cloth through the body)")


def test_cli_reports_the_imported_sequences_penetration(tmp_path, capsys):
    target = build_scene(tmp_path / "target")
    source = build_scene(tmp_path / "source", train_frames=4)
    path = source.garment_path("train")
    with np.load(path) as plain:  # the support scene's plain vertices/faces file, which records no penetration
        vertices, faces = plain["vertices"], plain["faces"]
    save_sequence(path, vertices, faces, color=(0.2, 0.4, 0.8), kind="skirt", fps=source.fps,
                  penetration_max_m=np.array([0.001, 0.002, 0.030, 0.004], np.float32))
    assert recorded_penetration(path)[2] == np.float32(0.030)
    assert main(["data", "add-sequence", str(target.root), "--from", str(source.root), "--as", "train_more"]) == 0
    out = capsys.readouterr().out
    assert "max penetration 30.0 mm, 1 of 4 frames over the 10 mm bound, the first at frame 2" in out
