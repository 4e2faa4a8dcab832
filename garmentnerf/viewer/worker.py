"""The render worker: one background thread that renders the newest request (the neural garment)
and hands each result to a sink (the neural view's, which queues it for the UI thread).

Requests coalesce: while a render runs, newer requests replace each other and only the newest is
rendered next, so a moving camera never builds a queue. Each request gets a generation number; the
render function may call :meth:`RenderWorker.should_cancel` with it and give up early (return None)
when a newer request makes its work worthless (``superseded``; by default any newer request does).
Progress is guaranteed, though: once the screen has gone ``max_stale_s`` without a new result, the
render in flight is no longer cancelled and is shown even if a newer request exists (a camera that
moves every UI frame would otherwise cancel every render, and the layer would never update).
A request may *stand* (``follow_up``): after its render the worker asks whether to render it again
(the next frame of a playing clip, the next frame to render ahead) before any idle work.
No GL here: the GL thread uploads what the UI thread chose to show.

:class:`NeuralRenderer` is the neural layer's worker: it runs
:meth:`garmentnerf.render.session.RenderSession.render` for the newest :class:`NeuralRequest`
(camera, quality, and the timeline's playhead clock), chooses which frame
(:mod:`~garmentnerf.viewer.playback`: the one the playhead will be at when the render ends, then
the frames ahead), cancels a superseded render between chunks of samples, and keeps finished
frames (the decomposed maps packed for the palette shader) in its render-ahead cache
(:class:`~garmentnerf.viewer.finished_frames.FinishedFrames`). Its session and that session's
headless GL context live on the worker thread (:class:`~garmentnerf.viewer.render_thread.ThreadSession`).
"""

from __future__ import annotations

import functools
import threading
import time
from collections.abc import Callable, Container
from dataclasses import dataclass
from typing import Any

from garmentnerf.bake.views import view_from_render
from garmentnerf.data.scene_images import SceneImages
from garmentnerf.model.pipeline import RenderCancelled
from garmentnerf.render.frame_cache import DEFAULT_CACHE_MB
from garmentnerf.render.presets import VIEWER_LEVELS
from garmentnerf.viewer.finished_frames import DEFAULT_FINISHED_MB, FinishedFrames
from garmentnerf.viewer.palette_layer import BodyView, crop_to_content, pack_frame
from garmentnerf.viewer.playback import (
    PlayheadClock,
    RenderTime,
    frame_of,
    next_unrendered,
    predict_target_frame,
    render_superseded,
)
from garmentnerf.viewer.render_thread import ThreadSession

#: What a render function returns when it found nothing to render (neither started nor dropped).
NOTHING = object()


@dataclass
class WorkerStats:
    """What the worker has done (read by the UI thread for the overlay and the bench)."""

    renders: int = 0
    dropped: int = 0        # requests superseded before they started, or renders abandoned
    errors: int = 0
    last_ms: float = 0.0    # wall time of the last delivered render (request taken -> result handed over)
    last_error: str = ""
    started: int = 0        # renders begun (a render function that returned NOTHING began none)
    abandoned: int = 0      # renders begun and then given up (superseded), part of ``dropped``

    @property
    def completed_share(self) -> float | None:
        """Finished renders over started ones (None before any started)."""
        return self.renders / self.started if self.started else None


