"""The tracker of `knockgs observe tracks` against truths it does not see: a known sub-pixel
shift of an analytic image, and the rendered truth of a rollout (where the surface point
under each seed went); its error estimate in the tracks' metadata, which the discrepancy loop
takes as its noise."""

from __future__ import annotations

import numpy as np
import pytest

from knockgs_core.errors import InputError


def _texture(rows, cols, rng_state):
    """An analytic smooth texture: a sum of 40 Gaussian blobs (radius 1.5-3 px) at fixed
    random centres, evaluated at any (fractional) pixel coordinates."""
    centres, radii, amps = rng_state
    img = np.zeros(np.broadcast(rows, cols).shape)
    for (r0, c0), s, a in zip(centres, radii, amps):
        img += a * np.exp(-0.5 * ((rows - r0) ** 2 + (cols - c0) ** 2) / s**2)
    return img


def test_lucas_kanade_recovers_a_known_subpixel_shift(rng):
    """An analytic texture moved by (0.37, -0.61) px: the windows of the sparse pyramidal
    Lucas-Kanade find it to within 0.01 px (the dense chained flow it replaces is no better
    than 0.1 px on the rendered sequences: docs/discrepancy.md)."""
    from knockgs_core.observe._lucas_kanade import pyramid, track_windows

    H, W = 64, 80
    state = (rng.uniform([4, 4], [H - 4, W - 4], size=(40, 2)), rng.uniform(1.5, 3.0, 40), rng.uniform(0.2, 1.0, 40))
    r, c = np.mgrid[0:H, 0:W].astype(float)
    shift = np.array([0.37, -0.61])
    ref = pyramid(_texture(r, c, state), levels=3)
    cur = pyramid(_texture(r - shift[0], c - shift[1], state), levels=3)
    pts = np.stack(np.meshgrid(np.arange(16.0, H - 16, 8), np.arange(16.0, W - 16, 8), indexing="ij"), -1).reshape(-1, 2)
    found, _, ok = track_windows(ref, cur, pts, pts, radius=7)
    assert ok.all()
    err = found - pts - shift
    assert np.max(np.abs(err)) < 0.01, np.max(np.abs(err))


@pytest.fixture(scope="module")
def rendered_probe_a(pillow_ci):
    """The ci Pillow's Probe-A rollout at theta (1, 1) rendered at 160x120 by the contract's
    camera (about 2 s)."""
    from knockgs_core.experiments import camera_from_contract
    from knockgs_core.observe import render_rgbd
    from knockgs_core.rollout import run_rollout

    c, asset = pillow_ci
    ro = run_rollout(c, (1.0, 1.0), "standard_x", particles=asset.particles, export_F=True)
    X = np.asarray(ro.positions, np.float64)[:, : asset.particles.n_gs]
    cam = camera_from_contract(c.camera, width=160, height=120)
    frames = render_rgbd(asset.gaussians, np.asarray(asset.static_mask), np.asarray(asset.particles.gaussian_index), X,
                         ro.F, cam, frame_dt=0.02)
    return asset, X, np.asarray(ro.F, np.float64), frames


def test_tracks_error_estimate_in_their_metadata_is_the_size_of_the_rendered_truth(rendered_probe_a, tmp_path, capsys):
    """`knockgs observe tracks` on the rendered Probe-A video: its tracks' error against the
    rendered truth (where the surface point under each seed went) is under 0.15 px and a
    quarter of the motion, and the error estimate it writes (``tracker_error_std``) is within
    a factor of 2 of it; read back, that estimate is the measurement's noise, and the output
    says where the noise came from."""
    from knockgs_core.cli import main
    from knockgs_core.cli.observe import TRACKS_SETTINGS
    from knockgs_core.discrepancy import read_measured
    from knockgs_core.observe import TrackSettings, read_rgbd, surface_truth, track_errors, track_pixels, write_rgbd

    asset, X, F, frames = rendered_probe_a
    write_rgbd(tmp_path / "v.npz", frames)
    assert main(["observe", "tracks", str(tmp_path / "v.npz"), "-o", str(tmp_path / "t.parquet")]) == 0
    assert "tracker error estimate" in capsys.readouterr().err
    m = read_measured(tmp_path / "t.parquet")
    est = m.meta["tracker_error_std"]
    assert m.meta["noise_std"] == est and "tracker" in m.meta["noise_source"]

    # the same tracks (of the stored frames: colour in float16), with their pixels
    tracks = track_pixels(read_rgbd(tmp_path / "v.npz"), TrackSettings(**TRACKS_SETTINGS))
    np.testing.assert_allclose(tracks.to_world(), m.points, atol=1e-9)
    truth = surface_truth(asset.gaussians, asset.static_mask, X, F, frames.camera, tracks.rows[0], tracks.cols[0],
                          tracks.depth[0])
    e = track_errors(frames.camera, tracks.rows, tracks.cols, m.points, truth)
    assert e.rms_px < 0.15 and e.rms_m < 0.25 * e.signal_m, e.as_dict()
    assert 0.5 * e.rms_m <= est <= 2.0 * e.rms_m, (est, e.rms_m)


def test_a_declared_noise_wins_over_the_trackers_estimate(rng):
    from knockgs_core.discrepancy import Measurement

    X = 1.0 + rng.normal(0.0, 1e-3, size=(4, 6, 3))

    def meas(meta):
        return Measurement(points=X, frames=np.arange(4), times=None, particle=None, track=np.arange(6), meta=meta,
                           source="m.parquet")

    assert meas({"tracker_error_std": 2e-3}).meta["noise_std"] == 2e-3
    declared = meas({"tracker_error_std": 2e-3, "noise_std": 5e-4}).meta
    assert declared["noise_std"] == 5e-4 and "declared" in declared["noise_source"]
    assert "noise_std" not in meas({}).meta
    with pytest.raises(InputError, match=r"m\.parquet.*metadata\.tracker_error_std"):
        meas({"tracker_error_std": -1.0})
