"""``garmentnerf bench``: time the per-frame stages and print (and optionally save) the figures.

Without ``--run``: the foundation GL/geometry passes (:func:`garmentnerf.benchmarks.foundation_benchmark`).

With ``--run DIR``: every render preset (:data:`garmentnerf.perf.presets.RENDER_PRESETS`, the table
``render --preset``, ``eval --preset`` and the previewer's quality levels use) on the run's model,
rendered through :class:`~garmentnerf.render.session.RenderSession` like every other command, in
one process so the ratios to ``reference`` compare like with like: ms per frame (one view of one
body frame: the frame stages plus the view's render) with a stage breakdown like the paper's,
points evaluated by the MLP per frame, and PSNR/SSIM against the ground truth of the run's
scene (images composited on the model's background over the full frame, data range 1). Times are
the fastest of ``--repeats`` renders of each view (the development machine's 2 cores are shared,
so the minimum is the least noisy), then the median over the views and frames measured.
Each row also gives the share of rays that hit nothing (no sample placed). Then the playback
figures (:func:`playback_benchmark`): neural frames per second per preset over a precomputed clip
window, the precompute cost per frame, and the scrub latency to a ready and to a cold frame.
``--plot`` draws ms/frame (log) against PSNR per preset (PIL; matplotlib is not needed).
"""

from __future__ import annotations

import argparse
import json
import time
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

#: Paper-like stages of one frame -> the pipeline's timing keys that make them up.
PAPER_STAGES = {
    "info_maps": ("info_maps",),
    "reference_images": ("reference_passes", "reference_images"),
    "encoders": ("encoders",),
    "projection": ("surface", "rays", "projection", "features"),
    "mlp": ("mlp",),
    "compositing": ("compositing",),
    "decoder": ("decoder",),
}


def register(sub) -> None:
    p = sub.add_parser("bench", help="benchmark the per-frame stages (prints figures, writes JSON); "
                                     "with --run: the render presets of a trained run")
    p.add_argument("--json", default=None, metavar="PATH", help="also write the figures as JSON")
    p.add_argument("--runs", type=int, default=20, help="timed repetitions per stage (median is reported)")
    p.add_argument("--run", default=None, metavar="DIR", help="benchmark the render presets of this run folder")
    p.add_argument("--plot", default=None, metavar="PNG", help="with --run: speed/accuracy plot")
    p.add_argument("--overwrite", action="store_true", help="replace --json / --plot if they exist")
    p.add_argument("--presets", default=None, help="with --run: comma-separated presets (default: all)")
    p.add_argument("--frames", type=int, default=2, help="with --run: body frames measured")
    p.add_argument("--views", type=int, default=2, help="with --run: cameras measured per frame")
    p.add_argument("--repeats", type=int, default=2, help="with --run: renders per view (fastest counts)")
    p.add_argument("--sequence", default=None, help="with --run: scene sequence (default: the first training one)")
    p.add_argument("--playback-frames", type=int, default=24, metavar="N",
                   help="with --run: precomputed frames played per preset for the playback figure (default: 24)")
    p.set_defaults(func=run_bench)


# ---------------------------------------------------------------------------------------------
# the run benchmark
# ---------------------------------------------------------------------------------------------
def _median(values):
    import numpy as np

    values = [v for v in values if v is not None]
    return float(np.median(values)) if values else None


def _pick(items, count):
    import numpy as np

    if count >= len(items):
        return list(items)
    return [items[int(i)] for i in np.linspace(0, len(items) - 1, count).round().astype(int)]


