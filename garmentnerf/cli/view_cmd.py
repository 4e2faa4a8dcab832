"""``garmentnerf view``: the desktop previewer (a window; needs a display)."""

from __future__ import annotations

import argparse
import os
import sys

from garmentnerf.cli import view_bench
from garmentnerf.cli.common import add_body_args, add_demo_arg, check_output_file, load_body, run_folder_arg
from garmentnerf.demos import DEFAULT_DEMO, demo

#: Printed (as the one line on stderr) when no display is named; exit code 2.
HEADLESS_HINT = "render headless instead: garmentnerf render --camera orbit --frames 0:30 --out frames/"
NO_DISPLAY_MESSAGE = f"garmentnerf: no display available (DISPLAY/WAYLAND_DISPLAY unset); {HEADLESS_HINT}"


def cannot_open_window_message() -> str:
    """The one line when a display is named but no window opens there (no server answers)."""
    named = ", ".join(f"{k}={os.environ[k]}" for k in ("DISPLAY", "WAYLAND_DISPLAY") if os.environ.get(k))
    if not named:
        return NO_DISPLAY_MESSAGE
    return f"garmentnerf: cannot open a window on {named} (no display server answers there); {HEADLESS_HINT}"


def register(sub) -> None:
    view = sub.add_parser(
        "view", help="open the desktop previewer (needs a display)",
        description="Open the interactive previewer: the body playing a motion, turntable camera, timeline, "
                    "snapshots. Press H in the window for the shortcuts. Without a display it prints how to "
                    "render headless instead and exits with code 2.")
    add_body_args(view)
    view.add_argument("--run", default=None, metavar="DIR",
                      help="a training run folder: show its neural garment (default: the bundled demo when "
                           "installed, else the body only)")
    add_demo_arg(view, f"default: {DEFAULT_DEMO} (the previewer's Garment menu switches between them)")
    view.add_argument("--scene", default=None, metavar="DIR", help="scene folder to use instead of the run's")
    view.add_argument("--no-watch", action="store_true",
                      help="with --run: do not show new checkpoints as the run trains (default: the newest "
                           "checkpoint is loaded in the background as it lands, and shown)")
    view.add_argument("--body-only", action="store_true", help="show only the body (no run, not even the demo)")
    view.add_argument("--motion", default=None,
                      help="motion name (see 'garmentnerf motion list'), names joined by ',', a motion/AMASS "
                           ".npz file, or a sequence of the run's scene (default: the run scene's first training "
                           "sequence, else walk)")
    view.add_argument("--size", default="1280x800", help="window size WIDTHxHEIGHT in screen units (default: 1280x800)")
    view.add_argument("--snapshot-dir", default="snapshots", help="folder for snapshots (default: ./snapshots)")
    view.add_argument("--snapshot-size", default="1920x1080",
                      help="snapshot resolution WIDTHxHEIGHT (default: 1920x1080)")
    view.add_argument("--msaa", type=int, default=None,
                      help="multisampling of the scene in the window (0 = off; default: 4 on a GPU, off on a "
                           "software rasteriser such as llvmpipe); snapshots always use 4")
    view.add_argument("--render-scale", type=float, default=1.0,
                      help="render the scene at this fraction of the window's pixels (0.25..1; lower is faster "
                           "on a software rasteriser; default: 1)")
    view.add_argument("--fixed-scene-scale", action="store_true",
                      help="draw the scene at --render-scale even while the view moves (default: smaller while "
                           "it moves, to keep the UI at 30 fps on a software rasteriser)")
    view.add_argument("--paused", action="store_true", help="start paused")
    view.add_argument("--no-bake", action="store_true",
                      help="do not bake the clip in the background (baked frames orbit and play at display rate; "
                           "they are kept in the user's cache, so a second launch opens on them)")
    view.add_argument("--no-vsync", action="store_true", help="do not wait for the display refresh")
    bench = view.add_argument_group("benchmark (--bench)")
    bench.add_argument("--bench", action="store_true",
                       help="measure the previewer instead of showing it: UI frame rate while the neural worker "
                            "renders, recolor latency in frames, neural frame time per quality preset; prints "
                            "the figures (vsync off; still needs a display, e.g. Xvfb)")
    bench.add_argument("--json", default=None, metavar="PATH", help="with --bench: also write the figures as JSON")
    bench.add_argument("--overwrite", action="store_true", help="with --bench: replace --json if it exists")
    bench.add_argument("--bench-seconds", type=float, default=5.0,
                       help="with --bench: how long to measure the busy UI frame rate (default: 5)")
    bench.add_argument("--bench-repeats", type=int, default=3,
                       help="with --bench: neural renders timed per quality preset (default: 3)")
    view.set_defaults(func=run_view)


