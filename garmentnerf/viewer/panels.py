"""The window's imgui panels: :func:`draw_all` draws every open one once per UI frame.

The control panel (top left) is :mod:`~garmentnerf.viewer.control_panel`; here are the timeline bar
(bottom), the stats overlay (top right) and the help window (H). Panels read the app's state and
change it only through actions (``app.do`` and the methods of the app and its parts), never
through GL. Sizes are multiples of the font size, so the layout follows the content scale.
"""

from __future__ import annotations

import math
import time

from garmentnerf.viewer.control_panel import draw_controls
from garmentnerf.viewer.export_panel import ERROR_COLOR, export_progress
from garmentnerf.viewer.gui_libs import imgui
from garmentnerf.viewer.playback import frames_behind
from garmentnerf.viewer.shortcuts import MOUSE_HELP, help_rows
from garmentnerf.viewer.timeline import MAX_SPEED, MIN_SPEED

_PANEL_FLAGS = imgui.WindowFlags_.no_saved_settings
_BAR_FLAGS = (imgui.WindowFlags_.no_title_bar | imgui.WindowFlags_.no_resize | imgui.WindowFlags_.no_move
              | imgui.WindowFlags_.no_saved_settings | imgui.WindowFlags_.always_auto_resize
              | imgui.WindowFlags_.no_collapse)
_OVERLAY_FLAGS = (imgui.WindowFlags_.no_decoration | imgui.WindowFlags_.no_saved_settings
                  | imgui.WindowFlags_.always_auto_resize | imgui.WindowFlags_.no_focus_on_appearing
                  | imgui.WindowFlags_.no_nav | imgui.WindowFlags_.no_inputs)


class StatusLine:
    """One line of news in the timeline bar, shown for a few seconds."""

    def __init__(self) -> None:
        self._text, self._since = "", 0.0

    def show(self, text: str) -> None:
        self._text, self._since = text, time.monotonic()

    def message(self, seconds: float = 6.0) -> str:
        """The line while it is younger than ``seconds``, else ``""``."""
        return self._text if self._text and time.monotonic() - self._since < seconds else ""


def draw_all(app) -> tuple[float, float, float, float]:
    """Every open panel (between ``imgui.new_frame`` and ``imgui.render``). Returns the part of the
    window no panel covers, in normalised device coordinates (x0, y0, x1, y1; y up): beside the
    control panel (on the side with more room) and above the timeline bar. The stats overlay and
    the help window float on top and do not count."""
    vp = imgui.get_main_viewport()
    left, top = vp.work_pos.x, vp.work_pos.y
    width, height = max(vp.work_size.x, 1.0), max(vp.work_size.y, 1.0)
    x0, x1, bottom = left, left + width, top + height
    if app.show_ui:
        panel = draw_controls(app)
        if panel is not None:
            if panel[0] - x0 < x1 - panel[2]:
                x0 = min(max(x0, panel[2]), x1 - 1.0)
            else:
                x1 = max(min(x1, panel[0]), x0 + 1.0)
        bottom = min(max(draw_timeline(app), top + 1.0), bottom)
        draw_stats(app)
    if app.show_help:
        draw_help(app)
    return (2.0 * (x0 - left) / width - 1.0, 1.0 - 2.0 * (bottom - top) / height,
            2.0 * (x1 - left) / width - 1.0, 1.0)


# ---- timeline bar (bottom) -----------------------------------------------------------------------
def draw_timeline(app) -> float:
    """The bar along the bottom; returns its top edge (window units)."""
    tl = app.timeline
    vp = imgui.get_main_viewport()
    imgui.set_next_window_pos(imgui.ImVec2(vp.work_pos.x, vp.work_pos.y + vp.work_size.y), imgui.Cond_.always,
                              imgui.ImVec2(0.0, 1.0))
    imgui.set_next_window_size(imgui.ImVec2(vp.work_size.x, 0.0), imgui.Cond_.always)
    imgui.set_next_window_bg_alpha(0.85)
    imgui.begin("Timeline", None, _BAR_FLAGS)
    top = imgui.get_window_pos().y
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
    if imgui.checkbox("Loop", tl.loop)[0]:
        app.do("toggle_loop")
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
        app.go_to_frame(target)
    imgui.same_line()
    imgui.text(f"frame {tl.frame:4d} / {tl.last_frame}   {tl.time:6.2f} s / {tl.num_frames / tl.fps:.2f} s   "
               f"{tl.fps:g} fps")
    message = app.status.message()
    if message:
        imgui.same_line()
        imgui.text_disabled(f"  {message}")
    if app.exports.busy:  # a row of its own while an export runs, whichever panels are open
        export_progress(app.exports.job)
    imgui.set_next_item_width(-1.0)
    changed, frame = imgui.slider_int("##frame", tl.frame, 0, tl.last_frame, "%d")
    app.set_scrubbing(imgui.is_item_active())
    if changed:
        app.set_frame(frame)
    _render_bar(app)
    imgui.end()
    return top


def ready_runs(ready: list[int]) -> list[tuple[int, int]]:
    """Sorted frames -> runs ``(first, last)`` of consecutive frames."""
    runs: list[tuple[int, int]] = []
    for f in ready:
        if runs and f == runs[-1][1] + 1:
            runs[-1] = (runs[-1][0], f)
        else:
            runs.append((f, f))
    return runs


