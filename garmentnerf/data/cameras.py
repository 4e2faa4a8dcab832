"""Camera rigs for synthetic training data: named cameras with a data split each.

Every rig places cameras on a horizontal circle around a look-at point, in the world of
:mod:`garmentnerf.conventions` (Z up, metres, the character at rest faces -Y). Azimuth 0 is in
front of the character (the camera stands on the -Y side and looks towards +Y); azimuth grows
counter-clockwise seen from above, so azimuth 90 is on the +X side (the character's left), as in
:func:`garmentnerf.conventions.orbit_camera`. ``height`` is the camera centre's z (metres), not
an elevation angle: with the defaults (z = 1.0 m, looking at (0, 0, 0.9) from 3 m) the cameras
look slightly down, like the paper's ring of 16 cameras.

Rigs and splits
    * :func:`circle_rig` -- ``count`` training cameras ``cam00 ..`` evenly spaced, ``cam00`` at
      azimuth 0 (split ``train``).
    * :func:`held_out_rig` -- cameras *halfway* between neighbouring circle cameras, for the
      unseen-view test (split ``unseen_view``), ``held00 ..``.
    * :func:`reference_cameras` -- ``ref_front`` (azimuth 0) and ``ref_back`` (azimuth 180), the
      paper's front/back reference views for detail features (split ``reference``).
    * :func:`default_rig` -- all three, the layout scenes are made with.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Protocol, TypeVar

import numpy as np

from garmentnerf.conventions import DEFAULT_FAR, DEFAULT_NEAR, Camera, intrinsics_from_fov, look_at

#: Camera splits a scene may use.
CAMERA_SPLITS = ("train", "unseen_view", "reference")

#: Default vertical field of view: a 1.65 m character plus a swinging skirt fits a 3 m ring with margin.
DEFAULT_FOV_Y_DEG = 40.0
DEFAULT_LOOK_AT = (0.0, 0.0, 0.9)


@dataclass(frozen=True)
class NamedCamera:
    """A camera of a rig or scene.

    Attributes:
        name: unique within a scene; also a folder name in caches (letters, digits, ``_-.``).
        camera: the pinhole camera (OpenCV convention, see :mod:`garmentnerf.conventions`).
        split: one of :data:`CAMERA_SPLITS` (or ``train``/``unseen_view`` for captured data).
        azimuth_deg: where a rig put it (None for captured or hand-made cameras).
    """

    name: str
    camera: Camera
    split: str = "train"
    azimuth_deg: float | None = None

    @property
    def K(self) -> np.ndarray:
        return self.camera.K

    @property
    def R(self) -> np.ndarray:
        return self.camera.R

    @property
    def t(self) -> np.ndarray:
        return self.camera.t

    @property
    def width(self) -> int:
        return self.camera.width

    @property
    def height(self) -> int:
        return self.camera.height


class _HasSplit(Protocol):
    split: str


_WithSplit = TypeVar("_WithSplit", bound=_HasSplit)


def in_splits(items: Iterable[_WithSplit], split: str | Sequence[str] | None, known: Sequence[str] | None = None,
              what: str = "camera", error: type[Exception] = ValueError) -> list[_WithSplit]:
    """The ``items`` (cameras, sequences: anything with a ``split``) whose split is ``split`` -- a
    name, several names, or None for all -- in their order. With ``known``, a name outside it
    raises ``error("unknown <what> split(s) [...] (known: ...)")``."""
    if split is None:
        return list(items)
    wanted = {split} if isinstance(split, str) else set(split)
    unknown = wanted - set(known) if known is not None else set()
    if unknown:
        raise error(f"unknown {what} split(s) {sorted(unknown)} (known: {', '.join(known)})")
    return [item for item in items if item.split in wanted]


class RigLookup:
    """Camera lookups shared by the scenes (synthetic and captured): ``camera_names`` and
    ``camera`` over ``self.rig`` (a list of :class:`NamedCamera`) and ``self.cameras(split)``.
    A class using it says how a missing name fails with :meth:`_lookup_error`."""

    rig: list[NamedCamera]

    def cameras(self, split: str | Sequence[str] | None = None) -> list[NamedCamera]:  # pragma: no cover
        raise NotImplementedError

    def _lookup_error(self, problem: str) -> Exception:  # pragma: no cover
        """The exception for ``problem`` (e.g. ``no camera 'x' (...)``), naming the scene's file."""
        raise NotImplementedError

    def camera_names(self, split: str | Sequence[str] | None = None) -> list[str]:
        """Names of the cameras of ``split`` (as :meth:`cameras` takes it), in rig order."""
        return [c.name for c in self.cameras(split)]

    def camera(self, name: str) -> NamedCamera:
        """The camera called ``name``; a missing one raises :meth:`_lookup_error`."""
        for cam in self.rig:
            if cam.name == name:
                return cam
        raise self._lookup_error(f"no camera '{name}' (cameras: {', '.join(self.camera_names())})")


