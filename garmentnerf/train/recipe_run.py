"""Running a recipe (:mod:`garmentnerf.train.recipe`) into one folder: ``garmentnerf train --recipe``.

Layout of the recipe's folder ``R``::

    R/recipe.json                  the recipe as run (every field written; a resume must give the same)
    R/recipe_log.json              what ran: per stage its folder, times, steps and CPU minutes (atomic)
    R/stages/<NN>-<name>/          each stage: a train stage's run folder (``garmentnerf train``'s own), a fit
                                   stage's body_appearance.safetensors
    R/scenes/<name>/               the recipe's scenes: a copy of their base scene with the added sequences
    R/data/<scene>/<sequence>/     each added sequence as ``garmentnerf data make`` made it
    R/run.json, R/model.safetensors, R/body_appearance.safetensors
                                   the last train stage's run (its scene recorded relative to R), so
                                   ``eval --run R`` and ``view --run R`` open the result

Stages run in order. A train stage is a :class:`~garmentnerf.train.trainer.Trainer` run of a
:class:`~garmentnerf.train.settings.TrainConfig` made from the stage as ``garmentnerf train`` makes one
from its flags (the model config of :func:`~garmentnerf.train.recipe.recipe_model_config`, the earlier
stages' weights and body appearance as its files). A fit stage fits the body appearance of the
previous train stage's run (:func:`~garmentnerf.train.body_appearance.fit_run_appearance`).

Resume (``resume=True``): stages the log records as finished are skipped; a train stage with a complete
checkpoint continues from it through the trainer's own resume (exact); one without (killed before its
first checkpoint) and a fit stage start again. The recipe must be the one ``R/recipe.json`` holds.

``recipe_log.json``::

    {"format": "garmentnerf-recipe-log", "version": 1, "recipe": <name>, "recipe_file": <path given>,
     "scene": <the --scene, absolute> | null,
     "scenes": {<name>: {"folder": "scenes/<name>", "sequences": {<seq>: {"data": "data/<name>/<seq>",
                                                                         "started", "finished", "cpu_minutes"}}}},
     "stages": [{"name", "kind", "folder": "stages/<NN>-<name>", "started", "finished" (UTC times or null),
                 "step" (global step reached), "end_step" (where the stage ends), "steps" (steps trained
                 here), "cpu_minutes", "sittings": [{"started", "from_step", "to_step", "cpu_minutes",
                 "threads", "device"}],
                 "fit": {the fit's summary} (fit stages)}],
     "published": {"stage", "time"} | null}

CPU minutes are the process's CPU time (user + system, with the children it waited for: the cloth
simulations), counted up to each checkpoint; a killed sitting's steps after its last checkpoint, which
the resume trains again, are not counted.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from types import MappingProxyType

from garmentnerf.io_utils import read_json_strict, write_file_atomic
from garmentnerf.folder_lock import folder_has_files, lock_folder
from garmentnerf.train.recipe import (
    DEMO_SCENE_PREFIX,
    RECIPE_FILE,
    Recipe,
    RecipeError,
    RecipeScene,
    Stage,
    first_difference,
    load_recipe_json,
    parse_recipe,
    previous_train_stage,
    stage_model_configs,
)

__all__ = ["LOG_FILE", "STAGES_DIR", "SCENES_DIR", "DATA_DIR", "RecipeOptions", "run_recipe", "check_scenes",
           "base_scene", "stage_folder", "read_log", "make_sequence_scene", "copy_scene"]

LOG_FILE = "recipe_log.json"
LOG_FORMAT = "garmentnerf-recipe-log"
STAGES_DIR = "stages"
SCENES_DIR = "scenes"
DATA_DIR = "data"


@dataclass(frozen=True)
class RecipeOptions:
    """How a recipe runs on this machine (what it trains is the recipe's); each ``garmentnerf train``
    flag allowed with ``--recipe``, applied to every train stage."""

    device: str = "cpu"
    """``--device``."""
    threads: int | None = None
    """``--threads``: overrides each stage's ``threads`` (None: the stage's)."""
    progress: bool = True
    """Progress bars (``--no-progress``: off)."""
    perceptual: str | None = None
    """``--perceptual`` (None: the trainer's default, or on a resumed stage its run's)."""
    vgg19_weights: str | None = None
    """``--vgg19-weights``."""
    log_every: int | None = None
    """``--log-every``."""
    image_every: int | None = None
    """``--image-every``."""
    ckpt_every: int | None = None
    """``--ckpt-every``: overrides each stage's ``ckpt_every``."""
    caches: Mapping[str, int] = dataclasses.field(default_factory=lambda: MappingProxyType({}))
    """:class:`~garmentnerf.train.settings.TrainConfig` cache bounds (``--cache-gib``)."""


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def _cpu_seconds() -> float:
    """CPU time of this process and the children it waited for (user + system)."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def stage_folder(out: Path, recipe: Recipe, stage: Stage) -> Path:
    """The folder of ``stage`` in the recipe's folder ``out``: ``stages/<NN>-<name>`` (NN from 01)."""
    return Path(out) / STAGES_DIR / f"{recipe.stages.index(stage) + 1:02d}-{stage.name}"


