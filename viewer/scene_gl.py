"""GL side of the previewer: renderables with a lifecycle, and the scene renderer that draws them.

Orientation (read this before touching projections)
    :meth:`garmentnerf.conventions.Camera.gl_projection` puts image row 0 at framebuffer row 0, which
    is right for read-back passes but upside down on a screen (GL's row 0 is the *bottom* of a
    window). The viewer therefore draws with :func:`display_projection`, the same matrix with the
    y flip undone: image row 0 is at the top of the window, triangles wound counter-clockwise seen
    from outside stay counter-clockwise on screen (GL's default front face), and a framebuffer
    read back with ``glReadPixels`` is upside down: :func:`read_image` flips it so every image this
    package returns is in the conventions' layout (row 0 at the top, pixel (u, v) of
    ``Camera.K`` at column u, row v).

Pipeline
    Every view (the window, a snapshot, a test's headless reference) is drawn by
    :meth:`SceneRenderer.render` into a :class:`RenderTarget` (multisampled colour + depth, resolved
    into a texture), in this order: clear to the background, floor (blended, no depth writes),
    body (opaque, depth tested), neural layer (blended, its own per-pixel depth), palette layer
    (:class:`PaletteLayer`: the network's decomposed maps composed with the palette in
    ``shaders/viewer_palette.frag``; blended by its mask over the scene, optionally depth-tested
    against the body, or opaque in the ground-truth/difference/maps modes). The window then
    shows the resolved texture with :meth:`SceneRenderer.present` and draws imgui on top. Because the
    window and a snapshot of the same size go through the same code, they match bit for bit.

Lifecycle
    A renderable builds its GL objects in ``__init__`` on the renderer's context, uploads lazily in
    ``prepare()`` when a dirty flag is set, draws in ``draw()`` and frees everything in ``release()``.
    Nothing is cached at module level, so any number of contexts can each own a renderer.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

import moderngl
import numpy as np

from garmentnerf.conventions import Camera
from garmentnerf.gl.context import current, is_released
from garmentnerf.gl.shaders import build_program

#: Window/snapshot background (display RGB).
BACKGROUND = (0.155, 0.165, 0.185)
#: Renderer names (substrings, lower case) of software rasterisers, where MSAA costs too much.
SOFTWARE_RENDERERS = ("llvmpipe", "softpipe", "swrast", "software", "swiftshader")

#: Body colour (display RGB): the ground-truth renderer's skin tone.
BODY_COLOR = (0.80, 0.63, 0.53)

_Y_FLIP = np.diag([1.0, -1.0, 1.0, 1.0])


def display_projection(camera: Camera) -> np.ndarray:
    """(4, 4) OpenCV camera -> GL clip with image row 0 at the *top* of the viewport (see module doc)."""
    return _Y_FLIP @ camera.gl_projection()


def is_software_renderer(name: str) -> bool:
    """Whether a GL_RENDERER string names a CPU rasteriser."""
    low = name.lower()
    return any(s in low for s in SOFTWARE_RENDERERS)


def _mat(m: np.ndarray) -> bytes:
    """Column-major float32 bytes of a (4, 4) matrix, as GLSL mat4 uniforms want."""
    return np.ascontiguousarray(np.asarray(m, dtype=np.float64).T, dtype=np.float32).tobytes()


@dataclass(frozen=True)
class ViewParams:
    """What a renderable needs to know about the view."""

    camera: Camera
    view: np.ndarray  # (4, 4) world -> OpenCV camera
    proj: np.ndarray  # (4, 4) display projection

    @staticmethod
    def of(camera: Camera) -> "ViewParams":
        return ViewParams(camera, camera.world_to_camera(), display_projection(camera))


@dataclass(frozen=True)
class StudioLighting:
    """Lights fixed to the camera, so every view is lit from the front; directions are in OpenCV
    camera coordinates (x right, y down, z forward) pointing *toward* the light."""

    key: tuple[float, float, float] = (-0.45, -0.55, -0.70)
    key_intensity: float = 0.62
    fill: tuple[float, float, float] = (0.70, -0.10, -0.70)
    fill_intensity: float = 0.25
    back: tuple[float, float, float] = (0.20, -0.60, 0.78)
    back_intensity: float = 0.22
    sky: tuple[float, float, float] = (0.32, 0.32, 0.34)
    ground: tuple[float, float, float] = (0.10, 0.095, 0.09)
    specular: float = 0.12
    shininess: float = 28.0
    rim: float = 0.10

    def world_directions(self, camera: Camera) -> list[tuple[float, float, float]]:
        out = []
        for d in (self.key, self.fill, self.back):
            v = camera.R.T @ np.asarray(d, dtype=np.float64)
            out.append(tuple(float(x) for x in v / np.linalg.norm(v)))
        return out


# ---- renderables ------------------------------------------------------------------------------------
class BodyMesh:
    """The posed body: one dynamic (position, normal) vertex buffer, re-uploaded only when the shown
    frame (its ``key``) changes; a static index buffer, replaced when the topology changes."""

    def __init__(self, ctx: moderngl.Context, lighting: StudioLighting | None = None) -> None:
        self.ctx = ctx
        self.lighting = lighting or StudioLighting()
        self.color = BODY_COLOR
        self.visible = True
        self.program = build_program(ctx, "viewer_mesh.vert", "viewer_mesh.frag")
        self.vbo: moderngl.Buffer | None = None
        self.ibo: moderngl.Buffer | None = None
        self.vao: moderngl.VertexArray | None = None
        self.index_count = 0
        self.num_vertices = 0
        self.key: object = None
        self._pending: np.ndarray | None = None
        self._pending_faces: np.ndarray | None = None
        self._faces: np.ndarray | None = None
        self.uploads = 0  # vertex uploads so far (tests check that a still frame uploads nothing)

    @property
    def dirty(self) -> bool:
        return self._pending is not None or self._pending_faces is not None

    def set_topology(self, faces: np.ndarray, num_vertices: int) -> None:
        """Use these triangles (a no-op when they are the ones in use)."""
        if self._faces is not None and self.num_vertices == num_vertices and (
                faces is self._faces or (faces.shape == self._faces.shape and np.array_equal(faces, self._faces))):
            return
        tris = np.ascontiguousarray(faces, dtype=np.int32)
        if tris.ndim != 2 or tris.shape[1] != 3:
            raise ValueError(f"faces must be (F, 3), got {tris.shape}")
        if tris.size and (tris.min() < 0 or tris.max() >= num_vertices):
            raise ValueError(f"faces index out of range [0, {num_vertices})")
        self._faces = faces
        self._pending_faces = tris
        self.num_vertices = int(num_vertices)
        self.key = None

    def set_frame(self, key: object, vertex_data: np.ndarray) -> bool:
        """Show ``vertex_data`` (V, 6) float32 [position, normal]; a no-op when ``key`` is the shown key.
        Returns whether an upload was scheduled."""
        if key is not None and key == self.key and self._pending is None:
            return False
        if vertex_data.shape != (self.num_vertices, 6):
            raise ValueError(f"body frame must be ({self.num_vertices}, 6), got {vertex_data.shape}")
        self._pending = np.ascontiguousarray(vertex_data, dtype=np.float32)
        self.key = key
        return True

    def prepare(self) -> None:
        if self._pending_faces is not None:
            self._release_buffers()
            self.vbo = self.ctx.buffer(reserve=max(self.num_vertices * 24, 24), dynamic=True)
            self.ibo = self.ctx.buffer(self._pending_faces.tobytes())
            self.vao = self.ctx.vertex_array(self.program, [(self.vbo, "3f 3f", "in_position", "in_normal")],
                                             index_buffer=self.ibo, index_element_size=4)
            self.index_count = int(self._pending_faces.size)
            self._pending_faces = None
        if self._pending is not None and self.vbo is not None:
            self.vbo.write(self._pending)
            self._pending = None
            self.uploads += 1

    def draw(self, view: ViewParams) -> None:
        if not self.visible or self.vao is None or self.key is None or self.index_count == 0:
            return
        p, L = self.program, self.lighting
        p["u_view"].write(_mat(view.view))
        p["u_proj"].write(_mat(view.proj))
        p["u_camera_center"].value = tuple(float(x) for x in view.camera.center)
        p["u_base_color"].value = tuple(float(x) for x in self.color)
        p["u_light_dir"].value = L.world_directions(view.camera)
        p["u_light_intensity"].value = [L.key_intensity, L.fill_intensity, L.back_intensity]
        p["u_sky"].value = L.sky
        p["u_ground"].value = L.ground
        p["u_specular"].value = L.specular
        p["u_shininess"].value = L.shininess
        p["u_rim"].value = L.rim
        self.vao.render(moderngl.TRIANGLES, vertices=self.index_count)

    def _release_buffers(self) -> None:
        for obj in (self.vao, self.vbo, self.ibo):
            if obj is not None:
                obj.release()
        self.vao = self.vbo = self.ibo = None
        self.index_count = 0

    def release(self) -> None:
        self._release_buffers()
        self.program.release()


class FloorGrid:
    """The ground plane z = 0: grid lines, axes, a contact shadow under the body, faded at the edges."""

    def __init__(self, ctx: moderngl.Context) -> None:
        self.ctx = ctx
        self.visible = True       # the floor (shadow + fade)
        self.show_lines = True    # the grid lines on it
        self.half_size = 8.0
        self.minor = 0.25
        self.center = np.zeros(2)
        self.shadow_center = np.zeros(2)
        self.shadow_radius = 0.32
        self.shadow_strength = 0.45
        self.program = build_program(ctx, "viewer_floor.vert", "viewer_floor.frag")
        self.vao = ctx.vertex_array(self.program, [])

    def prepare(self) -> None:
        pass  # nothing to upload: the quad is made in the vertex shader

    def draw(self, view: ViewParams) -> None:
        if not self.visible:
            return
        p = self.program
        below = view.camera.center[2] < 0.0
        p["u_view"].write(_mat(view.view))
        p["u_proj"].write(_mat(view.proj))
        p["u_center"].value = tuple(float(x) for x in self.center)
        p["u_half_size"].value = float(self.half_size)
        p["u_minor"].value = float(self.minor)
        p["u_show_grid"].value = 1.0 if self.show_lines else 0.0
        p["u_floor_color"].value = (0.25, 0.26, 0.28)
        p["u_line_color"].value = (0.42, 0.43, 0.46)
        p["u_axis_x_color"].value = (0.62, 0.30, 0.30)
        p["u_axis_y_color"].value = (0.32, 0.55, 0.32)
        p["u_opacity"].value = 0.35 if below else 1.0  # seen from below: a faint see-through floor
        p["u_shadow_center"].value = tuple(float(x) for x in self.shadow_center)
        p["u_shadow_radius"].value = float(self.shadow_radius)
        p["u_shadow_strength"].value = float(self.shadow_strength)
        self.vao.render(moderngl.TRIANGLE_STRIP, vertices=4)

    def release(self) -> None:
        self.vao.release()
        self.program.release()


@dataclass
class _LayerImage:
    color: np.ndarray          # (H, W, 4) uint8 premultiplied RGBA, row 0 at the top
    depth: np.ndarray          # (H, W) float32 camera-space z, <= 0 where empty
    tag: object = None         # whatever the producer wants back (e.g. the request it answers)


class NeuralLayer:
    """An image rendered elsewhere (the neural garment, later), composited by its mask and depth.

    Thread contract: a worker thread calls :meth:`submit` with numpy arrays (never GL); the GL thread
    uploads the newest submission in :meth:`prepare` and draws it in :meth:`draw`. Submissions that
    arrive faster than frames are drawn replace each other (only the newest is uploaded). The image
    may have any resolution: it is stretched bilinearly over the viewport, so a worker can render at
    a reduced scale while the camera moves.
    """

    def __init__(self, ctx: moderngl.Context) -> None:
        self.ctx = ctx
        self.visible = True
        self.opacity = 1.0
        self.program = build_program(ctx, "viewer_fullscreen.vert", "viewer_layer.frag")
        self.program["u_color"].value = 0
        self.program["u_depth"].value = 1
        self.vao = ctx.vertex_array(self.program, [])
        self.color_tex: moderngl.Texture | None = None
        self.depth_tex: moderngl.Texture | None = None
        self.tag: object = None  # the tag of the image on the GPU
        self._lock = threading.Lock()
        self._pending: _LayerImage | None = None

    @property
    def has_image(self) -> bool:
        return self.color_tex is not None

    def submit(self, color: np.ndarray, depth: np.ndarray, tag: object = None) -> None:
        """Queue an image for display (any thread). ``color`` (H, W, 4) premultiplied RGBA, uint8 or
        float in [0, 1]; ``depth`` (H, W) camera-space z in metres, <= 0 where empty."""
        color = np.asarray(color)
        depth = np.asarray(depth, dtype=np.float32)
        if color.ndim != 3 or color.shape[2] != 4 or depth.shape != color.shape[:2]:
            raise ValueError(f"neural layer needs color (H, W, 4) and depth (H, W), "
                             f"got {color.shape} and {depth.shape}")
        if color.dtype != np.uint8:
            color = np.clip(np.rint(np.asarray(color, dtype=np.float64) * 255.0), 0, 255).astype(np.uint8)
        image = _LayerImage(np.ascontiguousarray(color), np.ascontiguousarray(np.nan_to_num(depth, nan=0.0)), tag)
        with self._lock:
            self._pending = image

    def clear(self) -> None:
        with self._lock:
            self._pending = None
        self._release_textures()
        self.tag = None

    def prepare(self) -> None:
        with self._lock:
            image, self._pending = self._pending, None
        if image is None:
            return
        h, w = image.depth.shape
        if self.color_tex is None or self.color_tex.size != (w, h):
            self._release_textures()
            self.color_tex = self.ctx.texture((w, h), 4, dtype="f1")
            self.color_tex.filter = (moderngl.LINEAR, moderngl.LINEAR)
            self.depth_tex = self.ctx.texture((w, h), 1, dtype="f4")
            self.depth_tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
            for tex in (self.color_tex, self.depth_tex):
                tex.repeat_x = tex.repeat_y = False
        self.color_tex.write(image.color)
        self.depth_tex.write(image.depth)
        self.tag = image.tag

    def draw(self, view: ViewParams) -> None:
        if not self.visible or self.color_tex is None:
            return
        self.program["u_near"].value = float(view.camera.near)
        self.program["u_far"].value = float(view.camera.far)
        self.program["u_opacity"].value = float(self.opacity)
        self.color_tex.use(location=0)
        self.depth_tex.use(location=1)
        self.vao.render(moderngl.TRIANGLES, vertices=3)

    def _release_textures(self) -> None:
        for tex in (self.color_tex, self.depth_tex):
            if tex is not None:
                tex.release()
        self.color_tex = self.depth_tex = None

    def release(self) -> None:
        self._release_textures()
        self.vao.release()
        self.program.release()


#: View modes of the palette layer (what the neural layer shows).
PALETTE_MODES = {"neural": 0, "ground_truth": 1, "difference": 2, "maps": 3}
#: What the ``maps`` mode shows.
MAP_VIEWS = ("mask", "weights", "radiance")
#: Most palette colours the shader handles.
MAX_PALETTE = 4


def pack_maps(radiance: np.ndarray, offsets: np.ndarray, weights: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Decomposed maps (batch dimension dropped, rows top-first) -> (2 + P, H, W, 4) float32 layers
    for ``shaders/viewer_palette.frag``: [radiance rgb + mask], [weights], [offset_i rgb + 0] ...

    Args:
        radiance: (3 or 1, H, W); offsets: (P, 3, H, W); weights: (P, H, W); mask: (1, H, W) or (H, W).
    """
    radiance = np.asarray(radiance, dtype=np.float32)
    offsets = np.asarray(offsets, dtype=np.float32)
    weights = np.asarray(weights, dtype=np.float32)
    mask = np.asarray(mask, dtype=np.float32).reshape(-1, *weights.shape[-2:])[0]
    P, H, W = weights.shape
    if not 1 <= P <= MAX_PALETTE:
        raise ValueError(f"the viewer's palette shader handles 1..{MAX_PALETTE} colours, got {P}")
    if offsets.shape != (P, 3, H, W) or radiance.shape[1:] != (H, W) or radiance.shape[0] not in (1, 3):
        raise ValueError(f"maps disagree: radiance {radiance.shape}, offsets {offsets.shape}, weights {weights.shape}")
    out = np.zeros((2 + P, H, W, 4), dtype=np.float32)
    out[0, ..., :3] = np.broadcast_to(radiance, (3, H, W)).transpose(1, 2, 0)
    out[0, ..., 3] = mask
    out[1, ..., :P] = weights.transpose(1, 2, 0)
    out[2:, ..., :3] = offsets.transpose(0, 2, 3, 1)
    return out


