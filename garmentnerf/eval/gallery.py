"""A gallery of evaluated views: ground truth | render | error, one strip per view.

``garmentnerf eval --gallery FILE`` passes a :class:`Gallery` to
:func:`~garmentnerf.eval.evaluate.evaluate_run`, which offers it every view; the gallery keeps a
few, evenly spread over the evaluation (the first view always), and :meth:`Gallery.image` lays
them out as rows::

    ground truth | render | error of render [| nearest view | error of nearest view]

Each row has a caption with the view (sequence, camera, frame) and its foreground figures, and is
cropped to the character (the box around the ground truth's and the render's silhouettes, grown by
:data:`CROP_MARGIN_PX`; the same window in every tile of the row).
The error image is the per-pixel mean absolute RGB difference, ``|pred - gt|`` averaged over
channels, mapped through the *inferno* color map with :data:`ERROR_FULL_SCALE` as white-hot
(black: exact; so errors on the background show too).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import imageio.v3 as iio
import numpy as np

from garmentnerf.io_utils import atomic_write_path

__all__ = ["Gallery", "ERROR_FULL_SCALE", "error_image"]

#: Mean absolute RGB error shown at the top of the color map (errors above it saturate).
ERROR_FULL_SCALE = 0.25

#: Pixels kept around the character when a row is cropped to it.
CROP_MARGIN_PX = 16

#: Height of a caption band, pixels.
CAPTION_PX = 22


def error_image(pred: np.ndarray, target: np.ndarray, full_scale: float = ERROR_FULL_SCALE) -> np.ndarray:
    """(H, W, 3) uint8 color-mapped error of two (H, W, 3) images in [0, 1] (see the module docstring)."""
    err = np.abs(np.asarray(pred, np.float32) - np.asarray(target, np.float32)).mean(axis=-1)
    level = np.clip(err / float(full_scale), 0.0, 1.0)
    bgr = cv2.applyColorMap(np.round(level * 255.0).astype(np.uint8), cv2.COLORMAP_INFERNO)
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def _to_uint8(image: np.ndarray) -> np.ndarray:
    return np.round(np.clip(np.asarray(image, np.float32), 0.0, 1.0) * 255.0).astype(np.uint8)


def _caption(text: str, width: int) -> np.ndarray:
    band = np.zeros((CAPTION_PX, width, 3), np.uint8)
    cv2.putText(band, text, (4, CAPTION_PX - 7), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (230, 230, 230), 1, cv2.LINE_AA)
    return band


def _figures(row: dict) -> str:
    parts = []
    for key, label, fmt in (("fg_psnr", "fg PSNR", "{:.2f} dB"), ("psnr", "PSNR", "{:.2f} dB"),
                            ("silhouette_iou", "IoU", "{:.3f}"), ("sharpness", "sharpness", "{:.2f}")):
        value = row.get(key)
        if isinstance(value, (int, float)) and np.isfinite(value):
            parts.append(f"{label} " + fmt.format(value))
    return ", ".join(parts)


def _window(region: np.ndarray, margin: int) -> tuple[slice, slice]:
    """(rows, columns) of the box around ``region``'s pixels grown by ``margin`` (clipped to the
    image); the whole image when the region is empty."""
    rows, cols = np.nonzero(np.asarray(region, dtype=bool))
    if rows.size == 0:
        return slice(None), slice(None)
    h, w = region.shape
    return (slice(max(int(rows.min()) - margin, 0), min(int(rows.max()) + 1 + margin, h)),
            slice(max(int(cols.min()) - margin, 0), min(int(cols.max()) + 1 + margin, w)))


class Gallery:
    """Keeps ``count`` evaluated views and lays them out (see the module docstring).

    Args:
        count: how many views to keep (at least 1).
    """

    def __init__(self, count: int = 4):
        if count < 1:
            raise ValueError(f"a gallery needs at least one view, got {count}")
        self.count = int(count)
        self._picks: set[int] = set()
        self._rows: list[np.ndarray] = []

    def plan(self, total: int) -> None:
        """Choose which of ``total`` views (in evaluation order) to keep: evenly spread, first included."""
        n = min(self.count, int(total))
        self._picks = {(i * total) // n for i in range(n)} if n > 0 else set()
        self._rows = []

    def wants(self, index: int) -> bool:
        """Whether view number ``index`` (0-based, evaluation order) is one to keep."""
        return index in self._picks

    def add(self, title: str, truth: np.ndarray, shown: dict[str, np.ndarray], row: dict | None = None,
            character: np.ndarray | None = None) -> None:
        """Add one view.

        Args:
            title: the view's name (e.g. ``"train held00 frame 20"``).
            truth: (H, W, 3) ground truth in [0, 1].
            shown: method name -> (H, W, 3) image in [0, 1] (e.g. ``{"render": ..., "nearest view": ...}``).
            row: the view's per-frame figures (captioned when present).
            character: (H, W) bool, where the character is: the row is cropped to it (None: whole).
        """
        window = _window(character, CROP_MARGIN_PX) if character is not None else (slice(None), slice(None))
        tiles = [_to_uint8(truth)[window]]
        for image in shown.values():
            tiles += [_to_uint8(image)[window], error_image(image, truth)[window]]
        strip = np.concatenate(tiles, axis=1)
        heads = " | ".join(["ground truth"] + [f"{name} | error" for name in shown])
        text = f"{title}: {heads}" + (f"  ({_figures(row)})" if row else "")
        self._rows.append(np.concatenate([_caption(text, strip.shape[1]), strip], axis=0))

    def __len__(self) -> int:
        return len(self._rows)

    def image(self) -> np.ndarray:
        """(H, W, 3) uint8: the kept rows one under another."""
        if not self._rows:
            raise ValueError("the gallery is empty: no view was evaluated")
        width = max(r.shape[1] for r in self._rows)
        rows = [np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0))) for r in self._rows]
        return np.concatenate(rows, axis=0)

    def write(self, path: str | Path, overwrite: bool = False) -> Path:
        """Write :meth:`image` as a PNG, atomically (never over an existing file without ``overwrite``)."""
        with atomic_write_path(path, overwrite=overwrite) as tmp:
            iio.imwrite(tmp, self.image(), extension=".png")
        return Path(path)
