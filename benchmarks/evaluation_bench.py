"""The write-back evaluation's cost at paper scale on the CPU: one (prediction, target) pair
of the Pillow's duration-shift probe (121 frames, 584,000 Gaussian-associated particles of
695,881), scored as :func:`knockgs_core.experiments.evaluate_methods` scores it, against the
same formulas converting both whole trajectories to float64 first (the former metrics). The
results must be equal bit for bit; the script stops otherwise.

Timed, median of ``--repeats``: reading one rollout file (:func:`knockgs_core.rollout.read_rollout`),
the trajectory RMSE (100,000 particles sampled) and the curve metrics, each in both forms.

    python3 benchmarks/evaluation_bench.py [--frames 121] [--particles 695881] [--gs 584000] [--repeats 3]
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from _synthetic import sway, swaying_cloud
from _timing import median_time
from knockgs_core.metrics import curve_metrics, trajectory_rmse
from knockgs_core.rollout import Rollout, read_rollout, write_rollout


def _float64(X):
    """The former metrics' input check: the whole trajectory to float64, checked finite."""
    X = np.asarray(X, dtype=np.float64)
    assert np.all(np.isfinite(X))
    return X


def _former_rmse(pred, target, max_particles=100_000, seed=42):
    """The former trajectory RMSE: both trajectories to float64, then the sample."""
    pred, target = _float64(pred), _float64(target)
    n = pred.shape[1]
    if n > max_particles:
        idx = np.random.default_rng(seed).choice(n, size=max_particles, replace=False)
        pred, target = pred[:, idx], target[:, idx]
    return float(np.sqrt(np.mean(np.sum((pred - target) ** 2, axis=-1))))


def _former_curves(pred, target):
    """The former curve metrics: each trajectory to float64 whole."""
    def curve(X):
        X = _float64(X)
        return np.sqrt(np.mean(np.sum((X - X[0]) ** 2, axis=-1), axis=1))
    p, q = curve(pred), curve(target)
    return {"curve_rmse": float(np.sqrt(np.mean((p - q) ** 2))), "peak_abs_diff": float(abs(p.max() - q.max())),
            "auc_abs_diff": float(abs(p.sum() - q.sum())), "final_abs_diff": float(abs(p[-1] - q[-1]))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=121)
    ap.add_argument("--particles", type=int, default=695_881)
    ap.add_argument("--gs", type=int, default=584_000, help="Gaussian-associated particles (the first ones)")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    T, N = args.frames, args.particles
    x0, wave = swaying_cloud(rng, T, N)
    target = sway(rng, x0, wave)
    pred = (target + 1e-4 * rng.standard_normal(size=(T, N, 3))).astype(np.float32)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "rollout.parquet"
        write_rollout(path, Rollout(target, None, {"n_gs": args.gs, "n_fill": N - args.gs, "export_times": list(range(T))}))
        t_read, ro = median_time(lambda: read_rollout(path), args.repeats)
        assert np.array_equal(ro.positions, target)
        del ro
    P, X = pred[:, :args.gs], target[:, :args.gs]
    t_rmse, rmse = median_time(lambda: trajectory_rmse(P, X), args.repeats)
    t_rmse0, rmse0 = median_time(lambda: _former_rmse(P, X), args.repeats)
    t_curve, curves = median_time(lambda: curve_metrics(P, X), args.repeats)
    t_curve0, curves0 = median_time(lambda: _former_curves(P, X), args.repeats)
    if rmse != rmse0 or curves != curves0:
        raise SystemExit(f"the metrics differ from the former formulas: {rmse} / {rmse0}, {curves} / {curves0}")
    print(f"{T} frames x {args.gs} of {N} particles, median of {args.repeats}; the same bits as the former formulas")
    print(f"read one rollout file: {t_read:.2f} s")
    print(f"trajectory RMSE: {t_rmse:.2f} s (former {t_rmse0:.2f} s, {t_rmse0 / t_rmse:.1f}x)")
    print(f"curve metrics:   {t_curve:.2f} s (former {t_curve0:.2f} s, {t_curve0 / t_curve:.1f}x)")


if __name__ == "__main__":
    main()
