"""The palette composition formula: identities, recoloring, range checks, the decoder's heads."""

from __future__ import annotations

import pytest
import torch

from garmentnerf.model.losses import sparsity_loss
from garmentnerf.model.palette import (
    DecomposedMaps,
    Palette,
    PaletteDecoder,
    compose,
    palette_from_labels,
    restoring_clamp,
)

B, P, H, W = 2, 2, 5, 6
GARMENT = torch.tensor([0.8, 0.2, 0.1])
BODY = torch.tensor([0.6, 0.5, 0.4])
PALETTE = torch.stack([GARMENT, BODY])


def maps(weight_garment: torch.Tensor | float = 1.0, mask: float | torch.Tensor = 1.0, seed: int = 0,
         offsets: bool = False) -> DecomposedMaps:
    g = torch.Generator().manual_seed(seed)
    radiance = 0.2 + 0.8 * torch.rand(B, 3, H, W, generator=g)
    o = 0.03 * torch.randn(B, P, 3, H, W, generator=g) if offsets else torch.zeros(B, P, 3, H, W)
    wg = torch.as_tensor(weight_garment, dtype=torch.float32).expand(B, H, W)
    weights = torch.stack([wg, 1 - wg], dim=1)
    m = torch.as_tensor(mask, dtype=torch.float32).expand(B, 1, H, W)
    return DecomposedMaps(radiance, o, weights, m)


def test_garment_weight_one_gives_radiance_times_garment_color():
    m = maps(1.0)
    image = m.compose(PALETTE)
    torch.testing.assert_close(image, (m.radiance * GARMENT.view(1, 3, 1, 1)).clamp(0, 1))


def test_paper_formula_for_two_colors_on_black():
    g = torch.Generator().manual_seed(3)
    w = torch.rand(B, H, W, generator=g)
    m = maps(w, mask=torch.rand(B, 1, H, W, generator=g), offsets=True)
    o_g, o_b = m.offsets[:, 0], m.offsets[:, 1]
    wv = w.unsqueeze(1)
    paper = m.mask * m.radiance * (wv * (GARMENT.view(1, 3, 1, 1) + o_g) + (1 - wv) * (BODY.view(1, 3, 1, 1) + o_b))
    # The paper composites over black; radiance < 1 and colors < 1 keep it inside [0, 1].
    assert paper.max() <= 1 and paper.min() >= 0
    torch.testing.assert_close(compose(m.radiance, m.offsets, m.weights, m.mask, PALETTE), paper)


