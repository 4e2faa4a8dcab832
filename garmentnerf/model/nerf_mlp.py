"""M_NeRF: sample features -> density sigma and appearance feature zeta (paper Sec. 4.3).

Input per sample: x^b = [b_o (3), h (1)], the detail feature f^d (8) and the dynamic feature
f^s (8): 20 values, no positional encoding (paper). Six Linear(256) + ReLU layers, then two
linear heads: density (1) and zeta (128).

Density activation
    The authors' code feeds the raw, unbounded density head to the renderer as alpha. Here the
    head is a density in 1/metre, ``sigma = softplus(raw + bias)`` (bias -1 as in Mip-NeRF), and
    the renderer turns it into alpha with the sample spacing
    (:func:`garmentnerf.model.volume_rendering.alpha_from_density`), so opacity does not depend
    on how many samples a ray takes. ``"trunc_exp"`` (instant-ngp / torch-ngp) is the
    alternative: exp with its gradient clamped, sharper surfaces, less stable early on.

zeta is left linear: it is an intermediate feature decoded by M_D, and a bounded activation
would only saturate.

Precision
    Under autocast (``precision`` of the render path, the trainer's ``--precision``) the hidden
    layers and the appearance head run in the lower precision and the rest in float32: the input
    layer, since b_o's coordinates in bfloat16 lie 2 to 4 mm apart at 0.5 to 1 m, and the density
    head, since sigma is an exponential of its output. Both are small layers (20 inputs; one
    output), so this costs almost nothing of the speed-up.

The field interface
    :class:`GarmentNeRF` is the model's :class:`~garmentnerf.model.field.Field`: :meth:`GarmentNeRF.evaluate`
    reads a sample's f^s and f^d at its body point and runs the MLP; ``forward`` is the MLP alone.
"""

from __future__ import annotations

from contextlib import AbstractContextManager

import torch
import torch.nn.functional as F
from torch import nn

from garmentnerf.geometry.triangles import interpolate
from garmentnerf.model.config import BODY_PRIOR_WIDTH, DETAIL_FEATURE_DIM, DYNAMIC_FEATURE_DIM
from garmentnerf.model.detail_features import DEFAULT_VISIBILITY_TOLERANCE, read_detail_features
from garmentnerf.model.field import Field, StageClock
from garmentnerf.model.uv_maps import sample_uv_map

#: trunc_exp clamps its input's gradient here (torch-ngp's value); exp(15) ~ 3.3e6 per metre.
TRUNC_EXP_MAX = 15.0


class _TruncExp(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x):
        ctx.save_for_backward(x)
        return torch.exp(x)

    @staticmethod
    def backward(ctx, grad):
        (x,) = ctx.saved_tensors
        return grad * torch.exp(x.clamp(max=TRUNC_EXP_MAX))


def trunc_exp(x: torch.Tensor) -> torch.Tensor:
    """exp(x) whose gradient uses exp(min(x, 15)), so one large raw value cannot blow up a step."""
    return _TruncExp.apply(x)


def density_activation(raw: torch.Tensor, kind: str = "softplus", bias: float = -1.0,
                       scale: float = 1.0) -> torch.Tensor:
    """Density sigma >= 0 (1/metre) from the raw head output: ``scale * act(raw + bias)``; same shape."""
    if kind == "softplus":
        return scale * F.softplus(raw + bias)
    if kind == "trunc_exp":
        return scale * trunc_exp(raw + bias)
    raise ValueError(f"unknown density activation {kind!r} (known: 'softplus', 'trunc_exp')")


def body_density_prior(distance: torch.Tensor, strength: float, width: float) -> torch.Tensor:
    """(N,) raw-density offset from the body distance h (N,): ``strength`` inside the body and on
    it, falling linearly to 0 at ``h = width`` and to ``-strength`` from ``h = 2 width`` on.

    Why: the model renders the body as well as the garment, so the untrained density is made
    the body's shape instead of a uniform box. Most training rays are background; from a uniform
    box the cheapest first descent is to empty the whole box, after which the density's
    activation is saturated and nothing comes back. The network's own output adds to the prior,
    so it can still put density anywhere (the garment up to a hem 0.3 m out) or remove it.
    """
    return strength * (1.0 - distance.clamp_min(0.0) / width).clamp(-1.0, 1.0)


