"""``garmentnerf data``: make, render, describe and preview training scenes."""

from __future__ import annotations

import argparse
import json

import imageio.v3 as iio
from tqdm import tqdm

from garmentnerf.cli.common import check_output_dir, check_output_file, refuse_existing
from garmentnerf.io_utils import atomic_write_path


def register(sub) -> None:
    data = sub.add_parser("data", help="training scenes: simulate, render, inspect")
    data_sub = data.add_subparsers(dest="data_command", metavar="ACTION", required=True)

    make = data_sub.add_parser(
        "make", help="simulate a garment on body motions and write a training scene (resumable)",
        description="Create a training scene: cameras, motions, the cloth simulation of the garment on every "
                    "sequence (newton VBD, one process per sequence). Images are rendered on demand later. "
                    "Interrupted runs (Ctrl-C, SIGTERM, killed) continue where they stopped when re-run with the "
                    "same arguments (--processes and --drop-chunks may differ).")
    make.add_argument("--garment", default="skirt", help="garment kind: skirt, tshirt, dress (default: skirt)")
    make.add_argument("--motion", default="walk,dance_a",
                      help="training motion: clip names joined by ',' (default: walk,dance_a)")
    make.add_argument("--test-motion", action="append", default=[], metavar="MOTION",
                      help="held-out motion for the unseen-motion test (repeatable)")
    make.add_argument("--frames", type=int, default=300, help="frames of the training sequence (default: 300)")
    make.add_argument("--test-frames", type=int, default=0, help="cap on held-out frames (default: whole clip)")
    make.add_argument("--views", type=int, default=16, help="training cameras on the circle (default: 16)")
    make.add_argument("--held-out-views", type=int, default=4, help="unseen-view cameras (default: 4)")
    make.add_argument("--size", type=int, default=512, help="image side in pixels (default: 512)")
    make.add_argument("--radius", type=float, default=3.0, help="camera circle radius, m (default: 3)")
    make.add_argument("--height", type=float, default=1.0, help="camera height, m (default: 1)")
    make.add_argument("--shape", default="average", help="body shape preset or coefficients (default: average)")
    make.add_argument("--fps", type=float, default=30.0, help="frame rate (default: 30)")
    make.add_argument("--no-in-place", action="store_true",
                      help="keep the root's horizontal travel (default: removed, treadmill-style)")
    make.add_argument("--processes", type=int, default=0,
                      help="parallel simulations (default: one per core); does not change the scene, so it may "
                           "differ when resuming")
    make.add_argument("--substeps", type=int, default=None, help="solver substeps per frame (default: 10)")
    make.add_argument("--iterations", type=int, default=None, help="VBD iterations per substep (default: 10)")
    make.add_argument("--sim", action="append", default=[], metavar="KEY=VALUE",
                      help="any other simulation setting (see garmentnerf.data.simulate.SimSettings), repeatable")
    make.add_argument("--drop-chunks", action="store_true", help="delete the resumable chunks when done")
    make.add_argument("--out", required=True, help="scene folder to create (or to finish)")
    make.set_defaults(func=run_make)

    grow = data_sub.add_parser(
        "add-sequence", help="copy a sequence simulated for another scene into this one (no new simulation)",
        description="Copy a sequence (its motion and simulated garment) that 'data make' made for another scene "
                    "into SCENE, so it trains on more motions without simulating again. Both scenes must dress "
                    "the same body shape in the same garment at the same frame rate; SCENE's cameras render it.")
    grow.add_argument("scene", help="scene folder that receives the sequence (its scene.json is rewritten)")
    grow.add_argument("--from", dest="source", required=True, metavar="SCENE", help="scene folder to copy from")
    grow.add_argument("--sequence", default="train", help="sequence of the --from scene (default: train)")
    grow.add_argument("--as", dest="as_name", default=None, metavar="NAME",
                      help="its name in SCENE (default: the same; must be new there)")
    grow.add_argument("--split", default=None, choices=("train", "unseen_motion"),
                      help="its split in SCENE (default: its split in the --from scene)")
    grow.set_defaults(func=run_add_sequence)

    ambiguity = data_sub.add_parser(
        "ambiguity", help="how far apart the garments of frames with matching body motion are",
        description="For every training frame, the frame elsewhere whose body (pose, then also its 2-frame "
                    "velocities, then also 24 frames of history) matches best, and the RMS distance between the "
                    "two garments: a floor on what a model of the body's motion can get right "
                    "(garmentnerf.data.state_ambiguity).")
    ambiguity.add_argument("scene", help="scene folder")
    ambiguity.add_argument("--sequence", action="append", default=None,
                           help="sequence to include (repeatable; default: the training ones)")
    ambiguity.add_argument("--min-gap", type=int, default=15,
                           help="frames of one sequence closer than this never match (default: 15)")
    ambiguity.add_argument("--json", default=None, help="also write the figures to this JSON file")
    ambiguity.add_argument("--overwrite", action="store_true", help="replace --json if it exists")
    ambiguity.set_defaults(func=run_ambiguity)

    reach = data_sub.add_parser(
        "reach", help="how far the garment reaches from the body, against a recipe's sampling box and density prior",
        description="Every frame's simulated garment against the body box grown by --padding (the model samples "
                    "nothing outside it) and the body density prior of width --prior-width (negative beyond it, at "
                    "its floor beyond twice it) (garmentnerf.model.garment_reach).")
    reach.add_argument("scene", help="scene folder")
    reach.add_argument("--sequence", action="append", default=None,
                       help="sequence to measure (repeatable; default: all)")
    reach.add_argument("--padding", type=float, default=None,
                       help="box padding, m (default: the model's, 0.05)")
    reach.add_argument("--prior-width", type=float, default=None,
                       help="body prior width, m (default: the model's, 0.15)")
    reach.add_argument("--json", default=None, help="also write the figures to this JSON file")
    reach.add_argument("--overwrite", action="store_true", help="replace --json if it exists")
    reach.set_defaults(func=run_reach)

    info = data_sub.add_parser("info", help="summarise a scene (cameras, sequences, simulation statistics)")
    info.add_argument("scene", help="scene folder")
    info.add_argument("--json", action="store_true", help="print JSON")
    info.set_defaults(func=run_info)

    render = data_sub.add_parser("render", help="render (and cache) the ground-truth images of a scene")
    render.add_argument("scene", help="scene folder")
    render.add_argument("--sequence", action="append", default=None, help="sequence name (repeatable; default: all)")
    render.add_argument("--split", default=None, help="only cameras of this split (train, unseen_view, reference)")
    render.set_defaults(func=run_render)

    preview = data_sub.add_parser("preview", help="contact sheet of views x frames, so a person can look")
    preview.add_argument("scene", help="scene folder")
    preview.add_argument("--out", required=True, help="output PNG")
    preview.add_argument("--sequence", default=None, help="sequence (default: the first)")
    preview.add_argument("--labels", action="store_true", help="outline garment and body label regions")
    preview.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    preview.set_defaults(func=run_preview)


