"""``garmentnerf eval``: score a run on a scene split (PSNR, SSIM, LPIPS / ST-LPIPS, tOF) through the
same render path as the viewer and ``garmentnerf render`` (see :mod:`garmentnerf.eval.evaluate`).
``garmentnerf report``: train and evaluate the paper's ablations into a markdown report
(:mod:`garmentnerf.eval.report`)."""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

from garmentnerf.budgets import HISTORY, QUALITY, check_memory, render_memory
from garmentnerf.cli.common import (
    add_demo_arg,
    add_device_arg,
    add_memory_arg,
    add_scene_override_arg,
    check_memory_arg,
    check_output_file,
    parse_device,
    render_geometry,
    render_geometry_of,
    run_folder_arg,
)
from garmentnerf.io_utils import atomic_write_path
from garmentnerf.ranges import parse_frame_range, parse_list


def register(sub) -> None:
    p = sub.add_parser(
        "eval", help="evaluate a run on a scene split with the paper's metrics",
        description="Render a run's views of a scene split and compare them with "
                    "the ground truth: PSNR, SSIM, LPIPS (needs $GARMENTNERF_LPIPS_ALEXNET, else reported "
                    "unavailable), shift-tolerant LPIPS and tOF. Splits: seen (training motion and cameras; "
                    "subsampled by default to 4 cameras x 30 frames), unseen_view (training motion, held-out "
                    "cameras), unseen_motion (held-out motions, training cameras; 4 cameras by default). Beside "
                    "the full-frame figures: PSNR over the character (ground-truth or rendered pixels), per label "
                    "(body, garment), silhouette IoU and a sharpness ratio (gradient energy of the render over the "
                    "ground truth's inside the garment), and with --baseline the margin over the nearest view.")
    p.add_argument("--run", default=None, metavar="DIR", help="run folder (run.json + model.safetensors)")
    add_demo_arg(p, "give --run or --demo")
    # not argparse choices: an unknown split is a one-line error like every other bad input
    p.add_argument("--split", required=True, metavar="SPLIT", help="seen, unseen_view or unseen_motion")
    add_scene_override_arg(p)
    p.add_argument("--frames", default=None, metavar="A:B",
                   help="frames A..B-1 of every sequence of the split (A:B, A:B:S, A:, :B or A; default: the "
                        "split's default, see above)")
    p.add_argument("--cameras", default=None, metavar="NAMES",
                   help="comma-separated camera names of the split (default: the split's default)")
    p.add_argument("--baseline", action="store_true",
                   help="also score the nearest-training-view baseline (split unseen_view only)")
    p.add_argument("--resolution", default="native", metavar="RES",
                   help="native (the scene's image size: a model's blur shows; default) or model (the model's "
                        "internal resolution, the trainer's targets)")
    p.add_argument("--json", default=None, metavar="FILE", help="write the full result (per frame) as JSON")
    p.add_argument("--gallery", default=None, metavar="FILE",
                   help="write a PNG of ground truth | render | error strips for a few views")
    p.add_argument("--gallery-views", type=int, default=4, metavar="N",
                   help="views in the gallery, evenly spread over the evaluation (default: 4)")
    p.add_argument("--overwrite", action="store_true", help="replace --json / --gallery if they exist")
    p.add_argument("--preset", default="reference", metavar="NAME",
                   help="render preset: reference (the paper's sampling, default), full, balanced or interactive "
                        "(the rows of 'garmentnerf bench --run')")
    p.add_argument("--quality", type=float, default=None, metavar="Q",
                   help="render at Q times the pixel density the model was trained at, 0.0625..4 (default: the "
                        "preset's, 1 for reference); 0.5 on a model trained on character windows at the scene's density "
                        "casts the rays of one trained on whole frames: an equal-cost comparison")
    p.add_argument("--composition", default="auto", metavar="HOW",
                   help="raster_body (the body rasterised with the run's learned appearance, the garment from "
                        "the network), nerf (the paper's: the network draws both) or auto (default: raster_body "
                        "when the run has body_appearance.safetensors)")
    p.add_argument("--bake", default=None, metavar="PRESET",
                   help="also score the run's bake at this bake preset (draft, balanced, fine: 'garmentnerf bake'): "
                        "each frame baked once, drawn from every camera as the previewer draws it")
    add_device_arg(p)
    add_memory_arg(p)
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run_eval)

    r = sub.add_parser(
        "report", help="train and evaluate the paper's ablations into a markdown report",
        description="Train every ablation variant of the paper's tables (full; no detail feature; no dynamic "
                    "feature; neither; k history frames; number of training views) on a scene, evaluate each on "
                    "every split the scene has, and write markdown tables shaped like the paper's, with the "
                    "nearest-view baseline. Resumable: finished runs and evaluations in --runs-dir are reused, "
                    "unfinished runs resume from their checkpoint.")
    r.add_argument("--scene", required=True, metavar="DIR", help="scene folder")
    r.add_argument("--out", required=True, metavar="FILE", help="report file (markdown), written atomically")
    r.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    r.add_argument("--iterations", type=int, default=None, metavar="N",
                   help="NeRF training steps per variant (default: the preset's)")
    r.add_argument("--generator-iterations", type=int, default=None, metavar="N",
                   help="G_img pre-training steps per variant with the detail feature (default: the preset's)")
    r.add_argument("--preset", default="cpu_small", metavar="NAME",
                   help="model preset: tiny, cpu_small or paper (default: cpu_small)")
    r.add_argument("--runs-dir", default=None, metavar="DIR",
                   help="where the variants' runs go (default: <report name>_runs beside the report)")
    r.add_argument("--variants", default=None, metavar="NAMES",
                   help="comma-separated variants (full, no_detail, no_dynamic, no_features, k<N>, views_<N>; "
                        "default: all; full is always included)")
    r.add_argument("--views", default="4,8,16", metavar="N,..",
                   help="training-view counts of the views_<N> variants (default: 4,8,16)")
    r.add_argument("--history", default="0,1,2", metavar="K,..",
                   help="history frame counts k of the k<K> variants (default: 0,1,2)")
    r.add_argument("--splits", default=None, metavar="NAMES",
                   help="comma-separated splits (default: every split the scene has)")
    r.add_argument("--frames", default=None, metavar="A:B",
                   help="frames evaluated in every split (default: each split's default)")
    r.add_argument("--perceptual", default="auto", metavar="LOSS",
                   help="training perceptual loss: auto, stlpips, vgg19 or none (default: auto)")
    add_device_arg(r)
    r.add_argument("--seed", type=int, default=0, help="training seed of every variant (default: 0)")
    r.add_argument("--no-progress", action="store_true", help="no progress bars")
    r.set_defaults(func=run_report)


