"""Metrics: PSNR, SSIM (against scikit-image), tOF (against direct OpenCV calls), LPIPS and
shift-tolerant LPIPS (against the reference packages, imported with their unused torchvision /
IPython / torchsummary imports stubbed out)."""

from __future__ import annotations

import json
import math
import sys
import types
from unittest import mock

import numpy as np
import pytest
import torch
import torch.nn as nn
import torch.nn.functional as F

from garmentnerf.eval import metrics as M
from garmentnerf.model import perceptual as P

cv2 = pytest.importorskip("cv2")


def _structured_image(h: int, w: int, seed: int) -> np.ndarray:
    """A render-like image: black background, a shaded disc with stripes, a hard-edged box."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w] / max(h, w)
    img = np.zeros((h, w, 3))
    disc = (yy - 0.5) ** 2 + (xx - 0.45) ** 2 < 0.1
    shade = 0.5 + 0.4 * np.sin(25 * xx + 5 * yy)
    img[disc] = np.stack([shade, 0.8 * shade, 0.3 + 0.2 * yy], -1)[disc]
    img[int(0.1 * h):int(0.3 * h), int(0.6 * w):int(0.9 * w)] = rng.random(3)
    return img


def _stub_modules(alexnet_features: nn.Module | None = None) -> dict[str, types.ModuleType]:
    """Fake torchvision / IPython / torchsummary: the reference packages import them at top level
    but their shift-tolerant path (and LPIPS with a given trunk) never uses them."""
    tv = types.ModuleType("torchvision")
    tvm = types.ModuleType("torchvision.models")
    if alexnet_features is not None:
        tvm.alexnet = lambda pretrained=False, **kw: types.SimpleNamespace(features=alexnet_features)
    tv.models = tvm
    ipy = types.ModuleType("IPython")
    ipy.embed = lambda *a, **k: None
    tsum = types.ModuleType("torchsummary")
    tsum.summary = lambda *a, **k: None
    return {"torchvision": tv, "torchvision.models": tvm, "IPython": ipy, "torchsummary": tsum}


# ---------------------------------------------------------------------------------------------
# PSNR
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("e", [0.1, 0.01, 1e-3])
def test_psnr_constant_error_is_analytic(e):
    target = 0.2 + 0.6 * np.random.default_rng(0).random((32, 40, 3))
    assert M.psnr(target + e, target) == pytest.approx(-10 * math.log10(e * e), abs=1e-9)
    assert M.psnr(torch.from_numpy(target - e), torch.from_numpy(target)) == pytest.approx(-10 * math.log10(e * e))


def test_psnr_identical_is_inf_and_means_cap_it():
    img = np.random.default_rng(1).random((16, 16, 3))
    assert M.psnr(img, img) == float("inf")
    assert M.mean_psnr([float("inf"), 20.0]) == pytest.approx((M.PSNR_CAP_DB + 20.0) / 2)
    assert math.isnan(M.mean_psnr([]))


def test_psnr_uint8_and_shape_errors():
    a = np.full((8, 8, 3), 100, np.uint8)
    b = np.full((8, 8, 3), 110, np.uint8)
    assert M.psnr(a, b) == pytest.approx(-10 * math.log10((10 / 255) ** 2))
    with pytest.raises(ValueError):
        M.psnr(np.zeros((8, 8, 3)), np.zeros((8, 9, 3)))
    with pytest.raises(ValueError):
        M.psnr(np.full((8, 8, 3), np.nan), np.zeros((8, 8, 3)))


def test_composite_premultiplied():
    rgb = np.zeros((4, 4, 3))
    rgb[0, 0] = 0.25
    alpha = np.zeros((4, 4))
    alpha[0, 0] = 0.5
    out = M.composite_premultiplied(rgb, alpha, (1.0, 1.0, 1.0))
    assert out[0, 0] == pytest.approx([0.75] * 3)
    assert out[1, 1] == pytest.approx([1.0] * 3)


# ---------------------------------------------------------------------------------------------
# SSIM
# ---------------------------------------------------------------------------------------------

def _skimage_ssim(a, b):
    skm = pytest.importorskip("skimage.metrics")
    return skm.structural_similarity(a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                     data_range=1.0, channel_axis=-1)


@pytest.mark.parametrize("kind", ["random", "structured", "structured_shifted"])
def test_ssim_matches_scikit_image(kind):
    rng = np.random.default_rng(2)
    if kind == "random":
        a = rng.random((48, 57, 3))
        b = np.clip(a + 0.15 * rng.standard_normal(a.shape), 0, 1)
    else:
        a = _structured_image(64, 72, 3)
        b = np.clip(a + 0.03 * rng.standard_normal(a.shape), 0, 1) if kind == "structured" else np.roll(a, 2, 1)
    ours = M.ssim(a, b)
    assert ours == pytest.approx(_skimage_ssim(a, b), abs=1e-6)
    assert ours < 0.999


def test_ssim_identical_black_is_one_and_data_range_is_one():
    black = np.zeros((32, 32, 3))
    assert M.ssim(black, black) == pytest.approx(1.0, abs=1e-12)  # kornia's default eps would give 0.99998889
    a = _structured_image(40, 40, 4)
    b = np.clip(a * 0.8, 0, 1)
    # The authors' implicit data range 2 would give a higher value; ours is the range-1 number.
    skm = pytest.importorskip("skimage.metrics")
    range2 = skm.structural_similarity(a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                       data_range=2.0, channel_axis=-1)
    assert M.ssim(a, b) < range2
    with pytest.raises(ValueError):
        M.ssim(np.zeros((8, 8, 3)), np.zeros((8, 8, 3)))


# ---------------------------------------------------------------------------------------------
# tOF
# ---------------------------------------------------------------------------------------------

def _moving_sequence(n: int, size: int = 96, accelerate: bool = True) -> list[np.ndarray]:
    """A smooth texture translating right; shifts 0, 1, 3, 6, ... (accelerating) or 0, 2, 4, ..."""
    rng = np.random.default_rng(5)
    tex = cv2.GaussianBlur(rng.random((size, 2 * size, 3)), (0, 0), 2.0)
    tex = (tex - tex.min()) / (tex.max() - tex.min())
    frames = []
    for i in range(n):
        s = i * (i + 1) // 2 if accelerate else 2 * i
        frames.append(np.roll(tex, s, axis=1)[:, :size].copy())
    return frames


def test_tof_crop_is_tecogans():
    assert M.tof_crop(512, 512) == (16, 16, 480, 480)
    assert M.tof_crop(256, 320) == (16, 16, 224, 288)
    assert M.tof_crop(96, 96) == (16, 16, 64, 64)
    with pytest.raises(ValueError):
        M.tof_crop(40, 64)


def test_tof_identical_sequences_is_zero():
    seq = _moving_sequence(7)
    r = M.temporal_flow_error(seq, seq)
    assert r.pairs == [(2, 3), (3, 4)]
    assert r.values == [0.0, 0.0] and r.mean == 0.0 and r.reason is None


def test_tof_time_shifted_copy_is_positive():
    seq = _moving_sequence(8)
    r = M.temporal_flow_error(seq[1:], seq[:-1])  # output one frame ahead: each step 1 px faster
    assert len(r.values) == 7 - 5
    assert all(v > 0.3 for v in r.values)


def test_tof_matches_direct_opencv():
    gt = _moving_sequence(7)
    out = [np.clip(f + 0.05 * np.sin(3 * i + np.arange(96) / 7.0)[None, :, None], 0, 1) for i, f in enumerate(gt)]
    r = M.temporal_flow_error(out, gt)

    def grey(f):
        return cv2.cvtColor(np.rint(np.clip(f, 0, 1) * 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)

    expected = []
    for i in (3, 4):  # 7 frames: frames 0, 1 and 5, 6 skipped; pairs (2, 3), (3, 4)
        fg = cv2.calcOpticalFlowFarneback(grey(gt[i - 1]), grey(gt[i]), None, 0.5, 3, 15, 3, 5, 1.2, 0)
        fo = cv2.calcOpticalFlowFarneback(grey(out[i - 1]), grey(out[i]), None, 0.5, 3, 15, 3, 5, 1.2, 0)
        d = (fg - fo)[16:80, 16:80]
        expected.append(float(np.mean(np.sqrt(np.sum(d.astype(np.float64) ** 2, axis=-1)))))
    assert r.pairs == [(2, 3), (3, 4)]
    np.testing.assert_allclose(r.values, expected, rtol=1e-8)  # ours subtracts in float64
    assert r.mean == pytest.approx(np.mean(expected))
    assert r.mean > 0


def test_tof_short_sequences():
    seq = _moving_sequence(5)
    r = M.temporal_flow_error(seq, seq)
    assert math.isnan(r.mean) and r.values == [] and "at least 6 frames" in r.reason
    r0 = M.temporal_flow_error(seq[:2], seq[:2], skip_ends=0)
    assert r0.pairs == [(0, 1)] and r0.mean == 0.0
    with pytest.raises(ValueError):
        M.temporal_flow_error(seq, seq[:4])


# ---------------------------------------------------------------------------------------------
# Shift-tolerant LPIPS
# ---------------------------------------------------------------------------------------------

def _needs_stlpips(variant="alex"):
    ok, reason = P.stlpips_available(variant)
    if not ok:
        pytest.skip(reason)


@pytest.fixture(scope="module")
def st_alex():
    _needs_stlpips()
    return P.STLPIPS("alex")


def test_stlpips_identical_is_zero_and_different_is_positive(st_alex):
    x = torch.from_numpy(_structured_image(64, 64, 6)).permute(2, 0, 1)[None].float()
    y = (x + 0.1 * torch.randn_like(x)).clamp(0, 1)
    with torch.no_grad():
        assert float(st_alex(x, x)[0]) == pytest.approx(0.0, abs=1e-7)
        assert float(st_alex(x, y)[0]) > 1e-3
    assert st_alex.metric_name == "stlpips_alex"
    assert st_alex.distance(_structured_image(64, 64, 6), _structured_image(64, 64, 6)) == pytest.approx(0, abs=1e-7)


def test_stlpips_is_differentiable(st_alex):
    target = torch.from_numpy(_structured_image(64, 64, 7)).permute(2, 0, 1)[None].float()
    pred = torch.roll(target, 3, dims=-1).clone().requires_grad_(True)
    loss = P.STLPIPS("alex", reduction="mean")(pred, target)
    assert loss.ndim == 0
    loss.backward()
    assert torch.isfinite(pred.grad).all() and pred.grad.abs().max() > 0
    assert all(not p.requires_grad for p in st_alex.parameters())


def test_stlpips_input_range(st_alex):
    x = torch.rand(2, 3, 64, 64)
    y = torch.rand(2, 3, 64, 64)
    signed = P.STLPIPS("alex", input_range=(-1, 1))
    with torch.no_grad():
        torch.testing.assert_close(st_alex(x, y), signed(2 * x - 1, 2 * y - 1), rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("H, W, k, padding", [(40, 37, 11, 2), (41, 41, 11, 2), (64, 71, 11, 2), (30, 24, 5, 2),
                                             (60, 61, 3, 1), (12, 13, 11, 2)])
def test_conv_blurpool_is_the_convolution_then_the_blurpool(H, W, k, padding):
    # Both parities of the convolution's output (a last row/column that reads a reflected input
    # or not), kernels of 3 to 11: values and input gradients against the two layers run plainly.
    g = torch.Generator().manual_seed(H * W + k)
    x = torch.rand(2, 3, H, W, generator=g, dtype=torch.float64, requires_grad=True)
    weight = torch.randn(5, 3, k, k, generator=g, dtype=torch.float64)
    bias = torch.randn(5, generator=g, dtype=torch.float64)
    blur = P.BlurPool(5).double()
    expected = blur(F.conv2d(x, weight, bias, padding=padding))
    got = P.conv_blurpool(x, weight, bias, padding, blur.filt[0, 0], blur.pad)
    assert got.shape == expected.shape
    torch.testing.assert_close(got, expected, rtol=0, atol=1e-12)
    upstream = torch.randn(expected.shape, generator=g, dtype=torch.float64)
    (want,) = torch.autograd.grad(expected, x, upstream)
    (have,) = torch.autograd.grad(got, x, upstream)
    torch.testing.assert_close(have, want, rtol=0, atol=1e-12)


def test_stlpips_first_slice_fused_equals_its_layers_and_keeps_channels_last(st_alex):
    x = torch.rand(1, 3, 96, 90).contiguous(memory_format=torch.channels_last)
    s1 = st_alex.net.slice1
    with torch.no_grad():
        fused, plain = s1(x), s1.reference(x)
    torch.testing.assert_close(fused, plain, rtol=1e-5, atol=1e-5)
    assert fused.is_contiguous(memory_format=torch.channels_last)
    assert list(st_alex.state_dict())[:5] == ["scaling_layer.shift", "scaling_layer.scale", "net.slice1.0.weight",
                                              "net.slice1.0.bias", "net.slice1.1.filt"]


# The package's VGG builds (and randomly initialises) a 100M-parameter classifier: ~5 s.
@pytest.mark.parametrize("variant", ["alex", pytest.param("vgg", marks=pytest.mark.slow)])
def test_stlpips_matches_package(variant):
    _needs_stlpips(variant)
    mine = P.STLPIPS(variant)
    with mock.patch.dict(sys.modules, _stub_modules()):  # restores sys.modules on exit
        from stlpips_pytorch import stlpips as ref_module
        ref = ref_module.LPIPS(net=variant, variant="shift_tolerant", verbose=False)
    g = torch.Generator().manual_seed(8)
    a = torch.rand(2, 3, 64, 71, generator=g)
    b = (a + 0.2 * torch.randn(a.shape, generator=g)).clamp(0, 1)
    a[1] = torch.from_numpy(_structured_image(64, 71, 9)).permute(2, 0, 1).float()
    with torch.no_grad():
        expected = ref(a * 2 - 1, b * 2 - 1).flatten()
        got = mine(a, b)
    torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-7)


# ---------------------------------------------------------------------------------------------
# LPIPS
# ---------------------------------------------------------------------------------------------

def _torchvision_alexnet_features() -> nn.Sequential:
    """torchvision's AlexNet ``features`` layout, written out independently of the module."""
    return nn.Sequential(
        nn.Conv2d(3, 64, 11, 4, 2), nn.ReLU(), nn.MaxPool2d(3, 2),
        nn.Conv2d(64, 192, 5, padding=2), nn.ReLU(), nn.MaxPool2d(3, 2),
        nn.Conv2d(192, 384, 3, padding=1), nn.ReLU(),
        nn.Conv2d(384, 256, 3, padding=1), nn.ReLU(),
        nn.Conv2d(256, 256, 3, padding=1), nn.ReLU(), nn.MaxPool2d(3, 2))


