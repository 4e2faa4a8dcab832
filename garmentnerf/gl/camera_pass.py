"""Camera-view G-buffer pass: per pixel depth, face id, barycentrics and UV of the visible surface.

Serves visibility from reference cameras, per-ray depth bounds and neural-texture renders. Pixels
follow :mod:`garmentnerf.conventions`: pixel (row r, column c) is the ray through continuous pixel
coordinates (c, r); arrays are ``(H, W, ...)`` with row 0 at the top, read back with no flip.

Implementation: the mesh is expanded to non-indexed triangles (vertex 3 f + k is corner k of face
f), so the vertex shader derives the corner's barycentric one-hot from ``gl_VertexID`` and the
fragment shader writes ``gl_PrimitiveID`` (= f). One RGBA32F target holds (b1, b2, camera-space z,
f + 1) -- the face index is exact as a float32 below 2^24 faces -- and an RG32F target the UV when
there is one; a 24-bit depth buffer picks the closest surface (or the farthest, for
:meth:`CameraPass.render_depth_range`); no face culling. Packing into one target (rather than
float + integer targets) makes the pass about a third faster on Mesa llvmpipe.
"""

from __future__ import annotations

from dataclasses import dataclass

import moderngl
import numpy as np
import torch

from garmentnerf.conventions import Camera
from garmentnerf.gl.context import current
from garmentnerf.gl.mesh_arrays import as_numpy, check_mesh_arrays
from garmentnerf.gl.resources import GLObjectsOwner, TargetCache
from garmentnerf.gl.shaders import build_program


@dataclass
class CameraPassResult:
    """Per-pixel results of :meth:`CameraPass.render`, all CPU tensors.

    Attributes:
        depth: (H, W) float32 camera-space z (OpenCV, metres) of the closest surface; +inf where
            background.
        face_id: (H, W) int64 index into ``faces``; -1 where background.
        bary: (H, W, 3) float32 perspective-correct barycentrics of the face's corners in the
            order of ``faces[face_id]``; 0 where background.
        uv: (H, W, 2) float32 interpolated texture coordinates (0 without UVs or in background).
        mask: (H, W) bool, True where a surface is seen.
        depth_far: (H, W) float32 z of the farthest surface along the pixel's ray (+inf where
            background), only with ``depth_range=True``; else None.
        face_id_far: (H, W) int64 face of that farthest surface (-1 where background), or None.
    """

    depth: torch.Tensor
    face_id: torch.Tensor
    bary: torch.Tensor
    uv: torch.Tensor
    mask: torch.Tensor
    depth_far: torch.Tensor | None = None
    face_id_far: torch.Tensor | None = None


@dataclass
class DepthRange:
    """Nearest and farthest surface z (camera-space, metres) per pixel; +inf where ``mask`` is False."""

    near: torch.Tensor
    far: torch.Tensor
    mask: torch.Tensor


#: Face indices travel as float32 values, exact below 2^24.
MAX_FACES = 2**24 - 1


class _Targets:
    """Framebuffers for one image size: without and with the UV target (same depth buffer)."""

    def __init__(self, ctx: moderngl.Context, width: int, height: int) -> None:
        size = (width, height)
        self.main = ctx.texture(size, 4, dtype="f4")
        self.uv = ctx.texture(size, 2, dtype="f4")
        self.depth = ctx.depth_renderbuffer(size)
        self.fbos = {False: ctx.framebuffer(color_attachments=[self.main], depth_attachment=self.depth),
                     True: ctx.framebuffer(color_attachments=[self.main, self.uv], depth_attachment=self.depth)}
        self.scopes = {key: ctx.scope(fbo, enable_only=moderngl.DEPTH_TEST) for key, fbo in self.fbos.items()}

    def release(self) -> None:
        for obj in (*self.scopes.values(), *self.fbos.values(), self.main, self.uv, self.depth):
            obj.release()


