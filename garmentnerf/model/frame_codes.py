"""Per-frame codes (:class:`~garmentnerf.model.config.FrameCodeConfig`): a learned residual of E's output per
training frame, dense or held only where the garment reads it.

A code is ``C x r x r`` texels of the body's UV atlas, upsampled bilinearly to E's resolution and
added to F^s_t. The garment reads F^s_t only at the atlas coordinates of its samples' closest body
points, a part of the atlas (about a third for the bundled dress at 128 x 128), so a *sparse* code
(``FrameCodeConfig.support_margin`` >= 0) keeps values only on a fixed set of texels, its
**support**, and is zero elsewhere: codes as fine as E's own output then fit a demo's size budget.
The support is the bilinear footprint of the garment's closest body points over the training frames
(:func:`garment_texels`), grown by a margin (:func:`grow_texels`); it is data, not configuration, so
it is stored with the weights (the buffer ``support``) and a model takes it from the file it loads
(:meth:`FrameCodes.adopt_state`).

Layouts of ``codes``: ``(frames, C, r, r)`` dense; ``(frames, C, K)`` sparse, K the support's
texels in row-major order.
"""

from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

__all__ = ["FrameCodes", "on_grid", "garment_texels", "grow_texels", "resample_codes", "adapt_frame_codes"]


class FrameCodes(nn.Module):
    """``count`` codes of ``channels x resolution x resolution``, zero at the start; a call gives one
    code upsampled bilinearly to E's output resolution.

    Args:
        sparse: hold values only on a support (module docstring); it starts empty (every code
            zero) until :meth:`set_support` or a loaded state gives one.
    """

    def __init__(self, count: int, channels: int, resolution: int, sparse: bool = False) -> None:
        super().__init__()
        self.count, self.channels, self.resolution = int(count), int(channels), int(resolution)
        if sparse:
            self.register_buffer("support", torch.zeros(resolution, resolution, dtype=torch.bool))
            self.codes = nn.Parameter(torch.zeros(count, channels, 0))
        else:
            self.support = None
            self.codes = nn.Parameter(torch.zeros(count, channels, resolution, resolution))

    @property
    def sparse(self) -> bool:
        return self.support is not None

    def set_support(self, support: torch.Tensor) -> None:
        """Hold the codes on ``support`` ((r, r) bool), every code zero (sparse codes only; before
        an optimiser is made, which would keep the old tensor)."""
        if not self.sparse:
            raise ValueError("dense per-frame codes have no support (FrameCodeConfig.support_margin)")
        support = torch.as_tensor(support, dtype=torch.bool)
        if tuple(support.shape) != (self.resolution, self.resolution):
            raise ValueError(f"a support of shape {tuple(support.shape)} for codes of {self.resolution} x "
                             f"{self.resolution}")
        device = self.codes.device
        self.support = support.to(device).clone()
        self.codes = nn.Parameter(torch.zeros(self.count, self.channels, int(support.sum()), device=device,
                                              dtype=self.codes.dtype))

    def adopt_state(self, state: dict[str, torch.Tensor], prefix: str) -> None:
        """Take the support of a state dict about to be loaded (its ``prefix + 'support'``), so its
        codes fit; nothing for dense codes or a state without one."""
        support = state.get(prefix + "support")
        if self.sparse and support is not None:
            self.set_support(support)

    def dense(self, index: int) -> torch.Tensor:
        """(C, r, r) code ``index`` at its own resolution (zero off the support); ValueError when out
        of range."""
        if not 0 <= int(index) < self.count:
            raise ValueError(f"per-frame code {index} out of range (the model has {self.count})")
        code = self.codes[int(index)]
        return code if not self.sparse else on_grid(code, self.support)

    def forward(self, index: int, resolution: int) -> torch.Tensor:
        """(C, R, R) code ``index`` at ``resolution`` R (E's output); ValueError when out of range."""
        code = self.dense(index)
        if code.shape[-1] == int(resolution):
            return code
        return F.interpolate(code.unsqueeze(0), size=(resolution, resolution), mode="bilinear",
                             align_corners=False)[0]


