"""The distance range of a closed shell along every pixel-centre ray, in one GL draw.

:class:`ShellRaster` draws a closed surface (``shaders/shell_bounds.*``) with no depth test and MIN
blending into an RGBA32F target: per pixel-centre ray, the distance of the nearest *entering*
face (the face plane faces the camera: near), minus the farthest distance of any face (far).
A ray that crosses no face is not ``hit``. The raster's near/far planes are fitted to the shell
(not the camera's), so cameras 1 km away still see it. :func:`inflate_surface` makes the shell
the shell sampler draws (:mod:`garmentnerf.render.shell_sampler`): the skin pushed out along its
vertex normals.
"""

from __future__ import annotations

from dataclasses import dataclass

import moderngl
import numpy as np
import torch

from garmentnerf.body.surface import vertex_normals
from garmentnerf.conventions import Camera, gl_projection_from_intrinsics
from garmentnerf.gl.context import create_context, current, is_released
from garmentnerf.gl.shaders import build_program

_BIG = 1.0e37


def inflate_surface(vertices: torch.Tensor, faces: torch.Tensor, margin: float | torch.Tensor) -> torch.Tensor:
    """(V, 3) float32 vertices pushed out along their unit (area-weighted) normals by ``margin``
    (metres: a scalar, or (V,) per vertex)."""
    v = vertices.detach().to("cpu", torch.float32)
    m = torch.as_tensor(margin, dtype=torch.float32).reshape(-1, 1) if torch.is_tensor(margin) else float(margin)
    return v + m * vertex_normals(v, faces.detach().cpu().long())


@dataclass
class ShellBounds:
    """Per-pixel ray distances of a shell raster (H, W): near, far (0 where not ``hit``)."""

    near: torch.Tensor
    far: torch.Tensor
    hit: torch.Tensor


class ShellRaster:
    """Rasterises the distance range of a closed shell along every pixel-centre ray (one draw).

    Args:
        ctx: a moderngl context; None makes (and owns) a headless one on first use.
    """

    def __init__(self, ctx=None):
        self._ctx = ctx
        self._own = ctx is None
        self._program = None
        self._buffers: list = []
        self._vao = None
        self._capacity = 0
        self._targets: dict = {}

    @property
    def ctx(self):
        if self._ctx is None:
            self._ctx = create_context(headless=True)
        return self._ctx

    def _setup(self):
        if self._program is None:
            self._program = build_program(self.ctx, "shell_bounds.vert", "shell_bounds.frag")

    def _upload(self, corners: np.ndarray) -> None:
        if self._vao is None or corners.nbytes > self._capacity:
            self._release_buffers()
            self._capacity = max(2 * corners.nbytes, 64)
            self._buffers = [self.ctx.buffer(reserve=self._capacity, dynamic=True)]
            self._vao = self.ctx.vertex_array(self._program, [(self._buffers[0], "3f", "in_position")])
        self._buffers[0].write(corners)

    def _target(self, width: int, height: int):
        key = (width, height)
        if key not in self._targets:
            while len(self._targets) >= 4:
                tex, fbo = self._targets.pop(next(iter(self._targets)))
                fbo.release()
                tex.release()
            tex = self.ctx.texture(key, 2, dtype="f4")
            self._targets[key] = (tex, self.ctx.framebuffer(color_attachments=[tex]))
        return self._targets[key]

    def render(self, vertices: torch.Tensor, faces: torch.Tensor, camera: Camera,
               origin_inside: bool = False) -> ShellBounds:
        """Near/far ray distances of the closed shell ``(vertices, faces)`` seen by ``camera``:
        the nearest and farthest crossing of any face per pixel-centre ray; ``origin_inside``
        (the camera centre lies inside the shell): every ray starts at 0 and every ray hits."""
        verts = vertices.detach().to("cpu", torch.float32).numpy()
        tris = faces.detach().cpu().numpy().astype(np.int64)
        W, H = camera.width, camera.height
        centre = np.asarray(camera.center, dtype=np.float64)
        # Fit the clip planes to the shell: cameras inside it, very near or very far all see it.
        reach = float(np.sqrt(((verts.astype(np.float64) - centre) ** 2).sum(-1).max())) if len(verts) else 1.0
        far = max(reach * 1.01 + 1e-3, 1e-2)
        near = max(far * 1e-6, 1e-6)
        with current(self.ctx):
            self._setup()
            corners = np.ascontiguousarray(verts[tris.reshape(-1)], dtype=np.float32)
            tex, fbo = self._target(W, H)
            prog = self._program
            prog["u_view"].write(camera.world_to_camera().T.astype(np.float32).tobytes())
            prog["u_proj"].write(gl_projection_from_intrinsics(camera.K, W, H, near, far).T.astype(np.float32).tobytes())
            out = np.empty((H, W, 2), dtype=np.float32)
            with self.ctx.scope(fbo, enable_only=moderngl.BLEND):
                try:
                    self.ctx.blend_equation = moderngl.MIN
                    fbo.clear(_BIG, _BIG, 0.0, 0.0)
                    if len(tris):
                        self._upload(corners)
                        self._vao.render(moderngl.TRIANGLES, vertices=3 * len(tris))
                    fbo.read_into(out, components=2, dtype="f4")
                finally:
                    self.ctx.blend_equation = moderngl.FUNC_ADD
        raw = torch.from_numpy(out)
        hit = (raw[..., 0] < _BIG * 0.5) & (raw[..., 1] < _BIG * 0.5)
        near_t = torch.where(hit, raw[..., 0], torch.zeros_like(raw[..., 0]))
        far_t = torch.where(hit, -raw[..., 1], torch.zeros_like(raw[..., 1]))
        if origin_inside:
            hit = torch.ones_like(hit)
            near_t = torch.zeros_like(near_t)
            far_t = torch.where(far_t > 0, far_t, torch.full_like(far_t, far))
        return ShellBounds(near_t, far_t, hit)

    def _release_buffers(self) -> None:
        if self._vao is not None:
            self._vao.release()
            self._vao = None
        for b in self._buffers:
            b.release()
        self._buffers = []

    def release(self) -> None:
        if self._ctx is None or is_released(self._ctx):
            return

        with current(self._ctx):
            self._release_buffers()
            for tex, fbo in self._targets.values():
                fbo.release()
                tex.release()
            self._targets.clear()
            if self._program is not None:
                self._program.release()
                self._program = None
        if self._own:
            self._ctx.release()
            self._ctx = None


__all__ = ["ShellRaster", "ShellBounds", "inflate_surface"]
