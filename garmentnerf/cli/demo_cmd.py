"""``garmentnerf demo``: the bundled demos (:mod:`garmentnerf.demos`): list them, or pack a trained
run into one."""

from __future__ import annotations

import argparse
from pathlib import Path

from garmentnerf.cli.common import check_output_file
from garmentnerf.demos import DEMO_NAMES, installed_demos, pack_demo, results_table
from garmentnerf.io_utils import atomic_write_path


def register(sub) -> None:
    p = sub.add_parser("demo", help="the bundled demos: list them, or pack a trained run into one",
                       description="The bundled demos are trained runs, one per garment of the paper's Table 1, "
                                   "opened with --demo NAME by view, render, eval and bench.")
    actions = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    listing = actions.add_parser("list", help="name the installed demos with their size and figures")
    listing.set_defaults(func=run_list)
    table = actions.add_parser("table", help="the installed demos' figures as a table shaped like the paper's Table 1",
                               description="A markdown table of every installed demo's shipped evaluations (seen, "
                                           "unseen_view, unseen_motion) with the paper's Table 1 beside.")
    table.add_argument("--out", default=None, metavar="FILE", help="write it to FILE (default: print it)")
    table.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    table.set_defaults(func=run_table)
    pack = actions.add_parser(
        "pack", help="make a trained run a bundled demo (weights in float16, its scene's sequences beside it)",
        description="Copy a run folder into the package as demo NAME: its weights cast to float16, its body "
                    "appearance, TRAINING.md and eval_*.json if present, and its scene's scene.json and "
                    "sequences (not the rendered cache or the simulator's state) as the demo's scene. Written "
                    "to a temporary folder first and moved into place at the end.")
    pack.add_argument("run", metavar="RUN", help="the trained run folder (run.json + model.safetensors)")
    pack.add_argument("--name", required=True, metavar="NAME", help=f"the demo: {', '.join(DEMO_NAMES)}")
    pack.add_argument("--overwrite", action="store_true", help="replace the demo if it is installed")
    pack.set_defaults(func=run_pack)


def run_list(args: argparse.Namespace) -> int:
    demos = installed_demos()
    if not demos:
        print("no demo is installed")
        return 0
    print(f"{'demo':8s} {'MB':>6s}  {'unseen views: fg / garment PSNR, IoU, margin':46s} unseen motion: fg / garment, IoU")
    for d in demos:
        fig = d.figures()
        uv, um = fig.get("unseen_view"), fig.get("unseen_motion")
        uv_text = (f"{uv['fg_psnr']:.2f} / {uv['garment_psnr']:.2f} dB, {uv['silhouette_iou']:.3f}, "
                   + (f"{uv['fg_margin_db']:.2f} dB" if "fg_margin_db" in uv else "-")) if uv else "not evaluated"
        um_text = (f"{um['fg_psnr']:.2f} / {um['garment_psnr']:.2f} dB, {um['silhouette_iou']:.3f}"
                   if um else "not evaluated")
        print(f"{d.name:8s} {d.size_bytes() / 1e6:6.1f}  {uv_text:46s} {um_text}")
    return 0


def run_table(args: argparse.Namespace) -> int:
    if args.out:
        check_output_file(args.out, "--out", args.overwrite)
    text = results_table(installed_demos())
    if args.out:
        with atomic_write_path(Path(args.out), overwrite=args.overwrite) as tmp:
            tmp.write_text(text)
        print(f"wrote {args.out}")
    else:
        print(text, end="")
    return 0


def run_pack(args: argparse.Namespace) -> int:
    target = pack_demo(Path(args.run), args.name, overwrite=args.overwrite, what="--name")
    print(f"packed {args.run} as the {args.name} demo: {target.run_dir} ({target.size_bytes() / 1e6:.1f} MB with "
          f"its scene {target.scene_dir})")
    return 0
