"""The render presets measured on a trained run: speed, points evaluated and accuracy per preset,
and playback figures (what ``garmentnerf bench --run`` prints and saves).

:func:`preset_benchmark` renders every preset (:data:`garmentnerf.render.presets.RENDER_PRESETS`,
the table ``render --preset``, ``eval --preset`` and the previewer's quality levels use) on the
run's model through :class:`~garmentnerf.render.session.RenderSession` like every other command,
in one process so the ratios to ``reference`` compare like with like: ms per frame (one view of
one body frame: the frame stages plus the view's render) with a stage breakdown like the paper's
(:data:`PAPER_STAGES`, plus the ``raster_body`` composition's body layer where the run draws
one), points evaluated by the MLP per frame, and PSNR/SSIM against the ground
truth of the run's scene (images composited on the model's background over the full frame, data
range 1). Times are the fastest of ``repeats`` renders of each view (the development machine's 2
cores are shared, so the minimum is the least noisy), then the median over the views and frames
measured. Each row also gives the share of rays that hit nothing (no sample placed). Then the
playback figures (:func:`playback_benchmark`): neural frames per second per preset over a
precomputed clip window, the precompute cost per frame, and the scrub latency to a ready and to a
cold frame; and the previewer's render-ahead per preset
(:func:`garmentnerf.viewer.playback_bench.render_ahead_benchmark`: ``playback.render_ahead`` and
``playback.completed_share``).
"""

from __future__ import annotations

import dataclasses
import os
import platform
import time

import numpy as np
import torch

from garmentnerf.data.cameras import default_rig
from garmentnerf.data.render_gt import GroundTruthRenderer
from garmentnerf.data.scene_images import SceneImages
from garmentnerf.eval.metrics import psnr, ssim
from garmentnerf.gl.context import context_info, create_context
from garmentnerf.model.pipeline import FRAME_STAGES, RENDER_STAGES
from garmentnerf.render.cameras import orbit_view
from garmentnerf.render.presets import RENDER_PRESET_NAMES, get_render_preset
from garmentnerf.render.session import RenderSession
from garmentnerf.runs import load_run

__all__ = ["PAPER_STAGES", "preset_benchmark", "playback_benchmark", "previewer_view_benchmark"]

#: Paper-like stages of one frame -> the pipeline's timing keys that make them up.
PAPER_STAGES = {
    "info_maps": ("info_maps",),
    "reference_images": ("reference_passes", "reference_images"),
    "encoders": ("encoders",),
    "projection": ("surface", "rays", "projection", "features"),
    "mlp": ("mlp",),
    "compositing": ("compositing",),
    "decoder": ("decoder",),
    "body_layer": ("body_layer",),
}
#: The view's stages after the model's render (:meth:`RenderSession.render`'s own timing keys).
SESSION_STAGES = ("body_layer",)


def _view_ms(frame) -> float:
    """The per-view cost of a :class:`~garmentnerf.render.session.NeuralFrame`: the model's render
    plus the body layer (0 without one)."""
    return frame.timings["render_total"] + frame.timings.get("body_layer", 0.0)


def _median(values) -> float | None:
    """Median of the values that are not None (None when there are none)."""
    values = [v for v in values if v is not None]
    return float(np.median(values)) if values else None


def _pick(items, count):
    """``count`` items spread evenly over ``items`` (all of them when there are no more)."""
    if count >= len(items):
        return list(items)
    return [items[int(i)] for i in np.linspace(0, len(items) - 1, count).round().astype(int)]


