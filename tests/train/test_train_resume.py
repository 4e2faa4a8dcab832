"""``garmentnerf train --resume``: nothing lost, never a traceback.

A resume continues the run with its own settings (preset, seed, frames, checkpoint interval, ...)
and refuses ones that would change what the run is; SIGINT, SIGTERM and SIGKILL at random points
lose at most the steps since the last checkpoint (the resumed run ends bit-equal to an
uninterrupted one); a full disk is a one-line error that leaves no partial checkpoint; an
unreadable newest checkpoint falls back to the previous one; temporaries of killed writes are
removed. All on the tiny rigged scene (``tests/conftest.py``) with the tiny preset.
"""

from __future__ import annotations

import errno
import json
import random
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

from garmentnerf.cli.main import main
from garmentnerf.train.checkpoints import latest_checkpoint

LINUX = Path("/proc/stat").is_file()  # where garmentnerf.cpu_load can read the machine

#: Options that keep every run of this file small and fast.
FAST = ["--preset", "tiny", "--perceptual", "none", "--no-progress", "--threads", "1", "--log-every", "1",
        "--image-every", "0"]
#: What a resume passes besides --out (nothing about the run itself).
RESUME = ["--resume", "--no-progress", "--threads", "1"]


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # bit-equal resumes need one thread


def new_run(scene, out, *extra) -> list[str]:
    return ["train", "--scene", str(scene.root), "--out", str(out), *FAST, *extra]


def resume(out, *extra) -> list[str]:
    return ["train", "--out", str(out), *RESUME, *extra]


def info_of(out) -> dict:
    return json.loads((Path(out) / "run.json").read_text())


def checkpoint_names(out) -> list[str]:
    return sorted(p.name for p in (Path(out) / "checkpoints").iterdir())


def temporaries(out) -> list[Path]:
    return sorted(p for p in Path(out).rglob("*") if p.name.endswith(".tmp"))


def assert_same_weights(a, b) -> None:
    wa, wb = load_file(str(Path(a) / "model.safetensors")), load_file(str(Path(b) / "model.safetensors"))
    assert wa.keys() == wb.keys()
    for key in wa:
        assert torch.equal(wa[key], wb[key]), key


def assert_pairs_complete(out) -> None:
    names = checkpoint_names(out)
    weights = {n[:-len(".safetensors")] for n in names if n.endswith(".safetensors")}
    states = {n[:-len(".state.pt")] for n in names if n.endswith(".state.pt")}
    assert weights == states and weights, names


