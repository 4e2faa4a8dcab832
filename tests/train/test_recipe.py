"""``garmentnerf train --recipe``: a recipe's stages run in order into one folder, resume after a kill, and
record what ran; bad recipes and flags are one line and exit 2; the shipped demos' recipes are valid and
end in their bundled model's config. Training on the tiny rigged scene (``tests/conftest.py``)."""

from __future__ import annotations

import dataclasses
import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

from garmentnerf.cli.main import main
from garmentnerf.demos import demo
from garmentnerf.model.config import ModelConfig
from garmentnerf.runs import load_run
from garmentnerf.train.checkpoints import latest_checkpoint
from garmentnerf.train.recipe import RecipeError, parse_recipe, read_recipe, recipe_model_config, stage_model_configs
from garmentnerf.train.recipe_run import check_scenes, run_recipe

#: The tiny recipe: stage a trains every weight, a fit of its body appearance, stage b starts from a's
#: weights and trains the decoder alone, composed with the fitted body.
TINY = {"format": "garmentnerf-recipe", "version": 1, "name": "tiny", "description": "two tiny stages and a fit",
        "stages": [
            {"name": "a", "kind": "train", "model": "tiny", "iterations": 4, "generator_iterations": 1,
             "ckpt_every": 2},
            {"name": "fit", "kind": "fit_body_appearance", "iterations": 20, "frame_stride": 2},
            {"name": "b", "kind": "train", "model": "previous", "config": {"schedule.trained_parameters": ["decoder."]},
             "iterations": 40, "init": "previous", "body_appearance": "fit", "ckpt_every": 4}]}
#: What every run here passes besides the recipe.
FAST = ["--perceptual", "none", "--no-progress", "--threads", "1", "--image-every", "0"]
DEMO_FOLDERS = {"skirt": "run", "tshirt": "run_tshirt", "dress": "run_dress"}


def write_recipe(path: Path, recipe: dict) -> Path:
    path.write_text(json.dumps(recipe, indent=1))
    return path


def recipe_argv(recipe_file, out, scene=None, *extra) -> list[str]:
    scene_args = [] if scene is None else ["--scene", str(scene)]
    return ["train", "--recipe", str(recipe_file), *scene_args, "--out", str(out), *FAST, *extra]


def weights(path) -> dict[str, torch.Tensor]:
    return load_file(str(path))


def mtimes(folder: Path) -> dict[Path, int]:
    return {p: p.stat().st_mtime_ns for p in folder.rglob("*") if p.is_file()}


def one_error_line(capsys) -> str:
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in lines[0], lines
    return lines[0]


@pytest.fixture(scope="module")
def finished_recipe(tiny_scene, tmp_path_factory):
    """The tiny recipe run uninterrupted through the CLI: (recipe file, its folder R, stderr)."""
    threads = torch.get_num_threads()
    root = tmp_path_factory.mktemp("recipe")
    recipe_file = write_recipe(root / "tiny.json", TINY)
    out = root / "R"
    capture = root / "stderr.txt"
    try:
        # the trainer's lines go to stderr through tqdm: capture them by running main with stderr redirected
        with open(capture, "w") as err:
            saved, sys.stderr = sys.stderr, err
            try:
                status = main(recipe_argv(recipe_file, out, tiny_scene.root))
            finally:
                sys.stderr = saved
    finally:
        torch.set_num_threads(threads)
    assert status == 0, capture.read_text()
    return recipe_file, out, capture.read_text()


