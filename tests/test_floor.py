"""Where the floor lives: the MPM at several resolutions against the finite-element reference
(knockgs_core.experiments._floor; docs/floor.md), and the FEM world's probe load."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from knockgs_core.errors import InputError
from knockgs_core.experiments import (FloorSettings, at_resolution, band_components, band_limited, cells_through,
                                      enclosed_empty_cells, fit_theta, floor_study, probe_period)

ROOT = Path(__file__).resolve().parents[1]


def test_settings_defaults_are_the_config_schema_defaults():
    schema = yaml.safe_load((ROOT / "workflow/schemas/config.schema.yaml").read_text())
    props = schema["properties"]["floor"]["properties"]
    assert set(props) == {f.name for f in dataclasses.fields(FloorSettings)} | {"enabled", "objects"}
    for f in dataclasses.fields(FloorSettings):
        default = props[f.name]["default"]
        assert (tuple(default) if isinstance(default, list) else default) == f.default, f.name
    for profile in ("ci.yaml", "config.yaml", "paper.yaml"):
        FloorSettings.from_config(yaml.safe_load((ROOT / "config" / profile).read_text())["floor"])
    with pytest.raises(InputError, match="fem_check_n_grid"):
        FloorSettings(fem_n_grid=32, fem_check_n_grid=32)
    with pytest.raises(InputError, match="n_grid"):
        FloorSettings(n_grid=(32, 24))
    for bad in (0.0, -5.0, float("nan"), "5", True):
        with pytest.raises(InputError, match="band_hz"):
            FloorSettings(band_hz=bad)


def test_the_fem_worlds_box_probe_delivers_the_contracts_impulse_on_its_cells_only():
    """The Vasedeck's Probe A is a contact box: its load is the contract's total force on the
    selected particles' cells and nothing elsewhere (the load used to be clamped onto the
    whole body outside the box's cells: 4.0x the impulse at ci, the s_rho collapse)."""
    from knockgs_core.assets import build_asset
    from knockgs_core.contract import load_contract
    from knockgs_core.fem import assemble_elasticity, fem_world_mesh
    from knockgs_core.fem._elasticity import _dof_components
    from knockgs_core.fem._world import _cells, _probe_load

    contract = load_contract("vasedeck", "ci")
    particles = build_asset(contract).particles
    geo = fem_world_mesh(contract, particles)
    m = contract.materials["base"]
    system = assemble_elasticity(geo["mesh"], E=m.E, nu=m.nu, rho=m.rho, degree=2)
    pr = contract.resolve_probes(particles)["standard_x"]
    sel = contract.probe_selection(pr, particles.positions)
    cells, counts = _cells(np.asarray(particles.positions)[sel], geo["dx"])
    force = np.asarray(pr.force) * contract.probe_reference_particles / len(particles.positions)
    load = _probe_load(system, cells, counts, geo["dx"], force)
    comp = _dof_components(system)
    total = np.array([load[comp == k].sum() for k in range(3)])
    # the contract's total force: |f| x selected_reference at every profile
    expected = np.asarray(contract.probes["standard_x"].force) * contract.probe_selected_reference["standard_x"]
    np.testing.assert_allclose(total, expected, rtol=1e-9, atol=1e-12)
    # no load on a DOF farther than one cell from every selected cell
    loc = system.basis.doflocs.T
    far = np.min(np.abs(loc[:, None, :] / geo["dx"] - (cells[None] + 0.5)).max(axis=2), axis=1) > 1.5
    assert far.sum() > 0.5 * len(far) and np.all(load[far] == 0.0)


