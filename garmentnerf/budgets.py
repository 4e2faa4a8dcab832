"""The bounds of the arguments that scale what a command allocates or how long it runs.

Every such argument has a documented :class:`Bound` here, and each command checks its arguments
against them right after reading them, before loading a model or allocating anything large
(this module imports nothing heavy, so a refusal comes within a second). A value outside is
refused in one line naming the flag, the bound and why it is there.

=====================  ==========================================  ========================================
bound                  arguments                                   why
=====================  ==========================================  ========================================
:data:`QUALITY`        ``render --quality``, ``eval --quality``    rays grow with its square
:data:`VIDEO_FPS`      ``render --fps``, a camera path's ``fps``    ffmpeg writes nothing outside it
:data:`MOTION_FPS`     ``--fps`` of a motion (``maps``, ``body      resampled frames grow with it
                       export``, ``render``'s motion ...)
:data:`HISTORY`        ``maps --history``, ``report --variants     info-map channels grow with it
                       kN``
:data:`PLAYBACK`       ``bench --playback-frames``                 the benchmark's time grows with it
=====================  ==========================================  ========================================

Frame ranges are bounded by :data:`garmentnerf.ranges.MAX_FRAME`, render sizes by ``render --size``'s
8..8192 and the per-frame caches of training by ``train --cache-gib``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["Bound", "QUALITY", "VIDEO_FPS", "MOTION_FPS", "HISTORY", "PLAYBACK"]


@dataclass(frozen=True)
class Bound:
    """The values an argument may take: ``low .. high`` (whole numbers only with ``whole``), and why."""

    low: float
    high: float
    why: str
    whole: bool = False

    def check(self, value, flag: str):
        """``value`` (a float, or an int when ``whole``) when it is within the bound; ValueError of one
        line naming ``flag``, the bound and why otherwise (NaN and non-numbers included)."""
        try:
            number = float(value)
        except (TypeError, ValueError, OverflowError):
            raise ValueError(f"{flag} must be a number, got {value!r}") from None
        if self.whole and not (math.isfinite(number) and number == int(number)):
            raise ValueError(f"{flag} must be a whole number, got {value!r}")
        if not (self.low <= number <= self.high):  # also NaN
            shown = f"{value:g}" if isinstance(value, (int, float)) else repr(value)
            raise ValueError(f"{flag} must be in {self.low:g}..{self.high:g} ({self.why}), got {shown}")
        return int(number) if self.whole else number


#: Render quality, as a fraction of the pixel density the model was trained at.
QUALITY = Bound(1.0 / 16.0, 4.0, "fractions of the trained pixel density: below, no character is left in "
                                 "the view; above, the rays, which grow with its square, outgrow memory")
#: Frames per second of a video.
VIDEO_FPS = Bound(0.1, 1000.0, "frames per second: ffmpeg writes an empty file below, no player shows more")
#: Frames per second a motion may be resampled to.
MOTION_FPS = Bound(1.0, 1000.0, "frames per second: the resampled motion's frames, and memory, grow with it")
#: Velocity history slots of the info maps.
HISTORY = Bound(0, 8, "velocity history slots: the info maps' channels grow with them", whole=True)
#: Frames played per preset by the playback benchmark.
PLAYBACK = Bound(1, 240, "frames played per preset: the benchmark's time grows with them", whole=True)
