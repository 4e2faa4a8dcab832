"""Camera paths: keyframed camera moves over a motion, their interpolation and their JSON file.

A :class:`CameraPath` is a list of :class:`Keyframe` s, each a camera pose, a vertical field of view
and the *motion frame* at which the camera is there: the path's time is the timeline's frame, so
the camera and the character move together. The previewer's camera-path panel makes one, ``garmentnerf
render --camera-path`` renders one, and both go through :meth:`CameraPath.cameras` and the one render
path (:class:`~garmentnerf.render.session.RenderSession`), so a path gives the same pixels in both.

Interpolation (:class:`PathInterpolator`)
    * Position: a cubic Hermite spline with Catmull-Rom tangents for non-uniform knots
      (Barry-Goldman), C1, through every keyframe exactly.
    * Orientation: :class:`scipy.spatial.transform.RotationSpline` over the same knots, C2 in the
      rotation, through every keyframe exactly. It interpolates the relative rotation between
      neighbouring keyframes, so there are no flips: a 180-degree turn between two keyframes turns
      the camera through 180 degrees about the axis between them, and the image's up stays up.
    * Field of view: a monotone cubic (PCHIP), C1, with no overshoot between keyframes.
    * Timing: by default the knots are the keyframes' frames, so each keyframe is hit at its frame.
      With ``constant_speed`` the knots are centripetal (the square root of the distance between
      keyframes, which avoids cusps and loops) and the path is re-timed by arc length, so that the
      camera moves at constant speed from the first keyframe's frame to the last one's. Keyframes
      are still passed through exactly, but at the frame their distance along the path puts them.
      Arc length counts a radian of turn as :data:`TURN_METRES` metres, so a camera that only
      turns on the spot still takes time.
    Outside ``[first frame, last frame]`` the path holds its end cameras.

File format (``*.json``, written by :func:`save_camera_path`)::

    {"format": "garmentnerf-camera-path", "version": 1,
     "width": 1280, "height": 720, "fps": 30.0, "constant_speed": false,
     "keyframes": [{"frame": 0, "fov_y": 35.0,
                    "camera_to_world": [[r00, r01, r02, x], [r10, r11, r12, y], [r20, r21, r22, z], [0, 0, 0, 1]]},
                   ...]}

``camera_to_world`` is the OpenCV-convention pose of :mod:`garmentnerf.conventions`: its columns are
the image's right, the image's down and the viewing direction in world coordinates (Z up, metres)
and the camera centre. ``fov_y`` is the vertical field of view in degrees, ``frame`` the motion
frame (a number, may be fractional), ``width``/``height`` the render size (8..8192) and ``fps`` the
video's frame rate (:data:`~garmentnerf.budgets.VIDEO_FPS`). The file is read by the project's
strict JSON reader (:func:`~garmentnerf.io_utils.read_json_strict`: NaN, Infinity and ``1e999`` are
refused, naming the key), ``constant_speed`` must be a JSON boolean, and a camera may be at most
:data:`MAX_DISTANCE_M` from the origin.

nerfstudio's ``camera_path.json`` (``ns-render camera-path``) loads too: every entry of its
``camera_path`` list (``camera_to_world`` as 16 row-major numbers, ``fov`` vertical in degrees)
becomes a keyframe at motion frame 0, 1, 2 ...; ``render_width``/``render_height`` and ``fps``
carry over. Its cameras are OpenGL-convention (x right, y up, looking down -z); they are converted
by flipping the camera's y and z axes. Its world is taken as ours (Z up, metres), which holds for a
path made in nerfstudio's viewer on a Z-up scene.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from garmentnerf.conventions import Camera, intrinsics_from_fov
from garmentnerf.io_utils import json_bool, json_number, json_whole, read_json_strict, write_file_atomic
from garmentnerf.budgets import VIDEO_FPS

FORMAT = "garmentnerf-camera-path"
VERSION = 1
#: In constant-speed arc length, a radian of camera turn counts as this many metres of travel.
TURN_METRES = 1.0
#: Largest deviation of a keyframe's rotation from orthonormal (|R^T R - I|, |det R - 1|) accepted.
RIGID_TOLERANCE = 1e-4
#: Arc-length table resolution of constant-speed paths: samples per keyframe interval.
ARC_SAMPLES = 256
#: Render sizes a path may ask for (pixels per side).
MIN_SIZE, MAX_SIZE = 8, 8192
#: How far from the world's origin a keyframe's camera may be, metres (a character is a couple of metres
#: tall; further out, the projections lose every pixel to float rounding).
MAX_DISTANCE_M = 1000.0
#: OpenGL camera axes (x right, y up, z back) -> OpenCV camera axes (x right, y down, z forward).
_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def _rigid_error(rotation: np.ndarray) -> float:
    """How far (3, 3) ``rotation`` is from a proper rotation (orthonormal, determinant +1)."""
    orthonormal = np.abs(rotation.T @ rotation - np.eye(3)).max()
    return float(max(orthonormal, abs(np.linalg.det(rotation) - 1.0)))


@dataclass(frozen=True, eq=False)
class Keyframe:
    """One camera of a path.

    Attributes:
        camera_to_world: (4, 4) pose in the OpenCV convention (see the module doc).
        fov_y: vertical field of view, degrees, in (0, 180).
        frame: the motion frame at which the camera is here.
    """

    camera_to_world: np.ndarray
    fov_y: float
    frame: float

    def __post_init__(self) -> None:
        m = np.asarray(self.camera_to_world, dtype=np.float64)
        if m.shape == (3, 4):
            m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
        if m.shape != (4, 4):
            raise ValueError(f"camera_to_world must be 4x4 (or 3x4), got shape {m.shape}")
        if not np.all(np.isfinite(m)):
            raise ValueError("camera_to_world contains NaN or Inf")
        if np.abs(m[3] - [0.0, 0.0, 0.0, 1.0]).max() > RIGID_TOLERANCE:
            raise ValueError(f"camera_to_world's last row must be 0 0 0 1, got {m[3].tolist()}")
        distance = math.hypot(*(float(x) for x in m[:3, 3]))  # no overflow warning for a far one
        if distance > MAX_DISTANCE_M:
            raise ValueError(f"the camera is {distance:.3g} m from the world's origin, more than the "
                             f"{MAX_DISTANCE_M:g} m a path may go")
        error = _rigid_error(m[:3, :3])
        if error > RIGID_TOLERANCE:
            raise ValueError(f"camera_to_world's rotation is not rigid (off by {error:.2g}: scaled, sheared "
                             f"or mirrored)")
        fov = float(self.fov_y)
        if not 0.0 < fov < 180.0:
            raise ValueError(f"fov_y must be in (0, 180) degrees, got {self.fov_y}")
        frame = float(self.frame)
        if not math.isfinite(frame):
            raise ValueError(f"frame must be a number, got {self.frame}")
        object.__setattr__(self, "camera_to_world", m)
        object.__setattr__(self, "fov_y", fov)
        object.__setattr__(self, "frame", frame)

    @staticmethod
    def from_camera(camera: Camera, frame: float) -> "Keyframe":
        """The keyframe of ``camera`` (its pose and vertical field of view) at ``frame``."""
        m = np.eye(4)
        m[:3, :3] = camera.R.T
        m[:3, 3] = camera.center
        fov = math.degrees(2.0 * math.atan(0.5 * camera.height / camera.K[1, 1]))
        return Keyframe(m, fov, frame)

    @property
    def position(self) -> np.ndarray:
        return self.camera_to_world[:3, 3]

    def camera(self, width: int, height: int) -> Camera:
        return make_camera(self.camera_to_world[:3, :3], self.position, self.fov_y, width, height)


def make_camera(camera_to_world_rotation: np.ndarray, position: np.ndarray, fov_y: float, width: int,
                height: int) -> Camera:
    """A :class:`Camera` at ``position`` with axes ``camera_to_world_rotation`` (3, 3; OpenCV
    convention), principal point at the image centre and square pixels."""
    R = np.asarray(camera_to_world_rotation, dtype=np.float64).T
    K = intrinsics_from_fov(int(width), int(height), float(fov_y))
    return Camera(K, R, -R @ np.asarray(position, dtype=np.float64), int(width), int(height))


def catmull_rom_tangents(knots: np.ndarray, values: np.ndarray) -> np.ndarray:
    """(K, D) tangents of a Catmull-Rom spline through ``values`` (K, D) at increasing ``knots`` (K,).

    Interior tangents are Barry-Goldman's for non-uniform knots (for evenly spaced knots this is
    the classic ``(v[i+1] - v[i-1]) / (t[i+1] - t[i-1])``); the end tangents are one-sided
    differences, so two keyframes give a straight line at constant speed.
    """
    t = np.asarray(knots, dtype=np.float64)
    v = np.asarray(values, dtype=np.float64)
    if len(t) < 2:
        return np.zeros_like(v)
    slopes = np.diff(v, axis=0) / np.diff(t)[:, None]  # (K-1, D)
    tangents = np.empty_like(v)
    tangents[0], tangents[-1] = slopes[0], slopes[-1]
    if len(t) > 2:
        span = (t[2:] - t[:-2])[:, None]
        tangents[1:-1] = slopes[:-1] + slopes[1:] - (v[2:] - v[:-2]) / span
    return tangents


def centripetal_knots(keyframes: tuple[Keyframe, ...]) -> np.ndarray:
    """(K,) knots spaced by the square root of the distance between neighbouring keyframes
    (travel plus :data:`TURN_METRES` per radian of turn; a floor keeps coincident keyframes apart)."""
    from scipy.spatial.transform import Rotation  # lazy: scipy costs the previewer's start a second

    steps = [0.0]
    for a, b in zip(keyframes[:-1], keyframes[1:]):
        turn = Rotation.from_matrix(a.camera_to_world[:3, :3].T @ b.camera_to_world[:3, :3]).magnitude()
        distance = math.hypot(float(np.linalg.norm(b.position - a.position)), TURN_METRES * turn)
        steps.append(math.sqrt(max(distance, 1e-8)))
    return np.cumsum(steps)


class PathInterpolator:
    """The splines of a path (see the module doc), evaluated at motion frames.

    Args:
        keyframes: at least one, with strictly increasing frames.
        constant_speed: re-time by arc length (see the module doc).
    """

    def __init__(self, keyframes: tuple[Keyframe, ...], constant_speed: bool = False) -> None:
        self.keyframes = keyframes
        self.first_frame, self.last_frame = keyframes[0].frame, keyframes[-1].frame
        self.constant_speed = bool(constant_speed)
        self._single = len(keyframes) == 1
        if self._single:
            self.knots = np.array([self.first_frame])
            return
        from scipy.interpolate import CubicHermiteSpline, PchipInterpolator  # lazy: see centripetal_knots
        from scipy.spatial.transform import Rotation, RotationSpline

        knots = centripetal_knots(keyframes) if constant_speed else np.array([k.frame for k in keyframes])
        positions = np.stack([k.position for k in keyframes])
        self.knots = knots
        self._position = CubicHermiteSpline(knots, positions, catmull_rom_tangents(knots, positions), axis=0)
        self._rotation = RotationSpline(knots, Rotation.from_matrix(np.stack([k.camera_to_world[:3, :3]
                                                                               for k in keyframes])))
        self._fov = PchipInterpolator(knots, np.array([k.fov_y for k in keyframes]))
        self._arc = self._arc_length_table() if constant_speed else None

    def _arc_length_table(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(knot parameter (N,), arc length (N,)) sampled densely; None for a path that does not move."""
        u = np.linspace(self.knots[0], self.knots[-1], ARC_SAMPLES * (len(self.knots) - 1) + 1)
        travel = np.linalg.norm(np.diff(self._position(u), axis=0), axis=1)
        rotations = self._rotation(u)
        turn = (rotations[:-1].inv() * rotations[1:]).magnitude()
        s = np.concatenate([[0.0], np.cumsum(np.hypot(travel, TURN_METRES * turn))])
        return (u, s) if s[-1] > 1e-9 else None

    def parameter(self, frames: np.ndarray) -> np.ndarray:
        """(N,) spline parameter of motion ``frames`` (N,), clamped to the path's span."""
        f = np.clip(np.asarray(frames, dtype=np.float64), self.first_frame, self.last_frame)
        if not self.constant_speed:
            return f  # the knots are the frames
        if self._arc is None:  # a path that does not move: evenly in the knots
            return np.interp(f, [self.first_frame, self.last_frame], [self.knots[0], self.knots[-1]])
        u, s = self._arc
        fraction = (f - self.first_frame) / (self.last_frame - self.first_frame)
        return np.interp(fraction * s[-1], s, u)

    def poses(self, frames) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Camera-to-world rotations (N, 3, 3), positions (N, 3) and vertical fields of view (N,)
        at motion ``frames`` (N,)."""
        frames = np.atleast_1d(np.asarray(frames, dtype=np.float64))
        if self._single:
            k = self.keyframes[0]
            n = len(frames)
            return (np.repeat(k.camera_to_world[None, :3, :3], n, 0), np.repeat(k.position[None], n, 0),
                    np.full(n, k.fov_y))
        return self.poses_at_parameter(self.parameter(frames))

    def poses_at_parameter(self, u) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """As :meth:`poses`, at spline parameters ``u`` (N,) (``knots[i]`` is keyframe i)."""
        u = np.atleast_1d(np.asarray(u, dtype=np.float64))
        if self._single:
            return self.poses(np.full(len(u), self.first_frame))
        return self._rotation(u).as_matrix(), self._position(u), self._fov(u)


@dataclass(frozen=True, eq=False)
class CameraPath:
    """A keyframed camera move over a motion (see the module doc).

    Attributes:
        keyframes: sorted by frame, strictly increasing (at least one).
        width, height: render size in pixels.
        fps: video frame rate.
        constant_speed: move at constant speed instead of hitting each keyframe at its frame.
    """

    keyframes: tuple[Keyframe, ...]
    width: int = 1280
    height: int = 720
    fps: float = 30.0
    constant_speed: bool = False

    def __post_init__(self) -> None:
        keyframes = tuple(self.keyframes)
        if not keyframes:
            raise ValueError("the camera path has no keyframes")
        frames = [k.frame for k in keyframes]
        for i in range(1, len(frames)):
            if frames[i] <= frames[i - 1]:
                raise ValueError(f"keyframe {i} is at frame {frames[i]:g}, not after keyframe {i - 1} "
                                 f"(frame {frames[i - 1]:g}): frames must increase")
        for name in ("width", "height"):
            value = getattr(self, name)
            if not (isinstance(value, (int, np.integer)) and MIN_SIZE <= value <= MAX_SIZE):
                raise ValueError(f"{name} must be a whole number of pixels in {MIN_SIZE}..{MAX_SIZE}, got {value}")
        VIDEO_FPS.check(self.fps, "fps")
        object.__setattr__(self, "keyframes", keyframes)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        object.__setattr__(self, "fps", float(self.fps))
        object.__setattr__(self, "constant_speed", bool(self.constant_speed))

    @cached_property
    def token(self) -> tuple:
        """A hashable value equal for paths that place every camera alike (size and fps aside)."""
        return (self.constant_speed,) + tuple((k.frame, k.fov_y, k.camera_to_world.tobytes()) for k in self.keyframes)

    @cached_property
    def interpolator(self) -> PathInterpolator:
        return PathInterpolator(self.keyframes, self.constant_speed)

    @property
    def first_frame(self) -> float:
        return self.keyframes[0].frame

    @property
    def last_frame(self) -> float:
        return self.keyframes[-1].frame

    def frames(self) -> list[int]:
        """The whole motion frames the path spans: ceil(first) .. floor(last)."""
        return list(range(math.ceil(self.first_frame), math.floor(self.last_frame) + 1))

    def render_frames(self) -> list[int]:
        """:meth:`frames`, refusing (ValueError, one line) a path that spans no whole frame: a render
        of it would have nothing to show."""
        frames = self.frames()
        if not frames:
            raise ValueError(f"its keyframes (frames {self.first_frame:g}..{self.last_frame:g}) span no whole "
                             f"motion frame; put a keyframe on a whole frame, or pass the frames to render")
        return frames

    def check_motion(self, num_frames: int, motion: str = "the motion") -> None:
        """ValueError (one line) when a keyframe lies outside frames 0..num_frames-1 of the motion."""
        for i, k in enumerate(self.keyframes):
            if not 0.0 <= k.frame <= num_frames - 1:
                raise ValueError(f"keyframe {i} is at frame {k.frame:g}, outside {motion} "
                                 f"({num_frames} frames: 0..{num_frames - 1})")

    def size(self, size=None) -> tuple[int, int]:
        """(W, H): the path's own size (``size`` None), ``size`` (W, H), or an int: the longer side
        with the path's aspect ratio."""
        if size is None:
            return self.width, self.height
        if isinstance(size, (tuple, list)):
            return int(size[0]), int(size[1])
        s = int(size)
        if self.width >= self.height:
            return s, max(1, round(s * self.height / self.width))
        return max(1, round(s * self.width / self.height)), s

    def cameras(self, frames, size=None) -> list[Camera]:
        """One :class:`Camera` per motion frame of ``frames`` at ``size`` (see :meth:`size`)."""
        w, h = self.size(size)
        frames = np.atleast_1d(np.asarray(frames, dtype=np.float64))
        rotations, positions, fovs = self.interpolator.poses(frames)
        return [make_camera(r, p, f, w, h) for r, p, f in zip(rotations, positions, fovs)]

    def camera_at(self, frame: float, width: int, height: int) -> Camera:
        return self.cameras([frame], (width, height))[0]

    def polyline(self, samples_per_interval: int = 24) -> np.ndarray:
        """(N, 3) camera centres along the path (for drawing it)."""
        if len(self.keyframes) == 1:
            return self.keyframes[0].position[None].copy()
        n = samples_per_interval * (len(self.keyframes) - 1) + 1
        return self.interpolator.poses(np.linspace(self.first_frame, self.last_frame, n))[1]

    def with_keyframes(self, keyframes) -> "CameraPath":
        """This path's settings with other keyframes (sorted by frame)."""
        ordered = tuple(sorted(keyframes, key=lambda k: k.frame))
        return CameraPath(ordered, self.width, self.height, self.fps, self.constant_speed)


