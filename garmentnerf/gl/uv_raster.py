"""UV-space attribute rasteriser: per-vertex attributes of a mesh baked into a texture-space map.

Layout of the maps (the contract every user of them relies on)
    A map is a tensor ``(H, W, C)``. Texel (row r, column c) covers u in [c/W, (c+1)/W] and
    v in [r/H, (r+1)/H]; its centre is at ``((c + 0.5) / W, (r + 0.5) / H)``. So **row 0 is v = 0**
    (the bottom of the texture in the usual picture with v up): the same layout as GL texture
    memory, so a map can be uploaded with ``ctx.texture`` and sampled with ``texture(tex, uv)`` in a
    shader as is. Shown as an image with row 0 on top it appears upside down; that is intended.

    The model reads a map at texture coordinates with
    :func:`garmentnerf.model.uv_maps.sample_uv_map` (``grid_sample`` with ``align_corners=False``).

Rasterisation
    A texel is covered when its centre is inside a UV triangle (GL's fill rule; no conservative
    rasterisation); overlapping charts: the triangle drawn last wins. Attributes are interpolated
    linearly in UV space. Empty texels within ``dilation_radius`` of a covered one take the nearest
    covered texel's value (:class:`~garmentnerf.gl.dilation.NearestTexelDilation`, precomputed
    once); the rest are 0. Two methods give the same maps to float32 interpolation precision
    (positions on a 1 m cube at 128 x 128: 1e-7 m with ``"gather"``, 3e-7 m with ``"draw"``):

    ``"gather"`` (default)
        One GL draw at construction rasterises the atlas into a UV G-buffer: the UV face covering
        each texel centre (``shaders/uv_gbuffer.*``), whose barycentrics at the centre are then
        computed exactly in float64; gutter texels point at their nearest covered texel's face and
        barycentrics. Each frame is three row gathers and two multiply-adds in torch: about 0.3 ms
        at 128 x 128 x 12 for a 27k-triangle atlas on two CPU cores, on any torch device, and
        differentiable with respect to the attributes.
    ``"draw"``
        Each frame draws the atlas's triangles with the attributes as vertex data, the C channels
        split over ceil(C / 4) RGBA32F render targets of one draw call (``shaders/uv_attributes.*``),
        reads them back and fills the gutters with one gather. On Mesa llvmpipe per-triangle setup
        dominates (about 4-7 ms for 27k triangles at 128 x 128 x 12 on two cores); on a hardware
        GL driver it is the natural choice when the map should stay on the GPU as a texture.

    C <= 32 channels (8 render targets) for both.
"""

from __future__ import annotations

from typing import NamedTuple

import moderngl
import numpy as np
import torch

from garmentnerf.gl.context import current
from garmentnerf.gl.dilation import NearestTexelDilation
from garmentnerf.gl.mesh_arrays import as_numpy
from garmentnerf.gl.resources import GLObjectsOwner, TargetCache
from garmentnerf.gl.shaders import build_program

#: The most render targets one draw call writes (GL guarantees 8 draw buffers): 32 channels.
MAX_TARGETS = 8
MAX_CHANNELS = 4 * MAX_TARGETS

DEFAULT_RESOLUTION = 128
DEFAULT_DILATION_RADIUS = 4.0


class UVRaster(NamedTuple):
    """One UV-space map: ``values (H, W, C)`` float32, gutters filled; ``mask (H, W)`` bool, the
    texels the atlas covers (before dilation; the rasteriser's own tensor, the same every call:
    do not modify it in place)."""

    values: torch.Tensor
    mask: torch.Tensor


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