class RenderWorker:
    """Args:
        render: ``render(request, generation) -> result, None (given up) or NOTHING (nothing to
            render)``; runs on the worker thread.
        sink: ``sink(result, request, generation)``; runs on the worker thread after a render
            (must be thread-safe, e.g. ``PaletteLayer.submit``).
        idle_work: ``idle_work() -> bool``, one short step of background work (e.g. precomputing
            one frame) run on the worker thread whenever no request waits; True: there is more.
            A new request waits for at most one step.
        superseded: ``superseded(running, newest) -> bool``: whether the render of request
            ``running`` is worth nothing now that ``newest`` was requested (default: always, any
            newer request supersedes). Called by :meth:`should_cancel`.
        follow_up: ``follow_up(request) -> seconds or None``, asked after each render of the newest
            request while no newer one waits: 0 renders the same request again (a standing request:
            render-ahead, the next frame of a playing clip), a positive number asks again after that
            long, None ends it. These renders come before the idle work, and do not count as busy
            (:meth:`idle`) but do as not :meth:`quiet`.
    """

    def __init__(self, render: Callable[[Any, int], Any], sink: Callable[[Any, Any, int], None],
                 name: str = "garmentnerf-render", max_stale_s: float = 0.5,
                 idle_work: Callable[[], bool] | None = None,
                 superseded: Callable[[Any, Any], bool] | None = None,
                 follow_up: Callable[[Any], float | None] | None = None) -> None:
        self._render = render
        self._sink = sink
        self._idle_work = idle_work
        self._superseded = superseded
        self._follow_up = follow_up
        self._idle_pending = idle_work is not None  # cleared when idle_work has nothing left to do
        self._cond = threading.Condition()
        self._request: Any = None
        self._has_request = False
        self._generation = 0
        self._newest: Any = None     # the newest request (waiting or taken)
        self._running: Any = None    # the request being rendered
        self._following = False      # a standing request renders or is to be asked (follow_up)
        self._polling = False        # ... or is to be asked again after a while (nothing to do now)
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
            self._request, self._has_request, self._newest = request, True, request
            self._cond.notify()
            return self._generation

    def should_cancel(self, generation: int, progress: bool = True) -> bool:
        """True when the render of ``generation`` should give up: a newer request supersedes it
        (``superseded``) *and*, with ``progress``, the screen got a result less than
        ``max_stale_s`` ago (otherwise finishing it is the better choice; a render nobody would
        see before it is needed, e.g. one ahead of the playhead, passes ``progress=False``)."""
        with self._cond:
            if self._stop:
                return True
            if generation == self._generation:
                return False
            if progress and time.monotonic() - self._last_delivery >= self.max_stale_s:
                return False
            running, newest = self._running, self._newest
        return True if self._superseded is None else bool(self._superseded(running, newest))

    def idle(self) -> bool:
        """No render of a new request running or waiting (standing renders and idle work do not count)."""
        with self._cond:
            return not self._busy and not self._has_request

    def quiet(self) -> bool:
        """:meth:`idle`, and no standing request renders (render-ahead finished)."""
        with self._cond:
            return not self._busy and not self._has_request and not self._following

    def wake_idle(self) -> None:
        """Run the idle work and ask the standing request again (their situation changed, e.g. a larger budget)."""
        with self._cond:
            self._idle_pending = self._idle_work is not None
            self._following = self._follow_up is not None and self._newest is not None
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

    def _next_job(self) -> tuple[str, Any, int]:
        """Wait for the next job: ("render", request, generation), ("idle", None, 0) or ("stop", None, 0)."""
        with self._cond:
            while True:
                if self._stop:
                    return "stop", None, 0
                if self._has_request:
                    request, generation = self._request, self._generation
                    self._request, self._has_request, self._busy = None, False, True
                    self._running = request
                    return "render", request, generation
                wait = None
                if self._following or self._polling:
                    try:
                        wait = self._follow_up(self._newest)
                    except Exception as exc:  # noqa: BLE001 - ends the standing request, not the worker
                        self.stats.errors += 1
                        self.stats.last_error = f"{type(exc).__name__}: {exc}"
                        wait = None
                    if wait is not None and wait <= 0:
                        self._following, self._polling = True, False
                        self._running = self._newest
                        return "follow", self._newest, self._generation
                    self._following, self._polling = False, wait is not None
                if self._idle_pending:
                    return "idle", None, 0
                self._cond.wait(wait)

    def _loop(self) -> None:
        while True:
            kind, request, generation = self._next_job()
            if kind == "stop":
                return
            if kind == "idle":
                self._run_idle_step()
                continue
            failed = False
            try:
                start = time.perf_counter()
                result = self._render(request, generation)
                if result is NOTHING:
                    pass
                elif result is None or self.should_cancel(generation):
                    self.stats.started += 1
                    self.stats.abandoned += 1
                    self.stats.dropped += 1
                else:
                    self.stats.started += 1
                    self._sink(result, request, generation)
                    with self._cond:
                        self._last_delivery = time.monotonic()
                    self.stats.renders += 1
                    self.stats.last_ms = 1000.0 * (time.perf_counter() - start)
            except Exception as exc:  # noqa: BLE001 - a failed render must not kill the UI's worker
                failed = True
                self.stats.errors += 1
                self.stats.last_error = f"{type(exc).__name__}: {exc}"
            finally:
                with self._cond:
                    self._busy = False
                    self._running = None
                    self._idle_pending = self._idle_work is not None  # a new request may give it work
                    # ask the standing request what next (not after an error: no loop of failures)
                    self._following = self._follow_up is not None and not failed and generation == self._generation

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
#: How often a standing request of a playing clip asks again for a frame to render while every
#: frame it needs is finished (seconds).
POLL_SECONDS = 0.05