# ---- JSON ----------------------------------------------------------------------------------------------
def path_to_json(path: CameraPath) -> dict:
    return {"format": FORMAT, "version": VERSION, "width": path.width, "height": path.height, "fps": path.fps,
            "constant_speed": path.constant_speed,
            "keyframes": [{"frame": k.frame, "fov_y": k.fov_y,
                           "camera_to_world": [[float(x) for x in row] for row in k.camera_to_world]}
                          for k in path.keyframes]}


def _numbers(value, what: str) -> None:
    """ValueError naming ``what`` unless ``value`` is (nested lists of) JSON numbers."""
    if isinstance(value, list):
        for item in value:
            _numbers(item, what)
    else:
        json_number(value, f"{what}'s entries")


def _matrix(value, what: str) -> np.ndarray:
    if not isinstance(value, list):
        raise ValueError(f"{what} must be a 4x4 matrix of numbers, got {type(value).__name__}")
    _numbers(value, what)
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be a 4x4 matrix of numbers") from None
    if m.size == 16:
        return m.reshape(4, 4)
    if m.size == 12:
        return m.reshape(3, 4)
    raise ValueError(f"{what} must be 4x4 (or 3x4) numbers, got {m.size}")


def _keyframe(item, i: int, convert=None, frame=None, fov_key: str = "fov_y") -> Keyframe:
    if not isinstance(item, dict):
        raise ValueError(f"keyframe {i} must be an object, got {type(item).__name__}")
    for key in ("camera_to_world", fov_key) + (() if frame is not None else ("frame",)):
        if key not in item:
            raise ValueError(f"keyframe {i} has no '{key}'")
    m = _matrix(item["camera_to_world"], f"keyframe {i}'s camera_to_world")
    if convert is not None:
        m = (np.vstack([m, [0.0, 0.0, 0.0, 1.0]]) if m.shape == (3, 4) else m) @ convert
    try:
        return Keyframe(m, json_number(item[fov_key], f"keyframe {i}'s {fov_key}"),
                        frame if frame is not None else json_number(item["frame"], f"keyframe {i}'s frame"))
    except ValueError as exc:
        raise ValueError(f"keyframe {i}: {exc}") from None


