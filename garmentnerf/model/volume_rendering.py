"""Volume rendering as pure functions (nerfacc-style), dense and packed.

For samples i = 1..S along a ray with density sigma_i over the interval of length delta_i
(Mildenhall et al., 2020, Eq. 3):

    tau_i   = sigma_i delta_i                         optical thickness of the interval
    alpha_i = 1 - exp(-tau_i)                         its opacity
    T_i     = exp(-sum_{j<i} tau_j) = prod_{j<i} (1 - alpha_j)   transmittance up to it
    w_i     = T_i alpha_i                             its rendering weight
    F       = sum_i w_i f_i                           any per-sample value composited (paper: zeta)

``sum_i w_i = 1 - T_{S+1} <= 1`` is the accumulated opacity.

Dense functions take ``(R, S)`` per-sample tensors (any leading shape works). Packed functions
take flattened samples ``(N,)`` with ``ray_ids (N,)`` sorted non-decreasingly (samples of one ray
contiguous and in order along it), as an empty-space-skipping sampler produces; rays may have any
number of samples, zero included.

Numerical safety: densities from 0 to 1e8 and interval lengths from 0 to 1e6 give finite values
and finite gradients. alpha is ``-expm1(-tau)`` (exact for tiny tau); tau is clamped to
:data:`MAX_OPTICAL_THICKNESS`, where exp(-tau) is already 0 in float64, so the clamp changes no
value and only zeroes gradients that are 0 anyway; transmittance from densities is the exp of a
(exclusive) sum, never a product of tiny factors.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Callable
from dataclasses import dataclass

import torch

#: exp(-1e4) underflows to 0 even in float64; clamping tau here keeps sums of many saturated
#: intervals finite.
MAX_OPTICAL_THICKNESS = 1e4


def optical_thickness(sigmas: torch.Tensor, deltas: torch.Tensor) -> torch.Tensor:
    """tau = sigma delta, clamped to [0, MAX_OPTICAL_THICKNESS]; shape of the inputs."""
    return (sigmas * deltas).clamp(0.0, MAX_OPTICAL_THICKNESS)


def alpha_from_density(sigmas: torch.Tensor, deltas: torch.Tensor) -> torch.Tensor:
    """Opacity of each interval ``1 - exp(-sigma delta)``.

    Args:
        sigmas: (R, S) densities >= 0 (1/metre).
        deltas: (R, S) interval lengths >= 0 (metres).
    Returns:
        (R, S) alphas in [0, 1].
    """
    return -torch.expm1(-optical_thickness(sigmas, deltas))


def _exclusive_cumsum(x: torch.Tensor) -> torch.Tensor:
    # Shift instead of cumsum(x) - x: subtracting a large running sum would cancel small terms.
    c = torch.cumsum(x, dim=-1)
    return torch.cat([torch.zeros_like(c[..., :1]), c[..., :-1]], dim=-1)


def transmittance_from_density(sigmas: torch.Tensor, deltas: torch.Tensor) -> torch.Tensor:
    """T_i = exp(-sum_{j<i} sigma_j delta_j): (R, S) -> (R, S), T_1 = 1."""
    return torch.exp(-_exclusive_cumsum(optical_thickness(sigmas, deltas)))


def _alpha_ceiling(dtype: torch.dtype) -> float:
    # log1p(-1) = -inf and its gradient -1/(1 - alpha) are infinite: stop just below 1.
    return 1.0 - 16.0 * torch.finfo(dtype).eps


def transmittance_from_alpha(alphas: torch.Tensor) -> torch.Tensor:
    """T_i = prod_{j<i} (1 - alpha_j), computed as exp of a sum of log1p(-alpha): (R, S) -> (R, S).

    alpha is clamped to ``1 - 16 eps`` so a fully opaque sample leaves T ~ 2e-6 (float32) behind
    it instead of an infinite log; use :func:`transmittance_from_density` when densities are at
    hand (exact, no clamp).
    """
    log_1m = torch.log1p(-alphas.clamp(0.0, _alpha_ceiling(alphas.dtype)))
    return torch.exp(_exclusive_cumsum(log_1m))


def render_weights(alphas: torch.Tensor) -> torch.Tensor:
    """Weights w_i = T_i alpha_i from alphas: (R, S) -> (R, S); each row sums to at most 1.

    The clamped alpha of :func:`transmittance_from_alpha` is used in both factors, so the
    weights telescope to ``1 - T_{S+1}`` and never sum above 1.
    """
    alphas = alphas.clamp(0.0, _alpha_ceiling(alphas.dtype))
    return transmittance_from_alpha(alphas) * alphas


def render_weights_from_density(sigmas: torch.Tensor, deltas: torch.Tensor) -> torch.Tensor:
    """Weights w_i = T_i alpha_i from densities and interval lengths: (R, S) -> (R, S)."""
    tau = optical_thickness(sigmas, deltas)
    return torch.exp(-_exclusive_cumsum(tau)) * -torch.expm1(-tau)


def accumulate_opacity(weights: torch.Tensor) -> torch.Tensor:
    """Accumulated opacity sum_i w_i: (R, S) -> (R,)."""
    return weights.sum(dim=-1)


def composite(weights: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    """sum_i w_i v_i: weights (R, S), values (R, S, C) -> (R, C). Nothing is added for the
    background: a ray that hits nothing composites to 0."""
    return (weights.unsqueeze(-1) * values).sum(dim=-2)


def expected_depth(weights: torch.Tensor, t_starts: torch.Tensor, t_ends: torch.Tensor,
                   normalize: bool = False) -> torch.Tensor:
    """sum_i w_i t_i with t_i the interval midpoint: (R, S) -> (R,).

    Unnormalised (a ray of opacity 0 gets 0) unless ``normalize``, which divides by the opacity
    (the depth of the visible surface).
    """
    depth = (weights * (t_starts + t_ends) * 0.5).sum(dim=-1)
    if normalize:
        depth = depth / accumulate_opacity(weights).clamp_min(1e-10)
    return depth


# ---------------------------------------------------------------------------------------- packed
def packed_layout(ray_ids: torch.Tensor, n_rays: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Where each packed sample sits in its ray.

    Args:
        ray_ids: (N,) int, non-decreasing, in [0, n_rays).
        n_rays: R.
    Returns:
        index (N,) position of each sample within its ray (0 for the first), counts (R,) samples
        per ray.
    Raises:
        ValueError if ray_ids is not sorted or out of range.
    """
    if ray_ids.ndim != 1:
        raise ValueError(f"ray_ids must be (N,), got shape {tuple(ray_ids.shape)}")
    n = ray_ids.shape[0]
    if n:
        if bool((ray_ids[1:] < ray_ids[:-1]).any()):
            raise ValueError("ray_ids must be sorted (samples of a ray contiguous and in order)")
        if int(ray_ids[0]) < 0 or int(ray_ids[-1]) >= n_rays:
            raise ValueError(f"ray_ids must lie in [0, {n_rays})")
    counts = torch.bincount(ray_ids, minlength=n_rays)
    starts = torch.cumsum(counts, 0) - counts
    index = torch.arange(n, device=ray_ids.device) - starts[ray_ids]
    return index, counts


