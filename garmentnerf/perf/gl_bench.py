"""Timing of the GL passes (for the CLI's bench command): median ms per call after warm-up."""

from __future__ import annotations

import numpy as np
import torch
import trimesh

from garmentnerf.conventions import orbit_camera
from garmentnerf.gl.camera_pass import CameraPass
from garmentnerf.gl.context import context_info, create_context
from garmentnerf.gl.uv_raster import UVAttributeRasterizer
from garmentnerf.perf.timing import median_ms


def cube_atlas_mesh(subdivisions: int = 48, margin: float = 0.02):
    """A unit cube whose 6 faces are ``subdivisions x subdivisions`` grids, each its own UV chart
    laid out on a 3 x 2 grid of atlas cells (``margin`` of UV space around each chart).

    Returns:
        vertices (V, 3) float32, faces (F, 3) int64, uv (V, 2) float32 (one UV per vertex: charts do
        not share vertices, so F = 12 subdivisions^2).
    """
    n = int(subdivisions)
    s = np.linspace(0.0, 1.0, n + 1)
    a, b = np.meshgrid(s, s, indexing="xy")
    a, b = a.ravel(), b.ravel()
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    quads = np.stack([idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]], -1).reshape(-1, 4)
    grid_faces = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    verts, faces, uvs = [], [], []
    for k in range(6):
        axis, side = k // 2, k % 2
        p = np.zeros((len(a), 3))
        others = [i for i in range(3) if i != axis]
        p[:, others[0]], p[:, others[1]], p[:, axis] = a - 0.5, b - 0.5, side - 0.5
        cell_u, cell_v = k % 3, k // 3
        uv = np.stack([(cell_u + margin + a * (1 - 2 * margin)) / 3.0,
                       (cell_v + margin + b * (1 - 2 * margin)) / 2.0], -1)
        faces.append(grid_faces + len(a) * k)
        verts.append(p)
        uvs.append(uv)
    return (np.concatenate(verts).astype(np.float32), np.concatenate(faces).astype(np.int64),
            np.concatenate(uvs).astype(np.float32))


def benchmark_gl_passes(ctx=None, runs: int = 20, warmup: int = 3, uv_resolution: int = 128,
                        channels: int = 12, image_size: int = 512) -> dict:
    """Median milliseconds (readback to torch included) of:

    - ``uv_raster_ms``: one ``UVAttributeRasterizer.render`` of ``channels`` per-vertex channels
      at ``uv_resolution``^2 on a 27,648-triangle, 6-chart atlas (dilation included), default
      ``method="gather"``; ``uv_raster_draw_ms``: the same with ``method="draw"`` (one MRT draw
      call + readback per frame);
    - ``camera_pass_ms``: one ``CameraPass.render`` (depth, face id, barycentrics, UV) at
      ``image_size``^2 of a 20,480-triangle icosphere filling about half the frame;
    - ``depth_range_ms``: one ``CameraPass.render_depth_range`` (two draws) of the same.

    A headless context is made (and released) when ``ctx`` is None.
    """
    own = ctx is None
    if own:
        ctx = create_context(headless=True)
    try:
        verts, faces, uv = cube_atlas_mesh(48)
        rng = np.random.default_rng(0)
        attributes = torch.from_numpy(rng.standard_normal((len(uv), channels)).astype(np.float32))
        with UVAttributeRasterizer(ctx, uv, faces, uv_resolution) as raster:
            uv_ms = median_ms(lambda: raster.render(attributes), runs, warmup)
        with UVAttributeRasterizer(ctx, uv, faces, uv_resolution, method="draw") as raster:
            uv_draw_ms = median_ms(lambda: raster.render(attributes), runs, warmup)

        sphere = trimesh.creation.icosphere(subdivisions=5, radius=0.6)
        s_verts = torch.from_numpy(np.asarray(sphere.vertices, dtype=np.float32) + np.float32([0, 0, 0.9]))
        s_faces = torch.from_numpy(np.asarray(sphere.faces, dtype=np.int64))
        s_uv = torch.from_numpy(np.asarray(sphere.vertices[:, :2] * 0.5 + 0.5, dtype=np.float32))
        camera = orbit_camera(30.0, 10.0, 2.5, width=image_size, height=image_size)
        with CameraPass(ctx) as cam_pass:
            cam_ms = median_ms(lambda: cam_pass.render(s_verts, s_faces, camera, s_uv, s_faces), runs, warmup)
            range_ms = median_ms(lambda: cam_pass.render_depth_range(s_verts, s_faces, camera), runs, warmup)
        return {
            "uv_raster_ms": uv_ms,
            "uv_raster_draw_ms": uv_draw_ms,
            "uv_raster_faces": int(len(faces)),
            "uv_raster_shape": (uv_resolution, uv_resolution, channels),
            "camera_pass_ms": cam_ms,
            "depth_range_ms": range_ms,
            "camera_pass_faces": int(len(s_faces)),
            "camera_pass_shape": (image_size, image_size),
            "renderer": context_info(ctx)["GL_RENDERER"],
        }
    finally:
        if own:
            ctx.release()


if __name__ == "__main__":
    for key, value in benchmark_gl_passes().items():
        print(f"{key}: {value}")
