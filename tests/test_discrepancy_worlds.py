"""Discrepancy cases in worlds the loop's model cannot match: a finer MPM grid and the FEM
reference (docs/discrepancy.md, section 5; docs/verification.md, the FEM world)."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pyarrow.parquet as pq
import pytest

from knockgs_core.discrepancy import CaseSpec, make_case, read_measured, world_acceptance, world_cases, world_contract
from knockgs_core.errors import InputError


@pytest.fixture(scope="module")
def pillow():
    from knockgs_core.assets import build_asset
    from knockgs_core.contract import load_contract

    contract = load_contract("pillow", "ci")
    return contract, build_asset(contract).particles


def test_world_cases_and_their_validation():
    cases = world_cases()
    assert [c.name for c in cases][:2] == ["finer_null", "finer_damping"] and {c.world for c in cases} == {"finer", "fem"}
    assert all(c.observation == "gs_tracks" and c.level == "high" for c in cases)
    assert {"finer_vertical_push", "fem_null", "fem_damping", "fem_gravity", "fem_stiffness_gradient_z"} <= {
        c.name for c in cases}
    # the cases before the FEM stiffness gradient keep their seeds and thetas
    assert [c.seed for c in cases] == list(range(2000, 2000 + len(cases))) and cases[-1].name == "fem_stiffness_gradient_z"
    with pytest.raises(InputError, match="world"):
        CaseSpec("x", "none", world="moon")


def test_the_finer_world_has_twice_the_grid_the_next_profiles_gaussians_and_the_loops_body(pillow):
    from knockgs_core.contract import cfl_dt

    contract, _ = pillow
    w = world_contract(contract)
    assert (w.sim.n_grid, w.fill.resolution) == (2 * contract.sim.n_grid, 2 * contract.fill.resolution)
    assert w.profile == "default" and w.asset.n_gaussians > contract.asset.n_gaussians
    assert w.sim.dt <= cfl_dt(w.materials, n_grid=w.sim.n_grid, grid_lim=w.sim.grid_lim) * (1 + 1e-12)
    # the same body as the loop's: the loop contract's volume rule, whatever the world's profile says
    from knockgs_core.contract import with_body

    solid = with_body(contract, volumes="enclosed")
    assert world_contract(contract).fill.volumes == "cell_share"
    assert world_contract(solid).fill.volumes == "enclosed"
    own = world_contract(solid, profile=contract.profile)
    assert own.asset == contract.asset and own.sim.n_grid == 2 * contract.sim.n_grid and own.fill.volumes == "enclosed"
    # a shell stated as a solid (the Vasedeck's contracts fill nothing) stays a solid in its world
    from knockgs_core.contract import load_contract

    vase = with_body(load_contract("vasedeck", "ci"), solid=True)
    w = world_contract(vase)
    assert not world_contract(load_contract("vasedeck", "ci")).fill.enabled
    assert w.fill == dataclasses.replace(vase.fill, resolution=2 * vase.fill.resolution) and w.fill.enabled


@pytest.fixture(scope="module")
def fem_null(pillow, tmp_path_factory):
    """The FEM world's null case, made once: (its spec, its truth record, the measured and the
    truth folders)."""
    contract, particles = pillow
    spec = next(c for c in world_cases() if c.name == "fem_null")
    root = tmp_path_factory.mktemp("fem_null")
    truth = make_case(spec, contract, particles, measured_dir=root / "m", truth_dir=root / "t")
    return spec, truth, root / "m", root / "t"


@pytest.mark.slow
def test_the_fem_world_delivers_the_contracts_impulse_and_tracks_the_mpm(pillow, fem_null):
    """The FEM world's mesh has the MPM's volume, its probe load the contract's total impulse,
    and its Probe-A response (the null case's clean motion of the loop's Gaussian particles)
    follows the MPM's at the same theta within the discretization gap (12 % measured at ci);
    planted damping and a modulus gradient change it as they should."""
    # About 15 s, after the shared null case (about 30 s: two FEM rollouts on the world's mesh,
    # each factorizing two sparse systems of about 21,000 DOFs): one assembly on that mesh, one
    # MPM rollout, three FEM rollouts over a third of the record on a mesh of cells twice as
    # large and two assemblies there.
    import skfem  # noqa: F401

    from knockgs_core.fem import FemWorld, assemble_elasticity, fem_world_mesh, fem_world_rollout
    from knockgs_core.fem._world import _cells, _probe_load
    from knockgs_core.rollout import run_rollout
    from knockgs_core.sim import StiffnessGradient

    contract, particles = pillow
    spec, _, _, truth_dir = fem_null
    geo = fem_world_mesh(contract, particles)
    m = contract.materials["base"]
    system = assemble_elasticity(geo["mesh"], E=m.E, nu=m.nu, rho=m.rho, degree=2)
    assert system.volume == pytest.approx(geo["volume"], rel=1e-9)
    pr = contract.resolve_probes(particles)["standard_x"]
    cells, counts = _cells(particles.positions, geo["dx"])
    scale = contract.probe_reference_particles / len(particles.positions)
    load = _probe_load(system, cells, counts, geo["dx"], np.asarray(pr.force) * scale)
    comp = np.zeros(system.n_dofs, int)
    for k in range(3):
        comp[system.basis.nodal_dofs[k]] = k
        if system.basis.edge_dofs.size:
            comp[system.basis.edge_dofs[k]] = k
    total = abs(pr.force[0]) * contract.probe_reference_particles
    assert abs(load[comp == 0].sum()) == pytest.approx(total, rel=1e-9) and abs(load[comp == 1].sum()) < 1e-9 * total
    pts = np.asarray(particles.positions[: particles.n_gs], np.float64)
    theta = spec.theta
    with np.load(truth_dir / "clean.npz") as z:
        Y = z["calib"].astype(np.float64)  # the FEM world at theta under standard_x, at the loop's Gaussian particles
    X = np.asarray(run_rollout(contract, theta, "standard_x", particles=particles).positions, np.float64)
    X = X[:, : particles.n_gs]
    u, v = Y - Y[0], X - X[0]
    gap = np.sqrt(((u - v) ** 2).sum(-1).mean() / (v**2).sum(-1).mean())
    assert 0.02 < gap < 0.25
    assert np.sign(u[-1, :, 0].mean()) == np.sign(v[-1, :, 0].mean()) == -1.0
    # the planted effects over the first third of the record (a rollout's frames do not depend
    # on how many follow) and on the world's voxel mesh of cells twice the MPM's (n_grid 16): what
    # each effect does to the response is the same on any mesh, and each rollout on this one
    # factorizes systems of an eighth of the DOFs (the world's mesh is the null case's above)
    early = 11
    probe_x = contract.probes["standard_x"]
    short = dataclasses.replace(contract, probes={**contract.probes, "standard_x": dataclasses.replace(
        probe_x, export=dataclasses.replace(probe_x.export, n_frames=early))})
    coarse = contract.sim.n_grid // 2

    def rollout(**effects):
        Y = fem_world_rollout(short, particles, theta, "standard_x", pts, world=FemWorld(n_grid=coarse, **effects))
        assert len(Y) == early
        return Y - Y[0]

    u = rollout()
    # mass-proportional Rayleigh damping (C = alpha M) damps every mode of the free motion after
    # the impulse by exp(-alpha t / 2): 0.74 at the end of the third (the damped frequencies
    # move by alpha^2 / 8 omega^2, far below a percent)
    alpha = 3.0
    ud = rollout(rayleigh_alpha=alpha)
    t_end = (early - 1) * probe_x.export.frame_dt
    assert np.abs(ud[-1]).mean() / np.abs(u[-1]).mean() == pytest.approx(math.exp(-alpha * t_end / 2), rel=0.05)
    # a modulus graded along z: slope 0 is the same world (its modulus field is the uniform
    # one, the stiffness matrix unchanged); a softer base moves the body more
    assert FemWorld(stiffness_slope=0.0) == FemWorld()
    z_p = np.asarray(particles.positions, dtype=np.float64)[:, 2]
    mesh = fem_world_mesh(contract, particles, world=FemWorld(n_grid=coarse))["mesh"]
    uniform = assemble_elasticity(mesh, E=m.E, nu=m.nu, rho=m.rho, degree=2)
    flat = assemble_elasticity(mesh, E=m.E, nu=m.nu, rho=m.rho, degree=2,
                               stiffness_field=lambda x: StiffnessGradient(slope=0.0, axis=2).factor(x[2], z_p.min(), z_p.max()))
    assert (flat.K != uniform.K).nnz == 0
    ug = rollout(stiffness_slope=2.0)
    assert np.sqrt(np.mean(ug**2)) > 1.02 * np.sqrt(np.mean(u**2))


@pytest.mark.slow
def test_a_fem_case_is_observed_without_identity_and_its_truth_kept_apart(pillow, fem_null):
    contract, particles = pillow
    _, truth, mdir, tdir = fem_null
    m = read_measured(mdir / "measured_calib.parquet")
    assert m.particle is None and m.n_frames == contract.probes["standard_x"].export.n_frames
    meta = json.loads(pq.read_schema(mdir / "measured_calib.parquet").metadata[b"knockgs_measurement"])
    assert set(meta) <= {"object", "profile", "probe"} and meta["profile"] == "ci"
    with np.load(tdir / "clean.npz") as z:
        assert z["calib"].shape == (m.n_frames, particles.n_gs, 3) and z["heldout"].shape[1] == particles.n_gs
    assert truth["world"] == "fem" and truth["world_description"]["cells"] > 100
    assert truth["strength"] is None and truth["planted_parameter"] is None  # a null world: nothing planted
    assert not list(mdir.glob("truth*")) and (tdir / "truth.json").exists()


def test_world_acceptance_rule():
    base = {"in_catalogue": True, "heldout_traj_rmse_before": 2.0, "heldout_traj_rmse_after": 1.0, "heldout_improvement": 2.0,
            "theta_in_interval": True, "approximation": ""}
    assert world_acceptance({**base, "planted_effect": "damping", "identified_effect": "damping"})[0]
    assert not world_acceptance({**base, "planted_effect": "damping", "identified_effect": "damping",
                                 "heldout_improvement": 1.3})[0]
    assert world_acceptance({**base, "planted_effect": "none", "identified_effect": "none"})[0]
    assert not world_acceptance({**base, "planted_effect": "none", "identified_effect": "none", "theta_in_interval": False})[0]
    push = {**base, "planted_effect": "vertical_push", "in_catalogue": False}
    assert world_acceptance({**push, "identified_effect": "none"})[0]
    assert not world_acceptance({**push, "identified_effect": "gravity"})[0]
    assert not world_acceptance({**push, "identified_effect": "none", "heldout_traj_rmse_after": 2.5})[0]
    # the FEM world's Rayleigh damping is mass- plus stiffness-proportional: either catalogue term
    # names it; the finer world's damping is the catalogue's velocity damping only
    fem = {**base, "planted_effect": "damping", "world": "fem"}
    assert world_acceptance({**fem, "identified_effect": "viscosity"})[0]
    assert world_acceptance({**fem, "identified_effect": "damping+viscosity"})[0]
    assert not world_acceptance({**fem, "identified_effect": "gravity"})[0]
    assert not world_acceptance({**base, "planted_effect": "damping", "world": "finer", "identified_effect": "viscosity"})[0]
    # a grid whose floor table puts its floor above half the effect says so: judged by its interval
    floored = {**base, "planted_effect": "damping", "identified_effect": "none", "heldout_improvement": 1.0,
               "floor_within": False, "floor_pct": 39.0}
    assert world_acceptance(floored)[0] and "said so" in world_acceptance(floored)[1]
    assert not world_acceptance({**floored, "theta_in_interval": False})[0]
    assert not world_acceptance({**floored, "floor_within": True})[0]       # within: an effect must be named


@pytest.mark.slow
def test_the_worlds_target_plans_every_world_case_and_stays_out_of_all(tmp_path):
    from _workflow import scratch_copy, snakemake

    work = scratch_copy(tmp_path)
    out = snakemake(work, "-n", "discrepancy_worlds", "--configfile=config/ci.yaml")
    assert out.returncode == 0, out.stderr[-3000:]
    for c in world_cases():
        assert f"case={c.name}" in out.stdout
    assert "discrepancy_worlds_table" in out.stdout and "audit_discrepancy_worlds_truth" in out.stdout
    # the world cases stand for measured data: their runs read the floor table of the loop's body
    runs = [block.split("output:")[0] for block in out.stdout.split("rule discrepancy_run:")[1:]]
    assert len(runs) == len(world_cases()) and all("discrepancy/ci/floor_pillow.csv" in r for r in runs)
    assert out.stdout.count("rule discrepancy_floor:") == 1
    from knockgs_core.discrepancy import default_cases

    own = snakemake(work, "-n", f"results/ci/discrepancy/reports/{default_cases()[0].name}/report.md",
                    "--configfile=config/ci.yaml")
    assert own.returncode == 0 and "rule discrepancy_run:" in own.stdout and "floor_pillow" not in own.stdout
    sub = snakemake(work, "-n", "discrepancy_worlds", "--configfile=config/ci.yaml", "--config",
                    "discrepancy={worlds: [fem_null]}")
    assert sub.returncode == 0, sub.stderr[-3000:]
    assert "case=fem_null" in sub.stdout and "case=finer_null" not in sub.stdout
    bad = snakemake(work, "-n", "discrepancy_worlds", "--configfile=config/ci.yaml", "--config", "discrepancy={worlds: [moon]}")
    assert bad.returncode != 0 and "discrepancy.worlds" in (bad.stderr + bad.stdout)
    everything = snakemake(work, "-n", "all", "--configfile=config/ci.yaml")
    assert everything.returncode == 0 and "discrepancy_worlds" not in everything.stdout
