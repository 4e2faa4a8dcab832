"""The render worker: one background thread that renders the newest request (the neural garment)
and hands each result to a sink (the neural view's, which queues it for the palette layer).

Requests coalesce: while a render runs, newer requests replace each other and only the newest is
rendered next, so a moving camera never builds a queue. Each request gets a generation number; the
render function may call :meth:`RenderWorker.should_cancel` with it and give up early (return None)
when a newer request has arrived, which keeps a slow high-resolution render from blocking the next view.
Progress is guaranteed, though: once the screen has gone ``max_stale_s`` without a new result, the
render in flight is no longer cancelled and is shown even if a newer request exists (a camera that
moves every UI frame would otherwise cancel every render, and the layer would never update).
No GL here: the GL thread uploads what the sink received.

:class:`NeuralRenderer` is the neural layer's worker: it runs
:meth:`garmentnerf.render.session.RenderSession.render` for the newest :class:`NeuralRequest`
(frame, camera, quality), cancels a superseded render between chunks of samples, and hands the
decomposed maps (packed for the palette shader) to the GL thread. Its session and that session's
headless GL context live on the worker thread (:class:`~garmentnerf.viewer.render_thread.ThreadSession`).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from garmentnerf.perf.presets import VIEWER_LEVELS
from garmentnerf.render.frame_cache import DEFAULT_CACHE_MB
from garmentnerf.viewer.render_thread import ThreadSession


@dataclass
class WorkerStats:
    """What the worker has done (read by the UI thread for the overlay and the bench)."""

    renders: int = 0
    dropped: int = 0        # requests superseded before they started, or given up as stale
    errors: int = 0
    last_ms: float = 0.0    # wall time of the last delivered render (request taken -> result handed over)
    last_error: str = ""


class RenderWorker:
    """Args:
        render: ``render(request, generation) -> result or None``; runs on the worker thread.
        sink: ``sink(result, request, generation)``; runs on the worker thread after a render
            (must be thread-safe, e.g. ``PaletteLayer.submit``).
        idle_work: ``idle_work() -> bool``, one short step of background work (e.g. precomputing
            one frame) run on the worker thread whenever no request waits; True: there is more.
            A new request waits for at most one step.
    """

    def __init__(self, render: Callable[[Any, int], Any], sink: Callable[[Any, Any, int], None],
                 name: str = "garmentnerf-render", max_stale_s: float = 0.5,
                 idle_work: Callable[[], bool] | None = None) -> None:
        self._render = render
        self._sink = sink
        self._idle_work = idle_work
        self._idle_pending = idle_work is not None  # cleared when idle_work has nothing left to do
        self._cond = threading.Condition()
        self._request: Any = None
        self._has_request = False
        self._generation = 0
        self._stop = False
        self._busy = False
        self.max_stale_s = float(max_stale_s)
        self._last_delivery = time.monotonic()
        self.stats = WorkerStats()
        self._thread = threading.Thread(target=self._loop, name=name, daemon=True)
        self._thread.start()

    def request(self, request: Any) -> int:
        """Ask for a render of ``request`` (replacing any request not yet started); returns its generation."""
        with self._cond:
            if self._has_request:
                self.stats.dropped += 1
            self._generation += 1
            self._request, self._has_request = request, True
            self._cond.notify()
            return self._generation

    def should_cancel(self, generation: int) -> bool:
        """True when the render of ``generation`` should give up: it is stale *and* the screen got
        a result less than ``max_stale_s`` ago (otherwise finishing it is the better choice)."""
        with self._cond:
            if self._stop:
                return True
            if generation == self._generation:
                return False
            return time.monotonic() - self._last_delivery < self.max_stale_s

    def idle(self) -> bool:
        """No render running or waiting (background idle work does not count)."""
        with self._cond:
            return not self._busy and not self._has_request

    def wake_idle(self) -> None:
        """Run the idle work again (its situation changed, e.g. a larger budget)."""
        with self._cond:
            self._idle_pending = self._idle_work is not None
            self._cond.notify()

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
                while not self._has_request and not self._stop and not self._idle_pending:
                    self._cond.wait()
                if self._stop:
                    return
                run_idle = not self._has_request
            if run_idle:
                self._run_idle_step()
                continue
            with self._cond:
                if self._stop:
                    return
                request, generation = self._request, self._generation
                self._request, self._has_request, self._busy = None, False, True
            try:
                start = time.perf_counter()
                result = self._render(request, generation)
                if result is None or self.should_cancel(generation):
                    self.stats.dropped += 1
                else:
                    self._sink(result, request, generation)
                    with self._cond:
                        self._last_delivery = time.monotonic()
                    self.stats.renders += 1
                    self.stats.last_ms = 1000.0 * (time.perf_counter() - start)
            except Exception as exc:  # noqa: BLE001 - a failed render must not kill the UI's worker
                self.stats.errors += 1
                self.stats.last_error = f"{type(exc).__name__}: {exc}"
            finally:
                with self._cond:
                    self._busy = False
                    self._idle_pending = self._idle_work is not None  # a new request may give it work

    def _run_idle_step(self) -> None:
        try:
            more = bool(self._idle_work())
        except Exception as exc:  # noqa: BLE001 - background work must not kill the worker either
            self.stats.errors += 1
            self.stats.last_error = f"{type(exc).__name__}: {exc}"
            more = False
        with self._cond:
            self._idle_pending = more and self._idle_pending


# ---- the neural render worker -------------------------------------------------------------------------
@dataclass(frozen=True)
class NeuralRequest:
    """What to render: body ``frame`` of ``motion`` (a scene sequence or motion name) seen by ``camera``
    with render ``preset`` at ``quality`` (None: the preset's own resolution), composed as
    ``composition`` (:data:`~garmentnerf.render.session.COMPOSITIONS`); ``gt_camera`` names the scene
    camera whose ground truth to load (or None)."""

    frame: int
    camera: Any
    quality: float | None
    motion: Any = None
    gt_camera: str | None = None
    preset: str = VIEWER_LEVELS[-1]
    composition: str = "auto"


@dataclass
class NeuralResult:
    """One finished neural frame, as numpy for the GL thread.

    Attributes:
        layers: (2 + P, h, w, 4) float32 maps packed by :func:`~garmentnerf.viewer.palette_layer.pack_maps`.
        depth: (h, w) float32 camera-space z, 0 where empty.
        image_size: (W, H) of the requested camera; render_size: (w, h) actually rendered.
        quality, preset: what was rendered; frame: the clip frame (clamped to the clip).
        timings: stage -> ms (``RenderSession.render``'s); cached_frame: the frame's features were cached.
        ground_truth: (H, W, 3) of the request's scene camera, or None; counts: sample counts.
        body: the posed body the palette layer draws under the garment
            (:class:`~garmentnerf.viewer.palette_layer.BodyView`; the ``raster_body`` composition), or None.
    """

    layers: Any
    depth: Any
    image_size: tuple[int, int]
    render_size: tuple[int, int]
    quality: float
    frame: int
    timings: dict
    cached_frame: bool
    ground_truth: Any = None
    preset: str = ""
    counts: dict | None = None
    body: Any = None


class NeuralRenderer:
    """Runs :class:`garmentnerf.render.session.RenderSession` on a :class:`RenderWorker` thread.

    The session (and the headless GL context its input passes need) is made *on the worker thread*
    at the first request (:class:`~garmentnerf.viewer.render_thread.ThreadSession`), so the window's
    GL context is never touched from there. Each render polls :meth:`RenderWorker.should_cancel`
    between chunks of samples: a newer request cancels it
    (:class:`~garmentnerf.model.pipeline.RenderCancelled`, counted as dropped). Results go to
    ``sink(result, request)``, errors to :attr:`RenderWorker.stats` (``last_error``), which the
    window shows.

    Args:
        run: a :class:`~garmentnerf.train.run.LoadedRun`.
        sink: called on the worker thread with each :class:`NeuralResult` and its request.
        motion: the session's first motion (None: the run scene's first training sequence).
    """

    def __init__(self, run, sink: Callable[[NeuralResult, NeuralRequest], None], motion: Any = None) -> None:
        self.run = run
        self._sink = sink
        self._motion = motion
        self._cache_mb = DEFAULT_CACHE_MB
        self._thread_session = ThreadSession(run, cache_mb=self._cache_mb, cache_half=True)  # worker thread only
        self._gt_cache: dict = {}
        self.last: NeuralResult | None = None
        self.worker = RenderWorker(self._render, self._deliver, name="garmentnerf-neural", idle_work=self._precompute)

    @property
    def stats(self) -> WorkerStats:
        return self.worker.stats

    def request(self, request: NeuralRequest) -> int:
        return self.worker.request(request)

    def _ground_truth(self, session, request: NeuralRequest):
        """(H, W, 3) ground truth of the request's scene camera and frame, or None (worker thread)."""
        scene = session.scene
        if request.gt_camera is None or scene is None or session.sequence is None:
            return None
        if request.gt_camera not in scene.camera_names():
            return None
        key = (session.sequence, request.gt_camera, request.frame)
        if key not in self._gt_cache:
            from garmentnerf.data.scene_images import SceneImages

            images = self._thread_session.helper("images", lambda: SceneImages(scene, body_model=session.body))
            rgb, _ = images.image(session.sequence, request.gt_camera, request.frame)
            self._gt_cache.clear()  # one image is enough: the view shows one frame
            self._gt_cache[key] = rgb
        return self._gt_cache[key]

    def _render(self, request: NeuralRequest, generation: int):
        from garmentnerf.model.pipeline import RenderCancelled

        if request is _CLOSE:
            self._thread_session.close()
            return None
        from garmentnerf.viewer.palette_layer import BodyView, pack_frame

        session = self._thread_session.session(request.motion if request.motion is not None else self._motion)
        frame = min(max(0, int(request.frame)), session.num_frames - 1)
        session.frames.set_playhead(frame)
        session.set_composition(request.composition)
        try:
            nf = session.render(frame, request.camera, request.quality, preset=request.preset,
                                should_cancel=lambda: self.worker.should_cancel(generation), body_layer=False)
        except RenderCancelled:
            return None
        body = None
        if nf.body is not None:  # the window draws the body layer at the size it shows it
            body = BodyView(nf.body[0].numpy(), nf.body[1].numpy(), nf.camera)
        return NeuralResult(pack_frame(nf.maps), nf.depth, nf.output_size, nf.render_size, nf.quality, frame,
                            nf.timings, nf.cached_frame, self._ground_truth(session, request), nf.preset,
                            dict(nf.counts), body)

    def _precompute(self) -> bool:
        """Idle work: the next frame of the clip nearest to the playhead (see
        :meth:`RenderSession.precompute_next`); False when there is nothing (left) to do."""
        session = self._thread_session.current
        return session is not None and session.precompute_next() is not None

    def cache_status(self) -> dict | None:
        """The frame cache as the UI shows it (thread-safe): ``ready`` (sorted frames),
        ``frames`` (in the clip), ``bytes``, ``budget_bytes``; None before the first render."""
        session = self._thread_session.current
        if session is None:
            return None
        cache = session.frames
        return {"ready": cache.ready_frames(), "frames": session.num_frames, "bytes": cache.nbytes,
                "budget_bytes": cache.budget_bytes}

    def set_cache_mb(self, megabytes: float) -> None:
        """Change the frame cache's memory bound (frames farthest from the playhead leave first)."""
        if not megabytes >= 0:
            raise ValueError(f"frame cache budget must be >= 0 MiB, got {megabytes!r}")
        self._cache_mb = float(megabytes)
        self._thread_session.session_options["cache_mb"] = self._cache_mb  # a session made later
        session = self._thread_session.current
        if session is not None:
            session.frames.set_budget_mb(self._cache_mb)
        self.worker.wake_idle()

    def _deliver(self, result: NeuralResult, request: NeuralRequest, generation: int) -> None:
        self.last = result
        self._sink(result, request)

    def stop(self, timeout: float = 30.0) -> None:
        """Cancel any render, free the worker's GL objects on its thread, and end it."""
        self.worker.request(_CLOSE)
        self.worker.wait_idle(timeout)
        self.worker.stop(timeout)


_CLOSE = NeuralRequest(-1, None, 0.0)
