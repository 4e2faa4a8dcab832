"""Small, deterministic procedural motions (for tests, demos and quick previews).

They work on the anny rig and on SMPL (joints are looked up by name, with the other rig's names
as fallbacks). Arm motions are expressed relative to the rig's rest pose, so "raise the arm to
60 degrees above horizontal" means the same on anny's A-pose and SMPL's T-pose. Each clip loops:
the cycle lengths are rounded so that a whole number of cycles fits the clip.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Callable

import torch

from garmentnerf.motion.motion import Motion

if TYPE_CHECKING:  # pragma: no cover
    from garmentnerf.body.model import BodyModel

DEFAULT_FPS = 30.0

#: Our name -> candidate joint names (anny first, then SMPL).
_ALIASES = {
    "root": ("root", "pelvis"),
    "spine_low": ("spine04", "spine1"),
    "spine_mid": ("spine03", "spine2"),
    "spine_high": ("spine01", "spine3"),
    "hip.L": ("upperleg01.L", "left_hip"), "hip.R": ("upperleg01.R", "right_hip"),
    "knee.L": ("lowerleg01.L", "left_knee"), "knee.R": ("lowerleg01.R", "right_knee"),
    "ankle.L": ("foot.L", "left_ankle"), "ankle.R": ("foot.R", "right_ankle"),
    "arm.L": ("upperarm01.L", "left_shoulder"), "arm.R": ("upperarm01.R", "right_shoulder"),
    "forearm.L": ("lowerarm01.L", "left_elbow"), "forearm.R": ("lowerarm01.R", "right_elbow"),
    "hand.L": ("wrist.L", "left_wrist"), "hand.R": ("wrist.R", "right_wrist"),
}


def _skeleton(body: "BodyModel") -> str:
    return "smpl" if "left_hip" in body.joint_index and "upperleg01.L" not in body.joint_index else "anny"


def _joint(body: "BodyModel", key: str) -> int:
    for name in _ALIASES[key]:
        if name in body.joint_index:
            return body.joint_index[name]
    raise ValueError(f"procedural motions need a joint like {' or '.join(_ALIASES[key])}; body '{body.name}' "
                     f"has none")


def _cycles(frames: int, fps: float, period_s: float) -> float:
    """Angular frequency (rad/frame) of a whole number of cycles closest to ``period_s`` each."""
    n = max(1, round(frames / fps / period_s))
    return 2.0 * math.pi * n / frames


def _frames(frames: int, fps: float, name: str) -> tuple[int, float]:
    if isinstance(frames, bool) or int(frames) != frames or frames < 1:
        raise ValueError(f"{name}: frames must be an integer >= 1, got {frames!r}")
    fps = float(fps)
    if not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"{name}: fps must be a finite number > 0, got {fps!r}")
    return int(frames), fps


def _empty(body: "BodyModel", frames: int) -> tuple[torch.Tensor, torch.Tensor]:
    return (torch.zeros(frames, body.num_joints, 3, dtype=torch.float64),
            torch.zeros(frames, 3, dtype=torch.float64))


def _motion(name, body, rot, trans, fps) -> Motion:
    return Motion(name, list(body.joint_names), rot.float(), trans.float(), fps, _skeleton(body))


def _arm_elevation(body: "BodyModel", side: str) -> float:
    """Rest elevation (radians, + above horizontal) of the upper arm on ``side``."""
    _, j = body.rest()
    d = (j[_joint(body, f"forearm.{side}")] - j[_joint(body, f"arm.{side}")]).double()
    return math.atan2(float(d[2]), float(torch.hypot(d[0], d[1])))


def rest(body: "BodyModel", frames: int = 30, fps: float = DEFAULT_FPS) -> Motion:
    """The rest pose held still."""
    frames, fps = _frames(frames, fps, "rest")
    rot, trans = _empty(body, frames)
    return _motion("rest", body, rot, trans, fps)


def sway(body: "BodyModel", frames: int = 60, fps: float = DEFAULT_FPS, amplitude_deg: float = 10.0,
         period_s: float = 2.0) -> Motion:
    """Hip swing: the pelvis tilts and turns side to side, the upper body leans against it.

    The thighs counter-rotate so the legs stay vertical (the feet rise and sink by under 1 cm);
    the upper body bends over three spine joints.
    """
    frames, fps = _frames(frames, fps, "sway")
    rot, trans = _empty(body, frames)
    w = _cycles(frames, fps, period_s)
    t = torch.arange(frames, dtype=torch.float64)
    a = math.radians(amplitude_deg) * torch.sin(w * t)
    root = _joint(body, "root")
    rot[:, root, 1] = 0.4 * a  # roll about the forward axis: hips tilt
    rot[:, root, 2] = 0.3 * a  # a little yaw
    for key in ("hip.L", "hip.R"):
        rot[:, _joint(body, key), 1] = -0.4 * a  # legs stay vertical
        rot[:, _joint(body, key), 2] = -0.3 * a
    for key in ("spine_low", "spine_mid", "spine_high"):
        rot[:, _joint(body, key), 1] = -0.3 * a  # the torso leans back over the hips
    return _motion("sway", body, rot, trans, fps)


def arm_wave(body: "BodyModel", frames: int = 60, fps: float = DEFAULT_FPS, side: str = "R",
             period_s: float = 1.0) -> Motion:
    """One arm raised to about 60 degrees above horizontal, the forearm waving side to side."""
    frames, fps = _frames(frames, fps, "arm_wave")
    if side not in ("L", "R"):
        raise ValueError(f"arm_wave: side must be 'L' or 'R', got {side!r}")
    rot, trans = _empty(body, frames)
    w = _cycles(frames, fps, period_s)
    t = torch.arange(frames, dtype=torch.float64)
    sign = 1.0 if side == "R" else -1.0  # raising the right arm (-X side) is + about Y
    ramp = torch.clamp(t / max(1.0, 0.3 * fps), max=1.0)
    ramp = ramp * ramp * (3.0 - 2.0 * ramp)
    lift = math.radians(60.0) - _arm_elevation(body, side)
    rot[:, _joint(body, f"arm.{side}"), 1] = sign * lift * ramp
    # Forearm: bend the elbow up 45 degrees and wave it +-25 degrees about the forward axis.
    wave = math.radians(45.0) + math.radians(25.0) * torch.sin(w * t)
    rot[:, _joint(body, f"forearm.{side}"), 1] = sign * wave * ramp
    return _motion("arm_wave", body, rot, trans, fps)


def walk_in_place(body: "BodyModel", frames: int = 60, fps: float = DEFAULT_FPS, period_s: float = 1.0) -> Motion:
    """Marching on the spot: knees lift alternately, arms swing opposite, the body bobs slightly."""
    frames, fps = _frames(frames, fps, "walk_in_place")
    rot, trans = _empty(body, frames)
    w = _cycles(frames, fps, period_s)
    t = torch.arange(frames, dtype=torch.float64)
    phase = w * t
    for side, offset, arm_sign in (("L", 0.0, 1.0), ("R", math.pi, -1.0)):
        lift = torch.clamp(torch.sin(phase + offset), min=0.0)  # this leg swings half of the time
        # Hip flexion brings the thigh forward (-Y): negative about X. The knee folds back: + about X.
        rot[:, _joint(body, f"hip.{side}"), 0] = -math.radians(45.0) * lift
        rot[:, _joint(body, f"knee.{side}"), 0] = math.radians(80.0) * lift
        rot[:, _joint(body, f"ankle.{side}"), 0] = -math.radians(25.0) * lift
        # The arm on this side swings back while its leg lifts (opposite arm forward).
        rot[:, _joint(body, f"arm.{side}"), 0] = math.radians(20.0) * torch.sin(phase + offset)
    rot[:, _joint(body, "forearm.L"), 0] = -math.radians(20.0)
    rot[:, _joint(body, "forearm.R"), 0] = -math.radians(20.0)
    trans[:, 2] = 0.015 * (torch.cos(2.0 * phase) - 1.0) * 0.5  # down by <= 1.5 cm at mid-stride
    return _motion("walk_in_place", body, rot, trans, fps)


#: name -> (generator, default frames, default fps)
PROCEDURAL_MOTIONS: dict[str, tuple[Callable[..., Motion], int, float]] = {
    "rest": (rest, 30, DEFAULT_FPS),
    "sway": (sway, 60, DEFAULT_FPS),
    "arm_wave": (arm_wave, 60, DEFAULT_FPS),
    "walk_in_place": (walk_in_place, 60, DEFAULT_FPS),
}


def procedural_motion(name: str, body: "BodyModel", fps: float | None = None) -> Motion:
    """A procedural motion by name at its default length (the same duration at any ``fps``)."""
    fn, frames, default_fps = PROCEDURAL_MOTIONS[name]
    if fps is None:
        return fn(body, frames=frames, fps=default_fps)
    n = max(1, round(frames * float(fps) / default_fps))
    return fn(body, frames=n, fps=float(fps))