# ---------------------------------------------------------------------------------------- running
def test_a_recipe_runs_its_stages_into_one_run_folder(finished_recipe, tiny_scene):
    """Every stage ran in order into stages/<NN>-<name>; R is a loadable run (the last stage's, with the
    fitted body appearance); stage b started from a's weights and held all but the decoder to the bit;
    the log records each stage."""
    _, out, err = finished_recipe
    assert "recipe tiny: stage 1/3 a (train" in err and "stage 2/3 fit (body appearance fit of a's run" in err
    assert "stage 3/3 b (train, 40 NeRF steps, from a's weights" in err
    stages = out / "stages"
    assert sorted(p.name for p in stages.iterdir()) == ["01-a", "02-fit", "03-b"]
    run = load_run(out)
    assert run.step == 50 + 40 and run.body_appearance is not None  # b: the tiny config's 50 G_img steps skipped
    assert run.scene is not None and Path(run.scene.root).samefile(tiny_scene.root)
    assert run.info["recipe"] == {"name": "tiny", "stage": "b"}
    assert run.info["model_config"]["schedule"]["trained_parameters"] == ["decoder."]
    final, first = weights(out / "model.safetensors"), weights(stages / "01-a" / "model.safetensors")
    assert final.keys() == first.keys()
    changed = [k for k in final if not torch.equal(final[k], first[k])]
    assert changed and all(k.startswith("decoder.") for k in changed), changed
    assert (out / "model.safetensors").read_bytes() == (stages / "03-b" / "model.safetensors").read_bytes()
    published, fitted = (weights(folder / "body_appearance.safetensors") for folder in (out, stages / "02-fit"))
    assert published.keys() == fitted.keys() and all(torch.equal(published[k], fitted[k]) for k in fitted)
    b_train = json.loads((stages / "03-b" / "run.json").read_text())["train"]
    assert Path(b_train["init_weights"]) == (stages / "01-a" / "model.safetensors").resolve()
    log = json.loads((out / "recipe_log.json").read_text())
    assert [(s["name"], s["kind"], s["folder"]) for s in log["stages"]] == [
        ("a", "train", "stages/01-a"), ("fit", "fit_body_appearance", "stages/02-fit"), ("b", "train", "stages/03-b")]
    for record in log["stages"]:
        assert record["started"] and record["finished"] and record["cpu_minutes"] > 0, record
        assert record["step"] == record["end_step"] and len(record["sittings"]) == 1, record
    assert [s["steps"] for s in log["stages"]] == [5, 20, 40]
    assert log["stages"][2]["sittings"][0]["from_step"] == 50
    assert log["published"]["stage"] == "b"
    assert json.loads((out / "recipe.json").read_text())["stages"][2]["config"] == {"schedule.trained_parameters": ["decoder."]}


def test_a_killed_recipe_resumes_where_it_stopped(finished_recipe, tiny_scene, tmp_path, capsys):
    """SIGKILL once stage b has a checkpoint; --resume skips a and the fit (their files untouched), resumes
    b from its checkpoint through the trainer's resume, and ends bit-equal to the uninterrupted run."""
    recipe_file, reference, _ = finished_recipe
    out, log_file = tmp_path / "R", tmp_path / "stderr.txt"
    with open(log_file, "wb") as stderr:
        proc = subprocess.Popen([sys.executable, "-m", "garmentnerf.cli.main",
                                 *recipe_argv(recipe_file, out, tiny_scene.root)],
                                stdout=subprocess.DEVNULL, stderr=stderr)
        try:
            deadline = time.monotonic() + 180
            while not (out / "stages" / "03-b" / "run.json").exists():  # its first complete checkpoint
                assert proc.poll() is None, log_file.read_text()
                assert time.monotonic() < deadline, "stage b wrote no checkpoint within 180 s"
                time.sleep(0.02)
            proc.send_signal(signal.SIGKILL)
            assert proc.wait(timeout=60) == -signal.SIGKILL
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    killed_at, _, _ = latest_checkpoint(out / "stages" / "03-b")
    assert 50 < killed_at < 90, log_file.read_text()
    before = {**mtimes(out / "stages" / "01-a"), **mtimes(out / "stages" / "02-fit")}
    # without --resume the folder is refused; a resume needs no --scene (the log has it)
    assert main(recipe_argv(recipe_file, out, tiny_scene.root)) == 2
    assert "run folder is not empty; pass --resume" in one_error_line(capsys)
    assert main(recipe_argv(recipe_file, out, None, "--resume")) == 0
    err = capsys.readouterr().err
    assert "stage 1/3 a: finished" in err and "stage 2/3 fit: finished" in err
    assert f"resuming at step {killed_at}" in err
    assert {**mtimes(out / "stages" / "01-a"), **mtimes(out / "stages" / "02-fit")} == before
    log = json.loads((out / "recipe_log.json").read_text())
    sittings = log["stages"][2]["sittings"]
    assert [s["from_step"] for s in sittings] == [50, killed_at] and sittings[-1]["to_step"] == 90
    assert [len(s["sittings"]) for s in log["stages"]] == [1, 1, 2]
    assert all(s["finished"] for s in log["stages"])
    final, uninterrupted = weights(out / "model.safetensors"), weights(reference / "model.safetensors")
    assert all(torch.equal(final[k], uninterrupted[k]) for k in uninterrupted)


