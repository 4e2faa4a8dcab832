"""Baking a clip into a bake folder: the frames it lacks, in worker processes, resumable.

:func:`prepare_folder` opens the folder for a model, motion and capture settings (making it, resuming
it, or refusing one made for something else); :func:`bake_frames` bakes the frames it lacks, one
worker process per core by default, each rendering with one torch thread (the skirt demo's 170 frames at the
``balanced`` preset: 7.7 minutes in two processes on the 2-core machine, 2.7 s a frame of wall time where
each process spends 5.3 s on a frame), writing each frame's file as soon as it is done. A frame whose file is damaged is baked
again, with a notice. ``garmentnerf bake`` and the previewer's "Bake clip" are its users.
"""

from __future__ import annotations

import multiprocessing
import os
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from garmentnerf.bake.capture import capture_frame
from garmentnerf.bake.settings import BakeSettings
from garmentnerf.bake.store import MANIFEST_FILE, BakeFileError, BakeFolder, model_key, motion_key
from garmentnerf.folder_lock import LOCK_FILE


def manifest_for_session(session, settings: BakeSettings) -> dict:
    """The manifest of a bake of ``session``'s run and motion with ``settings``."""
    name = session.sequence or session.motion.name
    return BakeFolder.manifest_for(model_key(session.run), motion_key(session.posed.vertices.detach().cpu()), name,
                                   settings, session.num_frames, Path(session.run.root).name, session.fps,
                                   session.learned_palette().cpu().numpy())


def prepare_folder(root, manifest: dict, body_faces, overwrite: bool = False,
                   notice: Callable[[str], None] = print) -> BakeFolder:
    """The bake folder ``root`` ready for ``manifest``'s bake.

    - missing or empty: made;
    - a bake of the same model, motion and settings: resumed (its frames are kept);
    - a bake of something else, or a folder of other files: ValueError of one line, or with ``overwrite``
      (a bake folder only) its frames are deleted and it is made again.
    """
    root = Path(root)
    if root.exists() and not root.is_dir():
        raise ValueError(f"{root}: is a file, not a bake folder")
    if root.is_dir() and any(p.name != LOCK_FILE for p in root.iterdir()):
        if not (root / MANIFEST_FILE).is_file():
            raise ValueError(f"{root}: not empty and not a bake folder; give a new or empty folder")
        try:
            folder = BakeFolder.open(root)
            why = folder.mismatch(manifest)
        except ValueError as exc:
            why = str(exc)
        if why is None:
            return folder
        if not overwrite:
            raise ValueError(f"{why}; pass --overwrite to bake it again, or give another folder")
        notice(f"bake: {why}: baking it again")
        shutil.rmtree(root / "frames", ignore_errors=True)
    return BakeFolder.create(root, manifest, body_faces)


@dataclass
class FrameDone:
    """One baked frame, as a worker reports it."""

    frame: int
    seconds: float
    bytes: int


# ---- worker processes ------------------------------------------------------------------------------------
_WORKER: dict = {}  # the worker process's own session (set by _start_worker in that process only)


def _start_worker(run_dir: str, scene: str | None, motion, settings: BakeSettings, root: str, device: str) -> None:
    """A worker process's start: one torch thread, its own GL context and render session."""
    import torch

    from garmentnerf.gl.context import create_context
    from garmentnerf.render.session import RenderSession
    from garmentnerf.runs import load_run

    torch.set_num_threads(1)
    run = load_run(run_dir, device=device, scene=scene)
    ctx = create_context(headless=True)
    _WORKER.update(session=RenderSession(run, ctx, motion), settings=settings, folder=BakeFolder.open(root))


def _bake_in_worker(frame: int) -> FrameDone:
    session, settings, folder = _WORKER["session"], _WORKER["settings"], _WORKER["folder"]
    t0 = time.perf_counter()
    baked = capture_frame(session, frame, settings)
    path = folder.save_frame(baked)
    return FrameDone(frame, time.perf_counter() - t0, path.stat().st_size)


def frames_to_bake(folder: BakeFolder, frames: list[int], notice: Callable[[str], None] = print) -> list[int]:
    """Those of ``frames`` the folder lacks, or holds damaged (with a notice each)."""
    have = folder.baked_frames()
    todo = []
    for f in frames:
        if f in have:
            try:
                folder.load_frame(f)
                continue
            except BakeFileError as exc:
                notice(f"bake: {exc}: baking it again")
        todo.append(f)
    return todo


def bake_frames(run_dir, scene, motion, settings: BakeSettings, folder: BakeFolder, frames: list[int],
                workers: int = 1, device: str = "cpu",
                on_frame: Callable[[FrameDone], None] | None = None) -> list[FrameDone]:
    """Bake ``frames`` into ``folder`` in ``workers`` processes (module docstring); each frame's file is
    written when it is done, so an interruption (KeyboardInterrupt, raised here after the workers are
    stopped) keeps every finished frame."""
    if not frames:
        return []
    workers = max(1, min(int(workers), len(frames)))
    done: list[FrameDone] = []
    context = multiprocessing.get_context("spawn")
    pool = context.Pool(workers, initializer=_start_worker,
                        initargs=(str(run_dir), None if scene is None else str(scene), motion, settings,
                                  str(folder.root), device))
    try:
        for result in pool.imap_unordered(_bake_in_worker, frames):
            done.append(result)
            if on_frame is not None:
                on_frame(result)
        pool.close()
    except BaseException:
        pool.terminate()
        raise
    finally:
        pool.join()
    return done


def default_workers() -> int:
    """One bake process per core this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


__all__ = ["prepare_folder", "manifest_for_session", "frames_to_bake", "bake_frames", "default_workers", "FrameDone"]
