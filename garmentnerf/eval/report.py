"""The paper's ablation tables, reproduced on a scene: train every variant, evaluate it, write markdown.

Variants (:func:`default_variants`; each is one training run of the same preset, seed and schedule)
    ``full``          the model as configured (detail + dynamic features, k = the preset's history,
                      every training camera of the scene);
    ``no_detail``     ``encoder.detail_feature=False`` (no G_img / G_en; no G_img pre-training);
    ``no_dynamic``    ``encoder.dynamic_feature=False`` (no E);
    ``no_features``   both off (the paper's first row of its feature table);
    ``k0``, ``k1``... ``encoder.history=k`` for each asked k other than the preset's (that one is ``full``);
    ``views_N``       trained on N of the scene's training cameras, evenly spread over them. N equal
                      to the scene's count is ``full``; N larger than it is skipped (noted in the
                      report).

Tables (shaped like the paper's: rows = variants, column groups = splits, each PSNR / SSIM /
LPIPS / tOF)
    comparison (paper Table 1) -- ``nearest view`` baseline and ``ours`` (= ``full``);
    input features (Table 2) -- detail / dynamic check marks;
    number of training views (Table 3);
    history frames k (Table 4).
    Splits are those the scene has, see :mod:`garmentnerf.eval.evaluate` (the paper's "seen
    motion" columns correspond to ``unseen_view`` here: its seen-motion numbers are on held-out
    views). The perceptual column is LPIPS when the AlexNet backbone is supplied
    (``$GARMENTNERF_LPIPS_ALEXNET``), else shift-tolerant LPIPS, labelled as such (never
    presented as LPIPS). Values missing for a reason (baseline on a split where it is undefined,
    tOF on too few frames) are ``-`` with a note.

Resumable
    Runs live in ``runs_dir/<variant>``. A finished run (``run.json`` step = the expected total)
    with the expected model config and training cameras is not trained again; an unfinished one
    is resumed from its newest checkpoint; one trained with other settings is an error (choose
    another ``--runs-dir``). Evaluations are cached as ``runs_dir/<variant>/eval/<split>.json``
    and reused while the run's step and the frame selection are unchanged. The report is
    written atomically. A report holds the writer lock (:mod:`garmentnerf.folder_lock`) of
    ``runs_dir`` throughout, and of each variant's run while it trains or is evaluated.
"""

from __future__ import annotations

import json
import math
import re
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from garmentnerf.budgets import HISTORY
from garmentnerf.data.scene import Scene
from garmentnerf.eval.evaluate import SPLITS, _spread, evaluate_run
from garmentnerf.gl.context import create_context
from garmentnerf.io_utils import atomic_write_path, read_json_strict
from garmentnerf.model.config import ModelConfig
from garmentnerf.model.perceptual import lpips_available
from garmentnerf.folder_lock import folder_has_files, lock_folder
from garmentnerf.runs import RUN_FILE, load_run, read_run_info
from garmentnerf.train.checkpoints import latest_checkpoint
from garmentnerf.train.settings import MODEL_PRESETS, TrainConfig, model_config_for
from garmentnerf.train.trainer import Trainer

__all__ = ["Variant", "default_variants", "build_report", "train_variant", "render_markdown", "report_summary",
           "VARIANT_KINDS"]

#: Kinds of variants a user can ask for by name (``k<N>`` and ``views_<N>`` are patterns).
#: The ablation variants are scored at the model's internal resolution (the tables compare
#: recipes of one model size with each other; ``garmentnerf eval`` defaults to the scene's).
REPORT_RESOLUTION = "model"

VARIANT_KINDS = ("full", "no_detail", "no_dynamic", "no_features", "k<N>", "views_<N>")

_SPLIT_TITLE = {"seen": "seen", "unseen_view": "unseen view", "unseen_motion": "unseen motion"}
_PSNR_CAP = 100.0