def test_resuming_a_finished_recipe_runs_nothing_and_another_recipe_is_refused(finished_recipe, tmp_path, capsys):
    recipe_file, out, _ = finished_recipe
    before = mtimes(out)
    assert main(recipe_argv(recipe_file, out, None, "--resume")) == 0
    assert "stage 3/3 b: finished" in capsys.readouterr().err
    assert main(["train", "--out", str(out), "--resume", *FAST]) == 0  # a recipe folder alone: its recipe.json
    assert "recipe tiny: finished" in capsys.readouterr().err
    assert mtimes(out) == before
    changed = json.loads(json.dumps(TINY))
    changed["stages"][2]["iterations"] = 41
    other = write_recipe(tmp_path / "other.json", changed)
    assert main(recipe_argv(other, out, None, "--resume")) == 2
    line = one_error_line(capsys)
    assert f"--recipe {other}: differs from the recipe {out} was started with" in line
    assert "stages[2].iterations (40 against 41)" in line
    assert main(recipe_argv(recipe_file, out, tmp_path, "--resume")) == 2
    assert "was started on" in one_error_line(capsys)
    assert mtimes(out) == before


def test_a_recipe_scene_is_made_once_and_its_stage_trains_on_it(tiny_scene, gl_context, tmp_path, capsys,
                                                                one_torch_thread):
    """A recipe scene: the --scene copied into R/scenes/ with a sequence made (here by a stand-in for
    'data make': a rigged scene) and added; an interrupted make is made again on the resume."""
    from garmentnerf.data.synthetic import make_rigged_scene

    calls = []

    def make_sequence(out, garment, motions, frames, shape, fps, progress):
        calls.append((Path(out).relative_to(tmp_path / "R").as_posix(), garment, motions, frames, shape, fps))
        scene = make_rigged_scene(out, garment=garment, motion=motions, frames=frames, views=1, size=32,
                                  held_out_views=0, gl_context=gl_context)
        if len(calls) == 1:
            raise KeyboardInterrupt  # killed after the make, before the sequence was added
        return scene

    recipe = parse_recipe({
        "format": "garmentnerf-recipe", "version": 1, "name": "more", "description": "",
        "scenes": [{"name": "more", "base": None, "sequences": [{"name": "extra", "motions": "walk", "frames": 2}]}],
        "stages": [{"name": "a", "kind": "train", "scene": "more", "sequences": ["train", "extra"], "model": "tiny",
                    "iterations": 1, "generator_iterations": 0}]}, "more.json")
    out = tmp_path / "R"
    with pytest.raises(KeyboardInterrupt):
        run_recipe(recipe, "more.json", out, tiny_scene.root, make_sequence=make_sequence)
    assert run_recipe(recipe, "more.json", out, resume=True, make_sequence=make_sequence) == 0
    assert calls == [("data/more/extra", "skirt", "walk", 2, "average", tiny_scene.fps)] * 2
    scene = json.loads((out / "scenes" / "more" / "scene.json").read_text())
    assert set(scene["sequences"]) == {*tiny_scene.sequences, "extra"}
    assert set(json.loads((tiny_scene.root / "scene.json").read_text())["sequences"]) == set(tiny_scene.sequences)
    run = load_run(out)
    assert Path(run.scene.root).samefile(out / "scenes" / "more")
    assert run.info["train"]["sequences"] == ["train", "extra"]
    log = json.loads((out / "recipe_log.json").read_text())
    assert log["scenes"]["more"]["sequences"]["extra"]["finished"]


