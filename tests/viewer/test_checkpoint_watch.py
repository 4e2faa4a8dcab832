"""Watching a run while it trains: a checkpoint written atomically beside a running
watcher is loaded off the UI thread into a new model, and the neural view renders with it."""

from __future__ import annotations

import shutil
import time

import numpy as np
import pytest
import torch


def _write_checkpoint(run_dir, model, step: int) -> None:
    """What the trainer writes (:meth:`Trainer.save_checkpoint`): the weights, then the state, each atomically."""
    from garmentnerf.io_utils import write_file_atomic
    from garmentnerf.runs import save_weights
    from garmentnerf.train.checkpoints import checkpoint_files

    weights, state = checkpoint_files(run_dir, step)
    weights.parent.mkdir(parents=True, exist_ok=True)
    save_weights(weights, model, {"step": step})
    write_file_atomic(state, b"optimiser state (not read by the viewer)")


def _trained_further(run, seed: int):
    """The run's model with its palette and MLP moved (a stand-in for more training)."""
    from garmentnerf.runs import build_model

    model = build_model(run.config, torch.tensor(run.info["palette_init"]), run.model.body, run.model.projector)
    model.load_state_dict(run.model.state_dict())
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in model.named_parameters():
            if name.startswith("palette"):
                p.add_(0.3)
            elif p.dim() == 2:
                p.add_(0.05 * torch.randn(p.shape, generator=gen))
    return model


@pytest.fixture
def run_copy(untrained_run, tmp_path):
    from garmentnerf.runs import load_run

    root = tmp_path / "run"
    shutil.copytree(untrained_run, root)
    return load_run(root)


def _wait(predicate, timeout=60.0):
    deadline = time.monotonic() + timeout
    while not predicate() and time.monotonic() < deadline:
        time.sleep(0.02)
    return predicate()


def test_the_watcher_loads_a_checkpoint_written_atomically_beside_it(run_copy):
    from garmentnerf.viewer.checkpoint_watch import CheckpointWatcher

    run = run_copy
    before = {k: v.clone() for k, v in run.model.state_dict().items()}
    watcher = CheckpointWatcher(run, poll_seconds=0.05)
    try:
        time.sleep(0.3)
        assert watcher.poll() is None and watcher.step == run.step == 0  # no checkpoint yet
        # a half-written file under the trainer's temporary name, and weights without their state: not taken
        folder = run.root / "checkpoints"
        folder.mkdir()
        (folder / ".ckpt_9.safetensors.1a2b.tmp").write_bytes(b"half a file")
        (folder / "ckpt_8.safetensors").write_bytes(b"weights still being followed by their state")
        time.sleep(0.3)
        assert watcher.poll() is None and watcher.error == ""
        (folder / "ckpt_8.safetensors").unlink()
        newer = _trained_further(run, seed=1)
        _write_checkpoint(run.root, newer, 7)
        assert _wait(lambda: watcher.loads == 1), watcher.error
        loaded = watcher.poll()
        assert loaded is not None and loaded.step == 7 and watcher.step == 7 and watcher.poll() is None
        assert loaded.model is not run.model and loaded.config == run.config and loaded.root == run.root
        for key, value in newer.state_dict().items():  # the checkpoint's weights, bit for bit
            assert torch.equal(loaded.model.state_dict()[key], value), key
        for key, value in run.model.state_dict().items():  # the model being rendered is not touched
            assert torch.equal(value, before[key]), key
        assert not torch.equal(loaded.palette(), run.palette())
        # an older checkpoint is ignored; a damaged newer one is reported and skipped
        _write_checkpoint(run.root, newer, 5)
        (folder / "ckpt_11.safetensors").write_bytes(b"damaged")
        (folder / "ckpt_11.state.pt").write_bytes(b"state")
        assert _wait(lambda: "checkpoint 11" in watcher.error), watcher.error
        assert watcher.poll() is None and watcher.step == 7
    finally:
        watcher.close()


