"""Network modules: shapes, ranges, the config, and gradients through a tiny end-to-end forward."""

from __future__ import annotations

import json

import pytest
import torch
import torch.nn.functional as F

from garmentnerf.conventions import camera_rays, orbit_camera
from garmentnerf.model import (
    BoxStratifiedSampler,
    DetailEncoder,
    DynamicFeatureEncoder,
    GarmentNeRF,
    ImageGenerator,
    ModelConfig,
    NeuralTexture,
    Palette,
    PaletteDecoder,
    UNet,
    garment_losses,
    sample_image_features,
    select_detail_features,
)
from garmentnerf.model import volume_rendering as vr
from garmentnerf.model.config import (
    BACKGROUND,
    BBOX_PADDING,
    DETAIL_FEATURE_DIM,
    DYNAMIC_FEATURE_DIM,
    GRAD_CLIP_VALUE,
    UNET_DEPTH,
    LossConfig,
    convert_flat_config,
)
from garmentnerf.model.nerf_mlp import density_activation, trunc_exp
from garmentnerf.model.samplers import ray_aabb_intersect, stratified_intervals


# ---------------------------------------------------------------------------------------- U-Net
def test_dynamic_encoder_paper_shapes_and_range():
    torch.manual_seed(0)
    cfg = ModelConfig.paper()
    E = DynamicFeatureEncoder.from_config(cfg)
    assert E.widths == [32, 64, 128, 256, 512]
    bottleneck = {}
    E.down[-1].register_forward_hook(lambda m, i, o: bottleneck.update(shape=o.shape))
    x = torch.randn(1, 9, 128, 128)
    y = E(x)
    assert y.shape == (1, 8, 128, 128)
    assert bottleneck["shape"] == (1, 512, 8, 8)
    assert y.abs().max() < 1
    assert y.std() > 1e-3  # not collapsed


def test_small_preset_encoders():
    torch.manual_seed(0)
    cfg = ModelConfig.cpu_small()
    E = DynamicFeatureEncoder.from_config(cfg)
    G = DetailEncoder.from_config(cfg)
    assert E.widths[0] == 16 and len(E.widths) == UNET_DEPTH + 1
    y = E(torch.randn(1, cfg.encoder.in_channels, cfg.encoder.info_map_resolution, cfg.encoder.info_map_resolution))
    assert y.shape == (1, DYNAMIC_FEATURE_DIM, cfg.encoder.info_map_resolution, cfg.encoder.info_map_resolution)
    assert y.abs().max() < 1
    # G_en sees front and back reference images as one batch.
    d = G(torch.rand(2, 3, cfg.encoder.reference_resolution, cfg.encoder.reference_resolution))
    assert d.shape == (2, DETAIL_FEATURE_DIM, cfg.encoder.reference_resolution, cfg.encoder.reference_resolution)
    assert d.abs().max() < 1


def test_unet_rejects_indivisible_size():
    with pytest.raises(ValueError, match="divisible"):
        UNet(3, 2, base_width=4, depth=3)(torch.zeros(1, 3, 20, 24))
    with pytest.raises(ValueError, match="bottleneck"):
        UNet(3, 2, base_width=4, depth=3)(torch.zeros(1, 3, 8, 8))


# ---------------------------------------------------------------------------------------- G_img
def test_image_generator_shapes_mask_and_freeze():
    torch.manual_seed(0)
    gen = ImageGenerator(texture_channels=16, texture_levels=4, texture_resolution=64, base_width=8, depth=3)
    uv = torch.rand(2, 32, 32, 2)
    mask = torch.zeros(2, 32, 32, dtype=torch.bool)
    mask[:, 8:24, 8:24] = True
    q = gen.neural_image(uv, mask)
    assert q.shape == (2, 16, 32, 32)
    assert (q[:, :, ~mask[0]] == 0).all() and (q[:, :, mask[0]] != 0).any()
    image = gen(uv, mask)
    assert image.shape == (2, 3, 32, 32) and image.min() >= 0 and image.max() <= 1
    assert [t.shape[-1] for t in gen.texture.textures] == [64, 32, 16, 8]
    gen.freeze()
    assert not any(p.requires_grad for p in gen.parameters()) and not gen.training


def test_neural_texture_reads_texel_centres():
    tex = NeuralTexture(channels=1, levels=1, resolution=4)
    with torch.no_grad():
        tex.textures[0].copy_(torch.arange(16.0).view(1, 1, 4, 4))
    # Texel (row 1, column 2) has its centre at u = 2.5/4, v = 1.5/4 (row 0 is v = 0).
    uv = torch.tensor([[[[2.5 / 4, 1.5 / 4]]]])
    assert tex(uv).item() == pytest.approx(6.0)


