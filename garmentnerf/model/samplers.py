"""Where along each ray the NeRF is evaluated.

:class:`Sampler` is the interface every sampler implements; :class:`BoxStratifiedSampler` is the
paper's: S stratified samples between the ray's entry into and exit from the axis-aligned box
around the posed body, padded by 0.05 m (authors' code). An empty-space-skipping sampler can
return packed samples (a different count per ray) through the same :class:`RaySamples`.

Intervals tile the ray's segment inside the box: sample i stands for
``[t_starts_i, t_ends_i]`` with ``t_starts_1 = t_near``, ``t_ends_S = t_far`` and consecutive
intervals meeting halfway between samples. The deltas thus sum to the segment length exactly,
which is what makes the rendered opacity of a constant-density box exact for any S, and there is
no "last delta = 1e10" of the original NeRF (that would make the box's back face opaque).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import torch


@dataclass
class RaySamples:
    """Samples along R rays, dense (S per ray) or packed (N in all).

    Attributes:
        positions: (R, S, 3) dense or (N, 3) packed world positions (interval midpoints for
            eval-mode stratified samples, the drawn points in training).
        t_starts, t_ends: (R, S) or (N,) interval bounds along the ray, in metres for unit
            directions; equal for rays that miss (zero-length intervals -> zero weights).
        ray_ids: None (dense) or (N,) sorted ray index of each packed sample.
        n_rays: R.
        hit: (R,) bool, rays with a non-empty segment.
    """

    positions: torch.Tensor
    t_starts: torch.Tensor
    t_ends: torch.Tensor
    ray_ids: torch.Tensor | None
    n_rays: int
    hit: torch.Tensor

    @property
    def is_packed(self) -> bool:
        return self.ray_ids is not None

    @property
    def deltas(self) -> torch.Tensor:
        """Interval lengths, shape of ``t_starts``."""
        return self.t_ends - self.t_starts

    @property
    def t_mids(self) -> torch.Tensor:
        """Interval midpoints, shape of ``t_starts``."""
        return (self.t_starts + self.t_ends) * 0.5

    def to_packed(self, drop_missed: bool = True) -> "RaySamples":
        """Flatten dense samples to packed form; ``drop_missed`` leaves out rays that miss."""
        if self.is_packed:
            return self
        R, S = self.t_starts.shape
        ray_ids = torch.arange(R, device=self.t_starts.device).repeat_interleave(S)
        keep = self.hit.repeat_interleave(S) if drop_missed else torch.ones_like(ray_ids, dtype=torch.bool)
        return RaySamples(self.positions.reshape(-1, 3)[keep], self.t_starts.reshape(-1)[keep],
                          self.t_ends.reshape(-1)[keep], ray_ids[keep], R, self.hit)


@runtime_checkable
class Sampler(Protocol):
    """Places samples along rays."""

    def sample(self, origins: torch.Tensor, directions: torch.Tensor, aabb: torch.Tensor, *,
               training: bool = False, generator: torch.Generator | None = None) -> RaySamples:
        """Samples for R rays.

        Args:
            origins: (R, 3) ray origins.
            directions: (R, 3) unit directions (deltas are then metres, as densities expect).
            aabb: (2, 3) [min, max] corners of the tight box around the posed body.
            training: draw random (jittered) samples; False: deterministic.
            generator: random source for training-mode jitter.
        """
        ...


def body_aabb(vertices: torch.Tensor) -> torch.Tensor:
    """(2, 3) [min, max] corners of the points ``(V, 3)``."""
    return torch.stack([vertices.amin(dim=0), vertices.amax(dim=0)])


def ray_aabb_intersect(origins: torch.Tensor, directions: torch.Tensor, aabb: torch.Tensor,
                       near: float = 0.0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Slab test: where each ray enters and leaves an axis-aligned box.

    A direction component of exactly 0 is handled without dividing by it: the ray then stays in
    that slab for all t if its origin lies inside the slab, and never otherwise. Rays starting
    inside the box enter at ``near``.

    Args:
        origins, directions: (R, 3).
        aabb: (2, 3) [min, max].
        near: smallest t allowed (0: nothing behind the origin).
    Returns:
        t_near (R,), t_far (R,) with t_near = t_far = near for rays that miss, and hit (R,) bool.
    """
    lo, hi = aabb[0], aabb[1]
    parallel = directions == 0
    safe = torch.where(parallel, torch.ones_like(directions), directions)
    t0 = (lo - origins) / safe
    t1 = (hi - origins) / safe
    inside = (origins >= lo) & (origins <= hi)
    inf = torch.full_like(t0, float("inf"))
    t_min = torch.where(parallel, torch.where(inside, -inf, inf), torch.minimum(t0, t1))
    t_max = torch.where(parallel, torch.where(inside, inf, -inf), torch.maximum(t0, t1))
    t_near = t_min.amax(dim=-1).clamp_min(near)
    t_far = t_max.amin(dim=-1)
    hit = t_far > t_near
    start = torch.full_like(t_near, near)
    return torch.where(hit, t_near, start), torch.where(hit, t_far, start), hit


