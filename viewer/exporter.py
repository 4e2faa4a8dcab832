"""Exports that take time, off the UI thread: neural snapshots and mp4 videos.

One render path
    A neural frame is rendered exactly as ``garmentnerf render`` renders it:
    :meth:`RenderSession.render_image` (:meth:`~garmentnerf.render.session.RenderSession.render`
    then :meth:`~garmentnerf.render.session.NeuralFrame.composite` with the palette and the model's
    background) and :func:`garmentnerf.render.video.to_uint8`. A viewer export therefore equals the
    headless command's output for the same frame, camera, palette and quality. It is the
    network's image only: the floor, the rasterised body overlay and the window's preview quality
    are viewer aids and are not in it. Body-only exports (no run loaded, or the "body" view mode)
    draw the viewer's GL scene (floor, body) instead.

Threads
    :class:`Exporter` owns one thread. Made lazily *on that thread*, it has its own headless GL
    context, :class:`~garmentnerf.render.session.RenderSession` (neural jobs) and
    :class:`~garmentnerf.viewer.scene_gl.SceneRenderer` (body-only videos). It is deliberately
    separate from the interactive :class:`~garmentnerf.viewer.worker.NeuralRenderer`: a session
    must only be used from one thread, and the preview's coalescing (a newer view cancels the
    render in flight) must never cancel an export. One job runs at a time; the UI thread only reads
    an :class:`ExportJob`'s progress and may cancel it, so the window keeps drawing.

Plans
    A job renders a list of ``(body frame, camera)`` pairs built on the UI thread from a *copy* of
    the window's orbit controller (:func:`plan_turntable`, :func:`plan_range`): the export shows the
    view as it was when it started, whatever the user does meanwhile.

Cancel
    :meth:`ExportJob.cancel` is polled between chunks of samples (the session's ``should_cancel``)
    and between frames. A cancelled video is aborted (:meth:`VideoWriter.abort` deletes its
    temporary file), a cancelled snapshot writes nothing: no partial file is ever left.
"""

from __future__ import annotations

import copy
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from garmentnerf.viewer.export import check_size, write_png

#: Export modes: label per key, in menu order.
EXPORT_MODES = {"turntable": "Turntable", "range": "Timeline range"}
#: Render quality limits of exports (fraction of the training pixel density, as ``render --quality``).
MIN_QUALITY, MAX_QUALITY = 0.25, 4.0
#: Neural snapshots render at least at the training density (never at the preview's quality).
MIN_SNAPSHOT_QUALITY = 1.0
#: Most frames one video export may have.
MAX_VIDEO_FRAMES = 10000

#: A plan: (body frame, Camera) per output frame.
Plan = list[tuple[int, object]]


class ExportCancelled(Exception):
    """Raised on the export thread when the job was cancelled (between frames or chunks)."""


# ---- settings and plans (UI thread, pure) ------------------------------------------------------------
@dataclass
class ExportSettings:
    """What the Export panel edits.

    Attributes:
        mode: key of :data:`EXPORT_MODES`.
        turntable_frames: frames of one full turn.
        turntable_plays: the motion plays during the turn (else the current frame is held).
        range_first, range_last: the timeline range, inclusive (clamped to the clip when used).
        size: (W, H) output pixels.
        quality: neural render quality (1 = the training pixel density).
    """

    mode: str = "turntable"
    turntable_frames: int = 60
    turntable_plays: bool = False
    range_first: int = 0
    range_last: int = 0
    size: tuple[int, int] = (640, 360)
    quality: float = 1.0

    def check(self, num_frames: int) -> None:
        """ValueError (one line) when the settings cannot make a video of a ``num_frames`` clip."""
        if self.mode not in EXPORT_MODES:
            raise ValueError(f"unknown export mode '{self.mode}' (known: {', '.join(EXPORT_MODES)})")
        check_size(*self.size, "video size")
        if not (np.isfinite(self.quality) and MIN_QUALITY <= self.quality <= MAX_QUALITY):
            raise ValueError(f"export quality must be in [{MIN_QUALITY}, {MAX_QUALITY}], got {self.quality}")
        if self.mode == "turntable" and not 1 <= int(self.turntable_frames) <= MAX_VIDEO_FRAMES:
            raise ValueError(f"turntable frames must be in 1..{MAX_VIDEO_FRAMES}, got {self.turntable_frames}")
        if self.mode == "range":
            first, last = int(self.range_first), int(self.range_last)
            if not 0 <= first <= last < num_frames:
                raise ValueError(f"frame range {first}..{last} is not inside the clip (0..{num_frames - 1})")


