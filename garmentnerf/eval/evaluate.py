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

How an image is made (identical to training, the viewer and ``garmentnerf render``)
    Prediction: :class:`~garmentnerf.render.session.RenderSession` (the one render path) renders
    the scene camera resized to the model's image resolution (longer side
    ``cfg.image_resolution``, the other side proportional) with a render preset (default
    ``reference``: the paper's sampling at ``scale=1``, exactly the rays the model was trained
    with; another preset renders at its resolution scale and is resampled to that size) -- and :meth:`NeuralFrame.composite` composes the decomposed maps
    with the run's learned palette over ``cfg.background``.
    Ground truth: the scene's cached 8-bit image (:class:`~garmentnerf.data.scene.SceneImages`)
    area-downsampled to the same size and composited over ``cfg.background`` with the
    area-downsampled foreground coverage -- the trainer's targets
    (:class:`~garmentnerf.train.frames.SceneFrames`), byte for byte.

Metrics (conventions in :mod:`garmentnerf.eval.metrics`)
    Per frame: ``psnr``, ``ssim``, ``stlpips_alex`` (shift-tolerant LPIPS, its own metric) and
    ``lpips_alex`` (the paper's LPIPS) when the user supplied the AlexNet backbone
    (``$GARMENTNERF_LPIPS_ALEXNET``), else listed in ``unavailable`` with the reason. Per
    (sequence, camera): tOF over the consecutive evaluated frames (TecoGAN: at least 6 frames,
    2 skipped at each end; listed in ``unavailable`` with the reason when no camera has enough,
    or when the chosen frames are not consecutive). Means: PSNR, SSIM and the perceptual
    distances over every evaluated image (PSNR capped per frame at 100 dB), tOF over every
    evaluated frame pair of every camera.

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

    {"format": "garmentnerf-eval", "version": 1, "method": "model",
     "run": "...", "step": N, "scene": "...", "split": "unseen_view",
     "sequences": {"train": [frames...]}, "cameras": [...], "subsampled": false,
     "selection": "how frames/cameras were chosen", "resolution_wh": [W, H],
     "background": [r, g, b], "psnr_cap_db": 100.0, "palette": [[r, g, b], ...],
     "means": {"psnr": .., "ssim": .., "stlpips_alex": .., "tof": ..},
     "counts": {"images": .., "tof_pairs": ..},
     "unavailable": {"lpips_alex": "reason", ...},
     "per_frame": [{"sequence", "camera", "frame", "psnr", "ssim", "stlpips_alex"}, ...],
     "per_camera": [{"sequence", "camera", "means", "tof": {...}}, ...],
     "seconds": ..,
     "baseline": {... the same keys, "method": "nearest_view", "nearest_camera": {cam: train cam}}}
"""

from __future__ import annotations

import functools
import math
import sys
import time
from collections import OrderedDict
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from garmentnerf.eval.metrics import (PSNR_CAP_DB, MetricSummary, _encode_float, mean_psnr, psnr, ssim,
                                      temporal_flow_error, to_grey_uint8)

__all__ = ["SPLITS", "DEFAULT_LIMITS", "EVAL_FORMAT", "evaluate_run", "nearest_camera", "select_views",
           "eval_size", "parse_frame_range", "perceptual_metrics", "format_result_table", "BaselineNotDefined"]

EVAL_FORMAT = "garmentnerf-eval"
EVAL_VERSION = 1

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

def parse_frame_range(text: str | None) -> slice | None:
    """``"A:B"`` (B exclusive), ``"A:"``, ``":B"`` or ``"N"`` -> a slice (None for None/empty)."""
    if text is None or not str(text).strip():
        return None
    parts = [p.strip() for p in str(text).split(":")]
    try:
        nums = [int(p) if p else None for p in parts]
    except ValueError:
        raise ValueError(f"frames must look like A:B, A:, :B or N (integers), got '{text}'") from None
    if len(nums) == 1:
        if nums[0] is None or nums[0] < 0:
            raise ValueError(f"frames must look like A:B, A:, :B or N, got '{text}'")
        return slice(nums[0], nums[0] + 1)
    if len(nums) != 2:
        raise ValueError(f"frames must look like A:B, A:, :B or N, got '{text}'")
    if any(n is not None and n < 0 for n in nums):
        raise ValueError(f"frames must be >= 0, got '{text}'")
    return slice(nums[0], nums[1])


def _frames_of(spec, num_frames: int, sequence: str) -> list[int]:
    """Frame list of one sequence from None / a slice / "A:B" / a sequence of ints."""
    if isinstance(spec, str):
        spec = parse_frame_range(spec)
    if spec is None:
        return list(range(num_frames))
    if isinstance(spec, slice):
        if spec.step not in (None, 1):
            raise ValueError("frames: only contiguous ranges (step 1) are supported")
        a = 0 if spec.start is None else int(spec.start)
        b = num_frames if spec.stop is None else int(spec.stop)
        if not (0 <= a < b <= num_frames):
            raise ValueError(f"frames {a}:{b} are out of range for sequence '{sequence}' "
                             f"({num_frames} frames: 0..{num_frames - 1})")
        return list(range(a, b))
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


def _run_train_cameras(run, scene) -> list[str]:
    """The cameras the run was trained on (``run.json`` ``train.cameras``), else the scene's train split."""
    recorded = ((getattr(run, "info", None) or {}).get("train") or {}).get("cameras")
    names = set(scene.camera_names())
    if recorded:
        cams = [c for c in recorded if c in names]
        if cams:
            return cams
    return scene.camera_names("train")


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
    train_cams = _run_train_cameras(run, scene)
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
        cams = [c.strip() for c in cameras.split(",")] if isinstance(cameras, str) else [str(c) for c in cameras]
        cams = [c for c in cams if c]
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


def eval_size(config, camera) -> tuple[int, int]:
    """(w, h) of the evaluation images: longer side ``config.image_resolution``, aspect kept."""
    R = int(config.image_resolution)
    W, H = int(camera.width), int(camera.height)
    s = R / max(W, H)
    return max(1, round(W * s)), max(1, round(H * s))


# ---------------------------------------------------------------------------------------------
# Metrics set-up
# ---------------------------------------------------------------------------------------------

@functools.lru_cache(maxsize=4)
def _stlpips_module(variant: str):
    from garmentnerf.eval.perceptual import STLPIPS

    return STLPIPS(variant)


def perceptual_metrics(lpips_backbone: str | None = None) -> tuple[list, dict[str, str]]:
    """(modules, unavailable): ``stlpips_alex`` when stlpips-pytorch is installed and
    ``lpips_alex`` when the AlexNet backbone is supplied; each missing one with its reason."""
    from garmentnerf.eval.perceptual import LPIPS, lpips_available, stlpips_available

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

class _GroundTruth:
    """Ground-truth images at the evaluation size, composited as the trainer's targets."""

    def __init__(self, scene, ctx, body, background, cache_images: int = 64):
        from garmentnerf.data.render_gt import GroundTruthRenderer
        from garmentnerf.data.scene import SceneImages

        self.renderer = GroundTruthRenderer(ctx)
        self.images = SceneImages(scene, renderer=self.renderer, body_model=body)
        self.background = tuple(float(c) for c in background)
        self._cache: OrderedDict[tuple, np.ndarray] = OrderedDict()
        self.cache_images = cache_images

    def image(self, sequence: str, camera: str, frame: int, size: tuple[int, int]) -> np.ndarray:
        """(h, w, 3) float32 in [0, 1] over the background (see the module docstring)."""
        key = (sequence, camera, int(frame), tuple(size))
        hit = self._cache.get(key)
        if hit is not None:
            self._cache.move_to_end(key)
            return hit
        import torch

        from garmentnerf.train.frames import area_resize

        rgb, labels = self.images.image(sequence, camera, frame)
        image = area_resize(rgb, size)
        mask = area_resize((labels != 0).astype(np.float32), size)
        bg = torch.tensor(self.background, dtype=torch.float32).view(3, 1, 1)
        if bool((bg != 0).any()):
            image = image + (1.0 - mask) * bg
        out = image.clamp(0.0, 1.0).permute(1, 2, 0).contiguous().numpy()
        self._cache[key] = out
        while len(self._cache) > self.cache_images:
            self._cache.popitem(last=False)
        return out

    def close(self) -> None:
        self.images.close()
        self.renderer.release()


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

    def add(self, sequence: str, camera: str, frame: int, pred: np.ndarray, gt: np.ndarray) -> dict:
        values = {"psnr": psnr(pred, gt), "ssim": ssim(pred, gt)}
        for m in self.perceptual:
            values[m.metric_name] = m.distance(pred, gt)
        key = (sequence, camera)
        summary = self.summaries.get(key)
        if summary is None:
            summary = self.summaries[key] = MetricSummary()
            self._greys[key] = ([], [])
        summary.add_frame(frame, **values)
        preds, gts = self._greys[key]
        preds.append(to_grey_uint8(pred))
        gts.append(to_grey_uint8(gt))
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
            means[name] = mean_psnr(v, PSNR_CAP_DB) if name == "psnr" else float(np.mean(v))
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
                 lpips_backbone: str | None = None, tof: bool = True, preset: str = "reference") -> dict:
    """Render and score a run on one split (see the module docstring for every convention).

    Args:
        run: a :class:`~garmentnerf.train.run.LoadedRun` or a run folder.
        split: ``seen``, ``unseen_view`` or ``unseen_motion``.
        frames: None (the split's default), ``"A:B"``, a ``slice`` or a list of frame indices,
            applied to every sequence of the split.
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
        preset: the render preset (:data:`~garmentnerf.perf.presets.RENDER_PRESETS`; default
            ``reference``, the paper's sampling); the image is rendered at the preset's
            resolution scale of the evaluation size.
    Returns:
        A strict-JSON-serialisable dict (layout in the module docstring).
    Raises:
        ValueError: unknown split, run without a scene, baseline on another split, bad selection.
    """
    from garmentnerf.perf.presets import get_render_preset

    t_start = time.perf_counter()
    render_preset = get_render_preset(preset)
    if split not in SPLITS:
        raise ValueError(f"unknown split '{split}' (known: {', '.join(SPLITS)})")
    if baseline and split != "unseen_view":
        raise BaselineNotDefined(f"the nearest-view baseline is defined for split 'unseen_view' only (for 'seen' the "
                                 f"nearest training view is the view itself; for 'unseen_motion' no training "
                                 f"image of the frame exists), not '{split}'")
    if not model and not baseline:
        raise ValueError("nothing to evaluate: model=False and baseline=False")
    if isinstance(run, (str, Path)):
        from garmentnerf.train.run import load_run

        run = load_run(run, device=device, scene=scene)
    if run.scene is None:
        where = (run.info or {}).get("scene")
        raise ValueError(f"{run.root}: the run's scene folder ({where or 'not recorded'}) is missing; "
                         f"pass the scene explicitly (--scene DIR)")
    scene_obj = run.scene
    cfg = run.config
    sel = select_views(run, scene_obj, split, frames, cameras)
    background = tuple(float(c) for c in cfg.background)
    perceptual, unavailable = perceptual_metrics(lpips_backbone)
    nearest = {}
    if baseline:
        for c in sel["cameras"]:
            name, angle = nearest_camera(scene_obj, c, sel["train_cameras"])
            nearest[c] = {"camera": name, "angle_deg": angle}

    own_ctx = None
    if gl_context is None:
        from garmentnerf.gl.context import create_context

        gl_context = own_ctx = create_context(headless=True)
    session = None
    gt = None
    bar = None
    scores = _Scores(perceptual) if model else None
    base_scores = _Scores(perceptual) if baseline else None
    try:
        gt = _GroundTruth(scene_obj, gl_context, run.model.body, background)
        total = sum(len(f) for f in sel["sequences"].values()) * len(sel["cameras"])
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=total, desc=f"eval {split}", unit="view", file=sys.stderr, dynamic_ncols=True)
        if model:
            from garmentnerf.render.session import RenderSession

            session = RenderSession(run, gl_context, motion=next(iter(sel["sequences"])))
        for seq, frame_list in sel["sequences"].items():
            if session is not None and session.sequence != seq:
                session.set_motion(seq)
            for frame in frame_list:  # frames outer: the per-frame features are computed once
                for cam in sel["cameras"]:
                    camera = scene_obj.camera(cam).camera
                    size = eval_size(cfg, camera)
                    target = gt.image(seq, cam, frame, size)
                    if scores is not None:
                        nf = session.render(frame, camera.resized(*size), preset=render_preset,
                                            scale=render_preset.resolution_scale)
                        pred = nf.composite(None, background)
                        scores.add(seq, cam, frame, pred, target)
                    if base_scores is not None:
                        near = nearest[cam]["camera"]
                        near_size = eval_size(cfg, scene_obj.camera(near).camera)
                        if near_size != size:
                            raise ValueError(f"nearest-view baseline: camera '{near}' has another image size "
                                             f"than '{cam}'")
                        base_scores.add(seq, cam, frame, gt.image(seq, near, frame, size), target)
                    if bar is not None:
                        bar.update(1)
    finally:
        if bar is not None:
            bar.close()
        if session is not None:
            session.close()
        if gt is not None:
            gt.close()
        if own_ctx is not None:
            own_ctx.release()

    consecutive = {s: _consecutive(f) for s, f in sel["sequences"].items()}
    first_cam = scene_obj.camera(sel["cameras"][0]).camera
    common = {
        "format": EVAL_FORMAT, "version": EVAL_VERSION,
        "run": str(run.root), "step": int(run.step), "scene": str(scene_obj.root), "split": split, "preset": render_preset.name,
        "sequences": {s: list(f) for s, f in sel["sequences"].items()}, "cameras": list(sel["cameras"]),
        "train_cameras": list(sel["train_cameras"]), "subsampled": bool(sel["subsampled"]),
        "selection": sel["selection"], "resolution_wh": list(eval_size(cfg, first_cam)),
        "background": list(background), "data_range": 1.0, "psnr_cap_db": PSNR_CAP_DB,
    }

    def result_of(s: _Scores, method: str) -> dict:
        r = dict(common)
        r["method"] = method
        part = s.finish(consecutive, tof)
        r.update({"means": part["means"], "counts": part["counts"],
                  "unavailable": {**unavailable, **part["unavailable"]},
                  "per_frame": part["per_frame"], "per_camera": part["per_camera"]})
        return r

    out = result_of(scores, "model") if scores is not None else None
    if out is not None:
        out["palette"] = run.palette().cpu().tolist()
        out["model_config"] = {k: v for k, v in cfg.to_dict().items()
                               if k in ("image_resolution", "history", "use_detail_feature",
                                        "use_dynamic_feature", "iterations")}
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
    out["seconds"] = time.perf_counter() - t_start
    return _encode_float(out)


