"""The neural layer: the network's decomposed maps composed with the palette on the GPU.

:class:`PaletteLayer` holds the maps of the newest neural render as textures and composes them with
the palette in ``shaders/viewer_palette.frag`` (the formula of
:func:`garmentnerf.model.palette.compose`): recoloring changes a uniform and re-renders nothing.
It also shows the ground truth, their difference and the raw maps (:data:`PALETTE_MODES`).

How it is drawn is decided once per draw, by :meth:`PaletteLayer.composition`: the same
:class:`Composition` gives the GL state of its pass (blended by its mask over the scene, optionally
depth tested against the body; or opaque) and the shader's uniforms, so the two cannot disagree.

The body layer (the ``raster_body`` composition) is not uploaded with the maps: a result brings
the posed body (:class:`BodyView`) and :meth:`PaletteLayer.prepare` draws it with the run's body
appearance (:class:`~garmentnerf.gl.body_layer_pass.BodyLayerPass`, 2 x 2 supersampled) at the
size the layer is shown at, in the result's camera. So the body is as sharp as the view, costs the
render worker nothing, and is redrawn only when a result or the shown size changes.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import moderngl
import numpy as np

from garmentnerf.conventions import Camera
from garmentnerf.gl.body_layer_pass import BodyLayerPass
from garmentnerf.gl.shaders import build_program
from garmentnerf.render.body_layer import BODY_LAYER_SUPERSAMPLE
from garmentnerf.viewer.renderables import PassState, ViewParams

#: View modes of the palette layer (what the neural layer shows).
PALETTE_MODES = {"neural": 0, "ground_truth": 1, "difference": 2, "maps": 3}
#: Modes that need the ground-truth image (until it arrives the network's image is drawn).
NEEDS_GROUND_TRUTH = ("ground_truth", "difference")
#: What the ``maps`` mode shows.
MAP_VIEWS = ("mask", "weights", "radiance")
#: Most palette colors the shader handles.
MAX_PALETTE = 4
#: The maps' textures grow in steps of this many texels (and never shrink): the maps of a clip's
#: frames differ in size by a few pixels, and a new texture costs a clear of all of it.
MAP_CAPACITY_STEP = 64


@dataclass(frozen=True)
class BodyView:
    """The body of one neural result, for the layer to draw: ``vertices`` and unit vertex
    ``normals`` (V, 3) float32 of the posed body, seen by ``camera`` (the result's; the layer draws
    it resized to the size it is shown at)."""

    vertices: np.ndarray
    normals: np.ndarray
    camera: Camera


def pack_maps(radiance: np.ndarray, offsets: np.ndarray, weights: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Decomposed maps (batch dimension dropped, rows top-first) -> (2 + P, H, W, 4) float32
    layers for ``shaders/viewer_palette.frag``: [radiance rgb + mask], [weights], [offset_i rgb + 0] ...

    Args:
        radiance: (3 or 1, H, W); offsets: (P, 3, H, W); weights: (P, H, W); mask: (1, H, W) or (H, W).
    """
    radiance = np.asarray(radiance, dtype=np.float32)
    offsets = np.asarray(offsets, dtype=np.float32)
    weights = np.asarray(weights, dtype=np.float32)
    mask = np.asarray(mask, dtype=np.float32).reshape(-1, *weights.shape[-2:])[0]
    P, H, W = weights.shape
    if not 1 <= P <= MAX_PALETTE:
        raise ValueError(f"the viewer's palette shader handles 1..{MAX_PALETTE} colors, got {P}")
    if offsets.shape != (P, 3, H, W) or radiance.shape[1:] != (H, W) or radiance.shape[0] not in (1, 3):
        raise ValueError(f"maps disagree: radiance {radiance.shape}, offsets {offsets.shape}, weights {weights.shape}")
    out = np.zeros((2 + P, H, W, 4), dtype=np.float32)
    out[0, ..., :3] = np.broadcast_to(radiance, (3, H, W)).transpose(1, 2, 0)
    out[0, ..., 3] = mask
    out[1, ..., :P] = weights.transpose(1, 2, 0)
    out[2:2 + P, ..., :3] = offsets.transpose(0, 2, 3, 1)
    return out


