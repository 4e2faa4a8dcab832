"""Sampling only where the garment can be: inside the body inflated by the garment's height band.

On a 2-core CPU the paper's sampling (128 x 128 rays x 64 samples through a 6 x 256 MLP) costs
seconds per frame; the MLP runs at about 0.25 M points/s, so speed has to come from evaluating
fewer points. :class:`ShellSampler` gives every ray the segment where it crosses a shell around
the posed body, exact for a model with no density outside that shell:

1. **Shell bounds per ray** (:class:`~garmentnerf.gl.shell_raster.ShellRaster`). The skin (the
   projector's faces) is inflated: every vertex pushed out along its unit vertex normal by
   ``shell_margin`` (default: the height band's ``h_max`` + 3 cm, per vertex where the band has a
   per-vertex bound). One GL draw at the feature-image resolution gives each pixel-centre ray the
   nearest entering and the farthest crossing of the shell. A ray whose first crossing leaves
   the shell starts inside it (camera inside the body or the shell, or the entry clipped by the
   near plane): its near is 0. Rays that cross no face get no samples.
2. **Occlusion by the body** (``occlusion``): the same raster pass, drawn with the posed skin
   itself, gives per ray the distance of the first skin crossing; the ray's far bound becomes
   that distance plus ``occlusion_margin`` (default ``-h_min``: the band's depth under the
   skin). The model renders the body opaque (the ground truth's body is), so what lies behind
   the skin adds nothing but the transmittance left after ``-h_min`` of skin, the same order of
   approximation as the early termination. Cameras that may be inside the body skip it.

The two other culls of the render presets are not the sampler's: the height band is a sample
filter (:class:`~garmentnerf.model.height_band.HeightBandFilter`) and early termination an
argument of the volume rendering
(:func:`~garmentnerf.model.volume_rendering.render_packed_segmented`).

Sample placement
    The padded body box of the paper's sampler is cut into S equal bins exactly as
    :class:`~garmentnerf.model.samplers.BoxStratifiedSampler` does, and only the bins that
    overlap the ray's shell segment are kept. In eval mode the samples *are* the
    reference sampler's samples (same positions, same intervals), a subset of them: with
    zero density outside the shell and the band, the culled render equals the reference render
    up to float rounding. In training mode each kept sample is drawn uniformly in its bin and
    stands for its bin (a valid stratified estimate; the reference's intervals meet halfway
    between jittered neighbours instead).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

from garmentnerf.conventions import Camera
from garmentnerf.geometry.winding import point_in_shell
from garmentnerf.gl.shell_raster import ShellBounds, ShellRaster, inflate_surface
from garmentnerf.model.config import BBOX_PADDING
from garmentnerf.model.height_band import HeightRange
from garmentnerf.model.samplers import RaySamples, padded_box, pixel_rays, ray_aabb_intersect

if TYPE_CHECKING:  # pragma: no cover
    from garmentnerf.model.frame_context import FrameFeatures

#: Added to the band's h_max to get the inflation of the shell (metres).
SHELL_EXTRA_MARGIN = 0.03


class ShellSampler:
    """Samples only inside the inflated body shell (see the module docstring).

    Args:
        num_samples: S, bins of the padded box.
        faces: (F, 3) the skin faces to inflate (the model's ``projector.faces``).
        height_range: the band the garment occupies (default :meth:`HeightRange.default`); it sets
            the default shell margin and occlusion margin.
        shell_margin: inflation in metres, a scalar or (V,) per skin vertex (default
            :meth:`HeightRange.shell_margins` with ``SHELL_EXTRA_MARGIN``).
        padding: the box padding of the reference sampler (paper code: 0.05).
        gl_context: moderngl context of the shell raster (None: a headless one of its own).
        occlusion: cut every ray ``occlusion_margin`` behind its first skin crossing.
        occlusion_margin: metres (default ``max(0, -height_range.h_min)``).
    """

    def __init__(self, num_samples: int, faces: torch.Tensor, height_range: HeightRange | None = None, *,
                 shell_margin: float | torch.Tensor | None = None, padding: float = BBOX_PADDING,
                 gl_context=None, occlusion: bool = False, occlusion_margin: float | None = None):
        if num_samples < 1:
            raise ValueError(f"num_samples must be >= 1, got {num_samples}")
        if padding < 0:
            raise ValueError(f"padding must be >= 0, got {padding}")
        self.num_samples = int(num_samples)
        self.faces = torch.as_tensor(faces).detach().cpu().long()
        self.height_range = height_range if height_range is not None else HeightRange.default()
        margin = shell_margin if shell_margin is not None else self.height_range.shell_margins(SHELL_EXTRA_MARGIN)
        margin = margin.detach().cpu().float() if torch.is_tensor(margin) else float(margin)
        if float(torch.as_tensor(margin).min()) <= 0 or not bool(torch.isfinite(torch.as_tensor(margin)).all()):
            raise ValueError("shell_margin must be finite and > 0")
        self.shell_margin = margin
        self.padding = float(padding)
        self.occlusion = bool(occlusion)
        self.occlusion_margin = (float(occlusion_margin) if occlusion_margin is not None
                                 else max(0.0, -self.height_range.h_min))
        if self.occlusion_margin < 0:
            raise ValueError(f"occlusion_margin must be >= 0, got {occlusion_margin}")
        self.raster = ShellRaster(gl_context)
        self._shell: tuple[torch.Tensor, torch.Tensor] | None = None  # (inflated, skin) of the last frame
        self._shell_source: torch.Tensor | None = None  # the posed vertices it was made from (held: ids stay unique)
        self._shell_version = -1

    def shell(self, posed_vertices: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(inflated shell, skin) vertices (V, 3) of the body posed as ``posed_vertices``; the
        last frame's are reused while the same, unmodified tensor comes back."""
        if posed_vertices is not self._shell_source or posed_vertices._version != self._shell_version:
            skin = posed_vertices.detach().to("cpu", torch.float32).clone()
            self._shell = (inflate_surface(skin, self.faces, self.shell_margin), skin)
            self._shell_source, self._shell_version = posed_vertices, posed_vertices._version
        return self._shell

    def camera_bounds(self, posed_vertices: torch.Tensor, camera: Camera) -> ShellBounds:
        """The per-pixel ray bounds (H, W) of the shell around ``posed_vertices`` seen by ``camera``."""
        shell, skin = self.shell(posed_vertices)
        inside = point_in_shell(camera.center, skin, self.faces, float(torch.as_tensor(self.shell_margin).max()))
        bounds = self.raster.render(shell, self.faces, camera, origin_inside=inside)
        if self.occlusion and not point_in_shell(camera.center, skin, self.faces, 0.0):
            hit_skin = self.raster.render(skin, self.faces, camera)
            far = torch.where(hit_skin.hit, torch.minimum(bounds.far, hit_skin.near + self.occlusion_margin),
                              bounds.far)
            bounds = ShellBounds(bounds.near, far, bounds.hit)
        return bounds

    def bind(self, frame: "FrameFeatures", camera: Camera) -> "BoundShellSampler":
        """Rasterise the shell of ``frame``'s posed body seen by ``camera`` (the feature camera)."""
        return BoundShellSampler(self, frame.aabb, camera, self.camera_bounds(frame.posed_vertices, camera))

    def release(self) -> None:
        """Free the GL objects of the shell raster."""
        self.raster.release()


class BoundShellSampler:
    """A :class:`ShellSampler` bound to a frame and a feature camera: its shell raster is made."""

    def __init__(self, sampler: ShellSampler, aabb: torch.Tensor, camera: Camera, bounds: ShellBounds):
        self.sampler = sampler
        self.aabb = aabb
        self.camera = camera
        self.bounds = bounds

    def sample(self, pixels: torch.Tensor, *, training: bool = False,
               generator: torch.Generator | None = None) -> RaySamples:
        """Packed samples inside the shell of the rays through ``pixels (R,)``."""
        sampler = self.sampler
        origins, directions = pixel_rays(self.camera, pixels)
        R, dev, dt = origins.shape[0], origins.device, origins.dtype
        aabb = self.aabb.to(dt)
        tb0, tb1, box_hit = ray_aabb_intersect(origins, directions, padded_box(aabb, sampler.padding), 0.0)
        idx = pixels.to("cpu").long()
        b = self.bounds
        near, far, hit = (b.near.reshape(-1)[idx].to(dev, dt), b.far.reshape(-1)[idx].to(dev, dt),
                          b.hit.reshape(-1)[idx].to(dev))
        S = sampler.num_samples
        L = tb1 - tb0
        bw = L / S
        safe = torch.where(bw > 0, bw, torch.ones_like(bw))
        first = torch.floor((torch.maximum(near, tb0) - tb0) / safe).clamp(0, S - 1)
        last = (torch.ceil((torch.minimum(far, tb1) - tb0) / safe) - 1).clamp(0, S - 1)
        ok = box_hit & hit & (far > tb0) & (near < tb1) & (last >= first)
        first = first.long()
        counts = torch.where(ok, last.long() - first + 1, torch.zeros_like(first))
        ray_ids = torch.repeat_interleave(torch.arange(R, device=dev), counts)
        starts = torch.cumsum(counts, 0) - counts
        i = (torch.arange(ray_ids.shape[0], device=dev) - starts[ray_ids] + first[ray_ids]).to(dt)
        t0, Lr = tb0[ray_ids], L[ray_ids]
        # The reference sampler's formulas (samplers.stratified_intervals), bin for bin.
        if training:
            u = i + torch.rand(i.shape, dtype=dt, device=dev, generator=generator)
            t = t0 + Lr * (u / S)
            ts = t0 + Lr * (i / S)
            te = torch.where(i == S - 1, tb1[ray_ids], t0 + Lr * ((i + 1) / S))
        else:
            t = t0 + Lr * ((i + 0.5) / S)
            t_prev = t0 + Lr * ((i - 0.5) / S)
            t_next = t0 + Lr * ((i + 1.5) / S)
            ts = torch.where(i == 0, t0, (t_prev + t) * 0.5)
            te = torch.where(i == S - 1, tb1[ray_ids], (t + t_next) * 0.5)
        positions = origins[ray_ids] + t.unsqueeze(-1) * directions[ray_ids]
        zero = torch.zeros_like(near)
        return RaySamples(positions, ts, te, ray_ids, R, torch.where(ok, near, zero), torch.where(ok, far, zero), ok)


__all__ = ["ShellSampler", "BoundShellSampler", "SHELL_EXTRA_MARGIN"]