@dataclass(frozen=True)
class NeuralRequest:
    """What to render: body ``frame`` of ``motion`` (a scene sequence or motion name) seen by ``camera``
    with render ``preset`` at ``quality`` (None: the preset's own resolution), composed as
    ``composition`` (:data:`~garmentnerf.render.session.COMPOSITIONS`); ``gt_camera`` names the scene
    camera whose ground truth to load (or None). ``playhead``: the timeline's
    :class:`~garmentnerf.viewer.playback.PlayheadClock` (None: render ``frame`` once, nothing ahead);
    with it the worker renders the frame the playhead will be at when the render ends, then the
    frames ahead of it (render-ahead, see :class:`NeuralRenderer`). ``weights_step``: the training
    step of the weights to render with (part of the view). ``keep``: the render-ahead cache switches
    to this view and keeps its frames (False: a moving view's coarse request, shown once and
    forgotten, nothing rendered ahead). ``camera_path``: a
    :class:`~garmentnerf.render.camera_path.CameraPath` the window looks through: each frame is then
    seen by the path's camera at that frame (at ``camera``'s size), and the path, not ``camera``,
    is part of the view, so a clip played along the path renders ahead like a still camera."""

    frame: int
    camera: Any
    quality: float | None
    motion: Any = None
    gt_camera: str | None = None
    preset: str = VIEWER_LEVELS[-1]
    composition: str = "auto"
    playhead: PlayheadClock | None = None
    weights_step: int | None = None
    keep: bool = True
    camera_path: Any = None

    def camera_for(self, frame: int):
        """The camera of ``frame``: the path's there (at the request camera's size), else ``camera``."""
        if self.camera_path is None:
            return self.camera
        return self.camera_path.camera_at(frame, self.camera.width, self.camera.height)

    @functools.cached_property
    def view_key(self) -> tuple:
        """Everything but the frame (and the playhead) that decides the image: camera, quality,
        motion, ground-truth camera, preset, composition, the weights' training step. Not the
        palette (a shader uniform)."""
        cam = self.camera
        if self.camera_path is not None:
            camera = ("path", self.camera_path.token, cam.width, cam.height)
        else:
            camera = None if cam is None else (cam.K.tobytes(), cam.R.tobytes(), cam.t.tobytes(), cam.width,
                                               cam.height, float(cam.near), float(cam.far))
        return (camera, self.quality, self.motion, self.gt_camera, self.preset, self.composition, self.weights_step)


