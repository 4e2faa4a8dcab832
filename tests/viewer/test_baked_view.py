"""The window draws a baked frame from a camera no capture stood at, composed in its shader as compose()
composes the bake's maps, and a recolour shows exactly in the next UI frame."""

from __future__ import annotations

import numpy as np
import pytest
import torch


@pytest.fixture(scope="module")
def skirt_bake(gl_context, tmp_path_factory):
    """The bundled skirt and a bake folder holding its frame 0 (draft preset)."""
    from garmentnerf.bake.capture import capture_frame
    from garmentnerf.bake.settings import BAKE_PRESETS
    from garmentnerf.bake.clip import manifest_for_session, prepare_folder
    from garmentnerf.demos import demo
    from garmentnerf.render.session import RenderSession
    from garmentnerf.runs import load_run

    run = load_run(demo("skirt").run_dir)
    session = RenderSession(run, gl_context)
    try:
        settings = BAKE_PRESETS["draft"]
        folder = prepare_folder(tmp_path_factory.mktemp("bake") / "b", manifest_for_session(session, settings),
                                session.body.faces.numpy())
        folder.save_frame(capture_frame(session, 0, settings))
        yield run, folder
    finally:
        session.close()


def test_the_window_draws_and_recolours_a_baked_frame_as_compose_does(xvfb, gl_context, skirt_bake):
    from garmentnerf.bake.draw import BakeDrawer, baked_maps
    from garmentnerf.render.session import RenderSession
    from garmentnerf.viewer.app import App

    run, folder = skirt_bake
    size = (320, 240)
    with App(motion=None, run=run, size=size, samples=0, vsync=False, playing=False, dynamic_scene=False) as app:
        app.show_ui = False
        view = app.neural_view
        view.show_bakes(folder)
        assert app.run_until(lambda: view.bakes.get(0) is not None, 60)
        app.controller.set_azimuth(37.0)  # between two of the 8 captures
        app.step()
        app.step()
        assert view.showing_bake == "bake" and app.scene.baked_layer.showing
        camera = app.view_camera(*app.window.framebuffer_size)
        shown = app.read_framebuffer().astype(np.float64) / 255.0

        session = RenderSession(run, gl_context)
        drawer = BakeDrawer(gl_context, mesh_step=app.scene.baked_layer.drawer.mesh_step)  # the window's meshes
        try:
            maps = baked_maps(drawer, session, folder.load_frame(0), camera)
            palette = torch.as_tensor(view.palette)
            with torch.no_grad():
                want = maps.compose(palette, (0.0, 0.0, 0.0))[0].permute(1, 2, 0).numpy()
            opaque = maps.mask[0, 0].numpy() > 0.99  # the garment alone decides these pixels
            assert opaque.sum() > 500
            assert np.abs(shown[opaque] - want[opaque]).mean() < 2.0 / 255

            view.set_palette_color(0, (0.9, 0.1, 0.1))  # recolour: the next UI frame shows it
            app.step()
            shown = app.read_framebuffer().astype(np.float64) / 255.0
            with torch.no_grad():
                want = maps.compose(torch.as_tensor(view.palette), (0.0, 0.0, 0.0))[0].permute(1, 2, 0).numpy()
            assert np.abs(shown[opaque] - want[opaque]).mean() < 2.0 / 255
            assert want[opaque][:, 0].mean() > 3 * want[opaque][:, 2].mean()  # red now
        finally:
            drawer.release()
            session.close()
