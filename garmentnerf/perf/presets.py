"""Named render presets spanning the speed/accuracy trade, applied to a loaded model (no retraining).

Each preset fixes (resolution scale, samples per ray, sampler, precision):

===============  ==========  ===========  ===========================================  =========
preset           resolution  samples/ray  sampler                                      precision
===============  ==========  ===========  ===========================================  =========
``reference``    1           1 x S        paper: padded body box, stratified (dense)   float32
``full``         1           1 x S        shell + band + skin occlusion + stop (1e-4)  float32
``balanced``     0.75        0.5 x S      shell + band + occlusion + stop (1e-3)       auto
``interactive``  0.5         0.5 x S      shell + band + occlusion + stop (1e-2)       auto
===============  ==========  ===========  ===========================================  =========

S is the model's ``cfg.samples_per_ray`` (the sampling it was trained with; the paper: 64), at
least 4. The resolution scale multiplies the pixel density the model was trained at
(``cfg.image_resolution`` across the larger image side; ``RenderSession`` calls it ``quality``):
the number of rays goes with its square. ``full`` keeps the reference's samples exactly (the box
bins of the same S) and only skips those the culls prove empty, so it differs from
``reference`` only by density the model put outside the garment's band (and by at most 1e-4 of
transmittance). ``auto`` precision is float16 autocast on CUDA and float32 on the CPU (bfloat16
autocast is slower than float32 on the development CPU). See
:mod:`garmentnerf.model.samplers_culled` for the culls.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

from garmentnerf.model.samplers_culled import (PRECISIONS, HeightRange, ShellSampler, install_culled_renderer,
                                               measure_height_range, uninstall_culled_renderer)

SAMPLERS = ("box", "shell")


@dataclass(frozen=True)
class Preset:
    """One point of the speed/accuracy trade (see the module docstring)."""

    name: str
    resolution_scale: float
    samples_scale: float
    sampler: str
    precision: str = "float32"
    termination_eps: float = 0.0
    occlusion: bool = False
    description: str = ""

    def __post_init__(self) -> None:
        if not self.resolution_scale > 0:
            raise ValueError(f"preset {self.name}: resolution_scale must be > 0, got {self.resolution_scale}")
        if not self.samples_scale > 0:
            raise ValueError(f"preset {self.name}: samples_scale must be > 0, got {self.samples_scale}")
        if self.sampler not in SAMPLERS:
            raise ValueError(f"preset {self.name}: sampler must be one of {SAMPLERS}, got {self.sampler!r}")
        if self.precision not in PRECISIONS:
            raise ValueError(f"preset {self.name}: precision must be one of {PRECISIONS}, got {self.precision!r}")
        if not 0.0 <= self.termination_eps < 1.0:
            raise ValueError(f"preset {self.name}: termination_eps must be in [0, 1), got {self.termination_eps}")

    def samples_per_ray(self, cfg) -> int:
        return max(4, int(round(cfg.samples_per_ray * self.samples_scale)))

    def render_scale(self, cfg, camera) -> float:
        """Rendered pixels per output pixel of ``camera`` (``render_full_image(scale=...)``)."""
        return self.resolution_scale * cfg.image_resolution / max(camera.width, camera.height)

    def to_dict(self) -> dict:
        return asdict(self)


PRESETS: dict[str, Preset] = {p.name: p for p in (
    Preset("reference", 1.0, 1.0, "box", "float32", 0.0,
           description="the paper's sampling: S stratified samples in the padded body box, every ray that hits it"),
    Preset("full", 1.0, 1.0, "shell", "float32", 1e-4, occlusion=True,
           description="the reference's samples, minus those outside the shell/height band, behind the skin "
                       "or behind opacity"),
    Preset("balanced", 0.75, 0.5, "shell", "auto", 1e-3, occlusion=True,
           description="3/4 resolution, half the samples, culled"),
    Preset("interactive", 0.5, 0.5, "shell", "auto", 1e-2, occlusion=True,
           description="half resolution, half the samples, culled"),
)}
PRESET_NAMES = tuple(PRESETS)


def get_preset(name) -> Preset:
    if isinstance(name, Preset):
        return name
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown preset {name!r} (known: {', '.join(PRESETS)})") from None


def height_range_for_run(run, projector=None) -> HeightRange:
    """The garment's height band of a loaded run: measured on its scene's training garments, or
    :meth:`HeightRange.default` when the run has no scene (cached on the run object)."""
    cached = getattr(run, "_garment_height_range", None)
    if cached is not None:
        return cached
    scene = getattr(run, "scene", None)
    if scene is None:
        band = HeightRange.default()
    else:
        model = run.model
        band = measure_height_range(scene, model.body, getattr(run, "betas", None),
                                    projector if projector is not None else model.projector)
    try:
        run._garment_height_range = band
    except AttributeError:
        pass
    return band


@dataclass
class AppliedPreset:
    """What :func:`apply_preset` set up: the preset, its samples per ray, the sampler installed."""

    preset: Preset
    samples_per_ray: int
    sampler: object
    height_range: HeightRange | None

    def render_scale(self, cfg, camera) -> float:
        return self.preset.render_scale(cfg, camera)


def apply_preset(model, preset, *, height_range: HeightRange | None = None, gl_context=None) -> AppliedPreset:
    """Configure ``model`` (a loaded :class:`GarmentAnimationNeRF`) for ``preset``; the weights are
    untouched. The resolution part is the caller's (``AppliedPreset.render_scale``,
    ``RenderSession.render(quality=preset.resolution_scale)``)."""
    from garmentnerf.model.samplers import BoxStratifiedSampler

    preset = get_preset(preset)
    cfg = model.cfg
    n = preset.samples_per_ray(cfg)
    if preset.sampler == "box":
        sampler = BoxStratifiedSampler(n, cfg.bbox_padding)
        uninstall_culled_renderer(model, sampler)
        return AppliedPreset(preset, n, sampler, None)
    band = height_range if height_range is not None else HeightRange.default()
    old = model.sampler
    sampler = ShellSampler(n, band, faces=model.projector.faces, padding=cfg.bbox_padding,
                           termination_eps=preset.termination_eps, precision=preset.precision,
                           gl_context=gl_context, occlusion=preset.occlusion)
    if isinstance(old, ShellSampler) and (gl_context is None or old.raster._ctx is gl_context):
        sampler.raster = old.raster  # keep the GL objects (and the context) of the previous preset
    elif isinstance(old, ShellSampler):
        old.release()
    install_culled_renderer(model, sampler)
    return AppliedPreset(preset, n, sampler, band)


__all__ = ["Preset", "PRESETS", "PRESET_NAMES", "AppliedPreset", "apply_preset", "get_preset",
           "height_range_for_run"]
