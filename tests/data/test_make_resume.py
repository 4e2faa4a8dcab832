"""``garmentnerf data make`` interrupted (SIGINT, SIGTERM, SIGKILL) and resumed: nothing lost, never a traceback.

Every test makes the smallest scene there is: two sequences (``train`` and ``test_run``) of two
frames each, one camera of 32 x 32 pixels, one settling frame, one solver substep and iteration,
simulated one after the other (``--processes 1``). A signal sent once the first sequence has
finished must leave a folder that the same command finishes into the scene an uninterrupted make
writes: the same garment arrays bit for bit, the same ``scene.json`` (simulation timings aside),
a ``simulation`` entry for every sequence, and no temporary file.
"""

from __future__ import annotations

import copy
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

SPEC = ["--garment", "skirt", "--motion", "walk", "--frames", "2", "--test-motion", "run", "--test-frames", "2",
        "--views", "1", "--held-out-views", "0", "--size", "32", "--sim", "settle_hold_frames=0",
        "--sim", "settle_frames=1", "--sim", "chunk_frames=2", "--sim", "substeps=1", "--sim", "iterations=1"]
SEQUENCES = ("train", "test_run")
FRAMES = 2
#: Simulation statistics that are measured times: they differ between any two runs.
TIMINGS = ("seconds_per_frame", "cpu_seconds_per_frame")
#: Seconds to wait for a make (the first one on a machine also compiles warp's kernels).
TIMEOUT_S = 600


def _command(out: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "garmentnerf.cli.main", "data", "make", *SPEC, *extra, "--out", str(out)]


def _start(out: Path, logs: Path, *extra: str) -> subprocess.Popen:
    """A make in its own process group (as a shell job), its output in files (a full pipe would stall it)."""
    logs.mkdir(parents=True, exist_ok=True)
    with open(logs / "stdout", "w") as stdout, open(logs / "stderr", "w") as stderr:
        return subprocess.Popen(_command(out, *extra), stdout=stdout, stderr=stderr, text=True,
                                start_new_session=True)


def _run(out: Path, logs: Path, *extra: str) -> tuple[int, str, str]:
    proc = _start(out, logs, *extra)
    try:
        proc.wait(timeout=TIMEOUT_S)
    finally:
        _kill_group(proc.pid)
    return proc.returncode, (logs / "stdout").read_text(), (logs / "stderr").read_text()


def _group_members(pgid: int) -> list[int]:
    """Live (not zombie) processes of process group ``pgid`` (Linux /proc)."""
    members = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        if int(fields[2]) == pgid and fields[0] != "Z":
            members.append(int(stat.parent.name))
    return members


