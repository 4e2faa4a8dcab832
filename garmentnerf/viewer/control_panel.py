"""The control panel (top left): garment, motion, camera, camera path, display, neural render, palette, snapshot, export.

Each section reads the app's state and changes it only through actions (methods of the app, its
neural view, its exports) or the panel rows the renderables draw themselves (``gui(imgui)``);
never through GL. Sizes are multiples of the font size, so the layout follows the content scale.
"""

from __future__ import annotations

from garmentnerf.model.palette import palette_names
from garmentnerf.render.presets import VIEWER_LEVELS
from garmentnerf.viewer.camera import MAX_FOV_Y, MIN_FOV_Y, VIEW_DIRECTIONS
from garmentnerf.viewer.export_panel import ERROR_COLOR, export_section, snapshot_section
from garmentnerf.viewer.gui_libs import imgui
from garmentnerf.viewer.neural_view import GROUND_TRUTH_MODES, VIEW_MODES
from garmentnerf.viewer.palette_layer import MAP_VIEWS
from garmentnerf.viewer.path_panel import camera_path_section
from garmentnerf.viewer.scene_gl import MIN_RENDER_SCALE

_PANEL_FLAGS = imgui.WindowFlags_.no_saved_settings


def draw_controls(app) -> tuple[float, float, float, float] | None:
    """The panel; returns the window-unit rect (x0, y0, x1, y1) it covers, None while collapsed."""
    em = imgui.get_font_size()
    imgui.set_next_window_pos(imgui.ImVec2(0.6 * em, 0.6 * em), imgui.Cond_.first_use_ever)
    imgui.set_next_window_size(imgui.ImVec2(20 * em, 0.0), imgui.Cond_.first_use_ever)
    imgui.set_next_window_bg_alpha(0.88)
    expanded, _ = imgui.begin("garmentnerf", None, _PANEL_FLAGS)
    covered = None
    if expanded:
        pos, size = imgui.get_window_pos(), imgui.get_window_size()
        covered = (pos.x, pos.y, pos.x + size.x, pos.y + size.y)
        _garment_section(app)
        _motion_section(app)
        _camera_section(app, em)
        camera_path_section(app, em)
        _display_section(app)
        _neural_section(app, em)
        _palette_section(app)
        snapshot_section(app, em)
        export_section(app, em)
        imgui.separator()
        imgui.text_disabled("H or F1: shortcuts and mouse help")
    imgui.end()
    return covered


def _garment_section(app) -> None:
    """The bundled demos (one per garment of the paper's Table 1): choosing one loads it in the
    background; body, motion and camera stay."""
    names = app.garments.names()
    if not names or not imgui.collapsing_header("Garment", imgui.TreeNodeFlags_.default_open):
        return
    current = app.garments.current
    other = [] if current in names else ["(a run that is not a demo)"]  # shown first, not choosable
    shown = other + names
    imgui.set_next_item_width(-1.0)
    changed, index = imgui.combo("##garment", shown.index(current) if current in names else 0,
                                 other + app.garments.labels(names))
    if changed and shown[index] in names and shown[index] != current:
        app.switch_garment(shown[index])
    loading = app.garments.loading
    if loading:
        imgui.text_disabled(f"loading the {loading} ...")


def _motion_section(app) -> None:
    if not imgui.collapsing_header("Motion", imgui.TreeNodeFlags_.default_open):
        return
    names = app.motions.names(app.motion_name)
    current = names.index(app.motion_name) if app.motion_name in names else 0
    imgui.set_next_item_width(-1.0)
    changed, index = imgui.combo("##motion", current, app.motions.labels(names))
    if changed and names[index] != app.motion_name:
        app.load_motion(names[index])
    loading = app.motions.loading
    if loading:
        imgui.text_disabled(f"loading {loading} ...")
    seq = app.sequence
    imgui.text(f"{seq.name}: {seq.num_frames} frames at {seq.fps:g} fps")
    imgui.text_disabled(f"body shape: {app.shape_label}, {seq.num_vertices} vertices")


