"""Playback state of the previewer (current frame, play/pause, loop, speed) and the meters the stats
overlay and the bench read (:class:`PlaybackMeter`, :class:`FrameTimer`, :class:`FirstFrames`). Pure
logic, no GL.

Time is kept as a continuous position in frames (frame ``i`` is shown while ``i <= position < i + 1``,
as :class:`garmentnerf.motion.motion.Motion` defines a clip of T frames to last ``T / fps`` seconds).
Playing advances the position by ``dt * fps * speed`` per UI frame, so playback runs at the motion's
own rate whatever the UI frame rate is; a slow UI skips motion frames rather than slowing down.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

#: Playback speed range (factor of the motion's own frame rate).
MIN_SPEED = 1.0 / 16.0
MAX_SPEED = 16.0


@dataclass
class Timeline:
    """Playback of a clip of ``num_frames`` frames at ``fps``.

    Attributes:
        num_frames: frames in the clip (>= 1).
        fps: the clip's frame rate (> 0).
        loop: wrap to frame 0 at the end (else stop on the last frame and pause).
        speed: playback speed factor in [MIN_SPEED, MAX_SPEED].
        playing: whether :meth:`advance` moves the position.
    """

    num_frames: int = 1
    fps: float = 30.0
    loop: bool = True
    speed: float = 1.0
    playing: bool = False
    position: float = 0.0

    def __post_init__(self) -> None:
        self.reset(self.num_frames, self.fps, keep_frame=True)
        self.set_speed(self.speed)

    # ---- queries ------------------------------------------------------------------------------
    @property
    def frame(self) -> int:
        """The frame shown now."""
        return min(self.num_frames - 1, max(0, int(math.floor(self.position))))

    @property
    def last_frame(self) -> int:
        return self.num_frames - 1

    @property
    def time(self) -> float:
        """Seconds from the start of the clip to the shown frame."""
        return self.frame / self.fps

    @property
    def at_end(self) -> bool:
        return self.frame == self.last_frame

    # ---- changes (each returns True when the shown frame changed) -----------------------------
    def reset(self, num_frames: int, fps: float, keep_frame: bool = False) -> None:
        """A new clip: keep the play/loop/speed settings; go to frame 0 (or clamp the current one)."""
        num_frames = int(num_frames)
        fps = float(fps)
        if num_frames < 1:
            raise ValueError(f"a timeline needs at least 1 frame, got {num_frames}")
        if not (math.isfinite(fps) and fps > 0):
            raise ValueError(f"timeline fps must be a finite number > 0, got {fps!r}")
        self.num_frames, self.fps = num_frames, fps
        self.position = float(min(self.frame, num_frames - 1)) if keep_frame else 0.0

    def advance(self, dt: float, max_frames: int | None = None) -> bool:
        """Move on by ``dt`` seconds of UI time when playing; with ``max_frames`` by at most that
        many frames (0: stay on this frame, the position stopping just before the next one)."""
        before = self.frame
        if not self.playing or not math.isfinite(dt) or dt <= 0.0:
            return False
        step = dt * self.fps * self.speed
        if max_frames is not None:
            step = min(step, math.floor(self.position) + max(0, int(max_frames)) + 1 - 1e-6 - self.position)
        self.position += max(step, 0.0)
        if self.position >= self.num_frames:
            if self.loop:
                self.position = math.fmod(self.position, self.num_frames)
            else:
                self.position = float(self.last_frame)
                self.playing = False
        return self.frame != before

    def set_frame(self, frame: int) -> bool:
        """Show ``frame`` (clamped to the clip); playback state is unchanged."""
        before = self.frame
        self.position = float(min(self.last_frame, max(0, int(frame))))
        return self.frame != before

    def step(self, frames: int) -> bool:
        """Pause and move by ``frames`` (wraps around when looping, else clamps)."""
        self.playing = False
        target = self.frame + int(frames)
        if self.loop:
            target %= self.num_frames
        return self.set_frame(target)

    def play(self) -> None:
        """Start playing; from frame 0 when stopped at the end of a non-looping clip."""
        if not self.loop and self.at_end:
            self.position = 0.0
        self.playing = True

    def pause(self) -> None:
        self.playing = False
        self.position = float(self.frame)  # a paused timeline sits on a frame boundary

    def toggle_play(self) -> None:
        if self.playing:
            self.pause()
        else:
            self.play()

    def set_speed(self, speed: float) -> None:
        speed = float(speed)
        if not math.isfinite(speed):
            raise ValueError(f"playback speed must be finite, got {speed!r}")
        self.speed = min(MAX_SPEED, max(MIN_SPEED, speed))

    def faster(self) -> None:
        self.set_speed(self.speed * 2.0)

    def slower(self) -> None:
        self.set_speed(self.speed / 2.0)


@dataclass
class PlaybackMeter:
    """How many motion frames per second playback shows, and how many of them got a neural frame.

    Playback keeps the motion's clock (a slow machine skips frames, see :class:`Timeline`); the
    neural worker renders only the newest frame asked for, so on a slow machine it drops frames
    too. This counts both over the last ``window`` seconds so the overlay can say so.
    """

    window: float = 1.0
    _shown: deque = field(default_factory=deque, repr=False)     # (time, frame) of each new frame shown
    _rendered: deque = field(default_factory=deque, repr=False)  # (time, frame) of each neural frame received

    def _trim(self, now: float) -> None:
        for events in (self._shown, self._rendered):
            while events and now - events[0][0] > self.window:
                events.popleft()

    def frame_shown(self, frame: int, now: float) -> None:
        """The timeline shows ``frame`` (counted once per new frame)."""
        if not self._shown or self._shown[-1][1] != frame:
            self._shown.append((now, frame))
        self._trim(now)

    def neural_received(self, frame: int, now: float) -> None:
        """A neural render of ``frame`` arrived (counted once per new frame)."""
        if not self._rendered or self._rendered[-1][1] != frame:
            self._rendered.append((now, frame))
        self._trim(now)

    def rates(self, now: float) -> tuple[float, float]:
        """(motion frames shown, neural frames received) per second over the window."""
        self._trim(now)
        return len(self._shown) / self.window, len(self._rendered) / self.window

    def reset(self) -> None:
        self._shown.clear()
        self._rendered.clear()


class FrameTimer:
    """UI frame timing over the last ``window`` frames (seconds in, milliseconds out).

    interval: time between the starts of consecutive frames (what the user sees: 1 / fps).
    work: time spent inside one frame before the buffer swap; scene: the scene's share of it.
    """

    def __init__(self, window: int = 120) -> None:
        self.intervals: deque[float] = deque(maxlen=window)
        self.work: deque[float] = deque(maxlen=window)
        self.scene: deque[float] = deque(maxlen=window)
        self._last_start: float | None = None
        self.frames = 0

    def start(self, now: float) -> None:
        if self._last_start is not None:
            self.intervals.append(now - self._last_start)
        self._last_start = now

    def finish(self, work: float, scene: float) -> None:
        self.work.append(work)
        self.scene.append(scene)
        self.frames += 1

    @property
    def fps(self) -> float:
        total = sum(self.intervals)
        return len(self.intervals) / total if total > 0 else float("nan")

    @property
    def interval_ms(self) -> float:
        return _mean_ms(self.intervals)

    @property
    def work_ms(self) -> float:
        return _mean_ms(self.work)

    @property
    def scene_ms(self) -> float:
        return _mean_ms(self.scene)


def _mean_ms(seconds) -> float:
    """Mean of ``seconds`` in milliseconds (NaN when empty)."""
    return 1000.0 * sum(seconds) / len(seconds) if seconds else float("nan")


@dataclass
class FirstFrames:
    """When the window first showed the body and the garment: seconds from the command's start
    (:func:`garmentnerf.startup.seconds_since_start`) to the end of the first UI frame (after its
    swap) whose scene had the body / the neural garment in it. ``garmentnerf view --bench`` reports
    them (``first_frame.body_s``, ``first_frame.garment_s``); None until seen.

    A neural image carries the body (rasterised under the garment, or drawn by the network), so a
    frame that shows the garment shows the body too."""

    body_s: float | None = None
    garment_s: float | None = None

    def saw(self, body: bool, garment: bool, now: float) -> None:
        """A UI frame ended at ``now`` (seconds since the start) showing the body / the garment."""
        if (body or garment) and self.body_s is None:
            self.body_s = float(now)
        if garment and self.garment_s is None:
            self.garment_s = float(now)
