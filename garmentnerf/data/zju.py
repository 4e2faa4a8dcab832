"""ZJU-MoCap captures (the real-data experiment of the paper), in the layout Neural Body published.

Folder layout read here::

    <root>/annots.npy                 pickled dict:
        cams: {K: [N x (3, 3)], R: [N x (3, 3)], T: [N x (3, 1)] in MILLIMETRES, D: [N x (5, 1)]}
        ims:  [{ims: [N image paths relative to <root>]} per frame]
    <root>/mask_cihp/<image path minus extension>.png   and/or
    <root>/mask/<image path minus extension>.png        per-image masks (non-zero = person)
    <root>/new_params/<i>.npy  (or params/<i>.npy)      per-frame SMPL: dict with
        poses (1, 72) axis-angle, Rh (1, 3) axis-angle, Th (1, 3) metres, shapes (1, 10)

Units
    The calibration stores ``T`` in millimetres with ``x_cam = R X + T`` for X in millimetres
    (Neural Body divides it by 1000). Loading converts to metres: ``t = T / 1000``; pixels do
    not change. ``translation_unit="auto"`` (default) checks this: it takes millimetres when the
    median camera centre is more than 50 units from the origin (a capture dome is a few metres
    across, so millimetres give thousands) and metres otherwise; ``"mm"``/``"m"`` force it.
    SMPL ``Th`` and the vertices the dataset ships are in metres already.

Distortion
    ``D`` holds OpenCV coefficients ``(k1, k2, p1, p2, k3)`` for the full-resolution images.
    :meth:`CaptureScene.load_image` / :meth:`CaptureScene.load_mask` undistort by default
    (``cv2.undistort``-equivalent remap with the *same* K as the new camera matrix; bilinear for
    images, nearest for masks), after which the pinhole :class:`~garmentnerf.conventions.Camera`
    of each :class:`CaptureCamera` is exact. ``undistort=False`` returns the raw image, for which
    ``dist`` must be applied by the caller.

World axes (what is assumed, and how it is made consistent)
    ZJU-MoCap's world comes from its calibration board on the floor: the vertical is a world
    axis (Z), metres after the conversion above. We do not trust the sign blindly:
    ``align="auto"`` (default) takes the mean of the cameras' image-up directions in the world
    (cameras of a capture dome stand upright) and snaps it to the nearest signed world axis; the
    axis permutation that maps it to +Z (identity when it already is +Z) becomes
    :attr:`CaptureScene.world_from_capture`. ``align="none"`` keeps ZJU's axes; a (4, 4) rigid
    matrix may be given instead. The SAME transform ``x_ours = A x_zju + b`` is applied to the
    cameras (``R' = R A^T``, ``t' = t - R A^T b``) and to the SMPL bodies, so projections are
    unchanged by it. No horizontal rotation is applied: the subject's facing direction is
    whatever the capture had (our -Y convention only concerns the synthetic scenes' rigs).

SMPL
    As in EasyMocap, which fitted these parameters, the posed vertices in the ZJU world are
    ``v_zju = R(Rh) SMPL(poses, shapes) + Th``: SMPL in its own (Y-up) model frame, root joint
    rotation ``poses[:3]`` included, no SMPL translation; then the rigid (Rh, Th) about the
    model origin. :meth:`CaptureScene.smpl_motion` converts a sequence into a
    :class:`~garmentnerf.motion.motion.Motion` for a :class:`~garmentnerf.body.model.BodyModel`
    loaded from the user's SMPL file (:func:`~garmentnerf.body.smpl.load_smpl_asset`): local joint
    rotations convert as ``C r`` (:func:`~garmentnerf.body.smpl.smpl_rotvecs_to_world`); the
    global ``G = A R(Rh) C^T`` and ``g = A Th + b - h G e_z`` (h = the model's ground offset,
    :func:`~garmentnerf.body.smpl.smpl_ground_offset`) are folded into the root: root rotation
    ``G R_root`` and translation ``G J0 + g - J0`` (J0 = the rest root joint of the shape), which
    is exact because the skinning weights of every vertex sum to 1. The shape is the first
    frame's ``shapes`` of the sequence (ZJU keeps it constant). Loading cameras, images and masks
    never needs SMPL.

Frames and parameters
    Frame f of the capture is ``annots['ims'][f]``. Its parameter file is ``<i>.npy`` (or
    ``<i:06d>.npy``) in ``new_params/`` (else ``params/``), with i read from the file name of
    camera 0's image for that frame as Neural Body does: the name itself when it is a number, the
    frame field of the CoreView_313/315 names, else the last number in it; falling back to
    ``<f>.npy``. Sequences: ``train`` holds frames ``[0, train_frames)`` and ``unseen_motion``
    the rest (``train_frames=None``: all in ``train``).

Pickles: ``annots.npy`` and the parameter files are pickled numpy objects. They are read with the
package's restricted unpickler (:mod:`garmentnerf.safe_pickle`), which only rebuilds numpy arrays
and plain containers and refuses a file naming anything else (nothing else runs).
"""