def _kill_group(pgid: int) -> None:
    """End whatever a test's make left running (its own process group only)."""
    try:
        os.killpg(pgid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        pass


def _scene_json(root: Path) -> dict:
    return json.loads((root / "scene.json").read_text())


def _recorded(root: Path, name: str) -> bool:
    try:
        return name in _scene_json(root).get("simulation", {})
    except (OSError, ValueError):
        return False


def _without_timings(data: dict) -> dict:
    """``scene.json`` content without the measured times (checked to be real durations)."""
    data = copy.deepcopy(data)
    for name, stats in data["simulation"].items():
        for key in TIMINGS:
            value = stats.pop(key)
            assert isinstance(value, float) and 0.0 < value < 300.0, (name, key, value)
    return data


def _files(root: Path) -> list[str]:
    """Every file under ``root``, the cache's key folders (hashes of the garment files, whose zip
    headers carry write times) replaced by ``KEY``."""
    out = []
    for path in root.rglob("*"):
        if path.is_file():
            parts = list(path.relative_to(root).parts)
            if parts[0] == "cache" and len(parts) == 5:
                parts[3] = "KEY"
            out.append("/".join(parts))
    return sorted(out)


def _temporaries(root: Path) -> list[Path]:
    return sorted(root.rglob(".*.tmp"))


def _assert_same_scene(made: Path, reference: Path, timings_too: bool = False) -> None:
    """``made`` is the scene ``reference`` is: garment arrays bit-identical, scene.json equal (but
    for the measured times unless ``timings_too``), the same files, no temporaries."""
    a, b = _scene_json(made), _scene_json(reference)
    assert list(a["simulation"]) == list(SEQUENCES)
    if timings_too:
        assert a == b
    assert _without_timings(a) == _without_timings(b)
    assert "processes" not in a["make"]["spec"] and a["make"]["spec"]["frames"] == FRAMES
    for name in SEQUENCES:
        with np.load(made / "sequences" / name / "garment.npz") as x, \
                np.load(reference / "sequences" / name / "garment.npz") as y:
            assert sorted(x.files) == sorted(y.files)
            for key in x.files:
                assert x[key].dtype == y[key].dtype, key
                np.testing.assert_array_equal(x[key], y[key], err_msg=f"{name}: {key}")
            pen = x["penetration_max_m"]
            assert x["vertices_q"].shape[0] == FRAMES
        stats = a["simulation"][name]
        assert stats["frames"] == FRAMES
        assert stats["penetration_max_m"] == float(pen.max()) and stats["penetration_max_m"] > 0.0
        assert stats["penetration_mean_m"] == float(pen.mean())
        assert stats["frames_over_bound"] == int((pen > stats["penetration_bound_m"]).sum())
        assert stats["settings"]["iterations"] == 1 and stats["settings"]["chunk_frames"] == 2
    assert a["palette_init"]["garment"] is not None and a["palette_init"]["body"] is not None
    assert _files(made) == _files(reference)
    assert _temporaries(made) == []


class _Background:
    """A make started in the background (the reference scene is made while the first test's make
    runs: two cores); :meth:`scene` waits for it and checks it finished."""

    def __init__(self, base: Path) -> None:
        self.out, self.logs = base / "scene", base / "logs"
        self.proc = _start(self.out, self.logs, "--processes", "1")

    def scene(self) -> Path:
        rc = self.proc.wait(timeout=TIMEOUT_S)
        assert rc == 0, (self.logs / "stderr").read_text()[-2000:]
        stdout = (self.logs / "stdout").read_text()
        assert "train: 2 frames (train), max penetration" in stdout
        assert "test_run: 2 frames (unseen_motion)" in stdout
        return self.out


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The scene of an uninterrupted make (``reference.scene()``)."""
    made = _Background(tmp_path_factory.mktemp("reference"))
    yield made
    _kill_group(made.proc.pid)


def _started(name: str):
    """The simulation of ``name`` has begun (its manifest is written first, seconds before its garment)."""
    return lambda out: (out / "sim" / name / "manifest.json").is_file()


# (signal, sent to the whole process group as Ctrl-C does or to the make alone, what shows that
#  the first sequence has finished, --processes of the resume)
KILLS = [
    pytest.param(signal.SIGINT, True, lambda out: _recorded(out, "train"), "1", id="SIGINT-group"),
    pytest.param(signal.SIGTERM, False, lambda out: (out / "sequences/train/garment.npz").is_file(), "2",
                 id="SIGTERM-make"),
    pytest.param(signal.SIGKILL, False, _started("test_run"), "1", id="SIGKILL-make"),
]


@pytest.mark.parametrize("sig, group, finished, processes", KILLS)
def test_interrupted_make_resumes_to_the_uninterrupted_scene(reference, tmp_path, sig, group, finished, processes):
    out = tmp_path / "scene"
    proc = _start(out, tmp_path / "killed", "--processes", "1")
    try:
        deadline = time.monotonic() + TIMEOUT_S
        while not finished(out):
            assert proc.poll() is None, f"make ended (rc {proc.returncode}) before the signal: " \
                                        f"{(tmp_path / 'killed' / 'stderr').read_text()[-2000:]}"
            assert time.monotonic() < deadline, "the first sequence did not finish in time"
            time.sleep(0.05)
        workers = [pid for pid in _group_members(proc.pid) if pid != proc.pid]
        (os.killpg if group else os.kill)(proc.pid, sig)
        rc = proc.wait(timeout=120)
        # the make's simulation processes end with it (a killed make's ones by themselves)
        deadline = time.monotonic() + 30
        while _group_members(proc.pid) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert _group_members(proc.pid) == [], f"processes left running after {sig.name} (workers were {workers})"
    finally:
        _kill_group(proc.pid)
    err = (tmp_path / "killed" / "stderr").read_text()
    assert not (out / "sequences" / "test_run" / "garment.npz").exists()  # stopped part-way
    assert (out / "sequences" / "train" / "garment.npz").is_file()
    if sig == signal.SIGKILL:
        assert rc == -signal.SIGKILL
    else:
        assert rc == 130, err[-2000:]
        assert "Traceback" not in err
        assert err.rstrip().splitlines()[-1] == "garmentnerf: interrupted"
        assert _temporaries(out) == []  # a stopped make leaves nothing half-written
        if sig == signal.SIGINT:  # recorded as soon as the sequence finished, and kept
            assert _scene_json(out)["simulation"]["train"]["frames"] == FRAMES

    rc, stdout, err = _run(out, tmp_path / "resumed", "--processes", processes)
    assert rc == 0, err[-2000:]
    assert "Traceback" not in err
    assert f"scene written to {out}" in stdout
    _assert_same_scene(out, reference.scene())


def test_statistics_a_kill_lost_are_restored(reference, tmp_path):
    """A make killed after a sequence's garment was written but before its statistics reached
    scene.json (here: both lost), and from a version that recorded --processes: the resume
    computes the same entries from the files, timings included."""
    reference = reference.scene()
    out = tmp_path / "scene"
    shutil.copytree(reference, out)
    data = _scene_json(out)
    del data["simulation"]["train"], data["simulation"]["test_run"]
    data["make"]["spec"]["processes"] = 1
    (out / "scene.json").write_text(json.dumps(data, indent=1))
    rc, stdout, err = _run(out, tmp_path / "logs", "--processes", "2")
    assert rc == 0, err[-2000:]
    _assert_same_scene(out, reference, timings_too=True)


def _snapshot(root: Path) -> dict[str, tuple[int, bytes]]:
    return {str(p.relative_to(root)): (p.stat().st_mtime_ns, p.read_bytes()) for p in root.rglob("*") if p.is_file()}


def test_resume_with_other_output_settings_is_refused(reference, tmp_path):
    reference = reference.scene()
    out = tmp_path / "scene"
    shutil.copytree(reference, out)
    # as a killed make leaves it: the second sequence not finished
    (out / "sequences" / "test_run" / "garment.npz").unlink()
    data = _scene_json(out)
    del data["simulation"]["test_run"]
    (out / "scene.json").write_text(json.dumps(data, indent=1))
    before = _snapshot(out)

    frames = SPEC.index("--frames") + 1
    cases = [(SPEC[:frames] + ["3"] + SPEC[frames + 1:], "--frames: 2 in the folder, 3 now"),
             (SPEC + ["--sim", "iterations=2"], "--sim iterations: 1 in the folder, 2 now")]
    for args, named in cases:
        proc = subprocess.run([sys.executable, "-m", "garmentnerf.cli.main", "data", "make", *args,
                               "--out", str(out)], capture_output=True, text=True, timeout=TIMEOUT_S)
        assert proc.returncode == 2, proc.stderr
        lines = proc.stderr.splitlines()
        assert len(lines) == 1, proc.stderr
        assert lines == [f"garmentnerf: error: {out / 'scene.json'}: this scene was made with other settings "
                         f"({named}); give the folder's values to finish it, or choose another --out"]
        assert proc.stdout == ""
        assert _snapshot(out) == before  # nothing touched


def test_a_second_make_of_a_folder_being_made_is_refused(reference, tmp_path):
    from garmentnerf.folder_lock import lock_folder

    reference = reference.scene()
    out = tmp_path / "scene"
    shutil.copytree(reference, out)
    before = _snapshot(out)
    with lock_folder(out, "garmentnerf data make"):  # as a running make holds it
        proc = subprocess.run(_command(out), capture_output=True, text=True, timeout=TIMEOUT_S)
    assert proc.returncode == 2
    assert proc.stderr.splitlines() == [f"garmentnerf: error: {out}: another 'garmentnerf data make' (PID "
                                        f"{os.getpid()}, 'garmentnerf data make') is writing this scene; wait for "
                                        f"it to finish, or choose another --out"]
    assert _snapshot(out) == before


def test_record_differences_are_named_with_both_values():
    from garmentnerf.data.make import MakeSpec, _check_record, _make_record
    from garmentnerf.data.simulate import SimSettings

    folder = _make_record(MakeSpec(frames=6, test_motions=["run"]), SimSettings(iterations=4))
    assert "processes" not in folder["spec"]
    same = _make_record(MakeSpec(frames=6, test_motions=["run"], processes=3), SimSettings(iterations=4))
    _check_record(Path("s/scene.json"), folder, same)  # --processes does not change the scene
    old_style = copy.deepcopy(folder)
    old_style["spec"]["processes"] = 1  # scenes made before processes was left out
    _check_record(Path("s/scene.json"), old_style, same)

    other = _make_record(MakeSpec(frames=8, test_motions=[], in_place=False),
                         SimSettings(iterations=4, self_contact=False))
    with pytest.raises(ValueError) as info:
        _check_record(Path("s/scene.json"), folder, other)
    message = str(info.value)
    assert "\n" not in message
    assert message == ("s/scene.json: this scene was made with other settings (--frames: 6 in the folder, 8 now; "
                       "--test-motion: run in the folder, none now; --no-in-place: off in the folder, on now; "
                       "--sim self_contact: true in the folder, false now); give the folder's values to finish it, "
                       "or choose another --out")
    with pytest.raises(ValueError, match=r"s/scene.json: this scene was not made by 'garmentnerf data make'"):
        _check_record(Path("s/scene.json"), None, same)


def test_a_make_killed_before_scene_json_is_resumable(tmp_path):
    """A make killed while writing the motions (no scene.json yet) leaves a folder the next make
    takes up; a folder with anything else in it is not taken."""
    from garmentnerf.data.make import _is_interrupted_creation

    root = tmp_path / "scene"
    root.mkdir()
    assert _is_interrupted_creation(root, ["train", "test_run"])  # empty
    (root / "sequences" / "train").mkdir(parents=True)
    (root / "sequences" / "train" / "motion.npz").write_bytes(b"motion")
    (root / "sequences" / "train" / ".motion.npz.k2j4.tmp").write_bytes(b"half a motion")
    (root / ".scene.json.x8f1.tmp").write_bytes(b"half a scene")
    assert _is_interrupted_creation(root, ["train", "test_run"])
    assert not _is_interrupted_creation(root, ["test_run"])  # another plan: not this make's folder
    (root / "notes.txt").write_text("the user's")
    assert not _is_interrupted_creation(root, ["train", "test_run"])


def test_worker_interrupt_handler_fires_once_and_not_after_the_work():
    """A simulation process's handler: the first SIGINT/SIGTERM interrupts, later ones are ignored;
    once the work is over (disarmed) none interrupts, so a stop that reaches a process already
    shutting down cannot raise inside an exit handler (it printed a traceback into data make's
    stderr: a weakref finalizer of torch.library interrupted at exit)."""
    from garmentnerf.data.make import InterruptOnce

    handler = InterruptOnce()
    with pytest.raises(KeyboardInterrupt, match="SIGTERM"):
        handler(signal.SIGTERM, None)
    handler(signal.SIGINT, None)  # the clean-up the first one started is not cut short
    done = InterruptOnce()
    done.disarm()
    done(signal.SIGTERM, None)
    done(signal.SIGINT, None)
    assert handler.fired == signal.SIGTERM and done.fired == 0
