"""The Camera path section of the control panel: keyframes from the current view and frame, the list
(go to, take the current view, move, delete), timing, looking through the path, save and load.

It reads the app's :class:`~garmentnerf.viewer.path_editor.PathEditor` and changes it through the
app's actions and the editor's methods; export along the path is the Export video section's
"Camera path" mode.
"""

from __future__ import annotations

from garmentnerf.viewer.export_panel import ERROR_COLOR
from garmentnerf.viewer.gui_libs import imgui


def camera_path_section(app, em: float) -> None:
    editor = app.path_editor
    if not imgui.collapsing_header("Camera path"):
        return
    if imgui.button("Add keyframe (K)"):
        app.do("add_keyframe")
    imgui.same_line()
    imgui.begin_disabled(not editor.keyframes)
    if imgui.button("Clear all"):
        app.clear_keyframes()
    imgui.end_disabled()
    changed, on = imgui.checkbox("View through the path (P)", editor.look_through)
    if changed:
        app.set_path_view(on)
    changed, on = imgui.checkbox("Constant speed", editor.constant_speed)
    if changed:
        editor.set_constant_speed(on)
    if imgui.is_item_hovered():
        imgui.set_tooltip("on: the camera moves at an even speed from the first keyframe's frame to the last's; "
                          "off: each keyframe is reached at its own frame")
    changed, on = imgui.checkbox("Draw the path", editor.show)
    if changed:
        editor.set_show(on)
    _keyframe_list(app, em)
    imgui.set_next_item_width(-6 * em)
    changed, file = imgui.input_text("File", editor.file)
    if changed:
        editor.set_file(file)
    if imgui.button("Save"):
        app.save_camera_path()
    imgui.same_line()
    if imgui.button("Load"):
        app.load_camera_path()
    error = app.path_error
    if error:
        imgui.text_colored(imgui.ImVec4(*ERROR_COLOR), error)


def _keyframe_list(app, em: float) -> None:
    editor = app.path_editor
    if not editor.keyframes:
        imgui.text_disabled("no keyframes: orbit to a view, pick a frame, press K")
        return
    path = app.camera_path()
    imgui.text_disabled(f"{len(editor.keyframes)} keyframes, frames {path.first_frame:g}..{path.last_frame:g} "
                        f"({len(path.frames())} video frames)")
    for i, key in enumerate(list(editor.keyframes)):
        imgui.push_id(i)
        imgui.set_next_item_width(5 * em)
        changed, frame = imgui.input_int("##frame", int(round(key.frame)), 0, 0,
                                         imgui.InputTextFlags_.enter_returns_true)
        if changed:
            app.move_keyframe(i, frame)
        imgui.same_line()
        imgui.text(f"{key.fov_y:.0f} deg")
        imgui.same_line()
        if imgui.small_button("Go"):
            app.go_to_keyframe(i)
        imgui.same_line()
        if imgui.small_button("Set view"):
            app.replace_keyframe_view(i)
        imgui.same_line()
        if imgui.small_button("Delete"):
            app.remove_keyframe(i)
        imgui.pop_id()