def test_a_block_on_a_support_whose_top_lies_between_grid_planes_vibrates_as_one_clamped_at_its_foot():
    """The FEM world holds the grid nodes inside a still support box, as the MPM does, and no
    more: a block standing on the Pillow's support (its top z = 0.99 lies 0.115 m above the grid
    plane z = 0.875 under the block, below the next one) has the first period of the same block
    clamped at its bottom face (an independent tensor mesh, P2 eigenproblem). Holding every P2
    node inside the box also held the mid-edge nodes of the first element layer (z 0.9375):
    a period 20 % short at this grid (docs/floor.md, 2026-12-06)."""
    from knockgs_core.assets import ParticleSet
    from knockgs_core.contract import load_contract
    from knockgs_core.experiments._floor import _with_record
    from knockgs_core.fem import (FemWorld, Region, assemble_elasticity, box_mesh, fem_world_rollout, natural_frequencies,
                                  support_dofs)

    n, dx = 16, 2.0 / 16
    lo, hi = np.array([0.75, 0.75, 0.875]), np.array([1.25, 1.25, 1.375])      # 4 x 4 x 4 cells, on the grid
    contract = _with_record(load_contract("pillow", "ci"), "standard_x", 151)       # 3 s, ~1.4 periods
    (support,) = [bc.box for bc in contract.sim.boundaries if type(bc).__name__ == "FixedCuboid"]
    top = support.center[2] + support.half_size[2]
    assert lo[2] < top < lo[2] + dx / 2 + dx                                        # between grid planes, above a mid-edge node
    o = np.array([0.25, 0.75])
    cells = np.stack(np.meshgrid(*[np.arange(a, b) for a, b in zip(np.round(lo / dx), np.round(hi / dx))], indexing="ij"), -1)
    x = ((cells.reshape(-1, 1, 3) + np.stack(np.meshgrid(o, o, o, indexing="ij"), -1).reshape(1, -1, 3)) * dx).reshape(-1, 3)
    particles = ParticleSet(positions=x.astype(np.float32), volumes=None, n_gs=len(x), gaussian_index=np.arange(len(x)),
                            region=np.zeros(len(x), np.int32))
    Y = fem_world_rollout(contract, particles, (1.0, 1.0), "standard_x", x, world=FemWorld(n_grid=n))
    times = np.arange(len(Y)) * contract.probes["standard_x"].export.frame_dt
    period = probe_period(times, Y - Y[0], (1.0, 0.0, 0.0))

    m = contract.materials["base"]
    block = assemble_elasticity(box_mesh(tuple(lo), tuple(hi), (4, 4, 4)), E=m.E, nu=m.nu, rho=m.rho, degree=2)
    foot = support_dofs(block, Region(tuple(lo - 1.0), (hi[0] + 1.0, hi[1] + 1.0, lo[2])))
    clamped = 1.0 / natural_frequencies(block, foot, n_modes=1)[0]                  # the bending mode (x and y alike)
    assert period == pytest.approx(clamped, rel=0.01), (period, clamped)


def test_the_reference_mesh_does_not_change_with_the_mpm_resolution():
    from knockgs_core.assets import build_asset
    from knockgs_core.contract import load_contract
    from knockgs_core.fem import FemWorld, fem_world_mesh

    contract = load_contract("vasedeck", "ci")
    particles = build_asset(contract).particles
    world = FemWorld(n_grid=24)
    meshes = [fem_world_mesh(at_resolution(contract, n), particles, world=world)["mesh"] for n in (16, 32, 48)]
    for mesh in meshes[1:]:
        np.testing.assert_array_equal(mesh.p, meshes[0].p)
        np.testing.assert_array_equal(mesh.t, meshes[0].t)
    own = [fem_world_mesh(at_resolution(contract, n), particles)["mesh"] for n in (16, 32)]   # the MPM's cells
    assert own[0].p.shape != own[1].p.shape
    with pytest.raises(InputError, match="n_grid"):
        FemWorld(n_grid=1)


def test_at_resolution_refines_grid_and_fill_together_with_the_contracts_dt_rule():
    from knockgs_core.contract import cfl_dt, load_contract

    c = load_contract("pillow", "ci")
    r = at_resolution(c, 48)
    assert (r.sim.n_grid, r.fill.resolution) == (48, round(c.fill.resolution * 1.5))
    assert r.sim.dt <= cfl_dt(r.materials, n_grid=48, grid_lim=r.sim.grid_lim) * (1 + 1e-12) < c.sim.dt
    assert r.asset == c.asset and r.probes == c.probes


def test_probe_period_recovers_a_sinusoids_period_along_the_force(rng):
    """An oscillation of period 0.73 s along (1, 2, 0), a stronger one of 0.31 s across it
    (along (2, -1, 0)), a drift along z and noise, sampled like 61 frames at 20 ms: the period
    along the force to 0.2 % (the x component alone is dominated by the 0.31 s motion)."""
    t = np.arange(61) * 0.02
    d = np.array([1.0, 2.0, 0.0]) / np.sqrt(5.0)
    amp = rng.uniform(0.5, 1.5, size=40)
    u = (amp[None, :, None] * np.sin(2 * np.pi * t / 0.73)[:, None, None]) * d[None, None, :]
    across = np.array([2.0, -1.0, 0.0]) / np.sqrt(5.0)
    u += 2.0 * np.sin(2 * np.pi * t / 0.31)[:, None, None] * across    # motion across the force: ignored
    u[..., 2] += 0.3 * t[:, None]
    u += 1e-3 * rng.standard_normal(u.shape)
    assert probe_period(t, u, (1.0, 2.0, 0.0)) == pytest.approx(0.73, rel=2e-3)


