"""``garmentnerf view --bench``: measure the previewer in a real window (needs a display).

The figures are measured by driving the real :class:`~garmentnerf.viewer.app.App` (GLFW window,
imgui panels, the neural worker thread) the way a user would, with vsync off so the frame rate is
what the machine can do rather than the display's refresh:

* **First frame** (goals on a quiet machine: the body within 6 s, the garment within 12 s):
  ``first_frame.body_s`` and ``first_frame.garment_s``, seconds from the command's start (the
  process's, :func:`garmentnerf.startup.seconds_since_start`: the interpreter's start-up and every
  import count) to the end of the first UI frame that showed the body / the neural garment
  (:class:`~garmentnerf.viewer.timeline.FirstFrames`), the window opening paused on frame 0;
  ``first_frame.other_processes_cores``: how busy other processes kept the machine meanwhile.

* **UI frame rate while the worker is busy** (goal >= 30 fps): the timeline plays and the camera
  orbits a little every UI frame, so the neural worker always has a newer view to render (renders
  are superseded and cancelled, as while dragging). Reported: frames per second over the whole
  measurement, median / 95th percentile / worst frame time, and the fraction of UI frames during
  which the worker was rendering, and the scale the scene was drawn at while the view moved
  (:class:`~garmentnerf.viewer.quality.SceneScale`; 1 with ``--fixed-scene-scale``). Without a
  run (body only) the worker part is absent.
* **Recolor latency** (goal: the next frame): with the view still and the newest neural frame on
  the GPU, each palette entry is set to its complement and the window is read back after every UI
  frame; the latency is the number of frames until the garment's pixels change (1 = the next frame).
  The worker must not render again for it (palette edits are a shader uniform): ``worker_renders``
  counts the renders that happened during the recolor test (expected 0).
* **Neural frame time per quality level** (:data:`garmentnerf.render.presets.VIEWER_LEVELS`, render
  presets): with the
  dynamic resolution off, the camera steps a little and the full-quality render of the preset is
  awaited; median (and each) of ``RenderSession.render``'s total time, the render size, and the
  worker's wall time per render.

* **Baked frames** (goal >= 30 fps; needs the clip's frames baked, ``garmentnerf bake --cache``, or the
  window's own background bake): ``bake.orbit_ui_fps``, the UI frame rate while the camera orbits a
  paused baked frame, and ``bake.play_orbit_ui_fps`` while the clip plays and the camera orbits at once;
  ``bake.scene_scale`` (median scale the scene was drawn at), ``bake.shown_share`` (UI frames that drew
  a bake rather than a neural image) and ``bake.baked_frames`` (of the clip, when measured). Before orbiting,
  the window first waits for its loader to read every baked frame into memory (``bake.load_wait_s``).

Render-ahead is switched off for these figures (a still view would otherwise keep the worker
rendering the rest of the clip, which the recolor test counts and the preset times share the CPU
with); ``garmentnerf bench --run`` measures it (``playback.render_ahead``).

The JSON (``--json PATH``, written atomically) holds the same figures; numbers that could not be
measured are null.
"""

from __future__ import annotations

import json
import math
import statistics
import sys
import time

import numpy as np

from garmentnerf.cpu_load import OtherProcessesLoad, load_report
from garmentnerf.io_utils import atomic_write_path
from garmentnerf.startup import other_cores_since_start

#: UI frames read back after a palette change before giving up on seeing it.
RECOLOR_MAX_FRAMES = 10
#: Smallest per-channel change (0..255) that counts as "the garment changed color".
RECOLOR_THRESHOLD = 8
#: Camera step per UI frame while measuring the busy frame rate (pixels of mouse drag).
ORBIT_STEP = 4.0
#: Goals of the first frame on a quiet machine: seconds from the command's start to the body, the garment.
FIRST_BODY_GOAL_S = 6.0
FIRST_GARMENT_GOAL_S = 12.0


def _percentile(values, q: float) -> float:
    if not values:
        return float("nan")
    return float(np.percentile(np.asarray(values, dtype=np.float64), q))


def _finite(x):
    """JSON-safe: NaN/inf become None."""
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    return x


def _wait_settled(app, timeout: float) -> bool:
    """Step UI frames until the worker is idle, the view still and every result drained, twice in a
    row (a still view asks for its full quality in the frame after it settles; the last result then
    reaches the GPU)."""
    settled = app.neural_view.settled
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and not app.closed:
        app.step()
        if settled():
            app.step()
            if settled():
                return True
        time.sleep(0.005)
    return False


