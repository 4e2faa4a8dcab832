"""How fast a run's recipe learns its scene's garments from geometry alone: the sequence occupancy probe
(what ``garmentnerf bench --run DIR --occupancy`` prints and saves).

:func:`occupancy_probe` trains the run's model config from scratch (G_img taken from the run, as
``train --init-generator`` does) with the geometry warm-up alone (``ModelConfig.geometry_iterations``:
the occupancy term of :mod:`garmentnerf.model.occupancy`, nothing rendered) over the run's training
frames, in a temporary folder, and every ``eval_every`` steps scores the density against the
simulated garment on fresh points of a few training frames and of the scene's held-out motions:

- **IoU**: of ``occupancy > 0.5`` with the labels (inside the sheet around the cloth, or the body);
- **far recall**: the share of the sheet lying more than ``body_prior_width`` from the skin (a hem
  swung out) that the density holds.

Why (``docs/quality.md``, "Telling the field where the cloth is"): a sequence model learns the
average garment first and a frame's own shape only after many visits of each frame; this probe shows
that in minutes, where an image-trained run and its evaluation take an hour. It is the sequence-level
twin of the one-frame probe in ``shared/tools/occupancy_probe.py``.
"""

from __future__ import annotations

import platform
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from garmentnerf.model.occupancy import occupancy_iou
from garmentnerf.perf.train_bench import run_recipe
from garmentnerf.train.run import MODEL_FILE
from garmentnerf.train.settings import TrainConfig
from garmentnerf.train.trainer import Trainer

__all__ = ["occupancy_probe", "far_recall", "EVAL_POINTS"]

#: Points per evaluated frame (half around the cloth, half in the sampling box), drawn once per frame.
EVAL_POINTS = 16_000


def far_recall(sigma: torch.Tensor, garment_distance: torch.Tensor, body_height: torch.Tensor,
               half_thickness: float, far: float, step: float) -> float | None:
    """The share of the points within ``half_thickness`` of the garment and more than ``far`` from the
    skin (all (N,)) where ``1 - exp(-sigma * step) > 0.5``; None when there are none."""
    cloth = (garment_distance <= half_thickness) & (body_height > far)
    if not bool(cloth.any()):
        return None
    alpha = 1.0 - torch.exp(-sigma.detach().float()[cloth] * float(step))
    return float((alpha > 0.5).float().mean())


def _spread(frames: list[int], count: int) -> list[int]:
    """``count`` frames spread evenly over ``frames`` (all of them when fewer)."""
    if len(frames) <= count:
        return list(frames)
    return [frames[int(i)] for i in np.linspace(0, len(frames) - 1, count).round()]


