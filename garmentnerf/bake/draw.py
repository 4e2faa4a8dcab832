"""Drawing a baked frame from any camera on the GL context (no network): the previewer's draw, the
benchmark's and the tests' alike.

Passes (:meth:`BakeDrawer.draw`), each setting its whole state:

1. **Body depth.** The posed body into a depth texture of the drawing camera (the body test).
2. **Views.** The ``draw_views`` captures nearest the camera in angle
   (:func:`~garmentnerf.bake.views.nearest_views`), each as its surface mesh
   (:func:`~garmentnerf.bake.views.view_mesh`) into a slot of its own (its layers as float targets and a
   depth buffer: the view's nearest surface wins, ``shaders/bake_view.frag``), hidden where the body is
   more than :data:`BODY_MARGIN` in front of it.
3. **Blend.** ``shaders/bake_blend.frag`` averages the slots with their angle weights where they cover the
   pixel, then either composes the garment with the palette, premultiplied (the previewer blends it over
   its rasterised body), or returns one blended layer (:meth:`BakeDrawer.read_layers`, which the
   benchmark composes with :func:`~garmentnerf.model.palette.compose`).

GPU copies of the views (vertex buffers and layer textures) are kept for the :data:`VIEW_CACHE` most
recently drawn views, so orbiting a frame uploads nothing.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import moderngl
import numpy as np

from garmentnerf.bake.views import BakedFrame, BakedView, nearest_views
from garmentnerf.conventions import Camera
from garmentnerf.gl.context import current, is_released, make_current
from garmentnerf.gl.shaders import build_program

#: The body hides the baked garment only where it is more than this (metres) in front of it: cloth lies
#: within a couple of centimetres of the skin, where the network's own body weight decides and a bake
#: has none (the bake lab: at 0 the body pokes through, -1.5 dB).
BODY_MARGIN = 0.04
#: Views whose meshes and textures stay on the GPU.
VIEW_CACHE = 64
#: The most slots (views blended at one pixel) and layers (2 + garment colours) the shaders take.
MAX_SLOTS = 3
MAX_LAYERS = 5


@dataclass
class _GpuView:
    vao: moderngl.VertexArray
    buffers: tuple
    texture: moderngl.TextureArray
    triangles: int
    low: np.ndarray   # (L, 4) the range of each layer channel: value = low + code * span
    span: np.ndarray
    bounds: np.ndarray  # (2, 3) the mesh's box

    def release(self) -> None:
        self.vao.release()
        for b in self.buffers:
            b.release()
        self.texture.release()


class _Slots:
    """The float targets of the views drawn at one size: per slot ``layers`` RGBA16F textures and a depth
    buffer; plus the body's depth texture and an RGBA32F target for read-backs. Every pass touches only
    :attr:`rect`, the part of the target the frame's garment can cover."""

    def __init__(self, ctx: moderngl.Context, size: tuple[int, int], slots: int, layers: int) -> None:
        self.size, self.slots, self.layers = size, slots, layers
        self.textures = [[ctx.texture(size, 4, dtype="f2") for _ in range(layers)] for _ in range(slots)]
        self.depths = [ctx.depth_renderbuffer(size) for _ in range(slots)]
        self.fbos = [ctx.framebuffer(color_attachments=tex, depth_attachment=d) for tex, d in zip(self.textures, self.depths)]
        for row in self.textures:
            for t in row:
                t.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self.body_depth = ctx.depth_texture(size)
        self.body_depth.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self.body_depth.compare_func = ""  # sampled as depth values, not compared
        self.body_fbo = ctx.framebuffer(depth_attachment=self.body_depth)
        self.readback = ctx.texture(size, 4, dtype="f4")
        self.readback_fbo = ctx.framebuffer(color_attachments=[self.readback])
        self.rect = (0, 0, *size)  # (x, y, w, h) in the targets' pixels, set by each draw

    def release(self) -> None:
        for obj in (*self.fbos, *self.depths, *(t for row in self.textures for t in row), self.body_fbo,
                    self.body_depth, self.readback_fbo, self.readback):
            obj.release()


