"""Importance sampling: a coarse pass without gradient places the samples the field is trained and rendered on.

Why (``docs/quality.md``, "Where the samples go"): the paper's box sampler spaces ``samples_per_ray``
samples evenly across the body's box, about 4 cm apart on the bundled skirt's rays at 24 samples. A
garment is a sheet a few millimetres thick; a sheet thinner than the spacing is hit by a sample on some
rays and missed on others, so the field can only render it consistently as a fog at least one spacing
thick, and it does: the trained models spread a garment ray's weight over 4 to 11 cm (10-90 % of the
weight; body rays 1 to 2 cm). That fog averages zeta across the folds and softens the outline. NeRF's
hierarchical sampling (Mildenhall et al. 2020, Sec. 5.2; mip-NeRF's single network) is the classic
remedy: evaluate the density on the coarse samples, then draw the samples that count from the weights
they give, so they crowd where the cloth is.

:class:`ImportanceSampler` wraps a base sampler whose samples tile one contiguous segment per ray (the
box sampler). Bound to a frame and a camera it

1. places the base's samples (the *coarse* pass) and evaluates the density there with no gradient;
2. turns each ray's weights into a piecewise-constant density over its intervals, mixed with a share
   ``uniform_mix`` of the uniform one (so empty space keeps some samples: a floater the coarse pass
   missed can still be seen and removed, and a ray with no weight is sampled evenly);
3. draws ``num_samples`` samples per ray by inverting that distribution at stratified levels (jittered
   in training, the bin centres otherwise: :func:`sample_intervals`), and gives them intervals that tile
   the same segment (:func:`~garmentnerf.model.samplers.intervals_between`), so empty stretches are
   long intervals at their sample's density and the quadrature stays a partition of the segment.

Only the fine samples are returned: the field is evaluated on them with gradient, exactly as on a base
sampler's samples, so the renderer, the losses and every preset use it unchanged. The positions carry no
gradient (nor do the base's).

Shapes: R rays, K base samples per ray (padded), S fine samples per ray.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import torch

from garmentnerf.conventions import Camera
from garmentnerf.model.samplers import RaySamples, intervals_between, pixel_rays
from garmentnerf.model.volume_rendering import packed_layout, render_weights_from_density_packed

if TYPE_CHECKING:  # pragma: no cover
    from garmentnerf.model.frame_context import FrameFeatures

#: The density of a frame at world positions: ``density(frame, positions (n, 3)) -> sigma (n,)``.
DensityFn = Callable[["FrameFeatures", torch.Tensor], torch.Tensor]


def sample_intervals(t_starts: torch.Tensor, t_ends: torch.Tensor, weights: torch.Tensor, num_samples: int,
                     uniform_mix: float, training: bool = False,
                     generator: torch.Generator | None = None) -> torch.Tensor:
    """Inverse-transform samples of the piecewise-constant distribution the weights put on the intervals.

    Each ray's distribution gives interval k the mass ``(1 - uniform_mix) w_k / sum w + uniform_mix
    delta_k / L`` (L the summed interval lengths), spread evenly over the interval; a ray whose weights
    sum to 0 is sampled uniformly. The S levels are stratified: ``(i + u) / S`` with u uniform in [0, 1)
    in training, 0.5 otherwise, so the samples come out sorted along the ray.

    Args:
        t_starts, t_ends: (R, K) intervals in order along each ray (padding: zero-length intervals).
        weights: (R, K) rendering weights >= 0 of the intervals.
        num_samples: S.
        uniform_mix: in [0, 1], the uniform share of the distribution.
    Returns:
        t (R, S) sample distances, non-decreasing along each ray, each inside an interval of positive mass.
    """
    if not 0.0 <= uniform_mix <= 1.0:
        raise ValueError(f"uniform_mix must be in [0, 1], got {uniform_mix}")
    if num_samples < 1:
        raise ValueError(f"num_samples must be >= 1, got {num_samples}")
    R, K = t_starts.shape
    deltas = (t_ends - t_starts).clamp_min(0.0)
    length = deltas.sum(-1, keepdim=True)
    w = weights.clamp_min(0.0) * (deltas > 0)
    total = w.sum(-1, keepdim=True)
    uniform = deltas / length.clamp_min(torch.finfo(deltas.dtype).tiny)
    share = torch.where(total > 0, torch.full_like(total, 1.0 - uniform_mix), torch.zeros_like(total))
    mass = share * w / total.clamp_min(torch.finfo(w.dtype).tiny) + (1.0 - share) * uniform   # (R, K)
    cdf = torch.cumsum(mass, -1)
    cdf = cdf / cdf[:, -1:].clamp_min(torch.finfo(cdf.dtype).tiny)                                # exactly 1 at the end
    bins = torch.arange(num_samples, dtype=t_starts.dtype, device=t_starts.device)
    if training:
        u = bins + torch.rand(R, num_samples, dtype=t_starts.dtype, device=t_starts.device, generator=generator)
    else:
        u = (bins + 0.5).expand(R, num_samples)
    u = (u / num_samples).contiguous()
    # the interval holding each level: the first whose cumulative mass exceeds it (a zero-mass interval
    # never does, since its cdf equals its predecessor's)
    k = torch.searchsorted(cdf, u, right=True).clamp(max=K - 1)
    below = torch.where(k > 0, cdf.gather(1, (k - 1).clamp_min(0)), torch.zeros_like(u))
    m = mass.gather(1, k)
    frac = ((u - below) / m.clamp_min(torch.finfo(m.dtype).tiny)).clamp(0.0, 1.0)
    t = t_starts.gather(1, k) + frac * deltas.gather(1, k)
    return torch.cummax(t, dim=-1).values  # rounding cannot unsort them


class ImportanceSampler:
    """Samples drawn from a coarse pass of ``base`` (see the module docstring).

    Args:
        base: a :class:`~garmentnerf.model.samplers.Sampler` whose samples tile one contiguous segment per
            ray (the box sampler; :meth:`BoundImportanceSampler.sample` checks it).
        density: ``density(frame, positions)`` -> sigma; called under ``torch.no_grad``.
        num_samples: S, fine samples per ray.
        uniform_mix: the uniform share of each ray's sampling distribution.
    """

    def __init__(self, base, density: DensityFn, num_samples: int, uniform_mix: float = 0.1):
        if num_samples < 1:
            raise ValueError(f"num_samples must be >= 1, got {num_samples}")
        if not 0.0 <= uniform_mix <= 1.0:
            raise ValueError(f"uniform_mix must be in [0, 1], got {uniform_mix}")
        self.base, self.density = base, density
        self.num_samples, self.uniform_mix = int(num_samples), float(uniform_mix)

    def bind(self, frame: "FrameFeatures", camera: Camera) -> "BoundImportanceSampler":
        return BoundImportanceSampler(self, self.base.bind(frame, camera), frame, camera)


class BoundImportanceSampler:
    """An :class:`ImportanceSampler` bound to a frame and a feature camera."""

    def __init__(self, sampler: ImportanceSampler, base, frame: "FrameFeatures", camera: Camera):
        self.sampler, self.base, self.frame, self.camera = sampler, base, frame, camera

    def sample(self, pixels: torch.Tensor, *, training: bool = False,
               generator: torch.Generator | None = None) -> RaySamples:
        coarse = self.base.sample(pixels, training=training, generator=generator)
        R = coarse.n_rays
        if len(coarse) == 0:
            return coarse
        ids = coarse.ray_ids.long()
        same_ray = ids[1:] == ids[:-1]
        if bool((same_ray & ((coarse.t_starts[1:] - coarse.t_ends[:-1]).abs() > 1e-6)).any()):
            raise ValueError("ImportanceSampler needs a base sampler whose samples tile one contiguous segment "
                             "per ray (the box sampler)")
        with torch.no_grad():
            sigma = self.sampler.density(self.frame, coarse.positions).float().to(coarse.t_starts.device)
            weights = render_weights_from_density_packed(sigma, coarse.deltas.float(), ids, R)
        index, counts = packed_layout(ids, R)
        K = int(counts.max())
        hit_rays = torch.nonzero(counts > 0).squeeze(1)
        pad_t = coarse.far[:, None].expand(R, K).to(coarse.t_starts.dtype)
        t0 = pad_t.clone().index_put((ids, index), coarse.t_starts)[hit_rays]
        t1 = pad_t.clone().index_put((ids, index), coarse.t_ends)[hit_rays]
        w = weights.new_zeros(R, K).index_put((ids, index), weights)[hit_rays]
        S = self.sampler.num_samples
        t = sample_intervals(t0, t1, w.to(t0.dtype), S, self.sampler.uniform_mix, training, generator)
        near, far = coarse.near[hit_rays].to(t.dtype), coarse.far[hit_rays].to(t.dtype)
        t_starts, t_ends = intervals_between(t, near, far)
        origins, dirs = pixel_rays(self.camera, pixels.to("cpu").long()[hit_rays.cpu()])
        origins, dirs = origins.to(t.device, t.dtype), dirs.to(t.device, t.dtype)
        positions = origins[:, None] + t[..., None] * dirs[:, None]
        ray_ids = hit_rays.to(t.device).repeat_interleave(S)
        return RaySamples(positions.reshape(-1, 3).to(coarse.positions.dtype), t_starts.reshape(-1),
                          t_ends.reshape(-1), ray_ids.to(coarse.ray_ids.dtype), R, coarse.near, coarse.far,
                          coarse.hit)


__all__ = ["ImportanceSampler", "BoundImportanceSampler", "sample_intervals", "DensityFn"]
