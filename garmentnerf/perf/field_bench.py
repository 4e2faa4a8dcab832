"""Per-sample cost of each field (``ModelConfig.field``), side by side in one run.

What a sample costs once the body projection is done: the paper's field reads f^s at the UV and
runs M_NeRF on ``[b_o, h, f^d, f^s]``; the ``uvh`` field computes the offset direction in the
skin face's frame, reads the frame's UV-h volume and the tri-plane, and runs its small MLP. Both
read f^d the same way, so it is left out of both. Timed on random samples over the bundled body
with a random frame's feature maps, without autograd (rendering) and with the backward pass
(training), alternating the fields round by round so a busy machine slows both alike.
"""

from __future__ import annotations

import time

import torch

from garmentnerf.body.model import BodyModel
from garmentnerf.geometry.body_points import BodyPointProjector
from garmentnerf.gl.uv_raster import sample_uv_map
from garmentnerf.model.config import ModelConfig
from garmentnerf.model.nerf_mlp import GarmentNeRF
from garmentnerf.model.uvh_field import UVHField, face_tangent_frames, local_offset_direction


def bundled_field_configs() -> dict[str, ModelConfig]:
    """The two fields at the bundled demo's sizes: the paper's (4 x 128, ``cpu_small``) and the
    ``uvh`` field with a 2 x 64 head."""
    paper = ModelConfig.cpu_small()
    return {"paper": paper, "uvh": paper.replace(field="uvh", mlp_depth=2, mlp_width=64)}


def field_benchmark(samples: int = 16384, rounds: int = 5, configs: dict[str, ModelConfig] | None = None,
                    seed: int = 0) -> dict:
    """Microseconds per sample and samples per second of each field (median over ``rounds``).

    Args:
        samples: samples per call (the render's and trainer's chunk size).
        rounds: timed rounds per field and mode (the fields take turns).
        configs: field name -> config (default :func:`bundled_field_configs`).
    Returns:
        ``{name: {"render_us_per_sample", "render_samples_per_s", "train_us_per_sample",
        "train_samples_per_s", "parameters"}}`` plus ``"samples"``.
    """
    configs = bundled_field_configs() if configs is None else configs
    g = torch.Generator().manual_seed(seed)
    body = BodyModel.default()
    projector = BodyPointProjector(body)
    n = int(samples)
    face = torch.randint(len(projector.faces), (n,), generator=g)
    bary = torch.distributions.Dirichlet(torch.ones(3)).sample((n,))
    corners = body.template_vertices[projector.faces[face]]
    closest = (bary[:, :, None] * corners).sum(1)
    positions = closest + 0.1 * torch.randn(n, 3, generator=g)
    distance = (positions - closest).norm(dim=-1)
    uv = (bary[:, :, None] * body.uv[projector.uv_faces[face]]).sum(1)

    def evaluate(cfg: ModelConfig, field, maps: torch.Tensor):
        if cfg.field == "uvh":
            frames = face_tangent_frames(body.template_vertices, projector.faces[face], projector.uv,
                                         projector.uv_faces[face])
            direction = local_offset_direction(positions, closest, frames)
            return field(maps, uv, distance, direction, torch.zeros(n, cfg.detail_feature_dim))
        dynamic = sample_uv_map(maps.permute(1, 2, 0), uv)
        return field(closest, distance, torch.zeros(n, cfg.detail_feature_dim), dynamic)

    fields, maps, times = {}, {}, {}
    for name, cfg in configs.items():
        torch.manual_seed(seed)
        fields[name] = UVHField.from_config(cfg) if cfg.field == "uvh" else GarmentNeRF.from_config(cfg)
        R = cfg.info_map_resolution
        maps[name] = torch.randn(cfg.dynamic_encoder_channels, R, R, generator=g).tanh().requires_grad_(True)
        times[name] = {"render": [], "train": []}
    for _ in range(rounds + 1):  # the first round warms up
        for name, cfg in configs.items():
            with torch.no_grad():
                t0 = time.perf_counter()
                evaluate(cfg, fields[name], maps[name])
                times[name]["render"].append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            sigma, zeta = evaluate(cfg, fields[name], maps[name])
            (sigma.sum() + zeta.sum()).backward()
            times[name]["train"].append(time.perf_counter() - t0)
    out: dict = {"samples": n}
    for name in configs:
        row = {}
        for mode in ("render", "train"):
            t = sorted(times[name][mode][1:])[len(times[name][mode][1:]) // 2]
            row[f"{mode}_us_per_sample"] = t / n * 1e6
            row[f"{mode}_samples_per_s"] = n / t
        row["parameters"] = sum(p.numel() for p in fields[name].parameters())
        out[name] = row
    return out


__all__ = ["field_benchmark", "bundled_field_configs"]
