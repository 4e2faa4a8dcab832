"""Two-stage training of the Garment Animation NeRF on a scene (paper Sec. 4.4; numbers in
``implementation-notes.md`` Sec. 1.8).

Stage 1 -- G_img pre-training (``cfg.schedule.generator_iterations`` steps; skipped when the detail
    feature is ablated). The neural texture and G_img learn to reproduce the ground-truth front
    and back reference images (the scene's ``ref_front`` / ``ref_back`` cameras) of the training
    frames from the body's UVs seen by those cameras: ``cfg.schedule.batch_size`` frames (each both
    references, DNG's batch of 2) per step, ``loss.image * L1 + loss.perceptual * perceptual``, Adam
    at :data:`~garmentnerf.model.config.GENERATOR_LR`.
    Then G_img is frozen (:meth:`GarmentAnimationNeRF.set_image_generator_frozen`) and its
    reference images are computed once per frame and cached (it no longer changes).
    Left out from DNG: the SPADE temporal conditioning and the adversarial losses (see
    :mod:`garmentnerf.model.image_generator`).
Stage 2 -- the NeRF (``cfg.schedule.iterations`` steps). E, G_en, M_NeRF, M_D and the palette, with
    :func:`garmentnerf.model.losses.garment_losses` (weights from the config: L1 image + L1
    mask 1, perceptual 0.1, sparsity 2e-4, offsets 0.03, palette 1e-3). ``cfg.schedule.batch_size`` (frame,
    training camera) pairs per step (paper: 1), each rendered as the full feature image
    (``cfg.decoder.feature_image_resolution`` squared rays, decoded to ``cfg.decoder.image_resolution``): what the
    pipeline renders. The image is the
    whole camera, or with ``cfg.schedule.training_crop_density`` a window of the camera at that density
    placed on the character (:meth:`~garmentnerf.train.frames.SceneFrames.training_view`). The
    samples go where the ``reference`` render preset puts them: the paper's box. Adam with
    ``lr`` decaying exponentially to ``lr_final`` over ``cfg.schedule.iterations``
    (``lr_n = lr * (lr_final / lr) ** (n / iterations)``), gradients clipped by value
    (:data:`~garmentnerf.model.config.GRAD_CLIP_VALUE`).

Steps are counted globally: ``[0, G)`` stage 1, ``[G, G + N)`` stage 2; checkpoints and
``run.json`` ``step`` use that count.

Determinism and exact resume
    What each step trains on and its ray jitter depend only on ``(seed, rank, step)``: the
    i-th (frame, camera) of step s (``i < b``, the batch size) is entry ``((s * world + rank) * b + i)
    mod n`` of a permutation drawn from ``(seed, epoch)`` (every rank the same permutation, each its
    own share: the ``DistributedSampler`` partitioning), and the jitter generator, one per step, is
    seeded from ``(seed, rank, step)``. The batch's images are backpropagated one at a time, their
    gradients adding up (gradient accumulation: one image's graph in memory at a time). A
    checkpoint holds the weights (``.safetensors``), the optimiser state, the step and the
    python/numpy/torch RNG states (``.state.pt``); resuming from it gives the same losses as an
    uninterrupted run (tested bit-equal on the CPU).

Interruption, kills and a full disk
    Ctrl-C (``KeyboardInterrupt``) during a step abandons that step, writes a checkpoint of the
    last completed one (with the RNG states taken at that step's end) and returns with
    ``interrupted=True``; ``garmentnerf train ... --resume`` continues. SIGINT and SIGTERM that
    arrive while a step's update is applied (``optimizer.step()`` and the step count) are held
    until it is done, so a checkpoint never holds a half-updated step. Every file is written
    atomically (synced temporary + rename): a killed process (SIGKILL, power loss) leaves the
    previous complete checkpoint, plus temporaries that the next resume deletes. A write that
    fails (full disk, ...) removes the checkpoint it was writing and stops with
    :class:`~garmentnerf.train.checkpoints.CheckpointWriteError` naming the checkpoint folder.

Resume
    ``resume=True`` continues the run in ``out`` with the settings recorded in its ``run.json``
    (``train``: preset, seed, sequences, frames, cameras, iterations, checkpoint and log
    intervals, perceptual loss, ...); a :class:`~garmentnerf.train.settings.TrainConfig` field left at None takes the run's
    value. A field that would change what the run is (:data:`~garmentnerf.train.settings.RUN_SETTINGS`) and differs from
    the run's value is refused (ValueError naming the flag, the run's value and the given one);
    one that only changes how it goes on (:data:`~garmentnerf.train.settings.OVERRIDABLE_SETTINGS`, ``stop_after``, the
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
    checkpoints and the run files. The effective batch is ``world_size * batch_size`` images per
    step.

Caches
    Per-frame inputs and targets stay in memory on the CPU (:class:`~garmentnerf.train.frames.SceneFrames`),
    each in a byte-bounded LRU (``TrainConfig.inputs_cache_bytes``, ``cache_bytes``). There are no
    data-loader workers: a frame's inputs are built on first use (a few ms of GL) and later steps
    read memory until the cache evicts them. The body geometry of a frame (its bound closest-point
    search, vertex normals and box) is built at the frame's first NeRF step and reused by the later ones, in a byte-bounded LRU too
    (``TrainConfig.geometry_cache_bytes``, :attr:`Trainer.geometry_cache`): rebuilding it cost ~10 %
    of a step of the bundled recipe. With the encoders frozen (a codes-only stage), their outputs
    are kept with it, and the frame's later steps run neither E nor G_en. All three grow with the
    training frames (a four-sequence scene has 680), so all three are bounded.
"""

