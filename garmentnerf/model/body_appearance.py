"""The rasterised body's learned appearance: an albedo texture on the body's UV atlas times a
smooth shading of the world-space normal (the hybrid composition, :func:`~garmentnerf.model.palette.compose`).

Why
    The camera pass already rasterises the posed body exactly. Drawing the body with a learned
    appearance, instead of asking the NeRF and the decoder to reproduce it, gives the body's
    silhouette and every finger and toe for free and leaves the network the garment and its
    visibility (the decoder's mask times its garment blend weight).

The model (per pixel of the body, before the palette)
    ``a(uv, n) = A(uv) * max(S(n), 0)``

    ``A``: a ``(3, T, T)`` albedo multiplier on the body atlas, bilinear, starting at 1, so the
    body's palette colour p_body tints it (recolouring the body multiplies the whole texture);
    ``S``: an RGB irradiance that is a polynomial of degree :data:`SHADING_DEGREE` in the unit
    normal's coordinates (:func:`~garmentnerf.body.shading.normal_monomials`). On the sphere the monomials of degree <= d
    span exactly the real spherical harmonics of degree <= d, so ``S`` is SH lighting of that
    order written without any SH constants: degree 2 is the classic 9-coefficient irradiance
    (Ramamoorthi and Hanrahan); degree 4 also follows the terminator of a directional light.
    No view-dependent term: the ground truth's small specular lobe is left out.

    The image of the body is ``p_body * a`` (clamped), premultiplied by its coverage.

Atlas convention
    ``uv`` in [0, 1] (the body asset's atlas); texel row 0 is v = 0 (``grid_sample`` with
    ``y = 2 v - 1``). Only this module reads the texture, so the orientation is internal.
"""

from __future__ import annotations

from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from garmentnerf.body.shading import monomial_exponents, normal_monomials
from garmentnerf.io_utils import load_tagged_tensors, save_tagged_tensors

#: Degree of the shading polynomial (see the module docstring).
SHADING_DEGREE = 4
#: Side of the albedo texture, texels.
TEXTURE_SIZE = 256
#: The file a run folder keeps its body appearance in.
BODY_APPEARANCE_FILE = "body_appearance.safetensors"
#: The ``format`` tag in the file's metadata.
BODY_APPEARANCE_FORMAT = "garmentnerf-body-appearance"


class BodyAppearance(nn.Module):
    """``a(uv, n) = A(uv) * max(S(n), 0)`` (see the module docstring).

    Args:
        texture_size: T, the albedo texture's side in texels.
        degree: the shading polynomial's degree.
    """

    def __init__(self, texture_size: int = TEXTURE_SIZE, degree: int = SHADING_DEGREE):
        super().__init__()
        if texture_size < 1:
            raise ValueError(f"texture_size must be >= 1, got {texture_size}")
        self.degree = int(degree)
        self.albedo = nn.Parameter(torch.ones(3, int(texture_size), int(texture_size)))
        coefficients = torch.zeros(len(monomial_exponents(self.degree)), 3)
        coefficients[0] = 1.0  # S = 1 everywhere: the palette colour, unshaded
        self.shading = nn.Parameter(coefficients)

    def irradiance(self, normals: torch.Tensor) -> torch.Tensor:
        """(N, 3) unit world normals -> (N, 3) ``max(S(n), 0)``."""
        return (normal_monomials(normals, self.degree) @ self.shading).clamp_min(0.0)

    def albedo_at(self, uv: torch.Tensor) -> torch.Tensor:
        """(N, 2) atlas UV -> (N, 3) ``A(uv)`` (bilinear, clamped at the atlas border)."""
        grid = (uv * 2.0 - 1.0).view(1, 1, -1, 2).to(self.albedo.dtype)
        texels = F.grid_sample(self.albedo[None], grid, mode="bilinear", padding_mode="border", align_corners=False)
        return texels[0, :, 0].T

    def forward(self, uv: torch.Tensor, normals: torch.Tensor) -> torch.Tensor:
        """(N, 2) UV and (N, 3) unit normals -> (N, 3) ``a`` (multiply by the body's palette colour)."""
        return self.albedo_at(uv) * self.irradiance(normals)


def save_body_appearance(path, appearance: BodyAppearance) -> Path:
    """Write ``appearance`` to a ``.safetensors`` file atomically. Returns the path."""
    return save_tagged_tensors(path, {"albedo": appearance.albedo, "shading": appearance.shading},
                               BODY_APPEARANCE_FORMAT, {"degree": str(appearance.degree)})


def load_body_appearance(path) -> BodyAppearance:
    """Read a file written by :func:`save_body_appearance`.

    Raises:
        ValueError: a file that is not one (the message names it).
    """
    path = Path(path)
    tensors, meta = load_tagged_tensors(path, BODY_APPEARANCE_FORMAT, "body appearance")
    if set(tensors) != {"albedo", "shading"}:
        raise ValueError(f"{path}: not a body appearance file")
    albedo, shading = tensors["albedo"].float(), tensors["shading"].float()
    degree = int(meta.get("degree", SHADING_DEGREE))
    if albedo.ndim != 3 or albedo.shape[0] != 3 or albedo.shape[1] != albedo.shape[2] or \
            shading.shape != (len(monomial_exponents(degree)), 3):
        raise ValueError(f"{path}: body appearance tensors have the wrong shapes "
                         f"(albedo {tuple(albedo.shape)}, shading {tuple(shading.shape)}, degree {degree})")
    appearance = BodyAppearance(albedo.shape[-1], degree)
    with torch.no_grad():
        appearance.albedo.copy_(albedo)
        appearance.shading.copy_(shading)
    return appearance.eval()


__all__ = ["BodyAppearance", "save_body_appearance",
           "load_body_appearance", "SHADING_DEGREE", "TEXTURE_SIZE", "BODY_APPEARANCE_FILE"]