from __future__ import annotations

import re
import threading
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
import torch
from PIL import Image
from scipy.spatial.transform import Rotation

from garmentnerf.body.smpl import SMPL_TO_WORLD, smpl_rotvecs_to_world
from garmentnerf.conventions import DEFAULT_FAR, DEFAULT_NEAR, Camera
from garmentnerf.data.cameras import NamedCamera, RigLookup, in_splits
from garmentnerf.motion.motion import Motion
from garmentnerf.safe_pickle import RefusedGlobal, load_npy_restricted

if TYPE_CHECKING:  # pragma: no cover
    from garmentnerf.body.model import BodyModel

ANNOTS_FILE = "annots.npy"
#: Mask folders tried in order (Neural Body's later code prefers the CIHP parsing masks).
DEFAULT_MASK_DIRS = ("mask_cihp", "mask")
PARAMS_DIRS = ("new_params", "params")
CAPTURE_SPLITS = ("train", "unseen_view")
SEQUENCE_SPLITS = ("train", "unseen_motion")
ROTATION_TOLERANCE = 1e-4


class CaptureError(ValueError):
    """A capture folder that is missing files or holds malformed annotations (message names both)."""


# ---- restricted unpickling of .npy object arrays ---------------------------------------------------
def load_pickled_npy(path: str | Path):
    """``np.load(path, allow_pickle=True)`` without running foreign code (the allow-list of
    :mod:`garmentnerf.safe_pickle`); a 0-d object array (a pickled dict, as ZJU stores) is
    unwrapped with ``.item()``.

    Raises:
        CaptureError: naming the file: missing, unreadable, or naming a global outside the allow-list.
    """
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            array = load_npy_restricted(fh)
    except FileNotFoundError:
        raise CaptureError(f"{path}: no such file") from None
    except RefusedGlobal as exc:
        raise CaptureError(f"{path}: {exc}") from None
    except Exception as exc:  # truncated files, bad headers, pickle errors
        raise CaptureError(f"{path}: not a readable .npy file ({type(exc).__name__}: {exc})") from None
    if isinstance(array, np.ndarray) and array.dtype == object and array.shape == ():
        return array.item()
    return array


# ---- cameras --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class CaptureCamera(NamedCamera):
    """A calibrated capture camera: the pinhole ``camera`` (metres, our world axes) plus
    ``dist`` (OpenCV distortion of the raw images) and its column ``index`` in ``annots``."""

    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))
    index: int = -1


@dataclass
class SmplParams:
    """One frame's SMPL fit in ZJU's convention (see the module docstring).

    Attributes: poses (3 J,) axis-angle; Rh (3,) axis-angle; Th (3,) metres; shapes (S,).
    """

    poses: np.ndarray
    Rh: np.ndarray
    Th: np.ndarray
    shapes: np.ndarray


def _rodrigues(r: np.ndarray) -> np.ndarray:
    r = np.asarray(r, dtype=np.float64).reshape(3)
    theta = np.linalg.norm(r)
    if theta < 1e-12:
        return np.eye(3)
    k = r / theta
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(theta) * Kx + (1 - np.cos(theta)) * Kx @ Kx