def empty_texels(layers: int) -> np.ndarray:
    """(L, 4) float32: what the layers of :func:`pack_maps` hold where the maps are empty
    (:meth:`~garmentnerf.model.palette.DecomposedMaps.placed`: mask, radiance and offsets 0, the
    ``P = L - 2`` blend weights uniform)."""
    P = layers - 2
    out = np.zeros((layers, 4), np.float32)
    out[1, :P] = np.float32(1.0) / np.float32(P)
    return out


def uncovered(old: tuple[int, int, int, int] | None, new: tuple[int, int, int, int]) -> list[tuple[int, int, int, int]]:
    """The parts of rectangle ``old`` (x, y, w, h) outside rectangle ``new``: at most four
    rectangles (the rows above and below ``new``, then the columns beside it), none when ``old``
    is None or inside ``new``."""
    if old is None:
        return []
    ox0, oy0, ox1, oy1 = old[0], old[1], old[0] + old[2], old[1] + old[3]
    nx0, ny0, nx1, ny1 = new[0], new[1], new[0] + new[2], new[1] + new[3]
    parts = []
    top, bottom = min(oy1, max(oy0, ny0)), max(oy0, min(oy1, ny1))  # old's rows beside new: [top, bottom)
    if top > oy0:
        parts.append((ox0, oy0, ox1 - ox0, top - oy0))
    if oy1 > bottom:
        parts.append((ox0, bottom, ox1 - ox0, oy1 - bottom))
    if bottom > top:
        left, right = min(ox1, max(ox0, nx0)), max(ox0, min(ox1, nx1))
        if left > ox0:
            parts.append((ox0, top, left - ox0, bottom - top))
        if ox1 > right:
            parts.append((right, top, ox1 - right, bottom - top))
    return [p for p in parts if p[2] > 0 and p[3] > 0]


def filled_quad(rect: tuple[float, float, float, float], filled: tuple[int, int, int, int] | None,
                map_size: tuple[int, int]) -> tuple[tuple[float, float, float, float], tuple[float, float, float, float]]:
    """The part of the NDC ``rect`` (x0, y0, x1, y1; the whole maps, rows top-first) that can show
    anything: the texels ``filled`` (x, y, w, h; None: all) grown by one texel (the bilinear
    footprint), as (NDC rect, the quad's v_uv rect (u0, v0, u1, v1), v up). Blended over the scene,
    empty maps add nothing, so drawing only this part shows the same image with fewer fragments."""
    W, H = map_size
    if filled is None:
        return rect, (0.0, 0.0, 1.0, 1.0)
    fx, fy, fw, fh = filled
    tx0, tx1 = max(0, fx - 1), min(W, fx + fw + 1)
    ty0, ty1 = max(0, fy - 1), min(H, fy + fh + 1)
    if tx1 <= tx0 or ty1 <= ty0:
        return rect, (0.0, 0.0, 1.0, 1.0)
    u0, u1, v0, v1 = tx0 / W, tx1 / W, 1.0 - ty1 / H, 1.0 - ty0 / H
    x0, y0, x1, y1 = rect
    return ((x0 + u0 * (x1 - x0), y0 + v0 * (y1 - y0), x0 + u1 * (x1 - x0), y0 + v1 * (y1 - y0)),
            (u0, v0, u1, v1))


