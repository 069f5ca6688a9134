"""Discretization and object boundaries of a frozen library (knockgs_core.experiments._boundaries):
conditions change exactly one contract component, the probe-force rules deliver the per-particle
or total force they promise, the unchanged condition is the main rollout bit for bit, the tables'
invariants, and (ci workflow) a rebuilt matched library at the unchanged specification reproduces
the main local-ridge result exactly."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from _workflow import CI, CI_RUN_CONFIG, copy_run, scratch_copy, snakemake

from knockgs_core.assets import build_asset
from knockgs_core.calibration import calibrate
from knockgs_core.contract import load_contract
from knockgs_core.errors import InputError
from knockgs_core.experiments import (
    BoundarySettings,
    boundary_condition,
    boundary_conditions,
    boundary_note,
    boundary_table,
    condition_contract,
    condition_world,
    loo_table,
    resolution_profile,
    shared_library,
)
from knockgs_core.rollout import run_rollout

ROOT = Path(__file__).resolve().parents[1]
THETA = (0.95, 1.35)


@pytest.fixture(scope="module")
def pillow():
    return load_contract("pillow", "ci")


def _flat(d, prefix=""):
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def _changed(a, b) -> set[str]:
    fa, fb = _flat(a.to_dict()), _flat(b.to_dict())
    return {k for k in fa.keys() | fb.keys() if fa.get(k) != fb.get(k)}


# ------------------------------------------------------------------------------ settings


def test_settings_defaults_are_the_config_schema_defaults():
    schema = yaml.safe_load((ROOT / "workflow/schemas/config.schema.yaml").read_text())
    props = schema["properties"]["boundaries"]["properties"]
    for f in dataclasses.fields(BoundarySettings):
        default = f.default
        assert props[f.name]["default"] == (list(default) if isinstance(default, tuple) else default), f.name
    assert props["conditions"]["items"]["enum"] == list(BoundarySettings().conditions)


@pytest.mark.parametrize("kwargs, field", [({"conditions": ["fill_denisty"]}, "conditions"),
                                           ({"rebuild": ["gird"]}, "rebuild"),
                                           ({"n_grid_scale": 1.0}, "n_grid_scale"),
                                           ({"fill_seeds": 0}, "fill_seeds"),
                                           ({"fill_particles_per_cell": 0}, "fill_particles_per_cell"),
                                           ({"resolution_profile": "laptop"}, "resolution_profile")])
def test_bad_settings_are_one_line_errors(kwargs, field):
    with pytest.raises(InputError) as exc:
        BoundarySettings(**kwargs)
    assert exc.value.field == field and "\n" not in str(exc.value)


def test_conditions_follow_the_contract(pillow):
    s = BoundarySettings(fill_seeds=2)
    assert boundary_conditions(pillow, s) == ["reference", "fill_density", "fill_density_equal_force",
                                              "fill_seed1", "fill_seed2", "grid", "resolution"]
    # no interior fill: no fill conditions; its ci and default profiles have one resolution: no resolution world
    ficus = load_contract("ficus", "ci")
    assert boundary_conditions(ficus, s) == ["reference", "grid"]
    with pytest.raises(InputError) as exc:
        boundary_condition(ficus, "resolution", s)
    assert exc.value.field == "resolution_profile"
    with pytest.raises(InputError) as exc:   # a profile is not its own resolution world
        boundary_condition(pillow, "resolution", BoundarySettings(resolution_profile="ci"))
    assert exc.value.field == "resolution_profile"
    with pytest.raises(InputError) as exc:
        boundary_condition(ficus, "fill_density", s)
    assert exc.value.field == "fill.enabled"
    for bad in ("fill_seed3", "fill_seedx", "dt"):
        with pytest.raises(InputError):
            boundary_condition(pillow, bad, s)
    # the same fill density as the contract is no changed condition
    with pytest.raises(InputError) as exc:
        boundary_condition(pillow, "fill_density", BoundarySettings(fill_particles_per_cell=pillow.fill.max_particles_per_cell))
    assert exc.value.field == "fill_particles_per_cell"


@pytest.mark.parametrize("name, changed", [("reference", set()), ("fill_density", {"fill.max_particles_per_cell"}),
                                           ("fill_density_equal_force", {"fill.max_particles_per_cell"}),
                                           ("fill_seed2", {"fill.seed"}), ("grid", {"sim.n_grid"})])
def test_each_condition_changes_one_component(pillow, name, changed):
    s = BoundarySettings()
    cond = boundary_condition(pillow, name, s)
    variant = condition_contract(pillow, cond)
    assert _changed(pillow, variant) == changed
    assert (variant.hash == pillow.hash) == (not changed)
    # the original library's contract holds only where nothing but the fill's realization changed
    assert cond.contract_preserved == (name in ("reference", "fill_seed2"))


def test_a_finer_grid_keeps_the_substep_within_its_cfl_bound(pillow):
    cond = boundary_condition(pillow, "grid", BoundarySettings(n_grid_scale=2.0))
    variant = condition_contract(pillow, cond)
    assert variant.sim.n_grid == 2 * pillow.sim.n_grid
    assert variant.sim.dt <= variant.cfl_dt() * (1 + 1e-12) and variant.sim.dt < pillow.sim.dt
    frame_dt = pillow.calibration_probe.export.frame_dt
    assert abs(frame_dt / variant.sim.dt - round(frame_dt / variant.sim.dt)) < 1e-9


def test_a_new_fill_seed_is_a_new_realization_of_the_same_fill(pillow):
    orig = build_asset(pillow).particles
    world = condition_world(pillow, "fill_seed1", BoundarySettings(), original_particles=orig)
    new = world.particles
    assert len(new) == len(orig) and new.n_gs == orig.n_gs and new.n_fill > 0
    np.testing.assert_array_equal(new.positions[: new.n_gs], orig.positions[: orig.n_gs])
    assert not np.array_equal(new.positions[new.n_gs:], orig.positions[orig.n_gs:])
    assert world.force_factors[pillow.roles["calibration"]] == 1.0


def test_the_resolution_world_is_the_other_profiles_contract_exactly(pillow):
    """Data made at another resolution: that profile's contract, particles and probe forces as
    they are (force factors 1), not the library's contract with one component changed."""
    s = BoundarySettings()
    assert resolution_profile(pillow, s) == "default"
    assert resolution_profile(load_contract("pillow", "default"), s) == "ci"
    cond = boundary_condition(pillow, "resolution", s)
    assert (cond.kind, cond.value, cond.force, cond.contract_preserved) == ("resolution", "default", "contract", False)
    world = condition_world(pillow, "resolution", s, original_particles=build_asset(pillow).particles)
    other = load_contract("pillow", "default")
    assert world.contract.hash == other.hash and world.contract.profile == "default"
    assert set(world.force_factors) == set(other.probes) and set(world.force_factors.values()) == {1.0}
    assert len(world.particles) == len(build_asset(other).particles)
    assert world.summary(build_asset(pillow).particles)["n_grid"] == other.sim.n_grid