@dataclass(frozen=True)
class Variant:
    """One ablation run.

    Attributes:
        name: folder name and identifier (``full``, ``no_detail``, ``k0``, ``views_4``...).
        changes: :class:`ModelConfig` fields changed from the preset.
        views: number of training cameras (None: every ``train`` camera of the scene).
        cameras: the training cameras (None: the scene's default).
        note: why the variant is skipped, or None.
    """

    name: str
    changes: dict = field(default_factory=dict)
    views: int | None = None
    cameras: tuple[str, ...] | None = None
    note: str | None = None


def default_variants(scene, base_history: int, names: list[str] | None = None,
                     views: tuple[int, ...] = (4, 8, 16), histories: tuple[int, ...] = (0, 1, 2)) -> list[Variant]:
    """The variants of the report (see the module docstring).

    Args:
        scene: the :class:`~garmentnerf.data.scene.Scene` (its training cameras).
        base_history: the preset's k (that variant is ``full``).
        names: keep only these (``full`` is always added: the baseline and the other tables
            refer to it); unknown names raise ValueError.
        views, histories: the N of ``views_N`` and the k of ``k<k>``.
    """
    train_cams = scene.camera_names("train")
    out = [Variant("full"), Variant("no_detail", {"encoder.detail_feature": False}),
           Variant("no_dynamic", {"encoder.dynamic_feature": False}),
           Variant("no_features", {"encoder.detail_feature": False, "encoder.dynamic_feature": False})]
    for k in histories:
        if int(k) != int(base_history):
            out.append(Variant(f"k{int(k)}", {"encoder.history": int(k)}))
    for n in views:
        n = int(n)
        if n < 1:
            raise ValueError(f"views must be >= 1, got {n}")
        if n == len(train_cams):
            continue  # the full model
        if n > len(train_cams):
            out.append(Variant(f"views_{n}", views=n, note=f"the scene has only {len(train_cams)} training cameras"))
        else:
            out.append(Variant(f"views_{n}", views=n, cameras=tuple(_spread(train_cams, n))))
    if names is not None:
        known = {v.name: v for v in out}
        wanted = []
        for name in names:
            v = known.get(name)
            if v is None:
                v = _parse_variant(name, train_cams, base_history)
            wanted.append(v)
        if not any(v.name == "full" for v in wanted):
            wanted.insert(0, known["full"])
        seen = set()
        out = [v for v in wanted if not (v.name in seen or seen.add(v.name))]
    return out


def _parse_variant(name: str, train_cams: list[str], base_history: int) -> Variant:
    m = re.fullmatch(r"k(\d+)", name)
    if m:
        k = HISTORY.check(int(m.group(1)), f"variant '{name}': k")
        return Variant("full") if k == base_history else Variant(name, {"encoder.history": k})
    m = re.fullmatch(r"views_(\d+)", name)
    if m:
        n = int(m.group(1))
        if n < 1:
            raise ValueError(f"variant '{name}': views must be >= 1")
        if n == len(train_cams):
            return Variant("full")
        if n > len(train_cams):
            return Variant(name, views=n, note=f"the scene has only {len(train_cams)} training cameras")
        return Variant(name, views=n, cameras=tuple(_spread(train_cams, n)))
    raise ValueError(f"unknown variant '{name}' (known: full, no_detail, no_dynamic, no_features, k<N>, views_<N>)")


# ---------------------------------------------------------------------------------------------
# Training (resumable)
# ---------------------------------------------------------------------------------------------

def _expected(cfg, iterations: int | None, generator_iterations: int | None):
    """(model config as the trainer records it, G_img steps, total steps)."""
    changes = {}
    if iterations is not None:
        changes["schedule.iterations"] = int(iterations)
    if generator_iterations:
        changes["schedule.generator_iterations"] = int(generator_iterations)
    cfg = cfg.updated(changes) if changes else cfg
    gen = cfg.schedule.generator_iterations if generator_iterations is None else int(generator_iterations)
    gen = gen if cfg.encoder.detail_feature else 0
    return cfg, gen, gen + cfg.schedule.iterations


