"""Playback you can watch: which frame the worker renders while the clip plays, the
render-ahead cache of finished frames, and the worker's standing requests.

Pure scheduling first (analytic cases), then the cache and the palette layer's partial upload,
then the real :class:`~garmentnerf.viewer.worker.NeuralRenderer` and
:class:`~garmentnerf.viewer.neural_view.NeuralView` on the tiny untrained run (headless GL, no
window), with the model's render counted by a wrapper around the real
:meth:`RenderSession.render <garmentnerf.render.session.RenderSession.render>`.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from garmentnerf.viewer.finished_frames import FarthestAheadOfPlayhead, FinishedFrames, result_nbytes
from garmentnerf.viewer.playback import (
    PlayheadClock,
    RenderTime,
    frame_of,
    frames_ahead,
    frames_behind,
    next_unrendered,
    predict_target_frame,
    render_superseded,
    replaces_shown,
    wrap_position,
)
from garmentnerf.viewer.timeline import Timeline
from garmentnerf.viewer.worker import NOTHING, NeuralResult, RenderWorker


# ==== scheduling (pure) =================================================================================
def test_predict_target_frame_is_where_the_playhead_will_be():
    # 10.2 frames + 30 fps x 0.5 s = 25.2 -> frame 25
    assert predict_target_frame(10.2, 30.0, 0.5, 100, loop=True) == 25
    # a 20-frame loop wraps: 25.2 mod 20 = 5.2; without looping the clip stops on its last frame
    assert predict_target_frame(10.2, 30.0, 0.5, 20, loop=True) == 5
    assert predict_target_frame(10.2, 30.0, 0.5, 20, loop=False) == 19
    # paused, nothing measured yet, a nonsense duration: the playhead's own frame
    assert predict_target_frame(10.2, 0.0, 0.5, 20, loop=True) == 10
    assert predict_target_frame(10.2, 30.0, 0.0, 20, loop=True) == 10
    assert predict_target_frame(10.2, 30.0, float("nan"), 20, loop=True) == 10
    # double speed (60 frames/s) and a render of 1/60 s: exactly one frame on
    assert predict_target_frame(3.0, 60.0, 1.0 / 60.0, 20, loop=True) == 4
    # several loops ahead: 0 + 30 x 2.05 = 61.5 -> 61 mod 20 = 1
    assert predict_target_frame(0.0, 30.0, 2.05, 20, loop=True) == 1


def test_frame_arithmetic_round_the_loop():
    assert wrap_position(-0.5, 10, loop=True) == pytest.approx(9.5)
    assert wrap_position(12.25, 10, loop=False) == 9.0 and wrap_position(-3.0, 10, loop=False) == 0.0
    assert frame_of(9.999, 10, loop=True) == 9 and frame_of(10.0, 10, loop=True) == 0
    assert frames_ahead(2, 8, 10, loop=True) == 4 and frames_ahead(8, 8, 10, loop=True) == 0
    assert frames_ahead(2, 8, 10, loop=False) == -6
    assert frames_behind(5, 8, 10, loop=True) == 3 and frames_behind(8, 5, 10, loop=True) == 0
    assert frames_behind(9, 1, 10, loop=True) == 2  # the playhead wrapped past frame 9
    assert frames_behind(9, 1, 10, loop=False) == 0 and frames_behind(1, 9, 10, loop=False) == 8


def test_next_unrendered_wraps_only_when_looping():
    done = {3, 4, 5, 0}
    assert next_unrendered(3, done, 8, loop=True) == 6
    assert next_unrendered(3, set(), 8, loop=True) == 3
    assert next_unrendered(6, {6, 7, 0}, 8, loop=True) == 1  # 6, 7 done, wraps to 0 (done), then 1
    assert next_unrendered(6, {6, 7}, 8, loop=True) == 0
    assert next_unrendered(6, {6, 7}, 8, loop=False) is None
    assert next_unrendered(0, set(range(8)), 8, loop=True) is None
    assert next_unrendered(42, set(), 8, loop=False) == 7  # clamped into the clip


def test_a_render_is_superseded_only_when_it_can_no_longer_be_shown():
    # another view: always
    assert render_superseded(10, False, 10, 30.0, 1.0, 100, True)
    # paused: another frame supersedes, the same one does not
    assert render_superseded(10, True, 11, 0.0, 1.0, 100, True)
    assert not render_superseded(10, True, 10, 0.0, 1.0, 100, True)
    # playing, render time 0.5 s at 30 fps = 15 frames: a render 10 frames late is finished,
    # one the playhead left 17 frames behind (a seek) is not
    assert not render_superseded(10, True, 20, 30.0, 0.5, 100, True)
    assert not render_superseded(10, True, 26, 30.0, 0.5, 100, True)  # 16 = 15 + 1: still kept
    assert render_superseded(10, True, 27, 30.0, 0.5, 100, True)
    # a frame ahead of the playhead is what render-ahead is for
    assert not render_superseded(40, True, 20, 30.0, 0.5, 100, True)
    # round the loop, 30 x 0.2 + 1 = 7 frames allowed: target 98, the playhead wrapped to 3 (5 behind)
    # is late, to 6 (8 behind) a seek
    assert not render_superseded(98, True, 3, 30.0, 0.2, 100, True)
    assert render_superseded(98, True, 6, 30.0, 0.2, 100, True)


def test_playhead_clock_extrapolates_and_notices_seeks():
    clock = PlayheadClock(position=10.0, time=100.0, fps=30.0, n_frames=50, loop=True)
    assert clock.playing and clock.frame == 10
    assert clock.position_at(100.5) == pytest.approx(25.0)
    assert clock.frame_at(101.5) == 5  # 10 + 45 = 55 -> 5
    assert clock.position_at(99.0) == pytest.approx(10.0)  # never backwards
    # the timeline 1 s later at 40.5 frames: on time; at 45: a seek; another rate: a change
    assert not clock.drifted(PlayheadClock(40.5, 101.0, 30.0, 50, True))
    assert clock.drifted(PlayheadClock(45.0, 101.0, 30.0, 50, True))
    assert clock.drifted(PlayheadClock(40.0, 101.0, 60.0, 50, True))
    # round the loop: expected 49.5 at t = 101.318.., the timeline shows 0.2 -> 0.7 frames apart
    assert not clock.drifted(PlayheadClock(0.2, 100.0 + 39.5 / 30.0, 30.0, 50, True))
    paused = PlayheadClock(7.4, 0.0, 0.0, 50, True)
    assert not paused.playing and paused.position_at(1e6) == pytest.approx(7.4)
    assert not paused.drifted(PlayheadClock(7.0, 5.0, 0.0, 50, True))
    assert paused.drifted(PlayheadClock(8.0, 5.0, 0.0, 50, True))
    assert paused.drifted(clock)  # play state changed
    tl = Timeline(num_frames=50, fps=30.0, playing=True)
    tl.set_speed(2.0)
    tl.set_frame(12)
    assert PlayheadClock.of(tl, 3.0) == PlayheadClock(12.0, 3.0, 60.0, 50, True)
    tl.pause()
    assert PlayheadClock.of(tl, 3.0).fps == 0.0


def test_render_time_is_a_moving_average():
    rt = RenderTime(smoothing=0.5)
    assert rt.seconds == 0.0
    rt.observe(1.0)
    assert rt.seconds == 1.0
    rt.observe(2.0)
    assert rt.seconds == 1.5
    rt.observe(float("nan"))
    rt.observe(-1.0)
    assert rt.seconds == 1.5 and rt.measured == 2
    # cold renders (the frame's features computed too) are averaged apart; until one is measured a
    # kind takes the other's figure
    assert rt.expected(cold=True) == 1.5 and rt.expected(cold=False) == 1.5
    rt.observe(4.0, cold=True)
    rt.observe(2.0, cold=True)
    assert rt.cold_seconds == 3.0 and rt.cold_measured == 2 and rt.seconds == 1.5
    assert rt.expected(cold=True) == 3.0 and rt.expected(cold=False) == 1.5
    fresh = RenderTime()
    fresh.observe(2.0, cold=True)
    assert fresh.expected(cold=False) == 2.0 and fresh.measured == 0


def test_timeline_waits_on_a_frame_when_told():
    tl = Timeline(num_frames=10, fps=10.0, playing=True)
    tl.set_frame(3)
    assert not tl.advance(0.55, max_frames=0) and tl.frame == 3 and tl.position < 4.0  # held on frame 3
    assert tl.advance(0.55, max_frames=1) and tl.frame == 4  # 5.5 frames of time, one frame allowed
    assert tl.position == pytest.approx(5.0, abs=1e-5) and tl.position < 5.0  # just before frame 5
    assert tl.advance(0.55) and tl.frame == 0  # no limit: + 5.5 frames = 10.49.. wraps to 0.49


# ==== the render-ahead cache (pure) ====================================================================
def _result(frame: int, nbytes: int, key="view") -> NeuralResult:
    """A finished frame whose maps take ``nbytes`` bytes (float16, 1 x 1 pixel layers)."""
    layers = np.zeros((nbytes // 8, 1, 1, 4), np.float16)
    return NeuralResult(layers, np.zeros((0, 0), np.float32), (1, 1), (1, 1), 1.0, frame, {}, True, view_key=key)


def test_finished_frames_respect_their_memory_bound_and_keep_the_frames_just_ahead():
    mb = 2**20
    cache = FinishedFrames(budget_mb=3.5)  # 3.5 frames of 1 MiB
    cache.set_view("v")
    assert result_nbytes(_result(0, mb)) == mb
    for f in range(10):
        cache.put("v", f, _result(f, mb), playhead_frame=0, n_frames=10)
        assert cache.nbytes <= cache.budget_bytes
    assert cache.frames("v") == {0, 1, 2}  # nearest ahead of the playhead
    # the playhead at 8: ahead of it come 8, 9, then 0, 1 (looping)
    for f in (8, 9):
        cache.put("v", f, _result(f, mb), playhead_frame=8, n_frames=10)
    assert cache.frames("v") == {8, 9, 0} and cache.nbytes == 3 * mb
    assert not cache.worth_rendering(1, 8, 10)  # full, and 1 lies farther ahead than 0
    assert cache.worth_rendering(1, 9, 10)  # playhead at 9: 8 is farthest ahead now, 1 is nearer
    assert not cache.worth_rendering(5, 8, 10)
    cache.set_budget_mb(1.0)
    assert cache.nbytes <= cache.budget_bytes and len(cache.frames("v")) == 1
    cache.set_budget_mb(0.0)
    assert cache.frames("v") == set() and not cache.worth_rendering(3, 0, 10)


def test_the_eviction_order_is_farthest_ahead_of_the_playhead_round_the_clip():
    assert FarthestAheadOfPlayhead(5, 10)([4, 5, 6, 9]) == [4, 9, 6, 5]  # 4 is the last frame reached again
    # a frame past the clip's end (a longer clip's) counts the clip as long as it needs
    assert FarthestAheadOfPlayhead(1, 3)([0, 1, 2, 5]) == [0, 5, 2, 1]


def test_finished_frames_hold_one_view():
    cache = FinishedFrames(budget_mb=10.0)
    assert cache.set_view("a")
    cache.put("a", 1, _result(1, 64, "a"), 0, 5)
    assert not cache.put("b", 2, _result(2, 64, "b"), 0, 5)  # another view's result is not kept
    assert cache.get("a", 1) is not None and cache.get("b", 1) is None and cache.frames("b") == set()
    assert not cache.set_view("a") and cache.frames("a") == {1}  # the same view: nothing dropped
    assert cache.set_view("b") and cache.frames("a") == set() and cache.nbytes == 0 and cache.invalidations == 1


# ==== the palette layer's partial upload ==================================================================
def test_a_cut_out_rectangle_uploads_to_the_same_textures_as_the_whole_maps(gl_context):
    from garmentnerf.gl.context import make_current
    from garmentnerf.viewer.palette_layer import PaletteLayer, crop_to_content

    rng = np.random.default_rng(0)
    H, W = 24, 32

    def maps(y0, y1, x0, x1):
        layers = np.zeros((4, H, W, 4), np.float32)
        layers[1, ..., :2] = 0.5  # empty maps: uniform blend weights (DecomposedMaps.placed)
        depth = np.zeros((H, W), np.float32)
        layers[:, y0:y1, x0:x1] = rng.uniform(0.1, 1.0, (4, y1 - y0, x1 - x0, 4))
        depth[y0:y1, x0:x1] = 3.0
        return layers, depth

    make_current(gl_context)  # a window test may have left its own context current
    layer = PaletteLayer(gl_context)
    try:
        for box in ((2, 20, 3, 12), (10, 14, 20, 30), (0, 24, 0, 32), (5, 6, 5, 6)):
            layers, depth = maps(*box)
            cut, cut_depth, origin = crop_to_content(layers, depth)
            assert origin == (box[2], box[0]) and cut.shape == (4, box[1] - box[0], box[3] - box[2], 4)
            layer.submit(cut.astype(np.float16), cut_depth, (W, H), origin=origin, map_size=(W, H))
            layer.prepare()
            tex = layer.maps_tex
            assert tex.dtype == "f2" and layer.map_size == (W, H)  # half floats are uploaded as they are kept
            cw, ch = tex.width, tex.height  # the textures' capacity (grown in steps, never shrunk)
            got = np.frombuffer(tex.read(), np.float16).reshape(4, ch, cw, 4)[:, :H, :W].astype(np.float32)
            # what was shown before is gone, the new rectangle is there (float16-rounded)
            np.testing.assert_allclose(got, layers.astype(np.float16).astype(np.float32), rtol=0, atol=0)
            got_depth = np.frombuffer(layer.depth_tex.read(), np.float32).reshape(ch, cw)[:H, :W]
            np.testing.assert_array_equal(got_depth, depth)
        # a slightly smaller frame (another frame of the clip) keeps the textures
        tex = layer.maps_tex
        layer.submit(cut.astype(np.float16), cut_depth, (W, H), origin=(0, 0), map_size=(W - 3, H - 2))
        layer.prepare()
        assert layer.maps_tex is tex and layer.map_size == (W - 3, H - 2)
        blank, _ = maps(0, 0, 0, 0)
        empty = crop_to_content(blank, np.zeros((H, W), np.float32))
        assert empty[0].shape == (4, 1, 1, 4) and empty[2] == (0, 0)
        with pytest.raises(ValueError, match="does not fit"):
            layer.submit(cut, cut_depth, (W, H), origin=(W, 0), map_size=(W, H))
    finally:
        layer.release()


# ==== the worker's standing requests ========================================================================
def test_a_standing_request_renders_until_its_follow_up_ends_it_and_a_late_render_is_finished():
    rendered, delivered = [], []
    todo = [3, 2, 1]  # what the standing request still has to render

    def render(request, generation):
        if not todo:
            return NOTHING
        frame = todo.pop()
        rendered.append(frame)
        for _ in range(10):
            time.sleep(0.02)
            if worker.should_cancel(generation):
                return None
        return frame

    worker = RenderWorker(render, lambda result, request, gen: delivered.append((request, result)),
                          superseded=lambda running, newest: newest == "seek",
                          follow_up=lambda request: 0.0 if todo else None)
    try:
        worker.request("play")
        deadline = time.monotonic() + 5
        while not worker.quiet() and time.monotonic() < deadline:
            time.sleep(0.01)
        assert delivered == [("play", 1), ("play", 2), ("play", 3)]
        assert worker.idle() and worker.quiet()
        assert (worker.stats.started, worker.stats.renders, worker.stats.abandoned) == (3, 3, 0)
        # a newer request that does not supersede (same view, playhead moved a little): the render finishes
        todo[:] = [5, 4]
        worker.request("play")
        time.sleep(0.06)
        worker.request("play, a bit later")
        assert worker.wait_idle(5)
        deadline = time.monotonic() + 5
        while not worker.quiet() and time.monotonic() < deadline:
            time.sleep(0.01)
        assert worker.stats.abandoned == 0 and [r for _, r in delivered[3:]] == [4, 5]
        # one that does (a seek): abandoned between chunks
        todo[:] = [7, 6]
        worker.request("play")
        time.sleep(0.06)
        worker.request("seek")
        deadline = time.monotonic() + 5
        while not worker.quiet() and time.monotonic() < deadline:
            time.sleep(0.01)
        assert worker.stats.abandoned == 1 and delivered[-1] == ("seek", 7)
        assert worker.stats.completed_share == pytest.approx(worker.stats.renders / worker.stats.started)
    finally:
        worker.stop()



def test_a_playing_clip_shows_the_finished_frame_nearest_behind_the_playhead():
    """What the window shows while the playhead is on a frame not rendered: the nearest finished
    one behind it (or on it), never one ahead; looping, up to half a clip back across the wrap."""
    cache = FinishedFrames(budget_mb=10.0)
    cache.set_view("v")
    for f in (3, 10, 40):
        cache.put("v", f, _result(f, 64, "v"), 0, 50)
    frame = lambda head, loop=True: getattr(cache.latest_behind("v", head, 50, loop), "frame", None)  # noqa: E731
    assert frame(12) == 10 and frame(10) == 10 and frame(9) == 3 and frame(3) == 3 and frame(30) == 10
    assert frame(2) == 40  # looping: 12 frames back across the wrap
    assert frame(2, loop=False) is None and frame(45, loop=False) == 40
    assert cache.latest_behind("w", 12, 50, True) is None  # another view


def test_a_finished_frame_replaces_the_shown_one_unless_that_is_nearer_the_playhead():
    assert replaces_shown(10, None, 12, 50, True)  # nothing shown yet
    assert replaces_shown(10, 3, 12, 50, True) and replaces_shown(10, 10, 12, 50, True)
    assert not replaces_shown(3, 10, 12, 50, True)
    assert replaces_shown(48, 40, 2, 50, True) and not replaces_shown(40, 48, 2, 50, True)  # across the wrap


def test_a_render_nobody_waits_for_is_abandoned_even_when_the_screen_is_stale():
    worker = RenderWorker(lambda request, generation: NOTHING, lambda *args: None, max_stale_s=0.0,
                          superseded=lambda running, newest: newest == "orbit")
    try:
        first = worker.request("render ahead")
        second = worker.request("orbit")
        assert not worker.should_cancel(first)  # no result for max_stale_s: finish what would be shown
        assert worker.should_cancel(first, progress=False)  # a frame ahead would not be: give it up
        assert not worker.should_cancel(second, progress=False)  # the newest request is never superseded
    finally:
        worker.stop()


# ==== the real worker and neural view on the tiny untrained run (headless GL, no window) ===================
@pytest.fixture
def counted_renders(monkeypatch):
    """The frames :meth:`RenderSession.render` (the one camera-to-image entry point: every model
    evaluation of the previewer goes through it) was called for, in order."""
    from garmentnerf.render.session import RenderSession

    real = RenderSession.render
    calls: list[int] = []

    def render(self, frame, *args, **kwargs):
        calls.append(int(frame))
        return real(self, frame, *args, **kwargs)

    monkeypatch.setattr(RenderSession, "render", render)
    return calls


def _neural_view(gl_context, run_dir, preset="interactive"):
    from garmentnerf.runs import load_run
    from garmentnerf.viewer.neural_view import NeuralView
    from garmentnerf.viewer.scene_gl import SceneRenderer

    scene = SceneRenderer(gl_context, samples=0)
    view = NeuralView(scene, load_run(run_dir), None, lambda text: None, time.perf_counter)
    view.quality.dynamic = False  # the level's own quality, whatever moves
    view.quality.set_preset(preset)
    return scene, view


def _settle(view, camera, timeline, timeout=180.0):
    """Update the view (as the window does once per UI frame) until the worker has rendered ahead."""
    deadline = time.monotonic() + timeout
    view.update(camera, timeline)
    while not view.settled() and time.monotonic() < deadline:
        time.sleep(0.01)
        view.update(camera, timeline)
    view.update(camera, timeline)
    assert view.settled(), view.error()


def test_render_ahead_scrub_recolour_and_what_invalidates_it(gl_context, untrained_run, tiny_scene, counted_renders):
    from garmentnerf.conventions import orbit_camera

    n = 3  # the tiny scene's training sequence
    scene, view = _neural_view(gl_context, untrained_run)
    renderer = view.renderer
    try:
        timeline = Timeline(num_frames=n, fps=30.0, playing=False)
        camera = orbit_camera(0.0, 5.0, 3.0, width=64, height=48)
        _settle(view, camera, timeline)
        # paused on frame 0: the frame itself, then the rest of the clip rendered ahead, each once
        assert counted_renders == [0, 1, 2] and renderer.stats.renders == 3 and renderer.stats.errors == 0
        key = renderer.finished.view
        assert renderer.finished.frames(key) == {0, 1, 2} and view.shown_frame == 0
        assert renderer.finished.nbytes <= renderer.finished.budget_bytes
        # a scrub to a rendered frame shows it at once and makes no model call
        timeline.set_frame(2)
        view.update(camera, timeline)
        assert view.shown_frame == 2
        _settle(view, camera, timeline)
        assert counted_renders == [0, 1, 2] and view.shown_frame == 2
        # recolouring: every rendered frame shows the new palette, nothing is rendered again
        before = []
        for f in range(n):
            timeline.set_frame(f)
            view.update(camera, timeline)
            assert view.shown_frame == f
            before.append(scene.render_image(camera, samples=0).astype(int))
        assert max(np.abs(before[f] - before[0]).max() for f in range(1, n)) > 0  # the frames differ
        invalidations = renderer.finished.invalidations
        view.set_palette_color(0, (1.0, 0.0, 0.0))
        view.set_palette_color(1, (0.0, 0.0, 1.0))
        for f in range(n):
            timeline.set_frame(f)
            view.update(camera, timeline)
            after = scene.render_image(camera, samples=0).astype(int)
            assert np.abs(after - before[f]).max() > 10, f
        _settle(view, camera, timeline)
        assert counted_renders == [0, 1, 2] and renderer.finished.frames(key) == {0, 1, 2}
        assert renderer.finished.invalidations == invalidations  # a palette change invalidates nothing
        # an orbit invalidates: the new view is rendered again (from the playhead's frame)
        timeline.set_frame(1)
        moved = orbit_camera(30.0, 5.0, 3.0, width=64, height=48)
        _settle(view, moved, timeline)
        assert renderer.finished.invalidations == invalidations + 1 and renderer.finished.view != key
        assert counted_renders[3:] == [1, 2, 0] and renderer.finished.frames(renderer.finished.view) == {0, 1, 2}
        # so does another quality level (another quality and preset) ...
        view.quality.set_preset("balanced")
        view.update(moved, timeline)
        assert renderer.finished.invalidations == invalidations + 2
        _settle(view, moved, timeline)
        assert counted_renders[6:] == [1, 2, 0]
        # ... and the memory bound holds: room for one frame and a half keeps one
        one = max(renderer.finished.nbytes // 3, 1)
        renderer.set_finished_mb(1.5 * one / 2**20)
        assert len(renderer.finished.frames(renderer.finished.view)) == 1
        assert renderer.finished.nbytes <= renderer.finished.budget_bytes
        _settle(view, moved, timeline)
        assert counted_renders[9:] == [] and renderer.finished.nbytes <= renderer.finished.budget_bytes
        # another motion invalidates too
        renderer.set_render_ahead(False)
        view.set_motion("walk")
        view.update(moved, timeline)
        assert renderer.finished.invalidations == invalidations + 3
    finally:
        view.stop()
        scene.release()


def test_playing_over_rendered_frames_shows_each_in_step_with_the_timeline(gl_context, untrained_run, counted_renders):
    from garmentnerf.conventions import orbit_camera

    n = 3
    scene, view = _neural_view(gl_context, untrained_run)
    renderer = view.renderer
    try:
        timeline = Timeline(num_frames=n, fps=30.0, playing=True)
        camera = orbit_camera(0.0, 5.0, 3.0, width=64, height=48)
        _settle(view, camera, timeline)  # the timeline does not advance here: the worker renders ahead
        assert sorted(counted_renders) == [0, 1, 2] and renderer.stats.abandoned == 0
        assert renderer.stats.completed_share == 1.0
        shown = []
        for _ in range(12):  # a 60 Hz UI playing the 30 fps clip: every frame shown, in step
            timeline.advance(1.0 / 60.0)
            view.update(camera, timeline)
            assert view.shown_frame == timeline.frame
            shown.append(view.shown_frame)
        assert shown == [0, 1, 1, 2, 2, 0, 0, 1, 1, 2, 2, 0] and len(counted_renders) == 3
    finally:
        view.stop()
        scene.release()


def test_the_newest_frame_is_shown_unless_it_lies_ahead():
    from garmentnerf.viewer.playback import show_newest

    assert show_newest(5, 5, 10, loop=True) and show_newest(3, 5, 10, loop=True)  # on it, or behind: shown
    assert not show_newest(7, 5, 10, loop=True)  # rendered ahead: waits for the playhead
    assert show_newest(1, 5, 10, loop=True)      # 6 frames "ahead" of a 10-frame loop: behind it really
    assert not show_newest(9, 5, 10, loop=False) and show_newest(1, 5, 10, loop=False)


def test_scrubbing_over_rendered_frames_with_dynamic_quality_keeps_them(gl_context, untrained_run, counted_renders):
    """With the quality coarser while the view changes (the default), a scrub is a changing view; a
    scrub onto rendered frames shows them and asks for nothing coarser, so the rendered clip stays;
    one onto a frame not rendered shows a coarse render first and keeps the level's one."""
    from garmentnerf.conventions import orbit_camera

    scene, view = _neural_view(gl_context, untrained_run)
    view.quality.dynamic = True
    renderer = view.renderer
    try:
        timeline = Timeline(num_frames=3, fps=30.0, playing=False)
        camera = orbit_camera(0.0, 5.0, 3.0, width=64, height=48)
        _settle(view, camera, timeline)
        key, calls, invalidations = renderer.finished.view, len(counted_renders), renderer.finished.invalidations
        assert renderer.finished.frames(key) == {0, 1, 2} and key[1] == view.quality.full
        for f in (2, 1, 0, 2, 1):
            timeline.set_frame(f)
            view.update(camera, timeline)
            assert view.shown_frame == f and view.shown.quality == view.quality.full
            assert view.quality.moving(time.perf_counter())  # a scrub is a changing view ...
        _settle(view, camera, timeline)
        assert len(counted_renders) == calls  # ... but no model call, and the rendered clip stays
        assert renderer.finished.invalidations == invalidations and renderer.finished.frames(key) == {0, 1, 2}
        # as if the bound had dropped them (the newest result, frame 2, stays on hand): a scrub onto
        # frame 0 renders it, then the clip again
        assert view.shown_frame == 1
        renderer.finished.clear()
        timeline.set_frame(0)
        _settle(view, camera, timeline)
        assert counted_renders[calls] == 0 and set(counted_renders[calls:]) == {0, 1, 2}, counted_renders[calls:]
        assert renderer.finished.invalidations == invalidations and renderer.finished.frames(key) == {0, 1, 2}
        assert view.shown_frame == 0 and view.shown.quality == view.quality.full
    finally:
        view.stop()
        scene.release()


