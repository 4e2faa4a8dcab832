"""A synthetic training scene: cameras, body, garment and simulated sequences, in one small folder.

Layout::

    <scene>/scene.json                      what is below, validated on load
    <scene>/sequences/<name>/motion.npz     the body motion (:meth:`Motion.save`)
    <scene>/sequences/<name>/garment.npz    the simulated garment (written by the cloth simulation)
    <scene>/cache/...                       ground-truth images, rendered on demand (disposable)

Where the rest lives:
    * :mod:`garmentnerf.data.scene_schema` -- the format of ``scene.json`` and its validation:
      :meth:`Scene.load` fails with :class:`SceneError`, a one-line message naming the file and
      the field path, e.g. ``scenes/skirt/scene.json: cameras[3].K must be 3x3``.
    * :mod:`garmentnerf.data.scene_images` -- the ground-truth images
      (:class:`~garmentnerf.data.scene_images.SceneImages`), rendered on demand and cached under
      ``cache/`` at the paths :meth:`Scene.image_path` names.

The public names of :mod:`~garmentnerf.data.scene_schema` are importable from here too. Also here:
:func:`read_garment_arrays` (a sequence's ``garment.npz``, :meth:`Scene.garment_arrays`).
"""

from __future__ import annotations

import hashlib
import json
import shutil
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from garmentnerf.conventions import DEFAULT_FAR, DEFAULT_NEAR
from garmentnerf.data.cameras import CAMERA_SPLITS, NamedCamera, RigLookup, in_splits
from garmentnerf.data.garment_sequence import load_sequence
from garmentnerf.data.render_gt import SKIN_TONE
from garmentnerf.data.render_gt import renderer_settings as default_settings
from garmentnerf.data.scene_schema import (
    GARMENT_FILE,
    GARMENT_QUANTISED_KEY,
    GARMENT_VERTICES_KEY,
    MOTION_FILE,
    ROTATION_TOLERANCE,
    SCENE_FILE,
    SCENE_FORMAT,
    SCENE_VERSION,
    SEQUENCE_SPLITS,
    SceneError,
    SchemaChecker,
    SequenceInfo,
    parse_scene,
)
from garmentnerf.io_utils import FileDigests, atomic_write_path, npz_member_shape, read_json_strict
from garmentnerf.motion.motion import Motion
from garmentnerf.version import package_version

__all__ = ["Scene", "CACHE_DIR", "GarmentArrays", "read_garment_arrays",
           # re-exported from scene_schema, where they live
           "SceneError", "SequenceInfo", "SCENE_FORMAT", "SCENE_VERSION", "SCENE_FILE", "SEQUENCE_SPLITS",
           "MOTION_FILE", "GARMENT_FILE", "GARMENT_VERTICES_KEY", "GARMENT_QUANTISED_KEY", "ROTATION_TOLERANCE"]

CACHE_DIR = "cache"


# ---- garment sequences (written by the cloth simulation) ------------------------------------------
@dataclass
class GarmentArrays:
    """A simulated garment as plain arrays: vertices (T, Vg, 3) float32, faces (Fg, 3) int64 and
    the layer of each vertex (Vg,) int8 (None: one layer)."""

    vertices: np.ndarray
    faces: np.ndarray
    layer: np.ndarray | None = None


def read_garment_arrays(path: str | Path) -> GarmentArrays:
    """Read ``garment.npz``: the simulation's compressed format (``vertices_q``) through
    :mod:`garmentnerf.data.garment_sequence`, else the file's plain ``vertices`` and ``faces``."""
    path = Path(path)
    if npz_member_shape(path, GARMENT_QUANTISED_KEY) is not None:
        seq = load_sequence(path)
        verts, faces, layer = seq.vertices, seq.faces, seq.layer
    else:
        with np.load(path, allow_pickle=False) as npz:
            missing = [k for k in (GARMENT_VERTICES_KEY, "faces") if k not in npz.files]
            if missing:
                raise SceneError(f"{path}: not a garment sequence (missing {', '.join(missing)})")
            verts, faces, layer = npz[GARMENT_VERTICES_KEY], npz["faces"], None
    if hasattr(verts, "detach"):
        verts = verts.detach().cpu().numpy()
    if hasattr(faces, "detach"):
        faces = faces.detach().cpu().numpy()
    verts = np.asarray(verts, dtype=np.float32)
    faces = np.asarray(faces, dtype=np.int64)
    if verts.ndim != 3 or verts.shape[2] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
        raise SceneError(f"{path}: garment vertices must be (T, Vg, 3) and faces (Fg, 3), got "
                         f"{verts.shape} and {faces.shape}")
    return GarmentArrays(verts, faces, layer)