def plan_turntable(controller, size: tuple[int, int], count: int, start_frame: int, num_frames: int,
                   plays: bool, centers: np.ndarray) -> Plan:
    """``count`` (frame, camera) pairs orbiting the view's target once.

    The azimuth starts at the controller's and advances ``360 / count`` degrees per frame (the last
    frame stops one step short of the first, so the video loops, as
    :func:`garmentnerf.render.cameras.turntable`); distance, elevation, field of view and target are
    the current ones. Frames: ``start_frame`` held, or playing on from it (wrapping) when ``plays``.
    ``centers`` (T, 3): per-frame body centres; a following controller moves the target with them.
    """
    view = copy.deepcopy(controller)  # the window's controller keeps moving meanwhile
    w, h = (int(s) for s in size)
    start_azimuth = view.azimuth
    plan = []
    for i in range(int(count)):
        frame = (int(start_frame) + i) % int(num_frames) if plays else int(start_frame)
        view.azimuth = start_azimuth + 360.0 * i / count
        view.update_anchor(centers[frame])  # as the window does each frame (no-op unless following)
        plan.append((frame, view.camera(w, h)))
    return plan


def plan_range(controller, size: tuple[int, int], first: int, last: int, centers: np.ndarray) -> Plan:
    """Frames ``first..last`` (inclusive) seen from the controller's current view (following the
    body when the controller follows it). ``centers`` (T, 3): per-frame body centres."""
    view = copy.deepcopy(controller)
    w, h = (int(s) for s in size)
    plan = []
    for frame in range(int(first), int(last) + 1):
        view.update_anchor(centers[frame])
        plan.append((frame, view.camera(w, h)))
    return plan


# ---- one job -----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ExportProgress:
    """A consistent copy of a job's progress. ``fraction`` is None while unknown (a single frame
    in flight: the renderer reports no progress inside a frame); ``eta_s`` None until a frame is done."""

    state: str
    done: int
    total: int
    fraction: float | None
    elapsed_s: float
    eta_s: float | None


