"""UV-space attribute rasteriser: per-vertex attributes of a mesh baked into a texture-space map.

Layout of the maps (the contract every user of them relies on)
    A map is a tensor ``(H, W, C)``. Texel (row r, column c) covers u in [c/W, (c+1)/W] and
    v in [r/H, (r+1)/H]; its centre is at ``((c + 0.5) / W, (r + 0.5) / H)``. So **row 0 is v = 0**
    (the bottom of the texture in the usual picture with v up): the same layout as GL texture
    memory, so a map can be uploaded with ``ctx.texture`` and sampled with ``texture(tex, uv)`` in a
    shader as is. Shown as an image with row 0 on top it appears upside down; that is intended.

    ``torch.nn.functional.grid_sample(..., align_corners=False)`` reads the same texel for
    ``grid = uv_to_grid(uv) = 2 * uv - 1`` (grid x follows the columns, grid y the rows);
    :func:`sample_uv_map` wraps this.

Rasterisation
    One draw call of the atlas's triangles at their UV positions, with the C channels split over
    ceil(C / 4) RGBA32F render targets (at most 8, so C <= 32). Interpolation is linear in UV
    space. A texel is covered when its centre is inside a UV triangle (GL's fill rule; no
    conservative rasterisation). Overlapping charts: the triangle drawn last wins.
    Empty texels within ``dilation_radius`` of a covered one take the nearest covered texel's value
    (:class:`~garmentnerf.gl.dilation.NearestTexelDilation`, precomputed once); the rest are 0.
"""

from __future__ import annotations

from typing import NamedTuple

import moderngl
import numpy as np
import torch
import torch.nn.functional as F

from garmentnerf.gl.dilation import NearestTexelDilation
from garmentnerf.gl.shaders import build_program

#: The most render targets one draw call writes (GL guarantees 8 draw buffers): 32 channels.
MAX_TARGETS = 8
MAX_CHANNELS = 4 * MAX_TARGETS

DEFAULT_RESOLUTION = 128
DEFAULT_DILATION_RADIUS = 4.0


def uv_to_grid(uv: torch.Tensor) -> torch.Tensor:
    """Texture coordinates (N, 2) in [0, 1] (u right, v up) -> ``grid_sample`` coordinates in [-1, 1]
    for maps made by :class:`UVAttributeRasterizer`, with ``align_corners=False``."""
    return uv * 2.0 - 1.0


def texel_centers_uv(height: int, width: int, dtype=torch.float32, device=None) -> torch.Tensor:
    """(H, W, 2) texture coordinates (u, v) of every texel centre of a map."""
    v = (torch.arange(height, dtype=dtype, device=device) + 0.5) / height
    u = (torch.arange(width, dtype=dtype, device=device) + 0.5) / width
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    return torch.stack([uu, vv], dim=-1)


def sample_uv_map(values: torch.Tensor, uv: torch.Tensor, mode: str = "bilinear") -> torch.Tensor:
    """Look up a map ``(H, W, C)`` at texture coordinates ``uv (N, 2)`` -> ``(N, C)``.

    Bilinear by default, clamped at the map border (``padding_mode="border"``).
    """
    if values.ndim != 3:
        raise ValueError(f"values must be (H, W, C), got shape {tuple(values.shape)}")
    image = values.permute(2, 0, 1).unsqueeze(0)  # (1, C, H, W)
    grid = uv_to_grid(uv.to(values.dtype)).reshape(1, 1, -1, 2)
    out = F.grid_sample(image, grid, mode=mode, padding_mode="border", align_corners=False)
    return out[0, :, 0].T


class UVRaster(NamedTuple):
    """One UV-space map: ``values (H, W, C)`` float32, gutters filled; ``mask (H, W)`` bool, the
    texels the atlas covers (before dilation)."""

    values: torch.Tensor
    mask: torch.Tensor


def _as_numpy(array, dtype) -> np.ndarray:
    if isinstance(array, torch.Tensor):
        array = array.detach().cpu().numpy()
    return np.ascontiguousarray(array, dtype=dtype)


def _parse_resolution(resolution) -> tuple[int, int]:
    if isinstance(resolution, (int, np.integer)):
        height = width = int(resolution)
    else:
        height, width = (int(x) for x in resolution)
    if height < 1 or width < 1:
        raise ValueError(f"resolution must be positive, got {resolution}")
    return height, width


class _TargetSet:
    """GL objects for one number of render targets (4 channels each)."""

    def __init__(self, ctx: moderngl.Context, num_targets: int, uv_buffer: moderngl.Buffer,
                 index_buffer: moderngl.Buffer, num_vertices: int, height: int, width: int) -> None:
        self.num_targets = num_targets
        self.program = build_program(ctx, "uv_attributes.vert", "uv_attributes.frag",
                                     {"NUM_TARGETS": num_targets})
        self.staging = np.zeros((num_vertices, 4 * num_targets), dtype=np.float32)
        self.attr_buffer = ctx.buffer(reserve=max(4, self.staging.nbytes), dynamic=True)
        content = [(uv_buffer, "2f", "in_uv"), (self.attr_buffer, f"{4 * num_targets}f", "in_attr")]
        self.vao = ctx.vertex_array(self.program, content, index_buffer=index_buffer, index_element_size=4)
        self.textures = [ctx.texture((width, height), 4, dtype="f4") for _ in range(num_targets)]
        for texture in self.textures:
            texture.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self.fbo = ctx.framebuffer(color_attachments=self.textures)
        self.scope = ctx.scope(self.fbo, enable_only=moderngl.NOTHING)
        self.readback = np.empty((num_targets, height, width, 4), dtype=np.float32)

    def release(self) -> None:
        for obj in (self.scope, self.fbo, *self.textures, self.vao, self.attr_buffer, self.program):
            obj.release()


