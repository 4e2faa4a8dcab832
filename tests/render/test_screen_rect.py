"""The character's screen rectangle (garmentnerf.render.screen_rect) and cropped cameras, checked
against the rays themselves: every pixel whose ray meets the box lies inside the rectangle."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from garmentnerf.conventions import Camera, camera_rays, intrinsics_from_fov, look_at
from garmentnerf.model.samplers import ray_aabb_intersect
from garmentnerf.render.screen_rect import PixelRect, box_rect


def look_at_camera(eye, target, width: int, height: int, fov_y_deg: float) -> Camera:
    R, t = look_at(eye, target)
    return Camera(intrinsics_from_fov(width, height, fov_y_deg), R, t, width, height)


BOX = np.array([[-0.3, -0.2, 0.0], [0.35, 0.25, 1.7]])


def _hit_pixels(camera: Camera, box) -> np.ndarray:
    """(H, W) bool: the pixels whose ray meets the box (the slab test of the samplers)."""
    origins, dirs = camera_rays(camera, torch.float64)
    _, _, hit = ray_aabb_intersect(origins.reshape(-1, 3), dirs.reshape(-1, 3), torch.as_tensor(box))
    return hit.reshape(camera.height, camera.width).numpy()


@pytest.mark.parametrize("eye", [(0.4, -4.5, 1.2), (3.5, 2.5, 2.5), (-1.0, -1.2, 0.4)])
def test_rect_holds_every_pixel_that_sees_the_box(eye):
    camera = look_at_camera(np.array(eye), np.array([0.0, 0.0, 0.9]), 200, 160, fov_y_deg=45.0)
    hit = _hit_pixels(camera, BOX)
    assert hit.any() and not hit.all()
    rows, cols = np.nonzero(hit)
    tight_checked = False
    for cell, margin in ((1, 0), (8, 0), (8, 2)):
        rect = box_rect(camera, BOX, cell=cell, margin_cells=margin)
        assert rect.x0 % cell == 0 and rect.y0 % cell == 0 and rect.width % cell == 0 and rect.height % cell == 0
        assert rect.x0 <= cols.min() and cols.max() < rect.x1 and rect.y0 <= rows.min() and rows.max() < rect.y1
        # tight: without the margin, within one cell of the hit pixels' bounding box (or the image edge)
        # (where the box's outline is clipped by the image edge the hull's extent is not the
        # visible one, so the check is for a box wholly in view)
        if margin == 0 and rect.x0 > 0 and rect.y0 > 0 and rect.x1 < camera.width and rect.y1 < camera.height:
            assert cols.min() - rect.x0 < cell + 1 and rect.x1 - 1 - cols.max() < cell + 1
            assert rows.min() - rect.y0 < cell + 1 and rect.y1 - 1 - rows.max() < cell + 1
            tight_checked = True
        else:
            inner = box_rect(camera, BOX, cell=cell)
            assert rect.x0 == max(inner.x0 - margin * cell, 0) and rect.y1 == min(inner.y1 + margin * cell, 160)
    assert tight_checked or eye[1] > -2  # the two far cameras see the whole box


def test_rect_edge_cases():
    camera = look_at_camera(np.array([0.0, -3.0, 1.0]), np.array([0.0, 0.0, 1.0]), 64, 48, fov_y_deg=40.0)
    assert box_rect(camera, BOX + np.array([0.0, -3.5, 0.0])) == PixelRect(0, 0, 64, 48)  # camera inside
    assert box_rect(camera, BOX + np.array([0.0, -5.0, 0.0])) == PixelRect(0, 0, 64, 48)  # behind: unbounded
    assert box_rect(camera, BOX + np.array([30.0, 0.0, 0.0])) is None  # far to the side: not in view
    with pytest.raises(ValueError, match="multiple of the cell"):
        box_rect(camera, BOX, cell=5)


def test_cropped_camera_rays_are_the_full_cameras():
    camera = look_at_camera(np.array([1.0, -2.5, 1.4]), np.array([0.0, 0.0, 0.9]), 120, 90, fov_y_deg=50.0)
    rect = PixelRect(17, 9, 40, 64)
    crop = camera.cropped(rect.x0, rect.y0, rect.width, rect.height)
    o_full, d_full = camera_rays(camera, torch.float64)
    o_crop, d_crop = camera_rays(crop, torch.float64)
    assert torch.allclose(d_crop, d_full[rect.slices()], atol=1e-12)
    assert torch.allclose(o_crop, o_full[rect.slices()])
    # past the image's edge the crop keeps going with the same pinhole
    beyond = camera.cropped(100, 80, 40, 20)
    assert beyond.K[0, 2] == camera.K[0, 2] - 100 and beyond.K[1, 2] == camera.K[1, 2] - 80
