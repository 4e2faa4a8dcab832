"""Motions by name: the DeepMimic clips, procedural motions, motion files and AMASS files.

``load_motion`` accepts

* a name from :func:`available_motions` (``walk``, ``dance_a``, ``sway``, ...);
* names joined by ``,`` or ``+`` (``walk,dance_a``): the clips are played one after another
  with smooth transitions (:func:`garmentnerf.motion.blend.concatenate`, a cross-fade of about a
  third of a second);
* a path to a ``.npz`` file: a motion saved by :meth:`Motion.save` or an AMASS file (told apart
  by their fields).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from garmentnerf.budgets import MOTION_FPS
from garmentnerf.motion.amass import load_amass
from garmentnerf.motion.blend import concatenate, resample
from garmentnerf.motion.deepmimic import DEEPMIMIC_CLIPS, load_deepmimic, read_deepmimic
from garmentnerf.motion.motion import FrameRangeError, Motion, check_frame
from garmentnerf.motion.procedural import PROCEDURAL_MOTIONS, procedural_motion

if TYPE_CHECKING:  # pragma: no cover
    from garmentnerf.body.model import BodyModel

__all__ = ["MotionInfo", "UnknownMotionError", "FrameRangeError", "available_motions", "motion_names",
           "load_motion", "check_frame", "place_on_ground", "BLEND_SECONDS"]

#: Cross-fade length used when names are joined with ',' or '+'.
BLEND_SECONDS = 1.0 / 3.0


class UnknownMotionError(ValueError):
    """A motion name that is neither a known motion nor a file."""


@dataclass(frozen=True)
class MotionInfo:
    """What :func:`available_motions` lists.

    Attributes:
        name: the name ``load_motion`` accepts.
        source: ``deepmimic`` or ``procedural``.
        frames: frame count at the native rate.
        fps: native frame rate.
        duration: seconds (``frames / fps``, as :attr:`Motion.duration`).
    """

    name: str
    source: str
    frames: int
    fps: float
    duration: float


def motion_names() -> list[str]:
    """Every name :func:`load_motion` knows, DeepMimic clips first."""
    return list(DEEPMIMIC_CLIPS) + list(PROCEDURAL_MOTIONS)


def available_motions() -> list[MotionInfo]:
    """The DeepMimic clips (if pybullet's data is present) and the procedural motions."""
    infos = []
    for name in DEEPMIMIC_CLIPS:
        try:
            clip = read_deepmimic(name)
        except (ValueError, OSError):
            continue  # a missing clip is reported when it is loaded
        n = clip.uniform_frame_count()
        infos.append(MotionInfo(name, "deepmimic", n, clip.fps, n / clip.fps))
    for name, (_, frames, fps) in PROCEDURAL_MOTIONS.items():
        infos.append(MotionInfo(name, "procedural", frames, fps, frames / fps))
    return infos


def load_motion(name_or_path: str | Path, body: "BodyModel", betas: torch.Tensor | str | None = None,
                fps: float | None = None) -> Motion:
    """A motion for ``body`` by name, ``a,b`` list, or ``.npz`` path (see the module doc).

    Args:
        name_or_path: see the module doc.
        body: the body the motion will pose (DeepMimic clips are retargeted onto it; AMASS clips
            are put on the ground with it).
        betas: the subject's shape (tensor, preset name or None).
        fps: resample to this frame rate (default: the motion's own; for a list, the first
            clip's, the others are resampled to it).
    Raises:
        UnknownMotionError: an unknown name (the message lists the known ones).
        FileNotFoundError: a ``.npz`` path that does not exist.
    """
    if betas is not None and not isinstance(betas, torch.Tensor):
        betas = body.betas(betas)
    if fps is not None:
        fps = MOTION_FPS.check(fps, "fps")
    spec = str(name_or_path).strip()
    if spec in DEEPMIMIC_CLIPS or spec in PROCEDURAL_MOTIONS:
        return _load_single(spec, body, betas, fps)
    if isinstance(name_or_path, Path) or Path(str(name_or_path)).is_file():
        return _load_single(str(name_or_path), body, betas, fps)  # paths may contain ',' or '+'
    parts = [p.strip() for p in spec.replace("+", ",").split(",")]
    if len(parts) == 1:
        return _load_single(parts[0], body, betas, fps)
    if any(not p for p in parts):
        raise UnknownMotionError(f"empty motion name in '{spec}' (join names with ',' as in 'walk,dance_a')")
    motions = [_load_single(p, body, betas, fps) for p in parts]
    target = fps if fps is not None else motions[0].fps
    motions = [resample(m, target) for m in motions]
    blend = max(1, round(BLEND_SECONDS * target))
    return concatenate(motions, blend_frames=blend, body=body, betas=betas, name=",".join(parts))


def _load_single(spec: str, body: "BodyModel", betas, fps: float | None) -> Motion:
    if spec in DEEPMIMIC_CLIPS:
        return load_deepmimic(spec, body, betas, fps)
    if spec in PROCEDURAL_MOTIONS:
        return procedural_motion(spec, body, fps)
    path = Path(spec)
    if path.is_file() or path.suffix.lower() == ".npz":
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such motion file")
        motion = _load_file(path, body, betas)
        return motion if fps is None else resample(motion, fps)
    raise UnknownMotionError(f"unknown motion '{spec}' (available: {', '.join(motion_names())}; "
                             f"or a motion/AMASS .npz file)")


def _load_file(path: Path, body: "BodyModel", betas) -> Motion:
    try:
        with np.load(path, allow_pickle=False) as data:
            keys = set(data.files)
    except Exception as exc:
        raise ValueError(f"{path}: not a readable .npz motion file ({exc})") from exc
    if "poses" in keys:
        return place_on_ground(load_amass(path), body, betas)
    if "rotations" in keys and "joint_names" in keys:
        return Motion.load(path)
    raise ValueError(f"{path}: neither a garmentnerf motion file (rotations, joint_names, ...) nor an AMASS file "
                     f"(poses, trans, mocap_framerate); it has {', '.join(sorted(keys)) or 'no fields'}")


def place_on_ground(motion: Motion, body: "BodyModel", betas: torch.Tensor | None = None) -> Motion:
    """Shift the whole motion so that in frame 0 the lowest vertex is at z = 0 and the root joint
    is above x = y = 0 (one constant offset added to every frame's translation)."""
    first = motion.slice(0, 1)
    posed = first.pose(body, betas)
    root = motion.joint_names[0]
    offset = torch.zeros(3, dtype=torch.float64)
    offset[2] = -float(posed.vertices[0, :, 2].min())
    if root in body.joint_index:
        _, rest_j = body.rest(betas)
        A = posed.joint_transforms[0, body.joint_index[root]].double()
        j = rest_j[body.joint_index[root]].double()
        root_pos = A[:, :3] @ j + A[:, 3] + first.translation[0].double()
        offset[:2] = -root_pos[:2]
    trans = (motion.translation.double() + offset).float()
    return Motion(motion.name, list(motion.joint_names), motion.rotations, trans, motion.fps, motion.skeleton)
