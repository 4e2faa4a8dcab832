"""A training recipe: the stages that make a model, as data (``garmentnerf train --recipe``).

A recipe file is JSON, read by :func:`read_recipe` (typed, finite numbers only, real booleans, unknown
keys refused; every error is one line naming the file and the key). Its stages run in order with
:mod:`garmentnerf.train.recipe_run`; each ``train`` stage is an ordinary training run started as
``garmentnerf train`` starts one (a preset or the previous stage's model config with overrides, its
schedule, the previous stage's weights as the start, ...).

Format (``version`` 1)::

    {"format": "garmentnerf-recipe", "version": 1,
     "name": "skirt", "description": "...",
     "scenes": [                              (optional) scenes the recipe grows with more sequences
       {"name": "skirt_more", "base": null,   null: the --scene; "demo:<garment>": a bundled demo's scene
        "description": "...",
        "sequences": [{"name": "train_run_jump_walk", "motions": "run,jump,walk", "frames": 170,
                       "garment": null}]}],   made by `data make`, added by `data add-sequence`
     "stages": [
       {"name": "base", "kind": "train", "model": "cpu_small", "config": {...},
        "iterations": 2200, "generator_iterations": 600, ...},
       {"name": "fit", "kind": "fit_body_appearance", "iterations": 3000, "albedo_prior": 0},
       ...]}

Each field is documented on its dataclass (:class:`RecipeScene`, :class:`ExtraSequence`,
:class:`Stage`, :class:`Recipe`). Names a stage refers to (``init``, ``init_generator``,
``body_appearance``, ``model: previous``) must be earlier stages, so a recipe runs top to bottom.

Model configs: every one a recipe makes goes through :func:`recipe_model_config` (a preset or the
previous train stage's config, with the stage's ``config`` overrides): the one place that knows how
override keys map onto :class:`~garmentnerf.model.config.ModelConfig`.
"""

from __future__ import annotations

import dataclasses
import difflib
import json
import re
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType

from garmentnerf.io_utils import parse_json_strict, read_json_strict
from garmentnerf.model.config import ModelConfig
from garmentnerf.ranges import parse_frames
from garmentnerf.train.settings import MODEL_PRESETS, model_config_for

__all__ = ["RECIPE_FORMAT", "RECIPE_VERSION", "RECIPE_FILE", "STAGE_KINDS", "DEMO_SCENE_PREFIX", "RecipeError",
           "ExtraSequence", "RecipeScene", "Stage", "Recipe", "read_recipe", "parse_recipe", "load_recipe_json",
           "recipe_model_config", "stage_model_configs", "previous_train_stage", "first_difference"]

RECIPE_FORMAT = "garmentnerf-recipe"
RECIPE_VERSION = 1
#: The shipped recipe of a demo, in its run folder.
RECIPE_FILE = "recipe.json"
#: What a stage does: a training run, or a fit of the rasterised body's appearance.
STAGE_KINDS = ("train", "fit_body_appearance")
#: A scene named ``demo:<garment>`` is a bundled demo's scene (:mod:`garmentnerf.demos`).
DEMO_SCENE_PREFIX = "demo:"
#: Stage, scene and sequence names: what a folder name may be.
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


class RecipeError(ValueError):
    """A recipe that cannot be read or run as written (one line naming the file and the key)."""


# ---- the recipe's elements ----------------------------------------------------------------------------
@dataclass(frozen=True)
class ExtraSequence:
    """A training sequence a recipe's scene needs and makes: simulated by ``garmentnerf data make``
    for the scene's garment and body, then copied in by ``garmentnerf data add-sequence``."""

    name: str
    """Its name in the scene (``data add-sequence --as``); split ``train``."""
    motions: str
    """The motion: clip names joined by ``,`` (``data make --motion``)."""
    frames: int
    """Its frames (``data make --frames``)."""
    garment: str | None = None
    """``data make --garment``; None: the scene's own garment kind (a different one is refused)."""