# ---------------------------------------------------------------------------------------- MLP
def test_mlp_shapes_and_density_activation_not_raw():
    torch.manual_seed(0)
    mlp = GarmentNeRF.from_config(ModelConfig.paper())
    assert mlp.input_dim == 20
    assert sum(isinstance(m, torch.nn.Linear) for m in mlp.trunk) == 6
    n = 50
    args = (torch.randn(n, 3), torch.randn(n), torch.randn(n, 8), torch.randn(n, 8))
    sigma, zeta = mlp(*args)
    assert sigma.shape == (n,) and zeta.shape == (n, 128)
    # A strongly negative raw head must give a small positive density, not a negative alpha.
    with torch.no_grad():
        mlp.density_head.bias.fill_(-50.0)
    sigma, _ = mlp(*args)
    assert (sigma >= 0).all() and sigma.max() < 1e-10
    with torch.no_grad():
        mlp.density_head.weight.zero_()
        mlp.density_head.bias.zero_()
    sigma, _ = mlp(*args)
    torch.testing.assert_close(sigma, F.softplus(torch.full((n,), -1.0)))


def test_mlp_under_bfloat16_autocast_keeps_input_and_density_layers_in_float32():
    """Under bfloat16 autocast (training's and rendering's ``precision``) only the hidden layers and
    the appearance head run in bfloat16; the reference is the same network in float32."""
    torch.manual_seed(0)
    mlp = GarmentNeRF.from_config(ModelConfig.cpu_small())
    n = 2048
    args = [torch.rand(n, 3) - 0.5, torch.rand(n) * 0.3, torch.randn(n, 8), torch.randn(n, 8)]
    # two points 1.5 mm apart at 0.7 m: one and the same bfloat16 number, distinct in float32
    args[0][:2] = torch.tensor([[0.6995, 0.1, 0.2], [0.7010, 0.1, 0.2]])
    assert torch.equal(*args[0][:2, 0].to(torch.bfloat16))
    outputs = {}
    hooks = [module.register_forward_hook(lambda m, i, o, name=name: outputs.__setitem__(name, o))
             for name, module in mlp.named_modules() if isinstance(module, torch.nn.Linear)]
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        sigma, zeta = mlp(*args)
    first, density = outputs["trunk.0"], outputs["density_head"]
    assert first.dtype == density.dtype == sigma.dtype == torch.float32
    assert outputs["trunk.2"].dtype == outputs["appearance_head"].dtype == zeta.dtype == torch.bfloat16
    for hook in hooks:
        hook.remove()
    with torch.no_grad():
        ref_sigma, ref_zeta = mlp(*args)
    # the input layer is the float32 one to the last bit (its ReLU works in place), so the two
    # close points stay apart
    inputs = torch.cat([args[0], args[1][:, None], args[2], args[3]], 1)
    with torch.no_grad():
        torch.testing.assert_close(first, mlp.trunk[0](inputs).clamp_min(0), rtol=0, atol=0)
    assert not torch.equal(first[0], first[1])
    # the rest within bfloat16's rounding (8 bits of mantissa, three layers)
    torch.testing.assert_close(sigma, ref_sigma, rtol=0.03, atol=0.01 * float(ref_sigma.abs().max()))
    torch.testing.assert_close(zeta.float(), ref_zeta, rtol=0.05, atol=0.02 * float(ref_zeta.abs().max()))


def test_density_activations():
    raw = torch.tensor([-100.0, 0.0, 3.0, 40.0], requires_grad=True)
    assert (density_activation(raw) >= 0).all()
    torch.testing.assert_close(density_activation(raw, "trunc_exp", 0.0), torch.exp(raw))
    (g,) = torch.autograd.grad(trunc_exp(raw).sum(), raw)
    assert torch.isfinite(g).all() and g[-1].item() == pytest.approx(torch.exp(torch.tensor(15.0)).item())
    with pytest.raises(ValueError):
        density_activation(raw, "relu")


def test_mlp_ablations():
    cfg = ModelConfig.paper().updated({"encoder.detail_feature": False})
    mlp = GarmentNeRF.from_config(cfg)
    assert mlp.input_dim == cfg.mlp_input_dim == 3 + 1 + DYNAMIC_FEATURE_DIM
    n = 4
    sigma, zeta = mlp(torch.randn(n, 3), torch.randn(n), None, torch.randn(n, 8))
    assert sigma.shape == (n,)
    with pytest.raises(ValueError, match="without the detail"):
        mlp(torch.randn(n, 3), torch.randn(n), torch.randn(n, 8), torch.randn(n, 8))
    with pytest.raises(ValueError, match="needs the dynamic"):
        mlp(torch.randn(n, 3), torch.randn(n), None, None)


