"""What a training run is set up with: the :class:`TrainConfig`, the model presets, and how a
resume reconciles the settings it is given with those its run recorded (see
:mod:`garmentnerf.train.trainer`'s "Resume").
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType

import torch

from garmentnerf.model.config import LossConfig, ModelConfig
from garmentnerf.model.pipeline import bfloat16_is_fast
from garmentnerf.runs import recorded_scene_path

__all__ = ["TrainConfig", "MODEL_PRESETS", "TRAIN_DEFAULTS", "RUN_SETTINGS", "OVERRIDABLE_SETTINGS",
           "TRAINING_PRECISIONS", "model_config_for", "training_precision",
           "new_run_settings", "resume_settings", "show_setting"]

MODEL_PRESETS = ("paper", "cpu_small", "tiny")

#: What a new run uses for the :class:`TrainConfig` fields left at None (a resume: the run's values).
TRAIN_DEFAULTS = MappingProxyType({"preset": "cpu_small", "seed": 0, "log_every": 10, "image_every": 500,
                                   "ckpt_every": 1000, "keep_checkpoints": 2, "perceptual": "auto"})
#: :class:`TrainConfig` fields that define the run: a resume with another value is refused.
RUN_SETTINGS = ("preset", "seed", "iterations", "generator_iterations", "sequences", "frames", "cameras",
                "init_generator", "init_weights", "body_appearance", "precision")
#: What :attr:`TrainConfig.precision` may be (``auto`` is resolved when a run starts: :func:`training_precision`).
TRAINING_PRECISIONS = ("auto", "float32", "bfloat16")
#: :class:`TrainConfig` fields a resume may change (from the resumed step on; recorded in ``overrides``).
OVERRIDABLE_SETTINGS = ("log_every", "image_every", "ckpt_every", "keep_checkpoints", "perceptual", "vgg19_weights")


def model_config_for(preset: str) -> ModelConfig:
    """The :class:`ModelConfig` of a preset name (``paper``, ``cpu_small``, ``tiny``)."""
    if preset == "paper":
        return ModelConfig.paper()
    if preset == "cpu_small":
        return ModelConfig.cpu_small()
    if preset == "tiny":
        return ModelConfig.tiny()
    raise ValueError(f"unknown preset '{preset}' (known: {', '.join(MODEL_PRESETS)})")


@dataclass
class TrainConfig:
    """Settings of one training run (everything not in the :class:`ModelConfig`).

    Fields marked *run* (:data:`RUN_SETTINGS`) define the run: on ``resume`` None means the
    run's value and another value is refused. Fields marked *override*
    (:data:`OVERRIDABLE_SETTINGS`): on ``resume`` None means the run's value, another value
    applies from the resumed step on and is recorded in ``run.json``'s ``overrides``. For a new
    run None means the default (:data:`TRAIN_DEFAULTS`, or as described).

    Each field is documented under it.
    """

    scene: str | Path | None
    """The scene folder (on resume None: the run's; another folder, e.g. a moved scene, is recorded in
    ``overrides``)."""
    out: str | Path
    """The run folder (must be empty or absent unless ``resume``)."""
    preset: str | None = None
    """*run*; model preset (``paper``, ``cpu_small``, ``tiny``; default ``cpu_small``) when ``model_config``
    is None. With a ``model_config`` the run records the preset it equals (apart from iterations and loss
    weights), else None."""
    model_config: ModelConfig | None = None
    """An explicit model config (overrides ``preset``); on resume the run's own config is used and this is
    ignored."""
    device: str = "cpu"
    """``cpu``, ``cuda`` or ``cuda:N`` (under torchrun ``cuda`` means ``cuda:LOCAL_RANK``)."""
    seed: int | None = None
    """*run*; seeds the initialisation, the (frame, camera) order and the ray jitter (default 0)."""
    iterations: int | None = None
    """*run*; overrides ``cfg.schedule.iterations`` (NeRF steps; the lr decay spans them)."""
    generator_iterations: int | None = None
    """*run*; overrides ``cfg.schedule.generator_iterations`` (G_img pre-training steps)."""
    stop_after: int | None = None
    """Stop (writing a checkpoint) once this global step is reached, without changing the schedule (resume
    later to continue); None: train to the end. Not inherited by a resume (given on one, it is recorded in
    ``overrides``)."""
    log_every: int | None = None
    """*override*; steps between TensorBoard scalars (losses, lr, psnr; default 10)."""
    image_every: int | None = None
    """*override*; steps between TensorBoard images (render | ground truth); 0: never (default 500)."""
    ckpt_every: int | None = None
    """*override*; steps between checkpoints (one is also written at the end of each stage, at the end and on
    Ctrl-C; default 1000)."""
    keep_checkpoints: int | None = None
    """*override*; checkpoints kept (the newest ones; default 2)."""
    resume: bool = False
    """Continue the run in ``out`` from its newest readable checkpoint, with its settings."""
    sequences: tuple[str, ...] | None = None
    """*run*; training sequences (default: every ``train``-split sequence of the scene)."""
    frames: tuple[int, ...] | None = None
    """*run*; frame indices used in each sequence (default: all)."""
    cameras: tuple[str, ...] | None = None
    """*run*; training cameras (default: every ``train``-split camera)."""
    perceptual: str | None = None
    """*override*; ``auto`` (the default: VGG19 when ``vgg19_weights``/``$GARMENTNERF_VGG19`` names ImageNet
    weights, else shift-tolerant LPIPS), ``vgg19``, ``stlpips`` or ``none``."""
    vgg19_weights: str | None = None
    """*override*; torchvision ``vgg19-dcbb9e9d.pth``."""
    progress: bool = True
    """Show a tqdm progress bar (rank 0)."""
    threads: int | None = None
    """``torch.set_num_threads`` (None: leave as is)."""
    cache_bytes: int = 2 << 30
    """Bound of the in-memory target cache (the ground-truth images at the training density)."""
    inputs_cache_bytes: int = 1 << 30
    """Bound of the in-memory cache of the frames' inputs (info maps, reference G-buffers and images:
    1.8 MB a frame at the bundled sizes with G_img's reference images); evicted frames are built again."""
    geometry_cache_bytes: int = 4 << 30
    """Bound of the frames' body geometry kept between NeRF steps (the bound closest-point search: 18 MB of
    tensors a frame for the bundled body, the 170 frames of the bundled scene 3.0 GiB); evicted frames are
    bound again. 0: bound at every step."""
    init_generator: str | Path | None = None
    """*run*; a weights file (a run's ``model.safetensors`` or a checkpoint) whose pre-trained G_img (with its
    neural texture) a new run starts from, skipping stage 1; the model configs must agree on G_img's shapes.
    With ``init_weights``, G_img is this file's and every other weight that file's (another garment's run
    as the start: G_img pre-trained on this scene's images, the rest from the other garment)."""
    init_weights: str | Path | None = None
    """*run*; a weights file (a run's ``model.safetensors`` or a checkpoint) a new run takes *all* its weights
    from, starting at the NeRF stage with a fresh optimiser and the full lr schedule (fine-tuning, e.g. with
    another ``training_crop_density``); the model configs must agree on every shape but those
    :mod:`~garmentnerf.train.transfer` and the growable MLP bridge (another garment's run as the start)."""
    training_crop_density: float | None = None
    """Sets the model config's ``training_crop_density`` for a new run (None: the preset's; 0: whole frames; > 0:
    character windows at that many pixels per scene pixel). A resume keeps the run's and refuses another."""
    body_appearance: str | Path | None = None
    """*run*; a body appearance file (``garmentnerf body fit-appearance``): every NeRF step composes its image
    with the body rasterised and drawn with it (frozen), so the network learns the garment and its visibility
    (the ``raster_body`` composition). Copied into the run folder, where renders find it; a resume uses that
    copy (None: the paper's composition, the network draws the body; on a resume: the run's)."""
    precision: str | None = None
    """*run*; the precision of the NeRF MLP's hidden layers in the NeRF steps (autocast; the input and density
    layers stay float32, see ``model/nerf_mlp.py``): ``float32``, ``bfloat16``, or ``auto`` (the default):
    bfloat16 where it is fast (:func:`~garmentnerf.model.pipeline.bfloat16_is_fast`), else float32. A new run
    records what ``auto`` chose, so a resume on another machine trains on as the run began; a run.json from
    before this setting means float32."""
    loss_weights: dict[str, float] | None = None
    """Overrides of the config's loss weights (:class:`~garmentnerf.model.config.LossConfig`),
    ``{"segmentation": 0.5}``. On a resume they apply from the
    resumed step on (a curriculum: e.g. add a term once the geometry is there); each change is logged and kept
    in ``run.json``'s ``loss_weight_changes`` so the run's recipe stays on record."""

    def validate(self) -> None:
        """Raise ValueError naming the first impossible setting (None fields are not checked)."""
        if self.preset is not None and self.preset not in MODEL_PRESETS:
            raise ValueError(f"unknown preset '{self.preset}' (known: {', '.join(MODEL_PRESETS)})")
        known = LossConfig.weight_names()
        for name, value in (self.loss_weights or {}).items():
            if name not in known:
                raise ValueError(f"unknown loss weight '{name}' (known: {', '.join(known)})")
            if not math.isfinite(value) or value < 0:
                raise ValueError(f"loss weight {name} must be a finite number >= 0, got {value}")
        for name in ("log_every", "ckpt_every", "keep_checkpoints"):
            value = getattr(self, name)
            if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
        if self.image_every is not None and (isinstance(self.image_every, bool) or not isinstance(self.image_every, int)
                                             or self.image_every < 0):
            raise ValueError(f"image_every must be an integer >= 0, got {self.image_every!r}")
        if self.seed is not None and (isinstance(self.seed, bool) or not isinstance(self.seed, int)):
            raise ValueError(f"seed must be an integer, got {self.seed!r}")
        if self.iterations is not None and self.iterations < 1:
            raise ValueError(f"iterations must be >= 1, got {self.iterations}")
        if self.generator_iterations is not None and self.generator_iterations < 0:
            raise ValueError(f"generator_iterations must be >= 0, got {self.generator_iterations}")
        if self.training_crop_density is not None and not (0 <= self.training_crop_density < math.inf):
            raise ValueError(f"training_crop_density must be a number >= 0, got {self.training_crop_density}")
        if self.precision is not None and self.precision not in TRAINING_PRECISIONS:
            raise ValueError(f"precision must be one of {', '.join(TRAINING_PRECISIONS)}, got {self.precision!r}")
        if self.stop_after is not None and self.stop_after < 1:  # 0 would stop before the first checkpoint
            raise ValueError(f"stop_after must be >= 1 (a run stopped at 0 would have nothing to resume from), "
                             f"got {self.stop_after}")

    def to_json(self) -> dict:
        """The fields as JSON values (``run.json``'s ``train``; ``model_config`` left out)."""
        out = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if f.name == "model_config":
                continue
            out[f.name] = str(v) if isinstance(v, Path) else (list(v) if isinstance(v, tuple) else v)
        return out