@dataclass(frozen=True)
class RecipeScene:
    """A scene the recipe makes: a copy of a scene (its ``scene.json`` and sequences) with more
    training sequences, kept in the recipe's output folder (``scenes/<name>``)."""

    name: str
    """What stages call it (their ``scene``)."""
    base: str | None
    """The scene copied: None for the ``--scene`` given, ``demo:<garment>`` for a bundled demo's scene."""
    sequences: tuple[ExtraSequence, ...]
    """The sequences added to the copy."""
    description: str = ""
    """What it is for (free text)."""


@dataclass(frozen=True)
class Stage:
    """One stage of a recipe. Fields marked *train* belong to ``train`` stages only, *fit* to
    ``fit_body_appearance`` stages only (given on the other kind they are refused)."""

    name: str
    """Its name: the stage folder is ``stages/<NN>-<name>``, and later stages refer to it by it."""
    kind: str
    """``train`` (a ``garmentnerf train`` run) or ``fit_body_appearance`` (``garmentnerf body
    fit-appearance`` of the previous train stage's run, written into this stage's folder)."""
    iterations: int
    """*train*: the NeRF steps of the schedule (``--iterations``: the lr decays over them). *fit*: the
    optimisation steps (``--steps``)."""
    description: str = ""
    """What the stage is and why (free text)."""
    model: str | None = None
    """*train*, required: the model config's base: a preset (``paper``, ``cpu_small``, ``tiny``) or
    ``previous`` (the previous train stage's config, overrides included)."""
    config: Mapping[str, object] = dataclasses.field(default_factory=lambda: MappingProxyType({}))
    """*train*: model config overrides on the base (:func:`recipe_model_config`)."""
    scene: str | None = None
    """*train*: the scene it trains on: None for the ``--scene`` given, ``demo:<garment>`` for a bundled
    demo's scene, or the name of one of the recipe's ``scenes``."""
    sequences: tuple[str, ...] | None = None
    """*train*: the training sequences (None: every ``train``-split sequence of the scene)."""
    frames: str | None = None
    """*train*: the frame range of each sequence, ``A:B`` (``--frames``; None: all)."""
    generator_iterations: int | None = None
    """*train*: the G_img pre-training steps (``--generator-iterations``; None: the config's)."""
    stop_after: int | None = None
    """*train*: stop at this global step, short of the schedule's end (``--stop-after``); the stage is
    then finished."""
    training_crop_density: float | None = None
    """*train*: ``--training-crop-density`` for this stage (None: the config's; not inherited by
    ``model: previous``, which takes the config alone)."""
    init: str | None = None
    """*train*: the weights it starts from (``--init-weights``): ``previous`` (the previous train stage's),
    an earlier train stage's name, or None (a fresh model)."""
    init_generator: str | None = None
    """*train*: the pre-trained G_img it starts from (``--init-generator``): ``previous``, an earlier train
    stage's name, or None."""
    body_appearance: str | None = None
    """*train*: the body appearance it composes with (``--body-appearance``): the name of an earlier
    ``fit_body_appearance`` stage, or None (the network draws the body)."""
    seed: int = 0
    """*train*: ``--seed``."""
    ckpt_every: int | None = None
    """*train*: steps between checkpoints (``--ckpt-every``; None: the trainer's default): what a
    killed stage loses at most."""
    threads: int | None = None
    """torch CPU threads (``--threads``; None: torch's default); ``train --threads`` overrides it."""
    frame_stride: int = 5
    """*fit*: every N-th frame of the training sequences (``--frame-stride``)."""
    albedo_prior: float | None = None
    """*fit*: ``--albedo-prior`` (None: the fit's default)."""

    @property
    def trains(self) -> bool:
        """Whether it is a ``train`` stage."""
        return self.kind == "train"


#: The :class:`Stage` fields only ``train`` stages have, and those only fit stages have.
_TRAIN_ONLY = ("model", "config", "scene", "sequences", "frames", "generator_iterations", "stop_after",
               "training_crop_density", "init", "init_generator", "body_appearance", "seed", "ckpt_every")
