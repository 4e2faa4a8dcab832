"""``garmentnerf data make``: motions, in-place walking, and a killed run that resumes bit-identically."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from garmentnerf.data.garment_sequence import load_sequence
from garmentnerf.data.make import MakeSpec, build_motion, remove_drift
from garmentnerf.data.scene import Scene

TINY = ["--garment", "skirt", "--motion", "walk", "--frames", "6", "--views", "2", "--held-out-views", "0",
        "--size", "32", "--sim", "settle_hold_frames=1", "--sim", "settle_frames=2", "--sim", "chunk_frames=2",
        "--sim", "substeps=4", "--sim", "iterations=4", "--processes", "1"]


def test_training_motion_is_repeated_to_length_and_cut(body):
    motion = build_motion("walk", body, None, 30.0, frames=100, in_place=False)
    assert motion.num_frames == 100  # the 39-frame walk repeated, then cut


def test_remove_drift_keeps_the_walk_in_the_ring(body):
    walk = build_motion("walk", body, None, 30.0, frames=120, in_place=False)
    travel = walk.translation[:, :2]
    assert float((travel[-1] - travel[0]).norm()) > 1.0  # four walk cycles travel several metres
    still = remove_drift(walk)
    horizontal = still.translation[:, :2]
    assert float(horizontal.norm(dim=1).max()) < 0.25
    # vertical motion and joint rotations are untouched
    assert torch.equal(still.translation[:, 2], walk.translation[:, 2])
    assert torch.equal(still.rotations, walk.rotations)
    # the fast sway survives: frame-to-frame horizontal differences keep their high-frequency part
    assert float(torch.diff(horizontal, dim=0).abs().max()) > 1e-4


def test_spec_validation():
    with pytest.raises(ValueError, match="--frames"):
        MakeSpec(frames=0)
    with pytest.raises(ValueError, match="--radius"):
        MakeSpec(radius=float("nan"))


def _make(out: Path, **kw) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "garmentnerf.cli.main", "data", "make", *TINY, "--out", str(out)]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True, **kw)


def test_cli_rejects_unknown_setting(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "garmentnerf.cli.main", "data", "make", "--sim", "wobble=3",
                           "--out", str(tmp_path / "s")], capture_output=True, text=True)
    assert proc.returncode == 2
    assert "unknown simulation setting(s) wobble" in proc.stderr
    assert "Traceback" not in proc.stderr


@pytest.mark.slow
def test_killed_make_resumes_to_the_same_frames(tmp_path):
    full = _make(tmp_path / "full")
    out, _ = full.communicate(timeout=900)
    assert full.returncode == 0, out

    killed = _make(tmp_path / "killed")
    chunks = tmp_path / "killed" / "sim" / "train"
    deadline = time.time() + 900
    while time.time() < deadline and len(list(chunks.glob("chunk_*.npz"))) < 1:
        time.sleep(0.2)
    os.killpg(killed.pid, signal.SIGKILL)  # the whole process group: parent and simulation worker
    killed.wait()
    assert not (tmp_path / "killed" / "sequences" / "train" / "garment.npz").exists()
    done_before = len(list(chunks.glob("chunk_*.npz")))
    assert 1 <= done_before < 4  # killed part-way (6 frames in chunks of 2 = 3 chunks)

    resumed = _make(tmp_path / "killed")
    out, _ = resumed.communicate(timeout=900)
    assert resumed.returncode == 0, out
    a = load_sequence(tmp_path / "full" / "sequences" / "train" / "garment.npz")
    b = load_sequence(tmp_path / "killed" / "sequences" / "train" / "garment.npz")
    np.testing.assert_array_equal(np.asarray(a.vertices), np.asarray(b.vertices))
    scene = Scene.load(tmp_path / "killed")
    assert scene.palette_init["garment"] is not None
    assert scene.simulation["train"]["frames"] == 6
