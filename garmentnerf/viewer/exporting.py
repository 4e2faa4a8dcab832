"""Exporting: snapshots and mp4 videos of what the window shows (what an export *is* lives in
:mod:`~garmentnerf.viewer.export_jobs`; the panel in :mod:`~garmentnerf.viewer.export_panel`).

Two sources
    In the "neural" view of a run a snapshot renders the network at full quality
    (``snapshot_quality`` >= 1, never the preview's), and a video renders it in any view but "body",
    exactly as ``garmentnerf render`` does: :meth:`RenderSession.render_image
    <garmentnerf.render.session.RenderSession.render_image>` (the session's render, then
    :meth:`~garmentnerf.render.session.NeuralFrame.composite` with the palette and the model's
    background) and :func:`garmentnerf.render.video.to_uint8`. An export therefore equals the
    headless command's output for the same frame, camera, palette and quality; it is the network's
    image only (the floor, the rasterised body overlay and the preview quality are viewer aids). Body
    exports (no run, the "body" view, and snapshots of the diagnostic view modes) are the GL scene:
    drawn with the same code that draws the window, at the requested size and with the scene's
    snapshot multisampling; the panels are not in them.

Threads
    A GL snapshot is taken at once on the UI thread. Everything else runs on :class:`Exporter`'s
    thread, which has its own render session and headless GL context
    (:class:`~garmentnerf.viewer.render_thread.ThreadSession`). It is deliberately separate from
    the interactive :class:`~garmentnerf.viewer.worker.NeuralRenderer`: a session must only be
    used from one thread, and the preview's coalescing (a newer view cancels the render in flight)
    must never cancel an export. One job runs at a time; the UI thread only reads the job's
    progress and may cancel it, so the window keeps drawing. A cancelled video is aborted
    (:meth:`VideoWriter.abort` deletes its temporary file), a cancelled snapshot writes nothing.

:class:`Exports` is the window's side: it plans jobs from the current view, submits them, and tells
the status line how each ended.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from pathlib import Path

import numpy as np

from garmentnerf.model.pipeline import RenderCancelled
from garmentnerf.render.video import to_uint8
from garmentnerf.viewer.export_jobs import (
    EXPORT_MODES,
    MAX_QUALITY,
    MAX_VIDEO_FRAMES,
    MIN_QUALITY,
    MIN_SNAPSHOT_QUALITY,
    ExportCancelled,
    ExportJob,
    ExportSettings,
    check_size,
    open_video,
    plan_path,
    plan_range,
    plan_turntable,
    snapshot_name,
    video_name,
    write_png,
)
from garmentnerf.viewer.render_thread import ThreadSession
from garmentnerf.viewer.scene_gl import SceneRenderer


# ---- the export thread -------------------------------------------------------------------------------
class Exporter:
    """Runs :class:`ExportJob` s one at a time on its own thread (see the module docstring).

    Args:
        run: a :class:`~garmentnerf.runs.LoadedRun` for neural jobs (None: body-only jobs only).
    """

    def __init__(self, run=None, name: str = "garmentnerf-export") -> None:
        self.run = run
        self._cond = threading.Condition()
        self._queued: ExportJob | None = None
        self.current: ExportJob | None = None
        self._stop = False
        self._thread_session = ThreadSession(run)  # made and freed on the export thread only
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
            self._thread_session.close()

    def _run(self, job: ExportJob) -> None:
        job._start(job.clock())
        self._jobs_started += 1
        try:
            render = self._neural_renderer(job) if job.source == "neural" else self._body_renderer(job)
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
        writer = open_video(job.path, job.fps)
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

    # ---- renderers: render(frame, camera) -> (H, W, 3) uint8, on the export thread ---------------
    def _neural_renderer(self, job: ExportJob) -> Callable[[int, object], np.ndarray]:
        session = self._thread_session.session(job.motion)
        session.set_composition(job.composition)

        def render(frame: int, camera) -> np.ndarray:
            # the headless command's path: RenderSession.render + NeuralFrame.composite, then to_uint8
            image = session.render_image(frame, camera, job.palette, job.background, job.quality,
                                         should_cancel=job.cancel_requested)
            return to_uint8(image)

        return render

    def _body_renderer(self, job: ExportJob) -> Callable[[int, object], np.ndarray]:
        threads = self._thread_session
        scene = threads.helper("scene", lambda: SceneRenderer(threads.ctx, samples=0))
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


# ---- the window's side ---------------------------------------------------------------------------------
class Exports:
    """The window's exports: plans jobs from the current view, submits them to its :class:`Exporter`
    (made at the first job that needs it), and reports how each ended on the status line.

    Args:
        scene: the window's :class:`~garmentnerf.viewer.scene_gl.SceneRenderer` (GL snapshots, scene options).
        controller: the window's :class:`~garmentnerf.viewer.camera.OrbitController`.
        timeline: the window's :class:`~garmentnerf.viewer.timeline.Timeline` (the current frame).
        neural_view: the window's :class:`~garmentnerf.viewer.neural_view.NeuralView` (source, palette, motion).
        clip: returns the shown :class:`~garmentnerf.viewer.sequence.BodySequence`.
        prepare_scene: makes the window's GL context current and the scene show the current frame.
        status: shows one line on the status line.
        directory: where snapshots and videos go; snapshot_size: (W, H) of snapshots.
        view_camera: ``view_camera(width, height)``, the camera the window shows (default: the
            controller's; the app's looks through the camera path when asked to).
        camera_path: ``camera_path(size, fps)``, the edited
            :class:`~garmentnerf.render.camera_path.CameraPath` or None (the "path" export mode).
    """

    def __init__(self, scene, controller, timeline, neural_view, clip: Callable, prepare_scene: Callable[[], None],
                 status: Callable[[str], None], directory: str | Path, snapshot_size: tuple[int, int],
                 view_camera: Callable | None = None, camera_path: Callable | None = None) -> None:
        self.scene, self.controller, self.timeline, self.neural_view = scene, controller, timeline, neural_view
        self._view_camera = view_camera or controller.camera
        self._camera_path = camera_path or (lambda size, fps: None)
        self._clip, self._prepare_scene, self._status = clip, prepare_scene, status
        self.directory = Path(directory)
        self.snapshot_size = (int(snapshot_size[0]), int(snapshot_size[1]))
        self.snapshot_quality = 1.0
        self.settings = ExportSettings(range_last=timeline.last_frame)
        self.exporter: Exporter | None = None  # made at the first threaded job (its thread and GL context)
        self.job: ExportJob | None = None  # the newest job; its progress shows until it ends
        self.last_snapshot: Path | None = None
        self.last_export: Path | None = None

    # ---- state ------------------------------------------------------------------------------------
    @property
    def busy(self) -> bool:
        """Whether an export job (neural snapshot or video) is queued or running."""
        return self.job is not None and not self.job.finished

    def snapshot_is_neural(self) -> bool:
        """Whether a snapshot renders the network (a run's "neural" view) rather than the GL scene."""
        return self.neural_view.run is not None and self.neural_view.mode == "neural"

    def source(self) -> str:
        """A video's source: ``"neural"`` (the run's network) unless no run is loaded or the view
        shows the body only (``"body"``: the GL scene)."""
        return "neural" if self.neural_view.run is not None and self.neural_view.mode != "body" else "body"

    def _checked_size(self, width: int, height: int, what: str) -> tuple[int, int] | None:
        """(width, height), or None after telling the status line why it is out of range."""
        try:
            check_size(int(width), int(height), what)
        except ValueError as exc:
            self._status(str(exc))
            return None
        return int(width), int(height)

    def set_snapshot_size(self, width: int, height: int) -> None:
        self.snapshot_size = self._checked_size(width, height, "snapshot size") or self.snapshot_size

    def set_snapshot_quality(self, quality: float) -> None:
        """Render quality of neural snapshots, clamped to [1, 4] (1: the training pixel density)."""
        if math.isfinite(quality):
            self.snapshot_quality = min(MAX_QUALITY, max(MIN_SNAPSHOT_QUALITY, float(quality)))

    def set_video_size(self, width: int, height: int) -> None:
        self.settings.size = self._checked_size(width, height, "video size") or self.settings.size

    def set_mode(self, mode: str) -> None:
        """The video export's mode, a key of :data:`EXPORT_MODES`."""
        if mode not in EXPORT_MODES:
            raise ValueError(f"unknown export mode '{mode}' (known: {', '.join(EXPORT_MODES)})")
        self.settings.mode = mode

    def set_turntable(self, frames: int, plays: bool) -> None:
        """Frames of one turn (clamped to [1, MAX_VIDEO_FRAMES]) and whether the motion plays during it."""
        self.settings.turntable_frames = min(MAX_VIDEO_FRAMES, max(1, int(frames)))
        self.settings.turntable_plays = bool(plays)

    def set_video_quality(self, quality: float) -> None:
        """Render quality of neural videos, clamped to [MIN_QUALITY, MAX_QUALITY]."""
        if math.isfinite(quality):
            self.settings.quality = min(MAX_QUALITY, max(MIN_QUALITY, float(quality)))

    def set_range(self, first: int, last: int) -> None:
        """Timeline range of range exports, inclusive (clamped to the clip; ``last`` >= ``first``)."""
        top = self.timeline.last_frame
        first = min(max(0, int(first)), top)
        self.settings.range_first = first
        self.settings.range_last = min(max(first, int(last)), top)

    # ---- snapshots --------------------------------------------------------------------------------
    def start_snapshot(self, width: int | None = None, height: int | None = None,
                       directory: str | Path | None = None) -> ExportJob:
        """Snapshot the current view at ``width`` x ``height`` (default: the snapshot size) into
        ``directory`` (default: the export folder). Never overwrites: a taken name gets a numbered suffix.

        The network's view (:meth:`snapshot_is_neural`) renders on the exporter's thread at
        ``snapshot_quality`` (>= 1) with the current palette, exactly as ``garmentnerf render``
        does; the returned job is still running (RuntimeError when another export runs). Other
        views are the GL scene, rendered off-screen at once: the returned job is already done.
        """
        w, h = (width or self.snapshot_size[0]), (height or self.snapshot_size[1])
        check_size(w, h, "snapshot size")
        directory = Path(directory) if directory is not None else self.directory
        clip, frame = self._clip(), self.timeline.frame
        if not self.snapshot_is_neural():
            self._prepare_scene()
            image = self.scene.render_image(self._view_camera(w, h), samples=self.scene.snapshot_samples)
            return ExportJob.completed("snapshot", write_png(image, directory / snapshot_name(clip.name, frame)))
        self.controller.update_anchor(clip.track[frame])  # the camera the window shows
        quality = min(MAX_QUALITY, max(MIN_SNAPSHOT_QUALITY, self.snapshot_quality))
        view, path = self.neural_view, directory / snapshot_name(clip.name, frame)
        job = ExportJob("snapshot", [(frame, self._view_camera(w, h))], path, source="neural", quality=quality,
                        palette=view.palette.copy(), motion=view.motion, fps=clip.fps, composition=view.composition)
        return self._submit(job)

    def snapshot_with_status(self) -> None:
        """The S shortcut: errors go to the status line, never up."""
        try:
            job = self.start_snapshot()
        except (OSError, ValueError, RuntimeError) as exc:
            self._status(f"snapshot failed: {exc}")
            return
        if job.finished:
            self.report(job)

    # ---- videos -----------------------------------------------------------------------------------
    def plan(self, settings: ExportSettings | None = None) -> tuple[list, str]:
        """((frame, camera) per output frame, file label) of a video with ``settings`` (default: the
        panel's) from the current view."""
        s = settings or self.settings
        clip, frame = self._clip(), self.timeline.frame
        s.check(clip.num_frames)
        self.controller.update_anchor(clip.track[frame])
        if s.mode == "path":
            path = self._camera_path(s.size, clip.fps)
            if path is None:
                raise ValueError("the camera path has no keyframes: add some in the Camera path panel")
            plan = plan_path(path, s.size, clip.num_frames, clip.name)
            return plan, f"path_f{plan[0][0]:04d}-{plan[-1][0]:04d}"
        if s.mode == "turntable":
            plan = plan_turntable(self.controller, s.size, s.turntable_frames, frame, clip.num_frames,
                                  s.turntable_plays, clip.track)
            return plan, "turntable" if s.turntable_plays else f"turntable_f{frame:04d}"
        plan = plan_range(self.controller, s.size, s.range_first, s.range_last, clip.track)
        return plan, f"f{s.range_first:04d}-{s.range_last:04d}"

    def start_video(self, settings: ExportSettings | None = None, directory: str | Path | None = None) -> ExportJob:
        """Start an mp4 export (turntable or timeline range, see :class:`ExportSettings`) into
        ``directory`` (default: the export folder) under a never-overwritten name; returns the
        running job. ValueError for bad settings, RuntimeError while another export runs."""
        s = settings or self.settings
        plan, label = self.plan(s)
        clip, view = self._clip(), self.neural_view
        directory = Path(directory) if directory is not None else self.directory
        options = {"floor": self.scene.floor.visible, "grid": self.scene.floor.show_lines,
                   "body": self.scene.body.visible, "samples": self.scene.snapshot_samples}
        job = ExportJob("video", plan, directory / video_name(clip.name, label), source=self.source(),
                        quality=s.quality, palette=None if view.palette is None else view.palette.copy(),
                        motion=view.motion, fps=clip.fps, sequence=clip, scene_options=options,
                        composition=view.composition)
        return self._submit(job)

    def start_video_with_status(self) -> None:
        """The Export panel's Start: errors go to the status line, never up."""
        try:
            self.start_video()
        except (OSError, ValueError, RuntimeError) as exc:
            self._status(f"export failed: {exc}")

    # ---- jobs -------------------------------------------------------------------------------------
    def cancel(self) -> None:
        """Cancel the running export (it leaves no file)."""
        if self.busy:
            self.job.cancel()
            self._status(f"{self.job.label}: cancelling ...")

    def _submit(self, job: ExportJob) -> ExportJob:
        if self.exporter is not None and self.exporter.run is not self.neural_view.run and not self.exporter.busy:
            self.exporter.close()  # a newer checkpoint is shown (checkpoint_watch): export with it
            self.exporter = None
        if self.exporter is None:
            self.exporter = Exporter(self.neural_view.run)
        self.exporter.submit(job)
        self.job = job  # its progress shows in the timeline bar and the panels until it ends
        return job

    def poll(self) -> None:
        """UI thread, once per frame: tell the user how a finished export ended."""
        if self.job is not None and self.job.finished:
            self.report(self.job)

    def report(self, job: ExportJob) -> None:
        """Status line (once per job): the file written, or how it ended."""
        if job.reported:
            return
        job.reported = True
        if job.state == "done":
            if job.kind == "snapshot":
                self.last_snapshot = job.written
            else:
                self.last_export = job.written
            self._status(f"saved {job.written}")
        else:
            self._status(job.status_line())

    def outcome(self, job: ExportJob) -> Path:
        """The file a finished ``job`` wrote (reported on the status line); RuntimeError with its
        status line when it was cancelled or failed."""
        self.report(job)
        if job.state != "done":
            raise RuntimeError(job.status_line())
        return job.written

    def stats(self) -> dict | None:
        """The newest job for the stats hook: kind, state, frames done / total, seconds, file."""
        if self.job is None:
            return None
        p = self.job.progress()
        return {"kind": self.job.kind, "state": p.state, "done": p.done, "total": p.total, "seconds": p.elapsed_s,
                "written": self.job.written}

    def close(self) -> None:
        """End the exporter's thread; a running export is cancelled and leaves no file."""
        if self.exporter is not None:
            self.exporter.close()


__all__ = ["Exporter", "Exports"]