def preset_benchmark(run_dir, presets=None, frames: int = 2, views: int = 2, repeats: int = 2,
                     sequence: str | None = None, gl_context=None, log=print, playback_frames: int = 24,
                     render_ahead=None, against=()) -> dict:
    """Measure every preset on a run (see the module docstring) through
    :class:`~garmentnerf.render.session.RenderSession`, the path every command renders with.

    Args:
        run_dir: the run folder.
        presets: preset names (default: all); ``reference`` is always measured (first) since the
            ratios are to it.
        frames, views, repeats: body frames measured, cameras per frame, renders per view (the
            fastest counts).
        sequence: the scene sequence (default: the session's, the first training one).
        gl_context: a moderngl context (None: a headless one is made and released).
        log: where progress lines go.
        playback_frames: precomputed frames played per preset (:func:`playback_benchmark`).
        render_ahead: the previewer's render-ahead measurement,
            ``render_ahead(run, sequence, presets, frames, gl_context, log=log) -> dict`` with a
            ``completed_share`` (the CLI passes
            :func:`garmentnerf.viewer.playback_bench.render_ahead_benchmark`; it lives with the
            viewer it drives, above this layer); None: not measured.
        against: other run folders (e.g. the model a new one replaces) whose presets are measured
            the same way in the same process, taking turns with ``run_dir``'s preset by preset,
            so that their ratios compare like with like (a busy machine slows both alike); each
            on its own scene's views and frames, the same ones when the runs share a scene.
    Returns:
        A JSON-ready dict (``presets``: one row per preset; ``playback``; ``previewer_view``;
        with ``against``: ``against`` (``[{"run", "step", "presets": [row]}]``), and per other
        run and preset ``speedup_vs_against`` (its ms per frame over ``run_dir``'s) and
        ``psnr_vs_against_db`` (``run_dir``'s PSNR minus its)).
    """
    for name, value in (("frames", frames), ("views", views), ("repeats", repeats),
                        ("playback-frames", playback_frames)):
        if value < 1:
            raise ValueError(f"--{name} must be at least 1, got {value}")
    chosen = _chosen_presets(presets)
    own_ctx = gl_context is None
    ctx = create_context(headless=True) if own_ctx else gl_context
    measured: list[_MeasuredRun] = []
    try:
        for path in (run_dir, *against):
            measured.append(_MeasuredRun.open(path, ctx, sequence, frames, views, log))
        main = measured[0]
        for preset in chosen:
            for m in measured:  # taking turns, preset by preset
                row = _preset_row(preset, m.run.config, _measure_views(m.session, preset, m.frame_ids, m.cams, repeats,
                                                                       m.frame_timings, m.gts))
                m.rows.append(row)
                log(f"  {preset.name:12s} {row['ms_per_frame']:9.1f} ms/frame (render {row['render_ms']:8.1f} ms)  "
                    f"{row['points_per_frame']:>10,.0f} points" + (f"  PSNR {row['psnr']:.2f} SSIM {row['ssim']:.4f}"
                                                                  if row["psnr"] is not None else "")
                    + (f"  [{m.path}]" if against else ""))
        for m in measured:
            _add_reference_ratios(m.rows)
        session, cfg = main.session, main.run.config
        playback = playback_benchmark(session, main.cams[0].camera, chosen, playback_frames, log=log)
        if render_ahead is not None:
            ahead = render_ahead(main.run, sequence, chosen, playback_frames, ctx, log=log)
            playback["completed_share"] = ahead.pop("completed_share")
            playback["render_ahead"] = ahead
        previewer = previewer_view_benchmark(session, main.frame_ids[0], log=log)
        results = {"kind": "preset_benchmark", "run": str(run_dir), "step": main.run.step,
                   "created": time.strftime("%Y-%m-%d %H:%M:%S"),
                   "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), **context_info(ctx)},
                   "torch_threads": torch.get_num_threads(),
                   "model": {"image_resolution": cfg.decoder.image_resolution,
                             "feature_image_resolution": cfg.decoder.feature_image_resolution,
                             "samples_per_ray": cfg.sampler.samples_per_ray, "mlp_depth": cfg.nerf.mlp_depth,
                             "mlp_width": cfg.nerf.mlp_width, "appearance_dim": cfg.nerf.appearance_dim},
                   "motion": session.motion.name, "sequence": session.sequence, "frames": main.frame_ids,
                   "cameras": [c.name for c in main.cams], "camera_split": main.split,
                   "ground_truth": main.images is not None, "height_range": session.height_range.to_dict(),
                   "presets": main.rows, "playback": playback, "previewer_view": previewer}
        if against:
            results["against"] = [{"run": str(m.path), "step": m.run.step, "presets": m.rows} for m in measured[1:]]
            results["speedup_vs_against"] = {str(m.path): {o["preset"]: o["ms_per_frame"] / r["ms_per_frame"]
                                                           for o, r in zip(m.rows, main.rows)} for m in measured[1:]}
            results["psnr_vs_against_db"] = {
                str(m.path): {o["preset"]: (r["psnr"] - o["psnr"]) if r["psnr"] is not None and o["psnr"] is not None
                              else None for o, r in zip(m.rows, main.rows)} for m in measured[1:]}
        return results
    finally:
        for m in measured:
            m.close()
        if own_ctx:
            ctx.release()


