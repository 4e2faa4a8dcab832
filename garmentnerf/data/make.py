"""``garmentnerf data make``: a complete training scene from a garment kind and motion names.

What it does, in order (every step can be re-run; a killed run continues where it stopped):

1. Builds the motions: the training motion from its clip list (repeated until it has
   ``frames`` frames, then cut), and one held-out sequence per ``test_motions`` entry. With
   ``in_place`` (the default) the slow horizontal drift of the root is removed so the character
   stays inside the camera ring (see :func:`remove_drift`).
2. Writes the scene (cameras, body shape, garment kind and color, the motions) -- nothing is
   rendered yet: images are rendered on demand from the stored simulation (:mod:`scene`).
3. Simulates the garment on every sequence with newton's VBD solver
   (:func:`~garmentnerf.data.simulate.simulate`), one *process* per sequence because warp's CPU
   kernels are single-threaded. Each simulation writes atomically committed chunks under
   ``<scene>/sim/<sequence>/``; a restarted ``data make`` finds them and computes only what is
   missing, bit-identically (see the simulation module). The parent shows one progress bar over
   all frames by counting committed chunks.
4. Stores each garment sequence (``sequences/<name>/garment.npz``, with its per-frame maximum
   body penetration) and, as soon as the sequence is written, its simulation statistics in
   ``scene.json`` (``simulation.<name>``). The statistics are computed from the files alone (the
   garment, and the timings each chunk records), so a re-run restores those of a sequence that
   finished in a run killed before it could record them, equal to an uninterrupted make's
   (the timings aside: each chunk's are those of the run that computed it).
5. Renders a few training views to measure the mean garment and body colors for the palette
   initialisation (``palette_init``).

The chunk folders can be deleted once the scene is complete (``keep_chunks=False``).

Interruptions
    Ctrl-C and SIGTERM stop the run and its simulation processes at once; a simulation process
    whose ``data make`` is killed (SIGKILL) stops by itself within a second. Every file is
    written atomically, and a re-run first waits for such processes (their folder locks,
    :mod:`garmentnerf.folder_lock`) and removes the temporaries of the writes they abandoned, so
    nothing half-written is ever read and none is left behind. A second ``data make`` of a folder
    that one is writing is refused.

Settings
    ``scene.json`` records the spec and simulation settings under ``make``; a re-run must give the
    same ones (a one-line error names each difference with the folder's and the new value),
    except :data:`OUTPUT_NEUTRAL` ones such as ``processes``, which do not change the scene and
    are not recorded.
"""

from __future__ import annotations

import contextlib
import fnmatch
import json
import math
import multiprocessing
import os
import pickle
import shutil
import signal
import sys
import threading
import time
import traceback
import zipfile
from dataclasses import asdict, dataclass, field
from multiprocessing.connection import wait
from pathlib import Path

import numpy as np
import torch
from scipy.ndimage import gaussian_filter1d
from tqdm import tqdm

from garmentnerf.body.model import BodyModel
from garmentnerf.data.cameras import default_rig
from garmentnerf.data.garment_sequence import load_sequence, save_sequence
from garmentnerf.data.garments import GARMENT_COLORS, GARMENT_KINDS, make_garment
from garmentnerf.data.scene import Scene
from garmentnerf.data.scene_images import SceneImages, palette_from_images
from garmentnerf.data.scene_schema import MOTION_FILE, SCENE_FILE
from garmentnerf.data.simulate import PENETRATION_BOUND_M, SimSettings, _chunk_path, simulate
from garmentnerf.folder_lock import LOCK_FILE, lock_folder
from garmentnerf.io_utils import STALE_TEMPORARY_SECONDS, remove_stale_temporaries, temporary_pattern
from garmentnerf.interrupts import interrupting, raise_interrupted
from garmentnerf.motion.library import load_motion

#: Seconds of the Gaussian that defines the "slow" root drift removed by :func:`remove_drift`.
DRIFT_SIGMA_S = 1.0

#: :class:`MakeSpec` fields that do not change the scene: not stored in ``scene.json``, and free
#: to differ when an interrupted make is resumed.
OUTPUT_NEUTRAL = ("processes",)