@pytest.fixture()
def fake_lpips_files(tmp_path):
    """A randomly initialised torchvision-style AlexNet file (+ classifier entries to ignore) and
    random non-negative linear layers: enough to check shapes and plumbing, not values."""
    torch.manual_seed(10)
    features = _torchvision_alexnet_features()
    state = {f"features.{k}": v for k, v in features.state_dict().items()}
    state["classifier.1.weight"] = torch.zeros(4, 4)
    backbone = tmp_path / "alexnet-fake.pth"
    torch.save(state, backbone)
    lin = tmp_path / "lin.npz"
    np.savez(lin, **{f"lin{k}.model.1.weight": np.random.default_rng(k).random((1, c, 1, 1)).astype(np.float32)
                     for k, c in enumerate((64, 192, 384, 256, 256))})
    return backbone, lin, features


def test_lpips_unavailable_without_backbone(monkeypatch, tmp_path):
    monkeypatch.delenv(P.LPIPS_BACKBONE_ENV, raising=False)
    ok, reason = P.lpips_available()
    assert not ok and "AlexNet" in reason and P.LPIPS_BACKBONE_ENV in reason
    with pytest.raises(FileNotFoundError, match="AlexNet"):
        P.LPIPS()
    ok, reason = P.lpips_available(tmp_path / "missing.pth")
    assert not ok and "not found" in reason
    bad = tmp_path / "bad.pth"
    torch.save({"features.0.weight": torch.zeros(1)}, bad)
    ok, reason = P.lpips_available(bad, lin_path=bad)
    assert not ok and "features.0" in reason


