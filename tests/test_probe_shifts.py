"""Probe shifts and passive versus active observation (knockgs_core.experiments._probe_shifts,
_passive): the probes' invariants (same impulse, equal total force), the passive protocol's
scale invariance in the simulator itself, and the tables' arithmetic on cases whose answer is
known by construction."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from knockgs_core.contract import load_contract, load_targets
from knockgs_core.errors import InputError
from knockgs_core.experiments import (
    PASSIVE_PROBE,
    PassiveProtocol,
    contact_table,
    duration_table,
    error_directions,
    passive_active_table,
    passive_rollout,
    probe_impulse,
    probe_total_force,
    protocol_distance,
    ratio_span_pct,
)
from knockgs_core.experiments._probe_shifts import _common_frames


@pytest.fixture(scope="module")
def pillow_ps(pillow_ci):
    c, built = pillow_ci
    return c, built.particles


@pytest.mark.parametrize("profile", ["ci", "default", "paper"])
def test_duration_probe_delivers_probe_a_impulse(profile):
    c = load_contract("pillow", profile)
    a, d = c.probes["standard_x"], c.probes["duration_x_fine"]
    # at the paper's 0.1 ms reference step and at the profile's own dt
    for dt in (1e-4, c.sim.dt):
        np.testing.assert_allclose(probe_impulse(d, dt), probe_impulse(a, dt), rtol=1e-12, atol=0)
    # the same horizon, four times the frames
    assert d.duration == pytest.approx(0.02) and a.duration == pytest.approx(1e-4)
    assert (d.export.n_frames - 1) * d.export.frame_dt == pytest.approx((a.export.n_frames - 1) * a.export.frame_dt)


def test_contact_probes_have_equal_total_force(pillow_ps):
    c, ps = pillow_ps
    ref, shifted = probe_total_force(c, ps, "local_center_x"), probe_total_force(c, ps, "shifted_contact_x")
    np.testing.assert_allclose(shifted, ref, rtol=1e-9)
    # the reference's total is the paper's: 0.18 N per particle times its selected_reference
    assert ref[0] == pytest.approx(-0.18 * 65550, rel=1e-9)
    # and the two contacts select different particles (the shift is 0.12 in y)
    sel = [c.probe_selection(p, ps.positions) for p in ("local_center_x", "shifted_contact_x")]
    assert sel[0].sum() > 0 and sel[1].sum() > 0 and not np.array_equal(sel[0], sel[1])


@pytest.mark.slow
def test_passive_protocol_is_blind_to_a_common_scale(pillow_ps):
    """Under gravity alone, (a s_E, a s_rho) moves exactly like (s_E, s_rho): bit for bit for a
    in {0.5, 2}; a known force (Probe A) breaks it."""
    from knockgs_core.rollout import run_rollout

    c, ps = pillow_ps
    prot = PassiveProtocol(gravity=(0.0, 0.0, -0.3), frame_dt=0.02, n_frames=11)
    base = (0.8, 1.25)
    X = passive_rollout(c, base, prot, particles=ps).positions
    assert np.sqrt(np.mean(np.sum((X[-1] - X[0]) ** 2, -1))) > 1e-3  # it does sag
    probe = c.calibration_probe
    XA = run_rollout(c, base, probe.name, particles=ps).positions
    for a in (0.5, 2.0):
        th = (a * base[0], a * base[1])
        Xa = passive_rollout(c, th, prot, particles=ps).positions
        assert np.array_equal(Xa, X), a
        XAa = run_rollout(c, th, probe.name, particles=ps).positions
        assert np.max(np.abs(XAa - XA)) > 1e-3
    ro = passive_rollout(c, base, prot, particles=ps)
    assert ro.meta["probe"]["name"] == PASSIVE_PROBE and ro.meta["sim"]["gravity"] == [0.0, 0.0, -0.3]
    assert ro.meta["total_probe_force"] == [0.0, 0.0, 0.0]


def test_passive_protocol_round_trip_and_bad_input():
    p = PassiveProtocol(gravity=(0.0, 0.0, -0.25), frame_dt=0.02, n_frames=31)
    assert PassiveProtocol.from_dict(p.to_dict()) == p
    with pytest.raises(InputError, match="gravity"):
        PassiveProtocol.from_dict({"gravity": [0, 0], "frame_dt": 0.02, "n_frames": 31}, "p.json")
    with pytest.raises(InputError, match="p.json"):
        PassiveProtocol.from_dict({"frame_dt": 0.02}, "p.json")


def test_error_directions_split_ratio_and_scale():
    # an estimate on the target's invariance line has no ratio error
    d = error_directions((1.6, 2.4), (0.8, 1.2))
    assert d["ratio_error"] == pytest.approx(0.0, abs=1e-12)
    assert d["scale_error"] == pytest.approx(100 * math.sqrt(2) * math.log(2))
    # and one with the right product no scale error
    d = error_directions((1.6, 0.6), (0.8, 1.2))
    assert d["scale_error"] == pytest.approx(0.0, abs=1e-12)
    assert d["ratio_error"] == pytest.approx(100 * math.sqrt(2) * math.log(2))


def test_ratio_span_of_the_main_targets_is_the_papers():
    t = load_targets("main")
    assert ratio_span_pct(list(zip(t.E_scale, t.density_scale))) == pytest.approx(162.5, abs=0.05)


def test_passive_active_table_on_known_estimates():
    t = load_targets("main")
    truth = [{"case_name": r.case_name, "E_scale": r.E_scale, "density_scale": r.density_scale} for r in t.itertuples()]
    exact = {"predictions": truth}
    # a passive route that gets every ratio right and the scale 2x too large
    doubled = {"predictions": [dict(p, E_scale=2 * p["E_scale"], density_scale=2 * p["density_scale"]) for p in truth]}
    summary, rows = passive_active_table({"active": {"m": exact}, "passive": {"m": doubled}}, t, ["m"])
    s = summary.set_index("protocol")
    assert s.loc["active", "joint_error_pct"] == 0 and s.loc["active", "scale_error"] == 0
    assert s.loc["passive", "joint_error_pct"] == pytest.approx(100.0)
    assert s.loc["passive", "ratio_error"] == pytest.approx(0.0, abs=1e-9)
    assert s.loc["passive", "ratio_span_est_pct"] == pytest.approx(s.loc["passive", "ratio_span_true_pct"])
    assert len(rows) == 10
    with pytest.raises(InputError, match="no estimate"):
        passive_active_table({"active": {"m": {"predictions": truth[:3]}}}, t, ["m"])


def test_protocol_distance_compares_common_export_times():
    rng = np.random.default_rng(0)
    fine = rng.normal(size=(121, 7, 3))
    coarse = fine[::4].copy()  # 31 frames at 4x the interval: the same trajectory
    a, b = _common_frames(coarse, 0.02, fine, 0.005)
    assert a.shape == b.shape == (31, 7, 3) and np.array_equal(a, b)
    d = protocol_distance([(coarse, 0.02, fine, 0.005), (coarse + 1.0, 0.02, fine, 0.005)])
    assert d["per_target"][0] == 0.0 and d["per_target"][1] == pytest.approx(math.sqrt(3.0))
    assert d["mean"] == pytest.approx(math.sqrt(3.0) / 2)


def _evals(methods, probes, targets):
    rows = []
    for i, m in enumerate(methods):
        for j, t in enumerate(targets):
            for probe in probes:
                rows.append({"method": m, "target": t, "E_true": 1.0, "rho_true": 1.0, "E_hat": 1.0 + i, "rho_hat": 1.0,
                             "joint_error_pct": 50.0 * i, "probe": probe, "traj_rmse": (i + 1) * (j + 1) * 1e-4,
                             "curve_rmse": (i + 1) * 1e-5})
    return pd.DataFrame(rows)


def test_duration_and_contact_tables():
    ev = _evals(["a", "b"], ["duration_x_fine"], ["t1", "t2", "t3"])
    d = duration_table(ev, ["b", "a"]).set_index("method")
    assert list(d.index) == ["b", "a"]
    assert d.loc["a", "traj_rmse_mean"] == pytest.approx(2e-4) and d.loc["a", "traj_rmse_sd"] == pytest.approx(1e-4)
    assert d.loc["b", "joint_error_pct"] == 50.0 and (d["n_targets"] == 3).all()
    ev = _evals(["a", "b"], ["local_center_x", "shifted_contact_x"], ["t1"])
    c = contact_table(ev, ["a", "b"], ["local_center_x", "shifted_contact_x"])
    assert list(zip(c["contact"], c["method"]))[:2] == [("local_center_x", "a"), ("local_center_x", "b")] and len(c) == 4
    with pytest.raises(InputError, match="one target"):
        contact_table(_evals(["a"], ["local_center_x"], ["t1", "t2"]), ["a"], ["local_center_x"])


def test_leakage_audit_keeps_the_routes_apart(tmp_path):
    import json

    from knockgs_core.audits import audit_leakage
    from knockgs_core.contract import load_candidates

    def estimate(where, inputs):
        f = tmp_path / where / "estimates/pillow/main/local_ridge.json"
        f.parent.mkdir(parents=True, exist_ok=True)
        f.write_text(json.dumps({"deployable": True, "rule_inputs": inputs}))
        return f

    active_in = ["results/ci/descriptors/pillow/library.csv", "results/ci/descriptors/pillow/queries_main.csv"]
    passive_in = ["results/ci/passive/descriptors/pillow/library.csv", "results/ci/passive/descriptors/pillow/queries_main.csv"]
    kw = {"calibration_probes": {"pillow": "standard_x"}, "candidates": load_candidates(), "targets": load_targets()}
    ok = audit_leakage([estimate("a", active_in), estimate("b/passive", passive_in)], **kw)
    assert ok["passed"], ok["problems"]
    bad = audit_leakage([estimate("c/passive", active_in), estimate("d", passive_in[:1] + active_in[1:])], **kw)
    assert not bad["passed"] and len(bad["problems"]) == 3
    assert all("other route" in p for p in bad["problems"])


@pytest.mark.slow
def test_passive_protocol_gravity_search(pillow_ps):
    """The rule: the passive response at (1, 1) as large as Probe A's, within 10 %, from a
    rollout at 1 m/s^2 by secant steps; the record says how it got there and holds the
    invariance check (bit for bit on the Pillow)."""
    from knockgs_core.experiments import passive_protocol

    c, ps = pillow_ps
    prot, rec = passive_protocol(c, ps)
    assert rec["gravity_search"][0]["g"] == 1.0 and 2 <= len(rec["gravity_search"]) <= 4
    assert abs(rec["passive_mean_rms"] / rec["probe_a_mean_rms"] - 1.0) < 0.1
    assert prot.gravity == (0.0, 0.0, -rec["gravity_magnitude"])  # the camera's up is +z
    assert all(chk["passive_bitwise_equal"] and chk["active_max_abs_diff"] > 1e-3 for chk in rec["invariance"])


def test_shift_evaluation_reads_each_rollout_once_and_scores_as_each_method_alone(tmp_path, monkeypatch):
    # every method's frozen estimates against each target's rollout: the target's file is read
    # once for all methods and a prediction two methods share once, with the rows that a
    # method's own write-back evaluation gives and the metrics computed here from the files
    import knockgs_core.experiments._main as main
    from knockgs_core.experiments import evaluate_method, evaluate_shift
    from knockgs_core.metrics import curve_metrics, joint_error_pct, trajectory_rmse
    from knockgs_core.rollout import read_rollout, theta_tag

    from _rollouts import theta_rollouts

    n_gs = 40
    targets = pd.DataFrame({"case_name": ["t1", "t2"], "E_scale": [0.8, 1.2], "density_scale": [1.1, 0.9]})
    estimates = {
        "fixed": {"predictions": [{"case_name": c, "E_scale": 1.0, "density_scale": 1.0} for c in ("t1", "t2")]},
        "near": {"predictions": [{"case_name": "t1", "E_scale": 0.82, "density_scale": 1.08},
                                 {"case_name": "t2", "E_scale": 1.0, "density_scale": 1.0}]},
        "other": {"predictions": [{"case_name": "t1", "E_scale": 0.7, "density_scale": 1.2},
                                  {"case_name": "t2", "E_scale": 1.25, "density_scale": 0.95},
                                  {"case_name": "t9", "E_scale": 3.0, "density_scale": 3.0}]},
    }
    thetas = {(1.0, 1.0), (0.82, 1.08), (0.7, 1.2), (1.25, 0.95), (0.8, 1.1), (1.2, 0.9)}
    paths = theta_rollouts(tmp_path, thetas, "duration_x_fine", n_gs=n_gs)
    reads = []

    def counting(path):
        reads.append(path)
        return read_rollout(path)

    monkeypatch.setattr(main, "read_rollout", counting)
    where = lambda probe, th: paths[f"{probe}/{theta_tag(th)}"]  # noqa: E731
    ev = evaluate_shift(estimates, targets, where, ["duration_x_fine"])
    # t1: truth, fixed, near, other; t2: truth, fixed (= near's), other
    assert len(reads) == 7 and len(set(reads)) == 6
    assert list(ev["method"]) == ["fixed", "fixed", "near", "near", "other", "other"]
    for m, est in estimates.items():
        alone = evaluate_method({"predictions": est["predictions"][:2]}, targets, where, ["duration_x_fine"])
        rows = ev[ev["method"] == m].drop(columns="method").reset_index(drop=True)
        pd.testing.assert_frame_equal(rows, alone)
        for r in rows.itertuples(index=False):
            truth = read_rollout(where("duration_x_fine", (r.E_true, r.rho_true))).positions[:, :n_gs]
            pred = read_rollout(where("duration_x_fine", (r.E_hat, r.rho_hat))).positions[:, :n_gs]
            assert r.traj_rmse == trajectory_rmse(pred, truth)
            assert r.curve_rmse == curve_metrics(pred, truth)["curve_rmse"]
            assert r.joint_error_pct == joint_error_pct((r.E_hat, r.rho_hat), (r.E_true, r.rho_true))
    # three threads score the targets side by side: the same rows in the same order, each file
    # read as often
    reads.clear()
    pd.testing.assert_frame_equal(evaluate_shift(estimates, targets, where, ["duration_x_fine"], workers=3), ev)
    assert len(reads) == 7 and len(set(reads)) == 6
    # a target without an estimate is refused before any file is read
    reads.clear()
    with pytest.raises(InputError, match="no estimate for target t2"):
        evaluate_shift({"short": {"predictions": estimates["near"]["predictions"][:1]}}, targets, where,
                       ["duration_x_fine"], workers=2)
    assert reads == []