def screen_rect(points: np.ndarray, camera: Camera, projection: np.ndarray, margin: int = 2) -> tuple[int, int, int, int]:
    """(x, y, w, h) the framebuffer pixels (GL window coordinates of ``projection``, at the camera's size) that
    the box around ``points (N, 3)`` can cover, grown by ``margin``; the whole frame when a corner lies behind
    the camera; (0, 0, 0, 0) when the box is outside the frame."""
    W, H = camera.width, camera.height
    lo, hi = points.min(axis=0), points.max(axis=0)
    corners = np.array([[x, y, z, 1.0] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    clip = corners @ (projection @ camera.world_to_camera()).T
    if np.any(clip[:, 3] <= camera.near):
        return 0, 0, W, H
    ndc = clip[:, :2] / clip[:, 3:]
    x0 = int(np.floor((ndc[:, 0].min() + 1.0) * 0.5 * W)) - margin
    x1 = int(np.ceil((ndc[:, 0].max() + 1.0) * 0.5 * W)) + margin
    y0 = int(np.floor((ndc[:, 1].min() + 1.0) * 0.5 * H)) - margin
    y1 = int(np.ceil((ndc[:, 1].max() + 1.0) * 0.5 * H)) + margin
    x0, y0, x1, y1 = max(0, x0), max(0, y0), min(W, x1), min(H, y1)
    return (x0, y0, x1 - x0, y1 - y0) if x1 > x0 and y1 > y0 else (0, 0, 0, 0)


def _matrix(m: np.ndarray) -> bytes:
    return np.asarray(m, dtype=np.float64).T.astype(np.float32).tobytes()


class BakeDrawer:
    """Draws :class:`~garmentnerf.bake.views.BakedFrame` objects on ``ctx`` (module docstring).

    Every public method makes ``ctx`` current (and leaves it current), as the package's GL passes do.

    Args:
        draw_views: captures blended at a pixel (1..:data:`MAX_SLOTS`).
        mesh_step: map pixels between a view mesh's vertices.
        body_margin: :data:`BODY_MARGIN`.
    """

    def __init__(self, ctx: moderngl.Context, draw_views: int = 2, mesh_step: int = 1,
                 body_margin: float = BODY_MARGIN) -> None:
        if not 1 <= draw_views <= MAX_SLOTS:
            raise ValueError(f"draw_views must be in 1..{MAX_SLOTS}, got {draw_views}")
        self.ctx = ctx
        self.draw_views = int(draw_views)
        self.mesh_step = int(mesh_step)
        self.body_margin = float(body_margin)
        with current(ctx):
            self.depth_program = build_program(ctx, "bake_depth.vert", "bake_depth.frag")
        self._view_programs: dict[int, moderngl.Program] = {}
        self._blend_programs: dict[int, moderngl.Program] = {}
        self._views: OrderedDict[int, tuple[BakedView, _GpuView]] = OrderedDict()
        self._slots: _Slots | None = None
        self._blend_vaos: dict[int, moderngl.VertexArray] = {}
        self._body: tuple | None = None  # (key, vbo, ibo, vao)
        self._frame_geometry: tuple | None = None  # (baked frame, its captures' centres, the garment's centre)
        self._released = False
        self.triangles_drawn = 0

    # ---- resources ----------------------------------------------------------------------------------
    def _view_program(self, layers: int) -> moderngl.Program:
        if layers not in self._view_programs:
            self._view_programs[layers] = build_program(self.ctx, "bake_view.vert", "bake_view.frag",
                                                        {"LAYERS": layers})
        return self._view_programs[layers]

    def _blend_program(self, layers: int) -> moderngl.Program:
        if layers not in self._blend_programs:
            program = build_program(self.ctx, "fullscreen_triangle.vert", "bake_blend.frag",
                                    {"LAYERS": layers, "SLOTS": self.draw_views})
            self._blend_programs[layers] = program
            self._blend_vaos[layers] = self.ctx.vertex_array(program, [])
        return self._blend_programs[layers]

    def _gpu_view(self, view: BakedView) -> _GpuView:
        key = id(view)
        hit = self._views.get(key)
        if hit is not None and hit[0] is view:
            self._views.move_to_end(key)
            return hit[1]
        mesh = view.mesh(self.mesh_step)
        L = view.codes.shape[0]
        if L > MAX_LAYERS:
            raise ValueError(f"a bake of {L - 2} garment colours; the GL draw takes at most {MAX_LAYERS - 2}")
        program = self._view_program(L)
        data = np.concatenate([mesh.positions, mesh.texcoords], axis=1).astype(np.float32)
        vbo = self.ctx.buffer(data.tobytes() if len(data) else np.zeros((1, 5), np.float32).tobytes())
        ibo = self.ctx.buffer(mesh.faces.astype(np.uint32).tobytes() if len(mesh.faces) else np.zeros(3, np.uint32).tobytes())
        vao = self.ctx.vertex_array(program, [(vbo, "3f 2f", "in_position", "in_uv")], index_buffer=ibo,
                                    index_element_size=4)
        W, H = view.size
        texture = self.ctx.texture_array((W, H, L), 4, data=np.ascontiguousarray(view.codes).tobytes(), dtype="f1")
        texture.filter = (moderngl.LINEAR, moderngl.LINEAR)
        texture.repeat_x = texture.repeat_y = False
        bounds = (np.stack([mesh.positions.min(0), mesh.positions.max(0)]) if len(mesh.positions)
                  else np.zeros((2, 3), np.float32))
        gpu = _GpuView(vao, (vbo, ibo), texture, int(len(mesh.faces)), view.low, view.high - view.low, bounds)
        self._views[key] = (view, gpu)
        while len(self._views) > VIEW_CACHE:
            _, (_, old) = self._views.popitem(last=False)
            old.release()
        return gpu

    def _slots_for(self, size: tuple[int, int], layers: int) -> _Slots:
        if self._slots is None or self._slots.size != size or self._slots.layers != layers:
            if self._slots is not None:
                self._slots.release()
            self._slots = _Slots(self.ctx, size, self.draw_views, layers)
        return self._slots

    def set_body(self, key: object, vertices: np.ndarray, faces: np.ndarray) -> None:
        """The posed body the views are tested against (``vertices (V, 3)``, ``faces (F, 3)``); ``key`` names
        it, so an unchanged body is not uploaded again."""
        make_current(self.ctx)
        if self._body is not None and self._body[0] == key:
            return
        self._release_body()
        vbo = self.ctx.buffer(np.ascontiguousarray(vertices, np.float32).tobytes())
        ibo = self.ctx.buffer(np.ascontiguousarray(faces, np.uint32).tobytes())
        vao = self.ctx.vertex_array(self.depth_program, [(vbo, "3f", "in_position")], index_buffer=ibo,
                                    index_element_size=4)
        self._body = (key, vbo, ibo, vao)

    def _release_body(self) -> None:
        if self._body is not None:
            for obj in self._body[1:][::-1]:
                obj.release()
            self._body = None

    # ---- drawing ------------------------------------------------------------------------------------------
    def views_for(self, baked: BakedFrame, camera: Camera) -> list[tuple[BakedView, float]]:
        """The views ``camera`` draws, with their weights, nearest first."""
        if not baked.views:
            return []
        if self._frame_geometry is None or self._frame_geometry[0] is not baked:  # once per frame, not per draw
            self._frame_geometry = (baked, np.stack([v.camera.center for v in baked.views]),
                                    self._garment_center(baked))
        _, centers, target = self._frame_geometry
        return [(baked.views[i], w) for i, w in nearest_views(centers, target, camera.center, self.draw_views)]

    @staticmethod
    def _garment_center(baked: BakedFrame) -> np.ndarray:
        """The point the captures look at, as seen from above: where their optical axes pass nearest."""
        A = np.zeros((3, 3))
        b = np.zeros(3)
        for v in baked.views:
            d = v.camera.R[2]
            P = np.eye(3) - np.outer(d, d)
            A += P
            b += P @ v.camera.center
        return np.linalg.lstsq(A, b, rcond=None)[0]

    def draw_slots(self, baked: BakedFrame, camera: Camera, projection: np.ndarray | None = None,
                   body_depth: moderngl.Texture | None = None) -> tuple[_Slots, list[float]] | None:
        """Passes 1 and 2 (module docstring) at ``camera``'s size; None when the frame has no view.
        ``projection``: camera -> clip (default ``camera.gl_projection()``, image row 0 at the framebuffer's
        first row; a window that shows row 0 at the top passes its flipped one). ``body_depth``: a depth
        texture of the same camera and projection that holds the body already (the previewer's scene):
        pass 1 is skipped."""
        make_current(self.ctx)
        chosen = self.views_for(baked, camera)
        if not chosen:
            return None
        L = chosen[0][0].codes.shape[0]
        size = (camera.width, camera.height)
        slots = self._slots_for(size, L)
        ctx = self.ctx
        projection = camera.gl_projection() if projection is None else projection
        view_m, proj_m = _matrix(camera.world_to_camera()), _matrix(projection)
        points = np.concatenate([self._gpu_view(view).bounds for view, _ in chosen])
        slots.rect = screen_rect(points, camera, projection)
        if slots.rect[2] == 0:
            return None
        # 1. the body's depth
        ctx.viewport = (0, 0, *size)
        ctx.scissor = slots.rect
        ctx.disable(moderngl.BLEND | moderngl.CULL_FACE)
        ctx.enable(moderngl.DEPTH_TEST)
        ctx.depth_func = "<"
        if body_depth is None:
            slots.body_fbo.use()
            slots.body_fbo.clear(depth=1.0, viewport=slots.rect)
            if self._body is not None:
                self.depth_program["u_world_to_camera"].write(view_m)
                self.depth_program["u_projection"].write(proj_m)
                self._body[3].render(moderngl.TRIANGLES)
            body_depth = slots.body_depth
        # 2. each view into its slot
        program = self._view_program(L)
        program["u_world_to_camera"].write(view_m)
        program["u_projection"].write(proj_m)
        program["u_target_size"].value = (float(size[0]), float(size[1]))
        program["u_body_margin"].value = self.body_margin
        program["u_near"].value = float(camera.near)
        program["u_far"].value = float(camera.far)
        program["u_layers"].value = 0
        program["u_body_depth"].value = 1
        body_depth.use(1)
        weights = []
        self.triangles_drawn = 0
        for s in range(self.draw_views):
            fbo = slots.fbos[s]
            fbo.use()
            ctx.scissor = slots.rect
            fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0, viewport=slots.rect)
            if s < len(chosen):
                view, weight = chosen[s]
                gpu = self._gpu_view(view)
                gpu.texture.use(0)
                program["u_low"].write(np.ascontiguousarray(gpu.low, np.float32).tobytes())
                program["u_span"].write(np.ascontiguousarray(gpu.span, np.float32).tobytes())
                gpu.vao.render(moderngl.TRIANGLES, vertices=3 * gpu.triangles)
                self.triangles_drawn += gpu.triangles
                weights.append(float(weight))
            else:
                weights.append(0.0)
        ctx.scissor = None
        return slots, weights

    def _blend(self, slots: _Slots, weights: list[float], origin: tuple[int, int], mode: int, layer: int = 0,
               palette=None) -> None:
        program = self._blend_program(slots.layers)
        units = []
        for s in range(slots.slots):
            for j in range(slots.layers):
                units.append(2 + s * slots.layers + j)
                slots.textures[s][j].use(units[-1])
        program["u_slot"].value = tuple(units)
        program["u_weight"].value = tuple(weights) if len(weights) > 1 else weights[0]
        program["u_target_size"].value = (float(slots.size[0]), float(slots.size[1]))
        program["u_origin"].value = (float(origin[0]), float(origin[1]))
        program["u_mode"].value = mode
        if mode == 1:
            program["u_layer"].value = layer
        else:
            colors = np.zeros((3, 3), np.float32)
            pal = np.asarray(palette, np.float32).reshape(-1, 3)[:-1]  # the garment colours (the body's is last)
            colors[:len(pal)] = pal
            program["u_palette"].write(colors.tobytes())
        self.ctx.disable(moderngl.DEPTH_TEST | moderngl.CULL_FACE)
        x, y, w, h = slots.rect
        self.ctx.scissor = (x + int(origin[0]), y + int(origin[1]), w, h)
        self._blend_vaos[slots.layers].render(moderngl.TRIANGLES, vertices=3)
        self.ctx.scissor = None

    def read_layers(self, baked: BakedFrame, camera: Camera) -> np.ndarray | None:
        """(L, H, W, 4) float32 the blended layers of ``baked`` seen by ``camera`` (rows top-first), zero where
        no view covers; None when the frame has no view. With the body layer they compose as the network's
        maps do (:func:`~garmentnerf.bake.views.maps_from_layers`)."""
        make_current(self.ctx)
        drawn = self.draw_slots(baked, camera)
        if drawn is None:
            return None
        slots, weights = drawn
        W, H = slots.size
        out = np.zeros((slots.layers, H, W, 4), np.float32)
        slots.readback_fbo.use()
        self.ctx.viewport = (0, 0, W, H)
        self.ctx.disable(moderngl.BLEND)
        for j in range(slots.layers):
            slots.readback_fbo.clear(0.0, 0.0, 0.0, 0.0)
            self._blend(slots, weights, (0, 0), mode=1, layer=j)
            data = slots.readback_fbo.read(components=4, dtype="f4")
            out[j] = np.frombuffer(data, np.float32).reshape(H, W, 4)
        return out

    def compose_into(self, fbo: moderngl.Framebuffer, viewport: tuple[int, int, int, int], baked: BakedFrame,
                     camera: Camera, palette, projection: np.ndarray | None = None,
                     body_depth: moderngl.Texture | None = None) -> bool:
        """Draw ``baked`` seen by ``camera`` composed with ``palette`` ((P, 3), the body's colour last),
        premultiplied, blended (ONE, ONE_MINUS_SRC_ALPHA) over what ``fbo`` holds in ``viewport``; the
        camera's size is the viewport's, ``projection`` and ``body_depth`` as :meth:`draw_slots`. False when
        the frame has no view."""
        make_current(self.ctx)
        drawn = self.draw_slots(baked, camera, projection, body_depth)
        if drawn is None:
            return False
        slots, weights = drawn
        fbo.use()
        self.ctx.viewport = viewport
        self.ctx.enable(moderngl.BLEND)
        self.ctx.blend_func = moderngl.ONE, moderngl.ONE_MINUS_SRC_ALPHA
        self._blend(slots, weights, viewport[:2], mode=0, palette=palette)
        self.ctx.disable(moderngl.BLEND)
        return True

    def release(self) -> None:
        if self._released or is_released(self.ctx):
            return
        self._released = True
        make_current(self.ctx)
        for _, gpu in self._views.values():
            gpu.release()
        self._views.clear()
        if self._slots is not None:
            self._slots.release()
            self._slots = None
        self._release_body()
        for obj in (*self._blend_vaos.values(), *self._view_programs.values(), *self._blend_programs.values()):
            obj.release()
        self.depth_program.release()




def baked_maps(drawer: BakeDrawer, session, baked: BakedFrame, camera: Camera):
    """The :class:`~garmentnerf.model.palette.DecomposedMaps` (batch 1, at ``camera``'s size) of ``baked`` seen
    by ``camera``, with the frame's rasterised body layer attached (``session``'s,
    :meth:`~garmentnerf.render.session.RenderSession.body_layer`): composed with any palette they give the
    bake's image as :meth:`~garmentnerf.render.session.NeuralFrame.composite` gives the network's. None
    when the frame has no view."""
    import torch

    from garmentnerf.bake.views import maps_from_layers

    features, _ = session.frame_features(baked.frame)
    vertices = features.posed_vertices.detach().to("cpu", torch.float32).numpy()
    drawer.set_body(("frame", id(session), baked.frame), vertices, session.body.faces.cpu().numpy())
    layers = drawer.read_layers(baked, camera)
    if layers is None:
        return None
    with torch.no_grad():
        return maps_from_layers(layers).with_body(*session.body_layer(features, camera))


__all__ = ["BakeDrawer", "baked_maps", "screen_rect", "BODY_MARGIN", "VIEW_CACHE", "MAX_SLOTS", "MAX_LAYERS"]