# ==== the window (Xvfb) ======================================================================================
def test_window_render_bar_and_play_every_frame(xvfb, untrained_run, tmp_path):
    """The timeline bar shows the rendered-ahead frames in their own colour across the slider; with
    "play every frame" playback never skips a frame: it waits on a frame until the next one's image
    is finished (after an orbit nothing is), then shows each in step with the timeline."""
    from garmentnerf.viewer.app import App
    from garmentnerf.viewer.panels import RENDERED_COLOR

    with App(motion=None, run=untrained_run, size=(480, 320), samples=0, vsync=False, playing=False,
             snapshot_dir=tmp_path) as viewer:
        view, tl = viewer.neural_view, viewer.timeline
        assert viewer.wait_for_neural(180), view.error()
        viewer.run_until(view.settled, 180)
        viewer.step()
        assert view.renderer.finished.frames(view.renderer.finished.view) == set(range(tl.num_frames))
        image = viewer.read_framebuffer().astype(int)
        blue = (np.abs(image - np.array(RENDERED_COLOR[:3]) * 255).max(-1) <= 3)
        rows, cols = np.nonzero(blue[-60:])
        assert len(cols) > 0 and cols.max() - cols.min() > 0.8 * 480, (len(cols), cols.min(), cols.max())
        # play every frame after an orbit: the new view has nothing rendered, the timeline waits
        viewer.set_play_every_frame(True)
        viewer.fixed_dt = 2.0 / tl.fps  # two motion frames per UI frame: playing normally would skip one
        viewer.controller.orbit(40.0, 0.0)
        start = tl.frame
        tl.play()
        visited, waits = [start], 0
        deadline = time.monotonic() + 180
        while len(visited) < 7 and time.monotonic() < deadline:
            drawn = tl.frame
            viewer.step()
            assert view.shown_frame == drawn  # the image of the frame the timeline showed
            if tl.frame == visited[-1]:
                waits += 1
            else:
                assert tl.frame == (visited[-1] + 1) % tl.num_frames, (visited, tl.frame)  # never a skip
                visited.append(tl.frame)
            time.sleep(0.005)
        assert len(visited) == 7 and waits > 0 and view.renderer.stats.errors == 0, (visited, waits)
        tl.pause()
        viewer.fixed_dt = None
        viewer.set_play_every_frame(False)


