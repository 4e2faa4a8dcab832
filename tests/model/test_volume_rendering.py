"""Volume rendering against closed forms, numerical safety, packed == dense, and the box sampler."""

from __future__ import annotations

import math

import pytest
import torch

from garmentnerf.model import volume_rendering as vr
from garmentnerf.model.samplers import BoxStratifiedSampler, ray_aabb_intersect, stratified_intervals


def slab_density(t: torch.Tensor, sigma: float, t0: float, t1: float) -> torch.Tensor:
    return torch.where((t >= t0) & (t <= t1), torch.full_like(t, sigma), torch.zeros_like(t))


def slab_expected_depth(sigma: float, t0: float, t1: float) -> float:
    """int_t0^t1 t sigma exp(-sigma (t - t0)) dt."""
    L = t1 - t0
    e = math.exp(-sigma * L)
    return t0 * (1 - e) + (1 - e) / sigma - L * e


@pytest.mark.parametrize("sigma", [0.5, 3.0, 40.0])
def test_constant_slab_opacity_exact_when_intervals_align(sigma):
    t0, t1 = 1.3, 2.1
    edges = torch.linspace(t0, t1, 9, dtype=torch.float64)
    deltas = (edges[1:] - edges[:-1]).unsqueeze(0)
    sigmas = torch.full_like(deltas, sigma)
    expected = 1 - math.exp(-sigma * (t1 - t0))
    w_density = vr.render_weights_from_density(sigmas, deltas)
    w_alpha = vr.render_weights(vr.alpha_from_density(sigmas, deltas))
    for w in (w_density, w_alpha):
        assert vr.accumulate_opacity(w).item() == pytest.approx(expected, rel=1e-12, abs=1e-12)
    # Transmittance after the slab is exp(-sigma L) for both routes.
    T = vr.transmittance_from_density(sigmas, deltas)
    assert T[0, 0].item() == 1.0
    assert (T[0, -1] * (1 - vr.alpha_from_density(sigmas, deltas)[0, -1])).item() == pytest.approx(
        1 - expected, rel=1e-12)


@pytest.mark.parametrize("sigma", [0.5, 3.0, 40.0])
def test_constant_slab_fine_sampling_matches_closed_form(sigma):
    t0, t1 = 1.3, 2.1
    near, far = 0.5, 3.0
    S = 4096
    t, t_starts, t_ends = stratified_intervals(torch.tensor([near], dtype=torch.float64),
                                               torch.tensor([far], dtype=torch.float64), S)
    sigmas = slab_density(t, sigma, t0, t1)
    w = vr.render_weights_from_density(sigmas, t_ends - t_starts)
    opacity = vr.accumulate_opacity(w).item()
    depth = vr.expected_depth(w, t_starts, t_ends).item()
    assert opacity == pytest.approx(1 - math.exp(-sigma * (t1 - t0)), abs=5e-3)
    assert depth == pytest.approx(slab_expected_depth(sigma, t0, t1), abs=5e-3)
    # Normalised depth is the depth of the visible surface: t0 for an opaque slab.
    if sigma == 40.0:
        assert vr.expected_depth(w, t_starts, t_ends, normalize=True).item() == pytest.approx(t0 + 1 / sigma, abs=5e-3)


def test_weights_sum_at_most_one_and_composite():
    g = torch.Generator().manual_seed(0)
    sigmas = torch.rand(64, 32, generator=g) * 50
    deltas = torch.rand(64, 32, generator=g) * 0.1
    w = vr.render_weights_from_density(sigmas, deltas)
    assert (w >= 0).all()
    assert (vr.accumulate_opacity(w) <= 1 + 1e-6).all()
    w_alpha = vr.render_weights(vr.alpha_from_density(sigmas, deltas))
    torch.testing.assert_close(w_alpha, w, atol=1e-5, rtol=1e-4)
    values = torch.rand(64, 32, 5, generator=g)
    out = vr.composite(w, values)
    torch.testing.assert_close(out, torch.einsum("rs,rsc->rc", w, values))
    # Composite of a constant is that constant times the opacity.
    torch.testing.assert_close(vr.composite(w, torch.ones(64, 32, 1))[:, 0], vr.accumulate_opacity(w))


