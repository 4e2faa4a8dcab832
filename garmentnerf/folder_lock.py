"""One writer per folder: the advisory lock every command that writes into a run (or a scene) holds.

A writer takes :func:`lock_folder` on the folder before it reads what it will change:

- run folders: ``train`` (and each stage folder of ``train --recipe``, whose own folder is locked
  for the whole sitting), ``body fit-appearance`` writing into a run, ``report`` on its runs folder
  and on each variant while it trains or is evaluated;
- scene folders: ``data make`` on the scene, each of its simulation processes on its
  ``sim/<sequence>`` folder, ``data add-sequence`` on the scene that receives the sequence;
- the bundled demos' folder: ``demo pack`` while it checks and replaces a demo's run and scene.

The scene's image cache (``cache/``, filled by ``data render`` and by every reader that renders a
missing ground-truth image) takes no lock: its files are named by a digest of what they show and
written atomically, so two processes filling it write the same bytes to the same name.

The lock is ``flock`` on the file :data:`LOCK_FILE` in the folder: the kernel releases it when the
holding process ends, however it ends (a crash or SIGKILL leaves at most a stale file, which the
next writer takes over). A second writer is refused with :class:`FolderBusyError`, one line naming
the holder's PID and command (or, with ``wait_s``, after waiting that long for the holder to end).
Readers (``view``, ``eval``, ``render``, ``demo pack`` of the run it packs) take no lock: every file
of a run is written atomically, so they see the old or the new file, never half of one.

A clean release deletes the lock file (under the lock; a new holder checks that the file it locked
is still the one at the path, so two holders never coexist), and removes again the folders the
lock itself created when nothing else was written into them, so a writer refused later for another
reason leaves no trace. Checks such as "is the run folder empty?" ignore the lock file:
:func:`folder_has_files`.

POSIX only (``fcntl``); where ``fcntl`` is missing nothing is locked.
"""

from __future__ import annotations

import contextlib
import os
import time
from pathlib import Path

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX
    fcntl = None

__all__ = ["LOCK_FILE", "FolderBusyError", "FolderLock", "lock_folder", "folder_has_files"]

#: The lock file's name inside a locked folder.
LOCK_FILE = ".garmentnerf-writer.lock"


class FolderBusyError(ValueError):
    """Another process holds the folder's writer lock (a user error: one line, exit 2)."""


def folder_has_files(folder) -> bool:
    """Whether ``folder`` holds anything besides a writer's lock file (False for a missing folder;
    True for a path that is a file)."""
    folder = Path(folder)
    if not folder.exists():
        return False
    if not folder.is_dir():
        return True
    return any(p.name != LOCK_FILE for p in folder.iterdir())


def _holder(fd: int) -> str:
    with contextlib.suppress(OSError):
        text = os.pread(fd, 512, 0).decode("utf-8", "replace").strip()
        pid, _, command = text.partition(" ")
        if pid.isdigit():
            return f"PID {pid}" + (f", '{command}'" if command else "")
    return "PID unknown: it is starting"


class FolderLock:
    """The writer lock of one folder, held from :func:`lock_folder` until :meth:`release` (or the
    end of a ``with`` block, or the process)."""

    def __init__(self, folder: Path, fd: int | None, created: list[Path]):
        self.folder = folder
        self._fd = fd
        self._created = created  # folders the lock made, outermost first

    @property
    def held(self) -> bool:
        return self._fd is not None

    def release(self) -> None:
        """Delete the lock file, remove the folders the lock made if nothing else was written into
        them, and unlock. Safe to call twice."""
        fd, self._fd = self._fd, None
        if fd is None:
            return
        try:
            with contextlib.suppress(OSError):
                (self.folder / LOCK_FILE).unlink()
            for folder in reversed(self._created):
                with contextlib.suppress(OSError):  # not empty: something was written, keep it
                    folder.rmdir()
        finally:
            os.close(fd)  # closing the last descriptor of the file releases the flock

    def __enter__(self) -> "FolderLock":
        return self

    def __exit__(self, *exc) -> None:
        self.release()

    def __del__(self):  # dropped without release: the descriptor (and so the lock) goes with the object
        if getattr(self, "_fd", None) is not None:
            with contextlib.suppress(OSError):
                os.close(self._fd)


def lock_folder(folder, command: str = "garmentnerf", *, what: str = "run", wait_s: float = 0.0,
                busy: str | None = None) -> FolderLock:
    """Take the writer lock of ``folder`` (made if missing) for this process.

    Args:
        command: what the holder is doing, shown to a writer that is refused.
        what: what the folder is, for the refusal (``run``, ``scene``, ...).
        wait_s: how long to wait for a holder to end before refusing (0: refuse at once).
        busy: the refusal instead of the default; ``{holder}`` in it is replaced by the holder's
            PID and command.
    Raises:
        FolderBusyError: another process holds it.
        NotADirectoryError: ``folder`` is a file.
    """
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise NotADirectoryError(f"{folder}: is a file, not a {what} folder")
    created = []
    missing = folder
    while not missing.exists() and missing != missing.parent:
        created.append(missing)
        missing = missing.parent
    created.reverse()
    folder.mkdir(parents=True, exist_ok=True)
    if fcntl is None:  # pragma: no cover - not POSIX
        return FolderLock(folder, None, created)
    path = folder / LOCK_FILE
    deadline = time.monotonic() + wait_s
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _holder(fd)
            os.close(fd)
            if time.monotonic() < deadline:
                time.sleep(0.1)
                continue
            for made in reversed(created):
                with contextlib.suppress(OSError):
                    made.rmdir()
            text = busy if busy is not None else (f"{folder}: another process is writing this {what} ({{holder}}); "
                                                  f"wait for it to finish or stop it, then try again")
            raise FolderBusyError(text.replace("{holder}", holder)) from None
        except BaseException:
            os.close(fd)
            raise
        # the file may have been deleted by the holder that just released it: lock the current one
        try:
            same = os.stat(path).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"{os.getpid()} {command}\n".encode("utf-8"), 0)
    return FolderLock(folder, fd, created)
