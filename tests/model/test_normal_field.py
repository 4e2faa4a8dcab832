"""The blurred body normals the shading reads (``model/normal_field.py``): the grid against the plain sum
over faces, a sphere's radial normals, two legs whose gap gets the forward normal, and the model reading
them with ``shading_normal_blur``."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from garmentnerf.model.normal_field import (KERNEL_SIGMAS, blurred_normal_grid, blurred_normals_direct,
                                            read_normal_grid)


def angles_deg(a: torch.Tensor, b: torch.Tensor) -> np.ndarray:
    return np.degrees(np.arccos(np.clip((a.double() * b.double()).sum(-1).numpy(), -1.0, 1.0)))


def mesh_tensors(mesh: trimesh.Trimesh) -> tuple[torch.Tensor, torch.Tensor]:
    return torch.tensor(mesh.vertices, dtype=torch.float32), torch.tensor(mesh.faces)


def test_the_grid_is_the_sum_over_faces_and_a_spheres_field_is_radial():
    vertices, faces = mesh_tensors(trimesh.creation.icosphere(4, radius=0.3))
    sigma = 0.05
    grid = blurred_normal_grid(vertices, faces, sigma, reach=KERNEL_SIGMAS * sigma)
    rng = np.random.default_rng(0)
    direction = rng.normal(size=(400, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    radius = rng.uniform(0.31, 0.3 + 2 * sigma, size=(400, 1))  # within the kernel's reach of the surface
    positions = torch.tensor(direction * radius, dtype=torch.float32)
    fallback = torch.tensor([[0.0, 0.0, 1.0]]).expand(400, 3)
    got = read_normal_grid(grid, positions, fallback)
    want = blurred_normals_direct(vertices, faces, sigma, positions)
    assert np.max(angles_deg(got, want)) < 1.0
    assert np.max(angles_deg(want, torch.tensor(direction))) < 0.1  # a sphere's blurred normals are radial


def test_far_from_the_body_the_fallback_is_read():
    vertices, faces = mesh_tensors(trimesh.creation.icosphere(3, radius=0.3))
    sigma = 0.03
    grid = blurred_normal_grid(vertices, faces, sigma, reach=KERNEL_SIGMAS * sigma)
    positions = torch.tensor([[0.0, 0.0, 0.3 + 8 * sigma], [0.0, 0.0, 2.0], [0.0, 0.0, 0.31]])
    fallback = torch.tensor([[1.0, 0.0, 0.0]]).expand(3, 3)
    got = read_normal_grid(grid, positions, fallback)
    assert torch.equal(got[:2], fallback[:2])
    assert angles_deg(got[2:], torch.tensor([[0.0, 0.0, 1.0]]))[0] < 1.0


def test_the_gap_between_two_legs_gets_the_forward_normal_not_a_thighs():
    leg = trimesh.creation.cylinder(radius=0.07, height=0.8, sections=48)  # axis z
    legs = trimesh.util.concatenate([leg.copy().apply_translation([-0.09, 0, 0]),
                                     leg.copy().apply_translation([0.09, 0, 0])])
    vertices, faces = mesh_tensors(legs)
    grid = blurred_normal_grid(vertices, faces, 0.05, reach=0.15)
    # in front of the gap, where a skirt across the legs hangs
    positions = torch.tensor([[0.0, 0.06, 0.0]])
    closest, _, tri = trimesh.proximity.closest_point(legs, positions.double().numpy())
    thigh = torch.tensor(legs.face_normals[tri])
    got = read_normal_grid(grid, positions, thigh.float())
    assert angles_deg(got[:1], torch.tensor([[0.0, 1.0, 0.0]]))[0] < 5.0  # the cloth across the gap faces forward
    assert angles_deg(thigh[:1], torch.tensor([[0.0, 1.0, 0.0]]))[0] > 30.0  # the closest point's does not


def test_a_model_with_blurred_shading_normals_reads_the_grid(body, projector, walk_inputs):
    from garmentnerf.model.pipeline import GarmentAnimationNeRF
    from tests.model.test_uvh_field import PALETTE, uvh_config

    with pytest.raises(ValueError, match="shading_normals"):
        uvh_config(shading_normal_blur=0.05)
    torch.manual_seed(0)
    cfg = uvh_config(shading_normals=True, shading_normal_blur=0.05)
    model = GarmentAnimationNeRF(cfg, body, PALETTE, projector=projector)
    frame = model.prepare_frame(walk_inputs)
    assert frame.normal_grid is not None
    again = model.prepare_frame(walk_inputs, geometry=frame)
    assert again.normal_grid is frame.normal_grid  # built once per posed body
    mesh = trimesh.Trimesh(frame.posed_vertices.double().numpy(), projector.faces.numpy(), process=False)
    points, face_ids = trimesh.sample.sample_surface(mesh, 300, seed=2)
    positions = torch.tensor(points + 0.02 * mesh.face_normals[face_ids], dtype=torch.float32)
    with torch.no_grad():
        _, zeta, _ = model.evaluate_samples(frame, positions)
    want = blurred_normals_direct(frame.posed_vertices, projector.faces, 0.05, positions)
    assert np.median(angles_deg(zeta[:, cfg.appearance_dim:], want)) < 1.0