@pytest.mark.parametrize("sigma", [0.0, 1e8])
@pytest.mark.parametrize("delta", [0.0, 1e6])
def test_extreme_values_finite_with_finite_gradients(sigma, delta):
    # Mixed row: the extreme value next to ordinary ones.
    sigmas = torch.tensor([[1.0, sigma, 2.0, sigma], [sigma] * 4], requires_grad=True)
    deltas = torch.tensor([[0.1, delta, 0.1, delta], [delta] * 4], requires_grad=True)
    values = torch.rand(2, 4, 3, requires_grad=True)
    for route in ("density", "alpha"):
        if route == "density":
            w = vr.render_weights_from_density(sigmas, deltas)
        else:
            w = vr.render_weights(vr.alpha_from_density(sigmas, deltas))
        out = vr.composite(w, values).sum() + vr.expected_depth(w, deltas, deltas, normalize=True).sum()
        assert torch.isfinite(w).all() and torch.isfinite(out)
        assert (vr.accumulate_opacity(w) <= 1 + 1e-6).all()
        grads = torch.autograd.grad(out, (sigmas, deltas, values))
        for g in grads:
            assert torch.isfinite(g).all(), route


def test_extreme_values_packed_finite_gradients():
    sigmas = torch.tensor([0.0, 1e8, 1.0, 1e8, 0.0, 3.0], requires_grad=True)
    deltas = torch.tensor([1e6, 1e6, 0.0, 0.1, 0.0, 1e6], requires_grad=True)
    ray_ids = torch.tensor([0, 0, 0, 2, 2, 2])
    w = vr.render_weights_from_density_packed(sigmas, deltas, ray_ids, 3)
    total = vr.composite_packed(w, torch.ones(6, 2), ray_ids, 3).sum()
    assert torch.isfinite(w).all()
    for g in torch.autograd.grad(total, (sigmas, deltas)):
        assert torch.isfinite(g).all()


def test_opaque_first_sample_blocks_the_rest():
    sigmas = torch.tensor([[1e8, 5.0, 5.0]])
    deltas = torch.tensor([[0.1, 0.1, 0.1]])
    w = vr.render_weights_from_density(sigmas, deltas)
    torch.testing.assert_close(w, torch.tensor([[1.0, 0.0, 0.0]]))
    w_alpha = vr.render_weights(vr.alpha_from_density(sigmas, deltas))
    torch.testing.assert_close(w_alpha, w, atol=1e-5, rtol=0)


def test_packed_equals_dense():
    g = torch.Generator().manual_seed(1)
    R, S = 7, 11
    sigmas = torch.rand(R, S, generator=g) * 20
    deltas = torch.rand(R, S, generator=g) * 0.2
    values = torch.randn(R, S, 4, generator=g)
    t_starts = torch.cumsum(deltas, -1) - deltas
    t_ends = t_starts + deltas
    # Ray 2 is opaque (later rays must not notice); ray 3 has no samples at all in packed form.
    sigmas[2] = 1e8
    keep = torch.ones(R, S, dtype=torch.bool)
    keep[3] = False
    ray_ids = torch.arange(R).repeat_interleave(S)[keep.reshape(-1)]
    flat = lambda x: x.reshape(-1, *x.shape[2:])[keep.reshape(-1)]  # noqa: E731

    w_dense = vr.render_weights_from_density(sigmas, deltas)
    w_packed = vr.render_weights_from_density_packed(flat(sigmas), flat(deltas), ray_ids, R)
    torch.testing.assert_close(w_packed, flat(w_dense), rtol=0, atol=0)
    alphas = vr.alpha_from_density(sigmas, deltas)
    torch.testing.assert_close(vr.render_weights_packed(flat(alphas), ray_ids, R), flat(vr.render_weights(alphas)),
                               rtol=0, atol=0)
    torch.testing.assert_close(vr.transmittance_from_density_packed(flat(sigmas), flat(deltas), ray_ids, R),
                               flat(vr.transmittance_from_density(sigmas, deltas)), rtol=0, atol=0)

    out_dense = vr.composite(w_dense, values)
    out_dense[3] = 0
    torch.testing.assert_close(vr.composite_packed(w_packed, flat(values), ray_ids, R), out_dense)
    opacity = vr.accumulate_opacity(w_dense)
    opacity[3] = 0
    torch.testing.assert_close(vr.accumulate_opacity_packed(w_packed, ray_ids, R), opacity)
    depth = vr.expected_depth(w_dense, t_starts, t_ends)
    depth[3] = 0
    torch.testing.assert_close(vr.expected_depth_packed(w_packed, flat(t_starts), flat(t_ends), ray_ids, R), depth)


