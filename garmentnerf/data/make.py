"""``garmentnerf data make``: a complete training scene from a garment kind and motion names.

What it does, in order (every step can be re-run; a killed run continues where it stopped):

1. Builds the motions: the training motion from its clip list (repeated until it has
   ``frames`` frames, then cut), and one held-out sequence per ``test_motions`` entry. With
   ``in_place`` (the default) the slow horizontal drift of the root is removed so the character
   stays inside the camera ring (see :func:`remove_drift`).
2. Writes the scene (cameras, body shape, garment kind and colour, the motions) -- nothing is
   rendered yet: images are rendered on demand from the stored simulation (:mod:`scene`).
3. Simulates the garment on every sequence with newton's VBD solver
   (:func:`~garmentnerf.data.simulate.simulate`), one *process* per sequence because warp's CPU
   kernels are single-threaded. Each simulation writes atomically committed chunks under
   ``<scene>/sim/<sequence>/``; a restarted ``data make`` finds them and computes only what is
   missing, bit-identically (see the simulation module). The parent shows one progress bar over
   all frames by counting committed chunks.
4. Stores each garment sequence (``sequences/<name>/garment.npz``, with its per-frame maximum
   body penetration) and the simulation statistics in ``scene.json``.
5. Renders a few training views to measure the mean garment and body colours for the palette
   initialisation (``palette_init``).

The chunk folders can be deleted once the scene is complete (``keep_chunks=False``).
"""

from __future__ import annotations

import json
import math
import multiprocessing
import shutil
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

#: Seconds of the Gaussian that defines the "slow" root drift removed by :func:`remove_drift`.
DRIFT_SIGMA_S = 1.0


@dataclass
class MakeSpec:
    """Everything that defines a generated scene (stored in ``scene.json`` under ``make``).

    Attributes:
        garment: garment kind (``skirt``, ``tshirt``, ``dress``).
        motion: training motion: clip names joined by ',' (played one after another with blends).
        frames: frames of the training sequence (the clip list is repeated if it is shorter).
        test_motions: held-out motions, one sequence each (``test_<name>``); each may itself be
            a ',' list -- pass a list, not one string.
        test_frames: cap on each held-out sequence's frames (0: the whole clip).
        views: training cameras on the circle.
        held_out_views: cameras between them for the unseen-view test.
        size: image side in pixels (square images).
        radius, height: camera circle radius and height, metres.
        shape: body shape preset or comma-separated coefficients.
        fps: frame rate of every sequence (clips are resampled to it).
        in_place: remove the root's slow horizontal drift (see :func:`remove_drift`).
        processes: simulations run at once (one core each); 0 = one per sequence, capped at the
            number of cores.
    """

    garment: str = "skirt"
    motion: str = "walk"
    frames: int = 300
    test_motions: list[str] = field(default_factory=list)
    test_frames: int = 0
    views: int = 16
    held_out_views: int = 4
    size: int = 512
    radius: float = 3.0
    height: float = 1.0
    shape: str = "average"
    fps: float = 30.0
    in_place: bool = True
    processes: int = 0

    def __post_init__(self) -> None:
        if self.frames < 1:
            raise ValueError(f"--frames must be >= 1, got {self.frames}")
        if self.test_frames < 0:
            raise ValueError(f"--test-frames must be >= 0, got {self.test_frames}")
        if self.views < 1:
            raise ValueError(f"--views must be >= 1, got {self.views}")
        if self.held_out_views < 0:
            raise ValueError(f"--held-out-views must be >= 0, got {self.held_out_views}")
        if self.size < 16:
            raise ValueError(f"--size must be >= 16 pixels, got {self.size}")
        for name in ("radius", "height", "fps"):
            value = float(getattr(self, name))
            if not math.isfinite(value) or (value <= 0 and name != "height"):
                raise ValueError(f"--{name} must be a finite number > 0, got {value}")
        if self.processes < 0:
            raise ValueError(f"--processes must be >= 0, got {self.processes}")


def remove_drift(motion, sigma_s: float = DRIFT_SIGMA_S):
    """The motion with its root's slow horizontal travel removed, centred over the origin.

    A walk then stays in the middle of the camera ring like a walk on a treadmill. Only the
    Gaussian-smoothed (``sigma_s``) horizontal velocity, integrated, is subtracted, so the step-to-step sway
    of the hips stays; the cloth sees the same accelerations except the slow ones (a constant
    velocity changes nothing: the simulation has no air drag).
    """
    from scipy.ndimage import gaussian_filter1d

    trans = motion.translation.detach().cpu().numpy().astype(np.float64)
    out = trans.copy()
    if len(trans) > 1:
        # Smooth the *velocity* and integrate it: the remainder is the integral of the velocity's
        # fast part, which stays bounded (smoothing positions leaves the ends off by the lag).
        velocity = np.diff(trans[:, :2], axis=0)
        drift = gaussian_filter1d(velocity, sigma=max(sigma_s * motion.fps, 1e-6), axis=0, mode="nearest")
        out[1:, :2] -= np.cumsum(drift, axis=0)
    out[:, :2] -= out[:, :2].mean(axis=0)
    return type(motion)(motion.name, motion.joint_names, motion.rotations,
                        torch.as_tensor(out, dtype=torch.float32), motion.fps, motion.skeleton)