def train_variant(scene_path, run_dir, cfg, cameras=None, *, iterations: int | None = None,
                  generator_iterations: int | None = None, perceptual: str = "auto", device: str = "cpu",
                  seed: int = 0, progress: bool = True, gl_context=None,
                  log: Callable[[str], None] | None = None) -> str:
    """Train one variant into ``run_dir`` unless it is already there; returns ``"trained"``,
    ``"resumed"`` or ``"skipped"``.

    Raises:
        ValueError: ``run_dir`` holds a run with other settings, or something that is not a run.
    """
    run_dir = Path(run_dir)
    expected_cfg, gen, total = _expected(cfg, iterations, generator_iterations)
    resume = False
    if (run_dir / RUN_FILE).is_file():
        info = read_run_info(run_dir)
        try:
            recorded = ModelConfig.from_dict(dict(info["model_config"]))
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{run_dir / RUN_FILE}: model_config: {exc}") from exc
        rec_cams = (info.get("train") or {}).get("cameras")
        want_cams = list(cameras) if cameras else None
        differences = []
        if recorded != expected_cfg:
            a, b = recorded.to_dict(), expected_cfg.to_dict()
            differences += [f"{k} {a.get(k)!r} (want {b.get(k)!r})" for k in sorted(b) if a.get(k) != b.get(k)]
        if (rec_cams or None) != want_cams:
            differences.append(f"training cameras {rec_cams} (want {want_cams})")
        if not differences and "generator_iterations" in info and int(info["generator_iterations"]) != gen:
            differences.append(f"generator_iterations {info['generator_iterations']} (want {gen})")
        if differences:
            raise ValueError(f"{run_dir}: holds a run trained with other settings ({'; '.join(differences)}); "
                             f"use another --runs-dir or remove it")
        if int(info["step"]) >= total:
            return "skipped"
        if latest_checkpoint(run_dir) is None:
            raise ValueError(f"{run_dir}: unfinished run (step {info['step']} of {total}) without a checkpoint "
                             f"to resume from; remove it to train again")
        resume = True
    elif folder_has_files(run_dir):
        raise ValueError(f"{run_dir}: exists and is not a run folder; use another --runs-dir")
    tc = TrainConfig(scene=scene_path, out=run_dir, model_config=cfg, device=device, seed=seed,
                     iterations=iterations, generator_iterations=generator_iterations, resume=resume,
                     cameras=tuple(cameras) if cameras else None, perceptual=perceptual, progress=progress,
                     image_every=0)
    with Trainer(tc, gl_context, log=log) as trainer:
        result = trainer.train()
    if result.interrupted:
        raise KeyboardInterrupt
    return "resumed" if resume else "trained"


# ---------------------------------------------------------------------------------------------
# Evaluation (cached)
# ---------------------------------------------------------------------------------------------

def _write_json(path: Path, data: dict) -> None:
    text = json.dumps(data, indent=1, allow_nan=False)
    with atomic_write_path(path) as tmp:
        tmp.write_text(text + "\n", encoding="utf-8")


def _cached_eval(path: Path, request: dict, step: int, compute: Callable[[], dict]) -> dict:
    if path.is_file():
        try:
            old = read_json_strict(path, "evaluation")
            if old.get("request") == request and int(old.get("step", -1)) == int(step):
                return old
        except (OSError, ValueError):
            pass  # unreadable cache: evaluate again
    result = compute()
    result["request"] = request
    _write_json(path, result)
    return result


# ---------------------------------------------------------------------------------------------
# Markdown
# ---------------------------------------------------------------------------------------------

def _num(v) -> float | None:
    if v is None:
        return None
    if isinstance(v, str):
        try:
            return float(v)
        except ValueError:
            return None
    return float(v)


def _cell(result: dict | None, metric: str) -> str:
    if result is None:
        return "-"
    v = _num(result.get("means", {}).get(metric))
    if v is None or math.isnan(v):
        return "-"
    if math.isinf(v):
        return "inf"
    return f"{v:.2f}" if metric == "psnr" else f"{v:.3f}"


