"""Benchmarks of the foundation stages on the real body: info maps, camera pass, projection.

Figures are medians over repeated runs after warm-up, on whatever machine runs them; the JSON
records the machine (CPU count, GL renderer) so figures are never quoted without it.
"""

from __future__ import annotations

import os
import platform

import torch

from garmentnerf.body.model import BodyModel
from garmentnerf.body.surface import vertex_normals
from garmentnerf.conventions import orbit_camera
from garmentnerf.geometry.body_points import BodyPointProjector
from garmentnerf.gl.body_layer_pass import BodyLayerPass
from garmentnerf.gl.camera_pass import CameraPass
from garmentnerf.gl.context import context_info, create_context
from garmentnerf.gl.info_maps import InfoMapRenderer
from garmentnerf.model.body_appearance import BodyAppearance
from garmentnerf.motion.library import load_motion
from garmentnerf.perf.projection_bench import near_surface_points
from garmentnerf.perf.timing import median_ms
from garmentnerf.render.body_layer import render_body_layer


def foundation_benchmark(runs: int = 20, clip_frames: int = 30, projection_points: int = 262144) -> dict:
    """Time the per-frame foundation stages on the bundled body posed by the ``walk`` clip.

    Returns a dict of figures (milliseconds unless named otherwise) and the machine description.
    """
    body = BodyModel.default()
    motion = load_motion("walk", body)
    clip = motion.slice(0, min(clip_frames, motion.num_frames))
    posed = clip.pose(body)
    T = posed.vertices.shape[0]
    ctx = create_context()
    results: dict = {"machine": {"platform": platform.platform(), "cpus": os.cpu_count(),
                                 "torch_threads": torch.get_num_threads(), **context_info(ctx)}}

    maps = InfoMapRenderer(ctx, body, resolution=128, history=2)
    attrs = maps.vertex_attributes(posed, motion.fps)
    results["pose_clip_ms_per_frame"] = median_ms(lambda: clip.pose(body), max(3, runs // 4)) / T
    results["info_vertex_attributes_ms_per_frame"] = median_ms(lambda: maps.vertex_attributes(posed, motion.fps), max(3, runs // 4)) / T
    frame = [0]

    def raster_one():
        maps.render_attributes(attrs[frame[0] % T])
        frame[0] += 1

    results["info_maps_raster_ms_per_frame"] = median_ms(raster_one, runs)
    results["info_maps_total_ms_per_frame"] = results["info_vertex_attributes_ms_per_frame"] + results["info_maps_raster_ms_per_frame"]
    maps.release()

    camera = orbit_camera(30.0, 10.0, 3.0, width=512, height=512)
    verts = posed.vertices[T // 2]
    with CameraPass(ctx) as cam_pass:
        results["camera_pass_512_ms"] = median_ms(lambda: cam_pass.render(verts, body.faces, camera, body.uv, body.uv_faces), runs)
        results["depth_range_512_ms"] = median_ms(lambda: cam_pass.render_depth_range(verts, body.faces, camera), runs)
        # the raster_body composition's body layer, 2 x 2 supersampled: GL-shaded against the plain
        # reference (camera pass + torch), side by side on a random appearance
        appearance = BodyAppearance()
        normals = vertex_normals(verts, body.faces)
        with torch.no_grad(), BodyLayerPass(ctx) as layer_pass:
            results["body_layer_gl_512_ms"] = median_ms(lambda: layer_pass.render(
                verts, normals, body.faces, body.uv, body.uv_faces, camera, appearance), runs)
            results["body_layer_reference_512_ms"] = median_ms(lambda: render_body_layer(
                cam_pass, body, verts, camera, appearance, normals=normals), runs)

    projector = BodyPointProjector(body)  # closest point, signed h, b_o and uv
    normals = vertex_normals(verts, body.faces)
    points = near_surface_points(verts, normals, projection_points, spread=0.15)
    # The frame is bound once (per frame in training and in the previewer), then queried.
    bind_ms = median_ms(lambda: projector.bind(verts), max(3, runs // 4), warmup=1)
    bound = projector.bind(verts)
    proj_ms = median_ms(lambda: bound.project(points), max(3, runs // 4), warmup=1)
    results["projection_points"] = projection_points
    results["projection_bind_ms"] = bind_ms
    results["projection_ms"] = proj_ms
    results["projection_us_per_point"] = proj_ms * 1e3 / projection_points
    results["projection_points_per_s"] = projection_points / (proj_ms / 1e3)
    ctx.release()
    return results