# ---------------------------------------------------------------------------------------------
# Text output
# ---------------------------------------------------------------------------------------------

_HEAD = {"psnr": "PSNR↑", "ssim": "SSIM↑", "lpips_alex": "LPIPS↓", "stlpips_alex": "ST-LPIPS↓", "tof": "tOF↓"}


def _fmt(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, str):
        return v
    if not math.isfinite(v):
        return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf")
    return f"{v:.3f}"


def format_result_table(result: dict) -> str:
    """A small plain-text table of an :func:`evaluate_run` result (model and baseline rows)."""
    rows = []
    if result.get("method"):
        rows.append((result["method"], result))
    if result.get("baseline"):
        rows.append((result["baseline"]["method"], result["baseline"]))
    metrics = [m for m in METRIC_ORDER if any(m in r["means"] for _, r in rows)]
    header = ["method"] + [_HEAD[m] for m in metrics]
    table = [header] + [[name] + [_fmt(r["means"].get(m)) for m in metrics] for name, r in rows]
    widths = [max(len(str(row[i])) for row in table) for i in range(len(header))]
    lines = ["  ".join(str(c).ljust(w) for c, w in zip(row, widths)).rstrip() for row in table]
    frames = sum(len(f) for f in result["sequences"].values())
    lines.insert(0, f"split {result['split']}: {len(result['cameras'])} camera(s) x {frames} frame(s) at "
                    f"{result['resolution_wh'][0]}x{result['resolution_wh'][1]}, step {result['step']}"
                    + (" (subsampled)" if result.get("subsampled") else ""))
    for name, reason in result.get("unavailable", {}).items():
        lines.append(f"{name}: unavailable ({reason})")
    return "\n".join(lines)
