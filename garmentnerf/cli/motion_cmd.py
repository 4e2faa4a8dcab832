"""``garmentnerf motion``: list the available motions."""

from __future__ import annotations

import argparse
import json


def register(sub) -> None:
    motion = sub.add_parser("motion", help="body motions")
    motion_sub = motion.add_subparsers(dest="motion_command", metavar="ACTION", required=True)
    lst = motion_sub.add_parser("list", help="list the motions available by name, with frame counts and fps")
    lst.add_argument("--json", action="store_true", help="print JSON")
    lst.set_defaults(func=run_list)


def run_list(args: argparse.Namespace) -> int:
    # lazy: 'garmentnerf --help' and flag errors answer without torch and the model stack (0.4 s against 6 s)
    from garmentnerf.motion.library import available_motions

    infos = available_motions()
    if args.json:
        print(json.dumps([{"name": m.name, "source": m.source, "frames": m.frames, "fps": m.fps,
                           "duration_s": round(m.duration, 3)} for m in infos], indent=2))
        return 0
    print(f"{'name':18s} {'frames':>6s} {'fps':>6s} {'seconds':>8s}  source")
    for m in infos:
        print(f"{m.name:18s} {m.frames:6d} {m.fps:6.1f} {m.duration:8.2f}  {m.source}")
    print("\nJoin names with ',' to play clips one after another with smooth blends, e.g. --motion walk,dance_a")
    return 0
