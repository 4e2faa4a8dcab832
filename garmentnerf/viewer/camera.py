"""Turntable camera controller: orbit, pan, zoom, view presets, follow-the-body. Pure math, no GL.

The controller keeps spherical coordinates about a target point (azimuth and elevation in the sense
of :func:`garmentnerf.conventions.orbit_camera`: azimuth 0 looks at the character's front from the
-Y side, 90 is on +X, the character's left; elevation is above the horizon) and produces a
:class:`~garmentnerf.conventions.Camera` for any image size. The world's up (+Z) stays up on screen:
elevation is clamped short of the poles.

:class:`MouseGestures` turns the window's mouse input (imgui's state, handed in) into orbit, pan and
zoom of a controller.

Follow mode: the target is stored *relative to an anchor* (the body's ground position, updated by
the app every frame), so the camera travels with a walking body; switching follow on or off
re-expresses the target so the view does not jump. The anchor the app gives is the clip's follow
track (:func:`follow_track`): the body centre's ground position, smoothed over
:data:`FOLLOW_SMOOTHING_S` either side, so a clip that walks away is followed at its pace while a
dance in place, whose centre sways with the arms and hips, does not shake the camera.
:meth:`OrbitController.follow_view` is that camera as a function of the frame
(:class:`FollowView`), the form in which the neural render worker is given it (as a camera path it
looks through), so a followed clip renders ahead like one seen from a still camera.

The previewer follows the body by default: a clip may travel several metres (the library's ``run``
2.7 m, an AMASS walk tens of metres), and a camera that framed the whole trajectory would show the
character small (and the neural render has fewer pixels to work with), while a following camera keeps
it at the home distance, centred, whatever the clip does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from garmentnerf.conventions import DEFAULT_FAR, Camera, look_at, orbit_camera

#: View presets: azimuth in degrees (orbit_camera's convention).
VIEW_DIRECTIONS: dict[str, float] = {"front": 0.0, "left": 90.0, "back": 180.0, "right": -90.0}
#: The range of the orbit camera's vertical field of view, degrees.
MIN_FOV_Y, MAX_FOV_Y = 10.0, 90.0
#: The follow track averages the body centre over this many seconds either side of a frame.
FOLLOW_SMOOTHING_S = 0.5


def follow_track(centers: np.ndarray, fps: float, seconds: float = FOLLOW_SMOOTHING_S) -> np.ndarray:
    """(T, 3) float64 where a following camera is anchored at each frame: the ground position (z = 0)
    of the per-frame body ``centers`` (T, 3), averaged over ``seconds`` either side of the frame.
    The window shrinks symmetrically at the clip's ends (frame 0 and the last frame are their own
    centres), so a body moving at a constant velocity is followed without lag anywhere."""
    c = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    T = len(c)
    out = np.zeros((T, 3))
    if T == 0:
        return out
    ground = np.where(np.isfinite(c[:, :2]), c[:, :2], 0.0)
    half = max(0, int(round(float(seconds) * float(fps)))) if math.isfinite(seconds * fps) else 0
    cumulative = np.concatenate([np.zeros((1, 2)), np.cumsum(ground, axis=0)])
    for t in range(T):
        h = min(half, t, T - 1 - t)
        out[t, :2] = (cumulative[t + h + 1] - cumulative[t - h]) / (2 * h + 1)
    return out


@dataclass(frozen=True)
class FollowView:
    """A following :class:`OrbitController`'s camera as a function of the clip frame: the orbit
    (angles, distance, field of view, clip planes) about ``target`` relative to the anchor, with the
    anchor at ``track[frame]`` (a :func:`follow_track`). It has what the neural render worker asks of
    a camera path (:class:`~garmentnerf.render.camera_path.CameraPath`): :meth:`camera_at` and
    :attr:`token`."""

    azimuth: float
    elevation: float
    distance: float
    target: tuple[float, float, float]
    fov_y: float
    near: float
    far: float
    track: np.ndarray = field(repr=False, compare=False)
    track_key: object = None

    def anchor(self, frame: float) -> np.ndarray:
        """(3,) the anchor at ``frame`` (rounded, clamped to the track)."""
        i = min(max(0, int(round(float(frame)))), len(self.track) - 1)
        return self.track[i]

    def camera_at(self, frame: float, width: int, height: int) -> Camera:
        """The camera the following controller gives at ``frame`` for a ``width`` x ``height`` image."""
        world_target = np.asarray(self.target, dtype=np.float64) + self.anchor(frame)
        return orbit_camera(self.azimuth, self.elevation, self.distance, world_target, int(width), int(height),
                            self.fov_y, self.near, self.far)

    @property
    def token(self) -> tuple:
        """Equal for two follow views that place every frame's camera alike (size aside)."""
        return ("follow", self.azimuth, self.elevation, self.distance, self.target, self.fov_y, self.near, self.far,
                self.track_key)


