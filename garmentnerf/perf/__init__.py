"""The benchmarks behind ``garmentnerf bench``. They import the layers they measure; nothing but
the CLI imports a benchmark. The render presets they measure live with the render session
(:mod:`garmentnerf.render.presets`); the previewer's render-ahead bench lives with the viewer it
drives (:mod:`garmentnerf.viewer.playback_bench`) and reaches the preset bench as an argument.

- :mod:`~garmentnerf.perf.preset_bench`: every preset measured on a trained run (speed, points,
  PSNR/SSIM) and playback figures (``garmentnerf bench --run``).
- :mod:`~garmentnerf.perf.plot`: the speed/accuracy plot of those figures.
- :mod:`~garmentnerf.perf.foundation_bench`: the per-frame foundation stages on the bundled body
  (info maps, camera pass, body layer, projection; ``garmentnerf bench`` without ``--run``).
- :mod:`~garmentnerf.perf.gl_bench`: the GL passes on synthetic meshes.
- :mod:`~garmentnerf.perf.projection_bench`: the surface projectors' speed and the dense search's
  mismatch against the exact one.
- :mod:`~garmentnerf.perf.timing`: median wall-clock time of a call.
"""
