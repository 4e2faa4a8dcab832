"""The occupancy term (geometry supervision from the simulated garment): its points' distances against
trimesh, its labels, and its loss against torch's binary cross-entropy."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F
import trimesh

from garmentnerf.geometry.projection import SurfaceProjector
from garmentnerf.model.occupancy import occupancy_iou, occupancy_labels, occupancy_loss, occupancy_points


def _cloth() -> trimesh.Trimesh:
    """An open, wavy sheet (a stand-in for a skirt panel): 21 x 21 vertices over 0.6 x 0.6 m."""
    u, v = np.meshgrid(np.linspace(-0.3, 0.3, 21), np.linspace(-0.3, 0.3, 21), indexing="ij")
    z = 0.05 * np.sin(8.0 * u) * np.cos(5.0 * v)
    verts = np.stack([u, v, z], -1).reshape(-1, 3)
    faces = []
    for i in range(20):
        for j in range(20):
            a, b, c, d = i * 21 + j, i * 21 + j + 1, (i + 1) * 21 + j, (i + 1) * 21 + j + 1
            faces += [[a, c, b], [b, c, d]]
    return trimesh.Trimesh(verts, np.array(faces), process=False)


def test_points_distances_are_exact_against_trimesh():
    cloth = _cloth()
    verts = torch.tensor(cloth.vertices, dtype=torch.float32)
    projector = SurfaceProjector(torch.tensor(cloth.faces), verts.shape[0])
    box = torch.tensor([[-0.4, -0.4, -0.2], [0.4, 0.4, 0.2]])
    gen = torch.Generator().manual_seed(0)
    pts = occupancy_points(verts, projector, box, n_near=600, n_box=400, near_spread=0.03, generator=gen)
    assert pts.positions.shape == (1000, 3) and pts.garment_distance.shape == (1000,)
    uniform = pts.positions[600:]
    assert bool(((uniform >= box[0]) & (uniform <= box[1])).all())
    # the points around the cloth are within a few spreads of its vertices
    near_gap = torch.cdist(pts.positions[:600], verts).min(dim=1).values
    assert float(near_gap.max()) < 0.03 * 6
    _, reference, _ = trimesh.proximity.closest_point(cloth, pts.positions.double().numpy())
    np.testing.assert_allclose(pts.garment_distance.numpy(), reference, atol=1e-5)
    # the near half straddles the sheet: some points inside a 1.5 cm sheet, most of the box outside it
    assert 0.2 < float((pts.garment_distance[:600] < 0.015).float().mean()) < 0.8
    assert float((pts.garment_distance[600:] < 0.015).float().mean()) < 0.2


def test_labels_are_the_sheet_or_the_body():
    distance = torch.tensor([0.0, 0.01, 0.02, 0.3, 0.3])
    height = torch.tensor([0.2, 0.2, 0.2, -0.01, 0.05])
    assert occupancy_labels(distance, height, 0.015).tolist() == [1.0, 1.0, 0.0, 1.0, 0.0]


@pytest.mark.parametrize("step", [0.01, 0.025])
def test_loss_is_the_binary_cross_entropy_of_the_interval_alpha(step):
    gen = torch.Generator().manual_seed(1)
    sigma = torch.rand(500, generator=gen) * 200.0 + 5.0
    occupied = (torch.rand(500, generator=gen) > 0.5).float()
    alpha = 1.0 - torch.exp(-sigma.double() * step)
    reference = F.binary_cross_entropy(alpha, occupied.double())
    # the optical-depth floor of the occupied label's log moves it by at most floor / (sigma * step) = 0.2 %
    torch.testing.assert_close(occupancy_loss(sigma, occupied, step).double(), reference, rtol=2e-3, atol=1e-6)


def test_loss_gradient_matches_finite_differences_and_survives_zero_density():
    sigma = torch.tensor([0.0, 3.0, 80.0], dtype=torch.float64, requires_grad=True)
    occupied = torch.tensor([1.0, 0.0, 1.0], dtype=torch.float64)
    loss = occupancy_loss(sigma, occupied, 0.02)
    assert torch.isfinite(loss)
    (grad,) = torch.autograd.grad(loss, sigma)
    assert torch.isfinite(grad).all()
    # an empty point's loss rises with its density, an occupied point's falls
    assert grad[1] > 0 and grad[2] < 0 and grad[0] < 0
    eps = 1e-4
    for i in (1, 2):
        up, down = sigma.detach().clone(), sigma.detach().clone()
        up[i] += eps
        down[i] -= eps
        fd = (occupancy_loss(up, occupied, 0.02) - occupancy_loss(down, occupied, 0.02)) / (2 * eps)
        torch.testing.assert_close(grad[i], fd, rtol=1e-4, atol=1e-9)


def test_iou():
    sigma = torch.tensor([0.0, 100.0, 100.0, 0.0])
    occupied = torch.tensor([0.0, 1.0, 0.0, 1.0])
    assert occupancy_iou(sigma, occupied, 0.025) == pytest.approx(1 / 3)
