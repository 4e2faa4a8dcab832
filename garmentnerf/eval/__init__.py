"""Evaluation: the paper's metrics (PSNR, SSIM, LPIPS, tOF) and the shift-tolerant LPIPS.

- :mod:`~garmentnerf.eval.metrics`: PSNR, SSIM, tOF, :class:`MetricSummary`,
  :func:`evaluate_sequence`; the conventions (background, data range, caps) are stated there.
- :mod:`~garmentnerf.eval.perceptual`: :class:`LPIPS` (needs user-supplied AlexNet weights) and
  :class:`STLPIPS` (weights from ``stlpips-pytorch``; also the perceptual training loss).
"""

from garmentnerf.eval.metrics import (FARNEBACK_PARAMS, PSNR_CAP_DB, TOF_SKIP_ENDS, MetricSummary, TOFResult,
                                      composite_premultiplied, evaluate_sequence, farneback_flow, mean_psnr, psnr,
                                      ssim, temporal_flow_error, to_grey_uint8, tof_crop)
from garmentnerf.eval.perceptual import (LPIPS, LPIPS_BACKBONE_ENV, STLPIPS, image_batch, lpips_available,
                                         lpips_lin_path, stlpips_available, stlpips_weights_path)

__all__ = [
    "FARNEBACK_PARAMS", "PSNR_CAP_DB", "TOF_SKIP_ENDS", "MetricSummary", "TOFResult", "composite_premultiplied",
    "evaluate_sequence", "farneback_flow", "mean_psnr", "psnr", "ssim", "temporal_flow_error", "to_grey_uint8",
    "tof_crop", "LPIPS", "LPIPS_BACKBONE_ENV", "STLPIPS", "image_batch", "lpips_available", "lpips_lin_path",
    "stlpips_available", "stlpips_weights_path",
]