def test_packed_small_terms_after_a_huge_ray_keep_precision():
    # A global cumsum minus the ray start would lose 1e-3 next to 1e4 * S in float32.
    sigmas = torch.tensor([1e8] * 8 + [0.01] * 8)
    deltas = torch.tensor([1.0] * 8 + [0.1] * 8)
    ray_ids = torch.tensor([0] * 8 + [1] * 8)
    T = vr.transmittance_from_density_packed(sigmas, deltas, ray_ids, 2)
    expected = torch.exp(-0.001 * torch.arange(8, dtype=torch.float32))
    torch.testing.assert_close(T[8:], expected, rtol=1e-6, atol=0)


def test_packed_rejects_unsorted_or_out_of_range_ray_ids():
    x = torch.ones(3)
    with pytest.raises(ValueError, match="sorted"):
        vr.render_weights_packed(x * 0.5, torch.tensor([1, 0, 1]), 2)
    with pytest.raises(ValueError, match="lie in"):
        vr.render_weights_packed(x * 0.5, torch.tensor([0, 1, 2]), 2)


def test_packed_empty_input():
    empty = torch.zeros(0)
    ids = torch.zeros(0, dtype=torch.long)
    w = vr.render_weights_from_density_packed(empty, empty, ids, 4)
    assert w.shape == (0,)
    assert vr.composite_packed(w, torch.zeros(0, 3), ids, 4).shape == (4, 3)


# ---------------------------------------------------------------------------------------- sampler
def test_ray_aabb_slabs_with_zero_direction_components():
    aabb = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    origins = torch.tensor([[-5.0, 0.0, 0.0],    # along +x through the centre
                            [-5.0, 2.0, 0.0],    # parallel to x, outside in y -> miss
                            [-5.0, 1.0, 0.0],    # parallel, grazing the y = 1 face -> degenerate
                            [0.0, 0.0, 0.0],     # starts inside
                            [5.0, 5.0, 5.0],     # pointing away -> miss
                            [0.0, 0.0, 5.0]])    # straight down the z axis
    dirs = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0],
                         [0.0, 0.0, -1.0]])
    t_near, t_far, hit = ray_aabb_intersect(origins, dirs, aabb)
    assert hit.tolist() == [True, False, True, True, False, True]
    torch.testing.assert_close(t_near, torch.tensor([4.0, 0.0, 4.0, 0.0, 0.0, 4.0]))
    torch.testing.assert_close(t_far, torch.tensor([6.0, 0.0, 6.0, 1.0, 0.0, 6.0]))
    assert torch.isfinite(t_near).all() and torch.isfinite(t_far).all()


