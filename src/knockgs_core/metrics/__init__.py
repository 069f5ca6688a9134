"""Metrics of SPEC section 7: parameter error, trajectory error, response curves, and
rendered-frame agreement (foreground PSNR, object-crop SSIM).

Each metric scores one target; aggregating over targets (mean +- sample std) is the
caller's job -- frames and particles are never replicates.
"""

from ._image import crop_boxes, crop_ssim, foreground_psnr
from ._trajectory import curve_differences, curve_metrics, joint_error_pct, rms_displacement_curve, trajectory_rmse

__all__ = [
    "joint_error_pct",
    "trajectory_rmse",
    "rms_displacement_curve",
    "curve_metrics",
    "curve_differences",
    "foreground_psnr",
    "crop_ssim",
    "crop_boxes",
]
