"""The exact nearest-face search of :mod:`~garmentnerf.geometry.projection`: a bounding-volume
hierarchy of oriented boxes over the faces, built once per posed frame, walked by a native
(warp, CPU) kernel once per query point.

Tree
----
The faces are split recursively at the median of their centroids along the longest axis of the
node's centroid box, down to leaves of two or three faces. The tree is complete and implicit
(heap numbering: node ``j`` has children ``2j + 1`` and ``2j + 2``; at depth ``l`` node ``j``
holds the sorted faces ``[floor(j F / 2^l), floor((j + 1) F / 2^l))``), so it is a permutation of
the faces plus per-node bounds.

Each node is bounded by an *oriented box* whose first axis is the node's mean normal n (the
normalised sum of its faces' area vectors) and whose other two are the principal directions of
its corners in the plane across n: centre m, and per axis the interval of the corners' heights
along it. The box is convex and holds every corner, so it holds the faces (convex hulls of
corners): ``|q - p| >= lb_obb(q, node)`` for every point p of the node's faces, with
``lb_obb^2 = sum_k max(0, lo_k - a_k, a_k - hi_k)^2`` (a_k: the height of q along axis k). On a
body a low node's faces are a nearly flat patch, so the box is a thin slab and the bound nearly
tight; a node high in the tree is a tube (a forearm, a leg), whose normals sum across it, so the
box's in-plane principal axis runs along the tube. An axis-aligned box (or a sphere) around a
tilted or curved patch sticks out of the surface by about its own size, and a query point at a
distance d from the skin then has to open every node within ``sqrt(2 d size)`` of its foot point:
most of the tree for the samples tens of centimetres off the body. Each node also keeps its
axis-aligned box (the same centre m, half extents e), which is the tighter of the two for some
nodes high in the tree, and the bound used is the larger of the two,
``lb^2 = max(lb_obb^2, sum_i max(0, |q_i - m_i| - e_i)^2)``: still a lower bound.

On the bundled body walking (``garmentnerf bench``'s 262,144 points within 15 cm of the skin) the
walk tests 65 bounds and 23.2 faces per point, against 101 and 15.7 with the normal-aligned
cylinders, leaves of one or two faces and walks from the root this replaced (and 128 and 18.9
with the cylinders alone), for the same answers; the projection is about 1.4 times faster
(docs/lab/ledger.md, "The projection's bound" and "The projection's walk").

Search
------
The points of a batch are walked in Morton order (:func:`~garmentnerf.geometry.projection`'s
``walk_order``) in blocks of ``BLOCK``: samples along a ray, and neighbouring rays, share their
foot point's neighbourhood. Each point but a block's first starts at the leaf of its
predecessor's face: it measures that leaf's faces, then walks up to the root, and at every level
tests the sibling of the node it comes from, searching the sibling's subtree depth first (the
nearer child first) when the sibling's bound does not exceed the best squared distance found. A
block's first point searches from the root the same way. A node is skipped only when its bound
exceeds the best distance, so the answer is exact whatever the start: no certificate to fail, no
retry; ties go to the lowest slot. The point-face distance is that of
:func:`~garmentnerf.geometry.triangles.face_frame_distance2` (the face's own frame), in float64;
degenerate faces (no normal) are measured as their three edges.

The bounds are grown by ``BOUND_SLACK`` (a nanometre) against rounding, far above the float64
rounding of the coordinates (~1e-16 m), far below anything that would change which faces are
opened.
"""


import functools
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import torch

from garmentnerf.geometry.triangles import FEATURE_TOL, face_frame_table
from garmentnerf.interrupts import deferred_interrupts

__all__ = ["FaceBVH", "NearestFaces", "BOUND_SLACK", "DEFAULT_CHUNK_SIZE", "MORTON_MIN_POINTS", "tree_order", "tree_depth",
           "morton_order", "morton_codes_reference"]