class ExportJob:
    """One export (a snapshot or a video) and its progress, shared by the UI and export threads.

    The export thread sets the progress (under a lock); the UI thread reads it with
    :meth:`progress` and may :meth:`cancel`. States: ``queued``, ``running``, then one of ``done``
    (:attr:`written` is the file), ``cancelled`` (nothing written) or ``failed`` (:attr:`error`).

    Args:
        kind: ``"snapshot"`` (a PNG of ``plan[0]``) or ``"video"`` (an mp4 of the whole plan).
        plan: (body frame, camera) per output frame (see :func:`plan_turntable`).
        path: the wanted file; a taken name gets the next free ``_001`` ... suffix (never replaced).
        source: ``"neural"`` (the run's network, see the module docstring) or ``"body"`` (GL scene).
        quality: neural render quality; palette: (P, 3) colours in [0, 1] (None: the learned
            palette); background: RGB in [0, 1] (None: the model's); motion: the session's motion.
        fps: video frame rate.
        sequence: the :class:`~garmentnerf.viewer.sequence.BodySequence` (body-only jobs);
            scene_options: ``{"floor": bool, "grid": bool, "body": bool, "samples": int}`` for them.
    """

    def __init__(self, kind: str, plan: Plan, path: str | Path, *, source: str = "neural", quality: float = 1.0,
                 palette=None, background=None, motion=None, fps: float = 30.0, sequence=None,
                 scene_options: dict | None = None, clock: Callable[[], float] = time.monotonic) -> None:
        if kind not in ("snapshot", "video"):
            raise ValueError(f"unknown export kind '{kind}'")
        if source not in ("neural", "body"):
            raise ValueError(f"unknown export source '{source}'")
        if not plan:
            raise ValueError("an export needs at least one frame")
        self.kind, self.plan, self.path, self.source = kind, list(plan), Path(path), source
        self.quality = float(quality)
        self.palette = None if palette is None else np.array(palette, dtype=np.float32).reshape(-1, 3)
        self.background = background
        self.motion = motion
        self.fps = float(fps)
        self.sequence = sequence
        self.scene_options = dict(scene_options or {})
        self.clock = clock
        self.state = "queued"
        self.error = ""
        self.written: Path | None = None
        self.target: Path | None = None  # the file being written, once its name is chosen
        self.reported = False            # set by the app once it has told the user the outcome
        self._done = 0
        self._started: float | None = None
        self._ended: float | None = None
        self._frame_started: float | None = None
        self._lock = threading.Lock()
        self._cancel = threading.Event()
        self._finished = threading.Event()

    @classmethod
    def completed(cls, kind: str, path: Path, source: str = "body") -> "ExportJob":
        """A job that is already done (a GL snapshot taken at once on the UI thread)."""
        job = cls(kind, [(0, None)], path, source=source)
        now = job.clock()
        job._start(now)
        job._frame_done(now)
        job._finish("done", path)
        return job

    # ---- read by any thread ------------------------------------------------------------------
    @property
    def total(self) -> int:
        return len(self.plan)

    @property
    def finished(self) -> bool:
        return self._finished.is_set()

    @property
    def label(self) -> str:
        return "snapshot" if self.kind == "snapshot" else "export"

    def progress(self) -> ExportProgress:
        now = self.clock()
        with self._lock:
            state, done, total = self.state, self._done, self.total
            started, ended, frame_started = self._started, self._ended, self._frame_started
        elapsed = 0.0 if started is None else (ended if ended is not None else now) - started
        if state == "done":
            return ExportProgress(state, done, total, 1.0, elapsed, 0.0)
        fraction = done / total if (done or total > 1) else None
        eta = None
        if done and state == "running":
            per_frame = (frame_started - started) / done  # mean time of the frames finished so far
            in_flight = now - frame_started
            eta = max(0.0, per_frame * (total - done) - in_flight)
        return ExportProgress(state, done, total, fraction, elapsed, eta)

    def status_line(self) -> str:
        """One line for the window: ``snapshot: rendering... 2.1 s`` / ``export: 3/10 frames, ETA 8 s``."""
        p = self.progress()
        if p.state in ("queued", "running"):
            if self.total == 1:
                return f"{self.label}: rendering... {p.elapsed_s:.1f} s"
            eta = f", ETA {format_seconds(p.eta_s)}" if p.eta_s is not None else ""
            return f"{self.label}: {p.done}/{p.total} frames, {format_seconds(p.elapsed_s)}{eta}"
        if p.state == "done":
            return f"{self.label}: saved {self.written}"
        if p.state == "cancelled":
            return f"{self.label}: cancelled"
        return f"{self.label} failed: {self.error}"

    def wait(self, timeout: float | None = None) -> bool:
        """Block until the job has finished (True) or ``timeout`` seconds passed (False)."""
        return self._finished.wait(timeout)

    # ---- cancel (any thread) -------------------------------------------------------------------
    def cancel(self) -> None:
        """Ask the job to stop; it ends ``cancelled`` soon (between chunks) and leaves no file."""
        self._cancel.set()

    def cancel_requested(self) -> bool:
        """Polled by the renderer between chunks of samples."""
        return self._cancel.is_set()

    def check_cancel(self) -> None:
        if self._cancel.is_set():
            raise ExportCancelled()

    # ---- export thread -----------------------------------------------------------------------
    def _start(self, now: float) -> None:
        with self._lock:
            self.state = "running"
            self._started = self._frame_started = now

    def _frame_done(self, now: float) -> None:
        with self._lock:
            self._done += 1
            self._frame_started = now

    def _finish(self, state: str, path: Path | None = None, error: str = "") -> None:
        with self._lock:
            self.state, self.written, self.error = state, path, error
            self._ended = self.clock()
        self._finished.set()