def run_make(args: argparse.Namespace) -> int:
    # lazy: 'garmentnerf --help' and flag errors answer without torch and the model stack (0.4 s against 6 s)
    from garmentnerf.data.make import MakeSpec, make_scene
    from garmentnerf.data.simulate import SimSettings

    spec = MakeSpec(garment=args.garment, motion=args.motion, frames=args.frames, test_motions=list(args.test_motion),
                    test_frames=args.test_frames, views=args.views, held_out_views=args.held_out_views,
                    size=args.size, radius=args.radius, height=args.height, shape=args.shape, fps=args.fps,
                    in_place=not args.no_in_place, processes=args.processes)
    changes = {k: v for k, v in (("substeps", args.substeps), ("iterations", args.iterations)) if v is not None}
    for item in args.sim:
        key, sep, value = item.partition("=")
        if not sep:
            raise ValueError(f"--sim expects KEY=VALUE, got '{item}'")
        changes[key.strip()] = _parse_setting(value.strip())
    known = set(SimSettings().to_dict())
    unknown = sorted(set(changes) - known)
    if unknown:
        raise ValueError(f"unknown simulation setting(s) {', '.join(unknown)} (known: {', '.join(sorted(known))})")
    settings = SimSettings(**changes)

    check_output_dir(args.out)
    scene = make_scene(args.out, spec, settings=settings, keep_chunks=not args.drop_chunks)
    for name in scene.sequence_names():
        print(f"{name}: {scene.num_frames(name)} frames ({scene.sequence(name).split}){_penetration_text(scene, name)}")
    print(f"scene written to {scene.root}")
    return 0