def _rotvec(Rm: np.ndarray) -> np.ndarray:
    return Rotation.from_matrix(Rm).as_rotvec()


#: Rotations taking a signed world axis to +Z (exact axis permutations, det +1).
_TO_Z = {
    (2, 1): np.eye(3),
    (2, -1): np.diag([1.0, -1.0, -1.0]),
    (1, 1): np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]]),
    (1, -1): np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]]),
    (0, 1): np.array([[0, 0, -1.0], [0, 1.0, 0], [1.0, 0, 0]]),
    (0, -1): np.array([[0, 0, 1.0], [0, 1.0, 0], [-1.0, 0, 0]]),
}


def estimate_up(rotations: Sequence[np.ndarray]) -> np.ndarray:
    """Unit mean of the cameras' image-up directions in the world (``-R[1]`` per camera)."""
    up = -np.mean([np.asarray(R)[1] for R in rotations], axis=0)
    n = np.linalg.norm(up)
    if n < 1e-9:
        raise CaptureError("cannot tell the vertical from the cameras (their up directions cancel)")
    return up / n


def _param_index(stem: str) -> int | None:
    """The number naming a frame's parameter file, from its image's file name (Neural Body's rule):
    the name itself when it is a number (``000123``), the frame field of the CoreView_313/315
    names (``CoreView_313_Camera_(1)_0001_2019-08-23_16-08-50.592`` -> 1), else the last number."""
    if stem.isdigit():
        return int(stem)
    m = re.match(r"^CoreView_\d+_Camera_\(\d+\)_(\d+)_", stem)
    if m:
        return int(m.group(1))
    digits = re.findall(r"\d+", stem)
    return int(digits[-1]) if digits else None


# ---- reading annots.npy ---------------------------------------------------------------------------
def _read_annots(root: Path) -> tuple[Path, dict]:
    """``<root>/annots.npy`` and its dict, checked to hold ``cams`` (a dict) and ``ims``."""
    annots_path = root / ANNOTS_FILE
    if not root.is_dir():
        raise CaptureError(f"{root}: no such capture folder")
    if not annots_path.is_file():
        raise CaptureError(f"{annots_path}: no such file (not a ZJU-MoCap capture folder)")
    annots = load_pickled_npy(annots_path)
    src = str(annots_path)
    if not isinstance(annots, dict):
        raise CaptureError(f"{src}: must hold a dict with 'cams' and 'ims', got {type(annots).__name__}")
    for key in ("cams", "ims"):
        if key not in annots:
            raise CaptureError(f"{src}: '{key}' is missing")
    if not isinstance(annots["cams"], dict):
        raise CaptureError(f"{src}: cams must be a dict with K, R, T, D, got {type(annots['cams']).__name__}")
    return annots_path, annots