def _uv_gbuffer(ctx: moderngl.Context, uv: np.ndarray, faces: np.ndarray, height: int, width: int):
    """Rasterise the atlas once: per texel, the covering UV face (-1: none) and its barycentrics."""
    program = build_program(ctx, "uv_gbuffer.vert", "uv_gbuffer.frag")
    buffer = ctx.buffer(np.ascontiguousarray(uv[faces.reshape(-1)]).tobytes() or b"\0" * 8)
    vao = ctx.vertex_array(program, [(buffer, "2f", "in_uv")])
    texture = ctx.texture((width, height), 4, dtype="f4")
    fbo = ctx.framebuffer(color_attachments=[texture])
    scope = ctx.scope(fbo, enable_only=moderngl.NOTHING)
    data = np.empty((height, width, 4), dtype=np.float32)
    try:
        with scope:
            fbo.clear(0.0, 0.0, 0.0, 0.0)
            if len(faces):
                vao.render(moderngl.TRIANGLES, vertices=3 * len(faces))
            fbo.read_into(data, components=4, dtype="f4")
    finally:
        for obj in (scope, fbo, texture, vao, buffer, program):
            obj.release()
    face = np.rint(data[..., 2]).astype(np.int64) - 1
    covered = face >= 0
    # GL gives the covering face; its barycentrics are recomputed exactly (float64) at the texel
    # centre, since the rasteriser's interpolants carry ~1e-5 texel of sub-pixel snapping error.
    bary = np.stack([1.0 - data[..., 0] - data[..., 1], data[..., 0], data[..., 1]], axis=-1).astype(np.float64)
    bary[~covered] = 0.0
    rows, cols = np.nonzero(covered)
    if len(rows):
        corners = uv.astype(np.float64)[faces[face[rows, cols]]]  # (K, 3, 2)
        p = np.stack([(cols + 0.5) / width, (rows + 0.5) / height], axis=-1)
        e1, e2, d = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0], p - corners[:, 0]
        det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
        ok = np.abs(det) > 1e-300
        safe = np.where(ok, det, 1.0)
        b1 = (d[:, 0] * e2[:, 1] - d[:, 1] * e2[:, 0]) / safe
        b2 = (e1[:, 0] * d[:, 1] - e1[:, 1] * d[:, 0]) / safe
        exact = np.stack([1.0 - b1 - b2, b1, b2], axis=-1)
        bary[rows[ok], cols[ok]] = exact[ok]
    return face, bary.astype(np.float32)


METHODS = ("gather", "draw")