def test_lpips_with_fake_backbone_shapes(fake_lpips_files, monkeypatch):
    backbone, lin, _ = fake_lpips_files
    assert P.lpips_available(backbone, lin)[0]
    model = P.LPIPS(backbone, lin)
    x, y = torch.rand(3, 3, 64, 80), torch.rand(3, 3, 64, 80)
    with torch.no_grad():
        d = model(x, y)
        assert d.shape == (3,) and torch.all(d > 0)
        assert torch.all(model(x, x).abs() < 1e-7)
    assert model.metric_name == "lpips_alex"
    monkeypatch.setenv(P.LPIPS_BACKBONE_ENV, str(backbone))  # the environment variable is the default
    assert P.LPIPS(lin_path=lin).backbone_path == backbone


def test_lpips_head_matches_package(fake_lpips_files):
    """Same random trunk in both: checks scaling, normalisation, linear layers, averaging."""
    package_lin = P._package_file("lpips", "weights/v0.1/alex.pth")
    if package_lin is None:
        pytest.skip("the lpips package is not installed")
    backbone, _, features = fake_lpips_files
    mine = P.LPIPS(backbone, package_lin)
    with mock.patch.dict(sys.modules, _stub_modules(features)):
        import lpips
        ref = lpips.LPIPS(net="alex", version="0.1", verbose=False)
    g = torch.Generator().manual_seed(11)
    a = torch.rand(2, 3, 64, 70, generator=g)
    b = (a + 0.2 * torch.randn(a.shape, generator=g)).clamp(0, 1)
    with torch.no_grad():
        torch.testing.assert_close(mine(a, b), ref(a, b, normalize=True).flatten(), rtol=1e-5, atol=1e-7)