def test_box_sampler_intervals_and_missing_rays():
    sampler = BoxStratifiedSampler(num_samples=16, padding=0.05)
    aabb = torch.tensor([[-0.5, -0.5, 0.0], [0.5, 0.5, 1.8]])
    origins = torch.tensor([[0.0, -3.0, 0.9], [0.0, -3.0, 5.0], [3.0, 3.0, 0.9]])
    dirs = torch.nn.functional.normalize(torch.tensor([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]), dim=-1)
    for training in (False, True):
        s = sampler.sample_rays(origins, dirs, aabb, training=training, generator=torch.Generator().manual_seed(0))
        # Packed: only the ray that hits the padded box has samples, 16 of them, in order.
        assert s.positions.shape == (16, 3) and s.t_starts.shape == (16,) and s.n_rays == 3
        assert s.hit.tolist() == [True, False, False] and s.ray_ids.tolist() == [0] * 16
        # Intervals tile [entry, exit] of the padded box, which are the ray's bounds.
        assert s.t_starts[0].item() == pytest.approx(3.0 - 0.55) == s.near[0].item()
        assert s.t_ends[-1].item() == pytest.approx(3.0 + 0.55) == s.far[0].item()
        torch.testing.assert_close(s.t_ends[:-1], s.t_starts[1:])
        assert (s.deltas > 0).all() and (s.t_starts[1:] > s.t_starts[:-1]).all()
        # Samples lie inside the padded box.
        assert (s.positions >= aabb[0] - 0.05 - 1e-5).all() and (s.positions <= aabb[1] + 0.05 + 1e-5).all()
        # Any density: an opaque box, and the missing rays render nothing.
        w = vr.render_weights_from_density_packed(torch.full((16,), 1e3), s.deltas, s.ray_ids, 3)
        opacity = vr.accumulate_opacity_packed(w, s.ray_ids, 3)
        assert opacity[0].item() == pytest.approx(1.0) and opacity[1:].tolist() == [0.0, 0.0]
    eval_s = sampler.sample_rays(origins, dirs, aabb)
    torch.testing.assert_close(eval_s.t_mids, (eval_s.t_starts + eval_s.t_ends) / 2)
    torch.testing.assert_close(eval_s.deltas, torch.full((16,), 1.1 / 16))


def test_bound_box_sampler_is_the_box_sampler_on_the_camera_rays():
    from garmentnerf.conventions import camera_rays, orbit_camera
    from garmentnerf.model.samplers import pixel_rays

    class Frame:  # what bind() reads of a frame
        aabb = torch.tensor([[-0.3, -0.2, 0.0], [0.3, 0.2, 1.7]])

    cam = orbit_camera(20.0, 10.0, 3.0, width=12, height=10)
    sampler = BoxStratifiedSampler(num_samples=8)
    pixels = torch.tensor([0, 5, 55, 61, 119])
    bound = sampler.bind(Frame(), cam)
    got = bound.sample(pixels)
    o, d = camera_rays(cam)
    want = sampler.sample_rays(o.reshape(-1, 3)[pixels], d.reshape(-1, 3)[pixels], Frame.aabb)
    for k in ("positions", "t_starts", "t_ends", "ray_ids", "near", "far", "hit"):
        torch.testing.assert_close(getattr(got, k), getattr(want, k), atol=0, rtol=0)
    assert got.hit.any() and got.n_rays == 5
    torch.testing.assert_close(pixel_rays(cam)[1].reshape(10, 12, 3), d, atol=0, rtol=0)


def test_box_sampler_rejects_non_unit_directions():
    with pytest.raises(ValueError, match="unit"):
        BoxStratifiedSampler(4).sample_rays(torch.zeros(1, 3), torch.tensor([[0.0, 2.0, 0.0]]),
                                       torch.tensor([[-1.0, -1, -1], [1, 1, 1]]))


