"""Rendering a trained (or untrained) run: ONE path for the headless command, the viewer,
snapshots and video export, so their images agree.

* :mod:`~garmentnerf.render.session` -- :class:`RenderSession` (model + body + GL input builder +
  per-frame feature cache) and :class:`NeuralFrame` (the decomposed maps of one view, composed
  with any palette by :func:`garmentnerf.model.palette.compose`).
* :mod:`~garmentnerf.render.presets` -- the render presets (speed/accuracy points) and the
  previewer's quality levels: the one table bench, render, eval and the previewer use.
* :mod:`~garmentnerf.render.camera_path` -- keyframed camera paths (interpolation, file format).
* :mod:`~garmentnerf.render.frame_cache` -- the per-frame features of a clip, kept in half
  precision under a memory bound (what the session renders views from).
* :mod:`~garmentnerf.render.frame_inputs` -- the GL passes that make a body frame's inputs (info
  maps, reference-camera G-buffers) for the model.
* :mod:`~garmentnerf.render.shell_sampler` -- the sampler that keeps only the inflated-body shell
  (its bounds drawn by a GL pass).
* :mod:`~garmentnerf.render.screen_rect` -- the pixel rectangle a world box covers on screen (the
  part of the image a render needs).
* :mod:`~garmentnerf.render.cameras` -- turntable/orbit camera sequences, scene cameras by name or
  index, and the ``--camera`` argument.
* :mod:`~garmentnerf.render.video` -- PNG frames written atomically (never overwriting) and mp4
  through imageio-ffmpeg.
* :mod:`~garmentnerf.render.colors` -- hex color and palette parsing.
"""