def test_fit_theta_recovers_the_theta_of_an_oscillator_family():
    """A family whose response is an impulse-driven oscillator of stiffness s_E and mass s_rho
    (``u = I / sqrt(k m) sin(sqrt(k / m) t)``): Gauss-Newton from (1, 1) finds the target's theta."""
    t = np.arange(31) * 0.02
    shape = np.linspace(0.5, 1.5, 20)[None, :, None] * np.array([1.0, 0.0, 0.0])

    def response(theta):
        k, m = 40.0 * theta[0], 1.0 * theta[1]
        return (np.sin(np.sqrt(k / m) * t) / np.sqrt(k * m))[:, None, None] * shape

    calls = []

    def simulate(thetas):
        calls.append(len(thetas))
        return [response(th) for th in thetas]

    fit = fit_theta(simulate, response((0.8, 1.3)), steps=6)
    np.testing.assert_allclose(fit["theta"], (0.8, 1.3), rtol=1e-3)
    assert fit["residual_pct"] < 0.1 < fit["start_residual_pct"] and calls[0] == 3


def test_the_slow_band_keeps_a_records_slow_cosines_and_drops_its_fast_ones(rng):
    """The band of a Probe-A record (31 frames 0.02 s apart): the cosines at or below 5 Hz are
    the first 7 (component k at k / 1.24 s); a record's slow part passes unchanged, its fast part
    is removed, two records that differ only above the band agree in it, and the whole band
    returns the record."""
    T, dt = 31, 0.02
    assert band_components(5.0, dt, T) == 7 and band_components(100.0, dt, T) == T and band_components(0.1, dt, T) == 1
    n = np.arange(T)
    cos = lambda k: np.cos(np.pi * k * (n + 0.5) / T)  # noqa: E731  (the DCT-II's basis)
    shape = rng.standard_normal((1, 40, 3))
    slow = (cos(1) + 0.4 * cos(6))[:, None, None] * shape
    fast = (0.7 * cos(7) + 0.3 * cos(19))[:, None, None] * rng.standard_normal((1, 40, 3))
    np.testing.assert_allclose(band_limited(slow + fast, 7), slow, atol=1e-12)
    np.testing.assert_allclose(band_limited(slow + fast, T), slow + fast, atol=1e-12)
    assert np.abs(band_limited(fast, 7)).max() < 1e-12
    # a sampled sinusoid of 2 Hz keeps nearly all of itself in the 5 Hz band, one of 15 Hz little
    t = n * dt
    for f, kept in ((2.0, (0.95, 1.0)), (15.0, (0.0, 0.1))):
        u = np.sin(2 * np.pi * f * t)[:, None, None] * np.ones((1, 2, 3))
        share = np.linalg.norm(band_limited(u, 7)) / np.linalg.norm(u)
        assert kept[0] <= share <= kept[1], (f, share)


def test_cells_through_counts_a_slab_and_a_one_cell_shell():
    dx = 0.1
    g = np.stack(np.meshgrid(np.arange(10), np.arange(12), np.arange(3), indexing="ij"), -1).reshape(-1, 3)
    assert cells_through((g + 0.5) * dx, dx) == 3.0                  # a slab three cells thick
    u = np.random.default_rng(1).standard_normal((4000, 3))
    sphere = 1.0 + 0.6 * u / np.linalg.norm(u, axis=1, keepdims=True)  # a surface: 1-2 cells across
    assert cells_through(sphere, dx) <= 2.0


def test_enclosed_empty_cells_counts_a_hollow_boxs_void_and_nothing_in_a_solid_or_open_one():
    dx = 0.1
    g = np.stack(np.meshgrid(np.arange(6), np.arange(7), np.arange(8), indexing="ij"), -1).reshape(-1, 3)
    assert enclosed_empty_cells((g + 0.5) * dx, dx) == 0                      # solid
    wall = np.any((g == 0) | (g == [5, 6, 7]), axis=1)
    assert enclosed_empty_cells((g[wall] + 0.5) * dx, dx) == 4 * 5 * 6        # a closed box's inside
    cup = wall & (g[:, 2] < 7)
    assert enclosed_empty_cells((g[cup] + 0.5) * dx, dx) == 0                 # open at the top: no ray closes


@pytest.fixture(scope="module")
def pillow_floor(tmp_path_factory):
    """The ci Pillow's floor table at n_grid 16 and 24 against a reference at 24 (its check at
    16), written as the workflow writes it: (table, its CSV, the reference cache). ~25 s on two
    shared cores (two FEM runs and six MPM rollouts: the smallest grids that give two levels and
    a check)."""
    from knockgs_core.contract import load_contract
    from knockgs_core.reporting import write_table

    root = tmp_path_factory.mktemp("floor")
    table = floor_study(load_contract("pillow", "ci"), FloorSettings(n_grid=(16, 24), fem_n_grid=24, fem_check_n_grid=16,
                                                                     fit_steps=1, record_factor=1, band_hz=5.0),
                        reference_cache=root / "fem")
    write_table(table, root / "floor_pillow.csv")
    return table, root / "floor_pillow.csv", root / "fem"


