"""The byte-bounded cache behind every byte-bounded cache of the program (garmentnerf.byte_lru): its
operations against a plain reference model, under the eviction orders of its three uses."""

from __future__ import annotations

import random
from collections import OrderedDict

import pytest

from garmentnerf.byte_lru import ByteBoundedLRU, least_recently_used
from garmentnerf.render.frame_cache import FarthestFromPlayhead
from garmentnerf.viewer.finished_frames import FarthestAheadOfPlayhead


class ReferenceCache:
    """What the cache does, in the plainest terms: an OrderedDict of key -> (value, size), least
    recently used first; when over the budget, values leave in the order ``eviction_order`` gives."""

    def __init__(self, budget: int, eviction_order) -> None:
        self.entries: OrderedDict = OrderedDict()
        self.budget = budget
        self.eviction_order = eviction_order
        self.last_put = 0

    def total(self) -> int:
        return sum(size for _, size in self.entries.values())

    def evict(self) -> list:
        if self.total() <= self.budget:
            return []
        evicted = []
        for key in self.eviction_order(list(self.entries)):
            if self.total() <= self.budget:
                break
            del self.entries[key]
            evicted.append(key)
        return evicted

    def get(self, key):
        if key not in self.entries:
            return None
        self.entries.move_to_end(key)
        return self.entries[key][0]

    def peek(self, key):
        return self.entries[key][0] if key in self.entries else None

    def put(self, key, value) -> list:
        self.entries.pop(key, None)
        self.entries[key] = (value, len(value))
        self.last_put = len(value)
        return self.evict()

    def pop(self, key):
        entry = self.entries.pop(key, None)
        return None if entry is None else entry[0]

    def set_budget(self, budget: int) -> list:
        self.budget = budget
        return self.evict()

    def clear(self) -> None:
        self.entries.clear()


def _orders():
    """(name, the cache's order, the reference's order, a step that moves the playhead) of each use."""
    def still(rng):
        pass

    near = FarthestFromPlayhead()
    near_ref = FarthestFromPlayhead()

    def move_near(rng):
        near.frame = near_ref.frame = rng.randrange(-3, 25)

    ahead = FarthestAheadOfPlayhead()
    ahead_ref = FarthestAheadOfPlayhead()

    def move_ahead(rng):
        ahead.frame = ahead_ref.frame = rng.randrange(0, 20)
        ahead.n_frames = ahead_ref.n_frames = rng.randrange(1, 24)

    return [("least recently used", least_recently_used, least_recently_used, still),
            ("farthest from the playhead", near, near_ref, move_near),
            ("farthest ahead of the playhead", ahead, ahead_ref, move_ahead)]


@pytest.mark.parametrize("use", range(3), ids=[o[0] for o in _orders()])
def test_the_cache_does_what_the_reference_does(use):
    _, order, reference_order, move = _orders()[use]
    rng = random.Random(use)
    cache = ByteBoundedLRU(60, len, order)
    ref = ReferenceCache(60, reference_order)
    for _ in range(3000):
        op = rng.random()
        key = rng.randrange(20)
        if op < 0.35:
            value = bytes(rng.randrange(0, 30))
            assert cache.put(key, value) == ref.put(key, value)
        elif op < 0.55:
            assert cache.get(key) is ref.get(key)
        elif op < 0.65:
            assert cache.peek(key) is ref.peek(key)
        elif op < 0.72:
            assert cache.pop(key) is ref.pop(key)
        elif op < 0.8:
            value = bytes(rng.randrange(0, 30))
            made = cache.get_or_make(key, lambda: value)
            if ref.get(key) is None:
                ref.put(key, value)
                assert made is value
            else:
                assert made is ref.peek(key)
        elif op < 0.86:
            budget = rng.randrange(0, 120)
            assert cache.set_budget(budget) == ref.set_budget(budget)
        elif op < 0.87:
            cache.clear()
            ref.clear()
        else:
            move(rng)
        assert cache.keys() == list(ref.entries)
        assert [(k, v) for k, v in cache.items()] == [(k, v) for k, (v, _) in ref.entries.items()]
        assert cache.nbytes == ref.total() <= cache.budget_bytes == ref.budget
        assert len(cache) == len(ref.entries) and all(k in cache for k in ref.entries)
        assert cache.last_put_nbytes == ref.last_put


def test_least_recently_used_leaves_first():
    cache = ByteBoundedLRU(3 * 400, len)
    value = {k: bytes(400) for k in "abcd"}
    for k in "abc":
        assert cache.put(k, value[k]) == []
    assert cache.nbytes == 1200 and len(cache) == 3
    assert cache.get("a") is value["a"]  # a is now the most recent
    assert cache.put("d", value["d"]) == ["b"]
    assert "b" not in cache and all(k in cache for k in "acd") and cache.nbytes == 1200
    assert cache.put("a", bytes(800)) == ["c"]  # replaced: 800 bytes, so c goes
    assert cache.nbytes == 400 + 800 and cache.keys() == ["d", "a"]
    assert cache.peek("d") is value["d"] and cache.keys() == ["d", "a"]  # peeking is no use
    assert cache.set_budget(900) == ["d"]
    assert cache.keys() == ["a"] and cache.nbytes == 800
    made = []
    assert cache.get_or_make("e", lambda: made.append(1) or bytes(10)) is not None
    assert cache.get_or_make("e", lambda: made.append(1) or bytes(10)) is not None and made == [1]
    assert cache.pop("e") is not None and cache.pop("e") is None and cache.nbytes == 800


def test_a_value_over_the_budget_is_not_kept():
    cache = ByteBoundedLRU(100, len)
    cache.put("small", bytes(10))
    assert cache.put("big", bytes(101)) == ["small", "big"] and cache.last_put_nbytes == 101
    assert len(cache) == 0 and cache.nbytes == 0
    assert cache.get_or_make("big", lambda: bytes(101)) == bytes(101) and len(cache) == 0
    empty = ByteBoundedLRU(0, len)
    assert empty.put("x", bytes(1)) == ["x"] and len(empty) == 0
    assert empty.put("nothing", b"") == [] and "nothing" in empty  # a value of no bytes fits any budget
    with pytest.raises(ValueError, match="budget"):
        ByteBoundedLRU(-1, len)
