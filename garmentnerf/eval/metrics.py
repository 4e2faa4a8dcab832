"""The paper's image and video metrics: PSNR, SSIM, tOF, and a JSON-friendly summary of them.

Conventions (what every number reported by this project means)
    Images
        ``(H, W, 3)`` RGB, float in [0, 1] (uint8 arrays are divided by 255), numpy or torch.
        Metrics are computed over the **full frame** of images that are already composited on a
        background; the project's background is **black** (``(0, 0, 0)``, see
        :mod:`garmentnerf.data.render_gt`, whose RGB is premultiplied by coverage, so it *is* the
        black composite). :func:`composite_premultiplied` gives the composite on another color.
        Prediction and ground truth must be on the same background. The background is recorded
        in :class:`MetricSummary` because full-frame numbers depend on it: a large black
        border inflates PSNR and SSIM.
    PSNR
        ``10 log10(data_range^2 / MSE)``, MSE over all pixels and channels in float64, data range
        1. Identical images give ``+inf`` per frame; means cap every frame at
        :data:`PSNR_CAP_DB` (100 dB, i.e. an RMS error of 1e-5, far below 8-bit quantisation)
        so one perfect frame cannot make a mean infinite.
    SSIM
        ``kornia.metrics.ssim`` with an 11-tap Gaussian window (sigma 1.5), ``padding="valid"``
        (no border padding: the map is 5 pixels smaller on every side), data range 1, ``eps=0``,
        in float64, averaged over pixels and channels. This equals scikit-image's
        ``structural_similarity(gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
        data_range=1, channel_axis=-1)`` to ~1e-7. The authors' code calls scikit-image on
        float images without ``data_range``, an implicit range of 2 that inflates SSIM: not
        copied. kornia's default ``eps=1e-12`` is *not* used because it biases flat regions: two
        identical black images would score 0.99998889 instead of 1.
    tOF (TecoGAN, Chu et al. 2020, their ``metrics.py``)
        See :func:`temporal_flow_error`: Farneback flow between consecutive grey uint8 frames of
        the ground truth and of the output, cropped to the centre, mean L2 norm of the
        difference, averaged over frame pairs after skipping 2 frames at each end.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Sequence

import cv2
import numpy as np
import torch

#: Per-frame PSNR above this (identical images give +inf) counts as this value in means.
PSNR_CAP_DB = 100.0

#: Frames skipped at each end of a sequence for tOF (TecoGAN's ``cutfr``).
TOF_SKIP_ENDS = 2

#: ``cv2.calcOpticalFlowFarneback`` parameters after ``(prev, next, None)``, as TecoGAN:
#: pyr_scale, levels, winsize, iterations, poly_n, poly_sigma, flags.
FARNEBACK_PARAMS = (0.5, 3, 15, 3, 5, 1.2, 0)

SSIM_WINDOW = 11


# ---------------------------------------------------------------------------------------------
# Image conversion
# ---------------------------------------------------------------------------------------------

def _as_float64_image(image, name: str) -> np.ndarray:
    """(H, W, C) float64 array from a numpy array or torch tensor; uint8 is divided by 255."""
    if isinstance(image, torch.Tensor):
        image = image.detach().cpu().numpy()
    array = np.asarray(image)
    if array.ndim != 3:
        raise ValueError(f"{name} must be an (H, W, C) image, got shape {array.shape}")
    if array.dtype == np.uint8:
        return array.astype(np.float64) / 255.0
    if not np.issubdtype(array.dtype, np.floating):
        raise TypeError(f"{name} must be float in [0, 1] or uint8, got dtype {array.dtype}")
    array = array.astype(np.float64)
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name} contains NaN or Inf")
    return array


def _image_pair(pred, target) -> tuple[np.ndarray, np.ndarray]:
    p = _as_float64_image(pred, "pred")
    t = _as_float64_image(target, "target")
    if p.shape != t.shape:
        raise ValueError(f"pred and target shapes differ: {p.shape} vs {t.shape}")
    return p, t


def composite_premultiplied(rgb, alpha, background=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Composite premultiplied color over a background: ``rgb + (1 - alpha) * background``.

    Args:
        rgb: (H, W, 3) premultiplied color in [0, 1] (the project's renders on black).
        alpha: (H, W) or (H, W, 1) coverage in [0, 1].
        background: 3 values in [0, 1].
    Returns:
        (H, W, 3) float64 image on ``background``.
    """
    rgb = _as_float64_image(rgb, "rgb")
    a = np.asarray(alpha.detach().cpu().numpy() if isinstance(alpha, torch.Tensor) else alpha, dtype=np.float64)
    if a.ndim == 2:
        a = a[..., None]
    if a.shape[:2] != rgb.shape[:2] or a.shape[2] != 1:
        raise ValueError(f"alpha shape {a.shape} does not match image {rgb.shape}")
    bg = np.asarray(background, dtype=np.float64).reshape(1, 1, -1)
    if bg.shape[-1] != rgb.shape[-1] or np.any(bg < 0) or np.any(bg > 1):
        raise ValueError(f"background must be {rgb.shape[-1]} values in [0, 1], got {background}")
    return rgb + (1.0 - a) * bg


