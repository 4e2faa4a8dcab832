"""``garmentnerf maps``: the UV-space info maps (normal, velocity) of one frame."""

from __future__ import annotations

import argparse
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from garmentnerf.budgets import HISTORY
from garmentnerf.cli.common import (add_body_args, add_motion_args, check_frame, check_motion_fps, load_body,
                                    load_motion_arg, refuse_existing)
from garmentnerf.io_utils import atomic_write_path
from garmentnerf.output_checks import check_finite, check_points, check_varies

DESCRIPTION = """\
Rasterise the body's UV-space info maps for one frame of a motion and save them as .npz:

  normal    (H, W, 3)   float32  unit vertex normals of the posed body with the root's
                                 rotation removed (root-relative frame), interpolated in UV space
  velocity  (H, W, 3k)  float32  k velocity slots; slot i (channels 3(i-1)..3i) is the vertex
                                 displacement x(t-i+1) - x(t-i) mapped to the rest pose by the
                                 inverse skinning matrix, in m/s x 1/6 (= the paper's x5 per frame at
                                 30 fps). Before the motion starts the body is held at frame 0.
  mask      (H, W)      bool     texels the UV atlas covers (gutters are filled by dilation from the
                                 nearest covered texel, so bilinear lookups never read zeros)

Rows run along v from v = 0 (row 0) to v = 1; see garmentnerf.gl.uv_raster for the exact mapping.
"""


def register(sub) -> None:
    p = sub.add_parser("maps", help="UV-space normal/velocity info maps of one frame (.npz)", description=DESCRIPTION,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    add_body_args(p)
    add_motion_args(p)
    p.add_argument("--history", type=int, default=2, help="k, velocity history slots, 0..8 (default: 2)")
    p.add_argument("--resolution", type=int, default=128, help="map size in texels (default: 128)")
    p.add_argument("--out", required=True, help="output .npz")
    p.add_argument("--png", default=None, help="also write a preview image of the maps")
    p.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    p.set_defaults(func=run_maps)


def run_maps(args: argparse.Namespace) -> int:
    # the arguments that scale the work first, before anything is imported or loaded (garmentnerf.budgets)
    check_motion_fps(args)  # the resampled frames grow with it
    HISTORY.check(args.history, "--history")
    # lazy: 'garmentnerf --help' and flag errors answer without torch and the model stack (0.4 s against 6 s)
    from garmentnerf.gl.context import create_context
    from garmentnerf.gl.info_maps import InfoMapRenderer

    out = refuse_existing(args.out, args.overwrite)
    if not 8 <= args.resolution <= 4096:
        raise ValueError(f"--resolution must be between 8 and 4096, got {args.resolution}")
    body, betas = load_body(args)
    motion = load_motion_arg(args, body, betas)
    check_frame(motion, args.frame)
    ctx = create_context()
    renderer = InfoMapRenderer(ctx, body, resolution=args.resolution, history=args.history)
    first = max(0, args.frame - args.history)
    clip = motion.slice(first, args.frame + 1)
    posed = clip.pose(body, betas)
    # what the maps are made of, and the maps, checked before they are written (garmentnerf.output_checks)
    for i, vertices in enumerate(posed.vertices):
        check_points(vertices, "the posed body", f"--motion {args.motion} frame {first + i}")
    maps = renderer.render_clip(posed, fps=motion.fps)[args.frame - first]
    cause = f"--motion {args.motion} frame {args.frame}"
    check_varies(maps.normal, "the normal map", cause)  # a body's normals point every way
    check_finite(maps.velocity, "the velocity map", cause)
    with atomic_write_path(out) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, normal=maps.normal.numpy(), velocity=maps.velocity.numpy(), mask=maps.mask.numpy())
    if args.png:
        _write_preview(maps, Path(args.png))
    print(f"wrote {out}: normal {tuple(maps.normal.shape)}, velocity {tuple(maps.velocity.shape)}, "
          f"mask {tuple(maps.mask.shape)} ({float(maps.mask.float().mean()) * 100:.1f}% covered)")
    return 0


def _write_preview(maps, path: Path) -> None:
    normal = (maps.normal.numpy() * 0.5 + 0.5).clip(0, 1)
    tiles = [normal]
    vel = maps.velocity.numpy()
    for i in range(vel.shape[-1] // 3):
        tiles.append((vel[..., 3 * i:3 * i + 3] * 2.0 + 0.5).clip(0, 1))
    image = (np.concatenate(tiles, axis=1)[::-1] * 255).astype(np.uint8)  # v up in the picture
    with atomic_write_path(path) as tmp:
        iio.imwrite(tmp, image, extension=".png")
