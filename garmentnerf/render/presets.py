"""Named render presets spanning the speed/accuracy trade (no retraining): the one table.

:data:`RENDER_PRESETS` is used by everything that renders a trained model: ``garmentnerf bench
--run`` measures each row, ``garmentnerf render --preset`` and ``garmentnerf eval --preset`` run
one, and the previewer's quality levels are its rows (:data:`VIEWER_LEVELS`), so what the bench
measures is what the user runs. A preset becomes render arguments through
:meth:`RenderPreset.sampling` (:class:`SamplingPlan`: sampler, sample filter, early termination,
precision); :class:`~garmentnerf.render.session.RenderSession` does that once per preset.

Each preset fixes (resolution scale, samples per ray, sampler, precision):

===============  ==========  ===========  ===========================================  =========
preset           resolution  samples/ray  sampler                                      precision
===============  ==========  ===========  ===========================================  =========
``reference``    1           1 x S        paper: padded body box, stratified (dense)   float32
``full``         1           1 x S        shell + band + skin occlusion + stop (1e-4)  float32
``balanced``     0.75        0.5 x S      shell + band + occlusion + stop (1e-3)       auto
``interactive``  0.5         0.5 x S      shell + band + occlusion + stop (1e-2)       auto
===============  ==========  ===========  ===========================================  =========

The culled presets also render only the character's screen rectangle
(:attr:`RenderPreset.character_rect`): rays and the decoder run where the sampling box projects.

S is the model's ``cfg.sampler.samples_per_ray`` (the sampling it was trained with; the paper: 64), at
least 4. The resolution scale multiplies the pixel density the model was trained at
(``cfg.decoder.image_resolution`` across the larger image side; ``RenderSession`` calls it ``quality``):
the number of rays goes with its square. ``full`` keeps the reference's samples exactly (the box
bins of the same S) and only skips those outside the garment's band or behind the skin, so it
differs from ``reference`` only by density the model put there (and by at most 1e-4 of
transmittance). A model trained in the box puts some under the skin where the cloth lies on it, so
its band reaches :data:`BOX_TRAINED_MARGIN_IN` under the skin; behind a hand in front of the garment
the skipped density is what ``reference`` wrongly draws over the fingers. ``auto`` precision is
float16 autocast on CUDA and float32 on the CPU (bfloat16 autocast renders only 4 to 6 % faster on
the development CPU, whose AMX-BF16 makes the MLP's products 8 times faster: the MLP is a small share
of a render, the body projection the largest). See
:mod:`garmentnerf.render.shell_sampler` for the culls.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

from garmentnerf.model.config import BBOX_PADDING
from garmentnerf.model.height_band import HeightRange
from garmentnerf.render.band_cache import scene_height_range
from garmentnerf.model.pipeline import PRECISIONS
from garmentnerf.render.shell_sampler import ShellSampler

#: Where a preset's samples go: the padded body box (the paper's) or the garment's shell.
SAMPLERS = ("box", "shell")

#: Feature cells around the character's rectangle: the palette decoder's receptive field
#: (nearest x2 upsampling then 3x3 convolutions: 1.5 feature cells for the default 2 upsamplings,
#: 2 extra layers and the head) rounded up, so that inside the rectangle the decoder sees what it
#: sees in a whole-frame render.
CHARACTER_RECT_MARGIN = 2


#: Metres under the skin (below the garment's lowest measured height) that the culls of a model trained
#: in the box keep: the band's ``h_min`` and so the skin occlusion's margin. Such a model was never told
#: where under the skin its density may go (the body is drawn opaque over it), and where the cloth lies
#: on the skin it may put the garment's opacity there: the bundled t-shirt renders its chest at 5 to 7 cm
#: under the skin, so with the data's 5 cm (:data:`~garmentnerf.model.height_band.HEIGHT_MARGIN_IN`) the
#: culled presets cut it away and the chest showed holes (docs/lab/ledger.md, "Holes in the t-shirt's
#: chest"). 10 cm closes them for 2 to 8 % more samples.
BOX_TRAINED_MARGIN_IN = 0.10


@dataclass(frozen=True)
class RenderPreset:
    """One point of the speed/accuracy trade (see the module docstring)."""

    name: str
    """Key in :data:`RENDER_PRESETS`."""
    resolution_scale: float
    """Rendered pixels per pixel of the training density (``cfg.decoder.image_resolution`` across the
    larger image side); the rays go with its square."""
    samples_scale: float
    """Samples per ray as a fraction of the model's ``cfg.sampler.samples_per_ray`` (at least 4)."""
    sampler: str
    """``box`` (the paper's :class:`~garmentnerf.model.samplers.BoxStratifiedSampler`) or
    ``shell`` (:class:`~garmentnerf.render.shell_sampler.ShellSampler` with the garment's height
    band as sample filter)."""
    precision: str = "float32"
    """MLP precision (:data:`~garmentnerf.model.pipeline.PRECISIONS`)."""
    termination_eps: float = 0.0
    """Early ray termination: transmittance below which a ray stops (0: never)."""
    occlusion: bool = False
    """Shell sampler only: cut rays just behind their first skin crossing."""
    character_rect: bool = False
    """Cast rays and decode only in the screen rectangle of the sampling box (the padded body
    box, aligned to the decoder's feature grid, plus :data:`CHARACTER_RECT_MARGIN` feature
    cells); outside it the maps are empty (background). Rays outside that box meet no sample, so
    this changes nothing but the decoder's output in empty space
    (:mod:`garmentnerf.render.screen_rect`). Such a preset's ``resolution_scale`` is also measured
    on the character, not the window (:class:`~garmentnerf.render.session.RenderSession`,
    "Resolution")."""
    description: str = ""
    """One line for listings."""

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
        return max(4, int(round(cfg.sampler.samples_per_ray * self.samples_scale)))

    def uses_shell(self) -> bool:
        """Whether this preset samples in the garment's shell (else in the padded body box)."""
        return self.sampler == "shell"

    def sampling(self, model, height_range: HeightRange | None = None, gl_context=None) -> "SamplingPlan":
        """The render arguments of this preset for ``model`` (a loaded
        :class:`~garmentnerf.model.pipeline.GarmentAnimationNeRF`; its weights are untouched).

        Args:
            height_range: the garment's band (shell sampling; default :meth:`HeightRange.default`).
            gl_context: moderngl context of the shell raster (None: a headless one of its own).
        """
        n = self.samples_per_ray(model.cfg)
        if not self.uses_shell():
            return SamplingPlan(self, model.box_sampler(n), None, self.termination_eps, self.precision)
        band = height_range if height_range is not None else HeightRange.default()
        faces = model.projector.faces
        sampler = ShellSampler(n, faces, band, padding=BBOX_PADDING, gl_context=gl_context, occlusion=self.occlusion)
        return SamplingPlan(self, sampler, band.sample_filter(faces), self.termination_eps, self.precision)

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class SamplingPlan:
    """Where one preset's samples go: the sampling arguments of
    :meth:`~garmentnerf.model.pipeline.GarmentAnimationNeRF.render` (:meth:`render_kwargs`)."""

    preset: RenderPreset
    sampler: object
    """The :class:`~garmentnerf.model.samplers.Sampler`."""
    sample_filter: object | None
    """The :class:`~garmentnerf.model.samplers.SampleFilter`, or None."""
    termination_eps: float
    precision: str

    def render_kwargs(self) -> dict:
        return {"sampler": self.sampler, "sample_filter": self.sample_filter,
                "termination_eps": self.termination_eps, "precision": self.precision}

    def release(self) -> None:
        """Free the sampler's GL objects, if it has any."""
        release = getattr(self.sampler, "release", None)
        if release is not None:
            release()