@dataclass
class Scene(RigLookup):
    """A scene folder (see the module docstring). Build with :meth:`create`, read with :meth:`load`.

    Attributes:
        root: the scene folder.
        image_size: (W, H) of every camera.
        fps: frame rate of every sequence.
        body: ``{"model": "anny", "shape": "average" | [betas], "color": optional [r, g, b], ...}``.
        garment: ``{"kind": str, "color": [r, g, b], ...}``.
        rig: the cameras, in file order.
        sequences: name -> :class:`SequenceInfo`, in file order.
        palette_init: ``{"garment": rgb, "body": rgb}`` (mean ground-truth colors) or None.
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
    created_with: str = field(default_factory=package_version)
    extra: dict = field(default_factory=dict)
    #: Content digests of the sequences' files for :meth:`cache_key`; locked, as one scene is read
    #: by several threads (the viewer's UI, its render worker and its exporter).
    file_digests: FileDigests = field(default_factory=FileDigests, repr=False, compare=False)

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
        checker = SchemaChecker(str(self.scene_file))
        checker.name(name, f"sequences.{name}")
        checker.choice(split, f"sequences.{name}.split", SEQUENCE_SPLITS)
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
        return in_splits(self.rig, split, CAMERA_SPLITS, "camera", SceneError)

    def _lookup_error(self, problem: str) -> SceneError:
        return SceneError(f"{self.scene_file}: {problem}")

    def sequence_names(self, split: str | Sequence[str] | None = None) -> list[str]:
        """Sequence names of ``split`` (a name, several, or None for all), in file order."""
        return [info.name for info in in_splits(self.sequences.values(), split, SEQUENCE_SPLITS, "sequence", SceneError)]

    def sequence(self, name: str) -> SequenceInfo:
        info = self.sequences.get(name)
        if info is None:
            raise self._lookup_error(f"no sequence '{name}' (sequences: {', '.join(self.sequences)})")
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
        return tuple(self.body.get("color", SKIN_TONE))

    def load_motion(self, sequence: str) -> "Motion":
        return Motion.load(self.motion_path(sequence))

    def garment_arrays(self, sequence: str) -> GarmentArrays:
        """The simulated garment of ``sequence`` (its ``garment.npz``, :func:`read_garment_arrays`)."""
        return read_garment_arrays(self.garment_path(sequence))

    # ---- cache ----------------------------------------------------------------------------------
    def cache_key(self, sequence: str, camera: str, renderer_settings: dict | None = None) -> str:
        """16 hex digits identifying everything an image of (sequence, camera) depends on."""
        settings = renderer_settings if renderer_settings is not None else default_settings()
        cam = self.camera(camera).camera
        files = {label: self.file_digests.digest(path) for label, path in (("motion", self.motion_path(sequence)),
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
        parse_scene(json.loads(json.dumps(self.to_json())), str(self.scene_file), self.root, check_files=False)
        return self

    def save(self, overwrite: bool = True) -> Path:
        """Validate, then write ``scene.json`` atomically; returns its path."""
        data = self.to_json()
        text = json.dumps(data, indent=1, allow_nan=False)
        parse_scene(json.loads(text), str(self.scene_file), self.root, check_files=False)
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
            data = read_json_strict(file, "scene")  # NaN, Infinity, 1e999 and a key given twice refused, named
        except (OSError, ValueError) as exc:
            raise SceneError(str(exc)) from None
        return Scene(root, **parse_scene(data, str(file), root, check_files))

