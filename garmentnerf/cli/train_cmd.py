"""``garmentnerf train``: train a model on a scene into a run folder (see garmentnerf.train)."""

from __future__ import annotations

import argparse
import math
import signal
from pathlib import Path

from garmentnerf.cli.common import check_output_dir, parse_device
from garmentnerf.interrupts import interrupting
from garmentnerf.ranges import parse_frames


def register(sub) -> None:
    p = sub.add_parser("train", help="train the Garment Animation NeRF on a scene",
                       description="Two-stage training (G_img pre-training, then the NeRF) into a run folder: "
                                   "run.json + model.safetensors, checkpoints/, tb/ (TensorBoard). Ctrl-C saves "
                                   "a checkpoint (so does kill); --resume continues exactly, with the run's own "
                                   "settings from run.json. Under torchrun every process trains on its share "
                                   "of the views (gradients averaged). With --recipe, a recipe's stages (a "
                                   "demo's: its TRAINING.md) run in order into --out, each an ordinary run in "
                                   "--out/stages/, the last one published in --out itself.")
    p.add_argument("--recipe", default=None, metavar="FILE",
                   help="run a recipe's stages in order (garmentnerf/train/recipe.py): a recipe JSON file, or a "
                        "demo's name (skirt, tshirt, dress) for its shipped recipe. Each stage trains into "
                        "--out/stages/<NN>-<name>/ (fit stages write a body appearance there), the last train "
                        "stage is published into --out (run.json, model.safetensors, body_appearance.safetensors), "
                        "--out/recipe.json records the recipe and --out/recipe_log.json what ran. The recipe sets "
                        "what each stage trains: --preset, --model-config, --iterations, --generator-iterations, "
                        "--seed, --stop-after, --frames, --init-generator, --init-weights, "
                        "--training-crop-density, --body-appearance, --loss-weight and --precision are refused "
                        "with it; --device, --threads, --cache-gib, --perceptual, --vgg19-weights, --log-every, "
                        "--image-every, --ckpt-every and --no-progress apply to every stage")
    p.add_argument("--scene", default=None, metavar="DIR",
                   help="scene folder (required for a new run; on --resume default: the run's scene)")
    p.add_argument("--out", required=True, metavar="DIR", help="run folder, e.g. runs/skirt (must be empty "
                                                               "unless --resume)")
    # Options that define the run default to None: a new run fills in the default, --resume the
    # run's value (one given explicitly is checked against the run's; see Trainer).
    p.add_argument("--preset", default=None, choices=("paper", "cpu_small", "tiny"),
                   help="model size (default: cpu_small; on --resume: the run's, another one is refused)")
    p.add_argument("--model-config", default=None, metavar="JSON",
                   help="train this model config instead of a preset's: a JSON file of ModelConfig fields, or a "
                        "run's run.json (its model_config: the same recipe again); a new run only")
    p.add_argument("--iterations", type=int, default=None, metavar="N",
                   help="NeRF training steps (default: the preset's; the lr decays over them; on --resume: the "
                        "run's, another number is refused)")
    p.add_argument("--generator-iterations", type=int, default=None, metavar="N",
                   help="G_img pre-training steps (default: the preset's; 0 skips pre-training; on --resume: the "
                        "run's, another number is refused)")
    p.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N (default: cpu)")
    p.add_argument("--resume", action="store_true",
                   help="continue the run in --out from its newest readable checkpoint with the run's settings "
                        "(run.json); --preset, --seed, --frames, --iterations, --generator-iterations, "
                        "--init-generator, --init-weights or --training-crop-density that differ from the run's "
                        "are refused; --stop-after, --ckpt-every, --log-every, --image-every, --perceptual, "
                        "--vgg19-weights, --loss-weight and --scene apply from the resumed step on and are "
                        "recorded in run.json's overrides. With --recipe (or alone, on a folder --recipe made): "
                        "continue the recipe: finished stages are skipped, the interrupted one resumes from its "
                        "newest checkpoint, a recipe other than the folder's recipe.json is refused; re-running "
                        "without --resume is refused (the folder is not empty)")
    p.add_argument("--seed", type=int, default=None,
                   help="random seed (default: 0; on --resume: the run's, another one is refused)")
    p.add_argument("--stop-after", type=int, default=None, metavar="STEP",
                   help="stop with a checkpoint at this global step, at least 1 (resume later; a resume without "
                        "it trains to the end)")
    p.add_argument("--log-every", type=int, default=None, metavar="N",
                   help="steps between logged scalars (default: 10; on --resume: the run's)")
    p.add_argument("--image-every", type=int, default=None, metavar="N",
                   help="steps between logged images, 0: never (default: 500; on --resume: the run's)")
    p.add_argument("--ckpt-every", type=int, default=None, metavar="N",
                   help="steps between checkpoints (default: 1000; on --resume: the run's)")
    p.add_argument("--frames", default=None, metavar="A:B",
                   help="frame range used in each training sequence, Python slice syntax (default: all; on "
                        "--resume: the run's, another range is refused)")
    p.add_argument("--perceptual", default=None, choices=("auto", "vgg19", "stlpips", "none"),
                   help="perceptual loss (default: auto: VGG19 with --vgg19-weights, else shift-tolerant LPIPS; "
                        "on --resume: the run's)")
    p.add_argument("--vgg19-weights", default=None, metavar="PTH",
                   help="torchvision ImageNet VGG19 weights (vgg19-dcbb9e9d.pth); default $GARMENTNERF_VGG19 "
                        "(on --resume: the run's)")
    p.add_argument("--init-generator", default=None, metavar="SAFETENSORS",
                   help="start a new run from the pre-trained G_img in this weights file (a run's "
                        "model.safetensors or checkpoint) and skip G_img pre-training (a new run only); with "
                        "--init-weights, G_img from this file and every other weight from that one")
    p.add_argument("--init-weights", default=None, metavar="SAFETENSORS",
                   help="start a new run from all the weights of this file (a run's model.safetensors or "
                        "checkpoint) at the NeRF stage: fine-tuning (a new run only). The model sizes must match, "
                        "except a wider NeRF MLP, added per-frame codes, a decoder that also reads the shading "
                        "normals, and a palette of another size (another garment's run: each garment layer "
                        "starts from the file's garment channels, the colours from this scene's labels)")
    p.add_argument("--training-crop-density", type=float, default=None, metavar="D",
                   help="train on windows of the model's image size placed on the character, at D pixels per "
                        "scene pixel (1: the scene's own resolution); 0: whole frames (default: the preset's, 0; "
                        "a new run only)")
    p.add_argument("--body-appearance", default=None, metavar="SAFETENSORS",
                   help="compose every NeRF step's image with the body rasterised and drawn with this appearance "
                        "('garmentnerf body fit-appearance'), so the network learns the garment and its "
                        "visibility; copied into the run folder (a new run only)")
    p.add_argument("--loss-weight", action="append", default=[], metavar="NAME=VALUE",
                   help="override a loss weight of the config (repeatable), e.g. segmentation=0.5 (a field of the model config's loss); with "
                        "--resume it applies from the resumed step on and is recorded in run.json")
    p.add_argument("--precision", default=None, choices=("auto", "float32", "bfloat16"),  # TRAINING_PRECISIONS
                   help="NeRF MLP precision in the NeRF steps (default auto: bfloat16 where the machine multiplies "
                        "it fast, a CPU with AMX-BF16 or a CUDA GPU with bfloat16, else float32; on --resume: the "
                        "run's, another one is refused)")
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    p.add_argument("--cache-gib", type=float, default=None, metavar="G",
                   help="memory the per-frame caches may hold, in GiB (default 7: 4 for the body geometry, 2 for the "
                        "ground-truth images, 1 for the frames' inputs, shared in those proportions; training "
                        "results do not depend on it, only the time spent rebuilding what was evicted)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def _frames(text: str | None) -> tuple[int, ...] | None:
    """``--frames``: the frame indices used in each training sequence (a closed range: the sequences differ
    in length)."""
    frames = parse_frames(text, "--frames")
    return None if frames is None else tuple(frames)


def _loss_weights(items: list[str]) -> dict[str, float] | None:
    out = {}
    for item in items:
        name, sep, value = item.partition("=")
        try:
            if not sep:
                raise ValueError
            out[name.strip()] = float(value)
        except ValueError:
            raise ValueError(f"--loss-weight must be NAME=VALUE (a number), got {item!r}") from None
    return out or None


def _machine_options(args: argparse.Namespace) -> dict:
    """The cache bounds of ``--cache-gib`` (``{}`` without it), once ``--threads`` and it are checked."""
    if args.threads is not None and args.threads < 1:
        raise ValueError(f"--threads must be at least 1, got {args.threads}")
    if args.cache_gib is None:
        return {}
    if not (math.isfinite(args.cache_gib) and args.cache_gib > 0):
        raise ValueError(f"--cache-gib must be a positive number of GiB, got {args.cache_gib:g}")
    return cache_bounds(args.cache_gib)


def run(args: argparse.Namespace) -> int:
    # lazy: 'garmentnerf --help' and flag errors answer without torch and the model stack (0.4 s against 6 s)
    from garmentnerf.train.trainer import TrainConfig, Trainer

    parse_device(args.device)
    check_output_dir(args.out)
    if args.recipe is not None or (args.resume and is_recipe_folder(args.out)):
        return run_recipe_command(args)
    caches = _machine_options(args)

    bounds = (("--log-every", args.log_every, 1), ("--ckpt-every", args.ckpt_every, 1),
              ("--image-every", args.image_every, 0), ("--stop-after", args.stop_after, 1),
              ("--iterations", args.iterations, 1), ("--generator-iterations", args.generator_iterations, 0))
    for flag, value, least in bounds:
        if value is not None and value < least:
            raise ValueError(f"{flag} must be at least {least}, got {value}")
    # Options not given are None: a new run takes the defaults, --resume the run's own settings
    # (given ones are checked against the run's or recorded as overrides: Trainer).
    model_config = None
    if args.model_config is not None:
        if args.preset is not None:
            raise ValueError("--model-config and --preset exclude each other (the config holds every size)")
        if args.resume:
            raise ValueError("--model-config: a resume trains the run's own config (leave it out)")
        model_config = read_model_config(args.model_config)
    tc = TrainConfig(scene=args.scene, out=args.out, preset=args.preset, device=args.device, seed=args.seed,
                     model_config=model_config,
                     iterations=args.iterations, generator_iterations=args.generator_iterations,
                     stop_after=args.stop_after, log_every=args.log_every, image_every=args.image_every,
                     ckpt_every=args.ckpt_every, resume=args.resume, frames=_frames(args.frames),
                     perceptual=args.perceptual, vgg19_weights=args.vgg19_weights, threads=args.threads,
                     progress=not args.no_progress, init_generator=args.init_generator,
                     init_weights=args.init_weights, training_crop_density=args.training_crop_density,
                     body_appearance=args.body_appearance,
                     loss_weights=_loss_weights(args.loss_weight), precision=args.precision, **caches)
    if not args.resume and args.scene is None:
        raise ValueError("--scene is required for a new run")
    # `kill` (SIGTERM, what schedulers and `timeout` send) saves a checkpoint like Ctrl-C does.
    with interrupting(signal.SIGTERM), Trainer(tc) as trainer:
        result = trainer.train()
    return 130 if result.interrupted else 0


#: The flags that say what a run trains, which a recipe sets per stage: refused with --recipe.
RECIPE_EXCLUDES = ("preset", "model_config", "iterations", "generator_iterations", "seed", "stop_after", "frames",
                   "init_generator", "init_weights", "training_crop_density", "body_appearance", "loss_weight",
                   "precision")


def is_recipe_folder(out) -> bool:
    """Whether ``out`` is a folder ``train --recipe`` made (its ``recipe.json``, no checkpoints of its own)."""
    out = Path(out)
    return (out / "recipe.json").is_file() and (out / "recipe_log.json").is_file() and not (out / "checkpoints").exists()


def recipe_path(text: str) -> Path:
    """The recipe file ``--recipe`` names: a file, or a demo's name (its shipped ``recipe.json``)."""
    from garmentnerf.demos import DEMO_NAMES, demo

    path = Path(text)
    if not path.exists() and text in DEMO_NAMES:
        return demo(text).run_dir / "recipe.json"
    return path


def run_recipe_command(args: argparse.Namespace) -> int:
    """``train --recipe``: the recipe's stages in order into ``--out`` (:mod:`garmentnerf.train.recipe_run`)."""
    for name in RECIPE_EXCLUDES:
        value = getattr(args, name)
        if value is not None and value != []:
            flag = "--" + name.replace("_", "-")
            raise ValueError(f"--recipe and {flag}: the recipe sets each stage's {name.replace('_', ' ')} "
                             f"(leave {flag} out, or write it into the recipe)")
    # lazy: 'garmentnerf --help' and flag errors answer without torch and the model stack
    from garmentnerf.train.recipe import read_recipe
    from garmentnerf.train.recipe_run import RecipeOptions, run_recipe

    if args.recipe is not None:
        file = recipe_path(args.recipe)
    else:  # --resume of a recipe folder without --recipe: the recipe it was started with
        file = Path(args.out) / "recipe.json"
    recipe = read_recipe(file)
    caches = _machine_options(args)
    for flag, value, least in (("--log-every", args.log_every, 1), ("--ckpt-every", args.ckpt_every, 1),
                               ("--image-every", args.image_every, 0)):
        if value is not None and value < least:
            raise ValueError(f"{flag} must be at least {least}, got {value}")
    options = RecipeOptions(device=args.device, threads=args.threads, progress=not args.no_progress,
                            perceptual=args.perceptual, vgg19_weights=args.vgg19_weights, log_every=args.log_every,
                            image_every=args.image_every, ckpt_every=args.ckpt_every, caches=caches)
    # `kill` (SIGTERM) saves the running stage's checkpoint like Ctrl-C does
    with interrupting(signal.SIGTERM):
        return run_recipe(recipe, file, args.out, args.scene, resume=args.resume, options=options)


def cache_bounds(gib: float) -> dict[str, int]:
    """The :class:`~garmentnerf.train.settings.TrainConfig` cache bounds for ``gib`` GiB in all, shared as
    the defaults are (geometry 4 : targets 2 : inputs 1)."""
    unit = gib * 2**30 / 7
    return {"geometry_cache_bytes": int(4 * unit), "cache_bytes": int(2 * unit), "inputs_cache_bytes": int(unit)}


def read_model_config(path):
    """The :class:`~garmentnerf.model.config.ModelConfig` in a JSON file: a dict of its fields, or a
    run's ``run.json`` (its ``model_config``). ValueError naming the file when it is not one."""
    # lazy: 'garmentnerf --help' and flag errors answer without torch and the model stack (0.4 s against 6 s)
    from garmentnerf.model.config import ModelConfig

    from garmentnerf.io_utils import read_json_strict

    path = Path(path)
    try:
        data = read_json_strict(path, "model config")
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: missing (--model-config)") from None
    if isinstance(data, dict) and isinstance(data.get("model_config"), dict):
        data = data["model_config"]
    if not isinstance(data, dict):
        raise ValueError(f"{path}: not a model config (a JSON object of ModelConfig fields, or a run.json)")
    try:
        return ModelConfig.from_dict(dict(data))
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path}: not a valid model config: {' '.join(str(exc).split())}") from None
