"""The choices that define a Garment Animation NeRF: one small config per component.

A :class:`ModelConfig` holds seven component configs (:class:`EncoderConfig`,
:class:`FrameCodeConfig`, :class:`NerfConfig`, :class:`SamplerConfig`, :class:`DecoderConfig`,
:class:`LossConfig`, :class:`ScheduleConfig`); each field says what it does and the paper's value
(Sec. 4 and "Implementation details"; values the paper leaves out come from the authors' code,
``implementation-notes.md`` Sec. 1). What no preset or bundled model changes is a named constant
below, not a field. :meth:`ModelConfig.paper` is the published model, :meth:`ModelConfig.cpu_small`
the reduced model the bundled demos start from, :meth:`ModelConfig.tiny` a model for tests.

A run stores :meth:`ModelConfig.to_dict` (nested, one dict per component);
:meth:`ModelConfig.from_dict` reads it back, refusing unknown keys, and reads the flat dicts of
runs written before the components through :func:`convert_flat_config`, the one converter.
Changes are made with :meth:`ModelConfig.updated` and dotted names (``{"schedule.lr": 1e-3}``),
the form recipes and ``--loss-weight`` use.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

# ---- Constants: the paper's or the authors' values, which no preset or bundled model changes
#: Channels of the dynamic feature F^s_t (E's output) and of the detail feature F^d_t (paper: 8 each).
DYNAMIC_FEATURE_DIM = 8
DETAIL_FEATURE_DIM = 8
#: Width of the U-Nets' first conv, doubled at each of their ``UNET_DEPTH`` stride-2 blocks (paper: 32, 4).
UNET_BASE_WIDTH = 32
UNET_DEPTH = 4
#: Channels and pyramid levels of G_img's neural texture (DNG: 16 channels, 4 levels).
NEURAL_TEXTURE_CHANNELS = 16
NEURAL_TEXTURE_LEVELS = 4
#: Metres added on every side of the posed body's box the samples are drawn in (authors' code: 0.05).
BBOX_PADDING = 0.05
#: Metres from the skin at which the body density prior crosses 0 (``NerfConfig.body_prior_strength``).
BODY_PRIOR_WIDTH = 0.15
#: Palette colour offsets are ``OFFSET_SCALE * tanh(.)`` (small and bounded, so p + o stays near [0, 1]).
OFFSET_SCALE = 0.5
#: Added to the softplus of the blend weights before they are normalised (authors' code: 0.05).
BLEND_WEIGHT_FLOOR = 0.05
#: RGB the model's images are composed over: the ground truth's black background.
BACKGROUND = (0.0, 0.0, 0.0)
#: Gradient clipping by value in the NeRF stage (authors' code: 40).
GRAD_CLIP_VALUE = 40.0
#: Adam learning rate of G_img's pre-training (DNG: 1e-4).
GENERATOR_LR = 1e-4

DENSITY_ACTIVATIONS = ("softplus", "trunc_exp")


@dataclass
class EncoderConfig:
    """The networks that turn a frame into features: E, G_img and G_en (``model/unet.py``,
    ``model/image_generator.py``)."""

    history: int = 2
    """k, past velocity frames in E's input V_t; E sees 3 (k + 1) channels (paper: 2)."""
    info_map_resolution: int = 128
    """Side of the UV info maps N_t, V_t and of the dynamic feature map F^s_t (paper: 128)."""
    reference_resolution: int = 512
    """Side of G_img's front/back reference images and of G_en's detail maps F^d_t (paper: 512)."""
    width_scale: float = 1.0
    """Multiplies every width of E, G_en and G_img (paper: 1.0)."""
    neural_texture_resolution: int = 512
    """Side of the finest level of G_img's neural texture (DNG: 512)."""
    dynamic_feature: bool = True
    """Feed f^s_t (from E) to M_NeRF (paper: on; off only in the input-feature ablation)."""
    detail_feature: bool = True
    """Feed f^d_t (from G_img and G_en) to M_NeRF (paper: on; off only in the input-feature ablation)."""

    def validate(self) -> None:
        _at_least(self, 0, "history")
        _positive(self, "info_map_resolution", "reference_resolution", "width_scale", "neural_texture_resolution")
        for name in ("info_map_resolution", "reference_resolution"):
            size = getattr(self, name)
            if size % 2 ** UNET_DEPTH or size // 2 ** UNET_DEPTH < 2:
                raise ValueError(f"encoder.{name} ({size}) must be a multiple of {2 ** UNET_DEPTH} and at least "
                                 f"{2 ** (UNET_DEPTH + 1)} (the U-Nets' {UNET_DEPTH} halvings end at 2 x 2 or more)")
        if self.neural_texture_resolution // 2 ** (NEURAL_TEXTURE_LEVELS - 1) < 1:
            raise ValueError(f"encoder.neural_texture_resolution ({self.neural_texture_resolution}) is too small for "
                             f"{NEURAL_TEXTURE_LEVELS} levels")

    @property
    def in_channels(self) -> int:
        """Channels of E's input: the normal map and k velocity maps, 3 each."""
        return 3 * (self.history + 1)