_FIT_ONLY = ("frame_stride", "albedo_prior")


@dataclass(frozen=True)
class Recipe:
    """A recipe: the scenes it makes and its stages, in the order they run."""

    name: str
    """Its name (free of spaces: a folder name)."""
    description: str
    """What it makes (free text)."""
    stages: tuple[Stage, ...]
    """The stages, in order (at least one train stage)."""
    scenes: tuple[RecipeScene, ...] = ()
    """Scenes made from other scenes with more sequences (what stages name in ``scene``)."""

    def stage(self, name: str) -> Stage:
        """The stage called ``name`` (KeyError if none is)."""
        for stage in self.stages:
            if stage.name == name:
                return stage
        raise KeyError(name)

    def scene_named(self, name: str) -> RecipeScene | None:
        """The recipe scene called ``name``, or None."""
        return next((s for s in self.scenes if s.name == name), None)

    def to_json(self) -> dict:
        """The recipe as a JSON object, every field written (what ``recipe.json`` of a run records)."""
        return {"format": RECIPE_FORMAT, "version": RECIPE_VERSION, "name": self.name,
                "description": self.description, "scenes": [_plain(dataclasses.asdict(s)) for s in self.scenes],
                "stages": [_plain(_stage_json(s)) for s in self.stages]}


def _stage_json(stage: Stage) -> dict:
    """``stage``'s fields as a dict, without those of the other kind."""
    other = _FIT_ONLY if stage.trains else _TRAIN_ONLY
    first = ("name", "kind", "description")
    rest = [f.name for f in dataclasses.fields(Stage) if f.name not in other and f.name not in first]
    return {name: getattr(stage, name) for name in (*first, *rest)}


def _plain(value):
    """``value`` as JSON has it: mappings as dicts, tuples as lists."""
    if isinstance(value, Mapping):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


# ---- reading -------------------------------------------------------------------------------------------
def load_json(text: str, where: str):
    """The JSON value of ``text`` (a file called ``where``), read by the project's strict reader
    (:func:`~garmentnerf.io_utils.parse_json_strict`: NaN, Infinity, numbers beyond a float and a key
    given twice in an object are refused, naming the key)."""
    try:
        return parse_json_strict(text, where)
    except ValueError as exc:
        raise RecipeError(str(exc)) from None


def load_recipe_json(path) -> object:
    """The JSON value of the recipe file ``path`` (:func:`~garmentnerf.io_utils.read_json_strict`);
    FileNotFoundError / RecipeError naming it."""
    try:
        return read_json_strict(path, "recipe")
    except (IsADirectoryError, ValueError) as exc:
        raise RecipeError(str(exc)) from None


def read_recipe(path) -> Recipe:
    """The validated recipe in the JSON file ``path`` (every stage's model config built once).

    Raises:
        FileNotFoundError: no such file.
        RecipeError: anything else, one line naming the file and the key.
    """
    recipe = parse_recipe(load_recipe_json(path), str(path))
    stage_model_configs(recipe, str(path))
    return recipe


