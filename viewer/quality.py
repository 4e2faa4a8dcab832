"""Dynamic resolution of the neural render: coarse while the view changes, full when it is still.

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

Quality levels are the render presets of :data:`garmentnerf.perf.presets.VIEWER_LEVELS`
(``interactive``, ``balanced``, ``full``: rows of the table ``garmentnerf bench`` measures and
``garmentnerf render --preset`` runs). The level's preset sets where samples go and the still
quality (its ``resolution_scale``, also the cap of the moving one); with ``dynamic=False`` the
level's preset is rendered exactly as the bench row of that name, whatever happens.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from garmentnerf.perf.presets import VIEWER_LEVELS, get_render_preset

#: Quantisation step of the moving quality.
STEP = 1.0 / 16.0


@dataclass
class QualityController:
    """See the module docstring.

    Attributes:
        preset: the quality level, a render preset name of :data:`VIEWER_LEVELS`.
        dynamic: lower the quality while moving (False: always the preset's).
        target_ms: render time aimed at while moving.
        floor: lowest quality ever requested (0.25: below it a full-body view renders so few rays that
            the character all but vanishes while the view moves).
        hysteresis: relative change needed before the moving quality changes.
        settle_seconds: how long the view must be unchanged to count as still.
        smoothing: weight of a new measurement in the moving average of the unit cost.
        max_jump: a single measurement changes the unit cost by at most this factor.
    """

    preset: str = "full"
    dynamic: bool = True
    target_ms: float = 120.0
    floor: float = 0.25
    hysteresis: float = 0.2
    settle_seconds: float = 0.3
    smoothing: float = 0.35
    max_jump: float = 2.0
    unit_ms: float | None = None
    _moving_quality: float | None = field(default=None, repr=False)
    _last_change: float = field(default=-math.inf, repr=False)
    _view_key: object = field(default=None, repr=False)

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
        if self._moving_quality is not None:
            self._moving_quality = min(self._moving_quality, self.full)

    # ---- inputs ------------------------------------------------------------------------------------
    def view_changed(self, key: object, now: float) -> bool:
        """Tell the controller what is shown (camera + frame, any hashable key); returns whether it
        differs from the previous key."""
        if key != self._view_key:
            self._view_key = key
            self._last_change = now
            return True
        return False

    def observe(self, quality: float, ms: float) -> None:
        """A render at ``quality`` took ``ms`` milliseconds."""
        if not (quality > 0 and math.isfinite(ms) and ms >= 0):
            return
        unit = max(ms, 1e-3) / (quality * quality)
        if self.unit_ms is None:
            self.unit_ms = unit
            return
        unit = min(max(unit, self.unit_ms / self.max_jump), self.unit_ms * self.max_jump)
        self.unit_ms = (1.0 - self.smoothing) * self.unit_ms + self.smoothing * unit

    # ---- output ------------------------------------------------------------------------------------
    def moving(self, now: float) -> bool:
        return now - self._last_change < self.settle_seconds

    def estimate(self) -> float:
        """The quality whose predicted cost is :attr:`target_ms` (clamped to [floor, full])."""
        if not self.dynamic or self.unit_ms is None:
            return self.full if not self.dynamic else max(self.floor, min(self.full, 0.5 * self.full))
        q = math.sqrt(self.target_ms / self.unit_ms)
        return max(self.floor, min(self.full, q))

    def moving_quality(self) -> float:
        """The quality used while moving, with hysteresis and quantisation."""
        est = self.estimate()
        current = self._moving_quality
        if current is None or abs(est - current) > self.hysteresis * current or current > self.full:
            q = max(self.floor, min(self.full, round(est / STEP) * STEP))
            self._moving_quality = q
        return self._moving_quality

    def quality(self, now: float) -> float:
        """The quality to request now."""
        if not self.dynamic:
            return self.full
        return self.moving_quality() if self.moving(now) else self.full


__all__ = ["QualityController", "STEP"]
