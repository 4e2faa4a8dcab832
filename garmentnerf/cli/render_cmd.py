"""``garmentnerf render``: headless renders of a run (PNG frames and an mp4), through the same
:class:`~garmentnerf.render.session.RenderSession` the viewer uses."""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

from tqdm import tqdm

from garmentnerf.cli.common import (
    add_demo_arg,
    add_device_arg,
    add_memory_arg,
    add_scene_override_arg,
    check_memory_arg,
    check_output_dir,
    parse_device,
    render_geometry,
    render_geometry_of,
    run_folder_arg,
)
from garmentnerf.demos import DEFAULT_DEMO
from garmentnerf.ranges import parse_frames, parse_list
from garmentnerf.budgets import QUALITY, VIDEO_FPS, check_memory, render_memory
from garmentnerf.output_checks import check_finite, check_points
from garmentnerf.render.video import FrameWriter, VideoWriter


def register(sub) -> None:
    p = sub.add_parser(
        "render", help="render a trained run headless to PNG frames (and an mp4)",
        description="Render a run's neural garment for a motion and a camera path into PNG frames (and an mp4 "
                    "with --video). Existing files are never overwritten. Ctrl-C stops cleanly: the frames "
                    "written so far stay, and the video holds them.")
    p.add_argument("--run", default=None, metavar="DIR",
                   help="run folder (run.json + model.safetensors); default: the bundled demo (--demo)")
    add_demo_arg(p, f"default: {DEFAULT_DEMO}")
    add_scene_override_arg(p)
    p.add_argument("--motion", default=None,
                   help="a scene sequence name or a motion name/file (default: the scene's first training "
                        "sequence, else walk)")
    p.add_argument("--camera", default=None,
                   help="orbit (a turntable over the frames), orbit:AZ[:EL] (fixed), or a scene camera name or "
                        "index (default: orbit)")
    p.add_argument("--camera-path", default=None, metavar="JSON",
                   help="render along a camera path instead (the previewer's Camera path panel saves one; "
                        "nerfstudio's camera_path.json loads too): its keyframes' frames choose the motion's "
                        "frames, its size and fps are the defaults of --size and --fps")
    p.add_argument("--frames", default=None, metavar="A:B",
                   help="frames A..B-1 of the motion (A:B, A:B:S, A:, :B or A; default: all, or the camera path's span)")
    p.add_argument("--size", default=None,
                   help="output size: N (longer side; orbit views are square) or WxH (default: 256, or the "
                        "camera path's)")
    p.add_argument("--preset", default=None, metavar="NAME",
                   help="render preset: reference (the paper's sampling), full (default: the reference's image, "
                        "culled), balanced or interactive (the rows of 'garmentnerf bench --run')")
    p.add_argument("--quality", type=float, default=None,
                   help="neural render quality: fraction of the training pixel density, 0.0625..4 "
                        "(default: the preset's resolution)")
    p.add_argument("--palette", default=None,
                   help="palette colors as hex, in the model's order: '#garment[,#body]', or for a layered "
                        "garment '#inner,#outer[,#body]' ('-' keeps one; default: the learned palette)")
    p.add_argument("--body-color", "--body-colour", dest="body_color", default=None, metavar="HEX",
                   help="replace the body/other palette color (the palette's last)")
    p.add_argument("--background", default=None, metavar="HEX", help="background color (default: the model's)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (made if needed)")
    p.add_argument("--video", action="store_true", help="also write an mp4 of the frames")
    p.add_argument("--fps", type=float, default=None, help="video frame rate, 0.1..1000 (default: the motion's)")
    add_device_arg(p)
    add_memory_arg(p)
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run_render)


#: The output size of a render whose --size and camera path say none (an orbit's side).
DEFAULT_SIZE = 256


def render_frames(text: str | None, num_frames: int, motion: str) -> list[int]:
    """``--frames`` of the motion being rendered (:func:`garmentnerf.ranges.parse_frames`); all of them when
    not given."""
    frames = parse_frames(text, "--frames", num_frames, motion)
    return list(range(num_frames)) if frames is None else frames


def parse_output_size(text: str):
    t = str(text).strip()
    if re.fullmatch(r"\d+", t):
        n = int(t)
        if not 8 <= n <= 8192:
            raise ValueError(f"--size must be in 8..8192, got {n}")
        return n
    m = re.fullmatch(r"(\d+)\s*[xX]\s*(\d+)", t)
    if not m:
        raise ValueError(f"--size must be N or WIDTHxHEIGHT, got '{text}'")
    w, h = int(m.group(1)), int(m.group(2))
    if not (8 <= w <= 8192 and 8 <= h <= 8192):
        raise ValueError(f"--size {w}x{h} is out of range (8..8192 per side)")
    return (w, h)


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "-", Path(str(name)).stem or "render").strip("-.") or "render"