def _orbit_frames(app, seconds: float) -> dict:
    """Step UI frames for ``seconds`` with the camera orbiting a little each frame: fps, frame times, the
    scene's median draw scale, the share of frames the baked layer drew and the share the worker was busy."""
    intervals, scales, baked, busy = [], [], 0, 0
    renderer = app.neural_view.renderer
    start = last = time.perf_counter()
    while time.perf_counter() - start < seconds and not app.closed:
        app.controller.orbit(ORBIT_STEP, 0.0)
        if not app.step():
            break
        now = time.perf_counter()
        intervals.append(now - last)
        last = now
        scales.append(app.scene_draw_scale)
        baked += app.neural_view.showing_bake == "bake"
        busy += renderer is not None and not renderer.worker.idle()
    elapsed = time.perf_counter() - start
    ms = [1000.0 * x for x in intervals]
    n = len(ms)
    return {"seconds": elapsed, "frames": n, "fps": n / elapsed if elapsed > 0 else float("nan"),
            "frame_ms_median": _percentile(ms, 50), "frame_ms_p95": _percentile(ms, 95),
            "frame_ms_max": max(ms) if ms else float("nan"), "scene_scale": _percentile(scales, 50),
            "shown_share": baked / n if n else float("nan"), "busy_share": busy / n if n else float("nan")}


def measure_busy_fps(app, seconds: float) -> dict:
    """UI frame rate while the timeline plays, the camera orbits and the worker renders."""
    renderer = app.neural_view.renderer
    renders0 = renderer.stats.renders if renderer is not None else 0
    dropped0 = renderer.stats.dropped if renderer is not None else 0
    app.timeline.play()
    orbit = _orbit_frames(app, seconds)
    app.timeline.pause()
    out = {k: orbit[k] for k in ("seconds", "frames", "fps", "frame_ms_median", "frame_ms_p95", "frame_ms_max")}
    out.update({"goal_fps": 30.0,
                # the App's own split of the last frames: time inside a frame before the swap, and the scene's share
                "work_ms": app.timer.work_ms, "scene_ms": app.timer.scene_ms,
                # the scene's draw scale while the view moved (SceneScale; 1 with --fixed-scene-scale)
                "scene_scale_median": orbit["scene_scale"], "scene_scale_dynamic": app.scene_scale.dynamic})
    if renderer is not None:
        out["worker_busy_fraction"] = orbit["busy_share"]
        out["worker_renders"] = renderer.stats.renders - renders0
        out["worker_superseded"] = renderer.stats.dropped - dropped0
    out["meets_goal"] = bool(out["fps"] >= 30.0)
    return out


def measure_recolor(app, settle_timeout: float = 120.0) -> dict:
    """Frames from a palette change to changed garment pixels, per palette entry (1 = next frame)."""
    view = app.neural_view
    if view.renderer is None or view.palette is None:
        return {"available": False}
    _wait_settled(app, settle_timeout)
    show_ui = app.show_ui
    app.show_ui = False  # the panels show the palette too: judge the scene only
    renders0 = view.renderer.stats.renders
    uploads0 = app.scene.palette_layer.uploads
    per_entry = []
    try:
        for index in range(len(view.palette)):
            before = app.read_framebuffer()
            old = view.palette[index].copy()
            view.set_palette_color(index, 1.0 - old)
            latency = None
            for n in range(1, RECOLOR_MAX_FRAMES + 1):
                shot = app.read_framebuffer()
                changed = shot.shape == before.shape and np.abs(shot.astype(int) - before.astype(int)).max()
                if changed > RECOLOR_THRESHOLD:
                    latency = n
                    break
            view.set_palette_color(index, old)
            app.read_framebuffer()
            per_entry.append(latency)
    finally:
        app.show_ui = show_ui
    seen = [x for x in per_entry if x is not None]
    return {"available": True, "latency_frames": max(seen) if seen else None, "per_entry": per_entry,
            "entries_visible": len(seen), "entries": len(per_entry),
            "worker_renders": view.renderer.stats.renders - renders0,
            "layer_uploads": app.scene.palette_layer.uploads - uploads0,
            "threshold": RECOLOR_THRESHOLD, "goal_frames": 1,
            "meets_goal": bool(seen) and max(seen) <= 1 and view.renderer.stats.renders == renders0}


