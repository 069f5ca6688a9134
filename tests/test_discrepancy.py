"""The discrepancy loop: measured-data I/O, correspondence, residual views, and the loop on
planted-effect cases of the ci pillow (a reduced catalogue keeps the run short; the full
catalogue and every effect run in the workflow, results/<profile>/tables/discrepancy.md)."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest

from knockgs_core.discrepancy import (
    CaseSpec,
    LoopSettings,
    Measurement,
    acceptance,
    audit_truth_separation,
    evaluate_files,
    make_case,
    match_points,
    read_measured,
    residual_views,
    run_files,
    view_summary,
    write_measured,
)
from knockgs_core.errors import InputError


# -------------------------------------------------------------------------------------
# measured files
# -------------------------------------------------------------------------------------
def _measurement(rng, identity=True, T=5, M=7):
    X = rng.normal(size=(T, M, 3))
    ids = np.arange(10, 10 + M)
    return Measurement(points=X, frames=np.arange(T), times=None, particle=ids if identity else None, track=ids,
                       meta={"object": "pillow", "probe": "standard_x"}, source="test")


@pytest.mark.parametrize("suffix", [".parquet", ".csv", ".npz"])
@pytest.mark.parametrize("identity", [True, False])
def test_measured_round_trip(tmp_path, rng, suffix, identity):
    m = _measurement(rng, identity)
    path = tmp_path / f"m{suffix}"
    write_measured(path, m)
    back = read_measured(path)
    np.testing.assert_allclose(back.points, m.points, rtol=1e-7, atol=1e-12)
    assert back.has_identity == identity
    np.testing.assert_array_equal(back.frames, m.frames)
    if identity:
        np.testing.assert_array_equal(back.particle, m.particle)
    if suffix != ".csv":
        assert back.meta == m.meta


def test_measured_long_table_rows_in_any_order_and_times(tmp_path, rng):
    T, M = 4, 3
    X = rng.normal(size=(T, M, 3))
    rows = [{"time": 0.02 * t, "track": 5 + i, "x": X[t, i, 0], "y": X[t, i, 1], "z": X[t, i, 2]}
            for t in range(T) for i in range(M)]
    df = pd.DataFrame(rows).sample(frac=1.0, random_state=1)
    df.to_csv(tmp_path / "m.csv", index=False)
    m = read_measured(tmp_path / "m.csv")
    np.testing.assert_allclose(m.points, X)
    assert not m.has_identity
    np.testing.assert_array_equal(m.frame_indices(0.02, 31), np.arange(T))
    with pytest.raises(InputError, match="not on the probe's export schedule"):
        m.frame_indices(0.03, 31)
    with pytest.raises(InputError, match="past the probe"):
        m.frame_indices(0.02, 3)


def test_measured_file_errors(tmp_path, rng):
    m = _measurement(rng)
    write_measured(tmp_path / "m.csv", m)
    df = pd.read_csv(tmp_path / "m.csv")
    df.iloc[:-1].to_csv(tmp_path / "missing.csv", index=False)
    with pytest.raises(InputError, match="every point must be in every frame"):
        read_measured(tmp_path / "missing.csv")
    df.assign(track=df.particle).to_csv(tmp_path / "both.csv", index=False)
    with pytest.raises(InputError, match="exactly one of the columns 'particle'"):
        read_measured(tmp_path / "both.csv")
    df[df.frame > 0].to_csv(tmp_path / "noframe0.csv", index=False)
    with pytest.raises(InputError, match="start at 0"):
        read_measured(tmp_path / "noframe0.csv")
    with pytest.raises(InputError, match="unknown fields"):
        Measurement(points=m.points, frames=m.frames, times=None, particle=None, track=m.track, meta={"theta": [1, 1]})
    with pytest.raises(InputError, match="unknown format"):
        read_measured(tmp_path / "m.txt") if (tmp_path / "m.txt").write_text("x") else None


def test_match_points_identity_and_nearest_gaussian(rng):
    rest = rng.uniform(0.5, 1.5, size=(50, 3))
    n_gs = 30
    X = np.repeat(rest[None, [3, 40, 7]], 4, axis=0) + 1e-4
    m = Measurement(points=X, frames=np.arange(4), times=None, particle=np.array([3, 40, 7]), track=np.arange(3))
    c = match_points(m, rest, n_gs)
    np.testing.assert_array_equal(c.index, [3, 40, 7])
    # without identity, point 2 (at fill particle 40) may only match a Gaussian particle
    m2 = Measurement(points=X, frames=np.arange(4), times=None, particle=None, track=np.arange(3))
    c2 = match_points(m2, rest, n_gs)
    assert c2.index[0] == 3 and c2.index[2] == 7 and c2.index[1] < n_gs
    assert c2.index[1] == np.argmin(np.linalg.norm(rest[:n_gs] - rest[40], axis=1))
    # observation without identity: the simulated displacement starts from the measured frame 0
    sim = np.zeros((4, 50, 3))
    sim[:, :, 0] = np.arange(4)[:, None]
    obs = c2.observe(sim, np.arange(4), X[0])
    np.testing.assert_allclose(obs[:, :, 0] - X[0][None, :, 0], np.arange(4)[:, None] * np.ones(3))


def test_residual_views_closed_form():
    T, M = 64, 5
    t = np.arange(T) * 0.01
    rest = np.zeros((M, 3))
    f0, tau = 12.5, 0.2
    disp = 0.01 * np.exp(-t / tau) * np.sin(2 * np.pi * f0 * t)
    S = np.repeat(rest[None], T, axis=0)
    S[:, :, 0] += disp[:, None]
    Y = S.copy()
    v = residual_views(Y, S, t)
    s = view_summary(v)
    assert all(val == pytest.approx(0.0, abs=1e-15) for val in s.values())
    assert v["freq"][np.argmax(v["spectrum_measured"][:, 0])] == pytest.approx(f0, abs=1.0 / (T * 0.01))
    assert v["axis"] == 0
    # the decay envelope runs through the peaks: below the exponential bound, above the bound
    # one period later (a peak follows within a period), never increasing
    env = v["envelope_measured"]
    assert np.all(np.diff(env) <= 0) and env[0] == pytest.approx(np.abs(disp).max())
    mid = t < t[-1] - 1.0 / f0
    assert np.all(env <= 0.01 * np.exp(-t / tau) + 1e-15)
    assert np.all(env[mid] >= 0.9 * 0.01 * np.exp(-(t[mid] + 1.0 / f0) / tau))
    # a constant offset d on every point after frame 0: trajectory RMSE d * sqrt((T-1)/T)
    Y2 = S.copy()
    Y2[1:, :, 1] += 0.003
    s2 = view_summary(residual_views(Y2, S, t))
    assert s2["traj_rmse"] == pytest.approx(0.003 * np.sqrt((T - 1) / T), rel=1e-12)
    assert s2["centroid_rmse"] == pytest.approx(0.003 * np.sqrt((T - 1) / T), rel=1e-12)


def test_attribution_rows_serialize_in_the_order_their_stage_set_them():
    from knockgs_core.discrepancy import AttributionRound, AttributionRow

    failed = AttributionRow("poisson", "Poisson-ratio shift", error="unstable", rank=3)
    assert list(failed.to_dict()) == ["key", "label", "error", "explained_val", "refined", "rank"]
    screened = AttributionRow("damping", "velocity damping", trial_strength=1.0, coefficient=0.5, strength_estimate=0.5,
                              parameter="rate", value_estimate=0.5, unit="1/s", screen_explained_fit=0.9,
                              screen_explained_val=0.8)
    screened.explained_val = screened.screen_explained_val
    d = screened.to_dict()
    assert list(d)[-3:] == ["refined", "explained_val", "rank"] and d["explained_val"] == 0.8
    screened.refined, screened.theta_estimate, screened.explained_fit, screened.delta_bic = True, [1.0, 1.0], 0.95, -10.0
    assert list(screened.to_dict())[-6:] == ["refined", "theta_estimate", "explained_fit", "explained_val", "delta_bic", "rank"]
    rd = AttributionRound([1.0, 1.0], [], 9, 3, 1.0, 1.0, [1.0, 1.0], 1.0, 0.5, 1.0, 1.0, True, True, [failed]).to_dict()
    assert list(rd)[-2:] == ["table", "decision"] and "tried" not in rd and rd["table"][0]["error"] == "unstable"


def test_an_effect_is_judged_beyond_the_floor_where_the_residual_is_significant():
    """``decision_share``: of the validation energy above the noise and the discretization
    floor where that excess is significant, else of the whole theta-only residual."""
    from knockgs_core.discrepancy import AttributionRound, AttributionRow

    row = AttributionRow("plasticity", "von Mises plasticity", refined=True, explained_val=0.27)
    # theta-only validation energy 18, noise 1, floor 7.5: the excess is 9.5
    row.explained_excess = row.explained_val * 18.0 / (18.0 - 1.0 - 7.5)

    def round_(significant, model_floor):
        return AttributionRound([1.0, 1.0], [], 9, 3, 10.0, 18.0, [1.0, 1.0], 18.0, 1.0, 18.0 / 8.5 - 1, 17.0, True,
                                significant, [row], model_floor_val=model_floor)

    assert round_(True, 7.5).decision_share(row) == pytest.approx(0.27 * 18 / 9.5)  # 0.51: beyond the floor
    assert round_(False, 7.5).decision_share(row) == 0.27  # within the floor: of the whole residual
    assert round_(True, 0.0).decision_share(row) == 0.27  # no discretization floor (the model's own resolution)
    assert row.to_dict()["explained_excess"] == pytest.approx(0.27 * 18 / 9.5)
    # a row judged with its own term carries its own floor: the round's is not used
    row.model_floor_val, row.significant = 7.5, True
    assert round_(True, 0.0).decision_share(row) == pytest.approx(0.27 * 18 / 9.5)
    row.significant = False
    assert round_(True, 7.5).decision_share(row) == 0.27


def test_within_the_discretization_floor_no_effect_is_named_and_the_verdict_says_so():
    """A residual visible above the noise (17x its energy) but not beyond noise and
    discretization floor (18 against 1 + 15: excess 0.125 < 0.25): a candidate that explains
    90 % of it is not named, and the verdict opens with the floor's size; the same candidate on
    a round with no floor (data at the model's own resolution) passes, as it does where its own
    model's floor leaves the residual significant."""
    from knockgs_core.discrepancy import AttributionRound, AttributionRow, LoopSettings
    from knockgs_core.discrepancy._attribution import _passes, within_floor
    from knockgs_core.discrepancy._loop import _floor_statement, _verdict

    settings = LoopSettings()
    row = AttributionRow("damping", "velocity damping", refined=True, explained_val=0.9, delta_bic=-30.0)

    def round_(model_floor):
        floor = 1.0 + model_floor
        return AttributionRound([1.0, 1.0], [], 9, 3, 10.0, 18.0, [1.0, 1.0], 18.0, 1.0, 18.0 / floor - 1, 17.0, True,
                                18.0 / floor - 1 > settings.min_excess, [row], model_floor_val=model_floor)

    within, own = round_(15.0), round_(0.0)
    assert within_floor(within) and not _passes(within, row, settings)
    assert not within_floor(own) and _passes(own, row, settings)
    # a row scored with its own term: its own floor decides
    mine = dataclasses.replace(row, model_floor_val=2.0, significant=True)
    assert _passes(within, mine, settings)
    assert not _passes(own, dataclasses.replace(row, model_floor_val=15.0, significant=False), settings)
    model_error = {"change_share_of_response": 0.21, "floor_share_of_response": 0.083, "floor_rms_per_point": 1e-3,
                   "term_rms_per_point": 8e-4, "coefficient": 0.69}
    said = _floor_statement([within], model_error)
    assert said.startswith("the model at this resolution differs from its refined self by 21.0% of the measured response")
    assert "8.3%" in said and "effects smaller than that cannot be named" in said
    residual = {"excess_rms_per_point": 1e-3, "excess_fraction_of_response": 0.1}
    assert _verdict([], False, residual, model_error, "discretization", said).startswith(said)
    assert _floor_statement([own], model_error) is None  # no floor: nothing to say
    assert _floor_statement([within], None) is None  # no refined model: no floor measured


class _TermProblem:
    """A problem reduced to what judging a row with its own term reads: a fixed raw residual
    at every spec, the term, its profiled coefficient (fit rows = all rows, clipped to [0, 6])
    and the floor's weight and energy (the term's own, as :class:`Problem` does without floor
    shapes)."""

    def __init__(self, raw, term, settings):
        from knockgs_core.discrepancy._fitting import Problem

        self.raw, self.term, self.term_max, self.settings = raw, term, 6.0, settings
        self.fit_rows = self.val_rows = np.arange(raw.size)
        self.floor_shape = None
        self.coefficient = lambda raw: Problem.coefficient(self, raw)
        self.floor_weight = lambda c: Problem.floor_weight(self, c)
        self.model_floor = lambda rows, weight=1.0: Problem.model_floor(self, rows, weight)

    def raw_residual(self, spec):
        return self.raw


def test_a_candidate_is_judged_beyond_the_floor_its_own_model_shows():
    """Where theta has absorbed part of an effect, the theta-only model shows no
    discretization term; the candidate's own model does, and its floor (weight at its
    coefficient, at least the round's) sets what the candidate must explain."""
    from knockgs_core.discrepancy import AttributionRound, AttributionRow, LoopSettings
    from knockgs_core.discrepancy._attribution import _judge, _own_term, _passes
    from knockgs_core.discrepancy._forward import ModelSpec

    settings = LoopSettings()
    rng = np.random.default_rng(3)
    term = rng.normal(size=400)
    term *= 5.0 / np.linalg.norm(term)  # energy 25 m^2 per unit coefficient
    c = 0.3  # the own model's data lie 0.3 of a refinement step away: weight (0.3 - 0.15) / 0.25 = 0.6
    left = rng.normal(size=400)
    left -= term * float(left @ term) / float(term @ term)  # what the term cannot take
    left *= math.sqrt(50.0) / np.linalg.norm(left)
    problem = _TermProblem(-c * term + left, term, settings)  # simulated minus measured
    row = AttributionRow("damping", "velocity damping", refined=True, delta_bic=-50.0,
                         refined_spec=ModelSpec((1.0, 1.0), (("damping", 1.0),)))
    rss_val = float(left @ left) + 40.0  # the theta-only model leaves 40 m^2 more
    _own_term(problem, row, lambda spec: problem, (rss_val, rss_val), 0.0)
    assert row.own_term and row.refined_problem is problem
    assert row.explained_val == pytest.approx(40.0 / rss_val)  # the term's part is taken by the term
    assert row.floor_weight == pytest.approx(0.6)
    assert row.model_floor_val == pytest.approx(0.6 * float(term @ term))
    noise = 1.0
    _judge([row], rss_val, noise, 0.0, settings)
    assert row.explained_excess == pytest.approx(40.0 / (rss_val - noise - 0.6 * float(term @ term)))
    att = AttributionRound([1.0, 1.0], [], 400, 400, rss_val, rss_val, [1.0, 1.0], rss_val, noise, 1.0, 1.0, True, True,
                           [row], model_floor_val=0.0)
    # on the round's floor (none) the row explains under half; beyond its own floor, more
    assert row.explained_val < settings.min_explained <= att.decision_share(row)
    assert _passes(att, row, settings)
    theta_floor = dataclasses.replace(row, model_floor_val=math.nan, significant=None)
    _judge([theta_floor], rss_val, noise, 0.0, settings)
    assert not _passes(att, theta_floor, settings)  # judged on the theta-only model's floor it fails
    # the round's weight is a lower bound
    _own_term(problem, row, lambda spec: problem, (rss_val, rss_val), 1.0)
    assert row.floor_weight == 1.0


def test_catalogue_viscosity_stays_within_the_explicit_stability_limit():
    # the viscosity candidate's trials and bound sit below half the stability limit of the
    # calibrated model (and below 5 % of the record); off, its strength 0 is no viscosity
    from knockgs_core.discrepancy._catalogue import CatalogueContext, default_catalogue
    from knockgs_core.sim import MaterialViscosity

    def visc(limit):
        ctx = CatalogueContext(horizon=0.6, rms_displacement=5e-3, max_dev_strain=0.05, shear_modulus=4e3,
                               nu_range=(0.3, 0.3), has_gravity=False, has_support=True, viscous_limit=limit)
        (cand,) = [c for c in default_catalogue(ctx) if c.key == "viscosity"]
        return cand

    wide, tight = visc(1.0), visc(0.004)
    assert wide.bounds == (0.0, 0.05 * 0.6) and tight.bounds == (0.0, 0.002)
    assert all(0 < u <= 0.8 * tight.bounds[1] for u in tight.trials) and len(wide.trials) == 3
    assert wide.one_sided and isinstance(wide.effect(0.001), MaterialViscosity) and wide.effect(0.0).is_off


def test_default_cases_cycle_through_the_main_targets():
    from knockgs_core.contract import load_targets
    from knockgs_core.discrepancy import default_cases

    main = load_targets("main")
    targets = sorted(zip(main["E_scale"], main["density_scale"]))
    thetas = [c.theta for c in default_cases()]
    assert thetas[:5] == targets and thetas[5:10] == targets
    assert default_cases([(0.5, 0.5)])[3].theta == (0.5, 0.5)


def test_case_table_files(tmp_path):
    from knockgs_core.discrepancy import case_table, write_case_table
    from knockgs_core.discrepancy._tables import TABLE_COLUMNS

    row = {c: 1.0 for c in TABLE_COLUMNS if c not in ("accepted", "note")}
    row.update(case="null", planted_effect="none", identified_effect="none", first_ranked="damping", unexplained=False,
               in_catalogue=True, observation="gs_identity", parameter="", planted_value="", estimated_value="")
    df = case_table([row])
    write_case_table(df, tmp_path / "t.csv", tmp_path / "t.md")
    assert (tmp_path / "t.csv").read_text().splitlines()[0] == ",".join(TABLE_COLUMNS)
    md = (tmp_path / "t.md").read_text()
    assert "1 of 1 cases meet the acceptance rule" in md and not md.endswith("\n\n")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["t.csv", "t.md"]  # no temporary file left


# -------------------------------------------------------------------------------------
# the loop on the ci pillow
# -------------------------------------------------------------------------------------
# three catalogue terms: a planted damping competes with a sustained load and a stiffness
# gradient, all screened and the best two refined through the simulator (the threshold-type
# support terms, refined whatever the screen says, and the full catalogue run in the workflow's
# cases). The cases are made by the loop's own model, so the runs by run_files go without the
# discretization term (tests/test_discrepancy_model_error.py); the null case, run by the command
# with its default settings, keeps it.
CATALOGUE = ("damping", "gravity", "stiffness_gradient_z")
SETTINGS = LoopSettings(catalogue=CATALOGUE, joint_iterations=5, refine_top=2, model_error_refine=None)
CASES = {
    "damping": CaseSpec("damping", "damping", "high", theta=(0.7, 1.2), seed=1),
    "null": CaseSpec("null", "none", theta=(0.95, 1.35), observation="gs_tracks", seed=2),
    "pulse": CaseSpec("pulse", "force_pulse", "high", theta=(0.8, 1.6), seed=3),
}


@pytest.fixture(scope="module")
def pillow():
    from knockgs_core.assets import build_asset, save_particles
    from knockgs_core.contract import load_contract

    contract = load_contract("pillow", "ci")
    return contract, build_asset(contract).particles, save_particles


def _two_substeps(contract):
    """The ci Pillow with its calibration and first held-out probe and 2 substeps per frame
    (dt = 1e-2 s, not 5e-3 s: the Probe-A response moves by 0.5 %, every rollout takes half the
    time; tests/test_discrepancy_model_error.py), the model that makes the cases and that the
    files route loads for ``pillow``/``ci``."""
    calib, held = contract.roles["calibration"], contract.roles["heldout"][0]
    return dataclasses.replace(
        contract, probes={p: contract.probes[p] for p in (calib, held)},
        roles={"calibration": calib, "heldout": [held], "diagnostic": []}, probe_selected_reference={},
        probe_force_match={}, sim=dataclasses.replace(contract.sim, dt=contract.probes[calib].export.frame_dt / 2))


class _Cases:
    """The cases of :data:`CASES` (a planted catalogue effect, none, one outside the catalogue),
    each made and run through the loop from files, as the command line and the workflow do, the
    first time a test reads it (a test pays for the cases it reads): the null case by the
    `knockgs discrepancy run` command itself (``rc``: its exit status; ``result``: its
    result.json, with the command's default settings but the catalogue), the other two by
    :func:`run_files` (``result``: the DiscrepancyResult); ``row``: the evaluation, ``dirs``:
    the measured, truth and run folders. The model is :func:`_two_substeps`'s: it makes the
    cases, and the files route, which loads the contract by name, is handed it in place of the
    ci contract (the same object, profile, particles and probes at half the substeps)."""

    def __init__(self, contract, particles, root):
        self.contract, self.particles, self.root = _two_substeps(contract), particles, root
        self.particles_file = root / "particles.npz"
        self._done = {}

    def _load_contract(self, real):
        def load(name, profile="default", **kw):
            if (name, profile) == ("pillow", "ci") and not kw.get("config_dir") and kw.get("n_grid") is None:
                return self.contract
            return real(name, profile, **kw)

        return load

    def __getitem__(self, name):
        if name not in self._done:
            self._done[name] = self._run(CASES[name])
        return self._done[name]

    def _run(self, spec):
        import knockgs_core.contract

        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(knockgs_core.contract, "load_contract", self._load_contract(knockgs_core.contract.load_contract))
            return self._run_files(spec)

    def _run_files(self, spec):
        from knockgs_core.cli import main

        root = self.root
        mdir, tdir, rdir = root / "cases" / spec.name, root / "truth" / spec.name, root / "runs" / spec.name
        make_case(spec, self.contract, self.particles, measured_dir=mdir, truth_dir=tdir)
        case = {"dirs": (mdir, tdir, rdir)}
        if spec.name == "null":
            heldout = f"standard_y={mdir / 'measured_heldout.parquet'}"
            case["rc"] = main(["discrepancy", "run", "--object", "pillow", "--profile", "ci",
                               "--measured", str(mdir / "measured_calib.parquet"), "--particles", str(self.particles_file),
                               "--heldout-probe", "standard_y", "--heldout-measured", heldout,
                               "--catalogue", ",".join(CATALOGUE), "--max-effects", "1", "-o", str(rdir), "--quiet"])
            case["result"] = json.loads((rdir / "result.json").read_text()) if case["rc"] == 0 else None
        else:
            case["result"] = run_files("pillow", "ci", mdir / "measured_calib.parquet", rdir, particles=self.particles_file,
                                       heldout_probes=["standard_y"],
                                       heldout_measured={"standard_y": mdir / "measured_heldout.parquet"}, settings=SETTINGS)
        case["row"] = evaluate_files(rdir, tdir, root / "eval" / f"{spec.name}.json")
        return case


@pytest.fixture(scope="module")
def cases(pillow, tmp_path_factory):
    contract, particles, save_particles = pillow
    root = tmp_path_factory.mktemp("discrepancy")
    save_particles(particles, root / "particles.npz")
    return _Cases(contract, particles, root)


@pytest.mark.slow
def test_planted_damping_is_found_and_improves_the_heldout_prediction(cases):
    # About 30 s on an idle 2-core machine: the case is made (a strength search, 6 rollouts) and
    # run through files, about 85 rollouts of the ci Pillow at 2 substeps per frame (_two_substeps);
    # the catalogue is already cut to three terms, two of them refined, and the residual report
    # with its figures is written, which the test reads.
    c = cases["damping"]
    row, res = c["row"], c["result"]
    assert row["first_ranked"] == "damping" and row["identified_effect"] == "damping"
    assert row["heldout_traj_rmse_before"] >= 2.0 * row["heldout_traj_rmse_after"]
    assert row["calib_traj_rmse_before"] >= 2.0 * row["calib_traj_rmse_after"]
    assert row["theta_error_after_pct"] < row["theta_error_before_pct"]
    truth = json.loads((c["dirs"][1] / "truth.json").read_text())
    assert res.effects[0]["value"] == pytest.approx(truth["planted_parameter"]["value"], rel=0.1)
    assert acceptance(row)[0]
    # the report says what was found, with figures
    report = (c["dirs"][2] / "report.md").read_text()
    assert "damping" in report and "Verdict" in report and (c["dirs"][2] / "residuals_standard_y.png").exists()


@pytest.mark.slow
def test_null_case_reports_no_missing_effect(cases):
    row, res = cases["null"]["row"], cases["null"]["result"]
    assert row["identified_effect"] == "none" and not res["unexplained"]
    assert res["verdict_kind"] == "none" and res["verdict"].startswith("no missing effect found")
    assert not res["observation"]["identity"]  # tracks without identity, matched at frame 0
    assert res["rounds"][0]["excess_val"] < SETTINGS.min_excess


@pytest.mark.slow
def test_effect_outside_the_catalogue_stays_unexplained(cases):
    # About 20 s: the case through files at 2 substeps per frame (about 70 rollouts).
    row, res = cases["pulse"]["row"], cases["pulse"]["result"]
    assert row["identified_effect"] == "none" and res.unexplained
    assert "no catalogue effect explains" in res.verdict
    assert res.residual["excess_fraction_of_response"] > 0.05


@pytest.mark.slow
def test_truth_audit(cases, tmp_path):
    runs = [cases[name] for name in CASES]
    results = [c["dirs"][2] / "result.json" for c in runs]
    measured = [c["dirs"][0] / f"measured_{r}.parquet" for c in runs for r in ("calib", "heldout")]
    truth_root = cases["null"]["dirs"][1].parent
    ok = audit_truth_separation(results, measured, [truth_root])
    assert ok["passed"], ok["problems"]
    # a run that read a truth file, and a measured file that carries a label, both fail it
    doc = json.loads(results[0].read_text())
    doc["inputs"].append(str(truth_root / "damping" / "truth.json"))
    leaked = tmp_path / "result.json"
    leaked.write_text(json.dumps(doc))
    table = pq.read_table(measured[0])
    labelled = tmp_path / "labelled.parquet"
    label = json.dumps({"probe": "standard_x", "theta_true": [1, 1]}).encode()
    pq.write_table(table.replace_schema_metadata({b"knockgs_measurement": label}), labelled)
    bad = audit_truth_separation([leaked], [labelled], [truth_root])
    assert not bad["passed"] and len(bad["problems"]) >= 2
    assert any(f"read {truth_root / 'damping' / 'truth.json'}" in p for p in bad["problems"])
    assert any(p.startswith(str(labelled)) for p in bad["problems"])


@pytest.mark.slow
def test_cli_run_writes_a_report(cases, tmp_path):
    """`knockgs discrepancy run` (the null case of ``cases`` ran through it) takes its options
    into the loop's settings and writes the result, the held-out scores and every file it read;
    a missing input exits 2."""
    from knockgs_core.cli import main

    mdir, _, rdir = cases["null"]["dirs"]
    assert cases["null"]["rc"] == 0
    doc = json.loads((rdir / "result.json").read_text())
    assert doc["identified"] == [] and doc["inputs"] == [
        str(mdir / "measured_calib.parquet"), str(cases.particles_file), str(mdir / "measured_heldout.parquet")]
    assert doc["settings"]["catalogue"] == list(CATALOGUE) and doc["settings"]["max_effects"] == 1
    assert doc["heldout_probes"] == ["standard_y"] and set(doc["metrics"]) == {"standard_x", "standard_y"}
    assert (rdir / "report.md").exists()
    missing = str(tmp_path / "nope.csv")
    rc = main(["discrepancy", "run", "--object", "pillow", "--profile", "ci", "--measured", missing, "-o", str(tmp_path / "x")])
    assert rc == 2


@pytest.mark.slow
def test_library_base_calibration_on_a_null_measurement(pillow, rng):
    """Library route: local ridge on descriptors of the observed points, then the theta
    refit through the simulator; a clean response without extra effect finds none. The ci
    Pillow with its calibration probe alone at 2 substeps per frame (dt = 1e-2 s, not 5e-3 s:
    the response moves by 0.5 %, every rollout takes half the time), without the
    discretization term (data from the model itself; tests/test_discrepancy_model_error.py)."""
    from knockgs_core.discrepancy import LibrarySource, run_discrepancy
    from knockgs_core.rollout import run_rollout

    contract, particles, _ = pillow
    probe = contract.probes["standard_x"]
    contract = dataclasses.replace(
        contract, probes={"standard_x": probe}, roles={"calibration": "standard_x", "heldout": [], "diagnostic": []},
        probe_selected_reference={}, probe_force_match={}, sim=dataclasses.replace(contract.sim, dt=probe.export.frame_dt / 2))
    grid = [(se, sr) for se in (0.6, 0.8, 1.0) for sr in (1.0, 1.3, 1.6)]
    rollouts = tuple(run_rollout(contract, th, "standard_x", particles=particles).positions for th in grid)
    library = LibrarySource(theta=np.array(grid), names=tuple(f"c{i}" for i in range(len(grid))), rollouts=rollouts)
    truth = (0.75, 1.4)
    X = run_rollout(contract, truth, "standard_x", particles=particles).positions[:, : particles.n_gs].astype(np.float64)
    m = Measurement(points=X + rng.normal(0, 5e-5, X.shape), frames=np.arange(len(X)), times=None,
                    particle=np.arange(particles.n_gs), track=np.arange(particles.n_gs), meta={"probe": "standard_x"})
    res = run_discrepancy(m, contract, particles, library=library,
                          settings=LoopSettings(catalogue=("damping",), model_error_refine=None))
    assert res.base_method == "library_local_ridge"
    err = lambda th: 50 * (abs(th[0] - truth[0]) / truth[0] + abs(th[1] - truth[1]) / truth[1])  # noqa: E731
    assert err(res.theta_base) < 15.0 and err(res.theta_refit) < 1.0
    assert res.verdict_kind == "none" and res.identified_label == "none"
    assert res.noise["std"] == pytest.approx(5e-5, rel=0.05)


def test_library_members_are_named_by_theta_and_one_theta_is_refused(tmp_path):
    """The base-calibration library names its members by theta tag (not by path); two files
    with the same theta are refused, naming the file and the field."""
    from knockgs_core.discrepancy._files import library_source
    from knockgs_core.rollout import Rollout, write_rollout

    X = np.zeros((2, 3, 3), dtype=np.float32)
    paths = []
    for i, theta in enumerate([(1.15, 0.75), (0.5, 1.75), (1.15, 0.75)]):
        path = tmp_path / f"deep{i}" / "any_name.parquet"
        write_rollout(path, Rollout(positions=X, F=None, meta={"theta": list(theta)}))
        paths.append(path)
    lib = library_source(paths[:2])
    assert lib.names == ("sE1.150000_sR0.750000", "sE0.500000_sR1.750000")
    assert lib.rollouts == tuple(str(p) for p in paths[:2])
    np.testing.assert_array_equal(lib.theta, [[1.15, 0.75], [0.5, 1.75]])
    with pytest.raises(InputError, match="metadata.knockgs.theta.*also the theta of"):
        library_source(paths)


def test_where_the_theta_only_model_shows_no_floor_unpassed_candidates_are_rescored_with_their_own():
    """``_rescore_unpassed``: with no floor at the theta-only refit and no candidate passing,
    the best candidates are rescored with their own term; one whose model shows a floor is
    judged beyond it (and now passes), one whose model shows none is left exactly as it was;
    where a candidate already passes, nothing is rescored."""
    from knockgs_core.discrepancy import AttributionRound, AttributionRow, LoopSettings
    from knockgs_core.discrepancy._attribution import _passes, _rescore_unpassed
    from knockgs_core.discrepancy._forward import ModelSpec

    settings = LoopSettings()
    rng = np.random.default_rng(4)
    term = rng.normal(size=400)
    term *= 5.0 / np.linalg.norm(term)
    left = rng.normal(size=400)
    left -= term * float(left @ term) / float(term @ term)
    left *= math.sqrt(50.0) / np.linalg.norm(left)
    rss_val, noise = float(left @ left) + 40.0, 1.0
    shows = _TermProblem(-0.3 * term + left, term, settings)  # its model's data lie 0.3 of a step away
    hides = _TermProblem(left, term, settings)  # c = 0: no floor at its model either

    def round_(explained):
        rows = [AttributionRow("damping", "velocity damping", refined=True, delta_bic=-50.0, explained_val=explained,
                               refined_spec=ModelSpec((1.0, 1.0), (("damping", 1.0),)))]
        return AttributionRound([1.0, 1.0], [], 400, 400, rss_val, rss_val, [1.0, 1.0], rss_val, noise, 1.0, 1.0, True,
                                True, rows, model_floor_val=0.0, floor_weight=0.0)

    att = round_(40.0 / rss_val)
    assert not _passes(att, att.table[0], settings)
    _rescore_unpassed(shows, att, lambda spec: shows, (rss_val, rss_val), settings)
    row = att.table[0]
    assert row.own_term and row.floor_weight == pytest.approx(0.6) and _passes(att, row, settings)

    att = round_(40.0 / rss_val)
    _rescore_unpassed(hides, att, lambda spec: hides, (rss_val, rss_val), settings)
    row = att.table[0]
    assert not row.own_term and row.refined_problem is None and row.explained_val == 40.0 / rss_val
    assert math.isnan(row.floor_weight) and math.isnan(row.model_floor_val) and row.significant is None
    assert not _passes(att, row, settings)

    att = round_(0.9)  # passes on the round's floor: not rescored
    _rescore_unpassed(shows, att, lambda spec: shows, (rss_val, rss_val), settings)
    assert not att.table[0].own_term and att.table[0].explained_val == 0.9


def test_the_loop_runs_at_the_grid_it_is_told_and_refuses_particles_of_another(tmp_path, rng, monkeypatch, capsys):
    """``knockgs discrepancy run --n-grid N``: the loop's model is the contract at N cells per axis
    (fill refined with it, the substep by the contracts' rule); particles built at the profile's
    grid are refused by the contract's hash, in one line, exit 2. The loop itself is replaced by a
    recorder: what is tested is the model it is handed."""
    import knockgs_core.discrepancy._files as files
    from knockgs_core.assets import build_asset, save_particles
    from knockgs_core.cli import main
    from knockgs_core.contract import at_resolution, load_contract

    ci = load_contract("pillow", "ci")
    T, M = ci.probes["standard_x"].export.n_frames, 20
    X = rng.normal(scale=0.01, size=(T, M, 3)) + 1.0
    write_measured(tmp_path / "m.parquet", Measurement(points=X, frames=np.arange(T), times=None, particle=None,
                                                       track=np.arange(M), meta={"object": "pillow", "probe": "standard_x"},
                                                       source="test"))
    seen = {}

    def recorder(measured, contract, particles, **kw):
        seen.update(contract=contract, particles=particles)
        raise SystemExit(0)

    monkeypatch.setattr(files, "run_discrepancy", recorder)
    with pytest.raises(SystemExit):
        main(["discrepancy", "run", "--object", "pillow", "--profile", "ci", "--measured", str(tmp_path / "m.parquet"),
              "--n-grid", "48", "-o", str(tmp_path / "out"), "--quiet"])
    c = seen["contract"]
    assert c.hash == at_resolution(ci, 48).hash != ci.hash
    assert (c.sim.n_grid, c.fill.resolution) == (48, round(ci.fill.resolution * 48 / ci.sim.n_grid))
    assert c.sim.dt == pytest.approx(c.cfl_dt()) and c.sim.dt < ci.sim.dt
    assert len(seen["particles"].positions) == len(build_asset(c).particles.positions)
    save_particles(build_asset(ci).particles, tmp_path / "p.npz", contract=ci)
    capsys.readouterr()
    code = main(["discrepancy", "run", "--object", "pillow", "--profile", "ci", "--measured", str(tmp_path / "m.parquet"),
                 "--n-grid", "48", "--particles", str(tmp_path / "p.npz"), "-o", str(tmp_path / "out2"), "--quiet"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and "p.npz" in err and "contract_hash" in err, err
