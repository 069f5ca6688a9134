"""Eager input checks shared by the render functions (private)."""

from __future__ import annotations

import numpy as np

from knockgs_core.errors import InputError


def as_float_array(value, source: str, field: str, shape: tuple) -> np.ndarray:
    """Return ``value`` as a finite float64 array of ``shape`` (``-1`` matches any size).

    Raises :class:`InputError` naming ``source`` and ``field`` on a wrong shape or
    non-finite entries.
    """
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(source, field, f"not a numeric array ({exc})") from None
    want = "[" + ", ".join("N" if s == -1 else str(s) for s in shape) + "]"
    if arr.ndim != len(shape) or any(s != -1 and a != s for a, s in zip(arr.shape, shape)):
        raise InputError(source, field, f"expected shape {want}, got {list(arr.shape)}")
    if not np.all(np.isfinite(arr)):
        raise InputError(source, field, "contains NaN or infinite values")
    return arr


def check_count(arr: np.ndarray, n: int, source: str, field: str, other: str) -> None:
    """Check that ``arr`` has ``n`` rows, the row count of ``other``."""
    if arr.shape[0] != n:
        raise InputError(
            source, field, f"has {arr.shape[0]} rows but {other} has {n}; they must match"
        )


def check_range(arr: np.ndarray, lo: float, hi: float, source: str, field: str) -> None:
    """Check ``lo <= arr <= hi`` element-wise."""
    if arr.size and (arr.min() < lo or arr.max() > hi):
        raise InputError(
            source,
            field,
            f"values must lie in [{lo}, {hi}], got min {arr.min():.6g}, max {arr.max():.6g}",
        )


def check_scene(means, covariances, colors, opacities, source: str):
    """Validate one Gaussian scene; return float64 ``(means, covariances, colors, opacities)``.

    ``means: [N, 3]``, ``covariances: [N, 3, 3]``, ``colors: [N, 3]``
    in [0, 1], ``opacities: [N]`` in [0, 1].
    """
    means = as_float_array(means, source, "means", (-1, 3))
    n = means.shape[0]
    covariances = as_float_array(covariances, source, "covariances", (-1, 3, 3))
    check_count(covariances, n, source, "covariances", "means")
    colors = as_float_array(colors, source, "colors", (-1, 3))
    check_count(colors, n, source, "colors", "means")
    check_range(colors, 0.0, 1.0, source, "colors")
    opacities = as_float_array(opacities, source, "opacities", (-1,))
    check_count(opacities, n, source, "opacities", "means")
    check_range(opacities, 0.0, 1.0, source, "opacities")
    return means, covariances, colors, opacities


def check_background(background, source: str) -> np.ndarray:
    """Validate a background colour: 3 values in [0, 1]."""
    bg = as_float_array(background, source, "background", (3,))
    check_range(bg, 0.0, 1.0, source, "background")
    return bg