# ---------------------------------------------------------------------------------------------
# PSNR, SSIM
# ---------------------------------------------------------------------------------------------

def psnr(pred, target, data_range: float = 1.0) -> float:
    """Peak signal-to-noise ratio of one image, dB.

    Args:
        pred, target: (H, W, C) images in [0, 1] (or uint8), composited on the same background.
        data_range: the peak value (1 for images in [0, 1]).
    Returns:
        ``10 log10(data_range^2 / mean((pred - target)^2))``; ``float('inf')`` for identical
        images (means cap it at :data:`PSNR_CAP_DB`, see :func:`mean_psnr`).
    """
    p, t = _image_pair(pred, target)
    mse = float(np.mean((p - t) ** 2))
    if mse == 0.0:
        return float("inf")
    return 10.0 * math.log10(data_range * data_range / mse)


def is_psnr_metric(name: str) -> bool:
    """Whether a metric name is a PSNR (``psnr``, ``fg_psnr``, ``garment_psnr``, ...): its mean
    caps each frame (:func:`mean_psnr`)."""
    return name == "psnr" or name.endswith("_psnr")


def mean_psnr(values: Iterable[float], cap_db: float = PSNR_CAP_DB) -> float:
    """Mean of per-frame PSNR values with each capped at ``cap_db`` (so +inf counts as the cap)."""
    v = np.asarray(list(values), dtype=np.float64)
    if v.size == 0:
        return float("nan")
    return float(np.mean(np.minimum(v, cap_db)))


def ssim(pred, target, data_range: float = 1.0) -> float:
    """Structural similarity of one image (see the module docstring for the exact definition).

    Args:
        pred, target: (H, W, C) images in [0, 1] (or uint8), H and W >= 11.
        data_range: the data range L (c1 = (0.01 L)^2, c2 = (0.03 L)^2).
    Returns:
        The mean of the valid-region SSIM map over pixels and channels, in [-1, 1].
    """
    import kornia.metrics  # imported here: ~0.3 s, and only the SSIM needs it

    p, t = _image_pair(pred, target)
    if min(p.shape[0], p.shape[1]) < SSIM_WINDOW:
        raise ValueError(f"SSIM needs images of at least {SSIM_WINDOW}x{SSIM_WINDOW}, got {p.shape[:2]}")
    pt = torch.from_numpy(np.ascontiguousarray(p.transpose(2, 0, 1)))[None]
    tt = torch.from_numpy(np.ascontiguousarray(t.transpose(2, 0, 1)))[None]
    with torch.no_grad():
        ssim_map = kornia.metrics.ssim(pt, tt, window_size=SSIM_WINDOW, max_val=float(data_range), eps=0.0,
                                       padding="valid")
    return float(ssim_map.mean())


# ---------------------------------------------------------------------------------------------
# Foreground: what users look at
# ---------------------------------------------------------------------------------------------

