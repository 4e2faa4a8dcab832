"""Training: the run folder format (:mod:`.run`), per-frame inputs and targets (:mod:`.frames`)
and the two-stage trainer (:mod:`.trainer`)."""

from garmentnerf.train.run import LoadedRun, create_untrained_run, load_run, save_run_model

__all__ = ["LoadedRun", "load_run", "save_run_model", "create_untrained_run"]
