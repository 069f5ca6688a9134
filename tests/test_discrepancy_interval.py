"""The theta interval and the floor's statement of the discrepancy loop (docs/discrepancy.md,
"Theta interval"): on constructed estimates, and on the loop's model at its own resolution."""

from __future__ import annotations

import math

import numpy as np
import pytest
from _linear import LinearForward

from knockgs_core.discrepancy._interval import MIN_ORDER, interval_from_estimates

LOG_TRUTH = np.log([0.8, 1.2])
SD = np.array([0.01, 0.005])  # statistical sd in log theta: half-widths 0.02 and 0.01


def _log(iv):
    return np.log(np.asarray(iv, dtype=float))


def test_a_pair_that_moves_theta_more_than_its_statistics_leaves_the_refined_side_unbounded_and_no_continuum():
    """The refinement moves log s_E by 0.3 (15 half-widths: not asymptotic) up, and log s_rho
    by 0.008 (within its half-width 0.01: asymptotic) down. s_E: unbounded above, widened by 0.3
    below, no continuum value (the reason given); s_rho: out to the first-order continuum below
    (refined + (refined - estimate) / (r - 1) = estimate - 0.024), widened by 0.008 above."""
    refined = LOG_TRUTH + np.array([0.3, -0.008])
    u = interval_from_estimates(LOG_TRUTH, SD, refined=refined, factor=1.5)
    (lo_e, hi_e), (lo_r, hi_r) = u["interval"]
    assert u["basis"] == "refinement" and u["asymptotic"] == [False, True]
    assert hi_e == math.inf and u["unbounded"] == [[False, True], [False, False]]
    assert math.log(lo_e) == pytest.approx(LOG_TRUTH[0] - 0.3 - 0.02, abs=1e-12)
    assert u["continuum"][0] is None and "more than its statistical half-width" in u["continuum_reason"][0]
    assert math.log(u["continuum"][1]) == pytest.approx(LOG_TRUTH[1] - 0.024, abs=1e-12)
    assert u["continuum_reason"][1] is None
    assert math.log(lo_r) == pytest.approx(LOG_TRUTH[1] - 0.024 - 0.01, abs=1e-12)
    assert math.log(hi_r) == pytest.approx(LOG_TRUTH[1] + 0.008 + 0.01, abs=1e-12)
    # the truth of a world anywhere on the refinement's side of s_E is inside, however far
    assert lo_e <= 0.8 * math.exp(0.3) * 7 <= hi_e
    # the same estimates moved down in s_E: unbounded below (0), bounded above
    u = interval_from_estimates(LOG_TRUTH, SD, refined=LOG_TRUTH - np.array([0.3, 0.0]), factor=1.5)
    assert u["interval"][0][0] == 0.0 and u["unbounded"][0] == [True, False]
    assert math.log(u["interval"][0][1]) == pytest.approx(LOG_TRUTH[0] + 0.3 + 0.02, abs=1e-12)


def test_a_third_resolution_bounds_the_refined_side_only_at_an_observed_order_of_at_least_one_half():
    """Three estimates of log s_E, model -> refined -> second, changes e1 = 0.3 and e2 = e1 /
    1.5^p. At p = 1 the interval reaches the continuum extrapolated with the observed order
    (second + e2 / (1.5^p - 1) = estimate + 0.9) plus the statistical half-width; at p = 0.3,
    or where the second change turns back, it is unbounded on that side and no continuum is
    given."""
    def third(e2):
        refined = LOG_TRUTH + np.array([0.3, 0.0])
        return interval_from_estimates(LOG_TRUTH, SD, refined=refined, second=refined + np.array([e2, 0.0]), factor=1.5)

    u = third(0.3 / 1.5)
    assert u["observed_order"][0] == pytest.approx(1.0, abs=1e-12) and u["asymptotic"][0]
    assert math.log(u["continuum"][0]) == pytest.approx(LOG_TRUTH[0] + 0.9, abs=1e-12)
    assert math.log(u["interval"][0][1]) == pytest.approx(LOG_TRUTH[0] + 0.9 + 0.02, abs=1e-12)
    assert math.log(u["interval"][0][0]) == pytest.approx(LOG_TRUTH[0] - 0.3 - 0.02, abs=1e-12)
    slow = third(0.3 / 1.5**0.3)
    assert slow["observed_order"][0] == pytest.approx(0.3, abs=1e-12) and slow["observed_order"][0] < MIN_ORDER
    assert slow["interval"][0][1] == math.inf and slow["continuum"][0] is None
    assert "observed order 0.30 is below 0.5" in slow["continuum_reason"][0]
    back = third(-0.1)
    assert back["observed_order"][0] is None and back["interval"][0][1] == math.inf and back["continuum"][0] is None
    # s_rho, which no refinement moves, stays the statistical interval in all three
    for v in (u, slow, back):
        assert _log(v["interval"][1]) == pytest.approx([LOG_TRUTH[1] - 0.01, LOG_TRUTH[1] + 0.01], abs=1e-12)


