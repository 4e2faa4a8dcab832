"""The previewer's imgui panels. Each function draws one panel for an :class:`~garmentnerf.viewer.app.App`
and changes the app only through its public methods and state objects (timeline, controller,
scene), never through GL. Sizes are in multiples of the current font size, so the layout scales with
the window's content scale.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from garmentnerf.viewer.camera import VIEW_DIRECTIONS
from garmentnerf.viewer.exporter import EXPORT_MODES, MAX_QUALITY, MAX_VIDEO_FRAMES, MIN_QUALITY, MIN_SNAPSHOT_QUALITY
from garmentnerf.viewer.gui_libs import imgui
from garmentnerf.viewer.shortcuts import MOUSE_HELP, help_rows
from garmentnerf.viewer.timeline import MAX_SPEED, MIN_SPEED

if TYPE_CHECKING:  # pragma: no cover
    from garmentnerf.viewer.app import App

_PANEL_FLAGS = imgui.WindowFlags_.no_saved_settings
_BAR_FLAGS = (imgui.WindowFlags_.no_title_bar | imgui.WindowFlags_.no_resize | imgui.WindowFlags_.no_move
              | imgui.WindowFlags_.no_saved_settings | imgui.WindowFlags_.always_auto_resize
              | imgui.WindowFlags_.no_collapse)
_OVERLAY_FLAGS = (imgui.WindowFlags_.no_decoration | imgui.WindowFlags_.no_saved_settings
                  | imgui.WindowFlags_.always_auto_resize | imgui.WindowFlags_.no_focus_on_appearing
                  | imgui.WindowFlags_.no_nav | imgui.WindowFlags_.no_inputs)


def draw_all(app: "App") -> None:
    """Every panel that is open (called once per UI frame between imgui.new_frame and imgui.render)."""
    if app.show_ui:
        draw_controls(app)
        draw_timeline(app)
        draw_stats(app)
    if app.show_help:
        draw_help(app)


# ---- timeline bar (bottom) -----------------------------------------------------------------------
def draw_timeline(app: "App") -> None:
    tl = app.timeline
    vp = imgui.get_main_viewport()
    imgui.set_next_window_pos(imgui.ImVec2(vp.work_pos.x, vp.work_pos.y + vp.work_size.y), imgui.Cond_.always,
                              imgui.ImVec2(0.0, 1.0))
    imgui.set_next_window_size(imgui.ImVec2(vp.work_size.x, 0.0), imgui.Cond_.always)
    imgui.set_next_window_bg_alpha(0.85)
    imgui.begin("Timeline", None, _BAR_FLAGS)
    em = imgui.get_font_size()
    if imgui.button("Pause" if tl.playing else "Play", imgui.ImVec2(4.5 * em, 0)):
        app.do("toggle_play")
    imgui.same_line()
    if imgui.arrow_button("##prev", imgui.Dir.left):
        app.do("step_back")
    imgui.same_line()
    if imgui.arrow_button("##next", imgui.Dir.right):
        app.do("step_forward")
    imgui.same_line()
    _, tl.loop = imgui.checkbox("Loop", tl.loop)
    imgui.same_line()
    imgui.set_next_item_width(8 * em)
    changed, speed = imgui.slider_float("Speed", tl.speed, MIN_SPEED, MAX_SPEED, "%.2fx",
                                        imgui.SliderFlags_.logarithmic)
    if changed:
        tl.set_speed(speed)
    imgui.same_line()
    imgui.set_next_item_width(7 * em)
    changed, target = imgui.input_int("Go to", app.goto_frame, 1, 10, imgui.InputTextFlags_.enter_returns_true)
    if changed:
        app.goto_frame = target
        app.set_frame(target)
    imgui.same_line()
    imgui.text(f"frame {tl.frame:4d} / {tl.last_frame}   {tl.time:6.2f} s / {tl.num_frames / tl.fps:.2f} s   "
               f"{tl.fps:g} fps")
    message = app.status_message()
    if message:
        imgui.same_line()
        imgui.text_disabled(f"  {message}")
    if app.exporting:  # a row of its own while an export runs, whichever panels are open
        _export_progress(app.export_job, -1.0)
    imgui.set_next_item_width(-1.0)
    changed, frame = imgui.slider_int("##frame", tl.frame, 0, tl.last_frame, "%d")
    app.scrubbing = imgui.is_item_active()
    if changed:
        app.set_frame(frame)
    _render_bar(app)
    imgui.end()


def ready_runs(ready: list[int]) -> list[tuple[int, int]]:
    """Sorted frames -> runs ``(first, last)`` of consecutive frames."""
    runs: list[tuple[int, int]] = []
    for f in ready:
        if runs and f == runs[-1][1] + 1:
            runs[-1] = (runs[-1][0], f)
        else:
            runs.append((f, f))
    return runs


def _render_bar(app: "App") -> None:
    """A video editor's render bar under the frame slider: which frames are precomputed."""
    status = app.neural.cache_status() if app.neural is not None else None
    if not status or status["frames"] < 1:
        return
    lo, hi = imgui.get_item_rect_min(), imgui.get_item_rect_max()
    width, n = hi.x - lo.x, status["frames"]
    top = hi.y + 1.0
    draw = imgui.get_window_draw_list()
    colour = imgui.get_color_u32(imgui.ImVec4(0.35, 0.75, 0.4, 1.0))
    for first, last in ready_runs(status["ready"]):
        draw.add_rect_filled(imgui.ImVec2(lo.x + width * first / n, top),
                             imgui.ImVec2(lo.x + width * (last + 1) / n, top + 3.0), colour)
    imgui.dummy(imgui.ImVec2(0.0, 4.0))


