"""Tests of knockgs_core.metrics against closed-form answers (SPEC section 7)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from skimage.metrics import structural_similarity

from knockgs_core.errors import InputError
from knockgs_core.metrics import (
    crop_boxes,
    crop_ssim,
    curve_differences,
    curve_metrics,
    foreground_psnr,
    joint_error_pct,
    rms_displacement_curve,
    trajectory_rmse,
)


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


# --- parameters and trajectories -------------------------------------------------


def test_joint_error_pct():
    assert joint_error_pct((1.1, 0.8), (1.0, 1.0)) == pytest.approx(15.0)  # 50 (0.1 + 0.2)
    assert joint_error_pct((3.0, 0.5), (2.0, 0.25)) == pytest.approx(50 * (0.5 + 1.0))
    assert joint_error_pct((2.0, 0.25), (2.0, 0.25)) == 0.0
    with pytest.raises(InputError, match="theta_true"):
        joint_error_pct((1.0, 1.0), (0.0, 1.0))
    with pytest.raises(InputError, match="theta_hat"):
        joint_error_pct((1.0, 1.0, 1.0), (1.0, 1.0))


def test_trajectory_rmse_of_a_constant_shift_is_its_length(rng):
    target = rng.normal(size=(5, 300, 3))
    d = np.array([0.3, -0.4, 1.2])  # |d| = 1.3
    assert trajectory_rmse(target + d, target) == pytest.approx(1.3, rel=1e-12)
    # Subsampled (N > max_particles): still |d|.
    assert trajectory_rmse(target + d, target, max_particles=50) == pytest.approx(1.3, rel=1e-12)
    assert trajectory_rmse(target, target) == 0.0


def test_trajectory_rmse_pools_frames_and_particles(rng):
    target = np.zeros((2, 2, 3))
    pred = target.copy()
    pred[0, 0, 0] = 2.0  # one error of 2 among 4 (frame, particle) pairs
    assert trajectory_rmse(pred, target) == pytest.approx(1.0)  # sqrt(4 / 4)


def test_trajectory_rmse_subsample_is_seeded_without_replacement(rng):
    target = np.zeros((3, 1000, 3))
    pred = target + rng.uniform(0, 1, (1, 1000, 1)) * np.array([1.0, 0.0, 0.0])
    idx = np.random.default_rng(42).choice(1000, size=100, replace=False)
    expected = math.sqrt(np.mean(pred[0, idx, 0] ** 2))
    assert trajectory_rmse(pred, target, max_particles=100) == pytest.approx(expected, rel=1e-12)
    assert trajectory_rmse(pred, target, max_particles=100, seed=7) != pytest.approx(expected, rel=1e-6)
    full = math.sqrt(np.mean(pred[0, :, 0] ** 2))
    assert trajectory_rmse(pred, target) == pytest.approx(full, rel=1e-12)


def test_trajectory_rmse_shape_errors(rng):
    x = rng.normal(size=(4, 10, 3))
    with pytest.raises(InputError, match="pred"):
        trajectory_rmse(x[:, :9], x)
    with pytest.raises(InputError, match="target"):
        trajectory_rmse(x, x[..., :2])


def test_float32_trajectories_score_as_their_float64_copies_bit_for_bit(rng):
    # rollouts are float32; the metrics sample and convert what they use, frame by frame, and
    # must give the bits of the whole trajectory converted to float64 first (the reference)
    X = rng.uniform(0.0, 2.0, size=(7, 3001, 3)).astype(np.float32)
    P = (X + rng.normal(scale=1e-3, size=X.shape)).astype(np.float32)
    X64, P64 = X.astype(np.float64), P.astype(np.float64)
    ref_curve = np.sqrt(np.mean(np.sum((X64 - X64[0]) ** 2, axis=-1), axis=1))
    assert np.array_equal(rms_displacement_curve(X), ref_curve)
    idx = np.random.default_rng(42).choice(3001, size=500, replace=False)
    ref_rmse = float(np.sqrt(np.mean(np.sum((P64[:, idx] - X64[:, idx]) ** 2, axis=-1))))
    assert trajectory_rmse(P, X, max_particles=500) == ref_rmse
    assert trajectory_rmse(P, X) == float(np.sqrt(np.mean(np.sum((P64 - X64) ** 2, axis=-1))))
    assert curve_metrics(P, X) == curve_metrics(P64, X64)
    assert curve_differences(rms_displacement_curve(P), ref_curve) == curve_metrics(P, X)
    # a non-finite value is refused wherever it lies, sampled or not
    bad = P.copy()
    bad[3, np.setdiff1d(np.arange(3001), idx)[0], 1] = np.nan
    with pytest.raises(InputError, match="NaN"):
        trajectory_rmse(bad, X, max_particles=500)
    with pytest.raises(InputError, match="NaN"):
        rms_displacement_curve(bad)
    with pytest.raises(InputError, match="not a numeric array"):
        rms_displacement_curve(np.full((2, 2, 3), "a"))
    with pytest.raises(InputError, match="frames"):
        curve_differences(np.zeros(3), np.zeros(4))


def test_rms_displacement_curve_analytic(rng):
    t = np.arange(6.0)
    x0 = rng.normal(size=(40, 3))
    v = np.array([0.0, 0.6, 0.8])  # |v| = 1
    X = x0[None] + t[:, None, None] * v
    X[:, 20:] = x0[20:]  # half the particles stay at rest
    np.testing.assert_allclose(rms_displacement_curve(X), t / math.sqrt(2), rtol=1e-12)


def test_curve_metrics_analytic(rng):
    # p(t) = a t and q(t) = b t for t = 0..T-1 (all particles translated).
    T, a, b = 5, 2.0, 0.5
    t = np.arange(T, dtype=float)
    x0 = rng.normal(size=(7, 3))
    pred = x0[None] + (a * t)[:, None, None] * np.array([1.0, 0.0, 0.0])
    target = x0[None] + (b * t)[:, None, None] * np.array([0.0, 0.0, -1.0])
    m = curve_metrics(pred, target)
    assert m["curve_rmse"] == pytest.approx((a - b) * math.sqrt(np.mean(t**2)))  # 1.5 sqrt(6)
    assert m["peak_abs_diff"] == pytest.approx((a - b) * (T - 1))
    assert m["auc_abs_diff"] == pytest.approx((a - b) * t.sum())  # sum over frames
    assert m["final_abs_diff"] == pytest.approx((a - b) * (T - 1))
    assert set(m) == {"curve_rmse", "peak_abs_diff", "auc_abs_diff", "final_abs_diff"}
    assert curve_metrics(target, target) == dict.fromkeys(m, 0.0)


def test_curve_metrics_peak_and_final_differ_for_a_rebound():
    # p rises to 3 then returns to 1; q rises to 2 and stays.
    p = np.array([0.0, 3.0, 1.0])
    q = np.array([0.0, 2.0, 2.0])
    e = np.array([1.0, 0.0, 0.0])
    m = curve_metrics(p[:, None, None] * e, q[:, None, None] * e)
    assert m["peak_abs_diff"] == pytest.approx(1.0)
    assert m["final_abs_diff"] == pytest.approx(1.0)
    assert m["auc_abs_diff"] == pytest.approx(0.0)
    assert m["curve_rmse"] == pytest.approx(math.sqrt(2 / 3))
    with pytest.raises(InputError, match="frames"):
        curve_metrics(np.zeros((3, 2, 3)), np.zeros((4, 2, 3)))


# --- rendered frames -------------------------------------------------------------


def frames(rng, T=3, H=30, W=40):
    """A target sequence with a disc of foreground per frame."""
    rgb = rng.uniform(0.2, 0.8, (T, H, W, 3))
    rows, cols = np.mgrid[:H, :W]
    alpha = np.stack([((rows - 12 - t) ** 2 + (cols - 15 - 2 * t) ** 2 < 36).astype(float) for t in range(T)])
    return rgb, alpha


def test_foreground_psnr_of_a_constant_offset(rng):
    target, alpha = frames(rng)
    c = 0.05
    pred = target.copy()
    pred[alpha > 0.5] += c
    pred[alpha <= 0.5] += 0.3  # background errors outside the mask union do not count
    assert foreground_psnr(pred, target, alpha, alpha) == pytest.approx(10 * math.log10(1 / c**2), rel=1e-12)
    assert foreground_psnr(pred * 255, target * 255, alpha, alpha, data_range=255.0) == pytest.approx(
        10 * math.log10(1 / c**2), rel=1e-9)


def test_foreground_psnr_pools_before_db_and_uses_the_union(rng):
    target, alpha = frames(rng, T=2)
    pred_alpha = alpha.copy()
    pred_alpha[0, 0, :5] = 0.9  # 5 predicted-only foreground pixels in frame 0
    pred = target.copy()
    pred[0][alpha[0] > 0.5] += 0.1
    pred[1][alpha[1] > 0.5] += 0.02
    pred[0, 0, :5] += 0.2
    n0, n1 = int((alpha[0] > 0.5).sum()), int((alpha[1] > 0.5).sum())
    mse = (n0 * 0.1**2 + n1 * 0.02**2 + 5 * 0.2**2) / (n0 + n1 + 5)
    assert foreground_psnr(pred, target, pred_alpha, alpha) == pytest.approx(-10 * math.log10(mse), rel=1e-9)
    # Not the mean of per-frame PSNRs.
    per_frame = np.mean([foreground_psnr(pred[i:i + 1], target[i:i + 1], pred_alpha[i:i + 1], alpha[i:i + 1])
                         for i in range(2)])
    assert abs(per_frame - foreground_psnr(pred, target, pred_alpha, alpha)) > 1.0


def test_foreground_psnr_identical_is_inf_and_empty_union_raises(rng):
    target, alpha = frames(rng)
    with np.errstate(all="raise"):  # no division by zero on the way
        assert foreground_psnr(target, target.copy(), alpha, alpha) == math.inf
    with pytest.raises(InputError, match="no foreground"):
        foreground_psnr(target, target, np.zeros_like(alpha), np.zeros_like(alpha))


def test_foreground_psnr_threshold_is_strict(rng):
    target, _ = frames(rng, T=1)
    alpha = np.zeros(target.shape[:3])
    alpha[0, 3, 4] = 0.5  # not foreground at threshold 0.5
    alpha[0, 6, 7] = 0.51
    pred = target.copy()
    pred[0, 3, 4] += 0.5
    pred[0, 6, 7] += 0.1
    assert foreground_psnr(pred, target, alpha, alpha) == pytest.approx(20.0)
    with pytest.raises(InputError, match="pred_alpha"):
        foreground_psnr(pred, target, alpha[..., :-1], alpha)
    with pytest.raises(InputError, match="pred_rgb"):
        foreground_psnr(pred[..., :2], target, alpha, alpha)


def test_crop_boxes_pad_clip_and_minimum_size():
    T, H, W = 3, 30, 40
    a = np.zeros((T, H, W))
    a[0, 10:13, 20:26] = 1.0  # rows 10..12, cols 20..25 -> padded by 5
    a[1, 0:2, 38:40] = 1.0  # at a corner: clipped to the image
    b = np.zeros_like(a)
    b[2, 15, 3] = 1.0  # a single pixel, pad 0: enlarged to 7 x 7 inside the image
    b[0, 14, 20] = 1.0  # target-only pixel extends the union
    boxes = crop_boxes(a, b)
    assert boxes[0] == (5, 20, 15, 31)
    assert boxes[1] == (0, 7, 33, 40)
    assert crop_boxes(a, b, pad=0)[2] == (12, 19, 0, 7)  # centred at row 15, shifted right of col 0
    assert crop_boxes(a, b, pad=0)[1] == (0, 7, 33, 40)


def test_crop_ssim_identical_is_one_and_matches_skimage_on_the_crop(rng):
    target, alpha = frames(rng)
    assert crop_ssim(target, target.copy(), alpha, alpha) == pytest.approx(1.0, abs=1e-12)
    pred = np.clip(target + rng.normal(0, 0.05, target.shape), 0, 1)
    boxes = crop_boxes(alpha, alpha)
    expected = np.mean([
        structural_similarity(pred[t, r0:r1, c0:c1], target[t, r0:r1, c0:c1], channel_axis=-1, data_range=1.0)
        for t, (r0, r1, c0, c1) in enumerate(boxes)
    ])
    got = crop_ssim(pred, target, alpha, alpha)
    assert got == pytest.approx(expected, rel=1e-12)
    assert 0.3 < got < 0.99
    # Changes far outside the padded crop do not matter.
    far = pred.copy()
    far[:, -3:, -3:] = 0.0
    assert crop_ssim(far, target, alpha, alpha) == pytest.approx(got, rel=1e-12)


def test_crop_ssim_errors(rng):
    target, alpha = frames(rng)
    empty = alpha.copy()
    empty[1] = 0.0
    with pytest.raises(InputError, match="frame 1"):
        crop_ssim(target, target, empty, empty)
    with pytest.raises(InputError, match="SSIM window"):
        crop_ssim(target[:, :5, :5], target[:, :5, :5], alpha[:, :5, :5], alpha[:, :5, :5])
