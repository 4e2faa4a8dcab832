"""Dynamic resolution: coarse while the view changes, full when it is still, for the neural render
(:class:`QualityController`) and for the window's scene (:class:`SceneScale`).

Both share one cost model, :class:`AdaptiveScale`: a draw at scale ``q`` (a fraction of the full
resolution per side) costs ``unit_ms * q**2``, and the scale that fits a time budget is
``sqrt(budget / unit_ms)`` (instant-ngp's rule), with the outlier clamp, hysteresis and
quantisation below.

Pure logic (no GL), driven by the app once per UI frame:

* :meth:`QualityController.observe` records what a finished render cost. The cost of a render
  is modelled as ``unit_ms * quality**2`` (rays scale with the pixel count); ``unit_ms`` is an
  exponential moving average, and a single outlier (a frame whose features were not cached, a
  hiccup of the loaded machine) moves it by at most a factor :attr:`max_jump`, so one bad
  estimate cannot collapse the resolution (the nerfstudio complaint).
* :meth:`QualityController.quality` gives the quality to request: while the view is *moving*
  (camera or frame changed less than :attr:`settle_seconds` ago) the largest quality whose
  predicted cost fits :attr:`target_ms` (instant-ngp's ``sqrt(budget / cost)``), never below
  :attr:`floor`, never above the preset; once still, the preset's full quality.
* Hysteresis: the moving quality only changes when the new estimate differs from the current one
  by more than :attr:`hysteresis` (relative, +-20 % by default), and it is quantised to steps of
  1/16, so the resolution does not flicker between two neighbours.

Quality levels are the render presets of :data:`garmentnerf.render.presets.VIEWER_LEVELS`
(``interactive``, ``balanced``, ``full``: rows of the table ``garmentnerf bench`` measures and
``garmentnerf render --preset`` runs). The level's preset sets where samples go and the still
quality (its ``resolution_scale``, also the cap of the moving one); with ``dynamic=False`` the
level's preset is rendered exactly as the bench row of that name, whatever happens.

:class:`SceneScale` does the same for the window's GL scene (body, floor, the neural layer's
composition): on a software rasteriser (llvmpipe) a 1280 x 800 multisampled scene costs about
35 ms, which alone caps the UI below 30 fps while the camera orbits or the clip plays. While the
view moves the scene is drawn at the scale whose measured cost fits :attr:`SceneScale.target_ms`
and stretched to the window; once still it is drawn once more at the user's render scale.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from garmentnerf.render.presets import VIEWER_LEVELS, get_render_preset

#: Quantisation step of the moving quality (and of the moving scene scale).
STEP = 1.0 / 16.0


@dataclass
class AdaptiveScale:
    """The cost model shared by the neural render's quality and the scene's scale (see the module
    docstring).

    Attributes:
        target_ms: the time a draw aims at while the view moves.
        floor: the lowest scale ever chosen.
        hysteresis: relative change of the estimate needed before the chosen scale changes.
        smoothing: weight of a new measurement in the moving average of the unit cost.
        max_jump: a single measurement changes the unit cost by at most this factor.
        settle_seconds: how long the view must be unchanged to count as still.
        unit_ms: the estimated cost at scale 1 (None until a draw was measured).
        dynamic: lower the scale while the view moves (False: always the full scale).
    """

    target_ms: float = 120.0
    floor: float = 0.25
    hysteresis: float = 0.2
    smoothing: float = 0.35
    max_jump: float = 2.0
    settle_seconds: float = 0.3
    unit_ms: float | None = None
    dynamic: bool = True
    _moving_scale: float | None = field(default=None, repr=False)
    _last_change: float = field(default=-math.inf, repr=False)
    _view_key: object = field(default=None, repr=False)

    def set_dynamic(self, dynamic: bool) -> None:
        """Lower the scale while moving, or never (the panels' switch)."""
        self.dynamic = bool(dynamic)

    def view_changed(self, key: object, now: float) -> bool:
        """Tell the controller what is shown (camera + frame, any hashable key); returns whether it
        differs from the previous key."""
        if key != self._view_key:
            self._view_key = key
            self._last_change = now
            return True
        return False

    def moving(self, now: float) -> bool:
        """Whether the view changed less than :attr:`settle_seconds` ago."""
        return now - self._last_change < self.settle_seconds

    def observe(self, scale: float, ms: float) -> None:
        """A draw at ``scale`` took ``ms`` milliseconds."""
        if not (scale > 0 and math.isfinite(ms) and ms >= 0):
            return
        unit = max(ms, 1e-3) / (scale * scale)
        if self.unit_ms is None:
            self.unit_ms = unit
            return
        unit = min(max(unit, self.unit_ms / self.max_jump), self.unit_ms * self.max_jump)
        self.unit_ms = (1.0 - self.smoothing) * self.unit_ms + self.smoothing * unit

    def fitted(self, full: float) -> float:
        """The scale whose predicted cost is :attr:`target_ms`, clamped to [floor, full] (half of
        ``full`` before anything was measured)."""
        if self.unit_ms is None:
            return max(self.floor, min(full, 0.5 * full))
        return max(self.floor, min(full, math.sqrt(self.target_ms / self.unit_ms)))

    def moving_scale(self, full: float) -> float:
        """The scale used while moving: :meth:`fitted`, quantised to :data:`STEP`, changed only
        when the estimate moved by more than :attr:`hysteresis`."""
        est = self.fitted(full)
        current = self._moving_scale
        if current is None or abs(est - current) > self.hysteresis * current or current > full:
            self._moving_scale = max(self.floor, min(full, round(est / STEP) * STEP))
        return self._moving_scale

    def forget(self) -> None:
        """Measure anew (what a draw costs changed: another preset, another window)."""
        self.unit_ms = None
        self._moving_scale = None


@dataclass
class QualityController(AdaptiveScale):
    """See the module docstring: the neural render's quality (fraction of the training density).

    Attributes (besides :class:`AdaptiveScale`'s; ``floor`` 0.25: below it a full-body view
    renders so few rays that the character all but vanishes while the view moves):
        preset: the quality level, a render preset name of :data:`VIEWER_LEVELS`.
    """

    preset: str = "full"

    def __post_init__(self) -> None:
        self.set_preset(self.preset)
        if not (0 < self.floor <= 1):
            raise ValueError(f"quality floor must be in (0, 1], got {self.floor}")

    # ---- settings ----------------------------------------------------------------------------------
    @property
    def full(self) -> float:
        """The still quality of the level: its render preset's resolution scale."""
        return get_render_preset(self.preset).resolution_scale

    def set_preset(self, preset: str) -> None:
        """Switch to another quality level (the cost model starts over: presets differ per ray)."""
        if preset not in VIEWER_LEVELS:
            raise ValueError(f"unknown quality level '{preset}' (known: {', '.join(VIEWER_LEVELS)})")
        changed = preset != self.preset
        self.preset = preset
        if changed:
            self.unit_ms = None
        if self._moving_scale is not None:
            self._moving_scale = min(self._moving_scale, self.full)

    # ---- output ------------------------------------------------------------------------------------
    def estimate(self) -> float:
        """The quality whose predicted cost is :attr:`target_ms` (clamped to [floor, full]); the
        preset's when not dynamic."""
        return self.fitted(self.full) if self.dynamic else self.full

    def moving_quality(self) -> float:
        """The quality used while moving, with hysteresis and quantisation."""
        return self.moving_scale(self.full)

    def quality(self, now: float) -> float:
        """The quality to request now."""
        if not self.dynamic:
            return self.full
        return self.moving_quality() if self.moving(now) else self.full


@dataclass
class SceneScale(AdaptiveScale):
    """The window scene's resolution (a fraction of the user's render scale, see the module
    docstring). ``target_ms`` defaults to 12 ms: with imgui, the swap and the neural layer's upload,
    a UI frame then fits 33 ms (30 fps)."""

    target_ms: float = 12.0
    floor: float = 0.35
    settle_seconds: float = 0.15

    def scale(self, now: float) -> float:
        """The scene's scale now, a fraction of the render size the user chose: 1 when the view is
        still (:meth:`view_changed`) or not dynamic, else the moving scale."""
        if not self.dynamic or not self.moving(now):
            return 1.0
        return self.moving_scale(1.0)


__all__ = ["AdaptiveScale", "QualityController", "SceneScale", "STEP"]