@dataclasses.dataclass
class _MeasuredRun:
    """A run's render session and what :func:`preset_benchmark` measures it on."""

    path: object
    run: object
    session: RenderSession
    images: SceneImages | None
    frame_ids: list[int]
    split: str
    cams: list
    gts: dict
    frame_timings: dict
    rows: list = dataclasses.field(default_factory=list)

    @classmethod
    def open(cls, path, ctx, sequence, frames: int, views: int, log) -> "_MeasuredRun":
        run = load_run(path)
        session = RenderSession(run, ctx, sequence)
        images = None
        try:
            seq = session.sequence
            frame_ids = _pick(list(range(session.num_frames)), frames)
            split, cams = _measured_views(run, views)
            if run.scene is not None and seq is not None:
                images = SceneImages(run.scene, renderer=GroundTruthRenderer(ctx), body_model=session.body)
            cfg, band = run.config, session.height_range
            log(f"run {path}: step {run.step}, {cfg.decoder.feature_image_resolution}^2 rays x {cfg.sampler.samples_per_ray} samples, "
                f"MLP {cfg.nerf.mlp_depth}x{cfg.nerf.mlp_width}; motion {session.motion.name} frames {frame_ids}; "
                f"{len(cams)} '{split}' views; height band [{band.h_min:.3f}, {band.h_max:.3f}] m ({band.source})")
            frame_timings = _frame_stage_timings(session, frame_ids)
            gts = {} if images is None else {(f, c.name): images.image(seq, c.name, f)[0]
                                             for f in frame_ids for c in cams}
        except BaseException:
            if images is not None:
                images.close()
            session.close()
            raise
        return cls(path, run, session, images, frame_ids, split, cams, gts, frame_timings)

    def close(self) -> None:
        if self.images is not None:
            self.images.close()
        self.session.close()


def _chosen_presets(names) -> list:
    """The :class:`~garmentnerf.render.presets.RenderPreset` of ``names`` (default: all), with
    ``reference`` first when it is not among them (ratios are to a reference measured in the same run)."""
    chosen = [get_render_preset(n) for n in (list(names) if names else list(RENDER_PRESET_NAMES))]
    if "reference" not in [p.name for p in chosen]:
        chosen.insert(0, get_render_preset("reference"))
    return chosen


def _measured_views(run, views: int) -> tuple[str, list]:
    """(split, ``views`` named cameras): the scene's held-out views (else its training ones), or an
    orbit rig at the model's image size for a run without a scene."""
    if run.scene is not None:
        split = "unseen_view" if run.scene.camera_names("unseen_view") else "train"
        return split, _pick(run.scene.cameras(split), views)

    size = run.config.decoder.image_resolution
    return "orbit", _pick(default_rig(width=size, height_px=size, references=False), views)


def _frame_stage_timings(session, frame_ids: list[int]) -> dict[int, dict[str, float]]:
    """ms of each frame stage per frame. They do not depend on the preset: measured once per frame
    (after a warm-up), then every render finds the frame in the session's cache."""
    session.frame_features(frame_ids[0])
    session.clear_cache()
    return {f: {k: session.frame_features(f)[0].timings.get(k, 0.0) for k in FRAME_STAGES} for f in frame_ids}


def _measure_views(session, preset, frame_ids: list[int], cams: list, repeats: int,
                   frame_timings: dict[int, dict[str, float]], gts: dict) -> list[dict]:
    """One entry per (frame, camera): the fastest of ``repeats`` renders with ``preset``, its
    timings and counts, and PSNR/SSIM where ``gts`` has the ground truth."""
    session.render(frame_ids[0], cams[0].camera, preset=preset)  # warm-up (GL objects, allocator)
    per_view = []
    for f in frame_ids:
        for c in cams:
            best = None
            for _ in range(repeats):
                nf = session.render(f, c.camera, preset=preset)
                if best is None or _view_ms(nf) < _view_ms(best):
                    best = nf
            timings = dict(frame_timings[f])
            timings.update({k: best.timings.get(k, 0.0) for k in (*RENDER_STAGES, *SESSION_STAGES)})
            frame_ms = sum(frame_timings[f].values())
            counts = best.counts
            entry = {"frame": f, "camera": c.name, "render_ms": _view_ms(best),
                     "frame_ms": frame_ms, "ms_per_frame": frame_ms + _view_ms(best),
                     "points": counts["points_evaluated"], "rays": counts["rays_evaluated"],
                     "rays_total": counts["rays_total"], "timings": timings,
                     "samples_candidate": counts["samples_placed"],
                     "points_projected": counts["points_projected"]}
            gt = gts.get((f, c.name))
            if gt is not None:
                img = best.composite()
                entry["psnr"], entry["ssim"] = psnr(img, gt), ssim(img, gt)
            per_view.append(entry)
    return per_view