def measure_presets(app, repeats: int, timeout: float) -> dict:
    """Neural frame time at each quality preset (full quality, dynamic resolution off)."""
    renderer = app.neural_view.renderer
    if renderer is None:
        return {}
    # lazy: 'garmentnerf --help' and flag errors answer without torch and the model stack (0.4 s against 6 s)
    from garmentnerf.render.presets import VIEWER_LEVELS, get_render_preset

    q = app.neural_view.quality
    saved = (q.preset, q.dynamic)
    out = {}
    try:
        q.dynamic = False
        for name in VIEWER_LEVELS:
            quality = get_render_preset(name).resolution_scale
            q.set_preset(name)
            totals, walls, sizes, cached, rendered = [], [], [], [], []
            for _ in range(max(1, repeats)):
                renders = renderer.stats.renders
                app.controller.orbit(2.0, 0.0)  # a new view: one new request at the preset's quality
                deadline = time.monotonic() + timeout
                while time.monotonic() < deadline and not app.closed:
                    app.step()
                    last = renderer.last
                    if (renderer.stats.renders > renders and renderer.worker.idle() and last is not None
                            and abs(last.quality - quality) < 1e-6):
                        break
                    if renderer.stats.errors:
                        break
                    time.sleep(0.005)
                last = renderer.last
                if last is None or renderer.stats.renders <= renders or abs(last.quality - quality) > 1e-6:
                    continue
                totals.append(float(last.timings.get("total", float("nan"))))
                walls.append(float(renderer.stats.last_ms))
                sizes.append(list(last.render_size))
                cached.append(bool(last.cached_frame))
                rendered.append(last.preset)
            out[name] = {"quality": quality, "preset": sorted(set(rendered)), "render_ms_median": statistics.median(totals) if totals else None,
                         "render_ms": totals, "worker_ms": walls, "render_size": sizes[-1] if sizes else None,
                         "cached_frame": cached}
    finally:
        q.dynamic = saved[1]
        q.set_preset(saved[0])
    return out


def measure_bake(app, seconds: float, timeout: float) -> dict:
    """The baked-frame figures (module docstring): waits (up to ``timeout``) for the shown frame's bake."""
    view = app.neural_view
    if view.bakes is None:
        return {"available": False, "reason": "no bake (the run cannot be baked, or --no-bake)"}
    app.timeline.pause()
    deadline = time.monotonic() + timeout
    while view.bakes.get(app.timeline.frame) is None and time.monotonic() < deadline and not app.closed:
        app.step()
        time.sleep(0.01)
    if view.bakes.get(app.timeline.frame) is None:
        status = view.bake_status() or {}
        return {"available": False, "reason": f"frame {app.timeline.frame} not baked within {timeout:.0f} s "
                                              f"({status.get('error') or 'baking'})"}
    t0 = time.monotonic()
    while view.bakes.loaded() < len(view.bakes.baked()) and time.monotonic() - t0 < timeout and not app.closed:
        app.step()  # the loader reads the rest of the clip (a second launch's first seconds)
        time.sleep(0.01)
    loaded_s = time.monotonic() - t0
    orbit = _orbit_frames(app, seconds)
    app.timeline.play()
    play = _orbit_frames(app, seconds)
    app.timeline.pause()
    status = view.bake_status() or {}
    return {"available": True, "orbit_ui_fps": orbit["fps"], "play_orbit_ui_fps": play["fps"],
            "scene_scale": orbit["scene_scale"], "play_scene_scale": play["scene_scale"],
            "shown_share": orbit["shown_share"], "play_shown_share": play["shown_share"],
            "orbit_frame_ms_median": orbit["frame_ms_median"], "play_frame_ms_median": play["frame_ms_median"],
            "baked_frames": status.get("baked"), "frames": status.get("frames"), "loaded_frames": status.get("loaded"),
            "load_wait_s": loaded_s, "goal_fps": 30.0}


def run_bench(app, seconds: float = 5.0, repeats: int = 3, timeout: float = 180.0) -> dict:
    """All three measurements on an open ``app`` (see the module docstring); returns the figures."""
    w, h = app.window.framebuffer_size
    view = app.neural_view
    result = {"window": [w, h], "gl_renderer": app.window.gl_renderer, "run": None, "motion": app.motion_name,
              "neural": view.renderer is not None}
    if view.run is not None:
        result["run"] = str(getattr(view.run, "root", getattr(view.run, "path", "")) or "")
    if view.renderer is not None:
        view.renderer.set_render_ahead(False)  # see the module docstring
    for _ in range(3):
        app.step()
    if view.renderer is not None:
        t0 = time.perf_counter()
        ok = app.wait_for_neural(timeout)
        result["first_neural_frame_s"] = time.perf_counter() - t0
        if not ok:
            raise RuntimeError(f"no neural frame within {timeout:.0f} s ({view.error() or 'no error'})")
    first = app.first_frames
    result["first_frame"] = {"body_s": first.body_s, "garment_s": first.garment_s,
                             "goal_body_s": FIRST_BODY_GOAL_S, "goal_garment_s": FIRST_GARMENT_GOAL_S,
                             "other_processes_cores": other_cores_since_start()}
    with OtherProcessesLoad() as load:
        result["bake"] = measure_bake(app, seconds, timeout)
        result["ui_busy"] = measure_busy_fps(app, seconds)
        result["recolor"] = measure_recolor(app, timeout)
        result["presets"] = measure_presets(app, repeats, timeout)
    result["other_processes_cores"] = load.cores  # the X server's share included
    if view.renderer is not None:
        st = view.renderer.stats
        result["worker"] = {"renders": st.renders, "superseded": st.dropped, "errors": st.errors,
                            "last_error": st.last_error}
    return result


