"""The rasterised body's appearance (garmentnerf.model.body_appearance) and the hybrid composition
(garmentnerf.model.palette.compose with a body layer)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from garmentnerf.body.shading import monomial_exponents, normal_monomials
from garmentnerf.model.body_appearance import BodyAppearance, load_body_appearance, save_body_appearance
from garmentnerf.model.palette import DecomposedMaps, compose, composite_alpha


def _unit_normals(n: int, seed: int = 0) -> np.ndarray:
    v = np.random.default_rng(seed).normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _real_sh(l: int, m: int, n: np.ndarray) -> np.ndarray:
    """Real spherical harmonic Y_lm at unit vectors (scipy's complex ones, combined)."""
    from scipy.special import sph_harm_y

    theta = np.arccos(np.clip(n[:, 2], -1, 1))
    phi = np.arctan2(n[:, 1], n[:, 0])
    y = sph_harm_y(l, abs(m), theta, phi)
    if m > 0:
        return np.sqrt(2) * (-1) ** m * y.real
    if m < 0:
        return np.sqrt(2) * (-1) ** m * y.imag
    return y.real


@pytest.mark.parametrize("degree", [2, 4])
def test_monomials_span_exactly_the_spherical_harmonics_up_to_their_degree(degree):
    """Least squares of scipy's real SH on the monomials: exact up to ``degree``, not above."""
    n = _unit_normals(2000)
    basis = normal_monomials(torch.from_numpy(n), degree).numpy()
    assert basis.shape[1] == len(monomial_exponents(degree)) == (degree + 1) * (degree + 2) * (degree + 3) // 6

    def residual(l, m):
        y = _real_sh(l, m, n)
        coef, *_ = np.linalg.lstsq(basis, y, rcond=None)
        return np.abs(basis @ coef - y).max() / np.abs(y).max()

    for l in range(degree + 1):
        for m in range(-l, l + 1):
            assert residual(l, m) < 1e-9, (l, m)
    assert residual(degree + 1, 0) > 1e-2


def test_degree_4_shading_follows_a_directional_light():
    """max(0, n.l) (a Lambertian key light) fitted by the degree-4 polynomial: 2 % RMS (6 % at worst,
    at the terminator), where the 9-coefficient (degree 2) irradiance is off by twice that."""
    n = _unit_normals(4000, seed=1)
    light = np.array([-0.35, -0.8, 0.75])
    light /= np.linalg.norm(light)
    target = np.maximum(n @ light, 0.0)
    errors = {}
    for degree in (2, 4):
        basis = normal_monomials(torch.from_numpy(n), degree).numpy()
        coef, *_ = np.linalg.lstsq(basis, target, rcond=None)
        errors[degree] = np.sqrt(np.mean((basis @ coef - target) ** 2))
    assert errors[4] < 0.02
    assert errors[2] > 1.8 * errors[4]


def test_appearance_starts_at_one_and_reads_its_texture():
    app = BodyAppearance(texture_size=4)
    uv = torch.rand(50, 2)
    n = torch.from_numpy(_unit_normals(50)).float()
    assert torch.allclose(app(uv, n), torch.ones(50, 3))
    with torch.no_grad():
        app.albedo[0] = torch.arange(16.0).view(4, 4)  # red channel = row * 4 + column
    # texel centres: column c at u = (c + 0.5) / 4, row r at v = (r + 0.5) / 4
    uv = torch.tensor([[0.125, 0.125], [0.875, 0.125], [0.125, 0.875], [0.5, 0.5]])
    red = app.albedo_at(uv)[:, 0]
    assert red.tolist() == pytest.approx([0.0, 3.0, 12.0, (5 + 6 + 9 + 10) / 4])


def test_save_and_load(tmp_path):
    app = BodyAppearance(texture_size=8)
    with torch.no_grad():
        app.albedo.uniform_(0.5, 1.5)
        app.shading.normal_()
    path = save_body_appearance(tmp_path / "a.safetensors", app)
    back = load_body_appearance(path)
    assert torch.equal(back.albedo, app.albedo) and torch.equal(back.shading, app.shading)
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(b"not a file")
    with pytest.raises(ValueError, match="bad.safetensors"):
        load_body_appearance(bad)


# ---- the hybrid composition -------------------------------------------------------------------------
def _maps(H=3, W=4, P=2, seed=0):
    g = torch.Generator().manual_seed(seed)
    radiance = torch.rand(1, 3, H, W, generator=g) * 1.4
    offsets = (torch.rand(1, P, 3, H, W, generator=g) - 0.5) * 0.4
    w = torch.rand(1, P, H, W, generator=g) + 0.05
    weights = w / w.sum(dim=1, keepdim=True)
    mask = torch.rand(1, 1, H, W, generator=g)
    color = torch.rand(1, 3, H, W, generator=g) * 1.2
    coverage = torch.rand(1, 1, H, W, generator=g)
    return radiance, offsets, weights, mask, color * coverage, coverage


def test_hybrid_compose_matches_a_per_pixel_reference():
    """Every pixel recomputed in numpy from the formula in the module docstring (P = 3: two garment
    colors and the body)."""
    r, o, w, m, body, cov = _maps(P=3)
    palette = torch.tensor([[0.1, 0.3, 0.8], [0.9, 0.2, 0.1], [0.8, 0.6, 0.5]])
    bg = (0.2, 0.4, 0.1)
    out = compose(r, o, w, m, palette, bg, body, cov)[0].numpy()
    alpha = composite_alpha(m, w, cov)[0, 0].numpy()
    R, O, Wt, M, B, C = (x[0].double().numpy() for x in (r, o, w, m, body, cov))
    pal = palette.double().numpy()
    for y in range(R.shape[1]):
        for x in range(R.shape[2]):
            share = Wt[0, y, x] + Wt[1, y, x]
            g = sum(Wt[i, y, x] * (pal[i] + O[i, :, y, x]) for i in (0, 1)) / share
            g = np.clip(R[:, y, x] * g, 0, 1)
            vis = M[0, y, x] * share
            b = np.clip(pal[2] * B[:, y, x], 0, 1)
            expect = vis * g + (1 - vis) * (b + (1 - C[0, y, x]) * np.array(bg))
            assert out[:, y, x] == pytest.approx(expect, abs=1e-6)
            assert alpha[y, x] == pytest.approx(vis + (1 - vis) * C[0, y, x], abs=1e-6)


def test_hybrid_compose_without_a_body_is_the_garment_over_the_background():
    """Zero coverage: the garment layer alone (P = 2: clamp(r (p_G + o_G)) with visibility m w_G)."""
    r, o, w, m, _, _ = _maps()
    palette = torch.tensor([[0.1, 0.3, 0.8], [0.8, 0.6, 0.5]])
    zero = torch.zeros_like(m)
    out = compose(r, o, w, m, palette, (0, 0, 0), torch.zeros_like(r), zero)
    garment = (r * (palette[0].view(1, 3, 1, 1) + o[:, 0])).clamp(0, 1)
    assert torch.allclose(out, m * w[:, :1] * garment, atol=1e-6)
    # one-hot garment weights: the paper's composition exactly
    w1 = torch.cat([torch.ones_like(m), torch.zeros_like(m)], dim=1)
    assert torch.allclose(compose(r, o, w1, m, palette, (0.3, 0.3, 0.3), torch.zeros_like(r), zero),
                          compose(r, o, w1, m, palette, (0.3, 0.3, 0.3)), atol=1e-6)


def test_hybrid_recolor_is_linear_in_the_body_color():
    """Inside [0, 1] a new body color changes a pixel by (1 - m_G) (p_B' - p_B) a, nothing else."""
    r, o, w, m, body, cov = _maps()
    body = body * 0.5  # keep p_B * a inside [0, 1]
    p = torch.tensor([[0.1, 0.3, 0.8], [0.8, 0.6, 0.5]])
    q = p.clone()
    q[1] = torch.tensor([0.3, 0.7, 0.2])
    delta = compose(r, o, w, m, q, (0, 0, 0), body, cov) - compose(r, o, w, m, p, (0, 0, 0), body, cov)
    expect = (1 - m * w[:, :1]) * (q[1] - p[1]).view(1, 3, 1, 1) * body
    assert torch.allclose(delta, expect, atol=1e-6)


def test_decomposed_maps_carry_the_body_layer():
    r, o, w, m, body, cov = _maps(H=4, W=4)
    maps = DecomposedMaps(r, o, w, m).with_body(body, cov)
    pal = torch.tensor([[0.1, 0.3, 0.8], [0.8, 0.6, 0.5]])
    assert torch.equal(maps.compose(pal), compose(r, o, w, m, pal, (0, 0, 0), body, cov))
    placed = maps.placed(1, 2, 7, 8)
    assert placed.body_color.shape == (1, 3, 8, 7) and float(placed.body_coverage[..., :2, :].abs().sum()) == 0
    assert torch.equal(placed.body_coverage[..., 2:6, 1:5], cov)
    assert torch.equal(placed.cropped(5, 6).body_color, placed.body_color[..., :6, :5])
    big = maps.resized(8, 8)
    assert big.body_color.shape == (1, 3, 8, 8) and float(big.body_coverage.max()) <= 1.0
    assert torch.allclose(big.body_coverage.mean(), cov.mean(), atol=0.05)
    with pytest.raises(ValueError, match="both"):
        compose(r, o, w, m, pal, (0, 0, 0), body, None)
