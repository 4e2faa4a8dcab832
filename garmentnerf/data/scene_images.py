"""Ground-truth images of a scene, rendered on demand and cached as PNG files in the scene folder.

Images are not stored with the scene: :class:`SceneImages` renders them with
:class:`~garmentnerf.data.render_gt.GroundTruthRenderer` and caches them under
``<scene>/cache/<sequence>/<camera>/<key>/`` where ``key`` (:meth:`Scene.cache_key
<garmentnerf.data.scene.Scene.cache_key>`) hashes the renderer's version and settings, the camera,
the body, the colors and the content of the sequence's files (SHA-256, memoised by the scene on
size and modification time): any change renders afresh instead of reading a stale image, while a
copied scene folder keeps its cache. RGB is cached as 8-bit PNG and labels as 8-bit grey PNG (0
background, 1 body, 2 garment; a layered garment's layer k is 2 + k, :mod:`~garmentnerf.data.render_gt`);
:meth:`SceneImages.image` returns the *cached* (8-bit quantised) values whether or not it just
rendered them, so the two paths agree.

Also here: :func:`palette_from_images` (the palette initialisation from ground truth).
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from PIL import Image

from garmentnerf.data.render_gt import LABEL_BODY, LABEL_GARMENT, MAX_GARMENT_LAYERS, GroundTruthRenderer, to_uint8
from garmentnerf.data.scene import GarmentArrays, Scene, read_garment_arrays
from garmentnerf.data.scene_schema import SceneError
from garmentnerf.gl.context import create_context
from garmentnerf.io_utils import atomic_write_path

if TYPE_CHECKING:  # pragma: no cover
    from garmentnerf.body.model import BodyModel
    from garmentnerf.motion.motion import Motion


# ---- images on demand -----------------------------------------------------------------------------
@dataclass
class FrameGeometry:
    """The meshes of one frame, as the ground-truth renderer takes them (``garment_layer``: (Vg,)
    layer of each garment vertex, or None for one layer)."""

    body_vertices: np.ndarray
    body_faces: np.ndarray
    garment_vertices: np.ndarray
    garment_faces: np.ndarray
    garment_color: tuple[float, float, float]
    body_color: tuple[float, float, float]
    garment_layer: np.ndarray | None = None


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

    def __init__(self, scene: "Scene", renderer: "GroundTruthRenderer | None" = None,
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
            # local: garmentnerf.body.model brings roma (1.5 s), which 'garmentnerf data info' and 'data grow'
            # (reading scenes) never need; only images rendered without a given body get here
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
                            g.vertices[frame], g.faces, self.scene.garment_color, self.scene.body_color, g.layer)
        self._last_geometry = ((sequence, frame), geo)
        return geo

    def render(self, sequence: str, camera: str, frame: int) -> tuple[np.ndarray, np.ndarray]:
        """Render (no cache): float32 rgb in [0, 1] (not quantised) and uint8 labels."""
        geo = self.frame_geometry(sequence, frame)
        cam = self.scene.camera(camera).camera
        return self.renderer.render(geo.body_vertices, geo.body_faces, geo.garment_vertices, geo.garment_faces,
                                    geo.garment_color, cam, geo.body_color, geo.garment_layer)

    def paths(self, sequence: str, camera: str, frame: int) -> tuple[Path, Path]:
        settings = self.renderer.settings() if self._renderer is not None else None
        return (self.scene.image_path(sequence, camera, frame, settings),
                self.scene.label_path(sequence, camera, frame, settings))

    def image(self, sequence: str, camera: str, frame: int) -> tuple[np.ndarray, np.ndarray]:
        """(rgb (H, W, 3) float32 in [0, 1] with 8-bit steps, labels (H, W) uint8), from the
        cache when present, else rendered (and cached)."""
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
    with Image.open(path) as im:
        im = im.convert("RGB" if channels == 3 else "L")
        return np.asarray(im, dtype=np.uint8).copy()


def _write_png(path: Path, array: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write_path(path) as tmp:
        Image.fromarray(np.ascontiguousarray(array)).save(tmp, format="PNG", compress_level=3)


def palette_from_images(images: Iterable[tuple[np.ndarray, np.ndarray]], erode: int = 1) -> dict:
    """Mean garment and body colors (the paper's palette initialisation p*) from ground truth.

    Only pixels whose label region survives an ``erode``-pixel erosion count, so anti-aliased
    edges (blended with the background) do not darken the means. Returns
    ``{"garment": [r, g, b], "body": [r, g, b]}`` (a class never seen gives None; "garment" is
    every layer's), and for a layered garment (labels beyond 2) also ``"garment_layers"``: one mean
    color per layer, inner first.
    """
    from scipy.ndimage import binary_erosion  # local: making a scene only; 0.2 s on every import of data.scene_images

    layer_labels = [LABEL_GARMENT + k for k in range(MAX_GARMENT_LAYERS)]
    sums = {label: np.zeros(3) for label in [LABEL_BODY, *layer_labels]}
    counts = dict.fromkeys(sums, 0)
    structure = np.ones((3, 3), dtype=bool)
    for rgb, labels in images:
        rgb = np.asarray(rgb, dtype=np.float64)
        for label in sums:
            mask = labels == label
            if erode > 0:
                mask = binary_erosion(mask, structure=structure, iterations=erode)
            sums[label] += rgb[mask].sum(axis=0)
            counts[label] += int(mask.sum())

    def mean(labels: list[int]) -> list[float] | None:
        n = sum(counts[k] for k in labels)
        return [float(x) for x in sum(sums[k] for k in labels) / n] if n else None

    out = {"garment": mean(layer_labels), "body": mean([LABEL_BODY])}
    seen = [k for k in layer_labels if counts[k]]
    if len(seen) > 1:
        out["garment_layers"] = [mean([k]) for k in layer_labels[:max(seen) - LABEL_GARMENT + 1]]
    return out
