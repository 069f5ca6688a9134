"""Residual views between a measured and a simulated response (private).

All views take positions ``measured`` and ``simulated`` [T, M, 3] of the same points at
the same ``times`` [T] (s); displacements are taken from frame 0 of each.
"""

from __future__ import annotations

import numpy as np

__all__ = ["residual_views", "view_summary", "VIEW_METRICS"]

#: scalar summaries of the views, in report order
VIEW_METRICS = ("traj_rmse", "rms_curve_rmse", "centroid_rmse", "spectrum_rel_diff", "envelope_rmse")


def _envelope(signal: np.ndarray) -> np.ndarray:
    """Decay envelope: the largest amplitude still to come, ``max_{t' >= t} |signal(t')|``
    (through the peaks of a decaying oscillation; flat at the end value for a drift)."""
    return np.maximum.accumulate(np.abs(signal)[::-1])[::-1]


def residual_views(measured, simulated, times) -> dict:
    """Every view of the residual ``measured - simulated``.

    Returns a dict of arrays:

    * ``per_frame_rms`` [T]: RMS of the position residual over points and axes, per frame;
    * ``per_point_rms`` [M]: RMS over frames and axes, per point;
    * ``rms_curve_measured`` / ``rms_curve_simulated`` [T]: RMS displacement from frame 0;
    * ``centroid_measured`` / ``centroid_simulated`` [T, 3]: mean displacement per axis;
    * ``freq`` [K] (Hz), ``spectrum_measured`` / ``spectrum_simulated`` [K, 3]: amplitude
      spectra of the mean-removed centroid displacements (uniform times assumed; otherwise
      the frequencies are those of the mean frame interval);
    * ``axis``: the axis with the largest measured centroid motion, and
      ``envelope_measured`` / ``envelope_simulated`` [T]: decay envelopes of the centroid
      displacement along it (the largest amplitude from t on).
    """
    Y = np.asarray(measured, dtype=np.float64)
    S = np.asarray(simulated, dtype=np.float64)
    t = np.asarray(times, dtype=np.float64)
    R = Y - S
    dY = Y - Y[0]
    dS = S - S[0]
    cY = dY.mean(axis=1)
    cS = dS.mean(axis=1)
    dt = float(np.mean(np.diff(t))) if t.size > 1 else 1.0
    fY = np.abs(np.fft.rfft(cY - cY.mean(axis=0), axis=0)) / len(t)
    fS = np.abs(np.fft.rfft(cS - cS.mean(axis=0), axis=0)) / len(t)
    axis = int(np.argmax(np.ptp(cY, axis=0)))
    return {
        "times": t,
        "per_frame_rms": np.sqrt(np.mean(R**2, axis=(1, 2))),
        "per_point_rms": np.sqrt(np.mean(R**2, axis=(0, 2))),
        "rms_curve_measured": np.sqrt(np.mean(np.sum(dY**2, axis=-1), axis=1)),
        "rms_curve_simulated": np.sqrt(np.mean(np.sum(dS**2, axis=-1), axis=1)),
        "centroid_measured": cY,
        "centroid_simulated": cS,
        "freq": np.fft.rfftfreq(len(t), d=dt),
        "spectrum_measured": fY,
        "spectrum_simulated": fS,
        "axis": axis,
        "envelope_measured": _envelope(cY[:, axis]),
        "envelope_simulated": _envelope(cS[:, axis]),
    }


def view_summary(views: dict) -> dict:
    """Scalar summaries [m unless noted]: trajectory RMSE (``sqrt(mean ||r||^2)`` over
    points and frames), RMS-curve RMSE, centroid-curve RMSE (over frames, norm over axes),
    spectrum relative L2 difference [-], envelope RMSE."""
    traj = float(np.sqrt(3.0 * np.mean(views["per_frame_rms"] ** 2)))
    curve = float(np.sqrt(np.mean((views["rms_curve_measured"] - views["rms_curve_simulated"]) ** 2)))
    cen = float(np.sqrt(np.mean(np.sum((views["centroid_measured"] - views["centroid_simulated"]) ** 2, axis=-1))))
    fm, fs = views["spectrum_measured"], views["spectrum_simulated"]
    spec = float(np.linalg.norm(fm - fs) / max(np.linalg.norm(fm), 1e-30))
    env = float(np.sqrt(np.mean((views["envelope_measured"] - views["envelope_simulated"]) ** 2)))
    return dict(zip(VIEW_METRICS, (traj, curve, cen, spec, env)))