def _perceptual_metric(results: list[dict]) -> tuple[str, str]:
    """(metric key, column name): LPIPS when any result has it, else shift-tolerant LPIPS."""
    for r in results:
        if "lpips_alex" in r.get("means", {}):
            return "lpips_alex", "LPIPS↓"
    return "stlpips_alex", "ST-LPIPS↓"


def _table(first_cols: list[str], rows: list[tuple[list[str], dict[str, dict | None]]], splits: list[str],
           perceptual: tuple[str, str]) -> list[str]:
    metrics = [("psnr", "PSNR↑"), ("ssim", "SSIM↑"), perceptual, ("tof", "tOF↓")]
    header = list(first_cols) + [f"{_SPLIT_TITLE[s]} {name}" for s in splits for _, name in metrics]
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join(["---"] * len(header)) + "|"]
    for labels, per_split in rows:
        cells = list(labels) + [_cell(per_split.get(s), key) for s in splits for key, _ in metrics]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def render_markdown(meta: dict, variants: list[Variant], results: dict[str, dict[str, dict]],
                    baseline: dict | None, splits: list[str]) -> str:
    """The report's markdown.

    Args:
        meta: ``scene``, ``preset``, ``iterations``, ``generator_iterations``, ``seed``,
            ``history`` (the preset's k), ``train_cameras`` (count), ``runs_dir``, ``seconds``.
        variants: the variants (skipped ones carry a ``note``).
        results: variant name -> split -> :func:`evaluate_run` result.
        baseline: the nearest-view baseline result on ``unseen_view`` (or None).
        splits: the evaluated splits, in column order.
    """
    all_results = [r for per in results.values() for r in per.values()] + ([baseline] if baseline else [])
    perceptual = _perceptual_metric(all_results)
    out = _md_intro(meta, perceptual, all_results)
    out += _md_split_notes(results, baseline, splits)
    out += _md_comparison(results, baseline, splits, perceptual)
    out += _md_features(results, splits, perceptual)
    out += _md_views(meta, variants, results, splits, perceptual)
    out += _md_history(meta, variants, results, splits, perceptual)
    out += _md_runs(meta, variants, results)
    out += ["", f"Made in {meta.get('seconds', 0.0):.0f} s by `garmentnerf report`.", ""]
    return "\n".join(out)


def _md_intro(meta: dict, perceptual: tuple[str, str], all_results: list[dict]) -> list[str]:
    """The title, the run settings and how the numbers are made (with the note on the
    perceptual column when it is shift-tolerant LPIPS), as markdown lines."""
    out = ["# Garment Animation NeRF: ablation report", ""]
    out.append(f"Scene `{meta['scene']}`, preset `{meta['preset']}`, {meta['iterations']} NeRF + "
               f"{meta['generator_iterations']} G_img pre-training steps per variant (none without the detail "
               f"feature), seed {meta['seed']}; runs in `{meta['runs_dir']}`.")
    out.append("")
    out.append("How the numbers are made: each run renders through the one render path at the model's image "
               "resolution and is compared with the ground truth area-downsampled to it, over the full frame on "
               "the model's background (data range 1; PSNR capped at 100 dB per frame; SSIM with an 11-tap "
               "Gaussian window, valid region). tOF is TecoGAN's (Farneback flow, 2 frames skipped at each end).")
    if perceptual[0] == "stlpips_alex":
        reason = next((r.get("unavailable", {}).get("lpips_alex") for r in all_results
                       if r.get("unavailable", {}).get("lpips_alex")), None)
        out.append("")
        out.append("**The perceptual column is shift-tolerant LPIPS (AlexNet-like, stlpips-pytorch weights), not "
                   "the paper's LPIPS**" + (f": LPIPS is unavailable ({reason})." if reason else "."))
    return out


