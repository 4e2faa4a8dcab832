"""Cameras for rendering: turntable/orbit sequences, fixed orbit views, scene cameras by name or index.

The ``--camera`` argument of ``garmentnerf render`` (:func:`parse_camera_spec`):

* ``orbit`` / ``turntable`` -- one full turn around the body over the rendered frames (azimuth 0 =
  in front of the character), following the body's centre;
* ``orbit:AZ`` or ``orbit:AZ:EL`` -- a fixed orbit view at azimuth/elevation (degrees);
* a scene camera's name (``cam03``, ``ref_front`` ...) or its index in the scene's rig.

Orbit cameras default to the scene rig's geometry (3 m away, 40 degree vertical field of view,
at 1 m height looking at 0.9 m), so an orbit at the model's training resolution sees the body at
the scale it was trained at.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from garmentnerf.conventions import Camera, orbit_camera

#: Defaults matching :func:`garmentnerf.data.cameras.default_rig`.
ORBIT_RADIUS = 3.0
ORBIT_TARGET_HEIGHT = 0.9
ORBIT_ELEVATION = float(np.degrees(np.arctan2(1.0 - 0.9, 3.0)))
ORBIT_FOV = 40.0


@dataclass(frozen=True)
class CameraSpec:
    """A parsed ``--camera``: ``kind`` is ``"turntable"``, ``"orbit"`` (fixed) or ``"scene"``."""

    kind: str
    azimuth: float = 0.0
    elevation: float = ORBIT_ELEVATION
    name: str | None = None


def parse_camera_spec(text: str, scene=None) -> CameraSpec:
    """Parse ``--camera`` (see the module docstring); raises ValueError with a one-line message."""
    t = str(text).strip()
    low = t.lower()
    if low in ("orbit", "turntable"):
        return CameraSpec("turntable")
    if low.startswith("orbit:"):
        parts = t.split(":")[1:]
        try:
            values = [float(p) for p in parts]
        except ValueError:
            values = []
        if not 1 <= len(values) <= 2 or not all(np.isfinite(values)):
            raise ValueError(f"camera '{t}': use orbit:AZIMUTH or orbit:AZIMUTH:ELEVATION (degrees)")
        if len(values) == 2 and not -89.0 <= values[1] <= 89.0:
            raise ValueError(f"camera '{t}': elevation must be in [-89, 89] degrees")
        return CameraSpec("orbit", values[0], values[1] if len(values) == 2 else ORBIT_ELEVATION)
    names = scene.camera_names() if scene is not None else []
    if t in names:
        return CameraSpec("scene", name=t)
    if t.lstrip("-").isdigit():
        i = int(t)
        if scene is None:
            raise ValueError(f"camera index {i} needs a scene (--scene DIR or a run with a scene)")
        if not 0 <= i < len(names):
            raise ValueError(f"camera index {i} is out of range (the scene has {len(names)} cameras: 0..{len(names) - 1})")
        return CameraSpec("scene", name=names[i])
    known = ", ".join(names[:12]) + (" ..." if len(names) > 12 else "") if names else "none: no scene"
    raise ValueError(f"unknown camera '{t}' (use orbit, orbit:AZ[:EL], a scene camera index or name; "
                     f"scene cameras: {known})")


def scene_camera(scene, name_or_index) -> Camera:
    """A scene camera by name or rig index."""
    names = scene.camera_names()
    if isinstance(name_or_index, (int, np.integer)) and not isinstance(name_or_index, bool):
        if not 0 <= int(name_or_index) < len(names):
            raise ValueError(f"camera index {name_or_index} is out of range (0..{len(names) - 1})")
        name_or_index = names[int(name_or_index)]
    if name_or_index not in names:
        raise ValueError(f"unknown camera '{name_or_index}' (scene cameras: {', '.join(names)})")
    return scene.camera(name_or_index).camera


def fit_size(camera: Camera, size: int | tuple[int, int]) -> Camera:
    """``camera`` resized: an int is the longer side (aspect kept), a pair is (W, H)."""
    if isinstance(size, (tuple, list)):
        w, h = int(size[0]), int(size[1])
    else:
        s = int(size)
        if camera.width >= camera.height:
            w, h = s, max(1, round(s * camera.height / camera.width))
        else:
            w, h = max(1, round(s * camera.width / camera.height)), s
    return camera if (w, h) == (camera.width, camera.height) else camera.resized(w, h)


def orbit_view(azimuth: float, elevation: float = ORBIT_ELEVATION, center=(0.0, 0.0), width: int = 256,
               height: int = 256, radius: float = ORBIT_RADIUS, fov_y: float = ORBIT_FOV,
               target_height: float = ORBIT_TARGET_HEIGHT) -> Camera:
    """An orbit camera around ``(center_x, center_y, target_height)``."""
    target = (float(center[0]), float(center[1]), float(target_height))
    return orbit_camera(azimuth, elevation, radius, target, width, height, fov_y)


def turntable(count: int, width: int = 256, height: int = 256, centers=None, elevation: float = ORBIT_ELEVATION,
              start_azimuth: float = 0.0, turns: float = 1.0, **kwargs) -> list[Camera]:
    """``count`` cameras making ``turns`` full turns (the last frame stops one step short of the
    first, so the video loops); ``centers`` (count, >=2) optional per-frame body centres to follow."""
    if count < 1:
        raise ValueError(f"turntable needs at least one camera, got {count}")
    cams = []
    for i in range(count):
        az = start_azimuth + 360.0 * turns * i / count
        c = (0.0, 0.0) if centers is None else centers[i]
        cams.append(orbit_view(az, elevation, c, width, height, **kwargs))
    return cams


def cameras_for(spec: CameraSpec, frames: list[int], size, scene=None, centers=None) -> list[Camera]:
    """One camera per rendered frame for a parsed ``--camera``.

    ``size``: an int (the longer side; orbit views are square) or (W, H); ``centers``: per-frame
    (x, y) body centres (orbit views follow the body).
    """
    n = len(frames)
    if spec.kind == "scene":
        cam = fit_size(scene_camera(scene, spec.name), size)
        return [cam] * n
    w, h = (int(size[0]), int(size[1])) if isinstance(size, (tuple, list)) else (int(size), int(size))
    if spec.kind == "turntable":
        return turntable(n, w, h, centers, spec.elevation, spec.azimuth)
    return [orbit_view(spec.azimuth, spec.elevation, (0.0, 0.0) if centers is None else centers[i], w, h)
            for i in range(n)]


__all__ = ["CameraSpec", "parse_camera_spec", "scene_camera", "fit_size", "orbit_view", "turntable", "cameras_for"]
