"""A bake folder: the baked frames of one model and one motion, on disk, written as they are made.

Layout
    ``bake.json`` (the manifest: the format, the model's and the motion's keys, the capture settings,
    the motion's frame count and name) and ``frames/NNNNN.npz``, one file per baked frame, each
    written atomically when its frame is done. A killed bake loses at most the frame it was making;
    baking again into the folder makes only the frames it lacks.

Keys
    :func:`model_key` names the weights, the body appearance and the model's config; :func:`motion_key`
    the posed body of every frame (motion, shape and frame rate). A folder is only used for the
    model, motion and capture settings it was made with (:meth:`BakeFolder.mismatch`); the previewer's
    cache (:func:`cache_folder`) is keyed by all three, so a second launch finds its bake at once.

A frame file
    ``body.vertices`` (V, 3) float16, the posed body (millimetres at the scale of a body); per view ``i``: ``v{i}.layers`` (L, H, W, 4) uint8, quantised per layer channel between
    ``v{i}.low`` and ``v{i}.high`` (L, 4) float32 (about 1/500 of each channel's range);
    ``v{i}.depth`` float16 camera z of the feature rays; ``v{i}.camera`` float64 (K, R, t, width,
    height, near, far). A file that cannot be read, or holds another frame, is :class:`BakeFileError`.
"""

from __future__ import annotations

import hashlib
import io
import json
import zipfile
from pathlib import Path

import numpy as np

from garmentnerf.bake.settings import BakeSettings
from garmentnerf.bake.views import BakedFrame, BakedView
from garmentnerf.conventions import Camera
from garmentnerf.io_utils import read_json_strict, user_cache_dir, write_file_atomic

BAKE_FORMAT = "garmentnerf-bake"
#: Part of every frame's format: bump it when what a frame file holds changes.
BAKE_VERSION = 1
MANIFEST_FILE = "bake.json"
FRAMES_DIR = "frames"
BODY_FACES_FILE = "body_faces.npy"


class BakeFileError(ValueError):
    """A bake file that cannot be used: unreadable, damaged, or of another frame."""


def _digest(*parts: bytes) -> str:
    h = hashlib.sha256()
    for part in parts:
        h.update(hashlib.sha256(part).digest())
    return h.hexdigest()[:32]


def _file_bytes_digest(path: Path) -> bytes:
    if not path.is_file():
        return b"-"
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.digest()


def model_key(run) -> str:
    """32 hex digits naming what a bake of ``run`` (a :class:`~garmentnerf.runs.LoadedRun`) depends on: its
    weights, its body appearance and its model config."""
    from garmentnerf.model.body_appearance import BODY_APPEARANCE_FILE
    from garmentnerf.runs import MODEL_FILE

    root = Path(run.root)
    config = json.dumps(run.config.to_dict(), sort_keys=True).encode()
    return _digest(_file_bytes_digest(root / MODEL_FILE), _file_bytes_digest(root / BODY_APPEARANCE_FILE), config)


def motion_key(posed_vertices) -> str:
    """32 hex digits naming a posed motion: its (T, V, 3) posed body vertices (motion, shape, frame rate)."""
    a = np.ascontiguousarray(np.asarray(posed_vertices, dtype=np.float32))
    return _digest(str(a.shape).encode(), a.tobytes())


def _camera_record(c: Camera) -> np.ndarray:
    return np.concatenate([c.K.ravel(), c.R.ravel(), c.t, [c.width, c.height, c.near, c.far]]).astype(np.float64)


def _camera_from(record: np.ndarray) -> Camera:
    r = np.asarray(record, dtype=np.float64)
    if r.shape != (25,):
        raise ValueError(f"camera record of {r.shape} values")
    return Camera(r[:9].reshape(3, 3), r[9:18].reshape(3, 3), r[18:21], int(r[21]), int(r[22]), float(r[23]),
                  float(r[24]))


