"""The clip's frame cache (garmentnerf.render.frame_cache): memory bound, playhead order, half
precision, and its use by RenderSession and the previewer's worker."""

from __future__ import annotations

import time

import pytest
import torch

from garmentnerf.model.frame_context import FrameFeatures
from garmentnerf.render.frame_cache import FarthestFromPlayhead, FrameCache


def fake_features(seed: int, size: int = 32) -> FrameFeatures:
    g = torch.Generator().manual_seed(seed)
    verts = torch.rand(50, 3, generator=g)
    depth = torch.rand(2, size, size, generator=g) * 4
    depth[:, 0, 0] = float("inf")  # background
    return FrameFeatures(verts, torch.rand(50, 3, generator=g), f"surface {seed}",
                         torch.stack([verts.amin(0), verts.amax(0)]), torch.rand(8, size, size, generator=g),
                         torch.rand(2, 3, size, size, generator=g), torch.randn(2, 8, size, size, generator=g),
                         (None, None), depth, seed)


def binder(calls):
    def bind(vertices):
        calls.append(vertices)
        return "rebound"
    return bind


def test_memory_bound_and_playhead_order():
    calls = []
    one = FrameCache(binder(calls), budget_mb=1.0)
    one.put(0, fake_features(0))
    per_frame = one.nbytes
    assert per_frame == sum(t.numel() * 4 for t in (fake_features(0).posed_vertices, fake_features(0).vertex_normals,
                                                     fake_features(0).aabb, fake_features(0).dynamic_features,
                                                     fake_features(0).reference_images, fake_features(0).detail_features,
                                                     fake_features(0).reference_depth))
    cache = FrameCache(binder(calls), budget_mb=4.5 * per_frame / 2**20)  # room for 4 frames
    cache.set_playhead(10)
    order = []
    while (f := cache.next_to_compute(20)) is not None:
        cache.put(f, fake_features(f))
        order.append(f)
        assert cache.nbytes <= cache.budget_bytes
    assert order == [10, 11, 9, 12]  # nearest first, ties forwards; then the bound is spent
    assert cache.ready_frames() == [9, 10, 11, 12]
    cache.set_playhead(2)  # scrub: the far frames give way to frames near the new playhead
    assert cache.next_to_compute(20) == 2
    cache.put(2, fake_features(2))
    assert 12 not in cache and 2 in cache and cache.nbytes <= cache.budget_bytes
    cache.set_budget_mb(1.5 * per_frame / 2**20)  # a smaller bound: only the frame nearest the playhead stays
    assert cache.ready_frames() == [2]
    cache.set_budget_mb(0)
    assert len(cache) == 0 and cache.next_to_compute(20) is None  # nothing fits: no endless precompute
    with pytest.raises(ValueError):
        cache.set_budget_mb(-1)


def test_the_eviction_order_is_farthest_from_the_playhead_later_first():
    assert FarthestFromPlayhead(10)([9, 10, 11, 12, 8, 3]) == [3, 12, 8, 11, 9, 10]
    assert FarthestFromPlayhead(0)([]) == []


def test_get_returns_float32_rebinds_and_half_precision_is_close():
    calls = []
    exact, half = FrameCache(binder(calls)), FrameCache(binder(calls), half=True)
    f = fake_features(3)
    for cache in (exact, half):
        cache.put(3, f)
        got = cache.get(3)
        assert got.surface == "surface 3" and not calls  # the last frames keep their bound search
        for name in ("dynamic_features", "reference_images", "detail_features", "reference_depth"):
            t = getattr(got, name)
            assert t.dtype == torch.float32
            if cache is exact:
                assert torch.equal(t, getattr(f, name))
            else:
                torch.testing.assert_close(t, getattr(f, name), rtol=1e-3, atol=1e-3)
        assert torch.equal(got.posed_vertices, f.posed_vertices)  # geometry stays float32
    assert half.nbytes < 0.6 * exact.nbytes
    assert torch.isinf(half.get(3).reference_depth[:, 0, 0]).all()
    small = FrameCache(binder(calls), bound_frames=1)
    small.put(1, fake_features(1))
    small.put(2, fake_features(2))
    assert small.get(1).surface == "rebound" and len(calls) == 1  # frame 1's search was rebuilt once
    assert small.get(1).surface == "rebound" and len(calls) == 1
    assert small.get(7) is None


@pytest.fixture(scope="module")
def run_dir(tiny_scene, tmp_path_factory):
    from garmentnerf.model.config import ModelConfig
    from garmentnerf.runs import create_untrained_run

    return create_untrained_run(tmp_path_factory.mktemp("run") / "r", tiny_scene.root,
                                ModelConfig.tiny().updated({"sampler.samples_per_ray": 4}), seed=0)


def test_session_precomputes_and_a_ready_frame_costs_no_frame_work(run_dir, gl_context, monkeypatch):
    from garmentnerf.conventions import orbit_camera
    from garmentnerf.render.session import RenderSession
    from garmentnerf.runs import load_run

    with RenderSession(load_run(run_dir), gl_context) as session:
        calls = []
        original = session.model.prepare_frame
        monkeypatch.setattr(session.model, "prepare_frame", lambda inputs, **kw: calls.append(inputs.frame) or original(inputs, **kw))
        n = session.num_frames
        done = []
        while (f := session.precompute_next(playhead=1)) is not None:
            done.append(f)
        assert sorted(done) == list(range(n)) and done[0] == 1 and calls == done
        cam = orbit_camera(20.0, 5.0, 3.0, width=32, height=32)
        fresh = session._compute_frame(n - 1)
        calls.clear()
        for f in (n - 1, 0, 1):  # scrubbing between ready frames
            nf = session.render(f, cam, preset="interactive")
            assert nf.cached_frame
        assert calls == []  # no per-frame model call
        # the cached frame renders exactly as a freshly computed one (the session keeps float32)
        again = session.frames.get(n - 1)
        assert torch.equal(again.detail_features, fresh.detail_features)
        session.set_motion("walk")  # a new motion invalidates the clip
        assert len(session.frames) == 0 and session.frames.ready_frames() == []


def test_previewer_worker_precomputes_the_clip_in_the_background(run_dir):
    from garmentnerf.conventions import orbit_camera
    from garmentnerf.runs import load_run
    from garmentnerf.viewer.worker import NeuralRenderer, NeuralRequest

    results = []
    renderer = NeuralRenderer(load_run(run_dir), lambda result, request: results.append(result))
    try:
        assert renderer.cache_status() is None
        renderer.request(NeuralRequest(1, orbit_camera(0.0, 5.0, 3.0, width=32, height=32), 0.5, None, None,
                                       "interactive"))
        deadline = time.monotonic() + 120
        status = None
        while time.monotonic() < deadline:
            status = renderer.cache_status()
            if status is not None and len(status["ready"]) == status["frames"]:
                break
            time.sleep(0.05)
        assert status is not None and status["ready"] == list(range(status["frames"])), status
        assert 0 < status["bytes"] <= status["budget_bytes"] and len(results) == 1
        renderer.set_cache_mb(0.0)  # the user lowers the bound: the cache empties
        assert renderer.cache_status()["ready"] == [] and renderer.cache_status()["bytes"] == 0
    finally:
        renderer.stop()