def _penetration_text(scene, name: str) -> str:
    """", max penetration ..." for a sequence's line (empty when its garment file records none)."""
    from garmentnerf.data.garment_sequence import penetration_summary, recorded_penetration
    from garmentnerf.data.simulate import PENETRATION_BOUND_M

    pen = recorded_penetration(scene.garment_path(name))
    return "" if pen is None else f", {penetration_summary(pen, PENETRATION_BOUND_M)}"


def _parse_setting(text: str):
    if text.lower() in ("true", "false"):
        return text.lower() == "true"
    try:
        return int(text)
    except ValueError:
        pass
    try:
        return float(text)
    except ValueError:
        raise ValueError(f"--sim value '{text}' is not a number or true/false") from None


def run_add_sequence(args: argparse.Namespace) -> int:
    # lazy: 'garmentnerf --help' and flag errors answer without torch and the model stack (0.4 s against 6 s)
    from garmentnerf.data.scene_merge import add_sequence

    # the scene's writer lock held from before it is read (garmentnerf.folder_lock), as data make holds it
    target, info = add_sequence(args.scene, args.source, args.sequence, as_name=args.as_name, split=args.split)
    print(f"{info.name}: {info.frames} frames ({info.split}, {info.motion}) added to {target.scene_file}"
          f"{_penetration_text(target, info.name)}")
    return 0


def run_ambiguity(args: argparse.Namespace) -> int:
    # lazy: 'garmentnerf --help' and flag errors answer without torch and the model stack (0.4 s against 6 s)
    from garmentnerf.body.model import BodyModel
    from garmentnerf.data.scene import Scene
    from garmentnerf.data.state_ambiguity import state_ambiguity

    out = check_output_file(args.json, "--json", args.overwrite) if args.json else None
    if args.min_gap < 1:
        raise ValueError(f"--min-gap must be >= 1, got {args.min_gap}")
    scene = Scene.load(args.scene)
    for name in args.sequence or []:
        scene.sequence(name)
    report = state_ambiguity(scene, BodyModel.default(), args.sequence, min_gap=args.min_gap)
    print(f"{report.frames} frames; garment RMS distance to the frame whose body matches best (median):")
    for label, value in report.matched_garment_rms_m.items():
        apart = report.matched_descriptor_rms_m[label]
        print(f"  {label:24s} {value * 100:6.2f} cm  (descriptors {apart * 100:.2f} cm apart)")
    if report.close_pose_garment_rms_m is not None:
        print(f"  {report.close_pose_pairs} frames have a pose match within {report.close_m * 100:g} cm: garments "
              f"{report.close_pose_garment_rms_m * 100:.2f} cm apart")
    print(f"  a random other frame     {report.random_garment_rms_m * 100:6.2f} cm")
    if out is not None:
        with atomic_write_path(out, overwrite=args.overwrite) as tmp:
            tmp.write_text(json.dumps(report.to_json(), indent=1) + "\n", encoding="utf-8")
    return 0


def run_reach(args: argparse.Namespace) -> int:
    # lazy: 'garmentnerf --help' and flag errors answer without torch and the model stack
    from garmentnerf.body.model import BodyModel
    from garmentnerf.data.scene import Scene
    from garmentnerf.model.config import BBOX_PADDING, BODY_PRIOR_WIDTH
    from garmentnerf.model.garment_reach import garment_reach

    out = check_output_file(args.json, "--json", args.overwrite) if args.json else None
    padding = BBOX_PADDING if args.padding is None else args.padding
    width = BODY_PRIOR_WIDTH if args.prior_width is None else args.prior_width
    if not padding >= 0:
        raise ValueError(f"--padding must be >= 0, got {args.padding}")
    if not width > 0:
        raise ValueError(f"--prior-width must be > 0, got {args.prior_width}")
    scene = Scene.load(args.scene)
    for name in args.sequence or []:
        scene.sequence(name)
    reports = garment_reach(scene, BodyModel.default(), padding, width, args.sequence)
    for r in reports:
        print(f"{r.sequence} ({r.frames} frames):")
        print(f"  outside the body box + {padding:g} m: {r.frames_outside_box} frames, at most "
              f"{100 * r.worst_outside_share:.1f} % of the garment (frame {r.worst_outside_frame}), up to "
              f"{100 * r.farthest_outside_m:.1f} cm out")
        print(f"  height above the skin: p95 {r.h_p95_m:.3f} m, max {r.h_max_m:.3f} m (frame {r.h_max_frame})")
        print(f"  beyond the prior's zero ({width:g} m): {100 * r.beyond_prior_zero_share:.1f} % of the garment "
              f"(at most {100 * r.worst_beyond_prior_zero_share:.1f} %, frame {r.worst_beyond_prior_zero_frame}); "
              f"at its floor ({2 * width:g} m): {100 * r.at_prior_floor_share:.2f} %")
    if out is not None:
        with atomic_write_path(out, overwrite=args.overwrite) as tmp:
            tmp.write_text(json.dumps([r.to_json() for r in reports], indent=1) + "\n", encoding="utf-8")
    return 0


