"""``garmentnerf bench``: time the per-frame stages and print (and optionally save) the figures.

Without ``--run``: the foundation GL/geometry passes (:func:`garmentnerf.perf.foundation_bench.foundation_benchmark`).

With ``--run DIR``: every render preset on the run's model, then playback figures
(:func:`garmentnerf.perf.preset_bench.preset_benchmark`, which says what is measured and how),
the previewer's render-ahead among them (``playback.render_ahead``, ``playback.completed_share``:
:mod:`garmentnerf.viewer.playback_bench`; ``--playback-frames`` limits the clip).
``--plot`` draws ms/frame (log) against PSNR per preset (:func:`garmentnerf.perf.plot.write_plot`).
``--against RUN`` renders every preset with another run's model too, taking turns preset by preset, and
prints ``--run``'s speed-up over it per preset with the PSNR difference (e.g. a new bundled model
against the one it replaces, kept outside the repo).

With ``--run DIR --bake [PRESET]``: the bake's cost and its figures against the ``full`` render on the
held-out cameras (:mod:`garmentnerf.perf.bake_bench`; ``bake.seconds_per_frame``, ``bake.psnr_fg``, ...).

With ``--run DIR --training``: seconds per NeRF training step of the run's recipe per MLP precision,
side by side, whole and by stage (:func:`garmentnerf.perf.train_bench.training_benchmark`); ``--against RUN``
times other runs' recipes taking turns with it (recipes compared in one run).

Every mode ends with what other processes took of the machine while it ran
(:class:`~garmentnerf.cpu_load.OtherProcessesLoad`), in cores, also kept in the JSON as
``machine.other_processes_cores``: figures measured beside another CPU-heavy job say so.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from garmentnerf.cli.common import add_demo_arg, check_output_file, run_folder_arg
from garmentnerf.cpu_load import OtherProcessesLoad, load_report
from garmentnerf.io_utils import atomic_write_path
from garmentnerf.budgets import PLAYBACK
from garmentnerf.ranges import parse_list

ROWS = [
    ("pose_clip_ms_per_frame", "pose the body (LBS, batched clip)", "ms/frame"),
    ("info_vertex_attributes_ms_per_frame", "info maps: per-vertex normals + velocities", "ms/frame"),
    ("info_maps_raster_ms_per_frame", "info maps: UV rasterisation 128x128 (9 ch)", "ms/frame"),
    ("info_maps_total_ms_per_frame", "info maps total (paper: 130 ms)", "ms/frame"),
    ("camera_pass_512_ms", "camera pass 512x512 (depth, face, bary, uv)", "ms"),
    ("depth_range_512_ms", "ray bounds 512x512 (near + far depth)", "ms"),
    ("body_layer_gl_512_ms", "body layer 512x512, 2x2 supersampled: GL-shaded", "ms"),
    ("body_layer_reference_512_ms", "body layer: the reference (camera pass + torch)", "ms"),
    ("projection_bind_ms", "body projection: bind a frame (search tree)", "ms"),
    ("projection_ms", "body projection of 262,144 points (b_t, h, b_o, uv)", "ms"),
    ("projection_us_per_point", "body projection per point", "us"),
    ("projection_points_per_s", "surface projection throughput", "points/s"),
]


def register(sub) -> None:
    p = sub.add_parser("bench", help="benchmark the per-frame stages (prints figures, writes JSON); "
                                     "with --run: the render presets of a trained run")
    p.add_argument("--json", default=None, metavar="PATH", help="also write the figures as JSON")
    p.add_argument("--runs", type=int, default=20, help="timed repetitions per stage (median is reported)")
    p.add_argument("--run", default=None, metavar="DIR", help="benchmark the render presets of this run folder")
    add_demo_arg(p, "the flags 'with --run' apply to it")
    p.add_argument("--plot", default=None, metavar="PNG", help="with --run: speed/accuracy plot")
    p.add_argument("--overwrite", action="store_true", help="replace --json / --plot if they exist")
    p.add_argument("--presets", default=None, help="with --run: comma-separated presets (default: all)")
    p.add_argument("--frames", type=int, default=2, help="with --run: body frames measured")
    p.add_argument("--views", type=int, default=2, help="with --run: cameras measured per frame")
    p.add_argument("--repeats", type=int, default=2, help="with --run: renders per view (fastest counts)")
    p.add_argument("--sequence", default=None, help="with --run: scene sequence (default: the first training one)")
    p.add_argument("--playback-frames", type=int, default=24, metavar="N",
                   help="with --run: frames played per preset for the playback figures: precomputed playback, and the "
                        "previewer's render-ahead of the clip's first N frames, 1..240 (default: 24)")
    p.add_argument("--training", action="store_true",
                   help="with --run: time NeRF training steps of the run's recipe per MLP precision, side by side, "
                        "instead of the render presets")
    p.add_argument("--precisions", default="float32,bfloat16",
                   help="with --training: comma-separated precisions (default: float32,bfloat16)")
    p.add_argument("--steps", type=int, default=8, help="with --training: steps per round and precision (default: 8)")
    p.add_argument("--rounds", type=int, default=3, help="with --training: rounds, the precisions taking turns "
                                                         "(default: 3)")
    p.add_argument("--cold", action="store_true",
                   help="with --training: time each step with its frame's inputs, body geometry and frozen encoders "
                        "made in it (a run's first visit to each frame) instead of from the trainer's caches (a long "
                        "run's steady state)")
    p.add_argument("--bake", default=None, metavar="PRESET", nargs="?", const="balanced",
                   help="with --run/--demo: bake the held-out frames (--bake-frames) at this bake preset (default: "
                        "balanced) and score the bake's views beside the full render's, against ground truth")
    p.add_argument("--bake-frames", default="20:50", metavar="A:B", help="with --bake: frames scored (default: 20:50)")
    p.add_argument("--against", action="append", default=[], metavar="RUN",
                   help="with --run: also measure this run folder's model (repeatable), taking turns with --run's, and "
                        "print --run's speed-up over it: each render preset (its PSNR beside), or with --training each "
                        "one's step over --run's")
    p.set_defaults(func=run_bench)


def _print_presets(results: dict) -> None:
    # lazy: 'garmentnerf --help' and flag errors answer without torch and the model stack (0.4 s against 6 s)
    from garmentnerf.perf.preset_bench import PAPER_STAGES

    print(f"{'preset':12s} {'ms/frame':>9s} {'speed-up':>8s} {'points':>10s} {'PSNR':>6s} {'SSIM':>6s}  "
          + " ".join(f"{k[:9]:>9s}" for k in PAPER_STAGES))
    for r in results["presets"]:
        psnr = f"{r['psnr']:6.2f}" if r["psnr"] is not None else "   n/a"
        ssim = f"{r['ssim']:6.3f}" if r["ssim"] is not None else "   n/a"
        print(f"{r['preset']:12s} {r['ms_per_frame']:9.1f} {r['speedup_vs_reference']:7.2f}x "
              f"{r['points_per_frame']:10,.0f} {psnr} {ssim}  "
              + " ".join(f"{r['stages_ms'][k]:9.1f}" for k in PAPER_STAGES))


def _run_training_bench(args: argparse.Namespace) -> dict:
    # lazy: 'garmentnerf --help' and flag errors answer without torch and the model stack (0.4 s against 6 s)
    from garmentnerf.perf.train_bench import training_benchmark
    from garmentnerf.train.settings import TRAINING_PRECISIONS

    precisions = args.precisions  # a list: run_bench parsed it
    unknown = [p for p in precisions if p not in TRAINING_PRECISIONS]
    if unknown:
        raise ValueError(f"--precisions {','.join(precisions)}: each must be one of {', '.join(TRAINING_PRECISIONS)}")
    if args.steps < 3 or args.rounds < 1:
        raise ValueError(f"--steps must be >= 3 and --rounds >= 1, got {args.steps} and {args.rounds}")
    results = training_benchmark(args.run, precisions, steps=args.steps, rounds=args.rounds,
                                 against=args.against, cold=args.cold, log=print)
    machine = results["machine"]
    print(f"machine: {machine['processor']}, torch threads {machine['torch_threads']}, AMX-BF16 {machine['amx_bf16']}; "
          f"{results['steps_timed']} steps timed per precision, frames "
          f"{'cached' if results['frames_cached'] else 'prepared in the step (--cold)'}")
    columns = [(row["precision"], row) for row in results["precisions"]]
    columns += [(f"{Path(a['run']).name} {row['precision']}", row) for a in results.get("against", [])
                for row in a["precisions"]]
    print(f"{'s/step by stage (median)':24s}" + "".join(f" {label:>16s}" for label, _ in columns))
    for stage in results["stages"]:
        print(f"  {stage:22s}" + "".join(f" {row['stages_s'][stage]:16.3f}" for _, row in columns))
    print(f"  {'step':22s}" + "".join(f" {row['s_per_step']:16.3f}" for _, row in columns))
    for row in results["precisions"]:
        print(f"  {row['precision']:10s} {row['s_per_step']:7.3f} s/step   "
              f"{results['speedup_vs_first'][row['precision']]:5.2f}x")
    for a in results.get("against", []):
        for row in a["precisions"]:
            print(f"  {row['precision']:10s} {results['speedup_vs_against'][a['run']][row['precision']]:5.2f}x faster "
                  f"than {a['run']}'s recipe ({row['s_per_step']:.3f} s/step)")
    return results


# ---------------------------------------------------------------------------------------------
def run_bench(args: argparse.Namespace) -> int:
    run_dir = run_folder_arg(args)  # --demo NAME stands for --run of that demo's folder
    args.run, args.demo = (str(run_dir) if run_dir is not None else None), None
    if args.runs < 1:
        raise ValueError(f"--runs must be at least 1, got {args.runs}")
    if getattr(args, "playback_frames", None) is not None:
        PLAYBACK.check(args.playback_frames, "--playback-frames")  # the benchmark's time grows with it
    # the lists as lists from here on (an empty list or item is refused before any work)
    args.presets = parse_list(getattr(args, "presets", None), "--presets", kind="preset")
    args.precisions = parse_list(getattr(args, "precisions", None), "--precisions", kind="precision")
    if getattr(args, "plot", None) and not getattr(args, "run", None):
        raise ValueError("--plot needs --run")
    if getattr(args, "training", False) and (not getattr(args, "run", None) or getattr(args, "plot", None)):
        raise ValueError("--training needs --run (and draws no --plot)")
    if getattr(args, "against", None) and not getattr(args, "run", None):
        raise ValueError("--against needs --run")
    for run in getattr(args, "against", None) or []:
        if not (Path(run) / "run.json").is_file():
            raise ValueError(f"--against {run}: not a run folder (no run.json)")
    for flag, path in (("--json", args.json), ("--plot", getattr(args, "plot", None))):
        if path:
            check_output_file(path, flag, args.overwrite)
    if getattr(args, "bake", None) is not None:
        from garmentnerf.bake.settings import bake_settings

        if not getattr(args, "run", None) or getattr(args, "training", False):
            raise ValueError("--bake needs --run or --demo (and not --training)")
        bake_settings(args.bake)
        mode = _run_bake_bench
    elif getattr(args, "training", False):
        mode = _run_training_bench
    elif getattr(args, "run", None):
        mode = _run_presets
    else:
        mode = _run_foundation
    with OtherProcessesLoad() as load:
        results = mode(args)
    results.setdefault("machine", {})["other_processes_cores"] = load.cores
    print(load_report(load.cores))
    if args.json:
        with atomic_write_path(Path(args.json), overwrite=args.overwrite) as tmp:
            tmp.write_text(json.dumps(results, indent=1))
        print(f"wrote {args.json}")
    if getattr(args, "plot", None):
        from garmentnerf.perf.plot import write_plot

        write_plot(results, args.plot, overwrite=args.overwrite)
        print(f"wrote {args.plot}")
    return 0


def _run_bake_bench(args: argparse.Namespace) -> dict:
    # lazy: 'garmentnerf --help' and flag errors answer without torch and the model stack
    from garmentnerf.perf.bake_bench import bake_benchmark

    return bake_benchmark(args.run, args.bake, frames=args.bake_frames)


def _run_presets(args: argparse.Namespace) -> dict:
    # lazy: 'garmentnerf --help' and flag errors answer without torch and the model stack (0.4 s against 6 s)
    from garmentnerf.perf.preset_bench import preset_benchmark
    from garmentnerf.viewer.playback_bench import render_ahead_benchmark

    results = preset_benchmark(args.run, args.presets, frames=args.frames, views=args.views, repeats=args.repeats,
                               sequence=args.sequence, playback_frames=args.playback_frames,
                               render_ahead=render_ahead_benchmark, against=args.against)
    _print_presets(results)
    for other in results.get("against", []):
        for row in other["presets"]:
            name = row["preset"]
            delta = results["psnr_vs_against_db"][other["run"]][name]
            print(f"  {name:12s} {results['speedup_vs_against'][other['run']][name]:5.2f}x the speed of "
                  f"{other['run']}'s ({row['ms_per_frame']:.1f} ms/frame)"
                  + (f", PSNR {delta:+.2f} dB" if delta is not None else ""))
    ahead, share = results["playback"]["render_ahead"], results["playback"]["completed_share"]
    print(f"render-ahead of {ahead['frames']} frames at {ahead['fps']:g} fps, still {ahead['camera'][0]}x"
          f"{ahead['camera'][1]} camera; completed share of started renders "
          + (f"{share:.2f}" if share is not None else "n/a"))
    for name, row in ahead["presets"].items():
        clip = f"{row['seconds_for_clip']:7.1f} s" if row["seconds_for_clip"] is not None else "timeout"
        fps = f"{row['fps_after']:5.1f}" if row["fps_after"] is not None else "  n/a"
        print(f"  {name:12s} clip rendered ahead in {clip}, then {fps} fps; max lag {row['max_lag_frames']} "
              f"frames (one render: {row['lag_budget_frames']} frames; {1e3 * row['render_s']:.0f} ms with the "
              f"frame's features cached, {1e3 * row['render_s_cold']:.0f} ms without; the longest "
              f"{row['longest_render_frames']} frames)")
    return results


def _run_foundation(args: argparse.Namespace) -> dict:
    # lazy: 'garmentnerf --help' and flag errors answer without torch and the model stack
    from garmentnerf.perf.foundation_bench import foundation_benchmark

    results = foundation_benchmark(runs=args.runs)
    machine = results["machine"]
    print(f"machine: {machine.get('cpus')} CPUs, torch threads {machine.get('torch_threads')}, "
          f"GL: {machine.get('GL_RENDERER', '?')}")
    for key, label, unit in ROWS:
        value = results[key]
        text = f"{value:,.0f}" if unit == "points/s" else f"{value:8.2f}"
        print(f"  {label:48s} {text:>12s} {unit}")
    return results