def read_log(out) -> dict:
    """The ``recipe_log.json`` of the recipe folder ``out`` (ValueError naming it when unreadable)."""
    file = Path(out) / LOG_FILE
    try:
        log = read_json_strict(file, "recipe log")
    except FileNotFoundError:
        raise FileNotFoundError(f"{file}: missing (not a folder 'garmentnerf train --recipe' made)") from None
    except OSError as exc:
        raise ValueError(str(exc)) from None
    if not isinstance(log, dict) or log.get("format") != LOG_FORMAT or not isinstance(log.get("stages"), list):
        raise ValueError(f"{file}: not a recipe log")
    return log


def _write_log(out: Path, log: dict) -> None:
    write_file_atomic(out / LOG_FILE, (json.dumps(log, indent=1, allow_nan=False) + "\n").encode("utf-8"))


def _new_log(recipe: Recipe, recipe_file: str, scene: Path | None, out: Path) -> dict:
    return {"format": LOG_FORMAT, "version": 1, "recipe": recipe.name, "recipe_file": recipe_file,
            "scene": None if scene is None else str(scene.resolve()),
            "scenes": {s.name: {"folder": f"{SCENES_DIR}/{s.name}", "sequences": {}} for s in recipe.scenes},
            "stages": [{"name": s.name, "kind": s.kind,
                        "folder": stage_folder(out, recipe, s).relative_to(out).as_posix(),
                        "started": None, "finished": None, "step": None, "end_step": None, "steps": 0,
                        "cpu_minutes": 0.0, "sittings": []} for s in recipe.stages],
            "published": None}


def copy_scene(source: Path, folder: Path) -> None:
    """Copy the scene ``source`` (its ``scene.json`` and ``sequences/``; not its rendered ``cache/`` or
    the simulator's ``sim/``) to ``folder``, staged beside it and renamed into place."""
    staging = folder.with_name(f".{folder.name}.partial")
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    shutil.copy2(source / "scene.json", staging / "scene.json")
    shutil.copytree(source / "sequences", staging / "sequences")
    os.replace(staging, folder)


def make_sequence_scene(out: Path, garment: str, motions: str, frames: int, shape, fps: float, progress: bool):
    """``garmentnerf data make`` of a scene with one training sequence (``motions``, ``frames`` frames)
    of ``garment`` on the body ``shape`` at ``fps``, into ``out`` (resumable); returns its Scene."""
    from garmentnerf.data.make import MakeSpec, make_scene

    shape_text = shape if isinstance(shape, str) else ",".join(repr(float(x)) for x in shape)
    spec = MakeSpec(garment=garment, motion=motions, frames=frames, shape=shape_text, fps=fps, processes=1)
    return make_scene(out, spec, progress=progress, keep_chunks=False)


