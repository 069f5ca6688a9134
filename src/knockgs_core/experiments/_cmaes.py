"""CMA-ES direct video optimization: the alternative inverse route.

Instead of a library of offline rollouts and a descriptor, CMA-ES searches ``theta = (s_E,
s_rho)`` directly: every candidate is simulated under Probe A, rendered as an RGB-D video with
the contract camera, and scored against the target's rendered RGB-D Probe-A video by
:func:`video_loss`. The search runs in ``x = (log s_E, log s_rho)`` inside the candidates'
bounding box, spends exactly ``budget`` simulator calls per target (30, seeds 6401, 6402,
6403 in the paper's protocol) and is then frozen: the lowest-loss theta seen is written back
into the simulator and evaluated like every estimate of the main benchmark (Probe A and
every Probe B, trajectories and rendered frames; :func:`cmaes_rows`, :func:`cmaes_table`).

Only the target's Probe-A video enters the search: no descriptor, no library, no label.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from ..errors import InputError
from ..observe import RGBDFrames, render_rgbd

__all__ = [
    "DEPTH_WEIGHT",
    "CMAES_METHOD",
    "candidate_bounds",
    "video_depth_scale",
    "video_loss",
    "cmaes_calibrate",
    "VideoScene",
    "video_simulator",
    "rollout_video",
    "cmaes_estimate",
    "cmaes_rows",
    "cmaes_table",
    "cmaes_note",
]

#: Weight of the normalized depth term of :func:`video_loss` against the RGB term.
DEPTH_WEIGHT = 1.0
#: The route's name in estimate documents and tables.
CMAES_METHOD = "cmaes_video"


# ------------------------------------------------------------------------------------
# the loss
# ------------------------------------------------------------------------------------
def candidate_bounds(candidates: pd.DataFrame | None = None) -> tuple[tuple[float, float], tuple[float, float]]:
    """``((s_E min, s_E max), (s_rho min, s_rho max))`` of the candidate table (default
    ``config/candidates.csv``, :func:`knockgs_core.contract.load_candidates`)."""
    if candidates is None:
        from ..contract import load_candidates

        candidates = load_candidates()
    e = candidates["E_scale"].to_numpy(dtype=np.float64)
    r = candidates["density_scale"].to_numpy(dtype=np.float64)
    return (float(e.min()), float(e.max())), (float(r.min()), float(r.max()))


def _check_pair(pred: RGBDFrames, target: RGBDFrames) -> None:
    if pred.rgb.shape != target.rgb.shape:
        raise InputError(pred.source, "rgb", f"shape {list(pred.rgb.shape)} differs from the target's "
                         f"{list(target.rgb.shape)} ({target.source})")


def video_depth_scale(frames: RGBDFrames, *, alpha_min: float = 0.5) -> float:
    """The depth scale [m] of :func:`video_loss`: the extent (max minus min) of the expected
    depth over the pixels of the first frame covered at least ``alpha_min``, i.e. the depth
    range the object spans in the camera at rest."""
    covered = frames.alpha[0] >= alpha_min
    if not covered.any():
        raise InputError(frames.source, "alpha", f"the first frame covers no pixel (alpha >= {alpha_min})")
    d = frames.depth[0][covered].astype(np.float64)
    scale = float(d.max() - d.min())
    if not scale > 0:
        raise InputError(frames.source, "depth", "the covered pixels of the first frame have a single depth")
    return scale


def video_loss(pred: RGBDFrames, target: RGBDFrames, *, depth_weight: float = DEPTH_WEIGHT,
               depth_scale: float | None = None, alpha_min: float = 0.5) -> float:
    """Photometric plus depth loss between two RGB-D videos of the same camera and frames.

    ``L = mean_{(t, p) in U, c} (I_pred - I_target)^2 + w * mean_{(t, p) in C} ((d_pred - d_target) / D)^2``

    - ``I`` [T, H, W, 3]: the colour in [0, 1] (composited over the background); ``U`` the
      union over frames of both coverage masks (``alpha >= alpha_min`` in either video), so a
      pixel that only one of them covers compares object colour with background;
    - ``d`` [T, H, W]: the expected camera depth [m] of the covered part; ``C`` the
      intersection of both coverage masks (where both have a depth); a video pair without a
      common covered pixel has no depth term;
    - ``D`` [m]: ``depth_scale``, default the target's depth extent at rest
      (:func:`video_depth_scale`), so that both terms are dimensionless and of order one for
      an error of the object's size; ``w``: ``depth_weight`` (:data:`DEPTH_WEIGHT`).

    Returns a finite float >= 0, 0 for identical videos. Raises :class:`InputError` when the
    shapes differ or neither video covers a pixel.
    """
    _check_pair(pred, target)
    if not (math.isfinite(depth_weight) and depth_weight >= 0):
        raise InputError("video loss", "depth_weight", f"must be a finite number >= 0, got {depth_weight!r}")
    pm = pred.alpha >= alpha_min
    tm = target.alpha >= alpha_min
    union = pm | tm
    if not union.any():
        raise InputError(target.source, "alpha", f"neither video covers a pixel (alpha >= {alpha_min})")
    diff = pred.rgb.astype(np.float64) - target.rgb.astype(np.float64)
    loss = float(np.mean(diff[union] ** 2))
    if depth_weight > 0:
        inter = pm & tm
        if inter.any():
            D = video_depth_scale(target, alpha_min=alpha_min) if depth_scale is None else float(depth_scale)
            if not (math.isfinite(D) and D > 0):
                raise InputError("video loss", "depth_scale", f"must be a positive number of metres, got {depth_scale!r}")
            dd = (pred.depth[inter].astype(np.float64) - target.depth[inter].astype(np.float64)) / D
            loss += depth_weight * float(np.mean(dd**2))
    return loss


# ------------------------------------------------------------------------------------
# the search
# ------------------------------------------------------------------------------------
def _log_box(bounds) -> tuple[np.ndarray, np.ndarray]:
    b = np.asarray(bounds, dtype=np.float64)
    if b.shape != (2, 2) or not np.all(np.isfinite(b)) or np.any(b <= 0) or np.any(b[:, 1] <= b[:, 0]):
        raise InputError("CMA-ES", "bounds", "expected ((s_E min, s_E max), (s_rho min, s_rho max)), positive, "
                         f"min < max; got {bounds!r}")
    lo, hi = np.log(b[:, 0]), np.log(b[:, 1])
    return lo, hi - lo


def cmaes_calibrate(simulate_render: Callable[[tuple[float, float]], RGBDFrames], target: RGBDFrames, *,
                    bounds, budget: int = 30, seed: int, popsize: int | None = None, x0=None, sigma0: float = 0.3,
                    depth_weight: float = DEPTH_WEIGHT, depth_scale: float | None = None, decimals: int | None = 6) -> dict:
    """CMA-ES on ``x = (log s_E, log s_rho)`` against a target video, ``budget`` calls exactly.

    ``simulate_render(theta) -> RGBDFrames`` simulates and renders ``theta = (s_E, s_rho)``
    (e.g. :func:`video_simulator`); each call is scored by :func:`video_loss` against
    ``target`` (``depth_weight``, ``depth_scale`` passed on). The search uses ``cma``'s
    ``CMAEvolutionStrategy`` in ``x`` scaled to the unit box ``u = (x - log min) / (log max -
    log min)`` of ``bounds`` = ``((s_E min, s_E max), (s_rho min, s_rho max))``
    (:func:`candidate_bounds`), with the box as cma's bounds. It starts at the box centre, or
    at ``x0`` = ``(log s_E, log s_rho)`` inside the box; ``sigma0`` is the initial step size
    as a fraction of the box width in each log coordinate; ``popsize`` defaults to cma's
    ``4 + floor(3 ln 2)`` = 6. Each candidate theta is rounded to ``decimals`` decimals
    (the 6-decimal values rollout files are keyed by, so the frozen estimate is exactly the
    theta that was scored).

    Generations are asked and told in turn until ``budget`` calls are spent; the last
    generation is evaluated only as far as the budget allows (never more calls), and cma's
    own termination criteria are not consulted: the budget is the stop. ``seed`` (a positive
    integer) goes to cma's options, and cma's draws from NumPy's global generator are kept in
    a state of their own (the caller's global state is restored), so a fixed seed gives the
    same calls bit for bit whatever ``simulate_render`` draws. No files are written
    (``verbose=-9``, no log).

    Returns ``theta`` [s_E, s_rho] (the lowest loss seen, the first on ties), ``loss``,
    ``calls`` (= ``budget``), ``best_call`` (its index), ``generations``, ``history`` (per call:
    ``call``, ``generation``, ``E_scale``, ``density_scale``, ``loss``) and the settings
    (``seed``, ``budget``, ``popsize``, ``sigma0``, ``x0``, ``bounds``, ``depth_weight``,
    ``depth_scale``).
    """
    import cma

    if not isinstance(target, RGBDFrames):
        raise InputError("CMA-ES", "target", f"must be RGBDFrames, got {type(target).__name__}")
    lo, width = _log_box(bounds)
    if isinstance(budget, bool) or not isinstance(budget, (int, np.integer)) or budget < 1:
        raise InputError("CMA-ES", "budget", f"must be a positive integer, got {budget!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 < seed < 2**32:
        raise InputError("CMA-ES", "seed", f"must be a positive integer below 2**32 (0 would seed from the clock), got {seed!r}")
    if popsize is not None and (isinstance(popsize, bool) or not isinstance(popsize, (int, np.integer)) or popsize < 2):
        raise InputError("CMA-ES", "popsize", f"must be an integer >= 2, got {popsize!r}")
    if not (math.isfinite(sigma0) and 0 < sigma0 <= 1):
        raise InputError("CMA-ES", "sigma0", f"must be in (0, 1] (a fraction of the box width), got {sigma0!r}")
    if x0 is None:
        u0 = np.full(2, 0.5)
    else:
        x = np.asarray(x0, dtype=np.float64)
        if x.shape != (2,) or not np.all(np.isfinite(x)):
            raise InputError("CMA-ES", "x0", f"expected (log s_E, log s_rho), got {x0!r}")
        u0 = (x - lo) / width
        if np.any(u0 < 0) or np.any(u0 > 1):
            raise InputError("CMA-ES", "x0", f"theta {tuple(np.exp(x))} lies outside the bounds {bounds!r}")
    if depth_scale is None:
        depth_scale = video_depth_scale(target)
    theta_lo, theta_hi = np.exp(lo), np.exp(lo + width)

    opts = {"seed": int(seed), "bounds": [[0.0, 0.0], [1.0, 1.0]], "verbose": -9, "verb_log": 0, "verb_disp": 0,
            "verb_plot": 0}
    if popsize is not None:
        opts["popsize"] = int(popsize)
    outer = np.random.get_state()
    try:
        es = cma.CMAEvolutionStrategy(u0.tolist(), float(sigma0), opts)
        cma_state = np.random.get_state()
    finally:
        np.random.set_state(outer)

    def in_cma_rng(fn):
        nonlocal cma_state
        caller = np.random.get_state()
        np.random.set_state(cma_state)
        try:
            return fn()
        finally:
            cma_state = np.random.get_state()
            np.random.set_state(caller)

    history: list[dict] = []
    generation = 0
    while len(history) < budget:
        us = in_cma_rng(es.ask)
        take = min(len(us), budget - len(history))
        losses = []
        for u in us[:take]:
            theta = np.exp(lo + width * np.clip(np.asarray(u, dtype=np.float64), 0.0, 1.0))
            if decimals is not None:
                theta = np.clip(np.round(theta, decimals), theta_lo, theta_hi)
            th = (float(theta[0]), float(theta[1]))
            frames = simulate_render(th)
            if not isinstance(frames, RGBDFrames):
                raise InputError("CMA-ES", "simulate_render", f"must return RGBDFrames, got {type(frames).__name__}")
            loss = video_loss(frames, target, depth_weight=depth_weight, depth_scale=depth_scale)
            losses.append(loss)
            history.append({"call": len(history), "generation": generation, "E_scale": th[0], "density_scale": th[1],
                            "loss": loss})
        if take == len(us):
            in_cma_rng(lambda: es.tell(us, losses))
        generation += 1

    best = min(range(len(history)), key=lambda i: (history[i]["loss"], i))
    h = history[best]
    return {
        "theta": [h["E_scale"], h["density_scale"]],
        "loss": h["loss"],
        "calls": len(history),
        "best_call": best,
        "generations": generation,
        "history": history,
        "seed": int(seed),
        "budget": int(budget),
        "popsize": int(es.popsize),
        "sigma0": float(sigma0),
        "x0": (lo + width * u0).tolist(),
        "bounds": [[float(theta_lo[0]), float(theta_hi[0])], [float(theta_lo[1]), float(theta_hi[1])]],
        "depth_weight": float(depth_weight),
        "depth_scale": float(depth_scale),
    }


# ------------------------------------------------------------------------------------
# the object: simulate and render
# ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class VideoScene:
    """What the simulator moves and the camera sees: ``gaussians`` (the normalized 3DGS
    asset), ``static_mask`` [G] bool and ``gaussian_index`` [n_gs] (its scene data),
    ``particles`` (a :class:`knockgs_core.assets.ParticleSet`, GS particles first) and
    ``camera`` (the contract camera at the loss's image size)."""

    gaussians: object
    static_mask: np.ndarray
    gaussian_index: np.ndarray
    particles: object
    camera: object

    @classmethod
    def from_files(cls, contract, assets_dir: str | os.PathLike, *, width: int, height: int) -> VideoScene:
        """The asset files the workflow writes for the contract's object:
        ``{assets_dir}/{object}.ply``, ``.scene.npz`` and ``.particles.npz`` (the particles
        checked against ``contract``)."""
        from ..assets import load_particles, load_scene, read_ply
        from ..render import camera_from_contract

        root = Path(assets_dir)
        gaussians = read_ply(root / f"{contract.name}.ply")
        static_mask, gaussian_index = load_scene(root / f"{contract.name}.scene.npz", n_gaussians=len(gaussians))
        particles = load_particles(root / f"{contract.name}.particles.npz", contract=contract)
        return cls(gaussians, static_mask, gaussian_index, particles,
                   camera_from_contract(contract.camera, width=width, height=height))

    @classmethod
    def from_asset(cls, contract, built, *, width: int, height: int) -> VideoScene:
        """A :class:`knockgs_core.assets.BuiltAsset` of ``contract`` held in memory."""
        from ..render import camera_from_contract

        return cls(built.gaussians, np.asarray(built.static_mask), np.asarray(built.particles.gaussian_index),
                   built.particles, camera_from_contract(contract.camera, width=width, height=height))

    def render(self, positions, F, *, frame_dt: float, device: str = "cpu", source: str = "render") -> RGBDFrames:
        """The RGB-D video of a rollout: ``positions`` [T, N, 3] (the first n_gs rows
        Gaussian-associated), ``F`` [T, n_gs, 3, 3], taken as float32 as the rollout files
        store them, so a video rendered from a simulation in memory equals the one rendered
        from its files."""
        frames = render_rgbd(self.gaussians, self.static_mask, self.gaussian_index,
                             np.asarray(positions, dtype=np.float32), np.asarray(F, dtype=np.float32), self.camera,
                             frame_dt=frame_dt, device=device)
        return RGBDFrames(rgb=frames.rgb, alpha=frames.alpha, depth=frames.depth, camera=frames.camera,
                          frame_dt=frames.frame_dt, source=source)


def video_simulator(contract, scene: VideoScene, *, probe: str | None = None, device: str = "cpu",
                    deterministic: bool = False) -> Callable[[tuple[float, float]], RGBDFrames]:
    """``simulate_render(theta)`` for :func:`cmaes_calibrate`: one rollout of ``contract`` at
    ``theta`` under ``probe`` (default the contract's calibration probe, Probe A) with the
    deformation gradients (:func:`knockgs_core.rollout.run_rollout`, on ``device``, with
    ``deterministic`` as there), rendered with depth by ``scene`` (:meth:`VideoScene.render`)."""
    from ..rollout import run_rollout

    name = probe or contract.roles["calibration"]

    def simulate_render(theta: tuple[float, float]) -> RGBDFrames:
        ro = run_rollout(contract, theta, name, particles=scene.particles, export_F=True, device=device,
                         deterministic=deterministic)
        return scene.render(ro.positions, ro.F, frame_dt=ro.meta["probe"]["export"]["frame_dt"], device=device,
                            source=f"{contract.name} {name} theta ({theta[0]:.6f}, {theta[1]:.6f})")

    return simulate_render


def rollout_video(scene: VideoScene, rollout_path, F_path, *, device: str = "cpu") -> RGBDFrames:
    """The RGB-D video of a stored rollout (positions and its deformation-gradient file,
    checked to come from the same run)."""
    from ..rollout import read_deformation, read_rollout

    ro = read_rollout(rollout_path)
    F = read_deformation(F_path, rollout=ro, rollout_path=rollout_path)
    return scene.render(ro.positions, F, frame_dt=ro.meta["probe"]["export"]["frame_dt"], device=device,
                        source=str(rollout_path))


def cmaes_estimate(runs: Mapping[str, Mapping], *, seed: int, budget: int, settings: Mapping | None = None) -> dict:
    """The frozen-estimate document of one seed: ``runs`` maps target name -> the result of
    :func:`cmaes_calibrate`. ``predictions`` has the main estimates' layout (``case_name``,
    ``E_scale``, ``density_scale``); ``runs`` keeps each target's loss, calls, best call and
    loss history; ``settings`` (render size, depth weight, ...) is stored as given."""
    preds, detail = [], {}
    for name, r in runs.items():
        if r["calls"] != budget:
            raise InputError(f"CMA-ES run of {name}", "calls", f"{r['calls']} calls, the budget is {budget}")
        preds.append({"case_name": name, "E_scale": float(r["theta"][0]), "density_scale": float(r["theta"][1])})
        detail[name] = {k: r[k] for k in ("loss", "calls", "best_call", "generations", "popsize", "depth_scale", "history")}
    return {"method": CMAES_METHOD, "table_method": CMAES_METHOD, "deployable": True, "seed": int(seed),
            "budget": int(budget), "settings": dict(settings or {}), "predictions": preds,
            "calls": {n: d["calls"] for n, d in detail.items()}, "runs": detail}


# ------------------------------------------------------------------------------------
# evaluation and table
# ------------------------------------------------------------------------------------
def cmaes_rows(estimates: Mapping[int, Mapping], targets: pd.DataFrame, rollout_path: Callable, frames_path: Callable,
               probes: Sequence[str]) -> pd.DataFrame:
    """Write-back evaluation of every seed's frozen estimates, exactly as the main benchmark's
    (:func:`knockgs_core.experiments.evaluate_methods` for the joint error and the trajectory
    RMSE over the Gaussian-associated particles, :func:`~knockgs_core.experiments.render_metrics_rows`
    for the foreground PSNR and object-crop SSIM): one row per (seed, target, probe), with the
    estimate's final video loss. ``estimates``: seed -> estimate document
    (:func:`cmaes_estimate`); ``rollout_path(probe, theta)`` and ``frames_path(probe, theta)``
    locate rollouts and rendered frames (``.npz``)."""
    from ._main import evaluate_methods, render_metrics_rows

    if not estimates:
        raise InputError("CMA-ES table", "estimates", "no seed")
    evals = evaluate_methods(estimates, targets, rollout_path, probes)  # each target's rollout read once
    frames = []
    for seed, doc in estimates.items():
        ev = evals[seed]
        im = render_metrics_rows(doc, targets, frames_path, probes)
        df = ev.merge(im, on=["target", "probe"], how="left", validate="one_to_one")
        df.insert(0, "seed", int(seed))
        df["video_loss"] = df["target"].map({n: r["loss"] for n, r in doc.get("runs", {}).items()})
        frames.append(df)
    return pd.concat(frames, ignore_index=True)


def _mean_sd(x) -> tuple[float, float]:
    """Mean and sd (ddof 1; 0 for a single value) of ``x``; an infinite value (a PSNR of
    identical frames) gives an infinite mean and an undefined (NaN) sd."""
    x = np.asarray(x, dtype=np.float64)
    if len(x) < 2:
        return float(np.mean(x)), 0.0
    with np.errstate(invalid="ignore"):
        return float(np.mean(x)), float(np.std(x, ddof=1))


def cmaes_table(rows: pd.DataFrame, probes: Sequence[str], *, budget: int, library_rollouts: int = 54) -> pd.DataFrame:
    """One row per target, then a summary row (``target`` = ``mean over targets``).

    A target's row: the true theta, the mean and sd (ddof 1) over seeds of the estimate
    (``E_hat``, ``rho_hat``), of the joint error (``joint_error_pct``, ``joint_error_sd``, as the
    main table names them), of the trajectory RMSE (``traj_rmse_{probe}``)
    and of the image metrics (``psnr_fg_{probe}``, ``ssim_crop_{probe}``) under every probe, the
    final video loss, ``n_seeds``, ``sim_calls`` (simulator calls spent on the target:
    ``budget`` x seeds) and ``library_rollouts`` (the library route's offline rollouts, shared
    by every target). The summary row: mean and sd (ddof 1) over targets of the targets'
    seed means, as the main table's sd (no theta: NaN). ``rows``: :func:`cmaes_rows`.
    """
    per_probe = [(f"{m}_{p}", m, p) for m in ("traj_rmse", "psnr_fg", "ssim_crop") for p in probes]
    out = []
    for target, e in rows.groupby("target", sort=False):
        seeds = sorted(e["seed"].unique())
        per_seed = e.drop_duplicates("seed")
        first = e.iloc[0]
        row = {"target": target, "E_true": float(first["E_true"]), "rho_true": float(first["rho_true"]), "n_seeds": len(seeds)}
        for col in ("E_hat", "rho_hat"):
            row[col], row[f"{col}_sd"] = _mean_sd(per_seed[col])
        row["joint_error_pct"], row["joint_error_sd"] = _mean_sd(per_seed["joint_error_pct"])
        for col, metric, probe in per_probe:
            sel = e[e["probe"] == probe]
            if sorted(sel["seed"]) != seeds:
                raise InputError("CMA-ES table", "probe", f"target {target}, probe {probe}: rows for seeds "
                                 f"{sorted(sel['seed'])}, expected one for each of {seeds}")
            row[col], row[f"{col}_sd"] = _mean_sd(sel[metric])
        row["video_loss"], row["video_loss_sd"] = _mean_sd(per_seed["video_loss"])
        row["sim_calls"] = int(budget) * len(seeds)
        row["library_rollouts"] = int(library_rollouts)
        out.append(row)
    if not out:
        raise InputError("CMA-ES table", "target", "no rows")
    table = pd.DataFrame(out)
    # the summary row has no theta: the targets' estimates are of different materials
    summary = {"target": "mean over targets", "E_true": np.nan, "rho_true": np.nan, "n_seeds": int(table["n_seeds"].min()),
               "E_hat": np.nan, "E_hat_sd": np.nan, "rho_hat": np.nan, "rho_hat_sd": np.nan}
    for col in table.columns:
        if col.endswith("_sd") or col in summary or col in ("sim_calls", "library_rollouts"):
            continue
        sd_col = "joint_error_sd" if col == "joint_error_pct" else f"{col}_sd"
        summary[col], summary[sd_col] = _mean_sd(table[col])
    summary["sim_calls"] = int(table["sim_calls"].iloc[0])
    summary["library_rollouts"] = int(library_rollouts)
    return pd.concat([table, pd.DataFrame([summary])[table.columns]], ignore_index=True)


def cmaes_note(table: pd.DataFrame, *, budget: int, seeds: Sequence[int], width: int, height: int,
               profile: str = "") -> str:
    """The table's note: what was optimized, the budget beside the library's, what the sds are."""
    n_targets = len(table) - 1
    per_target = int(budget) * len(seeds)
    lib = int(table["library_rollouts"].iloc[0])
    prof = f"Profile `{profile}`. " if profile else ""
    return (f"{prof}CMA-ES on (log s_E, log s_rho) inside the candidates' box against each target's rendered RGB-D "
            f"Probe-A video ({width}x{height}; photometric + normalized-depth loss), {budget} simulator calls per run, "
            f"seeds {', '.join(str(s) for s in seeds)}, then frozen. Target rows: mean and sd (ddof 1) over seeds; last "
            f"row: mean and sd (ddof 1) over the {n_targets} targets of the seed means. Trajectory RMSE over the "
            f"Gaussian-associated particles (normalized-domain m); foreground PSNR [dB] and object-crop SSIM as in the "
            f"render table. Simulator calls: {per_target} per target ({per_target * n_targets} in all), against the "
            f"library route's {lib} offline rollouts shared by all targets.")
