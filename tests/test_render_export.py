"""Per-frame deformed 3DGS export (``deformed_gaussians``) and the ``knockgs render`` CLI."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from knockgs_core.assets import GaussianSet, read_ply, write_ply
from knockgs_core.cli import main
from knockgs_core.render import (
    Camera,
    covariance_to_scale_rotation,
    deform_covariances,
    deformed_gaussians,
    deformed_scene,
    render,
)
from knockgs_core.rollout import Rollout, write_deformation, write_rollout


def random_gaussians(rng, n):
    return GaussianSet(
        means=rng.normal(1.0, 0.2, (n, 3)),
        scales=rng.uniform(0.01, 0.08, (n, 3)),
        quats=Rotation.random(n, random_state=int(rng.integers(2**31))).as_quat()[:, [3, 0, 1, 2]],
        opacities=rng.uniform(0.2, 0.95, n),
        sh_dc=rng.normal(0.0, 0.5, (n, 3)),
    )


def random_F(rng, n):
    return np.eye(3) + 0.3 * rng.normal(size=(n, 3, 3))


def test_covariance_round_trip():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(50, 3, 3))
    cov = A @ np.swapaxes(A, 1, 2) + 1e-3 * np.eye(3)
    scales, quats = covariance_to_scale_rotation(cov)
    back = GaussianSet(np.zeros((50, 3)), scales, quats, np.full(50, 0.5), np.zeros((50, 3))).covariances()
    np.testing.assert_allclose(back, cov, rtol=2e-5, atol=2e-5 * np.abs(cov).max())
    assert np.allclose(np.linalg.norm(quats, axis=1), 1.0)


def test_deformed_gaussians_move_only_simulated_rows():
    rng = np.random.default_rng(1)
    g = random_gaussians(rng, 30)
    static = np.zeros(30, bool)
    static[::3] = True
    idx = np.flatnonzero(~static)
    pos = np.concatenate([g.means[idx] + 0.05, rng.normal(size=(7, 3))])  # 7 fill particles after
    F = random_F(rng, idx.size)
    out = deformed_gaussians(g, idx, pos, F)
    np.testing.assert_allclose(out.means[idx], pos[: idx.size], atol=1e-6)
    np.testing.assert_array_equal(out.means[static], g.means[static])
    np.testing.assert_allclose(out.covariances()[static], g.covariances()[static], rtol=1e-6, atol=1e-12)
    want = deform_covariances(g.covariances()[idx], F)
    np.testing.assert_allclose(out.covariances()[idx], want, rtol=1e-4, atol=1e-4 * np.abs(want).max())
    # the exported frame renders like the in-memory deformed scene
    cam = Camera.look_at([1.0, -2.0, 1.5], [1.0, 1.0, 1.0], [0, 0, 1], fov_deg=45, width=40, height=30)
    ref = render(*deformed_scene(g.means, g.covariances(), g.colors(), g.opacities, pos[: idx.size], F, static), cam)
    got = render(out.means, out.covariances(), out.colors(), out.opacities, cam)
    assert np.abs(got.rgb - ref.rgb).max() < 1e-3 and ref.alpha.max() > 0.3


def test_deformed_gaussians_rejects_bad_index():
    rng = np.random.default_rng(2)
    g = random_gaussians(rng, 5)
    with pytest.raises(Exception, match="gaussian_index"):
        deformed_gaussians(g, np.array([0, 9]), np.zeros((2, 3)), np.tile(np.eye(3), (2, 1, 1)))


@pytest.fixture
def exported(tmp_path):
    rng = np.random.default_rng(3)
    g = random_gaussians(rng, 20)
    static = np.zeros(20, bool)
    static[:4] = True
    idx = np.flatnonzero(~static)
    write_ply(g, tmp_path / "obj.ply")
    np.savez(tmp_path / "obj.scene.npz", static_mask=static, gaussian_index=idx)
    T = 3
    pos = np.stack([np.concatenate([g.means[idx] + 0.01 * t, np.ones((5, 3))]) for t in range(T)]).astype(np.float32)
    F = np.stack([np.eye(3) + 0.1 * t * np.diag([1.0, -0.5, 0.2]) for t in range(T)])
    F = np.broadcast_to(F[:, None], (T, idx.size, 3, 3)).astype(np.float32)
    ro = Rollout(positions=pos, F=F, meta={"object": "synthetic"})
    write_rollout(tmp_path / "r.parquet", ro)
    write_deformation(tmp_path / "r.F.parquet", ro)
    return tmp_path, g, idx, pos, F


def test_cli_render_ply_writes_viewer_frames(exported):
    d, g, idx, pos, F = exported
    assert main(["render", "ply", "--asset", str(d / "obj.ply"), "--rollout", str(d / "r.parquet"), "--frames", "0,2",
                 "-o", str(d / "ply")]) == 0
    assert sorted(p.name for p in (d / "ply").iterdir()) == ["frame_0000.ply", "frame_0002.ply"]
    f2 = read_ply(d / "ply" / "frame_0002.ply")
    np.testing.assert_allclose(f2.means[idx], pos[2, : idx.size], atol=1e-6)
    want = deform_covariances(g.covariances()[idx], F[2])
    np.testing.assert_allclose(f2.covariances()[idx], want, rtol=1e-4, atol=1e-4 * np.abs(want).max())
    f0 = read_ply(d / "ply" / "frame_0000.ply")
    np.testing.assert_allclose(f0.covariances(), g.covariances(), rtol=1e-4, atol=1e-6)


def test_cli_render_errors_name_file_and_field(exported, capsys):
    d = exported[0]
    (d / "r.F.parquet").unlink()
    assert main(["render", "ply", "--asset", str(d / "obj.ply"), "--rollout", str(d / "r.parquet"), "-o", str(d / "x")]) == 2
    err = capsys.readouterr().err
    assert "r.F.parquet" in err and "--deformation" in err and "Traceback" not in err
    assert main(["render", "ply", "--asset", str(d / "obj.ply"), "--rollout", str(d / "r.parquet"),
                 "--deformation", str(d / "r.parquet"), "-o", str(d / "x")]) == 2
    assert "F00" in capsys.readouterr().err  # positions are not deformation gradients
    ro = Rollout(positions=exported[3], F=exported[4], meta={})
    write_deformation(d / "r.F.parquet", ro)
    assert main(["render", "ply", "--asset", str(d / "obj.ply"), "--rollout", str(d / "r.parquet"), "--frames", "7",
                 "-o", str(d / "x")]) == 2
    err = capsys.readouterr().err
    assert "frames" in err and "0..2" in err


def test_cli_render_frames_png(exported):
    from PIL import Image

    d = exported[0]
    args = ["render", "frames", "--asset", str(d / "obj.ply"), "--rollout", str(d / "r.parquet"), "--object", "pillow",
            "--profile", "ci", "--width", "32", "--height", "24", "--frames", "1", "-o", str(d / "png")]
    assert main(args) == 0
    img = Image.open(d / "png" / "frame_0001.png")
    assert img.size == (32, 24) and img.mode == "RGB"


def test_render_rollout_is_deformed_scene_per_frame(exported):
    # one way of moving Gaussians: the rollout renderer gives deformed_scene's frames exactly
    from knockgs_core.experiments import render_rollout

    d, g, idx, pos, F = exported
    static = np.ones(len(g), bool)
    static[idx] = False
    cam = Camera.look_at([1.0, -2.0, 1.5], [1.0, 1.0, 1.0], [0, 0, 1], fov_deg=45, width=24, height=20)
    rgb, alpha = render_rollout(g, static, idx, pos, F, cam)
    for t in range(pos.shape[0]):
        ref = render(*deformed_scene(g.means, g.covariances(), g.colors(), g.opacities, pos[t, : idx.size], F[t], static), cam)
        np.testing.assert_array_equal(rgb[t], ref.rgb)
        np.testing.assert_array_equal(alpha[t], ref.alpha)
    with pytest.raises(Exception, match="gaussian_index"):  # the scene's two fields must agree
        render_rollout(g, static, idx[::-1], pos, F, cam)


def test_scene_file_round_trip_and_checks(tmp_path):
    from knockgs_core.assets import load_scene, scene_path
    from knockgs_core.errors import InputError

    assert scene_path(tmp_path / "pillow.ply") == tmp_path / "pillow.scene.npz"
    static = np.array([True, False, False, True, False])
    np.savez_compressed(tmp_path / "a.scene.npz", static_mask=static, gaussian_index=np.flatnonzero(~static))
    mask, idx = load_scene(tmp_path / "a.scene.npz", n_gaussians=5)
    assert mask.tolist() == static.tolist() and idx.tolist() == [1, 2, 4]
    with pytest.raises(InputError, match="static_mask"):
        load_scene(tmp_path / "a.scene.npz", n_gaussians=6)
    np.savez(tmp_path / "b.scene.npz", static_mask=static, gaussian_index=np.array([1, 2]))
    with pytest.raises(InputError, match="b.scene.npz.*gaussian_index"):
        load_scene(tmp_path / "b.scene.npz")
    with pytest.raises(InputError, match="asset make --normalized"):
        load_scene(tmp_path / "missing.scene.npz")