@dataclass
class FrameCodeConfig:
    """A learned residual of E's output per training frame (not in the paper; ``model/frame_codes.py``):
    a memory of the training motion's frames; any other motion renders through E alone."""

    resolution: int = 0
    """Side r of each code (DYNAMIC_FEATURE_DIM x r x r, upsampled to E's output); 0: no codes."""
    count: int = 0
    """Codes held: set by the trainer to the training sequences' frames (0 in a config written by hand)."""
    lr_scale: float = 50.0
    """The codes learn at the schedule's rate times this when they train beside the other weights."""
    support_margin: int = -1
    """-1: each code covers the whole atlas; k >= 0: only the texels the garment's body points read, grown by k."""

    def validate(self) -> None:
        _at_least(self, 0, "resolution", "count")
        _positive(self, "lr_scale")
        if self.support_margin < -1:
            raise ValueError(f"frame_codes.support_margin must be -1 (dense) or >= 0 texels, got {self.support_margin}")
        if self.support_margin >= 0 and not self.resolution:
            raise ValueError("frame_codes.support_margin needs codes (frame_codes.resolution > 0)")

    @property
    def enabled(self) -> bool:
        """Whether the model has codes (a resolution and a count)."""
        return bool(self.resolution and self.count)


@dataclass
class NerfConfig:
    """M_NeRF: a sample's body-relative description -> density sigma and appearance zeta
    (``model/nerf_mlp.py``)."""

    appearance_dim: int = 128
    """zeta, channels of the appearance feature each sample carries to the volume rendering (paper: 128)."""
    mlp_depth: int = 6
    """Hidden Linear + ReLU layers (paper: 6)."""
    mlp_width: int = 256
    """Hidden width (paper: 256)."""
    density_activation: str = "softplus"
    """``softplus`` or ``trunc_exp`` of the raw density head (the authors' code uses it raw as alpha)."""
    density_bias: float = -1.0
    """Added to the raw density before the activation (Mip-NeRF's -1)."""
    density_scale: float = 1.0
    """Multiplies the activated density (1/metre per unit)."""
    body_prior_strength: float = 0.0
    """Raw-density offset that starts the density in the body's shape (0: the paper's plain MLP)."""
    shading_normals: bool = False
    """Give M_D the body's world normal under each pixel as 3 more channels (not in the paper)."""

    def validate(self) -> None:
        _positive(self, "appearance_dim", "mlp_depth", "mlp_width", "density_scale")
        _at_least(self, 0, "body_prior_strength")
        if self.density_activation not in DENSITY_ACTIVATIONS:
            raise ValueError(f"nerf.density_activation must be one of {DENSITY_ACTIVATIONS}, "
                             f"got {self.density_activation!r}")

    @property
    def zeta_channels(self) -> int:
        """Channels each sample carries into the volume rendering: zeta, then the shading normal if on."""
        return self.appearance_dim + 3 * int(self.shading_normals)


@dataclass
class SamplerConfig:
    """Where each ray's samples go in training and in the ``reference`` render (``model/samplers.py``)."""

    samples_per_ray: int = 64
    """Stratified samples between the ray's entry and exit of the padded body box (paper: 64)."""

    def validate(self) -> None:
        _positive(self, "samples_per_ray")