@dataclass
class NeuralResult:
    """One finished neural frame, as numpy for the GL thread.

    Attributes:
        layers: (2 + P, h', w', 4) float16 maps packed by :func:`~garmentnerf.viewer.palette_layer.pack_maps`
            and cut to the character (:func:`~garmentnerf.viewer.palette_layer.crop_to_content`) at
            ``origin`` (x0, y0) of the full maps of ``render_size``.
        depth: (h', w') float32 camera-space z, 0 where empty (the same rectangle).
        image_size: (W, H) of the requested camera; render_size: (w, h) actually rendered.
        quality, preset: what was rendered; frame: the clip frame (clamped to the clip).
        timings: stage -> ms (``RenderSession.render``'s); cached_frame: the frame's features were cached.
        ground_truth: (H, W, 3) of the request's scene camera, or None; counts: sample counts.
        body: the posed body the palette layer draws under the garment
            (:class:`~garmentnerf.viewer.palette_layer.BodyView`; the ``raster_body`` composition), or None.
        view_key: the request's :attr:`NeuralRequest.view_key`; weights_step: the training step of
            the weights it was rendered with; ahead: rendered ahead of the frame the request wanted
            (shown only from the render-ahead cache, when the playhead gets there).
        reprojection: the garment of the render as a :class:`~garmentnerf.bake.views.BakedView` (its
            attributes and median depth; the ``raster_body`` composition), which the window draws from
            another camera while the frame has no bake; None otherwise.
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
    origin: tuple[int, int] = (0, 0)
    view_key: Any = None
    weights_step: int | None = None
    ahead: bool = False
    reprojection: Any = None


class NeuralRenderer:
    """Runs :class:`garmentnerf.render.session.RenderSession` on a :class:`RenderWorker` thread.

    The session (and the headless GL context its input passes need) is made *on the worker thread*
    at the first request (:class:`~garmentnerf.viewer.render_thread.ThreadSession`), so the window's
    GL context is never touched from there. Results go to ``sink(result, request)`` and into
    :attr:`finished` (the render-ahead cache, :class:`~garmentnerf.viewer.finished_frames.FinishedFrames`);
    errors to :attr:`RenderWorker.stats` (``last_error``), which the window shows.

    Which frame (:mod:`~garmentnerf.viewer.playback`): a request with a playing
    :class:`~garmentnerf.viewer.playback.PlayheadClock` renders the frame the playhead will be at
    when the render ends (:func:`~garmentnerf.viewer.playback.predict_target_frame` with
    :attr:`render_time`, the measured duration of its renders), or the first frame from there not
    finished yet; a paused one renders its frame, then (:attr:`render_ahead`) the frames after it.
    The request stands (:meth:`RenderWorker.follow_up <RenderWorker>`): once a frame is done the
    next one is chosen the same way, as long as the cache keeps it. With :attr:`every_frame` the
    prediction is the playhead itself (the window waits for each frame instead of dropping).

    Cancellation: a render polls :meth:`RenderWorker.should_cancel` between chunks of samples and
    gives up (:class:`~garmentnerf.model.pipeline.RenderCancelled`, counted as abandoned) when the
    newest request makes it worthless (:func:`~garmentnerf.viewer.playback.render_superseded`:
    another view, or a playhead that left it behind); the feature precomputation (idle work) waits
    while the clip plays.

    Args:
        run: a :class:`~garmentnerf.runs.LoadedRun`.
        sink: called on the worker thread with each :class:`NeuralResult` and its request.
        motion: the session's first motion (None: the run scene's first training sequence).
        clock: seconds, the time base of the requests' playhead clocks.
        finished_mb: the render-ahead cache's memory bound (MiB).
    """

    def __init__(self, run, sink: Callable[[NeuralResult, NeuralRequest], None], motion: Any = None,
                 clock: Callable[[], float] = time.perf_counter, finished_mb: float = DEFAULT_FINISHED_MB) -> None:
        self.run = run
        self._sink = sink
        self._motion = motion
        self._clock = clock
        self._cache_mb = DEFAULT_CACHE_MB
        self._thread_session = ThreadSession(run, cache_mb=self._cache_mb, cache_half=True)  # worker thread only
        self._gt_cache: dict = {}
        self.finished = FinishedFrames(finished_mb)
        self.render_time = RenderTime()
        self.render_ahead = True
        self.every_frame = False
        self.last: NeuralResult | None = None
        self._last_request: NeuralRequest | None = None
        self._target: tuple | None = None        # (view key, frame) of the render in flight (worker thread)
        self._last_done: tuple | None = None     # (view key, frame) of the last delivered render
        self._pending_run = None                 # a newer checkpoint's run, switched to before the next render
        # what the worker does, for the overlay: ("starting", None) while it makes its session,
        # ("rendering", frame) during a render (set on the worker thread, read anywhere: one tuple)
        self.activity: tuple[str, int | None] = ("starting", None)
        self._run_lock = threading.Lock()
        self.worker = RenderWorker(self._render, self._deliver, name="garmentnerf-neural", idle_work=self._precompute,
                                   superseded=self._superseded, follow_up=self._follow_up)

    @property
    def stats(self) -> WorkerStats:
        return self.worker.stats

    @property
    def session(self):
        """The worker's :class:`~garmentnerf.render.session.RenderSession` (None before the first
        render); use it from another thread only while the worker is idle (a bench)."""
        return self._thread_session.current

    def request(self, request: NeuralRequest) -> int:
        """Ask for ``request``; the render-ahead cache switches to its view (dropping another view's
        frames) unless the request is not to be kept (a moving view)."""
        if request is not _CLOSE:
            if request.keep:
                self.finished.set_view(request.view_key)
            self._last_request = request
        return self.worker.request(request)

    def set_run(self, run) -> None:
        """Render with ``run`` (a newer checkpoint of the run, :mod:`~garmentnerf.viewer.checkpoint_watch`)
        from the next render on; the worker switches between two renders. Requests should name its
        step (``weights_step``) so that frames of the old weights are not shown as new ones."""
        with self._run_lock:
            self._pending_run = run
        self.worker.wake_idle()

    def _switch_run(self) -> None:
        """Worker thread: adopt the run :meth:`set_run` left (the session's model and caches)."""
        with self._run_lock:
            run, self._pending_run = self._pending_run, None
        if run is None:
            return
        self.run = run
        self._thread_session.run = run
        session = self._thread_session.current
        if session is not None:
            session.set_run(run)
        self._last_done = None

    def set_every_frame(self, on: bool) -> None:
        """Play every frame: the worker renders the playhead's frame, not a predicted one."""
        self.every_frame = bool(on)
        self.worker.wake_idle()

    def set_render_ahead(self, on: bool) -> None:
        """Render the frames after the playhead while there is nothing else to do."""
        self.render_ahead = bool(on)
        self.worker.wake_idle()

    def set_finished_mb(self, megabytes: float) -> None:
        """Change the render-ahead cache's memory bound (frames farthest ahead leave first)."""
        self.finished.set_budget_mb(megabytes)
        self.worker.wake_idle()

    # ---- which frame (worker thread) ------------------------------------------------------------------
    def _next_target(self, request: NeuralRequest, n_frames: int, now: float,
                     cached: Container[int]) -> tuple[int, bool] | None:
        """(frame, ahead) to render next for ``request`` (see the class docstring), or None:
        ``ahead`` False for the frame the request itself wants (paused: its frame; playing: the
        predicted one), True for a frame rendered ahead of it. ``cached``: the frames whose features
        the session holds (a render of another frame computes them first: it takes longer)."""
        key = request.view_key
        done = self.finished.frames(key)
        if self._last_done is not None and self._last_done[0] == key:
            done.add(self._last_done[1])
        clock = request.playhead
        if clock is None or not clock.playing:
            frame = min(max(0, int(request.frame if clock is None else clock.frame)), n_frames - 1)
            if frame not in done:
                return frame, False
            if clock is None or not self.render_ahead or not request.keep:
                return None
            ahead = next_unrendered(frame, done, n_frames, clock.loop)
            worth = ahead is not None and self.finished.worth_rendering(ahead, frame, n_frames)
            return (ahead, True) if worth else None
        head = self._playhead_position(clock, now)
        render_s = 0.0 if self.every_frame else self._expected_render_s(head, clock, n_frames, cached)
        predicted = predict_target_frame(head, clock.fps, render_s, n_frames, clock.loop)
        target = next_unrendered(predicted, done, n_frames, clock.loop)
        if target is None:
            return None
        if target == predicted:
            return target, False
        playhead_frame = frame_of(head, n_frames, clock.loop)
        wanted = request.keep and (self.every_frame or (self.render_ahead and self.finished.worth_rendering(
            target, playhead_frame, n_frames)))
        return (target, True) if wanted else None

    def _expected_render_s(self, head: float, clock: PlayheadClock, n_frames: int, cached: Container[int]) -> float:
        """How long a render started now will take: the warm figure when the frame it predicts has
        its features cached, else the cold one (:class:`~garmentnerf.viewer.playback.RenderTime`)."""
        warm = self.render_time.expected(cold=False)
        frame = predict_target_frame(head, clock.fps, warm, n_frames, clock.loop)
        return warm if frame in cached else self.render_time.expected(cold=True)

    def _playhead_position(self, clock: PlayheadClock, now: float) -> float:
        """Where the playhead is now: extrapolated at the clock's rate, or, playing every frame (the
        timeline waits for each image), where the clock was sent."""
        return clock.position if self.every_frame else clock.position_at(now)

    @staticmethod
    def _clip_frames(session, request: NeuralRequest) -> int:
        """Frames of the clip the request plays: the session's motion, or the first ones of it the
        playhead clock names (a bench plays part of a clip)."""
        n = session.num_frames
        return n if request.playhead is None else max(1, min(n, request.playhead.n_frames))

    def _follow_up(self, request: NeuralRequest) -> float | None:
        """The standing request (:class:`RenderWorker`): 0 while it has a frame to render; while a
        clip plays, ask again in :data:`POLL_SECONDS`; else None."""
        session = self._thread_session.current
        if request is _CLOSE or session is None:
            return None
        if self._next_target(request, self._clip_frames(session, request), self._clock(), session.frames) is not None:
            return 0.0
        return POLL_SECONDS if request.playhead is not None and request.playhead.playing else None

    def _superseded(self, running: NeuralRequest | None, newest: NeuralRequest | None) -> bool:
        """Whether the render in flight is worthless for ``newest`` (:func:`render_superseded`)."""
        target = self._target
        if running is None or newest is None or newest is _CLOSE or target is None:
            return True
        key, frame = target
        clock = newest.playhead
        same = newest.view_key == key
        if clock is None:
            return render_superseded(frame, same, newest.frame, 0.0, 0.0, max(frame, newest.frame) + 1, False)
        head = frame_of(self._playhead_position(clock, self._clock()), clock.n_frames, clock.loop)
        # the longer figure: a render that is only late (a cold frame) is finished, not abandoned
        render_s = max(self.render_time.expected(cold=False), self.render_time.expected(cold=True))
        return render_superseded(frame, same, head, clock.fps, render_s, clock.n_frames, clock.loop)

    # ---- rendering (worker thread) --------------------------------------------------------------------
    def _ground_truth(self, session, request: NeuralRequest, frame: int):
        """(H, W, 3) ground truth of the request's scene camera at ``frame``, or None (worker thread)."""
        scene = session.scene
        if request.gt_camera is None or scene is None or session.sequence is None:
            return None
        if request.gt_camera not in scene.camera_names():
            return None
        key = (session.sequence, request.gt_camera, frame)
        if key not in self._gt_cache:
            images = self._thread_session.helper("images", lambda: SceneImages(scene, body_model=session.body))
            rgb, _ = images.image(session.sequence, request.gt_camera, frame)
            self._gt_cache.clear()  # one image is enough: the view shows one frame
            self._gt_cache[key] = rgb
        return self._gt_cache[key]

    def _render(self, request: NeuralRequest, generation: int):
        if request is _CLOSE:
            self._thread_session.close()
            return NOTHING

        self._switch_run()
        if self._thread_session.current is None:
            self.activity = ("starting", None)
        session = self._thread_session.session(request.motion if request.motion is not None else self._motion)
        target = self._next_target(request, self._clip_frames(session, request), self._clock(), session.frames)
        if target is None:
            return NOTHING
        frame, ahead = target
        self._target = (request.view_key, frame)
        self.activity = ("rendering", frame)
        session.frames.set_playhead(frame)
        session.set_composition(request.composition)
        start = time.perf_counter()
        try:
            nf = session.render(frame, request.camera_for(frame), request.quality, preset=request.preset,
                                should_cancel=lambda: self.worker.should_cancel(generation, progress=not ahead),
                                body_layer=False)
        except RenderCancelled:
            return None
        finally:
            self._target = None
        body = None
        if nf.body is not None:  # the window draws the body layer at the size it shows it
            body = BodyView(nf.body[0].numpy(), nf.body[1].numpy(), nf.camera)
        layers, depth, origin = crop_to_content(pack_frame(nf.maps), nf.depth)
        self.render_time.observe(time.perf_counter() - start, cold=not nf.cached_frame)
        reprojection = None
        if body is not None and request.gt_camera is None:
            up = 2 ** session.config.decoder.upsample_steps
            reprojection = view_from_render(nf.maps, nf.camera.resized(*nf.render_size), nf.surface_depth, up)
            if reprojection is not None:
                reprojection.mesh(1)  # made here, not on the UI thread
        return NeuralResult(layers.astype("float16"), depth, nf.output_size, nf.render_size, nf.quality, frame,
                            nf.timings, nf.cached_frame, self._ground_truth(session, request, frame), nf.preset,
                            dict(nf.counts), body, origin, request.view_key, getattr(self.run, "step", None), ahead,
                            reprojection)

    def _precompute(self) -> bool:
        """Idle work: the next frame of the clip nearest to the playhead (see
        :meth:`RenderSession.precompute_next`); False when there is nothing (left) to do, and while
        the clip plays (the frames the user watches come first)."""
        last = self._last_request
        if last is not None and last.playhead is not None and last.playhead.playing:
            return False
        self._switch_run()
        session = self._thread_session.current
        return session is not None and session.precompute_next() is not None

    def cache_status(self) -> dict | None:
        """The caches as the UI shows them (thread-safe): ``ready`` (sorted frames whose features are
        precomputed), ``finished`` (sorted frames rendered for the current view), ``frames`` (in the
        clip), ``bytes``, ``budget_bytes`` (of the feature cache), ``finished_bytes``,
        ``finished_budget_bytes``; None before the first render."""
        session = self._thread_session.current
        if session is None:
            return None
        cache = session.frames
        finished = self.finished
        return {"ready": cache.ready_frames(), "frames": session.num_frames, "bytes": cache.nbytes,
                "budget_bytes": cache.budget_bytes, "finished": sorted(finished.frames(finished.view)),
                "finished_bytes": finished.nbytes, "finished_budget_bytes": finished.budget_bytes}

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
        session = self._thread_session.current
        n = self._clip_frames(session, request) if session is not None else result.frame + 1
        clock = request.playhead
        playhead = (frame_of(self._playhead_position(clock, self._clock()), clock.n_frames, clock.loop)
                    if clock is not None else result.frame)
        self.finished.put(result.view_key, result.frame, result, playhead, n)
        self._last_done = (result.view_key, result.frame)
        self.last = result
        self._sink(result, request)

    def stop(self, timeout: float = 30.0) -> None:
        """Cancel any render, free the worker's GL objects on its thread, and end it."""
        self.worker.request(_CLOSE)
        self.worker.wait_idle(timeout)
        self.worker.stop(timeout)


_CLOSE = NeuralRequest(-1, None, 0.0)
