"""Training the model on a scene.

- :mod:`~garmentnerf.train.run`: the trainer's part of a run folder (checkpoints, logs, resuming);
  the run folder itself (``run.json``, weights, loading a run) is :mod:`garmentnerf.runs`.
- :mod:`~garmentnerf.train.settings`: :class:`~garmentnerf.train.settings.TrainConfig`, the model
  presets, and the settings a resume trains with.
- :mod:`~garmentnerf.train.trainer`: the two-stage trainer (G_img pre-training, then the NeRF).
- :mod:`~garmentnerf.train.checkpoints`: checkpoint files, their RNG states, pruning and write errors.
- :mod:`~garmentnerf.train.frames`: per-frame inputs and ground-truth targets, cached in memory.
- :mod:`~garmentnerf.train.perceptual`: the perceptual loss network (VGG19 or shift-tolerant LPIPS).
- :mod:`~garmentnerf.train.distributed`: data-parallel training over ``torch.distributed``.
- :mod:`~garmentnerf.train.recipe`: a recipe file (a model's stages as data) and its model configs.
- :mod:`~garmentnerf.train.recipe_run`: running a recipe's stages in order into one folder, resumable.
"""