def on_grid(values: torch.Tensor, support: torch.Tensor) -> torch.Tensor:
    """(..., K) values on the K texels of ``support`` ((r, r) bool, row-major) -> (..., r, r), zero
    off the support (differentiable in ``values``)."""
    r = support.shape[-1]
    texels = support.flatten().nonzero().squeeze(1)
    flat = values.new_zeros(*values.shape[:-1], r * r).index_copy(-1, texels, values)
    return flat.view(*values.shape[:-1], r, r)


def garment_texels(uv: torch.Tensor, resolution: int) -> torch.Tensor:
    """(r, r) bool: the texels of an ``r x r`` map that bilinear reads at ``uv`` ((N, 2) atlas
    coordinates, u right, v up, row 0 at v = 0: :func:`~garmentnerf.model.uv_maps.sample_uv_map`)
    weigh (the four around each point, clamped at the border)."""
    r = int(resolution)
    uv = torch.as_tensor(uv, dtype=torch.float64).reshape(-1, 2)
    hit = torch.zeros(r, r, dtype=torch.bool)
    x0 = torch.floor(uv[:, 0] * r - 0.5).long()
    y0 = torch.floor(uv[:, 1] * r - 0.5).long()
    for dx in (0, 1):
        for dy in (0, 1):
            hit[(y0 + dy).clamp(0, r - 1), (x0 + dx).clamp(0, r - 1)] = True
    return hit


def grow_texels(mask: torch.Tensor, margin: int) -> torch.Tensor:
    """(r, r) bool ``mask`` grown by ``margin`` texels: every texel within ``margin`` of a set one
    along both axes (a square neighbourhood)."""
    if margin <= 0:
        return mask.clone()
    grown = F.max_pool2d(mask[None, None].float(), 2 * margin + 1, stride=1, padding=margin)[0, 0]
    return grown > 0


def resample_codes(codes: torch.Tensor, resolution: int) -> torch.Tensor:
    """(N, C, r, r) dense codes -> (N, C, R, R) at ``resolution``, bilinear as :meth:`FrameCodes.forward`
    upsamples (codes upsampled to E's resolution compute what the coarse ones did)."""
    if codes.shape[-1] == int(resolution):
        return codes
    return F.interpolate(codes, size=(int(resolution), int(resolution)), mode="bilinear", align_corners=False)


def adapt_frame_codes(state: dict[str, torch.Tensor], own: dict[str, torch.Tensor],
                      prefix: str = "frame_codes.") -> list[str]:
    """Make a weights file's codes (``state``) fit a model's (``own``): dense or sparse, at another
    resolution. Codes of another resolution are resampled (:func:`resample_codes`) and a sparse
    model's are the resampled ones on its support (its support kept), so the model computes what the
    file's did wherever it holds values. Returns the keys changed; nothing when the file has no
    codes, another count or channels, or the same layout."""
    key, support_key = prefix + "codes", prefix + "support"
    if key not in state or key not in own:
        return []
    codes, want = state[key], own[key]
    if codes.shape[:2] != want.shape[:2]:
        return []
    if support_key in state:  # the file's codes are sparse: make them dense first
        codes = on_grid(codes, state[support_key].bool())
    target_support = own.get(support_key)
    if target_support is None:
        if support_key not in state and codes.shape == want.shape:
            return []
        state[key] = resample_codes(codes.float(), want.shape[-1]).to(codes.dtype)
        state.pop(support_key, None)
        return [key]
    if support_key in state and torch.equal(state[support_key].bool(), target_support.bool()):
        return []
    resampled = resample_codes(codes.float(), target_support.shape[-1]).flatten(2)
    state[key] = resampled[:, :, target_support.flatten().nonzero().squeeze(1)].to(codes.dtype)
    state[support_key] = target_support.clone()
    return [key, support_key]