def stratified_intervals(t_near: torch.Tensor, t_far: torch.Tensor, num_samples: int, training: bool = False,
                         generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """S stratified sample distances on [t_near, t_far] and the intervals they stand for.

    Sample i lies in the i-th of S equal bins: at its centre in eval mode, uniformly at random in
    training (Mildenhall et al., Eq. 2). Interval boundaries are halfway between samples, the
    first starts at t_near and the last ends at t_far.

    Args:
        t_near, t_far: (R,).
    Returns:
        t (R, S) sample distances, t_starts (R, S), t_ends (R, S).
    """
    R = t_near.shape[0]
    bins = torch.arange(num_samples, dtype=t_near.dtype, device=t_near.device)
    if training:
        u = (bins + torch.rand(R, num_samples, dtype=t_near.dtype, device=t_near.device, generator=generator))
    else:
        u = (bins + 0.5).expand(R, num_samples)
    length = (t_far - t_near).unsqueeze(-1)
    t = t_near.unsqueeze(-1) + length * (u / num_samples)
    mid = (t[:, 1:] + t[:, :-1]) * 0.5
    t_starts = torch.cat([t_near.unsqueeze(-1), mid], dim=-1)
    t_ends = torch.cat([mid, t_far.unsqueeze(-1)], dim=-1)
    return t, t_starts, t_ends


class BoxStratifiedSampler:
    """The paper's sampler: S stratified samples inside the padded body box (dense output).

    Args:
        num_samples: S (paper: 64).
        padding: metres added to every side of the box (paper code: 0.05).
        near: smallest distance from the ray origin.
    """

    def __init__(self, num_samples: int = 64, padding: float = 0.05, near: float = 0.0):
        if num_samples < 1:
            raise ValueError(f"num_samples must be >= 1, got {num_samples}")
        if padding < 0:
            raise ValueError(f"padding must be >= 0, got {padding}")
        self.num_samples = num_samples
        self.padding = padding
        self.near = near

    @classmethod
    def from_config(cls, cfg) -> "BoxStratifiedSampler":
        return cls(cfg.samples_per_ray, cfg.bbox_padding)

    def sample(self, origins: torch.Tensor, directions: torch.Tensor, aabb: torch.Tensor, *,
               training: bool = False, generator: torch.Generator | None = None) -> RaySamples:
        """Dense samples ``(R, S)``; see :class:`Sampler`. Rays that miss the padded box get S
        zero-length intervals at the ray origin."""
        if origins.ndim != 2 or origins.shape[-1] != 3 or directions.shape != origins.shape:
            raise ValueError(f"origins and directions must both be (R, 3), got {tuple(origins.shape)} "
                             f"and {tuple(directions.shape)}")
        if aabb.shape != (2, 3):
            raise ValueError(f"aabb must be (2, 3) [min, max], got {tuple(aabb.shape)}")
        if directions.numel() and float((directions.norm(dim=-1) - 1.0).abs().max()) > 1e-3:
            raise ValueError("directions must be unit vectors (interval lengths are metres)")
        pad = torch.tensor([[-self.padding], [self.padding]], dtype=aabb.dtype, device=aabb.device)
        t_near, t_far, hit = ray_aabb_intersect(origins, directions, aabb + pad, self.near)
        t, t_starts, t_ends = stratified_intervals(t_near, t_far, self.num_samples, training, generator)
        positions = origins.unsqueeze(1) + t.unsqueeze(-1) * directions.unsqueeze(1)
        return RaySamples(positions, t_starts, t_ends, None, origins.shape[0], hit)