# ---------------------------------------------------------------- segmented rendering, early termination
def _random_packed_rays(seed: int, n_rays: int = 40, max_samples: int = 30):
    g = torch.Generator().manual_seed(seed)
    counts = torch.randint(0, max_samples + 1, (n_rays,), generator=g)
    ray_ids = torch.repeat_interleave(torch.arange(n_rays), counts)
    n = int(counts.sum())
    deltas = torch.rand(n, generator=g, dtype=torch.float64) * 0.1
    t_starts = torch.zeros(n, dtype=torch.float64)
    for r in range(n_rays):  # intervals tile each ray from t = 1
        sel = ray_ids == r
        t_starts[sel] = 1.0 + torch.cumsum(deltas[sel], 0) - deltas[sel]
    t_ends = t_starts + deltas
    sigma = torch.rand(n, generator=g, dtype=torch.float64) * 80.0
    values = torch.rand(n, 3, generator=g, dtype=torch.float64) * 2 - 1
    return ray_ids, t_starts.float(), t_ends.float(), sigma.float(), values.float()


def _exact(ray_ids, t_starts, t_ends, sigma, values, n_rays):
    w = vr.render_weights_from_density_packed(sigma, t_ends - t_starts, ray_ids, n_rays)
    return (vr.composite_packed(w, values, ray_ids, n_rays), vr.accumulate_opacity_packed(w, ray_ids, n_rays),
            vr.expected_depth_packed(w, t_starts, t_ends, ray_ids, n_rays))


@pytest.mark.parametrize("chunk", [1, 7, 64, 100000])
def test_segmented_rendering_without_termination_is_exact(chunk):
    ray_ids, ts, te, sigma, values = _random_packed_rays(0)
    calls = []

    def field(index):
        calls.append(index.clone())
        return sigma[index], values[index]

    out = vr.render_packed_segmented(field, ts, te, ray_ids, 40, 3, chunk_points=chunk)
    want_v, want_o, want_d = _exact(ray_ids, ts, te, sigma, values, 40)
    torch.testing.assert_close(out.values, want_v, atol=1e-6, rtol=0)
    torch.testing.assert_close(out.opacity, want_o, atol=1e-6, rtol=0)
    torch.testing.assert_close(out.depth, want_d, atol=1e-5, rtol=0)
    # Every sample evaluated exactly once, whole rays per call (never split).
    seen = torch.cat(calls)
    assert sorted(seen.tolist()) == list(range(len(ray_ids))) and out.samples_evaluated == len(ray_ids)
    for index in calls:
        rays = torch.unique(ray_ids[index])
        assert int(torch.isin(ray_ids, rays).sum()) == index.numel()
    assert not out.terminated.any()


