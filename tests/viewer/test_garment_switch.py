"""The previewer's Garment menu: a bundled demo chosen in the window is loaded off the UI
thread and shown in place of the one shown, without a restart; the body, the motion and the camera stay."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from safetensors.torch import load_file, save_file


@pytest.fixture
def two_demos(untrained_run, tmp_path):
    """A demo root holding the tiny run as the "skirt" and, with its palette moved, as the "tshirt"."""
    from garmentnerf.demos import pack_demo

    root = tmp_path / "demo"
    pack_demo(untrained_run, "skirt", root)
    tshirt = pack_demo(untrained_run, "tshirt", root)
    weights = tshirt.run_dir / "model.safetensors"
    state = load_file(str(weights))
    state["palette.colors"] = (state["palette.colors"].float() * 0.5 + 0.25).to(state["palette.colors"].dtype)
    save_file(state, str(weights))
    return root


def test_the_window_switches_garment_without_a_restart(xvfb, two_demos, tmp_path):
    from PIL import Image

    from garmentnerf.runs import load_run
    from garmentnerf.viewer.app import App

    skirt = load_run(two_demos / "run")
    with App(motion=None, run=skirt, size=(320, 240), samples=0, vsync=False, playing=False,
             snapshot_dir=tmp_path / "shots", demo_root=two_demos) as viewer:
        view = viewer.neural_view
        assert viewer.garments.names() == ["skirt", "tshirt"] and viewer.garments.current == "skirt"
        assert viewer.wait_for_neural(180), view.error()
        viewer.set_frame(2)
        viewer.controller.set_azimuth(40.0)
        viewer.run_until(view.settled, 180)
        sequence, frame, camera = viewer.sequence, viewer.timeline.frame, viewer.view_camera(320, 240)
        before = np.asarray(Image.open(viewer.snapshot(96, 72)).convert("RGB")).astype(int)
        old_renderer = view.renderer

        viewer.switch_garment("tshirt")
        assert viewer.run_until(lambda: viewer.garments.current == "tshirt", 120), viewer.status.message()
        assert view.run.root == two_demos / "run_tshirt" and view.renderer is not old_renderer
        old_renderer.worker._thread.join(30)
        assert not old_renderer.worker._thread.is_alive()  # the old garment's worker ended (stopped off the UI thread)
        expected = load_file(str(two_demos / "run_tshirt" / "model.safetensors"))["palette.colors"].float().numpy()
        np.testing.assert_allclose(view.learned_palette, np.clip(expected, 0, 1), atol=1e-6)
        assert viewer.wait_for_neural(180), view.error()
        viewer.run_until(view.settled, 180)
        viewer.step()
        # the body, the motion, the frame and the camera stayed
        assert viewer.sequence is sequence and viewer.timeline.frame == frame
        now = viewer.view_camera(320, 240)
        assert np.array_equal(now.R, camera.R) and np.array_equal(now.t, camera.t) and np.array_equal(now.K, camera.K)
        assert view.shown is not None and view.shown.frame == frame and view.mode == "neural"
        after = np.asarray(Image.open(viewer.snapshot(96, 72)).convert("RGB")).astype(int)
        assert viewer.exports.exporter.run is view.run
        assert np.abs(after - before).max() > 10  # the new garment's palette shows
        assert viewer.stats()["neural"]["errors"] == 0


def test_a_garment_that_does_not_fit_the_body_or_motion_is_refused(untrained_run):
    from garmentnerf.runs import load_run
    from garmentnerf.viewer.garment_menu import check_switch

    run = load_run(untrained_run)
    assert check_switch(run, run, "train") == "" and check_switch(None, run, "walk") == ""
    other_body = dataclasses.replace(run, info={**run.info, "body": {"model": "anny", "shape": "thin"}})
    assert "is not the one shown" in check_switch(run, other_body, "train")
    seq = next(iter(run.scene.sequences))
    no_scene = dataclasses.replace(run, scene=None)
    assert f"no sequence '{seq}'" in check_switch(run, no_scene, seq)
    assert check_switch(run, no_scene, "walk") == ""  # a library motion plays on any run