def test_uncovered_parts_of_a_rectangle_match_a_pixel_mask():
    from garmentnerf.viewer.palette_layer import uncovered

    rng = np.random.default_rng(3)
    assert uncovered(None, (0, 0, 4, 4)) == [] and uncovered((1, 1, 2, 2), (0, 0, 4, 4)) == []
    assert uncovered((0, 0, 4, 4), (1, 1, 2, 2)) == [(0, 0, 4, 1), (0, 3, 4, 1), (0, 1, 1, 2), (3, 1, 1, 2)]
    for _ in range(500):
        old = (*rng.integers(0, 12, 2), *rng.integers(1, 10, 2))
        new = (*rng.integers(0, 12, 2), *rng.integers(1, 10, 2))
        want = np.zeros((24, 24), bool)
        want[old[1]:old[1] + old[3], old[0]:old[0] + old[2]] = True
        want[new[1]:new[1] + new[3], new[0]:new[0] + new[2]] = False
        got = np.zeros((24, 24), int)
        for x, y, w, h in uncovered(old, new):
            got[y:y + h, x:x + w] += 1
        np.testing.assert_array_equal(got, want.astype(int), err_msg=f"{old} {new}")  # exactly once each


def test_the_body_layer_is_not_supersampled_while_the_view_moves(gl_context, body, walk_clip):
    """A playing clip brings a new body every frame: while the view moves the palette layer draws
    the body layer at one sample per pixel (what a separate pass draws with supersample 1), once
    still at the usual 2 x 2 again; an unchanged state draws nothing."""
    import torch

    from garmentnerf.body.surface import vertex_normals
    from garmentnerf.conventions import orbit_camera
    from garmentnerf.gl.body_layer_pass import BodyLayerPass
    from garmentnerf.gl.context import make_current
    from garmentnerf.model.body_appearance import BodyAppearance
    from garmentnerf.viewer.palette_layer import BodyView, PaletteLayer, pack_maps
    from garmentnerf.viewer.renderables import ViewParams

    make_current(gl_context)
    posed, _ = walk_clip
    verts = posed.vertices[0].float()
    normals = vertex_normals(verts[None], torch.as_tensor(np.asarray(body.faces), dtype=torch.long))[0]
    camera = orbit_camera(0.0, 5.0, 3.0, width=64, height=48)
    appearance = BodyAppearance(texture_size=8)
    H, W = 48, 64
    weights = np.zeros((2, H, W), np.float32)
    weights[0] = 1.0
    maps = pack_maps(np.ones((3, H, W), np.float32), np.zeros((2, 3, H, W), np.float32), weights,
                     np.zeros((H, W), np.float32))
    layer = PaletteLayer(gl_context)
    reference = BodyLayerPass(gl_context)
    try:
        layer.set_body_model(body, appearance)
        layer.submit(maps, np.zeros((H, W), np.float32), (W, H),
                     body=BodyView(verts.numpy(), normals.numpy(), camera))
        view = ViewParams.of(camera)

        def drawn(supersample):
            want = reference.draw(verts.numpy(), normals.numpy(), np.asarray(body.faces), np.asarray(body.uv),
                                  np.asarray(body.uv_faces), camera, appearance, supersample)
            return np.frombuffer(want.read(), np.float32)

        layer.prepare(view)
        assert layer.body_draws == 1
        still = np.frombuffer(layer._body_tex.read(), np.float32)
        np.testing.assert_array_equal(still, drawn(2))
        layer.prepare(view)
        assert layer.body_draws == 1  # nothing changed: not drawn again
        layer.moving = True
        layer.prepare(view)
        assert layer.body_draws == 2
        moving = np.frombuffer(layer._body_tex.read(), np.float32)
        np.testing.assert_array_equal(moving, drawn(1))
        assert np.abs(moving - still).max() > 0  # the edges differ: really one sample per pixel
        layer.moving = False
        layer.prepare(view)
        assert layer.body_draws == 3
        np.testing.assert_array_equal(np.frombuffer(layer._body_tex.read(), np.float32), drawn(2))
        layer.submit(maps, np.zeros((H, W), np.float32), (W, H),  # the next frame's body (another result)
                     body=BodyView(verts.numpy(), normals.numpy(), camera))
        layer.prepare(view)
        assert layer.body_draws == 4
    finally:
        reference.release()
        layer.release()


