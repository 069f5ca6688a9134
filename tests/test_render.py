"""Tests of knockgs_core.render: the Warp rasterizer against a NumPy reference and
against closed-form single-Gaussian images."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from knockgs_core.errors import InputError
from knockgs_core.render import (
    TILE_SIZE,
    Camera,
    bin_tiles,
    deform_covariances,
    deformed_scene,
    project,
    rasterize,
    render,
    render_frames,
    render_reference,
)

TOL = 1e-4  # Warp (float32) vs reference (float64), max abs per pixel


def random_scene(rng, n=40, *, scale=(0.03, 0.3), opacity=(0.02, 1.0)):
    """``n`` anisotropic Gaussians around the origin: means [n, 3], covariances [n, 3, 3], ..."""
    means = rng.normal(0.0, 0.5, (n, 3))
    rot = Rotation.random(n, random_state=int(rng.integers(2**31))).as_matrix()
    s = rng.uniform(*scale, (n, 3))
    cov = np.einsum("nij,nj,nkj->nik", rot, s**2, rot)
    return means, cov, rng.uniform(0.0, 1.0, (n, 3)), rng.uniform(*opacity, n)


def axis_camera(width, height, f, cx, cy):
    """Camera at the world origin looking down +z (world_to_camera = identity)."""
    return Camera(width=width, height=height, fx=f, fy=f, cx=cx, cy=cy, world_to_camera=np.eye(4))


CAMERAS = {
    "front_48x40": lambda: Camera.look_at([0.2, -0.1, -3.0], [0, 0, 0], [0, -1, 0], fov_deg=50, width=48, height=40),
    "oblique_37x29": lambda: Camera.look_at([2.0, 1.5, 1.8], [0.1, 0, 0], [0, 0, 1], fov_deg=60, width=37, height=29),
    "close_off_centre_50x33": lambda: Camera(
        width=50, height=33, fx=40.0, fy=46.0, cx=21.3, cy=18.9,
        world_to_camera=np.block([[Rotation.from_euler("xyz", [0.3, -0.2, 0.1]).as_matrix(),
                                   np.array([[0.1], [0.0], [1.2]])], [np.zeros((1, 3)), np.ones((1, 1))]]),
    ),
}


def assert_matches_reference(scene, camera, background=(1.0, 1.0, 1.0)):
    fast = render(*scene, camera, background=background)
    ref = render_reference(*scene, camera, background=background)
    assert fast.rgb.shape == (camera.height, camera.width, 3) and fast.rgb.dtype == np.float32
    assert fast.depth.shape == fast.alpha.shape == (camera.height, camera.width)
    for name in ("rgb", "depth", "alpha"):
        err = np.abs(getattr(fast, name) - getattr(ref, name)).max()
        assert err < TOL, f"{name}: max abs difference {err:.3g}"
    return fast, ref


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("camera_name", sorted(CAMERAS))
def test_warp_matches_reference_on_random_scenes(seed, camera_name):
    rng = np.random.default_rng(seed)
    scene = random_scene(rng)
    camera = CAMERAS[camera_name]()
    bg = tuple(rng.uniform(0, 1, 3))
    fast, ref = assert_matches_reference(scene, camera, background=bg)
    assert ref.alpha.max() > 0.5  # the scene is in view


def test_warp_matches_reference_with_early_termination():
    rng = np.random.default_rng(7)
    scene = random_scene(rng, n=40, scale=(0.2, 0.5), opacity=(0.8, 1.0))
    camera = CAMERAS["front_48x40"]()
    _, ref = assert_matches_reference(scene, camera, background=(0.2, 0.4, 0.6))
    # Many pixels saturate: compositing stopped there before T < 1e-4.
    assert (ref.alpha > 0.999).sum() > 100


def test_culled_gaussians_match_reference():
    rng = np.random.default_rng(3)
    means, cov, colors, opac = random_scene(rng, n=40)
    camera = axis_camera(48, 40, 40.0, 24.0, 20.0)
    means[:, 2] += 2.0
    means[0] = [0.0, 0.0, -1.0]  # behind the camera
    means[1] = [0.0, 0.0, 0.005]  # in front of the near plane z = 0.01
    means[2] = [5.0, 0.0, 1.0]  # far outside the field of view (clamped Jacobian)
    means[3] = [0.0, 0.0, 0.02]  # just past the near plane: covers the whole image
    cov[3] = 1e-6 * np.eye(3)
    opac[4] = 0.5 / 255  # below the 1/255 alpha cut everywhere
    proj = project(means, cov, opac, camera)
    assert not proj.visible[[0, 1, 4]].any()
    assert proj.visible[[2, 3]].all()
    assert_matches_reference((means, cov, colors, opac), camera)


def test_equal_depths_composite_in_index_order():
    # Two overlapping Gaussians at the same depth: ties go to the lower index first,
    # in the tiled path as in the reference, and the order visibly matters.
    camera = axis_camera(40, 36, 50.0, 20.0, 18.0)
    means = np.array([[-0.05, 0.0, 2.0], [0.05, 0.0, 2.0]])
    cov = np.stack([0.15**2 * np.eye(3)] * 2)
    colors = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    opac = np.array([0.9, 0.9])
    a, _ = assert_matches_reference((means, cov, colors, opac), camera)
    b, _ = assert_matches_reference((means[::-1], cov, colors[::-1], opac), camera)
    centre = a.rgb[18, 20]
    assert centre[0] > centre[2]  # red (index 0) in front
    assert b.rgb[18, 20][2] > b.rgb[18, 20][0]


@pytest.mark.parametrize("sigma,z,o", [(0.05, 2.0, 0.8), (0.01, 1.5, 0.6)])
def test_single_isotropic_gaussian_alpha_is_analytic(sigma, z, o):
    # On the optical axis J = diag(f/z, f/z): Sigma_2D = ((f sigma / z)^2 + 0.3) I.
    f = 60.0
    camera = axis_camera(49, 41, f, 24.5, 20.5)  # Gaussian centre on pixel (20, 24)'s centre
    means, cov = np.array([[0.0, 0.0, z]]), sigma**2 * np.eye(3)[None]
    out = render(means, cov, np.array([[0.3, 0.6, 0.9]]), np.array([o]), camera)
    s2 = (f * sigma / z) ** 2 + 0.3
    proj = project(means, cov, np.array([o]), camera)
    np.testing.assert_allclose(proj.covs2d[0], [s2, 0.0, s2], rtol=1e-5, atol=1e-6)
    for dr, dc in [(0, 0), (0, 1), (2, 0), (-3, 0), (3, 4), (0, -5)]:
        expected = o * math.exp(-0.5 * (dr * dr + dc * dc) / s2)
        if expected < 1 / 255:
            expected = 0.0  # below the alpha cut
        assert out.alpha[20 + dr, 24 + dc] == pytest.approx(expected, abs=1e-5), (dr, dc)


def test_single_gaussian_depth_and_colour():
    z, o = 2.5, 0.95
    camera = axis_camera(40, 40, 50.0, 20.0, 20.0)
    colour, bg = np.array([0.3, 0.6, 0.9]), np.array([0.1, 0.2, 0.0])
    # centre at (u, v) = (22.5, 19.5): the centre of pixel (19, 22)
    out = render([[0.125, -0.025, z]], 0.1**2 * np.eye(3)[None], colour[None], [o], camera, background=bg)
    assert out.alpha[19, 22] == pytest.approx(o, abs=1e-6)
    np.testing.assert_allclose(out.depth, z * out.alpha, atol=1e-5)
    np.testing.assert_allclose(out.rgb, out.alpha[..., None] * colour + (1 - out.alpha[..., None]) * bg, atol=1e-5)


def test_compositing_stops_before_transmittance_below_1e_4():
    # Five wide Gaussians stacked on the axis, opacity 0.95 each: at the centre pixel
    # T = 0.05, 0.0025, 1.25e-4; the fourth would take T to 6.25e-6 < 1e-4, so it and
    # the fifth are not added.
    camera = axis_camera(17, 17, 30.0, 8.5, 8.5)
    n = 5
    means = np.array([[0.0, 0.0, 1.0 + 0.1 * i] for i in range(n)])
    cov = np.stack([np.eye(3)] * n)
    colors = np.zeros((n, 3))
    colors[3] = [1.0, 1.0, 1.0]
    colors[0] = [0.0, 0.0, 1.0]
    out = render(means, cov, colors, np.full(n, 0.95), camera, background=(0, 0, 0))
    centre = out.rgb[8, 8]
    assert centre[0] == pytest.approx(0.0, abs=1e-7)  # the fourth (white) Gaussian never added
    assert centre[2] == pytest.approx(0.95, abs=1e-6)
    assert out.alpha[8, 8] == pytest.approx(1 - 0.05**3, abs=1e-6)


def test_empty_scene_is_background():
    camera = axis_camera(20, 18, 20.0, 10.0, 9.0)
    out = render(np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros(0), camera,
                 background=(0.25, 0.5, 0.75))
    np.testing.assert_array_equal(out.rgb, np.broadcast_to([0.25, 0.5, 0.75], (18, 20, 3)))
    assert not out.alpha.any() and not out.depth.any()


def test_bin_tiles_lists_overlapped_tiles_in_depth_order():
    camera = axis_camera(50, 40, 50.0, 0.0, 0.0)  # u = 50 x / z, v = 50 y / z
    # Gaussian 0: tiny, at pixel (u, v) = (24, 8): tile (tx, ty) = (1, 0) only.
    # Gaussian 1: wide, nearer, centred on the image: several tiles. Gaussian 2: behind.
    means = np.array([[0.96, 0.32, 2.0], [0.5, 0.4, 1.0], [0.0, 0.0, -1.0]])
    cov = np.stack([1e-8 * np.eye(3), 0.05**2 * np.eye(3), np.eye(3)])
    proj = project(means, cov, np.ones(3), camera)
    bins = bin_tiles(proj, 50, 40)
    assert (bins.tiles_x, bins.tiles_y) == (4, 3) and bins.tile_size == TILE_SIZE
    lists = {t: bins.gaussian_ids[s:e].tolist() for t, (s, e) in enumerate(bins.tile_ranges)}
    assert 2 not in bins.gaussian_ids
    assert [t for t, ids in lists.items() if 0 in ids] == [1]
    tiles_of_1 = [t for t, ids in lists.items() if 1 in ids]
    assert len(tiles_of_1) >= 4
    assert lists[1] == [1, 0]  # front to back: the nearer wide Gaussian first
    assert bins.tile_ranges[-1, 1] == bins.gaussian_ids.size


def test_rasterize_uses_the_binned_lists_only():
    # Dropping a tile's list removes that tile's content: the per-pixel kernel reads bins.
    rng = np.random.default_rng(4)
    scene = random_scene(rng)
    camera = CAMERAS["front_48x40"]()
    proj = project(scene[0], scene[1], scene[3], camera)
    bins = bin_tiles(proj, camera.width, camera.height)
    full = rasterize(proj, scene[2], scene[3], bins)
    ranges = bins.tile_ranges.copy()
    ranges[0, 1] = ranges[0, 0]
    cut = rasterize(proj, scene[2], scene[3], type(bins)(bins.gaussian_ids, ranges, bins.width, bins.height, bins.tile_size))
    assert full.alpha[:16, :16].max() > 0.1
    assert not cut.alpha[:16, :16].any()
    np.testing.assert_array_equal(cut.rgb[16:], full.rgb[16:])


@pytest.mark.parametrize("tile_size", [1, 2, 4, 7, 8, 32])
def test_tile_size_changes_work_not_pixels(tile_size):
    # Binning is conservative at every tile edge: each pixel composites the same Gaussians in
    # the same depth order, so the image is identical (the CPU path uses small tiles).
    rng = np.random.default_rng(11)
    scene = random_scene(rng, n=60)
    camera = CAMERAS["oblique_37x29"]()
    proj = project(scene[0], scene[1], scene[3], camera)
    ref = rasterize(proj, scene[2], scene[3], bin_tiles(proj, camera.width, camera.height, tile_size=16))
    out = rasterize(proj, scene[2], scene[3], bin_tiles(proj, camera.width, camera.height, tile_size=tile_size))
    for name in ("rgb", "depth", "alpha"):
        np.testing.assert_array_equal(getattr(out, name), getattr(ref, name))
    assert ref.alpha.max() > 0.5


def test_cpu_tile_edge_follows_the_scene_size():
    import warp as wp

    from knockgs_core.render._constants import CPU_LARGE_SCENE, TILE_SIZE, tile_size_for

    cpu = wp.get_device("cpu")
    assert tile_size_for(cpu, 0) == 4 and tile_size_for(cpu, CPU_LARGE_SCENE - 1) == 4
    assert tile_size_for(cpu, CPU_LARGE_SCENE) == 8
    cuda_like = type("D", (), {"is_cpu": False})()
    assert tile_size_for(cuda_like, 10**6) == TILE_SIZE


@pytest.mark.parametrize("tile_size", [1, 4, 16])
@pytest.mark.parametrize("camera_name", sorted(CAMERAS))
def test_device_binning_gives_the_host_lists(camera_name, tile_size):
    # The device path (radix sorts, used on CUDA) must give the host sort's lists exactly,
    # ties included: a third of the Gaussians share one depth.
    rng = np.random.default_rng(12)
    means, cov, _, opac = random_scene(rng, n=300)
    camera = CAMERAS[camera_name]()
    proj = project(means, cov, opac, camera)
    depths = proj.depths.copy()
    depths[::3] = np.median(depths)
    proj = type(proj)(proj.means2d, proj.conics, proj.covs2d, depths, proj.radii)
    host = bin_tiles(proj, camera.width, camera.height, tile_size=tile_size)
    dev = bin_tiles(proj, camera.width, camera.height, tile_size=tile_size, device="cpu")
    assert host.gaussian_ids.size > 300
    np.testing.assert_array_equal(dev.gaussian_ids, host.gaussian_ids)
    np.testing.assert_array_equal(dev.tile_ranges, host.tile_ranges)


def test_device_binning_with_nothing_visible():
    camera = CAMERAS["front_48x40"]()
    proj = project(np.array([[0.0, 0.0, 10.0]]), np.eye(3)[None] * 1e-4, np.array([0.001]), camera)  # below 1/255
    dev = bin_tiles(proj, camera.width, camera.height, device="cpu")
    assert dev.gaussian_ids.size == 0 and not dev.tile_ranges.any()


def test_look_at_camera_conventions():
    cam = Camera.look_at([0, 0, 5], [0, 0, 0], [0, 1, 0], fov_deg=90, width=64, height=48)
    R = cam.rotation
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    assert cam.fx == cam.fy == pytest.approx(24.0)  # (H / 2) / tan(45 deg)
    assert (cam.cx, cam.cy) == (32.0, 24.0)
    target_cam = cam.world_to_camera @ [0, 0, 0, 1]
    np.testing.assert_allclose(target_cam[:3], [0, 0, 5], atol=1e-12)  # on the axis, z forward
    up_point = cam.world_to_camera @ [0, 1, 0, 1]
    assert up_point[1] < 0  # world up is image up (y down)
    right_point = cam.world_to_camera @ [1, 0, 0, 1]  # looking down -z with y up: +x is right
    assert right_point[0] > 0


def test_deform_identity_leaves_image_unchanged():
    rng = np.random.default_rng(5)
    means, cov, colors, opac = random_scene(rng)
    camera = CAMERAS["front_48x40"]()
    F = np.broadcast_to(np.eye(3), (40, 3, 3))
    np.testing.assert_array_equal(deform_covariances(cov, F), cov)
    scene = deformed_scene(means, cov, colors, opac, means, F, np.zeros(40, bool))
    np.testing.assert_array_equal(render(*scene, camera).rgb, render(means, cov, colors, opac, camera).rgb)


def test_deform_2i_quadruples_covariance_and_widens_splat():
    rng = np.random.default_rng(6)
    cov = random_scene(rng, n=5)[1]
    F = np.broadcast_to(2 * np.eye(3), (5, 3, 3))
    np.testing.assert_allclose(deform_covariances(cov, F), 4 * cov, rtol=1e-14)
    shear = np.eye(3) + np.array([[0, 0.5, 0], [0, 0, 0], [0, 0, 0]])
    np.testing.assert_allclose(deform_covariances(cov[:1], shear[None])[0], shear @ cov[0] @ shear.T)
    # Rendered: the on-axis splat variance becomes 4 (f sigma / z)^2 + 0.3.
    f, sigma, z = 60.0, 0.03, 2.0
    camera = axis_camera(49, 41, f, 24.5, 20.5)
    scene = deformed_scene([[0, 0, z]], sigma**2 * np.eye(3)[None], [[1, 1, 1]], [0.9],
                           [[0, 0, z]], 2 * np.eye(3)[None], np.array([False]))
    out = render(*scene, camera)
    s2 = 4 * (f * sigma / z) ** 2 + 0.3
    assert out.alpha[20, 27] == pytest.approx(0.9 * math.exp(-0.5 * 9 / s2), abs=1e-5)


def test_deformed_scene_moves_only_simulated_gaussians():
    rng = np.random.default_rng(8)
    means, cov, colors, opac = random_scene(rng, n=6)
    static = np.array([True, False, False, True, False, False])
    pos = rng.normal(size=(4, 3))
    F = np.eye(3) + 0.1 * rng.normal(size=(4, 3, 3))
    scene = deformed_scene(means, cov, colors, opac, pos, F, static)
    np.testing.assert_array_equal(scene.means[static], means[static])
    np.testing.assert_array_equal(scene.covariances[static], cov[static])
    np.testing.assert_array_equal(scene.means[~static], pos)
    np.testing.assert_allclose(scene.covariances[~static], F @ cov[~static] @ np.swapaxes(F, 1, 2))
    # One row per Gaussian is accepted too; static rows are ignored.
    full_pos = np.full((6, 3), 99.0)
    full_pos[~static] = pos
    full_F = np.broadcast_to(7 * np.eye(3), (6, 3, 3)).copy()
    full_F[~static] = F
    again = deformed_scene(means, cov, colors, opac, full_pos, full_F, static)
    np.testing.assert_array_equal(again.means, scene.means)
    np.testing.assert_array_equal(again.covariances, scene.covariances)
    with pytest.raises(InputError, match="positions_t"):
        deformed_scene(means, cov, colors, opac, pos[:3], F[:3], static)
    with pytest.raises(InputError, match="static_mask"):
        deformed_scene(means, cov, colors, opac, pos, F, static.astype(int))


@pytest.mark.parametrize(
    "change,field",
    [
        (lambda s: (s[0][:, :2],) + s[1:], "means"),
        (lambda s: (s[0], s[1][:-1]) + s[2:], "covariances"),
        (lambda s: (s[0], s[1][:, :2]) + s[2:], "covariances"),
        (lambda s: s[:2] + (s[2] * 2,) + s[3:], "colors"),
        (lambda s: s[:3] + (s[3][:, None],), "opacities"),
        (lambda s: s[:3] + (s[3] + 1,), "opacities"),
        (lambda s: (np.where(np.arange(3)[None] == 0, np.nan, s[0]),) + s[1:], "means"),
    ],
)
def test_shape_and_value_errors_name_the_field(change, field):
    scene = random_scene(np.random.default_rng(0), n=4)
    camera = CAMERAS["front_48x40"]()
    with pytest.raises(InputError) as info:
        render(*change(scene), camera)
    assert info.value.field == field
    with pytest.raises(InputError) as info:
        render_reference(*change(scene), camera)
    assert info.value.field == field


def test_camera_and_option_errors():
    scene = random_scene(np.random.default_rng(0), n=4)
    with pytest.raises(InputError, match="camera"):
        render(*scene, "not a camera")
    with pytest.raises(InputError, match="background"):
        render(*scene, CAMERAS["front_48x40"](), background=(1, 1))
    with pytest.raises(InputError, match="device"):
        render(*scene, CAMERAS["front_48x40"](), device="no-such-device")
    with pytest.raises(InputError, match="width"):
        Camera(width=0, height=4, fx=1, fy=1, cx=0, cy=0, world_to_camera=np.eye(4))
    with pytest.raises(InputError, match="world_to_camera"):
        Camera(width=4, height=4, fx=1, fy=1, cx=0, cy=0, world_to_camera=np.eye(3))
    with pytest.raises(InputError, match="up"):
        Camera.look_at([0, 0, 1], [0, 0, 0], [0, 0, 2], fov_deg=40, width=8, height=8)
    with pytest.raises(InputError, match="cov0"):
        deform_covariances(np.eye(3), np.eye(3)[None])


def test_an_unavailable_cuda_device_is_a_one_line_error():
    from knockgs_core._warp import warp_device

    with pytest.raises(InputError) as err:
        warp_device("cuda:99")
    assert "'cuda:99'" in str(err.value) and "\n" not in str(err.value)


def test_a_cpu_run_prints_no_warp_message():
    # Warp's native "no CUDA driver" warning and its banner are kept out of CPU runs (knockgs_core._warp)
    import subprocess
    import sys

    code = ("import numpy as np; from knockgs_core.sim import SimParams, build_model; "
            "from knockgs_core.render import Camera, render; "
            "build_model(np.full((8, 3), 1.0, np.float32), E=1e4, nu=0.3, rho=1e3, params=SimParams(n_grid=16, dt=1e-4)); "
            "cam = Camera.look_at([0, -3, 0], [0, 0, 0], [0, 0, 1], fov_deg=40, width=8, height=8); "
            "render([[0, 0, 0]], [np.eye(3) * 0.01], [[1, 0, 0]], [0.5], cam)")
    env = {k: v for k, v in __import__("os").environ.items() if k != "KNOCKGS_DEVICE"}
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout == "" and proc.stderr == ""


def test_render_frames_equals_rendering_each_deformed_scene():
    """A motion rendered with its rest scene checked once gives the pixels of rendering each
    frame's deformed scene, bit for bit (float32 or float64 motion; positions and F with a row
    per simulated Gaussian or per Gaussian); a non-finite frame is named."""
    rng = np.random.default_rng(12)
    means, cov, colors, opac = random_scene(rng, n=50)
    means = means + [0.0, 0.0, 3.0]
    static = rng.uniform(size=50) < 0.3
    m = int((~static).sum())
    T = 3
    pos = (means[~static][None] + 0.05 * rng.normal(size=(T, m, 3))).astype(np.float32)
    F = (np.eye(3) + 0.2 * rng.normal(size=(T, m, 3, 3))).astype(np.float32)
    camera = axis_camera(33, 27, 30.0, 16.5, 13.5)
    frames = render_frames(means, cov, colors, opac, static, pos, F, camera)
    assert len(frames) == T
    for t in range(T):
        ref = render(*deformed_scene(means, cov, colors, opac, pos[t], F[t], static), camera)
        for name in ("rgb", "depth", "alpha"):
            np.testing.assert_array_equal(getattr(frames[t], name), getattr(ref, name))
    assert frames[1].alpha.max() > 0.3 and not np.array_equal(frames[0].rgb, frames[1].rgb)
    full_pos = np.zeros((T, 50, 3))
    full_pos[:, ~static] = pos
    full_F = np.broadcast_to(np.eye(3), (T, 50, 3, 3)).copy()
    full_F[:, ~static] = F
    again = render_frames(means, cov, colors, opac, static, full_pos, full_F, camera)
    np.testing.assert_array_equal(again[2].rgb, frames[2].rgb)
    F[1, 0, 0, 0] = np.nan
    with pytest.raises(InputError, match=r"render_frames.*F\[1\].*NaN"):
        render_frames(means, cov, colors, opac, static, pos, F, camera)
    with pytest.raises(InputError, match="positions"):
        render_frames(means, cov, colors, opac, static, pos[:, :-1], F, camera)


def test_device_deformation_gives_the_host_float64_bits():
    """The deformation kernel's float64 ``0.5 (C + C^T)``, ``C = F Sigma_0 F^T``, equals the host
    ``_deform`` then symmetrization bit for bit (same summation order, no FMA), over a wide
    range of magnitudes; and ``_deform`` is ``F Sigma_0 F^T`` to 2e-16 relative."""
    import warp as wp

    from knockgs_core.render._deform import _deform
    from knockgs_core.render._kernels import EXACT_FP, deformed_covariance

    @wp.kernel(module="unique", module_options=EXACT_FP)
    def deform_f64(F: wp.array(dtype=wp.mat33d), cov0: wp.array(dtype=wp.mat33d), out: wp.array(dtype=wp.mat33d)):
        i = wp.tid()
        out[i] = deformed_covariance(F[i], cov0[i])

    rng = np.random.default_rng(21)
    n = 20_000
    A = rng.normal(size=(n, 3, 3)) * 10.0 ** rng.uniform(-4, 1, (n, 1, 1))
    cov0 = A @ np.swapaxes(A, 1, 2) + rng.normal(0.0, 1e-9, (n, 3, 3))  # not exactly symmetric
    F = np.eye(3) + 0.5 * rng.normal(size=(n, 3, 3)) * 10.0 ** rng.uniform(-3, 1, (n, 1, 1))
    out = wp.zeros(n, dtype=wp.mat33d, device="cpu")
    wp.launch(deform_f64, dim=n, inputs=[wp.array(F, dtype=wp.mat33d, device="cpu"),
                                         wp.array(cov0, dtype=wp.mat33d, device="cpu")], outputs=[out], device="cpu")
    c = _deform(cov0, F)
    np.testing.assert_array_equal(out.numpy(), 0.5 * (c + np.swapaxes(c, 1, 2)))
    want = np.einsum("nij,njk,nlk->nil", F, cov0, F)
    assert np.abs(c - want).max() <= 2e-15 * np.abs(want).max(axis=(1, 2)).max()
    np.testing.assert_allclose(c, want, rtol=1e-12, atol=1e-14 * np.abs(want).max())


@pytest.mark.parametrize("layout", ["simulated", "all"])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_render_frames_scene_buffers_equal_the_host_scene(layout, dtype):
    """The device-resident scene of ``render_frames``, after each frame's kernel update, holds
    exactly ``deformed_scene``'s centres and symmetrized covariances in float32 (what ``render``
    gives ``project``), static and simulated rows mixed, float32 or float64 motion (float64 F is
    copied in float64: its low bits reach the covariances)."""
    from knockgs_core._warp import warp_device
    from knockgs_core.render._deform import _DeviceScene, _frame_dtype

    rng = np.random.default_rng(31)
    n = 300
    means, cov, colors, opac = random_scene(rng, n=n)
    static = rng.uniform(size=n) < 0.4
    dyn = np.flatnonzero(~static)
    m = dyn.size
    T = 3
    pos = (means[dyn][None] + 0.1 * rng.normal(size=(T, m, 3))).astype(dtype)
    F = (np.eye(3) + 0.4 * rng.normal(size=(T, m, 3, 3))).astype(dtype)
    if layout == "all":
        P, G = np.full((T, n, 3), np.nan, dtype), np.full((T, n, 3, 3), np.inf, dtype)  # static rows ignored
        P[:, dyn], G[:, dyn] = pos, F
    else:
        P, G = pos, F
    rows = dyn if layout == "all" else slice(None)
    scene = _DeviceScene(means, cov, colors, opac, dyn, wide=_frame_dtype(G) == np.float64, dev=warp_device("cpu"))
    for t in range(T):
        scene.set_frame(P[t][rows], G[t][rows])
        ref = deformed_scene(means, cov, colors, opac, pos[t], F[t], static)
        np.testing.assert_array_equal(scene.means.numpy(), ref.means.astype(np.float32))
        sym = 0.5 * (ref.covariances + np.swapaxes(ref.covariances, 1, 2))
        np.testing.assert_array_equal(scene.covariances.numpy(), sym.astype(np.float32))
    np.testing.assert_array_equal(scene.colors.numpy(), colors.astype(np.float32))
    np.testing.assert_array_equal(scene.opacities.numpy(), opac.astype(np.float32))
    if dtype is np.float64:  # a float32 copy of F would have lost these bits
        F32 = F[-1].astype(np.float32).astype(np.float64)
        c32 = deformed_scene(means, cov, colors, opac, pos[-1], F32, static).covariances[dyn]
        assert not np.array_equal(scene.covariances.numpy()[dyn], (0.5 * (c32 + np.swapaxes(c32, 1, 2))).astype(np.float32))
    frames = render_frames(means + [0.0, 0.0, 3.0], cov, colors, opac, static, P + np.array([0.0, 0.0, 3.0], dtype), G,
                           axis_camera(30, 24, 28.0, 15.0, 12.0))
    for t in range(T):
        ref = render(*deformed_scene(means + [0.0, 0.0, 3.0], cov, colors, opac, pos[t] + np.array([0.0, 0.0, 3.0], dtype),
                                     F[t], static), axis_camera(30, 24, 28.0, 15.0, 12.0))
        for name in ("rgb", "depth", "alpha"):
            np.testing.assert_array_equal(getattr(frames[t], name), getattr(ref, name))
    assert frames[0].alpha.max() > 0.3


def test_render_frames_all_static_all_simulated_and_bad_frames():
    """No simulated Gaussians (the rest scene every frame), every Gaussian simulated, an empty
    scene, and a non-finite position named with its frame."""
    rng = np.random.default_rng(41)
    means, cov, colors, opac = random_scene(rng, n=30)
    means = means + [0.0, 0.0, 3.0]
    camera = axis_camera(26, 20, 24.0, 13.0, 10.0)
    rest = render(means, cov, colors, opac, camera)
    frames = render_frames(means, cov, colors, opac, np.ones(30, bool), np.zeros((2, 0, 3)), np.zeros((2, 0, 3, 3)), camera)
    assert len(frames) == 2 and all(np.array_equal(f.rgb, rest.rgb) for f in frames)
    pos = means[None] + 0.05 * rng.normal(size=(2, 30, 3))
    F = np.eye(3) + 0.3 * rng.normal(size=(2, 30, 3, 3))
    frames = render_frames(means, cov, colors, opac, np.zeros(30, bool), pos, F, camera)
    for t in range(2):
        ref = render(*deformed_scene(means, cov, colors, opac, pos[t], F[t], np.zeros(30, bool)), camera)
        np.testing.assert_array_equal(frames[t].rgb, ref.rgb)
    empty = render_frames(np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0, bool),
                          np.zeros((2, 0, 3)), np.zeros((2, 0, 3, 3)), camera)
    assert len(empty) == 2 and np.all(empty[1].rgb == 1.0)
    assert render_frames(means, cov, colors, opac, np.zeros(30, bool), pos[:0], F[:0], camera) == []
    pos[1, 4, 2] = np.inf
    with pytest.raises(InputError, match=r"render_frames.*positions\[1\].*NaN or infinite"):
        render_frames(means, cov, colors, opac, np.zeros(30, bool), pos.astype(np.float32), F, camera)


def test_cuda_build_of_the_deformation_kernel_has_no_fma(tmp_path):
    """On CUDA the deformation must round as the host does: its PTX (sm_90, built with NVRTC, no
    GPU needed) has separately rounded float64 products and sums and no fused multiply-add,
    which NVRTC would otherwise emit (``EXACT_FP``)."""
    import pathlib

    import warp as wp

    from knockgs_core.render._kernels import deform_rows_kernel

    for dtype in (wp.float32, wp.float64):
        wp.overload(deform_rows_kernel, {"frame": wp.array2d(dtype=dtype)})
    try:
        wp.compile_aot_module(deform_rows_kernel.module, arch=90, use_ptx=True, module_dir=tmp_path)
    except Exception as exc:  # a Warp build without NVRTC
        pytest.skip(f"no CUDA compiler in this Warp build ({exc})")
    ptx = "".join(p.read_text() for p in pathlib.Path(tmp_path).rglob("*.ptx"))
    assert ptx.count("mul.rn.f64") >= 2 * 54 and "fma.rn.f64" not in ptx


def resident_motion(rng):
    """A motion for the device-resident frame path: 200 Gaussians at 40x30 px, ``(means, cov,
    colors, opac, static, positions [5, M, 3], F [5, M, 3, 3], camera, tie_rows)``.

    The 30 static Gaussians are never visible (opacity below 1/255, or at rest behind the
    camera). Among the simulated ones, six overlapping ones (``tie_rows``) share one depth in
    frames 0, 1, 3 and 4, so their index order shows in the pixels. Frame 1 puts 25 simulated
    Gaussians behind the camera and 3 in front of the near plane; frame 2 puts all of them behind
    the camera (nothing visible); frame 3 triples every simulated Gaussian's extent (more tile
    pairs than the frames before)."""
    n, T = 200, 5
    means, cov, colors, opac = random_scene(rng, n=n, scale=(0.02, 0.15), opacity=(0.3, 1.0))
    means = means + [0.0, 0.0, 3.0]
    static = np.zeros(n, bool)
    static[:30] = True
    opac[:15] = rng.uniform(0.0, 0.9 / 255, 15)  # below the 1/255 alpha cut
    means[15:30, 2] = -2.0  # behind the camera
    dyn = np.flatnonzero(~static)
    tie_rows = dyn[10:16]
    means[tie_rows] = np.stack([np.linspace(-0.3, 0.3, 6), np.zeros(6), np.full(6, 2.5)], axis=1)
    cov[tie_rows] = 0.12**2 * np.eye(3)
    colors[tie_rows] = np.eye(3)[np.arange(6) % 3]
    opac[tie_rows] = 0.8
    m = dyn.size
    pos = np.repeat(means[dyn][None], T, axis=0) + 0.02 * rng.normal(size=(T, m, 3))
    F = np.eye(3) + 0.1 * rng.normal(size=(T, m, 3, 3))
    pos[:, 10:16] = means[tie_rows]  # the tie group keeps its common depth
    F[:, 10:16] = np.eye(3)
    pos[1, 20:45, 2] = -1.0
    pos[1, 45:48, 2] = 0.005
    pos[2, :, 2] = -1.0
    F[3] *= 3.0
    camera = axis_camera(40, 30, 30.0, 20.0, 15.0)
    return means, cov, colors, opac, static, pos.astype(np.float32), F.astype(np.float32), camera, tie_rows


def test_device_resident_frames_equal_the_host_binned_frames(monkeypatch):
    """The device-resident frame path (projection, visible compaction, depth and tile sorts and
    the rasterizer's inputs kept in Warp arrays; the default on CUDA), forced on the CPU, gives
    the frames of the host-binned path (the CPU default) bit for bit: Gaussians culled behind the
    camera, in front of the near plane or by opacity, a frame with nothing visible, and a group
    of equal-depth Gaussians whose index order shows in the pixels (a compaction that reordered
    the visible Gaussians would change them)."""
    from knockgs_core.render import _frame
    from knockgs_core.render._deform import _render_frames

    rng = np.random.default_rng(51)
    means, cov, colors, opac, static, pos, F, camera, tie_rows = resident_motion(rng)
    args = (means, cov, colors, opac, static, pos, F, camera)
    bg = (0.2, 0.5, 0.9)
    host = _render_frames(*args, background=bg, device="cpu", resident=False)
    resident = _render_frames(*args, background=bg, device="cpu", resident=True)
    monkeypatch.setattr(_frame, "DeviceFrames", None)  # not used on the CPU unless asked for
    assert len(host) == len(resident) == 5
    for t, (a, b) in enumerate(zip(host, resident)):
        for name in ("rgb", "depth", "alpha"):
            x, y = getattr(a, name), getattr(b, name)
            assert x.dtype == y.dtype == np.float32 and x.shape == y.shape
            assert np.array_equal(x, y), f"frame {t}: {name} differs"
    default = render_frames(*args, background=bg)  # the CPU default: the host path, no DeviceFrames
    assert all(np.array_equal(a.rgb, b.rgb) and np.array_equal(a.alpha, b.alpha) for a, b in zip(host, default))
    dyn = np.flatnonzero(~static)
    scenes = [deformed_scene(means, cov, colors, opac, pos[t], F[t], static) for t in range(5)]
    visible = [int(project(s.means, s.covariances, s.opacities, camera).visible.sum()) for s in scenes]
    assert visible[0] == dyn.size and visible[1] == dyn.size - 28 and visible[2] == 0 and visible[3] == dyn.size
    assert not resident[2].alpha.any() and np.array_equal(resident[2].rgb, np.broadcast_to(np.float32(bg), (30, 40, 3)))
    assert all(resident[t].alpha.max() > 0.9 for t in (0, 1, 3, 4))
    # the tie group's index order shows: the same scene with its six rows reversed renders otherwise
    perm = np.arange(means.shape[0])
    perm[tie_rows] = tie_rows[::-1]
    s = scenes[0]
    swapped = render(s.means[perm], s.covariances[perm], s.colors[perm], s.opacities[perm], camera, background=bg)
    assert not np.array_equal(swapped.rgb, resident[0].rgb)


def test_device_frames_bins_and_reused_buffers():
    """``DeviceFrames`` bins every frame as ``bin_tiles`` does (same per-tile lists and ranges, on
    the host and on the device path), keeps one set of buffers for the motion and regrows the pair
    buffer only when a frame has more pairs; bad scene arrays are an ``InputError``."""
    import warp as wp

    from knockgs_core._warp import warp_device
    from knockgs_core.render._frame import DeviceFrames

    rng = np.random.default_rng(52)
    means, cov, colors, opac, static, pos, F, camera, _ = resident_motion(rng)
    dev = warp_device("cpu")
    frames = DeviceFrames(means.shape[0], camera, np.ones(3), dev)
    first = (frames.means2d.ptr, frames.order.ptr, frames.tile_starts.ptr, frames.images[0].ptr)
    capacity = []
    for t in range(5):
        s = deformed_scene(means, cov, colors, opac, pos[t], F[t], static)
        sym = 0.5 * (s.covariances + np.swapaxes(s.covariances, 1, 2))
        arrays = [wp.array(a.astype(np.float32), dtype=d, device=dev) for a, d in
                  ((s.means, wp.vec3f), (sym, wp.mat33f), (s.colors, wp.vec3f), (s.opacities, wp.float32))]
        out = frames.render(*arrays)
        proj = project(s.means, s.covariances, s.opacities, camera)
        got = frames.tile_bins()
        for want in (bin_tiles(proj, camera.width, camera.height, tile_size=frames.tile_size),
                     bin_tiles(proj, camera.width, camera.height, tile_size=frames.tile_size, device="cpu")):
            np.testing.assert_array_equal(got.gaussian_ids, want.gaussian_ids)
            np.testing.assert_array_equal(got.tile_ranges, want.tile_ranges)
        np.testing.assert_array_equal(out.rgb, render(*s, camera).rgb)
        capacity.append(frames.pair_keys.shape[0])
        assert capacity[-1] >= 2 * frames.pairs
    assert frames.pairs > 2 * means.shape[0]  # frame 4 still fits the buffer grown for frame 3
    assert capacity[2] == capacity[1] and capacity[3] > capacity[2] and capacity[4] == capacity[3]
    assert (frames.means2d.ptr, frames.order.ptr, frames.tile_starts.ptr, frames.images[0].ptr) == first
    with pytest.raises(InputError, match="DeviceFrames.*opacities"):
        frames.render(*arrays[:3], wp.zeros(3, dtype=wp.float32, device=dev))
    with pytest.raises(InputError, match="DeviceFrames.*n"):
        DeviceFrames(0, camera, np.ones(3), dev)


def test_cuda_default_wiring_on_the_cpu(monkeypatch):
    """With the device-resident default switched on for the CPU (as it is for CUDA), ``render``
    and ``render_frames`` take ``DeviceFrames`` and give the same frames; an empty scene and a
    motion without simulated Gaussians still render the background or the rest scene."""
    from knockgs_core.render import _frame, _pipeline

    rng = np.random.default_rng(53)
    means, cov, colors, opac, static, pos, F, camera, _ = resident_motion(rng)
    args = (means, cov, colors, opac, static, pos[:2], F[:2], camera)
    host_frames = render_frames(*args)
    host_one = render(means, cov, colors, opac, camera)
    used = []
    real = _frame.DeviceFrames

    def counted(*a, **k):
        used.append(a[0])
        return real(*a, **k)

    monkeypatch.setattr(_frame, "resident_default", lambda dev: True)
    monkeypatch.setattr(_pipeline, "resident_default", lambda dev: True)
    monkeypatch.setattr(_frame, "DeviceFrames", counted)
    monkeypatch.setattr(_pipeline, "DeviceFrames", counted)
    frames = render_frames(*args)
    one = render(means, cov, colors, opac, camera)
    assert used == [200, 200]  # one DeviceFrames for the motion, one for the single render
    for a, b in [*zip(host_frames, frames), (host_one, one)]:
        for name in ("rgb", "depth", "alpha"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    empty = render(np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros(0), camera)
    assert not empty.alpha.any()
    rest = render_frames(means, cov, colors, opac, np.ones(200, bool), np.zeros((1, 0, 3)), np.zeros((1, 0, 3, 3)), camera)
    np.testing.assert_array_equal(rest[0].rgb, host_one.rgb)


def test_cuda_build_of_the_frame_kernels(tmp_path):
    """The render kernels, the device-resident path's compaction among them, build for CUDA
    (sm_90 PTX by NVRTC, no GPU needed)."""
    import pathlib

    import warp as wp

    from knockgs_core.render import _kernels

    try:
        wp.compile_aot_module(_kernels.project_kernel.module, arch=90, use_ptx=True, module_dir=tmp_path)
    except Exception as exc:  # a Warp build without NVRTC
        pytest.skip(f"no CUDA compiler in this Warp build ({exc})")
    ptx = "".join(p.read_text() for p in pathlib.Path(tmp_path).rglob("*.ptx"))
    for name in ("visible_flags_kernel", "compact_visible_kernel", "pair_total_kernel", "tile_emit_kernel", "rasterize_kernel"):
        assert name in ptx
