"""Observations a camera gives (knockgs_core.observe): the camera model, RGB-D files, the
optical-flow tracker against a known rigid motion, visibility, the descriptor of point sets
without correspondence against the tracked one, and the discrepancy loop run on ID-free tracks
from rendered frames of a world with a planted effect (the `knockgs observe` command)."""

from __future__ import annotations

import numpy as np
import pytest

from knockgs_core.descriptors import descriptor
from knockgs_core.errors import InputError
from knockgs_core.experiments import camera_from_contract
from knockgs_core.observe import (
    RGBDFrames,
    TrackSettings,
    pointset_descriptor,
    project,
    read_rgbd,
    render_rgbd,
    track_points,
    unproject,
    visible_particles,
    write_rgbd,
)


@pytest.fixture(scope="module")
def pillow(pillow_ci):
    return pillow_ci


def _render(pillow, X, F=None, *, width=160, height=120):
    c, asset = pillow
    n = asset.particles.n_gs
    if F is None:
        F = np.broadcast_to(np.eye(3), (X.shape[0], n, 3, 3)).copy()
    cam = camera_from_contract(c.camera, width=width, height=height)
    return render_rgbd(asset.gaussians, np.asarray(asset.static_mask), np.asarray(asset.particles.gaussian_index), X, F, cam,
                       frame_dt=0.02)


def test_project_unproject_round_trip(pillow):
    c, _ = pillow
    cam = camera_from_contract(c.camera, width=160, height=120)
    P = np.random.default_rng(0).uniform(0.6, 1.4, size=(50, 3))
    r, col, z = project(cam, P)
    np.testing.assert_allclose(unproject(cam, r, col, z), P, atol=1e-12)
    # the target point projects to the principal point
    r0, c0, _ = project(cam, np.asarray(c.camera["target"], dtype=float))
    assert (r0 + 0.5, c0 + 0.5) == pytest.approx((cam.cy, cam.cx), abs=1e-9)


def test_rgbd_file_round_trip_and_errors(pillow, tmp_path):
    X = np.stack([pillow[1].particles.positions] * 2)
    fr = _render(pillow, X, width=48, height=36)
    assert fr.mask is not None and fr.mask.any() and not fr.mask.all()
    write_rgbd(tmp_path / "f.npz", fr)
    back = read_rgbd(tmp_path / "f.npz")
    assert back.n_frames == 2 and back.camera.width == 48 and np.array_equal(back.mask, fr.mask)
    np.testing.assert_array_equal(back.depth, fr.depth)
    np.testing.assert_allclose(back.rgb, fr.rgb, atol=1e-3)  # stored as float16
    data = dict(np.load(tmp_path / "f.npz"))
    del data["depth"]
    np.savez(tmp_path / "bad.npz", **data)
    with pytest.raises(InputError, match=r"bad\.npz.*depth"):
        read_rgbd(tmp_path / "bad.npz")
    with pytest.raises(InputError, match="frame_dt"):
        RGBDFrames(rgb=fr.rgb, alpha=fr.alpha, depth=fr.depth, camera=fr.camera, frame_dt=0.0)


def test_tracker_recovers_a_rigid_translation(pillow):
    """The object moved rigidly by 2 mm per frame along x (10 frames): the lifted tracks'
    median displacement is within 5 % of the truth, their RMS error within 30 % of it."""
    ps = pillow[1].particles
    d = np.array([0.002, 0.0, 0.0])
    X = np.stack([ps.positions + t * d for t in range(11)])
    pts, info = track_points(_render(pillow, X), TrackSettings())
    assert info["tracks"] >= 20
    disp = pts[-1] - pts[0]
    truth = 10 * d
    assert np.linalg.norm(np.median(disp, axis=0) - truth) <= 0.05 * np.linalg.norm(truth)
    assert np.sqrt(np.mean(np.sum((disp - truth) ** 2, -1))) <= 0.3 * np.linalg.norm(truth)
    # a still scene gives still tracks
    still, _ = track_points(_render(pillow, np.stack([ps.positions] * 6)), TrackSettings())
    assert np.max(np.abs(still - still[0])) < 1e-6


def test_visibility_rule(pillow):
    ps = pillow[1].particles
    n = ps.n_gs
    X = np.stack([ps.positions] * 2)
    fr = _render(pillow, X)
    vis = visible_particles(X[:, :n], fr)
    assert 0 < vis.sum() < n
    # the particles seen are on the camera's side: nearer than the ones hidden, on average
    c, _ = pillow
    _, _, z = project(fr.camera, X[0, :n])
    assert np.median(z[vis]) < np.median(z[~vis])
    # a particle moved behind the camera in one frame is not visible
    Y = X[:, :n].copy()
    i = int(np.flatnonzero(vis)[0])
    Y[1, i] = np.asarray(c.camera["eye"]) + (np.asarray(c.camera["eye"]) - np.asarray(c.camera["target"]))
    assert not visible_particles(Y, fr)[i]