# ---- run settings on resume ------------------------------------------------------------------------
def _architecture(cfg: ModelConfig) -> dict:
    """``cfg`` without what a run may set apart from its preset (iterations, loss weights, the
    training crop)."""
    out = cfg.to_dict()
    for name in ("iterations", "generator_iterations", "training_crop_density"):
        out["schedule"].pop(name)
    for name in LossConfig.weight_names():
        out["loss"].pop(name)
    return out


def _preset_of(cfg: ModelConfig) -> str | None:
    """The preset ``cfg`` is (apart from iterations, loss weights and the training crop), or None."""
    arch = _architecture(cfg)
    return next((p for p in MODEL_PRESETS if _architecture(model_config_for(p)) == arch), None)


def _plain(value):
    """A setting as JSON has it (tuples as lists, paths as strings), to compare with ``run.json``."""
    if isinstance(value, (tuple, list)):
        return [_plain(v) for v in value]
    return str(value) if isinstance(value, Path) else value


def show_setting(name: str, value) -> str:
    """A setting as a message shows it (``all`` for no sequence/frame/camera selection, lists joined by ",")."""
    if value is None and name in ("sequences", "frames", "cameras"):
        return "all"
    if isinstance(value, (tuple, list)):
        return ",".join(str(v) for v in value)
    return str(value)


