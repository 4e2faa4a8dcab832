"""The body layer of the hybrid composition: the posed body rasterised by the camera pass and
shaded with its learned :class:`~garmentnerf.model.body_appearance.BodyAppearance`.

:func:`body_surface` gives, per pixel of a camera, whether the body is seen and the atlas UV and
smooth world normal of the visible point (vertex normals interpolated with the pass's
perspective-correct barycentrics, as the ground truth's renderer shades them);
:func:`render_body_layer` turns it into the layer :func:`~garmentnerf.model.palette.compose`
takes: the untinted colour premultiplied by coverage, and the coverage, both box-filtered from
``supersample`` x ``supersample`` subsamples (the ground truth's anti-aliasing).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from garmentnerf.body.surface import vertex_normals
from garmentnerf.conventions import Camera
from garmentnerf.geometry.triangles import interpolate

#: Subsamples per pixel side of the body layer (the ground truth's renderer uses 2).
BODY_LAYER_SUPERSAMPLE = 2


@dataclass
class BodySurfacePixels:
    """What a camera sees of the body, per pixel.

    Attributes:
        mask: (H, W) bool, the body is seen.
        uv: (N, 2) atlas UV of the N seen pixels (row-major order of ``mask``).
        normals: (N, 3) unit world normals there.
    """

    mask: torch.Tensor
    uv: torch.Tensor
    normals: torch.Tensor


def body_surface(camera_pass, vertices: torch.Tensor, faces: torch.Tensor, uv: torch.Tensor,
                 uv_faces: torch.Tensor, camera: Camera, normals: torch.Tensor | None = None) -> BodySurfacePixels:
    """Rasterise the posed body (``vertices`` (V, 3), ``faces`` (F, 3), atlas ``uv`` (Nuv, 2) and
    ``uv_faces`` (F, 3)) seen by ``camera``; ``normals`` (V, 3) default to the area-weighted
    vertex normals."""
    vertices = torch.as_tensor(vertices, dtype=torch.float32).cpu()
    faces = torch.as_tensor(faces, dtype=torch.long).cpu()
    normals = vertex_normals(vertices, faces) if normals is None else normals.to("cpu", torch.float32)
    g = camera_pass.render(vertices, faces, camera, uv, uv_faces)
    n = interpolate(normals, faces, g.face_id[g.mask], g.bary[g.mask])
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return BodySurfacePixels(g.mask, g.uv[g.mask], n)


def render_body_layer(camera_pass, body, vertices: torch.Tensor, camera: Camera, appearance,
                      supersample: int = BODY_LAYER_SUPERSAMPLE, normals: torch.Tensor | None = None
                      ) -> tuple[torch.Tensor, torch.Tensor]:
    """The body layer of ``camera`` at its size.

    Args:
        camera_pass: a :class:`~garmentnerf.gl.camera_pass.CameraPass`.
        body: the :class:`~garmentnerf.body.model.BodyModel` (faces and atlas).
        vertices: (V, 3) the posed body.
        appearance: the :class:`~garmentnerf.model.body_appearance.BodyAppearance`.
        supersample: subsamples per pixel side.
        normals: (V, 3) the posed body's vertex normals when already known (a frame's
            :class:`~garmentnerf.model.frame_context.FrameFeatures` has them); None computes them.
    Returns:
        ``color`` (1, 3, H, W) ``a(uv, n)`` premultiplied by coverage (untinted: compose multiplies
        it by the body's palette colour) and ``coverage`` (1, 1, H, W) in [0, 1].
    """
    s = max(1, int(supersample))
    fine = camera if s == 1 else camera.resized(camera.width * s, camera.height * s)
    pixels = body_surface(camera_pass, vertices, body.faces, body.uv, body.uv_faces, fine, normals)
    H, W = pixels.mask.shape
    color = torch.zeros(3, H * W, dtype=torch.float32)
    flat = pixels.mask.reshape(-1)
    color[:, flat] = appearance(pixels.uv, pixels.normals).T.to(torch.float32)
    color = color.view(1, 3, H, W)
    coverage = pixels.mask.to(torch.float32).view(1, 1, H, W)
    if s > 1:
        color = F.avg_pool2d(color, s)
        coverage = F.avg_pool2d(coverage, s)
    return color, coverage


def frame_body_layer(body_pass, body, features, camera: Camera, appearance) -> tuple[torch.Tensor, torch.Tensor]:
    """The body layer of a frame (its :class:`~garmentnerf.model.frame_context.FrameFeatures`: the
    posed body and its vertex normals) seen by ``camera``, drawn by ``body_pass`` (a
    :class:`~garmentnerf.gl.body_layer_pass.BodyLayerPass`, the GL side of :func:`render_body_layer`)
    at :data:`BODY_LAYER_SUPERSAMPLE`: what the render session and the trainer both compose with."""
    return body_pass.render(features.posed_vertices, features.vertex_normals, body.faces, body.uv, body.uv_faces,
                            camera, appearance, BODY_LAYER_SUPERSAMPLE)


__all__ = ["BodySurfacePixels", "body_surface", "render_body_layer", "frame_body_layer", "BODY_LAYER_SUPERSAMPLE"]
