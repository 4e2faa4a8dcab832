"""The body layer of the hybrid composition (garmentnerf.render.body_layer) and fitting its
appearance (garmentnerf.train.body_appearance), against the ground-truth renderer
(garmentnerf.data.render_gt) as the independent reference."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from garmentnerf.data.cameras import ring_camera
from garmentnerf.model.body_appearance import BodyAppearance
from garmentnerf.render.body_layer import body_surface, render_body_layer
from garmentnerf.train.body_appearance import BodySamples, fit_body_appearance, interior_body_pixels

SIZE = 96


@pytest.fixture(scope="module")
def posed(body, walk_clip):
    """(vertices (V, 3), six cameras around them) of the walk's first frame."""
    posed_clip, _ = walk_clip
    verts = posed_clip.vertices[0].detach().float()
    centre = verts.double().mean(dim=0).numpy()
    # the sixth camera (held out of the fit) sits between the first two
    azimuths = (0.0, 72.0, 144.0, 216.0, 288.0, 36.0)
    return verts, [ring_camera(a, 2.6, float(centre[2]), centre, SIZE, SIZE) for a in azimuths]


@pytest.fixture(scope="module")
def truths(gl_context, body, posed):
    """The ground-truth renderer's body-only images of every camera (skin tone, its light rig)."""
    from garmentnerf.data.render_gt import GroundTruthRenderer

    verts, cams = posed
    renderer = GroundTruthRenderer(gl_context)
    try:
        return [renderer.render_full(verts.numpy(), body.faces.numpy(), camera=c) for c in cams]
    finally:
        renderer.release()


@pytest.fixture(scope="module")
def camera_pass(gl_context):
    from garmentnerf.gl.camera_pass import CameraPass

    p = CameraPass(gl_context)
    yield p
    p.release()


def test_coverage_is_the_ground_truths(camera_pass, body, posed, truths):
    """The layer's 2 x 2 supersampled coverage against the ground-truth renderer's, which rasterises the
    same triangles at the same subsamples."""
    verts, cams = posed
    for cam, truth in zip(cams, truths):
        _, coverage = render_body_layer(camera_pass, body, verts, cam, BodyAppearance(texture_size=4))
        cov = coverage[0, 0].numpy()
        assert truth.alpha.sum() > 200
        assert np.abs(cov - truth.alpha).mean() < 2e-3
        assert np.mean(cov == truth.alpha) > 0.99


def test_fitted_appearance_reproduces_a_held_out_view(camera_pass, body, posed, truths):
    """Fit on five views' interior body pixels, then draw the sixth: over 35 dB against the ground
    truth over its body (scikit-image PSNR), where the flat palette colour is under 20 dB. Without
    the albedo prior the texture and the shading trade scale in the texels the five views saw, and
    the held-out view, which sees others, comes out more than 5 dB worse."""
    from skimage.metrics import peak_signal_noise_ratio

    from garmentnerf.data.render_gt import SKIN_TONE
    from garmentnerf.model.palette import DecomposedMaps

    verts, cams = posed
    uvs, normals, colors = [], [], []
    for cam, truth in zip(cams[:5], truths[:5]):
        px = body_surface(camera_pass, verts, body.faces, body.uv, body.uv_faces, cam)
        seen = px.mask.numpy()
        keep = torch.from_numpy(interior_body_pixels(truth.labels, seen)[seen])
        uvs.append(px.uv[keep])
        normals.append(px.normals[keep])
        colors.append(torch.from_numpy(truth.rgb[seen][keep.numpy()]))
    samples = BodySamples(torch.cat(uvs), torch.cat(normals), torch.cat(colors), 5)
    tint = torch.tensor(SKIN_TONE)
    palette = torch.stack([torch.tensor([0.1, 0.3, 0.8]), tint])
    cam, truth = cams[5], truths[5]
    region = truth.labels == 1
    P = 2
    empty = DecomposedMaps(torch.zeros(1, 3, SIZE, SIZE), torch.zeros(1, P, 3, SIZE, SIZE),
                           torch.full((1, P, SIZE, SIZE), 0.5), torch.zeros(1, 1, SIZE, SIZE))

    def held_out_psnr(appearance) -> float:
        with torch.no_grad():
            color, coverage = render_body_layer(camera_pass, body, verts, cam, appearance)
            image = empty.with_body(color, coverage).compose(palette)[0].permute(1, 2, 0).numpy()
        return peak_signal_noise_ratio(truth.rgb[region], image[region], data_range=1.0)

    # a stronger prior than the default settles the scale in few steps (the test's budget)
    fitted, summary = fit_body_appearance(samples, tint, steps=400, albedo_prior=0.1, progress=False)
    assert summary["psnr"] > summary["psnr_start"] + 15
    loose, _ = fit_body_appearance(samples, tint, steps=400, albedo_prior=0.0, progress=False)
    flat = held_out_psnr(BodyAppearance(texture_size=4))
    assert held_out_psnr(fitted) > 35.0
    assert flat < 20.0
    assert held_out_psnr(loose) < held_out_psnr(fitted) - 5.0


@pytest.mark.parametrize("degree", [4, 2])
def test_gl_body_layer_is_the_torch_reference(gl_context, camera_pass, body, posed, degree):
    """:class:`BodyLayerPass` (rasterised and shaded by GL) against :func:`render_body_layer` (the
    camera pass's G-buffer shaded in torch) with a random texture and shading: the same subsamples
    are covered, and the colour agrees to texture-filtering precision."""
    from garmentnerf.body.surface import vertex_normals
    from garmentnerf.gl.body_layer_pass import BodyLayerPass

    verts, cams = posed
    normals = vertex_normals(verts, body.faces)
    appearance = BodyAppearance(texture_size=32, degree=degree)
    g = torch.Generator().manual_seed(degree)
    with torch.no_grad():
        appearance.albedo.uniform_(0.2, 1.5, generator=g)
        appearance.shading.normal_(0.0, 0.4, generator=g)
        appearance.shading[0] += 0.8
    with BodyLayerPass(gl_context) as gl_pass:
        for cam in (cams[0], cams[3].resized(71, 53)):
            for supersample in (2, 1):
                ref_color, ref_coverage = render_body_layer(camera_pass, body, verts, cam, appearance,
                                                            supersample, normals=normals)
                color, coverage = gl_pass.render(verts, normals, body.faces, body.uv, body.uv_faces, cam,
                                                 appearance, supersample)
                assert color.shape == (1, 3, cam.height, cam.width) and coverage.shape == (1, 1, cam.height,
                                                                                            cam.width)
                assert coverage.sum() > 50 and torch.equal(coverage, ref_coverage)
                diff = (color - ref_color.detach()).abs()
                assert ref_color.amax() > 0.5 and ref_color.std() > 0.05  # a layer worth comparing
                assert diff.max() < 2e-3 and diff.mean() < 1e-5
        # the same frame from another camera reuses the uploaded mesh (above); another frame does not
        moved = verts + torch.tensor([0.15, 0.0, 0.0])
        ref_moved = render_body_layer(camera_pass, body, moved, cams[0], appearance, normals=normals)[1]
        got_moved = gl_pass.render(moved, normals, body.faces, body.uv, body.uv_faces, cams[0], appearance)[1]
        assert torch.equal(got_moved, ref_moved) and not torch.equal(got_moved, gl_pass.render(
            verts, normals, body.faces, body.uv, body.uv_faces, cams[0], appearance)[1])