def test_maps_in_a_larger_texture_draw_as_maps_of_their_own_size(gl_context):
    """After a larger frame the textures keep their size; the next, smaller maps must still draw
    exactly as they do in textures of their own size (the edge sampled as clamp-to-edge)."""
    from garmentnerf.conventions import orbit_camera
    from garmentnerf.gl.context import make_current
    from garmentnerf.viewer.palette_layer import PaletteLayer
    from garmentnerf.viewer.renderables import ViewParams

    make_current(gl_context)
    rng = np.random.default_rng(5)
    H, W = 64, 128  # a multiple of the capacity step: the first layer's textures are exactly this size
    maps = rng.uniform(0.05, 1.0, (4, H, W, 4)).astype(np.float16)
    depth = np.full((H, W), 2.0, np.float32)
    camera = orbit_camera(0.0, 5.0, 3.0, width=160, height=120)
    view = ViewParams.of(camera)
    fbo = gl_context.simple_framebuffer((160, 120), components=4, dtype="f4")
    images = []
    for first in (None, (4, 130, 200, 4)):
        layer = PaletteLayer(gl_context)
        try:
            layer.opaque = True
            layer.set_palette([(0.9, 0.1, 0.2), (0.1, 0.8, 0.3)])
            if first is not None:
                layer.submit(rng.uniform(0, 1, first).astype(np.float16), np.ones(first[1:3], np.float32), (W, H))
                layer.prepare()
            layer.submit(maps, depth, (W, H))
            layer.prepare()
            size = (layer.maps_tex.width, layer.maps_tex.height)
            assert size == (W, H) if first is None else size[0] > W and size[1] > H
            fbo.use()
            fbo.clear(0.0, 0.0, 0.0, 0.0)
            layer.draw(view)
            images.append(np.frombuffer(fbo.read(components=4, dtype="f4"), np.float32).reshape(120, 160, 4))
        finally:
            layer.release()
    fbo.release()
    assert images[0].max() > 0
    # the same texels with the same weights: equal up to the rounding of the scaled coordinate (a
    # border mixed with the empty texels beyond the maps would be off by a large part of a colour)
    np.testing.assert_allclose(images[1], images[0], rtol=0, atol=1e-4)