def _camera_section(app, em: float) -> None:
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
        cam.set_azimuth(value)
    imgui.set_next_item_width(-6 * em)
    changed, value = imgui.slider_float("Elevation", cam.elevation, -cam.max_elevation, cam.max_elevation, "%.0f deg")
    if changed:
        cam.set_elevation(value)
    imgui.set_next_item_width(-6 * em)
    changed, value = imgui.slider_float("Distance", cam.distance, cam.min_distance, cam.max_distance, "%.2f m",
                                        imgui.SliderFlags_.logarithmic)
    if changed:
        cam.set_distance(value)
    imgui.set_next_item_width(-6 * em)
    changed, value = imgui.slider_float("Field of view", cam.fov_y, MIN_FOV_Y, MAX_FOV_Y, "%.0f deg")
    if changed:
        cam.set_fov(value)
    changed, follow = imgui.checkbox("Follow the body (T)", cam.follow)
    if changed:
        app.set_follow(follow)


def _display_section(app) -> None:
    if not imgui.collapsing_header("Display"):
        return
    app.scene.floor.gui(imgui)
    app.scene.body.gui(imgui)
    changed, scale = imgui.slider_float("Render scale", app.scene.render_scale, MIN_RENDER_SCALE, 1.0, "%.2f")
    if changed:
        app.scene.set_render_scale(scale)
    changed, on = imgui.checkbox("Smaller while moving", app.scene_scale.dynamic)
    if changed:
        app.scene_scale.set_dynamic(on)
    if imgui.is_item_hovered():
        imgui.set_tooltip(f"draw the scene at the scale that fits {app.scene_scale.target_ms:.0f} ms while the "
                          f"view moves, then sharp once it is still")


def _neural_section(app, em: float) -> None:
    view = app.neural_view
    if view.run is None or not imgui.collapsing_header("Neural render", imgui.TreeNodeFlags_.default_open):
        return
    _combo(em, "View (V)", list(VIEW_MODES), view.mode, view.set_mode, labels=list(VIEW_MODES.values()))
    if view.mode == "maps":
        _combo(em, "Map", list(MAP_VIEWS), app.scene.palette_layer.map_view, view.set_map_view)
    if view.can_rasterise_body:
        changed, on = imgui.checkbox("Body from its learned texture", view.composition == "raster_body")
        if changed:
            view.set_composition("raster_body" if on else "nerf")
        if imgui.is_item_hovered():
            imgui.set_tooltip("on: the posed body rasterised with the run's learned appearance, the network's "
                              "garment over it; off: the network draws the body too (the paper's composition)")
    if view.mode == "neural":
        changed, on = imgui.checkbox("Rasterised body too (by depth)", view.body_with_neural)
        if changed:
            view.set_body_with_neural(on)
    names = view.run.scene.camera_names() if view.run.scene is not None else []
    if names and view.mode in GROUND_TRUTH_MODES:
        _combo(em, "Scene camera", names, view.gt_camera if view.gt_camera in names else names[0], view.set_gt_camera)
        if not view.ground_truth_available():
            imgui.text_disabled("no ground truth: pick a scene sequence")
    if view.can_bake:
        _bake_controls(view)
    q = view.quality
    _combo(em, "Quality", list(VIEWER_LEVELS), q.preset, q.set_preset)
    changed, on = imgui.checkbox("Coarser while moving", q.dynamic)
    if changed:
        q.set_dynamic(on)
    status = view.renderer.cache_status() if view.renderer is not None else None
    if status is not None:
        imgui.set_next_item_width(-6 * em)
        changed, mb = imgui.slider_float("Frame cache", status["budget_bytes"] / 2**20, 0.0, 4096.0, "%.0f MiB",
                                         imgui.SliderFlags_.logarithmic)
        if changed:
            view.set_cache_mb(mb)
        imgui.text_disabled(f"{len(status['ready'])} / {status['frames']} frames ready, "
                            f"{status['bytes'] / 2**20:.0f} MiB (half precision)")
        renderer = view.renderer
        changed, on = imgui.checkbox("Render ahead", renderer.render_ahead)
        if changed:
            renderer.set_render_ahead(on)
        if imgui.is_item_hovered():
            imgui.set_tooltip("while the camera is still, render the frames after the playhead at this quality; "
                              "playing over them shows every frame at the clip's rate (blue bar under the timeline)")
        imgui.same_line()
        changed, on = imgui.checkbox("Play every frame", app.play_every_frame)
        if changed:
            app.set_play_every_frame(on)
        if imgui.is_item_hovered():
            imgui.set_tooltip("playing waits for each frame's neural image instead of dropping frames to keep time")
        imgui.set_next_item_width(-6 * em)
        changed, mb = imgui.slider_float("Rendered", status["finished_budget_bytes"] / 2**20, 0.0, 8192.0,
                                         "%.0f MiB", imgui.SliderFlags_.logarithmic)
        if changed:
            renderer.set_finished_mb(mb)
        imgui.text_disabled(f"{len(status['finished'])} / {status['frames']} frames rendered, "
                            f"{status['finished_bytes'] / 2**20:.0f} MiB")
    error = view.error()
    if error:
        imgui.text_colored(imgui.ImVec4(*ERROR_COLOR), "render failed:")
        imgui.text_wrapped(error)


