"""The convergence study of the Probe-A response (knockgs_core.experiments._convergence).

The order solver and the Richardson extrapolation are checked against analytic sequences
``u_h = u* + C h^p``; the study itself runs through the workflow on the ci profile (one
object) and is checked for structure: three levels per refinement (dt, n_grid with the particles
fixed, n_grid+fill with the fill rebuilt per grid), each simulated, and an observed order that
follows from the table's own level values and changes.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from knockgs_core.contract import cfl_dt, load_candidates, load_contract, load_targets
from knockgs_core.errors import InputError

from knockgs_core.experiments import NOT_ASYMPTOTIC, convergence_study, observed_order
from knockgs_core.experiments._convergence import (
    convergence_levels,
    particles_per_cell,
    refined_particles,
    relative_change,
    richardson_limit,
)

ROOT = Path(__file__).resolve().parents[1]
CI = "results/ci"
H_RATIO_2 = (1.0, 0.5, 0.25)             # dt -> dt/2 -> dt/4
H_GRID = (1.0, 1.0 / 1.5, 1.0 / 2.0)     # n_grid -> 1.5x -> 2x: ratios 1.5 and 1.333


def _changes(h, p, c=0.7):
    """|u_h1 - u_h2| and |u_h2 - u_h3| of u_h = u* + c h^p."""
    u = [c * v**p for v in h]
    return abs(u[0] - u[1]), abs(u[1] - u[2])


# --------------------------------------------------------------------------- order solver

@pytest.mark.parametrize("h", [H_RATIO_2, H_GRID, (0.3, 0.2, 0.15)])
@pytest.mark.parametrize("p", [0.5, 1.0, 2.0, 3.0])
def test_observed_order_recovers_the_order_of_an_analytic_sequence(h, p):
    d12, d23 = _changes(h, p)
    assert observed_order(h, d12, d23) == pytest.approx(p, abs=1e-9)


@pytest.mark.parametrize("p", [1.0, 2.0])
def test_observed_order_at_ratio_2_is_log2_of_the_change_ratio(p, rng):
    c = rng.uniform(0.1, 10.0)
    d12, d23 = _changes(H_RATIO_2, p, c)
    assert observed_order(H_RATIO_2, d12, d23) == pytest.approx(math.log2(d12 / d23), abs=1e-9)


def test_observed_order_of_non_uniform_ratios_is_not_log2():
    # ratios 1.5 and 1.333: log2(d12/d23) would be wrong; the solver is not
    d12, d23 = _changes(H_GRID, 2.0)
    assert observed_order(H_GRID, d12, d23) == pytest.approx(2.0, abs=1e-9)
    assert abs(math.log2(d12 / d23) - 2.0) > 0.4


@pytest.mark.parametrize("h", [(0.25, 0.5, 1.0), (1.0, 0.5, 0.5), (1.0, 0.25, 0.5), (1.0, -0.5, -1.0), (1.0, 0.5)])
def test_observed_order_refuses_step_sizes_that_do_not_decrease(h):
    with pytest.raises(ValueError, match="strictly decreasing"):
        observed_order(h, 0.2, 0.1)


@pytest.mark.parametrize("changes", [(float("nan"), 0.1), (0.1, -0.1), (float("inf"), 1.0)])
def test_observed_order_refuses_bad_changes(changes):
    with pytest.raises(ValueError, match="changes"):
        observed_order(H_RATIO_2, *changes)


@pytest.mark.parametrize("h", [H_RATIO_2, H_GRID])
@pytest.mark.parametrize("changes", [(0.1, 0.1), (0.1, 0.2), (0.0, 0.1), (0.1, 0.0)])
def test_changes_that_do_not_decrease_have_no_order(h, changes):
    assert observed_order(h, *changes) is None


def test_no_order_below_the_zero_order_limit_of_non_uniform_ratios():
    # at p -> 0 the change ratio tends to ln(1.5)/ln(4/3) = 1.41: a smaller decrease has no p > 0
    limit = math.log(1.5) / math.log(4.0 / 3.0)
    assert observed_order(H_GRID, 0.99 * limit, 1.0) is None
    assert observed_order(H_GRID, 1.01 * limit, 1.0) == pytest.approx(0.0, abs=0.05)


# --------------------------------------------------------------------------- Richardson

@pytest.mark.parametrize("h", [H_RATIO_2, H_GRID])
@pytest.mark.parametrize("p", [1.0, 2.0])
def test_richardson_recovers_the_limit_of_an_analytic_field(h, p, rng):
    limit = rng.normal(size=(5, 7, 3))
    c = rng.normal(size=(5, 7, 3))
    u1, u2, u3 = (limit + c * v**p for v in h)
    d12 = relative_change(u1, u2, reference=u3)
    d23 = relative_change(u2, u3, reference=u3)
    q = observed_order(h, d12, d23)
    assert q == pytest.approx(p, abs=1e-9)
    np.testing.assert_allclose(richardson_limit(u2, u3, h2=h[1], h3=h[2], p=q), limit, atol=1e-9)


def test_relative_change_needs_a_moving_reference():
    a = np.ones((3, 2, 3))
    with pytest.raises(ValueError, match="zero"):
        relative_change(a, a, reference=np.zeros_like(a))
    with pytest.raises(ValueError, match="shapes"):
        relative_change(a, a[:2], reference=a)


# --------------------------------------------------------------------------- levels and inputs

@pytest.mark.parametrize("name", ["pillow", "ficus", "vasedeck"])
@pytest.mark.parametrize("profile", ["ci", "default"])
def test_levels_refine_one_thing_at_a_time(name, profile):
    c = load_contract(name, profile)
    frame_dt = c.calibration_probe.export.frame_dt
    lv = convergence_levels(c, frame_dt=frame_dt)
    assert [x["dt"] for x in lv["dt"]] == [c.sim.dt, c.sim.dt / 2, c.sim.dt / 4]
    assert {x["n_grid"] for x in lv["dt"]} == {c.sim.n_grid}
    assert [x["n_grid"] for x in lv["n_grid"]] == [c.sim.n_grid, round(1.5 * c.sim.n_grid), 2 * c.sim.n_grid]
    dts = {x["dt"] for x in lv["n_grid"]}
    assert len(dts) == 1                  # one substep for every space level
    dt = dts.pop()
    assert dt <= c.sim.dt and dt <= cfl_dt(c.materials, n_grid=2 * c.sim.n_grid, grid_lim=c.sim.grid_lim) * (1 + 1e-12)
    k = frame_dt / dt
    assert abs(k - round(k)) < 1e-6       # the substep divides the export interval
    assert {x["fill_resolution"] for x in lv["dt"] + lv["n_grid"]} == {None}     # the profile's particles
    if not c.fill.enabled:
        assert "n_grid+fill" not in lv    # no fill to refine: the particles are the Gaussians
        return
    both = lv["n_grid+fill"]
    assert [x["n_grid"] for x in both] == [x["n_grid"] for x in lv["n_grid"]]
    assert {x["dt"] for x in both} == {dt}
    r0 = c.fill.resolution
    assert [x["fill_resolution"] for x in both] == [None, round(1.5 * r0), 2 * r0]


def test_particles_per_cell_counts_occupied_cells_only():
    # 3 particles in cell (0,0,0), 1 in cell (1,0,0); the empty cells do not count
    x = np.array([[0.1, 0.1, 0.1], [0.2, 0.3, 0.4], [0.45, 0.05, 0.2], [0.7, 0.2, 0.2]])
    assert particles_per_cell(x, dx=0.5) == 2.0
    assert particles_per_cell(x, dx=0.25) == 1.0     # every particle alone in its cell
    assert particles_per_cell(x, dx=1.0) == 4.0


def test_refined_particles_keep_the_gaussians_and_rebuild_the_fill_per_cell():
    from knockgs_core.assets import build_asset

    c = load_contract("pillow", "ci")
    ps = build_asset(c).particles
    n, r = 2 * c.sim.n_grid, 2 * c.fill.resolution
    variant, fine = refined_particles(c, ps, n_grid=n, fill_resolution=r)
    assert variant.sim.n_grid == n and variant.fill.resolution == r
    assert variant.fill.max_particles_per_cell == c.fill.max_particles_per_cell and variant.fill.seed == c.fill.seed
    assert fine.n_gs == ps.n_gs
    np.testing.assert_array_equal(fine.positions[:ps.n_gs], ps.positions[:ps.n_gs])
    # the fill follows the cell: many more fill particles, about as many per occupied cell as the profile's
    assert fine.n_fill > 4 * ps.n_fill
    ppc0 = particles_per_cell(ps.positions, dx=c.sim.dx)
    assert 0.75 * ppc0 < particles_per_cell(fine.positions, dx=variant.sim.dx) < 1.25 * ppc0
    # rest volumes at the level's grid: dx^3 / (particles in the cell), so they fill the occupied cells
    cells = np.unique(np.floor(fine.positions.astype(np.float64) / variant.sim.dx), axis=0)
    assert float(np.sum(fine.volumes, dtype=np.float64)) == pytest.approx(len(cells) * variant.sim.dx**3, rel=1e-5)


def test_refined_particles_refuse_another_objects_particles():
    from knockgs_core.assets import build_asset

    c = load_contract("pillow", "ci")
    other = build_asset(load_contract("pillow", "default")).particles
    with pytest.raises(InputError, match="Gaussian-associated particles differ"):
        refined_particles(c, other, n_grid=48, fill_resolution=48)


def test_a_bad_frame_count_is_one_clear_error():
    c = load_contract("pillow", "ci")
    from knockgs_core.assets import build_asset

    ps = build_asset(c).particles
    with pytest.raises(InputError, match="n_frames"):
        convergence_study(c, ps, theta=(1.15, 0.75), n_frames=1)
    with pytest.raises(InputError, match="n_frames"):
        convergence_study(c, ps, theta=(1.15, 0.75), n_frames=c.calibration_probe.export.n_frames + 1)


def test_the_configured_theta_is_a_candidate_and_no_target():
    schema = yaml.safe_load((ROOT / "workflow/schemas/config.schema.yaml").read_text())
    theta = tuple(schema["properties"]["convergence"]["properties"]["theta"]["default"])
    cands = {(round(r.E_scale, 6), round(r.density_scale, 6)) for r in load_candidates().itertuples(index=False)}
    assert theta in cands
    for split in ["main", "alt_1", "alt_2", "alt_3"]:
        targets = {(round(r.E_scale, 6), round(r.density_scale, 6)) for r in load_targets(split).itertuples(index=False)}
        assert len(targets) == 5 and theta not in targets


# --------------------------------------------------------------------------- the study on the ci profile

@pytest.fixture
def ci_study(ci_run):
    """The Pillow convergence table of the ci profile, as the shared ci run made it (its job
    runs the table's script on the profile's settings)."""
    return ci_run


@pytest.mark.slow
def test_ci_convergence_table_structure(ci_study):
    c = load_contract("pillow", "ci")
    t = pd.read_csv(ci_study / f"{CI}/tables/convergence_pillow.csv")
    assert list(t["refinement"]) == ["dt", "n_grid", "n_grid+fill"]
    assert {"object", "profile", "fixed", "level_1", "level_2", "level_3", "particles_1", "particles_2", "particles_3",
            "particles_per_cell_1", "particles_per_cell_3", "change_1_2", "change_2_3", "observed_order",
            "richardson_error_pct", "asymptotic", "cost_s_1", "cost_s_2", "cost_s_3"} <= set(t.columns)
    assert (t["object"] == "pillow").all() and (t["profile"] == "ci").all()
    assert int(t["n_frames"].iloc[0]) == c.calibration_probe.export.n_frames
    dt_row, grid_row, fill_row = t.iloc[0], t.iloc[1], t.iloc[2]
    assert dt_row[["level_1", "level_2", "level_3"]].tolist() == pytest.approx([c.sim.dt, c.sim.dt / 2, c.sim.dt / 4])
    grids = [c.sim.n_grid, 1.5 * c.sim.n_grid, 2 * c.sim.n_grid]
    assert grid_row[["level_1", "level_2", "level_3"]].tolist() == grids
    assert fill_row[["level_1", "level_2", "level_3"]].tolist() == grids and fill_row["dt"] == grid_row["dt"]
    for col in ["change_1_2", "change_2_3", "rms_displacement_m", "cost_s_1", "cost_s_2", "cost_s_3",
                "particles_per_cell_1", "particles_per_cell_2", "particles_per_cell_3"]:
        assert np.isfinite(t[col]).all() and (t[col] > 0).all(), col
    # every row starts from the profile's particles; only n_grid+fill changes them, and it adds fill particles
    n0 = int(dt_row["particles_1"])
    assert (t["particles_1"] == n0).all()
    assert dt_row[["particles_2", "particles_3"]].tolist() == [n0, n0] == grid_row[["particles_2", "particles_3"]].tolist()
    assert n0 < fill_row["particles_2"] < fill_row["particles_3"]
    # particles fixed: the particles per cell thin out with the grid; grid and fill together: they stay
    ppc = [f"particles_per_cell_{k}" for k in (1, 2, 3)]
    assert grid_row[ppc[2]] < 0.5 * grid_row[ppc[0]]
    assert all(0.75 * fill_row[ppc[0]] < fill_row[q] < 1.25 * fill_row[ppc[0]] for q in ppc[1:])
    note = (ci_study / f"{CI}/tables/convergence_pillow.md").read_text()
    assert "Row n_grid (particles fixed)" in note and "not expected to converge" in note
    assert "Row n_grid+fill (grid and fill refined together)" in note
    assert (ci_study / f"{CI}/tables/convergence_pillow.md").read_text().startswith("# Probe-A convergence: pillow")
    assert (ci_study / f"{CI}/figures/convergence_pillow.png").stat().st_size > 1000
    assert (ci_study / f"{CI}/benchmarks/convergence/pillow.tsv").exists()


@pytest.mark.slow
def test_ci_observed_order_follows_from_three_simulated_levels(ci_study):
    c = load_contract("pillow", "ci")
    t = pd.read_csv(ci_study / f"{CI}/tables/convergence_pillow.csv", dtype={"observed_order": str,
                                                                              "richardson_error_pct": str})
    log = (ci_study / "logs/ci/tables/convergence_pillow.log").read_text()
    # every rollout: its dt, grid, fill resolution (levels with a rebuilt fill) and particle count
    simulated = {(float(dt), int(n), int(r) if r else None, int(m))
                 for dt, n, r, m in re.findall(r"dt ([0-9.e+-]+) s, n_grid (\d+)(?:, fill (\d+))?: (\d+) particles", log)}
    assert len(simulated) == 8           # 3 dt + 3 n_grid + 2 n_grid+fill (level 1 shared with n_grid)
    for row in t.itertuples(index=False):
        levels = [row.level_1, row.level_2, row.level_3]
        assert len(set(levels)) == 3     # three distinct resolutions
        counts = [row.particles_1, row.particles_2, row.particles_3]
        if row.refinement == "dt":
            h = levels
            runs = [(dt, c.sim.n_grid, None, m) for dt, m in zip(levels, counts)]
        else:
            h = [c.sim.grid_lim / n for n in levels]
            fills = [None, None, None] if row.refinement == "n_grid" else [None, 1.5 * c.fill.resolution, 2 * c.fill.resolution]
            runs = [(row.dt, int(n), r, m) for n, r, m in zip(levels, fills, counts)]
        # each level was simulated (the log names every rollout's dt, grid, fill and particles)
        assert all(any(abs(dt - a) <= 1e-6 * a and (n, r, m) == (b, q, k) for a, b, q, k in simulated)
                   for dt, n, r, m in runs), (runs, simulated)
        p = observed_order(h, row.change_1_2, row.change_2_3)
        assert bool(row.asymptotic) == (p is not None)
        if p is None:
            assert row.observed_order == NOT_ASYMPTOTIC and row.richardson_error_pct == NOT_ASYMPTOTIC
        else:
            assert float(row.observed_order) == pytest.approx(p, rel=1e-6)
            assert np.isfinite(float(row.richardson_error_pct)) and float(row.richardson_error_pct) >= 0
