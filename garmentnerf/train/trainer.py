"""Two-stage training of the Garment Animation NeRF on a scene (paper Sec. 4.4; numbers in
``implementation-notes.md`` Sec. 1.8).

Stage 1 -- G_img pre-training (``cfg.generator_iterations`` steps; skipped when the detail
    feature is ablated). The neural texture and G_img learn to reproduce the ground-truth front
    and back reference images (the scene's ``ref_front`` / ``ref_back`` cameras) of the training
    frames from the body's UVs seen by those cameras: one frame (both references, DNG's batch of
    2) per step, ``w_image * L1 + w_perceptual * perceptual``, Adam at ``cfg.generator_lr``.
    Then G_img is frozen (:meth:`GarmentAnimationNeRF.set_image_generator_frozen`) and its
    reference images are computed once per frame and cached (it no longer changes).
    Left out from DNG: the SPADE temporal conditioning and the adversarial losses (see
    :mod:`garmentnerf.model.image_generator`).
Stage 2 -- the NeRF (``cfg.iterations`` steps). E, G_en, M_NeRF, M_D and the palette, with
    :func:`garmentnerf.model.losses.garment_losses` (weights from the config: L1 image + L1
    mask 1, perceptual 0.1, sparsity 2e-4, offsets 0.03, palette 1e-3). One (frame, training
    camera) per step, rendered as the full feature image (``cfg.feature_image_resolution``
    squared rays, decoded to ``cfg.image_resolution``): what the pipeline renders. Adam with
    ``lr`` decaying exponentially to ``lr_final`` over ``cfg.iterations``
    (``lr_n = lr * (lr_final / lr) ** (n / iterations)``), gradients clipped by value
    (``cfg.grad_clip_value``).

Steps are counted globally: ``[0, G)`` stage 1, ``[G, G + N)`` stage 2; checkpoints and
``run.json`` ``step`` use that count.

Determinism and exact resume
    What each step trains on and its ray jitter depend only on ``(seed, rank, step)``: the
    (frame, camera) of step s is entry ``(s * world + rank) mod n`` of a permutation drawn from
    ``(seed, epoch)`` (every rank the same permutation, each its own share: the
    ``DistributedSampler`` partitioning), and the jitter generator is seeded from
    ``(seed, rank, step)``. A checkpoint holds the weights (``.safetensors``), the optimiser
    state, the step and the python/numpy/torch RNG states (``.state.pt``); resuming from it gives
    the same losses as an uninterrupted run (tested bit-equal on the CPU).

Interruption
    Ctrl-C (``KeyboardInterrupt``) during a step abandons that step, writes a checkpoint of the
    last completed one (with the RNG states taken at that step's start) and returns with
    ``interrupted=True``; ``garmentnerf train ... --resume`` continues. (An interrupt that
    lands inside ``optimizer.step()`` itself may leave a half-updated step; practically never.)

Devices and several processes
    ``device="cuda"`` puts the model, the perceptual network and the targets on the GPU;
    :class:`~garmentnerf.model.frame_context.FrameInputs` are built on the CPU (GL) and moved per
    step. Under ``torchrun`` (``WORLD_SIZE > 1``) the process group is initialised from the
    environment (NCCL on CUDA, gloo otherwise; each rank uses ``cuda:LOCAL_RANK``), every rank
    trains on its share of the (frame, camera) pairs, gradients are averaged across ranks after
    every backward pass (data parallel, as DDP does; done by hand because a step is two calls,
    ``prepare_frame`` then ``render``, not one ``forward``), and only rank 0 writes logs,
    checkpoints and the run files. The effective batch is ``world_size`` images per step.

Caches
    Per-frame inputs stay in memory on the CPU (:class:`~garmentnerf.train.frames.SceneFrames`);
    targets in a byte-bounded LRU. There are no data-loader workers: a frame's inputs are built
    once (a few ms of GL) and every later step reads memory.
"""

from __future__ import annotations

import dataclasses
import math
import os
import random
import re
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from garmentnerf.io_utils import atomic_write_path
from garmentnerf.model.config import ModelConfig
from garmentnerf.train.run import (CHECKPOINT_DIR, RUN_FILE, TB_DIR, body_info_from_scene, build_model, load_scene,
                                   load_module_weights, load_weights, read_run_info, save_run_model,
                                   save_weights)

