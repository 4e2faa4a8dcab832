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

Atlas feature f^a (optional, ``atlas_dim > 0``)
    A learned texture's read at the sample's atlas UV (``ModelConfig.atlas_feature_channels``).
    It enters the first hidden layer through its own weights, ``atlas_input``, added to the first
    layer's pre-activation and initialised to zero: a network built with it computes exactly what
    the same network without it computes, so the branch can be added to a trained model and
    fine-tuned from that model's output (:func:`garmentnerf.train.run.load_weights` with
    ``may_be_missing``).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

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


def positional_encoding(x: torch.Tensor, num_freqs: int) -> torch.Tensor:
    """NeRF encoding ``[x, sin(2^l pi x), cos(2^l pi x)]_{l < L}``: (N, D) -> (N, D (1 + 2 L))."""
    if num_freqs == 0:
        return x
    freqs = (2.0 ** torch.arange(num_freqs, dtype=x.dtype, device=x.device)) * math.pi
    angles = (x.unsqueeze(-1) * freqs).flatten(-2)  # (N, D L)
    return torch.cat([x, torch.sin(angles), torch.cos(angles)], dim=-1)


def field_heads(field: nn.Module, hidden: torch.Tensor, distance: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """sigma (N,) and zeta (N, C) from a field's last hidden layer (N, W): the density head in
    float32 (see "Precision"), the body prior of h ``distance (N,)`` added, the activation; the
    appearance head as is. ``field`` holds ``density_head``, ``appearance_head`` and the density
    settings (:class:`GarmentNeRF`, :class:`~garmentnerf.model.uvh_field.UVHField`)."""
    with torch.autocast(hidden.device.type, enabled=False):
        raw = field.density_head(hidden.float()).squeeze(-1)
    if field.body_prior_strength:
        raw = raw + body_density_prior(distance, field.body_prior_strength, field.body_prior_width)
    sigma = density_activation(raw, field.density_kind, field.density_bias, field.density_scale)
    return sigma, field.appearance_head(hidden)


class GarmentNeRF(nn.Module):
    """The NeRF MLP.

    Args:
        detail_dim: width of f^d (0: the detail-feature ablation).
        dynamic_dim: width of f^s (0: the dynamic-feature ablation).
        appearance_dim: width of zeta (paper: 128).
        depth, width: hidden Linear + ReLU layers (paper: 6 x 256).
        density_activation: ``"softplus"`` or ``"trunc_exp"``.
        density_bias: added to the raw density before the activation.
        positional_encoding_freqs: frequencies applied to b_o (paper: 0).
        atlas_dim: width of f^a (0: none, the paper's inputs).
    """

    #: Parameters that start at zero so that adding them leaves the network's output unchanged.
    ZERO_START = ("atlas_input.",)
    #: Parameters whose width follows ``width``: a wider MLP can start from a narrower one's weights.
    GROWABLE = ("trunk.", "density_head.", "appearance_head.", "atlas_input.")

    def __init__(self, detail_dim: int = 8, dynamic_dim: int = 8, appearance_dim: int = 128, depth: int = 6,
                 width: int = 256, density_activation: str = "softplus", density_bias: float = -1.0,
                 positional_encoding_freqs: int = 0, density_scale: float = 1.0,
                 body_prior_strength: float = 0.0, body_prior_width: float = 0.15, atlas_dim: int = 0):
        super().__init__()
        if density_activation not in ("softplus", "trunc_exp"):
            raise ValueError(f"unknown density activation {density_activation!r}")
        self.detail_dim = detail_dim
        self.dynamic_dim = dynamic_dim
        self.appearance_dim = appearance_dim
        self.density_kind = density_activation
        self.density_bias = density_bias
        self.density_scale = float(density_scale)
        self.body_prior_strength = float(body_prior_strength)
        self.body_prior_width = float(body_prior_width)
        self.num_freqs = positional_encoding_freqs
        self.atlas_dim = atlas_dim
        self.input_dim = 3 * (1 + 2 * positional_encoding_freqs) + 1 + detail_dim + dynamic_dim
        layers: list[nn.Module] = []
        for i in range(depth):
            layers += [nn.Linear(self.input_dim if i == 0 else width, width), nn.ReLU(inplace=True)]
        self.trunk = nn.Sequential(*layers)
        self.atlas_input = None
        if atlas_dim:
            self.atlas_input = nn.Linear(atlas_dim, width, bias=False)
            nn.init.zeros_(self.atlas_input.weight)
        self.density_head = nn.Linear(width, 1)
        self.appearance_head = nn.Linear(width, appearance_dim)

    @classmethod
    def from_config(cls, cfg) -> "GarmentNeRF":
        return cls(cfg.detail_feature_dim if cfg.use_detail_feature else 0,
                   cfg.dynamic_feature_dim if cfg.use_dynamic_feature else 0,
                   cfg.appearance_dim, cfg.mlp_depth, cfg.mlp_width, cfg.density_activation, cfg.density_bias,
                   cfg.positional_encoding_freqs, cfg.density_scale, cfg.body_prior_strength,
                   cfg.body_prior_width, cfg.atlas_feature_channels)

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
                dynamic: torch.Tensor | None = None, atlas: torch.Tensor | None = None
                ) -> tuple[torch.Tensor, torch.Tensor]:
        """Evaluate N samples.

        Args:
            canonical: (N, 3) b_o, the projected point on the canonical body.
            distance: (N,) h, signed distance to the posed body (positive outside).
            detail: (N, detail_dim) f^d, or None when built with detail_dim = 0.
            dynamic: (N, dynamic_dim) f^s, or None when built with dynamic_dim = 0.
            atlas: (N, atlas_dim) f^a, or None when built with atlas_dim = 0.
        Returns:
            sigma (N,) density >= 0 in 1/metre, zeta (N, appearance_dim).
        """
        n = canonical.shape[0]
        if canonical.shape != (n, 3) or distance.shape != (n,):
            raise ValueError(f"canonical must be (N, 3) and distance (N,), got {tuple(canonical.shape)} "
                             f"and {tuple(distance.shape)}")
        self._check("detail", detail, self.detail_dim, n)
        self._check("dynamic", dynamic, self.dynamic_dim, n)
        self._check("atlas", atlas, self.atlas_dim, n)
        parts = [positional_encoding(canonical, self.num_freqs), distance.unsqueeze(-1)]
        parts += [f for f in (detail, dynamic) if f is not None]
        # Under autocast only the hidden layers run in the lower precision: see "Precision" above.
        with torch.autocast(canonical.device.type, enabled=False):
            first = self.trunk[0](torch.cat(parts, dim=-1).float())
            if atlas is not None:
                first = first + self.atlas_input(atlas.float())
        return field_heads(self, self.trunk[1:](first), distance)
