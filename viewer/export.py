"""Snapshots: the scene rendered off-screen at a chosen resolution, saved as PNG; export file names.

This module holds the GL snapshot (body only, and the viewer's diagnostic view modes), taken at once
on the UI thread. Snapshots of the neural garment and videos take longer and render on their own
thread through the headless command's path: see :mod:`~garmentnerf.viewer.exporter`, which writes
its PNGs with :func:`write_png` (the same names and never-overwrite rule).

The snapshot resolution is independent of the window: the camera controller produces a camera of
the requested size (same vertical field of view; the horizontal extent follows the aspect ratio) and
the scene renderer draws it into its own target with the same code that draws the window, but
with its own multisampling (``SceneRenderer.snapshot_samples``, 4x by default, also where the window
runs without MSAA on a software rasteriser); the panels are not in it. Files are written
atomically (a temporary file renamed into place) and never replace an existing file: a taken name
gets the next free ``_001``, ``_002`` ... suffix.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from garmentnerf.io_utils import atomic_write_path, next_free_path

#: Largest snapshot side we accept (GL limits may be lower; the renderer checks those).
MAX_SIDE = 16384

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
    if not (1 <= width <= MAX_SIDE and 1 <= height <= MAX_SIDE):
        raise ValueError(f"{what} {width}x{height} is out of range (1..{MAX_SIDE} per side)")


def _safe_stem(motion: str) -> str:
    """``motion``'s name with characters unsafe in file names replaced."""
    return re.sub(r"[^A-Za-z0-9_.-]+", "-", Path(str(motion)).stem or "body").strip("-.") or "body"


def snapshot_name(motion: str, frame: int) -> str:
    """File name for a snapshot of ``motion`` at ``frame`` (characters unsafe in file names replaced)."""
    return f"{_safe_stem(motion)}_f{int(frame):04d}.png"


def video_name(motion: str, label: str) -> str:
    """File name of a video export, e.g. ``walk_turntable.mp4`` or ``walk_f0003-0010.mp4``."""
    tag = re.sub(r"[^A-Za-z0-9_.-]+", "-", str(label)).strip("-.") or "video"
    return f"{_safe_stem(motion)}_{tag}.mp4"


def write_png(image: np.ndarray, path: str | Path, attempts: int = 20) -> Path:
    """Write (H, W, 3|4) uint8 ``image`` to ``path`` or, if taken, the next free numbered name.

    Never overwrites: the final rename is a hard link that fails if the name appeared meanwhile
    (another process snapshotting into the same folder), in which case the next free name is tried.
    Returns the path written.
    """
    from PIL import Image

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


def render_snapshot(scene, controller, width: int, height: int) -> np.ndarray:
    """(H, W, 3) uint8: ``scene`` (a :class:`~garmentnerf.viewer.scene_gl.SceneRenderer`) seen by
    ``controller``'s current view at ``width`` x ``height``."""
    check_size(width, height, "snapshot size")
    return scene.render_image(controller.camera(width, height), samples=scene.snapshot_samples)


def save_snapshot(scene, controller, width: int, height: int, directory: str | Path, motion: str,
                  frame: int) -> Path:
    """Render and write one snapshot into ``directory``; returns its path."""
    image = render_snapshot(scene, controller, width, height)
    return write_png(image, Path(directory) / snapshot_name(motion, frame))