def training_precision(precision: str | None, device: str) -> str:
    """``precision`` (:data:`TRAINING_PRECISIONS`; None: ``auto``) as a run on ``device`` trains: ``auto`` is
    bfloat16 where bfloat16 is fast (:func:`~garmentnerf.model.pipeline.bfloat16_is_fast`), else float32."""
    if precision in (None, "auto"):
        return "bfloat16" if bfloat16_is_fast(torch.device(device)) else "float32"
    return precision


def new_run_settings(tc: TrainConfig) -> TrainConfig:
    """``tc`` with the defaults (:data:`TRAIN_DEFAULTS`) in its None fields, the preset it runs and the
    precision ``auto`` resolves to."""
    values = {k: v for k, v in TRAIN_DEFAULTS.items() if k != "preset" and getattr(tc, k) is None}
    values["precision"] = training_precision(tc.precision, tc.device)
    if tc.model_config is not None:
        values["preset"] = _preset_of(tc.model_config)
    elif tc.preset is None:
        values["preset"] = TRAIN_DEFAULTS["preset"]
    return dataclasses.replace(tc, **values)


def resume_settings(tc: TrainConfig, info: dict, cfg: ModelConfig, run_dir: Path) -> tuple[TrainConfig, dict]:
    """The settings a resume of the run (``run.json`` ``info``, model config ``cfg``) trains with,
    and what the resume changes (``{name: [run's value, new value]}``, for ``overrides``).

    Raises:
        ValueError: a :data:`RUN_SETTINGS` field of ``tc`` differs from the run's (names the
            flag, the run's value and the given one).
    """
    recorded = info.get("train") if isinstance(info.get("train"), dict) else {}
    run_values = {name: recorded.get(name) for name in RUN_SETTINGS}
    run_values["precision"] = recorded.get("precision") or "float32"  # runs from before it was recorded: float32
    if tc.precision is not None:
        tc = dataclasses.replace(tc, precision=training_precision(tc.precision, tc.device))
    run_values["seed"] = recorded.get("seed", info.get("seed"))
    rec_preset = recorded.get("preset")
    if rec_preset in MODEL_PRESETS and _architecture(model_config_for(rec_preset)) == _architecture(cfg):
        run_values["preset"] = rec_preset
    else:  # a custom config, or a run.json written by an older resume that recorded its default preset
        run_values["preset"] = _preset_of(cfg)
    # what the run trains for, when run.json recorded None (the preset's value)
    effective = {"iterations": cfg.schedule.iterations,
                 "generator_iterations": info.get("generator_iterations", cfg.schedule.generator_iterations)}
    values = {}
    for name in RUN_SETTINGS:
        given, run_value = getattr(tc, name), run_values[name]
        values[name] = tuple(run_value) if isinstance(run_value, list) else run_value
        if given is None:
            continue
        if name == "preset":
            same = given == run_value or _architecture(model_config_for(given)) == _architecture(cfg)
        elif name == "seed" and run_value is None:  # a run.json from before seeds were recorded
            same, values[name] = True, given
        else:
            same = _plain(given) == _plain(run_value) or (name in effective and given == effective[name])
        if not same:
            shown = effective[name] if run_value is None and name in effective else run_value
            if name == "preset" and shown is None:
                shown = "(a model config of no preset)"
            flag = "--" + name.replace("_", "-")
            raise ValueError(f"{flag} {show_setting(name, given)}: the run in {run_dir} was trained with "
                             f"{name} {show_setting(name, shown)}; --resume continues a run as it is (leave {flag} "
                             f"out, or train a new run into another --out)")
    changes = {}
    for name in OVERRIDABLE_SETTINGS:
        given, run_value = getattr(tc, name), recorded.get(name, TRAIN_DEFAULTS.get(name))
        values[name] = run_value
        if given is not None and _plain(given) != _plain(run_value):
            values[name] = given
            changes[name] = [run_value, _plain(given)]
    if tc.stop_after is not None:
        changes["stop_after"] = [recorded.get("stop_after"), tc.stop_after]
    if tc.scene is not None and info.get("scene"):
        if Path(tc.scene).resolve() != recorded_scene_path(run_dir, info).resolve():
            changes["scene"] = [info["scene"], str(tc.scene)]
    resolved = dataclasses.replace(tc, **values)
    # a run.json from before these settings were recorded: the defaults
    return dataclasses.replace(resolved, **{k: v for k, v in TRAIN_DEFAULTS.items()
                                            if k != "preset" and getattr(resolved, k) is None}), changes