def run_render(args: argparse.Namespace) -> int:
    # the arguments that scale the work first, before anything is imported or loaded (garmentnerf.budgets)
    if args.quality is not None:
        QUALITY.check(args.quality, "--quality")
    if args.fps is not None:
        VIDEO_FPS.check(args.fps, "--fps")
    max_gib = check_memory_arg(args)
    if args.size is not None:  # what any preset needs, before torch loads (garmentnerf.budgets, "Memory")
        _check_render_memory(args, parse_output_size(args.size), args.quality, max_gib)
    # lazy: 'garmentnerf --help' and flag errors answer without torch and the model stack (0.4 s against 6 s)
    from garmentnerf.gl.context import create_context
    from garmentnerf.render.cameras import cameras_for, parse_camera_spec
    from garmentnerf.render.colors import build_palette
    from garmentnerf.render.session import RenderSession

    size, preset, background, camera_path = _checked_render_args(args)  # before the model loads
    out_size = size if size is not None else (camera_path.size(None) if camera_path is not None else DEFAULT_SIZE)
    quality = args.quality if args.quality is not None else preset.resolution_scale
    geometry = _check_render_memory(args, out_size, quality, max_gib)
    run_dir, run = _load_render_run(args)
    if geometry is None:  # the run's files did not say: its loaded config does
        _check_render_memory(args, out_size, quality, max_gib, render_geometry_of(run))
    spec = parse_camera_spec(args.camera or "orbit", run.scene) if camera_path is None else None
    palette = build_palette(run.palette(), args.palette, args.body_color)
    ctx = create_context(headless=True)
    session = None
    try:
        session = RenderSession(run, ctx, args.motion)
        motion_name = session.sequence or session.motion.name
        if camera_path is not None:
            camera_path.check_motion(session.num_frames, f"motion '{motion_name}'")
            if args.frames is not None:
                frames = render_frames(args.frames, session.num_frames, f"motion '{motion_name}'")
            else:
                try:
                    frames = camera_path.render_frames()
                except ValueError as exc:
                    raise ValueError(f"--camera-path {args.camera_path}: {exc}") from None
        else:
            frames = render_frames(args.frames, session.num_frames, f"motion '{motion_name}'")
        given = f"--motion {args.motion}" if args.motion is not None else f"motion '{motion_name}'"
        for f in frames:  # a body float32 cannot place (moved 1e5 m away) renders nothing: refused, not rendered
            check_points(session.posed.vertices[f], "the posed body", f"{given} frame {f}")
        if camera_path is not None:
            cameras = camera_path.cameras(frames, size)
            cam_label, fps = Path(args.camera_path).stem, args.fps or camera_path.fps
        else:
            centers = [session.body_center(f)[:2] for f in frames]
            cameras = cameras_for(spec, frames, size or DEFAULT_SIZE, run.scene, centers)
            cam_label, fps = spec.name if spec.kind == "scene" else spec.kind, args.fps or session.fps
        out = Path(args.out)
        writer = FrameWriter(out, prefix="frame")
        writer.check(frames)
        video_path = out / f"{_safe(motion_name)}_{_safe(cam_label)}.mp4"
        video = VideoWriter(video_path, fps) if args.video else None
        times, interrupted, written_video = _render_frames(session, frames, cameras, args, preset, palette,
                                                           background, writer, video,
                                                           f"{given} seen by camera {cam_label}")
        n = len(writer.written)
        speed = f"{sum(times) / len(times):.0f} ms/frame" if times else "no frame finished"
        where = f"{out}" + (f" and {written_video}" if written_video else "")
        w, h = (cameras[0].width, cameras[0].height) if cameras else (0, 0)
        print(f"render: {n} frame(s) {w}x{h} of {motion_name} ({cam_label}) into {where}; "
              f"{speed}; palette {', '.join(_hex(c) for c in palette.tolist())}")
        if interrupted:
            print(f"garmentnerf: interrupted after {n} of {len(frames)} frames", file=sys.stderr)
            return 130
        return 0
    finally:
        if session is not None:
            session.close()
        ctx.release()


