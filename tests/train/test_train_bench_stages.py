"""``garmentnerf bench --run DIR --training``: the step by stage, and ``--before``, the step as it
was before issue 27 (geometry rebuilt every step, the perceptual target backpropagated) taking
turns with today's."""

from __future__ import annotations

import json

import pytest

from garmentnerf.cli.main import main
from garmentnerf.eval.perceptual import stlpips_available
from garmentnerf.perf.train_bench import STAGES

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def tiny_run(tiny_scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("train_bench_stages") / "run"
    assert main(["train", "--scene", str(tiny_scene.root), "--out", str(out), "--preset", "tiny", "--perceptual",
                 "none", "--no-progress", "--threads", "1", "--iterations", "2", "--generator-iterations", "1",
                 "--image-every", "0"]) == 0
    return out


def test_training_bench_splits_the_step_by_stage_beside_the_step_before(tiny_run, tmp_path, capsys):
    if not stlpips_available("alex")[0]:
        pytest.skip("the bench trains with the shift-tolerant LPIPS loss, not installed")
    out = tmp_path / "train_bench.json"
    assert main(["bench", "--run", str(tiny_run), "--training", "--precisions", "float32", "--steps", "5",
                 "--rounds", "2", "--before", "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    results = json.loads(out.read_text())
    assert results["stages"] == list(STAGES)
    now, = results["precisions"]
    before, = results["before"]
    assert now["precision"] == before["precision"] == "float32"
    for row in (now, before):
        assert len(row["stages_s_all"]) == len(row["s_per_step_all"]) == results["steps_timed"] == 6
        for step_s, stages in zip(row["s_per_step_all"], row["stages_s_all"]):
            # the stages partition the step (the step is timed from the callbacks, the stages inside)
            assert sum(stages.values()) == pytest.approx(step_s, abs=2e-3)
            assert all(stages[k] > 0 for k in ("encoders", "projection", "mlp", "decoder", "perceptual",
                                               "perceptual_backward", "backward_other", "optimizer"))
            assert all(v >= 0 for v in stages.values()), stages
    # 3 frames: from the second round on every frame's geometry is kept, while before it is rebuilt
    assert max(s["surface"] for s in now["stages_s_all"][3:]) < 0.1 * before["stages_s"]["surface"]
    assert results["speedup_vs_before"]["float32"] == pytest.approx(before["s_per_step"] / now["s_per_step"])
    for stage in STAGES:
        assert f"  {stage:22s} {now['stages_s'][stage]:16.3f} {before['stages_s'][stage]:16.3f}" in printed
    assert f"  {'float32':10s} {results['speedup_vs_before']['float32']:5.2f}x faster than before" in printed