def test_data_that_show_no_discretization_error_get_the_fits_interval_whatever_the_refinement():
    """At the model's own resolution the refinement's change is not in the data: the interval
    is the estimate +- (2 sd + the step the fit still asks for), though the refined model would
    fit theta 1.8x higher; the refined estimate is still reported, and no continuum from that
    non-asymptotic pair."""
    refined = LOG_TRUTH + np.array([0.6, 0.08])
    remaining = np.array([-0.004, 0.001])
    u = interval_from_estimates(LOG_TRUTH, SD, remaining=remaining, refined=refined, factor=1.5, shows_error=False)
    assert u["basis"] == "statistical" and u["unbounded"] == [[False, False], [False, False]]
    half = 2 * SD + np.abs(remaining)
    np.testing.assert_allclose(_log(u["interval"]), np.column_stack([LOG_TRUTH - half, LOG_TRUTH + half]), atol=1e-12)
    assert u["theta_at"]["refined"] == pytest.approx(np.exp(refined).tolist(), rel=1e-12)
    assert u["continuum"] == [None, None] and all(u["continuum_reason"])
    # without a refined model at all: the same interval, nothing asymptotic to judge
    v = interval_from_estimates(LOG_TRUTH, SD, remaining=remaining)
    assert v["interval"] == u["interval"] and v["asymptotic"] is None


# -------------------------------------------------------------------------------------
# the loop on data made at its own resolution (ci pillow)
# -------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def loop_model():
    """The ci Pillow with its calibration probe alone and 2 substeps per frame (as in
    tests/test_discrepancy_model_error.py: the step halves every rollout)."""
    import dataclasses

    from knockgs_core.assets import build_asset
    from knockgs_core.contract import load_contract

    contract = load_contract("pillow", "ci")
    probe = contract.roles["calibration"]
    model = dataclasses.replace(
        contract, probes={probe: contract.probes[probe]}, roles={"calibration": probe, "heldout": [], "diagnostic": []},
        probe_selected_reference={}, probe_force_match={},
        sim=dataclasses.replace(contract.sim, dt=contract.probes[probe].export.frame_dt / 2))
    return model, build_asset(contract).particles


def test_on_its_own_worlds_the_interval_is_the_fits_and_holds_the_truth(loop_model):
    """Data made by the loop's own model (tracks without identity of 60 % of the Gaussian
    particles, noise 2 % of the response): the term's coefficient is 0, so the interval is the
    fit's statistical one. It holds the truth and is far narrower than the refinement's change,
    which the data do not show: the refined model's theta (s_E about 1.8x the estimate at ci)
    lies outside it, and no continuum value is given from that non-asymptotic pair."""
    # About 10 s of CPU: LM from (1, 1) through the model (about 25 rollouts at 2 substeps per
    # frame), one attribution round over one catalogue term, one refined rollout.
    from knockgs_core.discrepancy import LoopSettings, Measurement, run_discrepancy
    from knockgs_core.rollout import run_rollout

    contract, particles = loop_model
    probe, truth = contract.roles["calibration"], (0.8, 1.2)
    rng = np.random.default_rng(5)
    X = np.asarray(run_rollout(contract, truth, probe, particles=particles).positions, np.float64)
    idx = rng.permutation(particles.n_gs)[: int(0.6 * particles.n_gs)]
    size = np.sqrt(np.mean(np.sum((X[:, : particles.n_gs] - X[0, : particles.n_gs]) ** 2, -1)))
    P = X[:, idx] + rng.normal(0.0, 0.02 * size, size=(X.shape[0], len(idx), 3))
    m = Measurement(points=P, frames=np.arange(X.shape[0]), times=None, particle=None, track=np.arange(len(idx)) + 1,
                    meta={"object": contract.name, "probe": probe})
    res = run_discrepancy(m, contract, particles, settings=LoopSettings(catalogue=("damping",)))
    u = res.theta_uncertainty
    assert res.verdict_kind == "none" and res.floor_statement is None
    assert res.model_error["coefficient"] < 0.05 and u["basis"] == "statistical"
    for k in range(2):
        lo, hi = res.theta_interval[k]
        assert lo <= truth[k] <= hi, res.theta_interval
    est, ref = np.log(u["theta_at"]["estimate"]), np.log(u["theta_at"]["refined"])
    assert abs(ref[0] - est[0]) > 0.3  # the refinement's change in s_E, which the old interval spanned
    half = np.log(np.asarray(res.theta_interval)[:, 1]) - est
    assert half[0] < abs(ref[0] - est[0]) / 20
    assert not res.theta_interval[0][0] <= u["theta_at"]["refined"][0] <= res.theta_interval[0][1]
    assert u["continuum"] == [None, None] and "statistical half-width" in u["continuum_reason"][0]