@dataclass(frozen=True)
class _Object:
    """One JSON object of a recipe, read key by key with its type checked; errors name ``where``."""

    data: dict
    """The object."""
    file: str
    """The recipe file (for messages)."""
    where: str
    """The object's path in the file, e.g. ``stages[2]`` ("" at the top)."""

    def key(self, name: str) -> str:
        return f"{self.where}.{name}" if self.where else name

    def fail(self, name: str, message: str) -> RecipeError:
        return RecipeError(f"{self.file}: {self.key(name)}: {message}")

    def check_keys(self, known: tuple[str, ...], misplaced: Mapping[str, str] = MappingProxyType({})) -> None:
        """Refuse a key not in ``known`` (``misplaced``: keys known elsewhere, with why not here)."""
        for name in self.data:
            if name in misplaced:
                raise self.fail(name, misplaced[name])
            if name not in known:
                close = difflib.get_close_matches(name, known, n=1)
                hint = f" (did you mean '{close[0]}'?)" if close else f" (known: {', '.join(known)})"
                raise self.fail(name, f"unknown key{hint}")

    def get(self, name: str, kind: str, default=dataclasses.MISSING):
        """The value of key ``name`` checked as ``kind`` (``str``, ``int``, ``number``, ``bool``,
        ``str_list``, ``list``, ``object``); ``default`` when absent (required when not given).
        A JSON null is the default of an optional key."""
        if name not in self.data or (self.data[name] is None and default is not dataclasses.MISSING):
            if default is dataclasses.MISSING:
                raise self.fail(name, "missing")
            return default
        value = self.data[name]
        ok = {"str": lambda v: isinstance(v, str),
              "int": lambda v: isinstance(v, int) and not isinstance(v, bool),
              "number": lambda v: isinstance(v, (int, float)) and not isinstance(v, bool),
              "bool": lambda v: isinstance(v, bool),
              "str_list": lambda v: isinstance(v, list) and all(isinstance(x, str) for x in v),
              "list": lambda v: isinstance(v, list),
              "object": lambda v: isinstance(v, dict)}[kind]
        if not ok(value):
            wanted = {"str": "a string", "int": "an integer", "number": "a number", "bool": "true or false",
                      "str_list": "a list of strings", "list": "a list", "object": "an object"}[kind]
            raise self.fail(name, f"must be {wanted}, got {json.dumps(value)}")
        return float(value) if kind == "number" else value

    def at_least(self, name: str, value, least):
        """``value`` (of key ``name``) when it is at least ``least`` (None passes)."""
        if value is not None and value < least:
            raise self.fail(name, f"must be at least {least}, got {value}")
        return value

    def name(self, name: str) -> str:
        """Key ``name``: a required name a folder may have."""
        value = self.get(name, "str")
        if not _NAME.match(value):
            raise self.fail(name, f"'{value}' must be letters, digits, '_', '-' or '.', starting with a letter or digit")
        return value

    def child(self, name: str, value, index: int | None = None) -> "_Object":
        where = self.key(name) + ("" if index is None else f"[{index}]")
        if not isinstance(value, dict):
            raise RecipeError(f"{self.file}: {where}: must be an object")
        return _Object(value, self.file, where)


def _frozen(value, obj: _Object, key: str):
    """A config override value, read-only: lists become tuples, objects mappings."""
    if isinstance(value, list):
        return tuple(_frozen(v, obj, f"{key}[{i}]") for i, v in enumerate(value))
    if isinstance(value, dict):
        return MappingProxyType({k: _frozen(v, obj, f"{key}.{k}") for k, v in value.items()})
    return value


def _extra_sequence(obj: _Object) -> ExtraSequence:
    obj.check_keys(tuple(f.name for f in dataclasses.fields(ExtraSequence)))
    return ExtraSequence(name=obj.name("name"), motions=obj.get("motions", "str"),
                         frames=obj.at_least("frames", obj.get("frames", "int"), 1),
                         garment=obj.get("garment", "str", None))


def _recipe_scene(obj: _Object) -> RecipeScene:
    obj.check_keys(tuple(f.name for f in dataclasses.fields(RecipeScene)))
    base = obj.get("base", "str", None)
    if base is not None:
        _check_demo_scene(obj, "base", base)
    sequences = obj.get("sequences", "list")
    if not sequences:
        raise obj.fail("sequences", "must list at least one sequence (a scene without new ones: name its base "
                                    "in the stages' scene instead)")
    extras = tuple(_extra_sequence(obj.child("sequences", s, i)) for i, s in enumerate(sequences))
    names = [e.name for e in extras]
    for i, name in enumerate(names):
        if name in names[:i]:
            raise obj.fail(f"sequences[{i}].name", f"'{name}' is given twice")
    return RecipeScene(obj.name("name"), base, extras, obj.get("description", "str", ""))