# ---- controls (left) ---------------------------------------------------------------------------------
def draw_controls(app: "App") -> None:
    em = imgui.get_font_size()
    imgui.set_next_window_pos(imgui.ImVec2(0.6 * em, 0.6 * em), imgui.Cond_.first_use_ever)
    imgui.set_next_window_size(imgui.ImVec2(20 * em, 0.0), imgui.Cond_.first_use_ever)
    imgui.set_next_window_bg_alpha(0.88)
    expanded, _ = imgui.begin("garmentnerf", None, _PANEL_FLAGS)
    if expanded:
        _motion_section(app, em)
        _camera_section(app, em)
        _display_section(app)
        _neural_section(app, em)
        _palette_section(app)
        _snapshot_section(app, em)
        _export_section(app, em)
        imgui.separator()
        imgui.text_disabled("H or F1: shortcuts and mouse help")
    imgui.end()


def _motion_section(app: "App", em: float) -> None:
    if not imgui.collapsing_header("Motion", imgui.TreeNodeFlags_.default_open):
        return
    names = app.motion_names()
    labels = app.motion_labels()
    current = names.index(app.motion_name) if app.motion_name in names else 0
    imgui.set_next_item_width(-1.0)
    changed, index = imgui.combo("##motion", current, labels)
    if changed and names[index] != app.motion_name:
        app.load_motion(names[index])
    loading = app.loading_motion()
    if loading:
        imgui.text_disabled(f"loading {loading} ...")
    seq = app.sequence
    imgui.text(f"{seq.name}: {seq.num_frames} frames at {seq.fps:g} fps")
    imgui.text_disabled(f"body shape: {app.shape_label}, {seq.num_vertices} vertices")


def _camera_section(app: "App", em: float) -> None:
    if not imgui.collapsing_header("Camera", imgui.TreeNodeFlags_.default_open):
        return
    cam = app.controller
    for i, name in enumerate(VIEW_DIRECTIONS):
        if i:
            imgui.same_line()
        if imgui.button(name.capitalize()):
            app.do(f"camera_{name}")
    imgui.same_line()
    if imgui.button("Reset"):
        app.do("reset_camera")
    imgui.set_next_item_width(-6 * em)
    changed, value = imgui.slider_float("Azimuth", cam.azimuth, -180.0, 180.0, "%.0f deg")
    if changed:
        cam.azimuth = value
    imgui.set_next_item_width(-6 * em)
    changed, value = imgui.slider_float("Elevation", cam.elevation, -cam.max_elevation, cam.max_elevation, "%.0f deg")
    if changed:
        cam.elevation = value
    imgui.set_next_item_width(-6 * em)
    changed, value = imgui.slider_float("Distance", cam.distance, cam.min_distance, cam.max_distance, "%.2f m",
                                        imgui.SliderFlags_.logarithmic)
    if changed:
        cam.set_distance(value)
    imgui.set_next_item_width(-6 * em)
    changed, value = imgui.slider_float("Field of view", cam.fov_y, 10.0, 90.0, "%.0f deg")
    if changed:
        cam.fov_y = value
    changed, follow = imgui.checkbox("Follow the body (T)", cam.follow)
    if changed:
        app.set_follow(follow)


