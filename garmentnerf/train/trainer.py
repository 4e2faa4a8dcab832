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

Interruption, kills and a full disk
    Ctrl-C (``KeyboardInterrupt``) during a step abandons that step, writes a checkpoint of the
    last completed one (with the RNG states taken at that step's end) and returns with
    ``interrupted=True``; ``garmentnerf train ... --resume`` continues. SIGINT and SIGTERM that
    arrive while a step's update is applied (``optimizer.step()`` and the step count) are held
    until it is done, so a checkpoint never holds a half-updated step. Every file is written
    atomically (synced temporary + rename): a killed process (SIGKILL, power loss) leaves the
    previous complete checkpoint, plus temporaries that the next resume deletes. A write that
    fails (full disk, ...) removes the checkpoint it was writing and stops with
    :class:`CheckpointWriteError` naming the checkpoint folder.

Resume
    ``resume=True`` continues the run in ``out`` with the settings recorded in its ``run.json``
    (``train``: preset, seed, sequences, frames, cameras, iterations, checkpoint and log
    intervals, perceptual loss, ...); a :class:`TrainConfig` field left at None takes the run's
    value. A field that would change what the run is (:data:`RUN_SETTINGS`) and differs from
    the run's value is refused (ValueError naming the flag, the run's value and the given one);
    one that only changes how it goes on (:data:`OVERRIDABLE_SETTINGS`, ``stop_after``, the
    scene folder) applies from the resumed step and is recorded in ``run.json``'s
    ``overrides``. Checkpoints are tried newest first: an unreadable one is skipped with a
    notice naming it.

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

import contextlib
import dataclasses
import io
import math
import os
import random
import re
import signal
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType

import numpy as np
import torch

from garmentnerf.model.config import ModelConfig
from garmentnerf.train.run import (CHECKPOINT_DIR, RUN_FILE, TB_DIR, body_info_from_scene, build_model, load_scene,
                                   load_module_weights, load_weights, read_run_info, remove_run_temporaries,
                                   save_run_model, save_weights, write_file_atomic)

__all__ = ["TrainConfig", "Trainer", "TrainResult", "MODEL_PRESETS", "model_config_for", "tiny_config", "train",
           "latest_checkpoint", "checkpoints", "CheckpointWriteError", "RUN_SETTINGS", "OVERRIDABLE_SETTINGS"]

MODEL_PRESETS = ("paper", "cpu_small", "tiny")
_CKPT = re.compile(r"^ckpt_(\d+)\.state\.pt$")
_CKPT_FILE = re.compile(r"^ckpt_(\d+)\.(?:safetensors|state\.pt)$")

#: What a new run uses for the :class:`TrainConfig` fields left at None (a resume: the run's values).
TRAIN_DEFAULTS = MappingProxyType({"preset": "cpu_small", "seed": 0, "log_every": 10, "image_every": 500,
                                   "ckpt_every": 1000, "keep_checkpoints": 2, "perceptual": "auto"})
#: :class:`TrainConfig` fields that define the run: a resume with another value is refused.
RUN_SETTINGS = ("preset", "seed", "iterations", "generator_iterations", "sequences", "frames", "cameras",
                "init_generator")
#: :class:`TrainConfig` fields a resume may change (from the resumed step on; recorded in ``overrides``).
OVERRIDABLE_SETTINGS = ("log_every", "image_every", "ckpt_every", "keep_checkpoints", "perceptual", "vgg19_weights")