def _check_demo_scene(obj: _Object, key: str, value: str) -> None:
    """Refuse a ``demo:<garment>`` naming no demo."""
    from garmentnerf.demos import DEMO_NAMES  # the demo registry; no torch

    garment = value[len(DEMO_SCENE_PREFIX):] if value.startswith(DEMO_SCENE_PREFIX) else None
    if garment not in DEMO_NAMES:
        raise obj.fail(key, f"'{value}' is not a scene a recipe knows (the --scene: null; a demo's: "
                            f"{', '.join(DEMO_SCENE_PREFIX + n for n in DEMO_NAMES)})")


def _stage(obj: _Object) -> Stage:
    fields = tuple(f.name for f in dataclasses.fields(Stage))
    kind = obj.get("kind", "str")
    if kind not in STAGE_KINDS:
        raise obj.fail("kind", f"'{kind}' is not a stage kind ({', '.join(STAGE_KINDS)})")
    trains = kind == "train"
    other = _FIT_ONLY if trains else _TRAIN_ONLY
    obj.check_keys(tuple(f for f in fields if f not in other),
                   {f: f"not a field of a {kind} stage" for f in other})
    common = {"name": obj.name("name"), "kind": kind, "description": obj.get("description", "str", ""),
              "iterations": obj.at_least("iterations", obj.get("iterations", "int"), 1),
              "threads": obj.at_least("threads", obj.get("threads", "int", None), 1)}
    if not trains:
        prior = obj.at_least("albedo_prior", obj.get("albedo_prior", "number", None), 0)
        return Stage(**common, frame_stride=obj.at_least("frame_stride", obj.get("frame_stride", "int", 5), 1),
                     albedo_prior=prior)
    config = obj.get("config", "object", {})
    frames = obj.get("frames", "str", None)
    if frames is not None:
        try:
            parse_frames(frames, "frames")
        except ValueError as exc:
            raise obj.fail("frames", str(exc)) from None
    density = obj.at_least("training_crop_density", obj.get("training_crop_density", "number", None), 0)
    sequences = obj.get("sequences", "str_list", None)
    if sequences is not None and not sequences:
        raise obj.fail("sequences", "lists no sequence (null: every training sequence of the scene)")
    return Stage(
        **common, model=obj.get("model", "str"),
        config=MappingProxyType({k: _frozen(v, obj, f"config.{k}") for k, v in config.items()}),
        scene=obj.get("scene", "str", None), sequences=None if sequences is None else tuple(sequences),
        frames=frames, generator_iterations=obj.at_least("generator_iterations",
                                                         obj.get("generator_iterations", "int", None), 0),
        stop_after=obj.at_least("stop_after", obj.get("stop_after", "int", None), 1),
        training_crop_density=density, init=obj.get("init", "str", None),
        init_generator=obj.get("init_generator", "str", None),
        body_appearance=obj.get("body_appearance", "str", None), seed=obj.get("seed", "int", 0),
        ckpt_every=obj.at_least("ckpt_every", obj.get("ckpt_every", "int", None), 1))


def parse_recipe(data, file: str) -> Recipe:
    """The :class:`Recipe` of a recipe file's JSON value ``data`` (the file called ``file``), its
    fields and references checked (model configs are not built: :func:`stage_model_configs`).

    Raises:
        RecipeError: one line naming ``file`` and the key.
    """
    if not isinstance(data, dict):
        raise RecipeError(f"{file}: a recipe is a JSON object")
    top = _Object(data, file, "")
    top.check_keys(("format", "version", "name", "description", "scenes", "stages"))
    if top.get("format", "str") != RECIPE_FORMAT:
        raise top.fail("format", f"must be '{RECIPE_FORMAT}', got '{data['format']}'")
    if top.get("version", "int") != RECIPE_VERSION:
        raise top.fail("version", f"{data['version']} is not supported (this program reads version {RECIPE_VERSION})")
    scenes = tuple(_recipe_scene(top.child("scenes", s, i)) for i, s in enumerate(top.get("scenes", "list", [])))
    stages = tuple(_stage(top.child("stages", s, i)) for i, s in enumerate(top.get("stages", "list")))
    if not any(s.trains for s in stages):
        raise top.fail("stages", "must hold at least one train stage")
    recipe = Recipe(top.name("name"), top.get("description", "str", ""), stages, scenes)
    _check_references(recipe, top)
    return recipe