def _display_section(app: "App") -> None:
    if not imgui.collapsing_header("Display"):
        return
    floor = app.scene.floor
    _, floor.visible = imgui.checkbox("Floor", floor.visible)
    imgui.same_line()
    _, floor.show_lines = imgui.checkbox("Grid lines (G)", floor.show_lines)
    _, app.scene.body.visible = imgui.checkbox("Body", app.scene.body.visible)
    changed, scale = imgui.slider_float("Render scale", app.render_scale, 0.25, 1.0, "%.2f")
    if changed:
        app.set_render_scale(scale)


def _neural_section(app: "App", em: float) -> None:
    if app.run_data is None or not imgui.collapsing_header("Neural render", imgui.TreeNodeFlags_.default_open):
        return
    from garmentnerf.perf.presets import VIEWER_LEVELS
    from garmentnerf.viewer.app import VIEW_MODES
    from garmentnerf.viewer.scene_gl import MAP_VIEWS

    keys = list(VIEW_MODES)
    imgui.set_next_item_width(-6 * em)
    changed, index = imgui.combo("View (V)", keys.index(app.view_mode), [VIEW_MODES[k] for k in keys])
    if changed:
        app.set_view_mode(keys[index])
    if app.view_mode == "maps":
        layer = app.scene.palette_layer
        imgui.set_next_item_width(-6 * em)
        changed, index = imgui.combo("Map", MAP_VIEWS.index(layer.map_view), list(MAP_VIEWS))
        if changed:
            layer.map_view = MAP_VIEWS[index]
    if app.view_mode == "neural":
        changed, on = imgui.checkbox("Rasterised body too (by depth)", app.body_with_neural)
        if changed:
            app.set_body_with_neural(on)
    scene = app.run_data.scene
    if scene is not None and app.view_mode in ("ground_truth", "side_by_side", "difference"):
        names = scene.camera_names()
        current = names.index(app.gt_camera) if app.gt_camera in names else 0
        imgui.set_next_item_width(-6 * em)
        changed, index = imgui.combo("Scene camera", current, names)
        if changed:
            app.gt_camera = names[index]
        if not app.ground_truth_available():
            imgui.text_disabled("no ground truth: pick a scene sequence")
    presets = list(VIEWER_LEVELS)
    q = app.quality
    imgui.set_next_item_width(-6 * em)
    changed, index = imgui.combo("Quality", presets.index(q.preset), presets)
    if changed:
        q.set_preset(presets[index])
    _, q.dynamic = imgui.checkbox("Coarser while moving", q.dynamic)
    status = app.neural.cache_status() if app.neural is not None else None
    if status is not None:
        imgui.set_next_item_width(-6 * em)
        changed, mb = imgui.slider_float("Frame cache", status["budget_bytes"] / 2**20, 0.0, 4096.0, "%.0f MiB",
                                         imgui.SliderFlags_.logarithmic)
        if changed:
            app.neural.set_cache_mb(mb)
        imgui.text_disabled(f"{len(status['ready'])} / {status['frames']} frames ready, "
                            f"{status['bytes'] / 2**20:.0f} MiB (half precision)")
    error = app.neural_error()
    if error:
        imgui.text_colored(imgui.ImVec4(1.0, 0.45, 0.4, 1.0), "render failed:")
        imgui.text_wrapped(error)


def _palette_section(app: "App") -> None:
    if not imgui.collapsing_header("Garment palette", imgui.TreeNodeFlags_.default_open if app.palette is not None
                                   else 0):
        return
    if app.palette is None:
        imgui.text_wrapped("No garment model loaded (body only). Open a run with garmentnerf view --run DIR "
                           "to recolour its neural garment.")
        return
    names = ["Garment", "Body / other"] + [f"Colour {i}" for i in range(2, len(app.palette))]
    flags = imgui.ColorEditFlags_.float | imgui.ColorEditFlags_.display_hex
    for i in range(len(app.palette)):
        changed, col = imgui.color_edit3(names[i], [float(c) for c in app.palette[i]], flags)
        if changed:
            app.set_palette_colour(i, col[:3])
    if imgui.button("Reset to learned palette"):
        app.reset_palette()
    imgui.text_disabled("recolouring only changes a shader uniform")