def field_heads(field: nn.Module, hidden: torch.Tensor, distance: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """sigma (N,) and zeta (N, C) from a field's last hidden layer (N, W): the density head in
    float32 (see "Precision"), the body prior of h ``distance (N,)`` added, the activation; the
    appearance head as is. ``field`` holds ``density_head``, ``appearance_head`` and the density
    settings (:class:`GarmentNeRF`)."""
    with torch.autocast(hidden.device.type, enabled=False):
        raw = field.density_head(hidden.float()).squeeze(-1)
    if field.body_prior_strength:
        raw = raw + body_density_prior(distance, field.body_prior_strength, BODY_PRIOR_WIDTH)
    sigma = density_activation(raw, field.density_kind, field.density_bias, field.density_scale)
    return sigma, field.appearance_head(hidden)


class GarmentNeRF(Field):
    """M_NeRF, the paper's field: an MLP on ``[b_o, h, f^d, f^s]``.

    Args:
        detail_dim: width of f^d (0: the detail-feature ablation).
        dynamic_dim: width of f^s (0: the dynamic-feature ablation).
        appearance_dim: width of zeta (paper: 128).
        depth, width: hidden Linear + ReLU layers (paper: 6 x 256).
        density_activation: ``"softplus"`` or ``"trunc_exp"``.
        density_bias: added to the raw density before the activation.
        density_scale: multiplies the activated density.
        body_prior_strength: the raw density offset of :func:`body_density_prior` (0: none).
        shading_normals: :meth:`evaluate` appends the skin's world normal at each sample's body point
            to zeta (``NerfConfig.shading_normals``).
        skin_faces: (F, 3) the body's skin triangles, for those normals.
        visibility_tolerance: metres, see
            :func:`~garmentnerf.model.detail_features.reference_visibility`.
    """

    #: Parameters whose width follows ``width``: a wider MLP can start from a narrower one's weights.
    GROWABLE = ("trunk.", "density_head.", "appearance_head.")

    def __init__(self, detail_dim: int = DETAIL_FEATURE_DIM, dynamic_dim: int = DYNAMIC_FEATURE_DIM,
                 appearance_dim: int = 128, depth: int = 6, width: int = 256, density_activation: str = "softplus",
                 density_bias: float = -1.0, density_scale: float = 1.0, body_prior_strength: float = 0.0, *,
                 shading_normals: bool = False, skin_faces: torch.Tensor | None = None,
                 visibility_tolerance: float = DEFAULT_VISIBILITY_TOLERANCE):
        super().__init__()
        if density_activation not in ("softplus", "trunc_exp"):
            raise ValueError(f"unknown density activation {density_activation!r}")
        if shading_normals and skin_faces is None:
            raise ValueError("shading_normals needs the skin's faces")
        if not visibility_tolerance >= 0:
            raise ValueError(f"visibility_tolerance must be >= 0, got {visibility_tolerance}")
        self.detail_dim = detail_dim
        self.dynamic_dim = dynamic_dim
        self.appearance_dim = appearance_dim
        self.zeta_channels = appearance_dim + 3 * int(shading_normals)
        self.density_kind = density_activation
        self.density_bias = density_bias
        self.density_scale = float(density_scale)
        self.body_prior_strength = float(body_prior_strength)
        self.shading_normals = bool(shading_normals)
        self.skin_faces = None if skin_faces is None else skin_faces.detach().cpu()  # not a parameter
        self.visibility_tolerance = float(visibility_tolerance)
        self.input_dim = 4 + detail_dim + dynamic_dim
        layers: list[nn.Module] = []
        for i in range(depth):
            layers += [nn.Linear(self.input_dim if i == 0 else width, width), nn.ReLU(inplace=True)]
        self.trunk = nn.Sequential(*layers)
        self.density_head = nn.Linear(width, 1)
        self.appearance_head = nn.Linear(width, appearance_dim)

    @classmethod
    def from_config(cls, cfg, skin_faces: torch.Tensor | None = None,
                    visibility_tolerance: float = DEFAULT_VISIBILITY_TOLERANCE) -> "GarmentNeRF":
        """M_NeRF of a :class:`~garmentnerf.model.config.ModelConfig`."""
        nerf = cfg.nerf
        return cls(DETAIL_FEATURE_DIM if cfg.encoder.detail_feature else 0,
                   DYNAMIC_FEATURE_DIM if cfg.encoder.dynamic_feature else 0,
                   nerf.appearance_dim, nerf.mlp_depth, nerf.mlp_width, nerf.density_activation, nerf.density_bias,
                   nerf.density_scale, nerf.body_prior_strength, shading_normals=nerf.shading_normals,
                   skin_faces=skin_faces, visibility_tolerance=visibility_tolerance)

    def _check(self, name: str, value: torch.Tensor | None, dim: int, n: int) -> None:
        if dim == 0:
            if value is not None:
                raise ValueError(f"GarmentNeRF was built without the {name} feature but one was given")
            return
        if value is None:
            raise ValueError(f"GarmentNeRF needs the {name} feature ({dim} channels)")
        if value.shape != (n, dim):
            raise ValueError(f"{name} feature must be ({n}, {dim}), got {tuple(value.shape)}")

    def forward(self, canonical: torch.Tensor, distance: torch.Tensor, detail: torch.Tensor | None = None,
                dynamic: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """The MLP on N samples.

        Args:
            canonical: (N, 3) b_o, the projected point on the canonical body.
            distance: (N,) h, signed distance to the posed body (positive outside).
            detail: (N, detail_dim) f^d, or None when built with detail_dim = 0.
            dynamic: (N, dynamic_dim) f^s, or None when built with dynamic_dim = 0.
        Returns:
            sigma (N,) density >= 0 in 1/metre, zeta (N, appearance_dim).
        """
        n = canonical.shape[0]
        if canonical.shape != (n, 3) or distance.shape != (n,):
            raise ValueError(f"canonical must be (N, 3) and distance (N,), got {tuple(canonical.shape)} "
                             f"and {tuple(distance.shape)}")
        self._check("detail", detail, self.detail_dim, n)
        self._check("dynamic", dynamic, self.dynamic_dim, n)
        parts = [canonical, distance.unsqueeze(-1)]
        parts += [f for f in (detail, dynamic) if f is not None]
        # Under autocast only the hidden layers run in the lower precision: see "Precision" above.
        with torch.autocast(canonical.device.type, enabled=False):
            first = self.trunk[0](torch.cat(parts, dim=-1).float())
        return field_heads(self, self.trunk[1:](first), distance)

    def evaluate(self, frame, points, *, clock: StageClock, autocast: AbstractContextManager
                 ) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`Field.evaluate <garmentnerf.model.field.Field.evaluate>`: f^d read from the reference
        detail maps where b_t is seen (:func:`~garmentnerf.model.detail_features.read_detail_features`),
        f^s from F^s_t at the atlas UV, then the MLP; with ``shading_normals`` the skin's posed normal at b_t
        appended to zeta."""
        dev = self.density_head.weight.device
        with clock("features"):
            detail = dynamic = None
            if self.detail_dim:
                detail, _ = read_detail_features(frame.detail_features, frame.reference_cameras,
                                                 frame.reference_depth, points.closest, self.visibility_tolerance)
            if self.dynamic_dim:
                dynamic = sample_uv_map(frame.dynamic_features.permute(1, 2, 0), points.uv.to(dev))
        with clock("mlp"), autocast:
            sigma, zeta = self(points.canonical.to(dev), points.signed_distance.to(dev), detail, dynamic)
        sigma, zeta = sigma.float(), zeta.float()
        if self.shading_normals:
            with clock("features"):
                normal = F.normalize(interpolate(frame.vertex_normals, self.skin_faces, points.face, points.bary),
                                     dim=-1)
                zeta = torch.cat([zeta, normal.to(dev, zeta.dtype)], dim=-1)
        return sigma, zeta