def run_info(args: argparse.Namespace) -> int:
    # lazy: 'garmentnerf --help' and flag errors answer without torch and the model stack (0.4 s against 6 s)
    from garmentnerf.data.scene import Scene

    scene = Scene.load(args.scene)
    size_bytes = sum(p.stat().st_size for p in scene.root.rglob("*") if p.is_file() and "cache" not in p.parts)
    summary = {
        "scene": str(scene.root), "image_size": list(scene.image_size), "fps": scene.fps,
        "garment": scene.garment, "body": scene.body,
        "cameras": {split: scene.camera_names(split) for split in ("train", "unseen_view", "reference")},
        "sequences": {name: {"frames": info.frames, "split": info.split, "motion": info.motion}
                      for name, info in scene.sequences.items()},
        "palette_init": scene.palette_init, "simulation": scene.simulation,
        "size_on_disk_bytes_without_cache": size_bytes,
    }
    if args.json:
        print(json.dumps(summary, indent=2))
        return 0
    print(f"scene      {scene.root}  ({size_bytes / 2**20:.1f} MiB without the image cache)")
    print(f"images     {scene.image_size[0]}x{scene.image_size[1]} at {scene.fps:g} fps")
    print(f"garment    {scene.garment.get('kind')}  color {scene.garment.get('color')}")
    print(f"body       {scene.body.get('model')}  shape {scene.body.get('shape')}")
    for split, names in summary["cameras"].items():
        print(f"cameras    {split:12s} {len(names):3d}  {' '.join(names)}")
    for name, info in summary["sequences"].items():
        stats = scene.simulation.get(name, {})
        extra = "".join(f"  {k}={v}" for k, v in stats.items() if not isinstance(v, (list, dict)))
        print(f"sequence   {name:12s} {info['frames']:5d} frames  {info['split']:13s} {info['motion']}{extra}")
    return 0


def run_render(args: argparse.Namespace) -> int:
    # lazy: 'garmentnerf --help' and flag errors answer without torch and the model stack (0.4 s against 6 s)
    from garmentnerf.data.scene import Scene
    from garmentnerf.data.scene_images import SceneImages

    scene = Scene.load(args.scene)
    sequences = args.sequence or scene.sequence_names()
    for name in sequences:
        scene.sequence(name)  # raises a clear error for an unknown name
    cams = scene.camera_names(args.split) if args.split else scene.camera_names()
    total = sum(len(cams) * scene.num_frames(s) for s in sequences)
    rendered = 0
    with SceneImages(scene) as images, tqdm(total=total, unit="img", desc="rendering") as bar:
        for name in sequences:
            done_before = bar.n
            rendered += images.ensure(name, cams, progress=lambda done, _total: bar.update(done_before + done - bar.n))
    print(f"{rendered} images rendered, {total - rendered} already cached, in {scene.cache_dir}")
    return 0


def run_preview(args: argparse.Namespace) -> int:
    # lazy: 'garmentnerf --help' and flag errors answer without torch and the model stack (0.4 s against 6 s)
    from garmentnerf.data.preview import scene_contact_sheet
    from garmentnerf.data.scene import Scene
    from garmentnerf.data.scene_images import SceneImages

    out = refuse_existing(args.out, args.overwrite)
    scene = Scene.load(args.scene)
    sequence = args.sequence or scene.sequence_names()[0]
    scene.sequence(sequence)
    with SceneImages(scene) as images:
        sheet = scene_contact_sheet(scene, images, sequence, show_labels=args.labels)
    with atomic_write_path(out) as tmp:
        iio.imwrite(tmp, sheet, extension=".png")
    print(f"wrote {out} ({sheet.shape[1]}x{sheet.shape[0]})")
    return 0