def packed_exclusive_cumsum(x: torch.Tensor, ray_ids: torch.Tensor, n_rays: int) -> torch.Tensor:
    # Scatter into a zero-padded (R, S_max) block and scan rows: exact per ray. A global cumsum
    # minus each ray's start would lose the small terms of a ray that follows a ray with a huge
    # optical thickness.
    index, counts = packed_layout(ray_ids, n_rays)
    width = int(counts.max()) if x.shape[0] else 0
    padded = x.new_zeros(n_rays, width).index_put((ray_ids, index), x)
    return _exclusive_cumsum(padded)[ray_ids, index]


def transmittance_from_density_packed(sigmas: torch.Tensor, deltas: torch.Tensor, ray_ids: torch.Tensor,
                                      n_rays: int) -> torch.Tensor:
    """Packed :func:`transmittance_from_density`: sigmas, deltas, ray_ids (N,) -> (N,)."""
    return torch.exp(-packed_exclusive_cumsum(optical_thickness(sigmas, deltas), ray_ids, n_rays))


def transmittance_from_alpha_packed(alphas: torch.Tensor, ray_ids: torch.Tensor, n_rays: int) -> torch.Tensor:
    """Packed :func:`transmittance_from_alpha`: alphas, ray_ids (N,) -> (N,)."""
    log_1m = torch.log1p(-alphas.clamp(0.0, _alpha_ceiling(alphas.dtype)))
    return torch.exp(packed_exclusive_cumsum(log_1m, ray_ids, n_rays))


