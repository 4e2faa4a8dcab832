"""What the scene is made of: renderables that own their GL objects, their pass state and their panel.

Orientation (read this before touching projections)
    :meth:`garmentnerf.conventions.Camera.gl_projection` puts image row 0 at framebuffer row 0, which
    is right for read-back passes but upside down on a screen (GL's row 0 is the *bottom* of a
    window). The viewer therefore draws with :func:`display_projection`, the same matrix with the
    y flip undone: image row 0 is at the top of the window, triangles wound counter-clockwise seen
    from outside stay counter-clockwise on screen (GL's default front face), and a framebuffer
    read back with ``glReadPixels`` is upside down: :func:`~garmentnerf.viewer.scene_gl.read_image`
    flips it so every image this package returns is in the conventions' layout (row 0 at the top,
    pixel (u, v) of ``Camera.K`` at column u, row v).

A renderable's lifecycle (as aitviewer's scene nodes)
    It builds its GL objects in ``__init__`` on the renderer's context, uploads lazily in
    ``prepare(view)`` when something is pending (and may draw into its own targets there: the
    renderer binds its framebuffer after every ``prepare``), declares the GL state of its pass in ``pass_state()``
    (the renderer sets exactly that state before ``draw()``; a renderable never touches GL flags
    itself), draws in ``draw(view)``, frees everything in ``release()``, and draws its own panel
    rows in ``gui(imgui)`` (the imgui module is handed in: this module imports no window library).
    Nothing is cached at module level, so any number of contexts can each own renderables.
"""

from __future__ import annotations

from dataclasses import dataclass

import moderngl
import numpy as np

from garmentnerf.conventions import Camera
from garmentnerf.gl.shaders import build_program

#: Body color (display RGB): the ground-truth renderer's skin tone.
BODY_COLOR = (0.80, 0.63, 0.53)
#: The whole view in normalised device coordinates (x0, y0, x1, y1).
FULL_VIEW = (-1.0, -1.0, 1.0, 1.0)

_Y_FLIP = np.diag([1.0, -1.0, 1.0, 1.0])


def display_projection(camera: Camera) -> np.ndarray:
    """(4, 4) OpenCV camera -> GL clip with image row 0 at the *top* of the viewport (see module doc)."""
    return _Y_FLIP @ camera.gl_projection()


def mat4_bytes(m: np.ndarray) -> bytes:
    """Column-major float32 bytes of a (4, 4) matrix, as GLSL mat4 uniforms want."""
    return np.ascontiguousarray(np.asarray(m, dtype=np.float64).T, dtype=np.float32).tobytes()


@dataclass(frozen=True)
class ViewParams:
    """What a renderable needs to know about the view.

    Attributes:
        camera: the view's camera (its size is the viewport's).
        view: (4, 4) world -> OpenCV camera; proj: (4, 4) display projection.
        free_area: NDC (x0, y0, x1, y1) of the part of the view the window's panels leave free
            (:data:`FULL_VIEW` off-screen); image layers that sit beside each other are fitted into it.
    """

    camera: Camera
    view: np.ndarray
    proj: np.ndarray
    free_area: tuple[float, float, float, float] = FULL_VIEW

    @staticmethod
    def of(camera: Camera, free_area=FULL_VIEW) -> "ViewParams":
        return ViewParams(camera, camera.world_to_camera(), display_projection(camera),
                          tuple(float(v) for v in free_area))


@dataclass(frozen=True)
class PassState:
    """The GL state of one pass, set whole by the renderer before the pass draws.

    Attributes:
        flags: moderngl enable bits (``DEPTH_TEST``, ``BLEND``); everything else is disabled.
        blend_func: (source, destination) factors when ``BLEND`` is on.
    """

    flags: int
    blend_func: tuple[int, int] = (moderngl.ONE, moderngl.ONE_MINUS_SRC_ALPHA)

    @staticmethod
    def of(depth_test: bool, blend: bool, premultiplied: bool = True) -> "PassState":
        flags = (moderngl.DEPTH_TEST if depth_test else 0) | (moderngl.BLEND if blend else 0)
        source = moderngl.ONE if premultiplied else moderngl.SRC_ALPHA
        return PassState(flags, (source, moderngl.ONE_MINUS_SRC_ALPHA))