@dataclass
class _PaletteMaps:
    layers: np.ndarray          # (2 + P, h, w, 4) float32, see pack_maps
    depth: np.ndarray           # (h, w) float32 camera-space z, 0 where empty
    image_size: tuple[int, int]  # (W, H) of the camera the maps belong to (its aspect is kept)
    tag: object = None


class PaletteLayer:
    """The neural render as decomposed maps, composed with the palette in a fragment shader
    (``shaders/viewer_palette.frag``, the formula of :func:`garmentnerf.model.palette.compose`).

    Thread contract as :class:`NeuralLayer`: :meth:`submit` / :meth:`submit_ground_truth` from any
    thread (numpy only), uploads in :meth:`prepare` on the GL thread. :meth:`set_palette` only sets
    a uniform: recolouring costs nothing.

    Attributes:
        mode: key of :data:`PALETTE_MODES`; side_by_side: draw the neural image and the ground truth
            next to each other (each fitted into half the view).
        map_view: what ``maps`` mode shows (:data:`MAP_VIEWS`).
        use_depth: write the network's depth (composite with the rasterised body by depth); off:
            drawn over everything by its mask.
        opaque: compose over :attr:`background` (as compose() does) instead of blending over the scene.
    """

    def __init__(self, ctx: moderngl.Context) -> None:
        self.ctx = ctx
        self.visible = True
        self.opacity = 1.0
        self.mode = "neural"
        self.side_by_side = False
        self.map_view = "mask"
        self.use_depth = False
        self.depth_bias = 0.03
        self.opaque = False
        self.background = (0.0, 0.0, 0.0)
        self.diff_gain = 4.0
        self.palette = np.full((1, 3), 0.5, dtype=np.float32)
        self.program = build_program(ctx, "viewer_palette.vert", "viewer_palette.frag")
        for name, unit in (("u_maps", 0), ("u_gt", 1), ("u_depth", 2)):
            self.program[name].value = unit
        self.vao = ctx.vertex_array(self.program, [])
        self.maps_tex: moderngl.TextureArray | None = None
        self.depth_tex: moderngl.Texture | None = None
        self.gt_tex: moderngl.Texture | None = None
        self.image_size: tuple[int, int] | None = None
        self.tag: object = None
        self.uploads = 0
        self._lock = threading.Lock()
        self._pending: _PaletteMaps | None = None
        self._pending_gt: np.ndarray | None = None
        self._clear_gt = False

    @property
    def has_image(self) -> bool:
        return self.maps_tex is not None

    @property
    def has_ground_truth(self) -> bool:
        return self.gt_tex is not None

    @property
    def palette_size(self) -> int:
        return 0 if self.maps_tex is None else self.maps_tex.layers - 2

    # ---- inputs (any thread) ---------------------------------------------------------------------
    def set_palette(self, palette) -> None:
        """(P, 3) colours in [0, 1] (a uniform; takes effect at the next draw)."""
        pal = np.asarray(palette, dtype=np.float32).reshape(-1, 3)
        if not 1 <= pal.shape[0] <= MAX_PALETTE or not np.all(np.isfinite(pal)):
            raise ValueError(f"palette must be (P, 3) finite with 1 <= P <= {MAX_PALETTE}, got {pal.shape}")
        self.palette = np.clip(pal, 0.0, 1.0)

    def submit(self, layers: np.ndarray, depth: np.ndarray, image_size: tuple[int, int], tag: object = None) -> None:
        """Queue maps packed by :func:`pack_maps` with their depth (h, w) and the output size (W, H)."""
        layers = np.ascontiguousarray(layers, dtype=np.float32)
        depth = np.ascontiguousarray(np.nan_to_num(np.asarray(depth, dtype=np.float32), nan=0.0))
        if layers.ndim != 4 or layers.shape[-1] != 4 or layers.shape[0] < 3 or depth.shape != layers.shape[1:3]:
            raise ValueError(f"palette layer needs (2 + P, h, w, 4) maps and (h, w) depth, got {layers.shape} "
                             f"and {depth.shape}")
        item = _PaletteMaps(layers, depth, (int(image_size[0]), int(image_size[1])), tag)
        with self._lock:
            self._pending = item

    def submit_ground_truth(self, image: np.ndarray | None) -> None:
        """Queue the ground-truth image (H, W, 3) uint8 or float in [0, 1] (None: none)."""
        if image is not None:
            image = np.asarray(image)
            if image.dtype != np.uint8:
                image = np.clip(np.rint(np.asarray(image, dtype=np.float64) * 255.0), 0, 255).astype(np.uint8)
            image = np.ascontiguousarray(image[..., :3])
        with self._lock:
            self._pending_gt = image
            self._clear_gt = image is None

    def clear(self) -> None:
        with self._lock:
            self._pending = None
        self._release_maps()
        self.tag = None

    # ---- GL thread -------------------------------------------------------------------------------
    def prepare(self) -> None:
        with self._lock:
            item, self._pending = self._pending, None
            gt, self._pending_gt = self._pending_gt, None
            clear_gt, self._clear_gt = self._clear_gt, False
        if clear_gt and self.gt_tex is not None:
            self.gt_tex.release()
            self.gt_tex = None
        if gt is not None:
            h, w = gt.shape[:2]
            if self.gt_tex is None or self.gt_tex.size != (w, h):
                if self.gt_tex is not None:
                    self.gt_tex.release()
                self.gt_tex = self.ctx.texture((w, h), 3, dtype="f1", alignment=1)
                self.gt_tex.filter = (moderngl.LINEAR, moderngl.LINEAR)
                self.gt_tex.repeat_x = self.gt_tex.repeat_y = False
            self.gt_tex.write(gt)
        if item is None:
            return
        L, h, w, _ = item.layers.shape
        if self.maps_tex is None or (self.maps_tex.width, self.maps_tex.height, self.maps_tex.layers) != (w, h, L):
            self._release_maps()
            self.maps_tex = self.ctx.texture_array((w, h, L), 4, dtype="f4")
            self.maps_tex.filter = (moderngl.LINEAR, moderngl.LINEAR)
            self.maps_tex.repeat_x = self.maps_tex.repeat_y = False
            self.depth_tex = self.ctx.texture((w, h), 1, dtype="f4")
            self.depth_tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
            self.depth_tex.repeat_x = self.depth_tex.repeat_y = False
        self.maps_tex.write(item.layers)
        self.depth_tex.write(item.depth)
        self.image_size = item.image_size
        self.tag = item.tag
        self.uploads += 1

    def _fit(self, x0: float, x1: float, vw: float, vh: float, size: tuple[int, int] | None) -> tuple:
        """NDC rect of an image of ``size`` fitted (aspect kept, centred) into [x0, x1] x [-1, 1]."""
        if size is None:
            return (x0, -1.0, x1, 1.0)
        avail_w, avail_h = vw * (x1 - x0) / 2.0, vh
        s = min(avail_w / size[0], avail_h / size[1])
        hw, hh = size[0] * s / vw, size[1] * s / vh  # half extents in NDC units (2 * px / (2 * v))
        cx = 0.5 * (x0 + x1)
        return (cx - hw, -hh, cx + hw, hh)

    def _draw_one(self, view: ViewParams, mode: str, rect) -> None:
        p = self.program
        pal = np.zeros((MAX_PALETTE, 3), dtype=np.float32)
        n = min(self.palette.shape[0], MAX_PALETTE)
        pal[:n] = self.palette[:n]
        p["u_palette"].write(pal.tobytes())
        p["u_palette_size"].value = int(min(n, self.palette_size))
        p["u_background"].value = tuple(float(c) for c in self.background)
        p["u_opaque"].value = int(bool(self.opaque) or self.side_by_side or mode != "neural")
        p["u_mode"].value = PALETTE_MODES[mode]
        p["u_map"].value = MAP_VIEWS.index(self.map_view)
        p["u_diff_gain"].value = float(self.diff_gain)
        p["u_opacity"].value = float(self.opacity)
        p["u_use_depth"].value = int(bool(self.use_depth) and mode == "neural")
        p["u_depth_bias"].value = float(self.depth_bias)
        p["u_near"].value = float(view.camera.near)
        p["u_far"].value = float(view.camera.far)
        p["u_rect"].value = tuple(float(v) for v in rect)
        self.vao.render(moderngl.TRIANGLE_STRIP, vertices=4)

    def draw(self, view: ViewParams) -> None:
        if not self.visible or self.maps_tex is None:
            return
        needs_gt = self.side_by_side or self.mode in ("ground_truth", "difference")
        if needs_gt and self.gt_tex is None:
            mode, side = ("neural" if self.mode in ("ground_truth", "difference") else self.mode), False
        else:
            mode, side = self.mode, self.side_by_side
        self.maps_tex.use(location=0)
        if self.gt_tex is not None:
            self.gt_tex.use(location=1)
        self.depth_tex.use(location=2)
        vw, vh = float(view.camera.width), float(view.camera.height)
        if side:
            self._draw_one(view, mode if mode != "ground_truth" else "neural", self._fit(-1.0, 0.0, vw, vh, self.image_size))
            self._draw_one(view, "ground_truth", self._fit(0.0, 1.0, vw, vh, self.image_size))
        else:
            self._draw_one(view, mode, self._fit(-1.0, 1.0, vw, vh, self.image_size))

    def _release_maps(self) -> None:
        for tex in (self.maps_tex, self.depth_tex):
            if tex is not None:
                tex.release()
        self.maps_tex = self.depth_tex = None

    def release(self) -> None:
        self._release_maps()
        if self.gt_tex is not None:
            self.gt_tex.release()
            self.gt_tex = None
        self.vao.release()
        self.program.release()