@dataclass
class DecoderConfig:
    """M_D: the volume-rendered feature image -> the palette-decomposed maps (``model/palette.py``)."""

    image_resolution: int = 512
    """Side of the output image (paper: 512)."""
    feature_image_resolution: int = 128
    """Rays per side of the feature image F^zeta; the image's side divided by a power of 2 (paper: 128)."""
    palette_size: int = 2
    """P, palette colours: one per garment layer, inner first, then the body's (paper: 2)."""
    radiance_channels: int = 3
    """3 (paper: r in R^3) or 1 (a grey shading that cannot absorb the garment's hue)."""
    width: int = 64
    """Width of the first conv, halved at every upsampling down to ``min_width`` (authors' code: 128)."""
    min_width: int = 32
    """Floor of the widths (authors' code: 32)."""
    extra_layers: int = 2
    """Full-resolution conv3x3 + LeakyReLU layers after the upsampling (authors' code: 2)."""

    def validate(self) -> None:
        _positive(self, "image_resolution", "feature_image_resolution", "palette_size", "width", "min_width")
        _at_least(self, 0, "extra_layers")
        ratio = self.image_resolution // self.feature_image_resolution
        if ratio * self.feature_image_resolution != self.image_resolution or ratio & (ratio - 1):
            raise ValueError(f"decoder.feature_image_resolution ({self.feature_image_resolution}) times a power of 2 "
                             f"must equal decoder.image_resolution ({self.image_resolution})")
        if self.radiance_channels not in (1, 3):
            raise ValueError(f"decoder.radiance_channels must be 1 or 3, got {self.radiance_channels}")

    @property
    def upsample_steps(self) -> int:
        """Nearest x2 upsamplings from the feature image to the output (paper: 2, 128 -> 512)."""
        return (self.image_resolution // self.feature_image_resolution).bit_length() - 1

    @property
    def out_channels(self) -> int:
        """Raw channels of M_D: radiance, 3 offsets and 1 weight per colour, mask (paper: 12)."""
        return self.radiance_channels + 4 * self.palette_size + 1


@dataclass
class LossConfig:
    """Weights of the training objective (``model/losses.py``; the paper's lambda_1..5, then ours)."""

    image: float = 1.0
    """L1 on the image (paper lambda_1 = 1)."""
    mask: float = 1.0
    """L1 on the mask (paper: inside L_img, 1)."""
    perceptual: float = 0.1
    """Perceptual term (paper lambda_2 = 0.1)."""
    perceptual_downsample: int = 1
    """The perceptual term compares image and target area-averaged by this factor (paper: 1)."""
    sparsity: float = 2e-4
    """Blend-weight sparsity (paper lambda_3 = 2e-4)."""
    offset: float = 0.03
    """Colour-offset magnitude (paper lambda_4 = 0.03)."""
    palette: float = 1e-3
    """Palette drift from its initial colours (paper lambda_5 = 1e-3)."""
    opacity: float = 1.0
    """L1 of the feature rays' opacity against the area-averaged mask (not in the paper: 0)."""
    segmentation: float = 0.0
    """L1 of each layer's blend weight against its label share of the pixel (not in the paper: 0)."""
    segmentation_start: int = 0
    """NeRF steps before the segmentation term applies."""
    segmentation_head_only: bool = True
    """The segmentation term trains only M_D's weight head, not the layers it shares."""

    def validate(self) -> None:
        _at_least(self, 0, "image", "mask", "perceptual", "sparsity", "offset", "palette", "opacity",
                  "segmentation", "segmentation_start")
        _positive(self, "perceptual_downsample")

    @classmethod
    def weight_names(cls) -> tuple[str, ...]:
        """The fields that weight a loss term (what ``train --loss-weight NAME=VALUE`` may change)."""
        return tuple(f.name for f in dataclasses.fields(cls) if f.type == "float")


@dataclass
class ScheduleConfig:
    """What a training run does over time (``train/trainer.py``)."""

    lr: float = 5e-4
    """Initial Adam learning rate of the NeRF stage (paper: 5e-4)."""
    lr_final: float = 5e-5
    """Learning rate at the last step, exponential decay (paper: 5e-5)."""
    iterations: int = 200_000
    """NeRF steps (paper: 200k)."""
    batch_size: int = 1
    """Images per step and process, back-propagated one at a time (paper: 1)."""
    trained_parameters: tuple[str, ...] = ()
    """Prefixes of the parameter names the NeRF stage trains; empty: every weight (paper)."""
    generator_iterations: int = 100_000
    """G_img pre-training steps (DNG: 100k)."""
    training_crop_density: float = 0.0
    """0: a step renders the whole training camera resized to the image (paper); d > 0: a window on the
    character at d pixels per scene pixel."""

    def __post_init__(self) -> None:
        self.trained_parameters = tuple(str(p) for p in self.trained_parameters)

    def validate(self) -> None:
        _positive(self, "lr", "lr_final", "iterations", "batch_size")
        _at_least(self, 0, "generator_iterations")
        if self.lr_final > self.lr:
            raise ValueError(f"schedule.lr_final ({self.lr_final}) must not exceed schedule.lr ({self.lr})")
        if any(not prefix for prefix in self.trained_parameters):
            raise ValueError(f"schedule.trained_parameters: empty prefix in {list(self.trained_parameters)} "
                             "(leave the list empty to train every weight)")
        if not (self.training_crop_density >= 0 and math.isfinite(self.training_crop_density)):
            raise ValueError(f"schedule.training_crop_density must be a number >= 0, got {self.training_crop_density}")


#: The component configs of a :class:`ModelConfig`, by the name it holds each under.
COMPONENTS = {"encoder": EncoderConfig, "frame_codes": FrameCodeConfig, "nerf": NerfConfig,
              "sampler": SamplerConfig, "decoder": DecoderConfig, "loss": LossConfig, "schedule": ScheduleConfig}


@dataclass
class ModelConfig:
    """A Garment Animation NeRF: its components' configs."""

    encoder: EncoderConfig = field(default_factory=EncoderConfig)
    """E, G_img and G_en."""
    frame_codes: FrameCodeConfig = field(default_factory=FrameCodeConfig)
    """The per-frame codes added to E's output."""
    nerf: NerfConfig = field(default_factory=NerfConfig)
    """M_NeRF."""
    sampler: SamplerConfig = field(default_factory=SamplerConfig)
    """The samples along each ray."""
    decoder: DecoderConfig = field(default_factory=DecoderConfig)
    """M_D and the output sizes."""
    loss: LossConfig = field(default_factory=LossConfig)
    """The training objective's weights."""
    schedule: ScheduleConfig = field(default_factory=ScheduleConfig)
    """The training schedule."""

    def __post_init__(self) -> None:
        self.validate()

    # ------------------------------------------------------------------ derived sizes
    @property
    def mlp_input_dim(self) -> int:
        """Width of M_NeRF's input [b_o, h, f^d, f^s] (paper: 4 + 8 + 8 = 20)."""
        return (4 + DETAIL_FEATURE_DIM * self.encoder.detail_feature
                + DYNAMIC_FEATURE_DIM * self.encoder.dynamic_feature)

    def training_scale(self, width: int, height: int) -> float:
        """Pixels the model was trained at per pixel of a scene camera of ``width x height``:
        ``image_resolution / max(width, height)`` for whole-frame training, else the crop density."""
        if self.schedule.training_crop_density > 0:
            return float(self.schedule.training_crop_density)
        return self.decoder.image_resolution / max(int(width), int(height))

    def training_camera(self, camera):
        """A scene camera (:class:`~garmentnerf.conventions.Camera`) at the density the model trains at:
        resized to the image's square for whole-frame training, else scaled by the crop density."""
        density = self.schedule.training_crop_density
        if density <= 0:
            return camera.resized(self.decoder.image_resolution, self.decoder.image_resolution)
        return camera.resized(max(1, round(camera.width * density)), max(1, round(camera.height * density)))

    # ------------------------------------------------------------------ checks
    def validate(self) -> None:
        """Raise ValueError on an out-of-range or inconsistent setting, naming it."""
        for name, kind in COMPONENTS.items():
            part = getattr(self, name)
            if not isinstance(part, kind):
                raise TypeError(f"ModelConfig.{name} must be a {kind.__name__}, got {type(part).__name__}")
            part.validate()
        if self.frame_codes.resolution and not self.encoder.dynamic_feature:
            raise ValueError("frame_codes need the dynamic feature (encoder.dynamic_feature)")
        if self.decoder.image_resolution % self.loss.perceptual_downsample:
            raise ValueError(f"loss.perceptual_downsample ({self.loss.perceptual_downsample}) must divide "
                             f"decoder.image_resolution ({self.decoder.image_resolution})")

    # ------------------------------------------------------------------ presets
    @classmethod
    def paper(cls) -> "ModelConfig":
        """The published model (every default)."""
        return cls()

    @classmethod
    def cpu_small(cls) -> "ModelConfig":
        """A reduced model for a 2-core CPU, the bundled demos' base: 64 x 64 rays of 24 samples, a
        4 x 128 MLP, 64-d zeta, half-width U-Nets, 256 x 256 images and 128 x 128 references.

        About 1 s a step on the development CPU. A few thousand steps are about 1 % of the paper's
        schedule, so the density moves fast (``trunc_exp``, scale 10, bias -3, a body prior) and the
        learning rate is doubled. The radiance is grey, so it cannot absorb the garment's hue, and the
        blend weights are supervised by the labels from step 550 (``docs/lab/bundles.md``, "The base model
        (B0)").
        """
        return cls().updated({
            "encoder.reference_resolution": 128, "encoder.width_scale": 0.5, "encoder.neural_texture_resolution": 256,
            "nerf.appearance_dim": 64, "nerf.mlp_depth": 4, "nerf.mlp_width": 128,
            "nerf.density_activation": "trunc_exp", "nerf.density_scale": 10.0, "nerf.density_bias": -3.0,
            "nerf.body_prior_strength": 3.0,
            "sampler.samples_per_ray": 24,
            "decoder.image_resolution": 256, "decoder.feature_image_resolution": 64, "decoder.width": 32,
            "decoder.min_width": 16, "decoder.extra_layers": 1, "decoder.radiance_channels": 1,
            "loss.segmentation": 0.5, "loss.segmentation_start": 550,
            "schedule.lr": 1e-3, "schedule.lr_final": 1e-4, "schedule.iterations": 3_000,
            "schedule.generator_iterations": 3_000})

    @classmethod
    def tiny(cls) -> "ModelConfig":
        """A model small enough for tests and smoke runs (64 x 64 images, seconds per dozen steps)."""
        return cls.cpu_small().updated({
            "encoder.info_map_resolution": 32, "encoder.reference_resolution": 32, "encoder.width_scale": 0.25,
            "encoder.neural_texture_resolution": 32, "nerf.appearance_dim": 16, "nerf.mlp_depth": 2,
            "nerf.mlp_width": 32, "sampler.samples_per_ray": 8, "decoder.image_resolution": 64,
            "decoder.feature_image_resolution": 16, "decoder.width": 16, "decoder.min_width": 8,
            "decoder.extra_layers": 0, "schedule.iterations": 200, "schedule.generator_iterations": 50})

    # ------------------------------------------------------------------ changes and checkpoints
    def updated(self, changes: dict) -> "ModelConfig":
        """A validated copy with ``changes``: ``{"component.field": value}`` (``"schedule.lr"``) or
        ``{"component": {"field": value}}``. Unknown names raise ValueError naming them."""
        parts = {name: dataclasses.asdict(getattr(self, name)) for name in COMPONENTS}
        for key, value in changes.items():
            name, _, attr = key.partition(".")
            if name not in COMPONENTS:
                raise ValueError(f"unknown model setting '{key}' (components: {', '.join(COMPONENTS)})")
            updates = {attr: value} if attr else value
            if not isinstance(updates, dict):
                raise ValueError(f"model setting '{key}' must be a component's fields (a dict), got {value!r}")
            known = {f.name for f in dataclasses.fields(COMPONENTS[name])}
            unknown = sorted(set(updates) - known)
            if unknown:
                raise ValueError(f"unknown model setting(s) {', '.join(f'{name}.{u}' for u in unknown)} "
                                 f"(known in {name}: {', '.join(sorted(known))})")
            parts[name].update(updates)
        return ModelConfig(**{name: COMPONENTS[name](**fields) for name, fields in parts.items()})

    def to_dict(self) -> dict:
        """Plain JSON-compatible nested dict of every field."""
        out = {name: dataclasses.asdict(getattr(self, name)) for name in COMPONENTS}
        out["schedule"]["trained_parameters"] = list(self.schedule.trained_parameters)
        return out

    @classmethod
    def from_dict(cls, data: dict) -> "ModelConfig":
        """Rebuild from :meth:`to_dict`, or from a flat dict of an older run (:func:`convert_flat_config`);
        missing keys take the defaults, unknown keys raise ValueError."""
        if not all(isinstance(value, dict) for value in data.values()):
            data, _ = convert_flat_config(data)
        return cls().updated(data)


# ---- Runs written before the components: one converter
#: Flat names of the older runs -> their dotted names now.
FLAT_NAMES = {
    "history": "encoder.history", "info_map_resolution": "encoder.info_map_resolution",
    "reference_resolution": "encoder.reference_resolution", "encoder_width_scale": "encoder.width_scale",
    "neural_texture_resolution": "encoder.neural_texture_resolution",
    "use_dynamic_feature": "encoder.dynamic_feature", "use_detail_feature": "encoder.detail_feature",
    "frame_code_resolution": "frame_codes.resolution", "frame_codes": "frame_codes.count",
    "frame_code_lr_scale": "frame_codes.lr_scale", "frame_code_support_margin": "frame_codes.support_margin",
    "appearance_dim": "nerf.appearance_dim", "mlp_depth": "nerf.mlp_depth", "mlp_width": "nerf.mlp_width",
    "density_activation": "nerf.density_activation", "density_bias": "nerf.density_bias",
    "density_scale": "nerf.density_scale", "body_prior_strength": "nerf.body_prior_strength",
    "shading_normals": "nerf.shading_normals", "samples_per_ray": "sampler.samples_per_ray",
    "image_resolution": "decoder.image_resolution", "feature_image_resolution": "decoder.feature_image_resolution",
    "palette_size": "decoder.palette_size", "radiance_channels": "decoder.radiance_channels",
    "decoder_width": "decoder.width", "decoder_min_width": "decoder.min_width",
    "decoder_extra_layers": "decoder.extra_layers",
    "w_image": "loss.image", "w_mask": "loss.mask", "w_perceptual": "loss.perceptual",
    "perceptual_downsample": "loss.perceptual_downsample", "w_sparsity": "loss.sparsity", "w_offset": "loss.offset",
    "w_palette": "loss.palette", "w_opacity": "loss.opacity", "w_segmentation": "loss.segmentation",
    "segmentation_start": "loss.segmentation_start", "segmentation_head_only": "loss.segmentation_head_only",
    "lr": "schedule.lr", "lr_final": "schedule.lr_final", "iterations": "schedule.iterations",
    "batch_size": "schedule.batch_size", "trained_parameters": "schedule.trained_parameters",
    "generator_iterations": "schedule.generator_iterations",
    "training_crop_density": "schedule.training_crop_density",
}
#: Older settings that are now constants or removed, and the one value a model built today computes
#: with: a run that set another can no longer be rendered as it was trained.
FLAT_FIXED = {
    "field": "paper", "world_normals": False, "velocity_smoothing": [], "depth_normals": False,
    "shading_normal_blur": 0.0, "atlas_feature_channels": 0, "positional_encoding_freqs": 0,
    "importance_samples": 0, "sampler": "box", "decoder_low_layers": 0, "radiance_activation": "softplus",
    "detail_selection": "visibility", "dynamic_feature_dim": DYNAMIC_FEATURE_DIM,
    "detail_feature_dim": DETAIL_FEATURE_DIM, "encoder_base_width": UNET_BASE_WIDTH, "encoder_depth": UNET_DEPTH,
    "neural_texture_channels": NEURAL_TEXTURE_CHANNELS, "neural_texture_levels": NEURAL_TEXTURE_LEVELS,
    "bbox_padding": BBOX_PADDING, "body_prior_width": BODY_PRIOR_WIDTH, "offset_scale": OFFSET_SCALE,
    "blend_weight_floor": BLEND_WEIGHT_FLOOR, "background": list(BACKGROUND), "garment_label": 2, "body_label": 1,
}
#: Older settings that shaped only training, and their value in a run trained as a model is today.
FLAT_TRAINING_ONLY = {
    "frame_code_dropout": 0.0, "encoder_lr_scale": 1.0, "views_per_step": 1, "geometry_iterations": 0,
    "w_occupancy": 0.0, "w_distortion": 0.0, "w_image_l2": 0.0, "w_plane_tv": 0.0, "occupancy_points": None,
    "occupancy_half_thickness": None, "occupancy_step": None, "occupancy_spread": None,
    "importance_uniform_mix": None, "shell_spacing": None, "uvh_slices": None, "uvh_height_range": None,
    "uvh_height_freqs": None, "uvh_canonical_freqs": None, "uvh_sheet_layers": None, "uvh_sheet_freqs": None,
    "uvh_plane_channels": None, "uvh_plane_resolution": None, "uvh_plane_height": None, "uvh_plane_lr_scale": None,
    "atlas_feature_levels": None, "atlas_feature_resolution": None, "atlas_feature_lr_scale": None,
    "grad_clip_value": GRAD_CLIP_VALUE, "generator_lr": GENERATOR_LR,
}


def convert_flat_config(flat: dict) -> tuple[dict, list[str]]:
    """An older run's flat config -> ``({"component.field": value}, training_differences)``.

    Raises ValueError naming the setting when the run used a removed choice that changes what the model
    computes (the ``uvh`` field, a shell sampler, ...). ``training_differences`` names the training-only
    settings the run had at another value than a run trained today (its render is unaffected; resuming
    its training would not continue it as it was).
    """
    out, differences = {}, []
    for key, value in flat.items():
        if key in FLAT_NAMES:
            out[FLAT_NAMES[key]] = value
        elif key == "generator_width_scale":
            if value != flat.get("encoder_width_scale", 1.0):
                raise ValueError(f"model config: generator_width_scale {value} differs from encoder_width_scale; "
                                 "one encoder.width_scale sizes every U-Net now")
        elif key == "decoder_upsample_steps":
            feature, image = flat.get("feature_image_resolution", 128), flat.get("image_resolution", 512)
            if feature * 2 ** int(value) != image:
                raise ValueError(f"model config: decoder_upsample_steps {value} does not take "
                                 f"feature_image_resolution {feature} to image_resolution {image}")
        elif key in FLAT_FIXED:
            fixed = FLAT_FIXED[key]
            same = list(value) == list(fixed) if isinstance(fixed, list) else value == fixed
            if not same:
                raise ValueError(f"model config: '{key}' = {value!r} is a removed setting (this version computes "
                                 f"{fixed!r}); render this run with the garmentnerf version that trained it")
        elif key in FLAT_TRAINING_ONLY:
            usual = FLAT_TRAINING_ONLY[key]
            if usual is not None and value != usual:
                differences.append(key)
        else:
            raise ValueError(f"unknown model config key '{key}'")
    return out, differences


def _positive(part, *names) -> None:
    """ValueError unless every named field of the component ``part`` is > 0."""
    for name in names:
        value = getattr(part, name)
        if not (value > 0 and math.isfinite(value)):
            raise ValueError(f"{_component_name(part)}.{name} must be positive, got {value}")


def _at_least(part, low, *names) -> None:
    """ValueError unless every named field of the component ``part`` is >= ``low``."""
    for name in names:
        value = getattr(part, name)
        if not (value >= low and math.isfinite(value)):
            raise ValueError(f"{_component_name(part)}.{name} must be >= {low}, got {value}")


def _component_name(part) -> str:
    return next(name for name, kind in COMPONENTS.items() if isinstance(part, kind))


__all__ = ["ModelConfig", "EncoderConfig", "FrameCodeConfig", "NerfConfig", "SamplerConfig", "DecoderConfig",
           "LossConfig", "ScheduleConfig", "COMPONENTS", "convert_flat_config", "DENSITY_ACTIVATIONS",
           "DYNAMIC_FEATURE_DIM", "DETAIL_FEATURE_DIM", "UNET_BASE_WIDTH", "UNET_DEPTH", "NEURAL_TEXTURE_CHANNELS",
           "NEURAL_TEXTURE_LEVELS", "BBOX_PADDING", "BODY_PRIOR_WIDTH", "OFFSET_SCALE", "BLEND_WEIGHT_FLOOR",
           "BACKGROUND", "GRAD_CLIP_VALUE", "GENERATOR_LR"]