#: Opaque surfaces, depth tested.
OPAQUE = PassState.of(depth_test=True, blend=False)
#: Straight-alpha blending over what is drawn, no depth test (and so no depth writes).
BLENDED_OVER = PassState.of(depth_test=False, blend=True, premultiplied=False)


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


class BodyMesh:
    """The posed body: one dynamic (position, normal) vertex buffer, re-uploaded only when the shown
    frame (its ``key``) changes; a static index buffer, replaced when the topology changes."""

    def __init__(self, ctx: moderngl.Context, lighting: StudioLighting | None = None) -> None:
        self.ctx = ctx
        self.lighting = lighting or StudioLighting()
        self.color = BODY_COLOR
        self.visible = True
        self.standin = False        # drawn even when not visible: the neural layer has no image yet
        self.learned = False        # draw in the learned appearance (set_appearance), when there is one
        self.tint = BODY_COLOR      # ... times this colour: the body's palette colour
        self.program = build_program(ctx, "viewer_mesh.vert", "viewer_mesh.frag")
        self._appearance = _Held()  # (uv, uv_faces, appearance) of set_appearance, or None (a new holder each)
        self._look: LearnedLook | None = None  # its GL objects (made in prepare)
        self._look_stale = False    # the appearance or the topology changed: make the look again
        self._shown = _Held()       # the vertex data of the shown frame (the look uploads it too)
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

    def set_topology(self, faces: np.ndarray, num_vertices: int) -> None:
        """Use these (F, 3) triangles (a no-op when they are the ones in use)."""
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
        self._look_stale = True

    def set_appearance(self, uv, uv_faces, appearance) -> None:
        """The body's atlas ``uv`` (Nuv, 2) and ``uv_faces`` (F, 3, rows of the topology's faces) and
        a run's :class:`~garmentnerf.model.body_appearance.BodyAppearance` (None: none): drawn when
        :attr:`learned` is set (as the ``raster_body`` composition shades the body, times
        :attr:`tint`), else the studio material. Read on the GL thread."""
        self._appearance = _Held(None if appearance is None else (
            np.asarray(uv, dtype=np.float32), np.asarray(uv_faces, dtype=np.int64), appearance))
        self._look_stale = True

    @property
    def has_appearance(self) -> bool:
        """Whether a learned appearance is set (:meth:`set_appearance`)."""
        return self._appearance.value is not None

    def set_frame(self, key: object, vertex_data: np.ndarray) -> bool:
        """Show ``vertex_data`` (V, 6) float32 [position, normal]; a no-op when ``key`` is the shown key.
        Returns whether an upload was scheduled."""
        if key is not None and key == self.key and self._pending is None:
            return False
        if vertex_data.shape != (self.num_vertices, 6):
            raise ValueError(f"body frame must be ({self.num_vertices}, 6), got {vertex_data.shape}")
        self._pending = np.ascontiguousarray(vertex_data, dtype=np.float32)
        self._shown.value = self._pending
        self.key = key
        return True

    def prepare(self, view: ViewParams | None = None) -> None:
        self._prepare_mesh()
        if not self.learned:
            return  # the look is made and filled only while it is drawn
        if self._look_stale and self._pending_faces is None:
            self._make_look()
        if self._look is not None and self._look.key != self.key and self._shown.value is not None:
            self._look.upload(self.key, self._shown.value)

    def _make_look(self) -> None:
        """(Re)make the learned look's GL objects for the current topology and appearance."""
        self._look_stale = False
        if self._look is not None:
            self._look.release()
            self._look = None
        if self._appearance.value is None or self._faces is None:
            return
        uv, uv_faces, appearance = self._appearance.value
        if uv_faces.shape != np.shape(self._faces):
            return  # another mesh than the appearance's: the studio material
        self._look = LearnedLook(self.ctx, np.asarray(self._faces), uv, uv_faces, appearance)

    def _prepare_mesh(self) -> None:
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

    def pass_state(self) -> PassState:
        return OPAQUE

    @property
    def drawn(self) -> bool:
        """Whether :meth:`draw` draws anything (shown, and a frame uploaded)."""
        return (self.visible or self.standin) and self.vao is not None and self.key is not None and self.index_count > 0

    def draw(self, view: ViewParams) -> None:
        if not self.drawn:
            return
        if self.learned and self._look is not None and self._look.key == self.key:
            self._look.draw(view, self.tint)
            return
        p, L = self.program, self.lighting
        p["u_view"].write(mat4_bytes(view.view))
        p["u_proj"].write(mat4_bytes(view.proj))
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

    def gui(self, imgui) -> None:
        """Display panel row: the body on / off."""
        _, self.visible = imgui.checkbox("Body", self.visible)

    def _release_buffers(self) -> None:
        for obj in (self.vao, self.vbo, self.ibo):
            if obj is not None:
                obj.release()
        self.vao = self.vbo = self.ibo = None
        self.index_count = 0

    def release(self) -> None:
        self._release_buffers()
        if self._look is not None:
            self._look.release()
            self._look = None
        self.program.release()