def _say(message: str) -> None:
    print(f"garmentnerf train: {message}", file=sys.stderr, flush=True)


def base_scene(base: str | None, key: str, scene: Path | None, recipe_file: str) -> Path:
    """The folder of the scene ``base`` names (None: the --scene ``scene``; ``demo:<garment>``: a bundled
    demo's), checked to hold a scene; ``key`` says what needs it (for messages)."""
    if base is None:
        if scene is None:
            raise ValueError(f"{recipe_file}: {key} uses the --scene: give --scene DIR")
        path = scene
    else:
        from garmentnerf.demos import demo

        garment = base[len(DEMO_SCENE_PREFIX):]
        path = demo(garment).scene_dir
        if path is None:
            raise FileNotFoundError(f"{recipe_file}: {key}: the {garment} demo is not installed")
    if not (path / "scene.json").is_file():
        raise FileNotFoundError(f"{path / 'scene.json'}: missing ({key} needs a scene folder)")
    return path


def check_scenes(recipe: Recipe, recipe_file: str, scene: Path | None) -> None:
    """Refuse, before anything runs, a scene that is missing, a sequence to add that its scene has
    already or whose garment is not the scene's, and a sequence a stage trains on that its scene lacks
    (``scene``: the --scene)."""
    from garmentnerf.data.garments import GARMENT_KINDS
    from garmentnerf.data.scene import Scene

    loaded: dict[Path, Scene] = {}

    def load(path: Path) -> Scene:
        if path not in loaded:
            loaded[path] = Scene.load(path)
        return loaded[path]

    names: dict[str | None, tuple[Path, set[str]]] = {}
    for i, rs in enumerate(recipe.scenes):
        base = base_scene(rs.base, f"scenes[{i}]", scene, recipe_file)
        loaded_base = load(base)
        kind = loaded_base.garment.get("kind")
        for j, extra in enumerate(rs.sequences):
            key = f"scenes[{i}].sequences[{j}]"
            if extra.name in loaded_base.sequences:
                raise RecipeError(f"{recipe_file}: {key}.name: '{extra.name}' is a sequence of "
                                  f"{loaded_base.scene_file} already (name the new one otherwise)")
            garment = extra.garment or kind
            if garment != kind:
                raise RecipeError(f"{recipe_file}: {key}.garment: a {garment} cannot train {loaded_base.scene_file}, "
                                  f"whose garment is a {kind}")
            if garment not in GARMENT_KINDS:
                raise RecipeError(f"{recipe_file}: {key}: 'garmentnerf data make' simulates "
                                  f"{', '.join(GARMENT_KINDS)}, not the scene's {kind} ({loaded_base.scene_file})")
        names[rs.name] = (base, set(loaded_base.sequence_names("train")) | {e.name for e in rs.sequences})
    for i, stage in enumerate(recipe.stages):
        if not stage.trains:
            continue
        key = f"stages[{i}] ({stage.name})"
        if stage.scene not in names:
            base = base_scene(stage.scene, key, scene, recipe_file)
            names[stage.scene] = (base, set(load(base).sequence_names("train")))
        path, available = names[stage.scene]
        missing = [s for s in stage.sequences or () if s not in available]
        if missing:
            raise RecipeError(f"{recipe_file}: {key}.sequences: {path / 'scene.json'} has no training sequence "
                              f"{', '.join(repr(m) for m in missing)} (it has {', '.join(sorted(available)) or 'none'})")