# ------------------------------------------------------------------------------ probe forces (rollouts)


@pytest.fixture(scope="module")
def rollouts(pillow):
    """Probe-A rollouts at THETA: the main one and those of three conditions."""
    probe = pillow.roles["calibration"]
    orig = build_asset(pillow).particles
    out = {"main": run_rollout(pillow, THETA, probe, particles=orig)}
    for name in ("reference", "fill_density", "fill_density_equal_force"):
        world = condition_world(pillow, name, BoundarySettings(), original_particles=orig)
        out[name] = world.rollout(THETA, probe)
        out[name].meta["summary"] = world.summary(orig)
    return out


@pytest.mark.slow
def test_the_unchanged_condition_is_the_main_rollout_bit_for_bit(rollouts):
    np.testing.assert_array_equal(rollouts["reference"].positions, rollouts["main"].positions)
    assert rollouts["reference"].meta["contract_hash"] == rollouts["main"].meta["contract_hash"]


@pytest.mark.slow
def test_fill_density_keeps_the_per_particle_force_and_equal_force_the_total(rollouts):
    main, per, tot = rollouts["main"].meta, rollouts["fill_density"].meta, rollouts["fill_density_equal_force"].meta
    n0, n1 = main["n_gs"] + main["n_fill"], per["n_gs"] + per["n_fill"]
    assert n1 < n0 and per["n_gs"] == main["n_gs"]   # fewer fill particles, the same Gaussians
    # the simulator's own accounting (model.probe_force, model.total_probe_force)
    np.testing.assert_allclose(per["probe_force_per_particle_step"], main["probe_force_per_particle_step"], rtol=1e-12)
    np.testing.assert_allclose(per["total_probe_force"], np.asarray(main["total_probe_force"]) * n1 / n0, rtol=1e-12)
    np.testing.assert_allclose(tot["total_probe_force"], main["total_probe_force"], rtol=1e-12)
    # the table's total-force ratio says the same
    probe = main["probe"]["name"]
    assert per["summary"]["total_force_ratio"][probe] == pytest.approx(n1 / n0, rel=1e-12)
    assert tot["summary"]["total_force_ratio"][probe] == pytest.approx(1.0, rel=1e-12)
    # a changed fill density changes the response, at either force
    for name in ("fill_density", "fill_density_equal_force"):
        assert not np.allclose(rollouts[name].positions[:, : main["n_gs"]], rollouts["main"].positions[:, : main["n_gs"]])


