"""The UV-h field: a second M_NeRF whose capacity sits in feature volumes read by interpolation.

Why (``docs/quality.md``, "A field that learns in CPU hours"): the paper's M_NeRF sees raw
``[b_o, h]`` and two features constant along h, so a thin garment sheet has to come out of a
smooth MLP of a raw scalar, and every sample pays a 4 x 128 MLP. Eighteen CPU recipes of it
plateau at a garment PSNR of about 20 dB. Here the capacity is in grids, which learn in few
steps (instant-ngp, tri-planes), and the per-sample work is an interpolation and a small MLP.

Per sample, with (u, v) the atlas UV of the closest skin point b_t and h the signed distance:

1. **f^s, the motion's UV-h volume.** E emits ``dynamic_dim x slices`` channels instead of
   ``dynamic_dim``: a per-frame feature volume over (u, v, h), ``slices`` deep along h across
   ``height_range`` (the garment's band). It is read trilinearly, so f^s now varies along h: the
   encoder says *where above the skin* the cloth of this frame is (SurMo's and TriHuman's
   surface-space features, lifted along h).
2. **f^p, a learned UV-h tri-plane**, shared by every frame: planes over (u, v), (u, h) and
   (v, h) (``plane_channels`` each, ``plane_resolution`` wide, ``plane_height`` along h), read
   bilinearly and concatenated: a fast-learning encoding of the sample's place on the body
   (grids train at about 10x an MLP's rate, hence ``ModelConfig.uvh_plane_lr_scale``).
3. **The local offset direction**: the unit offset ``x - b_t`` expressed in the tangent frame of
   b_t's face (T along the atlas u direction, B = N x T, N the face normal). Points that share
   (b_t, h) (a hem swung out past a knee, cloth between the legs: the closest point is then a
   corner or an edge of the skin) are told apart by it, and it means the same in every pose
   because the frame turns with the skin. Off the edge and corner cones it is (0, 0, +-1).
4. A frequency encoding of the normalised h (``height_freqs``), and f^d as in the paper.
5. Optionally (``canonical_freqs`` > 0) **the sample's canonical position**, frequency encoded:
   b_o plus the offset ``x - b_t`` turned from the posed face's tangent frame into the canonical
   face's (:func:`canonical_positions`), so that the point lands where it would sit around the
   canonical body. It carries what (b_o, h, direction) carry, as one 3-D point an MLP fits like
   posed xyz (one-frame occupancy probe) while it still follows the body.

A small MLP (``depth x width``, e.g. 2 x 64) maps ``[f^s, f^p, f^d, direction, PE(h), PE(x_c)]``
to the density (the paper field's activation, bias, scale and body prior) and zeta.

Shapes: N samples; R the info-map side; K ``slices``; C_s ``dynamic_dim``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from garmentnerf.gl.uv_raster import sample_uv_map
from garmentnerf.model.nerf_mlp import field_heads, positional_encoding

#: Standard deviation of the tri-plane's initial values (small: the MLP starts near its bias).
PLANE_INIT_STD = 0.1
#: Metres per unit of E's sheet-height channels (``sheet_layers``): its outputs start near 0 and a
#: unit is the order of a garment's height above the skin.
SHEET_UNIT = 0.1


def normalised_height(h: torch.Tensor, height_range: tuple[float, float]) -> torch.Tensor:
    """(N,) h mapped from ``height_range`` (metres) to [-1, 1] (grid coordinates), unclamped:
    reads outside the band take the border value."""
    lo, hi = height_range
    return (h - lo) * (2.0 / (hi - lo)) - 1.0


def face_tangent_frames(vertices: torch.Tensor, faces: torch.Tensor, uv: torch.Tensor,
                        uv_faces: torch.Tensor) -> torch.Tensor:
    """(F, 3, 3) rows T, B, N of each face: N the unit face normal (counter-clockwise winding),
    T the atlas u direction projected on the face plane, B = N x T.

    Args:
        vertices: (V, 3) posed vertices; faces: (F, 3) their indices.
        uv: (U, 2) atlas coordinates; uv_faces: (F, 3) their indices.
    """
    p = vertices[faces]
    t = uv.to(vertices.dtype)[uv_faces]
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    d1, d2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    normal = F.normalize(torch.linalg.cross(e1, e2, dim=-1), dim=-1)
    # dP/du up to a positive factor 1/det: (e1 dv2 - e2 dv1) / (du1 dv2 - dv1 du2).
    det = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]
    tangent = (e1 * d2[:, 1:2] - e2 * d1[:, 1:2]) * torch.where(det < 0, -1.0, 1.0).to(p.dtype)[:, None]
    tangent = tangent - (tangent * normal).sum(-1, keepdim=True) * normal
    # A face degenerate in the atlas (no u direction): any unit vector in the face plane.
    tangent = torch.where(tangent.norm(dim=-1, keepdim=True) > 1e-12, tangent, e1)
    tangent = F.normalize(tangent, dim=-1)
    return torch.stack([tangent, torch.linalg.cross(normal, tangent, dim=-1), normal], dim=1)


def local_offset_direction(positions: torch.Tensor, closest: torch.Tensor, frames: torch.Tensor) -> torch.Tensor:
    """(N, 3) the unit offset ``positions - closest`` in the frames (N, 3, 3) (rows T, B, N);
    zero where the two points coincide."""
    offset = F.normalize(positions - closest, dim=-1)
    return torch.einsum("nij,nj->ni", frames, offset)


def canonical_positions(canonical_closest: torch.Tensor, offset_length: torch.Tensor, direction: torch.Tensor,
                        canonical_frames: torch.Tensor) -> torch.Tensor:
    """(N, 3) samples carried to the canonical body through their closest faces.

    Args:
        canonical_closest: (N, 3) b_o, the closest point's barycentric twin on the canonical body.
        offset_length: (N,) ``|x - b_t|`` (metres).
        direction: (N, 3) the unit offset in the posed face's tangent frame
            (:func:`local_offset_direction`).
        canonical_frames: (N, 3, 3) the same faces' tangent frames on the canonical body
            (:func:`face_tangent_frames`; rows T, B, N).
    Returns:
        ``b_o + |x - b_t| F_c^T direction``: for a body moved rigidly, the sample moved back.
    """
    return canonical_closest + offset_length[:, None] * torch.einsum("nji,nj->ni", canonical_frames, direction)


def read_uvh_volume(volume: torch.Tensor, uv: torch.Tensor, height: torch.Tensor) -> torch.Tensor:
    """Trilinear reads of a UV-h feature volume.

    Args:
        volume: (C, K, R, R) features over (h, v, u): K slices along the normalised height.
        uv: (N, 2) atlas coordinates in [0, 1] (u right, v up, as the UV maps).
        height: (N,) normalised height in [-1, 1] (clamped to the border outside).
    Returns:
        (N, C).
    """
    grid = torch.cat([uv * 2.0 - 1.0, height[:, None]], dim=-1).to(volume.dtype)
    out = F.grid_sample(volume[None], grid.view(1, 1, 1, -1, 3), mode="bilinear", padding_mode="border",
                        align_corners=False)
    return out[0, :, 0, 0].T


def read_triplane(planes: nn.ParameterList, uv: torch.Tensor, height: torch.Tensor) -> torch.Tensor:
    """(N, 3 C) the (u, v), (u, h) and (v, h) planes ((1, C, R, R), (1, C, K, R), (1, C, K, R))
    read bilinearly at atlas ``uv (N, 2)`` and normalised ``height (N,)``, concatenated."""
    u, v = uv[:, 0] * 2.0 - 1.0, uv[:, 1] * 2.0 - 1.0
    reads = []
    for plane, (x, y) in zip(planes, ((u, v), (u, height), (v, height))):
        grid = torch.stack([x, y], dim=-1).to(plane.dtype).view(1, 1, -1, 2)
        reads.append(F.grid_sample(plane, grid, mode="bilinear", padding_mode="border", align_corners=False)[0, :, 0])
    return torch.cat(reads, dim=0).T


class UVHField(nn.Module):
    """The UV-h field (see the module docstring).

    Args:
        dynamic_dim: C_s, channels of each slice of E's UV-h volume (0: the dynamic ablation).
        slices: K, slices of that volume along h.
        detail_dim: width of f^d (0: the detail ablation).
        appearance_dim: width of zeta.
        plane_channels, plane_resolution, plane_height: the learned tri-plane's size.
        height_range: (h_min, h_max) metres spanned by the volume's slices and the planes' h axis.
        height_freqs: frequencies of the encoding of the normalised h.
        canonical_freqs: octaves of the encoding of the canonical position (0: not an input).
        depth, width: hidden Linear + ReLU layers of the head.
        density_activation, density_bias, density_scale, body_prior_strength, body_prior_width:
            as :class:`~garmentnerf.model.nerf_mlp.GarmentNeRF`.
    """

    def __init__(self, dynamic_dim: int = 8, slices: int = 8, detail_dim: int = 8, appearance_dim: int = 64,
                 plane_channels: int = 16, plane_resolution: int = 256, plane_height: int = 64,
                 height_range: tuple[float, float] = (-0.1, 0.4), height_freqs: int = 4, canonical_freqs: int = 0,
                 depth: int = 2, width: int = 64, density_activation: str = "softplus", density_bias: float = -1.0,
                 density_scale: float = 1.0, body_prior_strength: float = 0.0, body_prior_width: float = 0.15,
                 sheet_layers: int = 0, sheet_freqs: int = 6):
        super().__init__()
        if not height_range[1] > height_range[0]:
            raise ValueError(f"height_range must be (low, high) with high > low, got {height_range}")
        self.dynamic_dim, self.slices, self.detail_dim = dynamic_dim, slices, detail_dim
        self.appearance_dim = appearance_dim
        self.height_range = (float(height_range[0]), float(height_range[1]))
        self.height_freqs = height_freqs
        self.canonical_freqs = canonical_freqs
        self.sheet_layers, self.sheet_freqs = int(sheet_layers), int(sheet_freqs)
        if self.sheet_layers and not dynamic_dim:
            raise ValueError("sheet_layers needs the dynamic volume (E emits the sheet heights)")
        self.density_kind, self.density_bias, self.density_scale = density_activation, density_bias, density_scale
        self.body_prior_strength, self.body_prior_width = float(body_prior_strength), float(body_prior_width)
        self.planes = nn.ParameterList([
            nn.Parameter(torch.randn(1, plane_channels, rows, plane_resolution) * PLANE_INIT_STD)
            for rows in (plane_resolution, plane_height, plane_height)])
        self.input_dim = (dynamic_dim + 3 * plane_channels + detail_dim + 3 + (1 + 2 * height_freqs)
                          + (3 * (1 + 2 * canonical_freqs) if canonical_freqs else 0)
                          + self.sheet_layers * (1 + 2 * self.sheet_freqs))
        layers: list[nn.Module] = []
        for i in range(depth):
            layers += [nn.Linear(self.input_dim if i == 0 else width, width), nn.ReLU(inplace=True)]
        self.trunk = nn.Sequential(*layers)
        self.density_head = nn.Linear(width, 1)
        self.appearance_head = nn.Linear(width, appearance_dim)

    @classmethod
    def from_config(cls, cfg) -> "UVHField":
        return cls(cfg.dynamic_feature_dim if cfg.use_dynamic_feature else 0, cfg.uvh_slices,
                   cfg.detail_feature_dim if cfg.use_detail_feature else 0, cfg.appearance_dim,
                   cfg.uvh_plane_channels, cfg.uvh_plane_resolution, cfg.uvh_plane_height, cfg.uvh_height_range,
                   cfg.uvh_height_freqs, cfg.uvh_canonical_freqs, cfg.mlp_depth, cfg.mlp_width, cfg.density_activation,
                   cfg.density_bias, cfg.density_scale, cfg.body_prior_strength, cfg.body_prior_width,
                   cfg.uvh_sheet_layers, cfg.uvh_sheet_freqs)

    def forward(self, volume: torch.Tensor | None, uv: torch.Tensor, distance: torch.Tensor,
                direction: torch.Tensor, detail: torch.Tensor | None = None,
                canonical: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Evaluate N samples.

        Args:
            volume: (C_s K, R, R) E's output for the frame (None with the dynamic ablation).
            uv: (N, 2) atlas UV of b_t; distance: (N,) h (metres, positive outside).
            direction: (N, 3) :func:`local_offset_direction`.
            detail: (N, C_d) f^d, or None with the detail ablation.
            canonical: (N, 3) the canonical positions (:func:`canonical_positions`) mapped to about
                [-1, 1], exactly when built with ``canonical_freqs`` > 0.
        Returns:
            sigma (N,) density >= 0 in 1/metre, zeta (N, appearance_dim).
        """
        n = uv.shape[0]
        if uv.shape != (n, 2) or distance.shape != (n,) or direction.shape != (n, 3):
            raise ValueError(f"uv must be (N, 2), distance (N,) and direction (N, 3), got {tuple(uv.shape)}, "
                             f"{tuple(distance.shape)} and {tuple(direction.shape)}")
        if (volume is None) != (self.dynamic_dim == 0) or (detail is None) != (self.detail_dim == 0):
            raise ValueError("UVHField: give the dynamic volume and f^d exactly when built with them")
        if (canonical is None) != (self.canonical_freqs == 0):
            raise ValueError("UVHField: give the canonical positions exactly when built with canonical_freqs")
        height = normalised_height(distance, self.height_range)
        with torch.autocast(uv.device.type, enabled=False):
            parts = []
            if volume is not None:
                R = volume.shape[-1]
                body = self.dynamic_dim * self.slices
                parts.append(read_uvh_volume(volume[:body].float().reshape(self.dynamic_dim, self.slices, R, R),
                                             uv.float(), height.float()))
                if self.sheet_layers:  # h - g(u, v) per layer, normalised like h (a span of 2 over the band)
                    maps = volume[body:body + self.sheet_layers].float().permute(1, 2, 0)  # (R, R, layers)
                    sheet = sample_uv_map(maps, uv.float()) * SHEET_UNIT
                    offset = (distance.float()[:, None] - sheet) * (2.0 / (self.height_range[1] - self.height_range[0]))
                    parts.append(positional_encoding(offset, self.sheet_freqs))
            parts.append(read_triplane(self.planes, uv.float(), height.float()))
            if detail is not None:
                parts.append(detail.float())
            parts += [direction.float(), positional_encoding(height.float()[:, None], self.height_freqs)]
            if canonical is not None:
                parts.append(positional_encoding(canonical.float(), self.canonical_freqs))
            first = self.trunk[0](torch.cat(parts, dim=-1))
        return field_heads(self, self.trunk[1:](first), distance)


__all__ = ["UVHField", "face_tangent_frames", "local_offset_direction", "canonical_positions", "read_uvh_volume",
           "read_triplane", "normalised_height", "SHEET_UNIT"]