def _md_split_notes(results: dict[str, dict[str, dict]], baseline: dict | None, splits: list[str]) -> list[str]:
    """The lines saying what each split holds, then one note per split whose tOF is unavailable
    (the first variant's reason)."""
    out = [""]
    out.append("Splits: " + "; ".join(_split_text(s, results, baseline) for s in splits) + ". The paper's "
               "\"seen motion\" columns are on held-out views of the training motion, i.e. `unseen view` here.")
    notes = []
    for s in splits:
        for per in results.values():
            r = per.get(s)
            if r and "tof" in r.get("unavailable", {}):
                notes.append(f"tOF unavailable on {_SPLIT_TITLE[s]}: {r['unavailable']['tof']}")
                break
    for n in dict.fromkeys(notes):
        out.append("")
        out.append(f"Note: {n}.")
    return out


def _md_comparison(results: dict[str, dict[str, dict]], baseline: dict | None, splits: list[str],
                   perceptual: tuple[str, str]) -> list[str]:
    """The comparison table (paper Table 1): the nearest-view baseline and ``full``, with the
    baseline's explanation when there is one."""
    out = ["", "## Comparison with the nearest training view (paper Table 1)", ""]
    rows = []
    if baseline is not None:
        rows.append((["nearest view"], {"unseen_view": baseline}))
    if "full" in results:
        rows.append((["ours (full)"], results["full"]))
    out += _table(["method"], rows, splits, perceptual)
    if baseline is not None:
        out += ["", "The nearest-view baseline is the ground-truth image of the training camera nearest in "
                    "optical-axis angle at the same frame, not reprojected (nearest: "
                + ", ".join(f"{c} -> {n}" for c, n in baseline.get("nearest_camera", {}).items())
                + "); it is defined on unseen views only."]
    return out


def _md_features(results: dict[str, dict[str, dict]], splits: list[str], perceptual: tuple[str, str]) -> list[str]:
    """The input-features table (paper Table 2) with detail / dynamic check marks; no lines
    unless at least two of its variants were evaluated."""
    feat = [("no_features", "", ""), ("no_detail", "", "✓"), ("no_dynamic", "✓", ""), ("full", "✓", "✓")]
    rows = [([d, s], results[n]) for n, d, s in feat if n in results]
    if len(rows) <= 1:
        return []
    return ["", "## Input features (paper Table 2)", ""] + _table(["detail feature", "dynamic feature"], rows,
                                                                  splits, perceptual)


def _md_views(meta: dict, variants: list[Variant], results: dict[str, dict[str, dict]], splits: list[str],
              perceptual: tuple[str, str]) -> list[str]:
    """The number-of-training-views table (paper Table 3): the evaluated ``views_N`` variants and
    ``full`` (at the scene's camera count), by count."""
    rows = [(v.views, [str(v.views)], results[v.name]) for v in variants
            if v.name.startswith("views_") and v.name in results]
    return _md_sorted_table("## Number of training views (paper Table 3)", "# views", rows,
                            meta["train_cameras"], results, splits, perceptual)


def _md_history(meta: dict, variants: list[Variant], results: dict[str, dict[str, dict]], splits: list[str],
                perceptual: tuple[str, str]) -> list[str]:
    """The history-frames table (paper Table 4): the evaluated ``k<N>`` variants and ``full``
    (at the preset's k), by k."""
    rows = [(v.changes["encoder.history"], [str(v.changes["encoder.history"])], results[v.name]) for v in variants
            if v.name in results and "encoder.history" in v.changes and len(v.changes) == 1]
    return _md_sorted_table("## History frames k (paper Table 4)", "k", rows, meta["history"], results, splits,
                            perceptual)


def _md_sorted_table(title: str, column: str, rows: list[tuple[int, list[str], dict]], full_key: int,
                     results: dict[str, dict[str, dict]], splits: list[str], perceptual: tuple[str, str]) -> list[str]:
    """A table of (sort key, labels, per-split results) rows plus ``full`` labelled
    ``<full_key> (full)``, sorted by key (stably); no lines without such rows or without ``full``."""
    if not rows or "full" not in results:
        return []
    rows = sorted(rows + [(full_key, [f"{full_key} (full)"], results["full"])], key=lambda t: t[0])
    return ["", title, ""] + _table([column], [(lab, r) for _, lab, r in rows], splits, perceptual)


