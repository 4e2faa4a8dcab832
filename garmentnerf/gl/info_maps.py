"""UV-space info maps of a body motion: the normal map N_t and velocity map V_t (paper, Sec. 4.1).

Per-vertex quantities come from torch (:mod:`garmentnerf.body.surface`). The rasteriser spreads
them over the UV atlas: GL rasterises the atlas once into a per-texel (face, barycentrics) table,
after which every frame is a torch gather (the paper's authors spend 130 ms per frame on the CPU
for this; see ``garmentnerf bench``).
"""

from __future__ import annotations

from dataclasses import dataclass

import moderngl
import numpy as np
import torch

from garmentnerf.body.model import BodyModel, PosedBody
from garmentnerf.body.surface import canonical_velocities, root_relative_normals, vertex_normals
from garmentnerf.gl.uv_raster import UVAttributeRasterizer


@dataclass
class InfoMaps:
    """Info maps of one frame (layout: :mod:`garmentnerf.gl.uv_raster`, row 0 is v = 0).

    Attributes:
        normal: (H, W, 3) root-relative unit normals.
        velocity: (H, W, 3 k) canonical-frame velocity history (units:
            :data:`~garmentnerf.body.surface.VELOCITY_SCALE`).
        mask: (H, W) bool, texels covered by the atlas.
    """

    normal: torch.Tensor
    velocity: torch.Tensor
    mask: torch.Tensor

    def stacked(self) -> torch.Tensor:
        """(3 + 3 k, H, W) channels-first input of the dynamic feature encoder."""
        return torch.cat([self.normal, self.velocity], dim=-1).permute(2, 0, 1).contiguous()


def uv_vertex_to_vertex(faces: np.ndarray, uv_faces: np.ndarray, num_uv: int) -> np.ndarray:
    """(Nuv,) the mesh vertex behind every UV vertex (seams split one vertex into several UV vertices).

    Raises ValueError if a UV vertex is used by two different mesh vertices.
    """
    mapping = np.full(num_uv, -1, dtype=np.int64)
    mapping[uv_faces.reshape(-1)] = faces.reshape(-1)
    check = np.full(num_uv, -1, dtype=np.int64)
    check[uv_faces.reshape(-1)[::-1]] = faces.reshape(-1)[::-1]
    if np.any(mapping != check):
        raise ValueError("UV atlas maps one UV vertex to several mesh vertices")
    mapping[mapping < 0] = 0  # unused UV vertices: any value, they are never rasterised
    return mapping


class InfoMapRenderer:
    """Renders N_t and V_t for every frame of a posed clip.

    Args:
        ctx: moderngl context (headless or a window's).
        body: the body model (must have a UV atlas).
        resolution: map size (paper: 128).
        history: k, velocity slots (paper: 2).
    """

    def __init__(self, ctx: moderngl.Context, body: BodyModel, resolution: int = 128, history: int = 2):
        if not body.has_uv:
            raise ValueError(f"body model '{body.name}' has no UV atlas; info maps need one "
                             "(for SMPL pass the UV .obj file distributed with it)")
        self.body = body
        self.history = history
        self.root = int(np.flatnonzero(body.asset.parents < 0)[0])
        self.uv_to_vertex = torch.as_tensor(uv_vertex_to_vertex(body.asset.faces, body.asset.uv_faces, body.asset.uv.shape[0]))
        self.rasterizer = UVAttributeRasterizer(ctx, body.asset.uv, body.asset.uv_faces, resolution)

    @property
    def mask(self) -> torch.Tensor:
        return self.rasterizer.mask

    def frames_back(self, fps: float) -> int:
        """Frames before frame t that frame t's maps depend on: k, the velocity history."""
        return self.history

    def vertex_attributes(self, posed: PosedBody, fps: float) -> torch.Tensor:
        """(T, V, 3 + 3 k) per-vertex [root-relative normal, canonical velocities]."""
        world = vertex_normals(posed.vertices, self.body.faces)
        parts = [root_relative_normals(world, posed.joint_transforms[:, self.root, :, :3])]
        if self.history > 0:
            linear = self.body.vertex_transforms(posed.joint_transforms)[..., :3]
            parts.append(canonical_velocities(posed.vertices, linear, fps, self.history))
        return torch.cat(parts, dim=-1)

    def render_attributes(self, attributes: torch.Tensor) -> InfoMaps:
        """Rasterise one frame's (V, C) vertex attributes (:meth:`vertex_attributes`)."""
        raster = self.rasterizer.render(attributes[self.uv_to_vertex].float())

        def unit(n):  # interpolation shortens them
            return n / n.norm(dim=-1, keepdim=True).clamp_min(1e-8)

        return InfoMaps(unit(raster.values[..., :3]), raster.values[..., 3:], raster.mask)

    def render_clip(self, posed: PosedBody, fps: float) -> list[InfoMaps]:
        """Maps for every frame of ``posed`` (frame 0 has no history: see canonical_velocities)."""
        attributes = self.vertex_attributes(posed, fps)
        return [self.render_attributes(a) for a in attributes]

    def release(self) -> None:
        self.rasterizer.release()
