"""The trainer's per-frame caches (garmentnerf.train.byte_cache): sizes against hand-counted tensors,
and the caches as the trainer configures them (least recently used first, sized by tensor memory;
the cache itself is tested in tests/test_byte_lru.py)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
import torch

from garmentnerf.train.byte_cache import tensor_bytes, tensor_cache, tensor_pointers


@dataclass
class _Frame:
    vertices: torch.Tensor
    extra: object = None


class _Slotted:
    __slots__ = ("table", "arrays")

    def __init__(self, table, arrays):
        self.table, self.arrays = table, arrays


class _Tree:
    def __init__(self, nodes):
        self.nodes = nodes
        self.parent = self  # a cycle


def test_tensor_bytes_counts_each_buffer_once_at_what_it_keeps_alive():
    vertices = torch.zeros(7, 3)
    table = torch.zeros(5, 4, dtype=torch.float64)
    array = np.zeros((6, 2), dtype=np.float32)
    frame = _Frame(vertices, extra=[_Slotted(table, {"a": array, "again": array}), _Tree(table), (table,),
                                    table[1:3], array[::2]])  # views of buffers already counted
    assert tensor_bytes(frame) == 7 * 3 * 4 + 5 * 4 * 8 + 6 * 2 * 4
    # what the model holds is not charged, nor are views of it
    assert tensor_bytes(frame, exclude=tensor_pointers(table)) == 7 * 3 * 4 + 6 * 2 * 4
    assert tensor_bytes(_Frame(table[2:]), exclude=tensor_pointers(table)) == 0
    assert tensor_bytes(_Frame(torch.zeros(0))) == 0


def test_a_view_is_charged_the_buffer_it_keeps_alive():
    # a frame's row of a clip keeps the whole clip in memory for as long as the row lives
    clip = torch.zeros(10, 7, 3)
    row = clip[2]
    assert tensor_bytes(_Frame(row)) == 10 * 7 * 3 * 4
    del clip
    assert row._base is not None and row.untyped_storage().nbytes() == 10 * 7 * 3 * 4  # still alive
    assert tensor_bytes(_Frame(row.clone())) == 7 * 3 * 4
    grid = np.zeros((10, 8), np.float64)
    assert tensor_bytes(_Frame(grid[3:5, ::2].T)) == 10 * 8 * 8  # a view of a view: the outermost base


def test_tensor_cache_keeps_the_most_recently_used_by_what_their_tensors_hold():
    cache = tensor_cache(3 * 400)
    clip = torch.zeros(4, 100)
    value = {k: torch.zeros(100) for k in "abc"}  # 400 bytes each
    for k in "abc":
        cache.put(k, value[k])
    assert cache.nbytes == 1200 and cache.get("a") is value["a"]
    cache.put("row", _Frame(clip[0]))  # a row of a clip costs the clip: 1600 bytes, over the bound alone
    assert len(cache) == 0 and cache.nbytes == 0
    cache.put("d", torch.zeros(100))
    cache.put("e", torch.zeros(200))
    assert list(cache.keys()) == ["d", "e"] and cache.nbytes == 1200
    cache.put("f", torch.zeros(1))  # the least recently used goes first
    assert list(cache.keys()) == ["e", "f"]
    counted = tensor_cache(1000, size_of=lambda value: 999)
    counted.put("x", torch.zeros(1000))
    assert counted.nbytes == 999
    with pytest.raises(ValueError, match="budget"):
        tensor_cache(-1)


def test_train_cache_gib_shares_its_total_as_the_defaults_do():
    from garmentnerf.cli.train_cmd import cache_bounds
    from garmentnerf.train.settings import TrainConfig

    defaults = TrainConfig(scene=None, out="x")
    names = ("geometry_cache_bytes", "cache_bytes", "inputs_cache_bytes")
    assert cache_bounds(7) == {n: getattr(defaults, n) for n in names}
    half = cache_bounds(3.5)
    assert all(half[n] == getattr(defaults, n) // 2 for n in names) and sum(half.values()) == 7 * 2**29


def test_scene_frames_rebuild_evicted_inputs_and_targets_to_the_same_values(tiny_scene, gl_context):
    from garmentnerf.model.config import ModelConfig
    from garmentnerf.train.frames import SceneFrames

    with SceneFrames(tiny_scene, ModelConfig.tiny(), gl_context) as frames:
        first = frames.inputs("train", 1)
        target = frames.target("train", "cam01", 1)
        one_input, one_target = tensor_bytes(first), tensor_bytes(target)
    # room for one frame's inputs and one view's target: the second frame evicts the first
    with SceneFrames(tiny_scene, ModelConfig.tiny(), gl_context, cache_bytes=one_target,
                     inputs_cache_bytes=one_input) as frames:
        a, ta = frames.inputs("train", 1), frames.target("train", "cam01", 1)
        frames.inputs("train", 2), frames.target("train", "cam01", 2)
        assert frames.inputs("train", 1) is not a and frames.target("train", "cam01", 1) is not ta  # rebuilt
        b, tb = frames.inputs("train", 1), frames.target("train", "cam01", 1)
    for name in ("posed_vertices", "info_maps", "reference_uv", "reference_mask", "reference_depth", "reference_face"):
        assert torch.equal(getattr(a, name), getattr(first, name)) and torch.equal(getattr(b, name), getattr(a, name))
    assert all(torch.equal(x, y) for x, y in zip(ta, tb)) and all(torch.equal(x, y) for x, y in zip(ta, target))
