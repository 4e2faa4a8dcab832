"""The exact nearest-face search of :mod:`~garmentnerf.geometry.projection`: a bounding-volume
hierarchy of oriented cylinders over the faces, built once per posed frame, walked by a native
(warp, CPU) kernel once per query point.

Tree
----
The faces are split recursively at the median of their centroids along the longest axis of the
node's centroid box, down to leaves of one or two faces. The tree is complete and implicit
(heap numbering: node ``j`` has children ``2j + 1`` and ``2j + 2``; at depth ``l`` node ``j``
holds the sorted faces ``[floor(j F / 2^l), floor((j + 1) F / 2^l))``), so it is a permutation of
the faces plus per-node bounds.

Each node is bounded by a *cylinder* aligned with the node's mean normal n (the normalised sum
of its faces' area vectors): centre m, radius rho of the corners around the axis, and the slab
``[a_lo, a_hi]`` of their heights ``(v - m) . n``. Both are convex and hold every corner, so
they hold the faces (convex hulls of corners): ``|q - p| >= lb_cyl(q, node)`` for every point p of
the node's faces, with ``lb_cyl^2 = max(0, r - rho)^2 + max(0, a_lo - a, a - a_hi)^2`` (a, r: the
height and axial distance of q). On a body a node's faces are a nearly flat patch, so the slab
is thin and the bound nearly tight; an axis-aligned box (or a sphere) around a tilted or curved
patch sticks out of the surface by about its own size, and a query point at a distance d from the
skin then has to open every node within ``sqrt(2 d size)`` of its foot point: most of the tree
for the samples tens of centimetres off the body.

The nodes high in the tree are not flat (a whole forearm, a leg: a tube, whose mean normal says
little), and there the cylinder is the looser bound; so each node also keeps its axis-aligned
box (the same centre m, half extents e), and the bound used is the larger of the two,
``lb^2 = max(lb_cyl^2, sum_i max(0, |q_i - m_i| - e_i)^2)``: still a lower bound, with no square
root more. On the bundled body walking (``garmentnerf bench``'s 262,144 points within 15 cm of the
skin) the walk then tests 101 bounds and 15.7 faces per point, against 128 and 18.9 with the
cylinder alone, for the same answers (docs/quality.md, "The projection's bound").

Search
------
Depth first, the nearer child first, a node skipped when ``lb^2`` exceeds the best squared
distance found: exact, no certificate to fail, no retry. The point-face distance is that of
:func:`~garmentnerf.geometry.triangles.face_frame_distance2` (the face's own frame), in float64;
degenerate faces (no normal) are measured as their three edges. The points of a batch are walked
in Morton order in blocks; each point starts with the best face of the point before it in its
block as its bound (samples along a ray, and neighbouring rays, share their foot point's
neighbourhood), which prunes most of the walk from the start.

The bounds are grown by ``BOUND_SLACK`` (a nanometre) against rounding, far above the float64
rounding of the coordinates (~1e-16 m), far below anything that would change which faces are
opened.
"""


import functools
import threading
from concurrent.futures import ThreadPoolExecutor

import torch

from garmentnerf.geometry.triangles import FEATURE_TOL, face_frame_table

__all__ = ["FaceBVH", "BOUND_SLACK", "tree_order", "tree_depth"]

#: Metres added to every node bound (radius and slab) against rounding.
BOUND_SLACK = 1e-9
#: Points walked in a row by one kernel thread, each seeded with its predecessor's face.
BLOCK = 16
#: Columns of the per-face kernel table: the 19 rows of face_frame_table, then the corners b, c
#: (a is in the frame rows) and the degenerate flag.
_FACE_COLUMNS = 19 + 6 + 1
#: Columns of the node table: m (3), n (3), rho, a_lo, a_hi, the box's half extents e (3).
_NODE_COLUMNS = 12

#: Fewest blocks a thread is given (smaller launches are not worth a thread).
_MIN_BLOCKS_PER_THREAD = 256

_load_lock = threading.Lock()  # the first launch loads (maybe compiles) the module: one thread at a time
_loaded: list = []
_pools: dict = {}


