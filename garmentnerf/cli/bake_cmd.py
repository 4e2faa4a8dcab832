"""``garmentnerf bake``: bake a clip's frames into a bake folder (:mod:`garmentnerf.bake`), headless."""

from __future__ import annotations

import argparse
import sys
import time

from garmentnerf.cli.common import add_demo_arg, add_device_arg, add_scene_override_arg, check_output_dir, run_folder_arg

DEFAULT_DEMO = "skirt"


def register(sub) -> None:
    from garmentnerf.bake.settings import BAKE_PRESETS, DEFAULT_BAKE_PRESET

    p = sub.add_parser(
        "bake", help="bake a clip's garment once, for display-rate orbiting in the previewer and for export",
        description="Render each frame's garment from a ring of cameras once and keep it as view surfaces in a bake "
                    "folder, which the previewer draws from any camera without the network and 'garmentnerf export' "
                    "writes as glTF. Resumes: baking into the same folder makes only the frames it lacks. Ctrl-C "
                    "stops; the frames finished stay.")
    p.add_argument("--run", default=None, metavar="DIR", help="run folder; default: the bundled demo (--demo)")
    add_demo_arg(p, f"default: {DEFAULT_DEMO}")
    add_scene_override_arg(p)
    p.add_argument("--motion", default=None,
                   help="a scene sequence name or a motion name/file (default: the scene's first training sequence)")
    p.add_argument("--frames", default=None, metavar="A:B", help="frames A..B-1 (A:B, A:B:S, A:, :B or A; default: all)")
    p.add_argument("--preset", default=DEFAULT_BAKE_PRESET, choices=list(BAKE_PRESETS),
                   help=f"capture views and quality (default: {DEFAULT_BAKE_PRESET}; "
                        + "; ".join(f"{k}: {s.views} views at quality {s.quality:g}" for k, s in BAKE_PRESETS.items())
                        + ")")
    p.add_argument("--first", type=int, default=None, metavar="F",
                   help="bake from frame F on, then the frames before it (the previewer starts at its playhead)")
    p.add_argument("--workers", type=int, default=None,
                   help="bake processes, each on one core (default: one per core)")
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument("--out", metavar="DIR", help="the bake folder (made, or resumed)")
    where.add_argument("--cache", action="store_true",
                       help="bake into the user's cache folder of this run, motion and preset (where the previewer "
                            "looks), printing its path first")
    p.add_argument("--overwrite", action="store_true",
                   help="bake again into a folder that holds a bake of another model, motion or preset")
    add_device_arg(p)
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run_bake)


def run_bake(args: argparse.Namespace) -> int:
    from garmentnerf.bake.settings import bake_settings

    settings = bake_settings(args.preset)
    if args.workers is not None and not 1 <= args.workers <= 64:
        raise ValueError(f"--workers must be in 1..64, got {args.workers}")
    out = check_output_dir(args.out) if args.out is not None else None
    run_dir = run_folder_arg(args, DEFAULT_DEMO)
    # lazy: 'garmentnerf --help' and flag errors answer without torch and the model stack
    from tqdm import tqdm

    from garmentnerf.bake.capture import check_can_bake
    from garmentnerf.bake.clip import bake_frames, default_workers, frames_to_bake, manifest_for_session, prepare_folder
    from garmentnerf.bake.store import cache_folder
    from garmentnerf.folder_lock import lock_folder
    from garmentnerf.gl.context import create_context
    from garmentnerf.ranges import parse_frames
    from garmentnerf.render.session import RenderSession
    from garmentnerf.runs import load_run

    run = load_run(run_dir, device=args.device, scene=args.scene)
    ctx = create_context(headless=True)
    session = None
    try:
        session = RenderSession(run, ctx, args.motion)
        check_can_bake(session)
        name = session.sequence or session.motion.name
        frames = parse_frames(args.frames, "--frames", session.num_frames, f"motion '{name}'")
        frames = list(range(session.num_frames)) if frames is None else frames
        manifest = manifest_for_session(session, settings)
        faces = session.body.faces.cpu().numpy()
        if out is None:
            out = check_output_dir(cache_folder(manifest), "--cache")
        motion = args.motion
    finally:
        if session is not None:
            session.close()
        ctx.release()
    with lock_folder(out, "garmentnerf bake", what="bake"):
        folder = prepare_folder(out, manifest, faces, overwrite=args.overwrite or args.cache,
                                notice=lambda m: print(m, file=sys.stderr))
        if args.cache:
            print(f"bake folder: {out}", flush=True)  # the previewer reads this line
        todo = frames_to_bake(folder, frames, notice=lambda m: print(m, file=sys.stderr))
        if args.first is not None:
            todo = [f for f in todo if f >= args.first] + [f for f in todo if f < args.first]
        workers = args.workers or default_workers()
        print(f"bake: {len(frames) - len(todo)} of {len(frames)} frames of {name} already baked in {out}; "
              f"baking {len(todo)} with {settings.name} ({settings.views} views at quality {settings.quality:g}) "
              f"in {min(workers, max(1, len(todo)))} process(es)", file=sys.stderr)
        bar = None if args.no_progress or not todo else tqdm(total=len(todo), unit="frame", desc="bake",
                                                            file=sys.stderr, dynamic_ncols=True)
        t0 = time.perf_counter()
        done = []

        def on_frame(result):
            done.append(result)
            if bar is not None:
                bar.update(1)

        try:
            bake_frames(run_dir, args.scene, motion, settings, folder, todo, workers, args.device, on_frame)
        except KeyboardInterrupt:
            print(f"garmentnerf: interrupted after {len(done)} of {len(todo)} frames; bake again into {out} "
                  f"to finish", file=sys.stderr)
            return 130
        finally:
            if bar is not None:
                bar.close()
    wall = time.perf_counter() - t0
    size = sum(d.bytes for d in done)
    per = f"{wall / len(done):.2f} s a frame ({sum(d.seconds for d in done) / len(done):.1f} s in a process), " \
          f"{size / len(done) / 1e6:.2f} MB a frame" if done else "nothing to do"
    print(f"bake: {len(frames)} frames of {name} in {out}: {per}")
    return 0
