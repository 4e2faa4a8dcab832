"""``prepare_frame(inputs, geometry)`` reuses the body geometry of features prepared earlier for
the same posed body: nothing is rebuilt, and the render is bit for bit the same."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from garmentnerf.conventions import orbit_camera
from garmentnerf.model.config import ModelConfig
from garmentnerf.model.pipeline import GarmentAnimationNeRF

pytestmark = pytest.mark.usefixtures("one_torch_thread")

CAMERA = orbit_camera(30.0, 10.0, 3.0, width=64, height=64)


@pytest.fixture(scope="module")
def model(body, projector):
    torch.manual_seed(0)
    return GarmentAnimationNeRF(ModelConfig.tiny(), body, {"garment": [0.8, 0.2, 0.2], "body": [0.7, 0.6, 0.5]},
                                projector=projector).eval()


def test_reused_geometry_renders_bit_for_bit_without_rebuilding(model, walk_inputs, monkeypatch):
    gen = torch.Generator().manual_seed(3)
    with torch.no_grad():
        fresh = model.prepare_frame(walk_inputs)
        expected = model.render(fresh, CAMERA, training=True, generator=gen).image
    geometry = dataclasses.replace(fresh, dynamic_features=None, reference_images=None, detail_features=None)
    monkeypatch.setattr(model, "bind_body", lambda verts: pytest.fail("the body was bound again"))
    monkeypatch.setattr("garmentnerf.model.pipeline.vertex_normals",
                        lambda verts, faces: pytest.fail("the normals were computed again"))
    gen = torch.Generator().manual_seed(3)
    with torch.no_grad():
        reused = model.prepare_frame(walk_inputs, geometry)
        image = model.render(reused, CAMERA, training=True, generator=gen).image
    assert reused.surface is fresh.surface and reused.vertex_normals is fresh.vertex_normals
    assert reused.aabb is fresh.aabb
    assert torch.equal(reused.dynamic_features, fresh.dynamic_features)
    assert torch.equal(image, expected) and image.abs().sum() > 0


def test_geometry_of_another_pose_is_refused(model, walk_inputs):
    with torch.no_grad():
        fresh = model.prepare_frame(walk_inputs)
        moved = dataclasses.replace(walk_inputs, posed_vertices=walk_inputs.posed_vertices + 1e-6, frame=7)
        with pytest.raises(ValueError, match="not that of the posed body of frame 7"):
            model.prepare_frame(moved, fresh)
