"""The per-frame features of a clip, kept in half precision under a memory bound.

Everything a body frame costs before any camera is involved (GL passes, E, G_img, G_en: the
:class:`~garmentnerf.model.frame_context.FrameFeatures`) is computed once per frame and kept here,
so that playing, scrubbing and orbiting a ready frame cost only the per-view work.

Storage
    With ``half`` (the previewer's setting) the feature maps (F^s_t, the reference images, F^d_t)
    and the reference depth are stored in float16 and returned in float32 (a relative rounding of
    5e-4, half the memory); without it they are kept as computed, so a cached frame renders
    exactly as a fresh one (evaluation and benchmarks). The posed vertices, their normals and the box stay float32 (closest points need
    them exactly). The bound closest-point search of a frame (a KD-tree and face tables, several MB)
    is not stored: it is rebuilt when the frame is used, and the last :attr:`bound_frames` frames
    keep theirs.

Memory bound and order
    :attr:`budget_bytes` bounds what the stored frames hold (:attr:`nbytes`). The store is a
    :class:`~garmentnerf.byte_lru.ByteBoundedLRU` whose eviction order is the playhead's
    (:class:`FarthestFromPlayhead`): when full, the frame farthest from the playhead goes first
    (of two as far, the later one), and :meth:`next_to_compute` names the missing frame nearest to
    the playhead, or None once the budget is spent on frames nearer than any missing one (so a full
    cache never thrashes).

Threads
    One writer (the render worker), any number of readers (the UI asks :meth:`ready_frames` and
    :attr:`nbytes`): every method takes the cache's lock.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import replace
from typing import Callable

import torch

from garmentnerf.byte_lru import ByteBoundedLRU

#: Default memory bound of a session's frame cache (the bundled model's frames take 1.4 MB each,
#: so its 170-frame demo clip fits in 240 MB).
DEFAULT_CACHE_MB = 512.0
#: Frames whose bound closest-point search is kept (the rest rebuild it on use).
DEFAULT_BOUND_FRAMES = 4
_HALF_FIELDS = ("dynamic_features", "reference_images", "detail_features", "reference_depth")


def _nbytes(t: torch.Tensor | None) -> int:
    return 0 if t is None else t.numel() * t.element_size()


def stored_frame_bytes(features) -> int:
    """Bytes a stored frame (FrameFeatures without its surface) holds: its feature maps and reference
    depth (at their stored precision), posed vertices, normals and box."""
    return sum(_nbytes(getattr(features, k)) for k in (*_HALF_FIELDS, "posed_vertices", "vertex_normals", "aabb"))


class FarthestFromPlayhead:
    """The frame cache's eviction order: frames farthest from :attr:`frame` (the playhead) first, of
    two as far the later one first."""

    def __init__(self, frame: int = 0) -> None:
        self.frame = int(frame)

    def __call__(self, frames: list[int]) -> list[int]:
        return sorted(frames, key=lambda f: (abs(f - self.frame), f), reverse=True)


class FrameCache:
    """See the module docstring.

    Args:
        bind: ``bind(posed_vertices) -> bound body`` (the model's ``projector.bind``), used to
            rebuild a frame's closest-point search.
        budget_mb: the memory bound in MiB.
        bound_frames: frames whose bound search is kept.
        half: store the feature maps in float16.
    """

    def __init__(self, bind: Callable[[torch.Tensor], object], budget_mb: float = DEFAULT_CACHE_MB,
                 bound_frames: int = DEFAULT_BOUND_FRAMES, half: bool = False) -> None:
        self._bind = bind
        self.half = bool(half)
        self._lock = threading.Lock()
        self._playhead = FarthestFromPlayhead()
        self._frames: ByteBoundedLRU[int, object] = ByteBoundedLRU(0, stored_frame_bytes, self._playhead)
        self._bound: OrderedDict[int, object] = OrderedDict()
        self._bound_frames = max(1, int(bound_frames))
        self.set_budget_mb(budget_mb)

    # ---- settings -------------------------------------------------------------------------------------
    def set_budget_mb(self, budget_mb: float) -> None:
        """Change the bound (MiB, >= 0); frames farthest from the playhead leave until it holds."""
        if not budget_mb >= 0:
            raise ValueError(f"frame cache budget must be >= 0 MiB, got {budget_mb!r}")
        with self._lock:
            for frame in self._frames.set_budget(int(budget_mb * 2**20)):
                self._bound.pop(frame, None)

    def set_playhead(self, frame: int) -> None:
        with self._lock:
            self._playhead.frame = int(frame)

    # ---- state ----------------------------------------------------------------------------------------
    @property
    def budget_bytes(self) -> int:
        """The memory bound in bytes."""
        return self._frames.budget_bytes

    @property
    def nbytes(self) -> int:
        """Bytes the stored frames hold."""
        with self._lock:
            return self._frames.nbytes

    def ready_frames(self) -> list[int]:
        """Sorted frames whose features are stored."""
        with self._lock:
            return sorted(self._frames.keys())

    def __contains__(self, frame: int) -> bool:
        with self._lock:
            return int(frame) in self._frames

    def __len__(self) -> int:
        with self._lock:
            return len(self._frames)

    # ---- use ------------------------------------------------------------------------------------------
    def get(self, frame: int):
        """The stored features of ``frame`` in float32 with a bound surface, or None."""
        frame = int(frame)
        with self._lock:
            feats = self._frames.peek(frame)
            surface = self._bound.get(frame)
            if surface is not None:
                self._bound.move_to_end(frame)
        if feats is None:
            return None
        if surface is None:
            surface = self._bind(feats.posed_vertices)
            with self._lock:
                self._bound[frame] = surface
                while len(self._bound) > self._bound_frames:
                    self._bound.popitem(last=False)
        if not self.half:
            return replace(feats, surface=surface)
        full = {k: None if getattr(feats, k) is None else getattr(feats, k).float() for k in _HALF_FIELDS}
        return replace(feats, surface=surface, **full)

    def put(self, frame: int, features) -> bool:
        """Store ``features`` (FrameFeatures) of ``frame``; False when even an empty cache has no
        room for it, or it is farther from the playhead than every stored frame of a full cache."""
        frame = int(frame)
        stored = replace(features.detach(), surface=None)
        if self.half:
            stored = replace(stored, **{k: None if getattr(stored, k) is None else getattr(stored, k).to(torch.float16)
                                        for k in _HALF_FIELDS})
        with self._lock:
            evicted = self._frames.put(frame, stored)
            self._bound[frame] = features.surface
            self._bound.move_to_end(frame)
            while len(self._bound) > self._bound_frames:
                self._bound.popitem(last=False)
            for gone in evicted:
                self._bound.pop(gone, None)
            return frame in self._frames

    def next_to_compute(self, num_frames: int) -> int | None:
        """The missing frame in ``[0, num_frames)`` nearest to the playhead (ties: the later one,
        playback runs forwards), or None when every frame is stored or the budget is spent on
        nearer frames."""
        with self._lock:
            head = min(max(self._playhead.frame, 0), max(num_frames - 1, 0))
            missing = None
            for d in range(num_frames):
                for f in (head + d, head - d) if d else (head,):
                    if 0 <= f < num_frames and f not in self._frames:
                        missing = f
                        break
                if missing is not None:
                    break
            frame_bytes = max(self._frames.last_put_nbytes, 1)  # the last frame's size: what the next takes
            if missing is None or self.budget_bytes < frame_bytes:
                return None
            if self._frames.nbytes + frame_bytes <= self.budget_bytes:
                return missing
            farthest = max(abs(f - head) for f in self._frames.keys())
            return missing if abs(missing - head) < farthest else None

    def clear(self) -> None:
        with self._lock:
            self._frames.clear()
            self._bound.clear()


__all__ = ["FrameCache", "FarthestFromPlayhead", "stored_frame_bytes", "DEFAULT_CACHE_MB", "DEFAULT_BOUND_FRAMES"]
