"""The clip's baked frames in the previewer: baked by a background process, kept on disk, loaded for the window.

:class:`BakeProcess` runs ``garmentnerf bake --cache`` for the run and the clip (one process on one core,
with one torch thread: the window's render worker keeps the other), which bakes the frames the user's
cache folder of the run, motion and bake preset lacks (:func:`~garmentnerf.bake.store.cache_folder`),
resumable, and prints the folder first. :class:`ClipBakes` keeps the bakes for the UI thread: a loader
thread watches the folder for new frames, reads them nearest the playhead first, makes their view meshes
(so the UI thread only uploads) and keeps them in memory (a byte-bounded cache, :data:`BAKES_IN_MEMORY_MB`).
A second launch finds the folder full and loads it at once. The timeline's bar shows :meth:`ClipBakes.baked`.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

from garmentnerf.bake.store import BakeFileError, BakeFolder
from garmentnerf.bake.views import BakedFrame
from garmentnerf.byte_lru import ByteBoundedLRU

#: How often the loader looks for frames the bake process wrote (seconds).
DISK_POLL_SECONDS = 0.5
#: Frames whose arrival times give the bake's rate (and so its time left).
ETA_WINDOW = 8
#: Memory the baked frames of the clip may hold (MiB): a balanced skirt frame is about 8 MiB with its
#: view meshes, so this keeps a 170-frame clip.
BAKES_IN_MEMORY_MB = 2048.0


def _frame_bytes(baked: BakedFrame) -> int:
    meshes = sum(m.positions.nbytes + m.texcoords.nbytes + m.faces.nbytes
                 for v in baked.views for m in v._meshes.values())
    return baked.nbytes + meshes


class ClipBakes:
    """The baked frames of the clip the window shows (module docstring). Thread-safe.

    Args:
        mesh_step: the view meshes' step the window draws with (made off the UI thread).
        budget_mb: :data:`BAKES_IN_MEMORY_MB`.
    """

    def __init__(self, mesh_step: int = 1, budget_mb: float = BAKES_IN_MEMORY_MB) -> None:
        self.mesh_step = int(mesh_step)
        self._lock = threading.Condition()
        self._memory: ByteBoundedLRU[int, BakedFrame] = ByteBoundedLRU(int(budget_mb * 2**20), _frame_bytes)
        self._folder: BakeFolder | None = None
        self._on_disk: set[int] = set()
        self._num_frames = 0
        self._playhead = 0
        self._stop = False
        self._serial = 0  # a new folder (another clip or run) makes the loader start over
        self._arrivals: list[float] = []  # when the last frames appeared on disk (the bake's rate)
        self.errors: list[str] = []
        self._thread = threading.Thread(target=self._load_loop, name="garmentnerf-bake-loader", daemon=True)
        self._thread.start()

    # ---- the folder ----------------------------------------------------------------------------------
    def use_folder(self, folder: BakeFolder | None) -> None:
        """The bake folder of the clip now shown (None: none): what is in memory of another goes."""
        with self._lock:
            if folder is not None and self._folder is not None and folder.root == self._folder.root:
                return
            self._folder = folder
            self._serial += 1
            for key in list(self._memory.keys()):
                self._memory.pop(key)
            self._on_disk = folder.baked_frames() if folder is not None else set()
            self._arrivals = []
            self._num_frames = folder.num_frames if folder is not None else 0
            self._lock.notify_all()

    # ---- for the UI thread ---------------------------------------------------------------------------
    def set_playhead(self, frame: int) -> None:
        with self._lock:
            if frame != self._playhead:
                self._playhead = int(frame)
                self._lock.notify_all()

    def get(self, frame: int) -> BakedFrame | None:
        """The baked ``frame`` if it is in memory (never waits)."""
        with self._lock:
            return self._memory.get(int(frame))

    def baked(self) -> set[int]:
        """The frames that have a bake (on disk or just made)."""
        with self._lock:
            return set(self._on_disk)

    @property
    def num_frames(self) -> int:
        return self._num_frames

    @property
    def folder(self) -> BakeFolder | None:
        return self._folder

    def loaded(self) -> int:
        with self._lock:
            return len(self._memory)

    # ---- the loader thread -----------------------------------------------------------------------------
    def _next_to_load(self) -> tuple[int, BakeFolder, int] | None:
        """(frame, folder, serial) on disk and not in memory, nearest ahead of the playhead; None: nothing."""
        if self._folder is None or not self._on_disk:
            return None
        n = max(1, self._num_frames)
        missing = [f for f in self._on_disk if f not in self._memory]
        if not missing:
            return None
        frame = min(missing, key=lambda f: (f - self._playhead) % n)
        return frame, self._folder, self._serial

    def _look_at_disk(self) -> None:
        """The frames the folder holds now (another process bakes into it), and when new ones appeared."""
        folder = self._folder
        if folder is not None:
            found = folder.baked_frames()
            with self._lock:
                if folder is self._folder:
                    new = found - self._on_disk
                    if new:
                        self._arrivals.extend([time.monotonic()] * len(new))
                        del self._arrivals[:-ETA_WINDOW]
                    self._on_disk |= found

    def seconds_left(self) -> float | None:
        """The time the bake of the clip still needs at the rate its last frames arrived (None: unknown)."""
        with self._lock:
            left = self._num_frames - len(self._on_disk)
            if left <= 0:
                return 0.0
            if len(self._arrivals) < 2 or self._arrivals[-1] <= self._arrivals[0]:
                return None
            per_frame = (self._arrivals[-1] - self._arrivals[0]) / (len(self._arrivals) - 1)
            return left * per_frame

    def _load_loop(self) -> None:
        while True:
            self._look_at_disk()
            with self._lock:
                job = None
                deadline = time.monotonic() + DISK_POLL_SECONDS
                while not self._stop:
                    job = self._next_to_load()
                    if job is not None or time.monotonic() >= deadline:
                        break
                    self._lock.wait(DISK_POLL_SECONDS)
                if self._stop:
                    return
            if job is None:
                continue
            frame, folder, serial = job
            try:
                baked = folder.load_frame(frame)
            except (BakeFileError, OSError) as exc:
                with self._lock:
                    self.errors.append(str(exc))
                    self._on_disk.discard(frame)  # the worker bakes it again
                continue
            if baked is None:
                with self._lock:
                    self._on_disk.discard(frame)
                continue
            for view in baked.views:
                view.mesh(self.mesh_step)
            with self._lock:
                if serial == self._serial:
                    self._memory.put(frame, baked)

    def close(self) -> None:
        with self._lock:
            self._stop = True
            self._lock.notify_all()
        self._thread.join(2.0)


class BakeProcess:
    """``garmentnerf bake --cache`` of a run and clip in a process of its own (module docstring).

    Args:
        run_dir: the run folder; motion: the clip (a scene sequence or motion name); preset: the bake preset;
        scene: the scene folder the run is shown with (None: the run's own); first: the frame to bake first
            (the playhead's; the frames after it follow, then those before).
        on_folder: called (on a reader thread) with the bake folder's path once the process names it.
    """

    def __init__(self, run_dir, motion: str | None, preset: str, on_folder, scene=None, first: int = 0) -> None:
        command = [sys.executable, "-m", "garmentnerf.cli.main", "bake", "--run", str(run_dir), "--cache",
                   "--preset", preset, "--workers", "1", "--no-progress", "--first", str(int(first))]
        if motion is not None:
            command += ["--motion", str(motion)]
        if scene is not None:
            command += ["--scene", str(scene)]
        env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
        self.started = time.monotonic()
        self.error = ""
        self.folder: Path | None = None
        self._proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                                      start_new_session=True)
        self._on_folder = on_folder
        self._reader = threading.Thread(target=self._read, name="garmentnerf-bake-output", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self._proc.stdout:
            if line.startswith("bake folder: ") and self.folder is None:
                self.folder = Path(line[len("bake folder: "):].strip())
                self._on_folder(self.folder)
        err = self._proc.stderr.read().strip().splitlines()
        if self._proc.wait() not in (0, -15) and err:
            self.error = err[-1]

    @property
    def running(self) -> bool:
        return self._proc.poll() is None

    def stop(self) -> None:
        """End the process and its worker (the frames finished stay in the folder)."""
        if self._proc.poll() is None:
            try:
                os.killpg(self._proc.pid, signal.SIGTERM)  # its own session: the bake worker goes too
                self._proc.wait(5.0)
            except subprocess.TimeoutExpired:
                os.killpg(self._proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass


__all__ = ["ClipBakes", "BakeProcess", "BAKES_IN_MEMORY_MB", "DISK_POLL_SECONDS"]