# ---------------------------------------------------------------------------------------------
# Summary
# ---------------------------------------------------------------------------------------------

def test_metric_summary_json_roundtrip():
    s = M.MetricSummary(meta={"background": [0, 0, 0]})
    s.add_frame(0, psnr=float("inf"), ssim=1.0)
    s.add_frame(1, psnr=30.0, ssim=0.5)
    s.mark_unavailable("lpips_alex", "no backbone")
    s.tof = M.TOFResult([(2, 3)], [0.5], 0.5, None, (16, 16, 480, 480))
    assert s.means() == {"psnr": pytest.approx(65.0), "ssim": 0.75, "tof": 0.5}
    text = s.to_json()
    d = json.loads(text)  # strict JSON: no Infinity literal
    assert d["frames"][0]["psnr"] == "inf" and d["unavailable"] == {"lpips_alex": "no backbone"}
    back = M.MetricSummary.from_dict(d)
    assert back.frames[0]["psnr"] == float("inf") and back.means() == s.means()
    assert back.tof.pairs == [(2, 3)]


def test_evaluate_sequence(st_alex):
    gt = _moving_sequence(6, size=64)
    pred = [np.clip(f + 0.02, 0, 1) for f in gt]
    s = M.evaluate_sequence(pred, gt, frame_indices=range(10, 16), perceptual=[st_alex],
                            unavailable={"lpips_alex": P.lpips_available(None)[1]})
    assert [f["frame"] for f in s.frames] == list(range(10, 16))
    assert set(s.means()) == {"psnr", "ssim", "stlpips_alex", "tof"}
    assert s.tof.pairs == [(12, 13)]
    assert "lpips_alex" in s.unavailable
    json.loads(s.to_json())
    short = M.evaluate_sequence(pred[:3], gt[:3])
    assert "tof" in short.unavailable and "tof" not in short.means()


