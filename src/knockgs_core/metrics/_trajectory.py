"""Parameter and trajectory metrics (SPEC section 7) (private)."""

from __future__ import annotations

import numpy as np

from knockgs_core.errors import InputError


def _array(value, source: str, field: str, ndim: int, last: int | None = None) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(source, field, f"not a numeric array ({exc})") from None
    if arr.ndim != ndim or (last is not None and arr.shape[-1] != last):
        want = {3: "[T, N, 3]", 1: "[2]"}.get(ndim, f"{ndim}-D")
        raise InputError(source, field, f"expected shape {want}, got {list(arr.shape)}")
    if not np.all(np.isfinite(arr)):
        raise InputError(source, field, "contains NaN or infinite values")
    return arr


def joint_error_pct(theta_hat, theta_true) -> float:
    """Joint parameter error in percent.

    ``theta_hat``, ``theta_true``: ``[2]`` as ``(s_E, s_rho)``; returns
    ``50 * (|s_E^ - s_E| / s_E + |s_rho^ - s_rho| / s_rho)`` (the mean of the two
    relative errors, in %).
    """
    src = "metrics.joint_error_pct"
    hat = _array(theta_hat, src, "theta_hat", 1, 2)
    true = _array(theta_true, src, "theta_true", 1, 2)
    if np.any(true <= 0):
        raise InputError(src, "theta_true", f"scales must be > 0, got {true.tolist()}")
    return float(50.0 * np.sum(np.abs(hat - true) / true))


def _checked(value, source: str, field: str) -> np.ndarray:
    """``value`` as a [T, N, 3] array of real numbers, all finite, without a copy where it is
    one already (float32 rollouts stay float32: the callers convert what they use to float64)."""
    arr = np.asarray(value)
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        return _array(value, source, field, 3, 3)  # converted, or refused as not numeric
    if arr.ndim != 3 or arr.shape[-1] != 3:
        raise InputError(source, field, f"expected shape [T, N, 3], got {list(arr.shape)}")
    if np.issubdtype(arr.dtype, np.floating) and not np.isfinite(arr).all():
        raise InputError(source, field, "contains NaN or infinite values")
    return arr


def _pair(pred, target, src):
    pred = _checked(pred, src, "pred")
    target = _checked(target, src, "target")
    if pred.shape != target.shape:
        raise InputError(src, "pred", f"shape {list(pred.shape)} differs from target "
                         f"{list(target.shape)} (fixed correspondence needs equal shapes)")
    if pred.shape[0] == 0 or pred.shape[1] == 0:
        raise InputError(src, "pred", "needs at least one frame and one particle")
    return pred, target


def trajectory_rmse(pred, target, *, max_particles: int = 100_000, seed: int = 42) -> float:
    """Particle-trajectory RMSE under fixed correspondence.

    ``pred``, ``target``: ``[T, N, 3]`` positions of the same particles over the same
    frames. Returns ``sqrt(mean_{t, i} ||pred[t, i] - target[t, i]||^2)``. When
    ``N > max_particles``, ``max_particles`` particles are drawn without replacement
    with ``np.random.default_rng(seed)`` (the same particles in every frame).
    """
    src = "metrics.trajectory_rmse"
    pred, target = _pair(pred, target, src)
    if int(max_particles) < 1:
        raise InputError(src, "max_particles", f"must be >= 1, got {max_particles!r}")
    n = pred.shape[1]
    if n > max_particles:  # the sample first, then float64: the same values as converting first
        idx = np.random.default_rng(seed).choice(n, size=int(max_particles), replace=False)
        pred, target = pred[:, idx], target[:, idx]
    pred = np.asarray(pred, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    return float(np.sqrt(np.mean(np.sum((pred - target) ** 2, axis=-1))))


def rms_displacement_curve(X) -> np.ndarray:
    """RMS displacement from the first frame: ``c[t] = sqrt(mean_i ||x_i^t - x_i^0||^2)``.

    ``X: [T, N, 3]``; returns ``[T]`` (same length unit as ``X``; not normalized).
    """
    X = _checked(X, "metrics.rms_displacement_curve", "X")
    if X.shape[0] == 0 or X.shape[1] == 0:
        raise InputError("metrics.rms_displacement_curve", "X", "needs at least one frame and one particle")
    # frame by frame in float64 (a frame's copy, not the whole trajectory's): the same sums
    X0 = np.asarray(X[0], dtype=np.float64)
    return np.sqrt(np.array([np.mean(np.sum((np.asarray(Xt, dtype=np.float64) - X0) ** 2, axis=-1)) for Xt in X]))


def curve_metrics(pred_X, target_X) -> dict[str, float]:
    """Differences between the RMS-displacement curves of two trajectories.

    ``pred_X``, ``target_X``: ``[T, N, 3]`` with the same ``T`` (particle counts may
    differ). With ``p``, ``q`` their :func:`rms_displacement_curve` s, returns

    - ``curve_rmse``: ``sqrt(mean_t (p_t - q_t)^2)``;
    - ``peak_abs_diff``: ``|max_t p_t - max_t q_t|``;
    - ``auc_abs_diff``: ``|sum_t p_t - sum_t q_t|`` -- the area as a plain *sum over
      frames* (length x frames; multiply by the frame interval for length x time);
    - ``final_abs_diff``: ``|p_{T-1} - q_{T-1}|``.
    """
    return curve_differences(rms_displacement_curve(pred_X), rms_displacement_curve(target_X))


def curve_differences(p, q) -> dict[str, float]:
    """:func:`curve_metrics` of two RMS-displacement curves ``p`` (prediction) and ``q``
    (target), each ``[T]``: for a target compared with several predictions, its curve once."""
    p = np.asarray(p, dtype=np.float64)
    q = np.asarray(q, dtype=np.float64)
    if p.shape != q.shape:
        raise InputError("metrics.curve_metrics", "pred_X",
                         f"has {p.size} frames but target_X has {q.size}")
    return {
        "curve_rmse": float(np.sqrt(np.mean((p - q) ** 2))),
        "peak_abs_diff": float(abs(p.max() - q.max())),
        "auc_abs_diff": float(abs(p.sum() - q.sum())),
        "final_abs_diff": float(abs(p[-1] - q[-1])),
    }