@pytest.mark.parametrize("background", [(0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (0.2, 0.4, 0.9)])
def test_mask_zero_gives_background(background):
    image = maps(0.7, mask=0.0, offsets=True).compose(PALETTE, background)
    torch.testing.assert_close(image, torch.tensor(background).view(1, 3, 1, 1).expand(B, 3, H, W))


def test_recoloring_changes_pixels_in_proportion_to_garment_weight():
    g = torch.Generator().manual_seed(5)
    w = torch.rand(B, H, W, generator=g)
    w[0, 0, 0] = 0.0  # a pure body pixel must not change at all
    m = maps(w, mask=torch.rand(B, 1, H, W, generator=g), offsets=True)
    new = torch.stack([torch.tensor([0.1, 0.3, 0.9]), BODY])
    before, after = m.compose(PALETTE), m.compose(new)
    # Inside [0, 1] (no clamping) the formula is linear in the palette.
    assert (before > 0).all() and (before < 1).all() and (after > 0).all() and (after < 1).all()
    expected = m.mask * m.radiance * w.unsqueeze(1) * (new[0] - GARMENT).view(1, 3, 1, 1)
    torch.testing.assert_close(after - before, expected, atol=1e-6, rtol=1e-5)
    assert (after[0, :, 0, 0] == before[0, :, 0, 0]).all()
    # Same palette again: bit-identical (one formula for training and editing).
    assert torch.equal(m.compose(PALETTE.clone()), before)


@pytest.mark.parametrize("value", [0.0, 1.0])
def test_palette_at_range_ends_is_finite(value):
    image = maps(0.5, offsets=True).compose(torch.full((P, 3), value))
    assert torch.isfinite(image).all()
    assert image.min() >= 0 and image.max() <= 1


@pytest.mark.parametrize("bad", [1.2, -0.1, float("nan")])
def test_out_of_range_palette_raises(bad):
    palette = PALETTE.clone()
    palette[1, 2] = bad
    with pytest.raises(ValueError):
        maps().compose(palette)
    with pytest.raises(ValueError):
        Palette(palette)


def test_wrong_palette_size_or_background_raises():
    with pytest.raises(ValueError, match="palette size"):
        maps().compose(torch.rand(3, 3))
    with pytest.raises(ValueError, match="background"):
        maps().compose(PALETTE, (0.0, 2.0, 0.0))


def test_clamp_once_with_restoring_gradient():
    x = torch.tensor([-0.5, 0.5, 1.5, 1.5, -0.5], requires_grad=True)
    y = restoring_clamp(x)
    torch.testing.assert_close(y, torch.tensor([0.0, 0.5, 1.0, 1.0, 0.0]))
    # Upstream gradients: descent moves x by -grad. Entries 0 and 2 are pulled back into range
    # (kept); entries 3 and 4 would be pushed further out (dropped).
    (grad,) = torch.autograd.grad(y, x, torch.tensor([-1.0, 1.0, 1.0, -1.0, 1.0]))
    torch.testing.assert_close(grad, torch.tensor([-1.0, 1.0, 1.0, 0.0, 0.0]))
    # A saturated pixel whose target is darker still gets gradient through compose.
    m = maps(1.0)
    radiance = (m.radiance * 5).requires_grad_(True)
    image = compose(radiance, m.offsets, m.weights, m.mask, PALETTE)
    loss = (image - 0.3).abs().mean()
    (g,) = torch.autograd.grad(loss, radiance)
    saturated = radiance * GARMENT.view(1, 3, 1, 1) > 1
    assert saturated.any() and (g[saturated] > 0).all()


def test_decoder_heads():
    torch.manual_seed(0)
    dec = PaletteDecoder(in_channels=16, palette_size=3, width=16, min_width=8, extra_layers=1, offset_scale=0.25)
    out = dec(torch.randn(2, 16, 4, 6))
    assert out.radiance.shape == (2, 3, 16, 24)
    assert out.offsets.shape == (2, 3, 3, 16, 24)
    assert out.weights.shape == (2, 3, 16, 24)
    assert out.mask.shape == (2, 1, 16, 24)
    assert (out.radiance >= 0).all()
    assert out.offsets.abs().max() <= 0.25
    torch.testing.assert_close(out.weights.sum(dim=1), torch.ones(2, 16, 24))
    # softplus + 0.05 before normalising: no color's weight reaches 0.
    assert out.weights.min() > 0
    assert ((out.mask > 0) & (out.mask < 1)).all()
    # Untrained radiance is 1 where the raw head is 0 (shifted softplus).
    with torch.no_grad():
        dec.head.weight.zero_()
        dec.head.bias.zero_()
    torch.testing.assert_close(dec(torch.randn(1, 16, 2, 2)).radiance, torch.ones(1, 3, 8, 8))
    grey = PaletteDecoder(in_channels=16, radiance_channels=1, width=8, min_width=8, extra_layers=0)
    g_out = grey(torch.randn(1, 16, 2, 2))
    assert g_out.radiance.shape == (1, 1, 8, 8)
    assert g_out.compose(PALETTE).shape == (1, 3, 8, 8)


def _feature_support(decoder: PaletteDecoder, channels: int, size: int) -> int:
    """Rows of a (1, channels, size, size) feature image that the centre output pixel's radiance depends on."""
    features = torch.randn(1, channels, size, size, dtype=torch.float64, requires_grad=True)
    radiance = decoder(features).radiance
    centre = radiance.shape[-1] // 2
    (grad,) = torch.autograd.grad(radiance[0, 0, centre, centre], features)
    return int((grad.abs().sum(dim=(0, 1, 3)) > 0).sum())


def test_sparsity_loss_two_colors_matches_paper():
    w = torch.rand(1, 1, 4, 4)
    weights = torch.cat([w, 1 - w], dim=1)
    paper = (1 / (w ** 2 + (1 - w) ** 2) - 1).mean()
    torch.testing.assert_close(sparsity_loss(weights), paper)
    one_hot = torch.zeros(1, 3, 2, 2)
    one_hot[:, 1] = 1
    assert sparsity_loss(one_hot).item() == 0.0
    assert sparsity_loss(torch.full((1, 3, 2, 2), 1 / 3)).item() == pytest.approx(2.0)


def test_palette_module_and_init_from_labels():
    image = torch.zeros(1, 3, 2, 2)
    image[0, :, 0, 0] = torch.tensor([1.0, 0.0, 0.0])
    image[0, :, 0, 1] = torch.tensor([0.0, 1.0, 0.0])
    image[0, :, 1, 1] = torch.tensor([0.2, 0.2, 0.2])
    labels = torch.tensor([[[2, 2], [0, 1]]])
    p = palette_from_labels(image, labels)
    torch.testing.assert_close(p, torch.tensor([[0.5, 0.5, 0.0], [0.2, 0.2, 0.2]]))
    torch.testing.assert_close(palette_from_labels(image.permute(0, 2, 3, 1), labels), p)
    with pytest.raises(ValueError, match="label 7"):
        palette_from_labels(image, labels, classes=(2, 7))
    module = Palette(p)
    with torch.no_grad():
        module.colors[0, 0] = 1.5  # drifted out of range by an optimiser step
    assert module().max() == 1.0
    torch.testing.assert_close(module.initial, p)


def test_restoring_sigmoid_forward_and_gradient():
    from garmentnerf.model.palette import RESTORING_SIGMOID_FLOOR, restoring_sigmoid

    x = torch.tensor([-16.0, -16.0, 0.5, 16.0, 16.0], dtype=torch.float64, requires_grad=True)
    y = restoring_sigmoid(x)
    assert torch.allclose(y, torch.sigmoid(x.detach()), atol=0, rtol=0)
    # L1 towards targets: up for the first (restoring), down for the second (further into saturation)
    target = torch.tensor([1.0, 0.0, 1.0, 1.0, 0.0], dtype=torch.float64)
    (y - target).abs().sum().backward()
    s = torch.sigmoid(x.detach())
    plain = s * (1 - s)  # analytic sigmoid slope
    expect = torch.sign(s - target) * plain
    expect[0] = -RESTORING_SIGMOID_FLOOR  # saturated low, pulled up: the floor
    expect[4] = RESTORING_SIGMOID_FLOOR  # saturated high, pushed down: the floor
    assert torch.allclose(x.grad, expect, rtol=1e-12, atol=1e-15), (x.grad, expect)
    # in the sensitive region it is the plain sigmoid: finite differences
    xs = torch.linspace(-3, 3, 13, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t: restoring_sigmoid(t), (xs,))


def test_opacity_loss_against_block_means():
    from garmentnerf.model.losses import opacity_loss

    mask = torch.zeros(1, 1, 4, 4)
    mask[0, 0, :2, :2] = 1.0  # top-left 2x2 block full
    mask[0, 0, 2, 2] = 1.0  # one of four pixels of the bottom-right block
    opacity = torch.tensor([[[1.0, 0.5], [0.0, 0.0]]])
    # block means: [[1, 0], [0, 0.25]] -> |diff| = [[0, 0.5], [0, 0.25]] -> mean 0.1875
    assert float(opacity_loss(opacity, mask)) == pytest.approx(0.1875, abs=1e-7)


def test_density_scale_multiplies_the_activation():
    from garmentnerf.model.nerf_mlp import density_activation

    raw = torch.linspace(-5, 5, 11)
    for kind, act in (("softplus", torch.nn.functional.softplus), ("trunc_exp", torch.exp)):
        got = density_activation(raw, kind, bias=-3.0, scale=10.0)
        assert torch.allclose(got, 10.0 * act(raw - 3.0), rtol=1e-6)


def test_body_density_prior_shape():
    from garmentnerf.model.nerf_mlp import body_density_prior

    h = torch.tensor([-0.2, 0.0, 0.075, 0.15, 0.3, 5.0])
    got = body_density_prior(h, 3.0, 0.15)
    assert torch.allclose(got, torch.tensor([3.0, 3.0, 1.5, 0.0, -3.0, -3.0]), atol=1e-6)


def test_segmentation_loss_by_hand():
    from garmentnerf.model.losses import segmentation_loss

    # four pixels: garment, body, half garment half body, background (weights there do not count)
    w_g = torch.tensor([0.9, 0.3, 0.5, 0.7]).view(1, 1, 2, 2)
    weights = torch.cat([w_g, 1.0 - w_g], dim=1)
    garment = torch.tensor([1.0, 0.0, 0.5, 0.0]).view(1, 1, 2, 2)
    mask = torch.tensor([1.0, 1.0, 1.0, 0.0]).view(1, 1, 2, 2)
    # |0.9 - 1| + |0.3 - 0| + |0.5 - 0.5| over 3 foreground pixels
    assert float(segmentation_loss(weights, garment, mask)) == pytest.approx(0.4 / 3, abs=1e-7)
    # a pixel a quarter covered, all of it garment, asks for w_G = 1 with a quarter of the weight
    mask2 = torch.tensor([1.0, 1.0, 1.0, 0.25]).view(1, 1, 2, 2)
    garment2 = torch.tensor([1.0, 0.0, 0.5, 0.25]).view(1, 1, 2, 2)
    assert float(segmentation_loss(weights, garment2, mask2)) == pytest.approx((0.4 + 0.25 * 0.3) / 3.25, abs=1e-7)
    # finite differences agree with autograd away from the kinks
    x = torch.tensor([0.2, -0.4, 1.1, 0.3], dtype=torch.float64).view(1, 1, 2, 2).requires_grad_()
    f = lambda t: segmentation_loss(torch.cat([torch.sigmoid(t), 1 - torch.sigmoid(t)], 1),  # noqa: E731
                                    garment.double(), mask.double())
    assert torch.autograd.gradcheck(f, (x,))


def test_segmentation_loss_per_layer_by_hand():
    from garmentnerf.model.losses import segmentation_loss

    # a three-color palette (inner layer, outer layer, body) and two pixels: inner, outer
    weights = torch.tensor([[0.6, 0.1], [0.3, 0.7], [0.1, 0.2]]).view(1, 3, 1, 2)
    layers = torch.tensor([[1.0, 0.0], [0.0, 1.0]]).view(1, 2, 1, 2)
    mask = torch.ones(1, 1, 1, 2)
    # targets (1, 0, 0) and (0, 1, 0): (|0.6 - 1| + 0.3 + 0.1) / 2 and (0.1 + |0.7 - 1| + 0.2) / 2, over 2 pixels
    assert float(segmentation_loss(weights, layers, mask)) == pytest.approx((0.4 + 0.3) / 2, abs=1e-7)
    # weight moved from the wrong layer to the body costs the same, not less
    leaked = torch.tensor([[0.6, 0.1], [0.0, 0.7], [0.4, 0.2]]).view(1, 3, 1, 2)
    assert float(segmentation_loss(leaked, layers, mask)) == pytest.approx((0.4 + 0.3) / 2, abs=1e-7)
    with pytest.raises(ValueError, match="more than 3 colors"):
        segmentation_loss(weights, torch.cat([layers, layers[:, :1]], 1), mask)


def test_palette_names():
    from garmentnerf.model.palette import palette_names

    assert palette_names(2) == ["Garment", "Body / other"]
    assert palette_names(3) == ["Garment layer 1 (inner)", "Garment layer 2 (outer)", "Body / other"]


def test_segmentation_term_only_when_asked():
    from garmentnerf.model.config import ModelConfig
    from garmentnerf.model.losses import garment_losses
    from garmentnerf.model.palette import DecomposedMaps

    H = W = 4
    maps = DecomposedMaps(torch.ones(1, 1, H, W), torch.zeros(1, 2, 3, H, W),
                          torch.full((1, 2, H, W), 0.5), torch.ones(1, 1, H, W))
    p = torch.tensor([[0.2, 0.3, 0.8], [0.6, 0.5, 0.4]])
    image = maps.compose(p)
    mask, garment = torch.ones(1, 1, H, W), torch.ones(1, 1, H, W)
    paper = garment_losses(image, image, maps, mask, p, p, ModelConfig.paper().loss, target_garment=garment)
    assert "segmentation" not in paper  # the paper's objective has no such term
    small = ModelConfig.cpu_small().loss
    out = garment_losses(image, image, maps, mask, p, p, small, target_garment=garment)
    assert float(out["segmentation"]) == pytest.approx(0.5)
    expected = sum(getattr(small, k) * out[k] for k in out if k != "total")
    torch.testing.assert_close(out["total"], expected)


def test_head_only_weights_reach_only_the_weight_head():
    from garmentnerf.model.palette import PaletteDecoder

    torch.manual_seed(0)
    dec = PaletteDecoder(in_channels=8, palette_size=2, width=8, min_width=8, radiance_channels=1,
                         head_only_weights=True).train()
    maps = dec(torch.randn(1, 8, 4, 4))
    torch.testing.assert_close(maps.weights_head_only, maps.weights)  # same values, other gradient path
    (maps.weights_head_only[:, 0] * torch.randn(1, 16, 16)).sum().backward()
    for name, p in dec.body.named_parameters():
        assert p.grad is None, name  # the layers shared with the mask and radiance get nothing
    rows = slice(1 + 3 * 2, 1 + 4 * 2)  # radiance (1), offsets (3 x 2), then the 2 weight logits
    grad = dec.head.weight.grad
    assert grad[rows].abs().sum() > 0
    assert grad[: rows.start].abs().sum() == 0 and grad[rows.stop:].abs().sum() == 0
    with torch.no_grad():
        assert dec(torch.randn(1, 8, 4, 4)).weights_head_only is None  # rendering pays nothing for it
    assert dec.eval()(torch.randn(1, 8, 4, 4)).weights_head_only is None


@pytest.mark.parametrize("size", [(2, 1), (3, 5), (4, 3)])  # integer factors of (6, 5), and a non-integer shrink
def test_shrinking_maps_averages_each_output_pixels_area(size):
    """A shrink is the box filter the ground truth is made with: OpenCV's INTER_AREA, exactly for an
    integer factor; the weights still sum to 1."""
    cv2 = pytest.importorskip("cv2")
    import numpy as np
    m = maps(weight_garment=torch.rand(B, H, W, generator=torch.Generator().manual_seed(3)), offsets=True)
    big = DecomposedMaps(m.radiance, m.offsets, m.weights, m.mask, None, m.radiance.clone(), m.mask.clone())
    small = big.resized(*size)
    hwc = big.radiance[0].permute(1, 2, 0).numpy().astype(np.float64)
    ref = torch.from_numpy(cv2.resize(hwc, size, interpolation=cv2.INTER_AREA)).permute(2, 0, 1).float()
    exact = W % size[0] == 0 and H % size[1] == 0
    if exact:
        torch.testing.assert_close(small.radiance[0], ref, atol=1e-6, rtol=0)
        torch.testing.assert_close(small.body_color[0], ref, atol=1e-6, rtol=0)
    else:  # F.interpolate's area averages whole input pixels; INTER_AREA weighs the cut ones by their share
        assert float((small.radiance[0] - ref).abs().max()) < 0.25
    torch.testing.assert_close(small.weights.sum(1), torch.ones(B, size[1], size[0]))
    # Growing a side keeps the bilinear filter (what the previewer's GPU does when it magnifies).
    grown = big.resized(2 * W, 2 * H)
    expect = torch.nn.functional.interpolate(big.mask, size=(2 * H, 2 * W), mode="bilinear", align_corners=False)
    torch.testing.assert_close(grown.mask, expect, atol=1e-6, rtol=0)