def test_the_neural_layer_draws_only_where_its_maps_are_filled_and_shows_the_same(gl_context):
    """Blended over the scene, empty maps add nothing: the quad drawn over the filled texels (grown
    by the bilinear footprint) gives the image the whole quad gives."""
    from garmentnerf.conventions import orbit_camera
    from garmentnerf.gl.context import make_current
    from garmentnerf.viewer import palette_layer as pl
    from garmentnerf.viewer.renderables import ViewParams

    make_current(gl_context)
    rng = np.random.default_rng(7)
    H, W = 48, 80
    layers = np.zeros((4, H, W, 4), np.float32)
    layers[1, ..., :2] = 0.5
    layers[:, 10:30, 20:45] = rng.uniform(0.05, 1.0, (4, 20, 25, 4))
    depth = np.zeros((H, W), np.float32)
    depth[10:30, 20:45] = 2.0
    cut, cut_depth, origin = pl.crop_to_content(layers, depth)
    camera = orbit_camera(0.0, 5.0, 3.0, width=200, height=150)
    view = ViewParams.of(camera)
    fbo = gl_context.simple_framebuffer((200, 150), components=4, dtype="f4")
    layer = pl.PaletteLayer(gl_context)
    images = []
    try:
        layer.set_palette([(0.9, 0.1, 0.2), (0.1, 0.8, 0.3)])
        layer.submit(cut.astype(np.float16), cut_depth, (W, H), origin=origin, map_size=(W, H))
        layer.prepare()
        quad = pl.filled_quad(pl.fit_rect((-1.0, -1.0, 1.0, 1.0), 200, 150, (W, H)), layer._filled, (W, H))
        assert quad[1] != (0.0, 0.0, 1.0, 1.0)  # a part of the image
        for filled in (layer._filled, None):  # None: the whole quad
            layer._filled = filled
            fbo.use()
            fbo.clear(0.2, 0.3, 0.4, 1.0)  # a scene behind it
            gl_context.enable(gl_context.BLEND)
            gl_context.blend_func = gl_context.ONE, gl_context.ONE_MINUS_SRC_ALPHA
            layer.draw(view)
            gl_context.disable(gl_context.BLEND)
            images.append(np.frombuffer(fbo.read(components=4, dtype="f4"), np.float32).reshape(150, 200, 4))
    finally:
        layer.release()
        fbo.release()
    changed = np.abs(images[1] - np.array([0.2, 0.3, 0.4, 1.0], np.float32)).max(-1) > 1e-3
    assert changed.sum() > 500
    np.testing.assert_allclose(images[0], images[1], rtol=0, atol=1e-4)
