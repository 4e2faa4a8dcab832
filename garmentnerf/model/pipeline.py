"""The full Garment Animation NeRF forward pass (paper Sec. 4), assembled from the model modules.

Two levels, so that a viewer can cache what the camera does not change:

1. :meth:`GarmentAnimationNeRF.prepare_frame` ``(FrameInputs) -> FrameFeatures`` -- per body frame:
   the dynamic feature map F^s_t = E([N_t, V_t]); the reference images I^_t(c^fr), I^_t(c^ba) =
   G_img(body UVs at the reference cameras) (or images supplied in the inputs); the detail maps
   F^d_t = G_en(reference images); the frame's body bound for closest-point queries
   (:meth:`~garmentnerf.geometry.body_points.BodyPointProjector.bind`), its vertex normals and its
   box. The GL passes that make :class:`FrameInputs` live in
   :class:`~garmentnerf.render.frame_inputs.FrameInputBuilder`, outside this ``nn.Module``.
2. :meth:`GarmentAnimationNeRF.render` ``(FrameFeatures, camera) -> RenderOutput`` -- per view:
   rays through the pixel centres of the *feature image* (the camera
   :meth:`~garmentnerf.conventions.Camera.resized` to ``cfg.decoder.feature_image_resolution``); the
   sampler passed in (:class:`~garmentnerf.model.samplers.Sampler`, bound to the frame and the
   feature camera; default the paper's
   :class:`~garmentnerf.model.samplers.BoxStratifiedSampler`) places packed samples: rays it
   gives no segment get no sample at all. Per sample: the closest skin point b_t, its signed
   distance h, the canonical point b_o and its atlas UV; a sample filter passed in (e.g. the
   garment's height band) may drop the sample here; the field
   (:class:`~garmentnerf.model.field.Field`, the paper's M_NeRF) -> (sigma, zeta) from the body
   points and the frame's features; packed volume rendering, segment by segment with optional
   early ray termination (:func:`~garmentnerf.model.volume_rendering.render_packed_segmented`) ->
   F^zeta (C_zeta, h, w); M_D -> :class:`~garmentnerf.model.palette.DecomposedMaps` at
   ``2**cfg.decoder.upsample_steps`` times the feature size. :attr:`RenderOutput.image` composes them with the palette when asked
   for (training); a viewer composes them itself, once, at its output size.

Gradients
    Flow into E, G_en, M_NeRF, M_D and the palette. The body geometry of a sample (b_t, h, b_o,
    UV, reference-camera projections, visibility) is computed without gradient -- it is an input
    -- but the features read at it carry the gradient of the maps they were read from. G_img runs
    under ``torch.no_grad`` while frozen (:meth:`GarmentAnimationNeRF.set_image_generator_frozen`;
    frozen by default since its pre-training is a separate stage).

Chunking and cancellation
    Samples are processed in chunks of about ``chunk_points`` (default 16384; the 2-core CPU runs
    the MLP fastest on 4k-16k points per call): whole rays per chunk without early termination,
    a few samples of every live ray per segment with it; without autograd only one chunk's
    per-sample tensors are alive. The body projection comes first, for all of a render's samples,
    :data:`PROJECTION_CHUNK_POINTS` at a time (with early termination it also projects the samples
    the march then skips: 8 % of the ``full`` preset's). ``should_cancel()`` is called before every
    chunk and every projection call but the first; when it returns True the render raises
    :class:`RenderCancelled` (nothing is left half-written: the model holds no per-render state).

Timings
    :class:`RenderOutput` ``timings`` (milliseconds): the frame stages copied from the
    :class:`FrameFeatures` used (``info_maps``, ``reference_passes`` from the GL builder;
    ``surface``, ``reference_images``, ``encoders`` from :meth:`prepare_frame`; a cached frame
    shows what it cost when it was made) and this render's stages ``rays`` (rays + sampler),
    ``projection``, ``features`` (map reads + detail selection), ``mlp``, ``compositing``
    (volume rendering), ``decoder`` (M_D); plus ``frame_total`` and ``render_total``.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass, replace

import numpy as np
import torch
from torch import nn

from garmentnerf.body.surface import vertex_normals
from garmentnerf.conventions import Camera
from garmentnerf.geometry.body_points import BodyPointProjector, BodyPoints
from garmentnerf.model.config import BACKGROUND, BBOX_PADDING, DYNAMIC_FEATURE_DIM, ModelConfig
from garmentnerf.model.detail_features import DEFAULT_VISIBILITY_TOLERANCE
from garmentnerf.model.field import Field
from garmentnerf.model.frame_codes import FrameCodes
from garmentnerf.model.frame_context import FrameFeatures, FrameInputs
from garmentnerf.model.image_generator import ImageGenerator, freeze
from garmentnerf.model.nerf_mlp import GarmentNeRF
from garmentnerf.model.palette import DecomposedMaps, Palette, PaletteDecoder, check_palette
from garmentnerf.model.samplers import BoxStratifiedSampler, SampleFilter, Sampler, body_aabb
from garmentnerf.model.unet import DetailEncoder, DynamicFeatureEncoder
from garmentnerf.model.volume_rendering import render_packed_segmented

#: Default samples per chunk (per-sample work: feature reads, MLP, compositing).
DEFAULT_CHUNK_POINTS = 16384
#: Samples projected onto the body per call: a render's samples are projected before the march,
#: this many at a time (the exact search pays a fixed cost per call and walks longer Morton runs in
#: a larger set: 1.2 against 1.7 us per sample in the 16k chunks, docs/lab/ledger.md, "The projection's walk").
PROJECTION_CHUNK_POINTS = 1 << 17

#: Stages of :meth:`GarmentAnimationNeRF.prepare_frame` / the GL builder, in pipeline order.
FRAME_STAGES = ("info_maps", "reference_passes", "surface", "reference_images", "encoders")
#: Stages of :meth:`GarmentAnimationNeRF.render`, in pipeline order.
RENDER_STAGES = ("rays", "projection", "features", "mlp", "compositing", "decoder")
#: MLP precisions of :meth:`GarmentAnimationNeRF.render_features` (``auto``: float16 autocast on
#: CUDA, float32 elsewhere: on the development CPU, AMX-BF16 included, bfloat16 renders only 4 to 6 %
#: faster, the MLP being a small share of a render; training is where it pays, ``train --precision``).
PRECISIONS = ("float32", "bfloat16", "float16", "auto")


class RenderCancelled(RuntimeError):
    """``should_cancel()`` returned True between two chunks; ``points_evaluated`` before it."""

    def __init__(self, points_evaluated: int = 0):
        super().__init__(f"render cancelled after {points_evaluated} sample points")
        self.points_evaluated = points_evaluated


@dataclass
class RenderOutput:
    """One rendered view.

    Attributes:
        maps: the decoder's :class:`DecomposedMaps` (batch of 1) at the feature size times
            ``2**cfg.decoder.upsample_steps``; with :func:`compose` and any palette they give the
            image (:attr:`image`, :meth:`recolor`) without re-rendering.
        opacity: (h, w) accumulated opacity per feature-image ray (0 for rays not rendered).
        depth: (h, w) opacity-normalised expected depth along each ray (metres; 0 where opacity 0).
        median_depth: (h, w) the distance along each ray at which its opacity reaches one half
            (:func:`~garmentnerf.model.volume_rendering.median_depth_packed`; 0 where it never does): the
            surface a bake is built on.
        feature_image: (C_zeta, h, w) F^zeta, the decoder's input.
        palette: (P, 3) the palette :attr:`image` is composed with; background: its RGB.
        points_evaluated: samples the NeRF MLP was evaluated at.
        rays_evaluated: rays with at least one sample.
        rays_total: rays asked for (the whole feature image, or the subset).
        timings: milliseconds per stage (see the module docstring).
        samples_placed: samples the sampler placed.
        points_projected: samples projected on the body (those early termination did not skip).
        rays_terminated: rays stopped by early termination with samples left.
    """

    maps: DecomposedMaps
    opacity: torch.Tensor
    depth: torch.Tensor
    feature_image: torch.Tensor
    palette: torch.Tensor
    background: tuple[float, float, float]
    points_evaluated: int
    rays_evaluated: int
    rays_total: int
    timings: dict[str, float]
    samples_placed: int = 0
    points_projected: int = 0
    rays_terminated: int = 0
    median_depth: torch.Tensor | None = None

    @functools.cached_property
    def image(self) -> torch.Tensor:
        """(3, H, W) the maps composed with :attr:`palette` over :attr:`background` (computed on
        first use, with autograd as the grad mode then says)."""
        return self.maps.compose(self.palette.to(self.maps.mask.device), self.background)[0]

    def recolor(self, palette: torch.Tensor, background=None) -> torch.Tensor:
        """(3, H, W) the image with another palette (no network runs)."""
        bg = self.background if background is None else background
        return self.maps.compose(palette.to(self.maps.mask.device), bg)[0]


def _trains(module: nn.Module) -> bool:
    """Whether any parameter of ``module`` takes a gradient (False for a frozen module)."""
    return any(p.requires_grad for p in module.parameters())


class _Stopwatch:
    """Accumulates wall time per stage into a dict (ms), synchronising CUDA when used."""

    def __init__(self, timings: dict[str, float], device: torch.device):
        self.timings = timings
        self.cuda = device.type == "cuda"

    @contextmanager
    def __call__(self, name: str):
        if self.cuda:
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        try:
            yield
        finally:
            if self.cuda:
                torch.cuda.synchronize()
            self.timings[name] = self.timings.get(name, 0.0) + (time.perf_counter() - t0) * 1e3


def palette_initial_colors(init, palette_size: int = 2) -> torch.Tensor:
    """The palette's starting colors p* ``(P, 3)`` from a scene's ``palette_init`` or a tensor.

    Args:
        init: ``{"garment": rgb, "body": rgb}`` (``Scene.palette_init``; garment first as in
            :func:`~garmentnerf.model.palette.palette_from_labels`; with ``"garment_layers"``, a
            layered garment's colors, inner first), a ``(P, 3)`` tensor / array in [0, 1], or None
            (mid grey for every color, for tests and untrained models).
        palette_size: P of the config: 2 gives ``[garment, body]``; P > 2 gives the first P - 1
            garment layers and the body (the palette's last color is always the body's).
    """
    if init is None:
        return torch.full((palette_size, 3), 0.5)
    if isinstance(init, dict):
        missing = [k for k in ("garment", "body") if init.get(k) is None]
        if missing:
            raise ValueError(f"palette_init has no color for {', '.join(missing)}")
        if palette_size == 2:
            garment = [init["garment"]]
        else:
            layers = init.get("garment_layers") or []
            if len(layers) < palette_size - 1 or any(c is None for c in layers[:palette_size - 1]):
                raise ValueError(f"palette_size={palette_size} needs {palette_size - 1} garment layer colors; "
                                 f"palette_init has {len(layers)} (a one-layer garment's palette has 2 colors)")
            garment = list(layers[:palette_size - 1])
        out = torch.tensor([*garment, init["body"]], dtype=torch.float32)
    else:
        out = torch.as_tensor(np.asarray(init, dtype=np.float32))
    if out.shape != (palette_size, 3):
        raise ValueError(f"palette init must be ({palette_size}, 3), got {tuple(out.shape)}")
    check_palette(out)
    return out


def bfloat16_is_fast(device: torch.device | str) -> bool:
    """Whether ``device`` multiplies bfloat16 matrices much faster than float32 ones: a CUDA GPU
    that supports bfloat16, or a CPU with AMX-BF16 tiles (Intel Xeon from Sapphire Rapids on; on
    the development CPU a 60,000 x 128 by 128 x 128 product takes 0.94 ms in bfloat16 against
    8.1 ms in float32). Other CPUs get False."""
    device = torch.device(device)
    if device.type == "cuda":
        return torch.cuda.is_available() and torch.cuda.is_bf16_supported()
    if device.type == "cpu":
        return bool(torch.cpu.get_capabilities().get("amx_bf16", False))
    return False


def _autocast(precision: str, device: torch.device):
    """The autocast context of an MLP ``precision`` (one of :data:`PRECISIONS`)."""
    if precision == "auto":
        precision = "float16" if device.type == "cuda" else "float32"
    if precision == "float32":
        return nullcontext()
    return torch.autocast(device_type=device.type, dtype=getattr(torch, precision))


class GarmentAnimationNeRF(nn.Module):
    """E, G_img, G_en, M_NeRF, M_D and the palette, with the per-frame and per-view passes.

    Args:
        cfg: the components' sizes and switches.
        body: the body model (its topology and template; the skin shell is used for projection).
        palette_init: see :func:`palette_initial_colors` (a scene's ``palette_init``).
        freeze_image_generator: start with G_img frozen (its pre-training is a separate stage).
        visibility_tolerance: metres, see
            :func:`~garmentnerf.model.detail_features.reference_visibility`.
        chunk_points: samples per chunk (see the module docstring).
        projector: a prebuilt :class:`BodyPointProjector` for ``body`` (built here if None;
            building it takes about 0.4 s for the bundled body).

    Submodules (None when ablated): ``encoder`` (E), ``image_generator`` (G_img),
    ``detail_encoder`` (G_en), ``nerf`` (the :class:`~garmentnerf.model.field.Field`: M_NeRF),
    ``frame_codes``, ``decoder`` (M_D), ``palette``.
    """

    def __init__(self, cfg: ModelConfig, body, palette_init=None, *,
                 freeze_image_generator: bool = True, visibility_tolerance: float = DEFAULT_VISIBILITY_TOLERANCE,
                 chunk_points: int = DEFAULT_CHUNK_POINTS, projector: BodyPointProjector | None = None):
        super().__init__()
        cfg.validate()
        if cfg.encoder.dynamic_feature and not body.has_uv:
            raise ValueError(f"body model '{body.name}' has no UV atlas; the dynamic feature needs one")
        if chunk_points < 1:
            raise ValueError(f"chunk_points must be >= 1, got {chunk_points}")
        self.cfg = cfg
        self.body = body
        self.encoder = DynamicFeatureEncoder.from_config(cfg) if cfg.encoder.dynamic_feature else None
        self.image_generator = ImageGenerator.from_config(cfg) if cfg.encoder.detail_feature else None
        self.detail_encoder = DetailEncoder.from_config(cfg) if cfg.encoder.detail_feature else None
        self.chunk_points = int(chunk_points)
        self.projector = projector if projector is not None else BodyPointProjector(body)
        self._faces = body.faces.detach().cpu()
        # the one place a field is chosen: the paper's M_NeRF
        self.nerf: Field = GarmentNeRF.from_config(cfg, self.projector.faces, visibility_tolerance)
        self.frame_codes = None  # per-frame residuals of F^s_t (FrameCodeConfig)
        if cfg.frame_codes.enabled:
            self.frame_codes = FrameCodes(cfg.frame_codes.count, DYNAMIC_FEATURE_DIM, cfg.frame_codes.resolution,
                                          sparse=cfg.frame_codes.support_margin >= 0)
        self.decoder = PaletteDecoder.from_config(cfg)
        self.palette = Palette(palette_initial_colors(palette_init, cfg.decoder.palette_size))
        self._image_generator_frozen = False
        if self.image_generator is not None and freeze_image_generator:
            self.set_image_generator_frozen(True)

    # ------------------------------------------------------------------ modules and state
    @property
    def device(self) -> torch.device:
        return self.palette.colors.device

    @property
    def image_generator_frozen(self) -> bool:
        """True while G_img is frozen (no gradients, eval mode, run under no_grad)."""
        return self._image_generator_frozen

    def set_image_generator_frozen(self, frozen: bool = True) -> None:
        """Freeze G_img (after its pre-training) or unfreeze it (to pre-train or fine-tune)."""
        if self.image_generator is None:
            self._image_generator_frozen = bool(frozen)
            return
        if frozen:
            freeze(self.image_generator)
        else:
            for p in self.image_generator.parameters():
                p.requires_grad_(True)
            self.image_generator.train(self.training)
        self._image_generator_frozen = bool(frozen)

    def train(self, mode: bool = True) -> "GarmentAnimationNeRF":
        super().train(mode)
        if self.image_generator is not None and self._image_generator_frozen:
            self.image_generator.eval()
        return self

    def trainable_modules(self) -> dict[str, nn.Module]:
        """The modules the NeRF training updates: ``encoder``, ``detail_encoder``, ``nerf``,
        ``decoder``, ``palette``, ``frame_codes`` (those the config has), plus ``image_generator`` when
        unfrozen."""
        mods = {"encoder": self.encoder, "detail_encoder": self.detail_encoder, "nerf": self.nerf,
                "decoder": self.decoder, "palette": self.palette, "frame_codes": self.frame_codes}
        if not self._image_generator_frozen:
            mods["image_generator"] = self.image_generator
        return {k: m for k, m in mods.items() if m is not None}

    def growable_prefixes(self) -> tuple[str, ...]:
        """State-dict prefixes of the parameters that may come from a narrower MLP's weights (the
        NeRF MLP's layers, grown with :func:`~garmentnerf.train.run.grow_linear_tensor`)."""
        return tuple("nerf." + p for p in getattr(self.nerf, "GROWABLE", ()))

    def frame_code_prefixes(self) -> tuple[str, ...]:
        """State-dict prefixes of the per-frame codes (none without them): zero at the start, so they
        may be missing from weights trained without them (the model then computes what those weights'
        own model computes), and they learn at ``cfg.frame_codes.lr_scale`` times the rate."""
        return ("frame_codes.",) if self.frame_codes is not None else ()

    def frame_code(self, index: int, resolution: int) -> torch.Tensor:
        """(C_s, R, R) the per-frame code ``index`` upsampled bilinearly to E's output resolution R."""
        if self.frame_codes is None:
            raise ValueError("this model has no per-frame codes (FrameCodeConfig.resolution)")
        return self.frame_codes(index, resolution)

    def adopt_state_shapes(self, state: dict[str, torch.Tensor]) -> None:
        """Fit the tensors whose shape is data, not configuration, to a state dict about to be loaded:
        the sparse per-frame codes take its support (:meth:`FrameCodes.adopt_state
        <garmentnerf.model.frame_codes.FrameCodes.adopt_state>`)."""
        if self.frame_codes is not None:
            self.frame_codes.adopt_state(state, "frame_codes.")

    # ------------------------------------------------------------------ per frame
    def prepare_frame(self, inputs: FrameInputs, geometry: FrameFeatures | None = None,
                      code: int | None = None) -> FrameFeatures:
        """Everything of one frame that does not depend on the camera (see the module docstring).

        Runs E, G_img (unless ``inputs.reference_images`` is given) and G_en with autograd as the
        caller's grad mode says (G_img always without while frozen); call under
        ``torch.no_grad()`` for viewing.

        ``geometry``: features prepared earlier for the same frame (the same inputs; only their
        ``posed_vertices``, ``vertex_normals``, ``surface``, ``aabb`` and, as below,
        ``encoder_output`` and ``detail_features`` are read), whose body geometry is then reused
        instead of rebuilt: binding the body (its search tree) and its normals
        cost more than the encoders, and a trainer meets each frame many times. ValueError when
        its vertices are not exactly those of ``inputs``.

        ``code``: the frame's per-frame code (a training frame of a model with codes,
        :meth:`frame_code`), added to E's output; None: E's output alone.

        While no parameter of E trains, its output is the same every time the frame is prepared: it is
        returned as ``encoder_output`` and, when ``geometry`` carries it, reused instead of running E
        again; so is ``geometry``'s ``detail_features`` while neither G_en nor the reference images have
        a gradient to take. A codes-only stage (``ModelConfig.trained_parameters``) then runs neither
        encoder after a frame's first step.
        """
        cfg = self.cfg
        inputs.validate(cfg, self.body.asset.num_vertices)
        dev = self.device
        timings = dict(inputs.timings)
        sw = _Stopwatch(timings, dev)
        with sw("surface"), torch.no_grad():
            verts = inputs.posed_vertices.detach().to("cpu", torch.float32).contiguous()
            if geometry is None:
                normals = vertex_normals(verts, self._faces)
                surface = self.bind_body(verts)
                aabb = body_aabb(verts)
            elif torch.equal(geometry.posed_vertices, verts):
                verts, normals, surface, aabb = (geometry.posed_vertices, geometry.vertex_normals, geometry.surface,
                                                 geometry.aabb)
            else:
                raise ValueError(f"geometry of frame {geometry.frame} is not that of the posed body of frame "
                                 f"{inputs.frame}")
        dynamic = reference_images = detail = encoder_output = None
        if cfg.encoder.dynamic_feature:
            with sw("encoders"):
                frozen = not _trains(self.encoder)
                if frozen and geometry is not None and geometry.encoder_output is not None:
                    dynamic = geometry.encoder_output
                else:
                    dynamic = self.encoder(inputs.info_maps.to(dev, torch.float32).unsqueeze(0))[0]
                if frozen:
                    encoder_output = dynamic.detach()
                if code is not None:
                    dynamic = dynamic + self.frame_code(code, dynamic.shape[-1])
        if cfg.encoder.detail_feature:
            with sw("reference_images"):
                if inputs.reference_images is not None:
                    reference_images = inputs.reference_images.to(dev, torch.float32)
                else:
                    grad = torch.no_grad() if self._image_generator_frozen else nullcontext()
                    with grad:
                        reference_images = self.image_generator(inputs.reference_uv.to(dev, torch.float32),
                                                                inputs.reference_mask.to(dev))
            with sw("encoders"):
                kept = None if geometry is None else geometry.detail_features
                if (kept is not None and not kept.requires_grad and not reference_images.requires_grad
                        and not _trains(self.detail_encoder)):
                    detail = kept
                else:
                    detail = self.detail_encoder(reference_images)
        return FrameFeatures(verts, normals, surface, aabb, dynamic, reference_images, detail,
                             tuple(inputs.reference_cameras), inputs.reference_depth.detach().cpu(), inputs.frame,
                             timings, encoder_output)

    def reusable_frame(self, features: FrameFeatures) -> FrameFeatures:
        """What of a frame's ``features`` a later :meth:`prepare_frame` of the same frame reuses when given
        it as ``geometry``: the body geometry, E's output before the code (kept only while E is frozen)
        and G_en's output while neither G_en nor the reference images take a gradient; the rest (this
        step's graph, the reference images its inputs hold) left out."""
        detail = features.detail_features
        frozen_detail = (detail is not None and not detail.requires_grad and self.detail_encoder is not None
                         and not _trains(self.detail_encoder))
        return replace(features, dynamic_features=None, reference_images=None, timings={},
                       detail_features=detail if frozen_detail else None)

    def bind_body(self, posed_vertices: torch.Tensor):
        """The body posed as ``posed_vertices (V, 3)`` bound for closest-point queries on the
        model's device (the exact KD-tree search on the CPU, its dense twin elsewhere): what
        :meth:`prepare_frame` puts in ``FrameFeatures.surface``."""
        verts = posed_vertices.detach().to("cpu" if self.device.type == "cpu" else self.device, torch.float32)
        return self.projector.bind(verts, torch.float32)

    # ------------------------------------------------------------------ per sample
    def sample_geometry(self, frame: FrameFeatures, positions: torch.Tensor) -> BodyPoints:
        """Body-aware coordinates of ``positions (n, 3)`` (no gradient, float32, on the device the
        frame's body is bound on): b_t, h, b_o, UV and the skin face
        (:meth:`BodyPointProjector.bind`'s convention), from the frame's bound body."""
        with torch.no_grad():
            points = frame.surface.project(positions.detach().to(frame.surface.vertices.device, torch.float32))
        return BodyPoints(points.face, points.bary, points.closest.float(), points.signed_distance.float(),
                          points.canonical.float(), points.uv.float())

    def evaluate_samples(self, frame: FrameFeatures, positions: torch.Tensor, *,
                         sample_filter: SampleFilter | None = None, precision: str = "float32",
                         timings: dict | None = None,
                         points: BodyPoints | None = None) -> tuple[torch.Tensor, torch.Tensor, int]:
        """The field at world ``positions (n, 3)`` of ``frame``: body projection, the sample filter, the
        field (:meth:`Field.evaluate <garmentnerf.model.field.Field.evaluate>`). ``points``: the
        positions' :meth:`sample_geometry`, when the caller has it already (not projected again).

        Returns:
            sigma (n,), zeta (n, C) on the model's device (0 for the samples the filter drops; C is the
            field's ``zeta_channels``), and how many samples the field evaluated.
        """
        dev = self.device
        sw = _Stopwatch({} if timings is None else timings, dev)
        n = positions.shape[0]
        with sw("projection"):
            points = self.sample_geometry(frame, positions) if points is None else points
            kept = None
            if sample_filter is not None:
                kept = sample_filter.keep(points).nonzero().squeeze(1)
                points = points.select(kept)
        if len(points) == 0:
            return torch.zeros(n, device=dev), torch.zeros(n, self.nerf.zeta_channels, device=dev), 0
        sigma, zeta = self.nerf.evaluate(frame, points, clock=sw, autocast=_autocast(precision, dev))
        if kept is not None and kept.shape[0] < n:
            rows = kept.to(dev)
            sigma = torch.zeros(n, device=dev).index_copy(0, rows, sigma)
            zeta = torch.zeros(n, zeta.shape[-1], device=dev).index_copy(0, rows, zeta)
        return sigma, zeta, len(points)

    def box_sampler(self, samples_per_ray: int) -> BoxStratifiedSampler:
        """The paper's box sampler at ``samples_per_ray`` stratified samples, what this model is rendered
        with by default."""
        return BoxStratifiedSampler(samples_per_ray, BBOX_PADDING)

    # ------------------------------------------------------------------ per view
    def _ray_subset(self, rays, n_pixels: int, shape: tuple[int, int]) -> torch.Tensor | None:
        if rays is None:
            return None
        rays = torch.as_tensor(rays)
        if rays.dtype == torch.bool:
            if tuple(rays.shape) not in (shape, (n_pixels,)):
                raise ValueError(f"ray mask must be {shape} or ({n_pixels},), got {tuple(rays.shape)}")
            return rays.reshape(-1).nonzero().squeeze(1)
        rays = rays.reshape(-1).long()
        if rays.numel() and (int(rays.min()) < 0 or int(rays.max()) >= n_pixels):
            raise ValueError(f"ray indices must lie in [0, {n_pixels})")
        if torch.unique(rays).numel() != rays.numel():
            raise ValueError("ray indices must be unique")
        return rays

    def _project_samples(self, frame: FrameFeatures, positions: torch.Tensor,
                         should_cancel: Callable[[], bool] | None) -> BodyPoints:
        """:meth:`sample_geometry` of a render's samples ``positions (n, 3)``, :data:`PROJECTION_CHUNK_POINTS` per
        call, ``should_cancel`` asked before every call but the first."""
        parts = []
        for c0 in range(0, positions.shape[0], PROJECTION_CHUNK_POINTS):
            if c0 and should_cancel is not None and should_cancel():
                raise RenderCancelled(0)
            parts.append(self.sample_geometry(frame, positions[c0:c0 + PROJECTION_CHUNK_POINTS]))
        if not parts:
            return self.sample_geometry(frame, positions)
        return parts[0] if len(parts) == 1 else BodyPoints.concat(parts)

    def render_features(self, frame: FrameFeatures, camera: Camera, rays=None, *, sampler: Sampler | None = None,
                        sample_filter: SampleFilter | None = None, termination_eps: float = 0.0,
                        precision: str = "float32", feature_size: tuple[int, int] | None = None,
                        training: bool | None = None, generator: torch.Generator | None = None,
                        should_cancel: Callable[[], bool] | None = None,
                        chunk_points: int | None = None, timings: dict | None = None) -> dict:
        """The volume-rendering half of :meth:`render`: F^zeta, opacity, depth (no decoding).

        Returns a dict with ``feature_image (C, h, w)`` (the rendered zeta), ``opacity (h, w)``,
        ``depth (h, w)``, ``median_depth (h, w)`` and the counts ``points_evaluated``, ``rays_evaluated``, ``rays_total``, ``samples_placed``,
        ``points_projected``, ``rays_terminated``; stage times are added to ``timings`` when
        given. See :meth:`render` for the arguments.
        """
        cfg = self.cfg
        if precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {PRECISIONS}, got {precision!r}")
        fw, fh = feature_size if feature_size is not None else (cfg.decoder.feature_image_resolution,) * 2
        training = self.training if training is None else training
        chunk = self.chunk_points if chunk_points is None else int(chunk_points)
        sampler = self.box_sampler(cfg.sampler.samples_per_ray) if sampler is None else sampler
        dev = self.device
        timings = {} if timings is None else timings
        sw = _Stopwatch(timings, dev)
        C = self.nerf.zeta_channels
        n_pixels = fw * fh

        with sw("rays"):
            subset = self._ray_subset(rays, n_pixels, (fh, fw))
            pixels = torch.arange(n_pixels) if subset is None else subset.cpu()
            samples = sampler.bind(frame, camera.resized(fw, fh)).sample(pixels, training=training,
                                                                         generator=generator)
            n_rays = samples.n_rays
        evaluated = 0
        with sw("projection"):
            geometry = self._project_samples(frame, samples.positions, should_cancel)

        def field(index: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            """sigma (n,), zeta (n, C) of the packed samples ``index``, ``chunk`` at a time."""
            nonlocal evaluated
            sigmas, zetas = [], []
            for c0 in range(0, index.shape[0], chunk):
                if should_cancel is not None and should_cancel():
                    raise RenderCancelled(evaluated)
                part = index[c0:c0 + chunk].to(samples.positions.device)
                sigma, zeta, n = self.evaluate_samples(frame, samples.positions[part], sample_filter=sample_filter,
                                                       precision=precision, timings=timings,
                                                       points=geometry.select(part))
                sigmas.append(sigma)
                zetas.append(zeta)
                evaluated += n
            if len(sigmas) == 1:
                return sigmas[0], zetas[0]
            return torch.cat(sigmas), torch.cat(zetas)

        field_keys = ("projection", "features", "mlp")
        field_before = sum(timings.get(k, 0.0) for k in field_keys)
        t0 = time.perf_counter()
        march = render_packed_segmented(field, samples.t_starts, samples.t_ends, samples.ray_ids, n_rays, C,
                                        chunk_points=chunk, termination_eps=float(termination_eps), device=dev)
        march_ms = (time.perf_counter() - t0) * 1e3
        field_ms = sum(timings.get(k, 0.0) for k in field_keys) - field_before
        timings["compositing"] = timings.get("compositing", 0.0) + max(0.0, march_ms - field_ms)
        with sw("compositing"):
            opacity = march.opacity
            depth = torch.where(opacity > 0, march.depth / opacity.clamp_min(1e-10), torch.zeros_like(march.depth))
            median = march.median_depth
            feat = march.values
            if subset is not None:
                idx = subset.to(dev)
                feat = feat.new_zeros(n_pixels, C).index_copy(0, idx, feat)
                opacity = opacity.new_zeros(n_pixels).index_copy(0, idx, opacity)
                depth = depth.new_zeros(n_pixels).index_copy(0, idx, depth)
                median = median.new_zeros(n_pixels).index_copy(0, idx, median)
            feature_image = feat.T.reshape(C, fh, fw)
        hit = samples.hit.cpu()  # rays given a segment: exactly those with samples
        return {"feature_image": feature_image, "opacity": opacity.reshape(fh, fw), "depth": depth.reshape(fh, fw),
                "median_depth": median.reshape(fh, fw),
                "points_evaluated": evaluated, "rays_evaluated": int(hit.sum()), "rays_total": n_rays,
                "samples_placed": int(samples.ray_ids.shape[0]), "points_projected": march.samples_evaluated,
                "rays_terminated": int((march.terminated & hit).sum())}

    def decode(self, feature_image: torch.Tensor, timings: dict | None = None) -> DecomposedMaps:
        """M_D: F^zeta ``(C, h, w)`` -> the decomposed maps (batch of 1) at ``2**cfg.decoder.upsample_steps``
        times the size. Composition with a palette is the caller's (:meth:`DecomposedMaps.compose`)."""
        timings = {} if timings is None else timings
        with _Stopwatch(timings, self.device)("decoder"):
            return self.decoder(feature_image.unsqueeze(0))

    def render(self, frame: FrameFeatures, camera: Camera, rays=None, *, sampler: Sampler | None = None,
               sample_filter: SampleFilter | None = None, termination_eps: float = 0.0, precision: str = "float32",
               palette: torch.Tensor | None = None, background=None, feature_size: tuple[int, int] | None = None,
               training: bool | None = None, generator: torch.Generator | None = None,
               should_cancel: Callable[[], bool] | None = None, chunk_points: int | None = None) -> RenderOutput:
        """Render ``frame`` seen by ``camera`` (see the module docstring).

        Args:
            frame: from :meth:`prepare_frame`.
            camera: the target view, any resolution: rays go through the pixel centres of the
                camera resized to ``feature_size`` (default ``cfg.decoder.feature_image_resolution``
                squared), so the maps are ``2**cfg.decoder.upsample_steps`` times that.
            rays: None (all), or a subset of the feature-image rays: (M,) unique row-major pixel
                indices or an (h, w) bool mask; the others get zero features and opacity.
            sampler: where samples go (:class:`~garmentnerf.model.samplers.Sampler`); default
                :meth:`box_sampler` at ``cfg.sampler.samples_per_ray``: the paper's box sampler.
            sample_filter: drops projected samples before the MLP (e.g. the garment's height
                band, :class:`~garmentnerf.model.height_band.HeightBandFilter`); None keeps all.
            termination_eps: a ray stops once its transmittance falls below this (0: never; see
                :func:`~garmentnerf.model.volume_rendering.render_packed_segmented`).
            precision: MLP precision, one of :data:`PRECISIONS`.
            palette: (P, 3) in [0, 1] for :attr:`RenderOutput.image` (default: the learned palette).
            background: RGB in [0, 1] (default :data:`~garmentnerf.model.config.BACKGROUND`).
            feature_size: (w, h) rays per side.
            training: jittered (training-mode) samples; default ``self.training``.
            generator: random source of the jitter.
            should_cancel: called before every chunk; True raises :class:`RenderCancelled`.
            chunk_points: samples per chunk (default ``self.chunk_points``).
        """
        t0 = time.perf_counter()
        timings: dict[str, float] = {}
        out = self.render_features(frame, camera, rays, sampler=sampler, sample_filter=sample_filter,
                                   termination_eps=termination_eps, precision=precision, feature_size=feature_size,
                                   training=training, generator=generator, should_cancel=should_cancel,
                                   chunk_points=chunk_points, timings=timings)
        maps = self.decode(out["feature_image"], timings)
        render_total = (time.perf_counter() - t0) * 1e3
        all_timings = {k: frame.timings[k] for k in FRAME_STAGES if k in frame.timings}
        all_timings["frame_total"] = sum(all_timings.values())
        all_timings.update({k: timings.get(k, 0.0) for k in RENDER_STAGES})
        all_timings["render_total"] = render_total
        pal = self.palette() if palette is None else palette.to(self.device)
        bg = tuple(float(c) for c in (BACKGROUND if background is None else background))
        return RenderOutput(maps, out["opacity"], out["depth"], out["feature_image"], pal, bg,
                            out["points_evaluated"], out["rays_evaluated"], out["rays_total"], all_timings,
                            out["samples_placed"], out["points_projected"], out["rays_terminated"],
                            out["median_depth"])

    def forward(self, frame: FrameInputs | FrameFeatures, camera: Camera, **kwargs) -> RenderOutput:
        """:meth:`render`, preparing the frame first when given :class:`FrameInputs`."""
        if isinstance(frame, FrameInputs):
            frame = self.prepare_frame(frame)
        return self.render(frame, camera, **kwargs)


__all__ = ["GarmentAnimationNeRF", "RenderOutput", "RenderCancelled",
           "palette_initial_colors", "bfloat16_is_fast", "FRAME_STAGES", "RENDER_STAGES", "PRECISIONS",
           "DEFAULT_CHUNK_POINTS"]
