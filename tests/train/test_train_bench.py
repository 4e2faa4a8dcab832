"""``garmentnerf bench --run DIR --training``: seconds per NeRF step per MLP precision, side by side;
the step by stage, and other runs' recipes taking turns with it."""

from __future__ import annotations

import json
import statistics
import tempfile
from pathlib import Path

import pytest

from garmentnerf.cli.main import main
from garmentnerf.model.perceptual import stlpips_available
from garmentnerf.perf.train_bench import STAGES

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def tiny_run(tiny_scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("train_bench") / "run"
    assert main(["train", "--scene", str(tiny_scene.root), "--out", str(out), "--preset", "tiny", "--perceptual",
                 "none", "--no-progress", "--threads", "1", "--iterations", "2", "--generator-iterations", "1",
                 "--image-every", "0"]) == 0
    return out


def test_training_bench_times_each_precision_and_leaves_nothing_behind(tiny_run, tmp_path, capsys):
    before = {p: p.read_bytes() for p in tiny_run.rglob("*") if p.is_file()}
    temporaries = set(Path(tempfile.gettempdir()).glob("garmentnerf-train-bench-*"))
    out = tmp_path / "train_bench.json"
    assert main(["bench", "--run", str(tiny_run), "--training", "--steps", "4", "--rounds", "2",
                 "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    results = json.loads(out.read_text())
    assert [row["precision"] for row in results["precisions"]] == ["float32", "bfloat16"]
    # 4 steps a round: 3 intervals, the last (it writes the round's checkpoint) left out; 2 rounds
    assert results["steps_timed"] == 4
    for row in results["precisions"]:
        assert len(row["s_per_step_all"]) == 4 and all(t > 0 for t in row["s_per_step_all"])
        assert row["s_per_step"] == pytest.approx(statistics.median(row["s_per_step_all"]))
        assert f"{row['precision']:10s} {row['s_per_step']:7.3f} s/step" in printed
    speedup = results["speedup_vs_first"]
    assert speedup["float32"] == 1.0
    assert speedup["bfloat16"] == pytest.approx(results["precisions"][0]["s_per_step"]
                                                / results["precisions"][1]["s_per_step"])
    # the run is untouched and the trainers' folders are gone
    assert {p: p.read_bytes() for p in tiny_run.rglob("*") if p.is_file()} == before
    assert set(Path(tempfile.gettempdir()).glob("garmentnerf-train-bench-*")) == temporaries


@pytest.mark.parametrize("flags, message", [
    (["--training"], "--training needs --run"),
    (["--training", "--run", "RUN", "--precisions", "float16"], "--precisions float16: each must be one of"),
    (["--training", "--run", "RUN", "--steps", "2"], "--steps must be >= 3"),
    (["--training", "--run", "RUN", "--against", "nowhere"], "--against nowhere: not a run folder"),
    (["--against", "RUN"], "--against needs --run"),
    (["--run", "RUN", "--against", "nowhere"], "--against nowhere: not a run folder"),
])
def test_training_bench_refuses_bad_flags_in_one_line(tiny_run, capsys, flags, message):
    flags = [str(tiny_run) if f == "RUN" else f for f in flags]
    assert main(["bench", *flags]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], lines


def test_training_bench_splits_the_step_by_stage(tiny_run, tmp_path, capsys):
    if not stlpips_available("alex")[0]:
        pytest.skip("the bench trains with the shift-tolerant LPIPS loss, not installed")
    out = tmp_path / "train_bench.json"
    assert main(["bench", "--run", str(tiny_run), "--training", "--precisions", "float32", "--steps", "5",
                 "--rounds", "2", "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    results = json.loads(out.read_text())
    assert results["stages"] == list(STAGES)
    now, = results["precisions"]
    assert now["precision"] == "float32"
    assert len(now["stages_s_all"]) == len(now["s_per_step_all"]) == results["steps_timed"] == 6
    for step_s, stages in zip(now["s_per_step_all"], now["stages_s_all"]):
        # the stages partition the step (the step is timed from the callbacks, the stages inside)
        assert sum(stages.values()) == pytest.approx(step_s, abs=2e-3)
        assert all(stages[k] > 0 for k in ("encoders", "projection", "mlp", "decoder", "perceptual",
                                           "perceptual_backward", "backward_other", "optimizer"))
        assert all(v >= 0 for v in stages.values()), stages
    assert results["frames_cached"] is True
    for stage in STAGES:
        assert f"  {stage:22s} {now['stages_s'][stage]:16.3f}" in printed


def test_training_bench_cold_builds_each_frame_in_its_first_step(tiny_run, tmp_path, capsys):
    """``--cold``: a step meeting a frame for the first time binds its body (3 frames, so the first
    round's steps do), as the warm default's steps never do."""
    out = tmp_path / "cold.json"
    assert main(["bench", "--run", str(tiny_run), "--training", "--precisions", "float32", "--steps", "5",
                 "--rounds", "1", "--cold", "--json", str(out)]) == 0
    assert "frames prepared in the step (--cold)" in capsys.readouterr().out
    results = json.loads(out.read_text())
    assert results["frames_cached"] is False
    surface = [s["surface"] for s in results["precisions"][0]["stages_s_all"]]
    assert max(surface) > 1e-3 and min(surface) < 0.1 * max(surface)  # built on a first visit, kept after


def test_training_bench_times_another_recipe_in_turn(tiny_run, tiny_scene, tmp_path, capsys):
    from garmentnerf.model.config import ModelConfig

    heavy = tmp_path / "heavy"
    config = tmp_path / "heavy.json"
    cfg = ModelConfig.tiny()
    config.write_text(json.dumps(cfg.updated({"sampler.samples_per_ray": 16 * cfg.sampler.samples_per_ray}).to_dict()))
    assert main(["train", "--scene", str(tiny_scene.root), "--out", str(heavy), "--model-config", str(config),
                 "--perceptual", "none", "--no-progress", "--threads", "1", "--iterations", "2",
                 "--generator-iterations", "1", "--image-every", "0"]) == 0
    out = tmp_path / "against.json"
    assert main(["bench", "--run", str(tiny_run), "--training", "--precisions", "float32", "--steps", "5",
                 "--rounds", "2", "--against", str(heavy), "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    results = json.loads(out.read_text())
    light, = results["precisions"]
    against, = results["against"]
    assert against["run"] == str(heavy)
    heavy_row, = against["precisions"]
    assert len(heavy_row["s_per_step_all"]) == len(light["s_per_step_all"]) == results["steps_timed"] == 6
    # Sixteen times the samples per ray: the per-sample stages (together: each alone is a millisecond
    # or two on the tiny model, within a loaded machine's noise) take several times as long.
    per_sample = ("projection", "features", "mlp", "compositing")
    assert sum(heavy_row["stages_s"][k] for k in per_sample) > 3.0 * sum(light["stages_s"][k] for k in per_sample)
    ratio = results["speedup_vs_against"][str(heavy)]["float32"]
    assert ratio == pytest.approx(heavy_row["s_per_step"] / light["s_per_step"]) and ratio > 1.0
    assert f"{ratio:5.2f}x faster than {heavy}'s recipe" in printed