class _Program:
    """The pass's program (with or without UV) and its growing vertex buffer(s)."""

    def __init__(self, ctx: moderngl.Context, has_uv: bool) -> None:
        self.ctx = ctx
        self.has_uv = has_uv
        self.program = build_program(ctx, "camera_pass.vert", "camera_pass.frag", {"HAS_UV": int(has_uv)})
        self.buffers: list[moderngl.Buffer] = []
        self.vao: moderngl.VertexArray | None = None
        self.count = 0

    def upload(self, arrays: list[np.ndarray]) -> None:
        if not self.buffers or any(buf.size < arr.nbytes for buf, arr in zip(self.buffers, arrays)):
            self._release_buffers()
            self.buffers = [self.ctx.buffer(reserve=max(2 * arr.nbytes, 64), dynamic=True) for arr in arrays]
            content = [(self.buffers[0], "3f", "in_position")]
            if self.has_uv:
                content.append((self.buffers[1], "2f", "in_uv"))
            self.vao = self.ctx.vertex_array(self.program, content)
        for buf, arr in zip(self.buffers, arrays):
            buf.write(arr)

    def set_camera(self, camera: Camera) -> None:
        self.program["u_view"].write(camera.world_to_camera().T.astype(np.float32).tobytes())
        self.program["u_proj"].write(camera.gl_projection().T.astype(np.float32).tobytes())

    def _release_buffers(self) -> None:
        if self.vao is not None:
            self.vao.release()
            self.vao = None
        for buf in self.buffers:
            buf.release()
        self.buffers = []

    def release(self) -> None:
        self._release_buffers()
        self.program.release()


