"""Watch a run while it trains: the newest checkpoint, loaded off the UI thread.

``garmentnerf view --run RUN`` on a run that is training shows each new checkpoint as it lands
(nerfstudio's and instant-ngp's everyday workflow). :class:`CheckpointWatcher` polls the run's
``checkpoints/`` folder on a thread of its own; a checkpoint newer than the weights shown
(complete: its weights and state files are both there, each written atomically by the trainer, so
a half-written file is never seen under its name) is loaded there into a *new* model
(:func:`load_checkpoint_run`: the run's config and body, the checkpoint's weights), and handed over
once by :meth:`CheckpointWatcher.poll`. The window then gives it to the render worker, which
switches between two renders (:meth:`garmentnerf.render.session.RenderSession.set_run`): the model
the worker was rendering with is never written to, so nothing renders half-updated weights, and an
export already running keeps the weights it started with.

A checkpoint that cannot be read (pruned by the trainer while being read, a damaged file) is
reported in :attr:`CheckpointWatcher.error` and tried again at the next poll.
"""

from __future__ import annotations

import dataclasses
import threading
from pathlib import Path

import torch

from garmentnerf.runs import build_model, load_weights
from garmentnerf.train.checkpoints import latest_checkpoint

#: Seconds between two looks at the run's checkpoints.
DEFAULT_POLL_SECONDS = 2.0


def load_checkpoint_run(run, weights: str | Path, step: int):
    """A :class:`~garmentnerf.runs.LoadedRun` like ``run`` but with a new model holding the
    weights file ``weights`` (a checkpoint of the run: the same config; body and projector shared
    with ``run``'s model, which is not touched) at training step ``step``.

    Raises:
        FileNotFoundError / ValueError (naming the file): missing, unreadable or mismatched weights.
    """
    palette_init = run.info.get("palette_init")
    model = build_model(run.config, torch.tensor(palette_init, dtype=torch.float32) if palette_init is not None else None,
                        run.model.body, run.model.projector)
    load_weights(weights, model)
    return dataclasses.replace(run, model=model.eval(), step=int(step))


class CheckpointWatcher:
    """Loads the newest checkpoint of ``run``'s folder on a background thread (module docstring).

    Args:
        run: the :class:`~garmentnerf.runs.LoadedRun` shown (its ``step`` is the weights' step).
        poll_seconds: time between two looks at the folder.
    Attributes:
        step: the step of the newest weights loaded (``run.step`` until a checkpoint is).
        error: the last checkpoint that could not be loaded, as one line ("" when none).
    """

    def __init__(self, run, poll_seconds: float = DEFAULT_POLL_SECONDS) -> None:
        if not poll_seconds > 0:
            raise ValueError(f"poll_seconds must be > 0, got {poll_seconds!r}")
        self.run = run
        self.poll_seconds = float(poll_seconds)
        self.step = int(run.step)
        self.error = ""
        self.loads = 0
        self._lock = threading.Lock()
        self._ready = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="garmentnerf-checkpoints", daemon=True)
        self._thread.start()

    def poll(self):
        """The newest checkpoint loaded since the last call (a LoadedRun), or None; thread-safe."""
        with self._lock:
            ready, self._ready = self._ready, None
        return ready

    def check(self) -> bool:
        """Look at the folder once (the thread does this every ``poll_seconds``); True when a newer
        checkpoint was loaded."""
        found = latest_checkpoint(self.run.root)
        if found is None or found[0] <= self.step:
            return False
        step, weights, _ = found
        try:
            loaded = load_checkpoint_run(self.run, weights, step)
        except (OSError, ValueError) as exc:
            self.error = f"checkpoint {step}: {' '.join(str(exc).split())}"
            return False
        with self._lock:
            self._ready = loaded
            self.step = step
            self.error = ""
            self.loads += 1
        return True

    def _loop(self) -> None:
        while not self._stop.wait(self.poll_seconds):
            try:
                self.check()
            except Exception as exc:  # noqa: BLE001 - a watcher must not take the window down
                self.error = f"{type(exc).__name__}: {exc}"

    def close(self, timeout: float = 5.0) -> None:
        self._stop.set()
        self._thread.join(timeout)


__all__ = ["CheckpointWatcher", "load_checkpoint_run", "DEFAULT_POLL_SECONDS"]