def _pool(threads: int):
    """A thread pool of ``threads`` workers, kept for the process."""
    with _load_lock:
        if threads not in _pools:
            _pools[threads] = ThreadPoolExecutor(threads, thread_name_prefix="face-bvh")
        return _pools[threads]


_define_lock = threading.Lock()  # the kernels are defined once, by one thread


def _kernels():
    """Import warp (quietly) and define the kernels: once per process, whichever thread asks first
    (two threads defining them at once would redefine warp's module under each other's builds)."""
    with _define_lock:
        return _define_kernels()


@functools.cache
def _define_kernels():
    """See :func:`_kernels`. The compiled kernels are kept in warp's kernel cache, so only the
    first run on a machine compiles them."""
    # local: warp (0.3 s to import) serves only this exact CPU search; on a GPU the body projection
    # uses the dense torch search (BodyPointProjector's "auto") and never loads it
    import warp as wp

    if wp.config.log_level == wp.LOG_INFO:  # the default: hide the banner and module-load messages
        wp.config.log_level = wp.LOG_WARNING
    wp.config.quiet = True
    wp.init()
    wp.set_module_options({"enable_backward": False})  # forward only: half the compile time

    stack_vec = wp.types.vector(length=64, dtype=wp.int32)
    bound_vec = wp.types.vector(length=64, dtype=wp.float64)

    @wp.func
    def segment_d2(px: wp.float64, py: wp.float64, pz: wp.float64, sx: wp.float64, sy: wp.float64,
                   sz: wp.float64, ex: wp.float64, ey: wp.float64, ez: wp.float64):
        dx = ex - sx
        dy = ey - sy
        dz = ez - sz
        dd = dx * dx + dy * dy + dz * dz
        t = wp.float64(0.0)
        if dd > wp.float64(0.0):
            t = wp.clamp(((px - sx) * dx + (py - sy) * dy + (pz - sz) * dz) / dd, wp.float64(0.0),
                         wp.float64(1.0))
        rx = px - sx - t * dx
        ry = py - sy - t * dy
        rz = pz - sz - t * dz
        return rx * rx + ry * ry + rz * rz

    @wp.func
    def face_d2(T: wp.array2d(dtype=wp.float64), k: int, qx: wp.float64, qy: wp.float64, qz: wp.float64):
        # face_frame_distance2 of garmentnerf.geometry.triangles, for one point and one face.
        px = qx - T[k, 0]
        py = qy - T[k, 1]
        pz = qz - T[k, 2]
        if T[k, 25] != wp.float64(0.0):  # degenerate: the union of its edges
            d = segment_d2(qx, qy, qz, T[k, 0], T[k, 1], T[k, 2], T[k, 19], T[k, 20], T[k, 21])
            d = wp.min(d, segment_d2(qx, qy, qz, T[k, 0], T[k, 1], T[k, 2], T[k, 22], T[k, 23], T[k, 24]))
            return wp.min(d, segment_d2(qx, qy, qz, T[k, 19], T[k, 20], T[k, 21], T[k, 22], T[k, 23], T[k, 24]))
        x = px * T[k, 3] + py * T[k, 4] + pz * T[k, 5]
        y = px * T[k, 6] + py * T[k, 7] + pz * T[k, 8]
        z = px * T[k, 9] + py * T[k, 10] + pz * T[k, 11]
        bx = T[k, 12]
        cx = T[k, 14]
        cy = T[k, 15]
        cbx = T[k, 17]
        zero = wp.float64(0.0)
        one = wp.float64(1.0)
        xb = x - bx
        if y >= zero and cx * y <= cy * x and cbx * y >= cy * xb:
            return z * z
        s = wp.clamp(x * T[k, 13], zero, one)
        dx = x - s * bx
        d2 = dx * dx + y * y
        s = wp.clamp((x * cx + y * cy) * T[k, 16], zero, one)
        dx = x - s * cx
        dy = y - s * cy
        d2 = wp.min(d2, dx * dx + dy * dy)
        s = wp.clamp((xb * cbx + y * cy) * T[k, 18], zero, one)
        dx = xb - s * cbx
        dy = y - s * cy
        d2 = wp.min(d2, dx * dx + dy * dy)
        return d2 + z * z

    @wp.func
    def node_lb2(N: wp.array2d(dtype=wp.float64), j: int, qx: wp.float64, qy: wp.float64, qz: wp.float64):
        px = qx - N[j, 0]
        py = qy - N[j, 1]
        pz = qz - N[j, 2]
        a = px * N[j, 3] + py * N[j, 4] + pz * N[j, 5]
        wx = px - a * N[j, 3]
        wy = py - a * N[j, 4]
        wz = pz - a * N[j, 5]
        dr = wp.max(wp.sqrt(wx * wx + wy * wy + wz * wz) - N[j, 6], wp.float64(0.0))
        da = wp.max(wp.max(N[j, 7] - a, a - N[j, 8]), wp.float64(0.0))
        ex = wp.max(wp.abs(px) - N[j, 9], wp.float64(0.0))
        ey = wp.max(wp.abs(py) - N[j, 10], wp.float64(0.0))
        ez = wp.max(wp.abs(pz) - N[j, 11], wp.float64(0.0))
        return wp.max(dr * dr + da * da, ex * ex + ey * ey + ez * ez)

    @wp.func
    def safe_ratio(num: wp.float64, den: wp.float64, tiny: wp.float64):
        if den > tiny:
            return wp.clamp(num / den, wp.float64(0.0), wp.float64(1.0))
        return wp.float64(0.0)

    @wp.func
    def residual2(apx: wp.float64, apy: wp.float64, apz: wp.float64, abx: wp.float64, aby: wp.float64,
                  abz: wp.float64, acx: wp.float64, acy: wp.float64, acz: wp.float64, v: wp.float64, w: wp.float64):
        rx = apx - v * abx - w * acx
        ry = apy - v * aby - w * acy
        rz = apz - v * abz - w * acz
        return rx * rx + ry * ry + rz * rz

    @wp.func
    def finish(T: wp.array2d(dtype=wp.float64), S: wp.array2d(dtype=wp.float64), k: int, px: wp.float64,
               py: wp.float64, pz: wp.float64, feature_tol: wp.float64, out: wp.array2d(dtype=wp.float64), i: int):
        # closest_point_on_triangles of garmentnerf.geometry.triangles (float64) for the winner,
        # then PosedSurface._sign: the same candidates, order and ties, so the same answer.
        zero = wp.float64(0.0)
        one = wp.float64(1.0)
        tiny = wp.float64(2.2250738585072014e-308)
        eps = wp.float64(2.220446049250313e-16)
        ax = T[k, 0]
        ay = T[k, 1]
        az = T[k, 2]
        abx = T[k, 19] - ax
        aby = T[k, 20] - ay
        abz = T[k, 21] - az
        acx = T[k, 22] - ax
        acy = T[k, 23] - ay
        acz = T[k, 24] - az
        apx = px - ax
        apy = py - ay
        apz = pz - az
        saa = abx * abx + aby * aby + abz * abz
        scc = acx * acx + acy * acy + acz * acz
        nx = aby * acz - abz * acy
        ny = abz * acx - abx * acz
        nz = abx * acy - aby * acx
        nn = nx * nx + ny * ny + nz * nz
        v = zero
        w = zero
        best = wp.float64(1.0e308) * wp.float64(10.0)  # inf
        if nn > eps * eps * saa * scc + tiny:
            inv = one / nn
            v = ((apy * acz - apz * acy) * nx + (apz * acx - apx * acz) * ny + (apx * acy - apy * acx) * nz) * inv
            w = ((aby * apz - abz * apy) * nx + (abz * apx - abx * apz) * ny + (abx * apy - aby * apx) * nz) * inv
            if v >= zero and w >= zero and v + w <= one:
                best = residual2(apx, apy, apz, abx, aby, abz, acx, acy, acz, v, w)
        bu = wp.max(one - v - w, zero)
        bv = v
        bw = w
        t = safe_ratio(apx * abx + apy * aby + apz * abz, saa, tiny)  # edge ab
        d2 = residual2(apx, apy, apz, abx, aby, abz, acx, acy, acz, t, zero)
        if d2 < best:
            best = d2
            bu = one - t
            bv = t
            bw = zero
        t = safe_ratio(apx * acx + apy * acy + apz * acz, scc, tiny)  # edge ac
        d2 = residual2(apx, apy, apz, abx, aby, abz, acx, acy, acz, zero, t)
        if d2 < best:
            best = d2
            bu = one - t
            bv = zero
            bw = t
        bcx = acx - abx
        bcy = acy - aby
        bcz = acz - abz
        t = safe_ratio((px - T[k, 19]) * bcx + (py - T[k, 20]) * bcy + (pz - T[k, 21]) * bcz,
                       bcx * bcx + bcy * bcy + bcz * bcz, tiny)  # edge bc
        d2 = residual2(apx, apy, apz, abx, aby, abz, acx, acy, acz, one - t, t)
        if d2 < best:
            best = d2
            bu = zero
            bv = one - t
            bw = t
        cx = bu * ax + bv * T[k, 19] + bw * T[k, 22]
        cy = bu * ay + bv * T[k, 20] + bw * T[k, 23]
        cz = bu * az + bv * T[k, 21] + bw * T[k, 24]
        ox = px - cx
        oy = py - cy
        oz = pz - cz
        d = wp.sqrt(ox * ox + oy * oy + oz * oz)
        # Sign: the pseudo-normal of the feature holding the closest point (S: face normal, the
        # normals of the edges opposite corners 0, 1, 2, the normals of corners 0, 1, 2).
        z0 = bu <= feature_tol
        z1 = bv <= feature_tol
        z2 = bw <= feature_tol
        nzero = int(z0) + int(z1) + int(z2)
        col = int(0)
        if nzero == 1:
            col = 3
            if z1:
                col = 6
            if z2:
                col = 9
        elif nzero >= 2:
            col = 12
            if bv > bu:
                col = 15
            if bw > wp.max(bu, bv):
                col = 18
        dot = ox * S[k, col] + oy * S[k, col + 1] + oz * S[k, col + 2]
        out[i, 0] = bu
        out[i, 1] = bv
        out[i, 2] = bw
        out[i, 3] = cx
        out[i, 4] = cy
        out[i, 5] = cz
        out[i, 6] = d
        if dot < zero:
            out[i, 7] = -d
        else:
            out[i, 7] = d

    @wp.kernel
    def nearest_faces(points: wp.array2d(dtype=wp.float64), T: wp.array2d(dtype=wp.float64),
                      N: wp.array2d(dtype=wp.float64), first_leaf: int, num_faces: int, num_points: int,
                      block: int, out_face: wp.array(dtype=wp.int32), out_d2: wp.array(dtype=wp.float64),
                      out_work: wp.array2d(dtype=wp.int32), S: wp.array2d(dtype=wp.float64),
                      feature_tol: wp.float64, out_geom: wp.array2d(dtype=wp.float64)):
        b = wp.tid()
        start = b * block
        end = wp.min(start + block, num_points)
        leaves = first_leaf + 1
        seed = int(-1)
        for i in range(start, end):
            qx = points[i, 0]
            qy = points[i, 1]
            qz = points[i, 2]
            best = wp.float64(1.0e300)
            best_face = int(-1)
            if seed >= 0:
                best = face_d2(T, seed, qx, qy, qz)
                best_face = seed
            stack = stack_vec()
            bound = bound_vec()
            stack[0] = 0
            bound[0] = wp.float64(0.0)
            sp = int(1)
            n_nodes = int(0)
            n_faces = int(0)
            while sp > 0:
                sp -= 1
                node = stack[sp]
                if bound[sp] > best:
                    continue
                if node >= first_leaf:
                    leaf = node - first_leaf
                    lo = (leaf * num_faces) // leaves
                    hi = ((leaf + 1) * num_faces) // leaves
                    n_faces += hi - lo
                    for k in range(lo, hi):
                        d2 = face_d2(T, k, qx, qy, qz)
                        # Ties go to the lowest slot: the answer does not depend on the seed.
                        if d2 < best or (d2 == best and k < best_face):
                            best = d2
                            best_face = k
                else:
                    c1 = 2 * node + 1
                    c2 = c1 + 1
                    l1 = node_lb2(N, c1, qx, qy, qz)
                    l2 = node_lb2(N, c2, qx, qy, qz)
                    n_nodes += 2
                    if l2 < l1:  # c1 nearer first: it is pushed last
                        c1, c2 = c2, c1
                        l1, l2 = l2, l1
                    if l2 <= best:
                        stack[sp] = c2
                        bound[sp] = l2
                        sp += 1
                    if l1 <= best:
                        stack[sp] = c1
                        bound[sp] = l1
                        sp += 1
            out_face[i] = best_face
            out_d2[i] = best
            out_work[i, 0] = n_nodes
            out_work[i, 1] = n_faces
            seed = best_face
            if S.shape[0] > 0:
                finish(T, S, best_face, qx, qy, qz, feature_tol, out_geom, i)

    @wp.kernel
    def node_cylinders(corners: wp.array2d(dtype=wp.float64), num_faces: int, first_node: int,
                       out: wp.array2d(dtype=wp.float64), slack: wp.float64):
        # One node per thread: its faces are the sorted range of its level (heap numbering).
        j = wp.tid() + first_node
        level = int(0)
        while (1 << (level + 1)) - 1 <= j:
            level += 1
        n = 1 << level
        idx = j - (n - 1)
        lo = (idx * num_faces) // n
        hi = ((idx + 1) * num_faces) // n
        big = wp.float64(1.0e300)
        x0 = big
        y0 = big
        z0 = big
        x1 = -big
        y1 = -big
        z1 = -big
        sx = wp.float64(0.0)
        sy = wp.float64(0.0)
        sz = wp.float64(0.0)
        for k in range(lo, hi):
            for c in range(3):
                x0 = wp.min(x0, corners[k, 3 * c])
                y0 = wp.min(y0, corners[k, 3 * c + 1])
                z0 = wp.min(z0, corners[k, 3 * c + 2])
                x1 = wp.max(x1, corners[k, 3 * c])
                y1 = wp.max(y1, corners[k, 3 * c + 1])
                z1 = wp.max(z1, corners[k, 3 * c + 2])
            ux = corners[k, 3] - corners[k, 0]
            uy = corners[k, 4] - corners[k, 1]
            uz = corners[k, 5] - corners[k, 2]
            vx = corners[k, 6] - corners[k, 0]
            vy = corners[k, 7] - corners[k, 1]
            vz = corners[k, 8] - corners[k, 2]
            sx += uy * vz - uz * vy
            sy += uz * vx - ux * vz
            sz += ux * vy - uy * vx
        mx = wp.float64(0.5) * (x0 + x1)
        my = wp.float64(0.5) * (y0 + y1)
        mz = wp.float64(0.5) * (z0 + z1)
        norm = wp.sqrt(sx * sx + sy * sy + sz * sz)
        nx = wp.float64(0.0)
        ny = wp.float64(0.0)
        nz = wp.float64(1.0)
        if norm > wp.float64(0.0):
            nx = sx / norm
            ny = sy / norm
            nz = sz / norm
        rho2 = wp.float64(0.0)
        a_lo = big
        a_hi = -big
        for k in range(lo, hi):
            for c in range(3):
                px = corners[k, 3 * c] - mx
                py = corners[k, 3 * c + 1] - my
                pz = corners[k, 3 * c + 2] - mz
                a = px * nx + py * ny + pz * nz
                wx = px - a * nx
                wy = py - a * ny
                wz = pz - a * nz
                rho2 = wp.max(rho2, wx * wx + wy * wy + wz * wz)
                a_lo = wp.min(a_lo, a)
                a_hi = wp.max(a_hi, a)
        out[j, 0] = mx
        out[j, 1] = my
        out[j, 2] = mz
        out[j, 3] = nx
        out[j, 4] = ny
        out[j, 5] = nz
        out[j, 6] = wp.sqrt(rho2) + slack
        out[j, 7] = a_lo - slack
        out[j, 8] = a_hi + slack
        out[j, 9] = wp.float64(0.5) * (x1 - x0) + slack
        out[j, 10] = wp.float64(0.5) * (y1 - y0) + slack
        out[j, 11] = wp.float64(0.5) * (z1 - z0) + slack

    return wp, nearest_faces, node_cylinders