# ------------------------------------------------------------------------------ tables


def _metrics(rng, cells):
    rows = []
    for cond, lib, scale in cells:
        for t in range(5):
            rows.append({"object": "pillow", "condition": cond, "library": lib, "target": f"target_{t:03d}",
                         "joint_error_pct": scale * rng.uniform(0.1, 1.0), "probe": "standard_y",
                         "traj_rmse": scale * rng.uniform(1e-5, 1e-4)})
    return pd.DataFrame(rows)


def _summary(name, preserved, description="d"):
    return {"condition": name, "component": "x", "contract_preserved": preserved, "particles": 10, "n_grid": 32,
            "calibration_probe": "standard_x", "total_force_ratio": {"standard_x": 1.0}, "description": description}


def test_boundary_table_rows_and_invariants(rng):
    cells = [("reference", "original", 1), ("fill_density", "rebuilt", 1), ("fill_density", "original", 30),
             ("fill_seed1", "original", 2), ("fill_seed2", "original", 3)]
    m = _metrics(rng, cells)
    sums = {n: _summary(n, n in ("reference", "fill_seed1", "fill_seed2"))
            for n in ("reference", "fill_density", "fill_seed1", "fill_seed2")}
    t = boundary_table(m, sums, probe="standard_y")
    # summaries' order, original before rebuilt; a rebuilt library preserves the contract
    assert list(zip(t["condition"], t["library"])) == [("reference", "original"), ("fill_density", "original"),
                                                       ("fill_density", "rebuilt"), ("fill_seed1", "original"),
                                                       ("fill_seed2", "original")]
    assert list(t["contract_preserved"]) == [True, False, True, True, True]
    assert (t["joint_error_max_pct"] >= t["joint_error_mean_pct"]).all() and (t["n_targets"] == 5).all()
    for r in t.itertuples():
        e = m[(m["condition"] == r.condition) & (m["library"] == r.library)]
        assert r.joint_error_mean_pct == pytest.approx(e["joint_error_pct"].mean(), rel=1e-12)
        assert r.traj_rmse_standard_y == pytest.approx(e["traj_rmse"].mean(), rel=1e-12)
    seeds = m[m["condition"].str.startswith("fill_seed")]["joint_error_pct"]
    note = boundary_note(t, profile="ci", probe_a="standard_x", probe_b="standard_y")
    assert f"mean {seeds.mean():.3g} %, max {seeds.max():.3g} %" in note
    with pytest.raises(InputError):
        boundary_table(pd.concat([m, m.iloc[:1]]), sums, probe="standard_y")


def test_shared_library_calibrates_another_objects_queries():
    lib = pd.read_csv(ROOT / "tests/data/knockgs-ficus/library.csv")
    queries = pd.read_csv(ROOT / "tests/data/knockgs-ficus/queries.csv")
    shared = shared_library({"a": lib.iloc[:27], "b": lib.iloc[27:], "c": lib})
    assert len(shared) == 2 * len(lib) and shared["case_name"].is_unique
    assert set(shared["object"]) == {"a", "b", "c"} and shared["case_name"].str.match(r"^[abc]/").all()
    out = calibrate(shared, queries, "local_ridge", k=10, alpha=1e-3)
    assert len(out["predictions"]) == len(queries)
    with pytest.raises(InputError):
        shared_library({"a": lib.drop(columns=["E_scale"])})
    with pytest.raises(InputError):
        shared_library({})


def test_loo_table(rng):
    m = _metrics(rng, [("leave_one_object_out", "shared", 40)])
    own = _metrics(rng, [("main", "own", 1)])
    t = loo_table({"pillow": m}, {"pillow": own}, probes={"pillow": "standard_y"}, trained_on={"pillow": ["ficus", "vasedeck"]})
    r = t.iloc[0]
    assert r["library"] == "shared (ficus + vasedeck)" and not r["contract_preserved"]
    assert r["joint_error_mean_pct"] == pytest.approx(m["joint_error_pct"].mean())
    assert r["joint_error_max_pct"] == pytest.approx(m["joint_error_pct"].max())
    assert r["own_joint_error_mean_pct"] == pytest.approx(own["joint_error_pct"].mean())


# ------------------------------------------------------------------------------ workflow (ci profile)