def test_ctrl_c_in_a_stage_stops_the_recipe_with_its_checkpoint(tiny_scene, tmp_path, capsys, monkeypatch,
                                                               one_torch_thread):
    """Ctrl-C (or SIGTERM) in a stage: its checkpoint is written, the recipe stops with status 130 and says
    how to continue; the resume finishes it."""
    from garmentnerf.train.trainer import Trainer

    recipe = json.loads(json.dumps(TINY))
    recipe["stages"] = [recipe["stages"][0]]
    file = write_recipe(tmp_path / "one.json", recipe)
    out = tmp_path / "R"
    step = Trainer._nerf_step

    def interrupted(self, number, index, gen):
        if number == 3:
            raise KeyboardInterrupt
        return step(self, number, index, gen)

    monkeypatch.setattr(Trainer, "_nerf_step", interrupted)
    assert main(recipe_argv(file, out, tiny_scene.root)) == 130
    err = capsys.readouterr().err
    assert "interrupted: checkpoint of step 3 written" in err
    assert f"interrupted in stage 1/1 a; continue the recipe with 'garmentnerf train --out {out} --resume'" in err
    log = json.loads((out / "recipe_log.json").read_text())
    assert log["stages"][0]["finished"] is None and log["stages"][0]["sittings"][0]["to_step"] == 3
    assert not (out / "run.json").exists()  # nothing published before the last stage ends
    monkeypatch.setattr(Trainer, "_nerf_step", step)
    assert main(["train", "--out", str(out), "--resume", *FAST]) == 0
    assert "resuming at step 3" in capsys.readouterr().err
    assert load_run(out).step == 5


# ---------------------------------------------------------------------------------------- refusals
BAD = [
    (lambda r: r["stages"][0].update(bogus=1), "stages[0].bogus: unknown key"),
    (lambda r: r["stages"][1].update(model="tiny"), "stages[1].model: not a field of a fit_body_appearance stage"),
    (lambda r: r["stages"][2].update(init="nope"), "stages[2].init: no stage is called 'nope' (earlier train "
                                                   "stages: a)"),
    (lambda r: r["stages"][0].update(init="b"), "stages[0].init: 'b' comes later"),
    (lambda r: r["stages"][2].update(body_appearance="a"), "stages[2].body_appearance: 'a' is a train stage"),
    (lambda r: r["stages"][0].update(iterations=True), "stages[0].iterations: must be an integer, got true"),
    (lambda r: r["stages"][2]["config"].update({"schedule.lr_finall": 1e-4}),
     "stages[2].config: 'schedule.lr_finall' is not a model config field (did you mean 'schedule.lr_final'?)"),
    (lambda r: r["stages"][2]["config"].update({"nerf.mlp_depth": 2.5}),
     "stages[2].config: nerf.mlp_depth: must be an integer"),
    (lambda r: r["stages"][0].update(sequences=["train", "nope"]), "has no training sequence 'nope'"),
    (lambda r: r.update(version=2), "version: 2 is not supported"),
]


@pytest.mark.parametrize("change, message", BAD, ids=[m.split(":")[0] for _, m in BAD])
def test_a_bad_recipe_is_one_line_naming_the_file_and_the_key(tiny_scene, tmp_path, capsys, change, message):
    recipe = json.loads(json.dumps(TINY))
    change(recipe)
    file = write_recipe(tmp_path / "bad.json", recipe)
    assert main(recipe_argv(file, tmp_path / "R", tiny_scene.root)) == 2
    line = one_error_line(capsys)
    assert line.startswith(f"garmentnerf: error: {file}: ") and message in line, line
    assert not (tmp_path / "R").exists()


@pytest.mark.parametrize("text, message", [
    ('"iterations": NaN', "stages[0].iterations: NaN is not a finite number"),
    ('"iterations": 4, "config": {"schedule.lr": Infinity}',
     "stages[0].config.schedule.lr: Infinity is not a finite number"),
    ('"iterations": 4, "config": {"schedule.lr": 1e999}', "stages[0].config.schedule.lr: 1e999 is not a finite number"),
    ('"iterations": 4, "iterations": 5', "key 'iterations' is given twice"),
    ('"iterations": 4,', "not valid JSON"),
])
def test_non_finite_numbers_and_bad_json_are_refused(tiny_scene, tmp_path, capsys, text, message):
    body = json.dumps(TINY).replace('"iterations": 4', text, 1)
    file = tmp_path / "bad.json"
    file.write_text(body)
    assert main(recipe_argv(file, tmp_path / "R", tiny_scene.root)) == 2
    line = one_error_line(capsys)
    assert line.startswith(f"garmentnerf: error: {file}: ") and message in line, line


@pytest.mark.parametrize("flags", [["--preset", "tiny"], ["--model-config", "x.json"], ["--iterations", "3"],
                                   ["--init-weights", "x.safetensors"], ["--loss-weight", "w_mask=1"]])
def test_flags_the_recipe_sets_are_refused_with_it(tiny_scene, tmp_path, capsys, flags):
    file = write_recipe(tmp_path / "tiny.json", TINY)
    assert main(recipe_argv(file, tmp_path / "R", tiny_scene.root, *flags)) == 2
    assert f"--recipe and {flags[0]}: the recipe sets each stage's" in one_error_line(capsys)


