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
    body (opaque, depth tested), neural layer (blended, its own per-pixel depth). The window then
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


@dataclass
class SceneStats:
    draws: int = 0
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
            self.present_program = build_program(ctx, "viewer_fullscreen.vert", "viewer_present.frag")
            self.present_program["u_image"].value = 0
            self.present_vao = ctx.vertex_array(self.present_program, [])
        self.renderables = [self.floor, self.body, self.neural]
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

    def render(self, target: RenderTarget, camera: Camera) -> None:
        """Draw the scene as seen by ``camera`` into ``target`` (sizes must agree) and resolve it."""
        if (camera.width, camera.height) != target.size:
            raise ValueError(f"camera is {camera.width}x{camera.height} but the target is "
                             f"{target.size[0]}x{target.size[1]}")
        ctx = self.ctx
        view = ViewParams.of(camera)
        self.floor.center = self.floor.shadow_center  # the floor fades out around the body
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
            ctx.enable_only(moderngl.NOTHING)
            ctx.copy_framebuffer(target.resolve_fbo, target.fbo)
        self.stats.draws += 1

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