def print_figures(result: dict, file=sys.stdout) -> None:
    ui = result["ui_busy"]
    w, h = result["window"]
    busy = (f", worker busy in {100 * ui['worker_busy_fraction']:.0f}% of frames, {ui['worker_renders']} renders "
            f"finished, {ui['worker_superseded']} superseded") if "worker_busy_fraction" in ui else " (no run)"
    print(f"view bench: {w}x{h} on {result['gl_renderer']}", file=file)
    first = result.get("first_frame")
    if first is not None:
        print(f"  {first_frame_line(first)}", file=file)
    print(f"  UI while worker busy: {ui['fps']:.1f} fps (goal >= 30) over {ui['frames']} frames; frame "
          f"{ui['frame_ms_median']:.1f} ms median, {ui['frame_ms_p95']:.1f} ms p95, {ui['frame_ms_max']:.1f} ms worst "
          f"(work {ui['work_ms']:.1f} ms, scene {ui['scene_ms']:.1f} ms drawn at x{ui['scene_scale_median']:.2f}"
          f"{'' if ui['scene_scale_dynamic'] else ', --fixed-scene-scale'})"
          f"{busy}", file=file)
    bake = result.get("bake") or {}
    if bake.get("available"):
        print(f"  baked frames: orbiting {bake['orbit_ui_fps']:.1f} UI fps at scene scale x{bake['scene_scale']:.2f}, "
              f"playing and orbiting {bake['play_orbit_ui_fps']:.1f} UI fps at x{bake['play_scene_scale']:.2f} (goal "
              f">= 30); the bake drew {100 * bake['play_shown_share']:.0f}% of the playing frames "
              f"({bake['baked_frames']} of {bake['frames']} frames baked)", file=file)
    elif bake:
        print(f"  baked frames: n/a ({bake.get('reason')})", file=file)
    rc = result["recolor"]
    if rc.get("available"):
        lat = rc["latency_frames"]
        print(f"  recolor latency: {lat if lat is not None else 'not seen'} frame(s) (goal 1) over "
              f"{rc['entries_visible']}/{rc['entries']} palette entries visible; worker renders meanwhile: "
              f"{rc['worker_renders']}", file=file)
    else:
        print("  recolor latency: n/a (no run)", file=file)
    for name, p in result.get("presets", {}).items():
        med = p["render_ms_median"]
        size = "x".join(map(str, p["render_size"])) if p["render_size"] else "?"
        print(f"  neural frame, preset {name} (quality {p['quality']}): "
              f"{f'{med:.0f} ms' if med is not None else 'not measured'} at {size}", file=file)
    if "other_processes_cores" in result:
        print(f"  {load_report(result['other_processes_cores'])}", file=file)


def first_frame_line(first: dict) -> str:
    """One line of the first-frame figures (``result["first_frame"]``)."""
    def seconds(x):
        return f"{x:.1f} s" if x is not None else "not seen"

    others = first.get("other_processes_cores")
    load = f"; other processes used {others:.2f} cores meanwhile" if others is not None else ""
    return (f"first frame: body {seconds(first['body_s'])}, garment {seconds(first['garment_s'])} after the "
            f"command started (goals on a quiet machine: {first['goal_body_s']:g} s, {first['goal_garment_s']:g} s)"
            f"{load}")


def write_json(result: dict, path, overwrite: bool = False) -> None:
    with atomic_write_path(path, overwrite=overwrite) as tmp:
        tmp.write_text(json.dumps(_finite(result), indent=1, default=str), encoding="utf-8")


__all__ = ["run_bench", "print_figures", "first_frame_line", "write_json", "measure_busy_fps", "measure_recolor",
           "measure_presets", "FIRST_BODY_GOAL_S", "FIRST_GARMENT_GOAL_S"]
