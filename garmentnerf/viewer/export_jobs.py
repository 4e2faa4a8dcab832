"""What an export is: sizes and file names, the never-overwriting writers, the export settings, the
frame plans and one job's progress. Pure logic and files, no GL and no threads of its own: the
exports are *run* by :mod:`~garmentnerf.viewer.exporting`.

Files
    Snapshot and video names come from the motion and the frame (range) (:func:`snapshot_name`,
    :func:`video_name`). Files are written atomically (a temporary file renamed into place) and never
    replace an existing file: a taken name gets the next free ``_001``, ``_002`` ... suffix
    (:func:`write_png`, :func:`open_video`).

Plans
    A job renders a list of ``(body frame, camera)`` pairs built on the UI thread from a *copy* of
    the window's orbit controller (:func:`plan_turntable`, :func:`plan_range`): the export shows the
    view as it was when it started, whatever the user does meanwhile.

Jobs
    An :class:`ExportJob` is shared by the UI thread (reads :meth:`~ExportJob.progress`, may
    :meth:`~ExportJob.cancel`) and the export thread (sets the progress under a lock). Cancel is
    polled between chunks of samples and between frames; a cancelled job leaves no file.
"""

from __future__ import annotations

import copy
import re
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from garmentnerf.io_utils import atomic_write_path, next_free_path
from garmentnerf.render.video import VideoWriter

#: Largest image side we accept (GL limits may be lower; the renderer checks those).
MAX_SIDE = 16384
#: Export modes: label per key, in menu order.
EXPORT_MODES = {"turntable": "Turntable", "range": "Timeline range", "path": "Camera path"}
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


# ---- sizes, names and files --------------------------------------------------------------------------
_SIZE = re.compile(r"^\s*(\d+)\s*[xX*]\s*(\d+)\s*$")


def parse_size(text: str, what: str = "size") -> tuple[int, int]:
    """``"1280x800"`` -> (1280, 800); raises ValueError with a one-line message."""
    m = _SIZE.match(str(text))
    if not m:
        raise ValueError(f"{what} must look like WIDTHxHEIGHT (e.g. 1280x800), got '{text}'")
    w, h = int(m.group(1)), int(m.group(2))
    check_size(w, h, what)
    return w, h


def check_size(width: int, height: int, what: str = "size") -> None:
    """ValueError (one line) unless 1 <= width, height <= :data:`MAX_SIDE`."""
    if not (1 <= width <= MAX_SIDE and 1 <= height <= MAX_SIDE):
        raise ValueError(f"{what} {width}x{height} is out of range (1..{MAX_SIDE} per side)")


def _safe_name(text: str, fallback: str) -> str:
    """``text`` with characters unsafe in file names replaced by ``-`` (``fallback`` when nothing is left)."""
    return re.sub(r"[^A-Za-z0-9_.-]+", "-", text).strip("-.") or fallback


def snapshot_name(motion: str, frame: int) -> str:
    """File name for a snapshot of ``motion`` at ``frame`` (characters unsafe in file names replaced)."""
    return f"{_safe_name(Path(str(motion)).stem or 'body', 'body')}_f{int(frame):04d}.png"


def video_name(motion: str, label: str) -> str:
    """File name of a video export, e.g. ``walk_turntable.mp4`` or ``walk_f0003-0010.mp4``."""
    return f"{_safe_name(Path(str(motion)).stem or 'body', 'body')}_{_safe_name(str(label), 'video')}.mp4"


def write_png(image: np.ndarray, path: str | Path, attempts: int = 20) -> Path:
    """Write (H, W, 3|4) uint8 ``image`` to ``path`` or, if taken, the next free numbered name.

    Never overwrites: the final rename is a hard link that fails if the name appeared meanwhile
    (another process snapshotting into the same folder), in which case the next free name is tried.
    Returns the path written.
    """
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] not in (3, 4):
        raise ValueError(f"snapshot image must be (H, W, 3|4) uint8, got {image.dtype} {image.shape}")
    pil = Image.fromarray(image)
    path = Path(path)
    for _ in range(attempts):
        target = next_free_path(path)
        try:
            with atomic_write_path(target, overwrite=False) as tmp:
                pil.save(tmp, format="PNG")
            return target
        except FileExistsError:
            continue  # somebody took the name between next_free_path and the link: try the next one
    raise FileExistsError(f"{path}: could not find a free snapshot name after {attempts} attempts")


def open_video(path: Path, fps: float, attempts: int = 20):
    """A :class:`VideoWriter` on ``path`` or, if taken, the next free numbered name (never replaces)."""
    for _ in range(attempts):
        try:
            return VideoWriter(next_free_path(path), fps)
        except FileExistsError:
            continue  # the name appeared between next_free_path and the check: try the next one
    raise FileExistsError(f"{path}: could not find a free video name after {attempts} attempts")


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
    ``centers`` (T, 3): per-frame anchors (the clip's follow track, as the window's); a following
    controller moves the target with them.
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
    body when the controller follows it). ``centers`` (T, 3): per-frame anchors (the clip's follow track)."""
    view = copy.deepcopy(controller)
    w, h = (int(s) for s in size)
    plan = []
    for frame in range(int(first), int(last) + 1):
        view.update_anchor(centers[frame])
        plan.append((frame, view.camera(w, h)))
    return plan


def plan_path(path, size: tuple[int, int], num_frames: int, motion: str = "the clip") -> Plan:
    """The frames a :class:`~garmentnerf.render.camera_path.CameraPath` spans, each seen from the
    path's camera at ``size`` (W, H): what ``garmentnerf render --camera-path`` renders from the
    saved path. ValueError when a keyframe lies outside the ``num_frames`` clip or the path spans no
    whole frame."""
    path.check_motion(num_frames, motion)
    frames = path.render_frames()
    return list(zip(frames, path.cameras(frames, (int(size[0]), int(size[1])))))


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
        quality: neural render quality; palette: (P, 3) colors in [0, 1] (None: the learned
            palette); background: RGB in [0, 1] (None: the model's); motion: the session's motion;
            composition: how neural frames are composed (what the window shows,
            :data:`~garmentnerf.render.session.COMPOSITIONS`).
        fps: video frame rate.
        sequence: the :class:`~garmentnerf.viewer.sequence.BodySequence` (body-only jobs);
            scene_options: ``{"floor": bool, "grid": bool, "body": bool, "samples": int}`` for them.
    """

    def __init__(self, kind: str, plan: Plan, path: str | Path, *, source: str = "neural", quality: float = 1.0,
                 palette=None, background=None, motion=None, fps: float = 30.0, sequence=None,
                 scene_options: dict | None = None, clock: Callable[[], float] = time.monotonic,
                 composition: str = "auto") -> None:
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
        self.composition = composition
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