from __future__ import annotations

import contextlib
import functools
import io
import math
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch.utils.tensorboard import SummaryWriter
from tqdm import tqdm

from garmentnerf.cpu_load import BusyWatch, OtherProcessesLoad
from garmentnerf.data.scene import Scene, read_garment_arrays
from garmentnerf.folder_lock import folder_has_files, lock_folder
from garmentnerf.gl.body_layer_pass import BodyLayerPass
from garmentnerf.interrupts import HeldInterrupts
from garmentnerf.io_utils import write_file_atomic
from garmentnerf.lifecycle import Closeable
from garmentnerf.model.body_appearance import BODY_APPEARANCE_FILE, load_body_appearance, save_body_appearance
from garmentnerf.model.config import BBOX_PADDING, GENERATOR_LR, GRAD_CLIP_VALUE, ModelConfig, convert_flat_config
from garmentnerf.model.frame_codes import adapt_frame_codes, garment_texels, grow_texels
from garmentnerf.model.frame_context import frame_vertices
from garmentnerf.model.losses import garment_losses, generator_losses
from garmentnerf.model.samplers import padded_box
from garmentnerf.render.body_layer import frame_body_layer
from garmentnerf.render.presets import get_render_preset
from garmentnerf.runs import (
    RUN_FILE,
    body_info_from_scene,
    build_model,
    check_scene_for_run,
    frame_code_record,
    load_weights,
    read_run_info,
    recorded_scene_path,
    run_garment,
    save_run_model,
    save_weights,
)
from garmentnerf.train.byte_cache import tensor_bytes, tensor_cache, tensor_pointers
from garmentnerf.train.checkpoints import (
    CheckpointWriteError,
    checkpoint_files,
    checkpoint_write_error,
    checkpoints,
    first_line,
    latest_checkpoint,
    prune_checkpoints,
    read_checkpoint_state,
    rng_state,
    set_rng_state,
)
from garmentnerf.train.distributed import Distributed
from garmentnerf.train.frames import SceneFramesFactory
from garmentnerf.train.perceptual import make_perceptual
from garmentnerf.train.run import CHECKPOINT_DIR, TB_DIR, load_module_weights, remove_run_temporaries
from garmentnerf.train.settings import (
    MODEL_PRESETS,
    OVERRIDABLE_SETTINGS,
    RUN_SETTINGS,
    TrainConfig,
    model_config_for,
    new_run_settings,
    resume_settings,
    show_setting,
)
from garmentnerf.train.transfer import transfer_garment_state

# The settings and checkpoint names are defined in :mod:`.settings` and :mod:`.checkpoints`; they
# stay importable from here, where callers have always found them.
__all__ = ["Trainer", "TrainResult", "train", "TrainConfig", "MODEL_PRESETS", "model_config_for",
           "latest_checkpoint", "checkpoints", "CheckpointWriteError", "RUN_SETTINGS", "OVERRIDABLE_SETTINGS"]

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


def _seed_of(*parts: int) -> int:
    """A 63-bit seed from integers (the (frame, camera) order and the ray jitter of a step)."""
    return int(np.random.SeedSequence([int(p) for p in parts]).generate_state(1, np.uint64)[0] >> 1)


def param_groups(model, params: list[torch.nn.Parameter], code_lr_scale: float) -> list[dict]:
    """Adam parameter groups of ``params``, each with an ``lr_scale`` the schedule multiplies: the
    per-frame codes (``model.frame_code_prefixes()``) at ``code_lr_scale``, everything else at 1.
    Groups left empty are dropped."""
    prefixes = model.frame_code_prefixes()
    code_ids = {id(p) for name, p in model.named_parameters() if name.startswith(prefixes)} if prefixes else set()
    groups = [{"params": [p for p in params if id(p) not in code_ids], "lr_scale": 1.0},
              {"params": [p for p in params if id(p) in code_ids], "lr_scale": float(code_lr_scale)}]
    return [g for g in groups if g["params"]]


def trained_parameter_ids(model, prefixes: tuple[str, ...]) -> set[int]:
    """``id`` of each parameter of ``model`` whose name starts with one of ``prefixes``
    (:attr:`ModelConfig.trained_parameters`); ValueError naming a prefix no parameter has."""
    named = list(model.named_parameters())
    for prefix in prefixes:
        if not any(name.startswith(prefix) for name, _ in named):
            tops = sorted({name.split(".")[0] + "." for name, _ in named})
            raise ValueError(f"model_config.schedule.trained_parameters: no parameter of the model starts with '{prefix}' "
                             f"(its parameters start with {', '.join(tops)})")
    return {id(p) for name, p in named if name.startswith(prefixes)}