#: Seconds to wait for the simulation processes of a killed ``data make`` to stop (they notice
#: within half a second and abandon their chunk at once).
_ORPHAN_WAIT_S = 60.0


@dataclass
class MakeSpec:
    """Everything that defines a generated scene (stored in ``scene.json`` under ``make``, but for
    :data:`OUTPUT_NEUTRAL` fields).

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
            number of cores. Does not change the scene: not stored, and a resume may change it
            (see :data:`OUTPUT_NEUTRAL`).
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


# ---- the make record: which settings define the scene ---------------------------------------------
def _make_record(spec: MakeSpec, settings) -> dict:
    """What ``scene.json`` stores under ``make``: the spec without the :data:`OUTPUT_NEUTRAL`
    fields, and the simulation settings -- JSON-normalised, as they read back from the file."""
    fields = {k: v for k, v in asdict(spec).items() if k not in OUTPUT_NEUTRAL}
    return json.loads(json.dumps({"spec": fields, "settings": settings.to_dict()}))


_MISSING = object()  # marks a setting absent from one of two make records (a sentinel, never changed)


def _flag(section: str, key: str) -> str:
    """The command-line name of a recorded setting (``--frames``, ``--sim iterations``)."""
    if section == "settings":
        return f"--sim {key}"
    return {"test_motions": "--test-motion", "in_place": "--no-in-place"}.get(key, "--" + key.replace("_", "-"))


def _shown(section: str, key: str, value) -> str:
    """A recorded value as the user gives it (``--no-in-place`` is on when ``in_place`` is off)."""
    if value is _MISSING:
        return "not recorded"
    if section == "spec" and key == "in_place" and isinstance(value, bool):
        return "off" if value else "on"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, list):
        return " ".join(str(v) for v in value) if value else "none"
    return str(value)


def _check_record(file: Path, found, wanted: dict) -> None:
    """Refuse to finish the scene of ``file`` (make record ``found``) with this run's settings
    (``wanted``) where they differ: one line naming each differing setting with the folder's
    value and this run's value. The :data:`OUTPUT_NEUTRAL` fields are not compared.

    Raises:
        ValueError: ``found`` is not a make record, or a setting that changes the scene differs.
    """
    if not (isinstance(found, dict) and isinstance(found.get("spec"), dict)
            and isinstance(found.get("settings"), dict)):
        raise ValueError(f"{file}: this scene was not made by 'garmentnerf data make' (it has no 'make' record); "
                         f"choose another --out")
    differences = []
    for section in ("spec", "settings"):
        old, new = found[section], wanted[section]
        for key in [*new, *(k for k in old if k not in new)]:
            if section == "spec" and key in OUTPUT_NEUTRAL:
                continue
            a, b = old.get(key, _MISSING), new.get(key, _MISSING)
            if a != b or isinstance(a, bool) != isinstance(b, bool):  # True == 1 in Python
                differences.append(f"{_flag(section, key)}: {_shown(section, key, a)} in the folder, "
                                   f"{_shown(section, key, b)} now")
    if differences:
        raise ValueError(f"{file}: this scene was made with other settings ({'; '.join(differences)}); give the "
                         f"folder's values to finish it, or choose another --out")


# ---- locks, temporaries, signals --------------------------------------------------------------------
def _remove_temporaries(folder: Path, name: str = "*", min_age: float = 0.0) -> None:
    """Delete the leftovers of killed atomic writes of ``name`` (a glob) in ``folder`` (see
    :func:`~garmentnerf.io_utils.remove_stale_temporaries`); call it holding the folder's writer lock."""
    remove_stale_temporaries(folder, name, min_age=min_age)


class InterruptOnce:
    """A worker's SIGINT/SIGTERM handler: the first signal interrupts (KeyboardInterrupt); later
    ones are ignored, so that the clean-up the first one started (a temporary removed, a message
    printed) is not cut short. (Not SIG_IGN: a signal already caught but not yet handled would
    then be reported as "ignored due to race condition".) :meth:`disarm` makes it ignore every
    signal from then on: a worker whose work is over calls it, so that a signal arriving while the
    interpreter shuts down (the parent's stop, or its death noticed by the watch thread) cannot
    raise inside an exit handler and print a traceback."""

    def __init__(self) -> None:
        self.fired: int | None = None  # the signal that interrupted (or 0 once disarmed)

    def __call__(self, signum, frame) -> None:
        if self.fired is None:
            self.fired = signum
            raise_interrupted(signum, frame)

    def disarm(self) -> None:
        if self.fired is None:
            self.fired = 0