def _bake_controls(view) -> None:
    """"Bake the clip": the switch, what is baked (the violet bar under the timeline) and what shows."""
    changed, on = imgui.checkbox("Bake the clip", view.bake_wanted)
    if changed:
        view.set_baking(on)
    if imgui.is_item_hovered():
        imgui.set_tooltip("bake each frame's garment once, in the background on one core (kept in your cache): "
                          "baked frames orbit and play at display rate, recolour exactly, and the exact neural "
                          "image replaces the bake when the camera rests (violet bar under the timeline)")
    status = view.bake_status()
    if status is not None and status["frames"]:
        state = "baking" if status["running"] else "baked"
        left = status["seconds_left"]
        eta = f", {left / 60:.0f} min left" if status["running"] and left else ""
        imgui.text_disabled(f"{state} {status['baked']} / {status['frames']} frames{eta}, {status['loaded']} loaded"
                            + (f"; showing the {view.showing_bake}" if view.showing_bake else ""))
    if status is not None and status["error"]:
        imgui.text_colored(imgui.ImVec4(*ERROR_COLOR), status["error"][:120])


def _combo(em: float, label: str, keys: list, current, choose, labels: list | None = None) -> None:
    """A combo box of ``keys`` (shown as ``labels``) with ``current`` selected; ``choose(key)`` on a change."""
    imgui.set_next_item_width(-6 * em)
    changed, index = imgui.combo(label, keys.index(current), labels or [str(k) for k in keys])
    if changed:
        choose(keys[index])


def _palette_section(app) -> None:
    view = app.neural_view
    if not imgui.collapsing_header("Garment palette", imgui.TreeNodeFlags_.default_open if view.palette is not None
                                   else 0):
        return
    if view.palette is None:
        imgui.text_wrapped("No garment model loaded (body only). Open a run with garmentnerf view --run DIR "
                           "to recolor its neural garment.")
        return
    names = palette_names(len(view.palette))
    flags = imgui.ColorEditFlags_.float | imgui.ColorEditFlags_.display_hex
    for i in range(len(view.palette)):
        changed, col = imgui.color_edit3(names[i], [float(c) for c in view.palette[i]], flags)
        if changed:
            view.set_palette_color(i, col[:3])
    if imgui.button("Reset to learned palette"):
        view.reset_palette()
    imgui.text_disabled("recoloring only changes a shader uniform")

