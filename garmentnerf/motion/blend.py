"""Resampling and concatenation of motions.

Rotations are interpolated along the geodesic of SO(3) (quaternion slerp on the shortest arc),
translations linearly. All arithmetic runs in float64 and the results are stored as float32.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Sequence

import torch

from garmentnerf.motion.motion import Motion

if TYPE_CHECKING:  # pragma: no cover
    from garmentnerf.body.model import BodyModel


def _roma():
    """roma, imported at first use (it imports torch._dynamo: seconds of CPU; see
    :mod:`garmentnerf.body.rotations`)."""
    import roma

    return roma


#: Default cross-fade length of :func:`concatenate`, in frames.
DEFAULT_BLEND_FRAMES = 10


# ---- rotation helpers ------------------------------------------------------------------------------
def slerp_rotvec(r0: torch.Tensor, r1: torch.Tensor, t: torch.Tensor | float) -> torch.Tensor:
    """Geodesic interpolation between rotation vectors, per element.

    Args:
        r0, r1: (..., 3) rotation vectors.
        t: weights broadcastable to ``r0.shape[:-1]`` (0 gives r0, 1 gives r1).
    Returns:
        (..., 3) float64 rotation vectors of ``R0 exp(t log(R0^T R1))`` (the shortest arc; the
        same rotation as quaternion slerp with the sign of q1 chosen so that q0 . q1 >= 0).
    """
    R0 = _roma().rotvec_to_rotmat(r0.double())
    R1 = _roma().rotvec_to_rotmat(r1.double())
    rel = _roma().rotmat_to_rotvec(R0.transpose(-1, -2) @ R1)
    t = torch.as_tensor(t, dtype=torch.float64, device=rel.device)
    step = _roma().rotvec_to_rotmat(rel * t.unsqueeze(-1) if t.ndim else rel * t)
    return _roma().rotmat_to_rotvec(R0 @ step)


def yaw_angle(rotmat: torch.Tensor) -> torch.Tensor:
    """(...,) angle of the twist of each (..., 3, 3) rotation about the world up axis (Z).

    From the swing-twist decomposition of the quaternion (x, y, z, w): ``2 atan2(z, w)``. It is
    defined for every rotation except a half turn about a horizontal axis.
    """
    q = _roma().rotmat_to_unitquat(rotmat.double())
    return 2.0 * torch.atan2(q[..., 2], q[..., 3])


def rot_z(angle: torch.Tensor | float) -> torch.Tensor:
    """(..., 3, 3) float64 rotations about +Z by ``angle`` radians."""
    a = torch.as_tensor(angle, dtype=torch.float64)
    c, s = torch.cos(a), torch.sin(a)
    z, o = torch.zeros_like(a), torch.ones_like(a)
    return torch.stack([torch.stack([c, -s, z], -1), torch.stack([s, c, z], -1), torch.stack([z, z, o], -1)], -2)


# ---- resampling --------------------------------------------------------------------------------
def sample_at_times(rotations: torch.Tensor, translation: torch.Tensor, times: torch.Tensor,
                    new_times: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Interpolate frames given at increasing ``times`` (T,) at ``new_times`` (N,).

    Rotations (T, J, 3) are slerped per joint, translations (T, 3) interpolated linearly between
    the two neighbouring frames. Times outside ``[times[0], times[-1]]`` are clamped (the first or
    last frame is held; nothing is extrapolated). Returns float64 tensors.
    """
    times = torch.as_tensor(times, dtype=torch.float64)
    new_times = torch.as_tensor(new_times, dtype=torch.float64)
    T = times.shape[0]
    if rotations.shape[0] != T or translation.shape[0] != T:
        raise ValueError(f"sample_at_times: {T} times for {rotations.shape[0]} rotation / "
                         f"{translation.shape[0]} translation frames")
    if T > 1 and not bool((times[1:] > times[:-1]).all()):
        raise ValueError("sample_at_times: frame times must be strictly increasing")
    rot = rotations.double()
    trans = translation.double()
    if T == 1:
        N = new_times.shape[0]
        return rot.expand(N, -1, -1).clone(), trans.expand(N, -1).clone()
    nt = new_times.clamp(times[0], times[-1])
    hi = torch.searchsorted(times, nt, right=True).clamp(1, T - 1)
    lo = hi - 1
    w = ((nt - times[lo]) / (times[hi] - times[lo])).clamp(0.0, 1.0)
    exact_lo, exact_hi = w <= 1e-12, w >= 1.0 - 1e-12
    r = slerp_rotvec(rot[lo], rot[hi], w[:, None].expand(-1, rot.shape[1]))
    # Reproduce frames that fall on an original time bit-exactly (slerp round-trips lose ~1e-16).
    r = torch.where(exact_lo[:, None, None], rot[lo], torch.where(exact_hi[:, None, None], rot[hi], r))
    t = trans[lo] + w[:, None] * (trans[hi] - trans[lo])
    return r, t


