"""Render-ahead figures of the previewer (``garmentnerf bench --run``: ``playback.render_ahead``).

:func:`render_ahead_benchmark` runs the previewer's own neural worker
(:class:`~garmentnerf.viewer.worker.NeuralRenderer`, on its thread, with its own session) for one
still camera of the previewer's size, per preset, while a clip of ``frames`` frames plays at its own
rate from frame 0, and the UI's choice of what to show (the finished frame nearest behind the
playhead, :meth:`~garmentnerf.viewer.finished_frames.FinishedFrames.latest_behind` with
:func:`~garmentnerf.viewer.playback.replaces_shown`, as the window; else the newest result,
:func:`~garmentnerf.viewer.playback.show_newest`) is made at 60 Hz on the calling thread:

``seconds_for_clip``
    from pressing Play until every frame of the clip is rendered (the whole clip ahead, the frames'
    per-frame work included: the feature cache is emptied first).
``max_lag_frames``
    the largest gap, in frames, between the playhead and the frame the image shows while the clip
    plays before render-ahead finished (counted from the first image).
``fps_after``
    the rate at which playback over the rendered clip shows new frames: two loops of the clip at its
    frame rate, each frame put on the palette layer and the scene drawn (the window's path, on a
    headless context, at the scale the window draws a changing view at) and finished: frames shown
    (but the first) over the time from the first one's slot to the last one shown, so at most the
    clip's rate (a little below it over a short clip), lower when frames are late.
``render_s``, ``render_s_cold``, ``lag_budget_frames``
    the worker's expected render time of a frame whose features are cached and of one whose
    features the render computes (:class:`~garmentnerf.viewer.playback.RenderTime`), and one
    render time's worth of frames at the clip's rate (the longer of the two, rounded up): the
    bound ``max_lag_frames`` should keep.
``longest_render_s``, ``longest_render_frames``
    the longest time between two finished renders while the clip was rendered ahead (renders run
    back to back then, so: the longest render, to the UI's 1/60 s) and its frames at the clip's
    rate: the gap a render in flight leaves, what ``max_lag_frames`` is bound by when renders vary.
``renders``, ``started``, ``completed_share``
    the worker's renders finished and begun while the clip played (``completed_share`` over all
    presets: the issue's figure).
"""

from __future__ import annotations

import math
import time
from collections import deque

import numpy as np

from garmentnerf.render.cameras import orbit_view
from garmentnerf.viewer.neural_view import submit_result
from garmentnerf.viewer.playback import PlayheadClock, frames_behind, replaces_shown, show_newest
from garmentnerf.viewer.quality import SceneScale
from garmentnerf.viewer.scene_gl import SceneRenderer
from garmentnerf.viewer.worker import NeuralRenderer, NeuralRequest

#: The previewer's default window (the view the user watches).
PREVIEWER_SIZE = (1280, 800)
#: How often the simulated UI chooses what to show (Hz).
UI_HZ = 60.0