class Trainer(Closeable):
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
        self.dist = Distributed(tc.device)
        self._log = log
        self.out = Path(tc.out)
        self.step_callback: Callable[[int, dict], None] | None = None
        self._lock = None  # the run folder's writer lock (the main process's), from _check_run_folder to close()
        if tc.threads:
            torch.set_num_threads(int(tc.threads))
        self._busy_watch = BusyWatch(torch.get_num_threads(), "this training")  # checked at the start and checkpoints
        try:
            self._setup(gl_context)
        except BaseException:
            self._release_lock()
            self.dist.close()
            raise

    def _release_lock(self) -> None:
        if self._lock is not None:
            self._lock.release()
            self._lock = None

    # ---- setup -------------------------------------------------------------------------------------
    def log(self, message: str) -> None:
        if not self.dist.main:
            return
        if self._log is not None:
            self._log(message)
        else:
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
        resume_info, ckpts = self._check_run_folder()
        cfg, setting_changes = self._settle_settings(resume_info)
        self._load_scene(resume_info)
        weight_changes = self._settle_config(cfg, resume_info)
        self._select_training_set()
        self._build_model(gl_context, resume_info)
        self._start_position(ckpts, resume_info, setting_changes, weight_changes)
        self.dist.barrier()
        self.log(f"{len(self.frames_list)} frames x {len(self.cameras)} cameras, {self.generator_iterations} G_img + "
                 f"{self.cfg.schedule.iterations} NeRF steps, perceptual: {self.perceptual_name}, device: {self.device}, "
                 f"MLP precision: {self.tc.precision}"
                 + (f", {self.dist.world} processes" if self.dist.active else "")
                 + (f", resuming at step {self.step}" if ckpts else ""))

    def _check_run_folder(self) -> tuple[dict | None, list[tuple[int, Path, Path]]]:
        """(``run.json`` of the run resumed or None, its complete checkpoints newest first), with the
        folder's writer lock taken (by the main process); raises (on every rank together) when another
        process writes into ``out``, or ``out`` cannot be resumed or is not empty for a new run."""
        out = self.out
        resume_info = None
        ckpts = []
        problem = None
        if self.dist.main:  # one writer per run folder (garmentnerf.folder_lock); the other ranks follow the main one
            try:
                self._lock = lock_folder(out, "garmentnerf train" + (" --resume" if self.tc.resume else ""))
            except ValueError as exc:
                problem = exc
        if problem is None and self.tc.resume:
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
        elif problem is None and folder_has_files(out):
            problem = ValueError(f"{out}: run folder is not empty; pass --resume to continue the run in it, "
                                 f"or choose another --out")
        if not self.dist.all_ok(problem is None):
            raise problem if problem is not None else ValueError("another rank refused to start (see its message)")
        return resume_info, ckpts

    def _settle_settings(self, resume_info: dict | None) -> tuple[ModelConfig, dict]:
        """Resolve ``self.tc`` (a new run's defaults, or the resumed run's settings); returns the
        model config before this run's changes and what a resume changes (for ``overrides``)."""
        tc, out = self.tc, self.out
        if resume_info is None:
            self.tc = tc = new_run_settings(tc)
            return (tc.model_config if tc.model_config is not None else model_config_for(tc.preset)), {}
        try:
            recorded = dict(resume_info["model_config"])
            cfg = ModelConfig.from_dict(recorded)
            gone = [] if all(isinstance(v, dict) for v in recorded.values()) else convert_flat_config(recorded)[1]
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{out / RUN_FILE}: model_config: {exc}") from exc
        if gone:
            raise ValueError(f"{out / RUN_FILE}: the run trained with {', '.join(gone)}, which this version no longer "
                             "has; it renders as it was trained, but --resume would not continue it as it began")
        tc, setting_changes = resume_settings(tc, resume_info, cfg, out)
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
        return cfg, setting_changes

    def _load_scene(self, resume_info: dict | None) -> None:
        """``self.scene`` from ``--scene``, else (a resume) the folder the run recorded."""
        scene_path = self.tc.scene
        if resume_info is not None and scene_path is None and resume_info.get("scene"):
            # resolved, so the resume's record names the folder itself
            scene_path = recorded_scene_path(self.out, resume_info)
        if scene_path is None:
            raise ValueError("no scene given (--scene)")
        self.scene_path = Path(scene_path)
        if not (self.scene_path / "scene.json").is_file() and not self.scene_path.suffix == ".json":
            raise FileNotFoundError(f"{self.scene_path / 'scene.json'}: missing (--scene must be a scene folder)")
        self.scene = Scene.load(self.scene_path)
        if resume_info is not None and self.tc.scene is not None:  # another scene for a run: it must fit it
            cfg = ModelConfig.from_dict(dict(resume_info["model_config"]))
            check_scene_for_run(self.out, resume_info, cfg.decoder.palette_size, self.scene)

    def _settle_config(self, cfg: ModelConfig, resume_info: dict | None) -> dict[str, float]:
        """``self.cfg`` (``cfg`` with this run's iterations and loss weights), the step counts and the
        run's records of changes; returns the loss weights this run changes."""
        tc = self.tc
        changes = {}
        if tc.iterations is not None:
            changes["schedule.iterations"] = int(tc.iterations)
        if tc.generator_iterations:
            changes["schedule.generator_iterations"] = int(tc.generator_iterations)
        if tc.training_crop_density is not None and float(tc.training_crop_density) != cfg.schedule.training_crop_density:
            if resume_info is not None:
                raise ValueError(f"--training-crop-density {tc.training_crop_density:g}: the run in {self.out} was "
                                 f"trained with {cfg.schedule.training_crop_density:g}; --resume continues a run as it is")
            changes["schedule.training_crop_density"] = float(tc.training_crop_density)
        weight_changes = {k: float(v) for k, v in (tc.loss_weights or {}).items() if getattr(cfg.loss, k) != float(v)}
        changes.update({f"loss.{k}": v for k, v in weight_changes.items()})
        cfg = cfg.updated(changes) if changes else cfg
        self.cfg = cfg
        self.loss_weight_changes = list((resume_info or {}).get("loss_weight_changes", []))
        self.overrides = list((resume_info or {}).get("overrides", []))
        gen_iters = cfg.schedule.generator_iterations if tc.generator_iterations is None else int(tc.generator_iterations)
        if resume_info is not None and tc.generator_iterations is None:
            gen_iters = int(resume_info.get("generator_iterations", gen_iters))
        self.generator_iterations = gen_iters if cfg.encoder.detail_feature else 0
        self.total_steps = self.generator_iterations + cfg.schedule.iterations
        if self.scene.palette_init is None:
            self.log(f"{self.scene.scene_file}: no palette_init; the palette starts at mid grey")
        return weight_changes

    def _select_training_set(self) -> None:
        """``frames_list`` ((sequence, frame) of stage 1), ``cameras`` and ``pairs`` ((sequence,
        frame, camera) of stage 2), checked against the scene."""
        tc, scene = self.tc, self.scene
        seqs = list(tc.sequences) if tc.sequences else scene.sequence_names("train")
        if not seqs:
            raise ValueError(f"{scene.scene_file}: no training sequence (split 'train')")
        frames = []
        for s in seqs:
            n = scene.num_frames(s)
            idx = list(range(n)) if tc.frames is None else [scene.check_frame(s, f) for f in tc.frames]
            frames += [(s, f) for f in idx]
        cams = list(tc.cameras) if tc.cameras else scene.camera_names("train")
        if not cams:
            raise ValueError(f"{scene.scene_file}: no training camera (split 'train')")
        for c in cams:
            scene.camera(c)
        if self.generator_iterations:
            names = set(scene.camera_names())
            missing = [n for n in ("ref_front", "ref_back") if n not in names]
            if missing:
                raise ValueError(f"{scene.scene_file}: G_img pre-training needs the reference cameras "
                                 f"{', '.join(missing)}")
        self.frames_list = frames
        self.cameras = cams
        self.pairs = [(s, f, c) for (s, f) in frames for c in cams]
        self._settle_frame_codes(seqs)

    def _settle_frame_codes(self, seqs: list[str]) -> None:
        """The per-frame codes (``FrameCodeConfig``): one per frame of the training
        sequences ``seqs`` (all their frames, so that a code's index is its sequence's offset plus the
        frame), their count set in ``self.cfg`` on a new run and checked on a resume."""
        self.code_offsets: dict[str, int] = {}
        if not self.cfg.frame_codes.resolution:
            return
        count = 0
        for s in seqs:
            self.code_offsets[s] = count
            count += self.scene.num_frames(s)
        if self.cfg.frame_codes.count == 0:
            self.cfg = self.cfg.updated({"frame_codes.count": count})
        elif self.cfg.frame_codes.count != count:
            raise ValueError(f"{self.out}: the run has {self.cfg.frame_codes.count} per-frame codes, its training "
                             f"sequences ({', '.join(seqs)}) have {count} frames")

    def code_index(self, seq: str, frame: int) -> int | None:
        """The per-frame code of training frame (``seq``, ``frame``), or None (no codes, or not a
        training sequence)."""
        offset = self.code_offsets.get(seq)
        return None if offset is None else offset + int(frame)

    def _build_model(self, gl_context, resume_info: dict | None) -> None:
        """The model (seeded, the same on every rank), the perceptual network, the frame data and
        the training state at step 0."""
        tc, cfg = self.tc, self.cfg
        self.device = self._device()
        torch.manual_seed(tc.seed)
        self.model = build_model(cfg, self.scene.palette_init).to(self.device)
        self.dist.broadcast_module(self.model)

        self.perceptual, self.perceptual_name = make_perceptual(tc.perceptual, tc.vgg19_weights, cfg.loss.perceptual)
        if self.perceptual is not None:
            self.perceptual = self.perceptual.to(self.device)
        if resume_info is not None and resume_info.get("perceptual") not in (None, self.perceptual_name):
            self.log(f"note: the run was trained with perceptual '{resume_info.get('perceptual')}', "
                     f"continuing with '{self.perceptual_name}'")
        self.data = SceneFramesFactory(self.scene, cfg, gl_context, self.model.body, tc.cache_bytes,
                                       tc.inputs_cache_bytes)
        self.body_appearance = self._body_appearance(resume_info)
        self._body_pass = None  # the BodyLayerPass of the body layer, made on first use
        self.sampling = get_render_preset("reference").sampling(self.model, None, self.data.frames.ctx)
        #: The frames' body geometry kept between steps, by (sequence, frame).
        self.geometry_cache = tensor_cache(tc.geometry_cache_bytes, self._geometry_bytes)
        self._model_tensors: frozenset[int] | None = None
        self.step = 0
        self.optimizer = None
        self.stage = None
        self.writer = None
        self.last_checkpoint = None
        self.last_checkpoint_step = None

    def _body_appearance(self, resume_info: dict | None):
        """The frozen body appearance the NeRF steps compose with (:attr:`TrainConfig.body_appearance`),
        or None; a new run reads the given file (and copies it into the run folder with its first
        checkpoint, where renders find it), a resume reads that copy."""
        if self.tc.body_appearance is None:
            return None
        copy = self.out / BODY_APPEARANCE_FILE
        if resume_info is not None:
            if not copy.is_file():
                raise FileNotFoundError(f"{copy}: the run composes with a rasterised body but its appearance is gone")
            return load_body_appearance(copy).requires_grad_(False)
        source = Path(self.tc.body_appearance)
        if not source.is_file():
            raise FileNotFoundError(f"--body-appearance {source}: no such file")
        return load_body_appearance(source).requires_grad_(False)

    def _save_body_appearance(self) -> None:
        """The run's copy of its body appearance, written with its first checkpoint (before ``run.json``)."""
        if self.body_appearance is not None and not (self.out / BODY_APPEARANCE_FILE).is_file():
            save_body_appearance(self.out / BODY_APPEARANCE_FILE, self.body_appearance)

    def _start_position(self, ckpts: list[tuple[int, Path, Path]], resume_info: dict | None, setting_changes: dict,
                        weight_changes: dict[str, float]) -> None:
        """Resume from the newest readable checkpoint (recording what the resume changes), or start
        from a pre-trained G_img, or from step 0."""
        tc = self.tc
        if not ckpts:  # a resume takes the codes' support from its checkpoint
            self._find_code_support()
        if ckpts:
            self._resume_from(ckpts)
            if setting_changes:
                self.overrides.append({"step": self.step, **setting_changes})
                self.log("settings from step " + str(self.step) + ": " +
                         ", ".join(f"{k} {show_setting(k, a)} -> {show_setting(k, b)}"
                                   for k, (a, b) in setting_changes.items()))
            if weight_changes:
                old = ModelConfig.from_dict(dict(resume_info["model_config"]))
                record = {"step": self.step, **{k: [getattr(old.loss, k), v] for k, v in weight_changes.items()}}
                self.loss_weight_changes.append(record)
                self.log("loss weights from step " + str(self.step) + ": " +
                         ", ".join(f"{k} {getattr(old.loss, k):g} -> {v:g}" for k, v in weight_changes.items()))
        elif tc.init_weights is not None:
            file_garment = run_garment(Path(tc.init_weights).parent)
            same_garment = None if file_garment is None else file_garment == dict(self.scene.garment)
            garment_state = functools.partial(transfer_garment_state, same_garment=same_garment)
            new = load_weights(tc.init_weights, self.model,
                               self.model.frame_code_prefixes(),
                               self.model.growable_prefixes(),
                               adapt=lambda state, own: garment_state(state, own) + adapt_frame_codes(state, own))
            if tc.init_generator is not None:
                load_module_weights(tc.init_generator, self.model, "image_generator")
            self.step = self.generator_iterations
            self._enter_stage(self._stage_of(self.step))
            generator = "" if tc.init_generator is None else f", G_img from {tc.init_generator}"
            self.log(f"all weights from {tc.init_weights}{generator}: G_img pre-training skipped, the NeRF stage "
                     f"starts at step {self.step}")
            if same_garment is None:
                verdict = "no run.json naming a readable scene beside it: decided by its palette's starting colours"
            elif same_garment:
                verdict = f"{file_garment.get('kind')}, this scene's (its run.json's scene): its learned palette kept"
            else:
                verdict = f"{file_garment.get('kind')}, another (its run.json's scene): this scene's colours instead"
            self.log(f"the file's garment: {verdict}")
            if new:
                self.log(f"new or changed in this config (new tensors start at their initialisation, grown ones compute "
                         f"what the file's did, a palette of another size takes the file's garment channels and this "
                         f"scene's colours): {', '.join(new)}")
        elif tc.init_generator is not None and self.generator_iterations:
            load_module_weights(tc.init_generator, self.model, "image_generator")
            self.step = self.generator_iterations
            self._enter_stage(self._stage_of(self.step))
            self.log(f"G_img from {tc.init_generator}: pre-training skipped, starting at step {self.step}")
        else:
            self._enter_stage(self._stage_of(0))

    # ---- stages and optimiser ---------------------------------------------------------------------------
    def _stage_of(self, step: int) -> str:
        return "generator" if step < self.generator_iterations else "nerf"

    def _enter_stage(self, stage: str) -> None:
        m = self.model
        if stage == "generator":
            m.set_image_generator_frozen(False)
            params = [p for p in m.image_generator.parameters()]
            lr = GENERATOR_LR
        else:
            m.set_image_generator_frozen(True)
            params = [p for mod in m.trainable_modules().values() for p in mod.parameters() if p.requires_grad]
            if self.cfg.schedule.trained_parameters:
                trained = trained_parameter_ids(m, self.cfg.schedule.trained_parameters)
                for p in params:
                    p.requires_grad_(id(p) in trained)
                params = [p for p in params if id(p) in trained]
            lr = self.cfg.schedule.lr
        m.train()
        self.params = params
        # fused: one pass over each tensor instead of one per operation (the same update up to rounding),
        # 14 times faster on the CPU for the 5.6 M values of the bundled skirt's per-frame codes
        self.optimizer = torch.optim.Adam(param_groups(m, params, self.cfg.frame_codes.lr_scale), lr=lr, fused=True)
        self.stage = stage

    def lr_at(self, step: int) -> float:
        """Learning rate of global step ``step``."""
        cfg = self.cfg
        if step < self.generator_iterations:
            return GENERATOR_LR
        n = step - self.generator_iterations
        return cfg.schedule.lr * (cfg.schedule.lr_final / cfg.schedule.lr) ** (n / max(1, cfg.schedule.iterations))

    # ---- checkpoints -------------------------------------------------------------------------------
    def _run_extra(self) -> dict:
        return {"perceptual": self.perceptual_name, "body": body_info_from_scene(self.scene),
                "garment": dict(self.scene.garment),
                "generator_iterations": self.generator_iterations,
                "nerf_step": max(0, self.step - self.generator_iterations), "seed": self.tc.seed,
                "train": {**self.tc.to_json(), "scene": str(self.scene_path)},
                "loss_weight_changes": self.loss_weight_changes,
                "overrides": self.overrides,
                **({"frame_codes": frame_code_record(self.scene, self.code_offsets)} if self.code_offsets else {})}

    def save_checkpoint(self, rng: dict | None = None) -> Path | None:
        """Write ``checkpoints/ckpt_<step>`` (weights, then state) and the run's model files; rank 0 only.

        Raises:
            CheckpointWriteError: a write failed (full disk, ...); the message names the
                checkpoint folder. An incomplete checkpoint is removed (the previous ones stay).
        """
        if not self.dist.main:
            return None
        step = self.step
        folder = self.out / CHECKPOINT_DIR
        weights, state_file = checkpoint_files(self.out, step)
        state = {"step": step, "stage": self.stage, "optimizer": self.optimizer.state_dict(),
                 "rng": rng if rng is not None else rng_state(),
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
            self._save_body_appearance()
            save_run_model(self.out, self.model, self.cfg, self.scene_path, step, self._run_extra())
        except BaseException as exc:
            if not complete:  # no half checkpoint: weights without their state would never be resumed
                for path in (weights, state_file):
                    with contextlib.suppress(OSError):
                        path.unlink(missing_ok=True)
            if isinstance(exc, OSError):
                raise checkpoint_write_error(exc, self.out, step, complete, writing,
                                             self.last_checkpoint_step) from exc
            raise
        prune_checkpoints(self.out, self.step, self.tc.keep_checkpoints)
        self.last_checkpoint = state_file
        self.last_checkpoint_step = step
        return state_file

    def _find_code_support(self) -> None:
        """A new run's sparse per-frame codes (``FrameCodeConfig.support_margin``) take their
        support: the texels the garment's closest body points read over the training frames."""
        codes = self.model.frame_codes
        if codes is None or not codes.sparse:
            return
        hit = torch.zeros(codes.resolution, codes.resolution, dtype=torch.bool)
        for seq in self.code_offsets:
            vertices = read_garment_arrays(self.scene.garment_path(seq)).vertices
            posed = self.data.frames.posed(seq)
            for frame in range(len(vertices)):
                points = torch.from_numpy(np.ascontiguousarray(vertices[frame], dtype=np.float32))
                uv = self.model.projector.project(points, frame_vertices(posed, frame)).uv
                hit |= garment_texels(uv, codes.resolution)
        margin = self.cfg.frame_codes.support_margin
        support = grow_texels(hit, margin)
        codes.set_support(support)
        self.log(f"per-frame codes held on {int(support.sum())} of {support.numel()} texels "
                 f"({support.float().mean().item():.1%}: the garment's footprint over the training frames, "
                 f"grown by {margin})")

    def _resume_from(self, ckpts: list[tuple[int, Path, Path]]) -> None:
        """Load the newest readable checkpoint of ``ckpts`` (newest first); each unreadable one is
        skipped with a notice naming it. ValueError naming the folder when none is readable."""
        problems = []
        for i, (step, weights, state_file) in enumerate(ckpts):
            try:
                self._load_checkpoint(step, weights, state_file)
                return
            except (ValueError, FileNotFoundError) as exc:
                problems.append(first_line(exc))
                if i + 1 < len(ckpts):
                    self.log(f"note: skipping the checkpoint of step {step}: {problems[-1]}; "
                             f"trying the one of step {ckpts[i + 1][0]}")
        raise ValueError(f"{self.out / CHECKPOINT_DIR}: no readable checkpoint to resume from "
                         f"({'; '.join(problems)})")

    def _load_checkpoint(self, step: int, weights: Path, state_file: Path) -> None:
        state = read_checkpoint_state(state_file, step)
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
            set_rng_state(state["rng"])
        except (KeyError, IndexError, TypeError, ValueError) as exc:
            raise ValueError(f"{state_file}: unreadable RNG state ({first_line(exc)})") from exc
        self.dist.broadcast_module(self.model)
        self.last_checkpoint = state_file
        self.last_checkpoint_step = step

    # ---- steps -------------------------------------------------------------------------------------
    def _pick(self, items: list, step: int, salt: int, index: int = 0):
        """Image ``index`` (of ``cfg.schedule.batch_size``) of this rank's share of step ``step``."""
        n = len(items)
        g = (step * self.dist.world + self.dist.rank) * self.cfg.schedule.batch_size + index
        epoch, pos = divmod(g, n)
        perm = np.random.default_rng(_seed_of(self.tc.seed, salt, epoch)).permutation(n)
        return items[int(perm[pos])]

    def _generator_step(self, step: int, index: int) -> tuple[dict, dict]:
        seq, frame = self._pick(self.frames_list, step, 1, index)
        inputs = self.data.frames.inputs(seq, frame)
        target = self.data.frames.reference_targets(seq, frame).to(self.device)
        pred = self.model.image_generator(inputs.reference_uv.to(self.device, torch.float32),
                                          inputs.reference_mask.to(self.device))
        terms = generator_losses(pred, target, self.cfg.loss, self.perceptual)
        return terms, {"pred": pred, "target": target}

    def _nerf_inputs(self, seq: str, frame: int):
        frames = self.data.frames
        inputs = frames.inputs(seq, frame)
        if self.cfg.encoder.detail_feature and inputs.reference_images is None:
            with torch.no_grad():
                imgs = self.model.image_generator(inputs.reference_uv.to(self.device, torch.float32),
                                                  inputs.reference_mask.to(self.device))
            frames.set_reference_images(seq, frame, imgs)
            inputs = frames.inputs(seq, frame)
        return inputs

    def _prepared_frame(self, seq: str, frame: int, code: int | None):
        """The frame's features for this step's graph (with per-frame code ``code``, or None), its body
        geometry from the cache (kept for the next visit)."""
        inputs = self._nerf_inputs(seq, frame)
        geometry = self.geometry_cache.get((seq, frame))
        feats = self.model.prepare_frame(inputs, geometry, code=code)
        if self.geometry_cache.budget_bytes > 0:
            keep = self.model.reusable_frame(feats)
            # kept on the first visit, and again when it holds more (the encoders frozen since: a frame
            # prepared before the NeRF stage froze them, e.g. by warm_frames)
            if geometry is None or any(getattr(keep, k) is not None and getattr(geometry, k) is None
                                       for k in ("encoder_output", "detail_features")):
                self.geometry_cache.put((seq, frame), keep)
        return feats

    def warm_frames(self, steps: int) -> int:
        """Prepares the frames the next ``steps`` NeRF steps draw, once each, so that the caches hold
        their inputs and body geometry (with the frozen encoders' outputs) as a long run holds them once
        it has met each frame: the step ``garmentnerf bench --training`` times. Draws no random number
        and trains nothing. Returns the number of frames."""
        frames = set()
        with torch.no_grad():
            for step in range(max(self.step, self.generator_iterations), min(self.step + steps, self.total_steps)):
                for index in range(self.cfg.schedule.batch_size):
                    seq, frame, _ = self._pick(self.pairs, step, 2, index)
                    if (seq, frame) not in frames:
                        frames.add((seq, frame))
                        self._prepared_frame(seq, frame, self.code_index(seq, frame))
        return len(frames)

    def _geometry_bytes(self, geometry) -> int:
        """What a frame's geometry adds to memory: its tensors but those it shares with the model (the
        topology tables every bound body points at, which the model makes on its first frame)."""
        if self._model_tensors is None:
            self._model_tensors = tensor_pointers(self.model)
        return tensor_bytes(geometry, self._model_tensors)

    def _nerf_step(self, step: int, index: int, gen: torch.Generator) -> tuple[dict, dict]:
        seq, frame, cam = self._pick(self.pairs, step, 2, index)
        feats = self._prepared_frame(seq, frame, self.code_index(seq, frame))
        box = padded_box(feats.aabb.detach(), BBOX_PADDING)
        segment = step - self.generator_iterations >= self.cfg.loss.segmentation_start
        camera, window = self.data.frames.training_view(cam, box, gen)
        out = self.model.render(feats, camera, training=True, generator=gen, precision=self.tc.precision,
                                sampler=self.sampling.sampler, sample_filter=self.sampling.sample_filter)
        pred = out.image if self.body_appearance is None else self._with_body(out, feats, camera)
        image, mask, garment = (t.to(self.device) for t in self.data.frames.target(seq, cam, frame, window))
        pal = self.model.palette
        terms = garment_losses(pred[None], image[None], out.maps, mask[None], pal.colors, pal.initial,
                               self.cfg.loss, self.perceptual, opacity=out.opacity[None],
                               target_garment=garment[None] if segment else None)
        return terms, {"pred": pred, "target": image}

    def _backward_batch(self, step: int, stage: str) -> tuple[dict[str, float], dict]:
        """Backpropagates step ``step``'s ``cfg.schedule.batch_size`` images one after the other, each loss
        divided by the batch size, so the gradients add up to those of the batch's mean loss
        while only one image's graph is held at a time. Returns the mean of each loss term over the
        batch and the PSNR of its mean image MSE (floats), and the last image pair (for the log).
        The ray jitter of the whole step comes from one generator seeded from ``(seed, rank, step)``."""
        batch = self.cfg.schedule.batch_size
        gen = torch.Generator().manual_seed(_seed_of(self.tc.seed, self.dist.rank, step))
        sums: dict[str, float] = {}
        for index in range(batch):
            if stage == "generator":
                terms, images = self._generator_step(step, index)
            else:
                terms, images = self._nerf_step(step, index, gen)
            (terms["total"] / batch).backward()
            with torch.no_grad():
                terms = {**terms, "mse": (images["pred"].detach() - images["target"]).square().mean()}
            for k, v in terms.items():
                sums[k] = sums.get(k, 0.0) + float(v.detach())
        values = {k: v / batch for k, v in sums.items()}
        if "mse" in values:
            values["psnr"] = -10.0 * math.log10(max(values.pop("mse"), 1e-10))
        return values, images

    def _with_body(self, out, feats, camera) -> torch.Tensor:
        """(3, H, W) the step's image in the ``raster_body`` composition: ``out``'s maps over the
        frame's body (``feats``: posed vertices and normals) rasterised in ``camera`` and drawn with
        the frozen body appearance."""
        if self._body_pass is None:
            self._body_pass = BodyLayerPass(self.data.frames.ctx)
        with torch.no_grad():
            color, coverage = frame_body_layer(self._body_pass, self.model.body, feats, camera, self.body_appearance)
        maps = out.maps.with_body(color.to(self.device), coverage.to(self.device))
        return maps.compose(out.palette, out.background)[0]

    def _writer(self):
        if self.writer is None and self.dist.main:
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
        if images and self.tc.image_every and (step % self.tc.image_every == 0 or step == self.total_steps):
            pred, target = images["pred"].detach(), images["target"]
            if pred.ndim == 4:  # the two references: stack vertically
                pred, target = torch.cat(list(pred), 1), torch.cat(list(target), 1)
            w.add_image(f"{stage}/render_vs_gt", torch.cat([pred, target], 2).clamp(0, 1).cpu(), step)

    def train(self) -> TrainResult:
        """Train to the end (or to ``stop_after``); Ctrl-C saves a checkpoint and returns."""
        tc = self.tc
        end = self.total_steps if tc.stop_after is None else min(self.total_steps, tc.stop_after)
        history: list[dict] = []
        bar = tqdm(total=self.total_steps, initial=self.step, disable=not (tc.progress and self.dist.main),
                   desc="train", unit="step", dynamic_ncols=True, file=sys.stderr)
        rng_done = rng_state()  # the RNG state after the last completed step (what a checkpoint holds)
        interrupted = False
        warning = self._busy_watch.check()  # the set-up's stretch
        if warning is not None:
            self.log(f"warning: {warning}")
        t_start, s_start = time.perf_counter(), self.step
        load = OtherProcessesLoad()
        with HeldInterrupts() as interrupts:  # see hold() below
            try:
                while self.step < end:
                    step = self.step
                    stage = self._stage_of(step)
                    if stage != self.stage:
                        self._enter_stage(stage)
                    lr = self.lr_at(step)
                    for group in self.optimizer.param_groups:
                        group["lr"] = lr * group.get("lr_scale", 1.0)
                    self.optimizer.zero_grad(set_to_none=True)
                    values, images = self._backward_batch(step, stage)
                    self.dist.average_gradients(self.params)
                    torch.nn.utils.clip_grad_value_(self.params, GRAD_CLIP_VALUE)
                    with interrupts.hold():  # a step is applied whole or not at all
                        self.optimizer.step()
                        self.step = step + 1
                        rng_done = rng_state()
                    history.append({"step": self.step, "stage": stage, **values})
                    self._log_step(self.step, stage, values, lr, images)
                    bar.update(1)
                    bar.set_postfix(stage=stage, loss=f"{values['total']:.4f}",
                                    **({"psnr": f"{values['psnr']:.2f}"} if "psnr" in values else {}))
                    boundary = self.step == self.generator_iterations and self.generator_iterations > 0
                    if self.step % tc.ckpt_every == 0 or boundary or self.step == end:
                        if boundary:
                            self._enter_stage("nerf")
                        self.save_checkpoint(rng_done)
                        warning = self._busy_watch.check()
                        if warning is not None:
                            self.log(f"warning at step {self.step}: {warning}")
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
            others = load.stop()
            beside = "" if others is None else f"; other processes used {others:.1f} of {os.cpu_count() or 1} cores"
            self.log(f"{'finished' if done else 'stopped'} at step {self.step}/{self.total_steps} "
                     f"({rate:.2f} s/step{beside}); run: {self.out}")
        return TrainResult(self.step, interrupted, history, self.last_checkpoint, done)

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.writer = None
        if getattr(self, "_body_pass", None) is not None:
            self._body_pass.release()
            self._body_pass = None
        if getattr(self, "sampling", None) is not None:
            self.sampling.release()
            self.sampling = None
        if getattr(self, "data", None) is not None:
            self.data.close()
        self._release_lock()
        self.dist.close()


def train(tc: TrainConfig, gl_context=None) -> TrainResult:
    """Run :class:`Trainer` start to finish (closing it)."""
    with Trainer(tc, gl_context) as trainer:
        return trainer.train()