def resample(motion: Motion, fps: float) -> Motion:
    """The motion at another frame rate.

    New frame k is at time ``k / fps`` for every k with ``k / fps <= (T - 1) / motion.fps`` (a
    relative tolerance of 1e-9 absorbs rounding), so the new clip spans the same time as the old
    one up to less than one new frame period: the original last frame is reproduced when its time
    falls on the new grid (e.g. 30 -> 60 fps), otherwise the clip ends at the last new frame
    before it; nothing is extrapolated. Original frames at times on the new grid are reproduced
    exactly. Rotations are slerped, translations interpolated linearly.
    """
    fps = float(fps)
    if not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"resample: fps must be a finite number > 0, got {fps!r}")
    if fps == motion.fps:
        return motion
    last = (motion.num_frames - 1) / motion.fps
    n = int(math.floor(last * fps * (1.0 + 1e-9) + 1e-9)) + 1
    new_times = torch.arange(n, dtype=torch.float64) / fps
    rot, trans = sample_at_times(motion.rotations, motion.translation, motion.times, new_times)
    return Motion(motion.name, list(motion.joint_names), rot.float(), trans.float(), fps, motion.skeleton)


# ---- concatenation -----------------------------------------------------------------------------
def concatenate(motions: Sequence[Motion], blend_frames: int = DEFAULT_BLEND_FRAMES,
                body: "BodyModel | None" = None, betas: torch.Tensor | None = None,
                name: str | None = None, heading_window_s: float = 1.0) -> Motion:
    """Play clips one after another with smooth transitions.

    Each next clip B is first turned about the vertical axis so that its heading at the start
    matches A's heading at the end; its heights are kept. A heading is the circular mean of the
    root's yaw about Z over ``heading_window_s`` seconds (the end of A, the start of B), so the
    sway of the pelvis within a gait cycle does not turn the path (DeepMimic's walk swings its
    pelvis by +-7 degrees). Then the last ``blend_frames`` frames of A and the first
    ``blend_frames`` frames of the turned clip B' overlap and are cross-faded with smoothstep
    weights running from 0 (pure A, at the first overlapping frame) to 1 (pure B', at the
    last): joint rotations and root heights are
    interpolated (slerp, linear), and the horizontal root path is integrated from the blended
    per-frame displacements of A and B', so the root speed always lies between the two clips'
    speeds (a walk into a dance in place decelerates, it never slides back or lurches); after
    the fade B' carries on from where the blend ended. The result has
    ``len(A) + len(B) - blend_frames`` frames. ``blend_frames`` is clamped to the shorter clip's
    length; with 0 the clips are butted end to end, B' starting at A's last root position.

    The heading rotation of B is about the vertical line through the root joint. Its rest
    position is taken from ``body`` (and ``betas``) when given, else assumed to lie at x = y = 0
    (anny's rest root is 1 cm off that line, which then shifts B by at most 2 cm).

    All clips must share fps (resample first), skeleton and joint names; ``joint_names[0]`` is
    taken to be the root.
    """
    motions = list(motions)
    if not motions:
        raise ValueError("concatenate: no motions given")
    if isinstance(blend_frames, bool) or int(blend_frames) != blend_frames or blend_frames < 0:
        raise ValueError(f"concatenate: blend_frames must be an integer >= 0, got {blend_frames!r}")
    first = motions[0]
    for m in motions[1:]:
        if abs(m.fps - first.fps) > 1e-9 * first.fps:
            raise ValueError(f"concatenate: motion '{m.name}' runs at {m.fps:g} fps but '{first.name}' at "
                             f"{first.fps:g} fps; resample them to one frame rate first")
        if m.skeleton != first.skeleton or m.joint_names != first.joint_names:
            raise ValueError(f"concatenate: motion '{m.name}' ({m.skeleton}, {m.num_joints} joints) does not "
                             f"share the joints of '{first.name}' ({first.skeleton}, {first.num_joints} joints)")
    rest_root = torch.zeros(3, dtype=torch.float64)
    if body is not None:
        root = first.joint_names[0]
        if root in body.joint_index:
            _, rest_j = body.rest(betas)
            rest_root = rest_j[body.joint_index[root]].double().cpu()
    rest_root[2] = 0.0

    window = max(1, int(round(heading_window_s * first.fps)))
    rot = first.rotations.double()
    trans = first.translation.double()
    for m in motions[1:]:
        rot, trans = _append(rot, trans, m.rotations.double(), m.translation.double(), int(blend_frames), rest_root,
                             window)
    label = name if name is not None else ",".join(m.name for m in motions)
    return Motion(label, list(first.joint_names), rot.float(), trans.float(), first.fps, first.skeleton)