def test_pointset_descriptor_matches_tracked_points_for_normal_motion():
    """Points on a sphere moving along its normals (a breathing sphere): nearest-point
    distances are the true displacements, so the descriptor of the point sets without
    correspondence equals the tracked one; a sliding motion (a rotation about the centre) is
    invisible to it beyond the sampling's resolution."""
    rng = np.random.default_rng(1)
    u = rng.normal(size=(4000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    radius = 0.5 * (1.0 + 0.02 * np.sin(np.linspace(0.0, 3.0, 31)))
    X = 1.0 + radius[:, None, None] * u[None]
    np.testing.assert_allclose(pointset_descriptor(list(X)), descriptor(X), rtol=0.02)
    angle = np.linspace(0.0, 0.2, 31)
    rot = np.stack([np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]) for a in angle])
    Y = 1.0 + np.einsum("tij,nj->tni", rot, 0.5 * u)
    # (up to the sampling: nearest points lie at most about a point spacing, ~0.03, away)
    assert pointset_descriptor(list(Y))[0] < 0.4 * descriptor(Y)[0]
    with pytest.raises(InputError, match="6 frames"):
        pointset_descriptor(list(X[:3]))


@pytest.mark.slow
def test_discrepancy_loop_on_video_tracks_finds_a_planted_sag(pillow, tmp_path):
    """A world with a planted sag (gravity), filmed by the contract's camera (200x150 RGB-D);
    `knockgs observe tracks` turns the frames into ID-free tracks (at least 20: its seeds are
    only where the object, not the basket's haze, makes the pixel, and a track that fails its
    forward-backward check is dropped) with its error estimate, which the loop takes as its
    noise; the loop, given only those, names gravity with its value and improves the held-out
    prediction of the held-out video.
    World and loop are the ci Pillow at 2 substeps per frame (dt = 1e-2 s, not 5e-3 s: its
    response moves by 0.5 %, every rollout takes half the time); the loop runs without the
    discretization term (data from its own model; tests/test_discrepancy_model_error.py), over
    two catalogue terms: the sag and velocity damping, its rival in what the tracks show (the
    competition of more terms is tests/test_discrepancy.py's), each fitted by 2 LM iterations in
    the attribution (the joint fit that sets the value by 5)."""
    # About 30 s on an idle 2-core machine: two 31-frame videos rendered and tracked, then a
    # loop of about 100 rollouts of the model.
    import dataclasses

    from knockgs_core.cli import main
    from knockgs_core.discrepancy import LoopSettings, read_measured, run_discrepancy
    from knockgs_core.rollout import run_rollout
    from knockgs_core.sim import Gravity, with_effects

    c, asset = pillow
    c = dataclasses.replace(c, sim=dataclasses.replace(c.sim, dt=c.probes["standard_x"].export.frame_dt / 2))
    theta, g = (0.7, 1.2), -0.3
    p = with_effects(c.sim, Gravity(g=g))
    tracks = {}
    for probe in ("standard_x", "standard_y"):
        ro = run_rollout(c, theta, probe, particles=asset.particles, export_F=True,
                         sim_overrides={"effects": p.effects, "boundaries": p.boundaries})
        write_rgbd(tmp_path / f"{probe}.npz", _render(pillow, ro.positions, ro.F, width=200, height=150))
        out = tmp_path / f"{probe}.parquet"
        assert main(["observe", "tracks", str(tmp_path / f"{probe}.npz"), "--object", "pillow", "--profile", "ci",
                     "--probe", probe, "-o", str(out)]) == 0
        tracks[probe] = read_measured(out)
        assert not tracks[probe].has_identity and tracks[probe].n_points >= 20
    res = run_discrepancy(tracks["standard_x"], c, asset.particles, heldout_probes=["standard_y"],
                          heldout_measured={"standard_y": tracks["standard_y"]},
                          settings=LoopSettings(catalogue=("damping", "gravity"), refine_iterations=2, joint_iterations=5,
                                                model_error_refine=None))
    assert res.identified == ["gravity"]
    assert res.effects[0]["value"] == pytest.approx(g, rel=0.1)
    m = res.metrics["standard_y"]
    assert m["after"]["traj_rmse"] * 2.0 <= m["before"]["traj_rmse"]


def test_observe_describe_writes_query_descriptors(tmp_path, capsys):
    import pandas as pd

    from knockgs_core.cli import main
    from knockgs_core.descriptors import FEATURE_NAMES
    from knockgs_core.discrepancy import Measurement, write_measured

    rng = np.random.default_rng(3)
    X = 1.0 + np.cumsum(rng.normal(0.0, 1e-3, size=(31, 40, 3)), axis=0)
    write_measured(tmp_path / "a.parquet", Measurement(points=X, frames=np.arange(31), times=None, particle=None,
                                                       track=np.arange(1, 41), meta={}, source="a"))
    assert main(["observe", "describe", f"target_x={tmp_path / 'a.parquet'}", "-o", str(tmp_path / "q.csv")]) == 0
    capsys.readouterr()
    q = pd.read_csv(tmp_path / "q.csv")
    assert list(q.columns) == ["case_name", *FEATURE_NAMES] and q["case_name"].tolist() == ["target_x"]
    np.testing.assert_allclose(q[list(FEATURE_NAMES)].to_numpy()[0], descriptor(X), rtol=1e-8)
    # a missing file: one line naming it, exit 2, no output written
    assert main(["observe", "describe", str(tmp_path / "missing.parquet"), "-o", str(tmp_path / "q2.csv")]) == 2
    err = capsys.readouterr().err
    assert "missing.parquet" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "q2.csv").exists()
