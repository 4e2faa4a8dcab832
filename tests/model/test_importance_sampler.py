"""The importance sampler: inverse-transform sampling against a plain per-ray reference, and what it is
for, a thin opaque sheet that evenly spaced samples miss and the fine pass finds on every ray."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from garmentnerf.conventions import Camera, intrinsics_from_fov, look_at
from garmentnerf.model import volume_rendering as vr
from garmentnerf.model.config import ModelConfig
from garmentnerf.model.importance_sampler import ImportanceSampler, sample_intervals
from garmentnerf.model.samplers import BoxStratifiedSampler, stratified_intervals


def reference_samples(t_starts, t_ends, weights, levels, uniform_mix):
    """One ray at a time in numpy: the piecewise-linear CDF over the interval edges, inverted with np.interp."""
    out = []
    for t0, t1, w, u in zip(t_starts.numpy(), t_ends.numpy(), weights.numpy(), levels.numpy()):
        d = t1 - t0
        keep = d > 0
        t0, t1, w, d = t0[keep], t1[keep], w[keep], d[keep]
        mass = d / d.sum()
        if w.sum() > 0:
            mass = (1 - uniform_mix) * w / w.sum() + uniform_mix * mass
        cdf = np.concatenate([[0.0], np.cumsum(mass)])
        cdf /= cdf[-1]
        edges = np.concatenate([t0, t1[-1:]])
        # np.interp over a CDF with flat stretches (zero-mass intervals) returns the last edge of the stretch
        out.append(np.interp(u, cdf, edges))
    return np.stack(out)


def random_rays(R, K, seed=0):
    g = torch.Generator().manual_seed(seed)
    edges = torch.cumsum(torch.rand(R, K + 1, generator=g, dtype=torch.float64) + 0.05, -1)
    w = torch.rand(R, K, generator=g, dtype=torch.float64) ** 4
    w[0] = 0.0                           # a ray with no weight: uniform
    w[1, :] = 0.0
    w[1, 3] = 1.0                        # all the weight in one interval
    w[2, 2:5] = 0.0                      # zero-mass stretch
    return edges[:, :-1], edges[:, 1:], w


@pytest.mark.parametrize("uniform_mix", [0.0, 0.1, 1.0])
def test_samples_invert_the_distribution_as_a_plain_reference_does(uniform_mix):
    t0, t1, w = random_rays(6, 9)
    S = 32
    got = sample_intervals(t0, t1, w, S, uniform_mix)
    levels = ((torch.arange(S, dtype=torch.float64) + 0.5) / S).expand(6, S)
    want = reference_samples(t0, t1, w, levels, uniform_mix)
    np.testing.assert_allclose(got.numpy(), want, atol=1e-9)
    # training levels: jittered within their strata, the same inversion
    g = torch.Generator().manual_seed(3)
    got = sample_intervals(t0, t1, w, S, uniform_mix, training=True, generator=g)
    g = torch.Generator().manual_seed(3)
    levels = (torch.arange(S, dtype=torch.float64) + torch.rand(6, S, generator=g, dtype=torch.float64)) / S
    np.testing.assert_allclose(got.numpy(), reference_samples(t0, t1, w, levels, uniform_mix), atol=1e-9)
    assert (got[:, 1:] >= got[:, :-1]).all()


def test_samples_fall_in_intervals_in_proportion_to_their_mass():
    t0, t1, w = random_rays(4, 7, seed=1)
    S = 4000
    t = sample_intervals(t0, t1, w, S, 0.2)
    for r in range(4):
        mass = (t1[r] - t0[r]) / (t1[r] - t0[r]).sum()
        if w[r].sum() > 0:
            mass = 0.8 * w[r] / w[r].sum() + 0.2 * mass
        counts = torch.histogram(t[r], torch.cat([t0[r], t1[r, -1:]])).hist
        # stratified levels: each interval gets its share of the S samples to within one
        assert (counts - mass * S).abs().max() <= 1.0 + 1e-9


def test_no_weight_gives_the_stratified_samples():
    near, far = torch.tensor([0.5, 2.0], dtype=torch.float64), torch.tensor([1.5, 4.0], dtype=torch.float64)
    t, t0, t1 = stratified_intervals(near, far, 12)
    got = sample_intervals(t0, t1, torch.zeros_like(t0), 12, 0.1)
    torch.testing.assert_close(got, t)


def test_arguments_are_checked():
    t0, t1, w = random_rays(3, 6)
    with pytest.raises(ValueError, match="uniform_mix"):
        sample_intervals(t0, t1, w, 4, 1.5)
    with pytest.raises(ValueError, match="num_samples"):
        ImportanceSampler(BoxStratifiedSampler(8), lambda f, p: p[:, 0], 0)
    with pytest.raises(ValueError, match="needs sampler 'box'"):
        ModelConfig(importance_samples=16, sampler="shell").validate()


def sheet_scene(thickness=0.004, sigma=5000.0):
    """A camera 3 m in front of a box [-0.5, 0.5]^2 x [0, 1.8] looking along +y, and an opaque sheet
    ``|y - 0.13| < thickness / 2`` across it."""
    R, tvec = look_at((0.0, -3.0, 0.9), (0.0, 0.0, 0.9))
    camera = Camera(intrinsics_from_fov(16, 16, 10.0), R, tvec, 16, 16)
    frame = SimpleNamespace(aabb=torch.tensor([[-0.5, -0.5, 0.0], [0.5, 0.5, 1.8]]))

    def density(_frame, positions):
        return torch.where((positions[:, 1] - 0.13).abs() < thickness / 2, sigma, 0.0)
    return camera, frame, density


def opacity_of(samples, density):
    sig = density(None, samples.positions)
    w = vr.render_weights_from_density_packed(sig, samples.deltas, samples.ray_ids, samples.n_rays)
    return vr.accumulate_opacity_packed(w, samples.ray_ids, samples.n_rays)


def test_a_thin_sheet_missed_by_even_samples_is_found_on_every_ray():
    camera, frame, density = sheet_scene()
    pixels = torch.arange(16 * 16)
    box = BoxStratifiedSampler(24, padding=0.05)
    fine = ImportanceSampler(box, density, 24, uniform_mix=0.1)
    coarse = box.bind(frame, camera).sample(pixels, training=True, generator=torch.Generator().manual_seed(0))
    # 24 samples over about 1.1 m: one sample in eleven lands in a 4 mm sheet
    hit_coarse = opacity_of(coarse, density)
    assert hit_coarse.mean() < 0.5
    # the same seed: the fine sampler's coarse pass is the one above
    s = fine.bind(frame, camera).sample(pixels, training=True, generator=torch.Generator().manual_seed(0))
    assert s.n_rays == 256 and s.ray_ids.shape == (256 * 24,)
    # the fine intervals tile each ray's box segment, in order
    ids = s.ray_ids
    same = ids[1:] == ids[:-1]
    torch.testing.assert_close(s.t_ends[:-1][same], s.t_starts[1:][same])
    first = torch.ones_like(ids, dtype=torch.bool)
    first[1:] = ~same
    torch.testing.assert_close(s.t_starts[first], coarse.near[ids[first]])
    # positions are on their rays at distances inside their intervals
    t = (s.positions - torch.tensor([0.0, -3.0, 0.9])).norm(dim=-1)
    assert ((t >= s.t_starts - 1e-5) & (t <= s.t_ends + 1e-5)).all()
    # rays whose coarse pass saw the sheet put most of their fine samples in a band of a few spacings around it,
    # and render it opaque; the rest are spread evenly (the sheet was not seen) and stay as they were
    seen = hit_coarse > 0.5
    assert seen.sum() > 10
    y = s.positions[:, 1].reshape(256, 24)
    near_sheet = ((y - 0.13).abs() < 0.05).float().mean(-1)
    assert near_sheet[seen].min() > 0.8
    opacity = opacity_of(s, density)
    assert opacity[seen].min() > 0.99


def test_after_one_look_the_sheet_is_rendered_on_every_ray():
    """In training the coarse pass is jittered; with the sheet a few centimetres thick (as a field first
    learns it) every ray's coarse pass sees it, and the fine pass then resolves it like a dense sampling."""
    camera, frame, density = sheet_scene(thickness=0.06, sigma=200.0)
    pixels = torch.arange(16 * 16)
    fine = ImportanceSampler(BoxStratifiedSampler(24, padding=0.05), density, 24, uniform_mix=0.1)
    s = fine.bind(frame, camera).sample(pixels, training=False)
    dense = BoxStratifiedSampler(4096, padding=0.05).bind(frame, camera).sample(pixels)
    torch.testing.assert_close(opacity_of(s, density), opacity_of(dense, density), atol=2e-3, rtol=0)
    assert opacity_of(s, density).min() == pytest.approx(1 - math.exp(-200 * 0.06), abs=2e-3)


def test_a_base_with_gaps_is_refused():
    camera, frame, density = sheet_scene()

    class Gappy:
        def bind(self, frame, camera):
            base = BoxStratifiedSampler(8).bind(frame, camera)

            class Bound:
                def sample(self, pixels, training=False, generator=None):
                    s = base.sample(pixels)
                    s.t_starts = s.t_starts + 0.01 * (torch.arange(len(s)) % 8 == 3)
                    return s
            return Bound()
    with pytest.raises(ValueError, match="contiguous"):
        ImportanceSampler(Gappy(), density, 8).bind(frame, camera).sample(torch.arange(4))