class _Held:
    """A reference whose identity stays while its value changes (the scene's state sees the identity)."""

    __slots__ = ("value",)

    def __init__(self, value=None) -> None:
        self.value = value


#: Most shading monomials the learned look evaluates (``shaders/viewer_body_learned.vert``'s MAX_TERMS;
#: degree 4 has 35).
MAX_SHADING_TERMS = 64


class LearnedLook:
    """The body in a run's learned appearance, as the scene pass draws it (:class:`BodyMesh` owns one).

    The atlas has seams: a body vertex may carry several UVs. The mesh is drawn with one vertex per
    (body vertex, UV) pair of the faces (a few more vertices than the body's), whose position and
    normal are gathered from the body's frame at each upload; the UVs and the triangles are static.
    Shaded by ``shaders/viewer_body_learned.{vert,frag}`` (the appearance times the body's palette colour).
    """

    def __init__(self, ctx: moderngl.Context, faces: np.ndarray, uv: np.ndarray, uv_faces: np.ndarray,
                 appearance) -> None:
        from garmentnerf.body.shading import monomial_exponents  # lazy: torch, only with an appearance

        faces = np.asarray(faces, dtype=np.int64)
        pairs = faces.reshape(-1) * len(uv) + np.asarray(uv_faces, dtype=np.int64).reshape(-1)
        unique, inverse = np.unique(pairs, return_inverse=True)
        self.source = unique // len(uv)               # (Vs,) the body vertex of each drawn vertex
        split_uv = np.ascontiguousarray(uv[unique % len(uv)], dtype=np.float32)
        triangles = np.ascontiguousarray(inverse.reshape(-1), dtype=np.int32)
        self.ctx = ctx
        self.key: object = None
        exponents = np.asarray(monomial_exponents(int(appearance.degree)), dtype=np.int32).reshape(-1, 3)
        shading = appearance.shading.detach().to("cpu").float().numpy().reshape(-1, 3)
        if len(exponents) > MAX_SHADING_TERMS or shading.shape != exponents.shape:
            raise ValueError(f"a body appearance of {len(shading)} shading terms (degree {appearance.degree}) "
                             f"does not fit the viewer's {MAX_SHADING_TERMS}")
        self.program = build_program(ctx, "viewer_body_learned.vert", "viewer_body_learned.frag")
        self.program["u_albedo"].value = 0
        self.program["u_terms"].value = len(exponents)
        padded = np.zeros((MAX_SHADING_TERMS, 3), np.float32)
        padded[:len(shading)] = shading
        self.program["u_shading"].write(padded.tobytes())
        padded_e = np.zeros((MAX_SHADING_TERMS, 3), np.int32)
        padded_e[:len(exponents)] = exponents
        self.program["u_exponents"].write(padded_e.tobytes())
        albedo = appearance.albedo.detach().to("cpu").float().permute(1, 2, 0).numpy()  # (T, T, 3), row 0: v = 0
        self.albedo = ctx.texture((albedo.shape[1], albedo.shape[0]), 3, np.ascontiguousarray(albedo).tobytes(),
                                  dtype="f4")
        self.albedo.filter = (moderngl.LINEAR, moderngl.LINEAR)
        self.albedo.repeat_x = self.albedo.repeat_y = False
        self.vbo = ctx.buffer(reserve=max(len(self.source) * 24, 24), dynamic=True)
        self.uv_vbo = ctx.buffer(split_uv.tobytes() or b"\0" * 8)
        self.ibo = ctx.buffer(triangles.tobytes() or b"\0" * 4)
        self.index_count = int(triangles.size)
        self.vao = ctx.vertex_array(self.program, [(self.vbo, "3f 3f", "in_position", "in_normal"),
                                                   (self.uv_vbo, "2f", "in_uv")],
                                    index_buffer=self.ibo, index_element_size=4)

    def upload(self, key: object, vertex_data: np.ndarray) -> None:
        """The body's frame ``vertex_data`` (V, 6) [position, normal], gathered per drawn vertex."""
        self.vbo.write(np.ascontiguousarray(np.take(vertex_data, self.source, axis=0), dtype=np.float32))
        self.key = key

    def draw(self, view: ViewParams, tint) -> None:
        p = self.program
        p["u_view"].write(mat4_bytes(view.view))
        p["u_proj"].write(mat4_bytes(view.proj))
        p["u_tint"].value = tuple(float(x) for x in tint)
        self.albedo.use(location=0)
        self.vao.render(moderngl.TRIANGLES, vertices=self.index_count)

    def release(self) -> None:
        for obj in (self.vao, self.vbo, self.uv_vbo, self.ibo, self.albedo, self.program):
            obj.release()