def render_weights_packed(alphas: torch.Tensor, ray_ids: torch.Tensor, n_rays: int) -> torch.Tensor:
    """Packed :func:`render_weights`: alphas, ray_ids (N,) -> weights (N,)."""
    alphas = alphas.clamp(0.0, _alpha_ceiling(alphas.dtype))
    return transmittance_from_alpha_packed(alphas, ray_ids, n_rays) * alphas


def render_weights_from_density_packed(sigmas: torch.Tensor, deltas: torch.Tensor, ray_ids: torch.Tensor,
                                       n_rays: int) -> torch.Tensor:
    """Packed :func:`render_weights_from_density`: sigmas, deltas, ray_ids (N,) -> weights (N,)."""
    tau = optical_thickness(sigmas, deltas)
    return torch.exp(-packed_exclusive_cumsum(tau, ray_ids, n_rays)) * -torch.expm1(-tau)


def accumulate_opacity_packed(weights: torch.Tensor, ray_ids: torch.Tensor, n_rays: int) -> torch.Tensor:
    """Per-ray sum of weights: weights, ray_ids (N,) -> (R,); rays without samples get 0."""
    return weights.new_zeros(n_rays).index_add(0, ray_ids, weights)


def composite_packed(weights: torch.Tensor, values: torch.Tensor, ray_ids: torch.Tensor, n_rays: int) -> torch.Tensor:
    """Per-ray sum_i w_i v_i: weights (N,), values (N, C), ray_ids (N,) -> (R, C)."""
    return values.new_zeros(n_rays, values.shape[-1]).index_add(0, ray_ids, weights.unsqueeze(-1) * values)


def expected_depth_packed(weights: torch.Tensor, t_starts: torch.Tensor, t_ends: torch.Tensor, ray_ids: torch.Tensor,
                          n_rays: int, normalize: bool = False) -> torch.Tensor:
    """Packed :func:`expected_depth`: (N,) inputs -> (R,)."""
    depth = weights.new_zeros(n_rays).index_add(0, ray_ids, weights * (t_starts + t_ends) * 0.5)
    if normalize:
        opacity = accumulate_opacity_packed(weights, ray_ids, n_rays)
        depth = depth / opacity.clamp_min(1e-10)
    return depth


#: The accumulated opacity at which :func:`median_depth_packed` (and the march's ``median_depth``) reads a
#: ray's surface: half the ray's light is stopped in front of it.
SURFACE_OPACITY = 0.5


def median_depth_packed(sigmas: torch.Tensor, t_starts: torch.Tensor, t_ends: torch.Tensor, ray_ids: torch.Tensor,
                        n_rays: int, level: float = SURFACE_OPACITY) -> torch.Tensor:
    """(R,) the distance along each ray at which its accumulated opacity first reaches ``level``, linear in
    optical thickness inside the sample that crosses it; 0 for a ray that never reaches it.

    The plain reference of the march's ``median_depth`` (:func:`render_packed_segmented`). Unlike the
    expected depth it is not pulled back by faint density behind the surface: it is the depth a
    surface built from the render should sit at.

    Args:
        sigmas, t_starts, t_ends, ray_ids: (N,) packed samples, ``ray_ids`` sorted.
    """
    target = -math.log(1.0 - level)
    tau = optical_thickness(sigmas.float(), (t_ends - t_starts).float())
    before = packed_exclusive_cumsum(tau, ray_ids, n_rays)
    return _level_crossing(tau, before, t_starts.float(), t_ends.float(), ray_ids, n_rays, target)


def _level_crossing(tau: torch.Tensor, before: torch.Tensor, t_starts: torch.Tensor, t_ends: torch.Tensor,
                    ray_ids: torch.Tensor, n_rays: int, target: float,
                    out: torch.Tensor | None = None) -> torch.Tensor:
    """``out`` (R,) (zeros when None) with the distance where each ray's optical thickness crosses ``target``
    written for the samples (N,) that cross it (``before`` < target <= ``before + tau``)."""
    out = tau.new_zeros(n_rays) if out is None else out
    hit = (before < target) & (before + tau >= target)
    frac = ((target - before) / tau.clamp_min(1e-12)).clamp(0.0, 1.0)
    t = t_starts + (t_ends - t_starts) * frac
    return out.index_put((ray_ids[hit],), t[hit])


