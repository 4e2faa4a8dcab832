"""Seconds per NeRF training step of a run's recipe, per MLP precision, measured side by side,
whole and by stage (what ``garmentnerf bench --run DIR --training`` prints and saves).

:func:`training_benchmark` builds one :class:`~garmentnerf.train.trainer.Trainer` per precision on
the run's scene, model config and composition, starting from the run's weights at the NeRF stage
(as ``train --init-weights`` does), in a temporary folder that is removed afterwards. The
trainers take turns: ``rounds`` rounds of ``steps`` steps each, so both see the machine in the
same state, and both draw the same views (same seed). A step's time is the interval between
consecutive step callbacks (render, losses, backward, optimiser); the first step of each round
and the one that ends it (it writes a checkpoint) are left out, and the median is reported.

Before each round, each trainer prepares the frames its steps will draw (:meth:`Trainer.warm_frames
<garmentnerf.train.trainer.Trainer.warm_frames>`): a step is timed as a long run pays it once it has
met each frame, with the frame's inputs (info maps, reference passes, G_img's images) and body
geometry in the trainer's caches, and a frozen encoder's output with the geometry. ``cold=True``
times the steps with all of that built in them instead (a run's first visit to each frame).

Stages (:data:`STAGES`, seconds per step, the median of each over the timed steps)
    ``surface``, ``reference_images``, ``encoders``: :meth:`prepare_frame
    <garmentnerf.model.pipeline.GarmentAnimationNeRF.prepare_frame>`'s own timings (body geometry;
    G_img; E and G_en); ``rays`` ... ``decoder``: the render's
    (:data:`~garmentnerf.model.pipeline.RENDER_STAGES`); ``body_layer``: the body rasterised and
    composed under the garment (runs with a body appearance only); ``perceptual``: the perceptual
    loss's forward; ``forward_other``: the rest of the forward
    (data, other loss terms, palette composition); ``perceptual_backward``: from the gradient reaching
    the perceptual loss's output to its input's (module backward hooks); ``backward_other``: the rest of
    ``backward()``;
    ``optimizer``: the rest of the step (gradient clipping, Adam, bookkeeping). They add up to the
    step. The trainer is instrumented from outside (wrapped methods, module hooks): no timing
    code in the training loop.
"""

from __future__ import annotations

import dataclasses
import platform
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from garmentnerf.model.body_appearance import BODY_APPEARANCE_FILE
from garmentnerf.model.config import ModelConfig
from garmentnerf.model.perceptual import STLPIPS
from garmentnerf.runs import MODEL_FILE, read_run_info, recorded_scene_path
from garmentnerf.train.settings import TrainConfig, training_precision
from garmentnerf.train.trainer import Trainer

__all__ = ["training_benchmark", "training_inputs", "STAGES"]

#: The stages of a NeRF step timed by :func:`training_benchmark`, in step order.
STAGES = ("surface", "reference_images", "encoders", "rays", "projection", "features", "mlp", "compositing",
          "decoder", "body_layer", "perceptual", "forward_other", "perceptual_backward",
          "backward_other", "optimizer")
#: :class:`~garmentnerf.model.pipeline.RenderOutput` timings (ms) that a step pays.
_RENDER_TIMINGS = ("surface", "reference_images", "encoders", "rays", "projection", "features", "mlp",
                   "compositing", "decoder")