# ---- foreground figures ----------------------------------------------------------------------------
def test_masked_psnr_matches_skimage_on_the_region():
    from skimage.metrics import peak_signal_noise_ratio

    rng = np.random.default_rng(3)
    gt = rng.random((40, 50, 3))
    pred = np.clip(gt + rng.normal(0, 0.05, gt.shape), 0, 1)
    pred[:, :20] = gt[:, :20]  # exact outside the region: full-frame PSNR would be higher
    region = np.zeros((40, 50), bool)
    region[5:35, 18:45] = True
    ref = peak_signal_noise_ratio(gt[region], pred[region], data_range=1.0)
    assert M.masked_psnr(pred, gt, region) == pytest.approx(ref, abs=1e-9)
    assert M.masked_psnr(pred, gt, region) < M.psnr(pred, gt)
    assert M.masked_psnr(pred, gt, np.zeros((40, 50), bool)) is None
    assert M.masked_psnr(gt, gt, region) == math.inf
    with pytest.raises(ValueError, match="region"):
        M.masked_psnr(pred, gt, region[:10])


def test_silhouette_iou_of_overlapping_rectangles():
    a = np.zeros((20, 20), bool)
    b = np.zeros((20, 20), bool)
    a[0:10, 0:10] = True
    b[5:15, 0:10] = True  # 50 px shared, 150 px in the union
    assert M.silhouette_iou(a, b) == pytest.approx(1 / 3)
    assert M.silhouette_iou(a, a) == 1.0
    assert M.silhouette_iou(np.zeros_like(a), np.zeros_like(a)) == 1.0
    assert M.silhouette_iou(a, ~a) == 0.0