__all__ = ["TrainConfig", "Trainer", "TrainResult", "MODEL_PRESETS", "model_config_for", "tiny_config", "train",
           "latest_checkpoint"]

MODEL_PRESETS = ("paper", "cpu_small", "tiny")
_CKPT = re.compile(r"^ckpt_(\d+)\.state\.pt$")


def tiny_config() -> ModelConfig:
    """A model small enough for tests and smoke runs (64 x 64 images, seconds per dozen steps)."""
    return ModelConfig.cpu_small().replace(
        image_resolution=64, feature_image_resolution=16, reference_resolution=32, info_map_resolution=32,
        encoder_depth=3, encoder_width_scale=0.25, neural_texture_resolution=32, neural_texture_levels=2,
        generator_width_scale=0.25, appearance_dim=16, mlp_depth=2, mlp_width=32, samples_per_ray=8,
        decoder_width=16, decoder_min_width=8, decoder_extra_layers=0, iterations=200, generator_iterations=50)


def loss_weight_names() -> tuple[str, ...]:
    """The :class:`ModelConfig` fields that weight a loss term (``w_image``, ``w_mask``, ...)."""
    return tuple(f.name for f in dataclasses.fields(ModelConfig) if f.name.startswith("w_"))


def model_config_for(preset: str) -> ModelConfig:
    """The :class:`ModelConfig` of a preset name (``paper``, ``cpu_small``, ``tiny``)."""
    if preset == "paper":
        return ModelConfig.paper()
    if preset == "cpu_small":
        return ModelConfig.cpu_small()
    if preset == "tiny":
        return tiny_config()
    raise ValueError(f"unknown preset '{preset}' (known: {', '.join(MODEL_PRESETS)})")


