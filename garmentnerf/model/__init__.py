"""The Garment Animation NeRF networks (pure torch: no data loading, no training loop).

One concept per module:

- :mod:`~garmentnerf.model.config`: :class:`ModelConfig`, the components' configs.
- :mod:`~garmentnerf.model.unet`: the U-Net of E (dynamic features) and G_en (detail features).
- :mod:`~garmentnerf.model.image_generator`: G_img, neural texture + generator (frozen after
  pre-training).
- :mod:`~garmentnerf.model.detail_features`: reading f^d from the front/back detail maps.
- :mod:`~garmentnerf.model.field`: the field interface (body points -> sigma, zeta).
- :mod:`~garmentnerf.model.nerf_mlp`: M_NeRF, the paper's field.
- :mod:`~garmentnerf.model.samplers`: the sampler interface (where along each ray to evaluate
  M_NeRF) and the paper's box sampler.
- :mod:`~garmentnerf.model.height_band`: the garment's height band and the sample filter made of it.
- :mod:`~garmentnerf.model.volume_rendering`: weights and compositing, dense and packed, and the
  segmented renderer with early ray termination.
- :mod:`~garmentnerf.model.palette`: M_D, the palette and the one composition formula.
- :mod:`~garmentnerf.model.losses`: the training losses (the NeRF's and G_img's pre-training).
- :mod:`~garmentnerf.model.perceptual`: the learned perceptual distances (LPIPS, shift-tolerant
  LPIPS): the perceptual training loss and evaluation metric.
- :mod:`~garmentnerf.model.frame_context`: a body frame's inputs (tensors the GL passes of
  :mod:`garmentnerf.render.frame_inputs` make) and features.
- :mod:`~garmentnerf.model.pipeline`: the model, wiring the paper's equations together
  (per frame: :meth:`~garmentnerf.model.pipeline.GarmentAnimationNeRF.prepare_frame`; per view:
  :meth:`~garmentnerf.model.pipeline.GarmentAnimationNeRF.render`, given a sampler and a filter).
"""

import importlib

from garmentnerf.model import volume_rendering
from garmentnerf.model.config import ModelConfig
from garmentnerf.model.detail_features import sample_image_features, select_detail_features
from garmentnerf.model.field import Field
from garmentnerf.model.frame_context import FrameFeatures, FrameInputs
from garmentnerf.model.image_generator import ImageGenerator, NeuralTexture, freeze
from garmentnerf.model.losses import garment_losses, generator_losses, offset_loss, palette_loss, sparsity_loss
from garmentnerf.model.nerf_mlp import GarmentNeRF, density_activation, trunc_exp
from garmentnerf.model.palette import (
    DecomposedMaps,
    Palette,
    PaletteDecoder,
    check_palette,
    compose,
    palette_from_labels,
)
from garmentnerf.model.samplers import (
    BoundSampler,
    BoxStratifiedSampler,
    RaySamples,
    SampleFilter,
    Sampler,
    body_aabb,
    ray_aabb_intersect,
)
from garmentnerf.model.unet import DetailEncoder, DynamicFeatureEncoder, UNet

__all__ = [
    "ModelConfig", "UNet", "DynamicFeatureEncoder", "DetailEncoder", "ImageGenerator", "NeuralTexture", "freeze",
    "sample_image_features", "select_detail_features", "Field", "GarmentNeRF", "density_activation",
    "trunc_exp", "Sampler", "BoundSampler", "SampleFilter", "RaySamples", "BoxStratifiedSampler", "body_aabb",
    "ray_aabb_intersect", "HeightRange", "HeightBandFilter", "measure_height_range",
    "volume_rendering", "PaletteDecoder", "DecomposedMaps", "Palette", "compose", "check_palette",
    "palette_from_labels", "garment_losses", "generator_losses", "sparsity_loss", "offset_loss", "palette_loss",
    "FrameInputs", "FrameFeatures", "GarmentAnimationNeRF", "RenderOutput",
]

#: Names of the modules that bring in the body and the geometry (seconds of imports), loaded on first
#: use so that ``import garmentnerf.model.config`` stays light.
_LAZY = {"GarmentAnimationNeRF": "pipeline", "RenderOutput": "pipeline",
         "HeightRange": "height_band", "HeightBandFilter": "height_band", "measure_height_range": "height_band"}


def __getattr__(name: str):
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'garmentnerf.model' has no attribute {name!r}")
    return getattr(importlib.import_module(f"garmentnerf.model.{module}"), name)
