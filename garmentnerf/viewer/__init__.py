"""The desktop previewer (``garmentnerf view``): a GLFW window with a moderngl scene and imgui panels.

Modules, each with one job (none keeps mutable state at module level, so several windows and GL
contexts can live in one process):

* :mod:`~garmentnerf.viewer.app` -- :class:`~garmentnerf.viewer.app.App`: the main loop, input and actions.
* :mod:`~garmentnerf.viewer.window` -- the GLFW window, its GL and imgui contexts, HiDPI; the
  process's window system (GLFW init/terminate, EGL release).
* :mod:`~garmentnerf.viewer.neural_view` -- view modes, palette, ground-truth camera, quality, and the
  render worker's requests and results.
* :mod:`~garmentnerf.viewer.worker` -- the render worker thread (coalescing requests, standing
  requests) and the neural renderer that runs the render session on it.
* :mod:`~garmentnerf.viewer.playback` -- which frame the worker renders while the clip plays
  (predicted from its render time), when a render is superseded; pure logic.
* :mod:`~garmentnerf.viewer.finished_frames` -- the render-ahead cache: finished frames of one view
  (palette maps, so recolouring stays live) under a memory bound.
* :mod:`~garmentnerf.viewer.checkpoint_watch` -- the newest checkpoint of a run that is training,
  loaded off the UI thread.
* :mod:`~garmentnerf.viewer.render_thread` -- a render session (and its GL context) that lives on its
  own thread: the one helper of the worker and the exporter.
* :mod:`~garmentnerf.viewer.scene_gl` -- the scene renderer: render targets and the GL passes.
* :mod:`~garmentnerf.viewer.renderables` -- the body mesh and the floor (each owns its GL objects,
  pass state and panel rows); orientation of the display projection.
* :mod:`~garmentnerf.viewer.palette_layer` -- the neural layer: decomposed maps composed with the
  palette on the GPU.
* :mod:`~garmentnerf.viewer.exporting` -- snapshots and videos: the export thread and the window's side.
* :mod:`~garmentnerf.viewer.export_jobs` -- what an export is: sizes, names, writers, settings, plans, jobs.
* :mod:`~garmentnerf.viewer.panels`, :mod:`~garmentnerf.viewer.control_panel`,
  :mod:`~garmentnerf.viewer.export_panel` -- the imgui panels.
* :mod:`~garmentnerf.viewer.timeline` -- playback state and the overlay's meters; pure logic.
* :mod:`~garmentnerf.viewer.camera` -- turntable orbit/pan/zoom controller and its mouse gestures;
  pure math.
* :mod:`~garmentnerf.viewer.quality` -- dynamic resolution of the neural render; pure logic.
* :mod:`~garmentnerf.viewer.sequence` -- a posed body clip, the motions offered, the background loader.
* :mod:`~garmentnerf.viewer.shortcuts` -- the one shortcuts table (key handling and the help window).
* :mod:`~garmentnerf.viewer.gui_libs` -- imgui and glfw, imported in the one order that works.

Importing this package imports nothing heavy; the window libraries load with ``app``, ``window`` and
the panels.
"""
