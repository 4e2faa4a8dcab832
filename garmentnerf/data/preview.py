"""Contact sheets: a grid of views x frames with small text titles, to eyeball a data set.

:func:`contact_sheet` lays out any images; :func:`scene_contact_sheet` fetches a scene's
ground-truth images (through the on-demand cache of :class:`~garmentnerf.data.scene_images.SceneImages`)
with cameras as rows and frames as columns. With label maps, the label borders are drawn over the
images (garment border yellow, body border cyan) to check the labels against the pixels.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from garmentnerf.data.render_gt import LABEL_GARMENT, MAX_GARMENT_LAYERS
from garmentnerf.data.scene_images import SceneImages

if TYPE_CHECKING:  # pragma: no cover
    from garmentnerf.body.model import BodyModel
    from garmentnerf.data.render_gt import GroundTruthRenderer
    from garmentnerf.data.scene import Scene

GARMENT_EDGE = (255, 220, 0)
BODY_EDGE = (0, 220, 255)


def _to_rgb8(image: np.ndarray) -> np.ndarray:
    a = np.asarray(image)
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3 or a.shape[2] not in (1, 3, 4):
        raise ValueError(f"images must be (H, W), (H, W, 1), (H, W, 3) or (H, W, 4), got shape {a.shape}")
    a = a[..., :3] if a.shape[2] >= 3 else np.repeat(a, 3, axis=2)
    if a.dtype == np.uint8:
        return a
    if np.issubdtype(a.dtype, np.floating):
        return np.clip(np.rint(a.astype(np.float64) * 255.0), 0, 255).astype(np.uint8)
    return np.clip(a, 0, 255).astype(np.uint8)


def label_edges(labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Boolean maps of pixels on the garment's border and on the body's border (4-neighbourhood).
    A layered garment's border includes where one layer meets the other (each label's own border)."""
    lab = np.asarray(labels)
    edges = {}
    for label in (1, *range(LABEL_GARMENT, LABEL_GARMENT + MAX_GARMENT_LAYERS)):
        m = lab == label
        border = np.zeros_like(m)
        border[1:] |= m[1:] != m[:-1]
        border[:-1] |= m[1:] != m[:-1]
        border[:, 1:] |= m[:, 1:] != m[:, :-1]
        border[:, :-1] |= m[:, 1:] != m[:, :-1]
        edges[label] = border & m
    garment = np.logical_or.reduce([edges[k] for k in edges if k >= LABEL_GARMENT])
    return garment, edges[1]


def _font(size: int):
    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1
        return ImageFont.load_default()


