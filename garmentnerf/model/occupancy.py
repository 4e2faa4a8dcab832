"""Geometry supervision from the simulated garment: the occupancy term (not in the paper).

Why (``docs/quality.md``, "Telling the field where the cloth is"): the images tell the field where the
cloth is only through volume rendering, one view of one frame per step, so a frame's shape is learned
from about ten views over a whole training run. A scene made by ``garmentnerf data make`` also holds
the simulated garment of every training frame. This term asks the field's density, at points spread
over the frame's sampling box and around its cloth, to say *occupied* inside a sheet around the
garment's surface (and inside the body) and *empty* elsewhere: a direct, view-independent signal for
the whole frame's shape at every step, for the cost of projecting and evaluating a few thousand
points (no rendering).

The density becomes an occupancy as the renderer's quadrature would: ``alpha = 1 - exp(-sigma *
step)`` for an interval of length ``step`` (metres), and the term is the binary cross-entropy of that
alpha against the label. A sheet about as thick as the sampler's interval keeps the two consistent:
a sheet much thinner than an interval would be missed by most of a ray's jittered samples.

Shapes: N points; Vg, Fg the garment mesh's vertices and faces.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from garmentnerf.geometry.projection import SurfaceProjector


@dataclass(frozen=True)
class OccupancyPoints:
    """Points of one frame and what the garment says about them (CPU, float32)."""

    positions: torch.Tensor
    """(N, 3) world positions."""
    garment_distance: torch.Tensor
    """(N,) unsigned distance to the garment's surface (metres), exact."""


def occupancy_points(garment_vertices: torch.Tensor, garment: SurfaceProjector, box: torch.Tensor, n_near: int,
                     n_box: int, near_spread: float, generator: torch.Generator | None = None) -> OccupancyPoints:
    """Points to supervise one frame's density with, and their distance to its garment.

    Args:
        garment_vertices: (Vg, 3) the frame's simulated garment.
        garment: the garment topology's projector (its ``faces`` index ``garment_vertices``).
        box: (2, 3) min and max corners of the frame's sampling box.
        n_near: points around the cloth: garment vertices moved by isotropic Gaussian noise of standard
            deviation ``near_spread`` (metres), so both sides of the sheet and its edge are covered.
        n_box: points uniform in ``box`` (the empty space, and the body).
        generator: random source.
    """
    verts = garment_vertices.detach().to("cpu", torch.float32)
    box = box.detach().to("cpu", torch.float32)
    pick = torch.randint(0, verts.shape[0], (int(n_near),), generator=generator)
    near = verts[pick] + near_spread * torch.randn(int(n_near), 3, generator=generator)
    uniform = box[0] + (box[1] - box[0]) * torch.rand(int(n_box), 3, generator=generator)
    positions = torch.cat([near, uniform]).contiguous()
    distance = garment.bind(verts).project(positions).signed_distance.abs().float()
    return OccupancyPoints(positions, distance)


def occupancy_labels(garment_distance: torch.Tensor, body_height: torch.Tensor, half_thickness: float) -> torch.Tensor:
    """(N,) 1.0 where a point is occupied: within ``half_thickness`` of the garment's surface, or inside
    the body (``body_height`` (N,), the signed distance to the skin, < 0); else 0.0."""
    return ((garment_distance <= half_thickness) | (body_height < 0)).float()


#: Optical depth added inside the occupied label's log: keeps its gradient finite (about 1 / OCCUPANCY_TAU_FLOOR
#: per unit optical depth) at zero density, where ``log(1 - exp(-tau))`` has none.
OCCUPANCY_TAU_FLOOR = 1e-4


def occupancy_loss(sigma: torch.Tensor, occupied: torch.Tensor, step: float) -> torch.Tensor:
    """Binary cross-entropy of ``alpha = 1 - exp(-sigma * step)`` against ``occupied`` (both (N,)),
    averaged over the points; computed from the optical depth ``sigma * step`` directly (no log of 0:
    the occupied label reads ``alpha`` at an optical depth :data:`OCCUPANCY_TAU_FLOOR` higher)."""
    tau = (sigma.to(torch.promote_types(sigma.dtype, torch.float32)) * float(step)).clamp_min(0.0)  # float32 at least
    # log(alpha) = log(1 - exp(-tau)); log(1 - alpha) = -tau.
    log_alpha = torch.log(-torch.expm1(-(tau + OCCUPANCY_TAU_FLOOR)))
    target = occupied.to(tau.dtype)
    return -(target * log_alpha - (1.0 - target) * tau).mean()


def occupancy_iou(sigma: torch.Tensor, occupied: torch.Tensor, step: float) -> float:
    """IoU of ``alpha > 0.5`` with the labels (the occupancy probe's figure)."""
    pred = (1.0 - torch.exp(-sigma.detach().float() * float(step))) > 0.5
    truth = occupied > 0.5
    union = int((pred | truth).sum())
    return float((pred & truth).sum()) / union if union else 1.0


__all__ = ["OCCUPANCY_TAU_FLOOR", "OccupancyPoints", "occupancy_points", "occupancy_labels", "occupancy_loss",
           "occupancy_iou"]
