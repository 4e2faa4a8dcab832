"""Evaluation: the paper's metrics (PSNR, SSIM, LPIPS, tOF) and the shift-tolerant LPIPS.

- :mod:`~garmentnerf.eval.metrics`: PSNR, SSIM, tOF, :class:`MetricSummary`,
  :func:`evaluate_sequence`; the conventions (background, data range, caps) are stated there.
- The learned perceptual distances, :class:`~garmentnerf.model.perceptual.LPIPS` (needs
  user-supplied AlexNet weights) and :class:`~garmentnerf.model.perceptual.STLPIPS` (weights from
  ``stlpips-pytorch``; also the perceptual training loss), are networks of
  :mod:`garmentnerf.model.perceptual`.
"""

from garmentnerf.eval.metrics import (
                                      FARNEBACK_PARAMS,
                                      PSNR_CAP_DB,
                                      TOF_SKIP_ENDS,
                                      MetricSummary,
                                      TOFResult,
                                      composite_premultiplied,
                                      evaluate_sequence,
                                      farneback_flow,
                                      mean_psnr,
                                      psnr,
                                      ssim,
                                      temporal_flow_error,
                                      to_grey_uint8,
                                      tof_crop,
)

__all__ = [
    "FARNEBACK_PARAMS", "PSNR_CAP_DB", "TOF_SKIP_ENDS", "MetricSummary", "TOFResult", "composite_premultiplied",
    "evaluate_sequence", "farneback_flow", "mean_psnr", "psnr", "ssim", "temporal_flow_error", "to_grey_uint8",
    "tof_crop",
]
