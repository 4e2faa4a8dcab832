"""The small model configuration the pipeline, sampler and stability tests share."""

from __future__ import annotations

from garmentnerf.model.config import ModelConfig


def tiny_pipeline_config(**changes) -> ModelConfig:
    """``cpu_small`` shrunk to a 64 x 64 image of 16 x 16 rays with 8 samples each (a few ms per
    render on one core), with ``changes`` applied on top."""
    cfg = ModelConfig.cpu_small().replace(
        image_resolution=64, feature_image_resolution=16, reference_resolution=32, info_map_resolution=32,
        encoder_depth=3, encoder_width_scale=0.25, neural_texture_resolution=32, neural_texture_levels=2,
        generator_width_scale=0.25, appearance_dim=16, mlp_depth=2, mlp_width=32, samples_per_ray=8,
        decoder_width=16, decoder_min_width=8, decoder_extra_layers=0)
    return cfg.replace(**changes) if changes else cfg
