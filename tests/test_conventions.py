"""Camera and pixel conventions, checked against OpenCV and by hand-computed cases."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from garmentnerf.conventions import Camera, camera_rays, intrinsics_from_fov, look_at, orbit_camera, project_points


def test_front_camera_sees_an_upright_character_with_its_left_on_the_right():
    cam = orbit_camera(0.0, 0.0, 3.0, target=(0, 0, 1), width=100, height=100)
    np.testing.assert_allclose(cam.center, [0, -3, 1], atol=1e-12)  # azimuth 0 is in front (-Y)
    pts = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.5], [0.3, 0.0, 1.0]], dtype=torch.float64)
    uv, depth = project_points(cam, pts)
    np.testing.assert_allclose(uv[0].numpy(), [49.5, 49.5], atol=1e-9)  # the target is the image centre
    assert uv[1, 1] < uv[0, 1]  # higher in the world is higher in the image (smaller row)
    assert uv[2, 0] > uv[0, 0]  # +X (the character's left) appears on the image's right
    np.testing.assert_allclose(depth.numpy(), [3.0, 3.0, 3.0], atol=1e-9)
    left = orbit_camera(90.0, 0.0, 3.0, target=(0, 0, 1))
    np.testing.assert_allclose(left.center, [3, 0, 1], atol=1e-12)


def test_look_at_is_a_proper_rotation_and_rejects_degenerate_views():
    R, t = look_at([1.0, -2.0, 3.0], [0.2, 0.1, 0.9])
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.isclose(np.linalg.det(R), 1.0)
    with pytest.raises(ValueError, match="coincide"):
        look_at([0, 0, 1], [0, 0, 1])
    with pytest.raises(ValueError, match="parallel"):
        look_at([0, 0, 5], [0, 0, 1])


def test_projection_matches_opencv():  # (OpenCV ignores skew, so none here)
    rng = np.random.default_rng(0)
    K = np.array([[500.0, 0.0, 310.0], [0.0, 480.0, 250.0], [0.0, 0.0, 1.0]])
    R, t = look_at([2.0, -3.0, 1.5], [0.0, 0.0, 1.0])
    cam = Camera(K, R, t, 640, 480)
    pts = rng.normal(size=(50, 3)) * 0.3 + [0, 0, 1]
    expected, _ = cv2.projectPoints(pts, cv2.Rodrigues(R)[0], t, K, None)
    uv, _ = project_points(cam, torch.as_tensor(pts))
    np.testing.assert_allclose(uv.numpy(), expected[:, 0], atol=1e-9)


def test_rays_pass_through_their_pixel_centres():
    K = intrinsics_from_fov(64, 48, 50.0)
    R, t = look_at([0.5, -2.0, 1.2], [0.0, 0.0, 1.0])
    cam = Camera(K, R, t, 64, 48)
    origins, dirs = camera_rays(cam, torch.float64)
    points = (origins + dirs * 2.5).reshape(-1, 3)
    uv, _ = project_points(cam, points)
    rows, cols = np.meshgrid(np.arange(48), np.arange(64), indexing="ij")
    np.testing.assert_allclose(uv.numpy(), np.stack([cols.ravel(), rows.ravel()], 1), atol=1e-9)


def test_resizing_keeps_the_image_of_a_point():
    cam = orbit_camera(20.0, 5.0, 3.0, width=512, height=512)
    small = cam.resized(128, 128)
    p = torch.tensor([[0.1, 0.2, 1.1]], dtype=torch.float64)
    uv_big, _ = project_points(cam, p)
    uv_small, _ = project_points(small, p)
    # continuous coordinates scale about the image corner (-0.5, -0.5)
    np.testing.assert_allclose(((uv_big + 0.5) / 4 - 0.5).numpy(), uv_small.numpy(), atol=1e-9)


def test_bad_cameras_are_rejected():
    with pytest.raises(ValueError, match="shape"):
        Camera(np.eye(2), np.eye(3), np.zeros(3), 10, 10)
    with pytest.raises(ValueError, match="NaN"):
        Camera(np.eye(3), np.full((3, 3), np.nan), np.zeros(3), 10, 10)
    with pytest.raises(ValueError, match="near < far"):
        Camera(np.eye(3), np.eye(3), np.zeros(3), 10, 10, near=1.0, far=0.5)