def test_the_neural_view_shows_the_new_checkpoint(gl_context, run_copy):
    """A running view with a watcher: the checkpoint is taken over at the next UI update (no
    waiting on the UI thread), the rendered-ahead frames of the old weights are dropped, and the
    image shown afterwards comes from the new weights (and the new learned palette)."""
    from garmentnerf.conventions import orbit_camera
    from garmentnerf.viewer.neural_view import NeuralView
    from garmentnerf.viewer.scene_gl import SceneRenderer
    from garmentnerf.viewer.timeline import Timeline

    run = run_copy
    scene = SceneRenderer(gl_context, samples=0)
    messages = []
    view = NeuralView(scene, run, None, messages.append, time.perf_counter, watch=True)
    view.watcher.poll_seconds = 0.05
    view.quality.dynamic = False
    view.quality.set_preset("interactive")
    timeline = Timeline(num_frames=3, fps=30.0)
    camera = orbit_camera(0.0, 5.0, 3.0, width=64, height=48)

    def settle():
        view.update(camera, timeline)
        assert _wait(lambda: (view.update(camera, timeline), view.settled())[1], 180), view.error()
        view.update(camera, timeline)

    try:
        settle()
        old_key = view.renderer.finished.view
        assert view.shown.weights_step == 0 and view.renderer.finished.frames(old_key) == {0, 1, 2}
        old_image = scene.render_image(camera, samples=0).astype(int)
        _write_checkpoint(run.root, _trained_further(run, seed=2), 40)
        assert _wait(lambda: view.watcher.loads == 1), view.watcher.error
        start = time.perf_counter()
        view.update(camera, timeline)  # takes it over: the UI thread only hands it on
        assert time.perf_counter() - start < 0.5
        assert view.weights_step == 40 and any("step 40" in m for m in messages)
        assert view.renderer.finished.view != old_key  # another view key: the old frames are gone
        settle()
        assert view.shown.weights_step == 40 and view.renderer.stats.errors == 0
        np.testing.assert_allclose(view.learned_palette, view.run.palette().numpy())
        np.testing.assert_allclose(view.palette, view.learned_palette)  # unedited: follows the learned one
        assert np.abs(scene.render_image(camera, samples=0).astype(int) - old_image).max() > 10
        assert view.run.model is not run.model and run.step == 0  # the first model was not written to
    finally:
        view.stop()
        scene.release()


def test_the_window_watches_the_run_and_snapshots_use_the_new_checkpoint(xvfb, run_copy, tmp_path):
    """``garmentnerf view --run RUN`` (App(watch=True)): a checkpoint landing while the window runs
    is shown without restarting it, the overlay's figures name its step, and a snapshot taken
    afterwards renders with it (the export thread switches to the new weights)."""
    from PIL import Image

    from garmentnerf.viewer.app import App

    run = run_copy
    with App(motion=None, run=run, size=(320, 240), samples=0, vsync=False, playing=False,
             snapshot_dir=tmp_path / "shots", watch=True) as viewer:
        view = viewer.neural_view
        view.watcher.poll_seconds = 0.05
        assert viewer.wait_for_neural(180), view.error()
        before = np.asarray(Image.open(viewer.snapshot(96, 72)).convert("RGB")).astype(int)
        assert viewer.exports.exporter.run is run
        _write_checkpoint(run.root, _trained_further(run, seed=3), 12)
        assert viewer.run_until(lambda: view.weights_step == 12, 60)
        assert "step 12" in viewer.status.message()
        viewer.run_until(view.settled, 180)
        viewer.step()
        stats = viewer.stats()["neural"]
        assert stats["weights_step"] == stats["shown_step"] == 12 and stats["errors"] == 0
        after = np.asarray(Image.open(viewer.snapshot(96, 72)).convert("RGB")).astype(int)
        assert viewer.exports.exporter.run is view.run and view.run.step == 12
        assert np.abs(after - before).max() > 10
