"""Ground-truth images of a body dressed in a simulated garment: shaded RGB and per-pixel labels.

Conventions (what every consumer of these images relies on)
    Background
        **Black** ``(0, 0, 0)`` by default. The paper's palette decoder composes a pixel as
        ``c = m * r * (...)``: a zero mask gives black, so black ground truth needs no extra
        compositing term. The RGB is the box-filtered average of the subsamples over the
        background, i.e. premultiplied by the coverage ``alpha`` (:class:`GroundTruthImage`):
        ``rgb_on_white = rgb + (1 - alpha) * 1`` composites the same image over white exactly
        (for a black background). PSNR/SSIM are to be computed on the black composite.
    Anti-aliasing
        Supersampling: the scene is rendered at ``supersample`` (default 2) times the camera's
        resolution with the camera from :meth:`Camera.scaled` (so a 512 x 512 camera renders at
        1024 x 1024, as in the paper) and reduced by an ``s x s`` box filter (plain mean).
    Labels
        0 background, 1 body, 2 + k garment layer k (2 for a one-layer garment; the dress's inner
        skirt is 2, its outer tier 3), decided from the same ``s x s`` subsamples: a pixel is
        foreground when at least half of its subsamples are (coverage >= 0.5); a foreground
        pixel is garment when at least as many subsamples see the garment, all layers together, as
        the body (ties go to the garment), and its layer is the one most of those see (ties go to
        the outer layer). :func:`garment_pixels` is the garment of a label map, every layer.
        With ``supersample=1`` the label is the surface at the pixel centre,
        identical to :class:`~garmentnerf.gl.camera_pass.CameraPass` on the combined mesh; with
        s = 2 labels can differ from that pixel-centre reference only on pixels where the
        reference itself changes label within one pixel (silhouettes and body/garment borders).
    Lighting (fixed in the world, so all cameras see the same diffuse radiance)
        Hemispheric ambient (sky from +Z, ground from -Z) + a key directional light from the
        front, above, slightly from the character's right + a weaker fill from the back-left +
        a small Blinn-Phong specular lobe of the key light (the only view-dependent term).
        Per-vertex smooth normals are recomputed every frame on the CPU (area-weighted sums of
        face normals), which is what makes folds and wrinkles visible. Two-sided: a
        back-facing triangle (the inside of the garment, seen at the hem) is lit with its
        normal flipped toward the viewer and its color scaled by ``inside`` (default 0.7, an
        ambient-occlusion-like darkening). Meshes must wind counter-clockwise seen from outside
        (the body asset's and SMPL's winding); a garment wound the other way is shaded as if
        seen from inside. Colors are display values in [0, 1] (no gamma handling), clamped.
    Depth test, no face culling; the body is drawn before the garment (on exactly equal depth the
    body wins, as in one CameraPass draw of body faces followed by garment faces).
    Deterministic: the same inputs give identical bytes (fixed draw order, exact CPU reductions).

:data:`RENDERER_VERSION` names the image formation; scene caches key on it together with
:meth:`GroundTruthRenderer.settings` so a change of either re-renders stale images.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import asdict, dataclass

import moderngl
import numpy as np
import scipy.sparse as sp

from garmentnerf.conventions import Camera
from garmentnerf.gl.context import current
from garmentnerf.gl.mesh_arrays import check_mesh_arrays
from garmentnerf.gl.resources import GLObjectsOwner, SupersampleTargets, TargetCache
from garmentnerf.gl.shaders import build_program

#: Bump when the image formation changes (shaders, normals, filtering, label policy).
RENDERER_VERSION = "gt-2"  # gt-2: a layer label per garment layer

LABEL_BACKGROUND = 0
LABEL_BODY = 1
LABEL_GARMENT = 2
#: Garment layers the labels tell apart (labels LABEL_GARMENT .. LABEL_GARMENT + MAX_GARMENT_LAYERS - 1).
MAX_GARMENT_LAYERS = 2


def garment_pixels(labels: np.ndarray) -> np.ndarray:
    """(H, W) bool: the garment pixels of a label map, every layer."""
    return np.asarray(labels) >= LABEL_GARMENT


def face_layers(faces: np.ndarray, vertex_layer: np.ndarray | None) -> np.ndarray:
    """(F,) int layer of each face: the outermost layer of its vertices (0 for ``vertex_layer`` None)."""
    faces = np.asarray(faces)
    if vertex_layer is None:
        return np.zeros(len(faces), dtype=np.int64)
    return np.asarray(vertex_layer, dtype=np.int64)[faces].max(axis=1)

#: Default body color: a light skin tone (display RGB in [0, 1]).
SKIN_TONE = (0.80, 0.63, 0.53)
#: Default background (see the module docstring).
BACKGROUND = (0.0, 0.0, 0.0)


def _unit(v) -> tuple[float, float, float]:
    a = np.asarray(v, dtype=np.float64)
    return tuple(float(x) for x in a / np.linalg.norm(a))


@dataclass(frozen=True)
class Lighting:
    """The fixed world-space light rig. Directions point *toward* the lights.

    The key light comes from the front (-Y), above, slightly from the character's right (-X);
    the fill from behind (+Y), the character's left (+X), lower.
    """

    key_direction: tuple[float, float, float] = _unit((-0.35, -0.8, 0.75))
    key_intensity: float = 0.68
    fill_direction: tuple[float, float, float] = _unit((0.55, 0.7, 0.3))
    fill_intensity: float = 0.40
    sky: tuple[float, float, float] = (0.30, 0.30, 0.32)
    ground: tuple[float, float, float] = (0.12, 0.11, 0.10)
    specular: float = 0.10
    shininess: float = 32.0
    inside: float = 0.7

    def to_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}


@dataclass
class GroundTruthImage:
    """What :meth:`GroundTruthRenderer.render_full` returns.

    Attributes:
        rgb: (H, W, 3) float32 in [0, 1], composited over the renderer's background.
        labels: (H, W) uint8, 0 background / 1 body / 2 + k garment layer k (policy in the module docstring).
        alpha: (H, W) float32 coverage, the fraction of subsamples that see a surface.
        garment_coverage: (H, W) float32 fraction of subsamples that see the garment.
    """

    rgb: np.ndarray
    labels: np.ndarray
    alpha: np.ndarray
    garment_coverage: np.ndarray


def renderer_settings(supersample: int = 2, background=BACKGROUND, lighting: "Lighting | None" = None) -> dict:
    """Everything besides geometry, camera and colors that determines a render (cache keys use it).

    :meth:`GroundTruthRenderer.settings` returns this for the renderer's own settings; with the
    defaults it describes a default renderer without needing a GL context.
    """
    return {"version": RENDERER_VERSION, "supersample": int(supersample),
            "background": [float(x) for x in background], "lighting": (lighting or Lighting()).to_dict()}


# ---- geometry helpers -----------------------------------------------------------------------------
def _check_mesh(vertices, faces, what: str) -> tuple[np.ndarray, np.ndarray]:
    verts, tris = check_mesh_arrays(vertices, faces, what)
    if not np.all(np.isfinite(verts)):
        raise ValueError(f"{what} vertices contain NaN or Inf")
    if len(verts) >= 2**31:
        raise ValueError(f"{what}: too many vertices for 32-bit indices")
    return verts, tris


def _check_color(color, what: str) -> tuple[float, float, float]:
    c = np.asarray(color, dtype=np.float64).reshape(-1)
    if c.shape != (3,) or not np.all(np.isfinite(c)) or c.min() < 0.0 or c.max() > 1.0:
        raise ValueError(f"{what} must be 3 numbers in [0, 1], got {color!r}")
    return tuple(float(x) for x in c)


class _NormalOperator:
    """Sparse (V, F) incidence: vertex normal = sum of the (area-weighted) normals of its faces."""

    def __init__(self, faces: np.ndarray, num_vertices: int) -> None:
        F = len(faces)
        rows = faces.reshape(-1)
        cols = np.repeat(np.arange(F), 3)
        self.matrix = sp.csr_matrix((np.ones(3 * F), (rows, cols)), shape=(num_vertices, F))
        self.faces = faces

    def __call__(self, vertices: np.ndarray) -> np.ndarray:
        v = vertices.astype(np.float64)
        f = self.faces
        face_normals = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])  # |.| = 2 area
        n = self.matrix @ face_normals
        length = np.linalg.norm(n, axis=1, keepdims=True)
        ok = length[:, 0] > 1e-20
        n[ok] /= length[ok]
        n[~ok] = (0.0, 0.0, 1.0)  # isolated or fully degenerate vertices
        return n


def vertex_normals(vertices, faces) -> np.ndarray:
    """(V, 3) float64 unit area-weighted vertex normals (the sum of face cross products).

    Vertices in no face (or only in degenerate ones) get +Z.
    """
    verts, tris = _check_mesh(vertices, faces, "mesh")
    return _NormalOperator(tris, len(verts))(verts)


# ---- GL objects -----------------------------------------------------------------------------------
class _MeshBuffers:
    """Interleaved (position, normal) float32 vertex buffer + int32 index buffer, grown on demand."""

    def __init__(self, ctx: moderngl.Context, program: moderngl.Program) -> None:
        self.ctx = ctx
        self.program = program
        self.vbo: moderngl.Buffer | None = None
        self.ibo: moderngl.Buffer | None = None
        self.vao: moderngl.VertexArray | None = None
        self.count = 0

    def upload(self, interleaved: np.ndarray, indices: np.ndarray) -> None:
        if (self.vbo is None or self.vbo.size < interleaved.nbytes or self.ibo.size < indices.nbytes):
            self.release()
            self.vbo = self.ctx.buffer(reserve=max(2 * interleaved.nbytes, 64), dynamic=True)
            self.ibo = self.ctx.buffer(reserve=max(2 * indices.nbytes, 64), dynamic=True)
            self.vao = self.ctx.vertex_array(self.program, [(self.vbo, "3f 3f", "in_position", "in_normal")],
                                             index_buffer=self.ibo, index_element_size=4)
        self.vbo.write(interleaved)
        self.ibo.write(indices)
        self.count = indices.size

    def release(self) -> None:
        for obj in (self.vao, self.vbo, self.ibo):
            if obj is not None:
                obj.release()
        self.vao = self.vbo = self.ibo = None


class GroundTruthRenderer(GLObjectsOwner):
    """Shaded ground-truth renders of a body and (optionally) a garment on one moderngl context.

    Args:
        ctx: a context from :func:`garmentnerf.gl.context.create_context`; made current by every
            call and left current.
        supersample: render at this integer factor of the camera resolution, then box-filter (1..15).
        background: RGB in [0, 1] (default black; see the module docstring).
        lighting: the light rig (:class:`Lighting`).
    """

    def __init__(self, ctx: moderngl.Context, supersample: int = 2, background=BACKGROUND,
                 lighting: Lighting | None = None, max_sizes: int = 2) -> None:
        if (isinstance(supersample, bool) or not isinstance(supersample, (int, np.integer))
                or not 1 <= supersample <= 15):
            # at most 15: the resolve counts each label's subsamples in 8 bits
            raise ValueError(f"supersample must be an integer in [1, 15], got {supersample!r}")
        self.ctx = ctx
        self.supersample = int(supersample)
        self.background = _check_color(background, "background")
        self.lighting = lighting or Lighting()
        self.max_sizes = max(1, int(max_sizes))
        with current(ctx):
            self.program = build_program(ctx, "gt_shaded.vert", "gt_shaded.frag")
            self.resolve_program = build_program(ctx, "fullscreen_triangle.vert", "gt_resolve.frag")
            self.resolve_program["u_factor"].value = self.supersample
            self.resolve_program["u_source"].value = 0
            self.resolve_vao = ctx.vertex_array(self.resolve_program, [])
            self._meshes = {"body": _MeshBuffers(ctx, self.program), "garment": _MeshBuffers(ctx, self.program)}
        self._targets: TargetCache[SupersampleTargets] = TargetCache(
            lambda size: SupersampleTargets(ctx, *size, self.supersample), self.max_sizes)
        self._normal_ops: OrderedDict[tuple, _NormalOperator] = OrderedDict()
        self._released = False
        self._set_lighting()

    # ---- settings ---------------------------------------------------------------------------------
    def settings(self) -> dict:
        """Everything that determines the pixels besides the geometry, camera and colors."""
        return renderer_settings(self.supersample, self.background, self.lighting)

    def _set_lighting(self) -> None:
        L = self.lighting
        with current(self.ctx):
            p = self.program
            p["u_light_dir"].value = [tuple(_unit(L.key_direction)), tuple(_unit(L.fill_direction))]
            p["u_light_intensity"].value = [float(L.key_intensity), float(L.fill_intensity)]
            p["u_sky"].value = tuple(float(x) for x in L.sky)
            p["u_ground"].value = tuple(float(x) for x in L.ground)
            p["u_specular"].value = float(L.specular)
            p["u_shininess"].value = float(L.shininess)
            p["u_inside"].value = float(L.inside)

    # ---- helpers ----------------------------------------------------------------------------------
    def _normals(self, verts: np.ndarray, tris: np.ndarray) -> np.ndarray:
        key = (len(verts), tris.shape, hash(tris.tobytes()))
        op = self._normal_ops.get(key)
        if op is None:
            op = _NormalOperator(tris, len(verts))
            self._normal_ops[key] = op
            while len(self._normal_ops) > 4:
                self._normal_ops.popitem(last=False)
        else:
            self._normal_ops.move_to_end(key)
        return op(verts)

    def _targets_for(self, width: int, height: int) -> SupersampleTargets:
        return self._targets.get((width, height))

    def _upload(self, name: str, verts: np.ndarray, tris: np.ndarray) -> None:
        normals = self._normals(verts, tris)
        interleaved = np.empty((len(verts), 6), dtype=np.float32)
        interleaved[:, :3] = verts
        interleaved[:, 3:] = normals
        self._meshes[name].upload(interleaved, tris.astype(np.int32))

    # ---- rendering --------------------------------------------------------------------------------
    def render(self, body_vertices, body_faces, garment_vertices=None, garment_faces=None, garment_color=None,
               camera: Camera | None = None, body_color=SKIN_TONE,
               garment_layer=None) -> tuple[np.ndarray, np.ndarray]:
        """Render one view: ``(rgb (H, W, 3) float32 in [0, 1], labels (H, W) uint8)``.

        Args:
            body_vertices, body_faces: (V, 3) world positions (metres), (F, 3) indices.
            garment_vertices, garment_faces: (Vg, 3), (Fg, 3), or None for the body alone.
            garment_color: RGB in [0, 1] (required with a garment).
            camera: the view; the output has its resolution.
            body_color: RGB in [0, 1].
            garment_layer: (Vg,) layer of each garment vertex (labels ``2 + layer``; a face takes
                the outermost of its vertices'), at most :data:`MAX_GARMENT_LAYERS` layers; None: one layer.
        """
        out = self.render_full(body_vertices, body_faces, garment_vertices, garment_faces, garment_color,
                               camera, body_color, garment_layer)
        return out.rgb, out.labels

    def render_full(self, body_vertices, body_faces, garment_vertices=None, garment_faces=None,
                    garment_color=None, camera: Camera | None = None, body_color=SKIN_TONE,
                    garment_layer=None) -> GroundTruthImage:
        """:meth:`render` plus coverage maps (:class:`GroundTruthImage`)."""
        self._check_not_released()
        if not isinstance(camera, Camera):
            raise TypeError(f"camera must be a conventions.Camera, got {type(camera).__name__}")
        bverts, btris = _check_mesh(body_vertices, body_faces, "body")
        body_rgb = _check_color(body_color, "body_color")
        meshes = [("body", bverts, btris, body_rgb, [(LABEL_BODY, 0, len(btris))])]
        if garment_vertices is not None:
            if garment_faces is None or garment_color is None:
                raise ValueError("a garment needs garment_faces and garment_color")
            gverts, gtris = _check_mesh(garment_vertices, garment_faces, "garment")
            if garment_layer is not None and np.shape(garment_layer) != (len(gverts),):
                raise ValueError(f"garment_layer must have shape ({len(gverts)},), got {np.shape(garment_layer)}")
            layers = face_layers(gtris, garment_layer)
            if len(layers) and (layers.min() < 0 or layers.max() >= MAX_GARMENT_LAYERS):
                raise ValueError(f"garment layers must lie in [0, {MAX_GARMENT_LAYERS}), "
                                 f"got [{layers.min()}, {layers.max()}]")
            order = np.argsort(layers, kind="stable")  # each layer's faces one range, drawn inner first
            gtris = gtris[order]
            counts = np.bincount(layers, minlength=MAX_GARMENT_LAYERS)
            starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
            ranges = [(LABEL_GARMENT + k, int(starts[k]), int(counts[k])) for k in range(MAX_GARMENT_LAYERS)]
            meshes.append(("garment", gverts, gtris, _check_color(garment_color, "garment_color"), ranges))

        s = self.supersample
        big = camera.scaled(s) if s > 1 else camera
        with current(self.ctx):
            for name, verts, tris, _, _ in meshes:
                self._upload(name, verts, tris)
            p = self.program
            p["u_view"].write(big.world_to_camera().T.astype(np.float32).tobytes())
            p["u_proj"].write(big.gl_projection().T.astype(np.float32).tobytes())
            p["u_camera_center"].value = tuple(float(x) for x in big.center)
            targets = self._targets_for(camera.width, camera.height)
            with targets.scope:
                old_front = self.ctx.front_face
                try:
                    # The y flip of gl_projection mirrors the winding: faces CCW seen from outside are
                    # CW in window coordinates, so make CW the front for gl_FrontFacing.
                    self.ctx.front_face = "cw"
                    self.ctx.depth_func = "<"
                    targets.fbo.depth_mask = True
                    targets.fbo.clear(*self.background, 0.0, depth=1.0)
                    for name, _, _, rgb, ranges in meshes:
                        p["u_base_color"].value = rgb
                        for label, first, count in ranges:
                            if count == 0:
                                continue
                            p["u_label"].value = float(label)
                            self._meshes[name].vao.render(moderngl.TRIANGLES, vertices=3 * count, first=3 * first)
                finally:
                    self.ctx.front_face = old_front
            with targets.resolve_scope:
                targets.color.use(location=0)
                self.resolve_vao.render(moderngl.TRIANGLES, vertices=3)
                targets.resolve_fbo.read_into(targets.buffer, attachment=0, components=4, dtype="f4")
            return _unpack(targets.buffer, s)

    def _release_objects(self) -> None:
        self._targets.release()
        for mesh in self._meshes.values():
            mesh.release()
        self.resolve_vao.release()
        self.resolve_program.release()
        self.program.release()


def _unpack(resolved: np.ndarray, s: int) -> GroundTruthImage:
    """(H, W, 4) resolved target (mean rgb, n_body + 256 n_layer0 + 65536 n_layer1) -> image,
    labels, coverages."""
    counts = np.rint(resolved[..., 3]).astype(np.int32)
    n_outer = counts >> 16
    n_inner = (counts >> 8) & 255
    n_garment = n_inner + n_outer
    n_body = counts & 255
    n_fg = n_body + n_garment
    labels = np.zeros(counts.shape, dtype=np.uint8)
    fg = 2 * n_fg >= s * s
    labels[fg] = LABEL_BODY
    garment = fg & (n_garment >= n_body)
    labels[garment] = LABEL_GARMENT
    labels[garment & (n_outer >= n_inner)] = LABEL_GARMENT + 1  # a garment pixel has n_inner + n_outer >= 1
    n = float(s * s)
    return GroundTruthImage(np.clip(resolved[..., :3], 0.0, 1.0), labels,
                            (n_fg / n).astype(np.float32), (n_garment / n).astype(np.float32))


def to_uint8(rgb: np.ndarray) -> np.ndarray:
    """float [0, 1] -> uint8 with rounding (how scene caches store images)."""
    return np.clip(np.rint(np.asarray(rgb, dtype=np.float64) * 255.0), 0, 255).astype(np.uint8)
