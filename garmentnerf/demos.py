"""The bundled demos: one trained run per garment of the paper's Table 1, chosen by name.

Each demo is a run folder under ``garmentnerf/assets/demo/`` (``run.json``, ``model.safetensors``,
``body_appearance.safetensors``, ``TRAINING.md``, the ``recipe.json`` that trains it again
(``garmentnerf train --recipe``) and the ``eval_*.json`` its figures come from)
whose ``run.json`` points at the garment's scene beside it (``../<garment>``: the simulated
sequences; the ground-truth images are rendered into the scene's ``cache/`` on first use).

Usage::

    run_dir = demo_run_dir("tshirt")     # FileNotFoundError naming the demo when it is not installed
    for demo in installed_demos():
        print(demo.name, demo.size_bytes(), demo.figures())

The skirt's run keeps its historical folder name ``run``; the others are ``run_<garment>``.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

from garmentnerf.folder_lock import lock_folder
from garmentnerf.io_utils import atomic_write_path, read_json_strict

__all__ = ["DEMO_ROOT", "DEMO_NAMES", "DEFAULT_DEMO", "EVAL_FILES", "MAX_DEMO_WEIGHTS_BYTES", "PAPER_TABLE_1", "Demo",
           "BODY_APPEARANCE_FILE", "COMPOSITION_FILES", "missing_for_evaluation",
           "demo", "demo_run_dir", "results_table",
           "demo_of_run", "installed_demos", "pack_demo", "pack_weights"]

#: Where the demos live inside the package.
DEMO_ROOT = Path(__file__).resolve().parent / "assets" / "demo"
#: The paper's three garments, in its Table 1 order.
DEMO_NAMES = ("skirt", "tshirt", "dress")
#: The demo a plain ``garmentnerf view`` opens.
DEFAULT_DEMO = "skirt"
#: Run folder of each demo, relative to :data:`DEMO_ROOT`.
_RUN_FOLDERS = {"skirt": "run", "tshirt": "run_tshirt", "dress": "run_dress"}
#: Largest weights file a demo may ship (the demo budget: at most 25 MB per garment).
MAX_DEMO_WEIGHTS_BYTES = 25 * 1024 * 1024
#: The evaluations a demo's figures are read from (written by ``garmentnerf eval --json``), per split.
EVAL_FILES = {"seen": "eval_seen.json", "unseen_view": "eval_unseen_view.json",
              "unseen_motion": "eval_unseen_motion.json"}
#: A run's learned body appearance (:data:`garmentnerf.model.body_appearance.BODY_APPEARANCE_FILE`, named
#: here too so that listing the demos loads no torch).
BODY_APPEARANCE_FILE = "body_appearance.safetensors"
#: The file of the run folder, besides the weights, that an evaluation's ``composition`` draws with: its
#: figures describe the run only while the file is there (without its body appearance a run draws the
#: body with the network: another picture than the one measured).
COMPOSITION_FILES = {"raster_body": BODY_APPEARANCE_FILE}


def missing_for_evaluation(report, run_dir) -> Path | None:
    """The file of ``run_dir`` that the evaluation ``report`` (``garmentnerf eval --json``) was measured
    with and that is missing there (:data:`COMPOSITION_FILES`), or None: its figures describe the run."""
    needed = COMPOSITION_FILES.get(report.get("composition")) if isinstance(report, dict) else None
    if needed is None or (Path(run_dir) / needed).is_file():
        return None
    return Path(run_dir) / needed
#: The paper's Table 1 ("ours"): per garment and split (its "seen motion" is the training motion seen
#: from held-out cameras: our ``unseen_view``), PSNR / SSIM / LPIPS / tOF; "nearest view" its baseline.
PAPER_TABLE_1 = {
    "tshirt": {"unseen_view": (27.737, 0.974, 0.044, 0.520), "unseen_motion": (22.594, 0.939, 0.086, 0.656),
               "nearest view": (14.976, 0.816, 0.198, 1.305)},
    "skirt": {"unseen_view": (26.446, 0.966, 0.055, 0.681), "unseen_motion": (20.994, 0.927, 0.101, 0.875),
              "nearest view": (15.028, 0.815, 0.194, 1.438)},
    "dress": {"unseen_view": (26.677, 0.960, 0.050, 0.578), "unseen_motion": (21.175, 0.909, 0.093, 0.799),
              "nearest view": (15.132, 0.806, 0.181, 1.238)},
}


@dataclass(frozen=True)
class Demo:
    """One bundled demo.

    Attributes:
        name: the garment (one of :data:`DEMO_NAMES`).
        run_dir: its run folder (may be missing: see :attr:`installed`).
    """

    name: str
    run_dir: Path

    @property
    def installed(self) -> bool:
        """Whether the run folder holds a run (``run.json`` and ``model.safetensors``)."""
        return (self.run_dir / "run.json").is_file() and (self.run_dir / "model.safetensors").is_file()

    @property
    def scene_dir(self) -> Path | None:
        """The scene folder the run points at (None when the run is missing or names none)."""
        try:
            scene = read_json_strict(self.run_dir / "run.json", "run").get("scene")
        except (OSError, ValueError):
            return None
        return (self.run_dir / scene).resolve() if scene else None

    def size_bytes(self) -> int:
        """Bytes the demo adds to an install: its run folder and its scene's shipped files (the
        rendered ``cache/`` and the simulator's ``sim/`` state are not shipped)."""
        total = sum(p.stat().st_size for p in self.run_dir.rglob("*") if p.is_file())
        scene = self.scene_dir
        if scene is not None and scene.is_dir():
            total += sum(p.stat().st_size for p in scene.rglob("*")
                         if p.is_file() and p.relative_to(scene).parts[0] not in ("cache", "sim"))
        return total

    def evaluation(self, split: str) -> dict | None:
        """The shipped ``garmentnerf eval --json`` report of ``split`` (a key of :data:`EVAL_FILES`), or None:
        none is shipped, or the one shipped was measured with a file the demo lacks
        (:func:`missing_for_evaluation`; its figures are not the demo's, so it reads "not evaluated")."""
        path = self.run_dir / EVAL_FILES[split]
        if not path.is_file():
            return None
        report = read_json_strict(path, "evaluation")
        return None if missing_for_evaluation(report, self.run_dir) is not None else report

    def figures(self) -> dict[str, dict[str, float]]:
        """Per split with a shipped evaluation (``unseen_view``, ``unseen_motion``): the foreground
        PSNR, garment PSNR and silhouette IoU, and on ``unseen_view`` the foreground margin over the
        nearest training view."""
        out: dict[str, dict[str, float]] = {}
        for split in ("unseen_view", "unseen_motion"):
            report = self.evaluation(split)
            if report is None:
                continue
            means = report.get("means", {})
            row = {k: float(means[k]) for k in ("fg_psnr", "garment_psnr", "silhouette_iou") if k in means}
            margin = report.get("margin_db") or {}
            if "fg_psnr" in margin:
                row["fg_margin_db"] = float(margin["fg_psnr"])
            out[split] = row
        return out