def preset_benchmark(run_dir, presets=None, frames: int = 2, views: int = 2, repeats: int = 2,
                     sequence: str | None = None, gl_context=None, log=print, playback_frames: int = 24) -> dict:
    """Measure every preset on a run (see the module docstring) through
    :class:`~garmentnerf.render.session.RenderSession`, the path every command renders with.
    Returns a JSON-ready dict."""
    import os
    import platform

    import torch

    from garmentnerf.eval.metrics import psnr, ssim
    from garmentnerf.gl.context import context_info, create_context
    from garmentnerf.model.pipeline import FRAME_STAGES, RENDER_STAGES
    from garmentnerf.perf.presets import RENDER_PRESET_NAMES, get_render_preset
    from garmentnerf.render.session import RenderSession
    from garmentnerf.train.run import load_run

    for name, value in (("frames", frames), ("views", views), ("repeats", repeats),
                        ("playback-frames", playback_frames)):
        if value < 1:
            raise ValueError(f"--{name} must be at least 1, got {value}")
    names = list(presets) if presets else list(RENDER_PRESET_NAMES)
    chosen = [get_render_preset(n) for n in names]
    if "reference" not in [p.name for p in chosen]:
        chosen.insert(0, get_render_preset("reference"))  # ratios are to a reference measured in the same run
    own_ctx = gl_context is None
    ctx = create_context(headless=True) if own_ctx else gl_context
    run = load_run(run_dir)
    cfg, scene = run.config, run.scene
    images = session = None
    try:
        session = RenderSession(run, ctx, sequence)
        motion, seq = session.motion, session.sequence
        frame_ids = _pick(list(range(session.num_frames)), frames)
        if scene is not None:
            split = "unseen_view" if scene.camera_names("unseen_view") else "train"
            cams = _pick(scene.cameras(split), views)
            if seq is not None:
                from garmentnerf.data.render_gt import GroundTruthRenderer
                from garmentnerf.data.scene import SceneImages

                images = SceneImages(scene, renderer=GroundTruthRenderer(ctx), body_model=session.body)
        else:
            from garmentnerf.data.cameras import default_rig

            split = "orbit"
            rig = default_rig(width=cfg.image_resolution, height_px=cfg.image_resolution, references=False)
            cams = _pick(rig, views)
        band = session.height_range
        log(f"run {run_dir}: step {run.step}, {cfg.feature_image_resolution}^2 rays x {cfg.samples_per_ray} samples, "
            f"MLP {cfg.mlp_depth}x{cfg.mlp_width}; motion {motion.name} frames {frame_ids}; "
            f"{len(cams)} '{split}' views; height band [{band.h_min:.3f}, {band.h_max:.3f}] m ({band.source})")
        # Frame stages do not depend on the preset: measured once per frame (after a warm-up), then
        # every render finds the frame in the session's cache.
        session.frame_features(frame_ids[0])
        session.clear_cache()
        frame_timings = {f: {k: session.frame_features(f)[0].timings.get(k, 0.0) for k in FRAME_STAGES}
                         for f in frame_ids}
        gts = {}
        if images is not None:
            for f in frame_ids:
                for c in cams:
                    gts[(f, c.name)] = images.image(seq, c.name, f)[0]
        results = []
        for preset in chosen:
            session.render(frame_ids[0], cams[0].camera, preset=preset)  # warm-up (GL objects, allocator)
            per_view = []
            for f in frame_ids:
                for c in cams:
                    best = None
                    for _ in range(repeats):
                        nf = session.render(f, c.camera, preset=preset)
                        if best is None or nf.timings["render_total"] < best.timings["render_total"]:
                            best = nf
                    timings = dict(frame_timings[f])
                    timings.update({k: best.timings.get(k, 0.0) for k in RENDER_STAGES})
                    frame_ms = sum(frame_timings[f].values())
                    counts = best.counts
                    entry = {"frame": f, "camera": c.name, "render_ms": best.timings["render_total"],
                             "frame_ms": frame_ms, "ms_per_frame": frame_ms + best.timings["render_total"],
                             "points": counts["points_evaluated"], "rays": counts["rays_evaluated"],
                             "rays_total": counts["rays_total"], "timings": timings,
                             "samples_candidate": counts["samples_placed"],
                             "points_projected": counts["points_projected"]}
                    gt = gts.get((f, c.name))
                    if gt is not None:
                        img = best.composite()
                        entry["psnr"], entry["ssim"] = psnr(img, gt), ssim(img, gt)
                    per_view.append(entry)
            row = {"preset": preset.name, "settings": preset.to_dict(), "samples_per_ray": preset.samples_per_ray(cfg),
                   "ms_per_frame": _median([e["ms_per_frame"] for e in per_view]),
                   "render_ms": _median([e["render_ms"] for e in per_view]),
                   "frame_ms": _median([e["frame_ms"] for e in per_view]),
                   "points_per_frame": _median([e["points"] for e in per_view]),
                   "samples_candidate_per_frame": _median([e["samples_candidate"] for e in per_view]),
                   "points_projected_per_frame": _median([e["points_projected"] for e in per_view]),
                   "rays_per_frame": _median([e["rays"] for e in per_view]),
                   "feature_rays_total": _median([e["rays_total"] for e in per_view]),
                   "psnr": _median([e.get("psnr") for e in per_view]),
                   "ssim": _median([e.get("ssim") for e in per_view]),
                   "stages_ms": {k: _median([sum(e["timings"].get(s, 0.0) for s in keys) for e in per_view])
                                 for k, keys in PAPER_STAGES.items()},
                   "raw_stages_ms": {k: _median([e["timings"].get(k, 0.0) for e in per_view])
                                     for k in (*FRAME_STAGES, *RENDER_STAGES)},
                   "views": per_view}
            results.append(row)
            log(f"  {preset.name:12s} {row['ms_per_frame']:9.1f} ms/frame (render {row['render_ms']:8.1f} ms)  "
                f"{row['points_per_frame']:>10,.0f} points" + (f"  PSNR {row['psnr']:.2f} SSIM {row['ssim']:.4f}"
                                                              if row["psnr"] is not None else ""))
        ref = next(r for r in results if r["preset"] == "reference")
        for r in results:
            r["speedup_vs_reference"] = ref["ms_per_frame"] / r["ms_per_frame"]
            r["render_speedup_vs_reference"] = ref["render_ms"] / r["render_ms"]
            r["points_ratio_vs_reference"] = (r["points_per_frame"] / ref["points_per_frame"]
                                              if ref["points_per_frame"] else None)
            r["psnr_vs_reference_db"] = (r["psnr"] - ref["psnr"]) if r["psnr"] is not None and ref["psnr"] is not None else None
            r["rays_missing_share"] = (1.0 - r["rays_per_frame"] / r["feature_rays_total"]
                                       if r["feature_rays_total"] else None)
        playback = playback_benchmark(session, cams[0].camera, chosen, playback_frames, log=log)
        return {"kind": "preset_benchmark", "run": str(run_dir), "step": run.step, "created": time.strftime("%Y-%m-%d %H:%M:%S"),
                "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), **context_info(ctx)}, "torch_threads": torch.get_num_threads(),
                "model": {k: getattr(cfg, k) for k in ("image_resolution", "feature_image_resolution", "samples_per_ray",
                                                          "mlp_depth", "mlp_width", "appearance_dim")},
                "motion": motion.name, "sequence": seq, "frames": frame_ids, "cameras": [c.name for c in cams],
                "camera_split": split, "ground_truth": images is not None, "height_range": band.to_dict(),
                "presets": results, "playback": playback}
    finally:
        if images is not None:
            images.close()
        if session is not None:
            session.close()
        if own_ctx:
            ctx.release()