def masked_psnr(pred, target, region: np.ndarray, data_range: float = 1.0) -> float | None:
    """PSNR over the pixels of ``region`` only (every channel), dB.

    Args:
        pred, target: (H, W, C) images in [0, 1] (or uint8).
        region: (H, W) bool, the pixels that count.
    Returns:
        ``10 log10(data_range^2 / MSE)`` with the MSE over the region's pixels and channels;
        ``+inf`` for a region reproduced exactly; None for an empty region (no value, not a stand-in).
    """
    p, t = _image_pair(pred, target)
    region = np.asarray(region, dtype=bool)
    if region.shape != p.shape[:2]:
        raise ValueError(f"region {region.shape} does not match the images {p.shape[:2]}")
    if not region.any():
        return None
    mse = float(np.mean((p[region] - t[region]) ** 2))
    if mse == 0.0:
        return float("inf")
    return 10.0 * math.log10(data_range * data_range / mse)


def silhouette_iou(pred_region: np.ndarray, target_region: np.ndarray) -> float:
    """Intersection over union of two (H, W) bool silhouettes; 1 when both are empty."""
    a = np.asarray(pred_region, dtype=bool)
    b = np.asarray(target_region, dtype=bool)
    union = int(np.count_nonzero(a | b))
    return 1.0 if union == 0 else int(np.count_nonzero(a & b)) / union


def gradient_energy(image, region: np.ndarray) -> float:
    """Sum over ``region`` of the squared Sobel gradient magnitude of the image's luma.

    Args:
        image: (H, W, 3) image in [0, 1] (or uint8).
        region: (H, W) bool.
    Returns:
        ``sum(gx^2 + gy^2)`` over the region, with ``gx, gy`` the 3x3 Sobel derivatives
        (``cv2.Sobel``, reflected border) of ``0.299 R + 0.587 G + 0.114 B`` in float64.
    """
    img = _as_float64_image(image, "image")
    luma = img[..., :3] @ np.array([0.299, 0.587, 0.114])
    gx = cv2.Sobel(luma, cv2.CV_64F, 1, 0, ksize=3)
    gy = cv2.Sobel(luma, cv2.CV_64F, 0, 1, ksize=3)
    return float(np.sum((gx * gx + gy * gy)[np.asarray(region, dtype=bool)]))


def sharpness_ratio(pred, target, region: np.ndarray) -> float | None:
    """How much of the ground truth's detail the prediction keeps: :func:`gradient_energy` of
    ``pred`` over that of ``target`` in ``region`` (1 = as sharp, 0.5 = half the gradient energy:
    folds blurred away; above 1 = noisier or harder edges). None when the region (or the
    target's energy there) is empty."""
    reference = gradient_energy(target, region)
    if reference <= 0.0:
        return None
    return gradient_energy(pred, region) / reference


#: Rec. 709 luma weights of display RGB (what :func:`mean_luma` averages).
LUMA_WEIGHTS = (0.2126, 0.7152, 0.0722)


def mean_luma(image, region: np.ndarray) -> float | None:
    """Mean Rec. 709 luma of ``image`` ((H, W, 3) in [0, 1], or uint8) over ``region``; None when
    the region is empty."""
    region = np.asarray(region, dtype=bool)
    if not region.any():
        return None
    img = np.asarray(image)
    img = img.astype(np.float64) / 255.0 if img.dtype == np.uint8 else img.astype(np.float64)
    return float((img[region] @ np.asarray(LUMA_WEIGHTS)).mean())


def luma_correlation(pred, target, region: np.ndarray) -> float | None:
    """Pearson correlation of the Rec. 709 lumas of ``pred`` and ``target`` ((H, W, 3) in [0, 1], or uint8)
    over ``region``: do the prediction's bright and dark pixels (a fold's lit ridge, its shaded crease) lie
    where the truth's do? 1: they do; 0: no relation; a prediction of one brightness scores 0. None with
    fewer than 3 pixels or a truth of one brightness there (nothing to follow)."""
    region = np.asarray(region, dtype=bool)
    if int(region.sum()) < 3:
        return None
    pred, target = _image_pair(pred, target)
    p, t = pred[region] @ np.asarray(LUMA_WEIGHTS), target[region] @ np.asarray(LUMA_WEIGHTS)
    if t.std() <= 1e-12:
        return None
    return float(np.corrcoef(p, t)[0, 1]) if p.std() > 1e-12 else 0.0