def run_recipe(recipe: Recipe, recipe_file, out, scene=None, *, resume: bool = False,
               options: RecipeOptions = RecipeOptions(), say: Callable[[str], None] = _say,
               make_sequence: Callable = make_sequence_scene) -> int:
    """Run ``recipe`` into the folder ``out`` on the scene folder ``scene`` (see the module docstring).

    Args:
        recipe_file: the recipe file given (recorded in the log; named in messages).
        scene: the ``--scene`` (on ``resume`` None: the one the folder was started with).
        resume: continue the recipe in ``out``; else ``out`` must be absent or empty.
        say: where progress lines go.
        make_sequence: makes a recipe scene's sequence (:func:`make_sequence_scene`'s arguments).
    Returns:
        0 when every stage is finished and the result published, 130 when a stage was interrupted
        (Ctrl-C, SIGTERM: its checkpoint written; ``resume`` continues).
    Raises:
        ValueError, FileNotFoundError: a folder or scene that cannot be used, a recipe that differs
            from the one ``out`` was started with (one line, before anything is written).
    """
    out = Path(out)
    # one writer per folder: the recipe's folder for the whole sitting (each stage's run folder as well, by
    # its trainer or fit)
    with lock_folder(out, "garmentnerf train --recipe" + (" --resume" if resume else "")):
        scene_path = None if scene is None else Path(scene)
        if resume:
            log = _resumed_log(recipe, str(recipe_file), out, scene_path)
            scene_path = None if log["scene"] is None else Path(log["scene"])
        else:
            if folder_has_files(out):
                raise ValueError(f"{out}: run folder is not empty; pass --resume to continue the recipe in it, or "
                                 f"choose another --out")
            log = _new_log(recipe, str(recipe_file), scene_path, out)
        runner = _Runner(recipe, str(recipe_file), out, scene_path, options, say, make_sequence, log)
        check_scenes(recipe, str(recipe_file), scene_path)
        if not resume:
            write_file_atomic(out / RECIPE_FILE, (json.dumps(recipe.to_json(), indent=1) + "\n").encode("utf-8"))
            _write_log(out, log)
        return runner.run()


def _resumed_log(recipe: Recipe, recipe_file: str, out: Path, scene: Path | None) -> dict:
    """The log of the recipe folder ``out`` to continue, after checking that ``recipe`` and ``scene``
    are the ones it was started with."""
    recorded_file = out / RECIPE_FILE
    if not recorded_file.is_file():
        raise FileNotFoundError(f"{recorded_file}: missing; --resume with --recipe continues a folder made by "
                                f"'garmentnerf train --recipe' (start it without --resume)")
    recorded = parse_recipe(load_recipe_json(recorded_file), str(recorded_file))
    difference = first_difference(recorded.to_json(), recipe.to_json())
    if difference is not None:
        raise ValueError(f"--recipe {recipe_file}: differs from the recipe {out} was started with ({recorded_file}) "
                         f"at {difference}; a resume runs the recipe it began (give that file, or train into "
                         f"another --out)")
    log = read_log(out)
    if [s.get("name") for s in log["stages"]] != [s.name for s in recipe.stages]:
        raise ValueError(f"{out / LOG_FILE}: its stages are not the recipe's")
    if scene is not None and (log["scene"] is None or scene.resolve() != Path(log["scene"])):
        raise ValueError(f"--scene {scene}: the recipe in {out} was started on {log['scene']}; --resume continues "
                         f"it there (leave --scene out)")
    log["recipe_file"] = recipe_file
    return log


