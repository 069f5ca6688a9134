"""Rendered-frame metrics: foreground PSNR and object-crop SSIM (SPEC section 7) (private)."""

from __future__ import annotations

import math

import numpy as np

from knockgs_core.errors import InputError

SSIM_WINDOW = 7
"""scikit-image's default SSIM window [px]; crops are at least this large."""


def _sequences(pred_rgb, target_rgb, pred_alpha, target_alpha, threshold, src):
    arrays = {}
    for name, value, nd in (("pred_rgb", pred_rgb, 4), ("target_rgb", target_rgb, 4),
                            ("pred_alpha", pred_alpha, 3), ("target_alpha", target_alpha, 3)):
        try:
            arr = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise InputError(src, name, f"not a numeric array ({exc})") from None
        want = "[T, H, W, 3]" if nd == 4 else "[T, H, W]"
        if arr.ndim != nd or (nd == 4 and arr.shape[-1] != 3):
            raise InputError(src, name, f"expected shape {want}, got {list(arr.shape)}")
        if not np.all(np.isfinite(arr)):
            raise InputError(src, name, "contains NaN or infinite values")
        arrays[name] = arr
    shape = arrays["target_rgb"].shape
    if arrays["pred_rgb"].shape != shape:
        raise InputError(src, "pred_rgb", f"shape {list(arrays['pred_rgb'].shape)} differs from "
                         f"target_rgb {list(shape)}")
    for name in ("pred_alpha", "target_alpha"):
        if arrays[name].shape != shape[:3]:
            raise InputError(src, name, f"shape {list(arrays[name].shape)} does not match the "
                             f"images' [T, H, W] = {list(shape[:3])}")
    if shape[0] == 0:
        raise InputError(src, "target_rgb", "holds no frames")
    if not math.isfinite(threshold):
        raise InputError(src, "threshold", f"must be finite, got {threshold!r}")
    union = (arrays["pred_alpha"] > threshold) | (arrays["target_alpha"] > threshold)
    return arrays["pred_rgb"], arrays["target_rgb"], union


def foreground_psnr(pred_rgb, target_rgb, pred_alpha, target_alpha, *,
                    threshold: float = 0.5, data_range: float = 1.0) -> float:
    """PSNR [dB] over the union of the predicted and target foreground masks.

    Parameters
    ----------
    pred_rgb, target_rgb: [T, H, W, 3]
        Rendered sequences (same renderer and camera).
    pred_alpha, target_alpha: [T, H, W]
        Their alpha images; a pixel is foreground where ``alpha > threshold``.
    data_range:
        Maximum possible value range of the images.

    The squared error (over the three channels) and the pixel count are pooled over
    all frames before one conversion to dB: ``MSE = sum (pred - target)^2 /
    (3 * pixels in the union)``, ``PSNR = 10 log10(data_range^2 / MSE)``. Returns
    ``float('inf')`` when the sequences agree exactly on the union (MSE = 0). Raises
    :class:`InputError` when the union is empty in every frame.
    """
    src = "metrics.foreground_psnr"
    if not (math.isfinite(data_range) and data_range > 0):
        raise InputError(src, "data_range", f"must be > 0, got {data_range!r}")
    pred, target, union = _sequences(pred_rgb, target_rgb, pred_alpha, target_alpha, threshold, src)
    count = int(union.sum())
    if count == 0:
        raise InputError(src, "target_alpha", f"no foreground pixel (alpha > {threshold}) in "
                         "either sequence; the foreground PSNR is undefined")
    sse = float(np.sum((pred[union] - target[union]) ** 2))
    if sse == 0.0:
        return float("inf")
    mse = sse / (3 * count)
    return float(10.0 * np.log10(data_range**2 / mse))


def _span(lo: int, hi: int, size: int, pad: int) -> tuple[int, int]:
    """Padded, clipped ``[start, stop)`` of index range ``[lo, hi]``, at least 7 long."""
    start, stop = max(lo - pad, 0), min(hi + pad + 1, size)
    short = SSIM_WINDOW - (stop - start)
    if short > 0:  # enlarge around the crop, kept inside the image
        start = max(0, min(start - short // 2, size - SSIM_WINDOW))
        stop = start + SSIM_WINDOW
    return start, stop


def crop_boxes(pred_alpha, target_alpha, *, pad: int = 5, threshold: float = 0.5) -> list[tuple[int, int, int, int]]:
    """Per-frame crop ``(row0, row1, col0, col1)`` (half-open) used by :func:`crop_ssim`.

    ``pred_alpha``, ``target_alpha``: ``[T, H, W]``. The bounding box of the mask union
    ``(alpha > threshold)`` padded by ``pad`` px, clipped to the image, and enlarged
    within the image to at least 7 x 7 px (the SSIM window).
    """
    src = "metrics.crop_boxes"
    pa = np.asarray(pred_alpha, dtype=np.float64)
    ta = np.asarray(target_alpha, dtype=np.float64)
    if pa.ndim != 3 or pa.shape != ta.shape:
        raise InputError(src, "pred_alpha", f"expected two [T, H, W] arrays of one shape, got "
                         f"{list(pa.shape)} and {list(ta.shape)}")
    if int(pad) != pad or pad < 0:
        raise InputError(src, "pad", f"must be a non-negative integer, got {pad!r}")
    _, h, w = pa.shape
    if h < SSIM_WINDOW or w < SSIM_WINDOW:
        raise InputError(src, "pred_alpha", f"images of {h} x {w} px are smaller than the "
                         f"{SSIM_WINDOW} x {SSIM_WINDOW} SSIM window")
    boxes = []
    for t, union in enumerate((pa > threshold) | (ta > threshold)):
        rows = np.flatnonzero(union.any(axis=1))
        cols = np.flatnonzero(union.any(axis=0))
        if rows.size == 0:
            raise InputError(src, "target_alpha", f"frame {t}: no foreground pixel (alpha > "
                             f"{threshold}) in either sequence; the object crop is undefined")
        r0, r1 = _span(rows[0], rows[-1], h, int(pad))
        c0, c1 = _span(cols[0], cols[-1], w, int(pad))
        boxes.append((r0, r1, c0, c1))
    return boxes


def crop_ssim(pred_rgb, target_rgb, pred_alpha, target_alpha, *,
              pad: int = 5, threshold: float = 0.5) -> float:
    """Object-crop SSIM, averaged over frames.

    Parameters
    ----------
    pred_rgb, target_rgb: [T, H, W, 3]
        Rendered sequences with values in [0, 1].
    pred_alpha, target_alpha: [T, H, W]
        Their alpha images; foreground is ``alpha > threshold``.
    pad:
        Padding [px] of the per-frame crop around the mask-union bounding box
        (see :func:`crop_boxes`).

    Per frame: ``skimage.metrics.structural_similarity(channel_axis=-1,
    data_range=1.0)`` (7 x 7 uniform window) on the crop; the mean over frames is
    returned. Raises :class:`InputError` if a frame has no foreground at all.
    """
    from skimage.metrics import structural_similarity  # scikit-image (and SciPy) only where used

    src = "metrics.crop_ssim"
    pred, target, _ = _sequences(pred_rgb, target_rgb, pred_alpha, target_alpha, threshold, src)
    boxes = crop_boxes(pred_alpha, target_alpha, pad=pad, threshold=threshold)
    scores = [
        structural_similarity(pred[t, r0:r1, c0:c1], target[t, r0:r1, c0:c1],
                              channel_axis=-1, data_range=1.0)
        for t, (r0, r1, c0, c1) in enumerate(boxes)
    ]
    return float(np.mean(scores))
