"""Shared pytest fixtures."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session", autouse=True)
def _own_cache_dir(tmp_path_factory):
    """What the package caches under the user's cache folder (measured height bands,
    :mod:`garmentnerf.render.band_cache`) goes to a folder of the test session instead (commands the
    tests run in subprocesses inherit it)."""
    import os

    old = os.environ.get("GARMENTNERF_CACHE_DIR")
    os.environ["GARMENTNERF_CACHE_DIR"] = str(tmp_path_factory.mktemp("garmentnerf_cache"))
    yield
    if old is None:
        os.environ.pop("GARMENTNERF_CACHE_DIR", None)
    else:
        os.environ["GARMENTNERF_CACHE_DIR"] = old


@pytest.fixture(scope="session")
def gl_context():
    """A headless (EGL) moderngl context for the whole session; skips when none can be made."""
    from garmentnerf.gl.context import GLUnavailableError, create_context

    try:
        ctx = create_context(headless=True)
    except GLUnavailableError as exc:
        pytest.skip(f"no headless OpenGL: {exc}")
    yield ctx
    ctx.release()


@pytest.fixture(scope="session")
def body():
    """The bundled default body (float32); tests that need another one define their own."""
    from garmentnerf.body.model import BodyModel

    return BodyModel.default()


@pytest.fixture(scope="session")
def projector(body):
    """The body-point projector of the default body (its KD-tree is built once per session)."""
    from garmentnerf.geometry.body_points import BodyPointProjector

    return BodyPointProjector(body)


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory, gl_context):
    """A small unsimulated scene (garment rigidly skinned to the body, :mod:`garmentnerf.data.synthetic`):
    skirt on 3 walk frames, 3 training cameras + 1 held out + 2 references at 64 x 64."""
    from garmentnerf.data.synthetic import make_rigged_scene

    return make_rigged_scene(tmp_path_factory.mktemp("tiny_scene") / "scene", garment="skirt", motion="walk",
                             frames=3, views=3, size=64, held_out_views=1, gl_context=gl_context)


@pytest.fixture
def one_torch_thread():
    """Run the test with one torch thread (training compares runs bit for bit)."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def walk_clip(body):
    """The first three frames of the walk posed on the default body, and the walk's frame rate."""
    from garmentnerf.motion.library import load_motion

    motion = load_motion("walk", body)
    return motion.slice(0, 3).pose(body), motion.fps


@pytest.fixture(scope="module")
def walk_inputs(gl_context, body, walk_clip):
    """The :class:`~garmentnerf.model.frame_context.FrameInputs` of frame 2 of ``walk_clip`` for the
    tiny preset seen by the default reference cameras."""
    from garmentnerf.data.cameras import reference_cameras
    from garmentnerf.model.config import ModelConfig
    from garmentnerf.render.frame_inputs import FrameInputBuilder

    posed, fps = walk_clip
    with FrameInputBuilder(gl_context, body, reference_cameras(), ModelConfig.tiny()) as builder:
        yield builder.build(posed, 2, fps)
