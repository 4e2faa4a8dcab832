"""Evaluate a trained run on a scene split with the paper's metrics, and the nearest-view baseline.

Splits (what is compared with what)
    ``seen``
        The scene's training sequences seen from the cameras the run was trained on (``run.json``
        ``train.cameras``; default every ``train``-split camera): reconstruction quality.
        Subsampled by default (:data:`DEFAULT_LIMITS`): at most 4 cameras, evenly spread over
        the list, and a contiguous window of at most 30 frames in the middle of each sequence
        (contiguous so that tOF sees consecutive frames).
    ``unseen_view``
        The training sequences seen from the scene's ``unseen_view`` cameras (the paper's
        "seen motion" rows of its comparison table, which are evaluated on held-out views).
        Every frame and every such camera by default.
    ``unseen_motion``
        The scene's ``unseen_motion`` sequences seen from the scene's ``train`` cameras (the
        same set for every run of a scene, so ablations with fewer training views stay
        comparable), at most 4 of them evenly spread by default, every frame.

    Explicit ``frames`` / ``cameras`` replace these defaults (no subsampling then).

Resolution (``resolution``)
    ``native`` (default): the scene camera's own image size (512 x 512 for the bundled demo), so
    that a model's blur shows: the model renders at its trained pixel density and its maps are
    resampled (bilinear) to that size, as the previewer shows them. ``model``: the camera resized
    to the pixel density the model was trained at (:func:`eval_size`: longer side
    ``cfg.decoder.image_resolution``, the other side proportional, for whole-frame training; the scene's
    size times ``cfg.schedule.training_crop_density`` for character windows), the size of the trainer's
    targets.

How an image is made (identical to training, the viewer and ``garmentnerf render``)
    Prediction: :class:`~garmentnerf.render.session.RenderSession` (the one render path) renders
    the evaluation camera with a render preset (default ``reference``: the paper's sampling at
    quality 1, the pixel density the model was trained with; another preset renders at its own
    quality, and ``quality`` overrides either) and :meth:`NeuralFrame.composite` composes the
    decomposed maps with the run's learned palette over the model's black background at the evaluation size.
    Ground truth: the scene's cached 8-bit image (:class:`~garmentnerf.data.scene_images.SceneImages`)
    area-downsampled to the evaluation size when it is smaller and composited over
    the black background with the area-downsampled foreground coverage -- at the model's
    resolution, the trainer's targets (:class:`~garmentnerf.train.frames.SceneFrames`), byte for
    byte. Its labels (0 background, 1 body, 2 garment) are nearest-resampled.

Metrics (conventions in :mod:`garmentnerf.eval.metrics`)
    Per frame: ``psnr``, ``ssim``, ``stlpips_alex`` (shift-tolerant LPIPS, its own metric) and
    ``lpips_alex`` (the paper's LPIPS) when the user supplied the AlexNet backbone
    (``$GARMENTNERF_LPIPS_ALEXNET``), else listed in ``unavailable`` with the reason. Per
    (sequence, camera): tOF over the consecutive evaluated frames (TecoGAN: at least 6 frames,
    2 skipped at each end; listed in ``unavailable`` with the reason when no camera has enough,
    or when the chosen frames are not consecutive). Means: PSNR, SSIM and the perceptual
    distances over every evaluated image (every PSNR capped per frame at 100 dB), tOF over every
    evaluated frame pair of every camera.

Foreground (what a user looks at; full-frame PSNR over a black background is mostly background)
    The character's silhouette is the ground truth's labelled pixels; the prediction's is where
    its mask ``m > 0.5`` (the nearest-view baseline's: its ground-truth labels).
    ``fg_psnr``: PSNR over the union of both silhouettes (a missing or an extra limb counts).
    ``body_psnr`` / ``garment_psnr``: PSNR over the ground truth's body / garment pixels.
    ``silhouette_iou``: intersection over union of the two silhouettes.
    ``sharpness``: gradient energy (squared Sobel magnitude of the luma) of the prediction over
    the ground truth's, inside the garment at least :data:`SHARPNESS_MARGIN` pixels (at 512 px)
    from its outline: 1 keeps the folds, 0.5 has lost half their contrast energy.
    ``garment_inner_psnr``: PSNR over the ground truth's garment pixels at least
    :data:`OUTLINE_BAND` pixels (at 512 px) from its outline; ``garment_outline_share``: the share
    of the garment's squared error (over ``garment_psnr``'s pixels) within that band. Together they
    tell a garment of the wrong shape (most error in the band) from one shaded wrongly inside.
    ``garment_luma`` / ``garment_luma_truth``: the mean luma of the prediction / the ground truth over
    ``garment_inner_psnr``'s pixels; over the split's views they give ``shading_contrast`` and
    ``shading_correlation`` (:func:`~garmentnerf.eval.metrics.shading_agreement`: does the
    cloth's brightness follow the truth's from view to view, the lit side as bright and the
    shaded side as dark? 1 and 1 when it does).
    ``fold_correlation``: the correlation of the prediction's luma with the truth's over those pixels
    within one view (:func:`~garmentnerf.eval.metrics.luma_correlation`: are its folds' lit ridges and
    shaded creases where the truth's are? 0 for a garment of one brightness).
    ``garment_flat_psnr``: ``garment_psnr`` of the truth's garment painted its own mean colour (the
    outline exact, no shading; :func:`~garmentnerf.eval.metrics.flat_psnr`), a property of the
    ground truth alone: a render under it draws folds that cost more than drawing none.
    A figure whose region is empty in a view (e.g. no body pixel) is left out of that view's row
    and of the mean. With a baseline, ``margin_db`` is the model's mean PSNR and ``fg_psnr``
    minus the nearest view's: the paper's yardstick, independent of the framing.

Nearest-view baseline (the paper's "nearest view" row)
    For each evaluated view (camera ``c``, frame ``t``) the prediction is simply the ground-truth
    image of the *training camera nearest to c* at the same frame ``t``, unchanged (no
    reprojection or warping: the paper shows "the training samples with the nearest viewpoint").
    Nearest = smallest angle between the cameras' optical axes (``R[2]``, the camera's +z in
    world coordinates); ties go to the first camera in the scene's order. The training cameras
    are the run's (``train.cameras``) or else the scene's ``train`` split. It is defined for the
    ``unseen_view`` split only: for ``seen`` the nearest training view is the view itself, and
    for ``unseen_motion`` no training image of that frame exists. Scored with the same metrics
    (including tOF over the baseline's frame sequence).

Result (:func:`evaluate_run`): a strict-JSON-serialisable dict (non-finite floats as the strings
``"inf"``/``"nan"``, see :class:`~garmentnerf.eval.metrics.MetricSummary`)::

    {"format": "garmentnerf-eval", "version": 2, "method": "model",
     "run": "...", "step": N, "scene": "...", "split": "unseen_view", "preset": "reference", "quality": 1.0,
     "sequences": {"train": [frames...]}, "cameras": [...], "subsampled": false,
     "selection": "how frames/cameras were chosen", "resolution": "native", "resolution_wh": [W, H],
     "background": [r, g, b], "psnr_cap_db": 100.0, "palette": [[r, g, b], ...],
     "means": {"psnr": .., "ssim": .., "stlpips_alex": .., "tof": .., "fg_psnr": .., "body_psnr": ..,
               "garment_psnr": .., "garment_inner_psnr": .., "garment_outline_share": ..,
               "silhouette_iou": .., "sharpness": .., "garment_luma": .., "garment_luma_truth": ..,
               "shading_contrast": .., "shading_correlation": .., "fold_correlation": ..,
               "garment_flat_psnr": ..},
     "counts": {"images": .., "tof_pairs": ..},
     "unavailable": {"lpips_alex": "reason", ...},
     "per_frame": [{"sequence", "camera", "frame", "psnr", "ssim", "stlpips_alex"}, ...],
     "per_camera": [{"sequence", "camera", "means", "tof": {...}}, ...],
     "seconds": ..,
     "baseline": {... the same keys, "method": "nearest_view", "nearest_camera": {cam: train cam}},
     "margin_db": {"psnr": .., "fg_psnr": ..}}
"""

