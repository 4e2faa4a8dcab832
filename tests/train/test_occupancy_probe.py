"""The sequence occupancy probe (``garmentnerf bench --run DIR --occupancy STEPS``): its density learns the
tiny scene's garment, its figures against the package's own occupancy functions, its flags."""

from __future__ import annotations

import json

import pytest
import torch

from garmentnerf.cli.main import main
from garmentnerf.perf.occupancy_probe import far_recall, occupancy_probe

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def probe_run(tiny_scene, tmp_path_factory):
    from garmentnerf.train.settings import tiny_config

    out = tmp_path_factory.mktemp("occupancy_probe") / "run"
    config = out.parent / "fast.json"
    config.write_text(json.dumps(tiny_config().replace(lr=1e-2, lr_final=5e-3).to_dict()))
    assert main(["train", "--scene", str(tiny_scene.root), "--out", str(out), "--model-config", str(config),
                 "--perceptual", "none", "--no-progress", "--threads", "1", "--iterations", "1",
                 "--generator-iterations", "1", "--image-every", "0"]) == 0
    return out


def test_far_recall_counts_the_far_cloth_the_density_holds():
    sigma = torch.tensor([100.0, 0.0, 100.0, 100.0])
    distance = torch.tensor([0.0, 0.01, 0.2, 0.0])
    height = torch.tensor([0.3, 0.3, 0.3, 0.05])  # the last is near cloth, the third not cloth
    assert far_recall(sigma, distance, height, 0.015, 0.15, 0.025) == pytest.approx(0.5)
    assert far_recall(sigma, distance, height, 0.015, 0.5, 0.025) is None


def test_probe_density_learns_the_garment_and_leaves_the_run_alone(probe_run):
    before = {p: p.read_bytes() for p in probe_run.rglob("*") if p.is_file()}
    lines = []
    results = occupancy_probe(probe_run, steps=20, eval_every=10, log=lines.append)
    assert [r["step"] for r in results["rows"]] == [0, 10, 20] and len(lines) == 3
    first, last = results["rows"][0], results["rows"][-1]
    assert first["s_per_step"] is None and last["s_per_step"] > 0
    assert 0.0 <= first["train_iou"] <= 1.0 and last["train_iou"] > first["train_iou"] + 0.1, results["rows"]
    assert results["heldout_frames"] == [] and last["heldout_iou"] is None  # the tiny scene has no held-out motion
    assert len(results["eval_frames"]) == 3  # all three training frames
    assert {p: p.read_bytes() for p in probe_run.rglob("*") if p.is_file()} == before


def test_cli_writes_json_and_refuses_bad_flags(probe_run, tmp_path, capsys):
    out = tmp_path / "probe.json"
    assert main(["bench", "--run", str(probe_run), "--occupancy", "4", "--eval-every", "2", "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    rows = json.loads(out.read_text())["rows"]
    assert [r["step"] for r in rows] == [0, 2, 4] and "training frames IoU" in printed
    for flags, message in ((["--occupancy", "0"], "--occupancy and --eval-every must be at least 1"),
                           (["--occupancy", "3", "--training"], "--occupancy needs --run"),
                           (["--occupancy", "3", "--json", str(out)], "exists")):
        assert main(["bench", "--run", str(probe_run), *flags]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and message in err[0], err
    assert main(["bench", "--occupancy", "3"]) == 2
    assert "--occupancy needs --run" in capsys.readouterr().err