def flat_psnr(target, region: np.ndarray, data_range: float = 1.0) -> float | None:
    """PSNR over ``region`` of ``target`` ((H, W, C)) against its own mean colour there: what a
    prediction scores that has the region's outline and mean colour exactly and nothing else (no
    shading). None for an empty region."""
    region = np.asarray(region, dtype=bool)
    if not region.any():
        return None
    img = _as_float64_image(target, "target")
    flat = np.broadcast_to(img[region].mean(axis=0), img.shape)
    return masked_psnr(flat, img, region, data_range)


def shading_agreement(pred_luma: Sequence[float], truth_luma: Sequence[float]) -> dict[str, float] | None:
    """How a prediction's brightness follows the truth's from view to view: the per-view mean lumas of
    both (e.g. :func:`mean_luma` inside the garment) give ``shading_contrast``, the standard deviation
    of the prediction's over the truth's (1: the lit and the shaded views as far apart as in the truth;
    0.5: half the contrast; 0: one brightness everywhere), and ``shading_correlation`` (Pearson).
    None with fewer than 3 views or a truth of one brightness (nothing to follow)."""
    p, t = np.asarray(pred_luma, np.float64), np.asarray(truth_luma, np.float64)
    if p.shape != t.shape or p.ndim != 1:
        raise ValueError(f"shading_agreement needs two equal 1-D sequences, got {p.shape} and {t.shape}")
    if len(t) < 3 or t.std() <= 1e-12:
        return None
    correlation = float(np.corrcoef(p, t)[0, 1]) if p.std() > 1e-12 else 0.0
    return {"shading_contrast": float(p.std() / t.std()), "shading_correlation": correlation}


def interior(region: np.ndarray, margin: int) -> np.ndarray:
    """(H, W) bool: the pixels of ``region`` at least ``margin`` pixels (chessboard distance)
    inside it (``cv2.erode`` with a ``(2 margin + 1)^2`` square; outside the image counts as
    outside the region)."""
    region = np.asarray(region, dtype=bool)
    if margin <= 0:
        return region
    kernel = np.ones((2 * margin + 1, 2 * margin + 1), np.uint8)
    eroded = cv2.erode(region.astype(np.uint8), kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0)
    return eroded.astype(bool)


# ---------------------------------------------------------------------------------------------
# tOF
# ---------------------------------------------------------------------------------------------

def to_grey_uint8(frame) -> np.ndarray:
    """(H, W) uint8 grey frame as TecoGAN reads it (an 8-bit RGB PNG, then RGB -> grey).

    Float RGB in [0, 1] is rounded to 8 bits (``rint(clip(x, 0, 1) * 255)``, as writing a PNG
    does), then converted with ``cv2.COLOR_RGB2GRAY`` (0.299 R + 0.587 G + 0.114 B). uint8 RGB
    is converted directly; (H, W) frames are taken as grey already.
    """
    if isinstance(frame, torch.Tensor):
        frame = frame.detach().cpu().numpy()
    a = np.asarray(frame)
    if a.dtype != np.uint8:
        if not np.issubdtype(a.dtype, np.floating):
            raise TypeError(f"frames must be float in [0, 1] or uint8, got dtype {a.dtype}")
        if not np.all(np.isfinite(a)):
            raise ValueError("frame contains NaN or Inf")
        a = np.rint(np.clip(a, 0.0, 1.0) * 255.0).astype(np.uint8)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if a.ndim == 2:
        return np.ascontiguousarray(a)
    if a.ndim == 3 and a.shape[2] == 3:
        return cv2.cvtColor(np.ascontiguousarray(a), cv2.COLOR_RGB2GRAY)
    raise ValueError(f"frames must be (H, W, 3), (H, W, 1) or (H, W), got shape {a.shape}")


def farneback_flow(prev_grey: np.ndarray, next_grey: np.ndarray) -> np.ndarray:
    """(H, W, 2) float32 Farneback flow from ``prev_grey`` to ``next_grey`` ((H, W) uint8)."""
    return cv2.calcOpticalFlowFarneback(prev_grey, next_grey, None, *FARNEBACK_PARAMS)


