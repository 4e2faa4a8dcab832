"""``garmentnerf export``: a bake folder's frames as an animated glTF binary (:mod:`garmentnerf.bake.export`)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from garmentnerf.cli.common import check_output_file
from garmentnerf.ranges import parse_frames


def register(sub) -> None:
    p = sub.add_parser(
        "export", help="write a bake's frames as an animated glTF binary (.glb) for Blender or a game engine",
        description="Write the body and the garment of each baked frame of a bake folder ('garmentnerf bake') as one "
                    "glTF 2.0 binary at a chosen palette: one mesh a frame (each part of the cloth from the capture "
                    "that faces it best, coloured per vertex), shown in turn by an animation at the motion's frame "
                    "rate. The file is written when every frame is done; an existing file is never replaced "
                    "without --overwrite.")
    p.add_argument("bake", metavar="BAKE", help="the bake folder")
    p.add_argument("--out", required=True, metavar="FILE.glb", help="the glTF binary to write")
    p.add_argument("--palette", default=None,
                   help="palette colors as hex, in the model's order: '#garment[,#body]', or for a layered "
                        "garment '#inner,#outer[,#body]' ('-' keeps one; default: the bake's learned palette)")
    p.add_argument("--frames", default=None, metavar="A:B",
                   help="frames A..B-1 of the motion (A:B, A:B:S or A), all baked; default: the frames baked, "
                        "when they run without a gap")
    p.add_argument("--overwrite", action="store_true", help="replace --out when it exists")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run_export)


def _runs(frames: list[int]) -> str:
    """``frames`` (sorted) as runs: ``0..5, 9, 12..13``."""
    runs, start = [], None
    for i, f in enumerate(frames):
        if start is None:
            start = f
        if i + 1 == len(frames) or frames[i + 1] != f + 1:
            runs.append(f"{start}" if start == f else f"{start}..{f}")
            start = None
    return ", ".join(runs)


def export_frames(folder, text: str | None) -> list[int]:
    """The frames of bake ``folder`` that ``--frames`` ``text`` names (all baked; ValueError naming the missing
    ones otherwise), or, when None, the frames baked when they run without a gap."""
    name = folder.manifest.get("motion_name") or "the motion"
    baked = sorted(folder.baked_frames())
    if text is None:
        if not baked:
            raise ValueError(f"{folder.root}: no frame is baked yet; bake some with 'garmentnerf bake --out {folder.root}'")
        if baked[-1] - baked[0] + 1 != len(baked):
            raise ValueError(f"{folder.root}: the frames baked ({_runs(baked)}) have gaps; choose a run of them with "
                             f"--frames A:B")
        return baked
    frames = parse_frames(text, "--frames", folder.num_frames, f"the bake of '{name}'")
    missing = sorted(set(frames) - set(baked))
    if missing:
        have = f"baked: {_runs(baked)}" if baked else "none is baked"
        raise ValueError(f"--frames {text}: {len(missing)} of its {len(frames)} frames are not baked yet "
                         f"({_runs(missing)}; {have}); bake them into {folder.root} with 'garmentnerf bake', "
                         f"or choose baked frames")
    return frames


def _load(folder, frame: int, colors: int, body_faces):
    """Frame ``frame`` of bake ``folder`` (:meth:`~garmentnerf.bake.store.BakeFolder.load_frame`), checked
    against the bake's ``colors`` palette colours and its body's triangles ``body_faces (F, 3)`` (or None);
    ValueError naming its file when it does not fit, FileNotFoundError when it was deleted since listed."""
    from garmentnerf.bake.store import BakeFileError

    path = folder.frame_path(frame)
    baked = folder.load_frame(frame)
    if baked is None:
        raise FileNotFoundError(f"{path}: frame {frame} is no longer baked")
    for i, view in enumerate(baked.views):
        if view.garment_colors != colors - 1:
            raise BakeFileError(f"{path}: view {i} holds {view.garment_colors} garment colour(s), the bake's palette "
                                f"{colors - 1}")
    if body_faces is not None and baked.body_vertices is not None and body_faces.size \
            and int(body_faces.max()) >= len(baked.body_vertices):
        raise BakeFileError(f"{path}: its body has {len(baked.body_vertices)} vertices, fewer than the bake's body "
                            f"triangles use")
    return baked


def run_export(args: argparse.Namespace) -> int:
    out = check_output_file(args.out, "--out", args.overwrite)
    if out.suffix.lower() != ".glb":
        raise ValueError(f"--out {out}: a glTF binary is written; name it FILE.glb")
    # lazy: 'garmentnerf --help' and flag errors answer without torch and the model stack
    import numpy as np
    import torch
    from tqdm import tqdm

    from garmentnerf.bake.export import ExportFrame, garment_mesh, write_glb
    from garmentnerf.bake.store import MANIFEST_FILE, BakeFolder
    from garmentnerf.model.palette import check_palette
    from garmentnerf.render.colors import build_palette, to_hex

    folder = BakeFolder.open(args.bake)
    manifest_path = Path(folder.root) / MANIFEST_FILE
    try:
        learned = torch.tensor(folder.manifest.get("palette") or [], dtype=torch.float32)
        check_palette(learned)
        if learned.shape[0] < 2:
            raise ValueError("needs a garment and a body colour")
        fps = float(folder.manifest.get("fps"))
        if not 0 < fps < float("inf"):
            raise ValueError(f"`fps` must be positive, got {fps}")
    except (ValueError, TypeError, RuntimeError) as exc:
        raise ValueError(f"{manifest_path}: the bake's palette or frame rate is unusable ({exc})") from None
    palette = build_palette(learned, args.palette).numpy().astype(np.float64)
    frames = export_frames(folder, args.frames)
    step = frames[1] - frames[0] if len(frames) > 1 else 1
    body_faces = folder.body_faces()
    for f in frames:  # every frame file read once before the work: a damaged one fails here, in one line
        _load(folder, f, len(palette), body_faces)
    exported = []
    bar = None if args.no_progress else tqdm(total=len(frames), unit="frame", desc="export", file=sys.stderr,
                                            dynamic_ncols=True)
    try:
        for f in frames:
            baked = _load(folder, f, len(palette), body_faces)
            exported.append(ExportFrame(f, garment_mesh(baked, palette), baked.body_vertices))
            if bar is not None:
                bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    write_glb(out, exported, fps / step, body_faces, palette)
    garment = sum(len(e.garment.positions) for e in exported)
    body = sum(len(e.body_vertices) for e in exported if e.body_vertices is not None and body_faces is not None)
    name = folder.manifest.get("motion_name") or "the motion"
    print(f"export: {len(frames)} frames ({_runs(frames) if step == 1 else args.frames}) of {name} at "
          f"{fps / step:g} fps into {out}: {garment} garment and {body} body vertices, "
          f"{out.stat().st_size / 1e6:.2f} MB; palette {', '.join(to_hex(c) for c in palette)}")
    return 0