def _in_main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


@contextlib.contextmanager
def _children_start_deaf():
    """Processes started in the block begin with SIGINT and SIGTERM blocked (the signal mask is
    inherited through ``exec``) until they have installed their own handlers and unblock them
    (:func:`_simulate_sequence`): a Ctrl-C while a worker imports its modules would otherwise end
    it with a traceback; held, it stops the worker as soon as it can stop cleanly. The signals
    this process gets meanwhile are held too and delivered after the block. Blocked, not ignored:
    a signal that arrives while its action is SIG_IGN is discarded even when blocked, and a
    group Ctrl-C landing while a worker started was then lost by both (the run went on to the end)."""
    if not _in_main_thread() or not hasattr(signal, "pthread_sigmask"):
        yield
        return
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)


# ---- the simulation processes -----------------------------------------------------------------------
def _simulate_sequence(root: str, sequence: str, kind: str, shape: str, settings_dict: dict, parent: int,
                       conn) -> None:
    """Worker process: simulate one sequence of the scene at ``root`` and store its garment.

    Exit status 0 once ``garment.npz`` is written; 130 when stopped by SIGINT or SIGTERM or by
    the death of its parent (``parent``: the ``data make`` process), keeping the chunks committed
    so far and leaving nothing half-written; 1 after an error, which is sent through ``conn``.
    """
    handler = InterruptOnce()
    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    try:
        if hasattr(signal, "pthread_sigmask"):  # started with them blocked (see _children_start_deaf)
            signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})
        _stop_with_parent(parent)
        torch.set_num_threads(1)

        out_dir = _sim_dir(Path(root), sequence)
        out_dir.mkdir(parents=True, exist_ok=True)
        with lock_folder(out_dir, f"garmentnerf data make: simulation of {sequence}", wait_s=_ORPHAN_WAIT_S,
                         busy=f"{out_dir}: another simulation process ({{holder}}) writes here"):
            scene = Scene.load(root, check_files=False)
            body = BodyModel.default()
            betas = body.betas(body.shape_from_text(shape))
            garment = make_garment(kind, body, betas)
            motion = scene.load_motion(sequence)
            settings = SimSettings.from_dict(settings_dict)
            result = simulate(garment, body, motion, betas=betas, settings=settings, out_dir=out_dir,
                              progress=False)
            save_sequence(scene.garment_path(sequence), result.vertices, garment.faces, color=garment.color,
                          kind=kind, penetration_max_m=result.penetration_max_m, fps=motion.fps, settings=settings,
                          name=sequence, motion=motion.name, betas=betas.detach().cpu().numpy(), uv=garment.uv,
                          layer=garment.layer)
    except KeyboardInterrupt:
        sys.exit(130)
    except BaseException as exc:  # noqa: BLE001 - handed to the parent, which raises it
        _send_error(conn, exc)
        sys.exit(1)
    finally:
        handler.disarm()  # the work is over: a signal during the exit must not raise in an exit handler
        conn.close()


def _stop_with_parent(parent: int, poll_s: float = 0.5, grace_s: float = 30.0) -> None:
    """Stop this worker when its parent ``data make`` dies (killed): as an interrupt first (the
    chunk being written is abandoned cleanly), for good after ``grace_s``. An orphan would keep
    simulating into files that the next run is about to write."""

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(poll_s)
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(grace_s)
        os._exit(130)

    threading.Thread(target=watch, daemon=True, name="parent-watch").start()


def _send_error(conn, exc: BaseException) -> None:
    """Send a worker's exception (pickled, with its type, message and traceback as text)."""
    try:
        blob = pickle.dumps(exc)
    except Exception:  # noqa: BLE001 - an exception that does not pickle is sent as text
        blob = None
    try:
        conn.send({"error": blob, "type": type(exc).__name__, "message": str(exc),
                   "traceback": "".join(traceback.format_exception(exc))})
    except (OSError, ValueError):  # the parent is gone: nobody to tell
        pass