def test_gradient_energy_against_scipy_sobel_and_a_ramp():
    from scipy import ndimage

    img = _structured_image(48, 64, seed=2)
    luma = img @ np.array([0.299, 0.587, 0.114])
    gx, gy = ndimage.sobel(luma, axis=1), ndimage.sobel(luma, axis=0)
    inner = np.zeros(luma.shape, bool)
    inner[1:-1, 1:-1] = True  # the two libraries pad the border differently
    assert M.gradient_energy(img, inner) == pytest.approx(float(np.sum((gx ** 2 + gy ** 2)[inner])), rel=1e-9)
    # a ramp of slope s per pixel: the 3x3 Sobel gives 8 s everywhere inside
    ramp = np.repeat((0.2 + 0.01 * np.arange(30))[None, :, None], 20, axis=0).repeat(3, axis=2)
    inner = np.zeros((20, 30), bool)
    inner[1:-1, 1:-1] = True
    assert M.gradient_energy(ramp, inner) == pytest.approx(inner.sum() * (8 * 0.01) ** 2, rel=1e-9)


def test_sharpness_ratio_of_contrast_and_blur():
    gt = 0.5 + 0.2 * (_structured_image(64, 64, seed=5) - 0.5)  # within [0.4, 0.6]: room for 2x contrast
    region = np.ones((64, 64), bool)
    assert M.sharpness_ratio(gt, gt, region) == pytest.approx(1.0)
    doubled = 0.5 + 2.0 * (gt - 0.5)
    assert M.sharpness_ratio(doubled, gt, region) == pytest.approx(4.0, rel=1e-9)  # energy is quadratic
    blurred = cv2.GaussianBlur(gt, (0, 0), 2.0)
    assert 0.0 < M.sharpness_ratio(blurred, gt, region) < 0.5
    flat = np.full_like(gt, 0.3)
    assert M.sharpness_ratio(gt, flat, region) is None  # nothing to keep


def test_interior_matches_scipy_erosion():
    from scipy import ndimage

    region = np.zeros((30, 30), bool)
    region[2:20, 5:28] = True
    region[10:25, 0:8] = True  # touches the image border: outside counts as outside
    got = M.interior(region, 2)
    ref = ndimage.binary_erosion(region, structure=np.ones((5, 5), bool), border_value=0)
    assert np.array_equal(got, ref)
    assert M.interior(region, 0) is not None and np.array_equal(M.interior(region, 0), region)


