"""Writing rendered frames: PNGs written atomically that never replace a file, and mp4 video.

PNG frames (:class:`FrameWriter`)
    ``<out>/<prefix>_<frame:04d>.png``. :meth:`FrameWriter.check` fails *before any rendering*
    when one of the names is taken (a second run into the same folder stops with a clear message
    instead of mixing two renders); each file is written to a temporary name and hard-linked into
    place, which fails if the name appeared meanwhile, so even a race never overwrites.

Video (:class:`VideoWriter`)
    H.264 mp4 through imageio-ffmpeg, written to a temporary file in the same folder and linked
    into place when closed (never replacing a file). Frames with an odd side are padded by
    repeating the last row/column (yuv420p needs even sizes). Closing after an interruption still
    gives a valid, shorter video. Before it is linked into place the file is checked: not empty,
    readable by imageio, holding every frame appended (:func:`check_video`); a file that fails,
    or whose encoder failed, is removed and :class:`VideoError` says why. The frame rate must be
    in :data:`garmentnerf.budgets.VIDEO_FPS` (as ``render --fps`` and a camera path's ``fps`` must be).
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path

import imageio.v3 as iio
import imageio_ffmpeg
import numpy as np
from PIL import Image

from garmentnerf.budgets import VIDEO_FPS
from garmentnerf.io_utils import atomic_write_path, remove_stale_temporaries


class VideoError(ValueError):
    """A video could not be written or did not check out (one line; the partial file is removed)."""


def to_uint8(image: np.ndarray) -> np.ndarray:
    """(H, W, 3) float in [0, 1] (or uint8) -> uint8."""
    image = np.asarray(image)
    if image.dtype == np.uint8:
        return image
    return np.clip(np.rint(np.asarray(image, dtype=np.float64) * 255.0), 0, 255).astype(np.uint8)


def write_png_exclusive(image: np.ndarray, path: str | Path) -> Path:
    """Write ``image`` to ``path`` atomically; FileExistsError if ``path`` exists (never overwrites)."""
    path = Path(path)
    with atomic_write_path(path, overwrite=False) as tmp:
        Image.fromarray(to_uint8(image)).save(tmp, format="PNG")
    return path


class FrameWriter:
    """PNG frames ``<directory>/<prefix>_<frame:04d>.png`` (see the module docstring)."""

    def __init__(self, directory: str | Path, prefix: str = "frame") -> None:
        self.directory = Path(directory)
        self.prefix = prefix
        self.written: list[Path] = []

    def path(self, frame: int) -> Path:
        return self.directory / f"{self.prefix}_{int(frame):04d}.png"

    def check(self, frames) -> None:
        """FileExistsError naming the first taken file among ``frames``'s names."""
        if self.directory.exists() and not self.directory.is_dir():
            raise ValueError(f"{self.directory}: exists and is not a folder")
        remove_stale_temporaries(self.directory, f"{self.prefix}_*.png")
        for f in frames:
            p = self.path(f)
            if p.exists():
                raise FileExistsError(f"{p}: already exists (refusing to overwrite; choose another --out folder)")

    def write(self, frame: int, image: np.ndarray) -> Path:
        path = write_png_exclusive(image, self.path(frame))
        self.written.append(path)
        return path