class _Runner:
    """One sitting of a recipe run (see :func:`run_recipe`)."""

    def __init__(self, recipe: Recipe, recipe_file: str, out: Path, scene: Path | None, options: RecipeOptions,
                 say: Callable[[str], None], make_sequence: Callable, log: dict):
        self.recipe, self.recipe_file, self.out, self.scene = recipe, recipe_file, out, scene
        self.options, self.say, self.make_sequence, self.log = options, say, make_sequence, log
        self.configs = stage_model_configs(recipe, recipe_file)

    # ---- scenes --------------------------------------------------------------------------------------------
    def stage_scene(self, stage: Stage) -> Path:
        """The scene folder ``stage`` trains on (a recipe scene made first if it is not yet)."""
        rs = self.recipe.scene_named(stage.scene) if stage.scene is not None else None
        if rs is None:
            return base_scene(stage.scene, f"stage {stage.name}", self.scene, self.recipe_file)
        return self.recipe_scene(rs)

    def recipe_scene(self, rs: RecipeScene) -> Path:
        """The folder of the recipe scene ``rs``: its base copied and each sequence made (``data make``
        into ``data/``, resumable) and added (``data add-sequence``), where not done already."""
        from garmentnerf.data.scene import Scene
        from garmentnerf.data.scene_merge import import_sequence

        folder = self.out / SCENES_DIR / rs.name
        if not (folder / "scene.json").is_file():
            copy_scene(base_scene(rs.base, f"scene {rs.name}", self.scene, self.recipe_file), folder)
        scene = Scene.load(folder)
        record = self.log["scenes"].setdefault(rs.name, {"folder": f"{SCENES_DIR}/{rs.name}", "sequences": {}})
        for extra in rs.sequences:
            if extra.name in scene.sequences:
                continue
            data = self.out / DATA_DIR / rs.name / extra.name
            entry = record["sequences"].setdefault(extra.name, {"data": data.relative_to(self.out).as_posix(),
                                                                "started": _now(), "finished": None,
                                                                "cpu_minutes": 0.0})
            self.say(f"recipe {self.recipe.name}: scene {rs.name}: making sequence {extra.name} ({extra.motions}, "
                     f"{extra.frames} frames; 'garmentnerf data make' into {data})")
            _write_log(self.out, self.log)
            cpu = _cpu_seconds()
            made = self.make_sequence(data, extra.garment or scene.garment.get("kind"), extra.motions, extra.frames,
                                      scene.body.get("shape", "average"), scene.fps, self.options.progress)
            stale = folder / "sequences" / extra.name  # an add-sequence killed before it saved scene.json
            if stale.exists():
                shutil.rmtree(stale)
            import_sequence(scene, made, "train", as_name=extra.name, split="train")
            entry.update(finished=_now(), cpu_minutes=entry["cpu_minutes"] + (_cpu_seconds() - cpu) / 60)
            _write_log(self.out, self.log)
        return folder

    # ---- stages ---------------------------------------------------------------------------------------------
    def run(self) -> int:
        stages = self.recipe.stages
        for index, stage in enumerate(stages):
            record = self.log["stages"][index]
            head = f"recipe {self.recipe.name}: stage {index + 1}/{len(stages)} {stage.name}"
            if record.get("finished"):
                self.say(f"{head}: finished {record['finished']}, skipped")
                continue
            self.say(f"{head} ({self.describe(index, stage)})")
            if record.get("started") is None:
                record["started"] = _now()
            if stage.trains:
                if not self.train(index, stage, record):
                    self.say(f"recipe {self.recipe.name}: interrupted in stage {index + 1}/{len(stages)} "
                             f"{stage.name}; continue the recipe with 'garmentnerf train --out {self.out} --resume'")
                    return 130
            else:
                self.fit(index, stage, record)
            record["finished"] = _now()
            _write_log(self.out, self.log)
        self.publish()
        self.say(f"recipe {self.recipe.name}: finished; the model is {self.out} (its stages in "
                 f"{self.out / STAGES_DIR}, what ran in {self.out / LOG_FILE})")
        return 0

    def describe(self, index: int, stage: Stage) -> str:
        """One line of what ``stage`` does."""
        previous = previous_train_stage(self.recipe, index)
        if not stage.trains:
            return f"body appearance fit of {previous.name}'s run, {stage.iterations} steps"
        parts = [f"{stage.iterations} NeRF steps"]
        if stage.stop_after is not None:
            parts.append(f"stopping at global step {stage.stop_after}")
        if stage.init is not None:
            parts.append(f"from {previous.name if stage.init == 'previous' else stage.init}'s weights")
        if stage.body_appearance is not None:
            parts.append(f"the body drawn with {stage.body_appearance}'s appearance")
        if stage.scene is not None:
            parts.append(f"on scene {stage.scene}")
        return "train, " + ", ".join(parts)

    def _train_stage(self, ref: str, index: int) -> Stage:
        return previous_train_stage(self.recipe, index) if ref == "previous" else self.recipe.stage(ref)

    def _weights(self, ref: str | None, index: int) -> Path | None:
        """The weights file of the train stage ``ref`` (``previous`` or a name) of stage ``index``."""
        if ref is None:
            return None
        from garmentnerf.runs import MODEL_FILE

        return (stage_folder(self.out, self.recipe, self._train_stage(ref, index)) / MODEL_FILE).resolve()

    def new_config(self, index: int, stage: Stage, folder: Path):
        """The :class:`TrainConfig` of ``stage`` as a new run in ``folder``."""
        from garmentnerf.model.body_appearance import BODY_APPEARANCE_FILE
        from garmentnerf.ranges import parse_frames
        from garmentnerf.train.settings import TrainConfig

        opt = self.options
        appearance = None
        if stage.body_appearance is not None:
            fit = self.recipe.stage(stage.body_appearance)
            appearance = (stage_folder(self.out, self.recipe, fit) / BODY_APPEARANCE_FILE).resolve()
        return TrainConfig(
            scene=self.stage_scene(stage), out=folder, model_config=self.configs[stage.name], device=opt.device,
            seed=stage.seed, iterations=stage.iterations, generator_iterations=stage.generator_iterations,
            stop_after=stage.stop_after, log_every=opt.log_every, image_every=opt.image_every,
            ckpt_every=opt.ckpt_every or stage.ckpt_every, sequences=stage.sequences,
            frames=None if stage.frames is None else tuple(parse_frames(stage.frames, "frames")),
            perceptual=opt.perceptual, vgg19_weights=opt.vgg19_weights, threads=opt.threads or stage.threads,
            progress=opt.progress, init_generator=self._weights(stage.init_generator, index),
            init_weights=self._weights(stage.init, index), training_crop_density=stage.training_crop_density,
            body_appearance=appearance, **opt.caches)

    def resume_config(self, stage: Stage, folder: Path):
        """The :class:`TrainConfig` that resumes ``stage``'s run in ``folder`` with its own settings."""
        from garmentnerf.train.settings import TrainConfig

        opt = self.options
        return TrainConfig(scene=None, out=folder, resume=True, device=opt.device, stop_after=stage.stop_after,
                           log_every=opt.log_every, image_every=opt.image_every, ckpt_every=opt.ckpt_every,
                           perceptual=opt.perceptual, vgg19_weights=opt.vgg19_weights,
                           threads=opt.threads or stage.threads, progress=opt.progress, **opt.caches)

    def train(self, index: int, stage: Stage, record: dict) -> bool:
        """Run (or resume) train stage ``stage``; False when it was interrupted."""
        import torch

        from garmentnerf.runs import RUN_FILE
        from garmentnerf.train.checkpoints import checkpoints
        from garmentnerf.train.trainer import Trainer

        folder = stage_folder(self.out, self.recipe, stage)
        resumable = (folder / RUN_FILE).is_file() and bool(checkpoints(folder))
        if folder.exists() and not resumable:
            shutil.rmtree(folder)  # made before its first checkpoint: nothing in it to keep
        tc = self.resume_config(stage, folder) if resumable else self.new_config(index, stage, folder)
        sitting = {"started": _now(), "from_step": None, "to_step": None, "cpu_minutes": 0.0}
        record["sittings"].append(sitting)
        cpu = _cpu_seconds()

        def note(trainer) -> None:
            sitting.update(to_step=trainer.step, cpu_minutes=(_cpu_seconds() - cpu) / 60)
            record.update(step=trainer.step, steps=sum((s["to_step"] or 0) - (s["from_step"] or 0)
                                                       for s in record["sittings"] if s["from_step"] is not None),
                          cpu_minutes=sum(s["cpu_minutes"] for s in record["sittings"]))
            _write_log(self.out, self.log)

        with Trainer(tc) as trainer:
            end = trainer.total_steps if stage.stop_after is None else min(trainer.total_steps, stage.stop_after)
            sitting.update(from_step=trainer.step, threads=torch.get_num_threads(), device=str(trainer.device))
            record["end_step"] = end
            note(trainer)

            def on_step(step: int, values: dict) -> None:
                if trainer.last_checkpoint_step == step:
                    note(trainer)

            trainer.step_callback = on_step
            result = trainer.train()
            note(trainer)
        return not result.interrupted and result.step >= end

    def fit(self, index: int, stage: Stage, record: dict) -> None:
        """Fit the body appearance of the previous train stage's run into ``stage``'s folder (holding its
        writer lock)."""
        folder = stage_folder(self.out, self.recipe, stage)
        with lock_folder(folder, "garmentnerf train --recipe: fit stage"):
            self._fit(index, stage, record, folder)

    def _fit(self, index: int, stage: Stage, record: dict, folder: Path) -> None:
        import torch

        from garmentnerf.model.body_appearance import BODY_APPEARANCE_FILE
        from garmentnerf.train.body_appearance import fit_run_appearance

        threads = self.options.threads or stage.threads
        if threads:
            torch.set_num_threads(threads)
        cpu = _cpu_seconds()
        record["sittings"].append({"started": _now(), "from_step": None, "to_step": None, "cpu_minutes": 0.0})
        run_dir = stage_folder(self.out, self.recipe, previous_train_stage(self.recipe, index))
        summary = fit_run_appearance(run_dir, folder / BODY_APPEARANCE_FILE, frame_stride=stage.frame_stride,
                                     steps=stage.iterations, albedo_prior=stage.albedo_prior,
                                     progress=self.options.progress)
        minutes = (_cpu_seconds() - cpu) / 60
        record["sittings"][-1].update(to_step=stage.iterations, cpu_minutes=minutes)
        record.update(step=stage.iterations, end_step=stage.iterations, steps=stage.iterations,
                      cpu_minutes=record["cpu_minutes"] + minutes,
                      fit={k: summary[k] for k in ("psnr", "psnr_start", "samples", "views", "seconds")})
        self.say(f"body appearance of {run_dir.name}: {summary['views']} training views, PSNR over its body pixels "
                 f"{summary['psnr']:.2f} dB (palette colour alone: {summary['psnr_start']:.2f} dB)")

    # ---- the result ----------------------------------------------------------------------------------------
    def publish(self) -> None:
        """Make the recipe's folder the last train stage's run: its weights, its body appearance (a later
        fit stage's if the recipe ends with one) and its ``run.json`` with the scene
        recorded relative to the folder (written last)."""
        from garmentnerf.model.body_appearance import BODY_APPEARANCE_FILE
        from garmentnerf.runs import MODEL_FILE, RUN_FILE, read_run_info, recorded_scene_path

        stages = self.recipe.stages
        last = max(i for i, s in enumerate(stages) if s.trains)
        folder = stage_folder(self.out, self.recipe, stages[last])
        done = self.log.get("published")
        if done and done.get("stage") == stages[last].name and (self.out / RUN_FILE).is_file():
            return
        later_fits = [s for s in stages[last + 1:] if not s.trains]
        appearance = (stage_folder(self.out, self.recipe, later_fits[-1]) if later_fits else folder) \
            / BODY_APPEARANCE_FILE
        files = {MODEL_FILE: folder / MODEL_FILE, BODY_APPEARANCE_FILE: appearance}
        for name, source in files.items():
            if source.is_file():
                write_file_atomic(self.out / name, source.read_bytes())
            elif (self.out / name).exists():
                (self.out / name).unlink()
        info = read_run_info(folder)
        scene = recorded_scene_path(folder, info)
        if scene is not None:
            try:
                info["scene"] = os.path.relpath(scene, self.out.resolve())
            except ValueError:  # another drive (Windows)
                info["scene"] = str(scene)
        info["recipe"] = {"name": self.recipe.name, "stage": stages[last].name}
        write_file_atomic(self.out / RUN_FILE, (json.dumps(info, indent=1, allow_nan=False) + "\n").encode("utf-8"))
        self.log["published"] = {"stage": stages[last].name, "time": _now()}
        _write_log(self.out, self.log)
