"""The garment's height band of a scene, measured once and kept: what a render session needs before
its first shell-sampled frame.

:func:`~garmentnerf.model.height_band.measure_height_range` binds the posed body of up to 24 frames of
every training sequence and projects the simulated garment onto it: on the project's 2-core machine
6 to 11 s of CPU, the largest part of the time ``garmentnerf view`` took to show its first garment.
The band is a function of the scene's training garments and motions, the body and its shape, and
the measuring settings, so it is kept under a key made of exactly those (:func:`band_key`):

1. a scene folder may carry its band (:data:`SCENE_BAND_FILE`, written by ``garmentnerf demo pack``
   for the bundled demos): used when its recorded key is this key;
2. else the user's cache (:func:`cache_dir`, ``$XDG_CACHE_HOME/garmentnerf/height_band`` or
   ``~/.cache/...``; ``$GARMENTNERF_CACHE_DIR`` replaces ``.../garmentnerf``), one file per key;
3. else it is measured, and written to the user's cache (best effort: an unwritable cache only
   means measuring again next time).

A file that cannot be read, or that holds another key, is ignored (and a cache file of the key is
rewritten). Changing how the band is measured means changing :data:`BAND_VERSION`.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import torch

from garmentnerf.io_utils import load_tagged_tensors, save_tagged_tensors, user_cache_dir
from garmentnerf.model.height_band import (HEIGHT_MARGIN_IN, HEIGHT_MARGIN_OUT, VERTEX_BAND_RINGS, HeightRange,
                                           measure_height_range)

#: The band a scene folder carries (the bundled demos' scenes), with its key.
SCENE_BAND_FILE = "height_band.safetensors"
#: The ``format`` tag of a band file.
BAND_FORMAT = "garmentnerf-height-band"
#: Part of every key: bump it when the measurement changes.
BAND_VERSION = 1
#: Frames measured per training sequence (:func:`measure_height_range`'s default).
BAND_MAX_FRAMES = 24


def cache_dir() -> Path:
    """Where measured bands are kept: :func:`~garmentnerf.io_utils.user_cache_dir` ``height_band``."""
    return user_cache_dir("height_band")


def _tensor_digest(t) -> str:
    a = np.ascontiguousarray(torch.as_tensor(t).detach().cpu().numpy())
    return hashlib.sha256(a.dtype.str.encode() + str(a.shape).encode() + a.tobytes()).hexdigest()


def band_key(scene, body, betas=None, margin_in: float = HEIGHT_MARGIN_IN, margin_out: float = HEIGHT_MARGIN_OUT,
             max_frames: int = BAND_MAX_FRAMES, rings: int = VERTEX_BAND_RINGS) -> str:
    """32 hex digits naming everything the band of ``scene`` measured with ``body`` and ``betas``
    (None: the scene's shape, as the measurement takes it) depends on: the training sequences'
    names and the content of their garment and motion files, the body's template and faces, the
    shape, the margins, frames and rings, :data:`BAND_VERSION`."""
    betas = body.betas(scene.body.get("shape", "average")) if betas is None else betas
    names = scene.sequence_names("train") or scene.sequence_names()
    files = {name: [scene.file_digests.digest(scene.garment_path(name)), scene.file_digests.digest(scene.motion_path(name))]
             for name in names}
    blob = json.dumps({"version": BAND_VERSION, "sequences": names, "files": files,
                       "template": _tensor_digest(body.template_vertices), "faces": _tensor_digest(body.faces),
                       "betas": _tensor_digest(torch.as_tensor(betas, dtype=torch.float64)),
                       "margins": [float(margin_in), float(margin_out)], "max_frames": int(max_frames),
                       "rings": int(rings)}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:32]


def save_band(path, band: HeightRange, key: str) -> Path:
    """Write ``band`` (bounds, source, per-vertex bound) and its ``key`` atomically."""
    tensors = {"bounds": torch.tensor([band.h_min, band.h_max], dtype=torch.float64)}
    if band.vertex_h_max is not None:
        tensors["vertex_h_max"] = band.vertex_h_max.float()
    return save_tagged_tensors(path, tensors, BAND_FORMAT, {"source": band.source, "key": key})


def load_band(path, key: str | None = None) -> HeightRange | None:
    """The band in ``path`` if it is a band file (of ``key``, when given), else None."""
    path = Path(path)
    if not path.is_file():
        return None
    try:
        tensors, meta = load_tagged_tensors(path, BAND_FORMAT, "height band")
        bounds = tensors.get("bounds")
        if (key is not None and meta.get("key") != key) or bounds is None or tuple(bounds.shape) != (2,):
            return None
        return HeightRange(float(bounds[0]), float(bounds[1]), meta.get("source", "given"), tensors.get("vertex_h_max"))
    except (OSError, ValueError):
        return None


def scene_height_range(scene, body, betas=None, projector=None, margin_in: float = HEIGHT_MARGIN_IN) -> HeightRange:
    """The band :func:`measure_height_range` gives for ``scene`` (same arguments), from the scene's
    own band file or the user's cache when they hold it, else measured and cached (module docstring)."""
    key = band_key(scene, body, betas, margin_in)
    band = load_band(Path(scene.root) / SCENE_BAND_FILE, key)
    if band is not None:
        return band
    cached = cache_dir() / f"{key}.safetensors"
    band = load_band(cached, key)
    if band is not None:
        return band
    band = measure_height_range(scene, body, betas, projector, margin_in=margin_in, max_frames=BAND_MAX_FRAMES)
    try:
        cached.parent.mkdir(parents=True, exist_ok=True)
        save_band(cached, band, key)
    except OSError:
        pass  # an unwritable cache: measured again next time
    return band


__all__ = ["SCENE_BAND_FILE", "BAND_FORMAT", "BAND_VERSION", "cache_dir", "band_key", "save_band", "load_band",
           "scene_height_range"]