def demo(name: str, root: Path = DEMO_ROOT, what: str | None = None) -> Demo:
    """The demo called ``name`` (under ``root``); ValueError naming the choices for an unknown name,
    after ``what`` when given: the flag or key the name came from (``--demo``, ``--name``)."""
    if name not in _RUN_FOLDERS:
        where = f"{what}: " if what else ""
        raise ValueError(f"{where}unknown demo {name!r}; choose one of {', '.join(DEMO_NAMES)}")
    return Demo(name, Path(root) / _RUN_FOLDERS[name])


def demo_run_dir(name: str, root: Path = DEMO_ROOT, what: str | None = None) -> Path:
    """The run folder of demo ``name`` (``what``: where the name came from, as for :func:`demo`).
    FileNotFoundError when it is not installed (the message names the demos that are)."""
    d = demo(name, root, what)
    if not d.installed:
        have = ", ".join(x.name for x in installed_demos(root)) or "none"
        raise FileNotFoundError(f"{d.run_dir}: the {name} demo is not installed (installed demos: {have}); "
                                f"pass --run DIR")
    return d.run_dir


def installed_demos(root: Path = DEMO_ROOT) -> list[Demo]:
    """The installed demos under ``root``, in :data:`DEMO_NAMES` order."""
    return [d for d in (demo(n, root) for n in DEMO_NAMES) if d.installed]


def demo_of_run(run_dir, root: Path = DEMO_ROOT) -> str | None:
    """The name of the demo whose run folder is ``run_dir`` (None: not a demo under ``root``)."""
    run_dir = Path(run_dir).resolve()
    return next((n for n in DEMO_NAMES if demo(n, root).run_dir.resolve() == run_dir), None)