def _preset_row(preset, cfg, per_view: list[dict]) -> dict:
    """A preset's row: the medians over its views of :func:`_measure_views`' entries."""
    return {"preset": preset.name, "settings": preset.to_dict(), "samples_per_ray": preset.samples_per_ray(cfg),
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
                              for k in (*FRAME_STAGES, *RENDER_STAGES, *SESSION_STAGES)},
            "views": per_view}


def _add_reference_ratios(results: list[dict]) -> None:
    """Each row's speed-ups, points ratio and PSNR difference to the ``reference`` row, and the
    share of its rays that hit nothing."""
    ref = next(r for r in results if r["preset"] == "reference")
    for r in results:
        r["speedup_vs_reference"] = ref["ms_per_frame"] / r["ms_per_frame"]
        r["render_speedup_vs_reference"] = ref["render_ms"] / r["render_ms"]
        r["points_ratio_vs_reference"] = (r["points_per_frame"] / ref["points_per_frame"]
                                          if ref["points_per_frame"] else None)
        r["psnr_vs_reference_db"] = (r["psnr"] - ref["psnr"]) if r["psnr"] is not None and ref["psnr"] is not None else None
        r["rays_missing_share"] = (1.0 - r["rays_per_frame"] / r["feature_rays_total"]
                                   if r["feature_rays_total"] else None)


def playback_benchmark(session, camera, presets, frames: int = 24, log=print) -> dict:
    """Neural frames per second while a precomputed clip plays, per preset, and scrub latency.

    ``frames`` consecutive body frames from the session's playhead window are precomputed first
    (:meth:`RenderSession.precompute_next`, timed as ``precompute_ms_per_frame``); then each preset
    renders them in order with one camera (``fps``: frames over the wall time, everything a
    playing previewer's worker does per neural frame). Scrub latency (``full`` preset): the
    time from a jump to the image, to a ready frame whose closest-point search is not bound
    (``scrub_ready_ms``) and to a frame not precomputed (``scrub_cold_ms``).
    """
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


def previewer_view_benchmark(session, frame: int, size: tuple[int, int] = (1280, 800),
                             distances: tuple[float, ...] = (3.6, 2.2), repeats: int = 3, log=print) -> dict:
    """The ``full`` preset in a previewer-sized orbit view (the default distance and a closer one),
    three ways, measured side by side on one cached frame: the whole frame at the window's density
    (what the previewer did before the character's rectangle), the character's rectangle at that
    density, and the rectangle at the character's training density (what it does now).

    Returns:
        ``{"size": [W, H], "frame": f, "views": [{"distance", "rows": {way: {"ms", "rendered",
        "rays", "rays_frame", "points", "scale"}}}]}`` (``ms``: median of ``repeats`` after one warm-up).
    """
    full = get_render_preset("full")
    whole_frame = dataclasses.replace(full, name="full_whole_frame", character_rect=False)
    views = []
    for distance in distances:
        camera = orbit_view(25.0, width=size[0], height=size[1], radius=distance)
        window_scale = session.render_scale(camera, full.resolution_scale)
        rows = {}
        for way, preset, scale in (("whole frame, window density", whole_frame, window_scale),
                                   ("character rectangle, window density", full, window_scale),
                                   ("character rectangle, character density", full, None)):
            session.render(frame, camera, preset=preset, scale=scale)
            times = []
            for _ in range(repeats):
                t0 = time.perf_counter()
                nf = session.render(frame, camera, preset=preset, scale=scale)
                times.append((time.perf_counter() - t0) * 1e3)
            rows[way] = {"ms": _median(times), "rendered": list(nf.render_size), "rays": nf.counts["rays_total"],
                         "rays_frame": nf.counts["rays_frame"], "points": nf.counts["points_evaluated"],
                         "scale": nf.scale}
            log(f"  view {size[0]}x{size[1]} at {distance:.1f} m, {way:38s} {rows[way]['ms']:7.1f} ms  rendered "
                f"{nf.render_size[0]}x{nf.render_size[1]}  rays {nf.counts['rays_total']:,} of "
                f"{nf.counts['rays_frame']:,}")
        views.append({"distance": distance, "rows": rows})
    return {"size": list(size), "frame": int(frame), "views": views}
