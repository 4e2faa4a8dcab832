"""The camera path the previewer edits (the Camera path panel's state), and the lines that draw it.

Pure: no GL, no imgui. :class:`PathEditor` holds the keyframes the user adds from the window's view
and timeline frame; :meth:`PathEditor.path` makes the :class:`~garmentnerf.render.camera_path.CameraPath`
that the window looks through, the exporter renders and ``garmentnerf render --camera-path`` reads
back from the saved file. :func:`path_lines` draws it: the path's polyline, a small frustum per
keyframe, and the camera at the shown frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from garmentnerf.conventions import Camera
from garmentnerf.render.camera_path import CameraPath, Keyframe, load_camera_path, save_camera_path

#: Colours of the drawn path (display RGB): the polyline, the keyframes' frusta, the shown frame's camera.
PATH_COLOR = (0.95, 0.75, 0.20)
KEYFRAME_COLOR = (0.35, 0.75, 1.00)
CURRENT_COLOR = (1.00, 0.35, 0.35)
#: Depth of the drawn frusta, metres.
FRUSTUM_DEPTH = 0.2


@dataclass
class PathEditor:
    """Keyframes being edited, and how the window uses them.

    Attributes:
        keyframes: sorted by frame, at most one per frame.
        constant_speed: the path's timing (see :mod:`~garmentnerf.render.camera_path`).
        look_through: the window's camera follows the path (while there is one).
        show: the path is drawn in the scene (never while looking through it).
        file: where Save and Load go.
        version: counts changes (the drawn lines' upload key).
    """

    keyframes: list[Keyframe] = field(default_factory=list)
    constant_speed: bool = False
    look_through: bool = False
    show: bool = True
    file: str = "camera_path.json"
    version: int = 0
    _path_cache: tuple | None = field(default=None, repr=False)

    def _changed(self) -> None:
        self.keyframes.sort(key=lambda k: k.frame)
        self.version += 1

    def index_at(self, frame: float) -> int | None:
        """The keyframe at ``frame``, if any."""
        return next((i for i, k in enumerate(self.keyframes) if k.frame == float(frame)), None)

    def add(self, camera: Camera, frame: int) -> int:
        """A keyframe of ``camera`` at ``frame`` (replacing the one already there); returns its index."""
        key = Keyframe.from_camera(camera, frame)
        at = self.index_at(frame)
        if at is not None:
            self.keyframes[at] = key
        else:
            self.keyframes.append(key)
        self._changed()
        return self.index_at(frame)

    def replace_view(self, index: int, camera: Camera) -> None:
        """Keyframe ``index`` takes ``camera``'s view (its frame stays)."""
        self.keyframes[index] = Keyframe.from_camera(camera, self.keyframes[index].frame)
        self._changed()

    def move(self, index: int, frame: int) -> None:
        """Keyframe ``index`` to ``frame``; ValueError when another keyframe is there."""
        other = self.index_at(frame)
        if other is not None and other != index:
            raise ValueError(f"keyframe {other} is already at frame {frame}")
        k = self.keyframes[index]
        self.keyframes[index] = Keyframe(k.camera_to_world, k.fov_y, frame)
        self._changed()

    def remove(self, index: int) -> None:
        del self.keyframes[index]
        self._changed()

    def clear(self) -> None:
        self.keyframes.clear()
        self.look_through = False
        self._changed()

    def set_constant_speed(self, on: bool) -> None:
        if bool(on) != self.constant_speed:
            self.constant_speed = bool(on)
            self._changed()

    def set_show(self, on: bool) -> None:
        """Draw the path in the scene, or not."""
        self.show = bool(on)

    def set_file(self, file: str) -> None:
        """The file Save and Load use."""
        self.file = str(file)

    def path(self, size: tuple[int, int], fps: float) -> CameraPath | None:
        """The path at render ``size`` (W, H) and ``fps``; None without keyframes. Made once per change."""
        if not self.keyframes:
            return None
        key = (self.version, int(size[0]), int(size[1]), float(fps))
        if self._path_cache is None or self._path_cache[0] != key:
            path = CameraPath(tuple(self.keyframes), int(size[0]), int(size[1]), float(fps), self.constant_speed)
            self._path_cache = (key, path)
        return self._path_cache[1]

    def save(self, size: tuple[int, int], fps: float, overwrite: bool = False, file: str | Path | None = None) -> Path:
        """Write the path to ``file`` (default: :attr:`file`); ValueError without keyframes,
        FileExistsError when the file exists and not ``overwrite``."""
        path = self.path(size, fps)
        if path is None:
            raise ValueError("the camera path has no keyframes: add one first")
        return save_camera_path(path, Path(file if file is not None else self.file), overwrite=overwrite)

    def load(self, file: str | Path | None = None, num_frames: int | None = None,
             motion: str = "the clip") -> CameraPath:
        """Replace the keyframes with a path file's (ours or nerfstudio's; ``num_frames``: refuse
        keyframes outside a clip of that length); returns the path read. ValueError /
        FileNotFoundError for a bad file (the keyframes stay)."""
        path = load_camera_path(Path(file if file is not None else self.file))
        if num_frames is not None:
            path.check_motion(num_frames, motion)
        self.keyframes = list(path.keyframes)
        self.constant_speed = path.constant_speed
        self._changed()
        return path


def frustum_lines(key_camera_to_world: np.ndarray, fov_y: float, aspect: float,
                  depth: float = FRUSTUM_DEPTH) -> np.ndarray:
    """(20, 3) segment endpoints of a camera's frustum: apex to the four image corners at ``depth``
    metres, the image rectangle there, and a tick above its top edge (which way is up)."""
    half_h = depth * math.tan(math.radians(fov_y) / 2.0)
    half_w = half_h * aspect
    # image corners in OpenCV camera coordinates (x right, y down, z forward)
    corners = np.array([[-half_w, -half_h, depth], [half_w, -half_h, depth], [half_w, half_h, depth],
                        [-half_w, half_h, depth]])
    apex = np.zeros(3)
    tick = np.array([0.0, -1.6 * half_h, depth])
    local = [apex, corners[0], apex, corners[1], apex, corners[2], apex, corners[3]]
    for i in range(4):
        local += [corners[i], corners[(i + 1) % 4]]
    local += [corners[0] * [0.5, 1, 1], tick, tick, corners[1] * [0.5, 1, 1]]
    points = np.stack(local)
    return points @ key_camera_to_world[:3, :3].T + key_camera_to_world[:3, 3]


def path_lines(path: CameraPath, aspect: float, current_frame: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Segment endpoints (2N, 3) and colours (2N, 3) drawing ``path``: its polyline, a frustum per
    keyframe and (``current_frame``) the camera at that frame."""
    positions, colors = [], []
    line = path.polyline()
    if len(line) > 1:
        positions.append(np.repeat(line, 2, axis=0)[1:-1])
        colors.append(np.tile(PATH_COLOR, (2 * len(line) - 2, 1)))
    for key in path.keyframes:
        positions.append(frustum_lines(key.camera_to_world, key.fov_y, aspect))
        colors.append(np.tile(KEYFRAME_COLOR, (len(positions[-1]), 1)))
    if current_frame is not None:
        rotations, centres, fovs = path.interpolator.poses([current_frame])
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = rotations[0], centres[0]
        positions.append(frustum_lines(pose, float(fovs[0]), aspect, 1.3 * FRUSTUM_DEPTH))
        colors.append(np.tile(CURRENT_COLOR, (len(positions[-1]), 1)))
    return np.concatenate(positions), np.concatenate(colors)


__all__ = ["PathEditor", "frustum_lines", "path_lines", "PATH_COLOR", "KEYFRAME_COLOR", "CURRENT_COLOR"]