class UVAttributeRasterizer(GLObjectsOwner):
    """Rasterises per-UV-vertex attributes into UV-space maps, for one atlas at one resolution.

    GL objects made here belong to ``ctx``, which the methods make current (and leave current)
    before using GL.

    Args:
        ctx: the moderngl context that owns every GL object made here.
        uv: (Nuv, 2) texture coordinates in [0, 1], u right, v up.
        uv_faces: (F, 3) indices into ``uv``.
        resolution: ``H = W`` as an int, or ``(H, W)``; default 128.
        dilation_radius: gutter width in texels filled from the nearest covered texel (default 4).
        method: ``"gather"`` (default) or ``"draw"``; see the module docstring.

    Attributes:
        height, width: map size.
        mask: (H, W) bool tensor, texels covered by the atlas (constant; computed here once).
        texel_face: (H, W) int64 UV face covering each texel centre (-1: none).
        texel_bary: (H, W, 3) float32 barycentrics of the texel centre in that face (0: none).
        dilation: the precomputed gutter fill.
    """

    def __init__(self, ctx: moderngl.Context, uv, uv_faces, resolution=DEFAULT_RESOLUTION,
                 dilation_radius: float = DEFAULT_DILATION_RADIUS, method: str = "gather") -> None:
        uv_np = as_numpy(uv, np.float32)
        faces_np = as_numpy(uv_faces, np.int64)
        if uv_np.ndim != 2 or uv_np.shape[1] != 2 or len(uv_np) == 0:
            raise ValueError(f"uv must be (Nuv, 2) with Nuv > 0, got shape {uv_np.shape}")
        if not np.all(np.isfinite(uv_np)):
            raise ValueError("uv contains NaN or Inf")
        if faces_np.ndim != 2 or faces_np.shape[1] != 3:
            raise ValueError(f"uv_faces must be (F, 3), got shape {faces_np.shape}")
        if len(faces_np) >= 2**24:
            raise ValueError(f"at most 2^24 - 1 UV faces, got {len(faces_np)}")
        if faces_np.size and (faces_np.min() < 0 or faces_np.max() >= len(uv_np)):
            raise ValueError(f"uv_faces index out of range [0, {len(uv_np)})")
        if method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {method!r}")
        self.ctx = ctx
        self.method = method
        self.height, self.width = _parse_resolution(resolution)
        self.num_vertices = len(uv_np)
        self.num_faces = len(faces_np)
        self._uv_np, self._faces_np = uv_np, faces_np
        self._uv_buffer: moderngl.Buffer | None = None
        self._index_buffer: moderngl.Buffer | None = None
        self._targets: TargetCache[_TargetSet] = TargetCache(self._make_target_set)
        self._tables: dict[torch.device, tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = {}
        self._released = False

        with current(ctx):  # make this context current (several may live in one process)
            face, bary = _uv_gbuffer(ctx, uv_np, faces_np, self.height, self.width)
        self.texel_face = torch.from_numpy(face)
        self.texel_bary = torch.from_numpy(bary)
        self.mask = self.texel_face >= 0
        self.dilation = NearestTexelDilation(self.mask, dilation_radius)

        # Gather tables over the texels that get a value: covered ones read their own face, filled
        # gutter texels their nearest covered texel's.
        source = np.full(self.height * self.width, -1, dtype=np.int64)
        covered = np.flatnonzero(self.mask.numpy())
        source[covered] = covered
        source[self.dilation.dst.numpy()] = self.dilation.src.numpy()
        rows = np.flatnonzero(source >= 0)
        src = source[rows]
        self._gather_rows = torch.from_numpy(rows)
        self._gather_corners = torch.from_numpy(faces_np[face.reshape(-1)[src]].T.copy())  # (3, K)
        self._gather_weights = torch.from_numpy(bary.reshape(-1, 3)[src].T[:, :, None].copy())  # (3, K, 1)

    @property
    def resolution(self) -> tuple[int, int]:
        return self.height, self.width

    # -- "gather" ----------------------------------------------------------------------------
    def _tables_on(self, device: torch.device):
        tables = self._tables.get(device)
        if tables is None:
            tables = tuple(t.to(device) for t in (self._gather_rows, self._gather_corners, self._gather_weights))
            self._tables[device] = tables
        return tables

    def _render_gather(self, attributes: torch.Tensor) -> torch.Tensor:
        rows, corners, weights = self._tables_on(attributes.device)
        attr = attributes.to(torch.float32)
        out = attr.index_select(0, corners[0]) * weights[0]
        out.addcmul_(attr.index_select(0, corners[1]), weights[1])
        out.addcmul_(attr.index_select(0, corners[2]), weights[2])
        if len(rows) == self.height * self.width:
            return out.view(self.height, self.width, -1)
        full = out.new_zeros(self.height * self.width, out.shape[1])
        full = full.index_copy(0, rows, out)
        return full.view(self.height, self.width, -1)

    # -- "draw" ------------------------------------------------------------------------------
    def _make_target_set(self, num_targets: int) -> _TargetSet:
        if self._uv_buffer is None:
            self._uv_buffer = self.ctx.buffer(self._uv_np.tobytes())
            self._index_buffer = self.ctx.buffer(self._faces_np.astype(np.int32).tobytes() or b"\0" * 12)
        return _TargetSet(self.ctx, num_targets, self._uv_buffer, self._index_buffer, self.num_vertices,
                          self.height, self.width)

    def _render_draw(self, attr: np.ndarray) -> torch.Tensor:
        channels = attr.shape[1]
        num_targets = -(-channels // 4)
        targets = self._targets.get(num_targets)
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
        self.dilation.apply_(out)
        return out

    # -- public ------------------------------------------------------------------------------
    def render(self, attributes) -> UVRaster:
        """Rasterise ``attributes (Nuv, C)`` (float, 1 <= C <= 32).

        Returns:
            ``UVRaster(values (H, W, C) float32 with gutters filled, mask (H, W) bool)``. With
            ``method="gather"`` the values are on the attributes' device and carry their gradient;
            with ``"draw"`` they are a CPU tensor.
        """
        self._check_not_released()
        if not isinstance(attributes, torch.Tensor):
            attributes = torch.as_tensor(np.asarray(attributes))
        if attributes.ndim != 2 or attributes.shape[0] != self.num_vertices:
            raise ValueError(f"attributes must be ({self.num_vertices}, C), got shape {tuple(attributes.shape)}")
        if not 1 <= attributes.shape[1] <= MAX_CHANNELS:
            raise ValueError(f"attributes need 1 to {MAX_CHANNELS} channels, got {attributes.shape[1]}")
        if self.method == "gather":
            values = self._render_gather(attributes)
        else:
            with current(self.ctx):
                values = self._render_draw(attributes.detach().cpu().numpy())
        return UVRaster(values, self.mask if values.device == self.mask.device else self.mask.to(values.device))

    def render_raw(self, attributes) -> torch.Tensor:
        """Like :meth:`render` but without gutter filling: (H, W, C), 0 outside the coverage."""
        values = self.render(attributes).values
        return values.masked_fill(~self.mask.to(values.device).unsqueeze(-1), 0.0)

    def _release_objects(self) -> None:
        self._targets.release()
        for buffer in (self._uv_buffer, self._index_buffer):
            if buffer is not None:
                buffer.release()
