"""The small model configuration the pipeline, sampler and stability tests share."""

from __future__ import annotations

from garmentnerf.model.config import ModelConfig
from garmentnerf.train.trainer import tiny_config


def tiny_pipeline_config(**changes) -> ModelConfig:
    """The ``tiny`` preset (a 64 x 64 image of 16 x 16 rays with 8 samples each: a few ms per
    render on one core) with ``changes`` applied on top."""
    cfg = tiny_config()
    return cfg.replace(**changes) if changes else cfg