# ------------------------------------------------------------------------ segmented (field in the loop)
@dataclass
class MarchResult:
    """What :func:`render_packed_segmented` composited, per ray.

    Attributes:
        values: (R, C) sum_i w_i v_i.
        opacity: (R,) sum_i w_i.
        depth: (R,) sum_i w_i t_i (unnormalised; divide by the opacity for the surface depth).
        samples_evaluated: samples the field was asked for (the others were skipped by early
            termination).
        terminated: (R,) bool, rays stopped early with samples left (on the CPU).
        distortion: (R,) :func:`distortion_packed` of the evaluated samples, when asked for (else None).
        median_depth: (R,) :func:`median_depth_packed` of the evaluated samples (detached; 0 where the ray's
            opacity never reaches :data:`SURFACE_OPACITY`).
    """

    values: torch.Tensor
    opacity: torch.Tensor
    depth: torch.Tensor
    samples_evaluated: int
    terminated: torch.Tensor
    distortion: torch.Tensor | None = None
    median_depth: torch.Tensor | None = None


def distortion_packed(weights: torch.Tensor, t_starts: torch.Tensor, t_ends: torch.Tensor, ray_ids: torch.Tensor,
                      n_rays: int) -> torch.Tensor:
    """Per-ray distortion (mip-NeRF 360, Barron et al. 2022, Eq. 15) of packed samples: (N,) inputs -> (R,).

    ``sum_{i,j} w_i w_j |m_i - m_j| + 1/3 sum_i w_i^2 delta_i`` with m the interval midpoints: the
    expected distance between two points drawn from the ray's weights, each spread evenly over its
    interval. It is smallest when the weight sits in one short interval: a surface, not a fog. In metres
    here (unit directions). The pair sum is ``2 sum_i w_i (m_i W_i - S_i)``, with W_i and S_i the sums of
    w_j and w_j m_j over the samples before i (samples in order along each ray).
    """
    mids = (t_starts + t_ends) * 0.5
    before_w = packed_exclusive_cumsum(weights, ray_ids, n_rays)
    before_wm = packed_exclusive_cumsum(weights * mids, ray_ids, n_rays)
    per_sample = 2.0 * weights * (mids * before_w - before_wm) + weights ** 2 * (t_ends - t_starts) / 3.0
    return weights.new_zeros(n_rays).index_add(0, ray_ids, per_sample)


def _ray_aligned_chunks(counts: torch.Tensor, chunk_points: int) -> list[tuple[int, int, int, int]]:
    """(ray_start, ray_stop, sample_start, sample_stop) chunks of about ``chunk_points`` samples,
    never splitting a ray (a ray with more samples than that is a chunk of its own)."""
    ends = torch.cumsum(counts, 0).tolist()
    n_rays = len(ends)
    chunks = []
    r0 = s0 = 0
    while r0 < n_rays:
        r1 = bisect.bisect_right(ends, s0 + chunk_points, lo=r0)
        r1 = max(r1, r0 + 1)
        s1 = ends[r1 - 1]
        chunks.append((r0, r1, s0, s1))
        r0, s0 = r1, s1
    return chunks


def _front_segment(starts: torch.Tensor, counts: torch.Tensor, cursor: torch.Tensor, live: torch.Tensor,
                   per_ray: int) -> torch.Tensor:
    """Sample indices of the next ``per_ray`` samples of every live ray, in packed order."""
    rays = live.nonzero().squeeze(1)
    take = torch.minimum(counts[rays] - cursor[rays], torch.full_like(rays, per_ray))
    first = starts[rays] + cursor[rays]
    offsets = torch.arange(int(take.sum())) - torch.repeat_interleave(torch.cumsum(take, 0) - take, take)
    return torch.repeat_interleave(first, take) + offsets


