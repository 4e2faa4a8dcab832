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


def _packed_exclusive_cumsum(x: torch.Tensor, ray_ids: torch.Tensor, n_rays: int) -> torch.Tensor:
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
    return torch.exp(-_packed_exclusive_cumsum(optical_thickness(sigmas, deltas), ray_ids, n_rays))


def transmittance_from_alpha_packed(alphas: torch.Tensor, ray_ids: torch.Tensor, n_rays: int) -> torch.Tensor:
    """Packed :func:`transmittance_from_alpha`: alphas, ray_ids (N,) -> (N,)."""
    log_1m = torch.log1p(-alphas.clamp(0.0, _alpha_ceiling(alphas.dtype)))
    return torch.exp(_packed_exclusive_cumsum(log_1m, ray_ids, n_rays))


def render_weights_packed(alphas: torch.Tensor, ray_ids: torch.Tensor, n_rays: int) -> torch.Tensor:
    """Packed :func:`render_weights`: alphas, ray_ids (N,) -> weights (N,)."""
    alphas = alphas.clamp(0.0, _alpha_ceiling(alphas.dtype))
    return transmittance_from_alpha_packed(alphas, ray_ids, n_rays) * alphas


def render_weights_from_density_packed(sigmas: torch.Tensor, deltas: torch.Tensor, ray_ids: torch.Tensor,
                                       n_rays: int) -> torch.Tensor:
    """Packed :func:`render_weights_from_density`: sigmas, deltas, ray_ids (N,) -> weights (N,)."""
    tau = optical_thickness(sigmas, deltas)
    return torch.exp(-_packed_exclusive_cumsum(tau, ray_ids, n_rays)) * -torch.expm1(-tau)


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
