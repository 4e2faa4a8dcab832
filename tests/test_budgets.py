"""Arguments that scale memory or time (:mod:`garmentnerf.budgets`): each is refused in one line naming
the flag, the bound and why, before anything large is imported or allocated: within a second of
the arguments being read, and in a process whose address space is capped (``prlimit --as``), so
that a regression fails here instead of taking the machine's memory."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from garmentnerf.budgets import HISTORY, MOTION_FPS, PLAYBACK, QUALITY, VIDEO_FPS
from garmentnerf.cli.main import main
from garmentnerf.demos import demo

#: The address space a refused command may use: the command line alone needs about 40 MB of memory;
#: torch and the model stack need far more, so a check moved after them fails here.
CAP_BYTES = 512 * 2**20

CASES = [
    (["eval", "--demo", "skirt", "--split", "unseen_view", "--frames", "0:2", "--quality", "100"],
     "--quality must be in 0.0625..4"),
    (["render", "--demo", "skirt", "--quality", "1e-9", "--out", "{tmp}/r"], "--quality must be in 0.0625..4"),
    (["render", "--demo", "skirt", "--frames", "0:1", "--size", "64", "--fps", "1e-300", "--video", "--out", "{tmp}/r"],
     "--fps must be in 0.1..1000"),
    (["render", "--demo", "skirt", "--fps", "1e308", "--video", "--out", "{tmp}/r"], "--fps must be in 0.1..1000"),
    (["maps", "--motion", "walk", "--fps", "1e9", "--frame", "5", "--out", "{tmp}/m.npz"], "--fps must be in 1..1000"),
    (["body", "export", "--fps", "1e9", "--out", "{tmp}/b.ply"], "--fps must be in 1..1000"),
    (["maps", "--history", "100", "--out", "{tmp}/m.npz"], "--history must be in 0..8"),
    (["report", "--scene", "{scene}", "--preset", "tiny", "--variants", "k100000", "--out", "{tmp}/r.md"],
     "--variants k100000: k must be in 0..8"),
    (["bench", "--demo", "skirt", "--playback-frames", "100000"], "--playback-frames must be in 1..240"),
]
IDS = [f"{' '.join(a[:2])} #{i}" for i, (a, _) in enumerate(CASES)]


def _argv(argv, tmp_path) -> list[str]:
    return [a.format(tmp=tmp_path, scene=demo("skirt").scene_dir) for a in argv]


@pytest.mark.parametrize("argv, message", CASES, ids=IDS)
def test_a_large_argument_is_refused_within_a_second(argv, message, tmp_path, capfd):
    t0 = time.perf_counter()
    code = main(_argv(argv, tmp_path))
    seconds = time.perf_counter() - t0
    err = [line for line in capfd.readouterr().err.splitlines() if line.strip()]
    assert code == 2 and len(err) == 1 and message in err[0] and "(" in err[0], err  # the why, in brackets
    assert seconds < 1.0, f"refused after {seconds:.2f} s"
    assert not any(tmp_path.iterdir())


@pytest.mark.skipif(shutil.which("prlimit") is None, reason="no prlimit (util-linux)")
@pytest.mark.parametrize("argv, message", CASES, ids=IDS)
def test_a_large_argument_is_refused_under_a_memory_cap(argv, message, tmp_path):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(Path(__file__).resolve().parents[1]),
                                                        os.environ.get("PYTHONPATH", "")]))
    t0 = time.perf_counter()
    proc = subprocess.run(["prlimit", f"--as={CAP_BYTES}", sys.executable, "-m", "garmentnerf.cli.main",
                           *_argv(argv, tmp_path)], capture_output=True, text=True, timeout=120, env=env,
                          cwd=tmp_path)
    seconds = time.perf_counter() - t0
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and message in lines[0], proc.stderr[-3000:]
    # a fresh interpreter's start is most of it; the work a refusal must not begin takes minutes
    assert seconds < 15.0, f"refused after {seconds:.1f} s"
    assert not any(tmp_path.iterdir())


def test_bounds_refuse_nan_non_numbers_and_fractions_where_whole():
    assert QUALITY.check(4, "--quality") == 4.0 and HISTORY.check(8, "--history") == 8
    for bound, value, message in [(QUALITY, float("nan"), "must be in"), (VIDEO_FPS, "x", "must be a number"),
                                  (HISTORY, 2.5, "must be a whole number"), (PLAYBACK, 0, "must be in 1..240"),
                                  (MOTION_FPS, float("inf"), "must be in 1..1000")]:
        with pytest.raises(ValueError, match=message):
            bound.check(value, "--flag")
