"""The main benchmark: descriptor tables, frozen estimates, Probe-A/B evaluation, renders.

Workflow scripts call one function here each. Method names are the calibration registry's
(:data:`knockgs_core.calibration.METHOD_NAMES`, the names the paper's tables use). The
oracle is evaluation-only: it is built here from hidden labels and never reachable from
:func:`frozen_estimate` for deployable methods.
"""

from __future__ import annotations

import hashlib
from typing import Mapping, Sequence

import numpy as np
import pandas as pd

from ..descriptors import FEATURE_NAMES, descriptor
from ..errors import InputError
from ..metrics import curve_differences, joint_error_pct, rms_displacement_curve, trajectory_rmse
from ..render import camera_from_contract, render_rollout  # re-exported: the studies' callers import them from here
from ..rollout import read_rollout, theta_tag
from ..io import ordered_map

__all__ = [
    "library_table",
    "query_table",
    "frozen_estimate",
    "oracle_estimate",
    "evaluate_method",
    "evaluate_methods",
    "estimate_thetas",
    "file_sha256",
    "theta_tag",
    "camera_from_contract",
    "render_rollout",
    "render_metrics_rows",
]

def file_sha256(path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _descriptor_of(path) -> np.ndarray:
    ro = read_rollout(path)
    return descriptor(ro.positions, n_frames=ro.positions.shape[0], source=str(path))


def _descriptors_of(paths, workers: int) -> list[np.ndarray]:
    """The descriptors of rollout files ``paths``, in order, read by ``workers`` threads
    (:func:`knockgs_core.io.ordered_map`); the first failing file's error is raised, as
    a serial loop would."""
    return ordered_map(_descriptor_of, paths, workers=int(workers))


def library_table(candidates: pd.DataFrame, rollouts: Mapping[str, str], *, workers: int = 1) -> pd.DataFrame:
    """Candidate library: ``case_name, E_scale, density_scale`` + the five descriptor
    features of each candidate's Probe-A rollout (``rollouts[case_name] -> path``), the
    rollouts read by ``workers`` threads (the same table for any count)."""
    recs = list(candidates.itertuples(index=False))
    phis = _descriptors_of((rollouts[rec.case_name] for rec in recs), workers)
    return pd.DataFrame([{"case_name": rec.case_name, "E_scale": rec.E_scale, "density_scale": rec.density_scale,
                          **dict(zip(FEATURE_NAMES, phi))} for rec, phi in zip(recs, phis)])


def query_table(rollouts: Mapping[str, str], *, workers: int = 1) -> pd.DataFrame:
    """Query descriptors of the targets' Probe-A rollouts: ``case_name`` + five features,
    no labels (the labels never enter a deployable estimator); ``workers`` as in
    :func:`library_table`."""
    phis = _descriptors_of(rollouts.values(), workers)
    return pd.DataFrame([{"case_name": name, **dict(zip(FEATURE_NAMES, phi))} for name, phi in zip(rollouts, phis)])


def frozen_estimate(method: str, library_csv, queries_csv, params: Mapping | None = None, *, config_hash: str = "") -> dict:
    """A deployable method's frozen estimates: the calibration output plus provenance
    (inputs and their hashes, configuration hash). Reads only the library and query tables.

    ``method`` is a canonical name of :data:`knockgs_core.calibration.DEPLOYABLE_METHODS` or
    one of its aliases; the document's ``method`` and ``table_method`` hold the canonical name."""
    from .. import calibration

    try:
        name = calibration.canonical_method(method)
    except ValueError as exc:
        raise InputError("estimate", "method", str(exc)) from None
    if name not in calibration.DEPLOYABLE_METHODS:
        raise InputError("estimate", "method",
                         f"'{method}' is not deployable; deployable: {', '.join(calibration.DEPLOYABLE_METHODS)}")
    out = calibration.calibrate(str(library_csv), str(queries_csv), name, **dict(params or {}))
    out["table_method"] = name
    out["deployable"] = True
    out["inputs"] = {"library": str(library_csv), "queries": str(queries_csv)}
    out["input_sha256"] = {"library": file_sha256(library_csv), "queries": file_sha256(queries_csv)}
    out["config_hash"] = config_hash
    return out


def oracle_estimate(library_csv, targets: pd.DataFrame, params: Mapping | None = None, *, config_hash: str = "") -> dict:
    """Parameter-nearest oracle (reads the hidden targets; a diagnostic, never deployable).

    ``params``: the oracle's options (:data:`knockgs_core.calibration.METHOD_OPTIONS`, e.g.
    ``{"metric": "standardized"}``); an unknown option is an :class:`InputError`.
    """
    from ..calibration import METHOD_OPTIONS, ORACLE_METHOD
    from ..calibration.oracle import ParameterNearestOracle

    params = dict(params or {})
    for key in params:
        if key not in METHOD_OPTIONS[ORACLE_METHOD]:
            allowed = ", ".join(METHOD_OPTIONS[ORACLE_METHOD]) or "none"
            raise InputError(f"method_params.{ORACLE_METHOD}", key, f"unknown option; allowed: {allowed}")
    try:
        oracle = ParameterNearestOracle(**params)
    except ValueError as exc:
        raise InputError(f"method_params.{ORACLE_METHOD}", "metric", str(exc)) from None
    lib = pd.read_csv(library_csv)
    oracle = oracle.fit(None, lib[["E_scale", "density_scale"]].to_numpy(), lib["case_name"].tolist())
    est = oracle.predict(targets[["E_scale", "density_scale"]].to_numpy(), names=targets["case_name"].tolist())
    return {
        "method": "parameter_nearest_oracle",
        "table_method": "parameter_nearest_oracle",
        "deployable": False,
        "params": params,
        "predictions": [e.to_dict() for e in est],
        "inputs": {"library": str(library_csv), "targets": "hidden target labels"},
        "input_sha256": {"library": file_sha256(library_csv)},
        "config_hash": config_hash,
    }


def estimate_thetas(estimate: Mapping) -> dict[str, tuple[float, float]]:
    """target name -> frozen (s_E, s_rho) of an estimates JSON document."""
    return {p["case_name"]: (float(p["E_scale"]), float(p["density_scale"])) for p in estimate["predictions"]}


def evaluate_method(
    estimate: Mapping,
    targets: pd.DataFrame,
    rollout_path,
    probes: Sequence[str],
    *,
    max_particles: int = 100_000,
    seed: int = 42,
    workers: int = 1,
) -> pd.DataFrame:
    """Frozen write-back evaluation: one row per (target, probe) with the joint parameter
    error, trajectory RMSE over Gaussian-associated particles and curve metrics.

    ``rollout_path(probe, theta) -> path`` locates rollouts; a target's truth is the rollout
    at its hidden theta. One method's :func:`evaluate_methods` (``workers`` threads).
    """
    return evaluate_methods({"": estimate}, targets, rollout_path, probes, max_particles=max_particles, seed=seed,
                            workers=workers)[""]


def evaluate_methods(
    estimates: Mapping[str, Mapping],
    targets: pd.DataFrame,
    rollout_path,
    probes: Sequence[str],
    *,
    max_particles: int = 100_000,
    seed: int = 42,
    workers: int = 1,
) -> dict[str, pd.DataFrame]:
    """:func:`evaluate_method` of several methods' estimates (method -> estimates document)
    at once: each target's truth under a probe is read once for all methods, with its RMS
    displacement curve, and a prediction that several methods share (the same theta) is read
    once. Returns method -> its rows, the same as :func:`evaluate_method` of it alone.

    ``workers`` threads score the targets side by side (:func:`knockgs_core.io.ordered_map`;
    each holds a truth and a prediction in memory at a time); the rows are the same, in the
    same order, for any count. Every target's estimates are checked before a file is read.
    """
    thetas = {m: estimate_thetas(est) for m, est in estimates.items()}
    records = list(targets.itertuples(index=False))
    for rec in records:
        for m, th in thetas.items():
            if rec.case_name not in th:
                raise InputError("estimates", "predictions", f"no estimate for target {rec.case_name}")

    def target_rows(rec) -> dict[str, list]:
        rows: dict[str, list] = {m: [] for m in thetas}
        truth = (float(rec.E_scale), float(rec.density_scale))
        errors = {m: joint_error_pct(th[rec.case_name], truth) for m, th in thetas.items()}
        for probe in probes:
            true = read_rollout(rollout_path(probe, truth))
            n_gs = int(true.meta["n_gs"])
            X = true.positions[:, :n_gs]
            q = rms_displacement_curve(X)
            by_path: dict = {}  # prediction path -> its trajectory RMSE and curve metrics
            for m, th in thetas.items():
                est = th[rec.case_name]
                path = rollout_path(probe, est)
                if path not in by_path:
                    pred = read_rollout(path)
                    if pred.positions.shape != true.positions.shape:
                        raise InputError(path, "positions", "shape differs from the target rollout")
                    P = pred.positions[:, :n_gs]
                    by_path[path] = {"traj_rmse": trajectory_rmse(P, X, max_particles=max_particles, seed=seed),
                                     **curve_differences(rms_displacement_curve(P), q)}
                    del pred, P
                rows[m].append({
                    "target": rec.case_name,
                    "E_true": truth[0],
                    "rho_true": truth[1],
                    "E_hat": est[0],
                    "rho_hat": est[1],
                    "joint_error_pct": errors[m],
                    "probe": probe,
                    **by_path[path],
                })
            del true, X
        return rows

    per_target = ordered_map(target_rows, records, workers=workers)
    return {m: pd.DataFrame([row for rows in per_target for row in rows[m]]) for m in thetas}


# ------------------------------------------------------------------------------------
# rendered frames
# ------------------------------------------------------------------------------------
def render_metrics_rows(estimate: Mapping, targets: pd.DataFrame, render_path, probes: Sequence[str]) -> pd.DataFrame:
    """Foreground PSNR and object-crop SSIM of each target x probe (prediction vs truth,
    same renderer and camera). ``render_path(probe, theta)`` locates a render ``.npz``."""
    from ..metrics import crop_ssim, foreground_psnr

    thetas = estimate_thetas(estimate)
    rows = []
    for rec in targets.itertuples(index=False):
        truth = (float(rec.E_scale), float(rec.density_scale))
        for probe in probes:
            a = np.load(render_path(probe, thetas[rec.case_name]))
            b = np.load(render_path(probe, truth))
            pr, pa, tr, ta = (x.astype(np.float32) for x in (a["rgb"], a["alpha"], b["rgb"], b["alpha"]))
            rows.append({"target": rec.case_name, "probe": probe, "psnr_fg": foreground_psnr(pr, tr, pa, ta),
                         "ssim_crop": crop_ssim(pr, tr, pa, ta)})
    return pd.DataFrame(rows)
