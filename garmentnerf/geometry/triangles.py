"""Pure functions on triangles and triangle meshes, shared by the exact projector
(:mod:`~garmentnerf.geometry.projection`) and its dense GPU twin
(:mod:`~garmentnerf.geometry.projection_dense`): the exact closest point on a triangle, the
point-triangle distance in a face's own frame, per-face reach and frame constants, pseudo-normals,
and barycentric interpolation. Shapes are on each signature's docstring.
"""

from __future__ import annotations

import math

import torch

__all__ = ["FEATURE_TOL", "DEGENERATE_SIN", "check_points", "dot_rows", "closest_point_on_triangles",
           "face_frame_distance2", "face_reach", "face_frame_table", "pseudo_normals", "interpolate"]

#: Barycentric coordinates below this count as zero when picking the pseudo-normal feature.
#: Calling a point just inside a face an edge point is harmless (the edge pseudo-normal still
#: has a positive component along the face normal); the reverse could flip the sign at sharp
#: folds.
FEATURE_TOL = 1e-6
#: Faces with twice their area below this times their longest edge squared (sine of the largest
#: angle, roughly) have no usable normal: the fast pair kernel skips them and they are
#: re-evaluated with :func:`closest_point_on_triangles`.
DEGENERATE_SIN = 1e-9


def check_points(name: str, x: torch.Tensor) -> None:
    """Raise unless ``x`` is a finite floating-point (N, 3) tensor (the message names ``name``)."""
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {tuple(x.shape)}")
    if not x.is_floating_point():
        raise TypeError(f"{name} must be floating point, got {x.dtype}")
    if x.numel() and not bool(torch.isfinite(x).all()):
        bad = int((~torch.isfinite(x).all(dim=1)).sum())
        raise ValueError(f"{name} contains NaN or Inf ({bad} of {x.shape[0]} rows)")


