"""The body layer of the hybrid composition, drawn and shaded by GL in two passes.

:func:`garmentnerf.render.body_layer.render_body_layer` is the plain reference: it rasterises the
body's G-buffer with the camera pass, reads it back, interpolates the normals and evaluates the
:class:`~garmentnerf.model.body_appearance.BodyAppearance` in torch, then box-filters the
subsamples. :class:`BodyLayerPass` computes the same layer on the GL side:

1. ``shaders/body_layer.{vert,frag}`` draw the posed body at ``supersample`` times the camera's size
   (the camera pass's non-indexed triangles, projection and depth test, so the same subsamples are
   covered) and shade each subsample with the appearance: the albedo texture read at the
   interpolated UV, times the shading polynomial of the normalised interpolated normal; an RGBA32F
   target cleared to 0 holds ``(a, 1)`` where the body is.
2. ``shaders/box_resolve.frag`` averages each ``supersample x supersample`` block: ``a`` premultiplied
   by coverage, and the coverage. Only this image is read back.

What it saves: the G-buffer's read-back at the supersampled size, its unpacking, the normal
interpolation, the appearance and the pooling on the CPU (measured by ``garmentnerf bench``'s
``body_layer`` row). ``tests/render/test_body_layer.py`` holds the two to each other.
"""

from __future__ import annotations

import moderngl
import numpy as np
import torch

from garmentnerf.conventions import Camera
from garmentnerf.gl.context import current
from garmentnerf.gl.mesh_arrays import as_numpy, check_mesh_arrays
from garmentnerf.gl.resources import GLObjectsOwner, SupersampleTargets, TargetCache
from garmentnerf.gl.shaders import build_program
from garmentnerf.body.shading import monomial_exponents


def shading_sum_glsl(degree: int) -> str:
    """GLSL of ``S(n)``, the sum ``u_shading[k] * monomial_k(n)`` over
    :func:`~garmentnerf.body.shading.monomial_exponents`, written out term by term (a
    macro body for ``shaders/body_layer.frag``)."""
    terms = []
    for k, exponents in enumerate(monomial_exponents(degree)):
        factors = [f"n.{axis}" for axis, e in zip("xyz", exponents) for _ in range(e)]
        terms.append(f"u_shading[{k}]" + "".join(f" * {f}" for f in factors))
    return "(" + " + ".join(terms) + ")"


