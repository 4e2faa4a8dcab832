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
    # peak memory against --max-memory-gib: an estimate, not a fixed bound (garmentnerf.budgets, "Memory")
    (["render", "--demo", "skirt", "--size", "8192", "--max-memory-gib", "4", "--out", "{tmp}/r"],
     ("a render of 8192x8192 pixels needs about 12.9 GiB at its peak (estimated: 67.1 million output pixels), more "
     "than the 4.0 GiB --max-memory-gib allows; lower --size or --quality")),
    (["render", "--demo", "skirt", "--size", "300x8000", "--quality", "4", "--max-memory-gib", "1", "--out", "{tmp}/r"],
     ("a render of 300x8000 pixels at quality 4 needs about 1.4 GiB at its peak (estimated: 2.4 million output "
     "pixels, 0.157 million rendered, 0.00983 million rays)")),
    (["eval", "--demo", "skirt", "--split", "unseen_view", "--quality", "4", "--max-memory-gib", "2"],
     ("evaluating views of 512x512 pixels at quality 4 needs about 2.4 GiB at its peak (estimated: 0.262 million "
     "output pixels, 4.19 million rendered, 0.262 million rays)")),
    (["render", "--demo", "skirt", "--max-memory-gib", "0", "--out", "{tmp}/r"], "--max-memory-gib must be in 0.25..65536"),
    (["eval", "--demo", "skirt", "--split", "seen", "--max-memory-gib", "nan"], "--max-memory-gib must be in"),
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
                          cwd=tmp_path, check=False)
    seconds = time.perf_counter() - t0
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and message in lines[0], proc.stderr[-3000:]
    # a fresh interpreter's start is most of it; the work a refusal must not begin takes minutes
    assert seconds < 15.0, f"refused after {seconds:.1f} s"
    assert not any(tmp_path.iterdir())


@pytest.mark.skipif(shutil.which("prlimit") is None, reason="no prlimit (util-linux)")
@pytest.mark.parametrize("argv, message", [
    (["render", "--demo", "skirt", "--size", "8192", "--out", "{tmp}/r"],
     ("a render of 8192x8192 pixels needs about 12.9 GiB at its peak (estimated: 67.1 million output pixels), more "
     "than the ")),
    (["eval", "--demo", "skirt", "--split", "unseen_view", "--quality", "4"],
     "evaluating views of 512x512 pixels at quality 4 needs about 2.4 GiB at its peak"),
], ids=["render --size", "eval --quality"])
def test_what_the_memory_cap_leaves_refuses_a_render_that_would_outgrow_it(argv, message, tmp_path):
    """Without --max-memory-gib the estimate is held against what the process may use: here the address space
    ``prlimit --as`` leaves (a machine's free memory and a control group's limit the same way)."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(Path(__file__).resolve().parents[1]),
                                                        os.environ.get("PYTHONPATH", "")]))
    t0 = time.perf_counter()
    proc = subprocess.run(["prlimit", f"--as={CAP_BYTES}", sys.executable, "-m", "garmentnerf.cli.main",
                           *_argv(argv, tmp_path)], capture_output=True, text=True, timeout=120, env=env,
                          cwd=tmp_path, check=False)
    seconds = time.perf_counter() - t0
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and message in lines[0], proc.stderr[-3000:]
    left = float(lines[0].split("more than the ")[1].split(" GiB")[0])
    assert 0.0 < left <= CAP_BYTES / 2**30 and "this process's address-space limit leaves" in lines[0]
    assert lines[0].endswith("or pass --max-memory-gib N to allow N GiB")
    assert seconds < 3.0, f"refused after {seconds:.1f} s"  # before torch loads
    assert not any(tmp_path.iterdir())


def test_the_estimate_follows_the_renderers_resolution_rule():
    from garmentnerf.budgets import BASE_BYTES, RenderGeometry, render_memory

    demo_like = RenderGeometry(trained_side=512.0, upsample=4, image_size=(512, 512))
    # the demo's reference render of a 256 x 256 orbit: 512 x 512 rendered pixels, 128 x 128 rays (measured:
    # 16384 rays, 0.07 GiB above the base)
    estimate = render_memory(demo_like, 256, 256, 1.0)
    assert (estimate.rays, estimate.rendered_pixels, estimate.output_pixels) == (16384, 512 * 512, 256 * 256)
    assert 0.07 * 2**30 < estimate.peak_bytes - BASE_BYTES < 0.15 * 2**30
    # quality scales the rendered pixels with its square, the output size only the output's; a wide frame
    # renders the trained density across its longer side
    assert render_memory(demo_like, 256, 256, 4.0).rays == 16 * 16384
    assert render_memory(demo_like, 1024, 512, 1.0).rendered_pixels == 512 * 256
    # the measured 4096 x 4096 render at quality 1/4 peaked 2.7 GiB above the base: the estimate is above it
    assert 2.7 * 2**30 < render_memory(demo_like, 4096, 4096, 0.25).peak_bytes - BASE_BYTES < 3.5 * 2**30
    assert render_memory(demo_like, 300, 200).rays == 0 and render_memory(demo_like, 300, 200).output_pixels == 60000


def test_bounds_refuse_nan_non_numbers_and_fractions_where_whole():
    assert QUALITY.check(4, "--quality") == 4.0 and HISTORY.check(8, "--history") == 8
    for bound, value, message in [(QUALITY, float("nan"), "must be in"), (VIDEO_FPS, "x", "must be a number"),
                                  (HISTORY, 2.5, "must be a whole number"), (PLAYBACK, 0, "must be in 1..240"),
                                  (MOTION_FPS, float("inf"), "must be in 1..1000")]:
        with pytest.raises(ValueError, match=message):
            bound.check(value, "--flag")