# ---- targets and the renderer ---------------------------------------------------------------------
class RenderTarget:
    """Multisampled colour + depth renderbuffers and the single-sample texture they resolve into."""

    def __init__(self, ctx: moderngl.Context, width: int, height: int, samples: int = 4) -> None:
        if width < 1 or height < 1:
            raise ValueError(f"render target size must be positive, got {width}x{height}")
        limit = int(ctx.info.get("GL_MAX_RENDERBUFFER_SIZE", 16384))
        if width > limit or height > limit:
            raise ValueError(f"render size {width}x{height} exceeds this GPU's limit of {limit} pixels per side")
        self.ctx = ctx
        self.size = (int(width), int(height))
        self.drawn_state = None  # the scene state of the image it holds (SceneRenderer.render)
        self.samples = max(0, min(int(samples), int(ctx.max_samples))) if samples > 1 else 0
        self.color_ms = ctx.renderbuffer(self.size, 4, samples=self.samples)
        self.depth_ms = ctx.depth_renderbuffer(self.size, samples=self.samples)
        self.fbo = ctx.framebuffer(color_attachments=[self.color_ms], depth_attachment=self.depth_ms)
        self.resolved = ctx.texture(self.size, 4)
        self.resolved.repeat_x = self.resolved.repeat_y = False
        self.resolve_fbo = ctx.framebuffer(color_attachments=[self.resolved])

    def release(self) -> None:
        for obj in (self.fbo, self.color_ms, self.depth_ms, self.resolve_fbo, self.resolved):
            obj.release()