def test_an_unbounded_interval_is_scored_after_its_round_trip_through_the_results_json(tmp_path):
    """An interval unbounded above is written to JSON with ``"inf"`` (the project's JSON
    policy) and, read back, still holds a truth far above its lower bound and misses one below."""
    import json

    from knockgs_core.discrepancy._scoring import interval_cells
    from knockgs_core.io import write_json

    u = interval_from_estimates(LOG_TRUTH, SD, refined=LOG_TRUTH + np.array([0.3, 0.2]), factor=1.5)
    write_json(tmp_path / "result.json", {"theta_interval": u["interval"]})
    iv = json.loads((tmp_path / "result.json").read_text())["theta_interval"]
    assert iv[0][1] == "inf"
    text, holds = interval_cells(iv, (5.0, 9.0))
    assert holds and text.endswith(", inf]") and text.startswith(f"[{math.exp(LOG_TRUTH[0] - 0.32):.3f}, inf]")
    assert not interval_cells(iv, (0.5, 1.2))[1]
    assert interval_cells(None, (0.8, 1.2)) == ("", False)


def test_a_refinement_that_acts_as_a_change_of_theta_is_read_back_as_that_change(rng):
    """The loop reads a refinement's theta as the theta at which the model makes the refined
    model's response. A refined model (the second refinement) that responds as the model at
    theta x (e^0.3, e^-0.1) on a linear simulator: its estimate is the model's theta divided
    by the linearized change, theta x exp(-(e^0.3 - 1, e^-0.1 - 1) h / (e^h - 1)) (h the
    sensitivities' forward-difference step); it is simulated only where the data show the
    discretization error."""
    from types import SimpleNamespace

    from knockgs_core.discrepancy import LoopSettings, Measurement
    from knockgs_core.discrepancy._fitting import Problem
    from knockgs_core.discrepancy._forward import ModelSpec
    from knockgs_core.discrepancy._loop import _theta_interval

    T, M = 12, 40
    X0 = rng.uniform(0, 1, size=(M, 3))
    t = np.arange(T)[:, None, None] * 0.02
    A, B = np.sin(9 * t) * rng.normal(size=(1, M, 3)) * 1e-3, np.sin(4 * t) * rng.normal(size=(1, M, 3)) * 1e-3
    fw, spec = LinearForward(X0, A, B), ModelSpec((0.8, 1.2))
    noise = rng.normal(0.0, 1e-6, size=(T, M, 3))
    noise[0] = 0.0
    m = Measurement(points=fw.rollout(spec, "p") + noise, frames=np.arange(T), times=None, particle=np.arange(M),
                    track=np.arange(M))
    problem = Problem(m, fw, "p", LoopSettings())
    change = np.array([0.3, -0.1])

    def difference(model, at, probe, points, *, level=1):
        assert level == 2 and at is spec and points.shape == (M, 3)
        return model.rollout(at.with_theta(tuple(np.asarray(at.theta) * np.exp(change))), probe) - model.rollout(at, probe)

    me = SimpleNamespace(theta_shift=np.array([0.2, 0.0]), second=object(), spec=spec, factor=1.5, difference=difference,
                         theta_per_misfit=None)
    u = _theta_interval(problem, spec, me, LoopSettings(), shows_error=True)
    h = LoopSettings().theta_step  # the sensitivities are forward differences: slope (e^h - 1) / h per unit
    want = np.asarray(spec.theta) * np.exp(-(np.exp(change) - 1.0) * h / (math.exp(h) - 1.0))
    np.testing.assert_allclose(u["theta_at"]["second_refinement"], want, rtol=1e-6)
    np.testing.assert_allclose(u["theta_at"]["refined"], np.asarray(spec.theta) * np.exp([-0.2, 0.0]), rtol=1e-12)
    assert u["basis"] == "refinement" and u["shows_discretization_error"]
    me.difference = None  # not simulated where the data show no discretization error
    v = _theta_interval(problem, spec, me, LoopSettings(), shows_error=False)
    assert "second_refinement" not in v["theta_at"] and v["basis"] == "statistical"