def playback_benchmark(session, camera, presets, frames: int = 24, log=print) -> dict:
    """Neural frames per second while a precomputed clip plays, per preset, and scrub latency.

    ``frames`` consecutive body frames from the session's playhead window are precomputed first
    (:meth:`RenderSession.precompute_next`, timed as ``precompute_ms_per_frame``); then each preset
    renders them in order with one camera (``fps``: frames over the wall time, everything a
    playing previewer's worker does per neural frame). Scrub latency (``full`` preset): the
    time from a jump to the image, to a ready frame whose closest-point search is not bound
    (``scrub_ready_ms``) and to a frame not precomputed (``scrub_cold_ms``).
    """
    from garmentnerf.perf.presets import get_render_preset

    n = min(max(1, int(frames)), session.num_frames)
    start = max(0, (session.num_frames - n) // 2)
    window = list(range(start, start + n))
    session.clear_cache()
    session.frames.set_playhead(start)
    t0 = time.perf_counter()
    done = 0
    while done < n and session.precompute_next() is not None:
        done += 1
    precompute_ms = (time.perf_counter() - t0) * 1e3 / max(done, 1)
    ready = set(session.frames.ready_frames())
    rows = {}
    for preset in presets:
        session.render(window[0], camera, preset=preset)  # warm-up (GL objects of the preset)
        t0 = time.perf_counter()
        for f in window:
            session.render(f, camera, preset=preset)
        seconds = time.perf_counter() - t0
        rows[preset.name] = {"fps": len(window) / seconds, "ms_per_frame": seconds * 1e3 / len(window)}
        log(f"  playback {preset.name:12s} {rows[preset.name]['fps']:6.2f} neural frames/s over {len(window)} "
            f"precomputed frames")
    full = get_render_preset("full")
    far_ready = window[len(window) // 2]  # not among the last frames used: its search is rebuilt
    t0 = time.perf_counter()
    session.render(far_ready, camera, preset=full)
    scrub_ready = (time.perf_counter() - t0) * 1e3
    cold = next((f for f in range(session.num_frames) if f not in ready), None)
    scrub_cold = None
    if cold is not None:
        t0 = time.perf_counter()
        session.render(cold, camera, preset=full)
        scrub_cold = (time.perf_counter() - t0) * 1e3
    log(f"  precompute {precompute_ms:.0f} ms/frame; scrub to a ready frame {scrub_ready:.0f} ms, to a cold one "
        + (f"{scrub_cold:.0f} ms" if scrub_cold is not None else "n/a") + " (full preset)")
    return {"frames": window, "precomputed": done, "precompute_ms_per_frame": precompute_ms, "presets": rows,
            "scrub_ready_ms": scrub_ready, "scrub_cold_ms": scrub_cold}


def write_plot(results: dict, path, overwrite: bool = True) -> Path:
    """ms/frame (log x) against PSNR (or points per frame without ground truth), one labelled
    point per preset, as a PNG drawn with PIL."""
    import math

    from PIL import Image, ImageDraw

    rows = [r for r in results["presets"] if r["ms_per_frame"]]
    use_psnr = all(r["psnr"] is not None for r in rows)
    ys = [r["psnr"] if use_psnr else math.log10(max(r["points_per_frame"], 1)) for r in rows]
    xs = [math.log10(r["ms_per_frame"]) for r in rows]
    W, H, ml, mr, mt, mb = 720, 480, 80, 30, 50, 60
    img = Image.new("RGB", (W, H), "white")
    d = ImageDraw.Draw(img)
    x0, x1 = math.floor(min(xs) * 10) / 10 - 0.1, math.ceil(max(xs) * 10) / 10 + 0.1
    y_pad = max(0.5, (max(ys) - min(ys)) * 0.15)
    y0, y1 = min(ys) - y_pad, max(ys) + y_pad

    def px(x, y):
        return ml + (x - x0) / (x1 - x0) * (W - ml - mr), H - mb - (y - y0) / (y1 - y0) * (H - mt - mb)

    d.rectangle([ml, mt, W - mr, H - mb], outline="black")
    for e in range(int(math.floor(x0)), int(math.ceil(x1)) + 1):
        for m in (1, 2, 5):
            lx = e + math.log10(m)
            if x0 <= lx <= x1:
                gx, _ = px(lx, y0)
                d.line([gx, mt, gx, H - mb], fill=(225, 225, 225))
                d.text((gx - 12, H - mb + 6), f"{m * 10 ** e:g}", fill="black")
    for i in range(6):
        y = y0 + (y1 - y0) * i / 5
        _, gy = px(x0, y)
        d.line([ml, gy, W - mr, gy], fill=(235, 235, 235))
        d.text((8, gy - 6), f"{y:.2f}" if use_psnr else f"1e{y:.1f}", fill="black")
    d.text((W // 2 - 60, H - 25), "ms per frame (log)", fill="black")
    d.text((8, 12), ("PSNR (dB) vs ground truth" if use_psnr else "log10 points per frame") +
           f"   {results['machine'].get('cpus', '?')} CPUs, {results.get('run', '')}", fill="black")
    pts = sorted(zip(xs, ys, rows), key=lambda t: t[0])
    d.line([px(x, y) for x, y, _ in pts], fill=(120, 160, 220), width=2)
    for i, (x, y, r) in enumerate(pts):
        cx, cy = px(x, y)
        d.ellipse([cx - 5, cy - 5, cx + 5, cy + 5], fill=(30, 80, 200))
        cy += 30 if i % 2 else -10  # alternate labels below/above: neighbours on a flat curve do not overlap
        d.text((cx + 8, cy - 16), f"{r['preset']} {r['ms_per_frame']:.0f} ms, x{r['speedup_vs_reference']:.1f}",
               fill="black")
        d.text((cx + 8, cy - 4), f"{r['points_per_frame']:,.0f} pts", fill=(90, 90, 90))
    from garmentnerf.io_utils import atomic_write_path

    path = Path(path)
    with atomic_write_path(path, overwrite=overwrite) as tmp:
        img.save(tmp, format="PNG")
    return path


def _print_presets(results: dict) -> None:
    print(f"{'preset':12s} {'ms/frame':>9s} {'speed-up':>8s} {'points':>10s} {'PSNR':>6s} {'SSIM':>6s}  "
          + " ".join(f"{k[:9]:>9s}" for k in PAPER_STAGES))
    for r in results["presets"]:
        psnr = f"{r['psnr']:6.2f}" if r["psnr"] is not None else "   n/a"
        ssim = f"{r['ssim']:6.3f}" if r["ssim"] is not None else "   n/a"
        print(f"{r['preset']:12s} {r['ms_per_frame']:9.1f} {r['speedup_vs_reference']:7.2f}x "
              f"{r['points_per_frame']:10,.0f} {psnr} {ssim}  "
              + " ".join(f"{r['stages_ms'][k]:9.1f}" for k in PAPER_STAGES))


# ---------------------------------------------------------------------------------------------
def run_bench(args: argparse.Namespace) -> int:
    from garmentnerf.cli.common import check_output_file
    from garmentnerf.io_utils import atomic_write_path

    if args.runs < 1:
        raise ValueError(f"--runs must be at least 1, got {args.runs}")
    if getattr(args, "plot", None) and not getattr(args, "run", None):
        raise ValueError("--plot needs --run")
    for flag, path in (("--json", args.json), ("--plot", getattr(args, "plot", None))):
        if path:
            check_output_file(path, flag, args.overwrite)
    if getattr(args, "run", None):
        presets = [p.strip() for p in args.presets.split(",") if p.strip()] if args.presets else None
        results = preset_benchmark(args.run, presets, frames=args.frames, views=args.views, repeats=args.repeats,
                                   sequence=args.sequence, playback_frames=args.playback_frames)
        _print_presets(results)
        if args.json:
            with atomic_write_path(Path(args.json), overwrite=args.overwrite) as tmp:
                tmp.write_text(json.dumps(results, indent=1))
            print(f"wrote {args.json}")
        if args.plot:
            write_plot(results, args.plot, overwrite=args.overwrite)
            print(f"wrote {args.plot}")
        return 0
    from garmentnerf.benchmarks import foundation_benchmark

    results = foundation_benchmark(runs=args.runs)
    machine = results["machine"]
    print(f"machine: {machine.get('cpus')} CPUs, torch threads {machine.get('torch_threads')}, "
          f"GL: {machine.get('GL_RENDERER', '?')}")
    for key, label, unit in ROWS:
        value = results[key]
        text = f"{value:,.0f}" if unit == "points/s" else f"{value:8.2f}"
        print(f"  {label:48s} {text:>12s} {unit}")
    if args.json:
        with atomic_write_path(Path(args.json), overwrite=args.overwrite) as tmp:
            tmp.write_text(json.dumps(results, indent=2))
        print(f"wrote {args.json}")
    return 0
