"""A cache of values by key, bounded by the bytes its values hold: every byte-bounded cache of the program.

:class:`ByteBoundedLRU` keeps values with the bytes each holds (measured once, by ``size_of``, when
the value is put) in the order they were last used (put or :meth:`~ByteBoundedLRU.get`). When
the bytes kept pass ``budget_bytes``, values leave until the bound holds, in the order the cache's
*eviction order* gives: ``eviction_order(keys)`` is called with the keys from least to most
recently used and returns them in the order they are to leave. By default
(:func:`least_recently_used`) that is the order it is given: a plain LRU. A value larger than the
budget is not kept (a budget of 0 keeps nothing).

Its uses, each a configuration of this one class:

* the trainer's per-frame inputs, targets and body geometry
  (:mod:`garmentnerf.train.frames`, :class:`~garmentnerf.train.trainer.Trainer`): least recently
  used first, sized by what their tensors keep alive (:func:`garmentnerf.train.byte_cache.tensor_bytes`);
* a render session's per-frame features (:class:`garmentnerf.render.frame_cache.FrameCache`): the
  frame farthest from the playhead first;
* the previewer's finished frames (:class:`garmentnerf.viewer.finished_frames.FinishedFrames`): the
  frame farthest ahead of the playhead, round the clip, first.

Not thread-safe: a cache shared between threads is used under its owner's lock.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Hashable, Iterable, Iterator
from typing import Generic, TypeVar

__all__ = ["ByteBoundedLRU", "least_recently_used"]

K = TypeVar("K", bound=Hashable)
V = TypeVar("V")


def least_recently_used(keys: list[K]) -> list[K]:
    """The LRU eviction order: the keys as given, least recently used first."""
    return keys


class ByteBoundedLRU(Generic[K, V]):
    """Values by key, bounded by the bytes they hold (see the module docstring).

    Args:
        budget_bytes: the bound (>= 0).
        size_of: ``size_of(value) -> bytes`` (measured once, when the value is put).
        eviction_order: ``eviction_order(keys) -> keys``, given the kept keys from least to most
            recently used, returns them in the order they are to leave (default
            :func:`least_recently_used`). Called once per eviction, when the bound is passed.
    """

    def __init__(self, budget_bytes: int, size_of: Callable[[V], int],
                 eviction_order: Callable[[list[K]], Iterable[K]] = least_recently_used) -> None:
        self._size_of = size_of
        self._eviction_order = eviction_order
        self._entries: OrderedDict[K, tuple[V, int]] = OrderedDict()
        self._nbytes = 0
        self.last_put_nbytes = 0
        self.budget_bytes = 0
        self.set_budget(budget_bytes)

    # ---- bound --------------------------------------------------------------------------------------
    def set_budget(self, budget_bytes: int) -> list[K]:
        """Change the bound (>= 0); values leave in the eviction order until it holds. Returns
        the keys evicted."""
        if not budget_bytes >= 0:
            raise ValueError(f"cache budget must be >= 0 bytes, got {budget_bytes!r}")
        self.budget_bytes = int(budget_bytes)
        return self._evict()

    def _evict(self) -> list[K]:
        if self._nbytes <= self.budget_bytes or not self._entries:
            return []
        evicted = []
        for key in list(self._eviction_order(list(self._entries))):
            if self._nbytes <= self.budget_bytes:
                break
            self.pop(key)
            evicted.append(key)
        return evicted

    # ---- state --------------------------------------------------------------------------------------
    @property
    def nbytes(self) -> int:
        """Bytes the kept values hold (as ``size_of`` measured them)."""
        return self._nbytes

    def __len__(self) -> int:
        return len(self._entries)

    def __contains__(self, key: K) -> bool:
        return key in self._entries

    def keys(self) -> list[K]:
        """The kept keys, least recently used first."""
        return list(self._entries)

    def items(self) -> Iterator[tuple[K, V]]:
        """(key, value) of the kept values, least recently used first (use does not change)."""
        return ((key, value) for key, (value, _) in self._entries.items())

    # ---- use ----------------------------------------------------------------------------------------
    def get(self, key: K) -> V | None:
        """The value of ``key`` (now the most recently used), or None."""
        entry = self._entries.get(key)
        if entry is None:
            return None
        self._entries.move_to_end(key)
        return entry[0]

    def peek(self, key: K) -> V | None:
        """The value of ``key``, or None; its use does not change."""
        entry = self._entries.get(key)
        return None if entry is None else entry[0]

    def put(self, key: K, value: V) -> list[K]:
        """Keep ``value`` under ``key`` (replacing any; now the most recently used), then evict down
        to the budget. Returns the keys evicted (``key`` among them when it was not kept); the bytes
        ``value`` holds are :attr:`last_put_nbytes`."""
        self.pop(key)
        size = int(self._size_of(value))
        self.last_put_nbytes = size
        self._entries[key] = (value, size)
        self._nbytes += size
        return self._evict()

    def pop(self, key: K) -> V | None:
        """Remove ``key`` and return its value (None when absent)."""
        entry = self._entries.pop(key, None)
        if entry is None:
            return None
        self._nbytes -= entry[1]
        return entry[0]

    def get_or_make(self, key: K, make: Callable[[], V]) -> V:
        """The value of ``key``, made by ``make()`` and kept when absent (returned even when it is
        too large to keep)."""
        value = self.get(key)
        if value is None:
            value = make()
            self.put(key, value)
        return value

    def clear(self) -> None:
        """Drop every value (the bound and :attr:`last_put_nbytes` stay)."""
        self._entries.clear()
        self._nbytes = 0
