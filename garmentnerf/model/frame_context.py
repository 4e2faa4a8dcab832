"""Per-frame inputs of the Garment Animation NeRF, and the GL helper that makes them.

A body frame t is everything the model needs that does not depend on the target camera:

:class:`FrameInputs` (made by :class:`FrameInputBuilder`, which runs the GL passes)
    The posed body vertices, the UV info maps [N_t, V_t] and the G-buffers of the body seen from
    the two reference cameras (front, back): per-pixel UV, mask, depth and face. Plain tensors;
    no network has run yet.

:class:`FrameFeatures` (made by
:meth:`garmentnerf.model.pipeline.GarmentAnimationNeRF.prepare_frame`)
    What the networks make of a :class:`FrameInputs`: the dynamic feature map F^s_t (E), the
    reference images (G_img) and the detail feature maps F^d_t (G_en), plus the frame's body
    geometry prepared for sample projection (the bound closest-point search, vertex normals, the
    body box). A viewer caches it while the camera moves: rendering a new view then costs only the
    per-sample work.

GL stays here, out of the ``nn.Module``: the model only ever sees tensors, so it trains and
renders in processes (or on machines) without an OpenGL context, e.g. from cached inputs.

Reference cameras
    Front first, then back (paper: the front and back reference views; the scene rig's
    ``ref_front`` / ``ref_back``, :func:`garmentnerf.data.cameras.reference_cameras`). They are
    resized to ``cfg.encoder.reference_resolution`` squared (:meth:`Camera.resized`: the same view, so a
    non-square scene camera gets non-square pixels, consistently for the pass and for
    :func:`~garmentnerf.conventions.project_points`).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import torch

from garmentnerf.conventions import Camera
from garmentnerf.gl.camera_pass import CameraPass

if TYPE_CHECKING:  # pragma: no cover
    import moderngl

    from garmentnerf.body.model import BodyModel, PosedBody
    from garmentnerf.geometry.body_points import BoundBody
    from garmentnerf.model.config import ModelConfig

#: Names of the reference cameras in a scene rig, in the order the model uses them.
REFERENCE_CAMERA_NAMES = ("ref_front", "ref_back")


@dataclass
class FrameInputs:
    """Camera-independent inputs of one body frame (all CPU tensors, no gradient).

    Attributes:
        posed_vertices: (V, 3) float32 posed body vertices of frame t (world, metres).
        info_maps: (3 + 3 k, R, R) float32 [N_t, V_t] (:meth:`garmentnerf.gl.info_maps.InfoMaps.stacked`).
        reference_cameras: (front, back) cameras at the reference resolution S x S.
        reference_uv: (2, S, S, 2) body atlas UV seen at each reference pixel (0 in background).
        reference_mask: (2, S, S) bool, pixels that see the body.
        reference_depth: (2, S, S) camera-space z of the closest body surface (+inf in background).
        reference_face: (2, S, S) int64 body face seen at each pixel (-1 in background).
        reference_images: optional (2, 3, S, S) images in [0, 1] used *instead of* G_img (e.g.
            ground-truth reference views while G_img is not trained yet, as the authors' code
            does early on); None: G_img makes them.
        frame: the frame index this was built for (informative).
        timings: ms spent building it, per stage (``info_maps``, ``reference_passes``).
    """

    posed_vertices: torch.Tensor
    info_maps: torch.Tensor
    reference_cameras: tuple[Camera, Camera]
    reference_uv: torch.Tensor
    reference_mask: torch.Tensor
    reference_depth: torch.Tensor
    reference_face: torch.Tensor
    reference_images: torch.Tensor | None = None
    frame: int | None = None
    timings: dict[str, float] = field(default_factory=dict)

    def validate(self, cfg: "ModelConfig", num_vertices: int | None = None) -> None:
        """Raise ValueError when the shapes disagree with ``cfg`` (and the body's vertex count)."""
        V = self.posed_vertices.shape[0]
        if self.posed_vertices.ndim != 2 or self.posed_vertices.shape[1] != 3:
            raise ValueError(f"posed_vertices must be (V, 3), got {tuple(self.posed_vertices.shape)}")
        if num_vertices is not None and V != num_vertices:
            raise ValueError(f"posed_vertices has {V} rows, the body model has {num_vertices} vertices")
        R, C = cfg.encoder.info_map_resolution, cfg.encoder.in_channels
        if tuple(self.info_maps.shape) != (C, R, R):
            raise ValueError(f"info_maps must be ({C}, {R}, {R}) for history={cfg.encoder.history} and "
                             f"info_map_resolution={R}, got {tuple(self.info_maps.shape)}")
        S = cfg.encoder.reference_resolution
        if len(self.reference_cameras) != 2:
            raise ValueError(f"need 2 reference cameras (front, back), got {len(self.reference_cameras)}")
        for cam in self.reference_cameras:
            if (cam.width, cam.height) != (S, S):
                raise ValueError(f"reference cameras must be {S}x{S} (cfg.encoder.reference_resolution), "
                                 f"got {cam.width}x{cam.height}")
        for name, shape in (("reference_uv", (2, S, S, 2)), ("reference_mask", (2, S, S)),
                            ("reference_depth", (2, S, S)), ("reference_face", (2, S, S))):
            if tuple(getattr(self, name).shape) != shape:
                raise ValueError(f"{name} must be {shape}, got {tuple(getattr(self, name).shape)}")
        if self.reference_images is not None and tuple(self.reference_images.shape) != (2, 3, S, S):
            raise ValueError(f"reference_images must be (2, 3, {S}, {S}), got {tuple(self.reference_images.shape)}")

    def with_reference_images(self, images: torch.Tensor | None) -> "FrameInputs":
        """A copy whose reference images replace G_img's (None: back to G_img)."""
        return replace(self, reference_images=images)


@dataclass
class FrameFeatures:
    """Everything of one frame that the target camera does not change (see the module docstring).

    Attributes:
        posed_vertices: (V, 3) float32 posed body (CPU).
        vertex_normals: (V, 3) unit vertex normals of the posed body (CPU).
        surface: the body bound to this frame for closest-point queries
            (:meth:`~garmentnerf.geometry.body_points.BodyPointProjector.bind`: the exact KD-tree
            search on a CPU model, its dense twin on the model's device otherwise).
        aabb: (2, 3) tight box [min, max] of the posed body (CPU; the sampler pads it).
        dynamic_features: (C_s, R, R) F^s_t, or None when the dynamic feature is ablated.
        reference_images: (2, 3, S, S) front/back reference images, or None (detail ablated).
        detail_features: (2, C_d, S, S) F^d_t for front and back, or None (detail ablated).
        reference_cameras: (front, back) at S x S.
        reference_depth: (2, S, S) body depth seen by each reference camera (+inf background), for
            the visibility test.
        frame: the frame index (informative).
        timings: ms per stage of making it: those of the :class:`FrameInputs` (GL passes) plus
            ``surface`` (binding the projection), ``reference_images`` (G_img), ``encoders``
            (E and G_en).
        encoder_output: (C_s, R, R) E's output before the per-frame code, kept only while no
            parameter of E trains (then it is the same every time the frame is prepared, and
            :meth:`~garmentnerf.model.pipeline.GarmentAnimationNeRF.prepare_frame` reuses it from
            ``geometry``); None otherwise.
    """

    posed_vertices: torch.Tensor
    vertex_normals: torch.Tensor
    surface: "BoundBody"
    aabb: torch.Tensor
    dynamic_features: torch.Tensor | None
    reference_images: torch.Tensor | None
    detail_features: torch.Tensor | None
    reference_cameras: tuple[Camera, Camera]
    reference_depth: torch.Tensor
    frame: int | None = None
    timings: dict[str, float] = field(default_factory=dict)
    encoder_output: torch.Tensor | None = None

    def detach(self) -> "FrameFeatures":
        """The same features cut from the autograd graph (for caching across renders)."""
        def d(x):
            return None if x is None else x.detach()

        return replace(self, dynamic_features=d(self.dynamic_features), reference_images=d(self.reference_images),
                       detail_features=d(self.detail_features))


def resolve_reference_cameras(references) -> tuple[Camera, Camera]:
    """(front, back) cameras from a scene, named cameras or plain cameras.

    Args:
        references: a :class:`~garmentnerf.data.scene.Scene` (its ``reference`` split, which must
            hold ``ref_front`` and ``ref_back``), a sequence of
            :class:`~garmentnerf.data.cameras.NamedCamera` (``ref_front``/``ref_back`` by name
            when present, else the first two in order), or two :class:`Camera` (front, back).
    Raises:
        ValueError when two reference cameras cannot be found.
    """
    if hasattr(references, "cameras") and callable(references.cameras):  # a Scene
        named = references.cameras("reference")
        by_name = {c.name: c.camera for c in named}
        missing = [n for n in REFERENCE_CAMERA_NAMES if n not in by_name]
        if missing:
            raise ValueError(f"scene {getattr(references, 'root', '')} has no reference camera(s) "
                             f"{', '.join(missing)} (split 'reference'); pass the two cameras explicitly")
        return by_name["ref_front"], by_name["ref_back"]
    items = list(references)
    cams = [getattr(c, "camera", c) for c in items]
    if not all(isinstance(c, Camera) for c in cams):
        raise ValueError("reference cameras must be Camera or NamedCamera objects")
    names = [getattr(c, "name", None) for c in items]
    if all(n in names for n in REFERENCE_CAMERA_NAMES):
        return tuple(cams[names.index(n)] for n in REFERENCE_CAMERA_NAMES)  # type: ignore[return-value]
    if len(cams) < 2:
        raise ValueError(f"need 2 reference cameras (front, back), got {len(cams)}")
    return cams[0], cams[1]


def _slice_posed(posed: "PosedBody", start: int, stop: int) -> "PosedBody":
    # local: the garmentnerf.model package imports this module and keeps 'import garmentnerf.model.config'
    # light (0.03 s); garmentnerf.body.model brings roma (1.5 s)
    from garmentnerf.body.model import PosedBody

    return PosedBody(posed.vertices[start:stop], posed.joint_transforms[start:stop], posed.translation[start:stop],
                     posed.rest_vertices)


def frame_vertices(posed: "PosedBody", frame: int) -> torch.Tensor:
    """(V, 3) float32 CPU copy of frame ``frame``'s posed vertices, owning its memory.

    Not a view: a row of ``posed.vertices`` would keep the whole clip's (T, V, 3) tensor alive for
    as long as the frame's inputs live (28 MB for the demo's 170 frames, against the frame's 165 kB).
    The trainer keeps frames long after the clip they were built from is gone, and with several
    sequences each frame kept a different posing of its clip: training on four sequences grew by
    about 13 MB per new frame until it was killed (``docs/lab/ledger.md``, "The trainer's memory,
    found and fixed")."""
    return posed.vertices[frame].detach().to("cpu", torch.float32).clone(memory_format=torch.contiguous_format)


class FrameInputBuilder:
    """Runs the GL passes that make :class:`FrameInputs`: info maps and reference-camera G-buffers.

    Args:
        ctx: moderngl context (headless or a window's); every GL object made here belongs to it.
        body: the body model (needs a UV atlas).
        references: the reference cameras, see :func:`resolve_reference_cameras`.
        cfg: the model config (info-map resolution, history k, reference resolution).

    Call :meth:`release` (or use ``with``) to free the GL objects.
    """

    def __init__(self, ctx: "moderngl.Context", body: "BodyModel", references, cfg: "ModelConfig"):
        # local: as in _slice_posed (gl.info_maps brings the body model and roma: 1.6 s)
        from garmentnerf.gl.info_maps import InfoMapRenderer

        self.ctx = ctx
        self.body = body
        self.cfg = cfg
        S = cfg.encoder.reference_resolution
        front, back = resolve_reference_cameras(references)
        self.reference_cameras: tuple[Camera, Camera] = (front.resized(S, S), back.resized(S, S))
        self.info_map_renderer = InfoMapRenderer(ctx, body, cfg.encoder.info_map_resolution, cfg.encoder.history)
        self.camera_pass = CameraPass(ctx)
        self._faces = body.faces.cpu()
        self._uv = body.uv.cpu()
        self._uv_faces = body.uv_faces.cpu()

    # ------------------------------------------------------------------ passes
    def reference_passes(self, posed_vertices: torch.Tensor) -> dict[str, torch.Tensor]:
        """G-buffers of the body at both reference cameras: ``uv (2,S,S,2)``, ``mask``, ``depth``, ``face``."""
        results = [self.camera_pass.render(posed_vertices, self._faces, cam, self._uv, self._uv_faces)
                   for cam in self.reference_cameras]
        return {"uv": torch.stack([r.uv for r in results]), "mask": torch.stack([r.mask for r in results]),
                "depth": torch.stack([r.depth for r in results]), "face": torch.stack([r.face_id for r in results])}

    def _inputs(self, vertices: torch.Tensor, info_maps: torch.Tensor, frame: int | None,
                info_ms: float) -> FrameInputs:
        t0 = time.perf_counter()
        passes = self.reference_passes(vertices)
        ref_ms = (time.perf_counter() - t0) * 1e3
        return FrameInputs(vertices, info_maps, self.reference_cameras, passes["uv"], passes["mask"],
                           passes["depth"], passes["face"], None, frame,
                           {"info_maps": info_ms, "reference_passes": ref_ms})

    def build(self, posed: "PosedBody", frame: int, fps: float) -> FrameInputs:
        """Inputs of frame ``frame`` of a posed clip.

        Only frames ``frame - k .. frame`` are used (the velocity history; further back for smoothed
        velocity maps, :meth:`InfoMapRenderer.frames_back`); the result equals the
        corresponding frame of :meth:`build_clip` (frames before the clip's start count as the
        first frame held still, as in :func:`garmentnerf.body.surface.canonical_velocities`).
        """
        T = posed.vertices.shape[0]
        if not -T <= frame < T:
            raise IndexError(f"frame {frame} outside the clip's {T} frames")
        frame = frame % T
        t0 = time.perf_counter()
        window = _slice_posed(posed, max(0, frame - self.info_map_renderer.frames_back(fps)), frame + 1)
        attributes = self.info_map_renderer.vertex_attributes(window, fps)
        maps = self.info_map_renderer.render_attributes(attributes[-1]).stacked()
        info_ms = (time.perf_counter() - t0) * 1e3
        return self._inputs(frame_vertices(posed, frame), maps, frame, info_ms)

    def build_clip(self, posed: "PosedBody", fps: float, frames: Sequence[int] | None = None) -> list[FrameInputs]:
        """Inputs of every frame of a posed clip (or of ``frames``); per-vertex work done once."""
        T = posed.vertices.shape[0]
        frames = list(range(T)) if frames is None else [f % T for f in frames]
        t0 = time.perf_counter()
        attributes = self.info_map_renderer.vertex_attributes(posed, fps)
        shared_ms = (time.perf_counter() - t0) * 1e3 / max(1, len(frames))
        out = []
        for f in frames:
            t1 = time.perf_counter()
            maps = self.info_map_renderer.render_attributes(attributes[f]).stacked()
            info_ms = shared_ms + (time.perf_counter() - t1) * 1e3
            out.append(self._inputs(frame_vertices(posed, f), maps, f, info_ms))
        return out

    # ------------------------------------------------------------------ lifetime
    def release(self) -> None:
        """Free the GL objects (the context stays)."""
        self.info_map_renderer.release()
        self.camera_pass.release()

    def __enter__(self) -> "FrameInputBuilder":
        return self

    def __exit__(self, *exc) -> None:
        self.release()


__all__ = ["FrameInputs", "FrameFeatures", "FrameInputBuilder", "frame_vertices", "resolve_reference_cameras",
           "REFERENCE_CAMERA_NAMES"]