def render_packed_segmented(field: Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]],
                            t_starts: torch.Tensor, t_ends: torch.Tensor, ray_ids: torch.Tensor, n_rays: int,
                            num_channels: int, *, chunk_points: int = 16384, termination_eps: float = 0.0,
                            device: torch.device | str | None = None, with_distortion: bool = False) -> MarchResult:
    """Packed volume rendering that evaluates the field itself, segment by segment.

    ``field(index)`` gets ``index (n,)``, positions into the packed samples, and returns their
    ``sigma (n,)`` and ``values (n, C)``; it is called with about ``chunk_points`` samples at a
    time. The weights are those of :func:`render_weights_from_density_packed` (the transmittance
    of a segment continues from the optical thickness the ray accumulated before it).

    Early ray termination (``termination_eps > 0``): samples are visited front to back, a few of
    every live ray per segment (about ``chunk_points`` in all), and a ray stops once its
    transmittance falls below ``termination_eps``. The samples never evaluated then carry weights
    summing to at most eps, so each composited value changes by at most ``eps * max|v|`` and the
    opacity by at most eps. With ``termination_eps = 0`` whole rays are rendered in chunks of
    about ``chunk_points`` samples (a ray is never split) and the result equals
    :func:`render_weights_from_density_packed` followed by :func:`composite_packed`.

    Args:
        t_starts, t_ends, ray_ids: (N,) packed intervals (``ray_ids`` sorted; any device, the
            bookkeeping runs on the CPU).
        n_rays: R; num_channels: C.
        device: where the field's outputs live and the results are made (default: the device of
            ``t_starts``).
        with_distortion: also accumulate each ray's :func:`distortion_packed` (across segments too).
    """
    if not 0.0 <= termination_eps < 1.0:
        raise ValueError(f"termination_eps must be in [0, 1), got {termination_eps}")
    if chunk_points < 1:
        raise ValueError(f"chunk_points must be >= 1, got {chunk_points}")
    dev = torch.device(device) if device is not None else t_starts.device
    ids_cpu = ray_ids.detach().to("cpu").long()
    _, counts = packed_layout(ids_cpu, n_rays)
    starts = torch.cumsum(counts, 0) - counts
    values = torch.zeros(n_rays, num_channels, device=dev)
    opacity = torch.zeros(n_rays, device=dev)
    depth = torch.zeros(n_rays, device=dev)
    tau_before = torch.zeros(n_rays, device=dev)  # differentiable: what later segments start from
    w_before = torch.zeros(n_rays, device=dev)  # the weight and weighted midpoints earlier segments placed
    wm_before = torch.zeros(n_rays, device=dev)
    distortion = torch.zeros(n_rays, device=dev)
    median_depth = torch.zeros(n_rays, device=dev)
    surface_tau = -math.log(1.0 - SURFACE_OPACITY)
    tau_seen = torch.zeros(n_rays)  # CPU, detached: which rays are still live
    cursor = torch.zeros(n_rays, dtype=torch.long)
    evaluated = 0

    def segments():
        if termination_eps == 0.0:
            for r0, r1, s0, s1 in _ray_aligned_chunks(counts, chunk_points):
                if s1 > s0:
                    yield torch.arange(s0, s1)
            return
        while True:
            live = (cursor < counts) & (torch.exp(-tau_seen) >= termination_eps)
            n_live = int(live.sum())
            if n_live == 0:
                return
            yield _front_segment(starts, counts, cursor, live, max(1, chunk_points // n_live))

    for index in segments():
        sigma, vals = field(index)
        rid_cpu = ids_cpu[index]
        rid = rid_cpu.to(dev)
        dev_index = index.to(t_starts.device)
        ts = t_starts[dev_index].to(dev, torch.float32)
        te = t_ends[dev_index].to(dev, torch.float32)
        tau = optical_thickness(sigma.float(), te - ts)
        _, local = torch.unique_consecutive(rid_cpu, return_inverse=True)  # the segment's rays, numbered 0..
        local = local.to(dev)
        n_local = int(local[-1]) + 1 if local.numel() else 0
        before = packed_exclusive_cumsum(tau, local, n_local) + tau_before[rid]
        w = torch.exp(-before) * -torch.expm1(-tau)
        with torch.no_grad():
            median_depth = _level_crossing(tau.detach(), before.detach(), ts, te, rid, n_rays, surface_tau, median_depth)
        values = values.index_add(0, rid, w.unsqueeze(-1) * vals.float())
        opacity = opacity.index_add(0, rid, w)
        mids = (ts + te) * 0.5
        depth = depth.index_add(0, rid, w * mids)
        if with_distortion:
            seg_w = packed_exclusive_cumsum(w, local, n_local) + w_before[rid]
            seg_wm = packed_exclusive_cumsum(w * mids, local, n_local) + wm_before[rid]
            distortion = distortion.index_add(0, rid, 2.0 * w * (mids * seg_w - seg_wm) + w ** 2 * (te - ts) / 3.0)
            w_before = w_before.index_add(0, rid, w)
            wm_before = wm_before.index_add(0, rid, w * mids)
        tau_before = tau_before.index_add(0, rid, tau)
        tau_seen = tau_seen.index_add(0, rid_cpu, tau.detach().cpu())
        cursor = cursor.index_add(0, rid_cpu, torch.ones_like(rid_cpu))
        evaluated += int(index.shape[0])
    terminated = cursor < counts
    return MarchResult(values, opacity, depth, evaluated, terminated, distortion if with_distortion else None,
                       median_depth)
