"""What every GL pass does with the objects it owns: render targets kept per size, and one release.

A pass owns GL objects on the context it was given (its programs, buffers, framebuffers). It frees
them once, on :meth:`GLObjectsOwner.release` or at the end of a ``with`` block; after the context
itself was released (which takes its objects with it) that is a no-op.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Hashable
from typing import Generic, Protocol, TypeVar

import moderngl
import numpy as np

from garmentnerf.gl.context import current, is_released

__all__ = ["GLObjectsOwner", "SupersampleTargets", "TargetCache"]


class _Releasable(Protocol):
    def release(self) -> None: ...


T = TypeVar("T", bound=_Releasable)


class TargetCache(Generic[T]):
    """Render targets by key (an image size, a channel count), made on first use; at most
    ``capacity`` of them are kept, the least recently used released first (None: all kept)."""

    def __init__(self, make: Callable[[Hashable], T], capacity: int | None = None) -> None:
        self._make = make
        self._capacity = capacity
        self._targets: OrderedDict[Hashable, T] = OrderedDict()

    def get(self, key: Hashable) -> T:
        """The targets of ``key`` (made now when absent; the GL context must be current)."""
        targets = self._targets.get(key)
        if targets is None:
            targets = self._make(key)
            self._targets[key] = targets
            while self._capacity is not None and len(self._targets) > self._capacity:
                self._targets.popitem(last=False)[1].release()
        else:
            self._targets.move_to_end(key)
        return targets

    def release(self) -> None:
        """Release every target kept (the GL context must be current)."""
        for targets in self._targets.values():
            targets.release()
        self._targets.clear()


class GLObjectsOwner:
    """Base of a pass owning GL objects on ``self.ctx``: :meth:`release` frees them once (a no-op
    once the context is released) through :meth:`_release_objects`, with the context current;
    ``with`` releases at the end of the block."""

    ctx: moderngl.Context
    _released: bool = False

    def _release_objects(self) -> None:
        """Free this pass's GL objects (the context is current)."""
        raise NotImplementedError

    def _check_not_released(self) -> None:
        if self._released:
            raise RuntimeError(f"{type(self).__name__} used after release()")

    def release(self) -> None:
        """Free the GL objects (the context itself stays; a no-op once the context is released)."""
        if self._released:
            return
        self._released = True
        if is_released(self.ctx):  # the context took its objects with it
            return
        with current(self.ctx):
            self._release_objects()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.release()


class SupersampleTargets:
    """A supersampled RGBA32F target with its depth buffer, and the resolved one it is box-filtered
    into, for one output size (``width x height``, the supersampled one ``factor`` times larger).

    Attributes:
        color, depth, fbo, scope: the supersampled target, its depth buffer, framebuffer and scope
            (depth test only).
        resolved, resolve_fbo, resolve_scope: the output-size target (no depth, nothing enabled).
        buffer: (height, width, 4) float32 host array the resolved target is read into.
    """

    def __init__(self, ctx: moderngl.Context, width: int, height: int, factor: int) -> None:
        big = (width * factor, height * factor)
        self.color = ctx.texture(big, 4, dtype="f4")
        self.color.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self.depth = ctx.depth_renderbuffer(big)
        self.fbo = ctx.framebuffer(color_attachments=[self.color], depth_attachment=self.depth)
        self.scope = ctx.scope(self.fbo, enable_only=moderngl.DEPTH_TEST)
        self.resolved = ctx.texture((width, height), 4, dtype="f4")
        self.resolve_fbo = ctx.framebuffer(color_attachments=[self.resolved])
        self.resolve_scope = ctx.scope(self.resolve_fbo, enable_only=moderngl.NOTHING)
        self.buffer = np.empty((height, width, 4), dtype=np.float32)

    def release(self) -> None:
        for obj in (self.scope, self.fbo, self.color, self.depth, self.resolve_scope, self.resolve_fbo,
                    self.resolved):
            obj.release()