def run_view(args: argparse.Namespace) -> int:
    # lazy: 'garmentnerf --help' and flag errors answer without torch and the model stack (0.4 s against 6 s)
    from garmentnerf.viewer import export_jobs

    size = export_jobs.parse_size(args.size, "--size")
    snapshot_size = export_jobs.parse_size(args.snapshot_size, "--snapshot-size")
    if args.msaa is not None and args.msaa < 0:
        raise ValueError(f"--msaa must be >= 0, got {args.msaa}")
    if not (0.25 <= args.render_scale <= 1.0):
        raise ValueError(f"--render-scale must be in [0.25, 1], got {args.render_scale}")
    bench = getattr(args, "bench", False)
    if bench and not (args.bench_seconds > 0 and args.bench_repeats >= 1):
        raise ValueError("--bench-seconds must be > 0 and --bench-repeats >= 1")
    if not bench and getattr(args, "json", None):
        raise ValueError("--json needs --bench")
    if args.json:
        check_output_file(args.json, "--json", args.overwrite)
    run_dir = None
    if not args.body_only:
        default = DEFAULT_DEMO if demo(DEFAULT_DEMO).installed else None  # else: the body alone
        run_dir = run_folder_arg(args, default)
    # lazy: 'garmentnerf --help' and flag errors answer without torch and the model stack
    from garmentnerf.viewer import app as app_module

    if not app_module.display_available():
        print(NO_DISPLAY_MESSAGE, file=sys.stderr)
        return 2

    run = None
    if run_dir is not None:
        # lazy: 'garmentnerf --help' and flag errors answer without torch and the model stack
        from garmentnerf.runs import load_run

        run = load_run(run_dir, scene=args.scene)
        if run.scene is None and run.info.get("scene") and args.motion is None:
            raise FileNotFoundError(f"{run_dir}: the run's scene {run.info['scene']} is missing; pass --scene DIR, "
                                    f"or --motion NAME to play a motion without it")
        body = betas = None
    else:
        body, betas = load_body(args)
    try:
        app = app_module.App(motion=args.motion if run is not None else (args.motion or "walk"), body=body,
                             betas=betas, run=run, size=size, samples=args.msaa,
                             render_scale=args.render_scale, vsync=not (args.no_vsync or bench),
                             dynamic_scene=not args.fixed_scene_scale,
                             watch=args.run is not None and not args.no_watch and not bench,
                             snapshot_dir=args.snapshot_dir, snapshot_size=snapshot_size,
                             playing=not args.paused and not bench, bake=not args.no_bake)
    except app_module.NoDisplayError:
        print(cannot_open_window_message(), file=sys.stderr)
        return 2
    if run is None:
        app.shape_label = args.shape
    if bench:
        with app:
            result = view_bench.run_bench(app, seconds=args.bench_seconds, repeats=args.bench_repeats)
        view_bench.print_figures(result)
        if args.json:
            view_bench.write_json(result, args.json, overwrite=args.overwrite)
            print(f"wrote {args.json}")
        return 0
    with app:
        frames = app.run()
        if app.max_frames is not None:
            t = app.timer
            w, h = app.window.framebuffer_size
            print(f"viewer: {frames} frames, UI {t.fps:.1f} fps ({t.interval_ms:.1f} ms/frame, "
                  f"work {t.work_ms:.1f} ms, scene {t.scene_ms:.1f} ms) at {w}x{h} on {app.window.gl_renderer}")
            if app.neural_view.renderer is not None:
                st, n = app.neural_view.renderer.stats, app.neural_view.last_result
                last = f", last {n['timings'].get('render_total', 0):.0f} ms at quality {n['quality']:.2f}" if n else ""
                print(f"viewer: {st.renders} neural frame(s){last}; errors {st.errors}"
                      + (f" ({st.last_error})" if st.last_error else ""))
    return 0
