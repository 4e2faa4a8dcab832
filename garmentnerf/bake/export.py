"""A bake as glTF 2.0: the body and the garment of each baked frame, animated, at one palette.

One garment mesh a frame (:func:`garment_mesh`)
    A baked frame holds K view surfaces (:func:`~garmentnerf.bake.views.view_mesh`) that overlap: each
    neighbouring pair of captures sees much of the same cloth, a few millimetres apart. Drawn together in
    a player they would z-fight and double every colour; the previewer blends them per pixel in GL, which
    a glTF file cannot ask of a player. So each part of the cloth is kept from one view only, its *best
    view*: the one whose direction from the triangle (its centroid towards the camera's centre) is most
    aligned with the cloth's normal there, among the views that captured that point (it projects onto their
    surface, within :data:`~garmentnerf.bake.views.DEPTH_JUMP` of its depth, where their garment is
    visible); the owning view always counts. The normal is the mean of those views' normals at the point,
    each of its surface smoothed by :data:`NORMAL_SMOOTHING`: a triangle's own normal turns by tens of
    degrees from pixel to pixel, and each view's surface leans towards its own camera (two neighbouring
    views' normals of one point differ by a median 30 degrees on the skirt demo), so with its own normals
    every view would call itself best and half of all triangles would stay. The partition leaves one layer of cloth. The views' surfaces
    disagree by millimetres to centimetres, so two views decide a seam a little apart; a triangle whose best
    view keeps none of its own triangles there stays, so a seam overlaps by a triangle or two rather than
    cracks (on the skirt demo about one triangle in four kept is such a filler). A view whose camera does not
    see a point cannot claim it, so the partition leaves no hole where the most aligned camera was blocked.

Colours
    Each vertex carries the garment's colour at the palette, ``c_G = clamp(r * sum_i w_i (p_i + o_i), 0, 1)``
    over the garment colours i, from its view's layers at the vertex (``shaders/bake_blend.frag``, mode 0:
    the hybrid composition of :func:`garmentnerf.model.palette.compose`), and the garment's visibility
    ``a`` as alpha. Triangles whose three vertices all have ``a`` under :data:`ALPHA_CUTOFF` are dropped;
    the material's ``MASK`` mode cuts the rest at the same value.

The file (:func:`glb_bytes`)
    One node a frame under a root node (which turns the package's z-up world to glTF's y-up), each with a
    mesh of two primitives: the posed body (positions, normals, a lit material of the palette's last colour,
    the body's) and the garment (positions, ``COLOR_0``, an unlit material: ``c_G`` already holds the
    captured shading). An animation scales node i to 1 during ``[i / fps, (i + 1) / fps)`` and to 0 outside
    (``STEP`` keys), so players and Blender play the frames in turn. Colours are written in glTF's linear
    space (the palette and ``c_G`` are sRGB display values). The previewer hides the body behind the baked
    garment unless it is more than :data:`~garmentnerf.bake.draw.BODY_MARGIN` in front of it; a player draws
    the nearer surface, so where the skin comes within a few centimetres of the cloth it can show through.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from garmentnerf.bake.views import (DEPTH_JUMP, BakedFrame, BakedView, ViewMesh, _smoothed, view_mesh,
                                    view_surface_z)
from garmentnerf.io_utils import write_file_atomic

#: Triangles whose vertices all show less garment than this are dropped; the garment material's
#: ``alphaCutoff``.
ALPHA_CUTOFF = 0.5
#: Gaussian sigma, in map pixels, of the depth smoothing under a view's normals (:func:`view_surface`); the
#: mesh's own triangles turn by tens of degrees from pixel to pixel.
NORMAL_SMOOTHING = 2.0
#: The root node's rotation (x, y, z, w): -90 degrees about x, the package's z-up world to glTF's y-up.
Z_UP_TO_Y_UP = (-float(np.sqrt(0.5)), 0.0, 0.0, float(np.sqrt(0.5)))

_FLOAT, _UINT, _USHORT = 5126, 5125, 5123
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963


class GarmentMesh(NamedTuple):
    """A frame's garment as one mesh: ``positions (N, 3)`` float32 world points (metres, z up), ``colors
    (N, 4)`` uint8 RGBA (sRGB ``c_G`` at the palette, alpha the visibility ``a``), ``faces (M, 3)`` uint32."""

    positions: np.ndarray
    colors: np.ndarray
    faces: np.ndarray


class ExportFrame(NamedTuple):
    """What :func:`glb_bytes` writes of one frame: its index in the motion, its :class:`GarmentMesh` and the
    posed body ``(V, 3)`` float32 (None: the bake has none)."""

    frame: int
    garment: GarmentMesh
    body_vertices: np.ndarray | None


def sample_layers(layers: np.ndarray, texcoords: np.ndarray) -> np.ndarray:
    """(L, N, 4) float32 the layers ``(L, H, W, 4)`` sampled bilinearly at ``texcoords (N, 2)`` in [0, 1] (u
    right, v down, pixel centres at ``(x + 0.5) / W``), clamped to the edge pixels."""
    L, H, W, _ = layers.shape
    x = np.clip(texcoords[:, 0].astype(np.float64) * W - 0.5, 0.0, W - 1.0)
    y = np.clip(texcoords[:, 1].astype(np.float64) * H - 0.5, 0.0, H - 1.0)
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    x1, y1 = np.minimum(x0 + 1, W - 1), np.minimum(y0 + 1, H - 1)
    fx, fy = (x - x0)[None, :, None], (y - y0)[None, :, None]
    top = layers[:, y0, x0] * (1 - fx) + layers[:, y0, x1] * fx
    bottom = layers[:, y1, x0] * (1 - fx) + layers[:, y1, x1] * fx
    return (top * (1 - fy) + bottom * fy).astype(np.float32)


def garment_rgba(samples: np.ndarray, palette: np.ndarray) -> np.ndarray:
    """(N, 4) float32 ``(c_G, a)`` in [0, 1] (module docstring, "Colours") of garment attributes ``samples
    (2 + G, N, 4)`` at ``palette (G + 1, 3)`` (garment colours first, the body's last)."""
    G = samples.shape[0] - 2
    p = np.asarray(palette, dtype=np.float32)
    if p.shape != (G + 1, 3):
        raise ValueError(f"the bake has {G} garment colour(s) and a body colour; the palette has {p.shape[0]} colours")
    base = sum(samples[1, :, i:i + 1] * (p[i] + samples[2 + i, :, :3]) for i in range(G))
    out = np.empty((samples.shape[1], 4), np.float32)
    out[:, :3] = np.clip(samples[0, :, :3] * base, 0.0, 1.0)
    out[:, 3] = np.clip(samples[0, :, 3], 0.0, 1.0)
    return out


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


class ViewSurface(NamedTuple):
    """What the best-view partition reads of one view: its surface's camera z ``z (H, W)`` float32
    (:func:`~garmentnerf.bake.views.view_surface_z`, 0: none) and ``normals (H, W, 3)`` float64 world unit
    normals of that surface, smoothed by :data:`NORMAL_SMOOTHING`, facing the view's camera."""

    z: np.ndarray
    normals: np.ndarray


def view_surface(view: BakedView) -> ViewSurface:
    """The :class:`ViewSurface` of ``view``."""
    import torch  # lazy: the rest of the module is numpy

    z = view_surface_z(view)
    H, W = z.shape
    zt = torch.from_numpy(z.astype(np.float64))
    zs = _smoothed(zt, (zt > 0).double(), NORMAL_SMOOTHING).numpy()
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    xc = (np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(view.camera.K).T) * zs[..., None]
    dx = np.gradient(xc, axis=1) if W > 1 else np.zeros_like(xc)
    dy = np.gradient(xc, axis=0) if H > 1 else np.zeros_like(xc)
    n = _unit(np.cross(dx, dy))
    n *= np.where(np.sum(n * xc, axis=-1) > 0, -1.0, 1.0)[..., None]  # towards the camera, at the origin
    return ViewSurface(z, n @ view.camera.R)  # camera to world: R^T n


def _lookup(view: BakedView, surface: ViewSurface, points: np.ndarray,
            jump: float = DEPTH_JUMP) -> tuple[np.ndarray, np.ndarray]:
    """(seen (N,) bool, normals (N, 3)): whether ``points (N, 3)`` lie on ``view``'s captured surface (they
    project into its image onto a pixel with a surface within ``jump`` of their depth and a garment
    visibility of at least :data:`ALPHA_CUTOFF`), and its normal there (0 where not seen)."""
    cam = view.camera
    xc = points.astype(np.float64) @ cam.R.T + cam.t
    z = xc[:, 2]
    uv = xc @ cam.K.T
    with np.errstate(divide="ignore", invalid="ignore"):
        px = np.rint(uv[:, 0] / z)
        py = np.rint(uv[:, 1] / z)
    H, W = surface.z.shape
    inside = (z > 1e-6) & (px >= 0) & (px < W) & (py >= 0) & (py < H)
    seen = np.zeros(len(points), bool)
    normals = np.zeros((len(points), 3))
    ix, iy = px[inside].astype(np.int64), py[inside].astype(np.int64)
    zs = surface.z[iy, ix]
    seen[inside] = (zs > 0) & (np.abs(zs - z[inside]) <= jump) & (view.layers[0, iy, ix, 3] >= ALPHA_CUTOFF)
    normals[seen] = surface.normals[iy, ix][seen[inside]]
    return seen, normals


def best_views(points: np.ndarray, owner: int, views: tuple[BakedView, ...],
               surfaces: list[ViewSurface]) -> np.ndarray:
    """(N,) int64 the best view (module docstring) of ``points (N, 3)`` on view ``owner``'s surface: among
    the views that captured a point (``owner`` always), the one whose direction from the point is most
    aligned with the point's normal, the mean of those views' normals there; the first of equals."""
    seen = np.zeros((len(views), len(points)), bool)
    normal = np.zeros((len(points), 3))
    for j, view in enumerate(views):
        seen[j], n = _lookup(view, surfaces[j], points)
        normal += n
    if not seen[owner].all():  # the owner's own visibility at the point may fall under the cut-off
        missing = ~seen[owner]
        cam = views[owner].camera
        normal[missing] += surfaces[owner].normals[_pixel(cam, points[missing], surfaces[owner].z.shape)]
        seen[owner] = True
    normal = _unit(normal)
    score = np.full((len(views), len(points)), -np.inf)
    for j, view in enumerate(views):
        score[j, seen[j]] = np.sum(normal[seen[j]] * _unit(view.camera.center - points[seen[j]]), axis=1)
    return np.argmax(score, axis=0)


def _pixel(cam, points: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) the nearest pixels of ``points (N, 3)`` in ``cam``'s image of ``shape`` (H, W), clamped."""
    uv = (points.astype(np.float64) @ cam.R.T + cam.t) @ cam.K.T
    z = np.maximum(uv[:, 2], 1e-9)
    cols = np.clip(np.rint(uv[:, 0] / z), 0, shape[1] - 1).astype(np.int64)
    rows = np.clip(np.rint(uv[:, 1] / z), 0, shape[0] - 1).astype(np.int64)
    return rows, cols


class _ViewPart(NamedTuple):
    """One view's share of a frame's garment mesh while :func:`garment_mesh` partitions it."""

    mesh: ViewMesh
    rgba: np.ndarray  # (N, 4) (c_G, a) of the mesh's vertices
    faces: np.ndarray  # (M, 3) int64 the triangles that show garment
    centroids: np.ndarray  # (M, 3) float64
    best: np.ndarray  # (M,) int64 their best view
    cells: np.ndarray  # (H, W) bool: the grid cells (by their top-left pixel) whose triangles the view keeps


def _cells(view: BakedView, mesh: ViewMesh, faces: np.ndarray, step: int) -> np.ndarray:
    """(H, W) bool: the grid cells of ``view``'s mesh holding ``faces``, marked at their top-left pixel."""
    W, H = view.size
    px = np.rint(mesh.texcoords[faces] * [W, H] - 0.5).astype(np.int64)  # (M, 3, 2) the corners' pixels
    out = np.zeros((H, W), bool)
    out[px[..., 1].min(axis=1), px[..., 0].min(axis=1)] = True
    return out


def _kept_at(view: BakedView, part: _ViewPart, points: np.ndarray, step: int) -> np.ndarray:
    """(N,) bool: ``points (N, 3)`` project into a grid cell of ``view`` whose triangles it keeps."""
    cam = view.camera
    uv = (points @ cam.R.T + cam.t) @ cam.K.T
    z = np.maximum(uv[:, 2], 1e-9)
    H, W = part.cells.shape
    cols = np.clip(np.floor(uv[:, 0] / z / step).astype(np.int64) * step, 0, W - 1)
    rows = np.clip(np.floor(uv[:, 1] / z / step).astype(np.int64) * step, 0, H - 1)
    return part.cells[rows, cols]


def garment_mesh(baked: BakedFrame, palette, step: int = 1) -> GarmentMesh:
    """The garment of ``baked`` as one mesh at ``palette (G + 1, 3)`` (garment colours first, the body's
    last; sRGB in [0, 1]): each view's :func:`~garmentnerf.bake.views.view_mesh` (one vertex every ``step``
    map pixels) where that view is the best view, the parts concatenated, each vertex coloured with ``c_G``
    and ``a`` from its view's layers (module docstring: the views overlap, and the best-view partition keeps
    one layer of them). A triangle whose best view keeps none of its own triangles there (their surfaces
    disagree by a little, so they decide a little apart) stays, so the seams between views leave no crack."""
    views = tuple(baked.views)
    surfaces = [view_surface(v) for v in views]
    parts: list[_ViewPart | None] = []
    for k, view in enumerate(views):
        mesh = view_mesh(view, step)
        rgba = garment_rgba(sample_layers(view.layers, mesh.texcoords), palette)
        f = mesh.faces.astype(np.int64)
        f = f[(rgba[f, 3] >= ALPHA_CUTOFF).any(axis=1)]
        if len(f) == 0:
            parts.append(None)
            continue
        centroids = mesh.positions[f].astype(np.float64).mean(axis=1)
        best = best_views(centroids, k, views, surfaces)
        parts.append(_ViewPart(mesh, rgba, f, centroids, best, _cells(view, mesh, f[best == k], step)))
    positions, colors, faces = [], [], []
    count = 0
    for k, part in enumerate(parts):
        if part is None:
            continue
        keep = part.best == k
        for j in np.unique(part.best[~keep]):  # the triangles another view is best for: kept where it keeps none
            lost = np.flatnonzero(part.best == j)
            if parts[j] is None:
                keep[lost] = True
            else:
                keep[lost[~_kept_at(views[j], parts[j], part.centroids[lost], step)]] = True
        f = part.faces[keep]
        used = np.zeros(len(part.mesh.positions), bool)
        used[f.ravel()] = True
        index = np.cumsum(used) - 1
        positions.append(part.mesh.positions[used])
        colors.append(np.rint(part.rgba[used] * 255.0).astype(np.uint8))
        faces.append(index[f] + count)
        count += int(used.sum())
    if not positions:
        return GarmentMesh(np.zeros((0, 3), np.float32), np.zeros((0, 4), np.uint8), np.zeros((0, 3), np.uint32))
    return GarmentMesh(np.concatenate(positions).astype(np.float32), np.concatenate(colors),
                       np.concatenate(faces).astype(np.uint32))


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """sRGB values in [0, 1] to linear light (the sRGB transfer function), float64."""
    c = np.clip(np.asarray(c, dtype=np.float64), 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def body_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V, 3) float32 unit area-weighted vertex normals of the body (:func:`garmentnerf.body.surface.vertex_normals`)."""
    import torch  # lazy: the rest of the module is numpy

    from garmentnerf.body.surface import vertex_normals

    n = vertex_normals(torch.from_numpy(np.asarray(vertices, np.float32)), torch.from_numpy(np.asarray(faces, np.int64)))
    return n.numpy().astype(np.float32)


class _Blob:
    """The binary chunk of a glb being assembled, with its buffer views and accessors."""

    def __init__(self, gltf) -> None:
        self.gltf = gltf
        self.parts: list[bytes] = []
        self.size = 0

    def accessor(self, array: np.ndarray, kind: str, component: int, target: int | None,
                 normalized: bool = False, bounds: bool = False) -> int:
        import pygltflib

        data = np.ascontiguousarray(array).tobytes()
        view = pygltflib.BufferView(buffer=0, byteOffset=self.size, byteLength=len(data), target=target)
        self.parts.append(data)
        self.size += len(data)
        pad = -self.size % 4
        if pad:
            self.parts.append(b"\0" * pad)
            self.size += pad
        self.gltf.bufferViews.append(view)
        flat = array.reshape(len(array), -1)
        extra = {"min": flat.min(0).tolist(), "max": flat.max(0).tolist()} if bounds else {}
        self.gltf.accessors.append(pygltflib.Accessor(bufferView=len(self.gltf.bufferViews) - 1, componentType=component,
                                                      normalized=normalized, count=len(array), type=kind, **extra))
        return len(self.gltf.accessors) - 1

    def bytes(self) -> bytes:
        return b"".join(self.parts)


def glb_bytes(frames: list[ExportFrame], fps: float, body_faces: np.ndarray | None, palette) -> bytes:
    """The glb (module docstring, "The file") of ``frames``, frame i shown during ``[i / fps, (i + 1) / fps)``;
    ``body_faces (F, 3)`` the body's triangles (None: no body), ``palette (P, 3)`` sRGB, the body's colour last."""
    import pygltflib  # lazy: only exporting needs it

    if not frames:
        raise ValueError("nothing to export: no frame")
    if not fps > 0:
        raise ValueError(f"the frame rate must be positive, got {fps}")
    gltf = pygltflib.GLTF2(asset=pygltflib.Asset(generator="garmentnerf export", version="2.0"))
    gltf.extensionsUsed = ["KHR_materials_unlit"]
    skin = [*srgb_to_linear(np.asarray(palette, float)[-1]).tolist(), 1.0]
    gltf.materials = [
        pygltflib.Material(name="body", pbrMetallicRoughness=pygltflib.PbrMetallicRoughness(
            baseColorFactor=skin, metallicFactor=0.0, roughnessFactor=0.8)),
        pygltflib.Material(name="garment", alphaMode=pygltflib.MASK, alphaCutoff=ALPHA_CUTOFF, doubleSided=True,
                           pbrMetallicRoughness=pygltflib.PbrMetallicRoughness(
                               baseColorFactor=[1.0, 1.0, 1.0, 1.0], metallicFactor=0.0, roughnessFactor=1.0),
                           extensions={"KHR_materials_unlit": {}}),
    ]
    blob = _Blob(gltf)
    body_index = None
    if body_faces is not None:
        body_faces = np.asarray(body_faces, np.int64)
        body_index = blob.accessor(body_faces.astype(np.uint32).reshape(-1), pygltflib.SCALAR, _UINT,
                                   _ELEMENT_ARRAY_BUFFER)
    root = pygltflib.Node(name="clip", rotation=list(Z_UP_TO_Y_UP), children=[])
    gltf.nodes.append(root)
    animation = pygltflib.Animation(name="clip")
    for i, fr in enumerate(frames):
        primitives = []
        if body_index is not None and fr.body_vertices is not None:
            v = np.asarray(fr.body_vertices, np.float32)
            primitives.append(pygltflib.Primitive(
                attributes=pygltflib.Attributes(
                    POSITION=blob.accessor(v, pygltflib.VEC3, _FLOAT, _ARRAY_BUFFER, bounds=True),
                    NORMAL=blob.accessor(body_normals(v, body_faces), pygltflib.VEC3, _FLOAT, _ARRAY_BUFFER)),
                indices=body_index, material=0))
        g = fr.garment
        if len(g.faces):
            rgba = np.empty(g.colors.shape, np.float64)
            rgba[:, :3] = srgb_to_linear(g.colors[:, :3] / 255.0)
            rgba[:, 3] = g.colors[:, 3] / 255.0
            primitives.append(pygltflib.Primitive(
                attributes=pygltflib.Attributes(
                    POSITION=blob.accessor(g.positions.astype(np.float32), pygltflib.VEC3, _FLOAT, _ARRAY_BUFFER,
                                           bounds=True),
                    COLOR_0=blob.accessor(np.rint(rgba * 65535.0).astype(np.uint16), pygltflib.VEC4, _USHORT,
                                          _ARRAY_BUFFER, normalized=True)),
                indices=blob.accessor(g.faces.astype(np.uint32).reshape(-1), pygltflib.SCALAR, _UINT,
                                      _ELEMENT_ARRAY_BUFFER), material=1))
        node = pygltflib.Node(name=f"frame_{fr.frame:05d}", scale=[1.0, 1.0, 1.0] if i == 0 else [0.0, 0.0, 0.0])
        if primitives:
            gltf.meshes.append(pygltflib.Mesh(name=f"frame_{fr.frame:05d}", primitives=primitives))
            node.mesh = len(gltf.meshes) - 1
        gltf.nodes.append(node)
        root.children.append(len(gltf.nodes) - 1)
        times, scales = _visibility_keys(i, fps)
        sampler = pygltflib.AnimationSampler(
            input=blob.accessor(times, pygltflib.SCALAR, _FLOAT, None, bounds=True),
            output=blob.accessor(scales, pygltflib.VEC3, _FLOAT, None), interpolation=pygltflib.ANIM_STEP)
        animation.samplers.append(sampler)
        animation.channels.append(pygltflib.AnimationChannel(
            sampler=len(animation.samplers) - 1,
            target=pygltflib.AnimationChannelTarget(node=len(gltf.nodes) - 1, path="scale")))
    gltf.animations.append(animation)
    gltf.scenes.append(pygltflib.Scene(name="clip", nodes=[0]))
    gltf.scene = 0
    data = blob.bytes()
    gltf.buffers.append(pygltflib.Buffer(byteLength=len(data)))
    gltf.set_binary_blob(data)
    return b"".join(gltf.save_to_bytes())


def _visibility_keys(i: int, fps: float) -> tuple[np.ndarray, np.ndarray]:
    """(times (k,) float32 seconds, scales (k, 3) float32) of frame i's ``STEP`` keys: 0 before
    ``i / fps``, 1 until ``(i + 1) / fps``, 0 after."""
    times = [i / fps, (i + 1) / fps]
    values = [1.0, 0.0]
    if i > 0:
        times.insert(0, 0.0)
        values.insert(0, 0.0)
    return np.asarray(times, np.float32), np.repeat(np.asarray(values, np.float32)[:, None], 3, axis=1)


def write_glb(path, frames: list[ExportFrame], fps: float, body_faces: np.ndarray | None, palette):
    """Write :func:`glb_bytes` to ``path`` atomically (a reader sees the old file or the whole new one)."""
    return write_file_atomic(path, glb_bytes(frames, fps, body_faces, palette))


__all__ = ["GarmentMesh", "ExportFrame", "garment_mesh", "garment_rgba", "sample_layers", "best_views", "view_surface", "ViewSurface",
           "srgb_to_linear", "body_normals", "glb_bytes", "write_glb", "ALPHA_CUTOFF", "NORMAL_SMOOTHING", "Z_UP_TO_Y_UP"]