class VideoWriter:
    """mp4 (H.264, yuv420p) of equally sized RGB frames; use as a context manager or call
    :meth:`close`. ``path`` must not exist (checked at once and again when the file is linked)."""

    def __init__(self, path: str | Path, fps: float, quality: float = 7.0) -> None:
        self.path = Path(path)
        if self.path.exists():
            raise FileExistsError(f"{self.path}: already exists (refusing to overwrite)")
        self.fps = VIDEO_FPS.check(fps, "video fps")
        self.quality = quality
        self.frames = 0
        self._gen = None
        self._size: tuple[int, int] | None = None
        self.path.parent.mkdir(parents=True, exist_ok=True)
        remove_stale_temporaries(self.path.parent, self.path.name)
        fd, tmp = tempfile.mkstemp(prefix=f".{self.path.name}.", suffix=".tmp", dir=self.path.parent)
        os.close(fd)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; give the file the usual permissions
        self._tmp = Path(tmp)

    def append(self, image: np.ndarray) -> None:
        frame = to_uint8(image)
        if frame.ndim != 3 or frame.shape[2] != 3:
            raise ValueError(f"video frames must be (H, W, 3), got {frame.shape}")
        h, w = frame.shape[:2]
        ph, pw = h + (h % 2), w + (w % 2)
        if (ph, pw) != (h, w):
            frame = np.pad(frame, ((0, ph - h), (0, pw - w), (0, 0)), mode="edge")
        try:
            if self._gen is None:
                self._size = (pw, ph)
                self._gen = imageio_ffmpeg.write_frames(str(self._tmp), (pw, ph), fps=self.fps, codec="libx264",
                                                        quality=self.quality, macro_block_size=1,
                                                        output_params=["-f", "mp4"], ffmpeg_log_level="error")
                self._gen.send(None)
            elif (pw, ph) != self._size:
                raise ValueError(f"video frame {w}x{h} differs from the first frame's size {self._size}")
            self._gen.send(np.ascontiguousarray(frame))
        except (OSError, RuntimeError) as exc:  # the encoder died (a broken pipe) or would not start
            self.abort()
            raise VideoError(f"{self.path}: the video encoder failed at frame {self.frames + 1} "
                             f"({_first_line(exc)}); no video written") from None
        self.frames += 1

    def close(self) -> Path | None:
        """Finish the file, check it (:func:`check_video`) and link it into place; returns its path
        (None when no frame was added). VideoError (the file removed) when it does not check out."""
        gen, self._gen = self._gen, None
        try:
            if gen is None:
                return None
            try:
                gen.close()
            except (OSError, RuntimeError) as exc:
                raise VideoError(f"{self.path}: the video encoder failed ({_first_line(exc)}); no video "
                                 f"written") from None
            check_video(self._tmp, self.frames, shown=self.path)
            os.link(self._tmp, self.path)  # fails if the name appeared meanwhile: never clobber
            return self.path
        finally:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self._tmp)

    def abort(self) -> None:
        gen, self._gen = self._gen, None
        if gen is not None:
            with contextlib.suppress(Exception):
                gen.close()
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self._tmp)

    def __enter__(self) -> "VideoWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None or issubclass(exc_type, KeyboardInterrupt):
            self.close()
        else:
            self.abort()


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def count_video_frames(path: str | Path) -> int:
    """Frames in an mp4 file (whatever its name: a temporary too), decoded with imageio's ffmpeg
    reader (for tests and checks)."""
    return sum(1 for _ in iio.imiter(str(path), plugin="FFMPEG", extension=".mp4"))


def check_video(path: str | Path, frames: int, shown: str | Path | None = None) -> None:
    """VideoError (naming ``shown``, default ``path``) unless the video file ``path`` is not empty,
    is readable by imageio and holds ``frames`` frames."""
    shown = path if shown is None else shown
    try:
        size = os.path.getsize(path)
    except OSError as exc:
        raise VideoError(f"{shown}: the video was not written ({exc.strerror or exc})") from None
    if size == 0:
        raise VideoError(f"{shown}: the video encoder wrote an empty file; no video written")
    try:
        found = count_video_frames(path)
    except Exception as exc:  # noqa: BLE001 - imageio/ffmpeg raise many kinds for a damaged file
        raise VideoError(f"{shown}: the video written is not readable ({_first_line(exc)}); no video "
                         f"written") from None
    if found != frames:
        raise VideoError(f"{shown}: the video written holds {found} frame(s), not the {frames} rendered; no "
                         f"video written")


__all__ = ["FrameWriter", "VideoWriter", "VideoError", "write_png_exclusive", "to_uint8", "count_video_frames",
           "check_video"]