@pytest.mark.slow
def test_the_pillows_gap_to_the_fem_reference_falls_under_refinement(pillow_floor):
    """The ci Pillow at n_grid 16 and 24 against a reference at 24: the trajectory RMSE falls
    from the coarser level to the finer, the body's mass with it, and one Gauss-Newton step of
    the theta fit lowers the residual."""
    table, _, cache = pillow_floor
    assert sorted(p.name.split("_")[1] for p in cache.glob("fem_*.npz")) == ["n16", "n24"]  # both FEM runs kept
    mpm = table[table.model == "mpm"].reset_index()
    assert list(table.model) == ["mpm", "mpm", "fem (check)", "fem (reference)"]
    assert mpm.rmse_pct[1] < 0.75 * mpm.rmse_pct[0]
    assert table.rmse_pct.iloc[-1] == 0.0 and np.all(mpm.fit_residual_pct < mpm.rmse_pct)
    assert mpm.mass_kg[1] < mpm.mass_kg[0]                          # the voxel body thins towards the solid
    # the record's slow band (<= 5 Hz): its gap falls under refinement too, and its own fit lowers it
    assert np.all(table.band_hz == 5.0) and table.rmse_band_pct.iloc[-1] == 0.0
    assert mpm.rmse_band_pct[1] < mpm.rmse_band_pct[0] and np.all(mpm.fit_band_residual_pct < mpm.rmse_band_pct)
    assert np.all(np.isfinite(mpm[["s_E_fit_band", "s_rho_fit_band"]].to_numpy()))
    from knockgs_core.contract import load_contract
    from knockgs_core.experiments import floor_note

    note = floor_note(table, load_contract("pillow", "ci"), FloorSettings(n_grid=(16, 24), fem_n_grid=24, fem_check_n_grid=16,
                                                                          band_hz=5.0))
    assert "at or below 5 Hz (7 of 31)" in note


def test_a_kept_fem_run_is_read_back_only_for_the_same_inputs(tmp_path):
    """The floor study's finite-element runs are kept by what they depend on: the same inputs
    read the kept displacements back, bit for bit, without computing; another theta, another
    grid, another record length or another body code computes anew; where the checkout lies does
    not matter. The
    ci Pillow's FEM at n_grid 12, P1, one step a frame (about 2 s a run)."""
    import dataclasses

    from knockgs_core.assets import build_asset
    from knockgs_core.contract import load_contract
    from knockgs_core.experiments._floor import _fem_run, _with_record
    from knockgs_core.fem import FemWorld

    contract = load_contract("pillow", "ci")
    probe = contract.roles["calibration"]
    short = _with_record(contract, probe, 6)
    ps = build_asset(contract).particles
    points = np.asarray(ps.positions[: ps.n_gs], dtype=np.float64)
    world = FemWorld(degree=1, steps_per_frame=1, n_grid=12)
    first = _fem_run(short, ps, points, world, (1.0, 1.0), probe, cache=tmp_path)
    again = _fem_run(short, ps, points, world, (1.0, 1.0), probe, cache=tmp_path)
    assert not first["cached"] and again["cached"] and len(list(tmp_path.iterdir())) == 1
    assert first["u"].shape == (6, len(points), 3) and np.abs(first["u"]).max() > 0
    np.testing.assert_array_equal(again["u"], first["u"])
    keys = ("cells", "dofs", "volume", "scale")
    assert {k: again[k] for k in keys} == {k: first[k] for k in keys}
    # the same contract read from another checkout (its files elsewhere) reads it back too
    moved = dataclasses.replace(short, source=Path("elsewhere") / short.source.name,
                                candidates_path=Path("elsewhere") / short.candidates_path.name)
    assert _fem_run(moved, ps, points, world, (1.0, 1.0), probe, cache=tmp_path)["cached"]
    for other in (dict(theta=(1.2, 1.0)), dict(world=dataclasses.replace(world, n_grid=10)),
                  dict(contract=_with_record(contract, probe, 5))):
        args = {"contract": short, "world": world, "theta": (1.0, 1.0), **other}
        run = _fem_run(args["contract"], ps, points, args["world"], args["theta"], probe, cache=tmp_path)
        assert not run["cached"], other
    assert len(list(tmp_path.iterdir())) == 4
    assert not _fem_run(short, ps, points, world, (1.0, 1.0), probe)["cached"]   # no cache: computed
    # and by the code that builds the reference's body: the level set lives in the asset build
    from knockgs_core.assets import _build
    from knockgs_core.experiments._floor import _fem_key

    key = _fem_key(short, ps, points, world, (1.0, 1.0), probe)
    own = Path(_build.__file__).read_bytes()
    real = Path.read_bytes
    changed = lambda self: real(self) + b"#" if self == Path(_build.__file__) else real(self)  # noqa: E731
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(Path, "read_bytes", changed)
        assert _fem_key(short, ps, points, world, (1.0, 1.0), probe) != key
    assert Path(_build.__file__).read_bytes() == own


