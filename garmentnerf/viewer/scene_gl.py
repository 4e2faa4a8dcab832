"""The scene renderer: owns the GL passes that draw the previewer's renderables into a target.

Pipeline
    Every view (the window, a GL snapshot, a test's headless reference) is drawn by
    :meth:`SceneRenderer.render` into a :class:`RenderTarget` (multisampled color + depth, resolved
    into a texture): clear to the background, then one pass per renderable in this order: floor
    (blended over the background, no depth test), body (opaque, depth tested), baked layer
    (:class:`~garmentnerf.viewer.baked_layer.BakedLayer`: a baked frame's garment from this camera,
    blended over the body), neural layer
    (:class:`~garmentnerf.viewer.palette_layer.PaletteLayer`: the network's maps composed with the
    palette; blended by its mask, optionally depth tested against the body, or opaque in the
    ground-truth/difference/maps modes), camera path (:class:`~garmentnerf.viewer.renderables.LineSet`:
    lines, depth tested against the body). Before each pass the renderer sets the *whole* GL state
    the renderable declares (:class:`~garmentnerf.viewer.renderables.PassState`), so no pass
    inherits another's flags. The window then shows the resolved texture with
    :meth:`SceneRenderer.present` and draws imgui on top. Because the window and a snapshot of the
    same size go through the same code, they match bit for bit. How renderables are oriented and
    what they own: :mod:`~garmentnerf.viewer.renderables`.

Redraws
    A target remembers the state it was drawn with (:func:`scene_state`: the camera, the free area
    and every attribute of every renderable, pending uploads included); :meth:`SceneRenderer.render`
    redraws only when that state changed, so a still view reuses its image and leaves the CPU to the
    render worker.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass

import moderngl
import numpy as np

from garmentnerf.conventions import Camera
from garmentnerf.gl.context import current, is_released, make_current
from garmentnerf.gl.shaders import build_program
from garmentnerf.viewer.baked_layer import BakedLayer
from garmentnerf.viewer.palette_layer import PaletteLayer, pack_maps
from garmentnerf.viewer.renderables import FULL_VIEW, BodyMesh, FloorGrid, LineSet, PassState, ViewParams

# The renderables' names, for callers that know the scene by this module (tests/render/test_render.py).
__all__ = ["SceneRenderer", "RenderTarget", "SceneContent", "SceneStats", "read_image", "scene_state", "state_token",
           "is_software_renderer", "BACKGROUND", "BodyMesh", "FloorGrid", "PaletteLayer", "ViewParams", "pack_maps"]

#: Window/snapshot background (display RGB).
BACKGROUND = (0.155, 0.165, 0.185)
#: Lowest render scale of the window's scene (fraction of the framebuffer size).
MIN_RENDER_SCALE = 0.25
#: Window targets kept (one per size): the still view's and the moving view's
#: (:class:`~garmentnerf.viewer.quality.SceneScale`), so switching between them reallocates nothing.
WINDOW_TARGETS = 2
#: Renderer names (substrings, lower case) of software rasterisers, where MSAA costs too much.
SOFTWARE_RENDERERS = ("llvmpipe", "softpipe", "swrast", "software", "swiftshader")


def is_software_renderer(name: str) -> bool:
    """Whether a GL_RENDERER string names a CPU rasteriser."""
    low = name.lower()
    return any(s in low for s in SOFTWARE_RENDERERS)


class RenderTarget:
    """Multisampled color + depth renderbuffers and the single-sample texture they resolve into (without
    multisampling the depth is a texture: the baked layer tests the garment against the body drawn there)."""

    def __init__(self, ctx: moderngl.Context, width: int, height: int, samples: int = 4) -> None:
        if width < 1 or height < 1:
            raise ValueError(f"render target size must be positive, got {width}x{height}")
        limit = int(ctx.info.get("GL_MAX_RENDERBUFFER_SIZE", 16384))
        if width > limit or height > limit:
            raise ValueError(f"render size {width}x{height} exceeds this GPU's limit of {limit} pixels per side")
        self.ctx = ctx
        self.size = (int(width), int(height))
        self.drawn_state = None  # the scene state of the image it holds (SceneRenderer.render)
        self.content = SceneContent()  # what that image shows
        self.samples = max(0, min(int(samples), int(ctx.max_samples))) if samples > 1 else 0
        self.color_ms = ctx.renderbuffer(self.size, 4, samples=self.samples)
        if self.samples:
            self.depth_ms = ctx.depth_renderbuffer(self.size, samples=self.samples)
        else:  # single-sampled: a texture, which the baked layer reads as the body's depth
            self.depth_ms = ctx.depth_texture(self.size)
            self.depth_ms.compare_func = ""
            self.depth_ms.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self.fbo = ctx.framebuffer(color_attachments=[self.color_ms], depth_attachment=self.depth_ms)
        self.resolved = ctx.texture(self.size, 4)
        self.resolved.repeat_x = self.resolved.repeat_y = False
        self.resolve_fbo = ctx.framebuffer(color_attachments=[self.resolved])

    def release(self) -> None:
        for obj in (self.fbo, self.color_ms, self.depth_ms, self.resolve_fbo, self.resolved):
            obj.release()


def read_image(fbo: moderngl.Framebuffer, width: int, height: int) -> np.ndarray:
    """(H, W, 3) uint8 of ``fbo``'s first color attachment (or the window), row 0 at the top."""
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


