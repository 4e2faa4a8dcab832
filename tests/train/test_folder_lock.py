"""One writer per folder (:mod:`garmentnerf.folder_lock`): a second writer is refused in one line
naming the holder's PID, the kernel frees the lock of a killed holder, a clean release leaves
nothing behind; and two real ``garmentnerf train --out R --resume`` at once leave exactly one
run's work."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from garmentnerf.cli.main import main
from garmentnerf.folder_lock import LOCK_FILE, FolderBusyError, folder_has_files, lock_folder

#: A process that takes the lock of argv[1], says so on stdout, and sleeps until killed.
HOLDER = textwrap.dedent("""
    import sys, time
    from garmentnerf.folder_lock import lock_folder
    lock = lock_folder(sys.argv[1], "test holder")
    print("held", flush=True)
    time.sleep(600)
""")


def _holder(folder: Path) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-c", HOLDER, str(folder)], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "held"
    return proc


def test_a_second_writer_is_refused_naming_the_holder_and_a_killed_holder_frees_the_folder(tmp_path):
    run = tmp_path / "run"
    proc = _holder(run)
    try:
        with pytest.raises(FolderBusyError, match=rf"PID {proc.pid}, 'test holder'") as info:
            lock_folder(run, "second")
        assert "\n" not in str(info.value) and str(run) in str(info.value)
    finally:
        proc.kill()
        proc.wait()
    assert (run / LOCK_FILE).is_file()  # a killed holder leaves its file, not its lock
    assert not folder_has_files(run)
    with lock_folder(run, "third") as lock:
        assert lock.held and f"{os.getpid()} third" in (run / LOCK_FILE).read_text()
    assert not any(run.iterdir())  # its lock file gone; the folder stays (the killed holder made it)
    with lock_folder(tmp_path / "new" / "run"):
        pass
    assert not (tmp_path / "new").exists()  # the folders the lock made, with nothing written into them


def test_a_release_keeps_what_was_written_and_a_user_folder(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    with lock_folder(run):
        (run / "run.json").write_text("{}")
        with pytest.raises(FolderBusyError):  # another open of the file in this process is another writer too
            lock_folder(run)
    assert sorted(p.name for p in run.iterdir()) == ["run.json"]
    empty = tmp_path / "empty"
    empty.mkdir()
    lock_folder(empty).release()
    assert empty.is_dir() and not any(empty.iterdir())  # the user's (empty) folder stays
    (tmp_path / "file").write_text("x")
    with pytest.raises(NotADirectoryError, match="is a file"):
        lock_folder(tmp_path / "file")


FAST = ["--preset", "tiny", "--perceptual", "none", "--no-progress", "--threads", "1", "--log-every", "1",
        "--image-every", "0"]


def test_two_concurrent_resumes_leave_one_runs_work(tiny_scene, tmp_path, capfd):
    """``train --out R --resume`` twice at once (the second with another loss weight): the second is
    refused at once (exit 2, one line naming the first's PID) while the first runs; the first
    finishes, and R holds its work alone (no override of the second, one TensorBoard writer)."""
    out = tmp_path / "run"
    assert main(["train", "--scene", str(tiny_scene.root), "--out", str(out), *FAST, "--iterations", "4",
                 "--generator-iterations", "1", "--frames", "0:2", "--ckpt-every", "2", "--stop-after", "2"]) == 0
    capfd.readouterr()
    events_before = sorted(p.name for p in (out / "tb").iterdir())
    first = subprocess.Popen([sys.executable, "-m", "garmentnerf.cli.main", "train", "--out", str(out), "--resume",
                              "--no-progress", "--threads", "1"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                             text=True)
    try:
        deadline = time.monotonic() + 120
        lock = out / LOCK_FILE
        while not (lock.is_file() and lock.read_text().startswith(f"{first.pid} ")):
            assert first.poll() is None, first.stderr.read()
            assert time.monotonic() < deadline, "the first writer took no lock within 120 s"
            time.sleep(0.01)
        first.send_signal(signal.SIGSTOP)  # holds the lock, and is still running, while the second tries
        try:
            t0 = time.monotonic()
            second = subprocess.run([sys.executable, "-m", "garmentnerf.cli.main", "train", "--out", str(out),
                                     "--resume", "--no-progress", "--threads", "1", "--loss-weight", "image=5"],
                                    capture_output=True, text=True, timeout=120)
            seconds = time.monotonic() - t0
        finally:
            first.send_signal(signal.SIGCONT)
        lines = second.stderr.strip().splitlines()
        assert second.returncode == 2 and len(lines) == 1 and "Traceback" not in second.stderr, second.stderr
        assert f"PID {first.pid}" in lines[0] and "garmentnerf train --resume" in lines[0], lines
        assert seconds < 60
        assert first.wait(timeout=300) == 0, first.stderr.read()
    finally:
        if first.poll() is None:
            first.kill()
            first.wait()
    info = json.loads((out / "run.json").read_text())
    assert info["step"] == 5 and info["overrides"] == [] and info.get("loss_weight_changes", []) == []
    new_events = sorted(set(p.name for p in (out / "tb").iterdir()) - set(events_before))
    assert len(new_events) == 1, new_events  # the first writer's; the second never opened one
    assert not (out / LOCK_FILE).exists()