def ring_camera(azimuth_deg: float, radius: float = 3.0, height: float = 1.0, look_at_point=DEFAULT_LOOK_AT,
                width: int = 512, height_px: int = 512, fov_y_deg: float = DEFAULT_FOV_Y_DEG,
                near: float = DEFAULT_NEAR, far: float = DEFAULT_FAR) -> Camera:
    """One camera on the horizontal circle of ``radius`` around ``look_at_point``'s vertical axis,
    its centre at z = ``height``, looking at ``look_at_point``."""
    if not (np.isfinite(radius) and radius > 0):
        raise ValueError(f"rig radius must be > 0, got {radius}")
    target = np.asarray(look_at_point, dtype=np.float64).reshape(3)
    az = np.deg2rad(azimuth_deg)
    eye = np.array([target[0] + radius * np.sin(az), target[1] - radius * np.cos(az), float(height)])
    R, t = look_at(eye, target)
    return Camera(intrinsics_from_fov(width, height_px, fov_y_deg), R, t, int(width), int(height_px), near, far)


def _check_count(count: int, what: str) -> int:
    if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or count < 1:
        raise ValueError(f"{what} must be a positive integer, got {count!r}")
    return int(count)


def circle_rig(count: int = 16, radius: float = 3.0, height: float = 1.0, look_at=DEFAULT_LOOK_AT,
               width: int = 512, height_px: int = 512, fov_y_deg: float = DEFAULT_FOV_Y_DEG,
               near: float = DEFAULT_NEAR, far: float = DEFAULT_FAR, prefix: str = "cam",
               split: str = "train", start_azimuth_deg: float = 0.0) -> list[NamedCamera]:
    """``count`` cameras evenly spaced on a circle, ``<prefix>00`` at ``start_azimuth_deg``.

    Camera i sits at azimuth ``start + 360 i / count`` (counter-clockwise seen from above).
    """
    count = _check_count(count, "camera count")
    step = 360.0 / count
    return [NamedCamera(f"{prefix}{i:02d}",
                        ring_camera(start_azimuth_deg + i * step, radius, height, look_at, width, height_px,
                                    fov_y_deg, near, far),
                        split, float(start_azimuth_deg + i * step))
            for i in range(count)]


def held_out_rig(count: int = 4, circle_count: int = 16, radius: float = 3.0, height: float = 1.0,
                 look_at=DEFAULT_LOOK_AT, width: int = 512, height_px: int = 512,
                 fov_y_deg: float = DEFAULT_FOV_Y_DEG, near: float = DEFAULT_NEAR, far: float = DEFAULT_FAR,
                 prefix: str = "held", split: str = "unseen_view") -> list[NamedCamera]:
    """``count`` cameras halfway between neighbouring cameras of ``circle_rig(circle_count)``.

    The gaps are numbered from the one after ``cam00`` (azimuth ``180 / circle_count``); the
    cameras take every ``circle_count / count``-th gap (rounded), so they spread around the circle.
    """
    count = _check_count(count, "held-out camera count")
    circle_count = _check_count(circle_count, "circle camera count")
    if count > circle_count:
        raise ValueError(f"cannot place {count} held-out cameras in the {circle_count} gaps of the circle")
    step = 360.0 / circle_count
    gaps = [int(round(j * circle_count / count)) % circle_count for j in range(count)]
    cams = []
    for j, gap in enumerate(gaps):
        az = (gap + 0.5) * step
        cams.append(NamedCamera(f"{prefix}{j:02d}", ring_camera(az, radius, height, look_at, width, height_px,
                                                                fov_y_deg, near, far), split, float(az)))
    return cams


def reference_cameras(radius: float = 3.0, height: float = 1.0, look_at=DEFAULT_LOOK_AT, width: int = 512,
                      height_px: int = 512, fov_y_deg: float = DEFAULT_FOV_Y_DEG, near: float = DEFAULT_NEAR,
                      far: float = DEFAULT_FAR, split: str = "reference") -> list[NamedCamera]:
    """The front (``ref_front``, azimuth 0) and back (``ref_back``, azimuth 180) reference views."""
    return [NamedCamera(name, ring_camera(az, radius, height, look_at, width, height_px, fov_y_deg, near, far),
                        split, az)
            for name, az in (("ref_front", 0.0), ("ref_back", 180.0))]


def default_rig(count: int = 16, held_out: int = 4, radius: float = 3.0, height: float = 1.0,
                look_at=DEFAULT_LOOK_AT, width: int = 512, height_px: int = 512,
                fov_y_deg: float = DEFAULT_FOV_Y_DEG, references: bool = True) -> list[NamedCamera]:
    """The training circle, the held-out cameras between them and the two reference cameras."""
    kw = dict(radius=radius, height=height, look_at=look_at, width=width, height_px=height_px, fov_y_deg=fov_y_deg)
    cams = circle_rig(count, **kw)
    if held_out:
        cams += held_out_rig(held_out, count, **kw)
    if references:
        cams += reference_cameras(**kw)
    return cams