def test_boundaries_target_plans_every_object_and_the_loo_table(tmp_path):
    work = scratch_copy(tmp_path)
    out = snakemake(work, "-n", "boundaries", "--configfile=config/ci.yaml")
    assert out.returncode == 0, out.stderr[-3000:]
    planned = out.stdout
    for o in ("pillow", "ficus", "vasedeck"):
        assert f"{CI}/tables/boundaries_{o}.csv" in planned and f"{CI}/figures/boundaries_{o}.png" in planned
        assert f"{CI}/boundaries/{o}/grid/asset.json" in planned
    assert f"{CI}/tables/loo_object.csv" in planned and f"{CI}/boundaries/loo/pillow/library.csv" in planned
    # fill conditions only where a contract has an interior fill (Pillow's)
    assert f"{CI}/boundaries/pillow/fill_seed3/asset.json" in planned
    assert f"{CI}/boundaries/ficus/fill_density" not in planned
    # a world made at the default profile's resolution, with its rebuilt library, where that differs
    for o in ("pillow", "vasedeck"):
        assert f"{CI}/boundaries/{o}/resolution/asset.json" in planned
        assert f"{CI}/boundaries/{o}/resolution/estimates/rebuilt.json" in planned
    assert f"{CI}/boundaries/ficus/resolution" not in planned   # its ci and default profiles are one resolution


BOUNDARIES_REFERENCE = (*CI_RUN_CONFIG, "boundaries={conditions: [reference], rebuild: [reference]}")


@pytest.fixture(scope="module")
def ci_boundaries(ci_run, tmp_path_factory):
    """The ci-profile Pillow boundaries table at the unchanged specification, rebuilt, beside the
    main local-ridge evaluation: made in a copy of the shared ci run's asset, library, estimates
    and evaluations (tests/conftest.py), so only the boundaries' own jobs run."""
    work = copy_run(ci_run, tmp_path_factory.mktemp("bwf"), "assets", "rollouts/pillow/lib", "rollouts/pillow/eval",
                    "descriptors/pillow", "estimates/pillow/main", "metrics/pillow/main")
    targets = [f"{CI}/tables/boundaries_pillow.csv", f"{CI}/figures/boundaries_pillow.png",
               f"{CI}/metrics/pillow/main/local_ridge.csv"]
    out = snakemake(work, *targets, "--cores", "2", *BOUNDARIES_REFERENCE)
    assert out.returncode == 0, out.stderr[-4000:]
    assert "rule rollout_library:" not in out.stdout + out.stderr  # the shared run's library is used as it is
    return work


@pytest.mark.slow
def test_a_rebuilt_library_at_the_unchanged_contract_reproduces_the_main_result(ci_boundaries):
    w = ci_boundaries
    B = w / CI / "boundaries/pillow/reference"
    # the re-simulated candidates give the main library byte for byte
    assert (B / "descriptors/library.csv").read_bytes() == (w / CI / "descriptors/pillow/library.csv").read_bytes()
    main = pd.read_csv(w / CI / "metrics/pillow/main/local_ridge.csv")
    main_b = main[main["probe"] == "standard_y"].set_index("target")
    for library in ("original", "rebuilt"):
        m = pd.read_csv(B / f"metrics/{library}.csv").set_index("target")
        assert list(m.index) == list(main_b.index)
        for col in ("E_hat", "rho_hat", "joint_error_pct", "traj_rmse"):
            np.testing.assert_array_equal(m[col].to_numpy(), main_b[col].to_numpy(), err_msg=f"{library} {col}")
    t = pd.read_csv(w / CI / "tables/boundaries_pillow.csv")
    assert list(zip(t["condition"], t["library"])) == [("reference", "original"), ("reference", "rebuilt")]
    assert t["contract_preserved"].all() and (t["total_force_ratio"] == 1.0).all()
    per_target = main.drop_duplicates("target")["joint_error_pct"]
    assert t["joint_error_mean_pct"].tolist() == pytest.approx([per_target.mean()] * 2, rel=1e-7)   # %.8g in the CSV
    assert t["joint_error_max_pct"].tolist() == pytest.approx([per_target.max()] * 2, rel=1e-7)
    assert (w / CI / "figures/boundaries_pillow.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.slow
def test_boundaries_rerun_is_a_no_op(ci_boundaries):
    out = snakemake(ci_boundaries, "-n", f"{CI}/tables/boundaries_pillow.csv", *BOUNDARIES_REFERENCE)
    assert out.returncode == 0 and "Nothing to be done" in out.stdout + out.stderr, out.stdout[-2000:]
