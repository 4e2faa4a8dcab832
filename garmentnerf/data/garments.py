"""Procedural garments around the rest body: the paper's long skirt, t-shirt and multi-layer skirt.

The paper designs its three garments in Marvelous Designer; this module builds stand-ins from
the rest body of any shape (anny's rest pose is an A-pose: arms about 48 degrees below the
horizontal), so the whole data pipeline runs offline.

``make_garment(kind, body, betas)`` returns a :class:`Garment`:

``"skirt"`` (long skirt, teal blue)
    A surface of revolution about a vertical axis through the hips, from the natural waist
    (``spine03``) to mid-calf. Every ring follows the body's outline seen from the axis (the
    largest radius of the body's non-arm vertices in an angular sector, taken over everything
    between the ring and the waist, so the cloth never has to go inwards), plus a clearance,
    plus an A-line flare that grows towards the hem. 80 x 32 = 2,560 vertices.
``"tshirt"`` (red)
    A torso tube (hem at the hips up to the armpits), a front and a back yoke that meet in
    shoulder seams and leave a neck opening, and two short sleeves whose axes follow the upper
    arms' direction in the A-pose. Built as a structured quad layout (so the triangles are
    regular), placed roughly, then relaxed: Taubin smoothing (no shrinkage) alternating with a
    push-out to a clearance from the body surface, then smoothing within the surface to even
    out the triangles. 3,128 vertices.
``"dress"`` (yellow-orange; the paper's "multi-layer skirt")
    Two layers sewn to one waistband: an inner skirt to mid-calf and a shorter, wider outer
    tier to above the knee, 12 mm outside the inner one at the waist and further apart below.
    72 x 30 + 72 x 14 = 3,168 vertices.

Conventions of every garment: world axes and metres as the body (see
:mod:`garmentnerf.conventions`); triangles wound counter-clockwise seen from outside (normals
point away from the body, as the body mesh's); no duplicated vertices, every edge shared by at
most two triangles; every vertex at least :data:`MIN_CLEARANCE` from the rest body's surface.

Pins: the skirts are pinned at the waistband (their two top rings), the t-shirt at its
collar (the neck opening's boundary loop). The simulator moves pinned vertices with the body
(skinned with the skinning weights of the closest body point) and leaves the rest to the
cloth solver, so the garments hang from the waist or the neck and everything else is held by
collisions.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp
import torch
import trimesh
import trimesh.remesh
from scipy.spatial import cKDTree

if TYPE_CHECKING:  # pragma: no cover
    from garmentnerf.body.model import BodyModel

__all__ = ["GARMENT_KINDS", "GARMENT_COLORS", "MIN_CLEARANCE", "Garment", "GarmentError", "make_garment",
           "body_collision_faces", "garment_clearance"]

#: The kinds :func:`make_garment` builds.
GARMENT_KINDS = ("skirt", "tshirt", "dress")

#: Base color of each kind (linear-ish display RGB in [0, 1]); all far from the skin tone
#: (0.80, 0.63, 0.53) of the ground-truth renderer.
GARMENT_COLORS = {
    "skirt": (0.05, 0.42, 0.72),   # saturated teal blue
    "tshirt": (0.82, 0.08, 0.10),  # red
    "dress": (0.96, 0.66, 0.08),   # yellow-orange
}

#: Every garment vertex is at least this far outside the rest body (metres); the designs aim for
#: 10-20 mm, the relaxation guarantees 8 mm, this is the bound the tests check.
MIN_CLEARANCE = 0.005

#: Joint-name prefixes of the arms (their vertices are left out of the skirts' outlines).
_ARM_JOINT_PREFIXES = ("shoulder01", "upperarm", "lowerarm", "wrist", "finger", "metacarpal")


class GarmentError(ValueError):
    """An unknown garment kind, a body the garment cannot be built on, or inconsistent arrays."""


@dataclass
class Garment:
    """A garment mesh in its rest shape around the rest body it was built for.

    Attributes:
        name: label for files and messages (e.g. ``"skirt"``).
        kind: one of :data:`GARMENT_KINDS`.
        vertices: (V, 3) float32 rest positions, world metres, around ``body.rest(betas)``.
        faces: (F, 3) int32 triangles, counter-clockwise seen from outside.
        uv: (V, 2) float32 per-vertex parameter in [0, 1]: u around the body (it wraps, so it is
            not a seamless texture atlas), v from the top (waist or shoulders, 0) down (1); the
            sleeves of the t-shirt use u around the arm and v along it.
        pinned: (P,) int64 indices of the vertices the simulator moves with the body.
        color: (3,) float32 base color, RGB in [0, 1].
        betas: (S,) float32 shape coefficients of the body it was built around.
        layer: (V,) int8 layer of each vertex (0 = innermost; the dress has layers 0 and 1).
        part: (V,) int8 part of each vertex: 0 body of the garment, 1 left sleeve, 2 right sleeve.
    """

    name: str
    kind: str
    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    pinned: np.ndarray
    color: np.ndarray
    betas: np.ndarray
    layer: np.ndarray = field(default=None)
    part: np.ndarray = field(default=None)

    def __post_init__(self) -> None:
        label = f"garment '{self.name}'"
        self.vertices = np.ascontiguousarray(self.vertices, dtype=np.float32)
        V = self.vertices.shape[0] if self.vertices.ndim == 2 else -1
        if self.vertices.ndim != 2 or self.vertices.shape[1] != 3 or V < 3:
            raise GarmentError(f"{label}: vertices must have shape (V >= 3, 3), got {self.vertices.shape}")
        if not np.isfinite(self.vertices).all():
            raise GarmentError(f"{label}: vertices contain NaN or Inf")
        faces = np.asarray(self.faces)
        if faces.ndim != 2 or faces.shape[1] != 3 or faces.shape[0] < 1 or faces.dtype.kind not in "iu":
            raise GarmentError(f"{label}: faces must be integer (F >= 1, 3), got {faces.shape} {faces.dtype}")
        if faces.min() < 0 or faces.max() >= V:
            raise GarmentError(f"{label}: face indices must lie in [0, {V})")
        self.faces = np.ascontiguousarray(faces, dtype=np.int32)
        self.uv = np.ascontiguousarray(self.uv, dtype=np.float32)
        if self.uv.shape != (V, 2):
            raise GarmentError(f"{label}: uv must have shape ({V}, 2), got {self.uv.shape}")
        pinned = np.asarray(self.pinned)
        if pinned.ndim != 1 or (pinned.size and (pinned.dtype.kind not in "iu" or pinned.min() < 0
                                                 or pinned.max() >= V)):
            raise GarmentError(f"{label}: pinned must be a 1-D array of vertex indices in [0, {V})")
        if np.unique(pinned).size != pinned.size:
            raise GarmentError(f"{label}: pinned holds duplicate indices")
        self.pinned = np.ascontiguousarray(pinned, dtype=np.int64)
        self.color = np.asarray(self.color, dtype=np.float32).reshape(-1)
        if self.color.shape != (3,) or not np.all((self.color >= 0) & (self.color <= 1)):
            raise GarmentError(f"{label}: color must be 3 values in [0, 1], got {self.color}")
        self.betas = np.ascontiguousarray(np.asarray(self.betas, dtype=np.float32).reshape(-1))
        for name in ("layer", "part"):
            value = getattr(self, name)
            value = np.zeros(V, np.int8) if value is None else np.ascontiguousarray(value, dtype=np.int8)
            if value.shape != (V,):
                raise GarmentError(f"{label}: {name} must have shape ({V},), got {value.shape}")
            setattr(self, name, value)
        if self.kind not in GARMENT_KINDS:
            raise GarmentError(f"{label}: unknown kind '{self.kind}' (known: {', '.join(GARMENT_KINDS)})")

    @property
    def num_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])

    def to_trimesh(self) -> "trimesh.Trimesh":
        return trimesh.Trimesh(self.vertices.astype(np.float64), self.faces, process=False)

    def edge_lengths(self) -> np.ndarray:
        """(E,) length of every unique edge (metres)."""
        e = _unique_edges(self.faces)
        return np.linalg.norm(self.vertices[e[:, 0]] - self.vertices[e[:, 1]], axis=1)

    def __repr__(self) -> str:
        return (f"Garment(name={self.name!r}, kind={self.kind!r}, vertices={self.num_vertices}, "
                f"faces={self.num_faces}, pinned={self.pinned.size})")


# ------------------------------------------------------------------------------------------------
# Body measurements
# ------------------------------------------------------------------------------------------------
def body_collision_faces(body: "BodyModel") -> np.ndarray:
    """(F', 3) faces of the body's largest connected component (the skin without eyes or teeth).

    The inner components (eyeballs, teeth) are closed surfaces of their own inside the head; a
    pseudo-normal signed distance near them would call points inside the head "outside", and
    garments never reach them, so collision and penetration tests use the skin alone.
    """
    faces = body.faces.detach().cpu().numpy().astype(np.int64)
    V = int(body.template_vertices.shape[0])
    parent = np.arange(V)

    def find(i):
        root = i
        while parent[root] != root:
            root = parent[root]
        while parent[i] != root:
            parent[i], i = root, parent[i]
        return root

    for a, b in ((0, 1), (1, 2)):
        for u, v in zip(faces[:, a].tolist(), faces[:, b].tolist()):
            ru, rv = find(u), find(v)
            if ru != rv:
                parent[ru] = rv
    roots = np.array([find(i) for i in range(V)])
    face_root = roots[faces[:, 0]]
    labels, counts = np.unique(face_root, return_counts=True)
    return faces[face_root == labels[np.argmax(counts)]]


class _BodySurface:
    """Approximate signed distance to a body surface from a dense, normal-carrying sampling.

    The surface is subdivided until no edge exceeds ``max_edge``; the signed distance of a point
    is its distance to the nearest sample, signed by that sample's normal. With 5 mm samples the
    error at 10-20 mm is well under a millimetre, plenty for shaping garments (the final
    clearance is then checked exactly, see :func:`garment_clearance`).
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, max_edge: float = 0.005):
        v, f = trimesh.remesh.subdivide_to_size(vertices, faces, max_edge=max_edge)
        mesh = trimesh.Trimesh(v, f, process=False)
        self.points = np.asarray(mesh.vertices)
        self.normals = np.asarray(mesh.vertex_normals)
        self.tree = cKDTree(self.points)

    def query(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Signed distance (N,) and outward unit direction (N, 3) at points ``p`` (N, 3)."""
        _, idx = self.tree.query(p)
        s = self.points[idx]
        n = self.normals[idx]
        off = p - s
        dist = np.linalg.norm(off, axis=1)
        sign = np.where(np.einsum("ij,ij->i", off, n) >= 0.0, 1.0, -1.0)
        direction = np.where((dist > 1e-9)[:, None], off / np.maximum(dist, 1e-12)[:, None] * sign[:, None], n)
        return sign * dist, direction

    def push_out(self, p: np.ndarray, clearance: np.ndarray | float) -> np.ndarray:
        """``p`` with every point closer than ``clearance`` moved out to it along the normal."""
        sd, d = self.query(p)
        c = np.broadcast_to(np.asarray(clearance, dtype=np.float64), sd.shape)
        short = sd < c
        out = p.copy()
        out[short] += (c[short] - sd[short])[:, None] * d[short]
        return out


@dataclass
class _Body:
    vertices: np.ndarray        # (V, 3) float64 rest vertices of the shape
    faces: np.ndarray           # (F, 3) skin faces
    joints: dict                # name -> (3,) float64
    arm: np.ndarray             # (V,) bool, vertices driven mostly by the arms
    surface: _BodySurface


def _measure_body(body: "BodyModel", betas: torch.Tensor | None) -> _Body:
    rest_v, rest_j = body.rest(betas)
    v = rest_v.detach().cpu().double().numpy()
    j = rest_j.detach().cpu().double().numpy()
    names = body.joint_names
    required = ("root", "spine03", "neck01", "upperarm01.L", "upperarm01.R", "lowerarm01.L", "lowerarm01.R",
                "lowerleg01.L", "lowerleg01.R", "foot.L", "foot.R")
    missing = [n for n in required if n not in body.joint_index]
    if missing:
        raise GarmentError(f"garments are designed on the anny rig; body '{body.name}' lacks joints "
                           f"{', '.join(missing)}")
    joints = {n: j[i] for i, n in enumerate(names)}
    arm_cols = [i for i, n in enumerate(names) if n.startswith(_ARM_JOINT_PREFIXES)]
    weights = body.weights.detach().cpu().double().numpy()
    arm = weights[:, arm_cols].sum(1) > 0.5
    faces = body_collision_faces(body)
    return _Body(v, faces, joints, arm, _BodySurface(v, faces))


# ------------------------------------------------------------------------------------------------
# Mesh helpers
# ------------------------------------------------------------------------------------------------
def _unique_edges(faces: np.ndarray) -> np.ndarray:
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return np.unique(np.sort(e, axis=1), axis=0)


def _grid_faces(index: np.ndarray, wrap: bool) -> np.ndarray:
    """Triangles of a (rows, cols) grid of vertex indices; ``wrap`` closes it around the columns.

    Quads are split along alternating diagonals (a checkerboard), which keeps the triangulation
    free of a preferred direction; orientation is fixed afterwards by :func:`_orient`.
    """
    rows, cols = index.shape
    faces = []
    for r in range(rows - 1):
        for c in range(cols if wrap else cols - 1):
            c1 = (c + 1) % cols
            a, b, d, e = index[r, c], index[r, c1], index[r + 1, c], index[r + 1, c1]
            if (r + c) % 2 == 0:
                faces += [(a, b, e), (a, e, d)]
            else:
                faces += [(a, b, d), (b, e, d)]
    return np.asarray(faces, dtype=np.int64).reshape(-1, 3)


def _orient(faces: np.ndarray, vertices: np.ndarray, surface: _BodySurface) -> np.ndarray:
    """Faces wound consistently (each shared edge used in opposite directions), normals outward.

    Orientation spreads from one face of each connected component across shared edges; the
    component is then flipped if its normals point towards the body on average.
    """
    faces = faces.copy()
    F = faces.shape[0]
    edge_faces: dict[tuple[int, int], list[int]] = {}
    for f in range(F):
        for k in range(3):
            a, b = int(faces[f, k]), int(faces[f, (k + 1) % 3])
            edge_faces.setdefault((min(a, b), max(a, b)), []).append(f)
    bad = [e for e, fs in edge_faces.items() if len(fs) > 2]
    if bad:
        raise GarmentError(f"garment mesh is not manifold: edge {bad[0]} is shared by {len(edge_faces[bad[0]])} faces")

    def directed(f, a, b):
        row = faces[f].tolist()
        i = row.index(a)
        return row[(i + 1) % 3] == b

    done = np.zeros(F, bool)
    for seed in range(F):
        if done[seed]:
            continue
        done[seed] = True
        component = [seed]
        queue = deque([seed])
        while queue:
            f = queue.popleft()
            for k in range(3):
                a, b = int(faces[f, k]), int(faces[f, (k + 1) % 3])
                for g in edge_faces[(min(a, b), max(a, b))]:
                    if g == f:
                        continue
                    if not done[g]:
                        if directed(g, a, b):  # same direction as in f: flip g
                            faces[g] = faces[g, ::-1]
                        done[g] = True
                        component.append(g)
                        queue.append(g)
                    elif directed(g, a, b):
                        raise GarmentError("garment mesh is not orientable")
        comp = np.asarray(component)
        tri = vertices[faces[comp]]
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        centroid = tri.mean(1)
        _, outward = surface.query(centroid)
        if np.einsum("ij,ij->", normal, outward) < 0:
            faces[comp] = faces[comp][:, ::-1]
    return faces


def _vertex_neighbours(faces: np.ndarray, V: int) -> tuple[list[np.ndarray], np.ndarray]:
    """Neighbour lists of every vertex, and a mask of boundary vertices. Boundary vertices get
    only their boundary neighbours, so smoothing slides them along the opening, not across it."""
    e = _unique_edges(faces)
    ef = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    key = np.sort(ef, axis=1)
    _, counts = np.unique(key, axis=0, return_counts=True)
    # np.unique(axis=0) sorts the same way for `e` and `key`, so counts align with e.
    boundary_edges = e[counts == 1]
    is_boundary = np.zeros(V, bool)
    is_boundary[boundary_edges.reshape(-1)] = True
    nbrs: list[list[int]] = [[] for _ in range(V)]
    for a, b in e.tolist():
        nbrs[a].append(b)
        nbrs[b].append(a)
    bnbrs: list[list[int]] = [[] for _ in range(V)]
    for a, b in boundary_edges.tolist():
        bnbrs[a].append(b)
        bnbrs[b].append(a)
    out = [np.asarray(bnbrs[i] if is_boundary[i] else nbrs[i], dtype=np.int64) for i in range(V)]
    return out, is_boundary


def _laplacian_matrix(nbrs: list[np.ndarray]):
    rows, cols, vals = [], [], []
    for i, n in enumerate(nbrs):
        if len(n) == 0:
            continue
        rows += [i] * len(n)
        cols += n.tolist()
        vals += [1.0 / len(n)] * len(n)
    V = len(nbrs)
    return sp.csr_matrix((vals, (rows, cols)), shape=(V, V))


def _vertex_normals(p: np.ndarray, faces: np.ndarray) -> np.ndarray:
    tri = p[faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    vn = np.zeros_like(p)
    for k in range(3):
        np.add.at(vn, faces[:, k], fn)
    return vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-12)


def _relax(p: np.ndarray, faces: np.ndarray, surface: _BodySurface, clearance: np.ndarray | float, iterations: int,
           tangential_iterations: int = 0, lam: float = 0.5, mu: float = -0.53) -> np.ndarray:
    """Taubin smoothing (lam/mu: smooths without shrinking) alternating with a push-out to
    ``clearance`` from the body, then ``tangential_iterations`` of smoothing within the surface
    (the Laplacian less its normal component: evens out the vertex spacing without changing the
    shape) each followed by the push-out. ``faces`` must be consistently oriented."""
    nbrs, _ = _vertex_neighbours(faces, p.shape[0])
    W = _laplacian_matrix(nbrs)
    p = p.copy()
    for _ in range(iterations):
        for step in (lam, mu):
            p += step * (W @ p - p)
        p = surface.push_out(p, clearance)
    for _ in range(tangential_iterations):
        n = _vertex_normals(p, faces)
        delta = W @ p - p
        delta -= np.einsum("ij,ij->i", delta, n)[:, None] * n
        p = surface.push_out(p + lam * delta, clearance)
    return p


def _ring_radii(body: _Body, centre: np.ndarray, angles: np.ndarray, z_lo: float, z_hi: float,
                sector: float) -> np.ndarray:
    """(N,) largest distance from the vertical axis through ``centre`` of the non-arm body
    vertices with z in [z_lo, z_hi] within +-``sector`` radians of each angle (0 where none)."""
    v = body.vertices
    sel = (~body.arm) & (v[:, 2] >= z_lo) & (v[:, 2] <= z_hi)
    d = v[sel, :2] - centre[None, :2]
    r = np.linalg.norm(d, axis=1)
    th = np.arctan2(d[:, 1], d[:, 0])
    diff = np.abs((th[None, :] - angles[:, None] + np.pi) % (2 * np.pi) - np.pi)  # (N, n)
    inside = diff <= sector
    return np.where(inside, r[None, :], 0.0).max(axis=1) if r.size else np.zeros(angles.shape)


def _smooth_up(r: np.ndarray, sigma: float) -> np.ndarray:
    """Circularly smoothed radii, raised so that they nowhere fall below ``r``."""
    k = np.arange(-3 * int(math.ceil(sigma)), 3 * int(math.ceil(sigma)) + 1)
    w = np.exp(-0.5 * (k / sigma) ** 2)
    w /= w.sum()
    s = sum(wi * np.roll(r, int(ki)) for ki, wi in zip(k, w))
    return s + max(0.0, float((r - s).max()))


# ------------------------------------------------------------------------------------------------
# Skirts
# ------------------------------------------------------------------------------------------------
def _skirt_axis(body: _Body) -> np.ndarray:
    """(2,) x, y of the skirt's vertical axis: the middle of the hips."""
    v = body.vertices
    z_root = body.joints["root"][2]
    sel = (~body.arm) & (np.abs(v[:, 2] - (z_root - 0.05)) < 0.02)
    lo, hi = v[sel, :2].min(0), v[sel, :2].max(0)
    return np.array([0.0, 0.5 * (lo[1] + hi[1])])


def _skirt_rings(body: _Body, centre: np.ndarray, n_around: int, z_top: float, z_bottom: float, n_rings: int,
                 clearance_top: float, clearance: float, flare: float, extra=None) -> tuple[np.ndarray, np.ndarray]:
    """(R, N, 3) ring positions of a skirt layer and (R, N) radii.

    Radius = running maximum (from the waist down) of the body outline + clearance (growing
    from ``clearance_top`` at the waist to ``clearance`` one ring below) + ``flare`` x t^1.5,
    t = 0 at the waist and 1 at the hem; ``extra(t)`` adds more (the outer tier's gap)."""
    angles = -0.5 * np.pi + 2 * np.pi * np.arange(n_around) / n_around  # starts at the front
    zs = np.linspace(z_top, z_bottom, n_rings)
    dz = abs(zs[1] - zs[0])
    sector = 2.5 * 2 * np.pi / n_around
    running = np.zeros(n_around)
    rings, radii = [], []
    for i, z in enumerate(zs):
        outline = _ring_radii(body, centre, angles, z - dz, z + dz if i else z + 0.5 * dz, sector)
        running = np.maximum(running, outline)
        t = (z_top - z) / (z_top - z_bottom)
        c = clearance_top if i == 0 else clearance
        r = _smooth_up(running, sigma=2.0) + c + flare * t ** 1.5
        if extra is not None:
            r = r + extra(t)
        radii.append(r)
        rings.append(np.stack([centre[0] + r * np.cos(angles), centre[1] + r * np.sin(angles),
                               np.full(n_around, z)], axis=1))
    return np.asarray(rings), np.asarray(radii)


def _skirt_heights(body: _Body) -> tuple[float, float, float]:
    """Waist, knee and mid-calf heights of the body."""
    j = body.joints
    z_waist = float(j["spine03"][2])
    z_knee = 0.5 * float(j["lowerleg01.L"][2] + j["lowerleg01.R"][2])
    z_ankle = 0.5 * float(j["foot.L"][2] + j["foot.R"][2])
    return z_waist, z_knee, z_knee - 0.45 * (z_knee - z_ankle)


def _make_skirt(body: _Body) -> dict:
    z_waist, _, z_calf = _skirt_heights(body)
    centre = _skirt_axis(body)
    N, R = 80, 32
    rings, _ = _skirt_rings(body, centre, N, z_waist, z_calf, R, clearance_top=0.010, clearance=0.015,
                            flare=0.13)
    vertices = rings.reshape(-1, 3)
    index = np.arange(N * R).reshape(R, N)
    uv = np.stack(np.meshgrid(np.arange(N) / N, np.linspace(0, 1, R)), axis=-1).reshape(-1, 2)
    return dict(vertices=vertices, faces=_grid_faces(index, wrap=True), uv=uv, pinned=index[:2].reshape(-1),
                layer=np.zeros(N * R), part=np.zeros(N * R))


def _make_dress(body: _Body) -> dict:
    z_waist, z_knee, z_calf = _skirt_heights(body)
    centre = _skirt_axis(body)
    N, R_in, R_out = 72, 30, 14
    inner, r_in = _skirt_rings(body, centre, N, z_waist, z_calf, R_in, clearance_top=0.010, clearance=0.015,
                               flare=0.09)
    z_tier = z_knee + 0.10
    # The outer tier's rings sit at their own heights: take the inner layer's radius there
    # (interpolated between its rings) and add the gap.
    zs_in = np.linspace(z_waist, z_calf, R_in)
    zs_out = np.linspace(z_waist, z_tier, R_out)
    angles = -0.5 * np.pi + 2 * np.pi * np.arange(N) / N
    outer = []
    for i, z in enumerate(zs_out):
        k = np.searchsorted(-zs_in, -z)
        k0, k1 = max(0, k - 1), min(R_in - 1, k)
        w = 0.0 if k0 == k1 else (zs_in[k0] - z) / (zs_in[k0] - zs_in[k1])
        r = (1 - w) * r_in[k0] + w * r_in[k1]
        t = (z_waist - z) / (z_waist - z_tier)
        r = r + 0.012 + 0.06 * t ** 1.3
        outer.append(np.stack([centre[0] + r * np.cos(angles), centre[1] + r * np.sin(angles),
                               np.full(N, z)], axis=1))
    outer = np.asarray(outer)
    vertices = np.concatenate([inner.reshape(-1, 3), outer.reshape(-1, 3)])
    idx_in = np.arange(N * R_in).reshape(R_in, N)
    idx_out = N * R_in + np.arange(N * R_out).reshape(R_out, N)
    faces = np.concatenate([_grid_faces(idx_in, True), _grid_faces(idx_out, True)])
    u = np.arange(N) / N
    uv = np.concatenate([np.stack(np.meshgrid(u, np.linspace(0, 1, R_in)), -1).reshape(-1, 2),
                         np.stack(np.meshgrid(u, np.linspace(0, (z_waist - z_tier) / (z_waist - z_calf), R_out)),
                                  -1).reshape(-1, 2)])
    layer = np.concatenate([np.zeros(N * R_in), np.ones(N * R_out)])
    pinned = np.concatenate([idx_in[:2].reshape(-1), idx_out[:2].reshape(-1)])
    return dict(vertices=vertices, faces=faces, uv=uv, pinned=pinned, layer=layer, part=np.zeros(len(vertices)))


# ------------------------------------------------------------------------------------------------
# T-shirt
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _TshirtLayout:
    """Vertex counts of the t-shirt's structured mesh (see :func:`_make_tshirt`)."""

    a: int = 33  #: vertices of the front (and of the back) arc of a torso ring
    m: int = 3  #: vertices of each side arc of a torso ring
    J: int = 22  #: torso rings, from the hem up to the armpits
    H: int = 14  #: yoke rows above the top torso ring
    s: int = 10  #: vertices of each shoulder seam (the yokes' top rows share them)
    K: int = 10  #: sleeve rings beyond the armhole
    clearance: float = 0.018  #: distance kept from the body, m

    @property
    def N(self) -> int:
        """Vertices of a torso ring."""
        return 2 * self.a + 2 * self.m

    @property
    def L(self) -> int:
        """Vertices of an armhole loop (and of every sleeve ring)."""
        return 2 * self.H + self.m + 1


_TSHIRT = _TshirtLayout()


def _make_tshirt(body: _Body) -> dict:
    """Structured layout (see the module docstring; counts in :class:`_TshirtLayout`):

    torso rings j = 0..J-1 (hem up to the armpits), N = 2a + 2m vertices each, counter-clockwise
    seen from above starting at the front right: front arc (a), left side (m), back arc (a),
    right side (m); front and back yokes (H rows of a vertices above the top ring) whose top
    rows share their outer s vertices (the shoulder seams) and leave the neck opening between;
    each armhole loop (2H + m + 1 vertices: a yoke's outer column, the side arc, the other
    yoke's outer column, the shoulder point) is the first ring of a sleeve of K more rings.
    """
    lay = _TSHIRT
    a, m, H, K, L = lay.a, lay.m, lay.H, lay.K, lay.L
    torso, centre, z_hem = _tshirt_torso(body, lay)
    yoke_front = _tshirt_yoke(torso[-1, 0:a], _tshirt_top_row(body, lay, front=True), centre, H)
    yoke_back = _tshirt_yoke(torso[-1, a + m:2 * a + m], _tshirt_top_row(body, lay, front=False), centre, H)
    pos, torso_idx, front_idx, back_idx = _tshirt_torso_and_yokes(torso, yoke_front, yoke_back, lay)
    faces = [_grid_faces(torso_idx, wrap=True), _grid_faces(front_idx, wrap=False), _grid_faces(back_idx, wrap=False)]
    part = [np.zeros(pos.shape[0])]

    sleeve_pos, sleeve_uv = [], []
    first_new = pos.shape[0]
    for side, part_id in (("L", 1), ("R", 2)):
        loop = _tshirt_armhole_loop(side, torso_idx, front_idx, back_idx, lay)
        sleeve_pos.append(_tshirt_sleeve_rings(body, side, pos[loop], lay).reshape(-1, 3))
        ids = first_new + np.arange(K * L).reshape(K, L)
        first_new += K * L
        faces.append(_grid_faces(np.concatenate([loop[None], ids]), wrap=True))
        u, v = np.meshgrid(np.arange(L) / L, np.arange(1, K + 1) / K)
        sleeve_uv.append(np.stack([u, v], -1).reshape(-1, 2))
        part.append(np.full(K * L, part_id))
    pos = np.concatenate([pos] + sleeve_pos)
    faces = np.concatenate(faces)
    part = np.concatenate(part)
    uv = _tshirt_uv(pos, part, centre, z_hem, np.concatenate(sleeve_uv))

    # relax the rough placement: smooth junctions, keep the clearance
    faces = _orient(faces, pos, body.surface)
    pos = _relax(pos, faces, body.surface, lay.clearance, iterations=40, tangential_iterations=40)
    collar = np.concatenate([front_idx[H, lay.s - 1:a - lay.s + 1], back_idx[H, lay.s:a - lay.s]])
    return dict(vertices=pos, faces=faces, uv=np.clip(uv, 0, 1), pinned=np.unique(collar),
                layer=np.zeros(pos.shape[0]), part=part)


def _tshirt_torso(body: _Body, lay: _TshirtLayout) -> tuple[np.ndarray, np.ndarray, float]:
    """(J, N, 3) torso rings from the hem up to the armpits -- a straight-hanging tube: the
    running maximum of the body outline from the armpits down, plus the clearance -- its (2,)
    x, y axis and the hem height."""
    j, v, N, J = body.joints, body.vertices, lay.N, lay.J
    z_hem = float(j["root"][2]) - 0.04
    z_arm = 0.5 * float(j["upperarm01.L"][2] + j["upperarm01.R"][2]) - 0.10
    torso_sel = (~body.arm) & (np.abs(v[:, 2] - z_arm) < 0.03)
    centre = np.array([0.0, 0.5 * (v[torso_sel, 1].min() + v[torso_sel, 1].max())])
    delta = 2 * np.pi / N
    angles = -0.5 * np.pi - 0.5 * (lay.a - 1) * delta + delta * np.arange(N)
    zs = np.linspace(z_hem, z_arm, J)
    dz = zs[1] - zs[0]
    outlines = [_ring_radii(body, centre, angles, z - dz, z + dz, 2.5 * delta) for z in zs]
    running = np.zeros(N)
    radii = [None] * J
    for i in range(J - 1, -1, -1):
        running = np.maximum(running, outlines[i])
        radii[i] = _smooth_up(running, 2.0) + lay.clearance
    torso = np.stack([np.stack([centre[0] + r * np.cos(angles), centre[1] + r * np.sin(angles),
                                np.full(N, z)], 1) for r, z in zip(radii, zs)])
    return torso, centre, z_hem


def _tshirt_top_row(body: _Body, lay: _TshirtLayout, front: bool) -> np.ndarray:
    """(a, 3) top row of the front or back yoke, right to left seen from the front for the front
    yoke and reversed for the back: the shoulder seams (s vertices each, on the shoulders'
    top) with the neckline between them (dipping more in front)."""
    j, v, a, s = body.joints, body.vertices, lay.a, lay.s
    neck = j["neck01"]
    x_nb = 0.075  # half width of the neck opening at the seams
    x_sp = 0.5 * (j["upperarm01.L"][0] - j["upperarm01.R"][0]) + 0.03  # shoulder point

    def shoulder_top(x: float) -> float:
        sel = (np.abs(v[:, 0] - x) < 0.012) & (np.abs(v[:, 1] - neck[1]) < 0.04) & (v[:, 2] < neck[2] + 0.02)
        return float(v[sel, 2].max())

    pts = np.zeros((a, 3))
    for k in range(a):
        if k < s or k >= a - s:
            t = k / (s - 1) if k < s else (a - 1 - k) / (s - 1)  # 0 at the shoulder point
            x = -x_sp + t * (x_sp - x_nb) if k < s else x_sp - t * (x_sp - x_nb)
            pts[k] = (x, neck[1], shoulder_top(x) + lay.clearance)
        else:
            t = (k - (s - 1)) / (a - 2 * s + 1)
            phi = np.pi * (1 - t)
            ry, drop = (0.085, 0.07) if front else (0.07, 0.02)
            z_nb = shoulder_top(x_nb) + lay.clearance
            y = neck[1] - ry * np.sin(phi) if front else neck[1] + ry * np.sin(phi)
            pts[k] = (x_nb * np.cos(phi), y, z_nb - drop * np.sin(phi))
    if not front:
        pts = pts[::-1].copy()  # the back arc runs from left to right
    return pts


def _tshirt_yoke(base: np.ndarray, top: np.ndarray, centre: np.ndarray, H: int) -> np.ndarray:
    """(H, a, 3) yoke rows from the (a, 3) ``base`` (the top torso ring's arc, excluded) up to
    ``top``, bulging outwards from the (2,) axis ``centre`` over the chest and back."""
    rows = []
    for r in range(1, H + 1):
        t = r / H
        p = (1 - t) * base + t * top
        out = np.zeros_like(p)
        out[:, :2] = p[:, :2] - centre[None, :]
        out /= np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-9)
        rows.append(p + 0.04 * np.sin(np.pi * t) * out)
    return np.stack(rows)


