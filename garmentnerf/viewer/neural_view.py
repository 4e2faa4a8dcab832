"""The neural view: what the window's neural layer shows, and asking the render worker for it.

:class:`NeuralView` owns the view mode (:data:`VIEW_MODES`), the palette being edited (the learned
one until changed), the scene camera whose ground truth is shown, the quality controller, the
:class:`~garmentnerf.viewer.worker.NeuralRenderer` and its result sink. Per UI frame the app calls
:meth:`NeuralView.update`: finished renders are drained into the statistics and the quality
controller, and when the view, the frame or the quality changed the newest request goes to the
worker (which coalesces them; the request carries the timeline's playhead clock, so the worker
chooses the frame, :mod:`~garmentnerf.viewer.playback`). Then the UI thread chooses what the layer
shows: the finished frame at the playhead from the render-ahead cache
(:class:`~garmentnerf.viewer.finished_frames.FinishedFrames`), else the newest result unless it lies
ahead of the playhead, and hands it to the palette layer's ``submit``; the torch work never runs
on the UI thread. A newer checkpoint of the run (``watch``) is taken over here too.

Baked frames (:mod:`~garmentnerf.viewer.bakes`): with a run that composes over the rasterised body, a
background process bakes the clip into the user's cache (on by default; the "Bake the clip" switch).
In the ``neural`` mode the window then shows, per UI frame: the exact neural image when it is the
still view of this camera at this frame; else the frame's bake drawn from this camera (the baked layer,
:mod:`~garmentnerf.viewer.baked_layer`); else the last neural image of this frame reprojected by its
depth to this camera; else the neural layer as before. While the view moves over a baked frame, or a
baked stretch of the clip plays, no neural frame is asked for (the bake shows every frame from any camera,
and the cores go to the window); the exact still is asked for once the view rests.

Modes: ``neural`` (the network's image, composited into the scene; optionally with the rasterised
body by depth), ``ground_truth``, ``side_by_side`` (network | ground truth, fitted beside the
panels), ``difference``, ``body`` (the rasterised body only, no neural layer) and ``maps`` (the raw
decomposed maps). The ground-truth modes render the chosen scene camera's view, and only exist for
the run scene's sequences. Without a run only ``body`` is available.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable

import numpy as np

from garmentnerf.bake.settings import DEFAULT_BAKE_PRESET
from garmentnerf.bake.store import BakeFolder
from garmentnerf.bake.views import BakedFrame
from garmentnerf.model.config import BACKGROUND
from garmentnerf.viewer.bakes import BakeProcess, ClipBakes
from garmentnerf.viewer.checkpoint_watch import CheckpointWatcher
from garmentnerf.viewer.palette_layer import MAP_VIEWS
from garmentnerf.viewer.playback import PlayheadClock, replaces_shown, show_newest
from garmentnerf.viewer.quality import QualityController
from garmentnerf.viewer.worker import NeuralRenderer, NeuralRequest

#: View modes: label per key, in menu order.
VIEW_MODES = {"neural": "Neural render", "ground_truth": "Ground truth", "side_by_side": "Side by side",
              "difference": "Difference", "body": "Body only", "maps": "Maps"}
#: View modes that show the ground truth (and so render the scene camera's view).
GROUND_TRUTH_MODES = ("ground_truth", "side_by_side", "difference")


def _stop_all(renderer, watcher) -> None:
    """Stop a replaced run's worker and checkpoint watcher (either may be None)."""
    if watcher is not None:
        watcher.close()
    if renderer is not None:
        renderer.stop()


def submit_result(layer, result) -> None:
    """Put a :class:`~garmentnerf.viewer.worker.NeuralResult` on a
    :class:`~garmentnerf.viewer.palette_layer.PaletteLayer` (its maps, depth, body, ground truth)."""
    layer.submit(result.layers, result.depth, result.image_size, tag=(result.frame, result.quality),
                 body=result.body, origin=result.origin, map_size=result.render_size)
    if result.ground_truth is not None:
        layer.submit_ground_truth(result.ground_truth)