class LineSet:
    """Coloured line segments in the world (the camera path and its keyframe cameras): one vertex
    buffer, re-uploaded only when :meth:`set_lines` gets a new ``key``; depth tested, so the body hides
    what is behind it."""

    def __init__(self, ctx: moderngl.Context) -> None:
        self.ctx = ctx
        self.visible = True
        self.program = build_program(ctx, "viewer_lines.vert", "viewer_lines.frag")
        self.vbo: moderngl.Buffer | None = None
        self.vao: moderngl.VertexArray | None = None
        self.vertex_count = 0
        self.key: object = None
        self._pending: np.ndarray | None = None

    def set_lines(self, key: object, positions: np.ndarray, colors: np.ndarray) -> bool:
        """Show segments from ``positions`` (2N, 3) (each pair a segment) in ``colors`` (2N, 3); a
        no-op when ``key`` is the shown key. Returns whether an upload was scheduled."""
        if key is not None and key == self.key:
            return False
        positions = np.asarray(positions, dtype=np.float32).reshape(-1, 3)
        colors = np.asarray(colors, dtype=np.float32).reshape(-1, 3)
        if len(positions) % 2 or colors.shape != positions.shape:
            raise ValueError(f"line positions must be (2N, 3) with a colour each, got {positions.shape} and "
                             f"{colors.shape}")
        self._pending = np.ascontiguousarray(np.concatenate([positions, colors], axis=1))
        self.key = key
        return True

    def prepare(self, view: ViewParams | None = None) -> None:
        if self._pending is None:
            return
        data, self._pending = self._pending, None
        if self.vbo is None or self.vbo.size < max(data.nbytes, 24):
            self._release_buffers()
            self.vbo = self.ctx.buffer(reserve=max(data.nbytes, 24), dynamic=True)
            self.vao = self.ctx.vertex_array(self.program, [(self.vbo, "3f 3f", "in_position", "in_color")])
        if data.nbytes:
            self.vbo.write(data.tobytes())
        self.vertex_count = len(data)

    def pass_state(self) -> PassState:
        return OPAQUE

    def draw(self, view: ViewParams) -> None:
        if not self.visible or self.vao is None or self.vertex_count == 0:
            return
        self.program["u_view"].write(mat4_bytes(view.view))
        self.program["u_proj"].write(mat4_bytes(view.proj))
        self.vao.render(moderngl.LINES, vertices=self.vertex_count)

    def gui(self, imgui) -> None:
        pass  # the camera-path panel switches it

    def _release_buffers(self) -> None:
        for obj in (self.vao, self.vbo):
            if obj is not None:
                obj.release()
        self.vao = self.vbo = None

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

    def prepare(self, view: ViewParams | None = None) -> None:
        pass  # nothing to upload: the quad is made in the vertex shader

    def pass_state(self) -> PassState:
        return BLENDED_OVER  # over the cleared background, under everything else

    def draw(self, view: ViewParams) -> None:
        if not self.visible:
            return
        p = self.program
        below = view.camera.center[2] < 0.0
        p["u_view"].write(mat4_bytes(view.view))
        p["u_proj"].write(mat4_bytes(view.proj))
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

    def gui(self, imgui) -> None:
        """Display panel row: the floor and its grid lines on / off."""
        _, self.visible = imgui.checkbox("Floor", self.visible)
        imgui.same_line()
        _, self.show_lines = imgui.checkbox("Grid lines (G)", self.show_lines)

    def release(self) -> None:
        self.vao.release()
        self.program.release()
