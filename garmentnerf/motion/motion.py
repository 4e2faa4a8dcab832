"""A body motion: per-frame local joint rotations and a root translation, by joint name.

Rotations follow the rig semantics of :mod:`garmentnerf.body.skinning` (SMPL semantics): the
rotation of joint j is local, relative to its parent, expressed in the world axes of the rest
pose, in the project's world frame (Z up, the character at rest faces -Y; see
:mod:`garmentnerf.conventions`). The translation is added to every vertex after skinning, as in
SMPL. By convention ``joint_names[0]`` is the root joint (``root`` for anny, ``pelvis`` for SMPL);
:func:`garmentnerf.motion.blend.concatenate` relies on it.

Time: frame i is at ``i / fps`` seconds; a clip of T frames plays for ``T / fps`` seconds
(:attr:`Motion.duration`, each frame shown for one frame period).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from garmentnerf.body.smpl import SMPL_JOINT_NAMES
from garmentnerf.io_utils import atomic_write_path

if TYPE_CHECKING:  # pragma: no cover
    from garmentnerf.body.model import BodyModel, PosedBody

#: Skeleton names used by the project's loaders (any non-empty name is accepted).
KNOWN_SKELETONS = ("anny", "smpl")

_FILE_FORMAT = "garmentnerf.motion"
_FILE_VERSION = 1


class FrameRangeError(IndexError, ValueError):
    """A frame index outside a motion's frames."""