def test_mean_luma_is_rec709_over_the_region():
    rng = np.random.default_rng(3)
    img = rng.uniform(size=(6, 7, 3))
    region = rng.uniform(size=(6, 7)) > 0.5
    want = float(np.mean(0.2126 * img[..., 0][region] + 0.7152 * img[..., 1][region] + 0.0722 * img[..., 2][region]))
    assert M.mean_luma(img, region) == pytest.approx(want, rel=1e-12)
    assert M.mean_luma((img * 255).round().astype(np.uint8), region) == pytest.approx(want, abs=3e-3)
    assert M.mean_luma(img, np.zeros((6, 7), bool)) is None


def test_luma_correlation_and_flat_psnr_against_scipy_and_scikit_image():
    from scipy.stats import pearsonr
    from skimage.metrics import peak_signal_noise_ratio

    rng = np.random.default_rng(3)
    truth = rng.uniform(0.1, 0.6, size=(9, 11, 3))
    region = rng.uniform(size=(9, 11)) > 0.4
    luma = np.array([0.2126, 0.7152, 0.0722])
    # folds where the truth's are, darker and of half the contrast: correlation 1 (a gain and a bias are not
    # a misplaced fold); noise on top lowers it to scipy's figure; a flat image scores 0
    dimmer = 0.5 * truth + 0.1
    assert M.luma_correlation(dimmer, truth, region) == pytest.approx(1.0, abs=1e-12)
    noisy = truth + rng.normal(0, 0.1, truth.shape)
    want = pearsonr(noisy[region] @ luma, truth[region] @ luma)[0]
    assert M.luma_correlation(noisy, truth, region) == pytest.approx(want, abs=1e-12)
    assert M.luma_correlation(np.full_like(truth, 0.3), truth, region) == 0.0
    assert M.luma_correlation(noisy, np.full_like(truth, 0.3), region) is None  # nothing to follow
    assert M.luma_correlation(noisy, truth, np.zeros((9, 11), bool)) is None
    # the truth against its own mean colour over the region
    flat = np.broadcast_to(truth[region].mean(axis=0), truth[region].shape)
    want = peak_signal_noise_ratio(truth[region], flat, data_range=1.0)
    assert M.flat_psnr(truth, region) == pytest.approx(want, abs=1e-9)
    assert M.flat_psnr(np.full_like(truth, 0.5), region) == float("inf")  # one colour: exact
    assert M.flat_psnr(truth, np.zeros((9, 11), bool)) is None


def test_shading_agreement_of_flattened_shifted_and_constant_brightness():
    from scipy.stats import pearsonr

    truth = np.array([0.22, 0.19, 0.14, 0.25, 0.16, 0.12])
    mean = truth.mean()
    half = mean + 0.5 * (truth - mean) + 0.03  # half the contrast, brighter: a bias is not contrast
    out = M.shading_agreement(half, truth)
    assert out["shading_contrast"] == pytest.approx(0.5) and out["shading_correlation"] == pytest.approx(1.0)
    rng = np.random.default_rng(0)
    noisy = truth + rng.normal(0, 0.02, truth.shape)
    out = M.shading_agreement(noisy, truth)
    assert out["shading_contrast"] == pytest.approx(noisy.std() / truth.std())
    assert out["shading_correlation"] == pytest.approx(pearsonr(noisy, truth)[0])
    flat = M.shading_agreement(np.full(6, 0.2), truth)
    assert flat["shading_contrast"] == pytest.approx(0.0, abs=1e-12) and flat["shading_correlation"] == 0.0
    assert M.shading_agreement([0.1, 0.2], [0.1, 0.3]) is None  # too few views
    assert M.shading_agreement([0.1, 0.2, 0.3], [0.2, 0.2, 0.2]) is None  # nothing to follow
    with pytest.raises(ValueError, match="equal"):
        M.shading_agreement([0.1, 0.2, 0.3], [0.1, 0.2])