def build_motion(spec: str, body, betas, fps: float, frames: int | None, in_place: bool):
    """The motion of one sequence: ``spec`` loaded, repeated to ``frames``, cut, optionally in place."""
    from garmentnerf.motion.library import load_motion

    motion = load_motion(spec, body, betas, fps=fps)
    if frames:
        repeats = 1
        while motion.num_frames < frames:  # blends overlap the clips, so grow until long enough
            repeats += max(1, math.ceil((frames - motion.num_frames) / motion.num_frames * repeats))
            motion = load_motion(",".join([spec] * repeats), body, betas, fps=fps).renamed(spec)
        motion = motion.slice(0, frames)
    if in_place:
        motion = remove_drift(motion)
    return motion


def _sequence_plan(spec: MakeSpec) -> list[tuple[str, str, str, int]]:
    """(sequence name, motion spec, split, frame cap) for every sequence."""
    plan = [("train", spec.motion, "train", spec.frames)]
    for m in spec.test_motions:
        plan.append((f"test_{m.replace(',', '_')}", m, "unseen_motion", spec.test_frames))
    names = [p[0] for p in plan]
    if len(set(names)) != len(names):
        raise ValueError(f"held-out motions must differ: {', '.join(spec.test_motions)}")
    return plan


def _sim_dir(root: Path, sequence: str) -> Path:
    return root / "sim" / sequence


def _simulate_sequence(root: str, sequence: str, kind: str, shape: str, settings_dict: dict) -> dict:
    """Worker process: simulate one sequence of the scene at ``root`` and store its garment."""
    torch.set_num_threads(1)
    _exit_with_parent()
    from garmentnerf.body.model import BodyModel
    from garmentnerf.data.garment_sequence import save_sequence
    from garmentnerf.data.garments import make_garment
    from garmentnerf.data.scene import Scene
    from garmentnerf.data.simulate import SimSettings, simulate

    scene = Scene.load(root, check_files=False)
    body = BodyModel.default()
    betas = body.betas(shape)
    garment = make_garment(kind, body, betas)
    motion = scene.load_motion(sequence)
    settings = SimSettings.from_dict(settings_dict)
    result = simulate(garment, body, motion, betas=betas, settings=settings,
                      out_dir=_sim_dir(Path(root), sequence), progress=False)
    save_sequence(scene.garment_path(sequence), result.vertices, garment.faces, color=garment.color, kind=kind,
                  penetration_max_m=result.penetration_max_m, fps=motion.fps, settings=settings,
                  name=sequence, motion=motion.name, betas=betas.detach().cpu().numpy(), uv=garment.uv)
    pen = result.penetration_max_m
    return {"frames": int(len(pen)), "penetration_max_m": float(pen.max()),
            "penetration_mean_m": float(pen.mean()),
            "frames_over_bound": int((pen > _bound()).sum()), "penetration_bound_m": _bound(),
            "seconds_per_frame": float(result.seconds_per_frame),
            "cpu_seconds_per_frame": (None if math.isnan(result.cpu_seconds_per_frame)
                                      else float(result.cpu_seconds_per_frame)),
            "settings": settings.to_dict()}


def _exit_with_parent(poll_s: float = 2.0) -> None:
    """End this worker when its parent dies (killed ``data make``): committed chunks are safe, and
    an orphan would keep simulating into files the next run is about to write."""
    import os
    import threading

    parent = os.getppid()

    def watch() -> None:
        while True:
            time.sleep(poll_s)
            if os.getppid() != parent:
                os._exit(1)

    threading.Thread(target=watch, daemon=True, name="parent-watch").start()


def _bound() -> float:
    from garmentnerf.data.simulate import PENETRATION_BOUND_M

    return float(PENETRATION_BOUND_M)


def _committed_frames(root: Path, sequences: list[str], chunk_frames: int, totals: dict[str, int]) -> int:
    done = 0
    for name in sequences:
        chunks = len(list(_sim_dir(root, name).glob("chunk_*.npz")))
        done += min(chunks * chunk_frames, totals[name])
    return done


