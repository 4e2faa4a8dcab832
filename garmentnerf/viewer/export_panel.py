"""The Snapshot and Export video sections of the control panel, and an export's progress bar.

They read the app's :class:`~garmentnerf.viewer.exporting.Exports` and change it only through its
methods (and the :class:`~garmentnerf.viewer.export_jobs.ExportSettings` the Export section edits).
"""

from __future__ import annotations

from garmentnerf.viewer.export_jobs import EXPORT_MODES, MAX_QUALITY, MIN_QUALITY, MIN_SNAPSHOT_QUALITY
from garmentnerf.viewer.gui_libs import imgui

ERROR_COLOR = (1.0, 0.45, 0.4, 1.0)


def export_progress(job, width: float = -1.0) -> None:
    """A progress bar of ``job`` with its status line (frames, ETA) over it; ``width`` -1: the panel's."""
    p = job.progress()
    # a negative, moving value is imgui's indeterminate bar (a single frame reports no progress)
    fraction = p.fraction if p.fraction is not None else -1.0 * imgui.get_time()
    imgui.progress_bar(fraction, imgui.ImVec2(width, 0.0), job.status_line())


def snapshot_section(app, em: float) -> None:
    if not imgui.collapsing_header("Snapshot"):
        return
    exports = app.exports
    imgui.set_next_item_width(-6 * em)
    changed, size = imgui.input_int2("Size (px)", list(exports.snapshot_size))
    if changed:
        exports.set_snapshot_size(*size)
    if app.neural_view.run is not None:
        imgui.set_next_item_width(-6 * em)
        changed, q = imgui.slider_float("Quality##snapshot", exports.snapshot_quality, MIN_SNAPSHOT_QUALITY,
                                        MAX_QUALITY, "%.2f")
        if changed:
            exports.set_snapshot_quality(q)
    neural = exports.snapshot_is_neural()
    imgui.text_disabled("the network's image, as garmentnerf render" if neural else "the GL scene of this view")
    imgui.begin_disabled(neural and exports.busy)  # one export at a time; GL snapshots never wait
    if imgui.button("Window size"):
        exports.set_snapshot_size(*app.window.framebuffer_size)
    imgui.same_line()
    if imgui.button("Save PNG (S)"):
        app.do("snapshot")
    imgui.end_disabled()
    job = exports.job
    if job is not None and job.kind == "snapshot" and not job.finished:
        export_progress(job)
        if imgui.button("Cancel snapshot"):
            exports.cancel()
    imgui.text_disabled(f"into {exports.directory}")
    if exports.last_snapshot is not None:
        imgui.text_wrapped(f"last: {exports.last_snapshot}")


def export_section(app, em: float) -> None:
    if not imgui.collapsing_header("Export video"):
        return
    exports = app.exports
    s = exports.settings
    imgui.begin_disabled(exports.busy)  # the settings of a running export are fixed
    modes = list(EXPORT_MODES)
    imgui.set_next_item_width(-6 * em)
    changed, index = imgui.combo("Mode", modes.index(s.mode), [EXPORT_MODES[m] for m in modes])
    if changed:
        exports.set_mode(modes[index])
    imgui.set_next_item_width(-6 * em)
    if s.mode == "turntable":
        changed, count = imgui.input_int("Frames", s.turntable_frames, 1, 10)
        if changed:
            exports.set_turntable(count, s.turntable_plays)
        changed, plays = imgui.checkbox("Motion plays during the turn", s.turntable_plays)
        if changed:
            exports.set_turntable(s.turntable_frames, plays)
    elif s.mode == "path":
        imgui.text_disabled("the frames and cameras of the Camera path section")
    else:
        changed, frames = imgui.input_int2("Frames A..B", [s.range_first, s.range_last])
        if changed:
            exports.set_range(*frames)
        if imgui.button("Whole clip"):
            exports.set_range(0, app.timeline.last_frame)
        imgui.same_line()
        if imgui.button("From this frame"):
            exports.set_range(app.timeline.frame, s.range_last)
    imgui.set_next_item_width(-6 * em)
    changed, size = imgui.input_int2("Size (px)##export", list(s.size))
    if changed:
        exports.set_video_size(*size)
    neural = exports.source() == "neural"
    if neural:
        imgui.set_next_item_width(-6 * em)
        changed, q = imgui.slider_float("Quality##export", s.quality, MIN_QUALITY, MAX_QUALITY, "%.2f",
                                        imgui.SliderFlags_.logarithmic)
        if changed:
            exports.set_video_quality(q)
    imgui.end_disabled()
    if s.mode == "path":
        path = app.camera_path(s.size)
        count = len(path.frames()) if path is not None else 0
    else:
        count = s.turntable_frames if s.mode == "turntable" else s.range_last - s.range_first + 1
    what = "the network's image" if neural else "the GL scene"
    imgui.text_disabled(f"{count} frames at {app.sequence.fps:g} fps, {what}")
    job = exports.job
    if exports.busy and job.kind == "video":
        export_progress(job)
        if imgui.button("Cancel export"):
            exports.cancel()
    else:
        imgui.begin_disabled(exports.busy)  # a snapshot is rendering: one export at a time
        if imgui.button("Start export"):
            exports.start_video_with_status()
        imgui.end_disabled()
    if job is not None and job.finished and job.state == "failed":
        imgui.text_colored(imgui.ImVec4(*ERROR_COLOR), f"{job.label} failed:")
        imgui.text_wrapped(job.error)
    if exports.last_export is not None:
        imgui.text_wrapped(f"last: {exports.last_export}")
