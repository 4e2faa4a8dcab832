"""The garment menu: the bundled demos (:mod:`garmentnerf.demos`) the window can switch between.

Choosing a garment loads its run on a background thread (:class:`~garmentnerf.viewer.sequence.BackgroundLoader`;
a run takes seconds to load); the app polls it every frame and, once it is loaded, hands it to the
neural view (:meth:`~garmentnerf.viewer.neural_view.NeuralView.replace_run`). The body, the motion
being played and the camera stay: the demos share the bundled body and their scenes share their
sequences' names, which is checked (:func:`check_switch`) before the switch.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from garmentnerf.demos import DEMO_ROOT, demo_of_run, demo_run_dir, installed_demos
from garmentnerf.viewer.sequence import BackgroundLoader


class GarmentMenu:
    """The installed demos and the loading of the chosen one.

    Args:
        run: the :class:`~garmentnerf.runs.LoadedRun` shown first (None: the body alone).
        root: where the demos are (default: the package's).
    Attributes:
        current: the demo shown (None: a run that is not a demo, or none).
    """

    def __init__(self, run=None, root: Path = DEMO_ROOT) -> None:
        self.root = Path(root)
        self.current = demo_of_run(run.root, self.root) if run is not None else None
        # read once: the panel asks every frame it draws, and the demos do not change meanwhile
        demos = installed_demos(self.root)
        self._names = [d.name for d in demos]
        self._figures = {d.name: d.figures().get("unseen_view", {}) for d in demos}
        self._loader = BackgroundLoader(self._load, thread_name="garmentnerf-garment")

    def names(self) -> list[str]:
        """The installed demos, in the paper's order."""
        return list(self._names)

    def labels(self, names: list[str]) -> list[str]:
        """What the menu shows: ``tshirt  (unseen views 22.6 dB)``, or the bare name without figures."""
        return [f"{n}  (unseen views {self._figures[n]['fg_psnr']:.1f} dB)"
                if "fg_psnr" in self._figures.get(n, {}) else n for n in names]

    def _load(self, name: str) -> tuple[str, Any]:
        from garmentnerf.runs import load_run  # lazy: torch and the model stack

        return name, load_run(demo_run_dir(name, self.root))

    @property
    def loading(self) -> str | None:
        """The demo being loaded, or None."""
        return self._loader.loading

    def request(self, name: str) -> None:
        """Load demo ``name`` in the background (:meth:`poll` hands it over)."""
        self._loader.request(name)

    def poll(self) -> tuple[tuple[str, Any] | None, BaseException | None]:
        """((name, run), None) once the newest request is loaded, (None, error) if it failed, else (None, None)."""
        return self._loader.poll()

    def wait(self, timeout: float | None = None):
        """Block until the newest request is loaded (tests), then :meth:`poll`."""
        return self._loader.wait(timeout)

    def close(self) -> None:
        self._loader.close()


def check_switch(old_run, new_run, motion: str) -> str:
    """Why the window cannot show ``new_run`` in place of ``old_run`` with the body and motion it
    plays ("" when it can): the body and its shape must be the same, and a scene sequence being
    played must be one of the new scene's too."""
    if old_run is not None and old_run.info.get("body") != new_run.info.get("body"):
        return f"its body ({new_run.info.get('body')}) is not the one shown ({old_run.info.get('body')})"
    old_seqs = set(old_run.scene.sequences) if old_run is not None and old_run.scene is not None else set()
    new_seqs = set(new_run.scene.sequences) if new_run.scene is not None else set()
    if motion in old_seqs and motion not in new_seqs:
        return f"its scene has no sequence '{motion}' (it has {', '.join(sorted(new_seqs)) or 'none'})"
    return ""


__all__ = ["GarmentMenu", "check_switch"]