def read_image(fbo: moderngl.Framebuffer, width: int, height: int) -> np.ndarray:
    """(H, W, 3) uint8 of ``fbo``'s first colour attachment (or the window), row 0 at the top."""
    data = fbo.read(viewport=(0, 0, width, height), components=3, alignment=1)
    return np.frombuffer(data, dtype=np.uint8).reshape(height, width, 3)[::-1].copy()


def state_token(value, depth: int = 0):
    """A hashable token that changes whenever ``value`` does (as far as drawing is concerned):
    plain values themselves, arrays their bytes, containers their items, any other object (GL
    objects, pending uploads) its identity."""
    if value is None or isinstance(value, (bool, int, float, str, bytes)):
        return value
    if isinstance(value, np.ndarray):
        return (value.shape, value.dtype.str, value.tobytes())
    if depth < 4 and isinstance(value, (tuple, list)):
        return tuple(state_token(v, depth + 1) for v in value)
    if depth < 4 and isinstance(value, dict):
        return tuple((k, state_token(v, depth + 1)) for k, v in value.items())
    return ("id", id(value))


def scene_state(objects) -> tuple:
    """The drawing state of ``objects``: every attribute of each (and of its ``lighting``), as
    :func:`state_token` sees it. Two equal states draw the same image."""
    out = []
    for obj in objects:
        items = sorted(vars(obj).items())
        out.append(tuple((k, state_token(v)) for k, v in items if k != "lighting"))
        lighting = getattr(obj, "lighting", None)
        if lighting is not None:
            out.append(tuple((k, state_token(v)) for k, v in sorted(vars(lighting).items())))
    return tuple(out)