class _StageClock:
    """Times the stages of one trainer's NeRF steps (see the module docstring): wraps the trainer's
    ``_backward_batch``, ``_nerf_step``, ``_with_body`` and its model's ``render`` on the
    instances, and hooks the perceptual module. :meth:`lap` (called at each step's end) returns the
    step's stage seconds and starts the next step."""

    def __init__(self, trainer):
        self.current: dict[str, float] = {}
        self._t_step = time.perf_counter()
        self._t_perceptual = 0.0
        self._batch_s = self._forward_s = 0.0
        self._wrap(trainer, "_backward_batch", "backward_batch")
        self._wrap(trainer, "_nerf_step", "nerf_step")
        self._wrap(trainer, "_with_body", "body_layer")
        render = trainer.model.render

        def timed_render(feats, *args, **kwargs):
            out = render(feats, *args, **kwargs)
            for k in _RENDER_TIMINGS:
                self._add(k, out.timings.get(k, 0.0) / 1e3)
            return out

        trainer.model.render = timed_render
        if trainer.perceptual is not None:
            module = trainer.perceptual
            module.register_forward_pre_hook(lambda m, args: self._start())
            module.register_forward_hook(lambda m, args, out: self._stop("perceptual"))
            module.register_full_backward_pre_hook(lambda m, grad: self._start())
            module.register_full_backward_hook(lambda m, grad_in, grad_out: self._stop("perceptual_backward"))

    def _add(self, stage: str, seconds: float) -> None:
        self.current[stage] = self.current.get(stage, 0.0) + seconds

    def _start(self) -> None:
        self._t_perceptual = time.perf_counter()

    def _stop(self, stage: str) -> None:
        self._add(stage, time.perf_counter() - self._t_perceptual)

    def _wrap(self, obj, name: str, stage: str) -> None:
        method = getattr(obj, name)

        def timed(*args, **kwargs):
            t0 = time.perf_counter()
            try:
                return method(*args, **kwargs)
            finally:
                self._add(stage, time.perf_counter() - t0)

        setattr(obj, name, timed)

    def lap(self) -> dict[str, float]:
        """The stage seconds of the step that ends now (the remainders computed as described)."""
        now = time.perf_counter()
        c, self.current = self.current, {}
        step, self._t_step = now - self._t_step, now
        forward, batch = c.pop("nerf_step", 0.0), c.pop("backward_batch", 0.0)
        stages = {k: c.get(k, 0.0) for k in STAGES}
        stages["forward_other"] = forward - sum(c.get(k, 0.0) for k in (*_RENDER_TIMINGS, "body_layer", "perceptual"))
        stages["backward_other"] = batch - forward - stages["perceptual_backward"]
        stages["optimizer"] = step - batch
        return stages


