"""A scene given for a run (``eval --scene``, ``train --resume --scene``) must fit the run: the same garment
kind (the check ``data add-sequence`` makes) and palette size; one that does not is refused in one line
before any work, and the run is left as it was."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import pytest

from garmentnerf.cli.main import main

FAST = ["--preset", "tiny", "--perceptual", "none", "--no-progress", "--threads", "1", "--image-every", "0"]


def _digest(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def trained(tiny_scene, tmp_path_factory):
    """A skirt run stopped after its first checkpoint, and copies of its scene dressed otherwise."""
    root = tmp_path_factory.mktemp("fit")
    run = root / "run"
    assert main(["train", "--scene", str(tiny_scene.root), "--out", str(run), *FAST, "--iterations", "3",
                 "--generator-iterations", "1", "--frames", "0:2", "--stop-after", "1"]) == 0
    scenes = {}
    for name, change in (("tshirt", {"kind": "tshirt"}), ("layered", None)):
        copy = root / name
        shutil.copytree(tiny_scene.root, copy)
        meta = json.loads((copy / "scene.json").read_text())
        if change:
            meta["garment"].update(change)
        else:  # the same skirt as a garment of two layers: a palette of three colours
            meta["palette_init"]["garment_layers"] = [meta["palette_init"]["garment"]] * 2
        (copy / "scene.json").write_text(json.dumps(meta))
        scenes[name] = copy
    return run, scenes


@pytest.mark.parametrize("scene, message", [
    ("tshirt", "its garment is a tshirt, the run's a skirt"),
    ("layered", "its palette has 3 colours, the run's model 2"),
])
@pytest.mark.parametrize("command", ["eval", "train"])
def test_a_scene_that_does_not_fit_the_run_is_refused(trained, capfd, scene, message, command):
    run, scenes = trained
    argv = (["eval", "--run", str(run), "--split", "seen", "--scene", str(scenes[scene])] if command == "eval" else
            ["train", "--out", str(run), "--resume", "--scene", str(scenes[scene]), "--no-progress", "--threads", "1"])
    before = _digest(run)
    capfd.readouterr()
    assert main(argv) == 2
    lines = [line for line in capfd.readouterr().err.splitlines() if line.strip()]
    assert len(lines) == 1 and f"--scene {scenes[scene]}: cannot stand for the scene" in lines[0], lines
    assert message in lines[0], lines
    assert _digest(run) == before


def test_the_runs_garment_is_recorded_and_its_own_scene_fits(trained, tiny_scene):
    from garmentnerf.runs import load_run

    run, _ = trained
    info = json.loads((run / "run.json").read_text())
    assert info["garment"]["kind"] == "skirt"
    copy = run.parent / "moved_scene"
    shutil.copytree(tiny_scene.root, copy)  # the same scene elsewhere stands for it
    assert load_run(run, scene=copy).scene.garment["kind"] == "skirt"
