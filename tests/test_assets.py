"""Gaussian assets: PLY I/O, preprocessing, interior fill, procedural assets, building."""

from __future__ import annotations


import numpy as np
import pytest

from knockgs_core.assets import (
    CAPTURE_ROTATION,
    PROCEDURAL_ASSETS,
    SH_C0,
    GaussianSet,
    Normalization,
    ParticleSet,
    build_asset,
    fill_interior,
    load_particles,
    make_procedural,
    matrix_to_quat,
    preprocess,
    quat_to_matrix,
    read_ply,
    save_particles,
    write_ply,
)
from knockgs_core.assets import _build
from knockgs_core.contract import load_contract
from knockgs_core.sim._config import Box


def assert_cov_close(a, b, rel=2e-5):
    """Covariances equal up to float32 rounding, relative to each matrix's largest entry."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    scale = np.abs(b).max(axis=(1, 2), keepdims=True)
    assert np.all(np.abs(a - b) <= rel * scale), float((np.abs(a - b) / scale).max())


def random_gaussians(rng, n=200, k=3) -> GaussianSet:
    return GaussianSet(
        means=rng.normal(size=(n, 3)) * 2 + 5,
        scales=np.exp(rng.normal(-3, 0.5, size=(n, 3))),
        quats=rng.normal(size=(n, 4)),
        opacities=rng.uniform(0.01, 0.99, size=n),
        sh_dc=rng.normal(size=(n, 3)),
        sh_rest=rng.normal(size=(n, k, 3)) * 0.1,
    )


def sphere_gaussians(n, radius=0.3, center=(1.0, 1.0, 1.0), seed=0, open_top=False) -> GaussianSet:
    """Flat Gaussians tangent to a sphere (or its lower half), spacing-sized."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    if open_top:
        d[:, 2] = -np.abs(d[:, 2])
    ref = np.where(np.abs(d[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    t1 = np.cross(d, ref)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    frames = np.stack([t1, np.cross(d, t1), d], axis=2)
    sp = np.sqrt(4 * np.pi * radius ** 2 / n)
    return GaussianSet(np.asarray(center) + radius * d, np.tile([0.6 * sp, 0.6 * sp, 0.08 * sp], (n, 1)),
                       matrix_to_quat(frames), np.full(n, 0.9), np.zeros((n, 3)))


# --------------------------------------------------------------------------- PLY

@pytest.mark.parametrize("k", [0, 3, 8, 15])
def test_ply_round_trip(tmp_path, rng, k):
    gs = random_gaussians(rng, k=k)
    path = tmp_path / "g.ply"
    write_ply(gs, path)
    back = read_ply(path)
    assert len(back) == len(gs) and back.sh_rest.shape == (len(gs), k, 3)
    np.testing.assert_array_equal(back.means, gs.means)
    np.testing.assert_array_equal(back.sh_dc, gs.sh_dc)
    np.testing.assert_array_equal(back.sh_rest, gs.sh_rest)
    np.testing.assert_allclose(back.scales, gs.scales, rtol=2e-6)
    np.testing.assert_allclose(back.opacities, gs.opacities, atol=1e-6)
    np.testing.assert_allclose(back.quats, gs.quats, atol=1e-6)
    cov = back.covariances().astype(np.float64)
    np.testing.assert_allclose(cov, np.swapaxes(cov, 1, 2), atol=0)
    assert np.all(np.linalg.eigvalsh(cov) > -1e-9)
    # R S S^T R^T from the quaternion formula, written out
    w, x, y, z = gs.quats.astype(np.float64).T
    R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                  [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                  [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]).transpose(2, 0, 1)
    S = gs.scales.astype(np.float64)
    expected = np.einsum("nij,nj,nkj->nik", R, S ** 2, R)
    assert_cov_close(cov, expected)


def test_read_ply_inria_layout(tmp_path):
    """A file written the way the INRIA code writes it (channel-major f_rest, logits, logs)."""
    from plyfile import PlyData, PlyElement

    n, k = 2, 3
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(3 * k)] + ["opacity", "scale_0", "scale_1", "scale_2",
                                                       "rot_0", "rot_1", "rot_2", "rot_3"]
    rec = np.zeros(n, dtype=[(nm, "f4") for nm in names])
    rec["x"], rec["y"], rec["z"] = [1, 2], [3, 4], [5, 6]
    for i in range(3 * k):
        rec[f"f_rest_{i}"] = i
    rec["opacity"] = [0.0, 2.0]
    rec["scale_0"] = np.log(0.5)
    rec["rot_0"] = [2.0, 1.0]           # unnormalized; the second is 90 deg about x
    rec["rot_1"] = [0.0, 1.0]
    PlyData([PlyElement.describe(rec, "vertex")]).write(str(tmp_path / "p.ply"))
    gs = read_ply(tmp_path / "p.ply")
    np.testing.assert_allclose(gs.opacities, [0.5, 1 / (1 + np.exp(-2.0))], rtol=1e-6)
    np.testing.assert_allclose(gs.scales[:, 0], 0.5, rtol=1e-6)
    np.testing.assert_allclose(gs.quats[0], [1, 0, 0, 0])
    np.testing.assert_allclose(gs.quats[1], [2 ** -0.5, 2 ** -0.5, 0, 0], rtol=1e-6)
    # f_rest_{c*K + k} -> sh_rest[:, k, c]
    np.testing.assert_array_equal(gs.sh_rest[0], np.arange(9).reshape(3, 3).T)


def test_colors_use_sh_c0():
    gs = GaussianSet(np.zeros((2, 3)), np.ones((2, 3)), [[1, 0, 0, 0]] * 2, [0.5, 0.5],
                     [[0.0, 1.0, -10.0], [10.0, -1.0, 0.5]])
    np.testing.assert_allclose(gs.colors(), np.clip(0.5 + SH_C0 * gs.sh_dc, 0, 1))
    assert gs.colors()[0, 2] == 0.0 and gs.colors()[1, 0] == 1.0


def test_quaternion_matrix_round_trip(rng):
    q = rng.normal(size=(500, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q *= np.sign(q[:, :1])
    np.testing.assert_allclose(matrix_to_quat(quat_to_matrix(q)), q, atol=1e-12)


# --------------------------------------------------------------------------- preprocessing

def test_preprocess_normalizes_and_inverts(rng):
    gs = random_gaussians(rng, n=300)
    crop = Box((0.0, 0.0, 0.0), (100.0, 100.0, 100.0))
    out, norm = preprocess(gs, opacity_threshold=0.2, rotations=[("x", 90.0), ("z", 30.0)], crop=crop)
    keep = gs.opacities >= np.float32(0.2)
    assert len(out) == keep.sum()
    ext = out.means.max(0) - out.means.min(0)
    assert ext.max() == pytest.approx(1.0, abs=1e-6)
    np.testing.assert_allclose(0.5 * (out.means.max(0) + out.means.min(0)), [1, 1, 1], atol=1e-6)
    np.testing.assert_allclose(norm.inverse(out.means), gs.means[keep], atol=1e-5)
    np.testing.assert_allclose(norm.apply(gs.means[keep]), out.means, atol=1e-6)
    # covariances transformed consistently with the positions
    assert_cov_close(out.covariances(), norm.apply_covariances(gs.covariances()[keep]))
    assert_cov_close(norm.inverse_covariances(out.covariances()), gs.covariances()[keep])
    again = Normalization.from_dict(norm.to_dict())
    assert again == norm


def test_preprocess_rotation_direction():
    """+90 deg about x maps y to z (right-handed)."""
    gs = GaussianSet([[0, 0, 0], [0, 1, 0], [1, 0, 0]], np.ones((3, 3)), [[1, 0, 0, 0]] * 3,
                     [0.9] * 3, np.zeros((3, 3)))
    out, norm = preprocess(gs, rotations=[("x", 90.0)])
    np.testing.assert_allclose(norm.matrix @ [0, 1, 0], [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(out.means[1] - out.means[0], [0, 0, 1], atol=1e-6)


def test_crop_keeps_inside():
    gs = GaussianSet([[0, 0, 0], [1, 0, 0], [5, 0, 0]], np.ones((3, 3)), [[1, 0, 0, 0]] * 3,
                     [0.9] * 3, np.zeros((3, 3)))
    out, norm = preprocess(gs, crop=Box((0.5, 0, 0), (1.0, 1.0, 1.0)))
    assert len(out) == 2
    np.testing.assert_allclose(norm.inverse(out.means)[:, 0], [0, 1], atol=1e-6)


# --------------------------------------------------------------------------- fill

def test_fill_sphere_inside_and_volume():
    r, res = 0.3, 48
    gs = sphere_gaussians(12000, radius=r)
    box = Box((1.0, 1.0, 1.0), (1.0, 1.0, 1.0))
    pos, cells = fill_interior(gs, fill_box=box, resolution=res, density_threshold=0.3,
                               max_particles_per_cell=4, seed=3)
    h = 2.0 / res
    assert len(pos) == 4 * cells        # interior cells hold no Gaussian centres
    radius = np.linalg.norm(pos - 1.0, axis=1)
    assert radius.max() < r
    # the shell eats at most ~2 cells: fill volume between the balls of radius r - 2h and r
    vol = cells * h ** 3
    assert 4 / 3 * np.pi * (r - 2 * h) ** 3 < vol < 4 / 3 * np.pi * r ** 3
    # roughly uniform: the inner half-radius ball holds ~ its volume share
    share = np.mean(radius < 0.5 * (r - h))
    assert 0.1 < share < 0.3


def test_fill_deterministic_and_seeded():
    gs = sphere_gaussians(3000)
    kw = dict(fill_box=Box((1.0, 1.0, 1.0), (0.5, 0.5, 0.5)), resolution=24, density_threshold=0.3,
              max_particles_per_cell=2)
    a, b, c = (fill_interior(gs, seed=s, **kw) for s in (5, 5, 6))
    np.testing.assert_array_equal(a.positions, b.positions)
    assert a.filled_cells == c.filled_cells > 0
    assert not np.array_equal(a.positions, c.positions)


def test_an_open_bowl_encloses_nothing_and_a_noisy_cloud_is_filled_only_where_it_encloses():
    """An open bowl has no inside to fill; a cloud of 20,000 random Gaussians (sizes over two
    decades) is filled in exactly the cells its shell encloses, at most 4 particles each. (The
    fill's work is bounded by a fixed stencil per Gaussian, :mod:`knockgs_core.assets._fill`.)"""
    from knockgs_core.assets import fill_grid

    rng = np.random.default_rng(0)
    box = Box((1.0, 1.0, 1.0), (1.0, 1.0, 1.0))
    bowl = sphere_gaussians(8000, open_top=True)
    pos, cells = fill_interior(bowl, fill_box=box, resolution=48, density_threshold=0.3, max_particles_per_cell=4, seed=1)
    assert cells == 0 and len(pos) == 0          # open at the top: no cell is enclosed
    n = 20000
    noise = GaussianSet(rng.uniform(0.2, 1.8, size=(n, 3)), np.exp(rng.uniform(-6, -1, size=(n, 3))),
                        rng.normal(size=(n, 4)), rng.uniform(0.01, 1, size=n), np.zeros((n, 3)))
    pos, cells = fill_interior(noise, fill_box=box, resolution=32, density_threshold=0.3, max_particles_per_cell=4, seed=1)
    grid = fill_grid(noise, fill_box=box, resolution=32, density_threshold=0.3)
    held = grid.cell_of(pos)
    assert cells == int(grid.interior.sum()) == len(np.unique(held, axis=0)) and len(pos) <= 4 * cells
    assert grid.interior[tuple(held.T)].all()


# --------------------------------------------------------------------------- procedural assets

@pytest.mark.parametrize("name", PROCEDURAL_ASSETS)
def test_procedural_deterministic(tmp_path, name):
    a = make_procedural(name, n_gaussians=800, seed=3)
    b = make_procedural(name, n_gaussians=800, seed=3)
    c = make_procedural(name, n_gaussians=800, seed=4)
    assert len(a) == 800 and a.equals(b) and not a.equals(c)
    write_ply(a, tmp_path / "a.ply")
    write_ply(b, tmp_path / "b.ply")
    assert (tmp_path / "a.ply").read_bytes() == (tmp_path / "b.ply").read_bytes()
    # small, flat Gaussians: normal scale well below the tangent ones; colours not uniform
    visible = a.opacities > 0.5
    s = np.sort(a.scales[visible], axis=1)
    assert np.median(s[:, 0] / s[:, 2]) < 0.3
    assert np.median(s[:, 2]) < 0.05 * float(np.ptp(a.means[visible], axis=0).max())
    assert a.colors()[visible].std(axis=0).min() > 0.05
    # the contracts' rotation and normalization bring the design frame back: z up, centred
    out, _ = preprocess(a, opacity_threshold=0.02, rotations=CAPTURE_ROTATION)
    assert len(out) == visible.sum()
    assert out.means[:, 2].min() == pytest.approx(1.0 - 0.5 * np.ptp(out.means[:, 2]), abs=1e-6)


# --------------------------------------------------------------------------- built assets

EXPECTED_CI = {  # (simulated particles range, fill expected)
    "pillow": ((1500, 3000), True),
    "ficus": ((600, 1500), False),
    "vasedeck": ((1200, 3000), False),
}


@pytest.mark.parametrize("name", sorted(EXPECTED_CI))
def test_build_ci(name):
    c = load_contract(name, "ci")
    b = build_asset(c)
    ps, g = b.particles, b.gaussians
    (lo, hi), has_fill = EXPECTED_CI[name]
    assert lo <= len(ps) <= hi
    assert (ps.n_fill > 0) == has_fill and (ps.fill_cells > 0) == has_fill
    ext = g.means.max(0) - g.means.min(0)
    assert ext.max() == pytest.approx(1.0, abs=1e-6)
    np.testing.assert_allclose(0.5 * (g.means.max(0) + g.means.min(0)), 1.0, atol=1e-6)
    assert 0 < b.static_mask.sum() < len(g)
    np.testing.assert_array_equal(ps.gaussian_index, np.flatnonzero(~b.static_mask))
    np.testing.assert_array_equal(ps.positions[: ps.n_gs], g.means[ps.gaussian_index])
    assert ps.region_names == c.region_names and ps.volumes is None
    assert all(n > 0 for n in b.probe_counts.values())
    # the support holds the bottom of the object, not the object
    held = np.zeros(len(ps), dtype=bool)
    for bc in c.sim.boundaries:
        if hasattr(bc, "box"):
            held |= bc.box.contains(ps.positions)
    assert 0 < held.sum() < 0.2 * len(ps)
    # fill particles lie inside the simulated object's bounding box
    if has_fill:
        gs_pos = ps.positions[: ps.n_gs]
        assert np.all(ps.positions[ps.n_gs:] >= gs_pos.min(0)) and np.all(ps.positions[ps.n_gs:] <= gs_pos.max(0))


def test_ficus_has_foliage_region():
    ps = build_asset(load_contract("ficus", "ci")).particles
    counts = ps.region_counts()
    assert ps.region_names == ("base", "foliage")
    assert counts["foliage"] > counts["base"] > 0


def test_build_is_deterministic(tmp_path):
    c = load_contract("pillow", "ci")
    first = build_asset(c)
    _build._CACHE.clear()
    second = build_asset(c)
    assert first is not second
    save_particles(first.particles, tmp_path / "a.npz")
    save_particles(second.particles, tmp_path / "b.npz")
    assert (tmp_path / "a.npz").read_bytes() == (tmp_path / "b.npz").read_bytes()
    write_ply(first.gaussians, tmp_path / "a.ply")
    write_ply(second.gaussians, tmp_path / "b.ply")
    assert (tmp_path / "a.ply").read_bytes() == (tmp_path / "b.ply").read_bytes()
    assert first.normalization == second.normalization


def test_particles_save_load(tmp_path):
    ps = ParticleSet(positions=np.arange(12, dtype=np.float32).reshape(4, 3) / 10, volumes=[1, 2, 3, 4],
                     n_gs=3, gaussian_index=[5, 7, 9], region=[0, 1, 1, 0],
                     region_names=("base", "foliage"), fill_cells=1)
    save_particles(ps, tmp_path / "p.npz")
    back = load_particles(tmp_path / "p.npz")
    for f in ("positions", "volumes", "gaussian_index", "region"):
        np.testing.assert_array_equal(getattr(back, f), getattr(ps, f))
    assert (back.n_gs, back.n_fill, back.fill_cells, back.region_names) == (3, 1, 1, ("base", "foliage"))
    assert not back.positions.flags.writeable


def test_ply_sourced_contract_matches_procedural(tmp_path):
    """A contract reading a 3DGS PLY goes through the same path as a procedural one."""
    import yaml

    from knockgs_core.assets import load_source_gaussians
    from knockgs_core.contract import find_config_dir

    proc = load_contract("vasedeck", "ci")
    write_ply(load_source_gaussians(proc), tmp_path / "scan.ply")
    data = yaml.safe_load((find_config_dir() / "objects" / "vasedeck.yaml").read_text())
    del data["asset"]["procedural"]
    data["asset"]["ply"] = "../scan.ply"
    for prof in data["profiles"].values():
        prof["n_gaussians"] = None
    data["profiles"]["default"]["n_gaussians"] = 1000
    (tmp_path / "objects").mkdir()
    (tmp_path / "objects" / "vasedeck.yaml").write_text(yaml.safe_dump(data))
    from_ply = build_asset(load_contract(tmp_path / "objects" / "vasedeck.yaml", "ci"))
    built = build_asset(proc)
    np.testing.assert_array_equal(from_ply.gaussians.means, built.gaussians.means)
    np.testing.assert_array_equal(from_ply.static_mask, built.static_mask)
    np.testing.assert_array_equal(from_ply.particles.positions, built.particles.positions)
    # a profile count below the file's subsamples deterministically
    sub = load_contract(tmp_path / "objects" / "vasedeck.yaml", "default")
    assert len(load_source_gaussians(sub)) == 1000
    assert load_source_gaussians(sub).equals(load_source_gaussians(sub))
