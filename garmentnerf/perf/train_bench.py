"""Seconds per NeRF training step of a run's recipe, per MLP precision, measured side by side
(what ``garmentnerf bench --run DIR --training`` prints and saves).

:func:`training_benchmark` builds one :class:`~garmentnerf.train.trainer.Trainer` per precision on
the run's scene, model config and composition, starting from the run's weights at the NeRF stage
(as ``train --init-weights`` does), in a temporary folder that is removed afterwards. The
trainers take turns: ``rounds`` rounds of ``steps`` steps each, so both see the machine in the
same state, and both draw the same views (same seed). A step's time is the interval between
consecutive step callbacks (render, losses, backward, optimiser); the first step of each round
and the one that ends it (it writes a checkpoint) are left out, and the median is reported.
"""

from __future__ import annotations

import dataclasses
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

__all__ = ["training_benchmark"]


def training_benchmark(run_dir, precisions=("float32", "bfloat16"), *, steps: int = 8, rounds: int = 3,
                       log=None) -> dict:
    """Median seconds per NeRF step of the run in ``run_dir`` for each of ``precisions``.

    Args:
        run_dir: a run folder (its ``run.json`` names the scene; its body appearance, if any, is
            composed with as in its training).
        precisions: :data:`~garmentnerf.train.settings.TRAINING_PRECISIONS` to compare (``auto``
            is resolved first, as a run would).
        steps: steps per round and precision (at least 3: the first and last of a round are not timed).
        rounds: rounds; the precisions alternate within each.
        log: called with one line per finished round (None: silent).
    Returns:
        ``{"run", "steps_timed", "machine", "precisions": [{"precision", "s_per_step",
        "s_per_step_all"}], "speedup_vs_first"}``: ``speedup_vs_first`` is the first
        precision's seconds per step over each one's.
    """
    import torch

    from garmentnerf.model.body_appearance import BODY_APPEARANCE_FILE
    from garmentnerf.model.config import ModelConfig
    from garmentnerf.train.run import MODEL_FILE, read_run_info
    from garmentnerf.train.settings import TrainConfig, training_precision
    from garmentnerf.train.trainer import Trainer

    if steps < 3 or rounds < 1:
        raise ValueError(f"steps must be >= 3 and rounds >= 1, got {steps} and {rounds}")
    run_dir = Path(run_dir)
    info = read_run_info(run_dir)
    if not info.get("scene"):
        raise ValueError(f"{run_dir}: the run names no scene to train on")
    scene = Path(info["scene"])
    scene = scene if scene.is_absolute() else (run_dir / scene).resolve()
    cfg = ModelConfig.from_dict(dict(info["model_config"]))
    appearance = run_dir / BODY_APPEARANCE_FILE
    resolved = [training_precision(p, "cpu") for p in precisions]
    intervals = {p: [] for p in resolved}
    with tempfile.TemporaryDirectory(prefix="garmentnerf-train-bench-") as tmp:
        trainers = {}
        try:
            for p in resolved:
                tc = TrainConfig(scene=scene, out=Path(tmp) / p, model_config=cfg.replace(iterations=steps * rounds),
                                 init_weights=run_dir / MODEL_FILE, precision=p, progress=False,
                                 body_appearance=appearance if appearance.is_file() else None,
                                 generator_iterations=int(info.get("generator_iterations", cfg.generator_iterations)),
                                 log_every=10 ** 9, image_every=0, ckpt_every=10 ** 9, keep_checkpoints=1)
                trainers[p] = Trainer(tc, log=lambda message: None)
            for r in range(rounds):
                for p, trainer in trainers.items():
                    stamps: list[float] = []
                    trainer.step_callback = lambda step, values, stamps=stamps: stamps.append(time.perf_counter())
                    trainer.tc = dataclasses.replace(trainer.tc, stop_after=trainer.step + steps)
                    trainer.train()
                    intervals[p] += list(np.diff(stamps)[:-1])  # neither the first step nor the checkpointed last
                if log is not None:
                    log(f"round {r + 1}/{rounds}: " + ", ".join(f"{p} {np.median(v):.3f} s/step"
                                                                for p, v in intervals.items()))
        finally:
            for trainer in trainers.values():
                trainer.close()
    rows = [{"precision": p, "s_per_step": float(np.median(v)), "s_per_step_all": [float(x) for x in v]}
            for p, v in intervals.items()]
    first = rows[0]["s_per_step"]
    return {"run": str(run_dir), "steps_timed": len(intervals[resolved[0]]),
            "machine": {"torch_threads": torch.get_num_threads(), "processor": platform.processor() or platform.machine(),
                        "amx_bf16": bool(torch.cpu.get_capabilities().get("amx_bf16", False))},
            "precisions": rows, "speedup_vs_first": {r["precision"]: first / r["s_per_step"] for r in rows}}