#: Colours of the timeline's bars: frames whose per-frame work is precomputed, frames rendered
#: ahead (finished images), and the mark of the frame the neural image shows.
PRECOMPUTED_COLOR = (0.35, 0.75, 0.4, 1.0)
RENDERED_COLOR = (0.35, 0.6, 1.0, 1.0)
BAKED_COLOR = (0.7, 0.45, 1.0, 1.0)
SHOWN_COLOR = (1.0, 0.7, 0.2, 1.0)


def _render_bar(app) -> None:
    """A video editor's render bars under the frame slider: which frames are precomputed (green),
    which are rendered ahead (blue), which are baked (violet), and a mark at the frame the neural image
    shows (orange)."""
    renderer = app.neural_view.renderer
    status = renderer.cache_status() if renderer is not None else None
    if not status or status["frames"] < 1:
        return
    bakes = app.neural_view.bakes
    baked = sorted(f for f in bakes.baked() if f < status["frames"]) if bakes is not None else []
    lo, hi = imgui.get_item_rect_min(), imgui.get_item_rect_max()
    width, n = hi.x - lo.x, status["frames"]
    top = hi.y + 1.0
    draw = imgui.get_window_draw_list()
    for row, (frames, color) in enumerate(((status["ready"], PRECOMPUTED_COLOR),
                                           (status["finished"], RENDERED_COLOR), (baked, BAKED_COLOR))):
        y = top + 4.0 * row
        u32 = imgui.get_color_u32(imgui.ImVec4(*color))
        for first, last in ready_runs(frames):
            draw.add_rect_filled(imgui.ImVec2(lo.x + width * first / n, y),
                                 imgui.ImVec2(lo.x + width * (last + 1) / n, y + 3.0), u32)
    shown = app.neural_view.shown_frame
    if shown is not None and shown < n:
        x = lo.x + width * (shown + 0.5) / n
        draw.add_rect_filled(imgui.ImVec2(x - 1.5, lo.y), imgui.ImVec2(x + 1.5, top + 11.0),
                             imgui.get_color_u32(imgui.ImVec4(*SHOWN_COLOR)))
    imgui.dummy(imgui.ImVec2(0.0, 12.0))


# ---- stats overlay (top right) ------------------------------------------------------------------
def draw_stats(app) -> None:
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
    imgui.text_disabled(f"work {t.work_ms:5.1f} ms, scene {t.scene_ms:5.1f} ms at x{app.scene_draw_scale:.2f}")
    w, h = app.window.framebuffer_size
    imgui.text_disabled(f"{w}x{h} px, {app.scene.samples}x MSAA, scale {app.window.content_scale:g}")
    imgui.text_disabled(app.window.gl_renderer)
    if app.neural_view.renderer is not None:
        _neural_stats(app)
    imgui.end()


def _neural_stats(app) -> None:
    view = app.neural_view
    st, n = view.renderer.stats, view.last_result
    if n:
        w, h = n["render_size"]
        imgui.text(f"neural {n['timings'].get('render_total', 0.0):6.0f} ms  q {n['quality']:.2f} ({w}x{h})  "
                   f"frame {n['frame']}{'' if n['cached_frame'] else ' (new)'}")
        t = n["timings"]
        stages = [("frame", t.get("frame_total", 0.0))] if not n["cached_frame"] else []
        stages += [(k, t.get(k, 0.0)) for k in ("rays", "projection", "features", "mlp", "compositing", "decoder")]
        imgui.text_disabled("  ".join(f"{k} {v:.0f}" for k, v in stages) + " ms")
    else:
        imgui.text_colored(imgui.ImVec4(*SHOWN_COLOR), garment_status(view.renderer.activity))
    share = st.completed_share
    imgui.text_disabled(f"renders {st.renders} of {st.started} started"
                        + (f" ({100 * share:.0f}%)" if share is not None else "")
                        + f", superseded {st.dropped}, errors {st.errors}")
    if view.watcher is not None or view.weights_step:
        shown_step = view.shown.weights_step if view.shown is not None else None
        line = f"weights: step {view.weights_step}" + (
            f" (image: step {shown_step})" if shown_step is not None and shown_step != view.weights_step else "")
        imgui.text_disabled(line + (", watching the run" if view.watcher is not None else ""))
        if view.watcher is not None and view.watcher.error:
            imgui.text_colored(imgui.ImVec4(*ERROR_COLOR), view.watcher.error[:120])
    shown = view.shown_frame
    if shown is not None:
        tl = app.timeline
        behind = frames_behind(shown, tl.frame, tl.num_frames, tl.loop)
        line = f"image: frame {shown}, playhead {tl.frame}" + (f" ({behind} behind)" if behind else " (in step)")
        if behind:
            imgui.text_colored(imgui.ImVec4(*SHOWN_COLOR), line)
        else:
            imgui.text_disabled(line)
        status = view.renderer.cache_status()
        if status is not None:
            imgui.text_disabled(f"rendered ahead {len(status['finished'])} / {status['frames']} frames "
                                f"({status['finished_bytes'] / 2**20:.0f} MiB), render "
                                f"{1000 * view.renderer.render_time.seconds:.0f} ms")
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
        imgui.text_colored(imgui.ImVec4(*ERROR_COLOR), st.last_error[:120])


def garment_status(activity: tuple[str, int | None]) -> str:
    """The overlay's line while no neural image is shown (the window draws the body meanwhile):
    what the render worker is doing (:attr:`NeuralRenderer.activity <garmentnerf.viewer.worker.NeuralRenderer>`)."""
    what, frame = activity
    if what == "rendering" and frame is not None:
        return f"garment: rendering frame {frame} ..."
    return "garment: starting the renderer ..."


# ---- help ----------------------------------------------------------------------------------------
def draw_help(app) -> None:
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
        app.do("toggle_help")