@dataclass
class Motion:
    """A body motion.

    Attributes:
        name: a label for messages and file names (e.g. ``walk``).
        joint_names: (J,) joint names; ``joint_names[0]`` is the root.
        rotations: (T, J, 3) float32 rotation vectors (axis x angle, radians), local per joint.
        translation: (T, 3) float32 root translation in metres, added after skinning.
        fps: frames per second (> 0).
        skeleton: the rig the joint names belong to: ``"anny"`` or ``"smpl"``.
    """

    name: str
    joint_names: list[str]
    rotations: torch.Tensor
    translation: torch.Tensor
    fps: float
    skeleton: str = "anny"

    def __post_init__(self) -> None:
        if not isinstance(self.name, str):
            raise ValueError(f"motion name must be a string, got {type(self.name).__name__}")
        label = f"motion '{self.name}'"
        names = list(self.joint_names)
        if not names or not all(isinstance(n, str) and n for n in names):
            raise ValueError(f"{label}: joint_names must be a non-empty list of non-empty strings")
        if len(set(names)) != len(names):
            dup = sorted({n for n in names if names.count(n) > 1})
            raise ValueError(f"{label}: duplicate joint names {dup}")
        self.joint_names = names
        rot = _as_float_tensor(self.rotations, f"{label}: rotations")
        trans = _as_float_tensor(self.translation, f"{label}: translation")
        J = len(names)
        if rot.ndim != 3 or rot.shape[1:] != (J, 3):
            raise ValueError(f"{label}: rotations must have shape (T, {J}, 3) for its {J} joints, "
                             f"got {tuple(rot.shape)}")
        T = rot.shape[0]
        if T < 1:
            raise ValueError(f"{label}: a motion needs at least 1 frame, got 0")
        if trans.shape != (T, 3):
            raise ValueError(f"{label}: translation must have shape ({T}, 3), got {tuple(trans.shape)}")
        for field, value in (("rotations", rot), ("translation", trans)):
            bad = ~torch.isfinite(value)
            if bad.any():
                frame = int(bad.reshape(T, -1).any(dim=1).nonzero()[0, 0])
                raise ValueError(f"{label}: {field} contain NaN or Inf (first at frame {frame})")
        try:
            fps = float(self.fps)
        except (TypeError, ValueError):
            raise ValueError(f"{label}: fps must be a number, got {self.fps!r}") from None
        if not (math.isfinite(fps) and fps > 0):
            raise ValueError(f"{label}: fps must be a finite number > 0, got {self.fps!r}")
        if not isinstance(self.skeleton, str) or not self.skeleton:
            raise ValueError(f"{label}: skeleton must be a non-empty string such as 'anny' or 'smpl'")
        self.rotations, self.translation, self.fps = rot, trans, fps

    # ---- basic properties ---------------------------------------------------------------------
    @property
    def num_frames(self) -> int:
        return int(self.rotations.shape[0])

    @property
    def num_joints(self) -> int:
        return len(self.joint_names)

    @property
    def duration(self) -> float:
        """Playback length in seconds: ``num_frames / fps``."""
        return self.num_frames / self.fps

    @property
    def times(self) -> torch.Tensor:
        """(T,) float64 time of every frame in seconds (``i / fps``)."""
        return torch.arange(self.num_frames, dtype=torch.float64) / self.fps

    def __len__(self) -> int:
        return self.num_frames

    def __repr__(self) -> str:
        return (f"Motion(name={self.name!r}, skeleton={self.skeleton!r}, frames={self.num_frames}, "
                f"joints={self.num_joints}, fps={self.fps:g})")

    # ---- editing ------------------------------------------------------------------------------
    def slice(self, start: int | None = None, stop: int | None = None) -> "Motion":
        """Frames ``[start, stop)`` with Python slice semantics (negative indices count from the end).

        Raises ValueError when the range holds no frame.
        """
        idx = range(self.num_frames)[slice(start, stop)]
        if len(idx) == 0:
            raise FrameRangeError(f"motion '{self.name}': frame range [{start}, {stop}) is empty "
                                  f"(the motion has {self.num_frames} frames: 0..{self.num_frames - 1})")
        sl = slice(idx.start, idx.stop)
        return Motion(self.name, list(self.joint_names), self.rotations[sl].clone(), self.translation[sl].clone(),
                      self.fps, self.skeleton)

    def renamed(self, name: str) -> "Motion":
        return Motion(name, list(self.joint_names), self.rotations, self.translation, self.fps, self.skeleton)

    # ---- posing -------------------------------------------------------------------------------
    def rotations_for(self, body: "BodyModel") -> torch.Tensor:
        """(T, body.num_joints, 3) rotation vectors in the body's joint order, matched by name.

        Body joints the motion lacks get a zero rotation; motion joints the body lacks are ignored.
        Raises ValueError if none of the motion's joints exist in the body, or if the motion and
        the body belong to different known skeletons (an SMPL motion on the anny body).
        """
        out = torch.zeros(self.num_frames, body.num_joints, 3, dtype=body.dtype, device=body.device)
        body_skeleton = skeleton_of(body.joint_names)
        if self.skeleton in KNOWN_SKELETONS and body_skeleton in KNOWN_SKELETONS and body_skeleton != self.skeleton:
            # Both rigs name a joint 'head': matching by name alone would pose one joint.
            raise ValueError(f"motion '{self.name}' is for the {self.skeleton} skeleton, body '{body.name}' uses the "
                             f"{body_skeleton} skeleton (only {self.skeleton} bodies can play it)")
        src, dst = [], []
        for i, name in enumerate(self.joint_names):
            j = body.joint_index.get(name)
            if j is not None:
                src.append(i)
                dst.append(j)
        if not src:
            raise ValueError(f"motion '{self.name}' is for the {self.skeleton} skeleton, body '{body.name}' has "
                             f"none of its joints (motion joints: {', '.join(self.joint_names[:4])}, ...; "
                             f"body joints: {', '.join(body.joint_names[:4])}, ...)")
        out[:, dst] = self.rotations[:, src].to(dtype=body.dtype, device=body.device)
        return out

    def pose(self, body: "BodyModel", betas: torch.Tensor | str | None = None) -> "PosedBody":
        """Pose ``body`` with every frame of this motion (``betas``: tensor, preset name or None)."""
        if betas is not None and not isinstance(betas, torch.Tensor):
            betas = body.betas(betas)
        translation = self.translation.to(dtype=body.dtype, device=body.device)
        return body.pose(self.rotations_for(body), translation, betas)

    # ---- files --------------------------------------------------------------------------------
    def save(self, path: str | Path, overwrite: bool = True) -> Path:
        """Write the motion as an ``.npz`` file (atomically: readers never see a partial file)."""
        path = Path(path)
        if path.suffix != ".npz":
            raise ValueError(f"{path}: motion files use the .npz extension")
        with atomic_write_path(path, overwrite=overwrite) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(fh, format=np.array(_FILE_FORMAT), version=np.array(_FILE_VERSION),
                         name=np.array(self.name), joint_names=np.array(self.joint_names, dtype=np.str_),
                         rotations=self.rotations.detach().cpu().numpy(),
                         translation=self.translation.detach().cpu().numpy(),
                         fps=np.array(self.fps, dtype=np.float64), skeleton=np.array(self.skeleton))
        return path

    @staticmethod
    def load(path: str | Path) -> "Motion":
        """Read a file written by :meth:`save`; errors name the file and the bad field."""
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such motion file")
        try:
            data = np.load(path, allow_pickle=False)
        except Exception as exc:  # zip errors, pickle refusals, ...
            raise ValueError(f"{path}: not a readable .npz motion file ({exc})") from exc
        with data:
            files = set(data.files)
            missing = [k for k in ("name", "joint_names", "rotations", "translation", "fps", "skeleton")
                       if k not in files]
            if missing:
                raise ValueError(f"{path}: not a garmentnerf motion file (missing field(s) {', '.join(missing)})")
            if "version" in files and int(data["version"]) > _FILE_VERSION:
                raise ValueError(f"{path}: motion file version {int(data['version'])} is newer than this "
                                 f"program reads ({_FILE_VERSION})")
            try:
                name = str(data["name"])
                names = [str(n) for n in np.asarray(data["joint_names"]).reshape(-1)]
                rotations = np.asarray(data["rotations"])
                translation = np.asarray(data["translation"])
                fps = float(data["fps"])
                skeleton = str(data["skeleton"])
            except Exception as exc:
                raise ValueError(f"{path}: malformed motion field ({exc})") from exc
        for field, arr in (("rotations", rotations), ("translation", translation)):
            if not np.issubdtype(arr.dtype, np.floating):
                raise ValueError(f"{path}: field '{field}' must hold floats, got dtype {arr.dtype}")
        try:
            return Motion(name, names, torch.from_numpy(rotations.copy()), torch.from_numpy(translation.copy()),
                          fps, skeleton)
        except ValueError as exc:
            raise ValueError(f"{path}: {exc}") from exc