def _calibration_entry(cams: dict, key: str, i: int, shapes: set[tuple[int, ...]], shape_text: str,
                       src: str) -> np.ndarray:
    """float64 ``cams[key][i]``, checked to have one of ``shapes`` and finite values."""
    try:
        a = np.asarray(cams[key][i], dtype=np.float64)
    except (TypeError, ValueError):
        raise CaptureError(f"{src}: cams.{key}[{i}] must be numeric {shape_text}") from None
    if a.shape not in shapes:
        raise CaptureError(f"{src}: cams.{key}[{i}] must be {shape_text}, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise CaptureError(f"{src}: cams.{key}[{i}] contains NaN or Inf")
    return a


_DIST_SHAPES = {(k, 1) for k in (4, 5, 8)} | {(1, k) for k in (4, 5, 8)} | {(k,) for k in (4, 5, 8)}


def _read_calibration(cams: dict, src: str) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """Per camera (K (3, 3), R (3, 3), T (3,) in the file's unit, D (k,) OpenCV coefficients; zeros
    without ``cams['D']``), checked: intrinsics, rotations, matching counts."""
    for key in ("K", "R", "T"):
        if key not in cams:
            raise CaptureError(f"{src}: cams.{key} is missing")
    n = len(cams["K"])
    if n < 1:
        raise CaptureError(f"{src}: cams.K lists no camera")
    for key in ("R", "T", "D"):
        if key in cams and len(cams[key]) != n:
            raise CaptureError(f"{src}: cams.{key} has {len(cams[key])} entries, cams.K has {n}")
    calibration = []
    for i in range(n):
        K = _calibration_entry(cams, "K", i, {(3, 3)}, "3x3", src)
        if K[0, 0] <= 0 or K[1, 1] <= 0 or np.abs(K[2] - [0, 0, 1]).max() > 1e-9:
            raise CaptureError(f"{src}: cams.K[{i}] is not an intrinsics matrix (positive focal lengths, "
                               f"last row [0, 0, 1])")
        R = _calibration_entry(cams, "R", i, {(3, 3)}, "3x3", src)
        if np.abs(R @ R.T - np.eye(3)).max() > ROTATION_TOLERANCE or np.linalg.det(R) < 0:
            raise CaptureError(f"{src}: cams.R[{i}] is not a rotation matrix")
        T = _calibration_entry(cams, "T", i, {(3, 1), (3,), (1, 3)}, "3x1", src).reshape(3)
        if "D" in cams:
            D = _calibration_entry(cams, "D", i, _DIST_SHAPES, "5x1 (or 4/8 OpenCV coefficients)", src).reshape(-1)
        else:
            D = np.zeros(5)
        calibration.append((K, R, T, D))
    return calibration


def _read_frame_images(ims, n: int, src: str) -> list[list[str]]:
    """Per frame, the ``n`` image paths (relative to the capture folder) of ``annots['ims']``."""
    if not isinstance(ims, (list, tuple, np.ndarray)) or len(ims) < 1:
        raise CaptureError(f"{src}: ims must be a non-empty list of frames")
    frame_images: list[list[str]] = []
    for f, entry in enumerate(ims):
        paths = entry.get("ims") if isinstance(entry, dict) else None
        if paths is None:
            raise CaptureError(f"{src}: ims[{f}] must be a dict with an 'ims' list")
        paths = [str(p) for p in np.asarray(paths).reshape(-1)]
        if len(paths) != n:
            raise CaptureError(f"{src}: ims[{f}].ims lists {len(paths)} images for {n} cameras")
        frame_images.append(paths)
    return frame_images


def _guess_translation_unit(calibration) -> str:
    """``"mm"`` when the median camera centre is more than 50 units from the origin, else ``"m"``."""
    dist = np.median([np.linalg.norm(R.T @ T) for _, R, T, _ in calibration])
    return "mm" if dist > 50.0 else "m"


def _world_alignment(align: str | np.ndarray, rotations: Sequence[np.ndarray]) -> np.ndarray:
    """(4, 4) rigid ``world_from_capture`` for ``align`` (see the module docstring)."""
    if isinstance(align, str):
        if align == "none":
            return np.eye(4)
        if align == "auto":
            up = estimate_up(rotations)
            axis = int(np.argmax(np.abs(up)))
            M = np.eye(4)
            M[:3, :3] = _TO_Z[(axis, 1 if up[axis] > 0 else -1)]
            return M
        raise ValueError(f"align must be 'auto', 'none' or a (4, 4) matrix, got {align!r}")
    M = np.asarray(align, dtype=np.float64)
    if M.shape != (4, 4) or np.abs(M[:3, :3] @ M[:3, :3].T - np.eye(3)).max() > 1e-6 \
            or np.linalg.det(M[:3, :3]) < 0 or np.abs(M[3] - [0, 0, 0, 1]).max() > 0:
        raise ValueError("align must be a rigid (4, 4) matrix (rotation + translation)")
    return M


def _camera_names(first_frame_images: list[str]) -> list[str]:
    """The cameras' image folder names when unique and file-safe, else ``cam00``, ``cam01``, ..."""
    names = [Path(p).parent.name for p in first_frame_images]
    n = len(names)
    if len(set(names)) != n or not all(re.match(r"^[A-Za-z0-9][A-Za-z0-9_. ()-]*$", x) for x in names):
        names = [f"cam{i:02d}" for i in range(n)]
    return names


def _checked_camera_splits(camera_splits: dict[str, str] | None, names: list[str]) -> dict[str, str]:
    splits = dict(camera_splits or {})
    unknown = set(splits) - set(names)
    if unknown:
        raise ValueError(f"camera_splits names unknown cameras {sorted(unknown)} (cameras: {', '.join(names)})")
    for name, split in splits.items():
        if split not in CAPTURE_SPLITS:
            raise ValueError(f"camera '{name}': split must be one of {', '.join(CAPTURE_SPLITS)}, got {split!r}")
    return splits


def _image_size(image: Path, listed_as: str) -> tuple[int, int]:
    """(width, height) of an image the annotations list (``listed_as`` names where)."""
    try:
        with Image.open(image) as im:
            return im.size
    except FileNotFoundError:
        raise CaptureError(f"{listed_as} names a missing image {image}") from None
    except OSError as exc:
        raise CaptureError(f"{image}: not a readable image ({exc})") from None


def _split_frames(train_frames: int | None, total: int) -> dict[str, list[int]]:
    """Sequence name -> capture frames: ``train`` [0, train_frames), ``unseen_motion`` the rest."""
    if train_frames is None:
        return {"train": list(range(total))}
    if isinstance(train_frames, bool) or not isinstance(train_frames, (int, np.integer)) \
            or not 1 <= train_frames <= total:
        raise ValueError(f"train_frames must be in [1, {total}], got {train_frames!r}")
    sequences = {"train": list(range(int(train_frames)))}
    if train_frames < total:
        sequences["unseen_motion"] = list(range(int(train_frames), total))
    return sequences


# ---- the capture ----------------------------------------------------------------------------------
class CaptureScene(RigLookup):
    """A ZJU-MoCap capture with the accessors of :class:`~garmentnerf.data.scene.Scene` where they
    make sense. Build with :meth:`load`.

    Attributes:
        root: the capture folder.
        rig: :class:`CaptureCamera` list, in ``annots`` order.
        frame_images: per capture frame, the image paths (relative to root) per camera.
        sequences: name -> list of capture frame indices.
        world_from_capture: (4, 4) rigid transform from the ZJU world (metres) to ours.
        translation_unit: ``"mm"`` or ``"m"``, how ``T`` was read.
        fps: frame rate given at load (ZJU stores none).
    """

    def __init__(self, root: Path, rig: list[CaptureCamera], frame_images: list[list[str]],
                 sequences: dict[str, list[int]], world_from_capture: np.ndarray, translation_unit: str,
                 mask_dirs: Sequence[str], fps: float, annots_path: Path) -> None:
        self.root = root
        self.rig = rig
        self.frame_images = frame_images
        self.sequences = sequences
        self.world_from_capture = world_from_capture
        self.translation_unit = translation_unit
        self.mask_dirs = tuple(mask_dirs)
        self.fps = float(fps)
        self.annots_path = annots_path
        # camera index -> cv2 undistortion maps, made on first use (guarded by the lock: loaders
        # may read one capture from several threads)
        self._undistort_maps_by_camera: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._undistort_maps_lock = threading.Lock()

    # ---- loading ----------------------------------------------------------------------------------
    @staticmethod
    def load(root: str | Path, train_frames: int | None = None, camera_splits: dict[str, str] | None = None,
             align: str | np.ndarray = "auto", translation_unit: str = "auto",
             mask_dirs: Sequence[str] = DEFAULT_MASK_DIRS, fps: float = 50.0, near: float = DEFAULT_NEAR,
             far: float = DEFAULT_FAR) -> "CaptureScene":
        """Read ``<root>/annots.npy`` and the first frame's image sizes.

        Args:
            train_frames: frames ``[0, train_frames)`` form sequence ``train``, the rest
                ``unseen_motion`` (None: every frame in ``train``).
            camera_splits: camera name -> ``train`` | ``unseen_view`` (unnamed cameras: ``train``).
            align: ``"auto"``, ``"none"`` or a (4, 4) rigid matrix (see the module docstring).
            translation_unit: ``"auto"``, ``"mm"`` or ``"m"`` for ``cams['T']``.
            mask_dirs: mask folders to try, in order.
            fps: the capture's frame rate (not stored by ZJU-MoCap; used for motions).
        Raises:
            CaptureError: naming the file and the field.
        """
        root = Path(root)
        annots_path, annots = _read_annots(root)
        src = str(annots_path)
        calibration = _read_calibration(annots["cams"], src)
        frame_images = _read_frame_images(annots["ims"], len(calibration), src)
        if translation_unit not in ("auto", "mm", "m"):
            raise ValueError(f"translation_unit must be 'auto', 'mm' or 'm', got {translation_unit!r}")
        if translation_unit == "auto":
            translation_unit = _guess_translation_unit(calibration)
        world_from_capture = _world_alignment(align, [R for _, R, _, _ in calibration])
        names = _camera_names(frame_images[0])
        splits = _checked_camera_splits(camera_splits, names)
        rig = []
        for i, (K, R, T, D) in enumerate(calibration):
            width, height = _image_size(root / frame_images[0][i], f"{src}: ims[0].ims[{i}]")
            # x_cam = R x_zju + t = R A^T (x_ours - b) + t: R' = R A^T, t' = t - R' b
            A, b = world_from_capture[:3, :3], world_from_capture[:3, 3]
            R_ours = R @ A.T
            t_ours = T * (1e-3 if translation_unit == "mm" else 1.0) - R_ours @ b
            rig.append(CaptureCamera(names[i], Camera(K, R_ours, t_ours, width, height, near, far),
                                     splits.get(names[i], "train"), None, D, i))
        sequences = _split_frames(train_frames, len(frame_images))
        return CaptureScene(root, rig, frame_images, sequences, world_from_capture, translation_unit, mask_dirs,
                            fps, annots_path)

    # ---- accessors (as Scene) ---------------------------------------------------------------------
    def cameras(self, split: str | Sequence[str] | None = None) -> list[CaptureCamera]:
        return in_splits(self.rig, split)

    def _lookup_error(self, problem: str) -> CaptureError:
        return CaptureError(f"{self.annots_path}: {problem}")

    def sequence_names(self, split: str | Sequence[str] | None = None) -> list[str]:
        if split is None:
            return list(self.sequences)
        wanted = {split} if isinstance(split, str) else set(split)
        return [s for s in self.sequences if s in wanted]  # a capture's sequence is named after its split

    def num_frames(self, sequence: str) -> int:
        return len(self._frames(sequence))

    def _frames(self, sequence: str) -> list[int]:
        if sequence not in self.sequences:
            raise self._lookup_error(f"no sequence '{sequence}' (sequences: {', '.join(self.sequences)})")
        return self.sequences[sequence]

    def capture_frame(self, sequence: str, frame: int) -> int:
        """Index into ``annots['ims']`` of frame ``frame`` of ``sequence``."""
        frames = self._frames(sequence)
        if isinstance(frame, bool) or not isinstance(frame, (int, np.integer)) or not 0 <= frame < len(frames):
            raise CaptureError(f"{self.annots_path}: frame {frame!r} is out of range for sequence '{sequence}' "
                               f"({len(frames)} frames)")
        return frames[int(frame)]

    def image_path(self, sequence: str, camera: str, frame: int) -> Path:
        return self.root / self.frame_images[self.capture_frame(sequence, frame)][self.camera(camera).index]

    def mask_path(self, sequence: str, camera: str, frame: int) -> Path | None:
        """The first existing mask for the image (``<mask dir>/<image path minus ext>.png``), or None."""
        rel = Path(self.frame_images[self.capture_frame(sequence, frame)][self.camera(camera).index])
        for folder in self.mask_dirs:
            candidate = (self.root / folder / rel).with_suffix(".png")
            if candidate.is_file():
                return candidate
        return None

    # ---- images -----------------------------------------------------------------------------------
    def _undistort_maps(self, cam: CaptureCamera) -> tuple[np.ndarray, np.ndarray]:
        """(H, W) float32 source x and y of every pinhole pixel in the raw image (``cv2.remap`` maps)."""
        with self._undistort_maps_lock:
            maps = self._undistort_maps_by_camera.get(cam.index)
            if maps is None:
                c = cam.camera
                maps = cv2.initUndistortRectifyMap(c.K, cam.dist, None, c.K, (c.width, c.height), cv2.CV_32FC1)
                self._undistort_maps_by_camera[cam.index] = maps
        return maps

    def load_image(self, sequence: str, camera: str, frame: int, undistort: bool = True) -> np.ndarray:
        """(H, W, 3) float32 RGB in [0, 1]; undistorted to the pinhole camera by default."""
        path = self.image_path(sequence, camera, frame)
        try:
            with Image.open(path) as im:
                rgb = np.asarray(im.convert("RGB"), dtype=np.float32) / 255.0
        except FileNotFoundError:
            raise CaptureError(f"{path}: no such image (listed in {self.annots_path})") from None
        cam = self.camera(camera)
        if rgb.shape[:2] != (cam.height, cam.width):
            raise CaptureError(f"{path}: image is {rgb.shape[1]}x{rgb.shape[0]}, camera '{camera}' is "
                               f"{cam.width}x{cam.height}")
        if undistort and np.any(cam.dist != 0):
            mx, my = self._undistort_maps(cam)
            rgb = cv2.remap(rgb, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        return rgb

    def load_mask(self, sequence: str, camera: str, frame: int, undistort: bool = True) -> np.ndarray:
        """(H, W) bool person mask (non-zero pixels of the mask file); undistorted (nearest) by default."""
        path = self.mask_path(sequence, camera, frame)
        if path is None:
            raise CaptureError(f"{self.root}: no mask for {self.image_path(sequence, camera, frame).name} of camera "
                               f"'{camera}' in {', '.join(self.mask_dirs)}")
        with Image.open(path) as im:
            m = np.asarray(im)
        if m.ndim == 3:
            m = m[..., 0]
        cam = self.camera(camera)
        if m.shape != (cam.height, cam.width):
            m = cv2.resize(m.astype(np.uint8), (cam.width, cam.height), interpolation=cv2.INTER_NEAREST)
        mask = m != 0
        if undistort and np.any(cam.dist != 0):
            mx, my = self._undistort_maps(cam)
            mask = cv2.remap(mask.astype(np.uint8), mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                             borderValue=0) != 0
        return mask

    # ---- SMPL -------------------------------------------------------------------------------------
    def capture_to_world(self, points) -> np.ndarray:
        """(..., 3) ZJU-world points (metres) -> our world."""
        p = np.asarray(points, dtype=np.float64)
        return p @ self.world_from_capture[:3, :3].T + self.world_from_capture[:3, 3]

    def params_path(self, sequence: str, frame: int) -> Path:
        """The frame's SMPL parameter file (rule in the module docstring)."""
        f = self.capture_frame(sequence, frame)
        indices = [i for i in (_param_index(Path(self.frame_images[f][0]).stem), f) if i is not None]
        candidates = []
        for folder in PARAMS_DIRS:
            for i in dict.fromkeys(indices):
                candidates += [self.root / folder / f"{i}.npy", self.root / folder / f"{i:06d}.npy"]
        for c in candidates:
            if c.is_file():
                return c
        raise CaptureError(f"{self.root}: no SMPL parameters for capture frame {f} (tried {candidates[0].name} in "
                           f"{' and '.join(PARAMS_DIRS)})")

    def smpl_params(self, sequence: str, frame: int) -> SmplParams:
        """The frame's SMPL fit, in ZJU's convention, checked."""
        path = self.params_path(sequence, frame)
        data = load_pickled_npy(path)
        if not isinstance(data, dict):
            raise CaptureError(f"{path}: must hold a dict with poses, Rh, Th, shapes")
        out = {}
        for key, rule in (("poses", "3 J"), ("Rh", "3"), ("Th", "3"), ("shapes", "S")):
            if key not in data:
                raise CaptureError(f"{path}: '{key}' is missing")
            try:
                a = np.asarray(data[key], dtype=np.float64)
            except (TypeError, ValueError):
                raise CaptureError(f"{path}: '{key}' must be numeric") from None
            if a.ndim > 2 or (a.ndim == 2 and a.shape[0] != 1):
                raise CaptureError(f"{path}: '{key}' must be (1, {rule}), got shape {a.shape}")
            a = a.reshape(-1)
            if (rule == "3" and a.size != 3) or (rule == "3 J" and (a.size < 3 or a.size % 3)) or a.size == 0:
                raise CaptureError(f"{path}: '{key}' must be (1, {rule}), got shape {np.shape(data[key])}")
            if not np.all(np.isfinite(a)):
                raise CaptureError(f"{path}: '{key}' contains NaN or Inf")
            out[key] = a
        return SmplParams(out["poses"], out["Rh"], out["Th"], out["shapes"])

    def _smpl_pose_arrays(self, sequence: str, body: "BodyModel", ground_offset: float,
                          frames: Sequence[int] | None) -> tuple[np.ndarray, np.ndarray, "torch.Tensor"]:
        """float64 (T, J, 3) rotation vectors and (T, 3) translations for ``body``, and the betas."""
        frame_list = list(range(self.num_frames(sequence))) if frames is None else list(frames)
        if not frame_list:
            raise ValueError("smpl_motion needs at least one frame")
        params = [self.smpl_params(sequence, f) for f in frame_list]
        J = body.num_joints
        for f, p in zip(frame_list, params):
            if p.poses.size != 3 * J:
                raise CaptureError(f"{self.params_path(sequence, f)}: poses has {p.poses.size // 3} joints, body "
                                   f"'{body.name}' has {J} (use the SMPL model the capture was fitted with)")
        betas = body.betas(params[0].shapes)
        J0 = body.rest(betas)[1][0].detach().cpu().double().numpy()
        C = SMPL_TO_WORLD
        A, b = self.world_from_capture[:3, :3], self.world_from_capture[:3, 3]
        h = float(ground_offset)
        rotations = np.zeros((len(params), J, 3))
        translation = np.zeros((len(params), 3))
        for k, p in enumerate(params):
            local = smpl_rotvecs_to_world(p.poses.reshape(J, 3))
            G = A @ _rodrigues(p.Rh) @ C.T  # SMPL model frame (our axes) -> our world
            g = A @ p.Th + b - h * G[:, 2]
            rotations[k] = local
            rotations[k, 0] = _rotvec(G @ _rodrigues(local[0]))
            translation[k] = G @ J0 + g - J0
        return rotations, translation, betas

    def smpl_motion(self, sequence: str, body: "BodyModel", ground_offset: float,
                    frames: Sequence[int] | None = None) -> tuple["Motion", "torch.Tensor"]:
        """The sequence as a :class:`Motion` (skeleton ``smpl``) for ``body`` in our world, and the
        shape coefficients to pose it with: ``motion.pose(body, betas)`` gives the capture's bodies.

        Args:
            body: an SMPL :class:`BodyModel` from the user's model file (the one the capture was
                fitted with).
            ground_offset: that file's :func:`~garmentnerf.body.smpl.smpl_ground_offset`.
            frames: frames of the sequence (default all).
        """
        rotations, translation, betas = self._smpl_pose_arrays(sequence, body, ground_offset, frames)
        motion = Motion(f"zju_{sequence}", list(body.joint_names), torch.as_tensor(rotations, dtype=torch.float32),
                        torch.as_tensor(translation, dtype=torch.float32), self.fps, "smpl")
        return motion, betas

    def smpl_vertices(self, sequence: str, frame: int, body: "BodyModel", ground_offset: float) -> np.ndarray:
        """(V, 3) posed SMPL vertices of one frame in our world (posed in ``body.dtype`` from float64
        parameters)."""
        rot, trans, betas = self._smpl_pose_arrays(sequence, body, ground_offset, [frame])
        posed = body.pose(torch.as_tensor(rot, dtype=body.dtype), torch.as_tensor(trans, dtype=body.dtype), betas)
        return posed.vertices[0].detach().cpu().double().numpy()