def make_scene(out: str | Path, spec: MakeSpec, *, settings=None, progress: bool = True,
               keep_chunks: bool = True, palette_frames: int = 3):
    """Create (or finish) the scene at ``out`` (see the module docstring). Returns the Scene.

    Raises:
        ValueError: ``out`` holds a scene made with another spec, or bad settings.
        FileExistsError: ``out`` holds other files than a scene.
    """
    from garmentnerf.body.model import BodyModel
    from garmentnerf.data.cameras import default_rig
    from garmentnerf.data.garments import GARMENT_COLORS, GARMENT_KINDS
    from garmentnerf.data.scene import SCENE_FILE, Scene, SceneImages, palette_from_images
    from garmentnerf.data.simulate import SimSettings

    root = Path(out)
    settings = settings or SimSettings()
    if spec.garment not in GARMENT_KINDS:
        raise ValueError(f"unknown garment kind '{spec.garment}' (known: {', '.join(GARMENT_KINDS)})")
    plan = _sequence_plan(spec)
    wanted = {"spec": asdict(spec), "settings": settings.to_dict()}

    if (root / SCENE_FILE).is_file():
        scene = Scene.load(root, check_files=False)
        previous = scene.extra.get("make")
        if previous != json.loads(json.dumps(wanted)):
            raise ValueError(f"{root / SCENE_FILE}: this scene was made with other settings; "
                             f"choose another --out or delete the folder")
    else:
        if root.exists() and any(root.iterdir()):
            raise FileExistsError(f"{root}: exists and is not a garmentnerf scene; choose another --out")
        body = BodyModel.default()
        betas = body.betas(spec.shape)
        cams = default_rig(spec.views, spec.held_out_views, radius=spec.radius, height=spec.height,
                           width=spec.size, height_px=spec.size)
        shape = spec.shape if "," not in spec.shape else [float(x) for x in spec.shape.split(",")]
        scene = Scene.create(root, cams, spec.fps, spec.garment, GARMENT_COLORS[spec.garment], body_shape=shape)
        for name, motion_spec, split, cap in plan:
            motion = build_motion(motion_spec, body, betas, spec.fps, cap or None, spec.in_place)
            scene.add_sequence(name, motion, split=split, description=motion_spec)
        scene.extra["make"] = wanted
        scene.save()

    todo = [name for name, *_ in plan if not scene.garment_path(name).is_file()]
    if todo:
        totals = {name: scene.num_frames(name) for name in todo}
        workers = spec.processes or min(len(todo), multiprocessing.cpu_count())
        stats = _run_simulations(root, todo, spec, settings, workers, totals, progress)
        for name, s in stats.items():
            scene.simulation[name] = s
        scene.save()

    if scene.palette_init is None:
        with SceneImages(scene) as images:
            train = scene.camera_names("train")
            T = scene.num_frames("train")
            frames = sorted({int(round(x)) for x in np.linspace(0, T - 1, max(1, palette_frames))})
            cams = train[:: max(1, len(train) // 4)]
            scene.palette_init = palette_from_images(images.image("train", c, f) for c in cams for f in frames)
        scene.save()
    if not keep_chunks and (root / "sim").is_dir():
        shutil.rmtree(root / "sim")
    return Scene.load(root)


def _run_simulations(root: Path, todo: list[str], spec: MakeSpec, settings, workers: int,
                     totals: dict[str, int], progress: bool) -> dict:
    from tqdm import tqdm

    ctx = multiprocessing.get_context("spawn")
    results: dict[str, dict] = {}
    bar = tqdm(total=sum(totals.values()), unit="frame", desc="simulating", disable=not progress)
    pool = ProcessPoolExecutor(max_workers=workers, mp_context=ctx)
    try:
        futures = {pool.submit(_simulate_sequence, str(root), name, spec.garment, spec.shape,
                               settings.to_dict()): name for name in todo}
        pending = set(futures)
        while pending:
            finished = {f for f in pending if f.done()}
            for f in finished:
                results[futures[f]] = f.result()  # re-raises a worker's error
            pending -= finished
            bar.n = _committed_frames(root, todo, settings.chunk_frames, totals)
            bar.refresh()
            if pending:
                time.sleep(1.0)
        bar.n = bar.total
        bar.refresh()
    except BaseException:
        # Ctrl-C or a worker error: committed chunks stay on disk; the next run resumes from them.
        for proc in list(getattr(pool, "_processes", {}).values()):
            proc.terminate()
        pool.shutdown(wait=False, cancel_futures=True)
        raise
    finally:
        bar.close()
    pool.shutdown()
    return results


__all__ = ["MakeSpec", "make_scene", "build_motion", "remove_drift", "DRIFT_SIGMA_S"]