# ---------------------------------------------------------------------------------------- settings
def test_resume_keeps_the_runs_settings_and_refuses_other_ones(tiny_scene, tmp_path, capsys):
    """The issue's repro: a resume trains with the run's frames, seed and checkpoint interval, says
    its real preset in run.json, and ends bit-equal to an uninterrupted run; conflicting options
    are refused (exit 2, one line naming the flag, the run's value and the given one)."""
    out, ref = tmp_path / "run", tmp_path / "reference"
    run_args = ["--iterations", "6", "--generator-iterations", "1", "--frames", "0:2", "--ckpt-every", "2",
                "--seed", "7"]
    assert main(new_run(tiny_scene, out, *run_args, "--stop-after", "3")) == 0
    assert main(resume(out, "--stop-after", "5")) == 0
    err = capsys.readouterr().err
    assert "2 frames x 3 cameras, 1 G_img + 6 NeRF steps" in err and "resuming at step 3" in err
    info = info_of(out)
    train = info["train"]
    assert info["step"] == 5 and info["seed"] == 7 and info["generator_iterations"] == 1
    assert (train["preset"], train["seed"], train["frames"], train["ckpt_every"]) == ("tiny", 7, [0, 1], 2)
    assert (train["iterations"], train["generator_iterations"], train["perceptual"]) == (6, 1, "none")
    assert (train["log_every"], train["image_every"], train["stop_after"]) == (1, 0, 5)
    # the scene came from the run's record (relative to the run folder): recorded as the folder itself
    assert ".." not in train["scene"] and Path(train["scene"]).samefile(tiny_scene.root)
    assert info["model_config"]["schedule"]["iterations"] == 6
    assert info["overrides"] == [{"step": 3, "stop_after": [3, 5]}]
    # every 2 steps (the run's interval), not every 1000 (the option's default): 2, 3 (stop), 4, 5 (stop)
    assert checkpoint_names(out) == ["ckpt_4.safetensors", "ckpt_4.state.pt", "ckpt_5.safetensors",
                                     "ckpt_5.state.pt"]

    # options that change what the run is: refused, nothing written
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    refused = [(["--seed", "3"], "--seed 3", "seed 7"), (["--frames", "0:3"], "--frames 0,1,2", "frames 0,1"),
               (["--preset", "cpu_small"], "--preset cpu_small", "preset tiny"),
               (["--iterations", "9"], "--iterations 9", "iterations 6"),
               (["--generator-iterations", "0"], "--generator-iterations 0", "generator_iterations 1"),
               (["--init-generator", str(out / "model.safetensors")], "--init-generator", "init_generator None")]
    for flags, given, recorded in refused:
        assert main(resume(out, *flags)) == 2, flags
        lines = capsys.readouterr().err.strip().splitlines()
        assert len(lines) == 1 and "Traceback" not in lines[0], lines
        assert lines[0].startswith(f"garmentnerf: error: {given}") and f"trained with {recorded};" in lines[0], lines
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before

    # the run's own values are not a conflict; --ckpt-every is an override, recorded with its step
    assert main(resume(out, "--seed", "7", "--frames", "0:2", "--preset", "tiny", "--iterations", "6",
                       "--ckpt-every", "1", "--stop-after", "6")) == 0
    assert "settings from step 5: ckpt_every 2 -> 1, stop_after 5 -> 6" in capsys.readouterr().err
    info = info_of(out)
    assert info["step"] == 6 and info["train"]["ckpt_every"] == 1
    assert info["overrides"] == [{"step": 3, "stop_after": [3, 5]},
                                 {"step": 5, "ckpt_every": [2, 1], "stop_after": [5, 6]}]
    # a plain resume trains to the end (no --stop-after inherited), keeping the override
    assert main(resume(out)) == 0
    err = capsys.readouterr().err
    assert "finished at step 7/7" in err
    # the finish line says what other processes took of the machine meanwhile (garmentnerf.cpu_load)
    assert re.search(r"s/step; other processes used \d+\.\d of \d+ cores\); run:", err) or not LINUX, err
    info = info_of(out)
    assert info["step"] == 7 and info["train"]["ckpt_every"] == 1 and info["train"]["preset"] == "tiny"
    assert info["train"]["stop_after"] is None and len(info["overrides"]) == 2
    # the same run without interruption: the same weights (same seed, same frames)
    assert main(new_run(tiny_scene, ref, *run_args)) == 0
    assert info_of(ref)["step"] == 7
    assert_same_weights(out, ref)


