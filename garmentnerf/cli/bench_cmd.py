"""``garmentnerf bench``: time the per-frame stages and print (and optionally save) the figures."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

ROWS = [
    ("pose_clip_ms_per_frame", "pose the body (LBS, batched clip)", "ms/frame"),
    ("info_vertex_attributes_ms_per_frame", "info maps: per-vertex normals + velocities", "ms/frame"),
    ("info_maps_raster_ms_per_frame", "info maps: UV rasterisation 128x128 (9 ch)", "ms/frame"),
    ("info_maps_total_ms_per_frame", "info maps total (paper: 130 ms)", "ms/frame"),
    ("camera_pass_512_ms", "camera pass 512x512 (depth, face, bary, uv)", "ms"),
    ("depth_range_512_ms", "ray bounds 512x512 (near + far depth)", "ms"),
    ("projection_ms", "body projection of 262,144 points (b_t, h, b_o, uv)", "ms"),
    ("projection_points_per_s", "surface projection throughput", "points/s"),
]


def register(sub) -> None:
    p = sub.add_parser("bench", help="benchmark the per-frame stages (prints figures, writes JSON)")
    p.add_argument("--json", default=None, metavar="PATH", help="also write the figures as JSON")
    p.add_argument("--runs", type=int, default=20, help="timed repetitions per stage (median is reported)")
    p.set_defaults(func=run_bench)


def run_bench(args: argparse.Namespace) -> int:
    from garmentnerf.benchmarks import foundation_benchmark
    from garmentnerf.io_utils import atomic_write_path

    if args.runs < 1:
        raise ValueError(f"--runs must be at least 1, got {args.runs}")
    results = foundation_benchmark(runs=args.runs)
    machine = results["machine"]
    print(f"machine: {machine.get('cpus')} CPUs, torch threads {machine.get('torch_threads')}, "
          f"GL: {machine.get('GL_RENDERER', '?')}")
    for key, label, unit in ROWS:
        value = results[key]
        text = f"{value:,.0f}" if unit == "points/s" else f"{value:8.2f}"
        print(f"  {label:48s} {text:>12s} {unit}")
    if args.json:
        with atomic_write_path(Path(args.json)) as tmp:
            tmp.write_text(json.dumps(results, indent=2))
        print(f"wrote {args.json}")
    return 0
