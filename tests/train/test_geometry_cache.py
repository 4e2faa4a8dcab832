"""The trainer binds each frame's body once and reuses it at the frame's later NeRF steps: the
same losses and weights, bit for bit, as binding it at every step; the cache holds to its byte bound."""

from __future__ import annotations

from collections import Counter

import pytest
import torch

from garmentnerf.model.config import ModelConfig
from garmentnerf.train.trainer import TrainConfig, Trainer

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _train(scene, out, gl_context, cache_bytes: int):
    tc = TrainConfig(scene=scene.root, out=out, model_config=ModelConfig.tiny(), iterations=7, generator_iterations=1,
                     perceptual="none", progress=False, log_every=100, image_every=0, ckpt_every=100,
                     geometry_cache_bytes=cache_bytes)
    bound = Counter()
    with Trainer(tc, gl_context, log=lambda m: None) as tr:
        bind = tr.model.bind_body
        tr.model.bind_body = lambda verts: bound.update([verts.sum().item()]) or bind(verts)
        steps = range(tr.generator_iterations, tr.total_steps)
        order = [tr._pick(tr.pairs, step, 2)[:2] for step in steps]  # the (sequence, frame) of each step
        result = tr.train()
        state = {k: v.detach().clone() for k, v in tr.model.state_dict().items()}
        kept = len(tr.geometry_cache)
        held = tr.geometry_cache.nbytes
    assert len(steps) == 7
    return result.history, state, bound, order, kept, held


def test_each_frame_is_bound_once_and_training_is_unchanged(tiny_scene, gl_context, tmp_path):
    history, state, bound, order, kept, _ = _train(tiny_scene, tmp_path / "cached", gl_context, 4 << 30)
    visited = set(order)
    assert 1 < len(visited) < 7  # 7 NeRF steps on 3 frames: the frames come back
    assert sum(bound.values()) == len(visited) and set(bound.values()) == {1}
    assert kept == len(visited)
    history_every, state_every, bound_every, _, kept_every, _ = _train(tiny_scene, tmp_path / "every", gl_context, 0)
    assert sum(bound_every.values()) == 7 and kept_every == 0
    assert history == history_every
    assert state.keys() == state_every.keys()
    assert all(torch.equal(state[k], state_every[k]) for k in state)


def test_the_cache_keeps_the_most_recent_frames_under_its_bound(tiny_scene, gl_context, tmp_path):
    _, _, _, order, kept_all, held_all = _train(tiny_scene, tmp_path / "all", gl_context, 4 << 30)
    assert kept_all > 1 and held_all % kept_all == 0  # every frame of one body holds the same bytes
    frame_bytes = held_all // kept_all
    _, _, bound, order, kept, held = _train(tiny_scene, tmp_path / "one", gl_context, int(1.5 * frame_bytes))
    changes = sum(a != b for a, b in zip(order, order[1:]))
    assert 0 < changes < len(order) - 1  # a frame followed by another and by itself: both cases seen
    assert kept == 1 and held == frame_bytes and sum(bound.values()) == 1 + changes


def _encoder_calls(scene, out, gl_context, cache_bytes: int, trained_parameters=()):
    """A run of 7 NeRF steps with per-frame codes (only ``trained_parameters`` training, all when
    empty): its history, final weights, E's and G_en's forward calls and each step's frame."""
    cfg = ModelConfig.tiny().updated({"frame_codes.resolution": 4, "frame_codes.lr_scale": 20.0, "schedule.trained_parameters": tuple(trained_parameters)})
    tc = TrainConfig(scene=scene.root, out=out, model_config=cfg, iterations=7, generator_iterations=1,
                     perceptual="none", progress=False, log_every=100, image_every=0, ckpt_every=100,
                     geometry_cache_bytes=cache_bytes)
    calls = Counter()
    with Trainer(tc, gl_context, log=lambda m: None) as tr:
        for name in ("encoder", "detail_encoder"):
            getattr(tr.model, name).register_forward_hook(lambda m, i, o, name=name: calls.update([name]))
        order = [tr._pick(tr.pairs, step, 2)[:2] for step in range(tr.generator_iterations, tr.total_steps)]
        # the first two steps' frames prepared ahead, as the bench does, here before the NeRF stage froze
        # the encoders: each of those frames is kept again, with their outputs, at its first NeRF step
        tr.warm_frames(2)
        result = tr.train()
        state = {k: v.detach().clone() for k, v in tr.model.state_dict().items()}
        kept = [tr.geometry_cache.get(key) for key in set(order)]
    if cache_bytes:
        assert all((f.encoder_output is not None) == bool(trained_parameters) for f in kept)
        assert all((f.detail_features is not None) == bool(trained_parameters) for f in kept)
    return result.history, state, calls, order


def test_frozen_encoders_run_once_per_frame_and_training_is_unchanged(tiny_scene, gl_context, tmp_path):
    """A codes-only stage (E and G_en frozen) keeps their outputs with the frame's geometry: each runs
    once per frame (and once more for a frame prepared before the stage froze them), and the losses and
    weights are those of running them at every step, bit for bit.
    With every weight training they run at every step, cache or not."""
    codes = ("frame_codes.",)
    history, state, calls, order = _encoder_calls(tiny_scene, tmp_path / "cached", gl_context, 4 << 30, codes)
    frames, warmed = len(set(order)), len(set(order[:2]))
    assert 1 < frames < 7
    assert calls == {"encoder": warmed + frames, "detail_encoder": warmed + frames}
    history_every, state_every, calls_every, _ = _encoder_calls(tiny_scene, tmp_path / "every", gl_context, 0, codes)
    assert calls_every == {"encoder": warmed + 7, "detail_encoder": warmed + 7}
    assert history == history_every
    assert state.keys() == state_every.keys() and all(torch.equal(state[k], state_every[k]) for k in state)
    assert state["frame_codes.codes"].abs().amax() > 0  # the codes trained
    _, _, calls_all, _ = _encoder_calls(tiny_scene, tmp_path / "all", gl_context, 4 << 30)
    assert calls_all == {"encoder": warmed + 7, "detail_encoder": warmed + 7}
