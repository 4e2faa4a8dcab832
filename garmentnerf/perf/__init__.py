"""Speed/accuracy settings of rendering (presets) and their measurement.

- :mod:`~garmentnerf.perf.presets`: the render presets and the previewer's quality levels.
- :mod:`~garmentnerf.perf.preset_bench`: every preset measured on a trained run (speed, points,
  PSNR/SSIM) and playback figures (``garmentnerf bench --run``).
- :mod:`~garmentnerf.perf.plot`: the speed/accuracy plot of those figures.
"""
