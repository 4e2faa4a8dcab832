"""``garmentnerf view``: the desktop previewer (a window; needs a display)."""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import sys
from pathlib import Path

from garmentnerf.cli.common import add_body_args

#: Printed (as the one line on stderr) when no window can be opened; exit code 2.
NO_DISPLAY_MESSAGE = ("garmentnerf: no display available; render headless with: "
                      "garmentnerf body export --motion MOTION --frame N --out body.glb "
                      "(or garmentnerf maps ...)")


def register(sub) -> None:
    view = sub.add_parser(
        "view", help="open the desktop previewer (needs a display)",
        description="Open the interactive previewer: the body playing a motion, turntable camera, timeline, "
                    "snapshots. Press H in the window for the shortcuts. Without a display it prints how to "
                    "render headless instead and exits with code 2.")
    add_body_args(view)
    view.add_argument("--motion", default="walk",
                      help="motion name (see 'garmentnerf motion list'), names joined by ',', or a motion/AMASS "
                           ".npz file (default: walk)")
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
    view.add_argument("--paused", action="store_true", help="start paused")
    view.add_argument("--no-vsync", action="store_true", help="do not wait for the display refresh")
    view.set_defaults(func=run_view)


def import_viewer(module: str = "app"):
    """Import ``garmentnerf.viewer.<module>``.

    An installed garmentnerf maps the top-level ``viewer/`` folder to ``garmentnerf.viewer`` (see
    pyproject.toml). Run from a source tree via PYTHONPATH, that mapping does not exist, so the package
    is registered here from the folder beside the ``garmentnerf`` package (as the GLSL loader does for
    ``shaders/``).
    """
    try:
        importlib.import_module("garmentnerf.viewer")
    except ModuleNotFoundError as exc:
        if exc.name != "garmentnerf.viewer":
            raise
        import garmentnerf

        root = Path(garmentnerf.__file__).resolve().parent.parent / "viewer"
        if not (root / "__init__.py").is_file():
            raise
        spec = importlib.util.spec_from_file_location("garmentnerf.viewer", root / "__init__.py",
                                                      submodule_search_locations=[str(root)])
        package = importlib.util.module_from_spec(spec)
        sys.modules["garmentnerf.viewer"] = package
        try:
            spec.loader.exec_module(package)
        except BaseException:
            del sys.modules["garmentnerf.viewer"]
            raise
        garmentnerf.viewer = package
    return importlib.import_module(f"garmentnerf.viewer.{module}")


def run_view(args: argparse.Namespace) -> int:
    export = import_viewer("export")
    size = export.parse_size(args.size, "--size")
    snapshot_size = export.parse_size(args.snapshot_size, "--snapshot-size")
    if args.msaa is not None and args.msaa < 0:
        raise ValueError(f"--msaa must be >= 0, got {args.msaa}")
    if not (0.25 <= args.render_scale <= 1.0):
        raise ValueError(f"--render-scale must be in [0.25, 1], got {args.render_scale}")
    app_module = import_viewer("app")
    if not app_module.display_available():
        print(NO_DISPLAY_MESSAGE, file=sys.stderr)
        return 2
    from garmentnerf.cli.common import load_body

    body, betas = load_body(args)
    try:
        app = app_module.App(motion=args.motion, body=body, betas=betas, size=size, samples=args.msaa,
                             render_scale=args.render_scale, vsync=not args.no_vsync, snapshot_dir=args.snapshot_dir, snapshot_size=snapshot_size,
                             playing=not args.paused)
    except app_module.NoDisplayError:
        print(NO_DISPLAY_MESSAGE, file=sys.stderr)
        return 2
    app.shape_label = args.shape
    with app:
        frames = app.run()
        if app.max_frames is not None:
            t = app.timer
            w, h = app.framebuffer_size
            print(f"viewer: {frames} frames, UI {t.fps:.1f} fps ({t.interval_ms:.1f} ms/frame, "
                  f"work {t.work_ms:.1f} ms, scene {t.scene_ms:.1f} ms) at {w}x{h} on {app.gl_renderer}")
    return 0