def test_segmented_rendering_gradients_match_the_dense_reference():
    ray_ids, ts, te, sigma, values = _random_packed_rays(1, n_rays=12, max_samples=10)
    s1, v1 = sigma.clone().requires_grad_(), values.clone().requires_grad_()
    out = vr.render_packed_segmented(lambda i: (s1[i], v1[i]), ts, te, ray_ids, 12, 3, chunk_points=5,
                                     termination_eps=1e-9)  # segmented front to back, nothing skipped
    (out.values.sum() + out.opacity.sum()).backward()
    s2, v2 = sigma.clone().requires_grad_(), values.clone().requires_grad_()
    want_v, want_o, _ = _exact(ray_ids, ts, te, s2, v2, 12)
    (want_v.sum() + want_o.sum()).backward()
    torch.testing.assert_close(s1.grad, s2.grad, atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(v1.grad, v2.grad, atol=1e-6, rtol=0)


@pytest.mark.parametrize("eps", [1e-4, 1e-2, 0.2])
def test_early_termination_error_is_bounded_by_eps(eps):
    ray_ids, ts, te, sigma, values = _random_packed_rays(2, n_rays=60, max_samples=40)
    out = vr.render_packed_segmented(lambda i: (sigma[i], values[i]), ts, te, ray_ids, 60, 3, chunk_points=60,
                                     termination_eps=eps)
    want_v, want_o, _ = _exact(ray_ids, ts, te, sigma, values, 60)
    assert out.samples_evaluated < len(ray_ids) and out.terminated.any()
    # Skipped samples carry weights summing to at most eps per ray: |dF| <= eps max|v|, dO <= eps.
    assert float((want_o - out.opacity).max()) <= eps + 1e-6 and float((want_o - out.opacity).min()) >= -1e-6
    assert float((want_v - out.values).abs().max()) <= eps * float(values.abs().max()) + 1e-6
    # A terminated ray's transmittance did fall below eps; a live one's never did before its end.
    assert bool((1.0 - out.opacity[out.terminated] < eps + 1e-6).all())


def test_segmented_rendering_rejects_bad_settings():
    with pytest.raises(ValueError, match="termination_eps"):
        vr.render_packed_segmented(lambda i: None, torch.zeros(0), torch.zeros(0), torch.zeros(0, dtype=torch.long),
                                   1, 3, termination_eps=1.0)


def _distortion_brute_force(weights, t_starts, t_ends, ray_ids, n_rays):
    """The double sum of mip-NeRF 360's Eq. 15 written out, one ray at a time."""
    out = torch.zeros(n_rays, dtype=weights.dtype)
    mids = (t_starts + t_ends) / 2
    for r in range(n_rays):
        m = ray_ids == r
        w, mid, d = weights[m], mids[m], (t_ends - t_starts)[m]
        out[r] = (w[:, None] * w[None, :] * (mid[:, None] - mid[None, :]).abs()).sum() + (w ** 2 * d).sum() / 3
    return out


def test_distortion_of_analytic_cases():
    # one interval holding the whole weight: the mean distance of two uniform points on it, delta / 3
    one = vr.distortion_packed(torch.tensor([1.0]), torch.tensor([2.0]), torch.tensor([2.3]), torch.tensor([0]), 1)
    assert one.item() == pytest.approx(0.1)
    # two spikes: 2 w1 w2 |m1 - m2|
    two = vr.distortion_packed(torch.tensor([0.25, 0.5]), torch.tensor([1.0, 3.0]), torch.tensor([1.0, 3.0]),
                               torch.tensor([0, 0]), 1)
    assert two.item() == pytest.approx(2 * 0.25 * 0.5 * 2.0)
    # weight spread evenly over a segment of length L in many intervals: L / 3, the fog's cost
    edges = torch.linspace(0.0, 0.6, 601, dtype=torch.float64)
    fog = vr.distortion_packed(torch.full((600,), 1 / 600, dtype=torch.float64), edges[:-1], edges[1:],
                               torch.zeros(600, dtype=torch.long), 1)
    assert fog.item() == pytest.approx(0.2, rel=1e-6)


def test_distortion_matches_the_double_sum_and_its_gradient_the_finite_differences():
    ray_ids, ts, te, sigma, _ = _random_packed_rays(3, n_rays=9, max_samples=12)
    ts, te = ts.double(), te.double()
    w = vr.render_weights_from_density_packed(sigma.double(), te - ts, ray_ids, 9)
    torch.testing.assert_close(vr.distortion_packed(w, ts, te, ray_ids, 9), _distortion_brute_force(w, ts, te, ray_ids, 9))
    s = sigma.double().requires_grad_()
    torch.autograd.gradcheck(lambda x: vr.distortion_packed(vr.render_weights_from_density_packed(x, te - ts, ray_ids, 9),
                                                            ts, te, ray_ids, 9), (s,))


@pytest.mark.parametrize("eps", [0.0, 1e-9])
def test_segmented_rendering_accumulates_the_distortion_across_segments(eps):
    ray_ids, ts, te, sigma, values = _random_packed_rays(4, n_rays=12, max_samples=10)
    out = vr.render_packed_segmented(lambda i: (sigma[i], values[i]), ts, te, ray_ids, 12, 3, chunk_points=5,
                                     termination_eps=eps, with_distortion=True)
    w = vr.render_weights_from_density_packed(sigma, te - ts, ray_ids, 12)
    torch.testing.assert_close(out.distortion, vr.distortion_packed(w, ts, te, ray_ids, 12), atol=1e-6, rtol=1e-5)
    assert vr.render_packed_segmented(lambda i: (sigma[i], values[i]), ts, te, ray_ids, 12, 3).distortion is None
