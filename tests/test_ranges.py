"""The one frame-range and list parser (:mod:`garmentnerf.ranges`): the same rules for every
command, and for any text a result or a one-line ValueError naming the flag, never another
exception (Hypothesis)."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from garmentnerf.ranges import MAX_FRAME, FrameRange, parse_frame_range, parse_frames, parse_list


@pytest.mark.parametrize("text, count, frames", [
    ("2:5", 10, [2, 3, 4]), ("3", 10, [3]), (" 1 : 7 : 3 ", 10, [1, 4]), ("7:", 10, [7, 8, 9]), (":2", 10, [0, 1]),
    ("::4", 10, [0, 4, 8]), ("0:3", None, [0, 1, 2]), ("5:20:5", None, [5, 10, 15]),
])
def test_ranges_in_slice_syntax(text, count, frames):
    assert parse_frames(text, "--frames", count) == frames


@pytest.mark.parametrize("text, message", [
    ("0:10:0", "--frames 0:10:0: the step must be at least 1, got 0"),
    ("", "--frames is empty"), ("   ", "--frames is empty"),
    ("5:5", "--frames 5:5 selects no frame"), ("6:2", "--frames 6:2 selects no frame"),
    ("-1:3", "no negative numbers"), ("1:-1", "no negative numbers"),
    ("x", "--frames must look like A:B"), ("1:2:3:4", "--frames must look like A:B"), ("1.5", "must look like"),
    (f"0:{MAX_FRAME + 1}", f"frame numbers are at most {MAX_FRAME}"),
    ("3:", "--frames 3:: needs an end here"),  # no length known: train's frames apply to every sequence
])
def test_bad_ranges_are_one_line_naming_the_flag(text, message):
    with pytest.raises(ValueError) as info:
        parse_frames(text, "--frames")
    assert message in str(info.value) and "\n" not in str(info.value)


def test_a_range_past_the_sequence_names_it():
    with pytest.raises(ValueError, match=r"--frames 1:999 is out of range for motion 'walk' \(10 frames: 0..9\)"):
        parse_frames("1:999", "--frames", 10, "motion 'walk'")
    with pytest.raises(ValueError, match="--frames 12: is out of range"):
        parse_frames("12:", "--frames", 10)
    assert parse_frame_range(None) is None and parse_frames(None) is None


@pytest.mark.parametrize("text, message", [
    (",", "an empty camera"), ("", "--cameras is empty"), (" , ,", "an empty camera"), ("a,,b", "an empty camera"),
    ("a,", "an empty camera"),
])
def test_empty_lists_and_items_are_refused(text, message):
    with pytest.raises(ValueError, match=message):
        parse_list(text, "--cameras", kind="camera")


def test_an_empty_list_names_its_items_in_the_plural():
    with pytest.raises(ValueError, match=r"^--cameras is empty; give one or more cameras separated by commas$"):
        parse_list(" ", "--cameras", kind="camera")
    with pytest.raises(ValueError, match=r"^--palette is empty; give one or more colours \('-' keeps one\) separated"):
        parse_list("", "--palette", kind="colour ('-' keeps one)")


def test_list_items_are_stripped_and_converted():
    assert parse_list(" cam01 , cam02", "--cameras") == ["cam01", "cam02"]
    assert parse_list("1, 2.5", "--shape", float) == [1.0, 2.5]
    with pytest.raises(ValueError, match=r"--views '1,x': item 'x': not a whole number"):
        parse_list("1,x", "--views", int)
    assert parse_list(None, "--cameras") is None


@settings(max_examples=300, deadline=None)
@given(st.one_of(st.text(max_size=20), st.text(alphabet="0123456789: -,", max_size=16)),
       st.one_of(st.none(), st.integers(0, 50)))
def test_any_text_gives_frames_or_one_line(text, count):
    try:
        frames = parse_frames(text, "--frames", count)
    except ValueError as exc:
        assert str(exc).startswith("--frames") and "\n" not in str(exc)
        return
    assert frames and all(0 <= f <= MAX_FRAME for f in frames) and frames == sorted(set(frames))
    if count is not None:
        assert frames[-1] < count


@settings(max_examples=300, deadline=None)
@given(st.one_of(st.text(max_size=20), st.text(alphabet="ab1 ,", max_size=12)))
def test_any_text_gives_a_list_or_one_line(text):
    try:
        items = parse_list(text, "--presets", kind="preset")
    except ValueError as exc:
        assert str(exc).startswith("--presets") and "\n" not in str(exc)
        return
    assert items and all(item and item == item.strip() and "," not in item for item in items)


@given(st.integers(0, 40), st.integers(1, 41), st.integers(1, 5))
def test_a_range_selects_what_python_slices_select(start, stop, step):
    text = f"{start}:{stop}:{step}"
    if start >= stop:
        with pytest.raises(ValueError, match="selects no frame"):
            parse_frame_range(text)
        return
    spec = parse_frame_range(text)
    assert spec == FrameRange(start, stop, step, text, "--frames")
    assert spec.frames(41) == list(range(41))[start:stop:step]