@dataclass
class SceneStats:
    draws: int = 0
    skipped: int = 0  # render() calls that found the target already showing the same state
    last_ms: float = 0.0
    extra: dict = field(default_factory=dict)


class SceneRenderer:
    """The previewer's scene on one moderngl context: floor, body, neural layer.

    Args:
        ctx: the window's context (wrapped with ``create_context(headless=False)``) or a headless one.
        samples: MSAA samples of the window's render targets (0 or 1: none; None: 4 on a GPU, none on
            a software rasteriser such as llvmpipe, where 4x MSAA triples the frame time).
        snapshot_samples: MSAA samples of off-screen snapshots (quality over speed).
    """

    def __init__(self, ctx: moderngl.Context, samples: int | None = None, background=BACKGROUND,
                 snapshot_samples: int = 4) -> None:
        self.ctx = ctx
        self.renderer_name = str(ctx.info.get("GL_RENDERER", ""))
        if samples is None:
            samples = 0 if is_software_renderer(self.renderer_name) else 4
        self.samples = int(samples)
        self.snapshot_samples = int(snapshot_samples)
        self.background = tuple(float(x) for x in background)
        with current(ctx):
            self.floor = FloorGrid(ctx)
            self.body = BodyMesh(ctx)
            self.neural = NeuralLayer(ctx)
            self.palette_layer = PaletteLayer(ctx)
            self.present_program = build_program(ctx, "viewer_fullscreen.vert", "viewer_present.frag")
            self.present_program["u_image"].value = 0
            self.present_vao = ctx.vertex_array(self.present_program, [])
        self.renderables = [self.floor, self.body, self.neural, self.palette_layer]
        self.stats = SceneStats()
        self._released = False

    # ---- state updates (cheap; uploads happen in render) ---------------------------------------
    def set_body(self, key: object, vertex_data: np.ndarray, faces: np.ndarray, center=None) -> bool:
        """Show one body frame; ``key`` identifies it (same key: no upload). ``center`` (3,) places the
        floor's contact shadow."""
        self.body.set_topology(faces, vertex_data.shape[0])
        changed = self.body.set_frame(key, vertex_data)
        if center is not None:
            self.floor.shadow_center = np.asarray(center, dtype=np.float64)[:2].copy()
        return changed

    # ---- drawing ------------------------------------------------------------------------------------
    def make_target(self, width: int, height: int, samples: int | None = None) -> RenderTarget:
        with current(self.ctx):
            return RenderTarget(self.ctx, width, height, self.samples if samples is None else samples)

    def render(self, target: RenderTarget, camera: Camera, force: bool = False) -> bool:
        """Draw the scene as seen by ``camera`` into ``target`` (sizes must agree) and resolve it.

        Redraws only what changed: when ``target`` already holds an image of the same camera and
        the same scene state (:func:`scene_state`: every renderable's attributes, pending uploads
        included) nothing is drawn and False is returned (``force`` draws anyway)."""
        if (camera.width, camera.height) != target.size:
            raise ValueError(f"camera is {camera.width}x{camera.height} but the target is "
                             f"{target.size[0]}x{target.size[1]}")
        self.floor.center = self.floor.shadow_center  # the floor fades out around the body
        key = (state_token((camera.K, camera.R, camera.t, camera.width, camera.height)), self.background,
               scene_state(self.renderables))
        if not force and target.drawn_state == key:
            self.stats.skipped += 1
            return False
        ctx = self.ctx
        view = ViewParams.of(camera)
        with current(ctx):
            for r in self.renderables:
                r.prepare()
            target.fbo.use()
            ctx.viewport = (0, 0, *target.size)
            ctx.scissor = None
            target.fbo.depth_mask = True
            target.fbo.clear(*self.background, 1.0, depth=1.0)
            ctx.front_face = "ccw"
            ctx.depth_func = "<"
            ctx.enable_only(moderngl.BLEND)
            ctx.blend_func = moderngl.SRC_ALPHA, moderngl.ONE_MINUS_SRC_ALPHA
            self.floor.draw(view)
            ctx.enable_only(moderngl.DEPTH_TEST)
            self.body.draw(view)
            ctx.enable_only(moderngl.DEPTH_TEST | moderngl.BLEND)
            ctx.blend_func = moderngl.ONE, moderngl.ONE_MINUS_SRC_ALPHA  # premultiplied
            self.neural.draw(view)
            pl = self.palette_layer
            opaque_modes = pl.opaque or pl.side_by_side or pl.mode != "neural"
            depth_flag = moderngl.DEPTH_TEST if (pl.use_depth and pl.mode == "neural" and not pl.side_by_side) else 0
            ctx.enable_only(depth_flag | (0 if opaque_modes else moderngl.BLEND))
            ctx.blend_func = moderngl.ONE, moderngl.ONE_MINUS_SRC_ALPHA  # premultiplied
            pl.draw(view)
            ctx.enable_only(moderngl.NOTHING)
            ctx.copy_framebuffer(target.resolve_fbo, target.fbo)
        self.stats.draws += 1
        # The state before drawing: prepare() consumed the pending uploads, so the next call sees
        # another state and draws once more; a result submitted by the worker during this draw is
        # never mistaken for one already drawn.
        target.drawn_state = key
        return True

    def present(self, target: RenderTarget, screen: moderngl.Framebuffer, width: int, height: int) -> None:
        """Show ``target``'s resolved image on ``screen`` (the window), stretched to width x height."""
        ctx = self.ctx
        with current(ctx):
            screen.use()
            ctx.viewport = (0, 0, width, height)
            ctx.scissor = None
            ctx.enable_only(moderngl.NOTHING)
            same = target.size == (width, height)
            mode = moderngl.NEAREST if same else moderngl.LINEAR
            target.resolved.filter = (mode, mode)
            target.resolved.use(location=0)
            self.present_vao.render(moderngl.TRIANGLES, vertices=3)

    def read(self, target: RenderTarget) -> np.ndarray:
        """(H, W, 3) uint8 of the last :meth:`render` into ``target``, row 0 at the top."""
        with current(self.ctx):
            return read_image(target.resolve_fbo, *target.size)

    def render_image(self, camera: Camera, samples: int | None = None) -> np.ndarray:
        """Render off-screen at the camera's resolution and return (H, W, 3) uint8 (makes and frees a
        target: for snapshots and tests, not for every frame)."""
        target = self.make_target(camera.width, camera.height, samples)
        try:
            self.render(target, camera)
            return self.read(target)
        finally:
            with current(self.ctx):
                target.release()

    def release(self) -> None:
        if self._released:
            return
        self._released = True
        if is_released(self.ctx):
            return
        with current(self.ctx):
            for r in self.renderables:
                r.release()
            self.present_vao.release()
            self.present_program.release()