def _snapshot_section(app: "App", em: float) -> None:
    if not imgui.collapsing_header("Snapshot"):
        return
    imgui.set_next_item_width(-6 * em)
    changed, size = imgui.input_int2("Size (px)", list(app.snapshot_size))
    if changed:
        app.set_snapshot_size(*size)
    if app.run_data is not None:
        imgui.set_next_item_width(-6 * em)
        changed, q = imgui.slider_float("Quality##snapshot", app.snapshot_quality, MIN_SNAPSHOT_QUALITY, MAX_QUALITY,
                                        "%.2f")
        if changed:
            app.set_snapshot_quality(q)
    neural = app.snapshot_is_neural()
    imgui.text_disabled("the network's image, as garmentnerf render" if neural else "the GL scene of this view")
    busy = neural and app.exporting  # one export at a time; GL snapshots never wait
    imgui.begin_disabled(busy)
    if imgui.button("Window size"):
        app.set_snapshot_size(*app.framebuffer_size)
    imgui.same_line()
    if imgui.button("Save PNG (S)"):
        app.do("snapshot")
    imgui.end_disabled()
    job = app.export_job
    if job is not None and job.kind == "snapshot" and not job.finished:
        _export_progress(job, -1.0)
        if imgui.button("Cancel snapshot"):
            app.cancel_export()
    imgui.text_disabled(f"into {app.snapshot_dir}")
    if app.last_snapshot is not None:
        imgui.text_wrapped(f"last: {app.last_snapshot}")


def _export_section(app: "App", em: float) -> None:
    if not imgui.collapsing_header("Export video"):
        return
    s = app.export_settings
    imgui.begin_disabled(app.exporting)  # the settings of a running export are fixed
    modes = list(EXPORT_MODES)
    imgui.set_next_item_width(-6 * em)
    changed, index = imgui.combo("Mode", modes.index(s.mode), [EXPORT_MODES[m] for m in modes])
    if changed:
        s.mode = modes[index]
    imgui.set_next_item_width(-6 * em)
    if s.mode == "turntable":
        changed, count = imgui.input_int("Frames", s.turntable_frames, 1, 10)
        if changed:
            s.turntable_frames = min(MAX_VIDEO_FRAMES, max(1, count))
        _, s.turntable_plays = imgui.checkbox("Motion plays during the turn", s.turntable_plays)
    else:
        changed, frames = imgui.input_int2("Frames A..B", [s.range_first, s.range_last])
        if changed:
            app.set_export_range(*frames)
        if imgui.button("Whole clip"):
            app.set_export_range(0, app.timeline.last_frame)
        imgui.same_line()
        if imgui.button("From this frame"):
            app.set_export_range(app.timeline.frame, s.range_last)
    imgui.set_next_item_width(-6 * em)
    changed, size = imgui.input_int2("Size (px)##export", list(s.size))
    if changed:
        app.set_export_size(*size)
    neural = app.export_source() == "neural"
    if neural:
        imgui.set_next_item_width(-6 * em)
        changed, q = imgui.slider_float("Quality##export", s.quality, MIN_QUALITY, MAX_QUALITY, "%.2f",
                                        imgui.SliderFlags_.logarithmic)
        if changed:
            s.quality = q
    imgui.end_disabled()
    count = s.turntable_frames if s.mode == "turntable" else s.range_last - s.range_first + 1
    what = "the network's image" if neural else "the GL scene"
    imgui.text_disabled(f"{count} frames at {app.sequence.fps:g} fps, {what}")
    job = app.export_job
    if app.exporting and job.kind == "video":
        _export_progress(job, -1.0)
        if imgui.button("Cancel export"):
            app.cancel_export()
    else:
        imgui.begin_disabled(app.exporting)  # a snapshot is rendering: one export at a time
        if imgui.button("Start export"):
            app.start_export_with_status()
        imgui.end_disabled()
    if job is not None and job.finished and job.state == "failed":
        imgui.text_colored(imgui.ImVec4(1.0, 0.45, 0.4, 1.0), f"{job.label} failed:")
        imgui.text_wrapped(job.error)
    if app.last_export is not None:
        imgui.text_wrapped(f"last: {app.last_export}")


