"""A run's checkpoints: their files (``checkpoints/ckpt_<step>.safetensors`` + ``.state.pt``), the
RNG states they hold, what a failed write says, and which of them are kept.

A checkpoint's state file holds ``step``, ``stage``, ``optimizer``, ``rng`` (:func:`rng_state`),
``generator_iterations``, ``model_config``, ``seed`` and ``world_size``; the weights file the
model's parameters (:func:`garmentnerf.runs.save_weights`). Complete means both files are
there; readable is checked by :func:`read_checkpoint_state` when a run resumes.
"""

from __future__ import annotations

import random
import re
from pathlib import Path

import numpy as np
import torch

from garmentnerf.train.run import CHECKPOINT_DIR

__all__ = ["CheckpointWriteError", "checkpoints", "latest_checkpoint", "checkpoint_files", "prune_checkpoints",
           "checkpoint_write_error", "read_checkpoint_state", "rng_state", "set_rng_state", "first_line"]

_CKPT = re.compile(r"^ckpt_(\d+)\.state\.pt$")
_CKPT_FILE = re.compile(r"^ckpt_(\d+)\.(?:safetensors|state\.pt)$")


class CheckpointWriteError(ValueError):
    """A checkpoint could not be written (full disk, no permission, ...): the machine's state, not
    a bug, so the command line prints it as one line. ``errno`` is the OS error's."""

    def __init__(self, message: str, errno: int | None = None):
        super().__init__(message)
        self.errno = errno


def checkpoint_files(run_dir, step: int) -> tuple[Path, Path]:
    """(weights, state) file paths of the checkpoint of ``step`` in a run folder."""
    folder = Path(run_dir) / CHECKPOINT_DIR
    return folder / f"ckpt_{step}.safetensors", folder / f"ckpt_{step}.state.pt"


def checkpoints(run_dir) -> list[tuple[int, Path, Path]]:
    """(step, weights, state) of every complete checkpoint of a run (both files there), newest
    first. Complete is not readable: :class:`Trainer` checks that when it resumes."""
    folder = Path(run_dir) / CHECKPOINT_DIR
    if not folder.is_dir():
        return []
    found = []
    for p in folder.iterdir():
        m = _CKPT.match(p.name)
        if m:
            step = int(m.group(1))
            weights = folder / f"ckpt_{step}.safetensors"
            if weights.is_file():
                found.append((step, weights, p))
    return sorted(found, reverse=True)


def latest_checkpoint(run_dir) -> tuple[int, Path, Path] | None:
    """(step, weights, state) of the newest complete checkpoint of a run, or None."""
    found = checkpoints(run_dir)
    return found[0] if found else None


def prune_checkpoints(run_dir, step: int, keep: int) -> None:
    """Keep the newest ``keep`` complete checkpoints up to ``step``; delete the older ones and the
    files of any other (beyond ``step``, or without its pair: left by a killed or failed run, or
    skipped as unreadable on resume)."""
    done = [s for s, _, _ in checkpoints(run_dir) if s <= step]
    kept = set(done[:keep])
    for path in (Path(run_dir) / CHECKPOINT_DIR).iterdir():
        m = _CKPT_FILE.match(path.name)
        if m and int(m.group(1)) not in kept:
            path.unlink(missing_ok=True)


def checkpoint_write_error(exc: OSError, run_dir: Path, step: int, complete: bool, writing: Path,
                           previous_step: int | None) -> CheckpointWriteError:
    """The one-line error of a failed checkpoint write.

    Args:
        exc: the OS error of the write.
        run_dir: the run folder.
        step: the step whose checkpoint was written.
        complete: whether the checkpoint itself was written (then the run files were not).
        writing: the file or folder being written.
        previous_step: the step of the newest checkpoint written before, or None.
    """
    folder = run_dir / CHECKPOINT_DIR
    reason = exc.strerror or first_line(exc)
    named = exc.filename if exc.filename is not None else writing.name
    if str(named) not in reason and Path(str(named)).name not in reason:
        reason = f"{named}: {reason}"
    if complete:
        what = (f"the checkpoint of step {step} is written but the run files in {run_dir} are not "
                f"({reason})")
    else:
        what = (f"cannot write the checkpoint of step {step} ({reason}); nothing of it is kept, "
                + (f"the newest checkpoint is step {previous_step}" if previous_step is not None
                   else "no checkpoint yet"))
    if complete or previous_step is not None:
        then = f"free space, then continue with 'garmentnerf train --out {run_dir} --resume'"
    else:
        then = f"free space, remove {run_dir} and start the run again"
    return CheckpointWriteError(f"{folder}: {what}; {then}", exc.errno)


def read_checkpoint_state(state_file: Path, step: int) -> dict:
    """The state dict of the checkpoint of ``step``; ValueError naming the file when it cannot be
    read, is not a checkpoint state or holds another step."""
    try:
        state = torch.load(state_file, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise ValueError(f"{state_file}: unreadable checkpoint state ({first_line(exc)})") from exc
    if not isinstance(state, dict) or not {"step", "optimizer", "rng"} <= set(state):
        raise ValueError(f"{state_file}: not a checkpoint state (no step, optimizer and rng)")
    if state.get("step") != step:
        raise ValueError(f"{state_file}: holds step {state.get('step')}, its name says {step}")
    return state


def rng_state() -> dict:
    """The python, numpy, torch (and CUDA) RNG states, as a checkpoint holds them."""
    np_state = np.random.get_state(legacy=False)
    state = {"python": random.getstate(), "torch": torch.get_rng_state(),
             "numpy": {"bit_generator": np_state["bit_generator"],
                       "key": torch.from_numpy(np.asarray(np_state["state"]["key"]).astype(np.int64)),
                       "pos": int(np_state["state"]["pos"]), "has_gauss": int(np_state["has_gauss"]),
                       "gauss": float(np_state["gauss"])}}
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict) -> None:
    """Restore the RNG states of :func:`rng_state`."""
    py = state["python"]
    random.setstate((py[0], tuple(py[1]), py[2]))
    torch.set_rng_state(state["torch"])
    n = state["numpy"]
    np.random.set_state({"bit_generator": n["bit_generator"],
                         "state": {"key": n["key"].numpy().astype(np.uint32), "pos": n["pos"]},
                         "has_gauss": n["has_gauss"], "gauss": n["gauss"]})
    if "cuda" in state and torch.cuda.is_available():
        try:
            torch.cuda.set_rng_state_all(state["cuda"])
        except (RuntimeError, IndexError):
            pass  # another GPU count: the trainer's own randomness is seeded per step anyway


def first_line(exc: BaseException) -> str:
    """The first line of an error's message (library errors can run over several)."""
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    return lines[0] if lines else type(exc).__name__
