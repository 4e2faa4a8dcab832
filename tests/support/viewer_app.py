"""The previewer opened the way the window tests of ``tests/viewer`` use it (not a test itself)."""

from __future__ import annotations

from contextlib import contextmanager


@contextmanager
def small_neural_app(run, folder, snapshot_size):
    """A paused 240 x 180 previewer on ``run`` (multisampling and vsync off), stepped once, exporting
    into ``folder`` at ``snapshot_size``; closed on exit. Needs a display (the ``xvfb`` fixture)."""
    from garmentnerf.viewer.app import App

    with App(motion=None, run=run, size=(240, 180), samples=0, vsync=False, playing=False,
             snapshot_dir=folder, snapshot_size=snapshot_size) as viewer:
        viewer.step()
        yield viewer
