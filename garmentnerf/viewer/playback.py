"""Which frame the neural worker renders while the clip plays: pure scheduling, no GL, no torch.

The previewer's timeline keeps the motion's clock; a neural render takes far longer than a motion
frame on a CPU. So the worker never renders the frame the playhead is at when it *starts* (the
playhead would have moved on by the time it ends): it renders the frame the playhead will be at
when the render *ends*, predicted from its own measured render time (:func:`predict_target_frame`),
or, with render-ahead, the first frame from there that is not rendered yet (:func:`next_unrendered`).
A render in flight is abandoned only when what it renders can no longer be shown
(:func:`render_superseded`): another view, or a playhead that has left it more than one render time
behind (a seek). A render that is merely a little late is finished, so the completed share of
started renders stays high.

The UI thread hands the worker a :class:`PlayheadClock` (where the playhead was, when, and how fast
it moves) instead of a frame per UI frame: the worker extrapolates it to the moment it starts a
render, and the UI sends a new one only when the timeline left the extrapolation
(:meth:`PlayheadClock.drifted`: a seek, a speed change, a stalled UI).

Frame arithmetic on a looping clip is modular: "ahead" and "behind" are measured forwards from the
playhead (:func:`frames_ahead`).
"""

from __future__ import annotations

import math
from collections.abc import Container
from dataclasses import dataclass

#: The timeline may drift this many frames from the clock the worker extrapolates before the UI
#: sends a new one (:meth:`PlayheadClock.drifted`).
DRIFT_FRAMES = 1.5


def wrap_position(position: float, n_frames: int, loop: bool) -> float:
    """A position in frames put back on the clip: modulo ``n_frames`` when looping, else clamped
    to ``[0, n_frames - 1]``."""
    if n_frames < 1:
        raise ValueError(f"a clip has at least 1 frame, got {n_frames}")
    if loop:
        return math.fmod(position, n_frames) % n_frames
    return min(max(position, 0.0), float(n_frames - 1))


def frame_of(position: float, n_frames: int, loop: bool) -> int:
    """The frame shown at ``position`` (frame ``i`` while ``i <= position < i + 1``)."""
    return min(n_frames - 1, max(0, int(math.floor(wrap_position(position, n_frames, loop)))))


def predict_target_frame(playhead: float, fps: float, render_s: float, n_frames: int, loop: bool) -> int:
    """The frame the playhead will show when a render started now ends.

    Args:
        playhead: the playhead's position now, in frames (continuous).
        fps: frames per second it advances (the clip's rate times the speed; 0 when paused).
        render_s: the expected duration of the render (seconds).
        n_frames: frames in the clip; loop: it wraps around (else it stops on the last frame).
    """
    if not (math.isfinite(render_s) and render_s >= 0.0):
        render_s = 0.0
    return frame_of(playhead + max(fps, 0.0) * render_s, n_frames, loop)


def frames_ahead(frame: int, playhead_frame: int, n_frames: int, loop: bool) -> int:
    """How far ``frame`` lies ahead of the playhead's frame, counted forwards (0: the same frame).
    Looping: in ``[0, n_frames)`` (a frame just behind the playhead is almost a whole clip ahead);
    otherwise negative for frames behind."""
    d = int(frame) - int(playhead_frame)
    return d % n_frames if loop else d


def frames_behind(frame: int, playhead_frame: int, n_frames: int, loop: bool) -> int:
    """How many frames the playhead has gone past ``frame`` (0 when it is on it or before it).
    Looping, a frame more than half a clip "behind" counts as ahead (0)."""
    d = int(playhead_frame) - int(frame)
    if loop:
        d %= n_frames
        return d if d <= n_frames // 2 else 0
    return max(d, 0)


def next_unrendered(start: int, rendered: Container[int], n_frames: int, loop: bool) -> int | None:
    """The first frame from ``start`` forwards (wrapping when looping, up to the last frame otherwise)
    that is not in ``rendered``; None when there is none."""
    start = min(max(int(start), 0), n_frames - 1)
    count = n_frames if loop else n_frames - start
    for d in range(count):
        f = (start + d) % n_frames
        if f not in rendered:
            return f
    return None


def render_superseded(target: int, same_view: bool, playhead_frame: int, fps: float, render_s: float,
                      n_frames: int, loop: bool) -> bool:
    """Whether a render of frame ``target`` in flight should be abandoned for the newest request.

    Args:
        same_view: the newest request is for the same view (camera, quality, preset, motion, composition).
        playhead_frame: the newest request's playhead frame now; fps: its rate (0: paused).
        render_s: the expected duration of a render.
    Returns:
        True for another view; paused, for another frame; playing, when the playhead is more than one
        render time (and one frame) past ``target`` -- a seek: a render that is only late is finished.
    """
    if not same_view:
        return True
    if fps <= 0.0:
        return int(target) != int(playhead_frame)
    return frames_behind(target, playhead_frame, n_frames, loop) > fps * max(render_s, 0.0) + 1.0