from __future__ import annotations

import functools
import math
import sys
import time
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

import cv2
import numpy as np
import torch
from tqdm import tqdm

from garmentnerf.bake.capture import capture_frame, check_can_bake
from garmentnerf.bake.draw import BakeDrawer, baked_maps
from garmentnerf.bake.store import frame_bytes
from garmentnerf.data.render_gt import LABEL_BODY, GroundTruthRenderer, garment_pixels
from garmentnerf.data.scene_images import SceneImages
from garmentnerf.eval.metrics import (
    PSNR_CAP_DB,
    MetricSummary,
    _encode_float,
    flat_psnr,
    interior,
    is_psnr_metric,
    luma_correlation,
    masked_psnr,
    mean_luma,
    mean_psnr,
    psnr,
    shading_agreement,
    sharpness_ratio,
    silhouette_iou,
    ssim,
    temporal_flow_error,
    to_grey_uint8,
)
from garmentnerf.gl.context import create_context
from garmentnerf.model.config import BACKGROUND
from garmentnerf.model.perceptual import LPIPS, STLPIPS, lpips_available, stlpips_available
from garmentnerf.ranges import FrameRange, parse_frame_range, parse_list
from garmentnerf.render.presets import get_render_preset
from garmentnerf.render.session import RenderSession, resolve_composition
from garmentnerf.runs import load_run, run_train_cameras
from garmentnerf.train.frames import area_resize

if TYPE_CHECKING:
    from garmentnerf.eval.gallery import Gallery

__all__ = ["SPLITS", "RESOLUTIONS", "DEFAULT_LIMITS", "EVAL_FORMAT", "evaluate_run", "nearest_camera",
           "select_views", "eval_size", "perceptual_metrics", "foreground_metrics",
           "GroundTruthView", "format_result_table", "BaselineNotDefined"]

EVAL_FORMAT = "garmentnerf-eval"
EVAL_VERSION = 2

#: Evaluation resolutions: the scene's image size, or the model's internal resolution.
RESOLUTIONS = ("native", "model")

#: Pixels (at 512 x 512, proportionally at other sizes) between the garment's silhouette and the
#: region its sharpness is measured in: folds inside the garment, not its outline.
SHARPNESS_MARGIN = 3

#: Width in pixels (at 512 x 512, proportionally at other sizes) of the band inside the garment's
#: silhouette that ``garment_outline_share`` and ``garment_inner_psnr`` separate: an outline drawn
#: a few pixels off (the garment's shape) lands its error there, misplaced shading inside.
OUTLINE_BAND = 6

#: Evaluation splits.
SPLITS = ("seen", "unseen_view", "unseen_motion")

#: Default subsampling per split: (max frames per sequence, max cameras); None = all.
DEFAULT_LIMITS: dict[str, tuple[int | None, int | None]] = {
    "seen": (30, 4),
    "unseen_view": (None, None),
    "unseen_motion": (None, 4),
}

