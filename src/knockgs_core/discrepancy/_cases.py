"""Synthetic "measured" cases with a planted effect: the standard set and their generation (private).

What a case is and plants (:class:`CaseSpec`, :data:`PLANTED_EFFECTS`, :func:`search_strength`)
is defined in :mod:`._planted` and re-exported here; :func:`make_case` hands a case of another
world than ``same`` to :func:`._worlds.make_world_case`.

This is the *truth side*: :func:`make_case` writes the measured files (positions only,
metadata limited to object, profile and probe) to one directory and the truth (planted
effect, its magnitude, the true theta, clean rollouts) to another; only the scoring
(:mod:`._scoring`) reads the truth back. The loop (:func:`run_discrepancy`) never imports
this module.
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import numpy as np

from ..io import write_json, write_npz
from ._measured import Measurement, write_measured
from ._planted import LEVELS, PLANTED_EFFECTS, WORLDS, CaseSpec, planted_change, search_strength
from ._worlds import make_world_case

__all__ = ["PLANTED_EFFECTS", "LEVELS", "WORLDS", "CaseSpec", "default_cases", "make_case", "search_strength"]


def default_cases(targets: list[tuple[float, float]] | None = None, *, targets_path=None) -> list[CaseSpec]:
    """The standard set: every catalogue effect at two levels, a null case and two
    disturbances outside the catalogue; true thetas cycle through ``targets``, by default
    the held-out targets of split ``main`` in ``targets_path`` (default
    ``config/targets.csv``, :func:`knockgs_core.contract.load_targets`) in increasing
    order of (s_E, s_rho); every third case is observed without identity."""
    if not targets:
        from ..contract import load_targets

        main = load_targets("main", targets_path)
        targets = sorted(zip(main["E_scale"].astype(float), main["density_scale"].astype(float)))
    names = []
    for eff in ("damping", "gravity", "plasticity", "poisson", "stiffness_gradient_z", "support_slip"):
        for level in ("low", "high"):
            names.append((f"{eff}_{level}", eff, level))
    names += [("null", "none", "low"), ("force_pulse", "force_pulse", "high"), ("hidden_mass", "hidden_mass", "high")]
    out = []
    for i, (name, eff, level) in enumerate(names):
        out.append(CaseSpec(name=name, planted=eff, level=level, theta=targets[i % len(targets)],
                            observation="gs_tracks" if i % 3 == 2 else "gs_identity", seed=1000 + i))
    return out


def _sim(contract, particles, theta, probe, effects=(), *, device=None, deterministic: bool = False):
    from ..rollout import run_rollout

    from ..sim import with_effects

    params = with_effects(contract.sim, *effects)
    r = run_rollout(contract, theta, probe, particles=particles, device=device, deterministic=deterministic,
                    sim_overrides={"effects": params.effects, "boundaries": params.boundaries})
    return np.asarray(r.positions, dtype=np.float64)


def _find_strength(contract, particles, planted, target, theta, probe, H, log, *, device, deterministic):
    """Strength of ``planted`` whose held-out change relative to the clean response is
    ``target`` (within 10%): doubling/halving to bracket, then bisection in log."""
    build, s0, _, _ = PLANTED_EFFECTS[planted]
    Y0 = _sim(contract, particles, theta, probe, device=device, deterministic=deterministic)
    return search_strength(
        lambda s: planted_change(_sim(contract, particles, theta, probe, (build(s, particles, H),), device=device,
                                       deterministic=deterministic)[:, :particles.n_gs], Y0[:, :particles.n_gs]),
        s0, target, log)


def _observe(Y, n_gs, spec: CaseSpec, rng, sigma, frames):
    """Measured points: noisy positions of the chosen particles at ``frames``."""
    if spec.observation == "all_identity":
        idx = np.arange(Y.shape[1])
    elif spec.observation == "gs_identity":
        idx = np.arange(n_gs)
    else:
        idx = rng.permutation(n_gs)[: max(1, int(0.6 * n_gs))]
    P = Y[frames][:, idx] + rng.normal(0.0, sigma, size=(len(frames), len(idx), 3))
    return idx, P


def make_case(spec: CaseSpec, contract, particles, *, measured_dir, truth_dir, calibration_probe=None, heldout_probe=None,
              device=None, deterministic: bool = False) -> dict:
    """Write the case ``spec``: ``measured_dir/measured_calib.parquet`` and
    ``measured_dir/measured_heldout.parquet`` (what the loop and the report may read), and
    ``truth_dir/truth.json`` plus ``truth_dir/clean.npz`` (clean Gaussian-particle
    trajectories under both probes; only :func:`evaluate_case` reads them). ``device`` and
    ``deterministic``: every rollout's (:func:`knockgs_core.rollout.run_rollouts`). Returns
    the truth record."""
    calibration_probe = calibration_probe or contract.roles["calibration"]
    heldout_probe = heldout_probe or contract.roles["heldout"][0]
    if spec.world != "same":
        return make_world_case(spec, contract, particles, measured_dir=measured_dir, truth_dir=truth_dir,
                               calibration_probe=calibration_probe, heldout_probe=heldout_probe, device=device,
                               deterministic=deterministic)
    rng = np.random.default_rng(spec.seed)
    export_c = contract.probes[calibration_probe].export
    H = export_c.horizon
    effects, search, strength, achieved = (), [], None, 0.0
    param = None
    if spec.planted != "none":
        build, _, in_cat, describe = PLANTED_EFFECTS[spec.planted]
        target = LEVELS[spec.level] if isinstance(spec.level, str) else float(spec.level)
        strength, achieved = _find_strength(contract, particles, spec.planted, target, spec.theta, heldout_probe, H,
                                            search, device=device, deterministic=deterministic)
        effects = (build(strength, particles, H),)
        p, v, u = describe(strength)
        param = {"parameter": p, "value": v, "unit": u}
    n_gs = particles.n_gs
    clean = {}
    for role, pr in (("calib", calibration_probe), ("heldout", heldout_probe)):
        clean[role] = _sim(contract, particles, spec.theta, pr, effects, device=device, deterministic=deterministic)
    Yc = clean["calib"][:, :n_gs]
    D = float(np.sqrt(np.mean(np.sum((Yc - Yc[0]) ** 2, -1))))
    sigma = spec.noise_rel * D
    measured_dir, truth_dir = Path(measured_dir), Path(truth_dir)
    files = {}
    for role, pr in (("calib", calibration_probe), ("heldout", heldout_probe)):
        T = clean[role].shape[0]
        idx, P = _observe(clean[role], n_gs, spec, rng, sigma, np.arange(T))
        identity = spec.observation != "gs_tracks"
        m = Measurement(
            points=P, frames=np.arange(T), times=None,
            particle=idx if identity else None,
            track=idx if identity else rng.permutation(len(idx)) + 1,
            meta={"object": contract.name, "profile": contract.profile, "probe": pr},
            source=f"case {spec.name}",
        )
        path = measured_dir / f"measured_{role}.parquet"
        write_measured(path, m)
        files[role] = str(path)
    truth = {
        "case": spec.name,
        "planted_effect": spec.planted,
        "in_catalogue": bool(spec.planted == "none" or PLANTED_EFFECTS[spec.planted][2]),
        "level": spec.level,
        "planted_parameter": param,
        "planted_effect_repr": repr(effects[0]) if effects else None,
        "heldout_change": achieved,
        "strength_search": search,
        "theta_true": list(spec.theta),
        "noise_std": sigma,
        "observation": spec.observation,
        "seed": spec.seed,
        "calibration_probe": calibration_probe,
        "heldout_probe": heldout_probe,
        "measured_files": files,
        "spec": asdict(spec),
    }
    write_npz(truth_dir / "clean.npz", calib=clean["calib"][:, :n_gs].astype(np.float32),
              heldout=clean["heldout"][:, :n_gs].astype(np.float32))
    write_json(truth_dir / "truth.json", truth)
    return truth
