"""The schema of ``scene.json`` and its validation (the scene folder itself: :mod:`garmentnerf.data.scene`).

``scene.json``::

    {"format": "garmentnerf-scene", "version": 1,
     "image_size": [W, H], "fps": 30.0,
     "body": {"model": "anny", "shape": "average" | [betas...], "color": [r, g, b] (optional)},
     "garment": {"kind": "skirt", "color": [r, g, b], ...},
     "cameras": [{"name": "cam00", "K": 3x3, "R": 3x3, "t": [3], "width": W, "height": H,
                  "split": "train" | "unseen_view" | "reference", "near": .., "far": .. (optional)}],
     "sequences": {"train": {"motion": "walk,dance_a", "frames": N, "split": "train" | "unseen_motion", ...}},
     "palette_init": {"garment": [r, g, b], "body": [r, g, b],
                      "garment_layers": [[r, g, b], ...] (a layered garment's, inner first; optional)} or null,
     "simulation": {"<sequence>": {stats...}},
     "created_with": "garmentnerf 0.1.0"}

Colors are display RGB in [0, 1]. Cameras follow :mod:`garmentnerf.conventions` (OpenCV, world Z
up, metres); every camera has the scene's ``image_size``. Keys other than these are kept as they
are at the top level, in ``garment``, ``body`` and in each sequence; cameras accept no other keys
(a distortion model, say, must not be silently ignored).

:func:`parse_scene` checks everything and fails with :class:`SceneError`, a one-line message
naming the file and the field path, e.g. ``scenes/skirt/scene.json: cameras[3].K must be 3x3``.
"""

from __future__ import annotations

import math
import re
import zipfile
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from garmentnerf.conventions import DEFAULT_FAR, DEFAULT_NEAR, Camera
from garmentnerf.data.cameras import CAMERA_SPLITS, NamedCamera
from garmentnerf.io_utils import npz_member_shape

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

#: Tolerance of the rotation check (``|R R^T - I|`` entries, ``det R``): hand-written files round.
ROTATION_TOLERANCE = 1e-5

_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
_CAMERA_KEYS = frozenset({"name", "K", "R", "t", "width", "height", "split", "near", "far"})
_REQUIRED_KEYS = ("format", "version", "image_size", "fps", "body", "garment", "cameras", "sequences")
_KNOWN_KEYS = frozenset(_REQUIRED_KEYS) | {"palette_init", "simulation", "created_with"}


class SceneError(ValueError):
    """A scene folder or ``scene.json`` that is missing, malformed or inconsistent."""


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


# ---- field checks ---------------------------------------------------------------------------------
class SchemaChecker:
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

    def choice(self, value, path: str, options: tuple[str, ...]) -> str:
        if value not in options:
            raise self.fail(path, f"must be one of {', '.join(options)}, got {value!r}")
        return value

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


# ---- scene.json -----------------------------------------------------------------------------------
def parse_scene(data: Any, source: str, root: Path, check_files: bool) -> dict[str, Any]:
    """Validate a decoded ``scene.json`` and return the :class:`~garmentnerf.data.scene.Scene`
    constructor's keyword arguments (all but ``root``).

    Args:
        data: the decoded JSON.
        source: the file name errors start with.
        root: the scene folder (for ``check_files``).
        check_files: also check each sequence's ``motion.npz`` and ``garment.npz`` on disk.
    Raises:
        SceneError: one line naming ``source`` and the field.
    """
    v = SchemaChecker(source)
    v.obj(data, "")
    for key in _REQUIRED_KEYS:
        v.key(data, key, "")
    W, H, fps = _parse_header(v, data)
    body = _parse_body(v, data["body"])
    garment = _parse_garment(v, data["garment"])
    rig = _parse_cameras(v, data["cameras"], (W, H))
    sequences = _parse_sequences(v, data["sequences"])
    palette_init = _parse_palette(v, data.get("palette_init"))
    simulation = _parse_simulation(v, data.get("simulation", {}), sequences)
    created_with = v.string(data.get("created_with", "unknown"), "created_with")
    fields = {"image_size": (W, H), "fps": fps, "body": body, "garment": garment, "rig": rig, "sequences": sequences,
              "palette_init": palette_init, "simulation": simulation, "created_with": created_with,
              "extra": {k: val for k, val in data.items() if k not in _KNOWN_KEYS}}
    if check_files:
        for info in sequences.values():
            _check_sequence_files(v, root, info, fps)
    return fields


def _parse_header(v: SchemaChecker, data: dict) -> tuple[int, int, float]:
    """Format, version, ``image_size`` (W, H) and ``fps``."""
    if data["format"] != SCENE_FORMAT:
        raise v.fail("format", f"must be '{SCENE_FORMAT}', got {data['format']!r}")
    version = v.integer(data["version"], "version")
    if version > SCENE_VERSION:
        raise v.fail("version", f"{version} is newer than this program reads ({SCENE_VERSION})")
    size = data["image_size"]
    if not isinstance(size, list) or len(size) != 2:
        raise v.fail("image_size", "must be [width, height]")
    W, H = (v.integer(x, f"image_size[{i}]") for i, x in enumerate(size))
    return W, H, v.number(data["fps"], "fps", positive=True)