class UVAttributeRasterizer:
    """Rasterises per-UV-vertex attributes into UV-space maps, for one atlas at one resolution.

    Args:
        ctx: the moderngl context that owns every GL object made here.
        uv: (Nuv, 2) texture coordinates in [0, 1], u right, v up.
        uv_faces: (F, 3) indices into ``uv``.
        resolution: ``H = W`` as an int, or ``(H, W)``; default 128.
        dilation_radius: gutter width in texels filled from the nearest covered texel (default 4).

    Attributes:
        height, width: map size.
        mask: (H, W) bool tensor, texels covered by the atlas (constant; computed here once).
        dilation: the precomputed gutter fill.
    """

    def __init__(self, ctx: moderngl.Context, uv, uv_faces, resolution=DEFAULT_RESOLUTION,
                 dilation_radius: float = DEFAULT_DILATION_RADIUS) -> None:
        uv_np = _as_numpy(uv, np.float32)
        faces_np = _as_numpy(uv_faces, np.int64)
        if uv_np.ndim != 2 or uv_np.shape[1] != 2 or len(uv_np) == 0:
            raise ValueError(f"uv must be (Nuv, 2) with Nuv > 0, got shape {uv_np.shape}")
        if not np.all(np.isfinite(uv_np)):
            raise ValueError("uv contains NaN or Inf")
        if faces_np.ndim != 2 or faces_np.shape[1] != 3:
            raise ValueError(f"uv_faces must be (F, 3), got shape {faces_np.shape}")
        if faces_np.size and (faces_np.min() < 0 or faces_np.max() >= len(uv_np)):
            raise ValueError(f"uv_faces index out of range [0, {len(uv_np)})")
        self.ctx = ctx
        self.height, self.width = _parse_resolution(resolution)
        self.num_vertices = len(uv_np)
        self.num_faces = len(faces_np)
        self._uv_buffer = ctx.buffer(uv_np.tobytes())
        self._index_buffer = ctx.buffer(faces_np.astype(np.int32).tobytes() or b"\0" * 12)
        self._targets: dict[int, _TargetSet] = {}
        self._released = False

        ones = torch.ones(self.num_vertices, 1)
        self.mask = self.render_raw(ones)[..., 0] > 0.5
        self.dilation = NearestTexelDilation(self.mask, dilation_radius)

    @property
    def resolution(self) -> tuple[int, int]:
        return self.height, self.width

    def _target_set(self, num_targets: int) -> _TargetSet:
        targets = self._targets.get(num_targets)
        if targets is None:
            targets = _TargetSet(self.ctx, num_targets, self._uv_buffer, self._index_buffer,
                                 self.num_vertices, self.height, self.width)
            self._targets[num_targets] = targets
        return targets

    def render_raw(self, attributes) -> torch.Tensor:
        """Rasterise ``attributes (Nuv, C)`` -> ``(H, W, C)`` float32, without gutter filling
        (empty texels are 0)."""
        if self._released:
            raise RuntimeError("UVAttributeRasterizer used after release()")
        attr = attributes.detach().cpu().numpy() if isinstance(attributes, torch.Tensor) else np.asarray(attributes)
        if attr.ndim != 2 or attr.shape[0] != self.num_vertices:
            raise ValueError(f"attributes must be ({self.num_vertices}, C), got shape {attr.shape}")
        channels = attr.shape[1]
        if not 1 <= channels <= MAX_CHANNELS:
            raise ValueError(f"attributes need 1 to {MAX_CHANNELS} channels, got {channels}")
        num_targets = -(-channels // 4)
        targets = self._target_set(num_targets)

        if channels == 4 * num_targets and attr.dtype == np.float32 and attr.flags.c_contiguous:
            data = attr
        else:
            targets.staging[:, :channels] = attr
            data = targets.staging
        targets.attr_buffer.write(data)

        with targets.scope:
            targets.fbo.clear(0.0, 0.0, 0.0, 0.0)
            if self.num_faces:
                targets.vao.render(moderngl.TRIANGLES)
            for i in range(num_targets):
                targets.fbo.read_into(targets.readback[i], attachment=i, components=4, dtype="f4")

        out = torch.empty((self.height, self.width, num_targets, 4), dtype=torch.float32)
        out.copy_(torch.from_numpy(targets.readback).permute(1, 2, 0, 3))
        out = out.view(self.height, self.width, 4 * num_targets)
        if channels != 4 * num_targets:
            out = out[..., :channels].contiguous()
        return out

    def render(self, attributes) -> UVRaster:
        """Rasterise ``attributes (Nuv, C)`` (float, C <= 32) in one draw call.

        Returns:
            ``UVRaster(values (H, W, C) float32 with gutters filled, mask (H, W) bool)``.
        """
        values = self.render_raw(attributes)
        self.dilation.apply_(values)
        return UVRaster(values, self.mask)

    def release(self) -> None:
        """Free the GL objects (the context itself stays)."""
        if self._released:
            return
        for targets in self._targets.values():
            targets.release()
        self._targets.clear()
        self._uv_buffer.release()
        self._index_buffer.release()
        self._released = True

    def __enter__(self) -> "UVAttributeRasterizer":
        return self

    def __exit__(self, *exc) -> None:
        self.release()
