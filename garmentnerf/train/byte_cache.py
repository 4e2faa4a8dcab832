"""The trainer's byte-bounded caches: least recently used first, bounded by the bytes of the tensors their values hold.

The trainer keeps three kinds of per-frame data between steps (a frame's inputs, its ground-truth
targets, its bound body geometry); each grows with the training frames, so each is bounded in
bytes, not in entries: a four-sequence scene has 680 training frames, and a frame's body geometry
alone holds 18 MB of tensors (its closest-point search tables are float64). Each is a
:class:`~garmentnerf.byte_lru.ByteBoundedLRU` made by :func:`tensor_cache`: when full, the least
recently used value leaves first.

:func:`tensor_bytes` measures a value: the tensors (and numpy arrays) reachable from it through
dataclass fields, attributes, ``__slots__`` and containers, each charged the whole memory it keeps
alive -- a tensor its storage, a numpy array its outermost base array -- each storage once. A view
is charged its base's size: a frame's row of a (T, V, 3) clip keeps the whole clip in memory, and
the caches once held such rows at 1/170 of what they cost (``docs/lab/ledger.md``, "The trainer's
memory, found and fixed"). Tensors shared with something long-lived (the model's topology tables,
which every frame's bound body points at) are passed as ``exclude`` (:func:`tensor_pointers` of the
long-lived thing) so that they are not charged to every frame.
"""

from __future__ import annotations

import dataclasses
import types
from collections.abc import Callable, Iterator

import numpy as np
import torch

from garmentnerf.byte_lru import ByteBoundedLRU

__all__ = ["tensor_cache", "tensor_bytes", "tensor_pointers"]

#: Objects not looked into: scalars, strings, and modules and classes (whose attributes are not a value's).
_LEAVES = (str, bytes, int, float, bool, complex, torch.dtype, torch.device, types.ModuleType, type)


def _children(obj) -> Iterator[object]:
    if isinstance(obj, (list, tuple, set, frozenset)):
        yield from obj
    elif isinstance(obj, dict):
        yield from obj.values()
    elif dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        for f in dataclasses.fields(obj):
            yield getattr(obj, f.name, None)
    else:
        if hasattr(obj, "__dict__") and not isinstance(obj, type):
            yield from vars(obj).values()
        for cls in type(obj).__mro__:
            for name in getattr(cls, "__slots__", ()):
                yield getattr(obj, name, None)


def _walk_buffers(obj) -> Iterator[tuple[int, int]]:
    """(pointer, bytes) of the memory every tensor and numpy array reachable from ``obj`` keeps alive
    (repeats included): a tensor's storage, a numpy array's outermost ndarray base. A view yields
    its base's memory, which it keeps alive, so that all views of one buffer count it once."""
    seen: set[int] = set()
    stack = [obj]
    while stack:
        o = stack.pop()
        if o is None or isinstance(o, _LEAVES) or id(o) in seen:
            continue
        seen.add(id(o))
        if isinstance(o, torch.Tensor):
            storage = o.untyped_storage()
            yield storage.data_ptr(), storage.nbytes()
        elif isinstance(o, np.ndarray):
            while isinstance(o.base, np.ndarray):
                o = o.base
            yield o.__array_interface__["data"][0], o.nbytes
        else:
            stack.extend(_children(o))


def tensor_pointers(obj) -> frozenset[int]:
    """The pointers of the memory the tensors and numpy arrays reachable from ``obj`` keep alive
    (their storages and bases; for :func:`tensor_bytes`' ``exclude``)."""
    return frozenset(key for key, _ in _walk_buffers(obj))


def tensor_bytes(obj, exclude: frozenset[int] = frozenset()) -> int:
    """Bytes of memory the tensors and numpy arrays reachable from ``obj`` keep alive: each storage
    (or outermost numpy base) once, those whose pointer is in ``exclude`` not at all."""
    sizes: dict[int, int] = {}
    for key, size in _walk_buffers(obj):
        if key not in exclude and key != 0:
            sizes[key] = size  # every view of a storage yields the storage's size
    return sum(sizes.values())


def tensor_cache(budget_bytes: int, size_of: Callable[[object], int] = tensor_bytes) -> ByteBoundedLRU:
    """A cache of the trainer's per-frame data, bounded to ``budget_bytes``: the least recently used
    value leaves first; a value's size is ``size_of(value)`` (default :func:`tensor_bytes`)."""
    return ByteBoundedLRU(budget_bytes, size_of)