def test_a_model_error_shaped_like_a_grid_placements_change_is_covered_by_the_floors_share_on_both_sides(rng):
    """Data = the model at the truth + a model error C of the kind a grid placement makes: a
    part along theta's sensitivities, which biases the fitted theta, and a part no theta
    represents, which stays in the residual. On a simulator linear in log theta the bias is
    exactly C's theta part; the floor's share (C's theta-per-misfit ratio times the residual
    above the noise) equals it, so the interval holds the truth, where the statistical
    interval alone misses it by many half-widths. The share has no sign: the same error with
    the other sign is covered too. Data that do not show the error get no share."""
    from types import SimpleNamespace

    from knockgs_core.discrepancy import LoopSettings, Measurement
    from knockgs_core.discrepancy._fitting import Problem, theta_sensitivities
    from knockgs_core.discrepancy._forward import ModelSpec
    from knockgs_core.discrepancy._interval import theta_per_misfit
    from knockgs_core.discrepancy._loop import _theta_interval

    class LogLinear(LinearForward):
        def rollout(self, spec, probe):
            return self.X0[None] + math.log(spec.theta[0]) * self.A + math.log(spec.theta[1]) * self.B

    T, M, sigma = 12, 40, 1e-6
    X0 = rng.uniform(0, 1, size=(M, 3))
    t = np.arange(T)[:, None, None] * 0.02
    A, B = np.sin(9 * t) * rng.normal(size=(1, M, 3)) * 1e-2, np.sin(4 * t) * rng.normal(size=(1, M, 3)) * 1e-2
    other = np.sin(23 * t) * rng.normal(size=(1, M, 3)) * 1e-3  # what no theta represents
    fw, truth = LogLinear(X0, A, B), np.log([0.8, 1.2])
    settings = LoopSettings()
    for sign in (1.0, -1.0):
        C = sign * (0.03 * A - 0.02 * B + other)
        noise = rng.normal(0.0, sigma, size=(T, M, 3))
        noise[0] = 0.0
        Y = fw.rollout(ModelSpec(tuple(np.exp(truth))), "p") + C + noise
        m = Measurement(points=Y, frames=np.arange(T), times=None, particle=np.arange(M), track=np.arange(M))
        problem = Problem(m, fw, "p", settings)
        # the least-squares fit in log theta (exact here: the model is linear in it)
        cols = np.column_stack([np.broadcast_to(A, (T, M, 3))[1:].reshape(-1), np.broadcast_to(B, (T, M, 3))[1:].reshape(-1)])
        est = np.linalg.lstsq(cols, (Y - fw.rollout(ModelSpec((1.0, 1.0)), "p"))[1:].reshape(-1), rcond=None)[0]
        spec = ModelSpec(tuple(np.exp(est)))
        bias = est - truth
        assert np.all(np.abs(bias) > 0.015)  # C's theta part: 0.03 and 0.02 and the small projection of its other part
        J = theta_sensitivities(problem, spec, settings)
        ratios, _ = theta_per_misfit(J, [C[1:].reshape(-1)])
        me = SimpleNamespace(theta_shift=None, second=None, spec=spec, factor=1.5, theta_per_misfit=ratios)
        u = _theta_interval(problem, spec, me, settings, shows_error=True, noise_floor=sigma**2)
        np.testing.assert_allclose(u["floor_share_log"], np.abs(bias), rtol=0.02)
        for k in range(2):
            lo, hi = np.log(u["interval"][k])
            assert lo < truth[k] < hi, (k, u["interval"], np.exp(truth))
            assert abs(bias[k]) > 2 * u["statistical_half_width_log"][k]
        v = _theta_interval(problem, spec, me, settings, shows_error=False, noise_floor=sigma**2)
        assert v["floor_share_log"] == [0.0, 0.0]
        assert not all(lo <= x <= hi for (lo, hi), x in zip(v["interval"], np.exp(truth)))


def test_the_refinements_ratio_follows_the_term_the_model_was_last_recorded_at():
    """``ModelError.theta_per_misfit``: the floor's ratios, then the refinement's, |theta shift|
    over the norm of the recorded term; when the final model (with an effect) records its own
    term, the refinement's ratio is that model's, not the base model's."""
    from knockgs_core.discrepancy._model_error import ModelError

    me = ModelError(refined=None, factor=1.5, c_max=6.0, length=0.01)
    assert me.theta_per_misfit is None
    term = np.zeros((4, 3, 3))
    term[1:] = 0.002
    me.record(None, term, term, np.array([0.03, -0.01]))
    me.floor_ratios = np.array([[5.0, 1.0]])
    norm = np.linalg.norm(term)
    np.testing.assert_allclose(me.theta_per_misfit, [[5.0, 1.0], [0.03 / norm, 0.01 / norm]])
    me.record(None, 2 * term, 2 * term, np.array([0.01, 0.02]))  # the final model's term
    np.testing.assert_allclose(me.theta_per_misfit[-1], [0.01 / (2 * norm), 0.02 / (2 * norm)])
    me.record(None, 0 * term, 0 * term, np.array([0.01, 0.02]))  # no term: no refinement row
    np.testing.assert_allclose(me.theta_per_misfit, [[5.0, 1.0]])