def path_from_json(data) -> CameraPath:
    """A path from parsed JSON: this project's format or nerfstudio's ``camera_path.json`` (see the
    module doc). ValueError (one line) for anything else."""
    if not isinstance(data, dict):
        raise ValueError(f"a camera path must be a JSON object, got {type(data).__name__}")
    if data.get("format") == FORMAT:
        if json_whole(data.get("version", VERSION), "version", 1) > VERSION:
            raise ValueError(f"version {data['version']} is newer than this garmentnerf reads ({VERSION})")
        keyframes = data.get("keyframes")
        if not isinstance(keyframes, list) or not keyframes:
            raise ValueError("the camera path has no keyframes")
        items = [_keyframe(k, i) for i, k in enumerate(keyframes)]
        return CameraPath(tuple(items), json_whole(data.get("width", 1280), "width", MIN_SIZE, MAX_SIZE),
                          json_whole(data.get("height", 720), "height", MIN_SIZE, MAX_SIZE),
                          VIDEO_FPS.check(json_number(data.get("fps", 30.0), "fps"), "fps"),
                          json_bool(data.get("constant_speed", False), "constant_speed"))
    if "camera_path" in data:  # nerfstudio
        entries = data["camera_path"]
        if not isinstance(entries, list) or not entries:
            raise ValueError("the camera path has no keyframes (nerfstudio 'camera_path' is empty)")
        items = [_keyframe(k, i, convert=_GL_TO_CV, frame=float(i), fov_key="fov") for i, k in enumerate(entries)]
        fps = data.get("fps")
        if fps is None and data.get("seconds"):
            fps = len(entries) / json_number(data["seconds"], "seconds", 0.0, low_open=True)
        return CameraPath(tuple(items), json_whole(data.get("render_width", 1280), "render_width", MIN_SIZE, MAX_SIZE),
                          json_whole(data.get("render_height", 720), "render_height", MIN_SIZE, MAX_SIZE),
                          VIDEO_FPS.check(json_number(fps if fps is not None else 30.0, "fps"), "fps"))
    raise ValueError(f"not a camera path: no \"format\": \"{FORMAT}\" and no nerfstudio 'camera_path' list")


def load_camera_path(file: str | Path) -> CameraPath:
    """Read a path file (:func:`~garmentnerf.io_utils.read_json_strict`, then :func:`path_from_json`):
    ValueError naming the file (and the key) for anything wrong with it, FileNotFoundError, IsADirectoryError."""
    file = Path(file)
    data = read_json_strict(file, "camera path")  # NaN, Infinity, 1e999: refused naming the key
    try:
        return path_from_json(data)
    except ValueError as exc:
        raise ValueError(f"{file}: {exc}") from None


def save_camera_path(path: CameraPath, file: str | Path, overwrite: bool = False) -> Path:
    """Write ``path`` as JSON (atomically); FileExistsError when ``file`` exists and not ``overwrite``."""
    file = Path(file)
    if file.exists() and not overwrite:
        raise FileExistsError(f"{file} exists (pass overwrite to replace it)")
    write_file_atomic(file, json.dumps(path_to_json(path), indent=1).encode("utf-8"))
    return file


__all__ = ["Keyframe", "CameraPath", "PathInterpolator", "catmull_rom_tangents", "centripetal_knots",
           "make_camera", "path_to_json", "path_from_json", "load_camera_path", "save_camera_path",
           "FORMAT", "VERSION", "TURN_METRES"]