def _wrap_degrees(angle: float) -> float:
    """Angle in (-180, 180]."""
    a = math.fmod(angle, 360.0)
    if a <= -180.0:
        a += 360.0
    elif a > 180.0:
        a -= 360.0
    return a


@dataclass
class CameraHome:
    """The view :meth:`OrbitController.reset` returns to."""

    azimuth: float = 25.0
    elevation: float = 8.0
    distance: float = 3.6
    target: tuple[float, float, float] = (0.0, 0.0, 0.9)
    fov_y: float = 35.0


@dataclass
class OrbitController:
    """Turntable orbit/pan/zoom about a target.

    Attributes:
        azimuth, elevation: degrees; see the module doc.
        distance: metres from the target, clamped to [min_distance, max_distance].
        target: (3,) the orbit centre; relative to :attr:`anchor` (the world point is their sum).
        anchor: (3,) the follow anchor (zero unless following).
        fov_y: vertical field of view, degrees.
        follow: whether the app moves the anchor with the body.
    """

    home: CameraHome = field(default_factory=CameraHome)
    min_distance: float = 0.3
    max_distance: float = 40.0
    max_elevation: float = 89.0
    orbit_degrees_per_pixel: float = 0.35
    zoom_step: float = 1.12
    near: float = 0.02
    far: float = DEFAULT_FAR
    azimuth: float = 0.0
    elevation: float = 0.0
    distance: float = 1.0
    fov_y: float = 35.0
    target: np.ndarray = field(default_factory=lambda: np.zeros(3))
    anchor: np.ndarray = field(default_factory=lambda: np.zeros(3))
    follow: bool = False

    def __post_init__(self) -> None:
        self.reset()

    # ---- state --------------------------------------------------------------------------------
    @property
    def world_target(self) -> np.ndarray:
        return self.target + self.anchor

    @property
    def eye(self) -> np.ndarray:
        """(3,) camera centre in world coordinates."""
        az, el = math.radians(self.azimuth), math.radians(self.elevation)
        offset = self.distance * np.array([math.sin(az) * math.cos(el), -math.cos(az) * math.cos(el), math.sin(el)])
        return self.world_target + offset

    def reset(self) -> None:
        """Back to :attr:`home`; keeps the follow setting (when following, the target goes to the body:
        the anchor plus the home target's height)."""
        h = self.home
        self.azimuth = _wrap_degrees(h.azimuth)
        self.elevation = self._clamp_elevation(h.elevation)
        self.distance = self._clamp_distance(h.distance)
        self.fov_y = float(h.fov_y)
        self.target = np.array(h.target, dtype=np.float64)
        if self.follow:
            self.target[:2] = 0.0

    def aim_home(self, centers: np.ndarray) -> None:
        """The home view looks at the middle of a clip's path: ``centers`` (T, 3) per-frame body centres."""
        mid = np.asarray(centers).mean(axis=0)
        self.home.target = (float(mid[0]), float(mid[1]), self.home.target[2])

    def preset(self, name: str) -> None:
        """Look from a named side (:data:`VIEW_DIRECTIONS`) at the home elevation; distance and target stay."""
        if name not in VIEW_DIRECTIONS:
            raise ValueError(f"unknown camera preset '{name}' (known: {', '.join(VIEW_DIRECTIONS)})")
        self.azimuth = VIEW_DIRECTIONS[name]
        self.elevation = self._clamp_elevation(self.home.elevation)

    def look_from(self, eye, forward, fov_y: float | None = None) -> None:
        """Put the camera at ``eye`` (3,) looking along ``forward`` (3,), keeping the distance to the
        target (a view with roll comes back level: the turntable keeps +Z up); ``fov_y`` degrees."""
        f = np.asarray(forward, dtype=np.float64)
        f = f / max(np.linalg.norm(f), 1e-12)
        back = -f  # from the target to the eye
        self.elevation = self._clamp_elevation(math.degrees(math.asin(max(-1.0, min(1.0, back[2])))))
        self.azimuth = _wrap_degrees(math.degrees(math.atan2(back[0], -back[1])))
        self.target = np.asarray(eye, dtype=np.float64) + self.distance * f - self.anchor
        if fov_y is not None and math.isfinite(fov_y):
            self.fov_y = float(fov_y)

    # ---- mouse gestures (pixels are window units) ---------------------------------------------
    def orbit(self, dx: float, dy: float) -> None:
        """Drag right turns the character to its left-to-right (camera azimuth decreases); drag down
        raises the camera."""
        if not (math.isfinite(dx) and math.isfinite(dy)):
            return
        self.azimuth = _wrap_degrees(self.azimuth - dx * self.orbit_degrees_per_pixel)
        self.elevation = self._clamp_elevation(self.elevation + dy * self.orbit_degrees_per_pixel)

    def pan(self, dx: float, dy: float, viewport_height: float) -> None:
        """Move the target in the image plane so the point under the cursor follows the cursor
        (exactly at the target's depth)."""
        if not (math.isfinite(dx) and math.isfinite(dy)) or viewport_height <= 0:
            return
        metres_per_pixel = 2.0 * self.distance * math.tan(math.radians(self.fov_y) / 2.0) / viewport_height
        R, _ = look_at(self.eye, self.world_target)
        right, down = R[0], R[1]
        self.target = self.target - metres_per_pixel * (dx * right + dy * down)

    def zoom(self, steps: float) -> None:
        """Scroll: positive steps move closer (distance divided by zoom_step per step), clamped."""
        if not math.isfinite(steps):
            return
        self.distance = self._clamp_distance(self.distance * self.zoom_step ** (-steps))

    def set_distance(self, distance: float) -> None:
        if math.isfinite(distance):
            self.distance = self._clamp_distance(distance)

    def set_azimuth(self, degrees: float) -> None:
        """Azimuth in degrees (wrapped to (-180, 180])."""
        if math.isfinite(degrees):
            self.azimuth = _wrap_degrees(degrees)

    def set_elevation(self, degrees: float) -> None:
        """Elevation in degrees, clamped to +-:attr:`max_elevation`."""
        if math.isfinite(degrees):
            self.elevation = self._clamp_elevation(degrees)

    def set_fov(self, degrees: float) -> None:
        """Vertical field of view in degrees, clamped to [MIN_FOV_Y, MAX_FOV_Y]."""
        if math.isfinite(degrees):
            self.fov_y = min(MAX_FOV_Y, max(MIN_FOV_Y, float(degrees)))

    # ---- follow ---------------------------------------------------------------------------------
    def set_follow(self, follow: bool, body_position=None) -> None:
        """Switch follow mode; ``body_position`` (3,) is where the body is now (its z is ignored)."""
        follow = bool(follow)
        if follow == self.follow:
            return
        world = self.world_target
        self.follow = follow
        self.anchor = np.zeros(3)
        if follow and body_position is not None:
            self.anchor = self._ground(body_position)
        self.target = world - self.anchor

    def update_anchor(self, body_position) -> None:
        """Called by the app every frame; moves the camera with the body only when following."""
        if self.follow and body_position is not None:
            self.anchor = self._ground(body_position)

    def follow_view(self, track: np.ndarray, track_key: object = None) -> FollowView | None:
        """This controller's camera at every frame of a clip whose anchors are ``track`` (T, 3) (what
        :meth:`camera` gives after :meth:`update_anchor` with ``track[frame]``), or None when not
        following. ``track_key``: a value that tells this track from another (the view's token)."""
        if not self.follow:
            return None
        return FollowView(float(self.azimuth), float(self.elevation), float(self.distance),
                          tuple(float(x) for x in self.target), float(self.fov_y), float(self.near),
                          float(self.far), np.asarray(track, dtype=np.float64), track_key)

    # ---- output ---------------------------------------------------------------------------------
    def camera(self, width: int, height: int) -> Camera:
        """The :class:`Camera` of the current view for an image of ``width`` x ``height`` pixels."""
        return orbit_camera(self.azimuth, self.elevation, self.distance, self.world_target, int(width), int(height),
                            self.fov_y, self.near, self.far)

    # ---- helpers --------------------------------------------------------------------------------
    def _clamp_elevation(self, el: float) -> float:
        return float(min(self.max_elevation, max(-self.max_elevation, el)))

    def _clamp_distance(self, d: float) -> float:
        return float(min(self.max_distance, max(self.min_distance, d)))

    @staticmethod
    def _ground(p) -> np.ndarray:
        p = np.asarray(p, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(p)):
            return np.zeros(3)
        return np.array([p[0], p[1], 0.0])


