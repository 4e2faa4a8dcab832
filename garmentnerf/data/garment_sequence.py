"""Compressed storage of a simulated garment sequence: (T, V, 3) vertices and what goes with them.

File format (``.npz``, deflate-compressed, written atomically)
    ``format``/``version``        ``"garmentnerf.garment_sequence"`` / 1
    ``vertices_q``                (T, V, 3) uint16: every coordinate quantised over the whole
                                  sequence's bounding box, ``x = lo + q * (hi - lo) / 65535``
    ``bbox_min``, ``bbox_max``    (3,) float64 ``lo`` and ``hi``
    ``faces``                     (F, 3) int32, counter-clockwise seen from outside
    ``color``                     (3,) float32 base color, RGB in [0, 1]
    ``kind``, ``name``, ``motion`` strings (garment kind, garment label, motion name)
    ``penetration_max_m``         (T,) float32 per-frame depth of the deepest vertex inside the body
    ``fps``                       float64 frame rate
    ``settings_json``             the simulation settings (:class:`~garmentnerf.data.simulate.SimSettings`
                                  as a JSON object)
    ``betas``                     (S,) float32 body shape the garment was simulated on (may be empty)
    ``uv``                        (V, 2) float32 per-vertex garment parameter, or (0, 2)
    ``layer``                     (V,) int8 layer of each vertex, 0 innermost (optional: a file
                                  without it is a one-layer garment, all 0)

Quantisation error
    Rounding to the nearest of 65,536 levels per axis errs by at most half a level:
    ``(hi - lo) / 131070`` per coordinate, i.e. 0.023 mm over a 3 m box (0.04 mm as a 3-D
    distance); :attr:`GarmentSequence.max_quantization_error` gives the bound of a file. A
    garment sequence spans about 1-3 m, so the error is far below the simulation's own
    precision (collision thickness 5 mm).

Loading validates every field: a missing, truncated or unreadable member, a wrong dtype or
shape, indices out of range or non-finite values raise :class:`GarmentSequenceError` naming the
file and the field.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from garmentnerf.io_utils import atomic_write_path

if TYPE_CHECKING:  # pragma: no cover
    from garmentnerf.data.garments import Garment
    from garmentnerf.data.simulate import SimResult

__all__ = ["GarmentSequence", "GarmentSequenceError", "save_sequence", "load_sequence", "penetration_summary",
           "recorded_penetration", "QUANT_LEVELS"]

_FORMAT = "garmentnerf.garment_sequence"
_VERSION = 1
#: Number of quantisation levels per axis (uint16).
QUANT_LEVELS = 65535


class GarmentSequenceError(ValueError):
    """A garment sequence file that is missing, truncated or inconsistent (names file and field)."""


@dataclass
class GarmentSequence:
    """A simulated garment over T frames.

    Attributes:
        vertices: (T, V, 3) float32 positions, world metres (dequantised when loaded).
        faces: (F, 3) int32 triangles.
        color: (3,) float32 base color in [0, 1].
        kind: garment kind (``skirt``, ``tshirt``, ``dress``).
        penetration_max_m: (T,) float32 per-frame deepest penetration into the body, metres.
        fps: frames per second.
        settings: simulation settings as a plain dict (JSON-serialisable).
        name: garment label.
        motion: name of the motion it was simulated with.
        betas: (S,) float32 body shape (may be empty).
        uv: (V, 2) float32 per-vertex parameter, or None.
        layer: (V,) int8 layer of each vertex (0 innermost; the dress has 0 and 1), or None (one layer).
        bbox_min, bbox_max: (3,) float64 quantisation box (set by :func:`load_sequence`; None
            for a sequence that was not read from a file).
    """

    vertices: np.ndarray
    faces: np.ndarray
    color: np.ndarray
    kind: str
    penetration_max_m: np.ndarray
    fps: float
    settings: dict
    name: str = ""
    motion: str = ""
    betas: np.ndarray | None = None
    uv: np.ndarray | None = None
    layer: np.ndarray | None = None
    bbox_min: np.ndarray | None = None
    bbox_max: np.ndarray | None = None

    @property
    def num_frames(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def num_vertices(self) -> int:
        return int(self.vertices.shape[1])

    @property
    def max_quantization_error(self) -> float:
        """Largest per-coordinate error (metres) of storing these vertices (half a level)."""
        lo, hi = (self.bbox_min, self.bbox_max) if self.bbox_min is not None else _bbox(self.vertices)
        return float(np.max(np.asarray(hi) - np.asarray(lo))) / (2 * QUANT_LEVELS)

    def save(self, path: str | Path, overwrite: bool = True) -> Path:
        return save_sequence(path, self.vertices, self.faces, color=self.color, kind=self.kind,
                             penetration_max_m=self.penetration_max_m, fps=self.fps, settings=self.settings,
                             name=self.name, motion=self.motion, betas=self.betas, uv=self.uv, layer=self.layer,
                             overwrite=overwrite)

    @staticmethod
    def from_simulation(garment: "Garment", result: "SimResult", motion: str = "") -> "GarmentSequence":
        """The sequence of a :func:`~garmentnerf.data.simulate.simulate` result."""
        return GarmentSequence(vertices=result.vertices, faces=garment.faces, color=garment.color, kind=garment.kind,
                               penetration_max_m=result.penetration_max_m, fps=result.fps,
                               settings=result.settings.to_dict(), name=garment.name, motion=motion,
                               betas=garment.betas, uv=garment.uv, layer=garment.layer)


def _bbox(vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    return v.min(axis=0), v.max(axis=0)


def _check_arrays(vertices, faces, color, penetration, fps, where: str):
    """Shared validation of the in-memory arrays (save) and of a loaded file (load)."""

    def fail(field, msg):
        raise GarmentSequenceError(f"{where}: field '{field}': {msg}")

    if vertices.ndim != 3 or vertices.shape[2] != 3 or vertices.shape[0] < 1 or vertices.shape[1] < 3:
        fail("vertices", f"must have shape (T >= 1, V >= 3, 3), got {vertices.shape}")
    T, V = vertices.shape[:2]
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.shape[0] < 1:
        fail("faces", f"must have shape (F >= 1, 3), got {faces.shape}")
    if faces.dtype.kind not in "iu":
        fail("faces", f"must be integer indices, got {faces.dtype}")
    if faces.min() < 0 or faces.max() >= V:
        fail("faces", f"indices must lie in [0, {V}), got [{faces.min()}, {faces.max()}]")
    if color.shape != (3,) or not np.all(np.isfinite(color)) or color.min() < 0 or color.max() > 1:
        fail("color", f"must be 3 values in [0, 1], got {color.tolist()}")
    if penetration.shape != (T,):
        fail("penetration_max_m", f"must have shape ({T},) (one value per frame), got {penetration.shape}")
    if not np.all(np.isfinite(penetration)) or (penetration < 0).any():
        fail("penetration_max_m", "must be finite and >= 0")
    if not (isinstance(fps, (int, float, np.floating, np.integer)) and math.isfinite(float(fps)) and fps > 0):
        fail("fps", f"must be a finite number > 0, got {fps!r}")


def recorded_penetration(path: str | Path) -> np.ndarray | None:
    """The (T,) per-frame penetration (metres) a scene's ``garment.npz`` records: a file written by
    :func:`save_sequence` has it; a plain ``vertices``/``faces`` file (which scenes also accept)
    records none, and gives None."""
    with np.load(path, allow_pickle=False) as archive:
        return np.asarray(archive["penetration_max_m"]) if "penetration_max_m" in archive.files else None


def penetration_summary(penetration_max_m: np.ndarray, bound_m: float) -> str:
    """One line on how deep a simulated sequence's cloth went into the body: its deepest frame and,
    when frames pass ``bound_m`` (metres; the simulator's ``PENETRATION_BOUND_M``), how many and the
    first of them (where a sequence made with ``data make --frames`` should end).
    ``penetration_max_m``: (T,) metres per frame."""
    pen = np.asarray(penetration_max_m, dtype=np.float64)
    text = f"max penetration {pen.max() * 1000:.1f} mm"
    over = np.flatnonzero(pen > bound_m)
    if over.size:
        text += (f", {over.size} of {pen.size} frames over the {bound_m * 1000:g} mm bound, the first at frame"
                 f" {over[0]} (cloth through the body)")
    return text


def save_sequence(path: str | Path, vertices, faces, *, color, kind: str, penetration_max_m, fps: float,
                  settings: dict | None = None, name: str = "", motion: str = "", betas=None, uv=None,
                  layer=None, overwrite: bool = True) -> Path:
    """Write a garment sequence (atomically: readers never see a partial file).

    Args:
        path: destination ``.npz``.
        vertices: (T, V, 3) positions, metres.
        faces: (F, 3) triangles.
        color: (3,) RGB in [0, 1].
        kind: garment kind.
        penetration_max_m: (T,) per-frame penetration depth.
        fps: frame rate.
        settings: simulation settings (a dict, or anything with ``to_dict()``).
        name, motion: labels.
        betas: (S,) body shape, optional.
        uv: (V, 2) per-vertex parameter, optional.
        layer: (V,) integer layer of each vertex in [0, 127], optional (None: one layer, all 0).
        overwrite: False refuses to replace an existing file.
    Returns:
        the path written.
    """
    path = Path(path)
    if path.suffix != ".npz":
        raise GarmentSequenceError(f"{path}: garment sequences use the .npz extension")
    where = str(path)
    vertices = np.asarray(vertices)
    faces = np.asarray(faces)
    color = np.asarray(color, dtype=np.float32).reshape(-1)
    penetration = np.asarray(penetration_max_m, dtype=np.float32).reshape(-1)
    _check_arrays(vertices, faces, color, penetration, fps, where)
    if not np.all(np.isfinite(vertices)):
        raise GarmentSequenceError(f"{where}: field 'vertices': contains NaN or Inf")
    if settings is not None and hasattr(settings, "to_dict"):
        settings = settings.to_dict()
    settings = {} if settings is None else settings
    try:
        settings_json = json.dumps(settings, sort_keys=True)
    except (TypeError, ValueError) as exc:
        raise GarmentSequenceError(f"{where}: field 'settings': not JSON-serialisable ({exc})") from exc
    V = vertices.shape[1]
    uv = np.zeros((0, 2), np.float32) if uv is None else np.asarray(uv, dtype=np.float32)
    if uv.shape not in ((V, 2), (0, 2)) or not np.all(np.isfinite(uv)):
        raise GarmentSequenceError(f"{where}: field 'uv': must be finite with shape ({V}, 2), got {uv.shape}")
    betas = np.zeros(0, np.float32) if betas is None else np.asarray(betas, dtype=np.float32).reshape(-1)
    if not np.all(np.isfinite(betas)):
        raise GarmentSequenceError(f"{where}: field 'betas': contains NaN or Inf")
    layer = np.zeros(V, np.int8) if layer is None else np.asarray(layer)
    if layer.shape != (V,) or layer.dtype.kind not in "iu" or (V and (layer.min() < 0 or layer.max() > 127)):
        raise GarmentSequenceError(f"{where}: field 'layer': must be integers in [0, 127] with shape ({V},), "
                                   f"got {layer.dtype} {layer.shape}")

    lo, hi = _bbox(vertices)
    extent = hi - lo
    scale = np.where(extent > 0, QUANT_LEVELS / np.where(extent > 0, extent, 1.0), 0.0)
    q = np.rint((vertices.astype(np.float64) - lo) * scale)
    q = np.clip(q, 0, QUANT_LEVELS).astype(np.uint16)
    with atomic_write_path(path, overwrite=overwrite) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(
                fh, format=np.array(_FORMAT), version=np.array(_VERSION), vertices_q=q,
                bbox_min=lo.astype(np.float64), bbox_max=hi.astype(np.float64),
                faces=faces.astype(np.int32), color=color, kind=np.array(str(kind)), name=np.array(str(name)),
                motion=np.array(str(motion)), penetration_max_m=penetration, fps=np.array(float(fps)),
                settings_json=np.array(settings_json), betas=betas, uv=uv, layer=layer.astype(np.int8))
    return path


def _members_begun(path: Path) -> list[str]:
    """Names of the archive members whose local headers are in the file, in order.

    A file cut short has no central directory (zip keeps it at the end), so ``np.load`` cannot
    open it; the local headers still tell which field was being written where it ends."""
    try:
        raw = path.read_bytes()
    except OSError:
        return []
    names, pos = [], raw.find(b"PK\x03\x04")
    while pos >= 0 and pos + 30 <= len(raw):
        name_len = int.from_bytes(raw[pos + 26:pos + 28], "little")
        name = raw[pos + 30:pos + 30 + name_len].decode("utf-8", "replace")
        if name.endswith(".npy"):
            names.append(name[:-4])
        pos = raw.find(b"PK\x03\x04", pos + 30 + name_len)
    return names


_REQUIRED = ("format", "version", "vertices_q", "bbox_min", "bbox_max", "faces", "color", "kind", "name", "motion",
             "penetration_max_m", "fps", "settings_json", "betas", "uv")
#: Members a file may lack (written by later versions of this module; see the format above).
_OPTIONAL = ("layer",)


def load_sequence(path: str | Path) -> GarmentSequence:
    """Read and validate a file written by :func:`save_sequence`.

    Raises:
        FileNotFoundError: no such file.
        GarmentSequenceError: anything wrong with the file (the message names file and field).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such garment sequence file")
    f = _Fields(str(path), _read_members(path))
    if f.string("format") != _FORMAT:
        f.fail("format", f"expected '{_FORMAT}', got '{f.string('format')}'")
    version = f.data["version"]
    if version.shape != () or version.dtype.kind not in "iu" or int(version) != _VERSION:
        f.fail("version", f"unsupported version {version!r} (this code reads version {_VERSION})")
    vertices, lo, hi = _dequantised_vertices(f)
    fps = f.data["fps"]
    if fps.shape != () or fps.dtype.kind not in "fiu":
        f.fail("fps", f"must be a number, got {fps.dtype} {fps.shape}")
    fps = float(fps)
    color, pen = f.floats("color"), f.floats("penetration_max_m")
    _check_arrays(vertices, f.data["faces"], color.reshape(-1) if color.ndim == 1 else color, pen, fps, f.where)
    try:
        settings = json.loads(f.string("settings_json"))
    except ValueError as exc:
        raise GarmentSequenceError(f"{f.where}: field 'settings_json': not valid JSON ({exc})") from exc
    if not isinstance(settings, dict):
        f.fail("settings_json", "must hold a JSON object")
    V = vertices.shape[1]
    uv = f.data["uv"]
    if uv.dtype.kind != "f" or uv.shape not in ((V, 2), (0, 2)) or not np.all(np.isfinite(uv)):
        f.fail("uv", f"must be finite floats of shape ({V}, 2) or (0, 2), got {uv.dtype} {uv.shape}")
    betas = f.data["betas"]
    if betas.ndim != 1 or betas.dtype.kind != "f" or not np.all(np.isfinite(betas)):
        f.fail("betas", f"must be a finite 1-D float array, got {betas.dtype} {betas.shape}")
    kind = f.string("kind")
    if not kind:
        f.fail("kind", "is empty")
    layer = f.data.get("layer")
    if layer is not None and (layer.shape != (V,) or layer.dtype != np.int8 or (V and layer.min() < 0)):
        f.fail("layer", f"must be non-negative int8 of shape ({V},), got {layer.dtype} {layer.shape}")
    return GarmentSequence(vertices=vertices, faces=f.data["faces"].astype(np.int32), color=color.astype(np.float32),
                           kind=kind, penetration_max_m=pen.astype(np.float32), fps=fps, settings=settings,
                           name=f.string("name"), motion=f.string("motion"), betas=betas.astype(np.float32),
                           uv=uv.astype(np.float32) if uv.shape[0] else None, layer=layer,
                           bbox_min=lo.astype(np.float64),
                           bbox_max=hi.astype(np.float64))


def _read_members(path: Path) -> dict[str, np.ndarray]:
    """Every required array of the archive; a missing, truncated or unreadable one raises
    GarmentSequenceError naming it."""
    where = str(path)
    try:
        archive = np.load(path, allow_pickle=False)
    except Exception as exc:  # zipfile.BadZipFile, OSError, ValueError ...
        begun = _members_begun(path)
        if begun:
            raise GarmentSequenceError(
                f"{where}: field '{begun[-1]}': truncated file (the archive ends inside or after this field; "
                f"{len(begun)} of {len(_REQUIRED)} fields begun: {exc})") from exc
        raise GarmentSequenceError(f"{where}: not a garment sequence file (not an .npz archive: {exc})") from exc
    data = {}
    with archive:
        missing = [k for k in _REQUIRED if k not in archive.files]
        if missing:
            raise GarmentSequenceError(f"{where}: field '{missing[0]}': missing (the file lacks "
                                       f"{', '.join(missing)}; truncated or not a garment sequence)")
        for key in _REQUIRED + tuple(k for k in _OPTIONAL if k in archive.files):
            try:
                data[key] = archive[key]
            except Exception as exc:  # zipfile.BadZipFile, OSError, ValueError, EOFError, zlib.error ...
                raise GarmentSequenceError(f"{where}: field '{key}': unreadable (truncated file? {exc})") from exc
    return data


class _Fields:
    """The arrays of one garment sequence file and checks that fail naming the file and field."""

    def __init__(self, where: str, data: dict[str, np.ndarray]) -> None:
        self.where, self.data = where, data

    def fail(self, field: str, msg: str):
        raise GarmentSequenceError(f"{self.where}: field '{field}': {msg}")

    def string(self, field: str) -> str:
        v = self.data[field]
        if v.shape != () or v.dtype.kind != "U":
            self.fail(field, f"must be a string, got {v.dtype} {v.shape}")
        return str(v)

    def floats(self, field: str) -> np.ndarray:
        v = self.data[field]
        if v.dtype.kind != "f":
            self.fail(field, f"must be floats, got {v.dtype}")
        return v


def _dequantised_vertices(f: _Fields) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(T, V, 3) float32 vertices from the uint16 ``vertices_q`` over the box, and the box's
    (3,) ``bbox_min`` and ``bbox_max``, checked."""
    q = f.data["vertices_q"]
    if q.dtype != np.uint16:
        f.fail("vertices_q", f"must be uint16, got {q.dtype}")
    if q.ndim != 3 or q.shape[2] != 3 or q.shape[0] < 1 or q.shape[1] < 3:
        f.fail("vertices_q", f"must have shape (T >= 1, V >= 3, 3), got {q.shape}")
    lo, hi = f.data["bbox_min"], f.data["bbox_max"]
    for field, v in (("bbox_min", lo), ("bbox_max", hi)):
        if v.shape != (3,) or v.dtype.kind != "f" or not np.all(np.isfinite(v)):
            f.fail(field, f"must be 3 finite floats, got {v.dtype} {v.shape}")
    if np.any(hi < lo):
        f.fail("bbox_max", "is below bbox_min")
    vertices = (lo + q.astype(np.float64) * ((hi - lo) / QUANT_LEVELS)).astype(np.float32)
    return vertices, lo, hi
