"""The desktop previewer (``garmentnerf view``): a GLFW window with a moderngl scene and imgui panels.

Modules, each with one job (none keeps GL objects at module level, so several contexts can live in one
process):

* :mod:`~garmentnerf.viewer.timeline` -- playback state (frame, play/pause, loop, speed); pure logic.
* :mod:`~garmentnerf.viewer.camera` -- turntable orbit/pan/zoom controller producing a
  :class:`garmentnerf.conventions.Camera`; pure math.
* :mod:`~garmentnerf.viewer.shortcuts` -- the one shortcuts table (key handling and the help window).
* :mod:`~garmentnerf.viewer.sequence` -- a posed body clip ready for upload, and its background loader.
* :mod:`~garmentnerf.viewer.scene_gl` -- GL renderables (body mesh, floor grid, neural layer) and the
  scene renderer that draws them into an off-screen target.
* :mod:`~garmentnerf.viewer.worker` -- the render worker thread that will fill the neural layer.
* :mod:`~garmentnerf.viewer.export` -- snapshots: off-screen render at any resolution, atomic PNG.
* :mod:`~garmentnerf.viewer.exporter` -- the export thread: neural snapshots and mp4 videos (turntable or
  timeline range) through the headless command's render path, with progress and cancel.
* :mod:`~garmentnerf.viewer.panels` -- the imgui panels.
* :mod:`~garmentnerf.viewer.app` -- the window, the main loop and its frame-time measurement.

Importing this package imports nothing heavy; the window libraries load with ``app``/``panels``.
"""