def _export_progress(job, width: float, overlay: str | None = None) -> None:
    """A progress bar of ``job`` with ``overlay`` over it (default: its status line: frames, ETA);
    ``width`` -1: the panel's."""
    p = job.progress()
    # a negative, moving value is imgui's indeterminate bar (a single frame reports no progress)
    fraction = p.fraction if p.fraction is not None else -1.0 * imgui.get_time()
    imgui.progress_bar(fraction, imgui.ImVec2(width, 0.0), job.status_line() if overlay is None else overlay)


# ---- stats overlay (top right) ------------------------------------------------------------------
def draw_stats(app: "App") -> None:
    vp = imgui.get_main_viewport()
    pad = 0.6 * imgui.get_font_size()
    imgui.set_next_window_pos(imgui.ImVec2(vp.work_pos.x + vp.work_size.x - pad, vp.work_pos.y + pad),
                              imgui.Cond_.always, imgui.ImVec2(1.0, 0.0))
    imgui.set_next_window_bg_alpha(0.4)
    imgui.begin("##stats", None, _OVERLAY_FLAGS)
    t = app.timer
    fps = t.fps
    imgui.text(f"UI {fps:5.1f} fps ({t.interval_ms:5.1f} ms/frame)" if math.isfinite(fps) and fps > 0
               else "UI -- fps")
    imgui.text_disabled(f"work {t.work_ms:5.1f} ms, scene {t.scene_ms:5.1f} ms")
    w, h = app.framebuffer_size
    imgui.text_disabled(f"{w}x{h} px, {app.scene.samples}x MSAA, scale {app.content_scale:g}")
    imgui.text_disabled(app.gl_renderer)
    if app.neural is not None:
        st = app.neural.stats
        n = app.neural_stats
        if n:
            w, h = n["render_size"]
            imgui.text(f"neural {n['timings'].get('render_total', 0.0):6.0f} ms  q {n['quality']:.2f} ({w}x{h})  "
                       f"frame {n['frame']}{'' if n['cached_frame'] else ' (new)'}")
            t = n["timings"]
            stages = [("frame", t.get("frame_total", 0.0))] if not n["cached_frame"] else []
            stages += [(k, t.get(k, 0.0)) for k in ("rays", "projection", "features", "mlp", "compositing", "decoder")]
            imgui.text_disabled("  ".join(f"{k} {v:.0f}" for k, v in stages) + " ms")
        else:
            imgui.text_disabled("neural: waiting for the first frame ...")
        imgui.text_disabled(f"renders {st.renders}, superseded {st.dropped}, errors {st.errors}")
        if app.timeline.playing:
            motion_fps, neural_fps = app.playback_meter.rates(app.clock())
            dropping = neural_fps < 0.9 * motion_fps
            line = f"playing: {neural_fps:.0f} of {motion_fps:.0f} frames/s rendered" + (
                " (dropping neural frames to keep time)" if dropping else "")
            if dropping:
                imgui.text_colored(imgui.ImVec4(1.0, 0.8, 0.35, 1.0), line)
            else:
                imgui.text_disabled(line)
        if st.last_error:
            imgui.text_colored(imgui.ImVec4(1.0, 0.45, 0.4, 1.0), st.last_error[:120])
    imgui.end()


# ---- help ----------------------------------------------------------------------------------------
def draw_help(app: "App") -> None:
    em = imgui.get_font_size()
    vp = imgui.get_main_viewport()
    imgui.set_next_window_pos(imgui.ImVec2(vp.work_pos.x + vp.work_size.x * 0.5, vp.work_pos.y + vp.work_size.y * 0.45),
                              imgui.Cond_.appearing, imgui.ImVec2(0.5, 0.5))
    imgui.set_next_window_size(imgui.ImVec2(26 * em, 0.0), imgui.Cond_.appearing)
    _, keep_open = imgui.begin("Shortcuts", True, _PANEL_FLAGS)
    table_flags = imgui.TableFlags_.row_bg | imgui.TableFlags_.borders_inner_v
    if imgui.begin_table("##keys", 2, table_flags):
        imgui.table_setup_column("keys", imgui.TableColumnFlags_.width_fixed, 8 * em)
        imgui.table_setup_column("action", imgui.TableColumnFlags_.width_stretch)
        for keys, what in list(help_rows()) + list(MOUSE_HELP):
            imgui.table_next_row()
            imgui.table_set_column_index(0)
            imgui.text(keys)
            imgui.table_set_column_index(1)
            imgui.text_wrapped(what)
        imgui.end_table()
    imgui.end()
    if keep_open is False:
        app.show_help = False