def _tshirt_torso_and_yokes(torso: np.ndarray, yoke_front: np.ndarray, yoke_back: np.ndarray,
                            lay: _TshirtLayout) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The torso and yokes as one vertex array: positions (P, 3), and the vertex indices of the
    torso (J, N) and of the front and back yokes (H + 1, a) (row 0: the top torso ring's arc).
    The back yoke's top row reuses the front's shoulder-seam vertices, placed halfway between
    the two designs."""
    a, m, J, N, H, s = lay.a, lay.m, lay.J, lay.N, lay.H, lay.s
    positions = [torso.reshape(-1, 3)]
    torso_idx = np.arange(J * N).reshape(J, N)
    nxt = J * N
    front_idx = np.zeros((H + 1, a), np.int64)
    back_idx = np.zeros((H + 1, a), np.int64)
    front_idx[0] = torso_idx[-1, 0:a]
    back_idx[0] = torso_idx[-1, a + m:2 * a + m]
    front_idx[1:] = nxt + np.arange(H * a).reshape(H, a)
    positions.append(yoke_front.reshape(-1, 3))
    nxt += H * a
    # back yoke: rows 1..H-1 new, top row new only in the neck part (shoulders shared with the front)
    back_idx[1:H] = nxt + np.arange((H - 1) * a).reshape(H - 1, a)
    positions.append(yoke_back[:H - 1].reshape(-1, 3))
    nxt += (H - 1) * a
    for k in range(a):
        if k < s or k >= a - s:
            back_idx[H, k] = front_idx[H, a - 1 - k]
        else:
            back_idx[H, k] = nxt
            positions.append(yoke_back[H - 1, k][None])
            nxt += 1
    pos = np.concatenate(positions)
    for k in list(range(s)) + list(range(a - s, a)):
        pos[front_idx[H, k]] = 0.5 * (yoke_front[H - 1, k] + yoke_back[H - 1, a - 1 - k])
    return pos, torso_idx, front_idx, back_idx


def _tshirt_armhole_loop(side: str, torso_idx: np.ndarray, front_idx: np.ndarray, back_idx: np.ndarray,
                         lay: _TshirtLayout) -> np.ndarray:
    """(L,) vertex indices around the ``side`` ("L" or "R") armhole: the shoulder point, down the
    front yoke's outer column, along the torso's side arc, up the back yoke's outer column."""
    a, m, H, L = lay.a, lay.m, lay.H, lay.L
    if side == "L":  # front outer column is k = a-1, back outer column k = 0, side arc a..a+m-1
        loop = ([front_idx[H, a - 1]] + [front_idx[r, a - 1] for r in range(H - 1, -1, -1)]
                + list(torso_idx[-1, a:a + m]) + [back_idx[r, 0] for r in range(0, H)])
    else:  # front outer column k = 0, back outer column k = a-1, side arc 2a+m..2a+2m-1
        loop = ([front_idx[H, 0]] + [front_idx[r, 0] for r in range(H - 1, -1, -1)]
                + list(torso_idx[-1, 2 * a + m:2 * a + 2 * m][::-1]) + [back_idx[r, a - 1] for r in range(0, H)])
    loop = np.asarray(loop, dtype=np.int64)
    if loop.size != L or np.unique(loop).size != L:  # pragma: no cover - a layout bug
        raise GarmentError(f"t-shirt layout: the {side} armhole loop has {np.unique(loop).size} of {L} vertices")
    return loop


def _tshirt_sleeve_rings(body: _Body, side: str, loop: np.ndarray, lay: _TshirtLayout) -> np.ndarray:
    """(K, L, 3) sleeve rings of the ``side`` arm, blending from the armhole ``loop`` (L, 3) into a
    round cuff around the upper arm, 65% of the way from the shoulder to the elbow."""
    v, L, K = body.vertices, lay.L, lay.K
    shoulder = body.joints[f"upperarm01.{side}"]
    axis = body.joints[f"lowerarm01.{side}"] - shoulder
    length = np.linalg.norm(axis)
    axis /= length
    e1 = np.cross(axis, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    rel = loop - shoulder
    phi = np.unwrap(np.arctan2(rel @ e2, rel @ e1))
    if phi[-1] < phi[0]:  # make the angles increase around the loop
        phi = -phi
        e2 = -e2
    t_loop = rel @ axis
    r_loop = np.linalg.norm(rel - t_loop[:, None] * axis[None], axis=1)
    t_end = 0.65 * length
    arm_sel = body.arm & ((v - shoulder) @ axis > 0.02) & ((v - shoulder) @ axis < t_end + 0.03)
    arm_rel = v[arm_sel] - shoulder
    arm_radius = np.linalg.norm(arm_rel - (arm_rel @ axis)[:, None] * axis, axis=1).max()
    ring_r = arm_radius + lay.clearance + 0.012
    uniform = phi[0] + 2 * np.pi * np.arange(L) / L
    rings = []
    for q in range(1, K + 1):
        w = q / K
        # the cuff is tilted a little with the armhole, which evens out the ring spacing
        t = (1 - w) * t_loop + w * (t_end + 0.5 * (t_loop - t_loop.mean()))
        rad = (1 - w) * r_loop + w * ring_r
        ang = (1 - w) * phi + w * uniform
        rings.append(shoulder[None] + t[:, None] * axis[None]
                     + rad[:, None] * (np.cos(ang)[:, None] * e1[None] + np.sin(ang)[:, None] * e2[None]))
    return np.stack(rings)


def _tshirt_uv(pos: np.ndarray, part: np.ndarray, centre: np.ndarray, z_hem: float,
               sleeve_uv: np.ndarray) -> np.ndarray:
    """(P, 2) uv: torso and yokes (part 0) by angle around ``centre`` and height below the top,
    sleeves (parts 1, 2) from ``sleeve_uv`` (their vertices' uv, in order)."""
    uv = np.zeros((pos.shape[0], 2))
    z_top = float(pos[:, 2].max())
    body_part = part == 0
    rel = pos[body_part, :2] - centre
    uv[body_part, 0] = ((np.arctan2(rel[:, 1], rel[:, 0]) + 0.5 * np.pi) / (2 * np.pi)) % 1.0
    uv[body_part, 1] = (z_top - pos[body_part, 2]) / (z_top - z_hem)
    uv[~body_part] = sleeve_uv
    return uv


_BUILDERS = {"skirt": _make_skirt, "tshirt": _make_tshirt, "dress": _make_dress}


def make_garment(kind: str, body: "BodyModel", betas: torch.Tensor | str | np.ndarray | None = None,
                 name: str | None = None) -> Garment:
    """Build a garment of ``kind`` (see :data:`GARMENT_KINDS`) around ``body.rest(betas)``.

    Args:
        kind: ``"skirt"``, ``"tshirt"`` or ``"dress"``.
        body: the anny body model (the designs use its joint names).
        betas: body shape (tensor, preset name such as ``"round"``, vector, or None = average).
        name: label (default: the kind).
    Raises:
        GarmentError: unknown kind, a body without the anny joints, or a garment that ends up
            closer than :data:`MIN_CLEARANCE` to the body (a bug or an extreme shape).
    """
    if kind not in _BUILDERS:
        raise GarmentError(f"unknown garment kind '{kind}' (known: {', '.join(GARMENT_KINDS)})")
    if betas is None or not isinstance(betas, torch.Tensor):
        betas = body.betas(betas)
    measured = _measure_body(body, betas)
    parts = _BUILDERS[kind](measured)
    vertices = parts["vertices"]
    faces = _orient(parts["faces"], vertices, measured.surface)
    garment = Garment(name=name or kind, kind=kind, vertices=vertices, faces=faces, uv=parts["uv"],
                      pinned=parts["pinned"], color=GARMENT_COLORS[kind],
                      betas=betas.detach().cpu().numpy(), layer=parts["layer"], part=parts["part"])
    sd, _ = measured.surface.query(garment.vertices.astype(np.float64))
    if sd.min() < MIN_CLEARANCE:
        raise GarmentError(f"garment '{garment.name}': a vertex is only {sd.min() * 1000:.1f} mm from the body "
                           f"(at least {MIN_CLEARANCE * 1000:.0f} mm required)")
    return garment


def garment_clearance(vertices: np.ndarray, body_vertices: np.ndarray, body_faces: np.ndarray) -> np.ndarray:
    """(N,) signed distance of ``vertices`` to a closed body surface, positive outside (trimesh).

    Exact closest points (``trimesh.proximity.closest_point``), signed by the normal of the face
    holding the closest point; that sign is reliable for points that are not within a hair of
    the surface, which is what a clearance check needs (and avoids trimesh's slow ray-based
    inside test).
    """
    mesh = trimesh.Trimesh(np.asarray(body_vertices, np.float64), np.asarray(body_faces), process=False)
    p = np.asarray(vertices, np.float64)
    closest, dist, tri = trimesh.proximity.closest_point(mesh, p)
    sign = np.where(np.einsum("ij,ij->i", p - closest, mesh.face_normals[tri]) >= 0, 1.0, -1.0)
    return sign * dist