class BodyLayerPass(GLObjectsOwner):
    """Renders :func:`~garmentnerf.render.body_layer.render_body_layer`'s layer on one moderngl
    context (see the module docstring). Call :meth:`release` (or use ``with``) to free it.

    Args:
        ctx: the moderngl context (made current by every method, and left current).
        max_sizes: output sizes whose targets are kept.
    """

    def __init__(self, ctx: moderngl.Context, max_sizes: int = 4) -> None:
        self.ctx = ctx
        with current(ctx):
            self.resolve = build_program(ctx, "fullscreen_triangle.vert", "box_resolve.frag")
            self.resolve_vao = ctx.vertex_array(self.resolve, [])
        self.resolve["u_source"].value = 0
        self._programs: dict[int, moderngl.Program] = {}  # by shading degree
        self.program: moderngl.Program | None = None  # the program of the last render
        self._vao: moderngl.VertexArray | None = None
        self._position_buffer: moderngl.Buffer | None = None  # per corner, rewritten for each frame
        self._normal_buffer: moderngl.Buffer | None = None
        self._uv_buffer: moderngl.Buffer | None = None        # per corner, written once per topology
        self._topology: tuple | None = None  # the (faces, uv, uv_faces) objects the buffers were made for
        self._corner_index: np.ndarray | None = None  # (3F,) the vertex of each corner
        self._max_vertex = -1
        self._positions: np.ndarray | None = None  # (3F, 3) float32 gathered per corner (kept, refilled)
        self._normals: np.ndarray | None = None
        self._albedo: moderngl.Texture | None = None
        self._targets: TargetCache[SupersampleTargets] = TargetCache(lambda key: SupersampleTargets(ctx, *key),
                                                                   max(1, int(max_sizes)))
        self._last: SupersampleTargets | None = None  # the targets of the last draw
        self._mesh_inputs: tuple | None = None  # the objects the vertex buffer was made from
        self._mesh_count = 0
        self._released = False

    def _use_program(self, degree: int) -> None:
        """Make the program of ``degree`` current (built on first use; the vertex array follows it)."""
        program = self._programs.get(degree)
        if program is None:
            defines = {"SHADING_TERMS": len(monomial_exponents(degree)), "SHADING_SUM(n)": shading_sum_glsl(degree)}
            program = build_program(self.ctx, "body_layer.vert", "body_layer.frag", defines)
            program["u_albedo"].value = 0
            self._programs[degree] = program
        if program is not self.program:
            self.program = program
            if self._vao is not None:
                self._vao.release()
                self._vao = None

    def _upload_mesh(self, vertices, normals, faces, uv, uv_faces) -> int:
        """Position, normal and UV per corner (three vertex buffers); returns the vertex count. The
        same five objects as the last upload (a frame seen from another camera) upload nothing; the
        same ``faces``, ``uv`` and ``uv_faces`` (another frame of the body: a playing clip) upload
        only the positions and normals, gathered per corner into arrays kept for it. The arrays
        are read as they are at the call, not copied, so a caller must not change them in place."""
        inputs = (vertices, normals, faces, uv, uv_faces)
        if self._vao is not None and self._mesh_inputs is not None and \
                all(a is b for a, b in zip(inputs, self._mesh_inputs)):
            return self._mesh_count
        verts = as_numpy(vertices, np.float32)
        topology = (faces, uv, uv_faces)
        if self._topology is None or not all(a is b for a, b in zip(topology, self._topology)):
            self._set_topology(verts, topology)
        elif verts.ndim != 2 or verts.shape[1] != 3 or len(verts) <= self._max_vertex:
            check_mesh_arrays(verts, faces)  # raises, naming the problem
        normals = as_numpy(normals, np.float32)
        if normals.shape != verts.shape:
            raise ValueError(f"normals must have the shape of vertices {verts.shape}, got {normals.shape}")
        np.take(verts, self._corner_index, axis=0, out=self._positions)
        np.take(normals, self._corner_index, axis=0, out=self._normals)
        if self._vao is None:
            self._vao = self.ctx.vertex_array(self.program, [(self._position_buffer, "3f", "in_position"),
                                                             (self._normal_buffer, "3f", "in_normal"),
                                                             (self._uv_buffer, "2f", "in_uv")])
        self._position_buffer.write(self._positions)
        self._normal_buffer.write(self._normals)
        self._mesh_inputs, self._mesh_count = inputs, len(self._corner_index)
        return self._mesh_count

    def _set_topology(self, verts: np.ndarray, topology: tuple) -> None:
        """Check a new mesh topology (``faces``, ``uv``, ``uv_faces``) and make its buffers: the
        corners' vertex index and their UVs (uploaded once), and the position and normal buffers
        the frames fill."""
        faces, uv, uv_faces = topology
        verts, tris = check_mesh_arrays(verts, faces)
        uv = as_numpy(uv, np.float32)
        uv_tris = as_numpy(uv_faces, np.int64)
        if uv.ndim != 2 or uv.shape[1] != 2 or uv_tris.shape != tris.shape:
            raise ValueError(f"uv must be (Nuv, 2) and uv_faces {tris.shape}, got {uv.shape} and {uv_tris.shape}")
        if uv_tris.size and (uv_tris.min() < 0 or uv_tris.max() >= len(uv)):
            raise ValueError(f"uv_faces index out of range [0, {len(uv)})")
        self._release_mesh()
        self._corner_index = np.ascontiguousarray(tris.reshape(-1))
        self._max_vertex = int(tris.max()) if tris.size else -1
        n = len(self._corner_index)
        self._positions = np.empty((n, 3), np.float32)
        self._normals = np.empty((n, 3), np.float32)
        self._uv_buffer = self.ctx.buffer(np.ascontiguousarray(uv[uv_tris.reshape(-1)]).tobytes() or b"\0" * 8)
        self._position_buffer = self.ctx.buffer(reserve=max(self._positions.nbytes, 12), dynamic=True)
        self._normal_buffer = self.ctx.buffer(reserve=max(self._normals.nbytes, 12), dynamic=True)
        self._topology = topology

    def _release_mesh(self) -> None:
        """Free the mesh's buffers and the vertex array reading them (a new topology, or the end)."""
        for obj in (self._vao, self._position_buffer, self._normal_buffer, self._uv_buffer):
            if obj is not None:
                obj.release()
        self._vao = self._position_buffer = self._normal_buffer = self._uv_buffer = None
        self._topology = self._mesh_inputs = None

    def _upload_appearance(self, appearance) -> None:
        albedo = appearance.albedo.detach().to("cpu", torch.float32)  # (3, T, T), row 0 is v = 0
        texels = np.ascontiguousarray(albedo.permute(1, 2, 0).numpy())
        size = (texels.shape[1], texels.shape[0])
        if self._albedo is None or self._albedo.size != size:
            if self._albedo is not None:
                self._albedo.release()
            self._albedo = self.ctx.texture(size, 3, dtype="f4")
            self._albedo.filter = (moderngl.LINEAR, moderngl.LINEAR)
            self._albedo.repeat_x = self._albedo.repeat_y = False
        self._albedo.write(texels)
        shading = appearance.shading.detach().to("cpu", torch.float32).numpy()
        self.program["u_shading"].write(np.ascontiguousarray(shading).tobytes())

    def draw(self, vertices, normals, faces, uv, uv_faces, camera: Camera, appearance,
             supersample: int = 2) -> moderngl.Texture:
        """Draw the body layer of ``camera`` into the pass's RGBA32F texture of the camera's size
        (rgb: ``a`` premultiplied by coverage, a: coverage; row 0 is image row 0) and return it, for
        a caller that samples it on the GPU. The texture belongs to the pass: it is overwritten by
        the next draw of the same size and freed with the pass. Leaves the pass's framebuffer bound;
        the caller sets its own state after. Arguments as :meth:`render`."""
        self._check_not_released()
        if not isinstance(camera, Camera):
            raise TypeError(f"camera must be a conventions.Camera, got {type(camera).__name__}")
        s = max(1, int(supersample))
        W, H = camera.width, camera.height
        with current(self.ctx):
            self._use_program(int(appearance.degree))
            count = self._upload_mesh(vertices, normals, faces, uv, uv_faces)
            self._upload_appearance(appearance)
            fine = camera.resized(W * s, H * s) if s > 1 else camera
            self.program["u_view"].write(fine.world_to_camera().T.astype(np.float32).tobytes())
            self.program["u_proj"].write(fine.gl_projection().T.astype(np.float32).tobytes())
            targets = self._targets.get((W, H, s))
            with targets.scope:
                targets.fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
                self._albedo.use(location=0)
                self._vao.render(moderngl.TRIANGLES, vertices=count)
            with targets.resolve_scope:
                targets.color.use(location=0)
                self.resolve["u_factor"].value = s
                self.resolve_vao.render(moderngl.TRIANGLES, vertices=3)
        self._last = targets
        return targets.resolved

    def render(self, vertices, normals, faces, uv, uv_faces, camera: Camera, appearance,
               supersample: int = 2) -> tuple[torch.Tensor, torch.Tensor]:
        """The body layer of ``camera`` at its size, read back.

        Args:
            vertices, normals: (V, 3) the posed body and its unit vertex normals.
            faces: (F, 3); uv: (Nuv, 2) the atlas; uv_faces: (F, 3) indices into it.
            camera: the view.
            appearance: the :class:`~garmentnerf.model.body_appearance.BodyAppearance`.
            supersample: subsamples per pixel side.
        Returns:
            As :func:`~garmentnerf.render.body_layer.render_body_layer`: ``color`` (1, 3, H, W)
            premultiplied by ``coverage`` (1, 1, H, W).
        """
        self.draw(vertices, normals, faces, uv, uv_faces, camera, appearance, supersample)
        targets = self._last
        with current(self.ctx):
            targets.resolve_fbo.read_into(targets.buffer, components=4, dtype="f4")
        layer = torch.from_numpy(targets.buffer).permute(2, 0, 1).unsqueeze(0)  # (1, 4, H, W), row 0 at the top
        # both slices are strided views of the buffer, so contiguous() copies them (the buffer is reused)
        return layer[:, :3].contiguous(), layer[:, 3:].contiguous()

    def _release_objects(self) -> None:
        self._targets.release()
        self._release_mesh()
        for obj in (self._albedo, self.resolve_vao, self.resolve, *self._programs.values()):
            if obj is not None:
                obj.release()


__all__ = ["BodyLayerPass", "shading_sum_glsl"]
