"""A render session that lives on its own thread: the one helper of the preview worker and the exporter.

A :class:`~garmentnerf.render.session.RenderSession` must only be used from one thread, and its GL
passes need a GL context current on that thread. The window's context belongs to the UI thread, so
a thread that renders the network (the preview worker, :mod:`~garmentnerf.viewer.worker`; the
exporter, :mod:`~garmentnerf.viewer.exporting`) makes a headless EGL context of its own, the session
on it, and whatever else it draws with (the ground-truth image renderer, a GL scene for body-only
videos), all lazily *on that thread*, and frees them there when it ends. :class:`ThreadSession` is
that bookkeeping, written once.

Thread contract: every method is called on the owning thread only (nothing here locks).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from garmentnerf.gl.context import create_context
from garmentnerf.render.session import RenderSession


class ThreadSession:
    """The owning thread's headless GL context, its render session and its helper objects.

    Args:
        run: the :class:`~garmentnerf.runs.LoadedRun` the session renders (None: no session,
            only the GL context and helpers, e.g. an exporter of body-only videos).
        session_options: keyword arguments of :class:`~garmentnerf.render.session.RenderSession`
            (``cache_mb``, ``cache_half`` ...).
    """

    def __init__(self, run=None, **session_options) -> None:
        self.run = run
        self.session_options = dict(session_options)
        self._ctx = None
        self._session = None
        self._motion: Any = None
        self._helpers: dict[str, Any] = {}

    @property
    def ctx(self):
        """This thread's headless moderngl context (made at the first use; never the window's)."""
        if self._ctx is None:
            self._ctx = create_context(headless=True)
        return self._ctx

    @property
    def current(self):
        """The session if one was made, else None (never makes one)."""
        return self._session

    def session(self, motion: Any):
        """The session rendering ``motion`` (a scene sequence or motion spec): made at the first
        call, switched to ``motion`` (:meth:`RenderSession.set_motion`) when it differs."""
        if self._session is None:
            if self.run is None:
                raise ValueError("a neural render needs a run (garmentnerf view --run DIR)")

            self._session = RenderSession(self.run, self.ctx, motion, **self.session_options)
            self._motion = motion
        elif motion != self._motion:
            self._session.set_motion(motion)
            self._motion = motion
        return self._session

    def helper(self, name: str, make: Callable[[], Any]) -> Any:
        """The helper object ``name``, made by ``make()`` at the first call (on this thread, with
        :attr:`ctx` available) and freed by :meth:`close` (its ``close()`` or ``release()``)."""
        if name not in self._helpers:
            self._helpers[name] = make()
        return self._helpers[name]

    def close(self) -> None:
        """Free the session, the helpers, then the GL context (best effort; idempotent)."""
        owned = [self._session, *self._helpers.values(), self._ctx]
        self._session, self._helpers, self._ctx, self._motion = None, {}, None, None
        for obj in owned:
            if obj is None:
                continue
            free = getattr(obj, "close", None) or obj.release
            try:
                free()
            except Exception:  # noqa: BLE001 - best effort at shutdown
                pass