def test_the_kept_files_a_study_would_read_are_named_before_it_runs(tmp_path):
    """``kept_reference_files`` names, without solving, the two finite-element runs a floor study
    keeps: not there before the study, there after it, and the study's only files. The ci
    Pillow at MPM n_grid 12, its FEM at 12 (check 10), P1, one step a frame, one record."""
    from knockgs_core.contract import load_contract
    from knockgs_core.experiments import FloorSettings, floor_study, kept_reference_files

    contract = load_contract("pillow", "ci")
    settings = FloorSettings(n_grid=(12,), fem_n_grid=12, fem_check_n_grid=10, fem_degree=1, fem_steps_per_frame=1,
                             record_factor=1, fit_steps=0)
    before = kept_reference_files(contract, settings, reference_cache=tmp_path)
    assert set(before) == {"fem (reference)", "fem (check)"} and not any(kept for _, kept in before.values())
    floor_study(contract, settings, reference_cache=tmp_path)
    after = kept_reference_files(contract, settings, reference_cache=tmp_path)
    assert {p for p, _ in after.values()} == {p for p, _ in before.values()} == set(tmp_path.iterdir())
    assert all(kept for _, kept in after.values())


def test_the_references_check_is_the_same_construction_one_grid_coarser():
    """The check row's body is the particle set built at the check's grid and voxelized there, as
    the reference's is at its own: each finite-element cell carries the volume of the particles in
    it, and a set binned on a grid its fill was not built on gives the cells sampling shares (the
    solid ci Vasedeck built at 24 and binned at 16: no cell whole). About 1 s."""
    from knockgs_core.assets import build_asset
    from knockgs_core.contract import at_resolution, load_contract, with_body
    from knockgs_core.experiments._floor import _reference_runs
    from knockgs_core.fem import fem_world_mesh

    contract = with_body(load_contract("vasedeck", "ci"), solid=True)
    settings = FloorSettings(n_grid=(16,), fem_n_grid=24, fem_check_n_grid=16, fem_degree=1, fem_steps_per_frame=1,
                             record_factor=1, fit_steps=0)
    bodies = _reference_runs(contract, settings)
    for name, n in (("fem (reference)", 24), ("fem (check)", 16)):
        c, ps, world = bodies[name]
        assert world.n_grid == n and c.sim.n_grid == n
        np.testing.assert_array_equal(ps.positions, build_asset(at_resolution(contract, n)).particles.positions)
        share = fem_world_mesh(c, ps, world=world)["share"]
        assert np.quantile(share, 0.95) == pytest.approx(1.0)       # the body's inside: whole cells
    c, _, world = bodies["fem (check)"]
    binned = fem_world_mesh(c, bodies["fem (reference)"][1], world=world)["share"]
    assert np.quantile(binned, 0.95) < 0.9


def test_a_level_set_reference_meshes_the_fill_where_there_is_one_and_the_voxels_of_a_shell():
    """``fem_body: level_set``: an object with an interior fill (the solid ci Vasedeck) gets a
    reference meshed to the surface its fill encloses, measured on the fill grid the settings
    name, at both the reference's and the check's grid; a shell without a fill (the ci Vasedeck)
    keeps its voxels, which are its body (``cell_share``), and the table's note says which."""
    from knockgs_core.contract import load_contract, with_body
    from knockgs_core.experiments import floor_note
    from knockgs_core.experiments._floor import _reference_runs

    settings = FloorSettings(n_grid=(16,), fem_n_grid=24, fem_check_n_grid=16, fem_body="level_set",
                             fem_body_resolution=48, record_factor=1, fit_steps=0)
    shell = load_contract("vasedeck", "ci")
    for contract, body, resolution in ((with_body(shell, solid=True), "level_set", 48), (shell, "voxel", None)):
        worlds = [world for _, _, world in _reference_runs(contract, settings).values()]
        assert [(w.body, w.body_resolution) for w in worlds] == [(body, resolution)] * 2
        table = pd.DataFrame({"model": ["fem (check)"], "rmse_pct": [1.0], "period_error_pct": [0.5]})
        assert ("meshed to that surface" in floor_note(table, contract, settings)) == (body == "level_set")
    with pytest.raises(InputError, match="fem_body"):
        FloorSettings(fem_body="tetrahedra")


