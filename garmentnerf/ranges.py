"""Frame ranges and comma-separated lists, read the same way by every command and file.

Frame ranges (``train --frames``, ``eval --frames``, ``render --frames``, a recipe stage's
``frames``, ``report --frames``) are Python slices of frame indices:

``A:B``
    frames A .. B-1 (``A`` left out: 0; ``B`` left out: to the end of the sequence, where the
    command knows its length)
``A:B:S``
    every S-th of them, S >= 1 (``0:10:0`` is refused)
``A``
    frame A alone

Frame numbers are non-negative integers up to :data:`MAX_FRAME` (a bound on what a range can
make a command allocate before the sequence is known). A range that selects no frame (``5:5``),
empty text and anything else are refused with a :class:`ValueError` of one line naming the flag.

Lists (``--cameras``, ``--palette``, ``--shape``, ``bench --presets``, ``report --variants``, ...) are
comma-separated items with the spaces around each item stripped; an empty item (``a,,b``, ``,``)
and an empty list (``''``) are refused the same way: :func:`parse_list`.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import TypeVar

__all__ = ["FrameRange", "parse_frame_range", "parse_frames", "parse_list", "MAX_FRAME", "FRAME_RANGE_SYNTAX"]

#: The largest frame number a range may name (no sequence of the project comes near it).
MAX_FRAME = 1_000_000
#: How a frame range is written, for messages.
FRAME_RANGE_SYNTAX = "A:B, A:B:S, A:, :B or A (frame numbers >= 0, B exclusive, step S >= 1)"

_NUMBER = re.compile(r"[0-9]+")
T = TypeVar("T")


@dataclass(frozen=True)
class FrameRange:
    """A parsed frame range (:func:`parse_frame_range`).

    Attributes:
        start: first frame.
        stop: the frame after the last one (exclusive), None for "to the end of the sequence".
        step: frames between two selected ones (>= 1).
        text: the range as given (named in messages).
        what: the flag or key it came from (named in messages).
    """

    start: int
    stop: int | None
    step: int = 1
    text: str = ""
    what: str = "--frames"

    def frames(self, count: int | None = None, where: str = "the sequence") -> list[int]:
        """The selected frame indices; with ``count`` (the sequence's length, described by ``where``)
        the open end is filled in and a range past the end is refused."""
        stop = self.stop
        if stop is None:
            if count is None:
                raise ValueError(f"{self.what} {self.text}: needs an end here (A:B)")
            stop = count
        if count is not None and not (self.start < count and stop <= count):
            last = f"0..{count - 1}" if count > 0 else "none"
            raise ValueError(f"{self.what} {self.text} is out of range for {where} ({count} frames: {last})")
        out = list(range(self.start, stop, self.step))
        if not out:
            raise ValueError(f"{self.what} {self.text} selects no frame (A:B takes frames A..B-1)")
        return out


def parse_frame_range(text, what: str = "--frames") -> FrameRange | None:
    """The :class:`FrameRange` of ``text`` (None for None: "not given").

    Raises:
        ValueError: one line naming ``what``: not a range (see the module docstring), a negative
            or too large frame number, a step below 1, empty text, or a range that selects no frame.
    """
    if text is None:
        return None
    if not isinstance(text, str):
        raise ValueError(f"{what} must be a frame range ({FRAME_RANGE_SYNTAX}) as text, got {text!r}")
    shown = text.strip()
    if not shown:
        raise ValueError(f"{what} is empty; give a frame range: {FRAME_RANGE_SYNTAX}")
    parts = [p.strip() for p in shown.split(":")]
    if len(parts) > 3 or any(p and not _NUMBER.fullmatch(p) for p in parts):
        if any(re.fullmatch(r"-[0-9]+", p) for p in parts):
            raise ValueError(f"{what} {shown!r}: frame numbers start at 0 (no negative numbers)")
        raise ValueError(f"{what} must look like {FRAME_RANGE_SYNTAX}, got {shown!r}")
    nums = [int(p) if p else None for p in parts]
    for n in nums:
        if n is not None and n > MAX_FRAME:
            raise ValueError(f"{what} {shown}: frame numbers are at most {MAX_FRAME}")
    if len(nums) == 1:
        if nums[0] is None:
            raise ValueError(f"{what} must look like {FRAME_RANGE_SYNTAX}, got {shown!r}")
        return FrameRange(nums[0], nums[0] + 1, 1, shown, what)
    start = nums[0] or 0
    stop = nums[1]
    step = 1 if len(nums) < 3 or nums[2] is None else nums[2]
    if step < 1:
        raise ValueError(f"{what} {shown}: the step must be at least 1, got {step}")
    if stop is not None and start >= stop:
        raise ValueError(f"{what} {shown} selects no frame (A:B takes frames A..B-1)")
    return FrameRange(start, stop, step, shown, what)


def parse_frames(text, what: str = "--frames", count: int | None = None,
                 where: str = "the sequence") -> list[int] | None:
    """The frame indices of ``text`` (None for None): :func:`parse_frame_range`, then
    :meth:`FrameRange.frames` with ``count`` and ``where``."""
    spec = parse_frame_range(text, what)
    return None if spec is None else spec.frames(count, where)


def parse_list(text, what: str, item: Callable[[str], T] | None = None, *, kind: str = "item") -> list[T] | None:
    """The items of the comma-separated list ``text`` (None for None), each stripped of spaces and
    passed through ``item`` when given (a ValueError it raises is reported with ``what``).

    Raises:
        ValueError: one line naming ``what``: empty text, an empty item, or an item ``item`` refuses.
    """
    if text is None:
        return None
    if not isinstance(text, str):
        raise ValueError(f"{what} must be a comma-separated list as text, got {text!r}")
    if not text.strip():
        raise ValueError(f"{what} is empty; give one or more {_plural(kind)} separated by commas")
    items = [p.strip() for p in text.split(",")]
    if any(not p for p in items):
        raise ValueError(f"{what} {text.strip()!r}: an empty {kind} (two commas in a row, or one at an end)")
    if item is None:
        return items
    out = []
    for p in items:
        try:
            out.append(item(p))
        except ValueError as exc:
            plain = {int: "not a whole number", float: "not a number"}.get(item)  # Python's own words otherwise
            detail = plain or (str(exc).splitlines()[0] if str(exc) else "not valid")
            raise ValueError(f"{what} {text.strip()!r}: {kind} {p!r}: {detail}") from None
    return out


def _plural(kind: str) -> str:
    """``kind`` in the plural: ``colour ('-' keeps one)`` -> ``colours ('-' keeps one)``."""
    noun, sep, note = kind.partition(" (")
    return f"{noun}s{sep}{note}"
