"""Atomic file writing and the strict JSON reader (garmentnerf.io_utils)."""

from __future__ import annotations

import os
import stat

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from garmentnerf.io_utils import atomic_write_path, next_free_path


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def test_atomic_write_gives_usual_permissions_even_when_the_writer_recreates_the_file(tmp_path):
    from safetensors.torch import save_file

    target = tmp_path / "w.safetensors"
    with atomic_write_path(target) as tmp:
        save_file({"x": torch.zeros(2)}, str(tmp))
    assert stat.S_IMODE(target.stat().st_mode) == 0o666 & ~_umask()
    assert [p.name for p in tmp_path.iterdir()] == ["w.safetensors"]  # no temporary left


def test_atomic_write_never_clobbers_and_cleans_up_on_error(tmp_path):
    target = tmp_path / "a.txt"
    target.write_text("mine")
    with pytest.raises(FileExistsError):
        with atomic_write_path(target, overwrite=False) as tmp:
            tmp.write_text("theirs")
    with pytest.raises(RuntimeError):
        with atomic_write_path(tmp_path / "b.txt") as tmp:
            tmp.write_text("half")
            raise RuntimeError("interrupted")
    assert target.read_text() == "mine" and sorted(p.name for p in tmp_path.iterdir()) == ["a.txt"]
    assert next_free_path(target).name == "a_001.txt"


def test_a_failed_write_names_the_target_not_the_temporary(tmp_path):
    import errno

    target = tmp_path / "out.json"
    with pytest.raises(OSError) as info:
        with atomic_write_path(target) as tmp:
            raise OSError(errno.ENOSPC, "No space left on device", str(tmp))
    message = str(info.value)
    assert info.value.errno == errno.ENOSPC and str(target) in message and ".tmp" not in message
    assert list(tmp_path.iterdir()) == []  # neither the target nor the temporary


@pytest.mark.parametrize("overwrite", [True, False])
def test_a_full_disk_at_the_write_names_the_target_and_keeps_the_old_file(tmp_path, overwrite):
    """write() reports ENOSPC naming no file (the disk filled while the data went out): the error names
    the file asked for, in one line without "[Errno 28]", and the old file and nothing else is left."""
    import errno

    from garmentnerf.io_utils import write_file_atomic

    target = tmp_path / "mesh.ply"
    if overwrite:
        target.write_bytes(b"the user's mesh")
    with pytest.raises(OSError) as info, atomic_write_path(target, overwrite=overwrite) as tmp, open(tmp, "wb") as fh:
        fh.write(b"half a me")
        raise OSError(errno.ENOSPC, "No space left on device")  # what a full disk's write() raises
    assert info.value.errno == errno.ENOSPC and type(info.value) is OSError
    assert str(info.value) == f"{target}: cannot write (No space left on device)"
    assert sorted(p.name for p in tmp_path.iterdir()) == (["mesh.ply"] if overwrite else [])
    if overwrite:
        assert target.read_bytes() == b"the user's mesh"
    # the writers built on it say the same; an error naming another file, or a writer's own, passes unchanged
    import garmentnerf.io_utils as io_module

    def full(path, data):
        raise OSError(errno.EDQUOT, os.strerror(errno.EDQUOT))

    real, io_module._write_synced = io_module._write_synced, full
    try:
        with pytest.raises(OSError, match=rf"^{tmp_path / 'w.bin'}: cannot write \(Disk quota exceeded\)$"):
            write_file_atomic(tmp_path / "w.bin", b"x")
    finally:
        io_module._write_synced = real
    with pytest.raises(FileNotFoundError, match="input.npz") as other, atomic_write_path(tmp_path / "out.bin"):
        (tmp_path / "input.npz").read_bytes()
    assert other.value.filename == str(tmp_path / "input.npz")
    with pytest.raises(FileExistsError, match="^my own words$"), atomic_write_path(tmp_path / "out.bin"):
        raise FileExistsError("my own words")
    assert sorted(p.name for p in tmp_path.iterdir()) == (["mesh.ply"] if overwrite else [])


def test_stale_temporaries_of_killed_writes_are_removed(tmp_path):
    import time

    from garmentnerf.io_utils import STALE_TEMPORARY_SECONDS, remove_stale_temporaries
    from garmentnerf.render.video import FrameWriter, VideoWriter

    old = time.time() - STALE_TEMPORARY_SECONDS - 5
    stale = [tmp_path / ".frame_0003.png.abc123.tmp", tmp_path / ".walk_orbit.mp4.x9y8.tmp"]
    fresh = tmp_path / ".frame_0004.png.live01.tmp"  # a write in flight right now
    other = [tmp_path / "frame_0001.png", tmp_path / ".notes.txt.old.tmp", tmp_path / "keep.tmp"]
    for p in (*stale, fresh, *other):
        p.write_bytes(b"x")
    for p in (*stale, *other):
        os.utime(p, (old, old))
    FrameWriter(tmp_path).check([5])
    assert not stale[0].exists() and stale[1].exists() and fresh.exists()
    video = VideoWriter(tmp_path / "walk_orbit.mp4", 30.0)
    video.abort()
    assert not stale[1].exists() and fresh.exists() and all(p.exists() for p in other)
    assert remove_stale_temporaries(tmp_path / "missing", "x") == []