def pack_demo(run_dir: Path, name: str, root: Path = DEMO_ROOT, overwrite: bool = False,
              what: str | None = None) -> Demo:
    """Make the trained run ``run_dir`` demo ``name`` under ``root``: its weights cast to float16
    (:func:`pack_weights`), its body appearance, ``TRAINING.md``, ``recipe.json`` (a ``train --recipe``
    folder's: the recipe as run) and ``eval_*.json`` if present,
    ``run.json`` pointing at ``../<name>``, and that scene folder holding the run scene's
    ``scene.json`` and ``sequences/`` (not its rendered ``cache/`` or simulator ``sim/``) and the
    garment's height band measured on them
    (:data:`~garmentnerf.render.band_cache.SCENE_BAND_FILE`: the previewer's first garment frame
    does not wait for the measurement).

    An evaluation is shipped only with what it was measured with: a run whose ``eval_*.json`` used
    its body appearance (composition ``raster_body``) but has no ``body_appearance.safetensors`` any
    more is refused, naming the missing file (:func:`missing_for_evaluation`), rather than packed into a
    demo whose listed figures would describe another picture than the one it draws.

    Staged in a temporary folder under ``root`` and moved into place at the end. Raises
    ValueError (an unknown ``name``, named after ``what``, the flag or key it came from, as by
    :func:`demo`; an unreadable ``eval_*.json``; weights over :data:`MAX_DEMO_WEIGHTS_BYTES`),
    FileNotFoundError (not a run, its scene missing, or a file an evaluation was measured with
    missing) and FileExistsError (the demo is installed and ``overwrite`` is False), each before
    anything under ``root`` changes.
    """
    target = demo(name, root, what)  # an unknown name first, before torch loads
    # lazy: the registry above is read by every command's flag checks; loading a run needs torch
    from garmentnerf.render.band_cache import SCENE_BAND_FILE, band_key, save_band
    from garmentnerf.render.presets import BOX_TRAINED_MARGIN_IN, height_range_for_run
    from garmentnerf.runs import load_run

    run_dir = Path(run_dir)
    for file in ("run.json", "model.safetensors"):
        if not (run_dir / file).is_file():
            raise FileNotFoundError(f"{run_dir}: not a run folder (no {file})")
    run = load_run(run_dir)  # the weights match the config and the scene is there
    if run.scene is None:
        raise FileNotFoundError(f"{run_dir}: the run's scene ({run.info.get('scene') or 'not recorded'}) is missing")
    evaluations = sorted(run_dir.glob("eval_*.json"))
    for path in evaluations:
        report = read_json_strict(path, "evaluation")
        missing = missing_for_evaluation(report, run_dir)
        if missing is not None:
            raise FileNotFoundError(
                f"{missing}: missing, but {path.name} was measured with it (composition {report['composition']}), so "
                f"the demo's figures would describe another picture; put it back, or evaluate the run again "
                f"without it (garmentnerf eval --run {run_dir} --split {report.get('split', 'SPLIT')} "
                f"--composition nerf --json {path} --overwrite)")
    # one writer of the demos at a time (garmentnerf.folder_lock): the check that the demo is not installed
    # and the move into place see the same folder
    with lock_folder(root, f"garmentnerf demo pack --name {name}", what="demos"):
        scene_dst = Path(root) / name
        for path in (target.run_dir, scene_dst):
            if path.exists() and not overwrite:
                raise FileExistsError(f"{path}: already exists (pass --overwrite to replace the {name} demo)")
        staging = Path(tempfile.mkdtemp(prefix=f".pack-{name}-", dir=root))
        try:
            run_out, scene_out = staging / "run", staging / "scene"
            run_out.mkdir()
            weights = pack_weights(run_dir / "model.safetensors", run_out / "model.safetensors")
            if weights > MAX_DEMO_WEIGHTS_BYTES:
                raise ValueError(f"{run_dir / 'model.safetensors'}: {weights / 2**20:.1f} MiB in float16, more than the "
                                 f"{MAX_DEMO_WEIGHTS_BYTES / 2**20:.0f} MiB a demo may ship")
            extras = [BODY_APPEARANCE_FILE, "TRAINING.md", "recipe.json", *(p.name for p in evaluations)]
            for extra in extras:
                if (run_dir / extra).is_file():
                    shutil.copy2(run_dir / extra, run_out / extra)
            info = dict(run.info, scene=f"../{name}")
            (run_out / "run.json").write_text(json.dumps(info, indent=1) + "\n")
            scene_src = Path(run.scene.root)
            scene_out.mkdir()
            shutil.copy2(scene_src / "scene.json", scene_out / "scene.json")
            shutil.copytree(scene_src / "sequences", scene_out / "sequences")
            save_band(scene_out / SCENE_BAND_FILE, height_range_for_run(run),
                      band_key(run.scene, run.model.body, run.betas, BOX_TRAINED_MARGIN_IN))
            for src, dst in ((run_out, target.run_dir), (scene_out, scene_dst)):
                if dst.exists():
                    shutil.rmtree(dst)
                os.replace(src, dst)
        finally:
            shutil.rmtree(staging, ignore_errors=True)
    return target


