"""AMASS-style SMPL motions (``.npz`` with ``poses``, ``trans``, ``mocap_framerate``).

Layout: ``poses`` is (T, 72) for SMPL (24 joints), (T, 156) for SMPL-H (52 joints) or (T, 165)
for SMPL-X (55 joints), axis-angle, in :data:`~garmentnerf.body.smpl.SMPL_JOINT_NAMES` order for
the first 22 (body) joints. For SMPL-H/X the body joints are kept and SMPL's two hand joints
(``left_hand``, ``right_hand``) get zero rotation; jaw, eyes and fingers are dropped.
``(T, J, 3)`` arrays are accepted as well. The frame rate is ``mocap_framerate`` (SMPL-H files)
or ``mocap_frame_rate`` (SMPL-X files).

Axes
----
The SMPL body's own frame is Y up, facing +Z. Our body frame is Z up, facing -Y; the change of
axes is ``C = [[1, 0, 0], [0, 0, -1], [0, 1, 0]]`` (``C @ (x, y, z) = (x, -z, y)``), and a joint
rotation R (expressed in the body's axes) becomes ``C R C^T``. Every non-root joint is converted
so. The root (global orientation) and ``trans`` depend on the world the file was fitted in:

* ``up="y"``: the world is SMPL's (Y up), as in SMPL fits that keep SMPL's axes. The root is
  conjugated like the other joints and ``trans`` is rotated: ``C trans``. This is exact for an
  SMPL body whose rest mesh and joints are ``C`` times SMPL's.
* ``up="z"``: the world is already Z up. This is AMASS's own convention (its mocap worlds have
  the floor in the XY plane; the global orientation of a standing subject is about a quarter
  turn about X, which is exactly ``C``). The root becomes ``R C^T`` (the world needs no change,
  only the body's rest frame does) and ``trans`` is kept.
* ``up="auto"`` (default): picks "z" if SMPL's up axis, carried by the root orientations, points
  more along world z than along world y over the clip (median), else "y".

Translation caveat: ``trans`` is in SMPL's convention, a shift added after skinning with the root
rotating about the template's pelvis joint J0. With ``up="y"`` the result is exact; with
``up="z"`` the body ends up displaced by ``J0 - C J0`` (about (0, -0.20, 0.25) m for the SMPL
template), which depends on the body model and is not corrected here.
:func:`garmentnerf.motion.library.load_motion` puts AMASS clips on the ground (frame 0's lowest
vertex at z = 0, its root above the origin) after loading, which removes that offset.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from garmentnerf.body.smpl import SMPL_JOINT_NAMES
from garmentnerf.motion.motion import Motion


def _roma():
    """roma, imported at first use (it imports torch._dynamo: seconds of CPU; see
    :mod:`garmentnerf.body.rotations`)."""
    import roma

    return roma


#: SMPL axes (Y up, facing +Z) -> ours (Z up, facing -Y).
C_SMPL = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])

_JOINTS_BY_WIDTH = {72: 24, 156: 52, 165: 55}  # SMPL, SMPL-H, SMPL-X
_BODY_JOINTS = 22


class AmassError(ValueError):
    """An AMASS file that cannot be read as a motion."""


def _open(path: Path):
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such AMASS motion file")
    try:
        return np.load(path, allow_pickle=False)
    except Exception as exc:
        raise AmassError(f"{path}: not a readable .npz file ({exc})") from exc


def _field(data, path: Path, key: str) -> np.ndarray:
    try:
        arr = np.asarray(data[key])
    except Exception as exc:
        raise AmassError(f"{path}: field '{key}' cannot be read ({exc})") from exc
    if not np.issubdtype(arr.dtype, np.number):
        raise AmassError(f"{path}: field '{key}' must hold numbers, got dtype {arr.dtype}")
    arr = arr.astype(np.float64)
    if not np.all(np.isfinite(arr)):
        bad = np.nonzero(~np.isfinite(arr.reshape(arr.shape[0], -1)).all(axis=1))[0] if arr.ndim else [0]
        raise AmassError(f"{path}: field '{key}' contains NaN or Inf (first at frame {int(bad[0])})")
    return arr


def load_amass(path: str | Path, up: str = "auto", name: str | None = None) -> Motion:
    """Read an AMASS-style SMPL motion into our axes (see the module doc for ``up``).

    Returns a :class:`Motion` with skeleton ``"smpl"`` and the 24 SMPL joint names. Errors name
    the file and the field (missing key, wrong shape, NaN).
    """
    path = Path(path)
    if up not in ("auto", "y", "z"):
        raise ValueError(f"load_amass: up must be 'auto', 'y' or 'z', got {up!r}")
    with _open(path) as data:
        files = set(data.files)
        for key in ("poses", "trans"):
            if key not in files:
                raise AmassError(f"{path}: missing field '{key}' (an AMASS file has poses, trans, mocap_framerate; "
                                 f"this one has {', '.join(sorted(files)) or 'nothing'})")
        rate_key = next((k for k in ("mocap_framerate", "mocap_frame_rate") if k in files), None)
        if rate_key is None:
            raise AmassError(f"{path}: missing field 'mocap_framerate' (or 'mocap_frame_rate')")
        poses = _field(data, path, "poses")
        trans = _field(data, path, "trans")
        rate = _field(data, path, rate_key)
        if "betas" in files:
            _field(data, path, "betas")  # validated: a NaN shape is an error too
    if poses.ndim == 3 and poses.shape[2] == 3:
        poses = poses.reshape(poses.shape[0], -1)
    if poses.ndim != 2 or poses.shape[1] not in _JOINTS_BY_WIDTH:
        raise AmassError(f"{path}: field 'poses' must have shape (T, 72), (T, 156) or (T, 165) (SMPL, SMPL-H, "
                         f"SMPL-X axis-angle), got {poses.shape}")
    T = poses.shape[0]
    if T < 1:
        raise AmassError(f"{path}: field 'poses' has no frames")
    if trans.shape != (T, 3):
        raise AmassError(f"{path}: field 'trans' must have shape ({T}, 3) to match 'poses', got {trans.shape}")
    if rate.size != 1 or not (math.isfinite(float(rate.reshape(-1)[0])) and float(rate.reshape(-1)[0]) > 0):
        raise AmassError(f"{path}: field '{rate_key}' must be one positive number, got {rate.reshape(-1)[:3]}")
    fps = float(rate.reshape(-1)[0])

    n_joints = _JOINTS_BY_WIDTH[poses.shape[1]]
    aa = torch.as_tensor(poses, dtype=torch.float64).reshape(T, n_joints, 3)
    rotvec = torch.zeros(T, len(SMPL_JOINT_NAMES), 3, dtype=torch.float64)
    keep = len(SMPL_JOINT_NAMES) if n_joints == len(SMPL_JOINT_NAMES) else _BODY_JOINTS
    rotvec[:, :keep] = aa[:, :keep]

    C = torch.as_tensor(C_SMPL, dtype=torch.float64)
    R = _roma().rotvec_to_rotmat(rotvec)
    if up == "auto":
        up = detect_up_axis(R[:, 0])
    out = C @ R @ C.T
    t = torch.as_tensor(trans, dtype=torch.float64)
    if up == "z":
        out[:, 0] = R[:, 0] @ C.T
    else:
        t = t @ C.T
    return Motion(name or path.stem, list(SMPL_JOINT_NAMES), _roma().rotmat_to_rotvec(out).float(), t.float(), fps, "smpl")


def detect_up_axis(root_rotations: torch.Tensor) -> str:
    """``"z"`` or ``"y"``: the world axis SMPL's up axis (its y) points along, from (T, 3, 3) root rotations.

    Uses the median over the clip of the body's up direction, so a clip that starts lying down
    still detects correctly as long as the subject is upright for most of it.
    """
    body_up = root_rotations[..., :, 1]  # R @ (0, 1, 0)
    med = body_up.median(dim=0).values
    return "z" if abs(float(med[2])) > abs(float(med[1])) else "y"