def render_ahead_benchmark(run, motion, presets, frames: int, gl_context, size: tuple[int, int] = PREVIEWER_SIZE,
                           timeout_s: float = 3600.0, log=print) -> dict:
    """See the module docstring.

    Args:
        run: a :class:`~garmentnerf.runs.LoadedRun`; motion: the motion spec its session renders
            (None: the run scene's first training sequence).
        presets: :class:`~garmentnerf.render.presets.RenderPreset` rows measured.
        frames: the clip's first ``frames`` frames are played (fewer if the clip is shorter).
        gl_context: a moderngl context on this thread (the display side).
        size: the still camera's size (an orbit view at the previewer's default distance).
        timeout_s: per preset, give up render-ahead after this long (``seconds_for_clip`` None).
    Returns:
        ``{"camera": [W, H], "frames": n, "fps": clip rate, "presets": {name: row}, "completed_share": x}``.
    """
    if frames < 1:
        raise ValueError(f"render-ahead needs at least 1 frame, got {frames}")
    camera = orbit_view(25.0, width=size[0], height=size[1], radius=3.6)
    scene = SceneRenderer(gl_context, samples=0)
    scene.palette_layer.set_palette(run.palette().detach().cpu().numpy())
    if getattr(run, "body_appearance", None) is not None:  # the window draws the body layer itself
        scene.palette_layer.set_body_model(run.model.body, run.body_appearance)
    rows: dict[str, dict] = {}
    total_started = total_renders = 0
    n = fps = None
    try:
        for preset in presets:
            delivered: deque = deque()
            renderer = NeuralRenderer(run, lambda result, request: delivered.append(result), motion)
            try:
                quality = preset.resolution_scale
                # warm-up: the session, the preset's GL objects, a first render time (another view key)
                renderer.request(NeuralRequest(0, camera, quality * (1 - 1e-6), motion, None, preset.name))
                if not renderer.worker.wait_idle(timeout_s) or renderer.stats.errors:
                    raise RuntimeError(f"render-ahead bench: the warm-up render failed: {renderer.stats.last_error}")
                session = renderer.session
                n, fps = min(int(frames), session.num_frames), session.fps
                session.frames.clear()  # the clip's per-frame work counts
                delivered.clear()
                started0, renders0 = renderer.stats.started, renderer.stats.renders
                t0 = time.perf_counter()
                clock = PlayheadClock(0.0, t0, fps, n, True)
                request = NeuralRequest(0, camera, quality, motion, None, preset.name, "auto", clock)
                renderer.request(request)
                key = request.view_key
                shown = newest = None
                max_lag, done_s, arrivals = 0, None, []
                while time.perf_counter() - t0 < timeout_s:
                    now = time.perf_counter()
                    while delivered:
                        newest = delivered.popleft()
                        arrivals.append(now)
                    head = clock.frame_at(now)
                    behind = renderer.finished.latest_behind(key, head, n, True)  # the window's choice
                    if behind is not None and replaces_shown(behind.frame, shown, head, n, True):
                        shown = behind.frame
                    elif newest is not None and show_newest(newest.frame, head, n, True):
                        shown = newest.frame
                    if shown is not None:
                        max_lag = max(max_lag, frames_behind(shown, head, n, True))
                    if len(renderer.finished.frames(key)) >= n:
                        done_s = now - t0
                        break
                    time.sleep(1.0 / UI_HZ)
                started = renderer.stats.started - started0
                renders = renderer.stats.renders - renders0
                row = {"seconds_for_clip": done_s, "max_lag_frames": int(max_lag), "renders": renders,
                       "started": started, "completed_share": renders / started if started else None,
                       "render_s": renderer.render_time.expected(cold=False),
                       "render_s_cold": renderer.render_time.expected(cold=True)}
                row["lag_budget_frames"] = math.ceil(fps * max(row["render_s"], row["render_s_cold"]))
                gaps = [b - a for a, b in zip(arrivals, arrivals[1:])]
                row["longest_render_s"] = max(gaps) if gaps else None
                row["longest_render_frames"] = math.ceil(fps * max(gaps)) if gaps else None
                row.update(_play_rendered(renderer, key, n, fps, scene, camera, submit_result))
                rows[preset.name] = row
                total_started += started
                total_renders += renders
                log(f"  render-ahead {preset.name:12s} {n} frames in "
                    + (f"{done_s:7.1f} s" if done_s is not None else "  (timeout)")
                    + f", max lag {max_lag} frames, then {row['fps_after']:5.1f} fps "
                      f"({renders} of {started} renders finished)")
            finally:
                renderer.stop()
    finally:
        scene.release()
    return {"camera": list(size), "frames": n, "fps": fps, "presets": rows,
            "completed_share": total_renders / total_started if total_started else None}


def _play_rendered(renderer, key, n: int, fps: float, scene, camera, submit_result) -> dict:
    """Two loops of the rendered clip at its rate: each frame put on the palette layer and the scene
    drawn and finished as the window draws it (at the :class:`~garmentnerf.viewer.quality.SceneScale`
    of a view whose frame changes); ``fps_after`` (new frames shown per second), ``display_ms``
    (median time to show one) and ``scene_scale`` (the last scale drawn at)."""
    ctx = scene.ctx
    scale = SceneScale()
    shows, costs = [], []
    drawn_scale = 1.0
    t0 = time.perf_counter()
    for i in range(2 * n):
        due = t0 + i / fps
        wait = due - time.perf_counter()
        if wait > 0:
            time.sleep(wait)
        result = renderer.finished.get(key, i % n)
        if result is None:
            continue
        start = time.perf_counter()
        submit_result(scene.palette_layer, result)
        scale.view_changed(i, start)
        drawn_scale = scale.scale(start)
        scene.palette_layer.moving = drawn_scale < 1.0  # as the window does
        drawn = camera if drawn_scale == 1.0 else camera.resized(max(1, round(camera.width * drawn_scale)),
                                                                 max(1, round(camera.height * drawn_scale)))
        draw_start = time.perf_counter()
        if scene.render(scene.window_target(drawn.width, drawn.height), drawn):
            ctx.finish()
            scale.observe(drawn_scale, (time.perf_counter() - draw_start) * 1e3)
        end = time.perf_counter()
        shows.append(end)
        costs.append(end - start)
    if len(shows) < 2:
        return {"fps_after": None, "display_ms": None, "frames_shown": len(shows), "scene_scale": drawn_scale}
    # from the first frame's slot to the last one shown: at most the clip's rate, lower when frames are late
    return {"fps_after": (len(shows) - 1) / (shows[-1] - t0), "display_ms": 1e3 * float(np.median(costs)),
            "frames_shown": len(shows), "scene_scale": drawn_scale}


__all__ = ["render_ahead_benchmark", "PREVIEWER_SIZE"]