def _md_runs(meta: dict, variants: list[Variant], results: dict[str, dict[str, dict]]) -> list[str]:
    """The runs table: per variant its changes, training cameras, step and status (or why it
    was skipped)."""
    out = ["", "## Runs", "", "| variant | changes | training cameras | step | status |", "|---|---|---|---|---|"]
    for v in variants:
        changes = ", ".join(f"{k}={val}" for k, val in v.changes.items()) or ("-" if v.views is None else
                                                                                f"{v.views} views")
        cams = ", ".join(v.cameras) if v.cameras else "all"
        if v.note is not None:
            out.append(f"| {v.name} | {changes} | - | - | skipped: {v.note} |")
            continue
        per = results.get(v.name, {})
        step = next((r.get("step") for r in per.values()), "-")
        status = meta.get("status", {}).get(v.name, "")
        out.append(f"| {v.name} | {changes} | {cams} | {step} | {status} |")
    return out


def _split_text(split: str, results: dict, baseline: dict | None) -> str:
    r = next((per[split] for per in results.values() if split in per), None)
    if r is None and split == "unseen_view":
        r = baseline
    if r is None:
        return f"`{_SPLIT_TITLE[split]}` (not evaluated)"
    if split == "seen" and "full" in results and "seen" in results["full"]:
        r = results["full"]["seen"]
    frames = sum(len(f) for f in r.get("sequences", {}).values())
    seqs = ", ".join(r.get("sequences", {}))
    cams = ", ".join(r.get("cameras", []))
    if split == "seen":
        cams = f"each run's own training cameras (full: {cams})"
    else:
        cams = f"camera(s) {cams}"
    return (f"`{_SPLIT_TITLE[split]}` = sequence(s) {seqs} x {cams} "
            f"({frames} frame(s) per camera{', subsampled' if r.get('subsampled') else ''})")


# ---------------------------------------------------------------------------------------------
# The entry point
# ---------------------------------------------------------------------------------------------

def _available_splits(scene) -> list[str]:
    splits = []
    if scene.sequence_names("train") and scene.camera_names("train"):
        splits.append("seen")
    if scene.sequence_names("train") and scene.camera_names("unseen_view"):
        splits.append("unseen_view")
    if scene.sequence_names("unseen_motion") and scene.camera_names("train"):
        splits.append("unseen_motion")
    return splits