def previous_train_stage(recipe: Recipe, index: int) -> Stage | None:
    """The last train stage before ``recipe.stages[index]``, or None."""
    return next((s for s in reversed(recipe.stages[:index]) if s.trains), None)


def _check_references(recipe: Recipe, top: _Object) -> None:
    """Refuse names given twice and references to what is not an earlier stage of the right kind."""
    scene_names = [s.name for s in recipe.scenes]
    for i, name in enumerate(scene_names):
        if name in scene_names[:i]:
            raise top.fail(f"scenes[{i}].name", f"'{name}' is given twice")
    seen: dict[str, Stage] = {}
    for i, stage in enumerate(recipe.stages):
        where = f"stages[{i}]"
        if stage.name in seen:
            raise top.fail(f"{where}.name", f"'{stage.name}' is given twice")
        previous = previous_train_stage(recipe, i)
        if not stage.trains:
            if previous is None:
                raise top.fail(f"{where}.kind", "a fit_body_appearance stage fits the previous train stage's run, "
                                                "and there is none before it")
            seen[stage.name] = stage
            continue
        if stage.model not in (*MODEL_PRESETS, "previous"):
            raise top.fail(f"{where}.model", f"'{stage.model}' is neither a preset ({', '.join(MODEL_PRESETS)}) "
                                             f"nor 'previous'")
        if stage.model == "previous" and previous is None:
            raise top.fail(f"{where}.model", "'previous': there is no train stage before it")
        for key in ("init", "init_generator"):
            ref = getattr(stage, key)
            if ref is None:
                continue
            if ref == "previous":
                if previous is None:
                    raise top.fail(f"{where}.{key}", "'previous': there is no train stage before it")
            elif ref not in seen or not seen[ref].trains:
                raise top.fail(f"{where}.{key}", _not_earlier(ref, "train", seen, recipe))
        ref = stage.body_appearance
        if ref is not None and (ref not in seen or seen[ref].trains):
            raise top.fail(f"{where}.body_appearance", _not_earlier(ref, "fit_body_appearance", seen, recipe))
        if stage.scene is not None and stage.scene not in scene_names:
            if not stage.scene.startswith(DEMO_SCENE_PREFIX):
                raise top.fail(f"{where}.scene", f"'{stage.scene}' is not one of the recipe's scenes "
                                                 f"({', '.join(scene_names) or 'it has none'}) nor a demo's "
                                                 f"(demo:<garment>); null: the --scene")
            _check_demo_scene(top, f"{where}.scene", stage.scene)
        if stage.stop_after is not None and stage.generator_iterations is not None \
                and stage.stop_after > stage.generator_iterations + stage.iterations:
            raise top.fail(f"{where}.stop_after", f"{stage.stop_after} is past the schedule's end "
                                                  f"({stage.generator_iterations} + {stage.iterations} steps)")
        seen[stage.name] = stage


def _not_earlier(ref: str, kind: str, seen: Mapping[str, Stage], recipe: Recipe) -> str:
    """Why ``ref`` is not an earlier stage of ``kind`` (for a message)."""
    if ref in seen:
        return f"'{ref}' is a {seen[ref].kind} stage, not a {kind} stage"
    known = [s.name for s in recipe.stages]
    if ref in known:
        return f"'{ref}' comes later; a stage can only use an earlier one"
    earlier = [n for n, s in seen.items() if s.kind == kind]
    return f"no stage is called '{ref}' (earlier {kind} stages: {', '.join(earlier) or 'none'})"