#: Metrics in report order (the perceptual ones only when available).
METRIC_ORDER = ("psnr", "ssim", "lpips_alex", "stlpips_alex", "tof")


class BaselineNotDefined(ValueError):
    """The nearest-view baseline was asked for a split where it has no meaning."""


# ---------------------------------------------------------------------------------------------
# Selection
# ---------------------------------------------------------------------------------------------

def _frames_of(spec, num_frames: int, sequence: str) -> list[int]:
    """Frame list of one sequence from None (all) / ``"A:B"`` (:func:`garmentnerf.ranges.parse_frame_range`) /
    a :class:`~garmentnerf.ranges.FrameRange` / a ``slice`` / a sequence of ints."""
    if isinstance(spec, str):
        spec = parse_frame_range(spec, "--frames")
    if spec is None:
        return list(range(num_frames))
    if isinstance(spec, slice):
        text = ":".join("" if v is None else str(v) for v in (spec.start, spec.stop, spec.step))
        spec = parse_frame_range(text, "frames")
    if isinstance(spec, FrameRange):
        return spec.frames(num_frames, f"sequence '{sequence}'")
    out = []
    for f in spec:
        if isinstance(f, bool) or not isinstance(f, (int, np.integer)) or not 0 <= int(f) < num_frames:
            raise ValueError(f"frame {f!r} is out of range for sequence '{sequence}' "
                             f"({num_frames} frames: 0..{num_frames - 1})")
        out.append(int(f))
    if not out:
        raise ValueError("frames: the selection is empty")
    if len(set(out)) != len(out):
        raise ValueError(f"frames: duplicates in {out}")
    return out