def test_a_floor_object_the_reference_cannot_hold_is_one_line_at_config_read(tmp_path):
    # the Ficus has two material regions; the FEM reference holds one
    from _workflow import scratch_copy, snakemake

    work = scratch_copy(tmp_path)
    out = snakemake(work, "-n", "--configfile=config/ci.yaml", "--config", "floor={objects: [ficus]}", "--", "floor")
    text = (out.stdout + out.stderr).strip()
    assert out.returncode != 0 and "Traceback" not in text
    assert text.splitlines()[-1].startswith("knockgs workflow: config error: config floor.objects: 'ficus'"), text[-500:]


@pytest.mark.slow
def test_the_loop_runs_at_the_coarsest_level_whose_floor_is_under_half_the_effect(pillow_floor):
    """``choose_resolution``: the coarsest MPM level of a floor table whose RMSE against the
    reference is at most half the smallest effect to name; where none is, the finest, with the
    statement that effects below about twice its floor cannot be named. A level on the
    reference's own grid is never within: the two share the voxelized body, so their gap leaves
    out its discretization (the ci Pillow at 32 is 11 % from a reference at 32 and 39 % from one at
    48). The table is refused (one line naming the file and the field) for another body: another
    particle count at that grid, or the same particles of another mass. The level's calibration
    bias (its theta fit to the reference) widens a theta interval on both sides, and an effect
    named below the floor is said to be so in the verdict."""
    from knockgs_core.assets import build_asset
    from knockgs_core.contract import load_contract, with_body
    from knockgs_core.discrepancy._resolution import (check_floor_body, choose_resolution, qualify_verdict, read_floor_table,
                                                      widen_by_floor_bias)

    _, csv, _ = pillow_floor
    table = read_floor_table(csv)
    e16, e24 = (float(table[(table.model == "mpm") & (table.n_grid == n)].rmse_pct.iloc[0]) for n in (16, 24))
    assert e24 < e16
    between = (e24 + e16) / 100.0        # an effect twice the mean of the two floors: only 24 is under its half
    big = min(1.0, 2.2 * e16 / 100.0)    # both are under its half
    c = choose_resolution(table, smallest_effect=big, source=csv)
    assert (c["n_grid"], c["within"], c["rmse_pct"]) == (16, True, e16) and "n_grid 16" in c["statement"]
    # 24 is under half of `between` but on the reference's grid (24): not within, and said so
    c24 = choose_resolution(table, smallest_effect=between, source=csv)
    assert (c24["n_grid"], c24["within"], c24["rmse_pct"]) == (24, False, e24)
    assert "not finer than" in c24["statement"] and "cannot be named" in c24["statement"]
    on_ref = choose_resolution(table, smallest_effect=big, n_grid=24, source=csv)
    assert not on_ref["within"] and "not finer than" in on_ref["statement"]
    told = choose_resolution(table, smallest_effect=between, n_grid=16, source=csv)   # a grid the loop is told
    assert (told["n_grid"], told["within"], told["rmse_pct"]) == (16, False, e16) and "as told" in told["statement"]
    with pytest.raises(InputError, match="n_grid 20"):
        choose_resolution(table, smallest_effect=between, n_grid=20, source=csv)
    low = choose_resolution(table, smallest_effect=e24 / 100.0, source=csv)   # the effect is the floor's size
    assert (low["n_grid"], low["within"]) == (24, False)
    assert "cannot be named" in low["statement"] and f"{2 * e24:.0f} %" in low["statement"]
    # an effect named below the floor is said to be so; nothing named, or a floor that allows it: unchanged
    said = qualify_verdict("added damping", ["damping"], low)
    assert said.startswith("added damping; ") and "damping cannot be told from the model's own error" in said
    assert qualify_verdict("added damping", ["damping"], c) == "added damping"
    assert qualify_verdict("no effect", [], low) == "no effect"
    # the level's calibration bias (the theta it needs to reproduce the reference) widens the interval
    fit = [float(table[(table.model == "mpm") & (table.n_grid == 16)][k].iloc[0]) for k in ("s_E_fit", "s_rho_fit")]
    assert c["theta_fit"] == fit and all(np.isfinite(fit)) and fit != [1.0, 1.0]
    wide, w = widen_by_floor_bias([[0.5, 1.0], [0.0, float("inf")]], c)
    assert w == pytest.approx([abs(np.log(f)) for f in fit])
    assert wide[0] == pytest.approx([0.5 * np.exp(-w[0]), np.exp(w[0])]) and wide[1] == [0.0, float("inf")]
    # a run whose fit a model error of the floor's size could bias further is widened by that instead, per coordinate
    per_response = [0.0, 2.0 * w[1] / (c["rmse_pct"] / 100.0)]
    _, w2 = widen_by_floor_bias([[0.5, 1.0], [1.0, 2.0]], c, per_response)
    assert w2 == pytest.approx([w[0], 2.0 * w[1]])
    ci = load_contract("pillow", "ci")
    at24 = at_resolution(ci, 24)
    check_floor_body(c24, at24, build_asset(at24).particles)                     # the table's own body
    heavier = dataclasses.replace(at24, materials={"base": dataclasses.replace(at24.materials["base"],
                                                                               rho=1.1 * at24.materials["base"].rho)})
    with pytest.raises(InputError, match="mass_kg"):                             # the same particles, 10 % heavier
        check_floor_body(c24, heavier, build_asset(at24).particles)
    with pytest.raises(InputError, match="particles"):                           # another fill
        enclosed = at_resolution(with_body(ci, volumes="enclosed"), 24)
        check_floor_body(c24, enclosed, build_asset(enclosed).particles)
    vase = at_resolution(load_contract("vasedeck", "ci"), 24)
    with pytest.raises(InputError, match="particles"):
        check_floor_body(c24, vase, build_asset(vase).particles)