def _mean_angle(angles: torch.Tensor) -> torch.Tensor:
    return torch.atan2(torch.sin(angles).mean(), torch.cos(angles).mean())


def _append(rot_a, trans_a, rot_b, trans_b, n: int, rest_root: torch.Tensor, window: int):
    n = min(n, rot_a.shape[0], rot_b.shape[0])
    anchor = rot_a.shape[0] - 1  # B' starts at A's last root position
    # Heading: turn B about Z so its mean root yaw at the start equals A's at the end.
    Rb = _roma().rotvec_to_rotmat(rot_b[:, 0])
    yaw_a = _mean_angle(yaw_angle(_roma().rotvec_to_rotmat(rot_a[-window:, 0])))
    yaw_b = _mean_angle(yaw_angle(Rb[:window]))
    Y = rot_z(yaw_a - yaw_b)
    rot_b = rot_b.clone()
    rot_b[:, 0] = _roma().rotmat_to_rotvec(Y @ Rb)
    # Root positions p = translation + rest root. B's path is turned by Y about its first root
    # position; its heights are kept.
    pa = trans_a + rest_root
    pb = trans_b + rest_root
    turned = (pb - pb[0]) @ Y.T
    if n == 0:
        pb_new = turned + torch.stack([pa[anchor, 0], pa[anchor, 1], pb[0, 2]])
        return torch.cat([rot_a, rot_b]), torch.cat([trans_a, pb_new - rest_root])
    if n == 1:
        w = torch.ones(1, dtype=torch.float64)
    else:
        s = torch.linspace(0.0, 1.0, n, dtype=torch.float64)
        w = s * s * (3.0 - 2.0 * s)  # smoothstep: zero slope at both ends of the fade
    ra, rb = rot_a[-n:], rot_b[:n]
    mixed_r = slerp_rotvec(ra, rb, w[:, None].expand(-1, ra.shape[1]))
    # Horizontal root path: blend the per-frame displacements of A and B' and integrate from A's
    # first faded frame, so the root speed stays between the two clips' speeds; after the fade
    # B' follows on from where the blend ended. Heights are blended as positions.
    start = pa.shape[0] - n
    da = torch.zeros(n, 2, dtype=torch.float64)
    db = torch.zeros(n, 2, dtype=torch.float64)
    if n > 1:
        da[1:] = pa[start + 1:, :2] - pa[start:-1, :2]
        db[1:] = turned[1:n, :2] - turned[:n - 1, :2]
    xy = pa[start, :2] + torch.cumsum((1.0 - w[:, None]) * da + w[:, None] * db, dim=0)
    z = pa[start:, 2] + w * (pb[:n, 2] - pa[start:, 2])
    mixed_p = torch.cat([xy, z[:, None]], dim=1)
    tail = turned[n:] - turned[n - 1]
    tail[:, :2] += xy[-1]
    tail[:, 2] = pb[n:, 2]
    p_out = torch.cat([pa[:start], mixed_p, tail])
    return torch.cat([rot_a[:-n], mixed_r, rot_b[n:]]), p_out - rest_root
