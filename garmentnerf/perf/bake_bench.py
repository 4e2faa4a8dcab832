"""``garmentnerf bench --bake``: what a bake costs and loses against the network's ``full`` render.

One evaluation (:func:`~garmentnerf.eval.evaluate.evaluate_run` with ``bake``) renders the run's held-out
cameras (split ``unseen_view``) with the ``full`` preset and draws the same views from the frames' bakes
(the previewer's GL draw), both scored against the same ground truth over the character, beside the
nearest-view baseline. The figures under ``bake`` in the JSON, named to be compared from run to run:

``seconds_per_frame``  wall seconds to bake a frame in one process (the frame's features, the captures)
``mb_per_frame``       megabytes of a frame's bake file
``psnr_fg``, ``iou``   the bake's PSNR over the character and silhouette IoU
``full_psnr_fg``, ``full_iou``  the ``full`` render's, from the same run
``garment_psnr``, ``full_garment_psnr``, ``outline_share``, ``full_outline_share``  the garment's figures
``margin_db``          the bake's fg PSNR over the nearest training view's
"""

from __future__ import annotations

from garmentnerf.bake.settings import bake_settings
from garmentnerf.eval.evaluate import evaluate_run, format_result_table

#: The demo's held-out frames the figures are measured on.
DEFAULT_BAKE_FRAMES = "20:50"


def bake_benchmark(run, preset: str, frames: str = DEFAULT_BAKE_FRAMES, cameras=None, log=print) -> dict:
    """The figures of the module docstring for bake preset ``preset`` of ``run`` (a run folder or a loaded run),
    and the evaluation they come from under ``evaluation``."""
    settings = bake_settings(preset)
    result = evaluate_run(run, "unseen_view", frames=frames, cameras=cameras, progress=True, baseline=True,
                          preset="full", bake=settings, tof=False)
    log(format_result_table(result))
    bake, full, base = result["bake"], result["means"], result["baseline"]["means"]
    figures = {
        "preset": settings.to_dict(), "frames": frames, "cameras": result["cameras"],
        "seconds_per_frame": bake["seconds_per_frame"], "mb_per_frame": bake["mb_per_frame"],
        "psnr_fg": bake["means"].get("fg_psnr"), "iou": bake["means"].get("silhouette_iou"),
        "full_psnr_fg": full.get("fg_psnr"), "full_iou": full.get("silhouette_iou"),
        "garment_psnr": bake["means"].get("garment_psnr"), "full_garment_psnr": full.get("garment_psnr"),
        "outline_share": bake["means"].get("garment_outline_share"),
        "full_outline_share": full.get("garment_outline_share"),
        "margin_db": (bake["means"]["fg_psnr"] - base["fg_psnr"]) if "fg_psnr" in base else None,
    }
    log(f"bake {settings.name}: {figures['seconds_per_frame']:.2f} s a frame, {figures['mb_per_frame']:.2f} MB a "
        f"frame; fg PSNR {figures['psnr_fg']:.2f} dB (full {figures['full_psnr_fg']:.2f}, "
        f"{figures['psnr_fg'] - figures['full_psnr_fg']:+.2f}), IoU {figures['iou']:.4f} (full {figures['full_iou']:.4f}, "
        f"{figures['iou'] - figures['full_iou']:+.4f})")
    return {"bake": figures, "evaluation": result}


__all__ = ["bake_benchmark", "DEFAULT_BAKE_FRAMES"]