class FaceBVH:
    """The cylinder tree of one posed frame (see the module docstring).

    Args:
        vertices: (V, 3) float64 posed vertices (CPU).
        faces: (F, 3) long.
        normals: (face (F, 3), edge (E, 3), vertex (V, 3) pseudo-normals, face_edges (F, 3) the
            edge opposite each corner): if given, :meth:`query` also solves every winner in full
            (closest point, barycentrics, signed distance).
        order: (F,) the tree's face order (:func:`tree_order`), e.g. computed once per topology
            on a reference pose; default: computed here from ``vertices``. Any order gives the
            same exact answers (up to ties); one that groups faces that are near each other in
            this pose gives tighter bounds and a faster search.
    Attributes:
        order: (F,) the face of every sorted slot (the kernel's face numbering).
        depth: the level of the leaves (``2^depth`` leaves of one or two faces).
    """

    def __init__(self, vertices: torch.Tensor, faces: torch.Tensor, order: torch.Tensor | None = None,
                 normals: tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor] | None = None):
        F = faces.shape[0]
        self.num_faces = F
        self.depth = tree_depth(F)
        self.order = tree_order(vertices, faces) if order is None else order
        faces_s = faces[self.order]
        corners = vertices[faces_s]  # (F, 3, 3)
        table, degenerate = face_frame_table(vertices, faces_s)
        T = torch.empty(F, _FACE_COLUMNS, dtype=torch.float64)
        T[:, :19] = table.T
        T[:, 19:22] = corners[:, 1]
        T[:, 22:25] = corners[:, 2]
        T[:, 25] = degenerate.to(torch.float64)
        self.face_table = T.contiguous()
        self.node_table = _node_cylinders(corners, self.depth)
        if normals is None:
            self.sign_table = torch.zeros(0, 21, dtype=torch.float64)
        else:
            face_n, edge_n, vertex_n, face_edges = normals
            o = self.order
            self.sign_table = torch.cat([face_n[o], edge_n[face_edges[o]].reshape(F, 9),
                                         vertex_n[faces_s].reshape(F, 9)], dim=1).to(torch.float64).contiguous()

    def query(self, points: torch.Tensor, threads: int = 1
              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """The nearest face of every point of ``points`` (M, 3) float64, walked in the given
        order (put nearby points next to each other).

        Args:
            threads: kernel launches run at once on slices of the points (warp's CPU kernels
                are serial; a launch releases the GIL).
        Returns:
            (M,) face index (of the original ``faces``), (M,) float64 squared distance, (M, 2)
            int32 work: bounds tested and faces tested per point, and with ``normals`` (M, 8)
            float64: barycentrics (in ``faces`` corner order), closest point, distance, signed
            distance, as :func:`~garmentnerf.geometry.triangles.closest_point_on_triangles` and
            the pseudo-normal sign of :mod:`~garmentnerf.geometry.projection` give them (else None).
        """
        wp, kernel, _ = _kernels()
        M = points.shape[0]
        pts = points.to(torch.float64).contiguous()
        face = torch.empty(M, dtype=torch.int32)
        d2 = torch.empty(M, dtype=torch.float64)
        work = torch.empty(M, 2, dtype=torch.int32)
        solve = self.sign_table.shape[0] > 0
        geom = torch.empty(M if solve else 0, 8, dtype=torch.float64)
        blocks = (M + BLOCK - 1) // BLOCK
        tables = (wp.from_torch(self.face_table, dtype=wp.float64), wp.from_torch(self.node_table, dtype=wp.float64))

        def launch(b0: int, b1: int) -> None:
            r0, r1 = b0 * BLOCK, min(b1 * BLOCK, M)
            wp.launch(kernel, dim=b1 - b0, device="cpu",
                      inputs=[wp.from_torch(pts[r0:r1], dtype=wp.float64), *tables, (1 << self.depth) - 1,
                              self.num_faces, r1 - r0, BLOCK],
                      outputs=[wp.from_torch(face[r0:r1], dtype=wp.int32), wp.from_torch(d2[r0:r1], dtype=wp.float64),
                               wp.from_torch(work[r0:r1], dtype=wp.int32),
                               wp.from_torch(self.sign_table, dtype=wp.float64), FEATURE_TOL,
                               wp.from_torch(geom[r0:r1] if solve else geom, dtype=wp.float64)])

        threads = max(1, min(int(threads), blocks // _MIN_BLOCKS_PER_THREAD))
        if M == 0:
            pass
        elif threads == 1 or not _loaded:
            with _load_lock:
                launch(0, blocks)
                _loaded.append(True)
        else:
            cuts = [blocks * i // threads for i in range(threads + 1)]
            jobs = [_pool(threads).submit(launch, a, b) for a, b in zip(cuts[:-1], cuts[1:])]
            for job in jobs:
                job.result()
        return self.order[face.long()], d2, work, (geom if solve else None)


def tree_depth(num_faces: int) -> int:
    """Level of the leaves: ``2^depth <= F < 2^(depth + 1)``, so leaves hold one or two faces."""
    return max(0, int(num_faces).bit_length() - 1)


def tree_order(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """(F,) the face order of the tree of the mesh ``vertices (V, 3)``, ``faces (F, 3)``: see
    :func:`_median_split_order`."""
    v = vertices.detach().to("cpu", torch.float64)
    return _median_split_order(v[faces].mean(dim=1), tree_depth(faces.shape[0]))


def _median_split_order(centroids: torch.Tensor, depth: int) -> torch.Tensor:
    """(F,) permutation of the faces: every node of the implicit tree, level by level, sorted
    along the longest axis of its centroids' box, so that its two halves are its children."""
    F = centroids.shape[0]
    order = torch.arange(F)
    pos = torch.arange(F)
    for level in range(depth):
        n = 1 << level
        bounds = (torch.arange(n + 1) * F) // n
        seg = torch.searchsorted(bounds, pos, right=True) - 1
        c = centroids[order]
        lo = torch.full((n, 3), torch.inf, dtype=c.dtype).scatter_reduce(0, seg[:, None].expand(F, 3), c, "amin")
        hi = torch.full((n, 3), -torch.inf, dtype=c.dtype).scatter_reduce(0, seg[:, None].expand(F, 3), c, "amax")
        axis = (hi - lo).argmax(dim=1)
        key = c.gather(1, axis[seg][:, None]).squeeze(1)
        # Sort by key within each segment: the segment rank dominates the (normalised) key.
        span = (hi - lo).amax(dim=1).clamp_min(1e-300)
        unit = (key - lo.gather(1, axis[:, None]).squeeze(1)[seg]) / span[seg]  # in [0, 1]
        perm = torch.argsort(seg.to(torch.float64) * 4.0 + unit.clamp(0.0, 1.0) * 2.0, stable=True)
        order = order[perm]
    return order


def _node_cylinders(corners: torch.Tensor, depth: int) -> torch.Tensor:
    """(2^(depth+1) - 1, 12) the bounds of every node (heap order) from the corners (F, 3, 3) of the
    sorted faces: centre, unit axis, radius, slab [a_lo, a_hi] of the cylinder; half extents of the
    box around the same centre."""
    wp, _, kernel = _kernels()
    num_nodes = (1 << (depth + 1)) - 1
    out = torch.empty(num_nodes, _NODE_COLUMNS, dtype=torch.float64)
    flat = corners.reshape(-1, 9).contiguous()
    with _load_lock:
        wp.launch(kernel, dim=num_nodes, device="cpu",
                  inputs=[wp.from_torch(flat, dtype=wp.float64), corners.shape[0], 0,
                          wp.from_torch(out, dtype=wp.float64), BOUND_SLACK])
    return out