class CameraPass(GLObjectsOwner):
    """Renders camera-view G-buffers of triangle meshes on one moderngl context.

    Objects made here belong to ``ctx``, which every method makes current first (and leaves
    current; see :func:`~garmentnerf.gl.context.make_current`), so passes on different contexts can
    be used in any order. Call :meth:`release` (or use ``with``) to free them; releasing the
    context frees them too. Framebuffers are kept for the ``max_sizes`` most recently used sizes.
    """

    def __init__(self, ctx: moderngl.Context, max_sizes: int = 4) -> None:
        self.ctx = ctx
        self.max_sizes = max(1, int(max_sizes))
        with current(ctx):
            self._programs = {False: _Program(ctx, False), True: _Program(ctx, True)}
        self._targets: TargetCache[_Targets] = TargetCache(lambda size: _Targets(ctx, *size), self.max_sizes)
        self._released = False

    def _targets_for(self, width: int, height: int) -> _Targets:
        return self._targets.get((width, height))

    def _prepare(self, vertices, faces, camera: Camera, uv=None, uv_faces=None) -> _Program:
        """Check the inputs, upload the expanded corners and the camera; the program to draw with."""
        self._check_not_released()
        if not isinstance(camera, Camera):
            raise TypeError(f"camera must be a conventions.Camera, got {type(camera).__name__}")
        if (uv is None) != (uv_faces is None):
            raise ValueError("give both uv and uv_faces, or neither")
        verts, tris = check_mesh_arrays(vertices, faces)
        if len(tris) > MAX_FACES:
            raise ValueError(f"at most {MAX_FACES} faces, got {len(tris)}")
        arrays = [verts[tris.reshape(-1)]]
        if uv is not None:
            uv_np = as_numpy(uv, np.float32)
            uv_tris = as_numpy(uv_faces, np.int64)
            if uv_np.ndim != 2 or uv_np.shape[1] != 2:
                raise ValueError(f"uv must be (Nuv, 2), got shape {uv_np.shape}")
            if uv_tris.shape != tris.shape:
                raise ValueError(f"uv_faces must have the shape of faces {tris.shape}, got {uv_tris.shape}")
            if uv_tris.size and (uv_tris.min() < 0 or uv_tris.max() >= len(uv_np)):
                raise ValueError(f"uv_faces index out of range [0, {len(uv_np)})")
            arrays.append(uv_np[uv_tris.reshape(-1)])
        program = self._programs[uv is not None]
        program.upload(arrays)
        program.set_camera(camera)
        program.count = 3 * len(tris)
        return program

    def _draw(self, program: _Program, targets: _Targets, farthest: bool) -> None:
        """Clear and draw with the depth test keeping the closest (or farthest) surface."""
        fbo = targets.fbos[program.has_uv]
        with targets.scopes[program.has_uv]:
            try:
                self.ctx.depth_func = ">" if farthest else "<"
                fbo.depth_mask = True
                fbo.clear(0.0, 0.0, 0.0, 0.0, depth=0.0 if farthest else 1.0)
                if program.count:
                    program.vao.render(moderngl.TRIANGLES, vertices=program.count)
            finally:
                self.ctx.depth_func = "<"  # GL's default; moderngl cannot read the old value

    @staticmethod
    def _read(targets: _Targets, attachment: int, components: int) -> np.ndarray:
        width, height = targets.main.size
        out = np.empty((height, width, components), dtype=np.float32)
        targets.fbos[attachment == 1].read_into(out, attachment=attachment, components=components, dtype="f4")
        return out

    @staticmethod
    def _unpack(main: np.ndarray) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """(H, W, 4) target 0 -> depth (+inf background), face id (-1), bary (0), mask."""
        main_t = torch.from_numpy(main)
        face_id = main_t[..., 3].to(torch.int64) - 1
        mask = face_id >= 0
        depth = main_t[..., 2].masked_fill(~mask, float("inf"))
        bary = torch.empty(main_t.shape[:2] + (3,), dtype=torch.float32)
        bary[..., 1:] = main_t[..., :2]
        torch.sub(1.0, main_t[..., 0] + main_t[..., 1], out=bary[..., 0])
        bary[..., 0].masked_fill_(~mask, 0.0)
        return depth, face_id, bary, mask

    def render(self, vertices, faces, camera: Camera, uv=None, uv_faces=None,
               depth_range: bool = False) -> CameraPassResult:
        """Rasterise the mesh seen by ``camera`` at ``camera.width x camera.height``.

        Args:
            vertices: (V, 3) world positions (torch or numpy; converted to float32).
            faces: (F, 3) vertex indices.
            camera: the view; its ``near``/``far`` clip the geometry.
            uv, uv_faces: optional (Nuv, 2) texture coordinates and (F, 3) indices into them.
            depth_range: also render the farthest surface per pixel (``depth_far``, ``face_id_far``).
        """
        with current(self.ctx):
            program = self._prepare(vertices, faces, camera, uv, uv_faces)
            targets = self._targets_for(camera.width, camera.height)
            self._draw(program, targets, farthest=False)
            main = self._read(targets, 0, 4)
            uv_raw = self._read(targets, 1, 2) if program.has_uv else None
            if depth_range:
                self._draw(program, targets, farthest=True)
                main_far = self._read(targets, 0, 4)

        depth, face_id, bary, mask = self._unpack(main)
        if uv_raw is not None:
            uv_img = torch.from_numpy(uv_raw)
        else:
            uv_img = torch.zeros((camera.height, camera.width, 2), dtype=torch.float32)
        result = CameraPassResult(depth=depth, face_id=face_id, bary=bary, uv=uv_img, mask=mask)
        if depth_range:
            result.depth_far, result.face_id_far, _, _ = self._unpack(main_far)
        return result

    def render_depth_range(self, vertices, faces, camera: Camera) -> DepthRange:
        """Nearest and farthest surface z per pixel (front and back faces alike), e.g. for per-ray
        sampling bounds: along a unit ray of direction d, t = z / (d . optical axis)."""
        with current(self.ctx):
            program = self._prepare(vertices, faces, camera)
            targets = self._targets_for(camera.width, camera.height)
            self._draw(program, targets, farthest=False)
            main_near = self._read(targets, 0, 4)
            self._draw(program, targets, farthest=True)
            main_far = self._read(targets, 0, 4)
        near, _, _, mask = self._unpack(main_near)
        far, _, _, _ = self._unpack(main_far)
        return DepthRange(near=near, far=far, mask=mask)

    def _release_objects(self) -> None:
        self._targets.release()
        for program in self._programs.values():
            program.release()