@dataclass
class TrainConfig:
    """Settings of one training run (everything not in the :class:`ModelConfig`).

    Attributes:
        scene: the scene folder.
        out: the run folder (must be empty or absent unless ``resume``).
        preset: model preset (``paper``, ``cpu_small``, ``tiny``) when ``model_config`` is None.
        model_config: an explicit model config (overrides ``preset``); on resume the run's own
            config is used.
        device: ``cpu``, ``cuda`` or ``cuda:N`` (under torchrun ``cuda`` means ``cuda:LOCAL_RANK``).
        seed: seeds the initialisation, the (frame, camera) order and the ray jitter.
        iterations: overrides ``cfg.iterations`` (NeRF steps; the lr decay spans them).
        generator_iterations: overrides ``cfg.generator_iterations`` (G_img pre-training steps).
        stop_after: stop (writing a checkpoint) once this global step is reached, without
            changing the schedule (resume later to continue); None: train to the end.
        log_every: steps between TensorBoard scalars (losses, lr, psnr).
        image_every: steps between TensorBoard images (render | ground truth); 0: never.
        ckpt_every: steps between checkpoints (one is also written at the end of each stage,
            at the end and on Ctrl-C).
        keep_checkpoints: checkpoints kept (the newest ones).
        resume: continue the run in ``out`` from its newest checkpoint.
        sequences: training sequences (default: every ``train``-split sequence of the scene).
        frames: frame indices used in each sequence (default: all).
        cameras: training cameras (default: every ``train``-split camera).
        perceptual: ``auto`` (VGG19 when ``vgg19_weights``/``$GARMENTNERF_VGG19`` names
            ImageNet weights, else shift-tolerant LPIPS), ``vgg19``, ``stlpips`` or ``none``.
        vgg19_weights: torchvision ``vgg19-dcbb9e9d.pth``.
        progress: show a tqdm progress bar (rank 0).
        threads: ``torch.set_num_threads`` (None: leave as is).
        cache_bytes: bound of the in-memory target cache.
        init_generator: a weights file (a run's ``model.safetensors`` or a checkpoint) whose
            pre-trained G_img (with its neural texture) a new run starts from, skipping stage 1;
            the model configs must agree on G_img's shapes.
        loss_weights: overrides of the config's loss weights, ``{"w_segmentation": 0.5}``. On a
            resume they apply from the resumed step on (a curriculum: e.g. add a term once the
            geometry is there); each change is logged and kept in ``run.json``'s
            ``loss_weight_changes`` so the run's recipe stays on record.
    """

    scene: str | Path | None
    out: str | Path
    preset: str = "cpu_small"
    model_config: ModelConfig | None = None
    device: str = "cpu"
    seed: int = 0
    iterations: int | None = None
    generator_iterations: int | None = None
    stop_after: int | None = None
    log_every: int = 10
    image_every: int = 500
    ckpt_every: int = 1000
    keep_checkpoints: int = 2
    resume: bool = False
    sequences: tuple[str, ...] | None = None
    frames: tuple[int, ...] | None = None
    cameras: tuple[str, ...] | None = None
    perceptual: str = "auto"
    vgg19_weights: str | None = None
    progress: bool = True
    threads: int | None = None
    cache_bytes: int = 2 << 30
    init_generator: str | Path | None = None
    loss_weights: dict[str, float] | None = None

    def validate(self) -> None:
        if self.preset not in MODEL_PRESETS:
            raise ValueError(f"unknown preset '{self.preset}' (known: {', '.join(MODEL_PRESETS)})")
        known = loss_weight_names()
        for name, value in (self.loss_weights or {}).items():
            if name not in known:
                raise ValueError(f"unknown loss weight '{name}' (known: {', '.join(known)})")
            if not math.isfinite(value) or value < 0:
                raise ValueError(f"loss weight {name} must be a finite number >= 0, got {value}")
        for name in ("log_every", "ckpt_every", "keep_checkpoints"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.image_every < 0:
            raise ValueError(f"image_every must be >= 0, got {self.image_every}")
        if self.iterations is not None and self.iterations < 1:
            raise ValueError(f"iterations must be >= 1, got {self.iterations}")
        if self.generator_iterations is not None and self.generator_iterations < 0:
            raise ValueError(f"generator_iterations must be >= 0, got {self.generator_iterations}")
        if self.stop_after is not None and self.stop_after < 0:
            raise ValueError(f"stop_after must be >= 0, got {self.stop_after}")

    def to_json(self) -> dict:
        out = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if f.name == "model_config":
                continue
            out[f.name] = str(v) if isinstance(v, Path) else (list(v) if isinstance(v, tuple) else v)
        return out


@dataclass
class TrainResult:
    """What :meth:`Trainer.train` returns: the step reached, whether Ctrl-C stopped it, the
    per-step losses of this process (``{"step", "stage", <terms>...}``, ``step`` = global step
    after the update) and the newest checkpoint written."""

    step: int
    interrupted: bool
    history: list[dict] = field(default_factory=list)
    checkpoint: Path | None = None
    finished: bool = False


def latest_checkpoint(run_dir) -> tuple[int, Path, Path] | None:
    """(step, weights, state) of the newest complete checkpoint of a run, or None."""
    folder = Path(run_dir) / CHECKPOINT_DIR
    if not folder.is_dir():
        return None
    found = []
    for p in folder.iterdir():
        m = _CKPT.match(p.name)
        if m:
            step = int(m.group(1))
            weights = folder / f"ckpt_{step}.safetensors"
            if weights.is_file():
                found.append((step, weights, p))
    return max(found) if found else None


def _seed_of(*parts: int) -> int:
    return int(np.random.SeedSequence([int(p) for p in parts]).generate_state(1, np.uint64)[0] >> 1)


def _rng_state() -> dict:
    np_state = np.random.get_state(legacy=False)
    state = {"python": random.getstate(), "torch": torch.get_rng_state(),
             "numpy": {"bit_generator": np_state["bit_generator"],
                       "key": torch.from_numpy(np.asarray(np_state["state"]["key"]).astype(np.int64)),
                       "pos": int(np_state["state"]["pos"]), "has_gauss": int(np_state["has_gauss"]),
                       "gauss": float(np_state["gauss"])}}
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def _set_rng_state(state: dict) -> None:
    py = state["python"]
    random.setstate((py[0], tuple(py[1]), py[2]))
    torch.set_rng_state(state["torch"])
    n = state["numpy"]
    np.random.set_state({"bit_generator": n["bit_generator"],
                         "state": {"key": n["key"].numpy().astype(np.uint32), "pos": n["pos"]},
                         "has_gauss": n["has_gauss"], "gauss": n["gauss"]})
    if "cuda" in state and torch.cuda.is_available():
        try:
            torch.cuda.set_rng_state_all(state["cuda"])
        except (RuntimeError, IndexError):
            pass  # another GPU count: the trainer's own randomness is seeded per step anyway


class _Dist:
    """torch.distributed from the torchrun environment (a no-op for one process)."""

    def __init__(self, device: str):
        import torch.distributed as dist

        self.dist = dist
        self.world = int(os.environ.get("WORLD_SIZE", "1"))
        self.rank = int(os.environ.get("RANK", "0"))
        self.local_rank = int(os.environ.get("LOCAL_RANK", "0"))
        self.owned = False
        if self.world > 1:
            if not dist.is_initialized():
                backend = "nccl" if device.startswith("cuda") else "gloo"
                if device.startswith("cuda"):
                    torch.cuda.set_device(self.local_rank)
                dist.init_process_group(backend=backend)
                self.owned = True
            self.world, self.rank = dist.get_world_size(), dist.get_rank()

    @property
    def active(self) -> bool:
        return self.world > 1

    @property
    def main(self) -> bool:
        return self.rank == 0

    def barrier(self) -> None:
        if self.active:
            self.dist.barrier()

    def all_ok(self, ok: bool) -> bool:
        """True when ``ok`` on every rank (so all ranks raise together)."""
        if not self.active:
            return ok
        t = torch.tensor([0 if ok else 1], dtype=torch.int64)
        if self.dist.get_backend() == "nccl":
            t = t.cuda()
        self.dist.all_reduce(t)
        return int(t.item()) == 0

    def average_gradients(self, params: list[torch.nn.Parameter]) -> None:
        if not self.active or not params:
            return
        grads = [p.grad if p.grad is not None else torch.zeros_like(p) for p in params]
        flat = torch.cat([g.reshape(-1) for g in grads])
        self.dist.all_reduce(flat)
        flat /= self.world
        offset = 0
        for p in params:
            n = p.numel()
            p.grad = flat[offset:offset + n].view_as(p).clone()
            offset += n

    def broadcast_module(self, module: torch.nn.Module) -> None:
        if not self.active:
            return
        with torch.no_grad():
            for t in module.state_dict().values():
                self.dist.broadcast(t, 0)

    def close(self) -> None:
        if self.owned and self.dist.is_initialized():
            self.dist.destroy_process_group()
            self.owned = False


class Trainer:
    """One training run (see the module docstring). Use :meth:`train`, then :meth:`close`.

    Args:
        tc: the :class:`TrainConfig`.
        gl_context: a moderngl context for the GL passes (None: a headless one is made).
        log: where messages go (default: print to stderr on rank 0).

    Attributes:
        step_callback: ``callable(step, terms)`` run after every completed step (``terms``:
            float losses); raising ``KeyboardInterrupt`` there acts like Ctrl-C (tests).
    """

    def __init__(self, tc: TrainConfig, gl_context=None, log: Callable[[str], None] | None = None):
        tc.validate()
        self.tc = tc
        self.dist = _Dist(tc.device)
        self._log = log
        self.out = Path(tc.out)
        self.step_callback: Callable[[int, dict], None] | None = None
        if tc.threads:
            torch.set_num_threads(int(tc.threads))
        try:
            self._setup(gl_context)
        except BaseException:
            self.dist.close()
            raise

    # ---- setup -------------------------------------------------------------------------------------
    def log(self, message: str) -> None:
        if not self.dist.main:
            return
        if self._log is not None:
            self._log(message)
        else:
            from tqdm import tqdm

            tqdm.write(f"garmentnerf train: {message}", file=sys.stderr)

    def _device(self) -> torch.device:
        dev = torch.device(self.tc.device)
        if dev.type == "cuda":
            if not torch.cuda.is_available():
                raise ValueError("--device cuda: no CUDA device is available to this torch build")
            if self.dist.active and dev.index is None:
                dev = torch.device("cuda", self.dist.local_rank)
        return dev

    def _setup(self, gl_context) -> None:
        tc = self.tc
        out = self.out
        resume_info = None
        ckpt = None
        problem = None
        if tc.resume:
            if not (out / RUN_FILE).is_file():
                problem = FileNotFoundError(f"{out / RUN_FILE}: missing; --resume needs a run folder made by "
                                            f"'garmentnerf train'")
            else:
                resume_info = read_run_info(out)
                ckpt = latest_checkpoint(out)
                if ckpt is None:
                    problem = FileNotFoundError(f"{out / CHECKPOINT_DIR}: no complete checkpoint "
                                                f"(ckpt_<step>.safetensors + ckpt_<step>.state.pt) to resume from")
        elif out.exists() and (not out.is_dir() or any(out.iterdir())):
            problem = ValueError(f"{out}: run folder is not empty; pass --resume to continue the run in it, "
                                 f"or choose another --out")
        if not self.dist.all_ok(problem is None):
            raise problem if problem is not None else ValueError("another rank refused to start (see its message)")

        # scene and config
        if resume_info is not None:
            scene_path = tc.scene
            if scene_path is None and resume_info.get("scene"):
                p = Path(resume_info["scene"])
                scene_path = p if p.is_absolute() else out / p
            cfg = ModelConfig.from_dict(dict(resume_info["model_config"]))
        else:
            scene_path = tc.scene
            cfg = tc.model_config if tc.model_config is not None else model_config_for(tc.preset)
        if scene_path is None:
            raise ValueError("no scene given (--scene)")
        self.scene_path = Path(scene_path)
        if not (self.scene_path / "scene.json").is_file() and not self.scene_path.suffix == ".json":
            raise FileNotFoundError(f"{self.scene_path / 'scene.json'}: missing (--scene must be a scene folder)")
        self.scene = load_scene(self.scene_path)
        changes = {}
        if tc.iterations is not None:
            changes["iterations"] = int(tc.iterations)
        if tc.generator_iterations:
            # 0 (skip pre-training) is allowed here although ModelConfig wants > 0: kept apart.
            changes["generator_iterations"] = int(tc.generator_iterations)
        weight_changes = {k: float(v) for k, v in (tc.loss_weights or {}).items() if getattr(cfg, k) != float(v)}
        changes.update(weight_changes)
        cfg = cfg.replace(**changes) if changes else cfg
        self.cfg = cfg
        self.loss_weight_changes = list((resume_info or {}).get("loss_weight_changes", []))
        gen_iters = cfg.generator_iterations if tc.generator_iterations is None else int(tc.generator_iterations)
        if resume_info is not None and tc.generator_iterations is None:
            gen_iters = int(resume_info.get("generator_iterations", gen_iters))
        self.generator_iterations = gen_iters if cfg.use_detail_feature else 0
        self.total_steps = self.generator_iterations + cfg.iterations
        if self.scene.palette_init is None:
            self.log(f"{self.scene.scene_file}: no palette_init; the palette starts at mid grey")

        # training set
        seqs = list(tc.sequences) if tc.sequences else self.scene.sequence_names("train")
        if not seqs:
            raise ValueError(f"{self.scene.scene_file}: no training sequence (split 'train')")
        frames = []
        for s in seqs:
            n = self.scene.num_frames(s)
            idx = list(range(n)) if tc.frames is None else [self.scene.check_frame(s, f) for f in tc.frames]
            frames += [(s, f) for f in idx]
        cams = list(tc.cameras) if tc.cameras else self.scene.camera_names("train")
        if not cams:
            raise ValueError(f"{self.scene.scene_file}: no training camera (split 'train')")
        for c in cams:
            self.scene.camera(c)
        if self.generator_iterations:
            names = set(self.scene.camera_names())
            missing = [n for n in ("ref_front", "ref_back") if n not in names]
            if missing:
                raise ValueError(f"{self.scene.scene_file}: G_img pre-training needs the reference cameras "
                                 f"{', '.join(missing)}")
        self.frames_list = frames
        self.pairs = [(s, f, c) for (s, f) in frames for c in cams]

        # model
        self.device = self._device()
        torch.manual_seed(tc.seed)
        self.model = build_model(cfg, self.scene.palette_init).to(self.device)
        self.dist.broadcast_module(self.model)
        from garmentnerf.train.perceptual import make_perceptual

        self.perceptual, self.perceptual_name = make_perceptual(tc.perceptual, tc.vgg19_weights, cfg.w_perceptual)
        if self.perceptual is not None:
            self.perceptual = self.perceptual.to(self.device)
        if resume_info is not None and resume_info.get("perceptual") not in (None, self.perceptual_name):
            self.log(f"note: the run was trained with perceptual '{resume_info.get('perceptual')}', "
                     f"continuing with '{self.perceptual_name}'")
        self.data = SceneFramesFactory(self.scene, cfg, gl_context, self.model.body, tc.cache_bytes)
        self.step = 0
        self.optimizer = None
        self.stage = None
        self.writer = None
        self.last_checkpoint = None
        if ckpt is not None:
            self._load_checkpoint(*ckpt)
            if weight_changes:
                old = ModelConfig.from_dict(dict(resume_info["model_config"]))
                record = {"step": self.step, **{k: [getattr(old, k), v] for k, v in weight_changes.items()}}
                self.loss_weight_changes.append(record)
                self.log("loss weights from step " + str(self.step) + ": " +
                         ", ".join(f"{k} {getattr(old, k):g} -> {v:g}" for k, v in weight_changes.items()))
        elif tc.init_generator is not None and self.generator_iterations:
            load_module_weights(tc.init_generator, self.model, "image_generator")
            self.step = self.generator_iterations
            self._enter_stage(self._stage_of(self.step))
            self.log(f"G_img from {tc.init_generator}: pre-training skipped, starting at step {self.step}")
        else:
            self._enter_stage(self._stage_of(0))
        self.dist.barrier()
        self.log(f"{len(frames)} frames x {len(cams)} cameras, {self.generator_iterations} G_img + "
                 f"{cfg.iterations} NeRF steps, perceptual: {self.perceptual_name}, device: {self.device}"
                 + (f", {self.dist.world} processes" if self.dist.active else "")
                 + (f", resuming at step {self.step}" if ckpt is not None else ""))

    # ---- stages and optimiser ---------------------------------------------------------------------------
    def _stage_of(self, step: int) -> str:
        return "generator" if step < self.generator_iterations else "nerf"

    def _enter_stage(self, stage: str) -> None:
        m = self.model
        if stage == "generator":
            m.set_image_generator_frozen(False)
            params = [p for p in m.image_generator.parameters()]
            lr = self.cfg.generator_lr
        else:
            m.set_image_generator_frozen(True)
            params = [p for mod in m.trainable_modules().values() for p in mod.parameters() if p.requires_grad]
            lr = self.cfg.lr
        m.train()
        self.params = params
        self.optimizer = torch.optim.Adam(params, lr=lr)
        self.stage = stage

    def lr_at(self, step: int) -> float:
        """Learning rate of global step ``step``."""
        cfg = self.cfg
        if step < self.generator_iterations:
            return cfg.generator_lr
        n = step - self.generator_iterations
        return cfg.lr * (cfg.lr_final / cfg.lr) ** (n / max(1, cfg.iterations))

    # ---- checkpoints -------------------------------------------------------------------------------
    def _run_extra(self) -> dict:
        return {"perceptual": self.perceptual_name, "body": body_info_from_scene(self.scene),
                "generator_iterations": self.generator_iterations,
                "nerf_step": max(0, self.step - self.generator_iterations), "seed": self.tc.seed,
                "train": self.tc.to_json(), "loss_weight_changes": self.loss_weight_changes}

    def save_checkpoint(self, rng_state: dict | None = None) -> Path | None:
        """Write ``checkpoints/ckpt_<step>`` (weights, then state) and the run's model files; rank 0 only."""
        if not self.dist.main:
            return None
        folder = self.out / CHECKPOINT_DIR
        folder.mkdir(parents=True, exist_ok=True)
        weights = folder / f"ckpt_{self.step}.safetensors"
        state_file = folder / f"ckpt_{self.step}.state.pt"
        save_weights(weights, self.model, {"step": self.step})
        state = {"step": self.step, "stage": self.stage, "optimizer": self.optimizer.state_dict(),
                 "rng": rng_state if rng_state is not None else _rng_state(),
                 "generator_iterations": self.generator_iterations, "model_config": self.cfg.to_dict(),
                 "seed": self.tc.seed, "world_size": self.dist.world}
        with atomic_write_path(state_file) as tmp:
            torch.save(state, tmp)
        save_run_model(self.out, self.model, self.cfg, self.scene_path, self.step, self._run_extra())
        # keep the newest ones
        steps = sorted(int(m.group(1)) for p in folder.iterdir() if (m := _CKPT.match(p.name)))
        for old in steps[:-self.tc.keep_checkpoints]:
            for suffix in (".state.pt", ".safetensors"):
                (folder / f"ckpt_{old}{suffix}").unlink(missing_ok=True)
        self.last_checkpoint = state_file
        return state_file

    def _load_checkpoint(self, step: int, weights: Path, state_file: Path) -> None:
        load_weights(weights, self.model)
        try:
            state = torch.load(state_file, map_location="cpu", weights_only=True)
        except Exception as exc:
            raise ValueError(f"{state_file}: unreadable checkpoint state ({exc})") from exc
        if state.get("step") != step:
            raise ValueError(f"{state_file}: holds step {state.get('step')}, its name says {step}")
        if state.get("world_size", 1) != self.dist.world:
            self.log(f"note: checkpoint written with {state.get('world_size', 1)} processes, resuming with "
                     f"{self.dist.world}: the (frame, camera) order differs from an uninterrupted run")
        self.step = step
        stage = state.get("stage", self._stage_of(step))
        self._enter_stage(stage)
        if stage != self._stage_of(step):
            # e.g. the checkpoint ended stage 1 with different --generator-iterations: move on.
            self._enter_stage(self._stage_of(step))
        else:
            try:
                self.optimizer.load_state_dict(state["optimizer"])
            except (ValueError, KeyError) as exc:
                raise ValueError(f"{state_file}: optimiser state does not match the model ({exc})") from exc
        _set_rng_state(state["rng"])
        self.dist.broadcast_module(self.model)
        self.last_checkpoint = state_file

    # ---- steps -------------------------------------------------------------------------------------
    def _pick(self, items: list, step: int, salt: int):
        n = len(items)
        g = step * self.dist.world + self.dist.rank
        epoch, pos = divmod(g, n)
        perm = np.random.default_rng(_seed_of(self.tc.seed, salt, epoch)).permutation(n)
        return items[int(perm[pos])]

    def _generator_step(self, step: int) -> tuple[dict, dict]:
        seq, frame = self._pick(self.frames_list, step, 1)
        inputs = self.data.frames.inputs(seq, frame)
        target = self.data.frames.reference_targets(seq, frame).to(self.device)
        pred = self.model.image_generator(inputs.reference_uv.to(self.device, torch.float32),
                                          inputs.reference_mask.to(self.device))
        terms = {"image": (pred - target).abs().mean()}
        total = self.cfg.w_image * terms["image"]
        if self.perceptual is not None:
            terms["perceptual"] = self.perceptual(pred, target)
            total = total + self.cfg.w_perceptual * terms["perceptual"]
        terms["total"] = total
        return terms, {"pred": pred, "target": target}

    def _nerf_inputs(self, seq: str, frame: int):
        frames = self.data.frames
        inputs = frames.inputs(seq, frame)
        if self.cfg.use_detail_feature and inputs.reference_images is None:
            with torch.no_grad():
                imgs = self.model.image_generator(inputs.reference_uv.to(self.device, torch.float32),
                                                  inputs.reference_mask.to(self.device))
            frames.set_reference_images(seq, frame, imgs)
            inputs = frames.inputs(seq, frame)
        return inputs

    def _nerf_step(self, step: int) -> tuple[dict, dict]:
        from garmentnerf.model.losses import garment_losses

        seq, frame, cam = self._pick(self.pairs, step, 2)
        inputs = self._nerf_inputs(seq, frame)
        feats = self.model.prepare_frame(inputs)
        gen = torch.Generator().manual_seed(_seed_of(self.tc.seed, self.dist.rank, step))
        out = self.model.render(feats, self.data.frames.camera(cam), training=True, generator=gen)
        image, mask, garment = (t.to(self.device) for t in self.data.frames.target(seq, cam, frame))
        pal = self.model.palette
        segment = step - self.generator_iterations >= self.cfg.segmentation_start
        terms = garment_losses(out.image[None], image[None], out.maps, mask[None], pal.colours, pal.initial,
                               self.cfg, self.perceptual, opacity=out.opacity[None],
                               target_garment=garment[None] if segment else None)
        return terms, {"pred": out.image, "target": image}

    def _writer(self):
        if self.writer is None and self.dist.main:
            from torch.utils.tensorboard import SummaryWriter

            self.writer = SummaryWriter(str(self.out / TB_DIR), purge_step=self.step if self.step else None)
        return self.writer

    def _log_step(self, step: int, stage: str, terms: dict, lr: float, images: dict) -> None:
        w = self._writer()
        if w is None:
            return
        if step % self.tc.log_every == 0 or step == self.total_steps:
            for k, v in terms.items():
                w.add_scalar(f"{stage}/{k}", v, step)
            w.add_scalar(f"{stage}/lr", lr, step)
            w.add_scalar(f"{stage}/psnr", terms["psnr"], step)
        if self.tc.image_every and (step % self.tc.image_every == 0 or step == self.total_steps):
            pred, target = images["pred"].detach(), images["target"]
            if pred.ndim == 4:  # the two references: stack vertically
                pred, target = torch.cat(list(pred), 1), torch.cat(list(target), 1)
            w.add_image(f"{stage}/render_vs_gt", torch.cat([pred, target], 2).clamp(0, 1).cpu(), step)

    def train(self) -> TrainResult:
        """Train to the end (or to ``stop_after``); Ctrl-C saves a checkpoint and returns."""
        from tqdm import tqdm

        tc = self.tc
        end = self.total_steps if tc.stop_after is None else min(self.total_steps, tc.stop_after)
        history: list[dict] = []
        bar = tqdm(total=self.total_steps, initial=self.step, disable=not (tc.progress and self.dist.main),
                   desc="train", unit="step", dynamic_ncols=True, file=sys.stderr)
        rng_at_start = _rng_state()
        interrupted = False
        t_start, s_start = time.perf_counter(), self.step
        try:
            while self.step < end:
                step = self.step
                stage = self._stage_of(step)
                if stage != self.stage:
                    self._enter_stage(stage)
                lr = self.lr_at(step)
                for group in self.optimizer.param_groups:
                    group["lr"] = lr
                self.optimizer.zero_grad(set_to_none=True)
                terms, images = self._generator_step(step) if stage == "generator" else self._nerf_step(step)
                terms["total"].backward()
                self.dist.average_gradients(self.params)
                torch.nn.utils.clip_grad_value_(self.params, self.cfg.grad_clip_value)
                self.optimizer.step()
                self.step = step + 1
                values = {k: float(v.detach()) for k, v in terms.items()}
                with torch.no_grad():
                    mse = float((images["pred"].detach() - images["target"]).square().mean())
                values["psnr"] = -10.0 * math.log10(max(mse, 1e-10))
                history.append({"step": self.step, "stage": stage, **values})
                self._log_step(self.step, stage, values, lr, images)
                bar.update(1)
                bar.set_postfix(stage=stage, loss=f"{values['total']:.4f}", psnr=f"{values['psnr']:.2f}")
                boundary = self.step == self.generator_iterations and self.generator_iterations > 0
                if self.step % tc.ckpt_every == 0 or boundary or self.step == end:
                    if boundary:
                        self._enter_stage("nerf")
                    self.save_checkpoint()
                rng_at_start = _rng_state()  # the state after the last completed step
                if self.step_callback is not None:
                    self.step_callback(self.step, values)
        except KeyboardInterrupt:
            interrupted = True
            bar.close()
            # the step that was running is abandoned: save the last completed one
            self.save_checkpoint(rng_at_start)
            self.log(f"interrupted: checkpoint of step {self.step} written to {self.out / CHECKPOINT_DIR}; "
                     f"continue with 'garmentnerf train --out {self.out} --resume'")
        finally:
            bar.close()
            if self.writer is not None:
                self.writer.flush()
        done = self.step >= self.total_steps
        if not interrupted:
            rate = (time.perf_counter() - t_start) / max(1, self.step - s_start)
            self.log(f"{'finished' if done else 'stopped'} at step {self.step}/{self.total_steps} "
                     f"({rate:.2f} s/step); run: {self.out}")
        return TrainResult(self.step, interrupted, history, self.last_checkpoint, done)

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.writer = None
        if getattr(self, "data", None) is not None:
            self.data.close()
        self.dist.close()

    def __enter__(self) -> "Trainer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class SceneFramesFactory:
    """Makes the :class:`~garmentnerf.train.frames.SceneFrames` (and its GL context) on first use."""

    def __init__(self, scene, cfg, gl_context, body, cache_bytes):
        self._args = (scene, cfg, gl_context, body, cache_bytes)
        self._frames = None

    @property
    def frames(self):
        if self._frames is None:
            from garmentnerf.train.frames import SceneFrames

            scene, cfg, ctx, body, cache_bytes = self._args
            self._frames = SceneFrames(scene, cfg, ctx, body, cache_bytes)
        return self._frames

    def close(self) -> None:
        if self._frames is not None:
            self._frames.close()
            self._frames = None


def train(tc: TrainConfig, gl_context=None) -> TrainResult:
    """Run :class:`Trainer` start to finish (closing it)."""
    with Trainer(tc, gl_context) as trainer:
        return trainer.train()