def _spread(items: list, count: int | None) -> list:
    """At most ``count`` items evenly spread over the list (first one always kept)."""
    if count is None or len(items) <= count:
        return list(items)
    n = len(items)
    return [items[(i * n) // count] for i in range(count)]


def _middle_window(n: int, count: int | None) -> list[int]:
    if count is None or n <= count:
        return list(range(n))
    start = (n - count) // 2
    return list(range(start, start + count))


def select_views(run, scene, split: str, frames=None, cameras=None) -> dict[str, Any]:
    """What an evaluation of ``split`` covers (see the module docstring for the defaults).

    Returns:
        ``{"sequences": {name: [frames]}, "cameras": [names], "subsampled": bool,
        "selection": text, "train_cameras": [names]}``.
    Raises:
        ValueError: unknown split, a split the scene does not have, a camera that is not in the
            split, frames out of range.
    """
    if split not in SPLITS:
        raise ValueError(f"unknown split '{split}' (known: {', '.join(SPLITS)})")
    max_frames, max_cams = DEFAULT_LIMITS[split]
    train_cams = run_train_cameras(run, scene)
    if split == "seen":
        seqs = scene.sequence_names("train")
        pool = train_cams
        pool_text = "the run's training cameras"
        allowed = scene.camera_names("train")
    elif split == "unseen_view":
        seqs = scene.sequence_names("train")
        pool = allowed = scene.camera_names("unseen_view")
        pool_text = "the scene's unseen_view cameras"
    else:
        seqs = scene.sequence_names("unseen_motion")
        pool = allowed = scene.camera_names("train")
        pool_text = "the scene's train cameras"
    if not seqs:
        kind = "unseen_motion" if split == "unseen_motion" else "train"
        raise ValueError(f"{scene.scene_file}: no {kind} sequence, so nothing to evaluate for split '{split}'")
    if not pool:
        raise ValueError(f"{scene.scene_file}: no camera for split '{split}' ({pool_text})")
    subsampled = False
    notes = []
    if cameras is None or (not isinstance(cameras, str) and len(cameras) == 0):
        cams = _spread(pool, max_cams)
        if len(cams) < len(pool):
            subsampled = True
            notes.append(f"{len(cams)} of {len(pool)} {pool_text}, evenly spread")
        else:
            notes.append(f"all {len(pool)} of {pool_text}")
    else:
        cams = parse_list(cameras, "--cameras", kind="camera") if isinstance(cameras, str) else [str(c) for c in cameras]
        for c in cams:
            if c not in allowed:
                raise ValueError(f"camera '{c}' is not one of the {split} cameras of the scene "
                                 f"({', '.join(allowed) or 'none'})")
        if len(set(cams)) != len(cams):
            raise ValueError(f"cameras: duplicates in {cams}")
        notes.append("cameras given")
    sequences: dict[str, list[int]] = OrderedDict()
    for s in seqs:
        n = scene.num_frames(s)
        if frames is None:
            sel = _middle_window(n, max_frames)
            if len(sel) < n:
                subsampled = True
        else:
            sel = _frames_of(frames, n, s)
        sequences[s] = sel
    if frames is None:
        notes.append("all frames" if max_frames is None else
                     f"a contiguous window of at most {max_frames} frames in the middle of each sequence")
    else:
        notes.append("frames given")
    return {"sequences": sequences, "cameras": cams, "subsampled": subsampled, "selection": "; ".join(notes),
            "train_cameras": train_cams}


def nearest_camera(scene, camera: str, candidates: Sequence[str]) -> tuple[str, float]:
    """(name, angle in degrees) of the candidate camera whose optical axis is closest in angle to
    ``camera``'s (ties: the first in ``candidates``); ``camera`` itself is never returned."""
    def axis(name):
        return np.asarray(scene.camera(name).camera.R, dtype=np.float64)[2]

    a = axis(camera)
    best, best_angle = None, math.inf
    for c in candidates:
        if c == camera:
            continue
        cos = float(np.clip(np.dot(a, axis(c)), -1.0, 1.0))
        angle = math.degrees(math.acos(cos))
        if angle < best_angle - 1e-9:
            best, best_angle = c, angle
    if best is None:
        raise ValueError(f"no training camera other than '{camera}' to take the nearest view from")
    return best, best_angle


def eval_size(config, camera, resolution: str = "model") -> tuple[int, int]:
    """(w, h) of the evaluation images: the (scene) camera's own size for ``native``; for ``model``
    its size at the density the model was trained at
    (:meth:`~garmentnerf.model.config.ModelConfig.training_scale`: the longer side
    ``config.decoder.image_resolution`` for whole-frame training), aspect kept."""
    if resolution == "native":
        return int(camera.width), int(camera.height)
    W, H = int(camera.width), int(camera.height)
    s = config.training_scale(W, H)
    return max(1, round(W * s)), max(1, round(H * s))


# ---------------------------------------------------------------------------------------------
# Metrics set-up
# ---------------------------------------------------------------------------------------------

@functools.lru_cache(maxsize=4)
def _stlpips_module(variant: str):
    return STLPIPS(variant)


def perceptual_metrics(lpips_backbone: str | None = None) -> tuple[list, dict[str, str]]:
    """(modules, unavailable): ``stlpips_alex`` when stlpips-pytorch is installed and
    ``lpips_alex`` when the AlexNet backbone is supplied; each missing one with its reason."""
    modules, unavailable = [], {}
    ok, reason = lpips_available(lpips_backbone)
    if ok:
        modules.append(LPIPS(lpips_backbone))
    else:
        unavailable["lpips_alex"] = reason
    ok, reason = stlpips_available("alex")
    if ok:
        modules.append(_stlpips_module("alex"))
    else:
        unavailable["stlpips_alex"] = reason
    return modules, unavailable


# ---------------------------------------------------------------------------------------------
# Ground truth
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class GroundTruthView:
    """One ground-truth view at the evaluation size.

    Attributes:
        image: (h, w, 3) float32 in [0, 1], composited over the run's background as the trainer's
            targets are (area-downsampled color and coverage when the size is below the scene's).
        labels: (h, w) uint8 pixel labels (0 background, 1 body, 2 garment;
            :mod:`garmentnerf.data.render_gt`), nearest-resampled when the size differs.
    """

    image: np.ndarray
    labels: np.ndarray


class _GroundTruth:
    """Ground-truth views at the evaluation size, composited as the trainer's targets."""

    def __init__(self, scene, ctx, body, background, cache_images: int = 64):
        self.renderer = GroundTruthRenderer(ctx)
        self.images = SceneImages(scene, renderer=self.renderer, body_model=body)
        self.background = tuple(float(c) for c in background)
        self._cache: OrderedDict[tuple, GroundTruthView] = OrderedDict()
        self.cache_images = cache_images

    def view(self, sequence: str, camera: str, frame: int, size: tuple[int, int]) -> GroundTruthView:
        """The view of ``camera`` at ``frame`` at ``size`` = (w, h) (see :class:`GroundTruthView`)."""
        key = (sequence, camera, int(frame), tuple(size))
        hit = self._cache.get(key)
        if hit is not None:
            self._cache.move_to_end(key)
            return hit

        rgb, labels = self.images.image(sequence, camera, frame)
        image = area_resize(rgb, size)
        coverage = area_resize((labels != 0).astype(np.float32), size)
        bg = torch.tensor(self.background, dtype=torch.float32).view(3, 1, 1)
        if bool((bg != 0).any()):
            image = image + (1.0 - coverage) * bg
        if labels.shape[::-1] != tuple(size):
            labels = cv2.resize(labels, tuple(size), interpolation=cv2.INTER_NEAREST)
        out = GroundTruthView(image.clamp(0.0, 1.0).permute(1, 2, 0).contiguous().numpy(), labels)
        self._cache[key] = out
        while len(self._cache) > self.cache_images:
            self._cache.popitem(last=False)
        return out

    def close(self) -> None:
        self.images.close()
        self.renderer.release()


def foreground_metrics(pred: np.ndarray, target: GroundTruthView, pred_silhouette: np.ndarray) -> dict[str, float]:
    """The figures over the character (see the module docstring, "Foreground").

    Args:
        pred: (h, w, 3) prediction in [0, 1] over the same background as ``target.image``.
        target: the ground-truth view (image and labels).
        pred_silhouette: (h, w) bool, where the prediction shows the character.
    Returns:
        ``fg_psnr``, ``body_psnr``, ``garment_psnr``, ``garment_inner_psnr``,
        ``garment_outline_share``, ``silhouette_iou``, ``sharpness``, ``garment_luma``,
        ``garment_luma_truth``, ``fold_correlation``, ``garment_flat_psnr``; a figure whose region is
        empty in this view is left out.
    """
    truth = target.labels != 0
    garment = garment_pixels(target.labels)
    margin = max(1, round(SHARPNESS_MARGIN * max(truth.shape) / 512))
    inner = interior(garment, max(1, round(OUTLINE_BAND * max(truth.shape) / 512)))
    error = np.square(np.asarray(pred, np.float64) - np.asarray(target.image, np.float64)).sum(axis=-1)
    garment_error = float(error[garment].sum())
    values = {
        "fg_psnr": masked_psnr(pred, target.image, truth | pred_silhouette),
        "body_psnr": masked_psnr(pred, target.image, target.labels == LABEL_BODY),
        "garment_psnr": masked_psnr(pred, target.image, garment),
        "garment_inner_psnr": masked_psnr(pred, target.image, inner),
        "garment_outline_share": (float(error[garment & ~inner].sum()) / garment_error
                                  if garment_error > 0 else None),
        "silhouette_iou": silhouette_iou(pred_silhouette, truth),
        "sharpness": sharpness_ratio(pred, target.image, interior(garment, margin)),
        "garment_luma": mean_luma(pred, inner),
        "garment_luma_truth": mean_luma(target.image, inner),
        "fold_correlation": luma_correlation(pred, target.image, inner),
        "garment_flat_psnr": flat_psnr(target.image, garment),
    }
    return {k: v for k, v in values.items() if v is not None}


# ---------------------------------------------------------------------------------------------
# Accumulating one method's numbers
# ---------------------------------------------------------------------------------------------

class _Scores:
    """Per-frame metrics and per-camera grey frames (for tOF) of one method."""

    def __init__(self, perceptual: list):
        self.perceptual = perceptual
        self.per_frame: list[dict] = []
        self.summaries: "OrderedDict[tuple[str, str], MetricSummary]" = OrderedDict()
        self._greys: dict[tuple[str, str], tuple[list, list]] = {}

    def add(self, sequence: str, camera: str, frame: int, pred: np.ndarray, gt, *,
            pred_silhouette: np.ndarray | None = None) -> dict:
        """Score one view. ``gt`` is an (h, w, 3) image, or a :class:`GroundTruthView`, which with
        ``pred_silhouette`` ((h, w) bool) adds the foreground figures."""
        target = gt.image if isinstance(gt, GroundTruthView) else gt
        values = {"psnr": psnr(pred, target), "ssim": ssim(pred, target)}
        for m in self.perceptual:
            values[m.metric_name] = m.distance(pred, target)
        if isinstance(gt, GroundTruthView) and pred_silhouette is not None:
            values.update(foreground_metrics(pred, gt, pred_silhouette))
        key = (sequence, camera)
        summary = self.summaries.get(key)
        if summary is None:
            summary = self.summaries[key] = MetricSummary()
            self._greys[key] = ([], [])
        summary.add_frame(frame, **values)
        preds, gts = self._greys[key]
        preds.append(to_grey_uint8(pred))
        gts.append(to_grey_uint8(target))
        row = {"sequence": sequence, "camera": camera, "frame": int(frame), **values}
        self.per_frame.append(row)
        return row

    def finish(self, consecutive: dict[str, bool], tof: bool = True) -> dict[str, Any]:
        """Means, per-camera summaries and what could not be computed."""
        unavailable: dict[str, str] = {}
        pairs: list[float] = []
        per_camera = []
        reasons = set()
        for (seq, cam), summary in self.summaries.items():
            preds, gts = self._greys[(seq, cam)]
            frames = [f["frame"] for f in summary.frames]
            if not tof:
                reasons.add("tOF not asked for")
            elif not consecutive.get(seq, False):
                reasons.add("the evaluated frames are not consecutive (tOF needs a contiguous range)")
            else:
                result = temporal_flow_error(preds, gts)
                if result.reason is not None:
                    reasons.add(result.reason)
                    summary.mark_unavailable("tof", result.reason)
                else:
                    result.pairs = [(frames[a], frames[b]) for a, b in result.pairs]
                    summary.tof = result
                    pairs.extend(result.values)
            d = summary.to_dict()
            per_camera.append({"sequence": seq, "camera": cam, "means": d["means"], "tof": d.get("tof"),
                               "unavailable": d["unavailable"]})
        means: dict[str, float] = {}
        names: list[str] = []
        for row in self.per_frame:
            names.extend(k for k in row if k not in ("sequence", "camera", "frame") and k not in names)
        for name in names:
            v = [row[name] for row in self.per_frame if name in row]
            means[name] = mean_psnr(v, PSNR_CAP_DB) if is_psnr_metric(name) else float(np.mean(v))
        lumas = [(row["garment_luma"], row["garment_luma_truth"]) for row in self.per_frame if "garment_luma" in row]
        if lumas:
            means.update(shading_agreement(*zip(*lumas)) or {})
        if pairs:
            means["tof"] = float(np.mean(pairs))
        else:
            unavailable["tof"] = "; ".join(sorted(reasons)) or "no frame pair evaluated"
        return {"means": means, "counts": {"images": len(self.per_frame), "tof_pairs": len(pairs)},
                "unavailable": unavailable, "per_frame": self.per_frame, "per_camera": per_camera}


def _consecutive(frames: list[int]) -> bool:
    return all(b == a + 1 for a, b in zip(frames, frames[1:]))


# ---------------------------------------------------------------------------------------------
# The entry point
# ---------------------------------------------------------------------------------------------

def evaluate_run(run, split: str, frames=None, cameras=None, progress: bool = True, *, baseline: bool = False,
                 model: bool = True, gl_context=None, scene=None, device: str = "cpu",
                 lpips_backbone: str | None = None, tof: bool = True, preset: str = "reference",
                 quality: float | None = None, resolution: str = "native", gallery: "Gallery | None" = None,
                 composition: str = "auto", bake=None) -> dict:
    """Render and score a run on one split (see the module docstring for every convention).

    Args:
        run: a :class:`~garmentnerf.runs.LoadedRun` or a run folder.
        split: ``seen``, ``unseen_view`` or ``unseen_motion``.
        frames: None (the split's default), a frame range (``"A:B"``, ``"A:B:S"``, ... or a parsed
            :class:`~garmentnerf.ranges.FrameRange`), a ``slice`` or a list of frame indices, applied
            to every sequence of the split.
        cameras: None (the split's default), ``"a,b"`` or a list of camera names of the split.
        progress: a tqdm progress bar on stderr.
        baseline: also score the nearest-view baseline (``unseen_view`` only), under ``"baseline"``.
        model: score the run's model (False: baseline only; the result's top level is then the
            baseline's).
        gl_context: a moderngl context (None: a headless one is made and released).
        scene: a scene folder to use instead of the run's (when a run folder is given).
        device: torch device when a run folder is given.
        lpips_backbone: AlexNet weights for LPIPS (default ``$GARMENTNERF_LPIPS_ALEXNET``).
        tof: compute tOF.
        preset: the render preset (:data:`~garmentnerf.render.presets.RENDER_PRESETS`; default
            ``reference``, the paper's sampling), rendered at its quality (resolution scale).
        quality: render at this multiple of the pixel density the model was trained at instead of
            the preset's (a model trained at twice the density, rendered at 0.5, casts the rays of
            one trained at 1: an equal-cost comparison).
        resolution: ``native`` (the scene's image size, default) or ``model`` (the model's
            image resolution), see :data:`RESOLUTIONS`.
        gallery: a :class:`~garmentnerf.eval.gallery.Gallery` that keeps a few views' images.
        composition: how the model's views are composed
            (:data:`~garmentnerf.render.session.COMPOSITIONS`; ``auto``: with the rasterised body
            when the run has a body appearance).
        bake: also score the run's bake (:class:`~garmentnerf.bake.capture.BakeSettings`): each frame is
            baked once and drawn from every evaluated camera by the previewer's GL draw, scored against the
            same ground truth under ``"bake"``, with its seconds and megabytes a frame.
    Returns:
        A strict-JSON-serialisable dict (layout in the module docstring).
    Raises:
        ValueError: unknown split or resolution, run without a scene, baseline on another split,
            bad selection.
    """
    t_start = time.perf_counter()
    render_preset = get_render_preset(preset)
    if quality is None:
        quality = render_preset.resolution_scale
    elif not (np.isfinite(quality) and quality > 0):
        raise ValueError(f"quality must be a number > 0, got {quality!r}")
    _check_request(split, baseline, model, resolution)
    run = _loaded(run, device, scene)

    composition = resolve_composition(composition, run)
    scene_obj, cfg = run.scene, run.config
    sel = select_views(run, scene_obj, split, frames, cameras)
    background = BACKGROUND
    perceptual, unavailable = perceptual_metrics(lpips_backbone)
    nearest = {c: dict(zip(("camera", "angle_deg"), nearest_camera(scene_obj, c, sel["train_cameras"])))
               for c in sel["cameras"]} if baseline else {}
    scores = _Scores(perceptual) if model else None
    base_scores = _Scores(perceptual) if baseline else None
    if bake is not None and not model:
        raise ValueError("a bake is scored beside the model: model=False and a bake")
    bake_scores = _Scores(perceptual) if bake is not None else None
    views = _ViewPlan(scene_obj, cfg, sel, resolution)

    own_ctx = None
    if gl_context is None:
        gl_context = own_ctx = create_context(headless=True)
    session = gt = bar = baker = None
    try:
        gt = _GroundTruth(scene_obj, gl_context, run.model.body, background)
        if progress:
            bar = tqdm(total=views.total, desc=f"eval {split}", unit="view", file=sys.stderr, dynamic_ncols=True)
        if model:
            session = RenderSession(run, gl_context, motion=next(iter(sel["sequences"])), composition=composition)
        if gallery is not None:
            gallery.plan(views.total)
        if bake is not None:
            check_can_bake(session)
            baker = _Baker(bake, BakeDrawer(gl_context, bake.draw_views, bake.mesh_step))
        methods = _Methods(session, scores, base_scores, nearest, render_preset, float(quality), background,
                           baker, bake_scores)
        for index, view in enumerate(views):
            methods.score(index, *view, views=views, gt=gt, gallery=gallery)
            if bar is not None:
                bar.update(1)
    finally:
        for closable in (bar, session, gt):
            if closable is not None:
                closable.close()
        if baker is not None:
            baker.drawer.release()
        if own_ctx is not None:
            own_ctx.release()
    result = _result(run, split, sel, views, render_preset, float(quality), background, unavailable,
                     scores, base_scores, nearest, tof, time.perf_counter() - t_start, bake_scores, baker)
    if model:
        result["composition"] = composition
    return _encode_float(result)


@dataclass
class _Methods:
    """What an evaluation scores: the model through its render session and/or the nearest view."""

    session: Any
    """The :class:`~garmentnerf.render.session.RenderSession` (None: the model is not scored)."""
    scores: _Scores | None
    base_scores: _Scores | None
    nearest: dict
    """Evaluated camera -> ``{"camera": nearest training camera, "angle_deg": ...}``."""
    preset: Any
    """The :class:`~garmentnerf.render.presets.RenderPreset` the model renders with."""
    quality: float
    """The pixel density it renders at, as a multiple of the trained density."""
    background: tuple[float, float, float]
    baker: "_Baker | None" = None
    """Bakes the frames and draws them (None: no bake is scored)."""
    bake_scores: _Scores | None = None

    def score(self, index: int, sequence: str, frame: int, camera: str, *, views: "_ViewPlan",
              gt: _GroundTruth, gallery: "Gallery | None") -> None:
        """Score view number ``index`` with every method, and offer it to the gallery."""
        size = views.size(camera)
        target = gt.view(sequence, camera, frame, size)
        shown: dict[str, np.ndarray] = {}
        character = target.labels != 0
        row = None
        if self.scores is not None:
            if self.session.sequence != sequence:
                self.session.set_motion(sequence)
            nf = self.session.render(frame, views.camera(camera), quality=self.quality, preset=self.preset)
            shown["render"] = nf.composite(None, self.background)
            silhouette = nf.alpha() > 0.5
            character = character | silhouette
            row = self.scores.add(sequence, camera, frame, shown["render"], target, pred_silhouette=silhouette)
        if self.baker is not None:
            maps = baked_maps(self.baker.drawer, self.session, self.baker.frame(self.session, sequence, frame),
                              views.camera(camera))
            if maps is None:
                shown["bake"] = np.broadcast_to(np.asarray(self.background, np.float32), (*size[::-1], 3)).copy()
                silhouette = np.zeros(size[::-1], bool)
            else:
                with torch.no_grad():
                    shown["bake"] = maps.compose(self.session.learned_palette(), self.background)[0].permute(
                        1, 2, 0).contiguous().numpy()
                silhouette = maps.alpha[0, 0].numpy() > 0.5
            self.bake_scores.add(sequence, camera, frame, shown["bake"], target, pred_silhouette=silhouette)
        if self.base_scores is not None:
            near = self.nearest[camera]["camera"]
            if views.size(near) != size:
                raise ValueError(f"nearest-view baseline: camera '{near}' has another image size than '{camera}'")
            near_view = gt.view(sequence, near, frame, size)
            shown["nearest view"] = near_view.image
            base_row = self.base_scores.add(sequence, camera, frame, near_view.image, target,
                                            pred_silhouette=near_view.labels != 0)
            row = row if row is not None else base_row
        if gallery is not None and gallery.wants(index):
            gallery.add(f"{sequence} {camera} frame {frame}", target.image, shown, row, character)


class _Baker:
    """The bake an evaluation scores: each frame baked once (the views come in frame order), timed."""

    def __init__(self, settings, drawer) -> None:
        self.settings = settings
        self.drawer = drawer
        self.current: tuple[str, int, Any] | None = None
        self.seconds: list[float] = []
        self.megabytes: list[float] = []

    def frame(self, session, sequence: str, frame: int):
        if self.current is None or self.current[:2] != (sequence, frame):
            t0 = time.perf_counter()
            baked = capture_frame(session, frame, self.settings)
            self.seconds.append(time.perf_counter() - t0)
            self.megabytes.append(len(frame_bytes(baked)) / 1e6)
            self.current = (sequence, frame, baked)
        return self.current[2]


def _check_request(split: str, baseline: bool, model: bool, resolution: str) -> None:
    if split not in SPLITS:
        raise ValueError(f"unknown split '{split}' (known: {', '.join(SPLITS)})")
    if resolution not in RESOLUTIONS:
        raise ValueError(f"unknown resolution '{resolution}' (known: {', '.join(RESOLUTIONS)})")
    if baseline and split != "unseen_view":
        raise BaselineNotDefined(f"the nearest-view baseline is defined for split 'unseen_view' only (for 'seen' the "
                                 f"nearest training view is the view itself; for 'unseen_motion' no training "
                                 f"image of the frame exists), not '{split}'")
    if not model and not baseline:
        raise ValueError("nothing to evaluate: model=False and baseline=False")


def _loaded(run, device: str, scene):
    """The loaded run (a folder is loaded), with its scene present."""
    if isinstance(run, (str, Path)):
        run = load_run(run, device=device, scene=scene)
    if run.scene is None:
        where = (run.info or {}).get("scene")
        raise ValueError(f"{run.root}: the run's scene folder ({where or 'not recorded'}) is missing; "
                         f"pass the scene explicitly (--scene DIR)")
    return run


class _ViewPlan:
    """The evaluated views in order (sequences, then frames, then cameras: a frame's features are
    computed once) and each camera at the evaluation resolution."""

    def __init__(self, scene, cfg, selection: dict, resolution: str):
        self.selection = selection
        self.resolution = resolution
        self._cameras = {}
        for cam in set(selection["cameras"]) | set(selection["train_cameras"]):
            camera = scene.camera(cam).camera
            self._cameras[cam] = camera.resized(*eval_size(cfg, camera, resolution))

    @property
    def total(self) -> int:
        return sum(len(f) for f in self.selection["sequences"].values()) * len(self.selection["cameras"])

    def __iter__(self):
        for seq, frame_list in self.selection["sequences"].items():
            for frame in frame_list:
                for cam in self.selection["cameras"]:
                    yield seq, frame, cam

    def camera(self, name: str):
        """The scene camera ``name`` resized to the evaluation size."""
        return self._cameras[name]

    def size(self, name: str) -> tuple[int, int]:
        camera = self._cameras[name]
        return int(camera.width), int(camera.height)


def _result(run, split: str, sel, views: _ViewPlan, render_preset, quality: float, background, unavailable, scores,
            base_scores, nearest, tof: bool, seconds: float, bake_scores=None, baker=None) -> dict:
    """The result dict of :func:`evaluate_run` (layout in the module docstring)."""
    consecutive = {s: _consecutive(f) for s, f in sel["sequences"].items()}
    common = {
        "format": EVAL_FORMAT, "version": EVAL_VERSION,
        "run": str(run.root), "step": int(run.step), "scene": str(run.scene.root), "split": split,
        "preset": render_preset.name, "quality": quality, "resolution": views.resolution,
        "sequences": {s: list(f) for s, f in sel["sequences"].items()}, "cameras": list(sel["cameras"]),
        "train_cameras": list(sel["train_cameras"]), "subsampled": bool(sel["subsampled"]),
        "selection": sel["selection"], "resolution_wh": list(views.size(sel["cameras"][0])),
        "background": list(background), "data_range": 1.0, "psnr_cap_db": PSNR_CAP_DB,
    }

    def result_of(s: _Scores, method: str) -> dict:
        part = s.finish(consecutive, tof)
        return {**common, "method": method, "means": part["means"], "counts": part["counts"],
                "unavailable": {**unavailable, **part["unavailable"]},
                "per_frame": part["per_frame"], "per_camera": part["per_camera"]}

    out = result_of(scores, "model") if scores is not None else None
    if out is not None:
        cfg = run.config
        out["palette"] = run.palette().cpu().tolist()
        out["model_config"] = {"decoder.image_resolution": cfg.decoder.image_resolution,
                               "encoder.history": cfg.encoder.history,
                               "encoder.detail_feature": cfg.encoder.detail_feature,
                               "encoder.dynamic_feature": cfg.encoder.dynamic_feature,
                               "schedule.iterations": cfg.schedule.iterations}
    if base_scores is not None:
        b = result_of(base_scores, "nearest_view")
        b["nearest_camera"] = {c: v["camera"] for c, v in nearest.items()}
        b["nearest_angle_deg"] = {c: v["angle_deg"] for c, v in nearest.items()}
        b["description"] = ("ground-truth image of the training camera nearest in optical-axis angle, same frame, "
                            "not reprojected")
        if out is None:
            out = b
        else:
            out["baseline"] = b
            out["margin_db"] = {m: out["means"][m] - b["means"][m] for m in ("psnr", "fg_psnr")
                                if m in out["means"] and m in b["means"]}
    if bake_scores is not None:
        b = result_of(bake_scores, "bake")
        b["settings"] = baker.settings.to_dict()
        b["seconds_per_frame"] = float(np.mean(baker.seconds)) if baker.seconds else None
        b["mb_per_frame"] = float(np.mean(baker.megabytes)) if baker.megabytes else None
        b["description"] = ("the run's frames baked once from a ring of cameras and drawn from each evaluated camera "
                            "by the previewer's GL draw, composed with the same body layer and palette")
        out["bake"] = b
    out["seconds"] = seconds
    return out


# ---------------------------------------------------------------------------------------------
# Text output
# ---------------------------------------------------------------------------------------------

_HEAD = {"psnr": "PSNR↑", "ssim": "SSIM↑", "lpips_alex": "LPIPS↓", "stlpips_alex": "ST-LPIPS↓", "tof": "tOF↓",
         "fg_psnr": "fg PSNR↑", "body_psnr": "body PSNR↑", "garment_psnr": "garment PSNR↑",
         "garment_inner_psnr": "inside↑", "garment_outline_share": "outline err.",
         "silhouette_iou": "IoU↑", "sharpness": "sharpness→1", "shading_contrast": "shading→1",
         "shading_correlation": "shading corr.↑", "fold_correlation": "fold corr.↑",
         "garment_flat_psnr": "flat garment"}

#: The foreground figures in report order (a second table).
FOREGROUND_ORDER = ("fg_psnr", "body_psnr", "garment_psnr", "garment_inner_psnr", "garment_outline_share",
                    "silhouette_iou", "sharpness", "shading_contrast", "shading_correlation", "fold_correlation",
                    "garment_flat_psnr")


def _fmt(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, str):
        return v
    if not math.isfinite(v):
        return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf")
    return f"{v:.3f}"


def format_result_table(result: dict) -> str:
    """A small plain-text table of an :func:`evaluate_run` result (model and baseline rows; the
    foreground figures in a second table; the margin over the nearest view last)."""
    rows = []
    if result.get("method"):
        rows.append((result["method"], result))
    if result.get("bake"):
        rows.append(("bake", result["bake"]))
    if result.get("baseline"):
        rows.append((result["baseline"]["method"], result["baseline"]))
    frames = sum(len(f) for f in result["sequences"].values())
    lines = [f"split {result['split']}: {len(result['cameras'])} camera(s) x {frames} frame(s) at "
             f"{result['resolution_wh'][0]}x{result['resolution_wh'][1]} ({result.get('resolution', 'model')}), "
             f"step {result['step']}" + (" (subsampled)" if result.get("subsampled") else "")]
    for order in (METRIC_ORDER, FOREGROUND_ORDER):
        metrics = [m for m in order if any(m in r["means"] for _, r in rows)]
        if not metrics:
            continue
        header = ["method"] + [_HEAD[m] for m in metrics]
        table = [header] + [[name] + [_fmt(r["means"].get(m)) for m in metrics] for name, r in rows]
        widths = [max(len(str(row[i])) for row in table) for i in range(len(header))]
        lines += ["  ".join(str(c).ljust(w) for c, w in zip(row, widths)).rstrip() for row in table]
    margin = result.get("margin_db") or {}
    if margin:
        lines.append("margin over the nearest view: " + ", ".join(
            f"{_HEAD[m].rstrip('↑')} {_fmt(v)} dB" for m, v in margin.items()))
    for name, reason in result.get("unavailable", {}).items():
        lines.append(f"{name}: unavailable ({reason})")
    return "\n".join(lines)