# ---------------------------------------------------------------------------------------- config
def test_config_round_trip_and_unknown_keys():
    for cfg in (ModelConfig.paper(), ModelConfig.cpu_small(), ModelConfig.tiny()):
        data = json.loads(json.dumps(cfg.to_dict()))
        assert ModelConfig.from_dict(data) == cfg
    with pytest.raises(ValueError, match="sampler.samples_per_rays"):
        ModelConfig.from_dict({**ModelConfig.paper().to_dict(), "sampler": {"samples_per_rays": 32}})
    with pytest.raises(ValueError, match="unknown model setting 'samplers.samples_per_ray'"):
        ModelConfig.paper().updated({"samplers.samples_per_ray": 32})
    # Missing keys take the defaults; a component may be given whole or by dotted names.
    assert ModelConfig.from_dict({"nerf": {"mlp_width": 64}}).nerf.mlp_width == 64
    assert ModelConfig.paper().updated({"nerf": {"mlp_width": 64}}) == ModelConfig.paper().updated({"nerf.mlp_width": 64})


def test_a_flat_config_of_an_older_run_converts_or_is_refused_naming_the_setting():
    flat = {"mlp_width": 128, "w_segmentation": 0.5, "encoder_width_scale": 0.5, "generator_width_scale": 0.5,
            "decoder_upsample_steps": 2, "field": "paper", "bbox_padding": 0.05, "w_occupancy": 0.1,
            "trained_parameters": ["frame_codes."]}
    cfg = ModelConfig.from_dict(flat)
    assert (cfg.nerf.mlp_width, cfg.loss.segmentation, cfg.encoder.width_scale) == (128, 0.5, 0.5)
    assert cfg.schedule.trained_parameters == ("frame_codes.",)
    assert convert_flat_config(flat)[1] == ["w_occupancy"]  # training-only, another value than today's
    for key, value in (("field", "uvh"), ("importance_samples", 6), ("generator_width_scale", 1.0),
                       ("decoder_upsample_steps", 3), ("bbox_padding", 0.1)):
        with pytest.raises(ValueError, match=key):
            ModelConfig.from_dict({**flat, key: value})
    with pytest.raises(ValueError, match="unknown model config key 'mlp_widht'"):
        ModelConfig.from_dict({"mlp_widht": 3, "lr": 1e-3})


def test_config_paper_numbers_and_validation():
    cfg = ModelConfig.paper()
    assert (cfg.mlp_input_dim, cfg.encoder.in_channels, cfg.decoder.out_channels) == (20, 9, 12)
    assert (cfg.loss.image, cfg.loss.mask, cfg.loss.perceptual, cfg.loss.sparsity, cfg.loss.offset, cfg.loss.palette) == (
        1.0, 1.0, 0.1, 2e-4, 0.03, 1e-3)
    assert (cfg.schedule.lr, cfg.schedule.lr_final, GRAD_CLIP_VALUE, cfg.sampler.samples_per_ray, BBOX_PADDING) == (
        5e-4, 5e-5, 40.0, 64, 0.05)
    assert cfg.decoder.upsample_steps == 2 and DETAIL_FEATURE_DIM == 8
    assert LossConfig.weight_names() == ("image", "mask", "perceptual", "sparsity", "offset", "palette", "opacity",
                                         "segmentation")
    with pytest.raises(ValueError, match="image_resolution"):
        cfg.updated({"decoder.feature_image_resolution": 100})
    with pytest.raises(ValueError, match="image_resolution"):
        cfg.updated({"decoder.feature_image_resolution": 192})  # 512 / 192 is not a power of 2
    with pytest.raises(ValueError, match="density_activation"):
        cfg.updated({"nerf.density_activation": "raw"})
    with pytest.raises(ValueError, match="schedule.lr_final"):
        cfg.updated({"schedule.lr_final": 1.0})
    with pytest.raises(ValueError, match="nerf.mlp_width must be positive"):
        cfg.updated({"nerf.mlp_width": 0})


# ---------------------------------------------------------------------------------------- features
def test_detail_feature_lookup_and_selection():
    fmap = torch.arange(2 * 3 * 4, dtype=torch.float32).view(2, 3, 4)
    pixels = torch.tensor([[0.0, 0.0], [3.0, 2.0], [1.0, 1.0]])  # pixel centres (u = column, v = row)
    out = sample_image_features(fmap, pixels)
    torch.testing.assert_close(out, fmap[:, [0, 2, 1], [0, 3, 1]].T)
    front, back = torch.ones(3, 2), -torch.ones(3, 2)
    vis = torch.tensor([True, False, True])
    torch.testing.assert_close(select_detail_features(front, back, vis), torch.tensor([[1.0, 1], [-1, -1], [1, 1]]))