def skeleton_of(joint_names: list[str]) -> str | None:
    """``"anny"`` or ``"smpl"`` when the joint names are those of a known rig, else None."""
    names = set(joint_names)
    if {"root", "upperleg01.L", "upperleg01.R", "spine01"} <= names:
        return "anny"

    if set(SMPL_JOINT_NAMES[:22]) <= names:
        return "smpl"
    return None


def check_frame(motion: Motion, frame: int) -> int:
    """Raise :class:`FrameRangeError` unless ``0 <= frame < motion.num_frames``; returns ``frame``."""
    if isinstance(frame, bool) or not isinstance(frame, (int, np.integer)):
        raise FrameRangeError(f"frame index must be an integer, got {frame!r}")
    if not 0 <= int(frame) < motion.num_frames:
        raise FrameRangeError(f"frame {int(frame)} is out of range for motion '{motion.name}' "
                              f"({motion.num_frames} frames: 0..{motion.num_frames - 1})")
    return int(frame)


def _as_float_tensor(value, what: str) -> torch.Tensor:
    try:
        t = torch.as_tensor(np.asarray(value) if not isinstance(value, torch.Tensor) else value)
    except Exception as exc:
        raise ValueError(f"{what} must be a numeric array ({exc})") from exc
    if not (t.is_floating_point() or t.dtype in (torch.int32, torch.int64)):
        raise ValueError(f"{what} must be a numeric array, got dtype {t.dtype}")
    return t.detach().to(dtype=torch.float32, device="cpu")