def test_precision_is_chosen_once_recorded_and_kept_by_a_resume(tiny_scene, tmp_path, capsys, monkeypatch):
    """``--precision``: ``auto`` follows the machine (bfloat16 where AMX-BF16 makes it fast), the
    run records what it trains with, a resume keeps it and refuses another, and a run.json from
    before the setting means float32."""
    from garmentnerf.train.settings import training_precision

    for amx, want in ((True, "bfloat16"), (False, "float32")):
        monkeypatch.setattr(torch.cpu, "get_capabilities", lambda amx=amx: {"amx_bf16": amx})
        assert training_precision("auto", "cpu") == training_precision(None, "cpu") == want
        assert training_precision("float32", "cpu") == "float32"
    monkeypatch.undo()

    out, ref, plain = tmp_path / "run", tmp_path / "reference", tmp_path / "float32"
    run_args = ["--iterations", "4", "--generator-iterations", "1", "--frames", "0:2", "--ckpt-every", "1"]
    assert main(new_run(tiny_scene, out, *run_args, "--precision", "bfloat16", "--stop-after", "3")) == 0
    assert "MLP precision: bfloat16" in capsys.readouterr().err
    assert info_of(out)["train"]["precision"] == "bfloat16"
    assert main(resume(out, "--precision", "float32")) == 2
    line = capsys.readouterr().err.strip()
    assert line.startswith("garmentnerf: error: --precision float32") and "trained with precision bfloat16;" in line
    assert main(resume(out, "--precision", "bfloat16")) == 0
    assert info_of(out)["step"] == 5 and info_of(out)["train"]["precision"] == "bfloat16"
    # resumed or not, the same weights
    assert main(new_run(tiny_scene, ref, *run_args, "--precision", "bfloat16")) == 0
    assert_same_weights(out, ref)
    # a run from before the setting (no "precision" in run.json) trained in float32: a resume keeps
    # that, even where auto would now choose bfloat16
    assert main(new_run(tiny_scene, plain, *run_args, "--precision", "float32", "--stop-after", "3")) == 0
    info = info_of(plain)
    del info["train"]["precision"]
    (plain / "run.json").write_text(json.dumps(info))
    monkeypatch.setattr(torch.cpu, "get_capabilities", lambda: {"amx_bf16": True})
    capsys.readouterr()
    assert main(resume(plain, "--precision", "auto")) == 2
    assert "--precision bfloat16: the run" in capsys.readouterr().err
    assert main(resume(plain)) == 0
    assert info_of(plain)["step"] == 5 and info_of(plain)["train"]["precision"] == "float32"
    with pytest.raises(AssertionError):  # bfloat16 was used: the float32 run ends elsewhere
        assert_same_weights(out, plain)