def build_report(scene, out, *, iterations: int | None = None, generator_iterations: int | None = None,
                 preset: str = "cpu_small", runs_dir=None, variants: list[str] | None = None,
                 views: tuple[int, ...] = (4, 8, 16), histories: tuple[int, ...] = (0, 1, 2),
                 splits: list[str] | None = None, frames=None, perceptual: str = "auto", device: str = "cpu",
                 seed: int = 0, progress: bool = True, log: Callable[[str], None] | None = None,
                 overwrite: bool = False) -> Path:
    """Train (or reuse) every variant, evaluate it on every split, write the markdown report
    (an existing ``out`` is refused unless ``overwrite``, before any work).

    Args:
        scene: the scene folder.
        out: the report file (``.md``), written atomically.
        iterations: NeRF steps per variant (default: the preset's).
        generator_iterations: G_img pre-training steps (default: the preset's; 0 skips it).
        preset: ``tiny``, ``cpu_small`` or ``paper``.
        runs_dir: where the runs go (default: ``<out without suffix>_runs`` beside the report).
        variants: variant names (default: all of :func:`default_variants`).
        views, histories: the ``views_N`` and ``k<k>`` variants.
        splits: the splits (default: every split the scene has).
        frames: frame selection for every split (default: each split's default).
        perceptual: the training perceptual loss (``auto``, ``stlpips``, ``vgg19``, ``none``).
        log: where progress messages go (default: stderr).
    Returns:
        the report's path.
    """
    t0 = time.perf_counter()
    say = log or (lambda m: print(f"garmentnerf report: {m}", file=sys.stderr))
    _check_schedule(preset, iterations, generator_iterations)
    scene_path = _scene_folder(scene)
    scene_obj = Scene.load(scene_path)
    out = _report_file(out, overwrite)
    runs_dir = Path(runs_dir) if runs_dir is not None else out.with_name(out.stem + "_runs")
    base_cfg = model_config_for(preset)
    splits = _chosen_splits(scene_obj, splits)
    variant_list = default_variants(scene_obj, base_cfg.encoder.history, variants, tuple(views), tuple(histories))
    _, gen_full, _ = _expected(base_cfg, iterations, generator_iterations)
    n_iter = iterations if iterations is not None else base_cfg.schedule.iterations
    # an evaluation is reused only for the same frame selection and the same metric set
    request = {"frames": None if frames is None else str(frames), "lpips": bool(lpips_available()[0]),
               "resolution": REPORT_RESOLUTION}
    ctx = create_context(headless=True)
    try:
        job = _ReportJob(scene_path, runs_dir, base_cfg, list(splits), frames, request, iterations,
                         generator_iterations, perceptual, device, seed, progress, ctx, say)
        # one writer per folder: the runs folder for the whole report (each variant's run folder as well,
        # by its trainer and while it is evaluated)
        with lock_folder(runs_dir, "garmentnerf report"):
            results, status, baseline = job.run_all(variant_list)
    finally:
        ctx.release()
    meta = {"scene": str(scene_path), "preset": preset, "iterations": n_iter, "generator_iterations": gen_full,
            "seed": seed, "history": base_cfg.encoder.history, "train_cameras": len(scene_obj.camera_names("train")),
            "runs_dir": str(runs_dir), "seconds": time.perf_counter() - t0, "status": status}
    text = render_markdown(meta, variant_list, results, baseline, list(splits))
    with atomic_write_path(out, overwrite=overwrite) as tmp:
        tmp.write_text(text, encoding="utf-8")
    say(f"wrote {out}")
    return out


def _check_schedule(preset: str, iterations: int | None, generator_iterations: int | None) -> None:
    """Raise ValueError for an unknown preset or a step count out of range (NeRF >= 1, G_img >= 0)."""
    if preset not in MODEL_PRESETS:
        raise ValueError(f"unknown preset '{preset}' (known: {', '.join(MODEL_PRESETS)})")
    if iterations is not None and iterations < 1:
        raise ValueError(f"iterations must be >= 1, got {iterations}")
    if generator_iterations is not None and generator_iterations < 0:
        raise ValueError(f"generator iterations must be >= 0, got {generator_iterations}")


def _scene_folder(scene) -> Path:
    """The scene folder as a Path; FileNotFoundError when it holds no ``scene.json``."""
    scene_path = Path(scene)
    if not (scene_path / "scene.json").is_file():
        raise FileNotFoundError(f"{scene_path / 'scene.json'}: missing (--scene must be a scene folder)")
    return scene_path


def _report_file(out, overwrite: bool) -> Path:
    """The report's path; IsADirectoryError for a folder, FileExistsError for an existing file
    unless ``overwrite``."""
    out = Path(out)
    if out.is_dir():
        raise IsADirectoryError(f"{out}: is a folder (the report is a markdown file)")
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out}: already exists (pass --overwrite to replace it)")
    return out


def _chosen_splits(scene, splits: list[str] | None) -> list[str]:
    """The splits to evaluate: the asked ones (each must be known and present in the scene) or
    every split the scene has; ValueError when none is left."""
    have = _available_splits(scene)
    if splits is None:
        splits = have
    else:
        for s in splits:
            if s not in SPLITS:
                raise ValueError(f"unknown split '{s}' (known: {', '.join(SPLITS)})")
            if s not in have:
                raise ValueError(f"{scene.scene_file}: the scene has nothing to evaluate for split '{s}'")
    if not splits:
        raise ValueError(f"{scene.scene_file}: no split to evaluate (no training sequence or camera)")
    return splits