# ---------------------------------------------------------------------------------------- end to end
def tiny_config() -> ModelConfig:
    return ModelConfig().updated({
        "encoder.info_map_resolution": 32, "encoder.reference_resolution": 32, "encoder.width_scale": 0.25,
        "decoder.image_resolution": 32, "decoder.feature_image_resolution": 8, "nerf.appearance_dim": 16,
        "nerf.mlp_depth": 3, "nerf.mlp_width": 32, "sampler.samples_per_ray": 8, "decoder.width": 16,
        "decoder.min_width": 8, "decoder.extra_layers": 1})


def test_gradients_reach_every_parameter_end_to_end():
    torch.manual_seed(0)
    cfg = tiny_config()
    E = DynamicFeatureEncoder.from_config(cfg)
    G_en = DetailEncoder.from_config(cfg)
    mlp = GarmentNeRF.from_config(cfg)
    M_D = PaletteDecoder.from_config(cfg)
    palette = Palette(torch.tensor([[0.7, 0.2, 0.2], [0.5, 0.45, 0.4]]))
    sampler = BoxStratifiedSampler.from_config(cfg)

    # Rays of an 8 x 8 feature image at a camera looking at a 1 x 0.6 x 1.8 m "body" box.
    r = cfg.decoder.feature_image_resolution
    cam = orbit_camera(20.0, 10.0, 3.0, width=r, height=r)
    origins, dirs = (x.reshape(-1, 3) for x in camera_rays(cam))
    aabb = torch.tensor([[-0.5, -0.3, 0.0], [0.5, 0.3, 1.8]])
    # Dense (R, S) samples: the box sampler's own formulas before it packs them.
    t_near, t_far, hit = ray_aabb_intersect(origins, dirs, sampler.padded_box(aabb))
    t, t_starts, t_ends = stratified_intervals(t_near, t_far, sampler.num_samples, training=True)
    assert hit.float().mean() > 0.3
    x = (origins.unsqueeze(1) + t.unsqueeze(-1) * dirs.unsqueeze(1)).reshape(-1, 3)
    N = x.shape[0]

    # Stand-ins for the geometry stage: b_o, h, the UV of b_t and its pixel in each reference view.
    b_o = x + 0.01 * torch.randn(N, 3)
    h = torch.randn(N) * 0.05
    uv = torch.rand(N, 2)
    ref_pixels = torch.rand(2, N, 2) * (cfg.encoder.reference_resolution - 1)
    front_visible = torch.rand(N) > 0.5

    F_s = E(torch.randn(1, cfg.encoder.in_channels, cfg.encoder.info_map_resolution, cfg.encoder.info_map_resolution))
    f_s = F.grid_sample(F_s, (2 * uv - 1).view(1, 1, N, 2), align_corners=False)[0, :, 0].T
    F_d = G_en(torch.rand(2, 3, cfg.encoder.reference_resolution, cfg.encoder.reference_resolution))
    f_front, f_back = (sample_image_features(F_d[i], ref_pixels[i]) for i in range(2))
    f_d = select_detail_features(f_front, f_back, front_visible)

    sigma, zeta = mlp(b_o, h, f_d, f_s)
    R, S = t_starts.shape
    weights = vr.render_weights_from_density(sigma.view(R, S), t_ends - t_starts)
    feature_image = vr.composite(weights, zeta.view(R, S, -1)).T.reshape(1, -1, r, r)
    maps = M_D(feature_image)
    image = maps.compose(palette(), BACKGROUND)
    assert image.shape == (1, 3, cfg.decoder.image_resolution, cfg.decoder.image_resolution)

    target = torch.rand_like(image)
    target_mask = torch.rand(1, cfg.decoder.image_resolution, cfg.decoder.image_resolution) > 0.5
    perceptual = lambda a, b: F.l1_loss(F.avg_pool2d(a, 4), F.avg_pool2d(b, 4))  # noqa: E731
    losses = garment_losses(image, target, maps, target_mask, palette.colors, palette.initial, cfg.loss, perceptual)
    assert set(losses) == {"image", "mask", "perceptual", "sparsity", "offset", "palette", "total"}
    assert all(torch.isfinite(v) for v in losses.values())
    losses["total"].backward()

    for name, module in (("E", E), ("G_en", G_en), ("MLP", mlp), ("M_D", M_D), ("palette", palette)):
        for pname, p in module.named_parameters():
            assert p.grad is not None, f"{name}.{pname} got no gradient"
            assert torch.isfinite(p.grad).all(), f"{name}.{pname} gradient not finite"
            assert p.grad.abs().sum() > 0, f"{name}.{pname} gradient is zero"


