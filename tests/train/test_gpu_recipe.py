"""The documented GPU recipe (`docs/recipes/gpu_paper_size.json`, `docs/recipes/README.md`): the
bundled model's recipe at the paper's network size, whose weights still fit the bundle."""

from __future__ import annotations

import json
from pathlib import Path

import torch
from safetensors.torch import save_file

from garmentnerf.cli.train_cmd import read_model_config
from garmentnerf.model.config import ModelConfig
from garmentnerf.runs import build_model

REPO = Path(__file__).resolve().parents[2]
RECIPE = REPO / "docs" / "recipes" / "gpu_paper_size.json"
BUNDLED_RUN = REPO / "garmentnerf" / "assets" / "demo" / "run" / "run.json"

#: What makes the network the paper's size (the paper preset's values).
PAPER_SIZES = ("decoder.image_resolution", "encoder.reference_resolution", "decoder.feature_image_resolution",
               "nerf.appearance_dim", "encoder.neural_texture_resolution", "nerf.mlp_depth", "nerf.mlp_width",
               "sampler.samples_per_ray", "decoder.width", "decoder.min_width", "decoder.extra_layers")
#: Fields the recipe may set apart from the bundled recipe: the sizes and the schedule.
SCHEDULE = ("schedule.lr", "schedule.lr_final", "schedule.iterations", "schedule.generator_iterations",
            "loss.segmentation_start")
#: The bundled model's last stage learned per-frame codes alone on its finished field (its TRAINING.md): a
#: stage after the field's recipe, which the GPU recipe trains (the codes would follow it the same way).
CODES_STAGE = ("frame_codes.resolution", "frame_codes.lr_scale", "frame_codes.count", "schedule.trained_parameters")
#: The demo budget's limit on the bundled weights.
BUNDLE_LIMIT_BYTES = 25_000_000


def dotted(cfg: ModelConfig) -> dict:
    """``{"component.field": value}`` of every field of ``cfg``."""
    return {f"{name}.{k}": v for name, part in cfg.to_dict().items() for k, v in part.items()}


def bundled_config() -> ModelConfig:
    """The bundled model's config (its run.json)."""
    return ModelConfig.from_dict(json.loads(BUNDLED_RUN.read_text())["model_config"])


def test_recipe_has_the_paper_sizes_and_the_bundled_recipe_otherwise():
    recipe = dotted(read_model_config(RECIPE))
    paper = dotted(ModelConfig.paper())
    assert {k: recipe[k] for k in PAPER_SIZES} == {k: paper[k] for k in PAPER_SIZES}
    bundled = dotted(bundled_config())
    differing = {k for k in recipe if recipe[k] != bundled[k]}
    allowed = set(PAPER_SIZES) | set(SCHEDULE) | set(CODES_STAGE)
    assert differing <= allowed, sorted(differing - allowed)


def test_recipe_weights_fit_the_bundle_as_float16(tmp_path):
    model = build_model(read_model_config(RECIPE))
    state = {k: v.detach().to(torch.float16).contiguous() for k, v in model.state_dict().items()}
    path = tmp_path / "model.safetensors"
    save_file(state, str(path))
    size = path.stat().st_size
    assert size <= BUNDLE_LIMIT_BYTES, size
    # and the network is larger than the bundled one where the garment is drawn: the MLP and decoder
    bundled = build_model(bundled_config())
    for part in ("nerf", "decoder"):
        ours = sum(p.numel() for p in getattr(model, part).parameters())
        theirs = sum(p.numel() for p in getattr(bundled, part).parameters())
        assert ours > 3 * theirs, (part, ours, theirs)