def dot_rows(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Dot products along the last axis: (..., 3) x (..., 3) -> (...)."""
    return (x * y).sum(-1)


def closest_point_on_triangles(points: torch.Tensor, a: torch.Tensor, b: torch.Tensor,
                               c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Exact closest point on triangle ``(a[i], b[i], c[i])`` to ``points[i]``, vectorised.

    The candidates are those of Ericson's Voronoi-region test (Real-Time Collision Detection,
    5.1.5): the projection onto the face plane when it falls inside the triangle, and the
    clamped projections onto the three edges (which cover the corner regions). Rather than
    branching on signs of sub-areas, the closest candidate is kept, its distance measured as the
    explicit residual ``|p - candidate|``: the same answer for a proper triangle, while a
    zero-area triangle (collinear or coincident corners) simply reduces to its edges, so it
    never divides by a vanishing area and never returns NaN, and a badly rounded interior
    candidate of a sliver can only win if it really is closer.

    Args:
        points, a, b, c: (N, 3) float32 or float64, same dtype.
    Returns:
        closest (N, 3) the closest point on each triangle.
        bary (N, 3) its barycentric coordinates w.r.t. (a, b, c): non-negative, sum 1, and
        exactly zero for the corners not involved when the point is on an edge or a corner.
    """
    for name, x in (("points", points), ("a", a), ("b", b), ("c", c)):
        if x.ndim != 2 or x.shape[1] != 3 or not x.is_floating_point():
            raise ValueError(f"closest_point_on_triangles: {name} must be a float (N, 3) tensor, "
                             f"got {tuple(x.shape)} {x.dtype}")
    if not (points.shape == a.shape == b.shape == c.shape) or len({x.dtype for x in (points, a, b, c)}) > 1:
        raise ValueError("closest_point_on_triangles: points, a, b, c must have the same shape and dtype, got "
                         f"{[(tuple(x.shape), x.dtype) for x in (points, a, b, c)]}")
    dtype = points.dtype
    tiny = torch.finfo(dtype).tiny
    # Component-wise on contiguous rows: reductions over a trailing axis of 3 are slow on the CPU.
    px, py, pz = points.T.contiguous()
    ax, ay, az = a.T.contiguous()
    bx, by, bz = b.T.contiguous()
    cx, cy, cz = c.T.contiguous()
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    apx, apy, apz = px - ax, py - ay, pz - az

    def residual2(v, w):
        rx = apx - v * abx - w * acx
        ry = apy - v * aby - w * acy
        rz = apz - v * abz - w * acz
        return rx * rx + ry * ry + rz * rz

    def safe_ratio(num, den):
        return torch.where(den > tiny, num / den.clamp_min(tiny), torch.zeros_like(num)).clamp_(0.0, 1.0)

    saa = abx * abx + aby * aby + abz * abz
    scc = acx * acx + acy * acy + acz * acz
    # Interior: barycentrics as ratios of signed areas (cross products, not the normal
    # equations, whose determinant cancels badly for thin triangles).
    nx, ny, nz = aby * acz - abz * acy, abz * acx - abx * acz, abx * acy - aby * acx
    nn = nx * nx + ny * ny + nz * nz
    proper = nn > (torch.finfo(dtype).eps ** 2) * saa * scc + tiny
    inv_nn = torch.where(proper, 1.0 / torch.where(proper, nn, torch.ones_like(nn)), torch.zeros_like(nn))
    v = ((apy * acz - apz * acy) * nx + (apz * acx - apx * acz) * ny + (apx * acy - apy * acx) * nz) * inv_nn
    w = ((aby * apz - abz * apy) * nx + (abz * apx - abx * apz) * ny + (abx * apy - aby * apx) * nz) * inv_nn
    inside = proper & (v >= 0) & (w >= 0) & (v + w <= 1)
    best = torch.where(inside, residual2(v, w), math.inf)
    zero = torch.zeros_like(v)
    bu, bv, bw = (1.0 - v - w).clamp_(min=0.0), v, w  # clamp: v + w <= 1 may round to 1 - v - w < 0

    def keep(d2, u_, v_, w_):
        nonlocal best, bu, bv, bw
        take = d2 < best
        best = torch.where(take, d2, best)
        bu, bv, bw = torch.where(take, u_, bu), torch.where(take, v_, bv), torch.where(take, w_, bw)

    t = safe_ratio(apx * abx + apy * aby + apz * abz, saa)  # edge ab
    keep(residual2(t, zero), 1.0 - t, t, zero)
    t = safe_ratio(apx * acx + apy * acy + apz * acz, scc)  # edge ac
    keep(residual2(zero, t), 1.0 - t, zero, t)
    bcx, bcy, bcz = cx - bx, cy - by, cz - bz
    t = safe_ratio((px - bx) * bcx + (py - by) * bcy + (pz - bz) * bcz, bcx * bcx + bcy * bcy + bcz * bcz)  # edge bc
    keep(residual2(1.0 - t, t), zero, 1.0 - t, t)

    bary = torch.stack([bu, bv, bw], dim=1)
    closest = torch.stack([bu * ax + bv * bx + bw * cx, bu * ay + bv * by + bw * cy,
                           bu * az + bv * bz + bw * cz], dim=1)
    return closest, bary


def face_frame_distance2(px: torch.Tensor, py: torch.Tensor, pz: torch.Tensor, frame) -> torch.Tensor:
    """Squared point-triangle distances in each face's own frame (any matching shapes).

    Args:
        px, py, pz: the query minus the face's corner a, in world axes.
        frame: the 16 per-face constants after a in the pair table
            (e1, e2, e3 axes; bx, 1/bx; cx, cy, 1/|c|^2; cx - bx, 1/|c - b|^2).
    Returns:
        the squared height over the plane plus the squared 2-D distance to the triangle: zero
        inside it, else the least distance to its three edges (segments, so corners are
        covered). Degenerate faces come out wrong here; callers redo them.
    """
    e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z, bx, ibx, cx, cy, iscc, cbx, isbc = frame
    x = px * e1x + py * e1y + pz * e1z
    y = px * e2x + py * e2y + pz * e2z
    z = px * e3x + py * e3y + pz * e3z
    # Edge ab (the x axis).
    s = (x * ibx).clamp_(0.0, 1.0)
    dx = x - s * bx
    d2 = dx * dx + y * y
    # Edge ac.
    s = ((x * cx + y * cy) * iscc).clamp_(0.0, 1.0)
    dx, dy = x - s * cx, y - s * cy
    d2 = torch.minimum(d2, dx * dx + dy * dy)
    # Edge bc.
    xb = x - bx
    s = ((xb * cbx + y * cy) * isbc).clamp_(0.0, 1.0)
    dx, dy = xb - s * cbx, y - s * cy
    d2 = torch.minimum(d2, dx * dx + dy * dy)
    # Inside: left of every directed edge (counter-clockwise about e3).
    inside = (y >= 0) & (cx * y <= cy * x) & (cbx * y >= cy * xb)
    return torch.where(inside, 0.0, d2).add_(z * z)


def face_reach(a: torch.Tensor, b: torch.Tensor, c: torch.Tensor,
               tiny: float = 1e-300) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The reach of every face: the radius of its smallest enclosing circle (see the module
    docstring), never under-estimated by rounding.

    Args:
        a, b, c: (F, 3) the corners.
        tiny: the least twice-area divided by (degenerate faces).
    Returns:
        (F,) reach, (F, 3) ``(b - a) x (c - a)``, (F,) its norm (twice the area).
    """
    la, lb, lc = (c - b).norm(dim=1), (a - c).norm(dim=1), (b - a).norm(dim=1)
    cross = torch.cross(b - a, c - a, dim=1)
    twice_area = cross.norm(dim=1)
    longest = torch.maximum(torch.maximum(la, lb), lc)
    sq = la * la + lb * lb + lc * lc
    obtuse = 2.0 * longest * longest >= sq  # L^2 >= sum of the other two squares
    circum = la * lb * lc / (2.0 * twice_area.clamp_min(tiny))
    r_face = torch.where(obtuse, 0.5 * longest, torch.minimum(circum, longest))  # min(): rounding guard
    return r_face * (1.0 + 1e-6) + 1e-12, cross, twice_area  # never under-estimate by rounding


def face_frame_table(vertices: torch.Tensor, faces: torch.Tensor,
                     tiny: float = 1e-300) -> tuple[torch.Tensor, torch.Tensor]:
    """(19, F) per-face constants of the pair kernel (:func:`face_frame_distance2`) in the dtype
    of ``vertices`` (V, 3), and (F,) degenerate flags; ``faces`` (F, 3) long.

    Each face gets an orthonormal frame (e1 along ab, e3 its unit normal) in which it is the
    2-D triangle (0, 0), (bx, 0), (cx, cy) with cy > 0. The kernel then only forms
    coordinate differences, whose rounding error is eps |q - a|; the shorter
    ``|q - a|^2 - |projection|^2`` forms lose all digits for a point near a big face. Rows: a
    (3), e1, e2, e3 (3 each), bx, 1/bx, cx, cy, 1/|c|^2, cx - bx, 1/|c - b|^2.
    """
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    ab, ac = b - a, c - a
    n = torch.cross(ab, ac, dim=1)
    twice_area = n.norm(dim=1)
    longest2 = torch.stack([dot_rows(ab, ab), dot_rows(ac, ac), dot_rows(c - b, c - b)], 1).max(dim=1).values
    degenerate = twice_area <= DEGENERATE_SIN * longest2
    lab = ab.norm(dim=1, keepdim=True)
    e1 = torch.where(lab > 0, ab / lab.clamp_min(tiny), torch.zeros_like(ab))
    e3 = torch.where(degenerate.unsqueeze(1), torch.zeros_like(n), n / twice_area.clamp_min(tiny).unsqueeze(1))
    e2 = torch.cross(e3, e1, dim=1)
    bx, cx, cy = lab.squeeze(1), dot_rows(ac, e1), dot_rows(ac, e2)
    cbx = cx - bx
    scc, sbc = cx * cx + cy * cy, cbx * cbx + cy * cy

    def inv(x):
        return torch.where(x > 0, 1.0 / x.clamp_min(tiny), torch.zeros_like(x))

    table = torch.stack([
        a[:, 0], a[:, 1], a[:, 2], e1[:, 0], e1[:, 1], e1[:, 2], e2[:, 0], e2[:, 1], e2[:, 2],
        e3[:, 0], e3[:, 1], e3[:, 2], bx, inv(bx), cx, cy, inv(scc), cbx, inv(sbc),
    ], dim=0)
    return table, degenerate


def pseudo_normals(vertices: torch.Tensor, faces: torch.Tensor, face_edges: torch.Tensor, num_edges: int,
                   cross: torch.Tensor, twice_area: torch.Tensor,
                   tiny: float = 1e-300) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Unit face normals (F, 3) and angle-weighted edge (E, 3) and vertex (V, 3) pseudo-normals.

    Args:
        vertices: (V, 3); faces: (F, 3) long; face_edges: (F, 3) the edge opposite each corner.
        num_edges: E.
        cross, twice_area: of :func:`face_reach` (a zero-area face gets a zero normal).
        tiny: the least twice-area divided by.
    """
    n = cross / twice_area.clamp_min(tiny).unsqueeze(1)
    n = torch.where((twice_area > 0).unsqueeze(1), n, torch.zeros_like(n))
    edge_n = torch.zeros(num_edges, 3, dtype=vertices.dtype, device=vertices.device)
    edge_n.index_add_(0, face_edges.reshape(-1), n.repeat_interleave(3, dim=0))
    corner = torch.stack([vertices[faces[:, i]] for i in range(3)], dim=1)
    e_next = corner.roll(-1, dims=1) - corner
    e_prev = corner.roll(1, dims=1) - corner
    angle = torch.atan2(torch.cross(e_next, e_prev, dim=-1).norm(dim=-1), dot_rows(e_next, e_prev))  # (F, 3)
    vert_n = torch.zeros(vertices.shape[0], 3, dtype=vertices.dtype, device=vertices.device)
    vert_n.index_add_(0, faces.reshape(-1), (angle.unsqueeze(-1) * n.unsqueeze(1)).reshape(-1, 3))
    return n, edge_n, vert_n


def interpolate(values: torch.Tensor, faces: torch.Tensor, face: torch.Tensor, bary: torch.Tensor) -> torch.Tensor:
    """Barycentric interpolation of per-vertex values at points given as (face, bary).

    Args:
        values: (V, C) or (V,) per-vertex values, e.g. canonical vertex positions, or (U, 2) UVs.
        faces: (F, 3) long indices into ``values`` (``uv_faces`` for UVs).
        face: (N,) long face index of each point.
        bary: (N, 3) barycentric coordinates w.r.t. the corners of ``faces[face]``.
    Returns:
        (N, C), or (N,) for 1-D ``values``; in the dtype of ``values`` promoted with ``bary``.
    """
    squeeze = values.ndim == 1
    vals = values.unsqueeze(-1) if squeeze else values
    if face.ndim != 1 or bary.shape != (face.shape[0], 3):
        raise ValueError(f"interpolate: face must be (N,) and bary (N, 3), got {tuple(face.shape)} and "
                         f"{tuple(bary.shape)}")
    corners = faces.to(device=vals.device, dtype=torch.long)[face.to(vals.device)]  # (N, 3)
    dtype = torch.promote_types(vals.dtype, bary.dtype)
    w = bary.to(device=vals.device, dtype=dtype)
    out = (vals[corners].to(dtype) * w.unsqueeze(-1)).sum(1)
    return out.squeeze(-1) if squeeze else out