@pytest.mark.slow
def test_a_floor_table_that_is_not_one_is_one_line_naming_its_field(pillow_floor, tmp_path, rng, monkeypatch, capsys):
    """``knockgs discrepancy run --floor-table``: the loop's model is the contract at the level the
    table allows (the loop itself replaced by a recorder); a table lacking a column, with a
    level whose RMSE is not a number, or no table at all is refused in one line, exit 2; with
    ``--n-grid`` the loop runs at that grid, and a grid the table has no level of is refused."""
    import pandas as pd

    import knockgs_core.discrepancy._files as files
    from knockgs_core.cli import main
    from knockgs_core.contract import load_contract
    from knockgs_core.discrepancy import Measurement, write_measured

    table, csv, _ = pillow_floor
    ci = load_contract("pillow", "ci")
    T, M = ci.probes["standard_x"].export.n_frames, 20
    write_measured(tmp_path / "m.parquet", Measurement(points=rng.normal(scale=0.01, size=(T, M, 3)) + 1.0,
                                                       frames=np.arange(T), times=None, particle=None, track=np.arange(M),
                                                       meta={"object": "pillow", "probe": "standard_x"}, source="test"))
    seen = {}

    def recorder(measured, contract, particles, **kw):
        seen.update(contract=contract)
        raise SystemExit(0)

    monkeypatch.setattr(files, "run_discrepancy", recorder)
    run = ["discrepancy", "run", "--object", "pillow", "--profile", "ci", "--measured", str(tmp_path / "m.parquet"), "--quiet"]
    e24 = float(table[(table.model == "mpm") & (table.n_grid == 24)].rmse_pct.iloc[0])
    with pytest.raises(SystemExit):
        main(run + ["--floor-table", str(csv), "--smallest-effect", f"{min(1.0, 2.05 * e24 / 100):.6f}", "-o",
                    str(tmp_path / "out")])
    assert seen["contract"].hash == at_resolution(ci, 24).hash
    bad = {"no_rmse.csv": table.drop(columns=["rmse_pct"]), "nan.csv": table.assign(rmse_pct=np.nan)}
    for name, df in bad.items():
        df.to_csv(tmp_path / name, index=False)
    for name, field in (("no_rmse.csv", "rmse_pct"), ("nan.csv", "rmse_pct"), ("absent.csv", "--floor-table")):
        capsys.readouterr()
        code = main(run + ["--floor-table", str(tmp_path / name), "-o", str(tmp_path / f"out_{name}")])
        err = capsys.readouterr().err.strip()
        assert code == 2 and len(err.splitlines()) == 1 and name in err and field in err, err
    with pytest.raises(SystemExit):           # told a grid, the table's level of it judges it
        main(run + ["--floor-table", str(csv), "--n-grid", "16", "-o", str(tmp_path / "told")])
    assert seen["contract"].hash == at_resolution(ci, 16).hash
    # told its own grid, a contract stays itself (the default Vasedeck's substep is not the rule's)
    vase = load_contract("vasedeck", "default")
    assert at_resolution(vase, vase.sim.n_grid).sim.dt != vase.sim.dt
    write_measured(tmp_path / "v.parquet", Measurement(points=rng.normal(scale=0.01, size=(T, M, 3)) + 1.0,
                                                       frames=np.arange(T), times=None, particle=None, track=np.arange(M),
                                                       meta={"object": "vasedeck", "probe": "standard_x"}, source="test"))
    with pytest.raises(SystemExit):
        main(["discrepancy", "run", "--object", "vasedeck", "--profile", "default", "--measured", str(tmp_path / "v.parquet"),
              "--quiet", "--n-grid", str(vase.sim.n_grid), "-o", str(tmp_path / "own")])
    assert seen["contract"].hash == vase.hash
    capsys.readouterr()
    code = main(run + ["--floor-table", str(csv), "--n-grid", "20", "-o", str(tmp_path / "out_20")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and "n_grid 20" in err and "floor_pillow.csv" in err, err
    assert not any(tmp_path.glob("out_*"))
    assert isinstance(pd.read_csv(csv), pd.DataFrame)     # the table is read, never written


def test_a_model_error_of_a_given_norm_biases_theta_at_most_by_the_fits_worst_ratio():
    """The least-squares theta moves by at most ``sqrt(((A^T A)^-1)_jj)`` per unit norm of a
    change in the data, and a change in the columns' span reaches it; columns that do not
    determine theta give no bound."""
    from knockgs_core.discrepancy._interval import worst_theta_per_misfit

    rng = np.random.default_rng(5)
    A = rng.normal(size=(60, 3)) @ np.array([[1.0, 0.6, 0.2], [0.0, 0.8, 0.1], [0.0, 0.0, 0.5]])  # correlated columns
    bound = worst_theta_per_misfit(A)
    moves = [np.abs(np.linalg.lstsq(A, d / np.linalg.norm(d), rcond=None)[0][:2]) for d in rng.normal(size=(400, 60))]
    assert np.all(np.max(moves, axis=0) <= bound * (1 + 1e-12))
    G = np.linalg.inv(A.T @ A)
    for j in range(2):
        d = A @ G[:, j]                          # the change that moves theta_j most per unit norm
        x = np.linalg.lstsq(A, d / np.linalg.norm(d), rcond=None)[0]
        assert abs(x[j]) == pytest.approx(bound[j], rel=1e-10)
    assert np.all(np.isinf(worst_theta_per_misfit(np.column_stack([A[:, 0], 2 * A[:, 0], A[:, 2]]))))


def test_each_profiles_floor_block_sets_every_key_the_default_block_sets():
    """The workflow reads a profile over the default one (``config/config.yaml``, then
    ``--configfile``), so a key a profile's ``floor`` block leaves out is the default profile's:
    the ci floor once measured its reference on the default's level-set body at a fill of 128
    (45.9 % at n_grid 32 against its own voxel reference's 11.3 %). Every profile sets the whole
    block."""
    import yaml

    from knockgs_core.experiments import FloorSettings

    root = Path(__file__).resolve().parents[1] / "config"
    default = yaml.safe_load((root / "config.yaml").read_text())["floor"]
    fields = {f.name for f in dataclasses.fields(FloorSettings)}
    assert fields <= set(default), sorted(fields - set(default))
    for name in ("ci.yaml", "paper.yaml"):
        block = yaml.safe_load((root / name).read_text()).get("floor")
        assert block is not None and set(default) <= set(block), (name, sorted(set(default) - set(block or {})))



def test_the_report_says_by_how_much_the_floor_widened_the_interval_and_why():
    """The report's Resolution section gives the widening used (the larger share) beside the
    calibration bias it replaced, and the floor's size."""
    import types

    from knockgs_core.discrepancy._report import _calibration_lines

    choice = {"statement": "n_grid 32, as told", "levels": [[32, 11.25]], "theta_fit": [0.847, 0.99],
              "rmse_pct": 11.25, "theta_widening_log": [0.448, 0.126]}
    result = types.SimpleNamespace(
        object="pillow", profile="ci", probe="standard_x", verdict="no effect", resolution=choice, effects=[],
        theta_base=(1.0, 1.0), theta_refit=(1.0, 1.0), theta_final=(0.8, 1.3), base_method="library", identified=[],
        observation={"points": 10, "frames": 31, "identity": True, "fit_frames": 20, "validation_frames": 10},
        noise={"std": 1e-4, "source": "declared"}, n_simulations=1, seconds=1.0, theta_interval=None,
        residual={"rms_per_point": 1e-4, "excess_rms_per_point": 0.0, "excess_fraction_of_response": 0.0,
                  "measured_rms_displacement": 1e-3}, theta_uncertainty={})
    line = next(s for s in _calibration_lines(result) if "widened" in s)
    assert "0.448 and 0.126 in log theta" in line and "0.166 and 0.0101" in line and "11.2 % of the response" in line
