"""The GL passes that make a body frame's :class:`~garmentnerf.model.frame_context.FrameInputs`.

:class:`FrameInputBuilder` runs, per frame, the info-map raster (:mod:`garmentnerf.gl.info_maps`: the
posed body's normals and velocities baked into UV maps) and the camera pass of each reference
camera (:mod:`garmentnerf.gl.camera_pass`: per-pixel UV, mask, depth and face), and hands the model
their tensors.

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
from typing import TYPE_CHECKING

import torch

from garmentnerf.body.model import PosedBody
from garmentnerf.conventions import Camera
from garmentnerf.gl.camera_pass import CameraPass
from garmentnerf.gl.info_maps import InfoMapRenderer
from garmentnerf.model.frame_context import REFERENCE_CAMERA_NAMES, FrameInputs, frame_vertices

if TYPE_CHECKING:  # pragma: no cover
    import moderngl

    from garmentnerf.body.model import BodyModel
    from garmentnerf.model.config import ModelConfig


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
    return PosedBody(posed.vertices[start:stop], posed.joint_transforms[start:stop], posed.translation[start:stop],
                     posed.rest_vertices)


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

        Only frames ``frame - k .. frame`` are used (the velocity history,
        :meth:`InfoMapRenderer.frames_back`); the result equals the
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


__all__ = ["FrameInputBuilder", "resolve_reference_cameras"]