# ---- model configs ---------------------------------------------------------------------------------------
def _kind_of(value) -> str:
    """The JSON kind a config value has (for the override checks)."""
    if isinstance(value, bool):
        return "bool"
    if isinstance(value, int):
        return "int"
    if isinstance(value, float):
        return "number"
    if isinstance(value, str):
        return "str"
    if isinstance(value, (list, tuple)):
        return "list"
    return "other"


def recipe_model_config(base: str | ModelConfig, overrides: Mapping[str, object]) -> ModelConfig:
    """The model config of a recipe stage: ``base`` (a preset name, or a config: the previous train
    stage's) with ``overrides`` (``{"component.field": value}`` of :class:`ModelConfig`, JSON values,
    e.g. ``{"schedule.lr": 1e-3}``) applied.

    The one function through which a recipe's config keys reach :class:`ModelConfig`. Each override
    must be a field, of the field's kind (an integer for an integer, a number for a float, a list for
    a tuple, ...); the result is validated.

    Raises:
        ValueError: an unknown key, a value of the wrong kind, or a config the model refuses
            (one line, naming the key where it can).
    """
    config = model_config_for(base) if isinstance(base, str) else base
    current = {f"{name}.{key}": value for name, part in config.to_dict().items() for key, value in part.items()}
    for key, value in overrides.items():
        if key not in current:
            close = difflib.get_close_matches(key, list(current), n=1)
            raise ValueError(f"'{key}' is not a model config field" + (f" (did you mean '{close[0]}'?)" if close else ""))
        want, got = _kind_of(current[key]), _kind_of(value)
        if want != "other" and got != want and not (want == "number" and got == "int"):
            wanted = {"bool": "true or false", "int": "an integer", "number": "a number", "str": "a string",
                      "list": "a list"}[want]
            raise ValueError(f"{key}: must be {wanted}, got {json.dumps(_plain(value))}")
    try:
        return config.updated(_plain(overrides))
    except (TypeError, ValueError) as exc:
        raise ValueError(" ".join(str(exc).split())) from None


def stage_model_configs(recipe: Recipe, file: str = "recipe") -> dict[str, ModelConfig]:
    """The model config each train stage starts its run with, by stage name (``model`` + ``config``
    through :func:`recipe_model_config`). RecipeError naming ``file`` and the stage's ``config``."""
    configs: dict[str, ModelConfig] = {}
    last: ModelConfig | None = None
    for i, stage in enumerate(recipe.stages):
        if not stage.trains:
            continue
        try:
            last = recipe_model_config(last if stage.model == "previous" else stage.model, stage.config)
        except ValueError as exc:
            raise RecipeError(f"{file}: stages[{i}].config: {exc}") from None
        configs[stage.name] = last
    return configs


def first_difference(a, b, where: str = "") -> str | None:
    """The first key path where the JSON values ``a`` and ``b`` differ, with both values, or None."""
    if isinstance(a, dict) and isinstance(b, dict):
        for key in list(a) + [k for k in b if k not in a]:
            if key not in a or key not in b:
                return f"{where}.{key}" if where else key
            found = first_difference(a[key], b[key], f"{where}.{key}" if where else key)
            if found:
                return found
        return None
    if isinstance(a, list) and isinstance(b, list):
        found = next((d for i, (x, y) in enumerate(zip(a, b)) if (d := first_difference(x, y, f"{where}[{i}]"))),
                     None)
        return found or (None if len(a) == len(b) else f"{where} ({len(a)} against {len(b)} entries)")
    if a == b and isinstance(a, bool) == isinstance(b, bool):
        return None
    shown = [json.dumps(v) if not isinstance(v, (dict, list)) else ("an object" if isinstance(v, dict) else "a list")
             for v in (a, b)]
    return f"{where or 'the recipe'} ({shown[0]} against {shown[1]})"