@dataclass
class MouseGestures:
    """Turntable mouse gestures: left drag orbits, right / middle (or shift + left) drag pans, the
    wheel zooms. A drag starts only where imgui does not want the mouse (not over a panel) and lasts
    until its button is released.

    Attributes:
        drag: ``"orbit"``, ``"pan"`` or None; button: the mouse button holding the drag.
    """

    drag: str | None = None
    button: int = -1

    def update(self, imgui, controller: OrbitController, viewport_height: float) -> None:
        """Once per UI frame (between imgui's new_frame and render), with the imgui module."""
        io = imgui.get_io()
        if self.drag is not None and not imgui.is_mouse_down(self.button):
            self.drag = None
        if self.drag is None and not io.want_capture_mouse:
            for button in (0, 1, 2):
                if imgui.is_mouse_clicked(button):
                    pan = button in (1, 2) or io.key_shift
                    self.drag, self.button = ("pan" if pan else "orbit"), button
                    break
        if self.drag is not None:
            dx, dy = io.mouse_delta.x, io.mouse_delta.y
            if math.isfinite(dx) and math.isfinite(dy) and abs(dx) < 1e5 and abs(dy) < 1e5 and (dx or dy):
                if self.drag == "orbit":
                    controller.orbit(dx, dy)
                else:
                    controller.pan(dx, dy, viewport_height)
        if not io.want_capture_mouse and io.mouse_wheel and math.isfinite(io.mouse_wheel):
            controller.zoom(io.mouse_wheel)

    @staticmethod
    def grabbing(imgui) -> bool:
        """Whether this UI frame starts a gesture (a click or a wheel turn where imgui does not want
        the mouse): the window looking through a camera path hands the camera back then."""
        io = imgui.get_io()
        if io.want_capture_mouse:
            return False
        return any(imgui.is_mouse_clicked(b) for b in (0, 1, 2)) or bool(io.mouse_wheel)

    def cancel(self) -> None:
        """Drop a drag in progress (e.g. the window was minimised)."""
        self.drag = None