def crop_to_content(layers: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    """Maps packed by :func:`pack_maps` and their depth, cut to the smallest rectangle outside which
    the maps are empty (:func:`empty_texels`) and the depth 0: the character's rectangle of a culled
    preset (everything else is empty).

    Returns:
        (layers (2 + P, h', w', 4), depth (h', w'), (x0, y0)): copies of the rectangle and its top-left
        pixel; a 1 x 1 rectangle at (0, 0) when everything is empty. :meth:`PaletteLayer.submit` with
        ``origin=(x0, y0)`` and the full size shows exactly what the uncut maps show.
    """
    empty = empty_texels(layers.shape[0])[:, None, None, :]
    filled = np.any(layers != empty, axis=(0, 3)) | (depth != 0)
    rows, cols = np.flatnonzero(filled.any(axis=1)), np.flatnonzero(filled.any(axis=0))
    if rows.size == 0:
        return layers[:, :1, :1].copy(), depth[:1, :1].copy(), (0, 0)
    y0, y1, x0, x1 = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
    return layers[:, y0:y1, x0:x1].copy(), depth[y0:y1, x0:x1].copy(), (x0, y0)


def pack_frame(maps) -> np.ndarray:
    """:func:`pack_maps` of a :class:`~garmentnerf.model.palette.DecomposedMaps` (batch 1, CPU;
    a body layer attached to it is not packed: the layer draws its own, :class:`BodyView`)."""
    return pack_maps(maps.radiance[0].numpy(), maps.offsets[0].numpy(), maps.weights[0].numpy(),
                     maps.mask[0].numpy())


def fit_rect(area: tuple[float, float, float, float], vw: float, vh: float,
             size: tuple[int, int] | None) -> tuple[float, float, float, float]:
    """NDC rect of an image of ``size`` (W, H) fitted (aspect kept, centred) into the NDC rect
    ``area`` (x0, y0, x1, y1) of a ``vw`` x ``vh`` pixel viewport; ``area`` itself when ``size`` is None."""
    if size is None:
        return area
    x0, y0, x1, y1 = area
    s = min(vw * (x1 - x0) / 2.0 / size[0], vh * (y1 - y0) / 2.0 / size[1])
    hw, hh = size[0] * s / vw, size[1] * s / vh  # half extents in NDC units (2 * px / (2 * v))
    cx, cy = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
    return (cx - hw, cy - hh, cx + hw, cy + hh)


@dataclass(frozen=True)
class Composition:
    """How the layer is drawn this frame (see :meth:`PaletteLayer.composition`).

    Attributes:
        mode: the :data:`PALETTE_MODES` key drawn (the network's image until the ground truth arrives).
        side_by_side: the network's image and the ground truth beside each other.
        opaque: the layer covers its rectangles, composed over the layer's background; otherwise it is
            blended (premultiplied) over the scene by its mask.
        use_depth: depth tested against the rasterised body with the network's depth.
    """

    mode: str
    side_by_side: bool
    opaque: bool
    use_depth: bool

    def pass_state(self) -> PassState:
        return PassState.of(depth_test=self.use_depth, blend=not self.opaque)


@dataclass
class _PaletteMaps:
    layers: np.ndarray          # (2 + P, h, w, 4) float32, see pack_maps
    depth: np.ndarray           # (h, w) float32 camera-space z, 0 where empty
    image_size: tuple[int, int]  # (W, H) of the camera the maps belong to (its aspect is kept)
    tag: object = None
    body: BodyView | None = None  # the body to draw under the garment (the raster_body composition)
    origin: tuple[int, int] = (0, 0)        # top-left pixel of ``layers`` in the full maps
    map_size: tuple[int, int] | None = None  # (w, h) of the full maps (None: the size of ``layers``)


def _texture(ctx: moderngl.Context, size: tuple[int, int], components: int, dtype: str, filter_: int,
             **kwargs) -> moderngl.Texture:
    """A clamped (not repeating) texture with ``filter_`` for minification and magnification."""
    tex = ctx.texture(size, components, dtype=dtype, **kwargs)
    tex.filter = (filter_, filter_)
    tex.repeat_x = tex.repeat_y = False
    return tex


class PaletteLayer:
    """The neural render as decomposed maps, composed with the palette in a fragment shader.

    Thread contract: :meth:`submit` / :meth:`submit_ground_truth` from any thread (numpy only),
    uploads (and the body layer's draw) in :meth:`prepare` on the GL thread. :meth:`set_palette`
    only sets a uniform: recoloring costs nothing.

    Attributes:
        mode: key of :data:`PALETTE_MODES`; side_by_side: draw the neural image and the ground truth
            next to each other (each fitted into half of the view's free area).
        map_view: what ``maps`` mode shows (:data:`MAP_VIEWS`).
        use_depth: write the network's depth (composite with the rasterised body by depth); off:
            drawn over everything by its mask.
        moving: the view is changing (the window draws its scene smaller meanwhile): the body layer
            is drawn without supersampling (a quarter of the fragments: a playing clip shows a new
            body every frame), and supersampled again once the view is still.
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
        for name, unit in (("u_maps", 0), ("u_gt", 1), ("u_depth", 2), ("u_body", 3)):
            self.program[name].value = unit
        self.vao = ctx.vertex_array(self.program, [])
        self.maps_tex: moderngl.TextureArray | None = None
        self.depth_tex: moderngl.Texture | None = None
        self.gt_tex: moderngl.Texture | None = None
        self.image_size: tuple[int, int] | None = None
        self.map_size: tuple[int, int] | None = None  # (w, h) of the maps shown (the textures may be larger)
        self.tag: object = None
        self.body: BodyView | None = None     # the shown result's body (None: no body layer)
        self.body_draws = 0                   # body layers drawn so far (tests: a still view draws none)
        self._body_model = None               # (faces, uv, uv_faces, appearance) of set_body_model
        self._body_pass = None                # the BodyLayerPass, made at the first body
        self._body_tex: moderngl.Texture | None = None  # the pass's texture of the shown body
        self._body_key: tuple | None = None   # (BodyView, size, supersample) the texture holds
        self.moving = False                   # the view changes (drawn smaller): the body layer is not supersampled
        self.uploads = 0
        self._filled: tuple[int, int, int, int] | None = None  # (x, y, w, h) of the textures possibly not empty
        self._lock = threading.Lock()
        self._pending: _PaletteMaps | None = None
        self._pending_gt: np.ndarray | None = None
        self._clear_gt = False

    @property
    def has_image(self) -> bool:
        return self.maps_tex is not None

    @property
    def arriving(self) -> bool:
        """Whether submitted maps wait for the next draw (which uploads and shows them)."""
        with self._lock:
            return self._pending is not None

    @property
    def has_ground_truth(self) -> bool:
        return self.gt_tex is not None

    @property
    def has_body(self) -> bool:
        """Whether the shown result composes over a drawn body layer."""
        return self.body is not None

    @property
    def palette_size(self) -> int:
        return 0 if self.maps_tex is None else self.maps_tex.layers - 2

    # ---- inputs (any thread) ---------------------------------------------------------------------
    def set_palette(self, palette) -> None:
        """(P, 3) colors in [0, 1] (a uniform; takes effect at the next draw)."""
        pal = np.asarray(palette, dtype=np.float32).reshape(-1, 3)
        if not 1 <= pal.shape[0] <= MAX_PALETTE or not np.all(np.isfinite(pal)):
            raise ValueError(f"palette must be (P, 3) finite with 1 <= P <= {MAX_PALETTE}, got {pal.shape}")
        self.palette = np.clip(pal, 0.0, 1.0)

    def set_body_model(self, body, appearance) -> None:
        """The body a :class:`BodyView` poses (its ``faces``, atlas ``uv`` and ``uv_faces``) and the
        run's :class:`~garmentnerf.model.body_appearance.BodyAppearance`, read on the GL thread."""
        self._body_model = (np.asarray(body.faces), np.asarray(body.uv, dtype=np.float32),
                            np.asarray(body.uv_faces), appearance)
        self._body_key = None

    def submit(self, layers: np.ndarray, depth: np.ndarray, image_size: tuple[int, int], tag: object = None,
               body: BodyView | None = None, origin: tuple[int, int] = (0, 0),
               map_size: tuple[int, int] | None = None) -> None:
        """Queue maps packed by :func:`pack_maps` (float32, or float16: uploaded to half-float textures)
        with their depth (h, w) and the output size (W, H); ``body``: the result's body, drawn under
        the garment (needs :meth:`set_body_model`). A rectangle cut by :func:`crop_to_content` is
        passed with its ``origin`` (x0, y0) in the full maps of ``map_size`` (w, h): only it is
        uploaded (the rest of the textures is set to :func:`empty_texels`)."""
        layers = np.ascontiguousarray(layers)
        if layers.dtype not in (np.float16, np.float32):
            layers = layers.astype(np.float32)
        depth = np.ascontiguousarray(np.nan_to_num(np.asarray(depth, dtype=np.float32), nan=0.0))
        if layers.ndim != 4 or layers.shape[-1] != 4 or layers.shape[0] < 3 or depth.shape != layers.shape[1:3]:
            raise ValueError(f"palette layer needs (2 + P, h, w, 4) maps and (h, w) depth, got {layers.shape} "
                             f"and {depth.shape}")
        if body is not None and (layers.shape[0] < 4 or self._body_model is None):
            raise ValueError("a body layer needs a garment and a body color and set_body_model() first")
        h, w = depth.shape
        full = (w, h) if map_size is None else (int(map_size[0]), int(map_size[1]))
        x0, y0 = int(origin[0]), int(origin[1])
        if x0 < 0 or y0 < 0 or x0 + w > full[0] or y0 + h > full[1]:
            raise ValueError(f"a {w}x{h} rectangle at ({x0}, {y0}) does not fit maps of {full[0]}x{full[1]}")
        item = _PaletteMaps(layers, depth, (int(image_size[0]), int(image_size[1])), tag, body, (x0, y0), full)
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

    # ---- GL thread -------------------------------------------------------------------------------
    def prepare(self, view: ViewParams | None = None) -> None:
        """Upload what was submitted; with ``view``, draw the body layer at the size the layer is
        shown at in it (when that or the body changed)."""
        self._upload()
        if view is not None and self.visible and self.body is not None and self.maps_tex is not None:
            self._draw_body(view)

    def _upload(self) -> None:
        with self._lock:
            item, self._pending = self._pending, None
            gt, self._pending_gt = self._pending_gt, None
            clear_gt, self._clear_gt = self._clear_gt, False
        if self.gt_tex is not None and (clear_gt or (gt is not None and self.gt_tex.size != gt.shape[1::-1])):
            self.gt_tex.release()
            self.gt_tex = None
        if gt is not None:
            if self.gt_tex is None:
                self.gt_tex = _texture(self.ctx, gt.shape[1::-1], 3, "f1", moderngl.LINEAR, alignment=1)
            self.gt_tex.write(gt)
        if item is None:
            return
        L, h, w, _ = item.layers.shape
        W, H = item.map_size
        dtype = "f2" if item.layers.dtype == np.float16 else "f4"
        tex = self.maps_tex
        if tex is None or tex.layers != L or tex.dtype != dtype or tex.width < W or tex.height < H:
            # grown, never shrunk: the maps of a clip's frames differ in size by a few pixels
            cap = (max(W, tex.width if tex is not None else 0), max(H, tex.height if tex is not None else 0))
            cap = (-(-cap[0] // MAP_CAPACITY_STEP) * MAP_CAPACITY_STEP, -(-cap[1] // MAP_CAPACITY_STEP) * MAP_CAPACITY_STEP)
            self._release_maps()
            self.maps_tex = self.ctx.texture_array((*cap, L), 4, dtype=dtype)
            self.maps_tex.filter = (moderngl.LINEAR, moderngl.LINEAR)
            self.maps_tex.repeat_x = self.maps_tex.repeat_y = False
            self.depth_tex = _texture(self.ctx, cap, 1, "f4", moderngl.NEAREST)
            self._filled = (0, 0, *cap)  # new textures: contents undefined
        self.map_size = (W, H)
        rect = (*item.origin, w, h)
        empty = empty_texels(L).astype(item.layers.dtype)[:, None, None, :]
        for x, y, sw, sh in uncovered(self._filled, rect):  # what the new maps do not cover: empty
            self.maps_tex.write(np.ascontiguousarray(np.broadcast_to(empty, (L, sh, sw, 4))), viewport=(x, y, 0, sw, sh, L))
            self.depth_tex.write(np.zeros((sh, sw), np.float32), viewport=(x, y, sw, sh))
        self.maps_tex.write(item.layers, viewport=(*item.origin, 0, w, h, L))
        self.depth_tex.write(item.depth, viewport=rect)
        self._filled = rect
        self.image_size = item.image_size
        self.tag = item.tag
        self.body = item.body
        self.uploads += 1

    def _draw_body(self, view: ViewParams) -> None:
        x0, y0, x1, y1 = self._rects(view, self.composition())[0][1]
        size = (max(1, round((x1 - x0) * 0.5 * view.camera.width)),
                max(1, round((y1 - y0) * 0.5 * view.camera.height)))
        supersample = 1 if self.moving else BODY_LAYER_SUPERSAMPLE
        key = self._body_key
        if key is not None and key[0] is self.body and key[1:] == (size, supersample):
            return
        if self._body_pass is None:
            self._body_pass = BodyLayerPass(self.ctx, max_sizes=2)
        faces, uv, uv_faces, appearance = self._body_model
        self._body_tex = self._body_pass.draw(self.body.vertices, self.body.normals, faces, uv, uv_faces,
                                              self.body.camera.resized(*size), appearance, supersample)
        self._body_tex.filter = (moderngl.LINEAR, moderngl.LINEAR)
        self._body_tex.repeat_x = self._body_tex.repeat_y = False
        self._body_key = (self.body, size, supersample)
        self.body_draws += 1

    def composition(self) -> Composition:
        """How to draw now: the requested mode, or the network's image while a mode that needs the
        ground truth has none; opaque in every mode but the plain neural one (and when :attr:`opaque`);
        depth tested only in the plain neural mode with :attr:`use_depth`."""
        waiting = self.gt_tex is None and (self.side_by_side or self.mode in NEEDS_GROUND_TRUTH)
        mode = "neural" if waiting and self.mode in NEEDS_GROUND_TRUTH else self.mode
        plain = self.mode == "neural" and not self.side_by_side
        return Composition(mode, self.side_by_side and not waiting, opaque=bool(self.opaque) or not plain,
                           use_depth=bool(self.use_depth) and plain)

    def pass_state(self) -> PassState:
        return self.composition().pass_state()

    def draw(self, view: ViewParams) -> None:
        if not self.visible or self.maps_tex is None:
            return
        how = self.composition()
        self.maps_tex.use(location=0)
        if self.gt_tex is not None:
            self.gt_tex.use(location=1)
        self.depth_tex.use(location=2)
        with_body = self.has_body and self._body_tex is not None  # drawn by prepare(view)
        if with_body:
            self._body_tex.use(location=3)
        for mode, rect in self._rects(view, how):
            uv_rect = (0.0, 0.0, 1.0, 1.0)
            if mode == "neural" and not how.opaque and not how.side_by_side:
                rect, uv_rect = filled_quad(rect, self._filled, self.map_size)
            self._draw_rect(view, how, mode, rect, with_body, uv_rect)

    def _rects(self, view: ViewParams, how: Composition) -> list[tuple[str, tuple[float, float, float, float]]]:
        """(mode, NDC rect) of each image drawn: the neural one first."""
        vw, vh = float(view.camera.width), float(view.camera.height)
        if how.side_by_side:
            x0, y0, x1, y1 = view.free_area
            middle = 0.5 * (x0 + x1)
            left = "neural" if how.mode == "ground_truth" else how.mode
            return [(left, fit_rect((x0, y0, middle, y1), vw, vh, self.image_size)),
                    ("ground_truth", fit_rect((middle, y0, x1, y1), vw, vh, self.image_size))]
        return [(how.mode, fit_rect((-1.0, -1.0, 1.0, 1.0), vw, vh, self.image_size))]

    def _draw_rect(self, view: ViewParams, how: Composition, mode: str, rect, with_body: bool,
                   uv_rect=(0.0, 0.0, 1.0, 1.0)) -> None:
        p = self.program
        pal = np.zeros((MAX_PALETTE, 3), dtype=np.float32)
        n = min(self.palette.shape[0], MAX_PALETTE)
        pal[:n] = self.palette[:n]
        p["u_palette"].write(pal.tobytes())
        p["u_palette_size"].value = int(min(n, self.palette_size))
        p["u_has_body"].value = int(with_body)
        p["u_background"].value = tuple(float(c) for c in self.background)
        p["u_opaque"].value = int(how.opaque)
        p["u_mode"].value = PALETTE_MODES[mode]
        p["u_map"].value = MAP_VIEWS.index(self.map_view)
        p["u_diff_gain"].value = float(self.diff_gain)
        p["u_opacity"].value = float(self.opacity)
        p["u_use_depth"].value = int(how.use_depth)
        p["u_depth_bias"].value = float(self.depth_bias)
        p["u_near"].value = float(view.camera.near)
        p["u_far"].value = float(view.camera.far)
        p["u_rect"].value = tuple(float(v) for v in rect)
        p["u_uv_rect"].value = tuple(float(v) for v in uv_rect)
        cw, ch = self.maps_tex.width, self.maps_tex.height
        p["u_map_extent"].value = (self.map_size[0] / cw, self.map_size[1] / ch)
        p["u_map_half_texel"].value = (0.5 / cw, 0.5 / ch)
        self.vao.render(moderngl.TRIANGLE_STRIP, vertices=4)

    def _release_maps(self) -> None:
        for tex in (self.maps_tex, self.depth_tex):
            if tex is not None:
                tex.release()
        self.maps_tex = self.depth_tex = None

    def release(self) -> None:
        self._release_maps()
        if self._body_pass is not None:
            self._body_pass.release()
            self._body_pass = self._body_tex = None
        if self.gt_tex is not None:
            self.gt_tex.release()
            self.gt_tex = None
        self.vao.release()
        self.program.release()