def test_file_digests_match_hashlib_and_follow_changes(tmp_path):
    import hashlib

    from garmentnerf.io_utils import FileDigests

    digests = FileDigests(capacity=2)
    path = tmp_path / "a.bin"
    assert digests.digest(path) is None
    path.write_bytes(b"x" * 3_000_000)  # more than one 1 MiB block
    assert digests.digest(path) == hashlib.sha256(b"x" * 3_000_000).hexdigest()
    path.write_bytes(b"changed")
    os.utime(path, ns=(1, 1))  # a new (size, mtime): hashed afresh
    assert digests.digest(path) == hashlib.sha256(b"changed").hexdigest()
    for name in ("b", "c", "d"):
        (tmp_path / name).write_bytes(name.encode())
        assert digests.digest(tmp_path / name) == hashlib.sha256(name.encode()).hexdigest()
    assert len(digests._digests) == 2  # bounded by capacity


def test_file_digests_shared_between_threads(tmp_path):
    import hashlib
    from concurrent.futures import ThreadPoolExecutor

    from garmentnerf.io_utils import FileDigests

    files = []
    for i in range(12):
        files.append(tmp_path / f"f{i}")
        files[-1].write_bytes(bytes([i]) * (1000 * i + 1))
    expected = {f: hashlib.sha256(f.read_bytes()).hexdigest() for f in files}
    digests = FileDigests(capacity=5)  # smaller than the set: entries are evicted while others read
    with ThreadPoolExecutor(8) as pool:
        got = list(pool.map(lambda k: (files[k % 12], digests.digest(files[k % 12])), range(2000)))
    assert all(d == expected[f] for f, d in got)
    assert len(digests._digests) <= 5


def test_npz_member_shape_reads_headers_only(tmp_path):
    import numpy as np

    from garmentnerf.io_utils import npz_member_shape

    np.savez(tmp_path / "a.npz", v=np.zeros((4, 7, 3), np.float32), o=np.array([{"k": 1}], dtype=object))
    assert npz_member_shape(tmp_path / "a.npz", "v") == (4, 7, 3)
    assert npz_member_shape(tmp_path / "a.npz", "o") == (1,)  # an object array: not unpickled
    assert npz_member_shape(tmp_path / "a.npz", "missing") is None


# ---- the strict JSON reader ------------------------------------------------------------------------------
@pytest.mark.parametrize("text, message", [
    ('{"a": NaN}', "f.json: a: NaN is not a finite number"),
    ('{"a": [1, {"b": -Infinity}]}', "f.json: a[1].b: -Infinity is not a finite number"),
    ('{"a": 1e999}', "f.json: a: 1e999 is not a finite number"),
    ('{"a": 1' + "0" * 400 + "}", "f.json: a: 100000000000... (401 characters) is not a finite number"),
    ('{"a": 1, "a": 2}', "f.json: key 'a' is given twice in one object"),
    ('{"a\\nb": NaN}', 'f.json: "a\\nb": NaN is not a finite number'),
    ('{"a": 1,', "f.json: not valid JSON (Expecting property name"),
    ("[" * 100000, "f.json: not valid JSON (RecursionError"),
])
def test_the_strict_reader_refuses_what_json_would_let_through(text, message):
    from garmentnerf.io_utils import parse_json_strict

    with pytest.raises(ValueError) as info:
        parse_json_strict(text, "f.json")
    assert str(info.value).startswith(message) and "\n" not in str(info.value)


def test_typed_fields_take_real_numbers_and_booleans():
    from garmentnerf.io_utils import json_bool, json_number, json_whole

    assert json_bool(False, "x") is False and json_whole(3.0, "w", 1, 8) == 3 and json_number(2, "n", 0) == 2.0
    for call, message in [(lambda: json_bool("false", "constant_speed"), "constant_speed must be true or false"),
                          (lambda: json_bool(0, "flag"), "flag must be true or false"),
                          (lambda: json_number(True, "fps"), "fps must be a number, got True"),
                          (lambda: json_number("1", "fps"), "fps must be a number"),
                          (lambda: json_number(0.0, "fps", 0.0, low_open=True), "fps must be > 0"),
                          (lambda: json_whole(2.5, "width"), "width must be a whole number"),
                          (lambda: json_whole(9000, "width", 8, 8192), "width must be a whole number in 8..8192")]:
        with pytest.raises(ValueError, match=message):
            call()


def test_read_json_strict_names_the_file(tmp_path):
    from garmentnerf.io_utils import read_json_strict

    (tmp_path / "a.json").write_text('{"w": 1}')
    assert read_json_strict(tmp_path / "a.json", "thing") == {"w": 1}
    with pytest.raises(FileNotFoundError, match="no such thing file"):
        read_json_strict(tmp_path / "b.json", "thing")
    with pytest.raises(IsADirectoryError, match="is a folder, not a thing file"):
        read_json_strict(tmp_path, "thing")
    (tmp_path / "c.json").write_bytes(b"\xff\xfe")
    with pytest.raises(ValueError, match="not a thing file"):
        read_json_strict(tmp_path / "c.json", "thing")


@settings(max_examples=300, deadline=None)
@given(st.text(alphabet='{}[]":,-+.0123456789eEaINfinityNtrulse \n\\', max_size=40) | st.text(max_size=20))
def test_any_text_is_a_value_or_one_line(text):
    from garmentnerf.io_utils import parse_json_strict

    try:
        parse_json_strict(text, "f.json")
    except ValueError as exc:
        assert str(exc).startswith("f.json: ") and "\n" not in str(exc)