def tof_crop(height: int, width: int) -> tuple[int, int, int, int]:
    """The centre crop TecoGAN applies to flow fields: ``(y0, x0, h, w)``.

    Each side is the largest multiple of 32 that leaves at least 16 pixels of border in all
    (480 for 512, 224 for 256), centred (offset ``(size - crop) // 2``).
    """
    def side(n: int) -> int:
        s = (n // 32) * 32
        while s > n - 16:
            s -= 32
        return s

    h, w = side(height), side(width)
    if h <= 0 or w <= 0:
        raise ValueError(f"tOF needs frames of at least 48x48 pixels, got {height}x{width}")
    return (height - h) // 2, (width - w) // 2, h, w


@dataclass
class TOFResult:
    """tOF of one sequence.

    Attributes:
        pairs: (prev, next) frame indices of each evaluated pair, in order.
        values: per-pair tOF, same order (empty when the sequence is too short).
        mean: mean of ``values``; NaN when no pair was evaluated (see ``reason``).
        reason: why ``mean`` is NaN, else None.
        crop: (y0, x0, h, w) region of the flow fields that was compared.
    """

    pairs: list[tuple[int, int]]
    values: list[float]
    mean: float
    reason: str | None = None
    crop: tuple[int, int, int, int] | None = None


def temporal_flow_error(pred_frames: Sequence, gt_frames: Sequence, skip_ends: int = TOF_SKIP_ENDS) -> TOFResult:
    """tOF: how differently the output moves from the ground truth, in pixels (lower is better).

    Exactly TecoGAN's ``metrics.py`` (``cutfr = 2``): of T frames, frames ``skip_ends .. T-1-skip_ends``
    are used, and each pair ``(i - 1, i)`` with ``skip_ends < i < T - skip_ends`` is evaluated:

    1. both frames of output and of ground truth to grey uint8 (:func:`to_grey_uint8`);
    2. ``F_gt = farneback(gt[i-1], gt[i])``, ``F_out = farneback(out[i-1], out[i])`` on the full
       frames (:data:`FARNEBACK_PARAMS`);
    3. both flow fields cropped to :func:`tof_crop` (480x480 centre of a 512x512 frame);
    4. ``tOF_i = mean over pixels of |F_gt - F_out|_2``.

    The sequence tOF is the mean over pairs: T - 2 skip_ends - 1 pairs (a 60-frame sequence has
    55). Short sequences are not silently evaluated on fewer frames, which would make numbers
    incomparable: with fewer than ``2 skip_ends + 2`` frames (6 by default) the result has no
    pairs, ``mean`` NaN and a ``reason``; pass ``skip_ends=0`` explicitly to use every pair.

    Args:
        pred_frames, gt_frames: equally long sequences (a list, or an array with a leading time
            axis) of (H, W, 3) RGB frames in [0, 1] (or uint8), or (H, W) grey uint8 frames.
        skip_ends: frames ignored at each end (TecoGAN: 2).
    Returns:
        :class:`TOFResult` with per-pair values and their mean.
    """
    n = len(gt_frames)
    if len(pred_frames) != n:
        raise ValueError(f"pred has {len(pred_frames)} frames, ground truth {n}")
    if skip_ends < 0:
        raise ValueError(f"skip_ends must be >= 0, got {skip_ends}")
    first, last = skip_ends, n - 1 - skip_ends  # the frames used, inclusive
    if last - first < 1:
        return TOFResult([], [], float("nan"), reason=(
            f"tOF needs at least {2 * skip_ends + 2} frames ({skip_ends} skipped at each end, then one pair); "
            f"got {n}"))
    pairs, values = [], []
    crop = None
    prev_out = prev_gt = None
    for i in range(first, last + 1):
        out_g, gt_g = to_grey_uint8(pred_frames[i]), to_grey_uint8(gt_frames[i])
        if out_g.shape != gt_g.shape:
            raise ValueError(f"frame {i}: pred {out_g.shape} and ground truth {gt_g.shape} differ in size")
        if crop is None:
            crop = tof_crop(*gt_g.shape)
        if prev_out is not None:
            if out_g.shape != prev_out.shape:
                raise ValueError(f"frame {i} has size {out_g.shape}, frame {i - 1} {prev_out.shape}")
            y0, x0, h, w = crop
            f_gt = farneback_flow(prev_gt, gt_g)[y0:y0 + h, x0:x0 + w].astype(np.float64)
            f_out = farneback_flow(prev_out, out_g)[y0:y0 + h, x0:x0 + w].astype(np.float64)
            values.append(float(np.mean(np.sqrt(np.sum((f_gt - f_out) ** 2, axis=-1)))))
            pairs.append((i - 1, i))
        prev_out, prev_gt = out_g, gt_g
    return TOFResult(pairs, values, float(np.mean(values)), None, crop)


# ---------------------------------------------------------------------------------------------
# Summary
# ---------------------------------------------------------------------------------------------

def _encode_float(x):
    """JSON-safe float: finite floats as numbers, +inf / -inf / NaN as the strings "inf", "-inf", "nan"."""
    if isinstance(x, (float, np.floating)):
        x = float(x)
        if math.isfinite(x):
            return x
        return "nan" if math.isnan(x) else ("inf" if x > 0 else "-inf")
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, dict):
        return {k: _encode_float(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_encode_float(v) for v in x]
    return x


def _decode_float(x):
    if isinstance(x, str) and x in ("inf", "-inf", "nan"):
        return float(x)
    if isinstance(x, dict):
        return {k: _decode_float(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_decode_float(v) for v in x]
    return x


@dataclass
class MetricSummary:
    """Per-frame metric values of one sequence (one camera) and their means.

    Attributes:
        frames: one dict per evaluated frame, ``{"frame": index, "psnr": ..., "ssim": ..., ...}``;
            metric keys are the names used everywhere in reports (``psnr``, ``ssim``,
            ``stlpips_alex``, ``lpips_alex``, ...).
        tof: the :class:`TOFResult` of the sequence, if computed.
        unavailable: metric name -> reason it was not computed (e.g. LPIPS without backbone
            weights). A metric listed here has no values anywhere: never a stand-in.
        meta: free-form description of how the numbers were made (background, data range,
            PSNR cap, resolution, ...); written to JSON as is.

    JSON: strict JSON (no NaN/Infinity literals); non-finite floats are written as the strings
    ``"inf"``, ``"-inf"``, ``"nan"`` and read back as floats by :meth:`from_dict`.
    """

    frames: list[dict[str, float]] = field(default_factory=list)
    tof: TOFResult | None = None
    unavailable: dict[str, str] = field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)

    def add_frame(self, frame: int, **values: float) -> None:
        """Record the metrics of frame ``frame`` (e.g. ``add_frame(3, psnr=31.2, ssim=0.97)``)."""
        self.frames.append({"frame": int(frame), **{k: float(v) for k, v in values.items()}})

    def mark_unavailable(self, metric: str, reason: str) -> None:
        """Record that ``metric`` was not computed, and why."""
        self.unavailable[metric] = reason

    def metric_names(self) -> list[str]:
        """Per-frame metric names, in first-seen order."""
        names: list[str] = []
        for f in self.frames:
            names.extend(k for k in f if k != "frame" and k not in names)
        return names

    def values(self, metric: str) -> list[float]:
        """Per-frame values of ``metric`` (frames without it are left out)."""
        return [f[metric] for f in self.frames if metric in f]

    def means(self) -> dict[str, float]:
        """Mean of every per-frame metric over frames, plus ``tof`` (the mean over pairs).

        PSNR is averaged with each frame capped at ``meta["psnr_cap_db"]`` (default
        :data:`PSNR_CAP_DB`). NaN values (none are produced by this module) propagate.
        """
        cap = float(self.meta.get("psnr_cap_db", PSNR_CAP_DB))
        out: dict[str, float] = {}
        for name in self.metric_names():
            v = self.values(name)
            out[name] = mean_psnr(v, cap) if is_psnr_metric(name) else float(np.mean(v))
        if self.tof is not None:
            out["tof"] = self.tof.mean
        return out

    def to_dict(self) -> dict[str, Any]:
        """A strict-JSON-serialisable dict (see the class docstring for non-finite values)."""
        d: dict[str, Any] = {
            "means": self.means(),
            "frames": self.frames,
            "unavailable": self.unavailable,
            "meta": {"psnr_cap_db": PSNR_CAP_DB, **self.meta},
        }
        if self.tof is not None:
            d["tof"] = {"mean": self.tof.mean, "pairs": [list(p) for p in self.tof.pairs],
                        "values": self.tof.values, "reason": self.tof.reason,
                        "crop_yxhw": list(self.tof.crop) if self.tof.crop else None}
        return _encode_float(d)

    def to_json(self, path: str | Path | None = None, indent: int = 1) -> str:
        """JSON text of :meth:`to_dict`; also written to ``path`` when given."""
        text = json.dumps(self.to_dict(), indent=indent, allow_nan=False)
        if path is not None:
            Path(path).write_text(text + "\n")
        return text

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "MetricSummary":
        """Inverse of :meth:`to_dict` (the stored means are recomputed, not read)."""
        d = _decode_float(d)
        tof = None
        if d.get("tof") is not None:
            t = d["tof"]
            tof = TOFResult([tuple(p) for p in t["pairs"]], list(t["values"]), t["mean"], t.get("reason"),
                            tuple(t["crop_yxhw"]) if t.get("crop_yxhw") else None)
        return cls(frames=list(d.get("frames", [])), tof=tof, unavailable=dict(d.get("unavailable", {})),
                   meta=dict(d.get("meta", {})))


def evaluate_sequence(pred_frames: Sequence, gt_frames: Sequence, *, frame_indices: Sequence[int] | None = None,
                      background=(0.0, 0.0, 0.0), perceptual: Sequence = (), tof: bool = True,
                      unavailable: dict[str, str] | None = None) -> MetricSummary:
    """All metrics of one rendered sequence against its ground truth.

    Args:
        pred_frames, gt_frames: equally long sequences of (H, W, 3) images in [0, 1] composited on
            ``background`` (the caller composites; the value is only recorded).
        frame_indices: the frame number of each image (default 0..T-1).
        background: RGB the images were composited on, recorded in ``meta``.
        perceptual: modules from :mod:`garmentnerf.model.perceptual` (``STLPIPS``, ``LPIPS``); each
            is reported under its ``metric_name``.
        tof: compute tOF (needs at least 6 frames, else it is listed as unavailable).
        unavailable: metric name -> reason, for metrics the caller could not set up (e.g. the
            reason from :func:`~garmentnerf.model.perceptual.lpips_available`).
    Returns:
        :class:`MetricSummary`.
    """
    n = len(gt_frames)
    if len(pred_frames) != n:
        raise ValueError(f"pred has {len(pred_frames)} frames, ground truth {n}")
    indices = list(range(n)) if frame_indices is None else [int(i) for i in frame_indices]
    if len(indices) != n:
        raise ValueError(f"{len(indices)} frame indices for {n} frames")
    summary = MetricSummary(meta={"background": [float(c) for c in background], "data_range": 1.0,
                                  "psnr_cap_db": PSNR_CAP_DB, "full_frame": True, "num_frames": n})
    for name, reason in (unavailable or {}).items():
        summary.mark_unavailable(name, reason)
    if n:
        summary.meta["resolution_hw"] = list(_as_float64_image(gt_frames[0], "target").shape[:2])
    for k in range(n):
        values = {"psnr": psnr(pred_frames[k], gt_frames[k]), "ssim": ssim(pred_frames[k], gt_frames[k])}
        for module in perceptual:
            values[module.metric_name] = module.distance(pred_frames[k], gt_frames[k])
        summary.add_frame(indices[k], **values)
    if tof:
        result = temporal_flow_error(pred_frames, gt_frames)
        if result.reason is not None:
            summary.mark_unavailable("tof", result.reason)
        else:
            result.pairs = [(indices[a], indices[b]) for a, b in result.pairs]
            summary.tof = result
    return summary