def format_seconds(seconds: float | None) -> str:
    """``7.5`` -> ``"8 s"``, ``95`` -> ``"1:35"``, None -> ``"--"``."""
    if seconds is None or not np.isfinite(seconds):
        return "--"
    s = int(round(seconds))
    return f"{s} s" if s < 60 else f"{s // 60}:{s % 60:02d}"


# ---- the export thread -------------------------------------------------------------------------------
class Exporter:
    """Runs :class:`ExportJob` s one at a time on its own thread (see the module docstring).

    Args:
        run: a :class:`~garmentnerf.train.run.LoadedRun` for neural jobs (None: body-only jobs only).
    """

    def __init__(self, run=None, name: str = "garmentnerf-export") -> None:
        self.run = run
        self._cond = threading.Condition()
        self._queued: ExportJob | None = None
        self.current: ExportJob | None = None
        self._stop = False
        # made and freed on the export thread only
        self._ctx = None
        self._session = None
        self._session_motion = None
        self._scene = None
        self._jobs_started = 0
        self._thread = threading.Thread(target=self._loop, name=name, daemon=True)
        self._thread.start()

    @property
    def busy(self) -> bool:
        job = self.current
        return job is not None and not job.finished

    def submit(self, job: ExportJob) -> ExportJob:
        """Queue ``job``; RuntimeError while another job is queued or running (one at a time)."""
        if job.source == "neural" and self.run is None:
            raise ValueError("a neural export needs a run (garmentnerf view --run DIR)")
        with self._cond:
            if self._stop:
                raise RuntimeError("the exporter is closed")
            if self.busy:
                what = "a snapshot" if self.current.kind == "snapshot" else "an export"
                raise RuntimeError(f"{what} is still running: wait for it or cancel it")
            self._queued = self.current = job
            self._cond.notify()
        return job

    def cancel(self) -> None:
        job = self.current
        if job is not None:
            job.cancel()

    def close(self, timeout: float = 30.0) -> None:
        """Cancel any job, free the thread's GL objects (on it) and end it."""
        self.cancel()
        with self._cond:
            self._stop = True
            self._cond.notify()
        self._thread.join(timeout)

    # ---- the thread --------------------------------------------------------------------------
    def _loop(self) -> None:
        try:
            while True:
                with self._cond:
                    while self._queued is None and not self._stop:
                        self._cond.wait()
                    if self._stop:
                        if self._queued is not None:
                            self._queued._finish("cancelled")
                        return
                    job, self._queued = self._queued, None
                self._run(job)
        finally:
            self._release()

    def _run(self, job: ExportJob) -> None:
        from garmentnerf.model.pipeline import RenderCancelled

        job._start(job.clock())
        self._jobs_started += 1
        try:
            render = self._frame_renderer(job)
            path = self._run_snapshot(job, render) if job.kind == "snapshot" else self._run_video(job, render)
        except (ExportCancelled, RenderCancelled):
            job._finish("cancelled")
        except BaseException as exc:  # noqa: BLE001 - a failed export is shown in the window, never crashes it
            job._finish("failed", error=" ".join(f"{type(exc).__name__}: {exc}".split()))
            if not isinstance(exc, Exception):
                raise  # SystemExit and the like end the thread, but the job is not left "running"
        else:
            job._finish("done", path)

    @staticmethod
    def _run_snapshot(job: ExportJob, render) -> Path:
        frame, camera = job.plan[0]
        image = render(frame, camera)
        job.check_cancel()  # a cancel during the last chunk still writes nothing
        job.target = job.path
        path = write_png(image, job.path)
        job._frame_done(job.clock())
        return path

    @staticmethod
    def _run_video(job: ExportJob, render) -> Path:
        writer = _open_video(job.path, job.fps)
        job.target = writer.path
        try:
            for frame, camera in job.plan:
                job.check_cancel()
                writer.append(render(frame, camera))
                job._frame_done(job.clock())
            job.check_cancel()
            path = writer.close()
        except BaseException:
            writer.abort()  # deletes the temporary file: a cancelled or failed export leaves nothing
            raise
        if path is None:
            raise RuntimeError("no frame was written")
        return path

    # ---- renderers (export thread) -----------------------------------------------------------
    def _frame_renderer(self, job: ExportJob) -> Callable[[int, object], np.ndarray]:
        """``render(frame, camera) -> (H, W, 3) uint8`` for ``job``'s source."""
        return self._neural_renderer(job) if job.source == "neural" else self._body_renderer(job)

    def _neural_renderer(self, job: ExportJob):
        from garmentnerf.render.video import to_uint8

        session = self._neural_session(job.motion)

        def render(frame: int, camera) -> np.ndarray:
            # the headless command's path: RenderSession.render + NeuralFrame.composite, then to_uint8
            image = session.render_image(frame, camera, job.palette, job.background, job.quality,
                                         should_cancel=job.cancel_requested)
            return to_uint8(image)

        return render

    def _body_renderer(self, job: ExportJob):
        scene = self._body_scene()
        options = job.scene_options
        scene.floor.visible = bool(options.get("floor", True))
        scene.floor.show_lines = bool(options.get("grid", True))
        scene.body.visible = bool(options.get("body", True))
        samples = int(options.get("samples", scene.snapshot_samples))
        seq, serial = job.sequence, self._jobs_started

        def render(frame: int, camera) -> np.ndarray:
            scene.set_body((serial, frame), seq.frame(frame), seq.faces, seq.centers[frame])
            return scene.render_image(camera, samples=samples)

        return render

    def _gl_context(self):
        if self._ctx is None:
            from garmentnerf.gl.context import create_context

            self._ctx = create_context(headless=True)  # this thread's own context, never the window's
        return self._ctx

    def _neural_session(self, motion):
        if self._session is None:
            from garmentnerf.render.session import RenderSession

            self._session = RenderSession(self.run, self._gl_context(), motion)
            self._session_motion = motion
        elif motion != self._session_motion:
            self._session.set_motion(motion)
            self._session_motion = motion
        return self._session

    def _body_scene(self):
        if self._scene is None:
            from garmentnerf.viewer.scene_gl import SceneRenderer

            self._scene = SceneRenderer(self._gl_context(), samples=0)
        return self._scene

    def _release(self) -> None:
        for obj in (self._session, self._scene):
            if obj is not None:
                try:
                    (obj.close if obj is self._session else obj.release)()
                except Exception:  # noqa: BLE001 - best effort at shutdown
                    pass
        if self._ctx is not None:
            try:
                self._ctx.release()
            except Exception:  # noqa: BLE001
                pass
        self._session = self._scene = self._ctx = None


def _open_video(path: Path, fps: float, attempts: int = 20):
    """A :class:`VideoWriter` on ``path`` or, if taken, the next free numbered name (never replaces)."""
    from garmentnerf.io_utils import next_free_path
    from garmentnerf.render.video import VideoWriter

    for _ in range(attempts):
        try:
            return VideoWriter(next_free_path(path), fps)
        except FileExistsError:
            continue  # the name appeared between next_free_path and the check: try the next one
    raise FileExistsError(f"{path}: could not find a free video name after {attempts} attempts")


__all__ = ["EXPORT_MODES", "ExportSettings", "ExportJob", "ExportProgress", "Exporter", "ExportCancelled",
           "plan_turntable", "plan_range", "format_seconds"]
