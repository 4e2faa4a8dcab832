"""The one render path: :class:`RenderSession` renders views of a run's model; :class:`NeuralFrame`
holds the decomposed maps of one view and composes them with any palette.

What the network outputs, and the two compositions
    The model is trained on ground-truth images of the body *and* the garment over a black
    background (``garmentnerf.data.render_gt``), with the mask covering both; the palette has a
    garment color p_0 and a body/other color p_1. So the neural image already shows the body
    (composition ``nerf``, the paper's). When the run has a learned body appearance
    (``body_appearance.safetensors``, made by ``garmentnerf body fit-appearance``), composition
    ``raster_body`` draws the body instead: the posed body rasterised and shaded by that
    appearance (:mod:`garmentnerf.render.body_layer`), with the network's garment in front of it
    where its garment visibility says so (:func:`~garmentnerf.model.palette.compose`, "The hybrid
    composition"). ``auto`` (the default) is ``raster_body`` when the run has a body appearance,
    else ``nerf``. Either way :meth:`NeuralFrame.composite` is ``maps.compose(palette,
    background)`` and nothing else.

The camera-to-maps entry point
    :meth:`RenderSession.render` is the only place a camera becomes decomposed maps: the viewer,
    snapshots and exports, ``garmentnerf render``, ``garmentnerf eval`` and ``garmentnerf bench``
    all call it.

Presets
    Where samples go is a render preset (:data:`garmentnerf.render.presets.RENDER_PRESETS`: sampler,
    sample filter, early termination, precision, resolution); the session turns each preset it is
    asked for into a :class:`~garmentnerf.render.presets.SamplingPlan` once (measuring the
    garment's height band on the run's scene the first time a culled preset is used) and passes
    it to the model. Default: :data:`DEFAULT_PRESET`.

Resolution
    :meth:`RenderSession.render` renders a camera ``W x H`` at ``scale`` times its pixels;
    ``quality = 1`` is the pixel density the model was trained at and lower qualities are
    proportionally coarser (fewer rays: the cost is about ``quality**2``); ``quality`` defaults to
    the preset's ``resolution_scale``. The density is measured on the character for the presets
    that render only its rectangle (``character_rect``): ``scale = quality * e_train / e_view``
    with ``e`` the projected size of the frame's sampling box in the median training camera (at
    the density the model was trained at,
    :meth:`~garmentnerf.model.config.ModelConfig.training_scale`) and in this view, so a character
    filling a 1280 x 800 window is rendered as sharp as the model can make it, in about a training
    view's rays, and a distant one costs little (capped at one rendered pixel per output pixel, or
    the frame density when that is higher). The ``reference`` preset, and any view where the box's
    projection is unbounded, use the frame: ``scale = quality * S / max(W, H)`` with ``S`` the
    longer side of a training camera at the trained density (``cfg.decoder.image_resolution`` for
    whole-frame training). The rendered size is padded to a multiple of the decoder's upsampling
    factor (:func:`padded_render_camera`) and the maps cropped back
    (:meth:`~garmentnerf.model.palette.DecomposedMaps.cropped`). The :class:`NeuralFrame` keeps
    the maps at the *rendered* size; :meth:`NeuralFrame.maps_at` resamples them
    (:meth:`~garmentnerf.model.palette.DecomposedMaps.resized`: averaged by area when shrinking,
    bilinear when growing, weights renormalised) to any output size, and the composition happens
    there, once, with the palette the caller chose. The viewer uploads the rendered-size maps and
    lets the GPU upsample them bilinearly before the same formula (``shaders/viewer_palette.frag``),
    which equals the CPU path wherever the resampling is plain bilinear (upsampling).

Caching and precomputation
    The per-frame work (GL passes for the info maps and reference G-buffers, E, G_img, G_en, the
    bound surface) does not depend on the camera: :class:`FrameFeatures` are kept in a
    memory-bounded :class:`~garmentnerf.render.frame_cache.FrameCache` (:attr:`RenderSession.frames`),
    so orbiting a still frame or returning to a ready one only re-runs the per-ray work.
    :meth:`RenderSession.precompute_next` fills it one frame at a time, nearest to the playhead
    first (the previewer's worker calls it whenever it has no view to render); a new motion
    clears it.

Threads
    A session is used from one thread at a time (the viewer's worker thread owns one, created on
    that thread with its own headless GL context). ``should_cancel`` is polled between chunks of
    samples; a cancelled render raises :class:`~garmentnerf.model.pipeline.RenderCancelled` and
    leaves nothing half-written.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch

from garmentnerf.conventions import Camera, camera_rays
from garmentnerf.data.cameras import reference_cameras
from garmentnerf.gl.body_layer_pass import BodyLayerPass
from garmentnerf.lifecycle import Closeable
from garmentnerf.model.config import BBOX_PADDING
from garmentnerf.model.palette import DecomposedMaps, check_palette
from garmentnerf.model.samplers import padded_box
from garmentnerf.motion.library import load_motion
from garmentnerf.motion.motion import Motion
from garmentnerf.render.body_layer import frame_body_layer
from garmentnerf.render.frame_cache import DEFAULT_CACHE_MB, FrameCache
from garmentnerf.render.frame_inputs import FrameInputBuilder
from garmentnerf.render.presets import CHARACTER_RECT_MARGIN, get_render_preset, height_range_for_run
from garmentnerf.render.screen_rect import PixelRect, box_extent, box_rect
from garmentnerf.runs import frame_code_offset

#: How a view is composed (module docstring, "the two compositions").
COMPOSITIONS = ("auto", "nerf", "raster_body")


def resolve_composition(composition: str, run) -> str:
    """``nerf`` or ``raster_body`` for ``composition`` and a run (``auto``: ``raster_body`` when the
    run has a body appearance).

    Raises:
        ValueError: an unknown composition, or ``raster_body`` for a run without a body appearance.
    """
    if composition not in COMPOSITIONS:
        raise ValueError(f"unknown composition {composition!r} (choose from {', '.join(COMPOSITIONS)})")
    has_body = getattr(run, "body_appearance", None) is not None
    if composition == "auto":
        return "raster_body" if has_body else "nerf"
    if composition == "raster_body" and not has_body:
        root = getattr(run, "root", "the run")
        raise ValueError(f"{root}: composition raster_body needs a body appearance; make one with "
                         f"'garmentnerf body fit-appearance --run {root}'")
    return composition


#: The render preset used when none is named (``garmentnerf render``, snapshots, exports): ``full``,
#: the reference's samples minus those the culls prove empty (the same PSNR to 0.01 dB on the
#: bundled model, in a fraction of the time). ``garmentnerf eval`` names ``reference``.
DEFAULT_PRESET = "full"


@dataclass
class NeuralFrame:
    """One rendered view: the decomposed maps and what is needed to compose and display them.

    Attributes:
        maps: :class:`DecomposedMaps` (batch 1, CPU float32) at ``render_size``.
        camera: the target camera (the output size is ``camera.width x camera.height``).
        render_size: (w, h) the maps' size.
        depth: (h, w) float32 camera-space z (metres) of the rendered surface, 0 where the
            network saw nothing (opacity ~ 0); nearest-upsampled from the feature image.
        palette: (P, 3) the run's learned palette.
        background: RGB in [0, 1] the model composes over by default.
        frame: the body frame.
        quality: the quality it was rendered at; scale: rendered pixels per output pixel.
        timings: milliseconds per stage (model stages, plus ``cache`` hit/miss info and ``total``).
        cached_frame: whether the frame's features came from the cache.
        preset: the render preset's name.
        counts: ``points_evaluated``, ``points_projected``, ``samples_placed``, ``rays_evaluated``,
            ``rays_total`` (cast: the character's rectangle for presets that crop to it),
            ``rays_terminated`` of the render, and ``rays_frame`` (the whole frame's).
        body: in the ``raster_body`` composition, the frame's posed body vertices and unit vertex
            normals ((V, 3) each, CPU float32), to draw the body layer with; else None.
        surface_depth: (fh, fw) float32 camera-space z of each feature ray's median depth (where its
            opacity reaches one half; 0 where it never does), over :attr:`feature_camera`: the
            unbiased surface that :mod:`garmentnerf.bake` builds meshes on (the expected depth in
            :attr:`depth` lies behind thin cloth).
        feature_camera: the camera of those rays: the render camera padded to whole feature cells,
            at one pixel per feature ray.
    """

    maps: DecomposedMaps
    camera: Camera
    render_size: tuple[int, int]
    depth: np.ndarray
    palette: torch.Tensor
    background: tuple[float, float, float]
    frame: int
    quality: float
    scale: float
    timings: dict[str, float] = field(default_factory=dict)
    cached_frame: bool = False
    preset: str = DEFAULT_PRESET
    counts: dict[str, int] = field(default_factory=dict)
    body: tuple[torch.Tensor, torch.Tensor] | None = None
    surface_depth: np.ndarray | None = None
    feature_camera: Camera | None = None

    @property
    def output_size(self) -> tuple[int, int]:
        return self.camera.width, self.camera.height

    def maps_at(self, width: int | None = None, height: int | None = None) -> DecomposedMaps:
        """The maps resampled to ``width x height`` (default: the camera's size)."""
        w = self.camera.width if width is None else int(width)
        h = self.camera.height if height is None else int(height)
        return self.maps.resized(w, h)

    def composite(self, palette: torch.Tensor | np.ndarray | None = None, background=None,
                  size: tuple[int, int] | None = None) -> np.ndarray:
        """(H, W, 3) float32 image in [0, 1]: :func:`compose` of the maps (at ``size``, default the
        camera's) with ``palette`` (default: the learned one) over ``background``."""
        pal = self.palette if palette is None else torch.as_tensor(np.asarray(palette, dtype=np.float32))
        check_palette(pal)
        bg = self.background if background is None else tuple(float(c) for c in background)
        w, h = size if size is not None else self.output_size
        maps = self.maps_at(w, h)
        with torch.no_grad():
            image = maps.compose(pal.float(), bg)[0]
        return image.permute(1, 2, 0).contiguous().numpy().astype(np.float32, copy=False)

    def alpha(self, size: tuple[int, int] | None = None) -> np.ndarray:
        """(H, W) float32 the character's coverage in :meth:`composite` (the mask m, or with a
        body layer the garment's visibility over the body's coverage)."""
        w, h = size if size is not None else self.output_size
        return self.maps_at(w, h).alpha[0, 0].numpy()

    def weights(self, size: tuple[int, int] | None = None) -> np.ndarray:
        """(P, H, W) float32 blend weights."""
        w, h = size if size is not None else self.output_size
        return self.maps_at(w, h).weights[0].numpy()


def resolve_motion(motion, body, betas, scene=None):
    """(Motion, sequence name or None) from None / a scene sequence name / a motion name / a Motion.

    None: the scene's first training sequence when there is a scene, else the ``walk`` clip. A name
    that is one of the scene's sequences loads that sequence's motion (ground truth then exists
    for it); any other name goes to :func:`garmentnerf.motion.library.load_motion`.
    """
    if isinstance(motion, Motion):
        return motion, None
    if motion is None:
        if scene is not None and scene.sequences:
            names = scene.sequence_names("train") or scene.sequence_names()
            return scene.load_motion(names[0]), names[0]
        motion = "walk"
    name = str(motion)
    if scene is not None and name in scene.sequences:
        return scene.load_motion(name), name
    fps = scene.fps if scene is not None else None
    return load_motion(name, body, betas=betas, fps=fps), None


class RenderSession(Closeable):
    """Renders views of a run's model for a motion (see the module docstring).

    Args:
        run: a :class:`garmentnerf.runs.LoadedRun` (uses ``model``, ``config``, ``scene``,
            ``palette()``).
        gl_ctx: a moderngl context for the input passes (headless is fine); must be usable on the
            thread that calls :meth:`render`.
        motion: None, a scene sequence name, a motion name, or a Motion (see :func:`resolve_motion`).
        cache_mb: memory bound of the frame cache (:class:`~garmentnerf.render.frame_cache.FrameCache`).
        cache_half: keep cached feature maps in float16 (the previewer; default: as computed).
        composition: one of :data:`COMPOSITIONS` (module docstring).
    """

    def __init__(self, run, gl_ctx, motion=None, *, cache_mb: float = DEFAULT_CACHE_MB,
                 cache_half: bool = False, composition: str = "auto") -> None:
        self.run = run
        self._body_pass = None  # the BodyLayerPass, made on first use
        self.set_composition(composition)
        self.model = run.model.eval()
        self.config = run.config
        self.scene = getattr(run, "scene", None)
        self.body = self.model.body
        # the body the frames are posed with: the scene's (a scene of a held-out body shape is rendered
        # with that shape, as its ground truth is), else the one the run was trained with
        shape = self.scene.body.get("shape") if self.scene is not None else None
        betas = self.body.betas(shape) if shape is not None else getattr(run, "betas", None)
        self.betas = betas if betas is not None else self.body.betas("average")
        refs = self.scene if self.scene is not None else reference_cameras()
        self.gl_ctx = gl_ctx
        self.builder = FrameInputBuilder(gl_ctx, self.body, refs, self.config)
        self.frames = FrameCache(self.model.bind_body, cache_mb,
                                 half=cache_half)
        self._plans: dict[str, object] = {}  # preset name -> SamplingPlan
        self._height_range = None  # the garment's band, measured on first use
        self.cache_hits = 0
        self.cache_misses = 0
        self.motion = None
        self.sequence: str | None = None
        self.posed = None
        self.set_motion(motion)

    def set_composition(self, composition: str) -> None:
        """Compose the next renders as ``composition`` (:data:`COMPOSITIONS`; see
        :func:`resolve_composition`); :attr:`composition` is then ``nerf`` or ``raster_body``."""
        self.composition = resolve_composition(composition, self.run)
        self.body_appearance = self.run.body_appearance if self.composition == "raster_body" else None

    def set_run(self, run) -> None:
        """Render with ``run``'s model from now on: a newer checkpoint of the same run (the same model
        config, body and projector; the previewer's checkpoint watcher,
        :func:`~garmentnerf.viewer.checkpoint_watch.load_checkpoint_run`). The frame cache is
        cleared: its features come from the old weights."""
        if run.config != self.config:
            raise ValueError("set_run needs a run of the same model config (a checkpoint of the same run)")
        self.run = run
        self.model = run.model.eval()
        self.set_composition(self.composition)
        self.frames.clear()

    # ---- motion -----------------------------------------------------------------------------------
    def set_motion(self, motion) -> None:
        """Switch to another motion (clears the frame cache)."""
        clip, sequence = resolve_motion(motion, self.body, self.betas, self.scene)
        with torch.no_grad():
            posed = clip.pose(self.body, self.betas)
        self.motion, self.sequence, self.posed = clip, sequence, posed
        # a training sequence of the run's own scene renders with its per-frame codes (if the run has them)
        self._code_offset = frame_code_offset(getattr(self.run, "info", {}), self.scene, sequence)
        self.frames.clear()

    @property
    def num_frames(self) -> int:
        return int(self.posed.vertices.shape[0])

    @property
    def fps(self) -> float:
        return float(self.motion.fps)

    def body_center(self, frame: int) -> np.ndarray:
        """(3,) mean posed vertex of ``frame`` (a turntable's target)."""
        return self.posed.vertices[frame].detach().double().mean(dim=0).cpu().numpy()

    def check_frame(self, frame: int) -> int:
        n = self.num_frames
        if isinstance(frame, bool) or not isinstance(frame, (int, np.integer)) or not 0 <= int(frame) < n:
            raise ValueError(f"frame {frame!r} is out of range for motion '{self.motion.name}' ({n} frames: 0..{n - 1})")
        return int(frame)

    # ---- palette ------------------------------------------------------------------------------------
    def learned_palette(self) -> torch.Tensor:
        """(P, 3) CPU float32 learned palette."""
        pal = self.run.palette() if hasattr(self.run, "palette") else self.model.palette()
        return pal.detach().to("cpu", torch.float32).clone()

    # ---- frames -------------------------------------------------------------------------------------
    def frame_features(self, frame: int):
        """(FrameFeatures, was_cached) of ``frame``; computed and cached when missing."""
        frame = self.check_frame(frame)
        feats = self.frames.get(frame)
        if feats is not None:
            self.cache_hits += 1
            return feats, True
        self.cache_misses += 1
        feats = self._compute_frame(frame)
        self.frames.put(frame, feats)
        return feats, False

    def _compute_frame(self, frame: int):
        inputs = self.builder.build(self.posed, frame, self.fps)
        code = None if self._code_offset is None else self._code_offset + frame
        with torch.no_grad():
            return self.model.prepare_frame(inputs, code=code).detach()

    def precompute_next(self, playhead: int | None = None) -> int | None:
        """Compute and cache the missing frame nearest to ``playhead`` (default: the last one
        set); returns it, or None when the clip is ready or the cache's bound is spent (see
        :class:`~garmentnerf.render.frame_cache.FrameCache`). One frame's work: call it again
        while it returns a frame, between renders."""
        if playhead is not None:
            self.frames.set_playhead(playhead)
        frame = self.frames.next_to_compute(self.num_frames)
        if frame is not None:
            self.frames.put(frame, self._compute_frame(frame))
        return frame

    def clear_cache(self) -> None:
        self.frames.clear()

    # ---- presets -----------------------------------------------------------------------------------
    @property
    def height_range(self):
        """The garment's height band of the run (measured on its scene once, on first use)."""
        if self._height_range is None:
            self._height_range = height_range_for_run(self.run)
        return self._height_range

    def sampling(self, preset=DEFAULT_PRESET):
        """The :class:`~garmentnerf.render.presets.SamplingPlan` of ``preset`` (a name or a
        :class:`~garmentnerf.render.presets.RenderPreset`), made once per preset."""
        preset = get_render_preset(preset)
        plan = self._plans.get(preset.name)
        if plan is None or plan.preset != preset:
            if plan is not None:
                plan.release()
            band = self.height_range if preset.uses_shell() else None
            plan = preset.sampling(self.model, band, self.gl_ctx)
            self._plans[preset.name] = plan
        return plan

    # ---- views --------------------------------------------------------------------------------------
    def render_scale(self, camera: Camera, quality: float = 1.0, features=None) -> float:
        """Rendered pixels per output pixel for ``camera`` at ``quality`` (see the module docstring,
        "Resolution"): the character's training density when ``features`` (the frame's
        :class:`FrameFeatures`) are given and the run's training cameras are known, else the frame's."""
        if not (np.isfinite(quality) and quality > 0):
            raise ValueError(f"quality must be a number > 0, got {quality!r}")
        views = self.training_views
        trained_side = max(views[0].width, views[0].height) if views else self.config.decoder.image_resolution
        frame_scale = float(quality) * trained_side / max(camera.width, camera.height)
        if features is None or not views:
            return frame_scale
        box = self.sampling_box(features)
        seen = box_extent(camera, box)
        trained = [e for e in (box_extent(c, box) for c in views) if e is not None]
        if seen is None or seen <= 0 or not trained:
            return frame_scale
        return min(float(quality) * float(np.median(trained)) / seen, max(1.0, frame_scale))

    @functools.cached_property
    def training_views(self) -> list[Camera]:
        """The run's training cameras at the pixel density the model was trained at
        (:meth:`~garmentnerf.model.config.ModelConfig.training_camera`: ``image_resolution``
        squared for whole-frame training, the scene's size times ``training_crop_density`` for
        character windows); empty without a scene."""
        if self.scene is None:
            return []
        recorded = ((getattr(self.run, "info", None) or {}).get("train") or {}).get("cameras")
        names = [c for c in (recorded or []) if c in set(self.scene.camera_names())]
        names = names or self.scene.camera_names("train")
        return [self.config.training_camera(self.scene.camera(n).camera) for n in names]

    def sampling_box(self, features) -> torch.Tensor:
        """(2, 3) float64 the frame's sampling box: the body box padded by :data:`~garmentnerf.model.config.BBOX_PADDING`, as
        both samplers pad it; no sample of the frame lies outside it."""
        return padded_box(features.aabb.detach().to("cpu", torch.float64), BBOX_PADDING)

    def render(self, frame: int, camera: Camera, quality: float | None = None, *, preset=DEFAULT_PRESET,
               scale: float | None = None, should_cancel: Callable[[], bool] | None = None,
               body_layer: bool = True) -> NeuralFrame:
        """Render body frame ``frame`` seen by ``camera``.

        Args:
            quality: fraction of the training pixel density (default: the preset's
                ``resolution_scale``; ignored when ``scale`` is given).
            preset: render preset name (:data:`~garmentnerf.render.presets.RENDER_PRESETS`).
            scale: rendered pixels per output pixel (overrides ``quality``).
            should_cancel: polled between chunks; True raises RenderCancelled.
            body_layer: in the ``raster_body`` composition, attach the body layer to the maps at
                their size; False leaves it to the caller, who draws it from
                :attr:`NeuralFrame.body` (the previewer draws it on its own GL context at the
                resolution it shows the frame).
        """
        t0 = time.perf_counter()
        plan = self.sampling(preset)
        quality = plan.preset.resolution_scale if quality is None else quality
        feats, cached = self.frame_features(frame)
        character = feats if plan.preset.character_rect else None
        s = self.render_scale(camera, quality, character) if scale is None else float(scale)
        if not s > 0:
            raise ValueError(f"scale must be > 0, got {scale!r}")
        up = 2 ** self.config.decoder.upsample_steps
        padded, (fw, fh), (wr, hr) = padded_render_camera(camera, s, up)
        rect = PixelRect(0, 0, padded.width, padded.height)
        if plan.preset.character_rect:
            rect = self.character_rect(feats, padded, up)
        view = padded if rect.area == padded.width * padded.height else padded.cropped(
            rect.x0, rect.y0, rect.width, rect.height)
        with torch.no_grad():
            out = self.model.render(feats, view, feature_size=(rect.width // up, rect.height // up),
                                    should_cancel=should_cancel, **plan.render_kwargs())
        placed = out.maps.detach().placed(rect.x0, rect.y0, padded.width, padded.height).cropped(wr, hr)
        maps = placed.to("cpu", torch.float32)
        body_ms = None
        if self.body_appearance is not None and body_layer:
            t_body = time.perf_counter()
            with torch.no_grad():
                maps = maps.with_body(*self.body_layer(feats, padded.cropped(0, 0, wr, hr)))
            body_ms = (time.perf_counter() - t_body) * 1e3
        depth = np.zeros((fh, fw), np.float32)
        depth[rect.y0 // up:rect.y1 // up, rect.x0 // up:rect.x1 // up] = _camera_depth(
            out.depth.detach().cpu(), out.opacity.detach().cpu(), view.resized(rect.width // up, rect.height // up))
        depth = np.repeat(np.repeat(depth, up, axis=0), up, axis=1)[:hr, :wr]
        rect_cells = view.resized(rect.width // up, rect.height // up)
        surface = np.zeros((fh, fw), np.float32)
        median = out.median_depth.detach().cpu()
        surface[rect.y0 // up:rect.y1 // up, rect.x0 // up:rect.x1 // up] = _camera_depth(median, (median > 0).float(),
                                                                                          rect_cells, min_opacity=0.5)
        timings = dict(out.timings)
        if body_ms is not None:
            timings["body_layer"] = body_ms
        timings["total"] = (time.perf_counter() - t0) * 1e3
        counts = {k: int(getattr(out, k)) for k in ("points_evaluated", "points_projected", "samples_placed",
                                                      "rays_evaluated", "rays_total", "rays_terminated")}
        counts["rays_frame"] = fw * fh
        return NeuralFrame(maps, camera, (wr, hr), np.ascontiguousarray(depth, dtype=np.float32),
                           self.learned_palette(), tuple(out.background), int(frame), float(quality), s,
                           timings, cached, plan.preset.name, counts,
                           self._body_geometry(feats) if self.body_appearance is not None else None,
                           surface, padded.resized(fw, fh))

    @staticmethod
    def _body_geometry(features) -> tuple[torch.Tensor, torch.Tensor]:
        """The frame's posed body vertices and vertex normals, (V, 3) each, CPU float32."""
        return tuple(t.detach().to("cpu", torch.float32) for t in (features.posed_vertices, features.vertex_normals))

    def body_layer(self, features, camera: Camera) -> tuple[torch.Tensor, torch.Tensor]:
        """The rasterised body layer of a frame (its :class:`~garmentnerf.model.frame_context.FrameFeatures`:
        the posed body and its vertex normals) seen by ``camera`` at its size
        (drawn and shaded by :class:`~garmentnerf.gl.body_layer_pass.BodyLayerPass`, the GL side of
        :func:`~garmentnerf.render.body_layer.render_body_layer`; needs a body appearance)."""
        if self.body_appearance is None:
            raise ValueError("this session composes without a body layer (composition 'nerf')")
        if self._body_pass is None:
            self._body_pass = BodyLayerPass(self.gl_ctx)
        return frame_body_layer(self._body_pass, self.body, features, camera, self.body_appearance)

    def character_rect(self, features, camera: Camera, cell: int) -> PixelRect:
        """The cell-aligned rectangle of ``camera`` (a multiple of ``cell`` on both sides) in which
        the frame's sampling box (the body box padded by :data:`~garmentnerf.model.config.BBOX_PADDING`, as both samplers pad
        it) can be seen, grown by :data:`~garmentnerf.render.presets.CHARACTER_RECT_MARGIN` cells; one
        cell in the corner when the box is out of view (nothing to render)."""
        rect = box_rect(camera, self.sampling_box(features), cell=cell, margin_cells=CHARACTER_RECT_MARGIN)
        return rect if rect is not None else PixelRect(0, 0, cell, cell)

    def render_image(self, frame: int, camera: Camera, palette=None, background=None, quality: float | None = None,
                     **kwargs) -> np.ndarray:
        """(H, W, 3) float32: :meth:`render` then :meth:`NeuralFrame.composite` at the camera's size."""
        return self.render(frame, camera, quality, **kwargs).composite(palette, background)

    # ---- lifetime -------------------------------------------------------------------------------------
    def close(self) -> None:
        self.frames.clear()
        for plan in self._plans.values():
            plan.release()
        self._plans.clear()
        if self.builder is not None:
            self.builder.release()
            self.builder = None
        if self._body_pass is not None:
            self._body_pass.release()
            self._body_pass = None


def padded_render_camera(camera: Camera, scale: float, upsample: int) -> tuple[Camera, tuple[int, int], tuple[int, int]]:
    """The camera the model renders to show ``camera`` at ``scale`` times its pixels.

    Returns:
        the camera resized to ``(wr, hr) = round((W, H) * scale)`` and padded on the right and
        bottom to multiples of ``upsample`` (pixel centres stay put); the feature size
        ``(fw, fh)`` (the padded size over ``upsample``); and ``(wr, hr)``, to crop the maps back to.
    """
    W, H = camera.width, camera.height
    wr, hr = max(1, round(W * scale)), max(1, round(H * scale))
    fw, fh = -(-wr // upsample), -(-hr // upsample)
    cam_r = camera if (wr, hr) == (W, H) else camera.resized(wr, hr)
    padded = Camera(cam_r.K, cam_r.R, cam_r.t, fw * upsample, fh * upsample, cam_r.near, cam_r.far)
    return padded, (fw, fh), (wr, hr)


def _camera_depth(distance: torch.Tensor, opacity: torch.Tensor, camera: Camera,
                  min_opacity: float = 0.05) -> np.ndarray:
    """Ray distances (h, w) -> camera-space z, 0 where the opacity is below ``min_opacity``."""
    _, dirs = camera_rays(camera, torch.float64)
    cos = (dirs @ torch.as_tensor(camera.R, dtype=torch.float64).T)[..., 2]  # z of the unit camera ray
    z = distance.double() * cos
    z = torch.where(opacity >= min_opacity, z, torch.zeros_like(z))
    return z.float().numpy()


__all__ = ["RenderSession", "NeuralFrame", "resolve_motion", "resolve_composition", "padded_render_camera",
           "DEFAULT_PRESET", "COMPOSITIONS"]