def test_losses_without_perceptual_and_weighting():
    cfg = tiny_config()
    dec = PaletteDecoder.from_config(cfg)
    maps = dec(torch.randn(1, cfg.nerf.appearance_dim, 2, 2))
    p = torch.tensor([[0.5, 0.5, 0.5], [0.2, 0.2, 0.2]])
    image = maps.compose(p)
    out = garment_losses(image, image.detach(), maps, torch.ones(1, 8, 8), p + 0.1, p, cfg.loss)
    assert "perceptual" not in out
    assert out["image"].item() == 0.0
    assert out["palette"].item() == pytest.approx(6 * 0.01)
    expected = sum(getattr(cfg.loss, k) * out[k] for k in ("image", "mask", "sparsity", "offset", "palette"))
    torch.testing.assert_close(out["total"], expected)
    # the image term, by hand: a constant 0.1 off everywhere, weighted
    off = garment_losses(image, image.detach() + 0.1, maps, torch.ones(1, 8, 8), p, p, cfg.loss)
    assert off["image"].item() == pytest.approx(0.1, abs=1e-6)
    torch.testing.assert_close(off["total"] - out["total"], torch.tensor(cfg.loss.image * 0.1 - cfg.loss.palette * 6 * 0.01),
                               atol=1e-5, rtol=0)


@pytest.mark.parametrize("factor", [1, 2, 4])
def test_perceptual_term_sees_the_images_area_averaged_by_perceptual_downsample(factor):
    """``perceptual_downsample`` hands the perceptual network both images area-averaged by the factor:
    what OpenCV's INTER_AREA resize gives (an independent reference); factor 1 hands them over as they are."""
    cv2 = pytest.importorskip("cv2")
    cfg = tiny_config().updated({"loss.perceptual_downsample": factor})
    n = cfg.decoder.image_resolution
    maps = PaletteDecoder.from_config(cfg)(torch.randn(1, cfg.nerf.appearance_dim, cfg.decoder.feature_image_resolution,
                                                       cfg.decoder.feature_image_resolution))
    gen = torch.Generator().manual_seed(3)
    image = torch.rand(1, 3, n, n, generator=gen, dtype=torch.float64)
    target = torch.rand(1, 3, n, n, generator=gen, dtype=torch.float64)
    seen = []
    perceptual = lambda a, b: seen.append((a, b)) or (a - b).abs().mean()  # noqa: E731
    p = torch.tensor([[0.5, 0.5, 0.5], [0.2, 0.2, 0.2]])
    garment_losses(image, target, maps, torch.ones(1, n, n), p, p, cfg.loss, perceptual)
    (a, b), = seen
    for got, full in ((a, image), (b, target)):
        hwc = full[0].permute(1, 2, 0).numpy()
        ref = cv2.resize(hwc, (n // factor, n // factor), interpolation=cv2.INTER_AREA)
        torch.testing.assert_close(got[0].permute(1, 2, 0), torch.from_numpy(ref), rtol=0, atol=1e-12)


def test_perceptual_downsample_must_divide_the_image():
    with pytest.raises(ValueError, match="perceptual_downsample"):
        ModelConfig.cpu_small().updated({"loss.perceptual_downsample": 3})
    with pytest.raises(ValueError, match="perceptual_downsample"):
        ModelConfig.cpu_small().updated({"loss.perceptual_downsample": 0})


def test_generator_losses_are_the_weighted_l1_and_perceptual_terms():
    """G_img's pre-training loss: image * mean |pred - target| + perceptual * perceptual."""
    from garmentnerf.model.losses import generator_losses

    pred = torch.tensor([[[[0.0, 1.0], [0.5, 0.25]]]]).expand(2, 3, 2, 2)
    target = torch.zeros(2, 3, 2, 2)
    cfg = LossConfig(image=2.0, perceptual=0.5)
    plain = generator_losses(pred, target, cfg)
    assert set(plain) == {"image", "total"}
    assert float(plain["image"]) == pytest.approx(0.4375)  # (0 + 1 + 0.5 + 0.25) / 4
    assert float(plain["total"]) == pytest.approx(0.875)
    with_perceptual = generator_losses(pred, target, cfg, perceptual=lambda a, b: torch.tensor(3.0))
    assert float(with_perceptual["perceptual"]) == 3.0
    assert float(with_perceptual["total"]) == pytest.approx(0.875 + 1.5)