def run_eval(args: argparse.Namespace) -> int:
    # the arguments that scale the work first, before anything is imported or loaded (garmentnerf.budgets)
    if args.quality is not None:
        QUALITY.check(args.quality, "--quality")
    max_gib = check_memory_arg(args)
    run_dir = run_folder_arg(args)
    if run_dir is None:
        raise ValueError("eval needs --run DIR or --demo NAME")
    # its peak memory against what the process may use, before torch loads (garmentnerf.budgets, "Memory")
    geometry = _check_eval_memory(args, render_geometry(run_dir, args.scene), args.quality, max_gib)
    # lazy: 'garmentnerf --help' and flag errors answer without torch and the model stack (0.4 s against 6 s)
    from garmentnerf.eval.evaluate import RESOLUTIONS, SPLITS, evaluate_run, format_result_table
    from garmentnerf.eval.gallery import Gallery
    from garmentnerf.render.presets import get_render_preset
    from garmentnerf.runs import load_run

    # everything that can be wrong with the arguments fails before the model loads
    if args.split not in SPLITS:
        raise ValueError(f"unknown split '{args.split}' (known: {', '.join(SPLITS)})")
    try:
        preset = get_render_preset(args.preset)
    except ValueError as e:
        raise ValueError(f"--preset: {e}") from None
    if args.resolution not in RESOLUTIONS:
        raise ValueError(f"--resolution: unknown resolution '{args.resolution}' (known: {', '.join(RESOLUTIONS)})")
    if args.gallery_views < 1:
        raise ValueError(f"--gallery-views must be at least 1, got {args.gallery_views}")
    if args.baseline and args.split != "unseen_view":
        raise ValueError(f"--baseline (nearest training view) is defined for --split unseen_view only, "
                         f"not '{args.split}'")
    frames = parse_frame_range(args.frames, "--frames")
    cameras = parse_list(args.cameras, "--cameras", kind="camera")
    parse_device(args.device)
    bake = None
    if args.bake is not None:
        from garmentnerf.bake.settings import bake_settings

        try:
            bake = bake_settings(args.bake)
        except ValueError as e:
            raise ValueError(f"--bake: {e}") from None
    # lazy: 'garmentnerf --help' and flag errors answer without torch and the model stack
    from garmentnerf.render.session import COMPOSITIONS, resolve_composition

    if args.composition not in COMPOSITIONS:
        raise ValueError(f"--composition: unknown composition '{args.composition}' (known: {', '.join(COMPOSITIONS)})")
    quality = args.quality if args.quality is not None else preset.resolution_scale
    _check_eval_memory(args, geometry, quality, max_gib)
    if args.json is not None:
        check_output_file(args.json, "--json", args.overwrite)
    if args.gallery is not None:
        check_output_file(args.gallery, "--gallery", args.overwrite)
    if args.scene is not None and not (Path(args.scene) / "scene.json").is_file():
        raise FileNotFoundError(f"--scene {args.scene}: no scene.json")
    run = load_run(run_dir, device=args.device, scene=args.scene)
    if run.scene is None:
        raise ValueError(f"{run_dir}: the run's scene ({run.info.get('scene') or 'not recorded'}) is missing; "
                         f"pass --scene DIR")
    resolve_composition(args.composition, run)  # raster_body without a body appearance fails here, not mid-way
    if geometry is None:  # the run's files did not say: its loaded config does
        _check_eval_memory(args, render_geometry_of(run), quality, max_gib)
    gallery = Gallery(args.gallery_views) if args.gallery is not None else None
    result = evaluate_run(run, args.split, frames=frames, cameras=cameras, progress=not args.no_progress,
                          baseline=args.baseline, preset=args.preset, quality=args.quality,
                          resolution=args.resolution, gallery=gallery, composition=args.composition, bake=bake)
    print(format_result_table(result))
    if gallery is not None:
        gallery.write(args.gallery, overwrite=args.overwrite)
        print(f"eval: wrote {args.gallery} ({len(gallery)} views)")
    if args.json is not None:
        text = json.dumps(result, indent=1, allow_nan=False)
        with atomic_write_path(args.json, overwrite=args.overwrite) as tmp:
            tmp.write_text(text + "\n", encoding="utf-8")
        print(f"eval: wrote {args.json}")
    return 0