def pack_weights(source: Path, destination: Path) -> int:
    """Copy a weights file with its float32 tensors cast to float16 (what a demo ships; the
    model computes in float32 after loading, :func:`~garmentnerf.runs.load_weights`).
    Returns the bytes written."""
    import torch
    from safetensors import safe_open
    from safetensors.torch import save_file

    with safe_open(str(source), framework="pt") as f:
        metadata = f.metadata()
        tensors = {k: f.get_tensor(k) for k in f.keys()}
    # through atomic_write_path for its permissions: safetensors 0.8 creates files 0600, which another
    # user of a shared install could not read
    with atomic_write_path(Path(destination), overwrite=True) as tmp:
        save_file({k: v.to(torch.float16) if v.dtype == torch.float32 else v for k, v in tensors.items()},
                  str(tmp), metadata=metadata)
    return Path(destination).stat().st_size


def _cell(value, digits: int) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def results_table(demos: list[Demo]) -> str:
    """A markdown table shaped like the paper's Table 1 from the demos' shipped evaluations: per
    garment and split (training cameras, held-out cameras, held-out motion) PSNR / SSIM / ST-LPIPS /
    tOF, the foreground and garment PSNR, the silhouette IoU and, on held-out cameras, the margin
    over the nearest training view (full frame, as the paper's, then over the character); the paper's
    figures beside (its LPIPS is AlexNet LPIPS, ours the shift-tolerant ST-LPIPS). A split without an
    evaluation reads "not evaluated"."""
    splits = {"seen": "training motion, training cameras", "unseen_view": "training motion, held-out cameras",
              "unseen_motion": "held-out motion"}
    lines = ["| garment | split | PSNR / SSIM / ST-LPIPS / tOF | fg / garment PSNR | IoU | margin (fg) | "
             "paper: PSNR / SSIM / LPIPS / tOF | paper's margin |",
             "|---|---|---|---|---|---|---|---|"]
    for d in demos:
        paper = PAPER_TABLE_1.get(d.name, {})
        for split, label in splits.items():
            report = d.evaluation(split)
            ref = paper.get(split)
            ref_text = " / ".join(_cell(v, k) for v, k in zip(ref, (2, 3, 3, 3))) if ref else "-"
            ref_margin = (f"{ref[0] - paper['nearest view'][0]:.2f} dB" if ref and split == "unseen_view" else "-")
            if report is None:
                lines.append(f"| {d.name} | {label} | not evaluated | | | | {ref_text} | {ref_margin} |")
                continue
            m = report["means"]
            margins = report.get("margin_db") or {}
            full, fg = margins.get("psnr"), margins.get("fg_psnr")
            margin = "-" if fg is None else (f"{_cell(full, 2)} ({_cell(fg, 2)}) dB" if full is not None
                                             else f"- ({_cell(fg, 2)}) dB")
            lines.append(
                f"| {d.name} | {label} | {_cell(m.get('psnr'), 2)} / {_cell(m.get('ssim'), 3)} / "
                f"{_cell(m.get('stlpips_alex'), 3)} / {_cell(m.get('tof'), 3)} | {_cell(m.get('fg_psnr'), 2)} / "
                f"{_cell(m.get('garment_psnr'), 2)} | {_cell(m.get('silhouette_iou'), 3)} | "
                f"{margin} | {ref_text} | {ref_margin} |")
    return "\n".join(lines) + "\n"