@dataclass
class _ReportJob:
    """What training and evaluating the report's variants share: where the scene and the runs
    are, the preset's model config, the splits, the frame selection and cache request (see
    :func:`_cached_eval`), the training schedule and options, the GL context and the logger."""

    scene_path: Path
    runs_dir: Path
    base_cfg: Any
    splits: list[str]
    frames: Any
    request: dict
    iterations: int | None
    generator_iterations: int | None
    perceptual: str
    device: str
    seed: int
    progress: bool
    ctx: Any
    say: Callable[[str], None]

    def run_all(self, variants: list[Variant]) -> tuple[dict[str, dict[str, dict]], dict[str, str], dict | None]:
        """Train and evaluate every variant that is not skipped; returns (variant -> split ->
        result, variant -> training status, the nearest-view baseline or None)."""
        results: dict[str, dict[str, dict]] = {}
        status: dict[str, str] = {}
        baseline = None
        for v in variants:
            if v.note is not None:
                self.say(f"{v.name}: skipped ({v.note})")
                continue
            status[v.name] = self.train(v)
            results[v.name], step = self.evaluate(v)
            if v.name == "full" and "unseen_view" in self.splits:
                baseline = self.baseline(step)
        return results, status, baseline

    def train(self, v: Variant) -> str:
        """Train (or resume, or reuse) one variant's run; returns its :func:`train_variant` status."""
        run_dir = self.runs_dir / v.name
        cfg = self.base_cfg.updated(v.changes) if v.changes else self.base_cfg
        self.say(f"{v.name}: training into {run_dir}")
        result = train_variant(self.scene_path, run_dir, cfg, v.cameras, iterations=self.iterations,
                               generator_iterations=self.generator_iterations, perceptual=self.perceptual,
                               device=self.device, seed=self.seed, progress=self.progress, gl_context=self.ctx,
                               log=self.say)
        self.say(f"{v.name}: {result}")
        return result

    def evaluate(self, v: Variant) -> tuple[dict[str, dict], int]:
        """One variant's results on every split (cached; the run is loaded once, only when a
        split must be computed) and its run's step."""
        run_dir = self.runs_dir / v.name
        with lock_folder(run_dir, "garmentnerf report: evaluation"):  # its eval/ cache is written into the run
            return self._evaluate(run_dir)

    def _evaluate(self, run_dir: Path) -> tuple[dict[str, dict], int]:
        run = None
        per: dict[str, dict] = {}
        step = int(read_run_info(run_dir)["step"])
        for split in self.splits:
            def compute(split=split):
                nonlocal run
                if run is None:
                    run = load_run(run_dir, device=self.device, scene=self.scene_path)
                return evaluate_run(run, split, frames=self.frames, progress=self.progress, gl_context=self.ctx,
                                    resolution=REPORT_RESOLUTION)

            self.say(f"{run_dir.name}: evaluating {split}")
            per[split] = _cached_eval(run_dir / "eval" / f"{split}.json", self.request, step, compute)
        return per, step

    def baseline(self, step: int) -> dict:
        """The nearest-view baseline on ``unseen_view`` (cached with the ``full`` run's step)."""
        def compute_baseline():
            r = load_run(self.runs_dir / "full", device=self.device, scene=self.scene_path)
            return evaluate_run(r, "unseen_view", frames=self.frames, progress=self.progress, gl_context=self.ctx,
                                model=False, baseline=True, resolution=REPORT_RESOLUTION)

        self.say("nearest-view baseline: evaluating unseen_view")
        return _cached_eval(self.runs_dir / "baseline_unseen_view.json", self.request, step, compute_baseline)


def report_summary(results: dict[str, dict[str, dict]]) -> dict[str, Any]:
    """variant -> split -> means (for scripts)."""
    return {v: {s: r.get("means", {}) for s, r in per.items()} for v, per in results.items()}