@dataclass(frozen=True)
class SceneContent:
    """What an image of the scene shows: the body (rasterised, or in the neural image, which carries
    it) and the neural garment (the network's image in the layer)."""

    body: bool = False
    garment: bool = False


@dataclass
class SceneStats:
    """draws: :meth:`SceneRenderer.render` calls that drew; skipped: those that found the target
    already showing the same state."""

    draws: int = 0
    skipped: int = 0


class SceneRenderer:
    """The previewer's scene on one moderngl context: floor, body, neural layer, camera path (in drawing order).

    Args:
        ctx: the window's context (wrapped with ``create_context(headless=False)``) or a headless one.
        samples: MSAA samples of the window's render targets (0 or 1: none; None: 4 on a GPU, none on
            a software rasteriser such as llvmpipe, where 4x MSAA triples the frame time).
        snapshot_samples: MSAA samples of off-screen snapshots (quality over speed).
        render_scale: the window's scene renders at this fraction of the framebuffer size (see
            :meth:`set_render_scale`); snapshots ignore it.
    """

    def __init__(self, ctx: moderngl.Context, samples: int | None = None, background=BACKGROUND,
                 snapshot_samples: int = 4, render_scale: float = 1.0) -> None:
        self.ctx = ctx
        make_current(ctx)  # moderngl reads (and caches) ctx.info from whichever context is current
        self.renderer_name = str(ctx.info.get("GL_RENDERER", ""))
        if samples is None:
            samples = 0 if is_software_renderer(self.renderer_name) else 4
        self.samples = int(samples)
        self.snapshot_samples = int(snapshot_samples)
        self.background = tuple(float(x) for x in background)
        self.render_scale = 1.0
        self.set_render_scale(render_scale)
        with current(ctx):
            self.floor = FloorGrid(ctx)
            self.body = BodyMesh(ctx)
            self.baked_layer = BakedLayer(ctx)
            self.palette_layer = PaletteLayer(ctx)
            self.path_lines = LineSet(ctx)
            self.present_program = build_program(ctx, "viewer_fullscreen.vert", "viewer_present.frag")
            self.present_program["u_image"].value = 0
            self.present_vao = ctx.vertex_array(self.present_program, [])
        self.renderables = [self.floor, self.body, self.baked_layer, self.palette_layer, self.path_lines]
        self.stats = SceneStats()
        self._window_targets: OrderedDict[tuple[int, int], RenderTarget] = OrderedDict()
        self._released = False

    # ---- state updates (cheap; uploads happen in render) ---------------------------------------
    def set_body(self, key: object, vertex_data: np.ndarray, faces: np.ndarray, center=None) -> bool:
        """Show one body frame ((V, 6) position + normal); ``key`` identifies it (same key: no upload).
        ``center`` (3,) places the floor's contact shadow."""
        self.body.set_topology(faces, vertex_data.shape[0])
        changed = self.body.set_frame(key, vertex_data)
        self.baked_layer.set_body(key, vertex_data, faces)
        if center is not None:
            self.floor.shadow_center = np.asarray(center, dtype=np.float64)[:2].copy()
        return changed

    # ---- drawing ------------------------------------------------------------------------------------
    def make_target(self, width: int, height: int, samples: int | None = None) -> RenderTarget:
        with current(self.ctx):
            return RenderTarget(self.ctx, width, height, self.samples if samples is None else samples)

    def set_render_scale(self, scale: float) -> None:
        """Render the window's scene at this fraction of the framebuffer size, clamped to
        [:data:`MIN_RENDER_SCALE`, 1] (lower is faster on a software rasteriser; the image is stretched)."""
        scale = float(scale)
        if not math.isfinite(scale):
            raise ValueError(f"render scale must be a number in [{MIN_RENDER_SCALE}, 1], got {scale!r}")
        self.render_scale = min(1.0, max(MIN_RENDER_SCALE, scale))

    def render_size(self, framebuffer_size: tuple[int, int]) -> tuple[int, int]:
        """(W, H) of the window's render target: the framebuffer size times :attr:`render_scale`."""
        w, h = framebuffer_size
        return max(1, round(w * self.render_scale)), max(1, round(h * self.render_scale))

    def window_target(self, width: int, height: int) -> RenderTarget:
        """The window's render target (``samples``) at this size: the last :data:`WINDOW_TARGETS`
        sizes are kept (the still and the moving scale), older ones freed; all freed with the
        renderer."""
        target = self._window_targets.pop((width, height), None)
        if target is None:
            target = self.make_target(width, height)
        self._window_targets[(width, height)] = target  # the newest last
        while len(self._window_targets) > WINDOW_TARGETS:
            _, old = self._window_targets.popitem(last=False)
            with current(self.ctx):
                old.release()
        return target

    def render(self, target: RenderTarget, camera: Camera, force: bool = False, free_area=FULL_VIEW) -> bool:
        """Draw the scene as seen by ``camera`` into ``target`` (sizes must agree) and resolve it.

        ``free_area``: NDC (x0, y0, x1, y1) the window's panels leave free (see
        :class:`~garmentnerf.viewer.renderables.ViewParams`). Redraws only what changed: when
        ``target`` already holds an image of the same camera, free area and scene state
        (:func:`scene_state`) nothing is drawn and False is returned (``force`` draws anyway)."""
        if (camera.width, camera.height) != target.size:
            raise ValueError(f"camera is {camera.width}x{camera.height} but the target is "
                             f"{target.size[0]}x{target.size[1]}")
        self.floor.center = self.floor.shadow_center  # the floor fades out around the body
        view = ViewParams.of(camera, free_area)
        key = (state_token((camera.K, camera.R, camera.t, camera.width, camera.height, view.free_area)),
               self.background, scene_state(self.renderables))
        if not force and target.drawn_state == key:
            self.stats.skipped += 1
            return False
        ctx = self.ctx
        with current(ctx):
            for r in self.renderables:
                r.prepare(view)
            layer = self.palette_layer
            garment = (layer.visible and layer.has_image) or self.baked_layer.showing
            content = SceneContent(body=self.body.drawn or garment, garment=garment)
            target.fbo.use()
            ctx.viewport = (0, 0, *target.size)
            ctx.scissor = None
            target.fbo.depth_mask = True
            target.fbo.clear(*self.background, 1.0, depth=1.0)
            for r in self.renderables:
                self._set_pass_state(r.pass_state())
                r.draw(view)
            ctx.enable_only(moderngl.NOTHING)
            ctx.copy_framebuffer(target.resolve_fbo, target.fbo)
        self.stats.draws += 1
        # The state before drawing: prepare() consumed the pending uploads, so the next call sees
        # another state and draws once more; a result submitted by the worker during this draw is
        # never mistaken for one already drawn.
        target.drawn_state = key
        target.content = content
        return True

    def _set_pass_state(self, state: PassState) -> None:
        """The whole GL state of one pass (nothing is inherited from the previous pass)."""
        ctx = self.ctx
        ctx.enable_only(state.flags)
        ctx.blend_func = state.blend_func
        ctx.depth_func = "<"
        ctx.front_face = "ccw"

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
            for target in self._window_targets.values():
                target.release()
            self._window_targets.clear()
            for r in self.renderables:
                r.release()
            self.present_vao.release()
            self.present_program.release()