RENDER_PRESETS: dict[str, RenderPreset] = {p.name: p for p in (
    RenderPreset("reference", 1.0, 1.0, "box", "float32", 0.0,
                 description="the paper's sampling: S stratified samples in the padded body box, every ray that hits it"),
    RenderPreset("full", 1.0, 1.0, "shell", "float32", 1e-4, occlusion=True, character_rect=True,
                 description="the reference's samples, minus those outside the shell/height band, behind the skin "
                             "or behind opacity"),
    RenderPreset("balanced", 0.75, 0.5, "shell", "auto", 1e-3, occlusion=True, character_rect=True,
                 description="3/4 resolution, half the samples, culled"),
    RenderPreset("interactive", 0.5, 0.5, "shell", "auto", 1e-2, occlusion=True, character_rect=True,
                 description="half resolution, half the samples, culled"),
)}
RENDER_PRESET_NAMES = tuple(RENDER_PRESETS)
#: The previewer's quality levels, lowest first: rows of :data:`RENDER_PRESETS`.
VIEWER_LEVELS = ("interactive", "balanced", "full")


def get_render_preset(name) -> RenderPreset:
    """The preset called ``name`` (a :class:`RenderPreset` is returned as it is)."""
    if isinstance(name, RenderPreset):
        return name
    try:
        return RENDER_PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown render preset {name!r} (known: {', '.join(RENDER_PRESETS)})") from None


def height_range_for_run(run, projector=None) -> HeightRange:
    """The garment's height band of a loaded run: measured on its scene's training garments with
    :data:`BOX_TRAINED_MARGIN_IN` under the skin (measured once per scene, body and shape, and kept:
    :func:`~garmentnerf.render.band_cache.scene_height_range`; measuring takes 6 to 11 s of CPU on a
    2-core machine: callers keep it), else :meth:`HeightRange.default` when the run has no scene."""
    scene = getattr(run, "scene", None)
    if scene is None:
        return HeightRange.default()
    model = run.model
    return scene_height_range(scene, model.body, getattr(run, "betas", None),
                              projector if projector is not None else model.projector,
                              margin_in=BOX_TRAINED_MARGIN_IN)


__all__ = ["RenderPreset", "SamplingPlan", "RENDER_PRESETS", "RENDER_PRESET_NAMES", "VIEWER_LEVELS",
           "get_render_preset", "height_range_for_run", "BOX_TRAINED_MARGIN_IN"]