def show_newest(newest_frame: int, playhead_frame: int, n_frames: int, loop: bool) -> bool:
    """Whether the newest finished frame of the shown view may be shown while the playhead is on
    another frame that is not rendered: yes unless it lies ahead of the playhead (rendered ahead:
    it is shown when the playhead gets there). Looping, "ahead" is at most half a clip forwards."""
    ahead = frames_ahead(newest_frame, playhead_frame, n_frames, loop)
    return not 0 < ahead <= (n_frames // 2 if loop else n_frames)


def replaces_shown(candidate_frame: int, shown_frame: int | None, playhead_frame: int, n_frames: int,
                   loop: bool) -> bool:
    """Whether a finished frame behind the playhead (or on it) should replace the shown one while
    a clip plays: yes unless the shown one is nearer the playhead."""
    if shown_frame is None:
        return True
    return (frames_behind(candidate_frame, playhead_frame, n_frames, loop)
            <= frames_behind(shown_frame, playhead_frame, n_frames, loop))


@dataclass(frozen=True)
class PlayheadClock:
    """Where the playhead is: at ``position`` (frames) at clock time ``time`` (seconds), moving at
    ``fps`` frames per second (the clip's rate times the speed; 0 when paused), on a clip of
    ``n_frames`` that ``loop``\\ s (or stops on its last frame)."""

    position: float
    time: float
    fps: float
    n_frames: int
    loop: bool = True

    @property
    def playing(self) -> bool:
        return self.fps > 0.0

    @property
    def frame(self) -> int:
        """The frame at :attr:`time`."""
        return frame_of(self.position, self.n_frames, self.loop)

    def position_at(self, now: float) -> float:
        """The position extrapolated to ``now`` (wrapped / clamped to the clip)."""
        return wrap_position(self.position + self.fps * max(0.0, now - self.time), self.n_frames, self.loop)

    def frame_at(self, now: float) -> int:
        return frame_of(self.position_at(now), self.n_frames, self.loop)

    def drifted(self, current: "PlayheadClock", tolerance: float = DRIFT_FRAMES) -> bool:
        """Whether the timeline's ``current`` clock has left this one: another clip length, loop
        setting, rate or play state, another frame while paused, or (playing) a position more than
        ``tolerance`` frames from this clock's extrapolation to ``current.time`` (round the loop)."""
        if (current.n_frames, current.loop, current.playing) != (self.n_frames, self.loop, self.playing):
            return True
        if not current.playing:
            return current.frame != self.frame
        if not math.isclose(current.fps, self.fps, rel_tol=1e-6):
            return True
        d = abs(wrap_position(current.position, self.n_frames, self.loop) - self.position_at(current.time))
        if self.loop:
            d = min(d, self.n_frames - d)
        return d > tolerance

    @staticmethod
    def of(timeline, now: float) -> "PlayheadClock":
        """The clock of a :class:`~garmentnerf.viewer.timeline.Timeline` at time ``now``."""
        fps = timeline.fps * timeline.speed if timeline.playing else 0.0
        return PlayheadClock(float(timeline.position), float(now), fps, int(timeline.num_frames), bool(timeline.loop))


@dataclass
class RenderTime:
    """The worker's expected render durations (seconds): exponential moving averages of the measured
    ones, kept apart for the two kinds of render a clip mixes. ``seconds``: a frame whose per-frame
    features were cached (the view's work only); ``cold_seconds``: a frame whose features the render
    computed first (E, G_en and the body's bind on top: on the bundled model about as long again).
    Predicting a cold frame with the warm figure makes it land late, behind the playhead. Each is 0
    until measured; :meth:`expected` gives an unmeasured kind the other's figure."""

    smoothing: float = 0.3
    seconds: float = 0.0
    measured: int = 0
    cold_seconds: float = 0.0
    cold_measured: int = 0

    def observe(self, seconds: float, cold: bool = False) -> None:
        """Add a measured render; ``cold``: its frame's features were computed by it."""
        if not (math.isfinite(seconds) and seconds >= 0.0):
            return
        if cold:
            self.cold_seconds = self._average(self.cold_seconds, self.cold_measured, seconds)
            self.cold_measured += 1
        else:
            self.seconds = self._average(self.seconds, self.measured, seconds)
            self.measured += 1

    def expected(self, cold: bool) -> float:
        """The expected duration of a render of a frame with (``cold`` False) or without cached features."""
        mine, other = (self.cold_seconds, self.seconds) if cold else (self.seconds, self.cold_seconds)
        return mine if (self.cold_measured if cold else self.measured) else other

    def _average(self, mean: float, count: int, seconds: float) -> float:
        return seconds if count == 0 else (1 - self.smoothing) * mean + self.smoothing * seconds


__all__ = ["PlayheadClock", "RenderTime", "DRIFT_FRAMES", "wrap_position", "frame_of", "predict_target_frame",
           "frames_ahead", "frames_behind", "next_unrendered", "render_superseded", "show_newest",
           "replaces_shown"]