#: Metres added to every node bound (each interval and half extent) against rounding.
BOUND_SLACK = 1e-9
#: Points walked per round of kernel launches (a Ctrl-C acts between rounds).
DEFAULT_CHUNK_SIZE = 65536
#: Points walked in a row by one kernel thread, each starting at its predecessor's face.
BLOCK = 64
#: Columns of the per-face kernel table: the 19 rows of face_frame_table, then the corners b, c
#: (a is in the frame rows) and the degenerate flag.
_FACE_COLUMNS = 19 + 6 + 1
#: Columns of the node table: m (3), the oriented box's axes n, t1, t2 (9), its intervals [lo, hi]
#: along n, t1, t2 (6), the axis-aligned box's half extents e (3).
_NODE_COLUMNS = 21

#: Fewest blocks a launch is given (a launch costs tens of microseconds; 16 blocks, a millisecond of work).
_MIN_BLOCKS_PER_LAUNCH = 16
#: Launches per thread and round: the threads share the round's work as they finish, so a slow
#: stretch of points (far from the body, or a shared core) does not leave the other threads idle.
_LAUNCHES_PER_THREAD = 4

_load_lock = threading.Lock()  # the first launch loads (maybe compiles) the module: one thread at a time
_loaded: list = []


def _mark_loaded() -> None:
    """Record that warp has loaded the kernels' module (under ``_load_lock``): later launches may run at once."""
    if not _loaded:
        _loaded.append(True)


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
        # columns: m (0:3), n (3:6), t1 (6:9), t2 (9:12), lo/hi along n, t1, t2 (12:18), box e (18:21)
        px = qx - N[j, 0]
        py = qy - N[j, 1]
        pz = qz - N[j, 2]
        a = px * N[j, 3] + py * N[j, 4] + pz * N[j, 5]
        b = px * N[j, 6] + py * N[j, 7] + pz * N[j, 8]
        c = px * N[j, 9] + py * N[j, 10] + pz * N[j, 11]
        zero = wp.float64(0.0)
        da = wp.max(wp.max(N[j, 12] - a, a - N[j, 13]), zero)
        db = wp.max(wp.max(N[j, 14] - b, b - N[j, 15]), zero)
        dc = wp.max(wp.max(N[j, 16] - c, c - N[j, 17]), zero)
        ex = wp.max(wp.abs(px) - N[j, 18], zero)
        ey = wp.max(wp.abs(py) - N[j, 19], zero)
        ez = wp.max(wp.abs(pz) - N[j, 20], zero)
        return wp.max(da * da + db * db + dc * dc, ex * ex + ey * ey + ez * ez)

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
    def nearest_faces(points: wp.array2d(dtype=wp.float64), rows: wp.array(dtype=wp.int64),
                      T: wp.array2d(dtype=wp.float64), N: wp.array2d(dtype=wp.float64),
                      slot_face: wp.array(dtype=wp.int32), first_leaf: int, num_faces: int, num_walked: int,
                      block: int, out_face: wp.array(dtype=wp.int32), out_d2: wp.array(dtype=wp.float64),
                      out_work: wp.array2d(dtype=wp.int32), S: wp.array2d(dtype=wp.float64),
                      feature_tol: wp.float64, out_geom: wp.array2d(dtype=wp.float64),
                      V: wp.array2d(dtype=wp.float64), out_values: wp.array2d(dtype=wp.float64)):
        # Thread b walks the points rows[b * block : (b + 1) * block] in that order; every output
        # goes to the point's own row.
        b = wp.tid()
        start = b * block
        end = wp.min(start + block, num_walked)
        leaves = first_leaf + 1
        seed = int(-1)
        for w in range(start, end):
            i = int(rows[w])
            qx = points[i, 0]
            qy = points[i, 1]
            qz = points[i, 2]
            best = wp.float64(1.0e300)
            best_face = int(-1)
            stack = stack_vec()
            bound = bound_vec()
            cur = int(0)
            n_nodes = int(0)
            n_faces = int(0)
            # Start at the leaf of the seed's face (else at the root) and, when the stack runs
            # out, walk up from it, searching each sibling on the way whose bound admits it.
            if seed >= 0:
                cur = first_leaf + ((seed + 1) * leaves - 1) // num_faces
            stack[0] = cur
            bound[0] = wp.float64(0.0)
            sp = int(1)
            while sp > 0 or cur > 0:
                if sp == 0:
                    sib = cur + 1
                    if cur % 2 == 0:
                        sib = cur - 1
                    cur = (cur - 1) // 2
                    l = node_lb2(N, sib, qx, qy, qz)
                    n_nodes += 1
                    if l <= best:
                        stack[0] = sib
                        bound[0] = l
                        sp = 1
                    continue
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
            out_face[i] = slot_face[best_face]
            out_d2[i] = best
            out_work[i, 0] = n_nodes
            out_work[i, 1] = n_faces
            seed = best_face
            if S.shape[0] > 0:
                finish(T, S, best_face, qx, qy, qz, feature_tol, out_geom, i)
                # the corner values at the closest point (V: per slot, corners a, b, c one after another)
                if V.shape[0] > 0:
                    nv = V.shape[1] // 3
                    for c in range(nv):
                        out_values[i, c] = (out_geom[i, 0] * V[best_face, c] + out_geom[i, 1] * V[best_face, nv + c]
                                            + out_geom[i, 2] * V[best_face, 2 * nv + c])

    @wp.func
    def corner_offset(corners: wp.array2d(dtype=wp.float64), k: int, c: int, m: wp.vec3d):
        return wp.vec3d(corners[k, 3 * c], corners[k, 3 * c + 1], corners[k, 3 * c + 2]) - m

    @wp.kernel
    def node_boxes(corners: wp.array2d(dtype=wp.float64), num_faces: int, first_node: int,
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
        # an orthonormal frame (n, u0, u1) (Duff et al. 2017, "Building an orthonormal basis,
        # revisited"), then the principal axes (t1, t2) of the corners' spread across n
        sgn = wp.float64(1.0)
        if nz < wp.float64(0.0):
            sgn = wp.float64(-1.0)
        aa = wp.float64(-1.0) / (sgn + nz)
        bb = nx * ny * aa
        u0x = wp.float64(1.0) + sgn * nx * nx * aa
        u0y = sgn * bb
        u0z = -sgn * nx
        u1x = bb
        u1y = sgn + ny * ny * aa
        u1z = -ny
        m = wp.vec3d(mx, my, mz)
        u0 = wp.vec3d(u0x, u0y, u0z)
        u1 = wp.vec3d(u1x, u1y, u1z)
        sxx = wp.float64(0.0)
        sxy = wp.float64(0.0)
        syy = wp.float64(0.0)
        for k in range(lo, hi):
            for c in range(3):
                p = corner_offset(corners, k, c, m)
                x = wp.dot(p, u0)
                y = wp.dot(p, u1)
                sxx += x * x
                sxy += x * y
                syy += y * y
        th = wp.float64(0.5) * wp.atan2(wp.float64(2.0) * sxy, sxx - syy)
        axis = wp.vec3d(nx, ny, nz)
        t1 = wp.cos(th) * u0 + wp.sin(th) * u1
        t2 = wp.cross(axis, t1)
        lo3 = wp.vec3d(big, big, big)
        hi3 = wp.vec3d(-big, -big, -big)
        for k in range(lo, hi):
            for c in range(3):
                p = corner_offset(corners, k, c, m)
                h = wp.vec3d(wp.dot(p, axis), wp.dot(p, t1), wp.dot(p, t2))
                lo3 = wp.min(lo3, h)
                hi3 = wp.max(hi3, h)
        out[j, 0] = mx
        out[j, 1] = my
        out[j, 2] = mz
        out[j, 3] = nx
        out[j, 4] = ny
        out[j, 5] = nz
        for a in range(3):
            out[j, 6 + a] = t1[a]
            out[j, 9 + a] = t2[a]
            out[j, 12 + 2 * a] = lo3[a] - slack
            out[j, 13 + 2 * a] = hi3[a] + slack
        out[j, 18] = wp.float64(0.5) * (x1 - x0) + slack
        out[j, 19] = wp.float64(0.5) * (y1 - y0) + slack
        out[j, 20] = wp.float64(0.5) * (z1 - z0) + slack

    @wp.func
    def spread_bits(v: int):  # bit i of a 10-bit v -> bit 3 i
        v = (v | (v << 16)) & 0x030000FF
        v = (v | (v << 8)) & 0x0300F00F
        v = (v | (v << 4)) & 0x030C30C3
        return (v | (v << 2)) & 0x09249249

    @wp.kernel
    def morton_codes(points: wp.array2d(dtype=wp.float64), lo: wp.vec3d, scale: wp.vec3d,
                     out: wp.array(dtype=wp.int32)):
        # morton_codes_reference's codes: 10 bits per axis over the points' box, interleaved x, y, z
        i = wp.tid()
        x = spread_bits(int((points[i, 0] - lo[0]) * scale[0]))
        y = spread_bits(int((points[i, 1] - lo[1]) * scale[1]))
        z = spread_bits(int((points[i, 2] - lo[2]) * scale[2]))
        out[i] = x | (y << 1) | (z << 2)

    return _Kernels(wp, nearest_faces, node_boxes, morton_codes)


class _Kernels(NamedTuple):
    warp: object  # the warp module
    nearest_faces: object
    node_boxes: object
    morton_codes: object


#: Points below which :func:`morton_order` keeps the given order (sorting them costs more than it saves).
MORTON_MIN_POINTS = 1024


def _morton_cells(points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(lo (3,), scale (3,)) float64: a point's cell along each axis is ``(p - lo) * scale`` truncated,
    0 to 1023 over the points' box."""
    lo, hi = points.min(dim=0).values, points.max(dim=0).values
    return lo, 1023.0 / (hi - lo).clamp_min(1e-12)


def morton_order(points: torch.Tensor) -> torch.Tensor:
    """(N,) permutation putting points (N, 3) float64 in Morton (Z-curve) order over their bounding box
    (10 bits per axis; fewer than :data:`MORTON_MIN_POINTS` points keep their order): the codes in one
    kernel pass, then a sort (:func:`morton_codes_reference` computes the codes in torch)."""
    N = points.shape[0]
    if N < MORTON_MIN_POINTS:
        return torch.arange(N)
    kernels = _kernels()
    wp = kernels.warp
    pts = points.to(torch.float64).contiguous()
    lo, scale = _morton_cells(pts)
    codes = torch.empty(N, dtype=torch.int32)
    args = [wp.from_torch(pts, dtype=wp.float64), wp.vec3d(*lo.tolist()), wp.vec3d(*scale.tolist()),
            wp.from_torch(codes, dtype=wp.int32)]
    if _loaded:
        wp.launch(kernels.morton_codes, dim=N, device="cpu", inputs=args)
    else:
        with _load_lock:  # the first launch of the module loads it
            wp.launch(kernels.morton_codes, dim=N, device="cpu", inputs=args)
            _mark_loaded()
    return torch.argsort(codes)


def morton_codes_reference(points: torch.Tensor) -> torch.Tensor:
    """(N,) int64 the Morton codes of points (N, 3) that :func:`morton_order` sorts by, in torch
    operations (the reference the tests compare its kernel with)."""
    pts = points.to(torch.float64)
    lo, scale = _morton_cells(pts)
    cells = ((pts - lo) * scale).to(torch.int64)

    def spread(v):  # bit i of v -> bit 3 i
        v = (v | (v << 16)) & 0x030000FF
        v = (v | (v << 8)) & 0x0300F00F
        v = (v | (v << 4)) & 0x030C30C3
        return (v | (v << 2)) & 0x09249249

    return spread(cells[:, 0]) | (spread(cells[:, 1]) << 1) | (spread(cells[:, 2]) << 2)


class NearestFaces(NamedTuple):
    """What :meth:`FaceBVH.query` finds for M points."""

    face: torch.Tensor
    """(M,) long: the nearest face (a row of the tree's ``faces``)."""
    d2: torch.Tensor
    """(M,) float64: the squared distance to it."""
    work: torch.Tensor
    """(M, 2) int32: node bounds and faces tested per point."""
    geom: torch.Tensor | None
    """(M, 8) float64 with the tree's ``normals``: barycentrics (in ``faces`` corner order),
    closest point, distance, signed distance, as
    :func:`~garmentnerf.geometry.triangles.closest_point_on_triangles` and the pseudo-normal sign
    of :mod:`~garmentnerf.geometry.projection` give them; else None."""
    values: torch.Tensor | None
    """(M, C) float64 with ``normals`` and ``corner_values``: the corner values interpolated at the
    closest point; else None."""


class FaceBVH:
    """The oriented-box tree of one posed frame (see the module docstring).

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
        corner_values: (F, 3, C) values at the corners of every face (e.g. canonical positions and
            UVs), interpolated at every closest point when ``normals`` is given.
        threads: the node bounds are computed on two threads when this is 2 or more.
    Attributes:
        order: (F,) the face of every sorted slot (the kernel's face numbering).
        depth: the level of the leaves (``2^depth`` leaves of two or three faces).
    """

    def __init__(self, vertices: torch.Tensor, faces: torch.Tensor, order: torch.Tensor | None = None,
                 normals: tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor] | None = None,
                 corner_values: torch.Tensor | None = None, threads: int = 1):
        F = faces.shape[0]
        self.num_faces = F
        self.depth = tree_depth(F)
        self.order = tree_order(vertices, faces) if order is None else order
        self.slot_face = self.order.to(torch.int32).contiguous()
        faces_s = faces[self.order]
        corners = vertices[faces_s]  # (F, 3, 3)
        table, degenerate = face_frame_table(vertices, faces_s)
        T = torch.empty(F, _FACE_COLUMNS, dtype=torch.float64)
        T[:, :19] = table.T
        T[:, 19:22] = corners[:, 1]
        T[:, 22:25] = corners[:, 2]
        T[:, 25] = degenerate.to(torch.float64)
        self.face_table = T.contiguous()
        self.node_table = _node_boxes(corners, self.depth, threads)
        if normals is None:
            self.sign_table = torch.zeros(0, 21, dtype=torch.float64)
        else:
            face_n, edge_n, vertex_n, face_edges = normals
            o = self.order
            self.sign_table = torch.cat([face_n[o], edge_n[face_edges[o]].reshape(F, 9),
                                         vertex_n[faces_s].reshape(F, 9)], dim=1).to(torch.float64).contiguous()
        if corner_values is None:
            self.value_table = torch.zeros(0, 0, dtype=torch.float64)
        else:
            if corner_values.ndim != 3 or corner_values.shape[:2] != (F, 3):
                raise ValueError(f"corner_values must be (F={F}, 3, C), got {tuple(corner_values.shape)}")
            self.value_table = corner_values[self.order].to(torch.float64).reshape(F, -1).contiguous()

    def query(self, points: torch.Tensor, threads: int = 1, walk_order: torch.Tensor | None = None,
              chunk_size: int = DEFAULT_CHUNK_SIZE) -> "NearestFaces":
        """The nearest face of every point of ``points`` (M, 3) float64.

        Args:
            threads: kernel launches run at once on slices of the walk (warp's CPU kernels are
                serial; a launch releases the GIL).
            walk_order: (M,) the rows of ``points`` in the order to walk them (put nearby points
                next to each other: see the module docstring); default: as given.
            chunk_size: points walked per round of launches; a Ctrl-C acts between rounds.
        Returns:
            :class:`NearestFaces`, in the rows of ``points``.
        """
        kernels = _kernels()
        wp, kernel = kernels.warp, kernels.nearest_faces
        M = points.shape[0]
        pts = points.to(torch.float64).contiguous()
        rows = torch.arange(M) if walk_order is None else walk_order.to(torch.int64).contiguous()
        if rows.shape != (M,):
            raise ValueError(f"walk_order must hold the {M} rows of points, got shape {tuple(rows.shape)}")
        face = torch.empty(M, dtype=torch.int32)
        d2 = torch.empty(M, dtype=torch.float64)
        work = torch.empty(M, 2, dtype=torch.int32)
        solve = self.sign_table.shape[0] > 0
        geom = torch.empty(M if solve else 0, 8, dtype=torch.float64)
        values = torch.empty(M if solve else 0, self.value_table.shape[1] // 3, dtype=torch.float64)
        points_wp = wp.from_torch(pts, dtype=wp.float64)
        tables = [wp.from_torch(self.face_table, dtype=wp.float64), wp.from_torch(self.node_table, dtype=wp.float64),
                  wp.from_torch(self.slot_face, dtype=wp.int32), (1 << self.depth) - 1, self.num_faces]
        outputs = [wp.from_torch(face, dtype=wp.int32), wp.from_torch(d2, dtype=wp.float64),
                   wp.from_torch(work, dtype=wp.int32), wp.from_torch(self.sign_table, dtype=wp.float64),
                   FEATURE_TOL, wp.from_torch(geom, dtype=wp.float64),
                   wp.from_torch(self.value_table, dtype=wp.float64), wp.from_torch(values, dtype=wp.float64)]

        def launch(w0: int, w1: int) -> None:  # walks rows[w0:w1]
            wp.launch(kernel, dim=(w1 - w0 + BLOCK - 1) // BLOCK, device="cpu",
                      inputs=[points_wp, wp.from_torch(rows[w0:w1], dtype=wp.int64), *tables, w1 - w0, BLOCK],
                      outputs=outputs)

        for c0 in range(0, M, max(1, int(chunk_size))):
            c1 = min(c0 + max(1, int(chunk_size)), M)
            blocks = (c1 - c0 + BLOCK - 1) // BLOCK
            # a multiple of the threads, so that none is left with one launch more than the others
            per_thread = max(1, min(_LAUNCHES_PER_THREAD, blocks // (_MIN_BLOCKS_PER_LAUNCH * max(1, int(threads)))))
            n_launches = max(1, min(int(threads) * per_thread, blocks // _MIN_BLOCKS_PER_LAUNCH))
            with deferred_interrupts():  # the kernel threads must finish before a Ctrl-C acts
                if threads <= 1 or n_launches == 1 or not _loaded:
                    with _load_lock:
                        launch(c0, c1)
                        _mark_loaded()
                else:
                    cuts = [c0 + min(c1 - c0, BLOCK * (blocks * i // n_launches)) for i in range(n_launches + 1)]
                    pool = _pool(min(int(threads), n_launches))
                    jobs = [pool.submit(launch, a, b) for a, b in zip(cuts[:-1], cuts[1:])]
                    for job in jobs:
                        job.result()
        return NearestFaces(face.long(), d2, work, geom if solve else None,
                            values if solve and self.value_table.shape[0] > 0 else None)


def tree_depth(num_faces: int) -> int:
    """Level of the leaves: ``2^(depth + 1) <= F < 2^(depth + 2)``, so leaves hold two or three
    faces (one or more for F < 4)."""
    return max(0, int(num_faces).bit_length() - 2)


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


def _node_boxes(corners: torch.Tensor, depth: int, threads: int = 1) -> torch.Tensor:
    """(2^(depth+1) - 1, 21) the bounds of every node (heap order) from the corners (F, 3, 3) of the
    sorted faces: the centre m of the corners' box; the oriented box's axes n (the mean normal),
    t1, t2 (the principal directions of the corners across n); its intervals [lo, hi] of the
    corners' heights about m along n, t1, t2; the axis-aligned box's half extents around m.
    Every level reads all the corners, so with two or more ``threads`` the top levels and the
    lower ones are computed at once (the lower part gets fewer levels: its many small nodes cost
    more per corner)."""
    kernels = _kernels()
    wp, kernel = kernels.warp, kernels.node_boxes
    num_nodes = (1 << (depth + 1)) - 1
    out = torch.empty(num_nodes, _NODE_COLUMNS, dtype=torch.float64)
    arrays = (wp.from_torch(corners.reshape(-1, 9).contiguous(), dtype=wp.float64), wp.from_torch(out, dtype=wp.float64))

    def launch(j0: int, j1: int) -> None:  # the nodes [j0, j1)
        wp.launch(kernel, dim=j1 - j0, device="cpu", inputs=[arrays[0], corners.shape[0], j0, arrays[1], BOUND_SLACK])

    if threads <= 1 or depth < 2 or not _loaded:
        with _load_lock:
            launch(0, num_nodes)
            _mark_loaded()
    else:
        cut = (1 << ((depth + 4) // 2)) - 1  # the first node of the lower levels (their nodes cost more each)
        jobs = [_pool(2).submit(launch, 0, cut), _pool(2).submit(launch, cut, num_nodes)]
        for job in jobs:
            job.result()
    return out