class NeuralView:
    """See the module docstring.

    Args:
        scene: the window's :class:`~garmentnerf.viewer.scene_gl.SceneRenderer` (its palette layer and body).
        run: a :class:`~garmentnerf.runs.LoadedRun`, or None (body only).
        motion: the motion spec the worker's session renders (a scene sequence or motion name).
        status: shows one line on the window's status line.
        clock: seconds (the quality controller's time base).
        watch: show each new checkpoint of the run's folder as it lands
            (:class:`~garmentnerf.viewer.checkpoint_watch.CheckpointWatcher`; loaded off the UI thread).
    """

    def __init__(self, scene, run, motion, status: Callable[[str], None], clock: Callable[[], float],
                 watch: bool = False, bake: bool = True) -> None:
        self.scene, self.run, self.motion = scene, run, motion
        self.watcher = None                             # the CheckpointWatcher (watch=True with a run)
        self._status, self._clock = status, clock
        self.mode = "neural" if run is not None else "body"
        self.quality = QualityController()
        self.body_with_neural = False
        # the run's body appearance draws the body rasterised (raster_body); without one the network does
        self.composition = "raster_body" if self.can_rasterise_body else "nerf"
        self.learned_palette: np.ndarray | None = None  # (P, 3) in [0, 1]
        self.palette: np.ndarray | None = None          # (P, 3): what the shader composes with
        self.gt_camera: str | None = None
        self.last_result: dict = {}                     # the shown result's figures (overlay, stats hook)
        self.results: deque = deque(maxlen=64)          # the result sink: worker thread -> UI thread
        self.renderer = None                            # the NeuralRenderer (None without a run)
        self._watch = bool(watch)
        self.shown = None                               # the NeuralResult on the layer (its frame: the image's)
        self._newest = None                             # the newest result delivered
        self._last_request = None
        self._sent_clock = None                         # the PlayheadClock of the last request
        self._keys = None                               # (still, requested) view keys of the last update
        self._clip_serial = 0
        self.bake_wanted = bool(bake)                   # bake the clip (when the run can be baked)
        self.bakes: ClipBakes | None = None             # the clip's baked frames (loaded off the UI thread)
        self.bake_process: BakeProcess | None = None    # the process baking the clip
        self.showing_bake = ""                          # what the baked layer shows: "", "bake", "reprojection"
        self._reprojected = None                        # (result, BakedFrame) of the last reprojection
        self._baked_playback = False                    # a baked stretch plays: no neural request is sent
        self._playhead = 0                              # the timeline's frame at the last update
        if run is not None:
            self._start()

    def _start(self) -> None:
        run, layer = self.run, self.scene.palette_layer
        self.learned_palette = run.palette().detach().cpu().numpy().astype(np.float32)
        self.palette = self.learned_palette.copy()
        layer.set_palette(self.palette)
        layer.background = tuple(float(c) for c in BACKGROUND)
        body = run.model.body
        if self.can_rasterise_body:
            layer.set_body_model(body, run.body_appearance)
            self.scene.body.set_appearance(body.uv, body.uv_faces, run.body_appearance)  # the stand-in's look
        else:
            self.scene.body.set_appearance(None, None, None)
        if run.scene is not None:
            names = run.scene.camera_names("train") or run.scene.camera_names()
            self.gt_camera = names[0] if names else None
        self.set_mode(self.mode)
        renderer = NeuralRenderer(run, lambda result, request: self._sink(result, request, renderer), self.motion,
                                  clock=self._clock)
        self.renderer = renderer
        self.scene.baked_layer.palette = self.palette
        self.set_baking(self.bake_wanted)
        if self._watch:
            self.watcher = CheckpointWatcher(run)

    def replace_run(self, run) -> None:
        """Show another run (another garment, :mod:`~garmentnerf.viewer.garment_menu`) from the
        next frame on: a worker of its own, its learned palette, composition and ground-truth camera.
        The view mode and the motion stay; unlike a newer checkpoint of the same run
        (:meth:`_take_checkpoint`) no render, cache or palette edit of the old run carries over.
        The old worker is stopped on a thread of its own (it may be mid-render: the window does not
        wait for it), and its results are dropped (:meth:`_sink`)."""
        old_renderer, old_watcher = self.renderer, self.watcher
        self.watcher = self.renderer = None
        self._stop_baking()
        threading.Thread(target=_stop_all, args=(old_renderer, old_watcher), name="garmentnerf-old-garment",
                         daemon=True).start()
        self._watch = False  # a demo is not training
        self.run = run
        self.composition = "raster_body" if self.can_rasterise_body else "nerf"
        self.shown = self._newest = self._last_request = self._sent_clock = self._keys = None
        self.results.clear()
        self.last_result = {}
        self._clip_serial += 1
        self.scene.palette_layer.submit_ground_truth(None)
        if self.mode == "body":
            self.mode = "neural"
        self._start()

    @property
    def weights_step(self) -> int:
        """The training step of the weights the worker renders with (the newest checkpoint loaded)."""
        return int(getattr(self.run, "step", 0) or 0)

    def _take_checkpoint(self) -> None:
        """A newer checkpoint the watcher loaded goes to the worker; the learned palette follows it
        (and the palette shown too, unless it was edited)."""
        run = self.watcher.poll() if self.watcher is not None else None
        if run is None:
            return
        edited = self.palette is not None and not np.array_equal(self.palette, self.learned_palette)
        self.run = run
        self.renderer.set_run(run)
        self.learned_palette = run.palette().detach().cpu().numpy().astype(np.float32)
        if not edited:
            self.palette = self.learned_palette.copy()
            self.scene.palette_layer.set_palette(self.palette)
            self.scene.baked_layer.palette = self.palette
        if self.bakes is not None:  # the bakes were of the old weights: bake the new ones
            self._stop_baking()
            self.set_baking(self.bake_wanted)
        self._status(f"checkpoint step {run.step} loaded: showing it")

    def _sink(self, result, request, renderer) -> None:
        """Worker thread: queue the result of ``renderer`` for the UI thread (which chooses what the
        layer shows); a result of a renderer replaced meanwhile (:meth:`replace_run`) is dropped."""
        if renderer is self.renderer:
            self.results.append(result)

    def _show(self, result, playback_meter=None) -> None:
        """Put ``result`` on the palette layer (thread-safe; uploaded at the next draw)."""
        if result is self.shown:
            return
        submit_result(self.scene.palette_layer, result)
        self.shown = result
        # the overlay's figures are the shown image's: where its time went
        self.last_result = {"renders": self.renderer.stats.renders, "quality": result.quality,
                            "render_size": list(result.render_size), "frame": result.frame,
                            "cached_frame": result.cached_frame,
                            "timings": {k: round(float(v), 2) for k, v in result.timings.items()}}
        if playback_meter is not None:
            playback_meter.neural_received(result.frame, self._clock())

    # ---- actions ----------------------------------------------------------------------------------
    def ground_truth_available(self) -> bool:
        run = self.run
        return (run is not None and run.scene is not None and self.gt_camera is not None
                and self.motion in run.scene.sequences)

    def set_mode(self, mode: str) -> None:
        """Show ``mode`` (a key of :data:`VIEW_MODES`; without a run only ``body``, said on the status line)."""
        if mode not in VIEW_MODES:
            raise ValueError(f"unknown view mode '{mode}' (known: {', '.join(VIEW_MODES)})")
        if self.run is None and mode != "body":
            self._status("no run loaded: body only (open one with garmentnerf view --run DIR)")
            mode = "body"
        self.mode = mode
        layer = self.scene.palette_layer
        layer.visible = mode != "body"
        layer.side_by_side = mode == "side_by_side"
        layer.mode = mode if mode in ("ground_truth", "difference", "maps") else "neural"
        layer.use_depth = mode == "neural" and self.body_with_neural
        if mode != "neural":  # the bake shows in the neural mode only (chosen per UI frame, _choose_bake)
            self.scene.baked_layer.visible, self.scene.baked_layer.frame = False, None
            self.showing_bake = ""
        self.scene.body.visible = mode == "body" or (mode == "neural" and self.body_with_neural)
        self.sync_body()
        if mode in GROUND_TRUTH_MODES and not self.ground_truth_available():
            self._status("no ground truth for this motion (only the run scene's sequences have it)")

    @property
    def waiting_for_garment(self) -> bool:
        """A neural mode is shown and no neural image has reached the layer yet (none drawn, none
        on its way to the next draw): the window draws the posed body meanwhile (:meth:`sync_body`)."""
        layer = self.scene.palette_layer
        return self.run is not None and self.mode != "body" and not layer.has_image and not layer.arriving

    def sync_body(self) -> None:
        """Per UI frame, before the scene is drawn: while :attr:`waiting_for_garment`, the rasterised
        body stands in (depth tested, in the run's learned appearance times the body's palette colour
        when the run has one, else the studio material), so the stage is never empty; it goes as
        soon as the first neural image (which carries the body) is drawn."""
        body = self.scene.body
        body.standin = self.waiting_for_garment or self.scene.baked_layer.visible
        body.learned = body.standin and not body.visible and body.has_appearance and self.palette is not None
        if body.learned:
            body.tint = tuple(float(c) for c in self.palette[-1])

    def next_mode(self) -> None:
        modes = list(VIEW_MODES)
        self.set_mode(modes[(modes.index(self.mode) + 1) % len(modes)])

    def set_body_with_neural(self, on: bool) -> None:
        """Draw the rasterised body too, composited with the network's image by depth."""
        self.body_with_neural = bool(on)
        self.set_mode(self.mode)

    @property
    def can_rasterise_body(self) -> bool:
        """Whether the run has a body appearance (so both compositions can be shown)."""
        return getattr(self.run, "body_appearance", None) is not None

    def set_composition(self, composition: str) -> None:
        """``raster_body`` (the body rasterised with the run's appearance) or ``nerf`` (the network's
        body); the view re-renders."""
        if composition not in ("raster_body", "nerf") or (composition == "raster_body" and not self.can_rasterise_body):
            raise ValueError(f"composition {composition!r} is not available for this run")
        self.composition = composition

    def set_palette_color(self, index: int, rgb) -> None:
        """Change one palette color (only the shader's uniform changes; nothing re-renders)."""
        if self.palette is None:
            return
        self.palette[index] = np.clip(np.asarray(rgb, dtype=np.float32)[:3], 0.0, 1.0)
        self.scene.palette_layer.set_palette(self.palette)
        self.scene.baked_layer.palette = self.palette.copy()  # a new array: the scene sees the change

    def reset_palette(self) -> None:
        if self.learned_palette is not None:
            self.palette = self.learned_palette.copy()
            self.scene.palette_layer.set_palette(self.palette)
            self.scene.baked_layer.palette = self.palette

    def set_gt_camera(self, name: str) -> None:
        """Show the ground truth of scene camera ``name`` (and render the network from it)."""
        self.gt_camera = name

    def set_map_view(self, name: str) -> None:
        """What the ``maps`` mode shows: a key of :data:`~garmentnerf.viewer.palette_layer.MAP_VIEWS`."""
        if name not in MAP_VIEWS:
            raise ValueError(f"unknown map '{name}' (known: {', '.join(MAP_VIEWS)})")
        self.scene.palette_layer.map_view = name

    def set_cache_mb(self, megabytes: float) -> None:
        if self.renderer is not None:
            self.renderer.set_cache_mb(megabytes)

    def set_motion(self, motion) -> None:
        """The shown clip changed: the worker's session switches to ``motion`` at the next request."""
        if self.run is None:
            return
        self.motion = motion
        self._clip_serial += 1
        self.scene.palette_layer.submit_ground_truth(None)
        if self.bakes is not None:
            self._stop_baking()
            self.set_baking(self.bake_wanted)

    # ---- per UI frame -----------------------------------------------------------------------------
    def update(self, camera, timeline, playback_meter=None, camera_path=None) -> None:
        """Drain finished renders into the statistics and the quality controller, request the view
        of ``camera`` at the ``timeline``'s frame when it changed, and show the right finished frame.
        ``camera_path``: the window looks through this path (each frame its own camera, at
        ``camera``'s size; see :class:`~garmentnerf.viewer.worker.NeuralRequest`).

        The request carries the timeline's :class:`~garmentnerf.viewer.playback.PlayheadClock`:
        while it plays, the request names the clock, not the frame, and is sent again only when the
        timeline left it (a seek, a speed change). ``playback_meter`` counts the neural frames shown
        while playing.
        """
        if self.renderer is None:
            return

        self._take_checkpoint()

        frame = self._playhead = timeline.frame
        playhead = PlayheadClock.of(timeline, self._clock())
        while self.results:
            result = self.results.popleft()
            self._newest = result
            self.quality.observe(result.quality, result.timings.get("render_total", result.timings.get("total", 0.0)))
        if self.mode == "body":
            return

        gt = self.gt_camera if self.mode in GROUND_TRUTH_MODES and self.ground_truth_available() else None
        cam = self.run.scene.camera(gt).camera if gt is not None else camera
        path = camera_path if gt is None else None
        now = self._clock()
        playing = playhead.playing
        # a playing clip is not a moving view: it plays at the level's still quality (rendered ahead);
        # nor is a path the window looks through, whose camera moves with the frame
        where = ("path", path.token, cam.width, cam.height) if path is not None else (
            cam.K.tobytes(), cam.R.tobytes(), cam.t.tobytes(), cam.width, cam.height)
        key = (where, None if playing else frame, self.motion, self._clip_serial)
        self.quality.view_changed(key, now)
        q = self.quality.quality(now)
        # the still request (the level's quality) is the one rendered ahead and kept; a moving view's
        # coarser one is shown and forgotten. A scrub onto a rendered frame asks for nothing coarser.
        still = NeuralRequest(frame, cam, self.quality.full, self.motion, gt, self.quality.preset, self.composition,
                              playhead, self.weights_step, camera_path=path)
        request = still
        if q != self.quality.full and (playing or self.renderer.finished.get(still.view_key, frame) is None):
            request = NeuralRequest(frame, cam, q, self.motion, gt, self.quality.preset, self.composition, playhead,
                                    self.weights_step, keep=False, camera_path=path)
        request_key = (request.view_key, self._clip_serial, None if playing else frame, playing)
        drifted = playing and (self._sent_clock is None or self._sent_clock.drifted(playhead))
        baked_here = self.bakes is not None and self.bakes.get(frame) is not None
        if self.bakes is not None:
            self.bakes.set_playhead(frame)
        bake_shows = baked_here and self.mode == "neural" and not self.body_with_neural
        if bake_shows and not playing and request is not still:
            pass  # the view moves over a baked frame: the bake shows it, the exact still is asked for once it rests
        elif bake_shows and playing:
            # a baked stretch plays: the bake shows every frame; the worker's standing request ends with one
            # still render, and the cores go to the window
            if not self._baked_playback:
                self._baked_playback = True
                self._last_request = None
                self.renderer.request(NeuralRequest(frame, cam, self.quality.full, self.motion, gt, self.quality.preset,
                                                    self.composition, None, self.weights_step))
        elif request_key != self._last_request or drifted:
            self._baked_playback = False
            self._last_request, self._sent_clock = request_key, playhead
            self.renderer.request(request)
        self._keys = (still.view_key, request.view_key)
        self._choose_shown(still.view_key, request.view_key, frame, playhead, playback_meter if playing else None)
        self._choose_bake(frame, still.view_key)

    # ---- baked frames ---------------------------------------------------------------------------------
    @property
    def can_bake(self) -> bool:
        """A bake carries the garment over the rasterised body: the run needs a body appearance and a folder."""
        return self.can_rasterise_body and getattr(self.run, "root", None) is not None

    def set_baking(self, on: bool) -> None:
        """Bake the clip in the background (and show its bakes), or stop (the bakes made stay on disk)."""
        self.bake_wanted = bool(on)
        if not on:
            self._stop_baking()
            return
        if not self.can_bake or self.bake_process is not None:
            return
        if self.bakes is None:
            self.bakes = ClipBakes(self.scene.baked_layer.drawer.mesh_step)
        bakes = self.bakes
        motion = self.motion if isinstance(self.motion, str) else None
        scene = self.run.scene.root if self.run.scene is not None else None
        self.bake_process = BakeProcess(self.run.root, motion, DEFAULT_BAKE_PRESET,
                                        lambda path: bakes.use_folder(BakeFolder.open(path)), scene, self._playhead)

    def show_bakes(self, folder: BakeFolder) -> None:
        """Show the bakes of ``folder`` (made by ``garmentnerf bake`` for this run and clip) without baking."""
        self._stop_baking()
        self.bakes = ClipBakes(self.scene.baked_layer.drawer.mesh_step)
        self.bakes.use_folder(folder)

    def _stop_baking(self) -> None:
        if self.bake_process is not None:
            process, self.bake_process = self.bake_process, None
            threading.Thread(target=process.stop, name="garmentnerf-stop-bake", daemon=True).start()
        if self.bakes is not None:
            self.bakes.close()
            self.bakes = None
        layer = self.scene.baked_layer
        layer.visible, layer.frame = False, None
        self.showing_bake = ""

    def bake_status(self) -> dict | None:
        """The clip's bake as the panel shows it: ``baked`` frames of ``frames``, ``loaded`` in memory,
        ``running`` (the process bakes), ``error``; None when nothing is baked or baking."""
        if self.bakes is None:
            return None
        process = self.bake_process
        return {"baked": len(self.bakes.baked()), "frames": self.bakes.num_frames, "loaded": self.bakes.loaded(),
                "running": process is not None and process.running, "seconds_left": self.bakes.seconds_left(),
                "error": (process.error if process is not None else "") or "; ".join(self.bakes.errors[-1:])}

    def _choose_bake(self, frame: int, still_key) -> None:
        """What the baked layer shows this UI frame (module docstring, "Baked frames")."""
        layer, palette_layer = self.scene.baked_layer, self.scene.palette_layer
        shown = None
        self.showing_bake = ""
        if self.mode == "neural" and not self.body_with_neural:
            exact = self.shown is not None and self.shown.frame == frame and self.shown.view_key == still_key
            if not exact:
                shown = self.bakes.get(frame) if self.bakes is not None else None
                self.showing_bake = "bake" if shown is not None else ""
                if shown is None and self.shown is not None and self.shown.frame == frame \
                        and self.shown.reprojection is not None:
                    if self._reprojected is None or self._reprojected[0] is not self.shown:
                        self._reprojected = (self.shown, BakedFrame(frame, (self.shown.reprojection,)))
                    shown = self._reprojected[1]
                    self.showing_bake = "reprojection"
        layer.visible, layer.frame = shown is not None, shown
        palette_layer.visible = self.mode != "body" and shown is None

    def _choose_shown(self, still_key, request_key, frame: int, playhead, playback_meter) -> None:
        """Show the finished frame of the still view at ``frame`` if the render-ahead cache has it
        (playing: the finished one nearest behind the playhead, unless the shown one is nearer),
        else the newest result unless it was rendered ahead of another frame (its own frame is
        shown from the cache) or lies ahead of the playhead (predicted: shown when the playhead
        reaches it)."""
        cached = self.renderer.finished.get(still_key, frame)
        if cached is None and playback_meter is not None:  # playing: the newest frame the playhead reached
            cached = self.renderer.finished.latest_behind(still_key, frame, playhead.n_frames, playhead.loop)
            shown = self.shown.frame if self.shown is not None and self.shown.view_key == still_key else None
            if cached is not None and not replaces_shown(cached.frame, shown, frame, playhead.n_frames, playhead.loop):
                cached = None  # what is shown is nearer the playhead
        if cached is not None:
            self._show(cached, playback_meter)
            return
        newest = self._newest
        if newest is None or newest is self.shown or (newest.ahead and newest.frame != frame):
            return

        # paused, "ahead" is later in the clip (a frame rendered ahead is never shown early)
        if show_newest(newest.frame, frame, playhead.n_frames, playhead.loop and playhead.playing):
            self._show(newest, playback_meter)

    @property
    def shown_frame(self) -> int | None:
        """The clip frame the neural image shows (None before the first)."""
        return None if self.shown is None else self.shown.frame

    def frame_ready(self, frame: int) -> bool:
        """Whether the image of ``frame`` for the view last requested is finished (play every frame
        waits for it): rendered ahead for the still view, or the newest result of that view."""
        if self.renderer is None or self.mode == "body" or self._keys is None:
            return True
        still_key, request_key = self._keys
        newest = self._newest
        return (self.renderer.finished.get(still_key, frame) is not None
                or (newest is not None and newest.view_key in (still_key, request_key) and newest.frame == frame))

    def busy(self) -> bool:
        """Whether the worker renders a request, a result waits to be drained, or the view is still
        moving (rendering ahead does not count: the window may wait for events meanwhile)."""
        return self.renderer is not None and not (self.renderer.worker.idle() and not self.results
                                                  and not self.quality.moving(self._clock()))

    def settled(self) -> bool:
        """Not :meth:`busy`, and the worker has finished rendering ahead (True without a run)."""
        return self.renderer is None or (not self.busy() and self.renderer.worker.quiet() and not self.results)

    @property
    def has_image(self) -> bool:
        """Whether a neural frame is on the GPU."""
        return self.scene.palette_layer.has_image

    def error(self) -> str:
        return self.renderer.stats.last_error if self.renderer is not None else ""

    def stats(self) -> dict | None:
        """The worker's figures and the newest result's (the stats hook); None without a run."""
        if self.renderer is None:
            return None
        st = self.renderer.stats
        return {"renders": st.renders, "dropped": st.dropped, "errors": st.errors, "last_error": st.last_error,
                "last_ms": st.last_ms, "started": st.started, "abandoned": st.abandoned,
                "completed_share": st.completed_share, "shown_frame": self.shown_frame,
                "render_s": self.renderer.render_time.seconds, "weights_step": self.weights_step,
                "shown_step": None if self.shown is None else self.shown.weights_step,
                "finished_frames": len(self.renderer.finished.frames(self.renderer.finished.view)),
                "layer_has_image": self.has_image, **self.last_result}

    def stop(self) -> None:
        self._stop_baking()
        if self.watcher is not None:
            self.watcher.close()
        if self.renderer is not None:
            self.renderer.stop()