def contact_sheet(images: Sequence[Sequence[np.ndarray]], labels: Sequence[Sequence[np.ndarray]] | None = None,
                  row_titles: Sequence[str] | None = None, col_titles: Sequence[str] | None = None,
                  cell_scale: float = 1.0, gap: int = 2, font_size: int = 12,
                  background=(40, 40, 40), text_color=(235, 235, 235)) -> np.ndarray:
    """A grid image (H, W, 3) uint8: ``images[row][col]`` placed in rows and columns.

    Args:
        images: rows of images ((H, W), (H, W, 3|4), float in [0, 1] or uint8); rows may differ
            in length and cells in size (each cell is the largest size, images top-left aligned).
        labels: optional label maps of the same nesting (0 background, 1 body, 2 + k garment layer k); their
            borders are drawn over the images.
        row_titles, col_titles: text left of each row / above each column.
        cell_scale: resize every cell by this factor (e.g. 0.5 for compact sheets).
    """
    rows = [list(r) for r in images]
    if not rows or not any(rows):
        raise ValueError("contact_sheet needs at least one image")
    if labels is not None:
        label_rows = [list(r) for r in labels]
        if [len(r) for r in label_rows] != [len(r) for r in rows]:
            raise ValueError("labels must have the same rows and columns as images")
    if row_titles is not None and len(row_titles) != len(rows):
        raise ValueError(f"{len(row_titles)} row titles for {len(rows)} rows")
    ncols = max(len(r) for r in rows)
    if col_titles is not None and len(col_titles) != ncols:
        raise ValueError(f"{len(col_titles)} column titles for {ncols} columns")

    cells: list[list[Image.Image]] = []
    for i, row in enumerate(rows):
        out_row = []
        for j, img in enumerate(row):
            rgb = _to_rgb8(img).copy()
            if labels is not None:
                lab = np.asarray(label_rows[i][j])
                if lab.shape != rgb.shape[:2]:
                    raise ValueError(f"labels[{i}][{j}] has shape {lab.shape}, image {rgb.shape[:2]}")
                g_edge, b_edge = label_edges(lab)
                rgb[b_edge] = BODY_EDGE
                rgb[g_edge] = GARMENT_EDGE
            im = Image.fromarray(rgb)
            if cell_scale != 1.0:
                w = max(1, round(im.width * cell_scale))
                h = max(1, round(im.height * cell_scale))
                im = im.resize((w, h), Image.Resampling.BOX)
            out_row.append(im)
        cells.append(out_row)
    cell_w = max(im.width for r in cells for im in r)
    cell_h = max(im.height for r in cells for im in r)

    font = _font(font_size)
    probe = ImageDraw.Draw(Image.new("RGB", (1, 1)))

    def text_size(text: str) -> tuple[int, int]:
        box = probe.textbbox((0, 0), text, font=font)
        return box[2] - box[0], box[3] - box[1]

    left = (max(text_size(t)[0] for t in row_titles) + 2 * gap + 4) if row_titles else 0
    top = (font_size + 2 * gap + 4) if col_titles else 0
    W = left + ncols * cell_w + (ncols + 1) * gap
    H = top + len(rows) * cell_h + (len(rows) + 1) * gap
    sheet = Image.new("RGB", (W, H), tuple(background))
    draw = ImageDraw.Draw(sheet)
    for i, row in enumerate(cells):
        y = top + gap + i * (cell_h + gap)
        for j, im in enumerate(row):
            sheet.paste(im, (left + gap + j * (cell_w + gap), y))
        if row_titles:
            th = text_size(row_titles[i])[1]
            draw.text((gap + 2, y + (cell_h - th) // 2), row_titles[i], fill=tuple(text_color), font=font)
    if col_titles:
        for j, title in enumerate(col_titles):
            tw = text_size(title)[0]
            draw.text((left + gap + j * (cell_w + gap) + (cell_w - tw) // 2, gap + 2), title,
                      fill=tuple(text_color), font=font)
    return np.asarray(sheet, dtype=np.uint8).copy()


def scene_contact_sheet(scene: "Scene", renderer: "GroundTruthRenderer | SceneImages | None", sequence: str,
                        cameras: Sequence[str] | None = None, frames: Sequence[int] | None = None,
                        body_model: "BodyModel | None" = None, show_labels: bool = False,
                        cell_scale: float = 0.5, use_cache: bool = True) -> np.ndarray:
    """Ground truth of ``sequence``: one row per camera, one column per frame.

    Args:
        renderer: a :class:`GroundTruthRenderer`, a :class:`SceneImages` (its cache and body are
            used), or None (a renderer on a fresh headless context, released afterwards).
        cameras: camera names (default: the ``train`` cameras, at most 8 spread over the circle).
        frames: frame indices (default: 6 spread over the sequence).
    """
    if cameras is None:
        names = scene.camera_names("train") or scene.camera_names()
        step = max(1, len(names) // 8)
        cameras = names[::step][:8]
    if frames is None:
        n = scene.num_frames(sequence)
        frames = sorted({int(round(x)) for x in np.linspace(0, n - 1, min(6, n))})
    if isinstance(renderer, SceneImages):
        source, own = renderer, False
    else:
        source, own = SceneImages(scene, renderer, body_model, use_cache=use_cache), True
    try:
        rows, label_rows = [], []
        for cam in cameras:
            row, lrow = [], []
            for f in frames:
                rgb, lab = source.image(sequence, cam, f)
                row.append(rgb)
                lrow.append(lab)
            rows.append(row)
            label_rows.append(lrow)
    finally:
        if own:
            source.close()
    return contact_sheet(rows, label_rows if show_labels else None, row_titles=list(cameras),
                         col_titles=[f"{sequence} #{f}" for f in frames], cell_scale=cell_scale)
