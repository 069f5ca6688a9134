"""CMA-ES direct video optimization (knockgs_core.experiments._cmaes): the video loss, the
search's budget and seed-determinism on a synthetic video whose optimum is known, the table's
arithmetic, and (slow) determinism on the real Pillow."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from knockgs_core.errors import InputError
from knockgs_core.experiments._cmaes import (
    candidate_bounds,
    cmaes_calibrate,
    cmaes_estimate,
    cmaes_table,
    video_depth_scale,
    video_loss,
)
from knockgs_core.metrics import joint_error_pct
from knockgs_core.observe import RGBDFrames
from knockgs_core.render import Camera

CAM = Camera.look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), fov_deg=40.0, width=32, height=24)
BOUNDS = ((0.5, 1.15), (0.75, 1.75))
TRUTH = (0.6, 0.9)
_ROWS, _COLS = np.mgrid[0:24, 0:32].astype(np.float64)


def blob_video(theta, *, T: int = 8, coverage: float = 1.0) -> RGBDFrames:
    """A bright blob whose path depends smoothly on (log s_E, log s_rho) (rows on s_E, columns
    on s_rho), drawn on a covered background whose depth rises under the blob."""
    le, lr = np.log(np.asarray(theta, dtype=np.float64))
    t = np.arange(T)[:, None, None] / (T - 1)
    g = np.exp(-((_ROWS - (12 + 6 * t * (le + 0.1))) ** 2 + (_COLS - (16 + 8 * t * (lr - 0.2))) ** 2) / 32.0)
    rgb = np.stack([g, 0.5 * g, 1.0 - g], axis=-1)
    return RGBDFrames(rgb=rgb, alpha=np.full(g.shape, coverage), depth=2.5 + 0.3 * g, camera=CAM, frame_dt=0.02,
                      source="blob")


def with_(frames: RGBDFrames, **fields) -> RGBDFrames:
    d = {"rgb": frames.rgb, "alpha": frames.alpha, "depth": frames.depth, "camera": frames.camera,
         "frame_dt": frames.frame_dt}
    return RGBDFrames(**{**d, **fields})


def test_video_loss_is_zero_for_identical_frames_and_grows_with_a_difference():
    target = blob_video(TRUTH)
    assert video_loss(target, blob_video(TRUTH)) == 0.0
    near, far = blob_video((0.65, 0.9)), blob_video((1.1, 0.9))
    assert 0.0 < video_loss(near, target) < video_loss(far, target)
    # the depth term: a depth-only change costs exactly w * mean(((d - d*) / D)^2) over the covered pixels
    deeper = with_(target, depth=target.depth + 0.01)
    D = video_depth_scale(target)
    assert D == pytest.approx(0.3, rel=1e-3)
    assert video_loss(deeper, target, depth_weight=0.0) == 0.0
    assert video_loss(deeper, target, depth_weight=2.0) == pytest.approx(2.0 * (0.01 / D) ** 2, rel=1e-4)
    assert video_loss(deeper, target, depth_weight=1.0, depth_scale=0.1) == pytest.approx(0.01, rel=1e-4)


def test_video_loss_compares_colour_over_the_union_and_depth_over_the_intersection():
    target = blob_video(TRUTH)
    alpha = np.ones_like(target.alpha)
    alpha[:, :, 16:] = 0.0  # the prediction covers only the left half
    pred = with_(target, alpha=alpha, depth=np.where(alpha > 0, target.depth + 0.05, 0.0))
    # same colour everywhere: no photometric term; depth differs on the intersection (left half) only
    assert video_loss(pred, target, depth_weight=1.0, depth_scale=1.0) == pytest.approx(0.05**2, rel=1e-4)
    # colour differing only where neither covers is not compared
    bg = with_(target, alpha=alpha, rgb=np.where(alpha[..., None] > 0, target.rgb, 0.0))
    empty = with_(target, alpha=alpha)
    assert video_loss(bg, empty, depth_weight=0.0) == 0.0
    assert video_loss(bg, target, depth_weight=0.0) > 0.0  # the target covers the right half: compared there
    with pytest.raises(InputError, match="rgb"):
        video_loss(blob_video(TRUTH, T=6), target)
    with pytest.raises(InputError, match="alpha"):
        video_loss(blob_video(TRUTH, coverage=0.0), blob_video(TRUTH, coverage=0.0))


@pytest.mark.parametrize("budget", [1, 7, 30])
def test_cmaes_spends_exactly_the_budget(budget):
    calls = []

    def simulate_render(theta):
        calls.append(theta)
        return blob_video(theta)

    r = cmaes_calibrate(simulate_render, blob_video(TRUTH), bounds=BOUNDS, budget=budget, seed=6401)
    assert len(calls) == budget == r["calls"] == len(r["history"])
    assert r["popsize"] == 6 and r["generations"] == math.ceil(budget / 6)
    assert [(h["E_scale"], h["density_scale"]) for h in r["history"]] == calls
    for se, sr in calls:
        assert BOUNDS[0][0] <= se <= BOUNDS[0][1] and BOUNDS[1][0] <= sr <= BOUNDS[1][1]
        assert se == round(se, 6) and sr == round(sr, 6)
    best = min(r["history"], key=lambda h: h["loss"])
    assert r["loss"] == best["loss"] and r["theta"] == [best["E_scale"], best["density_scale"]]


def test_cmaes_is_deterministic_for_a_seed_and_keeps_to_its_own_random_state():
    target = blob_video(TRUTH)
    first = cmaes_calibrate(blob_video, target, bounds=BOUNDS, budget=14, seed=6402)

    def noisy_caller(theta):  # a simulator that draws from NumPy's global generator
        np.random.standard_normal(5)
        return blob_video(theta)

    np.random.seed(123)
    state = np.random.get_state()
    second = cmaes_calibrate(noisy_caller, target, bounds=BOUNDS, budget=14, seed=6402)
    assert second["history"] == first["history"] and second["theta"] == first["theta"]
    after = np.random.get_state()
    np.random.set_state(state)
    np.random.standard_normal(5 * 14)  # only the simulator's own draws moved the caller's generator
    assert np.array_equal(np.random.get_state()[1], after[1])
    other = cmaes_calibrate(blob_video, target, bounds=BOUNDS, budget=14, seed=6403)
    assert other["history"] != first["history"]


@pytest.mark.parametrize("seed", [6401, 6402, 6403])
def test_cmaes_finds_the_known_optimum_within_30_calls(seed):
    target = blob_video(TRUTH)
    r = cmaes_calibrate(blob_video, target, bounds=BOUNDS, budget=30, seed=seed)
    centre = tuple(float(np.sqrt(lo * hi)) for lo, hi in BOUNDS)
    assert r["history"][0]["loss"] > 0 and r["loss"] < 0.1 * video_loss(blob_video(centre), target)
    assert joint_error_pct(r["theta"], TRUTH) < 5.0


def test_cmaes_starts_at_x0_and_rejects_bad_settings():
    target = blob_video(TRUTH)
    x0 = np.log([0.6, 1.6])
    r = cmaes_calibrate(blob_video, target, bounds=BOUNDS, budget=6, seed=6401, x0=x0, sigma0=1e-6)
    for h in r["history"]:
        assert h["E_scale"] == pytest.approx(0.6, abs=1e-5) and h["density_scale"] == pytest.approx(1.6, abs=1e-5)
    for bad, field in (({"seed": 0}, "seed"), ({"budget": 0}, "budget"), ({"x0": np.log([2.0, 1.0])}, "x0"),
                       ({"bounds": ((1.0, 0.5), (0.75, 1.75))}, "bounds"), ({"sigma0": 0.0}, "sigma0"),
                       ({"popsize": 1}, "popsize")):
        kw = {"bounds": BOUNDS, "budget": 3, "seed": 6401, **bad}
        with pytest.raises(InputError, match=field):
            cmaes_calibrate(blob_video, target, **kw)


def test_candidate_bounds_are_the_candidate_box():
    assert candidate_bounds() == BOUNDS


def test_estimate_document_and_table_arithmetic():
    runs = {"a": {"theta": [0.9, 1.2], "loss": 0.1, "calls": 4, "best_call": 2, "generations": 1, "popsize": 6,
                  "depth_scale": 0.3, "history": []}}
    doc = cmaes_estimate(runs, seed=6401, budget=4, settings={"width": 48})
    assert doc["predictions"] == [{"case_name": "a", "E_scale": 0.9, "density_scale": 1.2}]
    assert doc["deployable"] is True and doc["calls"] == {"a": 4} and doc["seed"] == 6401
    with pytest.raises(InputError, match="calls"):
        cmaes_estimate(runs, seed=6401, budget=5)

    probes = ["pa", "pb"]
    rows = []
    for target, (et, rt) in {"t1": (1.0, 1.0), "t2": (0.6, 1.6)}.items():
        for k, seed in enumerate((1, 2, 3)):
            for j, probe in enumerate(probes):
                rows.append({"seed": seed, "target": target, "E_true": et, "rho_true": rt, "E_hat": et + 0.01 * k,
                             "rho_hat": rt, "joint_error_pct": float(k), "probe": probe,
                             "traj_rmse": (1.0 + k) * (j + 1) * (2.0 if target == "t2" else 1.0),
                             "psnr_fg": 30.0 + k, "ssim_crop": 0.9, "video_loss": 0.01 * k})
    table = cmaes_table(pd.DataFrame(rows), probes, budget=30, library_rollouts=54)
    assert list(table["target"]) == ["t1", "t2", "mean over targets"]
    t1 = table.iloc[0]
    assert t1["joint_error_pct"] == pytest.approx(1.0) and t1["joint_error_sd"] == pytest.approx(1.0)
    assert t1["traj_rmse_pb"] == pytest.approx(4.0) and t1["traj_rmse_pb_sd"] == pytest.approx(2.0)
    assert t1["E_hat"] == pytest.approx(1.01) and t1["n_seeds"] == 3 and t1["sim_calls"] == 90
    s = table.iloc[-1]
    assert s["traj_rmse_pa"] == pytest.approx(3.0) and s["traj_rmse_pa_sd"] == pytest.approx(math.sqrt(2.0))
    assert s["joint_error_sd"] == pytest.approx(0.0) and s["library_rollouts"] == 54 and s["sim_calls"] == 90
    with pytest.raises(InputError, match="probe"):
        cmaes_table(pd.DataFrame(rows[:-1]), probes, budget=30)


@pytest.mark.slow
def test_cmaes_on_the_pillow_is_deterministic_on_the_cpu(tmp_path):
    from knockgs_core.assets import build_asset, save_particles, save_scene, write_ply
    from knockgs_core.contract import load_contract
    from knockgs_core.experiments._cmaes import VideoScene, rollout_video, video_simulator
    from knockgs_core.rollout import run_rollout, write_deformation, write_rollout

    contract = load_contract("pillow", "ci")
    built = build_asset(contract)
    write_ply(built.gaussians, tmp_path / "pillow.ply")
    save_scene(built, tmp_path / "pillow.scene.npz")
    save_particles(built.particles, tmp_path / "pillow.particles.npz", contract=contract)
    scene = VideoScene.from_files(contract, tmp_path, width=48, height=36)
    truth = (0.95, 1.35)
    ro = run_rollout(contract, truth, contract.roles["calibration"], particles=scene.particles, export_F=True, device="cpu")
    write_rollout(tmp_path / "t.parquet", ro)
    write_deformation(tmp_path / "t.F.parquet", ro)
    target = rollout_video(scene, tmp_path / "t.parquet", tmp_path / "t.F.parquet")
    assert target.rgb.shape == (31, 36, 48, 3) and (target.alpha >= 0.5).any()

    simulate_render = video_simulator(contract, scene, device="cpu")
    assert video_loss(simulate_render(truth), target) == 0.0  # the stored rollout's video, from memory
    in_memory = video_simulator(contract, VideoScene.from_asset(contract, built, width=48, height=36), device="cpu")
    assert video_loss(in_memory(truth), target) < 1e-10  # the asset before its PLY round trip
    runs = [cmaes_calibrate(simulate_render, target, bounds=BOUNDS, budget=4, seed=6401) for _ in range(2)]
    assert runs[0]["calls"] == 4 and runs[0]["history"] == runs[1]["history"]
    assert all(h["loss"] > 0 for h in runs[0]["history"])


def test_cmaes_rows_score_every_seed_as_alone_reading_each_target_rollout_once(tmp_path, monkeypatch):
    # the seeds' frozen estimates are scored together: each target's rollout is read once for all
    # seeds (and a theta two seeds share once), with the rows each seed's own evaluation gives
    import pandas as pd

    import knockgs_core.experiments._main as main
    from _rollouts import theta_rollouts
    from knockgs_core.experiments import evaluate_method
    from knockgs_core.experiments._cmaes import cmaes_rows
    from knockgs_core.rollout import read_rollout, theta_tag

    targets = pd.DataFrame({"case_name": ["t1", "t2"], "E_scale": [0.8, 1.2], "density_scale": [1.1, 0.9]})
    docs = {6401: {"predictions": [{"case_name": "t1", "E_scale": 0.82, "density_scale": 1.08},
                                   {"case_name": "t2", "E_scale": 1.25, "density_scale": 0.95}],
                   "runs": {"t1": {"loss": 0.5}, "t2": {"loss": 0.25}}},
            6402: {"predictions": [{"case_name": "t1", "E_scale": 0.82, "density_scale": 1.08},
                                   {"case_name": "t2", "E_scale": 1.1, "density_scale": 1.0}]}}
    thetas = {(0.8, 1.1), (1.2, 0.9), (0.82, 1.08), (1.25, 0.95), (1.1, 1.0)}
    paths = theta_rollouts(tmp_path, thetas, "standard_y")
    where = lambda probe, th: paths[f"{probe}/{theta_tag(th)}"]  # noqa: E731
    reads = []

    def counting(path):
        reads.append(path)
        return read_rollout(path)

    def image_rows(doc, targets, frames_path, probes):
        return pd.DataFrame([{"target": c, "probe": p, "psnr_fg": 40.0} for c in targets["case_name"] for p in probes])

    monkeypatch.setattr(main, "read_rollout", counting)
    monkeypatch.setattr(main, "render_metrics_rows", image_rows)
    rows = cmaes_rows(docs, targets, where, None, ["standard_y"])
    # t1: truth and the shared estimate; t2: truth and the two seeds' estimates
    assert len(reads) == 5 and len(set(reads)) == 5
    assert list(rows["seed"]) == [6401, 6401, 6402, 6402]
    assert list(rows["video_loss"].iloc[:2]) == [0.5, 0.25] and rows["video_loss"].iloc[2:].isna().all()
    monkeypatch.setattr(main, "read_rollout", read_rollout)
    for seed, doc in docs.items():
        alone = evaluate_method(doc, targets, where, ["standard_y"])
        got = rows[rows["seed"] == seed].reset_index(drop=True)
        pd.testing.assert_frame_equal(got[alone.columns], alone)
    with pytest.raises(InputError, match="no seed"):
        cmaes_rows({}, targets, where, None, ["standard_y"])