class CheckpointWriteError(ValueError):
    """A checkpoint could not be written (full disk, no permission, ...): the machine's state, not
    a bug, so the command line prints it as one line. ``errno`` is the OS error's."""

    def __init__(self, message: str, errno: int | None = None):
        super().__init__(message)
        self.errno = errno


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

    Fields marked *run* (:data:`RUN_SETTINGS`) define the run: on ``resume`` None means the
    run's value and another value is refused. Fields marked *override*
    (:data:`OVERRIDABLE_SETTINGS`): on ``resume`` None means the run's value, another value
    applies from the resumed step on and is recorded in ``run.json``'s ``overrides``. For a new
    run None means the default (:data:`TRAIN_DEFAULTS`, or as described).

    Attributes:
        scene: the scene folder (on resume None: the run's; another folder, e.g. a moved scene,
            is recorded in ``overrides``).
        out: the run folder (must be empty or absent unless ``resume``).
        preset: *run*; model preset (``paper``, ``cpu_small``, ``tiny``; default ``cpu_small``)
            when ``model_config`` is None. With a ``model_config`` the run records the preset it
            equals (apart from iterations and loss weights), else None.
        model_config: an explicit model config (overrides ``preset``); on resume the run's own
            config is used and this is ignored.
        device: ``cpu``, ``cuda`` or ``cuda:N`` (under torchrun ``cuda`` means ``cuda:LOCAL_RANK``).
        seed: *run*; seeds the initialisation, the (frame, camera) order and the ray jitter (default 0).
        iterations: *run*; overrides ``cfg.iterations`` (NeRF steps; the lr decay spans them).
        generator_iterations: *run*; overrides ``cfg.generator_iterations`` (G_img pre-training steps).
        stop_after: stop (writing a checkpoint) once this global step is reached, without
            changing the schedule (resume later to continue); None: train to the end. Not
            inherited by a resume (given on one, it is recorded in ``overrides``).
        log_every: *override*; steps between TensorBoard scalars (losses, lr, psnr; default 10).
        image_every: *override*; steps between TensorBoard images (render | ground truth); 0:
            never (default 500).
        ckpt_every: *override*; steps between checkpoints (one is also written at the end of
            each stage, at the end and on Ctrl-C; default 1000).
        keep_checkpoints: *override*; checkpoints kept (the newest ones; default 2).
        resume: continue the run in ``out`` from its newest readable checkpoint, with its settings.
        sequences: *run*; training sequences (default: every ``train``-split sequence of the scene).
        frames: *run*; frame indices used in each sequence (default: all).
        cameras: *run*; training cameras (default: every ``train``-split camera).
        perceptual: *override*; ``auto`` (the default: VGG19 when
            ``vgg19_weights``/``$GARMENTNERF_VGG19`` names ImageNet weights, else shift-tolerant
            LPIPS), ``vgg19``, ``stlpips`` or ``none``.
        vgg19_weights: *override*; torchvision ``vgg19-dcbb9e9d.pth``.
        progress: show a tqdm progress bar (rank 0).
        threads: ``torch.set_num_threads`` (None: leave as is).
        cache_bytes: bound of the in-memory target cache.
        init_generator: *run*; a weights file (a run's ``model.safetensors`` or a checkpoint)
            whose pre-trained G_img (with its neural texture) a new run starts from, skipping
            stage 1; the model configs must agree on G_img's shapes.
        loss_weights: overrides of the config's loss weights, ``{"w_segmentation": 0.5}``. On a
            resume they apply from the resumed step on (a curriculum: e.g. add a term once the
            geometry is there); each change is logged and kept in ``run.json``'s
            ``loss_weight_changes`` so the run's recipe stays on record.
    """

    scene: str | Path | None
    out: str | Path
    preset: str | None = None
    model_config: ModelConfig | None = None
    device: str = "cpu"
    seed: int | None = None
    iterations: int | None = None
    generator_iterations: int | None = None
    stop_after: int | None = None
    log_every: int | None = None
    image_every: int | None = None
    ckpt_every: int | None = None
    keep_checkpoints: int | None = None
    resume: bool = False
    sequences: tuple[str, ...] | None = None
    frames: tuple[int, ...] | None = None
    cameras: tuple[str, ...] | None = None
    perceptual: str | None = None
    vgg19_weights: str | None = None
    progress: bool = True
    threads: int | None = None
    cache_bytes: int = 2 << 30
    init_generator: str | Path | None = None
    loss_weights: dict[str, float] | None = None

    def validate(self) -> None:
        """Raise ValueError naming the first impossible setting (None fields are not checked)."""
        if self.preset is not None and self.preset not in MODEL_PRESETS:
            raise ValueError(f"unknown preset '{self.preset}' (known: {', '.join(MODEL_PRESETS)})")
        known = loss_weight_names()
        for name, value in (self.loss_weights or {}).items():
            if name not in known:
                raise ValueError(f"unknown loss weight '{name}' (known: {', '.join(known)})")
            if not math.isfinite(value) or value < 0:
                raise ValueError(f"loss weight {name} must be a finite number >= 0, got {value}")
        for name in ("log_every", "ckpt_every", "keep_checkpoints"):
            value = getattr(self, name)
            if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
        if self.image_every is not None and (isinstance(self.image_every, bool) or not isinstance(self.image_every, int)
                                             or self.image_every < 0):
            raise ValueError(f"image_every must be an integer >= 0, got {self.image_every!r}")
        if self.seed is not None and (isinstance(self.seed, bool) or not isinstance(self.seed, int)):
            raise ValueError(f"seed must be an integer, got {self.seed!r}")
        if self.iterations is not None and self.iterations < 1:
            raise ValueError(f"iterations must be >= 1, got {self.iterations}")
        if self.generator_iterations is not None and self.generator_iterations < 0:
            raise ValueError(f"generator_iterations must be >= 0, got {self.generator_iterations}")
        if self.stop_after is not None and self.stop_after < 0:
            raise ValueError(f"stop_after must be >= 0, got {self.stop_after}")

    def to_json(self) -> dict:
        """The fields as JSON values (``run.json``'s ``train``; ``model_config`` left out)."""
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


def checkpoints(run_dir) -> list[tuple[int, Path, Path]]:
    """(step, weights, state) of every complete checkpoint of a run (both files there), newest
    first. Complete is not readable: :class:`Trainer` checks that when it resumes."""
    folder = Path(run_dir) / CHECKPOINT_DIR
    if not folder.is_dir():
        return []
    found = []
    for p in folder.iterdir():
        m = _CKPT.match(p.name)
        if m:
            step = int(m.group(1))
            weights = folder / f"ckpt_{step}.safetensors"
            if weights.is_file():
                found.append((step, weights, p))
    return sorted(found, reverse=True)


def latest_checkpoint(run_dir) -> tuple[int, Path, Path] | None:
    """(step, weights, state) of the newest complete checkpoint of a run, or None."""
    found = checkpoints(run_dir)
    return found[0] if found else None


# ---- run settings on resume ------------------------------------------------------------------------
def _architecture(cfg: ModelConfig) -> dict:
    """``cfg`` without what a run may set apart from its preset (iterations, loss weights)."""
    names = {"iterations", "generator_iterations", *loss_weight_names()}
    return {k: v for k, v in cfg.to_dict().items() if k not in names}


def _preset_of(cfg: ModelConfig) -> str | None:
    """The preset ``cfg`` is (apart from iterations and loss weights), or None."""
    arch = _architecture(cfg)
    return next((p for p in MODEL_PRESETS if _architecture(model_config_for(p)) == arch), None)


def _plain(value):
    """A setting as JSON has it (tuples as lists, paths as strings), to compare with ``run.json``."""
    if isinstance(value, (tuple, list)):
        return [_plain(v) for v in value]
    return str(value) if isinstance(value, Path) else value


def _show(name: str, value) -> str:
    if value is None and name in ("sequences", "frames", "cameras"):
        return "all"
    if isinstance(value, (tuple, list)):
        return ",".join(str(v) for v in value)
    return str(value)


def _one_line(exc: BaseException) -> str:
    """The first line of an error's message (library errors can run over several)."""
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    return lines[0] if lines else type(exc).__name__


def _new_run_settings(tc: TrainConfig) -> TrainConfig:
    """``tc`` with the defaults (:data:`TRAIN_DEFAULTS`) in its None fields and the preset it runs."""
    values = {k: v for k, v in TRAIN_DEFAULTS.items() if k != "preset" and getattr(tc, k) is None}
    if tc.model_config is not None:
        values["preset"] = _preset_of(tc.model_config)
    elif tc.preset is None:
        values["preset"] = TRAIN_DEFAULTS["preset"]
    return dataclasses.replace(tc, **values)


def _resume_settings(tc: TrainConfig, info: dict, cfg: ModelConfig, run_dir: Path) -> tuple[TrainConfig, dict]:
    """The settings a resume of the run (``run.json`` ``info``, model config ``cfg``) trains with,
    and what the resume changes (``{name: [run's value, new value]}``, for ``overrides``).

    Raises:
        ValueError: a :data:`RUN_SETTINGS` field of ``tc`` differs from the run's (names the
            flag, the run's value and the given one).
    """
    recorded = info.get("train") if isinstance(info.get("train"), dict) else {}
    run_values = {name: recorded.get(name) for name in RUN_SETTINGS}
    run_values["seed"] = recorded.get("seed", info.get("seed"))
    rec_preset = recorded.get("preset")
    if rec_preset in MODEL_PRESETS and _architecture(model_config_for(rec_preset)) == _architecture(cfg):
        run_values["preset"] = rec_preset
    else:  # a custom config, or a run.json written by an older resume that recorded its default preset
        run_values["preset"] = _preset_of(cfg)
    # what the run trains for, when run.json recorded None (the preset's value)
    effective = {"iterations": cfg.iterations,
                 "generator_iterations": info.get("generator_iterations", cfg.generator_iterations)}
    values = {}
    for name in RUN_SETTINGS:
        given, run_value = getattr(tc, name), run_values[name]
        values[name] = tuple(run_value) if isinstance(run_value, list) else run_value
        if given is None:
            continue
        if name == "preset":
            same = given == run_value or _architecture(model_config_for(given)) == _architecture(cfg)
        elif name == "seed" and run_value is None:  # a run.json from before seeds were recorded
            same, values[name] = True, given
        else:
            same = _plain(given) == _plain(run_value) or (name in effective and given == effective[name])
        if not same:
            shown = effective[name] if run_value is None and name in effective else run_value
            if name == "preset" and shown is None:
                shown = "(a model config of no preset)"
            flag = "--" + name.replace("_", "-")
            raise ValueError(f"{flag} {_show(name, given)}: the run in {run_dir} was trained with {name} "
                             f"{_show(name, shown)}; --resume continues a run as it is (leave {flag} out, or "
                             f"train a new run into another --out)")
    changes = {}
    for name in OVERRIDABLE_SETTINGS:
        given, run_value = getattr(tc, name), recorded.get(name, TRAIN_DEFAULTS.get(name))
        values[name] = run_value
        if given is not None and _plain(given) != _plain(run_value):
            values[name] = given
            changes[name] = [run_value, _plain(given)]
    if tc.stop_after is not None:
        changes["stop_after"] = [recorded.get("stop_after"), tc.stop_after]
    if tc.scene is not None and info.get("scene"):
        rec_scene = Path(info["scene"])
        rec_scene = rec_scene if rec_scene.is_absolute() else run_dir / rec_scene
        if Path(tc.scene).resolve() != rec_scene.resolve():
            changes["scene"] = [info["scene"], str(tc.scene)]
    resolved = dataclasses.replace(tc, **values)
    # a run.json from before these settings were recorded: the defaults
    return dataclasses.replace(resolved, **{k: v for k, v in TRAIN_DEFAULTS.items()
                                            if k != "preset" and getattr(resolved, k) is None}), changes


class _HeldInterrupts:
    """SIGINT and SIGTERM wait while :meth:`hold` is active, then act (e.g. raise KeyboardInterrupt).

    The handlers are wrapped only from the main thread and only where they are Python functions
    (Python's default SIGINT handler, ``garmentnerf train``'s SIGTERM one); ``with`` restores them.
    """

    def __init__(self):
        self._previous: dict = {}
        self._holding = False
        self._pending = None

    def __enter__(self) -> "_HeldInterrupts":
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                handler = signal.getsignal(sig)
                if callable(handler):
                    self._previous[sig] = handler
                    signal.signal(sig, self._handle)
        return self

    def __exit__(self, *exc) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous = {}

    def _handle(self, signum, frame) -> None:
        if self._holding:
            self._pending = (signum, frame)
            return
        self._previous[signum](signum, frame)

    @contextlib.contextmanager
    def hold(self):
        """Run the body without interruption by SIGINT/SIGTERM; one that came meanwhile acts after it."""
        self._holding = True
        try:
            yield
        finally:
            self._holding = False
        pending, self._pending = self._pending, None
        if pending is not None:
            self._previous[pending[0]](*pending)


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
        ckpts = []
        problem = None
        if tc.resume:
            if not (out / RUN_FILE).is_file():
                if (out / CHECKPOINT_DIR).is_dir() or (out / TB_DIR).is_dir():
                    problem = FileNotFoundError(f"{out / RUN_FILE}: missing: the run stopped before its first "
                                                f"checkpoint; remove {out} and start it again")
                else:
                    problem = FileNotFoundError(f"{out / RUN_FILE}: missing; --resume needs a run folder made by "
                                                f"'garmentnerf train'")
            else:
                resume_info = read_run_info(out)
                ckpts = checkpoints(out)
                if not ckpts:
                    problem = FileNotFoundError(f"{out / CHECKPOINT_DIR}: no complete checkpoint "
                                                f"(ckpt_<step>.safetensors + ckpt_<step>.state.pt) to resume from")
        elif out.exists() and (not out.is_dir() or any(out.iterdir())):
            problem = ValueError(f"{out}: run folder is not empty; pass --resume to continue the run in it, "
                                 f"or choose another --out")
        if not self.dist.all_ok(problem is None):
            raise problem if problem is not None else ValueError("another rank refused to start (see its message)")

        # settings, scene and config
        setting_changes = {}
        if resume_info is not None:
            try:
                cfg = ModelConfig.from_dict(dict(resume_info["model_config"]))
            except (TypeError, ValueError) as exc:
                raise ValueError(f"{out / RUN_FILE}: model_config: {exc}") from exc
            tc, setting_changes = _resume_settings(tc, resume_info, cfg, out)
            try:
                tc.validate()
            except ValueError as exc:
                raise ValueError(f"{out / RUN_FILE}: train: {exc}") from exc
            self.tc = tc
            if self.dist.main:
                removed = remove_run_temporaries(out)
                if removed:
                    self.log(f"removed {len(removed)} temporary file(s) of interrupted writes: "
                             + ", ".join(p.name for p in removed))
            scene_path = tc.scene
            if scene_path is None and resume_info.get("scene"):
                p = Path(resume_info["scene"])
                scene_path = p if p.is_absolute() else out / p
        else:
            tc = self.tc = _new_run_settings(tc)
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
        self.overrides = list((resume_info or {}).get("overrides", []))
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
        self.last_checkpoint_step = None
        if ckpts:
            self._resume_from(ckpts)
            if setting_changes:
                self.overrides.append({"step": self.step, **setting_changes})
                self.log("settings from step " + str(self.step) + ": " +
                         ", ".join(f"{k} {_show(k, a)} -> {_show(k, b)}" for k, (a, b) in setting_changes.items()))
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
                 + (f", resuming at step {self.step}" if ckpts else ""))

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
                "train": {**self.tc.to_json(), "scene": str(self.scene_path)},
                "loss_weight_changes": self.loss_weight_changes,
                "overrides": self.overrides}

    def save_checkpoint(self, rng_state: dict | None = None) -> Path | None:
        """Write ``checkpoints/ckpt_<step>`` (weights, then state) and the run's model files; rank 0 only.

        Raises:
            CheckpointWriteError: a write failed (full disk, ...); the message names the
                checkpoint folder. An incomplete checkpoint is removed (the previous ones stay).
        """
        if not self.dist.main:
            return None
        step = self.step
        folder = self.out / CHECKPOINT_DIR
        weights = folder / f"ckpt_{step}.safetensors"
        state_file = folder / f"ckpt_{step}.state.pt"
        state = {"step": step, "stage": self.stage, "optimizer": self.optimizer.state_dict(),
                 "rng": rng_state if rng_state is not None else _rng_state(),
                 "generator_iterations": self.generator_iterations, "model_config": self.cfg.to_dict(),
                 "seed": self.tc.seed, "world_size": self.dist.world}
        complete, writing = False, folder
        try:
            folder.mkdir(parents=True, exist_ok=True)
            writing = weights
            save_weights(weights, self.model, {"step": step})
            buffer = io.BytesIO()  # serialised in memory: a full disk is then an OSError of the write
            torch.save(state, buffer)
            writing = state_file
            write_file_atomic(state_file, buffer.getvalue())
            complete, writing = True, self.out
            save_run_model(self.out, self.model, self.cfg, self.scene_path, step, self._run_extra())
        except BaseException as exc:
            if not complete:  # no half checkpoint: weights without their state would never be resumed
                for path in (weights, state_file):
                    with contextlib.suppress(OSError):
                        path.unlink(missing_ok=True)
            if isinstance(exc, OSError):
                raise self._write_error(exc, step, complete, writing) from exc
            raise
        self._prune_checkpoints(folder)
        self.last_checkpoint = state_file
        self.last_checkpoint_step = step
        return state_file

    def _write_error(self, exc: OSError, step: int, complete: bool, writing: Path) -> CheckpointWriteError:
        """The one-line error of a failed checkpoint write (``writing``: the file or folder written)."""
        folder = self.out / CHECKPOINT_DIR
        reason = exc.strerror or _one_line(exc)
        named = exc.filename if exc.filename is not None else writing.name
        if str(named) not in reason and Path(str(named)).name not in reason:
            reason = f"{named}: {reason}"
        if complete:
            what = (f"the checkpoint of step {step} is written but the run files in {self.out} are not "
                    f"({reason})")
        else:
            prev = self.last_checkpoint_step
            what = (f"cannot write the checkpoint of step {step} ({reason}); nothing of it is kept, "
                    + (f"the newest checkpoint is step {prev}" if prev is not None else "no checkpoint yet"))
        if complete or self.last_checkpoint_step is not None:
            then = f"free space, then continue with 'garmentnerf train --out {self.out} --resume'"
        else:
            then = f"free space, remove {self.out} and start the run again"
        return CheckpointWriteError(f"{folder}: {what}; {then}", exc.errno)

    def _prune_checkpoints(self, folder: Path) -> None:
        """Keep the newest ``keep_checkpoints`` complete checkpoints up to the current step; delete
        the older ones and the files of any other (beyond the current step, or without its pair:
        left by a killed or failed run, or skipped as unreadable on resume)."""
        done = [s for s, _, _ in checkpoints(self.out) if s <= self.step]
        keep = set(done[:self.tc.keep_checkpoints])
        for path in folder.iterdir():
            m = _CKPT_FILE.match(path.name)
            if m and int(m.group(1)) not in keep:
                path.unlink(missing_ok=True)

    def _resume_from(self, ckpts: list[tuple[int, Path, Path]]) -> None:
        """Load the newest readable checkpoint of ``ckpts`` (newest first); each unreadable one is
        skipped with a notice naming it. ValueError naming the folder when none is readable."""
        problems = []
        for i, (step, weights, state_file) in enumerate(ckpts):
            try:
                self._load_checkpoint(step, weights, state_file)
                return
            except (ValueError, FileNotFoundError) as exc:
                problems.append(_one_line(exc))
                if i + 1 < len(ckpts):
                    self.log(f"note: skipping the checkpoint of step {step}: {problems[-1]}; "
                             f"trying the one of step {ckpts[i + 1][0]}")
        raise ValueError(f"{self.out / CHECKPOINT_DIR}: no readable checkpoint to resume from "
                         f"({'; '.join(problems)})")

    def _load_checkpoint(self, step: int, weights: Path, state_file: Path) -> None:
        try:
            state = torch.load(state_file, map_location="cpu", weights_only=True)
        except Exception as exc:
            raise ValueError(f"{state_file}: unreadable checkpoint state ({_one_line(exc)})") from exc
        if not isinstance(state, dict) or not {"step", "optimizer", "rng"} <= set(state):
            raise ValueError(f"{state_file}: not a checkpoint state (no step, optimizer and rng)")
        if state.get("step") != step:
            raise ValueError(f"{state_file}: holds step {state.get('step')}, its name says {step}")
        load_weights(weights, self.model)
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
        try:
            _set_rng_state(state["rng"])
        except (KeyError, IndexError, TypeError, ValueError) as exc:
            raise ValueError(f"{state_file}: unreadable RNG state ({_one_line(exc)})") from exc
        self.dist.broadcast_module(self.model)
        self.last_checkpoint = state_file
        self.last_checkpoint_step = step

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
        rng_done = _rng_state()  # the RNG state after the last completed step (what a checkpoint holds)
        interrupted = False
        t_start, s_start = time.perf_counter(), self.step
        with _HeldInterrupts() as interrupts:  # see hold() below
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
                    with interrupts.hold():  # a step is applied whole or not at all
                        self.optimizer.step()
                        self.step = step + 1
                        rng_done = _rng_state()
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
                        self.save_checkpoint(rng_done)
                    if self.step_callback is not None:
                        self.step_callback(self.step, values)
            except KeyboardInterrupt:
                interrupted = True
                bar.close()
                # the step that was running is abandoned: save the last completed one (unless saved)
                if self.last_checkpoint_step != self.step:
                    self.save_checkpoint(rng_done)
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