def _check_render_memory(args, size, quality, max_gib, geometry=None):
    """Refuse a render of ``size`` (N: at most N x N; or (W, H)) at ``quality`` (None: not known yet)
    whose estimated peak memory does not fit (:func:`garmentnerf.budgets.check_memory`). Returns the
    run's :class:`~garmentnerf.budgets.RenderGeometry` read from its files (``geometry`` when given), or
    None when they do not say (then only the output pixels were counted)."""
    width, height = (size, size) if isinstance(size, int) else size
    if geometry is None:
        geometry = render_geometry(run_folder_arg(args, DEFAULT_DEMO), args.scene)
    estimate = render_memory(geometry, width, height, quality if geometry is not None else None)
    shown = f" at quality {quality:g}" if estimate.rays else ""
    check_memory(estimate, f"a render of {width}x{height} pixels{shown}", max_gib, lower="--size or --quality")
    return geometry


def _checked_render_args(args: argparse.Namespace):
    """(output size or None (the default), render preset, background color or None, camera path or
    None); everything that can be wrong with the arguments fails here, before the model loads."""
    # lazy: 'garmentnerf --help' and flag errors answer without torch and the model stack (0.4 s against 6 s)
    from garmentnerf.render.colors import parse_hex_color
    from garmentnerf.render.presets import get_render_preset
    from garmentnerf.render.session import DEFAULT_PRESET

    size = parse_output_size(args.size) if args.size is not None else None
    camera_path = None
    if args.camera_path is not None:
        # lazy: 'garmentnerf --help' and flag errors answer without torch and the model stack
        from garmentnerf.render.camera_path import load_camera_path

        if args.camera is not None:
            raise ValueError("--camera and --camera-path both choose the camera: pass one")
        camera_path = load_camera_path(args.camera_path)
    parse_device(args.device)
    check_output_dir(args.out)
    preset = get_render_preset(args.preset if args.preset is not None else DEFAULT_PRESET)
    if args.palette is not None:
        for i, item in enumerate(parse_list(args.palette, "--palette", kind="colour ('-' keeps one)")):
            if item != "-":
                parse_hex_color(item, f"--palette color {i}")
    if args.body_color is not None:
        parse_hex_color(args.body_color, "--body-color")
    background = parse_hex_color(args.background, "--background") if args.background else None
    return size, preset, background, camera_path


def _load_render_run(args: argparse.Namespace):
    """(run folder, loaded run) of ``--run`` or ``--demo`` (default: the default demo) with ``--scene``."""
    # lazy: 'garmentnerf --help' and flag errors answer without torch and the model stack (0.4 s against 6 s)
    from garmentnerf.runs import load_run

    run_dir = run_folder_arg(args, DEFAULT_DEMO)
    run = load_run(run_dir, device=args.device, scene=args.scene)
    if run.scene is None and run.info.get("scene") and args.motion is None:
        raise FileNotFoundError(f"{run_dir}: the run's scene {run.info['scene']} is missing; pass --scene DIR, or "
                                f"--motion NAME to render a motion without it")
    return run_dir, run


def _render_frames(session, frames, cameras, args, preset, palette, background, writer, video, label):
    """Render and write every frame (and append it to ``video``); Ctrl-C stops after the frames
    written, an image that is not finite before it is written (``label``: what is rendered, for the
    message). Returns (ms per frame rendered, interrupted, the video written or None)."""
    interrupted = False
    times = []
    progress = None
    if not args.no_progress:
        progress = tqdm(total=len(frames), unit="frame", desc="render", file=sys.stderr)
    try:
        for f, cam in zip(frames, cameras):
            nf = session.render(f, cam, args.quality, preset=preset)
            image = nf.composite(palette, background)
            check_finite(image, "the rendered image", f"{label}, frame {f}")
            writer.write(f, image)
            if video is not None:
                video.append(image)
            times.append(nf.timings["total"])
            if progress is not None:
                progress.set_postfix_str(f"{nf.timings['total']:.0f} ms")
                progress.update(1)
    except KeyboardInterrupt:
        interrupted = True
    finally:
        if progress is not None:
            progress.close()
        if video is not None:
            try:
                written_video = video.close()
            except BaseException:
                video.abort()
                raise
        else:
            written_video = None
    return times, interrupted, written_video


def _hex(rgb) -> str:
    # lazy: 'garmentnerf --help' and flag errors answer without torch and the model stack (0.4 s against 6 s)
    from garmentnerf.render.colors import to_hex

    return to_hex(rgb)
