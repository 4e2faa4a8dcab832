"""The render worker: one background thread that renders the newest request (the neural garment,
once a trained model exists) and hands each result to a sink (:meth:`NeuralLayer.submit`).

Requests coalesce: while a render runs, newer requests replace each other and only the newest is
rendered next, so a moving camera never builds a queue. Each request gets a generation number; the
render function may call :meth:`RenderWorker.is_stale` with it and give up early (return None) when a
newer request has arrived, which keeps a slow high-resolution render from blocking the next view.
No GL here: the GL thread uploads what the sink received.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any


@dataclass
class WorkerStats:
    renders: int = 0
    dropped: int = 0        # requests superseded before they started, or given up as stale
    errors: int = 0
    last_ms: float = 0.0
    last_error: str = ""


class RenderWorker:
    """Args:
        render: ``render(request, generation) -> result or None``; runs on the worker thread.
        sink: ``sink(result, request, generation)``; runs on the worker thread after a render
            (must be thread-safe, e.g. ``NeuralLayer.submit``).
    """

    def __init__(self, render: Callable[[Any, int], Any], sink: Callable[[Any, Any, int], None],
                 name: str = "garmentnerf-render") -> None:
        self._render = render
        self._sink = sink
        self._cond = threading.Condition()
        self._request: Any = None
        self._has_request = False
        self._generation = 0
        self._stop = False
        self._busy = False
        self.stats = WorkerStats()
        self._thread = threading.Thread(target=self._loop, name=name, daemon=True)
        self._thread.start()

    @property
    def generation(self) -> int:
        with self._cond:
            return self._generation

    def request(self, request: Any) -> int:
        """Ask for a render of ``request`` (replacing any request not yet started); returns its generation."""
        with self._cond:
            if self._has_request:
                self.stats.dropped += 1
            self._generation += 1
            self._request, self._has_request = request, True
            self._cond.notify()
            return self._generation

    def is_stale(self, generation: int) -> bool:
        """True when a newer request exists (or the worker is stopping)."""
        with self._cond:
            return self._stop or generation != self._generation

    def idle(self) -> bool:
        with self._cond:
            return not self._busy and not self._has_request

    def wait_idle(self, timeout: float = 10.0) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.idle():
                return True
            time.sleep(0.002)
        return self.idle()

    def stop(self, timeout: float = 5.0) -> None:
        with self._cond:
            self._stop = True
            self._cond.notify()
        self._thread.join(timeout)

    def _loop(self) -> None:
        while True:
            with self._cond:
                while not self._has_request and not self._stop:
                    self._cond.wait()
                if self._stop:
                    return
                request, generation = self._request, self._generation
                self._request, self._has_request, self._busy = None, False, True
            try:
                start = time.perf_counter()
                result = self._render(request, generation)
                if result is None or self.is_stale(generation):
                    self.stats.dropped += 1
                else:
                    self._sink(result, request, generation)
                    self.stats.renders += 1
                    self.stats.last_ms = 1000.0 * (time.perf_counter() - start)
            except Exception as exc:  # noqa: BLE001 - a failed render must not kill the UI's worker
                self.stats.errors += 1
                self.stats.last_error = f"{type(exc).__name__}: {exc}"
            finally:
                with self._cond:
                    self._busy = False