def test_a_new_recipe_run_needs_its_scene_and_a_resume_its_folder(tmp_path, capsys):
    file = write_recipe(tmp_path / "tiny.json", TINY)
    assert main(recipe_argv(file, tmp_path / "R", None)) == 2
    assert one_error_line(capsys).endswith(f"{file}: stages[0] (a) uses the --scene: give --scene DIR")
    assert main(recipe_argv(file, tmp_path / "R", tmp_path / "nowhere")) == 2
    assert "nowhere/scene.json: missing" in one_error_line(capsys)
    assert main(recipe_argv(file, tmp_path / "R", None, "--resume")) == 2
    assert "recipe.json: missing; --resume with --recipe continues a folder made by" in one_error_line(capsys)
    assert main(recipe_argv(tmp_path / "none.json", tmp_path / "R", None)) == 2
    assert "none.json: no such recipe file" in one_error_line(capsys)
    assert not (tmp_path / "R").exists()


def test_model_configs_come_from_the_preset_or_the_previous_stage():
    recipe = parse_recipe(TINY, "tiny.json")
    configs = stage_model_configs(recipe)
    assert set(configs) == {"a", "b"}
    assert configs["b"] == configs["a"].updated({"schedule.trained_parameters": ("decoder.",)})
    assert recipe_model_config("cpu_small", {"schedule.lr": 1}).schedule.lr == 1.0  # an integer is a number
    with pytest.raises(ValueError, match="loss.mask: must be a number"):
        recipe_model_config("tiny", {"loss.mask": "1"})
    with pytest.raises(RecipeError, match=r"stages\[2\].config: .*lr_final"):
        stage_model_configs(parse_recipe({**TINY, "stages": [*TINY["stages"][:2], {
            **TINY["stages"][2], "config": {"schedule.lr_final": 1.0}}]}, "tiny.json"), "tiny.json")


# ---------------------------------------------------------------------------------------- the demos
@pytest.mark.parametrize("name", ["skirt", "tshirt", "dress"])
def test_each_demos_recipe_is_valid_and_ends_in_its_bundled_config(name):
    """The shipped recipe parses, builds every stage's config, finds its scenes and sequences on the demo's
    scene, and its last stage trains the config of the bundled model's run.json."""
    run_dir = demo(name).run_dir
    file = run_dir / "recipe.json"
    recipe = read_recipe(file)
    assert recipe.name == name
    configs = stage_model_configs(recipe, str(file))
    check_scenes(recipe, str(file), demo(name).scene_dir)
    last = [s for s in recipe.stages if s.trains][-1]
    bundled = ModelConfig.from_dict(json.loads((run_dir / "run.json").read_text())["model_config"])
    assert configs[last.name].updated({"schedule.iterations": last.iterations,
                                       "schedule.generator_iterations": last.generator_iterations,
                                       "frame_codes.count": bundled.frame_codes.count}) == bundled
    assert all(s.ckpt_every == 100 for s in recipe.stages if s.trains)


def test_the_tshirt_and_dress_start_from_the_skirts_field():
    """Their first six stages are the skirt's (C7r, the body appearance fit included), on the skirt's scene."""
    skirt = read_recipe(demo("skirt").run_dir / "recipe.json")
    for name in ("tshirt", "dress"):
        recipe = read_recipe(demo(name).run_dir / "recipe.json")
        head = recipe.stages[:6]
        assert [s.name for s in head] == [s.name for s in skirt.stages[:6]]
        for mine, theirs in zip(head, skirt.stages[:6]):
            assert mine == dataclasses.replace(theirs, scene=mine.scene), mine.name
            assert mine.scene == ("skirt_more" if theirs.scene == "skirt_more" else None if not mine.trains
                                  else "demo:skirt"), mine.name
        assert [s.sequences for s in recipe.scenes] == [s.sequences for s in skirt.scenes]
        assert recipe.scenes[0].base == "demo:skirt"


def test_the_recipes_are_package_data():
    pyproject = (Path(__file__).resolve().parents[2] / "pyproject.toml").read_text()
    assert '"demo/*/*.json"' in pyproject
    for name, folder in DEMO_FOLDERS.items():
        assert (demo(name).run_dir / "recipe.json").is_file() and demo(name).run_dir.name == folder
