"""Finished neural frames of one view, kept under a memory bound: the previewer's render-ahead cache.

A video editor's render cache: once the worker has rendered a frame for the current view (camera,
quality, preset, motion, composition: the *view key*, :meth:`garmentnerf.viewer.worker.NeuralRequest.view_key`),
the frame is kept here, so playing or scrubbing over it shows it without any network evaluation.
An entry is a compact :class:`~garmentnerf.viewer.worker.NeuralResult` (the decomposed maps cut to
the character, :func:`~garmentnerf.viewer.palette_layer.crop_to_content`, in float16): the
palette maps, not RGB, so recolouring the whole rendered clip stays a shader uniform.

View
    The cache holds the frames of one view key at a time. :meth:`FinishedFrames.set_view` with
    another key (an orbit, another quality, preset, motion or composition) drops them all; the
    palette is not part of the key, so a palette change keeps them. A frame :meth:`put` for
    another key than the current one is not kept.

Memory bound and order
    :attr:`FinishedFrames.budget_bytes` bounds :attr:`FinishedFrames.nbytes` (the arrays the entries
    hold). The store is a :class:`~garmentnerf.byte_lru.ByteBoundedLRU` whose eviction order is the
    playhead's (:class:`FarthestAheadOfPlayhead`): when full, the frame farthest *ahead* of the
    playhead (counted forwards, round the clip: a frame just behind the playhead is needed last)
    leaves first, and :meth:`FinishedFrames.worth_rendering` says whether a missing frame would be kept.

Threads
    The render worker writes, the UI thread reads; every method takes the cache's lock.
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np

from garmentnerf.byte_lru import ByteBoundedLRU

#: Default memory bound of the render-ahead cache (MiB). The bundled demo's frames at ``full`` in a
#: 1280 x 800 window take about 5 MB each once cut to the character.
DEFAULT_FINISHED_MB = 1024.0


def _ahead(frame: int, playhead_frame: int, n_frames: int) -> int:
    """Frames from the playhead forwards to ``frame``, round the clip (a frame behind the playhead
    of a clip that does not loop is only needed again after a seek: it counts as far ahead too)."""
    return (int(frame) - int(playhead_frame)) % max(int(n_frames), 1)


def result_nbytes(result: Any) -> int:
    """Bytes the arrays of a :class:`~garmentnerf.viewer.worker.NeuralResult` hold (maps, depth,
    ground truth, the body's vertices and normals)."""
    arrays = [result.layers, result.depth, result.ground_truth]
    if result.body is not None:
        arrays += [result.body.vertices, result.body.normals]
    return int(sum(np.asarray(a).nbytes for a in arrays if a is not None))


class FarthestAheadOfPlayhead:
    """The render-ahead cache's eviction order: frames farthest ahead of :attr:`frame` (the playhead
    of the last frame put) in a clip of :attr:`n_frames` (at least the largest frame kept + 1),
    counted forwards round the clip, first; of two as far, the later one first."""

    def __init__(self, frame: int = 0, n_frames: int = 1) -> None:
        self.frame = int(frame)
        self.n_frames = int(n_frames)

    def __call__(self, frames: list[int]) -> list[int]:
        n = max(self.n_frames, max(frames, default=0) + 1)
        return sorted(frames, key=lambda f: (_ahead(f, self.frame, n), f), reverse=True)


class FinishedFrames:
    """See the module docstring.

    Args:
        budget_mb: the memory bound in MiB (>= 0; 0 keeps nothing).
    """

    def __init__(self, budget_mb: float = DEFAULT_FINISHED_MB) -> None:
        self._lock = threading.Lock()
        self._view: Any = None
        self._playhead = FarthestAheadOfPlayhead()
        self._frames: ByteBoundedLRU[int, Any] = ByteBoundedLRU(0, result_nbytes, self._playhead)
        self.invalidations = 0
        self.set_budget_mb(budget_mb)

    # ---- settings ---------------------------------------------------------------------------------
    def set_budget_mb(self, budget_mb: float) -> None:
        """Change the bound; frames farthest ahead of the last playhead leave until it holds."""
        if not budget_mb >= 0:
            raise ValueError(f"render-ahead budget must be >= 0 MiB, got {budget_mb!r}")
        with self._lock:
            self._frames.set_budget(int(budget_mb * 2**20))

    def set_view(self, key: Any) -> bool:
        """The view now shown; returns True when it differs from the cached one (whose frames are
        dropped: they show another view)."""
        with self._lock:
            if key == self._view:
                return False
            self._view = key
            if len(self._frames):
                self.invalidations += 1
            self._frames.clear()
            return True

    # ---- state ------------------------------------------------------------------------------------
    @property
    def budget_bytes(self) -> int:
        """The memory bound in bytes."""
        return self._frames.budget_bytes

    @property
    def view(self) -> Any:
        with self._lock:
            return self._view

    @property
    def nbytes(self) -> int:
        with self._lock:
            return self._frames.nbytes

    def frames(self, key: Any) -> set[int]:
        """The frames rendered for view ``key`` (empty for another view)."""
        with self._lock:
            return set(self._frames.keys()) if key == self._view else set()

    def get(self, key: Any, frame: int) -> Any:
        """The finished frame ``frame`` of view ``key``, or None."""
        with self._lock:
            if key != self._view:
                return None
            return self._frames.peek(int(frame))

    def latest_behind(self, key: Any, frame: int, n_frames: int, loop: bool) -> Any:
        """The finished frame of view ``key`` nearest behind ``frame`` or on it (looping: within half
        a clip behind), or None: what a playing clip shows while the playhead's own frame is not
        rendered, so the image is the newest frame the playhead has reached, even when the UI's
        redraws skipped the frame it was finished for."""
        with self._lock:
            if key != self._view:
                return None
            best, best_d = None, None
            for f, result in self._frames.items():
                d = int(frame) - f
                if loop:
                    d %= n_frames
                    if d > n_frames // 2:
                        continue
                elif d < 0:
                    continue
                if best_d is None or d < best_d:
                    best, best_d = result, d
            return best

    # ---- use --------------------------------------------------------------------------------------
    def put(self, key: Any, frame: int, result: Any, playhead_frame: int, n_frames: int) -> bool:
        """Keep ``result`` (a compact NeuralResult) as frame ``frame`` of view ``key``, the playhead
        being at ``playhead_frame`` of a clip of ``n_frames``; evicts the frames farthest ahead until
        the bound holds. Returns whether it was kept (not for another view, nor when it is itself
        the farthest ahead of a full cache)."""
        frame = int(frame)
        with self._lock:
            if key != self._view:
                return False
            self._playhead.frame, self._playhead.n_frames = int(playhead_frame), int(n_frames)
            self._frames.put(frame, result)
            return frame in self._frames

    def worth_rendering(self, frame: int, playhead_frame: int, n_frames: int) -> bool:
        """Whether a missing ``frame`` would be kept: the cache has room for a frame of the last
        size, or ``frame`` is nearer ahead of the playhead than the farthest one stored (so a full
        cache never thrashes)."""
        with self._lock:
            frame_bytes = max(self._frames.last_put_nbytes, 1)  # the last frame's size: what the next takes
            if self.budget_bytes < frame_bytes:
                return False
            if self._frames.nbytes + frame_bytes <= self.budget_bytes or not len(self._frames):
                return True
            farthest = max(_ahead(f, playhead_frame, n_frames) for f in self._frames.keys())
            return _ahead(frame, playhead_frame, n_frames) < farthest

    def clear(self) -> None:
        with self._lock:
            self._frames.clear()


__all__ = ["FinishedFrames", "FarthestAheadOfPlayhead", "DEFAULT_FINISHED_MB", "result_nbytes"]