def frame_bytes(baked: BakedFrame) -> bytes:
    """The frame file of ``baked`` (module docstring)."""
    arrays: dict[str, np.ndarray] = {"frame": np.array([baked.frame], np.int64),
                                     "version": np.array([BAKE_VERSION], np.int64),
                                     "views": np.array([len(baked.views)], np.int64)}
    for i, view in enumerate(baked.views):
        arrays[f"v{i}.layers"] = view.codes
        arrays[f"v{i}.low"] = view.low
        arrays[f"v{i}.high"] = view.high
        arrays[f"v{i}.depth"] = view.depth.astype(np.float16)
        arrays[f"v{i}.camera"] = _camera_record(view.camera)
        arrays[f"v{i}.cell"] = np.array([view.cell], np.int64)
    if baked.body_vertices is not None:
        arrays["body.vertices"] = np.asarray(baked.body_vertices, np.float16)
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **arrays)
    return buffer.getvalue()


def read_frame_file(path: Path, frame: int | None = None) -> BakedFrame:
    """The :class:`BakedFrame` in ``path``; :class:`BakeFileError` naming the file when it cannot be used."""
    try:
        with np.load(path, allow_pickle=False) as data:
            version = int(data["version"][0])
            if version != BAKE_VERSION:
                raise BakeFileError(f"{path}: a bake file of format {version}, this version reads {BAKE_VERSION}")
            stored = int(data["frame"][0])
            if frame is not None and stored != frame:
                raise BakeFileError(f"{path}: holds frame {stored}, not {frame}")
            views = []
            for i in range(int(data["views"][0])):
                codes = data[f"v{i}.layers"]
                low, high = data[f"v{i}.low"].astype(np.float32), data[f"v{i}.high"].astype(np.float32)
                depth = data[f"v{i}.depth"].astype(np.float32)
                cell = int(data[f"v{i}.cell"][0])
                camera = _camera_from(data[f"v{i}.camera"])
                if (codes.dtype != np.uint8 or codes.ndim != 4 or codes.shape[3] != 4
                        or codes.shape[1:3] != (camera.height, camera.width) or low.shape != (codes.shape[0], 4)
                        or high.shape != low.shape or depth.shape != (camera.height // cell, camera.width // cell)
                        or not np.isfinite(low).all() or not np.isfinite(high).all() or not np.isfinite(depth).all()):
                    raise BakeFileError(f"{path}: view {i} is inconsistent")
                views.append(BakedView(camera, codes, low, high, depth, cell))
            body = data["body.vertices"].astype(np.float32) if "body.vertices" in data.files else None
            if body is not None and (body.ndim != 2 or body.shape[1] != 3 or not np.isfinite(body).all()):
                raise BakeFileError(f"{path}: the body's vertices are inconsistent")
    except BakeFileError:
        raise
    except (OSError, KeyError, ValueError, IndexError, EOFError, zipfile.BadZipFile) as exc:
        raise BakeFileError(f"{path}: not a readable bake frame ({type(exc).__name__}: {exc})") from None
    return BakedFrame(stored, tuple(views), body)


class BakeFolder:
    """A bake folder (module docstring). Make one with :meth:`create`, open one with :meth:`open`."""

    def __init__(self, root: Path, manifest: dict) -> None:
        self.root = Path(root)
        self.manifest = manifest

    @property
    def num_frames(self) -> int:
        return int(self.manifest["num_frames"])

    @property
    def settings(self) -> dict:
        return dict(self.manifest["capture"])

    @staticmethod
    def manifest_for(model: str, motion: str, motion_name: str, settings: BakeSettings, num_frames: int,
                     run_name: str = "", fps: float = 30.0, palette=None) -> dict:
        """What :meth:`create` writes: the keys, the capture settings, the motion's name, frame count and
        rate, the run's name and its learned palette (the body's colour last)."""
        return {"format": BAKE_FORMAT, "version": BAKE_VERSION, "model": model, "motion": motion,
                "motion_name": str(motion_name), "run": str(run_name), "num_frames": int(num_frames),
                "fps": float(fps), "palette": [] if palette is None else np.asarray(palette, float).tolist(),
                "capture": settings.capture_key()}

    def body_faces(self) -> np.ndarray | None:
        """(F, 3) int64 the body's triangles (written by :meth:`create` when given), None when missing."""
        path = self.root / BODY_FACES_FILE
        if not path.is_file():
            return None
        try:
            faces = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise BakeFileError(f"{path}: not readable ({exc})") from None
        if faces.ndim != 2 or faces.shape[1] != 3:
            raise BakeFileError(f"{path}: not a (F, 3) array of triangles")
        return faces.astype(np.int64)

    @classmethod
    def create(cls, root, manifest: dict, body_faces: np.ndarray | None = None) -> "BakeFolder":
        """A new bake folder at ``root`` (made if missing, or empty) with ``manifest`` and the body's
        triangles."""
        root = Path(root)
        (root / FRAMES_DIR).mkdir(parents=True, exist_ok=True)
        if body_faces is not None:
            buffer = io.BytesIO()
            np.save(buffer, np.asarray(body_faces, np.int32))
            write_file_atomic(root / BODY_FACES_FILE, buffer.getvalue())
        write_file_atomic(root / MANIFEST_FILE, (json.dumps(manifest, indent=1, sort_keys=True) + "\n").encode())
        return cls(root, manifest)

    @classmethod
    def open(cls, root) -> "BakeFolder":
        """The bake folder at ``root``; ValueError of one line naming it when it is not one."""
        root = Path(root)
        path = root / MANIFEST_FILE
        if not path.is_file():
            raise ValueError(f"{root}: not a bake folder (no {MANIFEST_FILE})")
        manifest = read_json_strict(path, "bake manifest")
        if not isinstance(manifest, dict) or manifest.get("format") != BAKE_FORMAT:
            raise ValueError(f"{path}: not a garmentnerf bake manifest")
        if manifest.get("version") != BAKE_VERSION:
            raise ValueError(f"{path}: a bake of format {manifest.get('version')}, this version reads {BAKE_VERSION}")
        for key, kind in (("model", str), ("motion", str), ("num_frames", int), ("capture", dict)):
            if not isinstance(manifest.get(key), kind) or isinstance(manifest.get(key), bool):
                raise ValueError(f"{path}: `{key}` is missing or not a {kind.__name__}")
        if manifest["num_frames"] < 1:
            raise ValueError(f"{path}: `num_frames` must be at least 1")
        return cls(root, manifest)

    def mismatch(self, manifest: dict) -> str | None:
        """Why this folder cannot hold the bake ``manifest`` describes (another model, motion or capture
        settings), or None when it can."""
        for key, what in (("model", "another model (or other weights)"), ("motion", "another motion or body"),
                          ("capture", "other bake settings")):
            if self.manifest.get(key) != manifest.get(key):
                return f"{self.root}: a bake of {what}"
        return None

    def frame_path(self, frame: int) -> Path:
        return self.root / FRAMES_DIR / f"{int(frame):05d}.npz"

    def baked_frames(self) -> set[int]:
        """The frames that have a file (not checked: :meth:`load_frame` checks)."""
        out = set()
        folder = self.root / FRAMES_DIR
        if folder.is_dir():
            for path in folder.glob("[0-9][0-9][0-9][0-9][0-9].npz"):
                out.add(int(path.stem))
        return {f for f in out if f < self.num_frames}

    def save_frame(self, baked: BakedFrame) -> Path:
        """Write ``baked`` atomically (replacing a damaged file of the same frame)."""
        return write_file_atomic(self.frame_path(baked.frame), frame_bytes(baked))

    def load_frame(self, frame: int) -> BakedFrame | None:
        """The baked frame, None when it has no file; :class:`BakeFileError` when its file is damaged."""
        path = self.frame_path(frame)
        if not path.is_file():
            return None
        return read_frame_file(path, int(frame))


def cache_folder(manifest: dict) -> Path:
    """The user's cache folder of the bake ``manifest`` describes (:func:`~garmentnerf.io_utils.user_cache_dir`
    ``bakes``, one folder per model, motion and capture settings)."""
    blob = json.dumps({k: manifest[k] for k in ("model", "motion", "capture")}, sort_keys=True).encode()
    return user_cache_dir("bakes") / _digest(blob)


__all__ = ["BakeFolder", "BakeFileError", "model_key", "motion_key", "frame_bytes", "read_frame_file", "cache_folder",
           "BAKE_FORMAT", "BAKE_VERSION", "MANIFEST_FILE", "FRAMES_DIR", "BODY_FACES_FILE"]
