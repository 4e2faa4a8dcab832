"""Where along each ray the NeRF is evaluated: the sampler interface and the paper's box sampler.

The interface (modelled on nerfacc's estimators)
    A :class:`Sampler` is bound to one body frame and one camera (:meth:`Sampler.bind`): the
    camera is the *feature* camera, whose pixel centres the rays go through. The
    :class:`BoundSampler` it returns places samples for any subset of those rays
    (:meth:`BoundSampler.sample`, rays named by their row-major pixel index) and returns
    :class:`RaySamples`: packed samples (a different count per ray, zero included) with the
    per-ray bounds the sampler used. Binding is where a sampler does its per-frame or per-camera
    work (the shell sampler rasterises its shell there). Samplers are passed to
    :meth:`~garmentnerf.model.pipeline.GarmentAnimationNeRF.render` as arguments, in training and
    in rendering alike; nothing is installed on a model.

Samplers
    :class:`BoxStratifiedSampler` is the paper's: S stratified samples between the ray's entry
    into and exit from the axis-aligned box around the posed body, padded by 0.05 m (authors'
    code). :class:`~garmentnerf.render.shell_sampler.ShellSampler` keeps only the part of each ray
    inside an inflated-body shell.

Intervals tile the ray's segment inside the box: sample i stands for
``[t_starts_i, t_ends_i]`` with ``t_starts_1 = t_near``, ``t_ends_S = t_far`` and consecutive
intervals meeting halfway between samples. The deltas thus sum to the segment length exactly,
which is what makes the rendered opacity of a constant-density box exact for any S, and there is
no "last delta = 1e10" of the original NeRF (that would make the box's back face opaque).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import torch

from garmentnerf.conventions import Camera, camera_rays
from garmentnerf.model.config import BBOX_PADDING

if TYPE_CHECKING:  # pragma: no cover
    from garmentnerf.geometry.body_points import BodyPoints
    from garmentnerf.model.frame_context import FrameFeatures


@dataclass
class RaySamples:
    """Packed samples along R rays (N in all), with the bounds each ray was sampled within.

    Attributes:
        positions: (N, 3) world positions (interval midpoints for eval-mode stratified samples,
            the drawn points in training).
        t_starts, t_ends: (N,) interval bounds along the ray, in metres (unit directions).
        ray_ids: (N,) ray index of each sample, non-decreasing (a ray's samples contiguous and
            in order along it).
        n_rays: R.
        near, far: (R,) the segment of each ray the sampler placed samples in (0 where missed).
        hit: (R,) bool, rays with a non-empty segment.
    """

    positions: torch.Tensor
    t_starts: torch.Tensor
    t_ends: torch.Tensor
    ray_ids: torch.Tensor
    n_rays: int
    near: torch.Tensor
    far: torch.Tensor
    hit: torch.Tensor

    def __len__(self) -> int:
        return int(self.ray_ids.shape[0])

    @property
    def deltas(self) -> torch.Tensor:
        """(N,) interval lengths."""
        return self.t_ends - self.t_starts

    @property
    def t_mids(self) -> torch.Tensor:
        """(N,) interval midpoints."""
        return (self.t_starts + self.t_ends) * 0.5

    @classmethod
    def from_dense(cls, positions: torch.Tensor, t_starts: torch.Tensor, t_ends: torch.Tensor,
                   near: torch.Tensor, far: torch.Tensor, hit: torch.Tensor) -> "RaySamples":
        """Pack dense samples ``positions (R, S, 3)``, ``t_starts/t_ends (R, S)``, leaving out
        the rays that miss (``hit (R,)`` False)."""
        R, S = t_starts.shape
        ray_ids = torch.arange(R, device=t_starts.device).repeat_interleave(S)
        keep = hit.repeat_interleave(S)
        return cls(positions.reshape(-1, 3)[keep], t_starts.reshape(-1)[keep], t_ends.reshape(-1)[keep],
                   ray_ids[keep], R, near, far, hit)


@runtime_checkable
class BoundSampler(Protocol):
    """A sampler bound to one frame and one feature camera (:meth:`Sampler.bind`)."""

    camera: Camera

    def sample(self, pixels: torch.Tensor, *, training: bool = False,
               generator: torch.Generator | None = None) -> RaySamples:
        """Packed samples of the rays through the pixel centres ``pixels (R,)`` (row-major
        indices into the bound camera's image).

        Args:
            training: draw random (jittered) samples; False: deterministic.
            generator: random source for training-mode jitter.
        """
        ...


@runtime_checkable
class Sampler(Protocol):
    """Places samples along rays; see the module docstring."""

    def bind(self, frame: "FrameFeatures", camera: Camera) -> BoundSampler:
        """Bind to the posed body of ``frame`` and to ``camera`` (the feature-resolution camera
        whose pixel centres the rays go through)."""
        ...


@runtime_checkable
class SampleFilter(Protocol):
    """Drops samples after the body projection and before the MLP (dropping a sample is giving
    its interval zero density), e.g. :class:`~garmentnerf.model.height_band.HeightBandFilter`."""

    def keep(self, points: "BodyPoints") -> torch.Tensor:
        """(n,) bool on the CPU: which of the projected samples ``points`` to evaluate."""
        ...


def pixel_rays(camera: Camera, pixels: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """(R, 3) origins and unit directions of the rays through the pixel centres ``pixels (R,)``
    (row-major; None: every pixel) of ``camera``, float32."""
    origins, dirs = camera_rays(camera)
    origins, dirs = origins.reshape(-1, 3), dirs.reshape(-1, 3)
    if pixels is None:
        return origins, dirs
    pixels = pixels.to("cpu").long()
    return origins[pixels], dirs[pixels]


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
    t_starts, t_ends = intervals_between(t, t_near, t_far)
    return t, t_starts, t_ends


def intervals_between(t: torch.Tensor, t_near: torch.Tensor, t_far: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The intervals that samples ``t (R, S)`` (sorted along each ray, inside [t_near, t_far] (R,)) stand
    for: boundaries halfway between neighbours, the first starting at t_near and the last ending at
    t_far, so they tile the segment. Returns t_starts, t_ends (R, S)."""
    mid = (t[:, 1:] + t[:, :-1]) * 0.5
    t_starts = torch.cat([t_near.unsqueeze(-1), mid], dim=-1)
    t_ends = torch.cat([mid, t_far.unsqueeze(-1)], dim=-1)
    return t_starts, t_ends


def padded_box(aabb: torch.Tensor, padding: float) -> torch.Tensor:
    """(2, 3) the body box ``aabb`` [min, max] grown by ``padding`` metres on every side: the box
    the samplers place samples in (no sample of a frame lies outside it)."""
    pad = torch.tensor([[-float(padding)], [float(padding)]], dtype=aabb.dtype, device=aabb.device)
    return aabb + pad


class BoxStratifiedSampler:
    """The paper's sampler: S stratified samples inside the padded body box.

    Args:
        num_samples: S (paper: 64).
        padding: metres added to every side of the box (paper code: 0.05).
        near: smallest distance from the ray origin.
    """

    def __init__(self, num_samples: int = 64, padding: float = BBOX_PADDING, near: float = 0.0):
        if num_samples < 1:
            raise ValueError(f"num_samples must be >= 1, got {num_samples}")
        if padding < 0:
            raise ValueError(f"padding must be >= 0, got {padding}")
        self.num_samples = num_samples
        self.padding = padding
        self.near = near

    @classmethod
    def from_config(cls, cfg) -> "BoxStratifiedSampler":
        return cls(cfg.sampler.samples_per_ray, BBOX_PADDING)

    def padded_box(self, aabb: torch.Tensor) -> torch.Tensor:
        """(2, 3) the body box ``aabb`` grown by :attr:`padding` on every side."""
        return padded_box(aabb, self.padding)

    def bind(self, frame: "FrameFeatures", camera: Camera) -> "BoundBoxSampler":
        return BoundBoxSampler(self, frame.aabb, camera)

    def sample_rays(self, origins: torch.Tensor, directions: torch.Tensor, aabb: torch.Tensor, *,
                    training: bool = False, generator: torch.Generator | None = None) -> RaySamples:
        """Packed samples of arbitrary rays ``origins, directions (R, 3)`` (unit directions) in
        the body box ``aabb (2, 3)`` [min, max]; rays that miss the padded box get none."""
        if origins.ndim != 2 or origins.shape[-1] != 3 or directions.shape != origins.shape:
            raise ValueError(f"origins and directions must both be (R, 3), got {tuple(origins.shape)} "
                             f"and {tuple(directions.shape)}")
        if aabb.shape != (2, 3):
            raise ValueError(f"aabb must be (2, 3) [min, max], got {tuple(aabb.shape)}")
        if directions.numel() and float((directions.norm(dim=-1) - 1.0).abs().max()) > 1e-3:
            raise ValueError("directions must be unit vectors (interval lengths are metres)")
        t_near, t_far, hit = ray_aabb_intersect(origins, directions, self.padded_box(aabb.to(origins.dtype)),
                                                self.near)
        t, t_starts, t_ends = stratified_intervals(t_near, t_far, self.num_samples, training, generator)
        positions = origins.unsqueeze(1) + t.unsqueeze(-1) * directions.unsqueeze(1)
        return RaySamples.from_dense(positions, t_starts, t_ends, t_near, t_far, hit)


class BoundBoxSampler:
    """A :class:`BoxStratifiedSampler` bound to a body box and a feature camera."""

    def __init__(self, sampler: BoxStratifiedSampler, aabb: torch.Tensor, camera: Camera):
        self.sampler = sampler
        self.aabb = aabb
        self.camera = camera

    def sample(self, pixels: torch.Tensor, *, training: bool = False,
               generator: torch.Generator | None = None) -> RaySamples:
        origins, dirs = pixel_rays(self.camera, pixels)
        return self.sampler.sample_rays(origins, dirs, self.aabb, training=training, generator=generator)


__all__ = ["RaySamples", "Sampler", "BoundSampler", "SampleFilter", "BoxStratifiedSampler", "BoundBoxSampler", "pixel_rays",
           "padded_box", "body_aabb", "ray_aabb_intersect", "stratified_intervals", "intervals_between"]