def _check_eval_memory(args, geometry, quality, max_gib):
    """Refuse an evaluation whose views (the scene's cameras at ``--resolution``) at ``quality`` (None: not
    known yet) need more memory than the process may use (:func:`garmentnerf.budgets.check_memory`);
    returns ``geometry`` (None: the run's files did not say, nothing was checked)."""
    if geometry is None:
        return None
    width, height = geometry.image_size
    if args.resolution == "model":  # the training camera's size
        scale = geometry.trained_side / max(width, height)
        width, height = max(1, round(width * scale)), max(1, round(height * scale))
    estimate = render_memory(geometry, width, height, quality)
    shown = f" at quality {quality:g}" if quality is not None else ""
    check_memory(estimate, f"evaluating views of {width}x{height} pixels{shown}", max_gib,
                 lower="--quality (or --resolution model)" if args.resolution != "model" else "--quality")
    return geometry


def _whole_number(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise ValueError("not a whole number") from None
    if value < 0:
        raise ValueError("must be >= 0")
    return value


def run_report(args: argparse.Namespace) -> int:
    # the arguments that scale the work first, before anything is imported or loaded (garmentnerf.budgets)
    for name in parse_list(args.variants, "--variants", kind="variant") or ():
        k = re.fullmatch(r"k(\d+)", name)  # a history variant: its info maps grow with k
        if k:
            HISTORY.check(int(k.group(1)), f"--variants {name}: k")
    # lazy: 'garmentnerf --help' and flag errors answer without torch and the model stack (0.4 s against 6 s)
    from garmentnerf.eval.evaluate import SPLITS
    from garmentnerf.eval.report import build_report
    from garmentnerf.train.settings import MODEL_PRESETS

    if args.preset not in MODEL_PRESETS:
        raise ValueError(f"unknown preset '{args.preset}' (known: {', '.join(MODEL_PRESETS)})")
    parse_device(args.device)
    check_output_file(args.out, "--out", args.overwrite)
    if args.perceptual not in ("auto", "stlpips", "vgg19", "none"):
        raise ValueError(f"unknown perceptual loss '{args.perceptual}' (known: auto, stlpips, vgg19, none)")
    splits = parse_list(args.splits, "--splits", kind="split")
    for s in splits or ():
        if s not in SPLITS:
            raise ValueError(f"unknown split '{s}' (known: {', '.join(SPLITS)})")
    variants = parse_list(args.variants, "--variants", kind="variant")
    frames = args.frames
    parse_frame_range(frames, "--frames")  # fails early on a malformed range
    views = tuple(parse_list(args.views, "--views", _whole_number, kind="number"))
    histories = tuple(parse_list(args.history, "--history", _whole_number, kind="number"))
    out = build_report(args.scene, args.out, iterations=args.iterations,
                       generator_iterations=args.generator_iterations, preset=args.preset, runs_dir=args.runs_dir,
                       variants=variants, views=views, histories=histories, splits=splits, frames=frames,
                       perceptual=args.perceptual, device=args.device, seed=args.seed,
                       progress=not args.no_progress, overwrite=args.overwrite)
    print(f"report: wrote {out}")
    return 0