def training_benchmark(run_dir, precisions=("float32", "bfloat16"), *, steps: int = 8, rounds: int = 3,
                       against=(), cold: bool = False, log=None) -> dict:
    """Median seconds per NeRF step of the run in ``run_dir`` for each of ``precisions``, whole and
    by stage.

    Args:
        run_dir: a run folder (its ``run.json`` names the scene; its body appearance, if any, is
            composed with as in its training).
        precisions: :data:`~garmentnerf.train.settings.TRAINING_PRECISIONS` to compare (``auto``
            is resolved first, as a run would).
        steps: steps per round and trainer (at least 3: the first and last of a round are not timed).
        rounds: rounds; the trainers alternate within each.
        against: other run folders whose recipes are timed the same way, at the same precisions,
            taking their turns with ``run_dir``'s (recipes compared in one run: e.g. a new recipe
            against the bundled model's).
        cold: time each step with its frame prepared in it (see the module docstring) instead of
            from the caches.
        log: called with one line per finished round (None: silent).
    Returns:
        ``{"run", "steps_timed", "machine", "stages", "precisions": [row], "speedup_vs_first"}``,
        a row ``{"precision", "s_per_step", "s_per_step_all", "stages_s", "stages_s_all"}`` (``stages_s``: the median seconds per step of each of ``stages``; ``stages_s_all``: each
        timed step's, in the order of ``s_per_step_all``); ``speedup_vs_first`` is the first
        precision's seconds per step over each one's. With ``against``, also ``"against": [{"run", "precisions": [row]}]`` and
        ``"speedup_vs_against"``: ``{run: {precision: its seconds per step over run_dir's}}``.
    """
    if steps < 3 or rounds < 1:
        raise ValueError(f"steps must be >= 3 and rounds >= 1, got {steps} and {rounds}")
    runs = [Path(run_dir), *(Path(r) for r in against)]
    infos = [training_inputs(r) for r in runs]
    resolved = list(dict.fromkeys(training_precision(p, "cpu") for p in precisions))
    # A variant: (index of the run in ``runs``, precision).
    variants = [(i, p) for i in range(len(runs)) for p in resolved]
    intervals = {v: [] for v in variants}
    stages = {v: [] for v in variants}
    with tempfile.TemporaryDirectory(prefix="garmentnerf-train-bench-") as tmp:
        trainers, clocks = {}, {}
        try:
            for v in variants:
                i, p = v
                scene, cfg, appearance, generator_iterations = infos[i]
                tc = TrainConfig(scene=scene, out=Path(tmp) / f"{i}-{p}",
                                 model_config=cfg.updated({"schedule.iterations": steps * rounds}),
                                 init_weights=runs[i] / MODEL_FILE, precision=p, progress=False,
                                 body_appearance=appearance, generator_iterations=generator_iterations,
                                 log_every=10 ** 9, image_every=0, ckpt_every=10 ** 9, keep_checkpoints=1)
                trainer = trainers[v] = Trainer(tc, log=lambda message: None)
                clocks[v] = _StageClock(trainer)
            for r in range(rounds):
                for v, trainer in trainers.items():
                    stamps: list[float] = []
                    laps: list[dict[str, float]] = []

                    def done(step, values, stamps=stamps, laps=laps, clock=clocks[v]):
                        stamps.append(time.perf_counter())
                        laps.append(clock.lap())

                    trainer.step_callback = done
                    if not cold:
                        trainer.warm_frames(steps)
                    trainer.tc = dataclasses.replace(trainer.tc, stop_after=trainer.step + steps)
                    trainer.train()
                    intervals[v] += list(np.diff(stamps)[:-1])  # neither the first step nor the checkpointed last
                    stages[v] += laps[1:-1]  # the same steps
                if log is not None:
                    log(f"round {r + 1}/{rounds}: " + ", ".join(f"{_label(v, runs)} {np.median(t):.3f} s/step"
                                                                for v, t in intervals.items()))
        finally:
            for trainer in trainers.values():
                trainer.close()

    def row(v) -> dict:
        return {"precision": v[1], "s_per_step": float(np.median(intervals[v])),
                "s_per_step_all": [float(x) for x in intervals[v]],
                "stages_s": {k: float(np.median([lap[k] for lap in stages[v]])) for k in STAGES},
                "stages_s_all": [{k: float(lap[k]) for k in STAGES} for lap in stages[v]]}

    rows = [row((0, p)) for p in resolved]
    first = rows[0]["s_per_step"]
    results = {"run": str(run_dir), "steps_timed": len(intervals[variants[0]]), "frames_cached": not cold,
               "machine": {"torch_threads": torch.get_num_threads(),
                           "processor": platform.processor() or platform.machine(),
                           "amx_bf16": bool(torch.cpu.get_capabilities().get("amx_bf16", False))},
               "stages": list(STAGES), "precisions": rows,
               "speedup_vs_first": {r["precision"]: first / r["s_per_step"] for r in rows}}
    if len(runs) > 1:
        results["against"] = [{"run": str(runs[i]), "precisions": [row((i, p)) for p in resolved]}
                              for i in range(1, len(runs))]
        results["speedup_vs_against"] = {
            a["run"]: {o["precision"]: o["s_per_step"] / r["s_per_step"] for o, r in zip(a["precisions"], rows)}
            for a in results["against"]}
    return results


def training_inputs(run_dir: Path) -> tuple[Path, ModelConfig, Path | None, int]:
    """(scene folder, model config, body appearance file or None, G_img steps) of a run folder."""
    info = read_run_info(run_dir)
    scene = recorded_scene_path(run_dir, info)
    if scene is None:
        raise ValueError(f"{run_dir}: the run names no scene to train on")
    cfg = ModelConfig.from_dict(dict(info["model_config"]))
    appearance = run_dir / BODY_APPEARANCE_FILE
    return (scene, cfg, appearance if appearance.is_file() else None,
            int(info.get("generator_iterations", cfg.schedule.generator_iterations)))


def _label(variant, runs) -> str:
    i, precision = variant
    return precision if i == 0 else f"{runs[i].name} {precision}"