# ---------------------------------------------------------------------------------------- full disk
@pytest.mark.parametrize("failing", ["ckpt_4.safetensors", "ckpt_4.state.pt", "run.json"])
def test_full_disk_is_one_line_and_leaves_no_partial_checkpoint(tiny_scene, tmp_path, capsys, monkeypatch, failing):
    """ENOSPC while the checkpoint of step 4 is written: exit 2, one line naming the checkpoint
    folder; no partial checkpoint, no temporary; after freeing space --resume finishes."""
    import garmentnerf.io_utils as io_module

    out = tmp_path / "run"
    real = io_module._write_synced
    seen = []

    def full_disk(path: Path, data: bytes) -> None:
        seen.append(path.name)
        step_4 = any(n.startswith(".ckpt_4.state.pt.") for n in seen)  # run.json: only step 4's
        if path.name.startswith(f".{failing}.") and (failing != "run.json" or step_4):
            path.write_bytes(data[:len(data) // 2])  # what a full disk leaves
            raise OSError(errno.ENOSPC, "No space left on device")
        real(path, data)

    monkeypatch.setattr(io_module, "_write_synced", full_disk)
    assert main(new_run(tiny_scene, out, "--iterations", "5", "--generator-iterations", "0", "--ckpt-every", "2",
                        "--seed", "3")) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    error = lines[-1]
    assert error.startswith(f"garmentnerf: error: {out / 'checkpoints'}: ") and "Traceback" not in error, lines
    assert "step 4" in error and "No space left on device" in error and "--resume" in error, error
    assert temporaries(out) == []
    if failing == "run.json":  # the checkpoint itself is complete: kept; the run files are step 2's
        assert "written but the run files" in error
        assert checkpoint_names(out) == ["ckpt_2.safetensors", "ckpt_2.state.pt", "ckpt_4.safetensors",
                                         "ckpt_4.state.pt"]
    else:
        assert failing in error and "nothing of it is kept, the newest checkpoint is step 2" in error
        assert checkpoint_names(out) == ["ckpt_2.safetensors", "ckpt_2.state.pt"]
    assert info_of(out)["step"] == 2
    monkeypatch.undo()  # space freed
    assert main(resume(out)) == 0
    err = capsys.readouterr().err
    assert f"resuming at step {4 if failing == 'run.json' else 2}" in err and "finished at step 5/5" in err
    info = info_of(out)
    assert info["step"] == 5 and info["train"]["seed"] == 3 and info["train"]["ckpt_every"] == 2
    assert temporaries(out) == []
    assert_pairs_complete(out)


# ---------------------------------------------------------------------------------------- damaged checkpoints
def test_unreadable_newest_checkpoint_falls_back_to_the_previous_one(tiny_scene, tmp_path, capsys):
    """A truncated newest checkpoint: a one-line notice naming it, the previous one is resumed
    (the run still ends bit-equal to an uninterrupted one); none readable: one-line error."""
    out, ref = tmp_path / "run", tmp_path / "reference"
    run_args = ["--iterations", "6", "--generator-iterations", "0", "--ckpt-every", "2", "--seed", "4"]
    assert main(new_run(tiny_scene, out, *run_args, "--stop-after", "4")) == 0
    newest = out / "checkpoints" / "ckpt_4.safetensors"
    newest.write_bytes(newest.read_bytes()[:1000])  # truncated (e.g. a copy cut short)
    capsys.readouterr()
    assert main(resume(out)) == 0
    lines = capsys.readouterr().err.strip().splitlines()
    notes = [line for line in lines if "skipping" in line]
    assert len(notes) == 1 and str(newest) in notes[0] and "trying the one of step 2" in notes[0], lines
    assert any("resuming at step 2" in line for line in lines) and info_of(out)["step"] == 6
    assert_pairs_complete(out)
    assert main(new_run(tiny_scene, ref, *run_args)) == 0
    assert_same_weights(out, ref)
    # nothing readable at all: one line naming the folder and each checkpoint
    for step in (4, 6):
        state = out / "checkpoints" / f"ckpt_{step}.state.pt"
        state.write_bytes(state.read_bytes()[:500])
    capsys.readouterr()
    assert main(resume(out)) == 2
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert error.startswith(f"garmentnerf: error: {out / 'checkpoints'}: no readable checkpoint"), error
    assert "ckpt_6.state.pt: unreadable" in error and "ckpt_4.state.pt: unreadable" in error


def test_stale_temporaries_of_killed_writes_are_removed_on_resume(tiny_scene, tmp_path, capsys):
    """Only the run's own temporaries (and half checkpoints beyond the resumed step) go."""
    out = tmp_path / "run"
    assert main(new_run(tiny_scene, out, "--iterations", "3", "--generator-iterations", "0", "--ckpt-every", "2",
                        "--stop-after", "2")) == 0
    ck = out / "checkpoints"
    stale = [out / ".run.json.k1l2m3n4.tmp", out / ".model.safetensors.abcd_123.tmp",
             ck / ".ckpt_4.safetensors.zz9yx8w7.tmp", ck / ".ckpt_4.state.pt.q1w2e3r4.tmp"]
    orphan = ck / "ckpt_4.safetensors"  # weights of a checkpoint whose state was never written
    mine = [out / "notes.tmp", out / ".notes.txt.abc.tmp", ck / "mine.txt", out / "tb" / ".x.tmp"]
    for p in (*stale, orphan, *mine):
        p.write_bytes(b"left over")
    capsys.readouterr()
    assert main(resume(out)) == 0
    err = capsys.readouterr().err
    assert "removed 4 temporary file(s) of interrupted writes" in err and "resuming at step 2" in err
    assert not any(p.exists() for p in (*stale, orphan)) and all(p.exists() for p in mine)
    assert checkpoint_names(out) == ["ckpt_2.safetensors", "ckpt_2.state.pt", "ckpt_3.safetensors",
                                     "ckpt_3.state.pt", "mine.txt"]
    assert info_of(out)["step"] == 3


# ---------------------------------------------------------------------------------------- kills
KILL_RUN = ["--iterations", "24", "--generator-iterations", "1", "--frames", "0:2", "--ckpt-every", "3",
            "--seed", "5"]


@pytest.fixture(scope="module")
def reference_run(tiny_scene, tmp_path_factory):
    """The kill tests' run, uninterrupted."""
    out = tmp_path_factory.mktemp("kill_reference") / "run"
    threads = torch.get_num_threads()
    try:
        assert main(new_run(tiny_scene, out, *KILL_RUN)) == 0
    finally:
        torch.set_num_threads(threads)
    return out


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.mark.parametrize("signame", ["SIGINT", "SIGTERM", "SIGKILL"])
def test_killed_training_resumes_with_the_runs_settings(tiny_scene, reference_run, tmp_path, capsys, signame):
    """``garmentnerf train`` in a subprocess gets a signal at a random (seeded) point after its
    first checkpoint; --resume continues from the newest checkpoint with the run's settings,
    finishes bit-equal to the uninterrupted run, and leaves no temporary file."""
    sig = getattr(signal, signame)
    out, log = tmp_path / "run", tmp_path / "stderr.txt"
    delay = random.Random(f"kill-{signame}").uniform(0.0, 0.8)
    with open(log, "wb") as stderr:
        # SIGINT at its default in the child, as in a terminal: a shell without job control (`pytest &`,
        # nohup) starts background commands with SIGINT ignored, and Python keeps it ignored
        proc = subprocess.Popen([sys.executable, "-m", "garmentnerf.cli.main",
                                 *new_run(tiny_scene, out, *KILL_RUN)], stdout=subprocess.DEVNULL, stderr=stderr,
                                preexec_fn=_default_sigint)
        try:
            deadline = time.monotonic() + 120
            while not (out / "run.json").exists():  # the first complete checkpoint
                assert proc.poll() is None, log.read_text()
                assert time.monotonic() < deadline, "no checkpoint within 120 s"
                time.sleep(0.02)
            time.sleep(delay)
            proc.send_signal(sig)
            rc = proc.wait(timeout=120)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    child_err = log.read_text()
    # the whole of the child's stderr on failure (a crash prints its Python stack there)
    assert rc == (-signal.SIGKILL if sig == signal.SIGKILL else 130), f"exit {rc}, stderr:\n{child_err}"
    assert "Traceback" not in child_err, child_err
    step, _, _ = latest_checkpoint(out)
    assert 1 <= step < 25  # the first checkpoint ends G_img pre-training (step 1)
    if sig != signal.SIGKILL:  # a checkpoint of the last completed step, and the run files with it
        assert f"interrupted: checkpoint of step {step} written" in child_err, child_err
        assert info_of(out)["step"] == step and temporaries(out) == []
    capsys.readouterr()
    assert main(resume(out)) == 0
    err = capsys.readouterr().err
    assert f"resuming at step {step}" in err and "2 frames x 3 cameras, 1 G_img + 24 NeRF steps" in err, err
    assert "finished at step 25/25" in err
    info = info_of(out)
    train = info["train"]
    assert info["step"] == 25 and info["seed"] == 5 and info["overrides"] == []
    assert (train["preset"], train["seed"], train["frames"], train["ckpt_every"]) == ("tiny", 5, [0, 1], 3)
    assert (train["iterations"], train["generator_iterations"]) == (24, 1)
    assert temporaries(out) == []
    assert_pairs_complete(out)
    assert checkpoint_names(out)[-2:] == ["ckpt_25.safetensors", "ckpt_25.state.pt"]
    assert_same_weights(out, reference_run)