def occupancy_probe(run_dir, *, steps: int = 600, eval_every: int = 100, frames=None, train_frames: int = 6,
                    heldout_frames: int = 3, seed: int = 0, log=None) -> dict:
    """Train the run's recipe on the occupancy term alone and score its density as it learns.

    Args:
        run_dir: a run folder (its scene and model config; its G_img is reused).
        steps: probe steps (geometry steps of the recipe, one frame each).
        eval_every: steps between evaluations (also at 0 and at the end).
        frames: training frames to use (None: the run's scene's, all of them).
        train_frames, heldout_frames: frames scored, spread over the training frames and over each
            held-out-motion (``unseen_motion``) sequence of the scene.
        seed: the probe's training seed (the scored points have their own, fixed).
        log: called with one line per evaluation (None: silent).
    Returns:
        ``{"run", "steps", "machine", "eval_frames", "heldout_frames", "rows": [{"step", "train_iou",
        "train_far_recall", "heldout_iou", "heldout_far_recall", "s_per_step"}]}``: means over the scored
        frames (far recall over the frames that have far cloth; None when none has), ``s_per_step`` the
        mean wall seconds of the probe's training steps so far (evaluations excluded).
    """
    if steps < 1 or eval_every < 1:
        raise ValueError(f"steps and eval_every must be >= 1, got {steps} and {eval_every}")
    run_dir = Path(run_dir)
    scene_dir, cfg, _, _ = run_recipe(run_dir)
    cfg = cfg.replace(iterations=steps, geometry_iterations=steps)
    with tempfile.TemporaryDirectory(prefix="garmentnerf-occupancy-probe-") as tmp:
        tc = TrainConfig(scene=scene_dir, out=Path(tmp) / "run", model_config=cfg, generator_iterations=0,
                         init_generator=run_dir / MODEL_FILE, perceptual="none", progress=False, seed=seed,
                         frames=None if frames is None else tuple(int(f) for f in frames),
                         log_every=10 ** 9, image_every=0, ckpt_every=10 ** 9, keep_checkpoints=1)
        with Trainer(tc, log=lambda message: None) as trainer:
            scored = [("train", s, f) for s, f in _spread(list(trainer.frames_list), train_frames)]
            scene = trainer.scene
            heldout = [("heldout", s, f) for s in scene.sequence_names("unseen_motion")
                       for f in _spread(list(range(scene.num_frames(s))), heldout_frames)]
            points = {}

            def score() -> dict:
                model = trainer.model
                model.eval()
                out = {"train": ([], []), "heldout": ([], [])}
                with torch.no_grad():
                    for kind, seq, f in scored + heldout:
                        feats = model.prepare_frame(trainer._nerf_inputs(seq, f), code=trainer.code_index(seq, f))
                        if (seq, f) not in points:  # drawn once: the frame's body and garment are fixed
                            points[seq, f] = trainer.occupancy_targets(seq, f, feats, EVAL_POINTS,
                                                                       torch.Generator().manual_seed(1000 + f))
                        pts, body, labels = points[seq, f]
                        height = body.signed_distance.cpu()
                        sigma = model.evaluate_samples(feats, pts.positions, points=body)[0].cpu()
                        out[kind][0].append(occupancy_iou(sigma, labels, cfg.occupancy_step))
                        out[kind][1].append(far_recall(sigma, pts.garment_distance, height,
                                                       cfg.occupancy_half_thickness, cfg.body_prior_width,
                                                       cfg.occupancy_step))
                model.train()

                def mean(values):
                    values = [v for v in values if v is not None]
                    return float(np.mean(values)) if values else None

                return {"train_iou": mean(out["train"][0]), "train_far_recall": mean(out["train"][1]),
                        "heldout_iou": mean(out["heldout"][0]), "heldout_far_recall": mean(out["heldout"][1])}

            rows = []
            train_seconds = [0.0]
            t_step = [0.0]

            def evaluate(step: int) -> None:
                row = {"step": step, **score(), "s_per_step": train_seconds[0] / step if step else None}
                rows.append(row)
                if log is not None:
                    log(_format(row))

            def on_step(step: int, values: dict) -> None:
                train_seconds[0] += time.perf_counter() - t_step[0]
                if step % eval_every == 0 or step == steps:
                    evaluate(step)
                t_step[0] = time.perf_counter()

            evaluate(0)
            trainer.step_callback = on_step
            t_step[0] = time.perf_counter()
            trainer.train()
    return {"run": str(run_dir), "steps": steps, "eval_every": eval_every,
            "machine": {"processor": platform.processor() or platform.machine(),
                        "torch_threads": torch.get_num_threads()},
            "eval_frames": [[s, f] for _, s, f in scored], "heldout_frames": [[s, f] for _, s, f in heldout],
            "rows": rows}


def _format(row: dict) -> str:
    def f(v):
        return "  n/a" if v is None else f"{v:5.3f}"

    rate = "" if row["s_per_step"] is None else f"   {row['s_per_step']:.2f} s/step"
    return (f"step {row['step']:6d}   training frames IoU {f(row['train_iou'])} far {f(row['train_far_recall'])}"
            f"   held-out motion IoU {f(row['heldout_iou'])} far {f(row['heldout_far_recall'])}{rate}")
