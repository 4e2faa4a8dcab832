"""Per-frame inputs of the Garment Animation NeRF, and the features the networks make of them.

A body frame t is everything the model needs that does not depend on the target camera:

:class:`FrameInputs` (made by :class:`garmentnerf.render.frame_inputs.FrameInputBuilder`, which runs
the GL passes)
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

GL stays out of the model: it only ever sees tensors, so it trains and renders in processes (or on
machines) without an OpenGL context, e.g. from cached inputs.

Reference cameras
    Front first, then back (paper: the front and back reference views; the scene rig's
    ``ref_front`` / ``ref_back``, :data:`REFERENCE_CAMERA_NAMES`), at ``cfg.encoder.reference_resolution``
    squared.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import torch

from garmentnerf.conventions import Camera

if TYPE_CHECKING:  # pragma: no cover
    from garmentnerf.body.model import PosedBody
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


def frame_vertices(posed: "PosedBody", frame: int) -> torch.Tensor:
    """(V, 3) float32 CPU copy of frame ``frame``'s posed vertices, owning its memory.

    Not a view: a row of ``posed.vertices`` would keep the whole clip's (T, V, 3) tensor alive for
    as long as the frame's inputs live (28 MB for the demo's 170 frames, against the frame's 165 kB).
    The trainer keeps frames long after the clip they were built from is gone, and with several
    sequences each frame kept a different posing of its clip: training on four sequences grew by
    about 13 MB per new frame until it was killed (``docs/lab/ledger.md``, "The trainer's memory,
    found and fixed")."""
    return posed.vertices[frame].detach().to("cpu", torch.float32).clone(memory_format=torch.contiguous_format)


__all__ = ["FrameInputs", "FrameFeatures", "frame_vertices", "REFERENCE_CAMERA_NAMES"]
