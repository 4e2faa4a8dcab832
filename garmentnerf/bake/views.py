"""A baked frame: the garment of one body frame, rendered once from K cameras and kept as K view surfaces.

Why views and not one fused surface
    The network's geometry is about 2 cm fuzzy and its 2D decoder's maps are view-dependent, so a
    single fused surface (TSDF, surfels, marching cubes on the density) has to choose or average
    between captures that disagree, and shows seams, speckle and holes. Kept apart, each capture's
    surface is consistent with its own maps, and a nearby camera sees it reprojected by a few
    millimetres. The ledger's bake lab (``docs/lab/bake.md``) measured the alternatives.

What a view holds (:class:`BakedView`)
    - ``layers (L, H, W, 4)``: the garment's attributes at the maps' resolution, in the layout of the
      previewer's palette shader (:func:`garment_layers`): layer 0 the radiance (rgb) and the
      garment's visibility ``a = m (1 - w_B)``; layer 1 the garment colours' blend weights
      ``w_i / (1 - w_B)`` (they sum to 1); layer ``2 + i`` the offset ``o_i`` of garment colour i.
    - ``depth (H / c, W / c)``: camera-space z of each feature ray's median depth (where the ray's
      opacity reaches one half), ``c`` the decoder's upsampling: unbiased, where the expected
      depth lies behind thin cloth.
    - ``camera``: the camera of the layers' pixels.

Exact recolouring
    :func:`maps_from_layers` turns the attributes (a view's, or the blend of several that the GL pass
    draws) back into :class:`~garmentnerf.model.palette.DecomposedMaps` whose body weight is 0 and
    whose mask is ``a``; with the frame's body layer attached, :func:`~garmentnerf.model.palette.compose`
    gives exactly what it gives for the network's own maps, for every palette (the hybrid
    composition, :mod:`garmentnerf.model.palette`). Baking needs that composition (``raster_body``).

The surface of a view
    :func:`view_surface_z` smooths the feature-resolution depth by a Gaussian of one feature pixel
    (normalised over the rays that have a depth), upsamples it bilinearly to the maps, and keeps the
    nearest feature ray's depth across jumps over :data:`DEPTH_JUMP`; :func:`view_mesh` makes a
    grid mesh of it, two triangles per cell whose corners all have a depth and agree within
    :data:`DEPTH_JUMP`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F

from garmentnerf.conventions import Camera, look_at
from garmentnerf.model.palette import DecomposedMaps

#: Cells whose depth spans more than this (metres) are a jump between surfaces: no triangle spans
#: them and no depth is interpolated across them.
DEPTH_JUMP = 0.05
#: Gaussian sigma, in feature pixels, of the depth smoothing (the median depth of neighbouring rays
#: differs by a median 6 mm and a 90th percentile of 39 mm).
DEPTH_SMOOTHING = 1.0
#: Feature rays without a median depth (the opacity of a ray at the garment's fringe may stay under one
#: half) within this many rays of ones with a depth take their neighbours' mean depth, so the mesh reaches
#: the outline the maps draw.
DEPTH_FILL_RAYS = 2
#: A view's mesh keeps the cells where the garment's visibility reaches this somewhere.
MIN_VISIBILITY = 1.0 / 255.0
#: A view keeps the rectangle of whole feature cells around the pixels whose visibility reaches this (a few
#: faint pixels far from the garment, on a hand or the hair, would double its size).
CROP_VISIBILITY = 0.1
#: The most palette colours a baked garment carries (the palette shader's limit, garment and body).
MAX_PALETTE = 4


@dataclass(frozen=True, eq=False)
class BakedView:
    """One capture of a frame's garment (module docstring), its attributes quantised to 8 bits per channel.

    Attributes:
        camera: the layers' camera (``camera.width x camera.height`` = W x H).
        codes: (L, H, W, 4) uint8 attributes, ``L = 2 + G`` for G garment colours: the value of a channel is
            ``low + code / 255 (high - low)`` (about 1/500 of the channel's range in this view).
        low, high: (L, 4) float32 each channel's range.
        depth: (H / cell, W / cell) float32 camera-space z of the median depth, 0 where none.
        cell: map pixels per feature ray on each side (the decoder's upsampling).
    """

    camera: Camera
    codes: np.ndarray
    low: np.ndarray
    high: np.ndarray
    depth: np.ndarray
    cell: int
    _meshes: dict = field(default_factory=dict, repr=False)  # mesh step -> ViewMesh, made on first use

    @classmethod
    def from_values(cls, camera: Camera, layers: np.ndarray, depth: np.ndarray, cell: int) -> "BakedView":
        """The view of float attributes ``layers (L, H, W, 4)``, quantised."""
        layers = np.asarray(layers, np.float32)
        low = layers.min(axis=(1, 2)).astype(np.float32)
        high = layers.max(axis=(1, 2)).astype(np.float32)
        span = np.where(high > low, high - low, 1.0)[:, None, None, :]
        codes = np.clip(np.rint((layers - low[:, None, None, :]) / span * 255.0), 0, 255).astype(np.uint8)
        return cls(camera, codes, low, high, np.ascontiguousarray(depth, np.float32), int(cell))

    @property
    def layers(self) -> np.ndarray:
        """(L, H, W, 4) float32 the attributes."""
        span = (self.high - self.low)[:, None, None, :] / np.float32(255.0)
        return (self.codes.astype(np.float32) * span + self.low[:, None, None, :]).astype(np.float32)

    @property
    def visibility(self) -> np.ndarray:
        """(H, W) float32 the garment's visibility a."""
        return (self.low[0, 3] + self.codes[0, ..., 3].astype(np.float32) / 255.0 * (self.high[0, 3] - self.low[0, 3]))

    def mesh(self, step: int = 1) -> "ViewMesh":
        """:func:`view_mesh` of this view, made once per step."""
        made = self._meshes.get(step)
        if made is None:
            made = self._meshes[step] = view_mesh(self, step)
        return made

    @property
    def garment_colors(self) -> int:
        return int(self.codes.shape[0]) - 2

    @property
    def size(self) -> tuple[int, int]:
        """(W, H) of the layers."""
        return int(self.codes.shape[2]), int(self.codes.shape[1])

    @property
    def nbytes(self) -> int:
        return self.codes.nbytes + self.depth.nbytes + self.low.nbytes + self.high.nbytes


@dataclass(frozen=True)
class BakedFrame:
    """The K captures of one body frame, and the posed body they were baked over (``body_vertices (V, 3)``
    float32; the faces are the body model's), so that a bake can be drawn and exported on its own."""

    frame: int
    views: tuple[BakedView, ...]
    body_vertices: np.ndarray | None = None

    @property
    def nbytes(self) -> int:
        return sum(v.nbytes for v in self.views)


def garment_layers(maps: DecomposedMaps) -> np.ndarray:
    """(2 + G, H, W, 4) float32 garment attributes (module docstring) of decomposed maps (batch 1, CPU)
    whose last palette colour is the body's, G = P - 1 garment colours."""
    w = maps.weights[0].float()
    P, H, W = w.shape
    if not 2 <= P <= MAX_PALETTE:
        raise ValueError(f"a bake needs a garment and a body palette colour (2..{MAX_PALETTE} colours), got {P}")
    share = 1.0 - w[-1]
    visible = maps.mask[0, 0].float() * share
    out = np.zeros((P + 1, H, W, 4), np.float32)
    radiance = maps.radiance[0].float()
    out[0, ..., :3] = radiance.expand(3, H, W).permute(1, 2, 0).numpy()
    out[0, ..., 3] = visible.numpy()
    out[1, ..., :P - 1] = (w[:-1] / share.clamp_min(1e-6)).permute(1, 2, 0).numpy()
    out[2:, ..., :3] = maps.offsets[0, :-1].float().permute(0, 2, 3, 1).numpy()
    return out


def maps_from_layers(layers: np.ndarray | torch.Tensor) -> DecomposedMaps:
    """:class:`DecomposedMaps` (batch 1, P = G + 1) of garment attributes ``(2 + G, H, W, 4)``: the garment
    colours' weights and offsets, a body weight and offset of 0, the mask ``a``. Composed with a body
    layer they give the image the captured maps give (module docstring)."""
    t = torch.as_tensor(np.asarray(layers, dtype=np.float32))
    L, H, W, _ = t.shape
    G = L - 2
    weights = torch.zeros(1, G + 1, H, W)
    weights[0, :G] = t[1, ..., :G].permute(2, 0, 1)
    offsets = torch.zeros(1, G + 1, 3, H, W)
    offsets[0, :G] = t[2:, ..., :3].permute(0, 3, 1, 2)
    radiance = t[0, ..., :3].permute(2, 0, 1).unsqueeze(0).contiguous()
    mask = t[0, ..., 3].reshape(1, 1, H, W).contiguous()
    return DecomposedMaps(radiance, offsets, weights, mask)


def view_from_render(maps: DecomposedMaps, map_camera: Camera, surface_depth: np.ndarray, cell: int,
                     min_visibility: float = CROP_VISIBILITY) -> BakedView | None:
    """A :class:`BakedView` of one render: its maps (batch 1, CPU, W x H) seen by ``map_camera``, and
    ``surface_depth`` (ceil(H / cell), ceil(W / cell)) camera z of the feature rays (0: none), cut to
    the whole feature cells around the garment's visible pixels. None when no pixel shows garment."""
    layers = garment_layers(maps)
    H, W = layers.shape[1:3]
    seen = layers[0, ..., 3] >= min_visibility
    rows, cols = np.flatnonzero(seen.any(axis=1)), np.flatnonzero(seen.any(axis=0))
    if rows.size == 0:
        return None
    fy0, fy1 = rows[0] // cell, -(-(rows[-1] + 1) // cell)
    fx0, fx1 = cols[0] // cell, -(-(cols[-1] + 1) // cell)
    fy0, fx0 = max(0, fy0 - 1), max(0, fx0 - 1)  # one feature cell of margin: the outline's neighbours
    fy1, fx1 = min(surface_depth.shape[0], fy1 + 1), min(surface_depth.shape[1], fx1 + 1)
    y0, x0 = fy0 * cell, fx0 * cell
    y1, x1 = min(H, fy1 * cell), min(W, fx1 * cell)
    crop = np.zeros((layers.shape[0], (fy1 - fy0) * cell, (fx1 - fx0) * cell, 4), np.float32)
    crop[:, :y1 - y0, :x1 - x0] = layers[:, y0:y1, x0:x1]
    depth = np.ascontiguousarray(surface_depth[fy0:fy1, fx0:fx1], dtype=np.float32)
    camera = map_camera.cropped(x0, y0, crop.shape[2], crop.shape[1])
    return BakedView.from_values(camera, crop, depth, int(cell))


# ---- the surface of a view ------------------------------------------------------------------------------
def _smoothed(z: torch.Tensor, valid: torch.Tensor, sigma: float) -> torch.Tensor:
    """(h, w) ``z`` smoothed by a Gaussian of ``sigma`` pixels, normalised over ``valid``; 0 outside it."""
    if sigma <= 0:
        return z * valid
    r = int(math.ceil(2.5 * sigma))
    x = torch.arange(-r, r + 1, dtype=torch.float64)
    g = torch.exp(-0.5 * (x / sigma) ** 2)
    kernel = (g[:, None] * g[None, :] / (g.sum() ** 2)).to(z.dtype)[None, None]
    both = torch.stack([z * valid, valid])[:, None]
    out = F.conv2d(F.pad(both, (r, r, r, r)), kernel)[:, 0]
    return torch.where(valid > 0, out[0] / out[1].clamp_min(1e-9), torch.zeros_like(z))


def filled_depth(z: torch.Tensor, rays: int = DEPTH_FILL_RAYS) -> torch.Tensor:
    """(h, w) ``z`` (0: no depth) with each ray that has none but a neighbour (3 x 3) that has given the mean
    of those neighbours, ``rays`` times over."""
    z = z.clone()
    ones = torch.ones(1, 1, 3, 3, dtype=z.dtype)
    for _ in range(int(rays)):
        valid = (z > 0).to(z.dtype)
        total = F.conv2d(F.pad((z * valid)[None, None], (1, 1, 1, 1)), ones)[0, 0]
        count = F.conv2d(F.pad(valid[None, None], (1, 1, 1, 1)), ones)[0, 0]
        grow = (valid == 0) & (count > 0)
        if not bool(grow.any()):
            break
        z = torch.where(grow, total / count.clamp_min(1.0), z)
    return z


def view_surface_z(view: BakedView, smoothing: float = DEPTH_SMOOTHING, jump: float = DEPTH_JUMP) -> np.ndarray:
    """(H, W) float32 camera z of the view's surface at every map pixel, 0 where it has none (module
    docstring, "The surface of a view")."""
    zf = filled_depth(torch.from_numpy(view.depth.astype(np.float64)))
    valid = (zf > 0).double()
    zs = _smoothed(zf, valid, smoothing)
    W, H = view.size
    both = torch.stack([zs, valid])[None]
    up = F.interpolate(both, size=(H, W), mode="bilinear", align_corners=False)[0]
    covered = up[1] > 0.25
    z = torch.where(covered, up[0] / up[1].clamp_min(1e-9), torch.zeros_like(up[0]))
    far = torch.where(valid > 0, zs, torch.full_like(zs, -1e9))
    near = torch.where(valid > 0, -zs, torch.full_like(zs, -1e9))
    spread = F.max_pool2d(far[None, None], 3, 1, 1)[0, 0] + F.max_pool2d(near[None, None], 3, 1, 1)[0, 0]
    jumps = (spread > jump).repeat_interleave(view.cell, 0).repeat_interleave(view.cell, 1)[:H, :W]
    nearest = zs.repeat_interleave(view.cell, 0).repeat_interleave(view.cell, 1)[:H, :W]
    z = torch.where(jumps & covered, nearest, z)
    return z.float().numpy()


@dataclass(frozen=True)
class ViewMesh:
    """A view's surface as a grid mesh: ``positions (N, 3)`` float32 world points, ``texcoords (N, 2)``
    float32 in [0, 1] over the view's layers (u right, v down), ``faces (M, 3)`` uint32."""

    positions: np.ndarray
    texcoords: np.ndarray
    faces: np.ndarray


def view_mesh(view: BakedView, step: int = 1, jump: float = DEPTH_JUMP) -> ViewMesh:
    """The grid mesh of ``view``'s surface (:func:`view_surface_z`), one vertex every ``step`` map pixels
    (at the pixel centres) where the surface and the garment are; two triangles per grid cell whose four
    corners have a depth within ``jump`` of each other and show some garment."""
    z = view_surface_z(view, jump=jump)
    H, W = z.shape
    rows = np.arange(0, H, step)
    cols = np.arange(0, W, step)
    zg = z[np.ix_(rows, cols)].astype(np.float64)
    ag = view.visibility[np.ix_(rows, cols)]
    h, w = zg.shape
    valid = zg > 0
    corners = (valid[:-1, :-1] & valid[:-1, 1:] & valid[1:, :-1] & valid[1:, 1:])
    quad = np.stack([zg[:-1, :-1], zg[:-1, 1:], zg[1:, :-1], zg[1:, 1:]])
    corners &= (quad.max(0) - quad.min(0)) <= jump
    shows = np.stack([ag[:-1, :-1], ag[:-1, 1:], ag[1:, :-1], ag[1:, 1:]]).max(0) >= MIN_VISIBILITY
    cells = corners & shows
    used = np.zeros((h, w), bool)
    used[:-1, :-1] |= cells
    used[:-1, 1:] |= cells
    used[1:, :-1] |= cells
    used[1:, 1:] |= cells
    index = -np.ones((h, w), np.int64)
    index[used] = np.arange(int(used.sum()))
    cy, cx = np.nonzero(cells)
    i00, i01, i10, i11 = index[cy, cx], index[cy, cx + 1], index[cy + 1, cx], index[cy + 1, cx + 1]
    faces = np.concatenate([np.stack([i00, i10, i01], 1), np.stack([i01, i10, i11], 1)]).astype(np.uint32)
    vy, vx = np.nonzero(used)
    u = cols[vx].astype(np.float64)
    v = rows[vy].astype(np.float64)
    depth = zg[vy, vx]
    cam = view.camera
    pix = np.stack([u, v, np.ones_like(u)], 1)
    xc = (pix @ np.linalg.inv(cam.K).T) * depth[:, None]
    world = (xc - cam.t) @ cam.R  # R^T (x - t)
    tex = np.stack([(u + 0.5) / W, (v + 0.5) / H], 1)
    return ViewMesh(world.astype(np.float32), tex.astype(np.float32), faces)


# ---- which views a camera draws -----------------------------------------------------------------------
def nearest_views(view_centers: np.ndarray, target: np.ndarray, camera_center: np.ndarray,
                  count: int) -> list[tuple[int, float]]:
    """The ``count`` captures nearest in angle to a camera, as seen from ``target`` (the garment's centre),
    with unstructured-lumigraph weights ``1 - angle_i / angle_(count+1)`` normalised to sum 1.

    Args:
        view_centers: (K, 3) the captures' camera centres; target: (3,); camera_center: (3,).
    Returns:
        [(index, weight)], nearest first; weights > 0 (the nearest gets 1 when the others are at the
        cut-off angle, or when ``count`` is 1).
    """
    centers = np.asarray(view_centers, dtype=np.float64)
    dirs = centers - target
    dirs /= np.maximum(np.linalg.norm(dirs, axis=1, keepdims=True), 1e-12)
    eye = np.asarray(camera_center, dtype=np.float64) - target
    eye /= max(float(np.linalg.norm(eye)), 1e-12)
    angles = np.arccos(np.clip(dirs @ eye, -1.0, 1.0))
    order = np.argsort(angles, kind="stable")
    count = max(1, min(int(count), len(order)))
    cut = angles[order[count]] if count < len(order) else angles[order[-1]] + 1e-6
    chosen = order[:count]
    raw = np.maximum(1.0 - angles[chosen] / max(float(cut), 1e-9), 0.0)
    if raw.sum() <= 1e-9:  # all at the cut-off angle: the nearest alone
        raw = np.zeros(count)
        raw[0] = 1.0
    raw /= raw.sum()
    return [(int(i), float(w)) for i, w in zip(chosen, raw) if w > 0]


def ring_cameras(training_views: list[Camera], center_xy, count: int) -> list[Camera]:
    """``count`` capture cameras evenly spaced in azimuth around ``center_xy`` (the frame's body), on the
    ring the training cameras stand on: their median distance from their common centre, their median
    height, their median downward tilt, the intrinsics and size of the first (at the trained density)."""
    if not training_views:
        raise ValueError("baking needs the run's training cameras (its scene)")
    centers = np.stack([c.center for c in training_views])
    mid = centers[:, :2].mean(0)
    radius = float(np.median(np.linalg.norm(centers[:, :2] - mid, axis=1)))
    height = float(np.median(centers[:, 2]))
    forward = np.stack([c.R[2] for c in training_views])  # each camera's viewing direction
    tilt = float(np.median(forward[:, 2] / np.maximum(np.linalg.norm(forward[:, :2], axis=1), 1e-9)))
    base = training_views[0]
    if radius < 1e-3:
        raise ValueError("the run's training cameras do not stand on a ring around the character")
    cams = []
    for i in range(int(count)):
        az = 2.0 * math.pi * i / count
        eye = np.array([center_xy[0] + radius * math.sin(az), center_xy[1] - radius * math.cos(az), height])
        target = np.array([center_xy[0], center_xy[1], height + tilt * radius])
        R, t = look_at(eye, target)
        cams.append(Camera(base.K.copy(), R, t, base.width, base.height, base.near, base.far))
    return cams


__all__ = ["filled_depth", "DEPTH_FILL_RAYS", "BakedView", "BakedFrame", "ViewMesh", "garment_layers", "maps_from_layers", "view_from_render",
           "view_surface_z", "view_mesh", "nearest_views", "ring_cameras", "DEPTH_JUMP", "DEPTH_SMOOTHING",
           "MIN_VISIBILITY", "CROP_VISIBILITY", "MAX_PALETTE"]