def _parse_body(v: SchemaChecker, raw) -> dict:
    body = dict(v.obj(raw, "body"))
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
    return body


def _parse_garment(v: SchemaChecker, raw) -> dict:
    garment = dict(v.obj(raw, "garment"))
    v.string(v.key(garment, "kind", "garment"), "garment.kind")
    garment["color"] = v.color(v.key(garment, "color", "garment"), "garment.color")
    return garment


def _parse_cameras(v: SchemaChecker, raw, image_size: tuple[int, int]) -> list[NamedCamera]:
    if not isinstance(raw, list) or not raw:
        raise v.fail("cameras", "must be a non-empty list")
    rig: list[NamedCamera] = []
    for i, entry in enumerate(raw):
        rig.append(_parse_camera(v, entry, f"cameras[{i}]", image_size, {c.name for c in rig}))
    return rig


def _parse_camera(v: SchemaChecker, entry, p: str, image_size: tuple[int, int], taken: set[str]) -> NamedCamera:
    """One entry of ``cameras`` (field path ``p``): a pinhole of the scene's image size, named
    other than the cameras before it (``taken``)."""
    v.obj(entry, p)
    unknown = sorted(set(entry) - _CAMERA_KEYS)
    if unknown:
        raise v.fail(p, f"has unknown key(s) {', '.join(unknown)} (cameras are pinholes: "
                        f"{', '.join(sorted(_CAMERA_KEYS))})")
    for key in ("name", "K", "R", "t", "width", "height", "split"):
        v.key(entry, key, p)
    name = v.name(entry["name"], f"{p}.name")
    if name in taken:
        raise v.fail(f"{p}.name", f"'{name}' is used by another camera")
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
    if (w, h) != tuple(image_size):
        raise v.fail(f"{p}", f"is {w}x{h}, the scene's image_size is {image_size[0]}x{image_size[1]}")
    split = v.choice(entry["split"], f"{p}.split", CAMERA_SPLITS)
    near = v.number(entry.get("near", DEFAULT_NEAR), f"{p}.near", positive=True)
    far = v.number(entry.get("far", DEFAULT_FAR), f"{p}.far", positive=True)
    if near >= far:
        raise v.fail(f"{p}.far", f"must be greater than near ({near:g}), got {far:g}")
    return NamedCamera(name, Camera(K, R, t, w, h, near, far), split)


def _parse_sequences(v: SchemaChecker, raw) -> dict[str, SequenceInfo]:
    seqs_raw = v.obj(raw, "sequences")  # may be empty while a scene is being made
    sequences: dict[str, SequenceInfo] = OrderedDict()
    for name, entry in seqs_raw.items():
        p = f"sequences.{name}"
        v.name(name, p)
        v.obj(entry, p)
        motion = v.string(v.key(entry, "motion", p), f"{p}.motion")
        frames = v.integer(v.key(entry, "frames", p), f"{p}.frames")
        split = v.choice(v.key(entry, "split", p), f"{p}.split", SEQUENCE_SPLITS)
        extra = {k: val for k, val in entry.items() if k not in ("motion", "frames", "split")}
        sequences[name] = SequenceInfo(name, motion, frames, split, extra)
    return sequences


def _parse_palette(v: SchemaChecker, palette) -> dict | None:
    if palette is None:
        return None
    v.obj(palette, "palette_init")
    colors = {key: v.color(v.key(palette, key, "palette_init"), f"palette_init.{key}") for key in ("garment", "body")}
    layers = palette.get("garment_layers")
    if layers is not None:
        if not isinstance(layers, list) or len(layers) < 2:
            raise v.fail("palette_init.garment_layers", f"must be a list of at least 2 colors, got {_kind(layers)}")
        colors["garment_layers"] = [v.color(c, f"palette_init.garment_layers[{i}]") for i, c in enumerate(layers)]
    return {**palette, **colors}


def _parse_simulation(v: SchemaChecker, simulation, sequences: dict[str, SequenceInfo]) -> dict:
    if simulation is None:
        return {}
    v.obj(simulation, "simulation")
    for name, stats in simulation.items():
        if name not in sequences:
            raise v.fail(f"simulation.{name}", f"names no sequence (sequences: {', '.join(sequences)})")
        v.obj(stats, f"simulation.{name}")
    return dict(simulation)


def _check_sequence_files(v: SchemaChecker, root: Path, info: SequenceInfo, fps: float) -> None:
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
        rot_shape = npz_member_shape(motion_file, "rotations")
        with np.load(motion_file, allow_pickle=False) as npz:
            motion_fps = float(npz["fps"]) if "fps" in npz.files else None
        reading = garment_file
        vert_shape = npz_member_shape(garment_file, GARMENT_VERTICES_KEY)
        if vert_shape is None:  # the simulation's compressed format (garment_sequence.py)
            vert_shape = npz_member_shape(garment_file, GARMENT_QUANTISED_KEY)
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