def _worker_error(name: str, message: dict) -> BaseException:
    """The exception a worker sent, rebuilt (a RuntimeError naming its type when it does not unpickle)."""
    exc = None
    if message.get("error") is not None:
        try:
            exc = pickle.loads(message["error"])
        except Exception:  # noqa: BLE001
            exc = None
    if not isinstance(exc, BaseException):
        exc = RuntimeError(f"{message.get('type')}: {message.get('message')}")
    exc.add_note(f"raised in the simulation process of sequence '{name}':\n{message.get('traceback', '')}")
    return exc


def _bound() -> float:
    return float(PENETRATION_BOUND_M)


def _committed_frames(root: Path, sequences: list[str], chunk_frames: int, totals: dict[str, int]) -> int:
    done = 0
    for name in sequences:
        chunks = len(list(_sim_dir(root, name).glob("chunk_*.npz")))
        done += min(chunks * chunk_frames, totals[name])
    return done


def _chunk_seconds(folder: Path, frames: int, chunk_frames: int) -> tuple[float | None, float | None]:
    """Mean wall-clock and CPU seconds per frame over the chunks of a finished simulation (each
    chunk records what computing it took, in whichever run computed it); None where a chunk or
    its record is missing (chunks deleted, or written before chunks recorded CPU time)."""
    wall: float | None = 0.0
    cpu: float | None = 0.0
    for k in range(-(-frames // chunk_frames)):
        try:
            with np.load(_chunk_path(folder, k), allow_pickle=False) as data:
                wall = wall + float(data["seconds"]) if wall is not None and "seconds" in data.files else None
                cpu = cpu + float(data["cpu_seconds"]) if cpu is not None and "cpu_seconds" in data.files else None
        except (OSError, ValueError, zipfile.BadZipFile):
            return None, None
    return (None if wall is None else wall / frames), (None if cpu is None else cpu / frames)


def _sequence_stats(scene, name: str, chunk_frames: int) -> dict:
    """The ``simulation`` entry of a finished sequence, from its files alone (``garment.npz`` and
    the chunks under ``sim/``): the same whether the sequence finished in this run, in an
    interrupted one, or in pieces over several."""
    seq = load_sequence(scene.garment_path(name))
    pen = np.asarray(seq.penetration_max_m, dtype=np.float32)
    seconds, cpu_seconds = _chunk_seconds(_sim_dir(scene.root, name), len(pen), chunk_frames)
    return {"frames": int(len(pen)), "penetration_max_m": float(pen.max()),
            "penetration_mean_m": float(pen.mean()),
            "frames_over_bound": int((pen > _bound()).sum()), "penetration_bound_m": _bound(),
            "seconds_per_frame": seconds, "cpu_seconds_per_frame": cpu_seconds,
            "settings": SimSettings.from_dict(seq.settings).to_dict()}


def _is_interrupted_creation(root: Path, names: list[str]) -> bool:
    """True when ``root`` holds nothing but what a ``data make`` killed while writing the scene
    (before ``scene.json``) leaves: motion files of the planned sequences, and temporaries of
    them and of ``scene.json``. (An empty folder is such a folder.)"""
    sequences = root / "sequences"
    folders = {sequences / n for n in names}
    for path in root.rglob("*"):
        if path.is_dir() and not path.is_symlink():
            if path != sequences and path not in folders:
                return False
        elif path.parent == root:
            if path.name != LOCK_FILE and not fnmatch.fnmatch(path.name, temporary_pattern(SCENE_FILE)):
                return False
        elif not (path.parent in folders and not path.is_symlink()
                  and (path.name == MOTION_FILE or fnmatch.fnmatch(path.name, temporary_pattern(MOTION_FILE)))):
            return False
    return True


def make_scene(out: str | Path, spec: MakeSpec, *, settings=None, progress: bool = True,
               keep_chunks: bool = True, palette_frames: int = 3):
    """Create (or finish) the scene at ``out`` (see the module docstring). Returns the Scene.

    SIGTERM stops it as Ctrl-C does (KeyboardInterrupt) while it runs in the main thread. It holds
    a lock on ``out`` (``flock``) while it works: a second make of the same folder is refused.

    Raises:
        ValueError: ``out`` holds a scene made with settings that change the scene (the message
            names them with both values), another ``data make`` is writing it, or bad settings.
        FileExistsError: ``out`` holds other files than a scene.
        KeyboardInterrupt: interrupted (or a simulation process was killed); a re-run resumes.
    """
    root = Path(out)
    settings = settings or SimSettings()
    if spec.garment not in GARMENT_KINDS:
        raise ValueError(f"unknown garment kind '{spec.garment}' (known: {', '.join(GARMENT_KINDS)})")
    plan = _sequence_plan(spec)
    # SIGTERM stops the run as Ctrl-C does: the simulation processes are stopped, nothing
    # half-written stays, and a re-run resumes
    with interrupting(signal.SIGTERM):
        created = not root.exists()
        root.mkdir(parents=True, exist_ok=True)
        try:
            with lock_folder(root, "garmentnerf data make",
                             busy=f"{root}: another 'garmentnerf data make' ({{holder}}) is writing this scene; wait "
                                  f"for it to finish, or choose another --out"):
                return _make_locked(root, spec, settings, plan, progress, keep_chunks, palette_frames)
        except BaseException:
            if created:  # failed before writing anything: leave no empty folder behind
                with contextlib.suppress(OSError):
                    root.rmdir()
            raise


def _make_locked(root: Path, spec: MakeSpec, settings, plan, progress: bool, keep_chunks: bool,
                 palette_frames: int):
    """:func:`make_scene` holding the scene folder's lock."""
    names = [name for name, *_ in plan]
    wanted = _make_record(spec, settings)
    if (root / SCENE_FILE).is_file():
        scene = Scene.load(root, check_files=False)
        _check_record(root / SCENE_FILE, scene.extra.get("make"), wanted)
        _remove_temporaries(root, SCENE_FILE)  # scene.json is written by the lock holder only
    else:
        if not _is_interrupted_creation(root, names):
            raise FileExistsError(f"{root}: exists and is not a garmentnerf scene; choose another --out")
        _remove_temporaries(root, SCENE_FILE)
        body = BodyModel.default()
        shape = body.shape_from_text(spec.shape)
        betas = body.betas(shape)
        cams = default_rig(spec.views, spec.held_out_views, radius=spec.radius, height=spec.height,
                           width=spec.size, height_px=spec.size)
        scene = Scene.create(root, cams, spec.fps, spec.garment, GARMENT_COLORS[spec.garment], body_shape=shape)
        for name, motion_spec, split, cap in plan:
            motion = build_motion(motion_spec, body, betas, spec.fps, cap or None, spec.in_place)
            scene.add_sequence(name, motion, split=split, description=motion_spec)
    scene.extra["make"] = wanted  # an older record may still list output-neutral fields

    # Simulation processes of a killed run stop within a second or two; wait for them (their
    # folder locks), then clear what they left half-written.
    for name in names:
        folder = _sim_dir(root, name)
        if folder.is_dir():
            with lock_folder(folder, "garmentnerf data make", wait_s=_ORPHAN_WAIT_S,
                             busy=f"{folder}: a simulation process of an earlier 'data make' ({{holder}}) still "
                                  f"writes here; wait for it to end and run again"):
                _remove_temporaries(folder)
                _remove_temporaries(root / "sequences" / name)
        else:
            _remove_temporaries(root / "sequences" / name)

    def record(*finished_now: str) -> None:
        """Store the statistics of sequences just finished in scene.json at once (entries in plan order)."""
        stats = dict(scene.simulation)
        for name in finished_now:
            stats[name] = _sequence_stats(scene, name, settings.chunk_frames)
        scene.simulation = {n: stats[n] for n in names if n in stats}
        scene.save()

    # Sequences that an interrupted run finished but was killed before recording.
    finished = [name for name in names if scene.garment_path(name).is_file()]
    record(*(name for name in finished if name not in scene.simulation))

    todo = [name for name in names if name not in finished]
    if todo:
        totals = {name: scene.num_frames(name) for name in todo}
        workers = spec.processes or min(len(todo), multiprocessing.cpu_count())
        _run_simulations(root, todo, spec, settings, workers, totals, progress, record)

    if scene.palette_init is None:
        for folder in scene.cache_dir.glob("*/*/*"):  # a killed palette rendering's PNG temporaries
            _remove_temporaries(folder, "*.png", min_age=STALE_TEMPORARY_SECONDS)
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
                     totals: dict[str, int], progress: bool, on_finished) -> None:
    """Simulate the ``todo`` sequences, one process each, ``workers`` at a time; call
    ``on_finished(name)`` as soon as one has written its garment. A worker's error is raised
    here; on any exception (Ctrl-C, SIGTERM, an error) the running workers are stopped first."""
    ctx = multiprocessing.get_context("spawn")
    waiting = list(todo)
    running: dict[str, tuple] = {}  # name -> (process, receiving end of its pipe, message or None)
    bar = tqdm(total=sum(totals.values()), unit="frame", desc="simulating", disable=not progress)
    try:
        while waiting or running:
            while waiting and len(running) < workers:
                name = waiting.pop(0)
                receiver, sender = ctx.Pipe(duplex=False)
                proc = ctx.Process(target=_simulate_sequence, name=f"simulate-{name}", daemon=True,
                                   args=(str(root), name, spec.garment, spec.shape, settings.to_dict(), os.getpid(),
                                         sender))
                with _children_start_deaf():
                    proc.start()
                sender.close()
                running[name] = (proc, receiver, None)
            wait([p.sentinel for p, _, _ in running.values()] + [r for _, r, m in running.values() if m is None],
                 timeout=1.0)
            for name, (proc, receiver, message) in list(running.items()):
                if message is None and receiver.poll():
                    try:
                        message = receiver.recv()
                    except (EOFError, OSError):
                        message = {}
                    running[name] = (proc, receiver, message)
                if proc.exitcode is None:
                    continue
                del running[name]
                receiver.close()
                _check_exit(name, proc.exitcode, message)
                on_finished(name)
            bar.n = _committed_frames(root, todo, settings.chunk_frames, totals)
            bar.refresh()
        bar.n = bar.total
        bar.refresh()
    except BaseException:
        # Ctrl-C, SIGTERM or an error: committed chunks stay on disk; the next run resumes from them.
        _stop_workers([proc for proc, _, _ in running.values()])
        raise
    finally:
        bar.close()


def _check_exit(name: str, exitcode: int, message: dict | None) -> None:
    """Raise what a finished worker's exit says went wrong (nothing for exit status 0)."""
    if exitcode == 0:
        return
    if message and message.get("type"):
        raise _worker_error(name, message)
    stopping = {130, -signal.SIGINT, -signal.SIGTERM, -signal.SIGKILL, -signal.SIGHUP}
    if exitcode in stopping:
        how = "was interrupted" if exitcode in (130, -signal.SIGINT) else \
            f"was stopped by {signal.Signals(-exitcode).name}"
        print(f"garmentnerf: the simulation of '{name}' {how}; run the same command again to resume it",
              file=sys.stderr)
        raise KeyboardInterrupt(name)
    why = f"signal {signal.Signals(-exitcode).name}" if exitcode < 0 else f"exit status {exitcode}"
    raise RuntimeError(f"the simulation process of sequence '{name}' crashed ({why})")


def _stop_workers(procs: list, timeout_s: float = 30.0) -> None:
    """Stop the running simulation processes: SIGTERM (a worker still starting up holds it until
    it can stop cleanly; sent again each half second all the same), then SIGKILL after
    ``timeout_s``. A stopped worker abandons its chunk cleanly."""
    deadline = time.monotonic() + timeout_s
    alive = [p for p in procs if p.exitcode is None]
    while alive and time.monotonic() < deadline:
        for p in alive:
            p.terminate()
        wait([p.sentinel for p in alive], timeout=0.5)
        alive = [p for p in alive if p.exitcode is None]
    for p in alive:
        p.kill()
        p.join()


__all__ = ["MakeSpec", "make_scene", "build_motion", "remove_drift", "DRIFT_SIGMA_S", "OUTPUT_NEUTRAL"]
