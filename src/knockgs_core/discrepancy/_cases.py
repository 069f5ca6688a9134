"""Synthetic "measured" cases with a planted effect: their definitions and generation (private).

This is the *truth side*: :func:`make_case` writes the measured files (positions only,
metadata limited to object, profile and probe) to one directory and the truth (planted
effect, its magnitude, the true theta, clean rollouts) to another; only the scoring
(:mod:`._scoring`) reads the truth back. The loop (:func:`run_discrepancy`) never imports
this module.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..io import write_json, write_npz
from ..errors import InputError
from ..sim import (
    BodyForcePulse,
    Box,
    Gravity,
    HiddenMass,
    PoissonShift,
    StiffnessGradient,
    SupportSlip,
    VelocityDamping,
    VonMisesPlasticity,
    with_effects,
)
from ._measured import Measurement, write_measured

__all__ = ["PLANTED_EFFECTS", "LEVELS", "WORLDS", "CaseSpec", "default_cases", "make_case", "search_strength"]


def _top_box(particles, frac=0.5):
    """The upper ``frac`` of the object along z (a region for out-of-catalogue terms)."""
    X = np.asarray(particles.positions, dtype=np.float64)
    lo, hi = X.min(0), X.max(0)
    zc = hi[2] - 0.5 * frac * (hi[2] - lo[2])
    c = ((lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, zc)
    h = ((hi[0] - lo[0]) / 2 + 1e-3, (hi[1] - lo[1]) / 2 + 1e-3, 0.5 * frac * (hi[2] - lo[2]) + 1e-3)
    return Box(tuple(map(float, c)), tuple(map(float, h)))


def _end_box(particles, frac=0.3):
    """The ``frac`` of the object with the largest x (a hidden insert)."""
    X = np.asarray(particles.positions, dtype=np.float64)
    lo, hi = X.min(0), X.max(0)
    w = frac * (hi[0] - lo[0])
    c = (hi[0] - w / 2, (lo[1] + hi[1]) / 2, (lo[2] + hi[2]) / 2)
    h = (w / 2 + 1e-3, (hi[1] - lo[1]) / 2 + 1e-3, (hi[2] - lo[2]) / 2 + 1e-3)
    return Box(tuple(map(float, c)), tuple(map(float, h)))


#: planted effect -> (builder(strength, particles, horizon), starting strength, in the catalogue,
#: strength -> (parameter, value, unit)). Strength grows with the effect's size.
PLANTED_EFFECTS = {
    "damping": (lambda s, ps, H: VelocityDamping(rate=s), 1.0, True, lambda s: ("rate", s, "1/s")),
    "gravity": (lambda s, ps, H: Gravity(g=s), 0.02, True, lambda s: ("g", s, "m/s^2")),
    "plasticity": (lambda s, ps, H: VonMisesPlasticity(yield_stress=1.0 / s), 1.0 / 40.0, True,
                   lambda s: ("yield_stress", 1.0 / s, "Pa")),
    # a shear-dominated response barely sees nu: a 12-25% change needs a large drop
    "poisson": (lambda s, ps, H: PoissonShift(delta_nu=-s), 0.3, True, lambda s: ("delta_nu", -s, "")),
    "stiffness_gradient_z": (lambda s, ps, H: StiffnessGradient(slope=s, axis=2), 1.0, True, lambda s: ("slope", s, "")),
    "support_slip": (lambda s, ps, H: SupportSlip(slip_time=s), 0.005, True, lambda s: ("slip_time", s, "s")),
    "force_pulse": (lambda s, ps, H: BodyForcePulse(accel=s, direction=(0.0, 1.0, 0.0), box=_top_box(ps),
                                                    start=0.2 * H, end=0.6 * H),
                    0.05, False, lambda s: ("accel", s, "m/s^2")),
    "hidden_mass": (lambda s, ps, H: HiddenMass(fraction=s, box=_end_box(ps)), 0.5, False, lambda s: ("fraction", s, "")),
    # a transient push on the whole body along -z: not a sustained load
    "vertical_push": (lambda s, ps, H: BodyForcePulse(accel=s, direction=(0.0, 0.0, -1.0), box=_top_box(ps, frac=1.0),
                                                      start=0.2 * H, end=0.6 * H),
                      0.1, False, lambda s: ("accel", s, "m/s^2")),
}

#: relative change of the held-out response aimed at, per level
LEVELS = {"low": 0.12, "high": 0.25}

#: who makes a case's data: the loop's own model, the same MPM on a finer grid, the FEM reference
WORLDS = ("same", "finer", "fem")


@dataclass(frozen=True)
class CaseSpec:
    """One synthetic case: ``planted`` (a key of :data:`PLANTED_EFFECTS` or ``"none"``),
    ``level`` (``low``/``high``: a 12% / 25% change of the held-out response, or a number),
    the true ``theta``, observation noise ``noise_rel`` (per-coordinate std as a fraction of
    the calibration response's RMS displacement), ``observation`` (``gs_identity``: the
    Gaussian-associated particles with identity; ``gs_tracks``: a random 60% of them,
    shuffled, without identity), ``seed``, and the ``world`` that makes the data (``same``:
    the loop's own contract and particles; ``finer``, ``fem``: :mod:`._worlds`)."""

    name: str
    planted: str
    level: str | float = "low"
    theta: tuple[float, float] = (0.8, 1.2)
    noise_rel: float = 0.02
    observation: str = "gs_identity"
    seed: int = 0
    world: str = "same"

    def __post_init__(self):
        if self.world not in WORLDS:
            raise InputError("case", "world", f"unknown world '{self.world}'; known: {', '.join(WORLDS)}")
        if self.planted != "none" and self.planted not in PLANTED_EFFECTS:
            raise InputError("case", "planted", f"unknown effect '{self.planted}'; known: none, {', '.join(PLANTED_EFFECTS)}")
        if self.observation not in ("gs_identity", "gs_tracks", "all_identity"):
            raise InputError("case", "observation", "one of gs_identity, gs_tracks, all_identity")


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

    params = with_effects(contract.sim, *effects)
    r = run_rollout(contract, theta, probe, particles=particles, device=device, deterministic=deterministic,
                    sim_overrides={"effects": params.effects, "boundaries": params.boundaries})
    return np.asarray(r.positions, dtype=np.float64)


def _rel_change(Y, Y0, n_gs):
    d = Y[:, :n_gs] - Y0[:, :n_gs]
    D = Y0[:, :n_gs] - Y0[0, :n_gs]
    return float(np.sqrt(np.mean(np.sum(d**2, -1))) / np.sqrt(np.mean(np.sum(D**2, -1))))


def _find_strength(contract, particles, planted, target, theta, probe, H, log, *, device, deterministic):
    """Strength of ``planted`` whose held-out change relative to the clean response is
    ``target`` (within 10%): doubling/halving to bracket, then bisection in log."""
    build, s0, _, _ = PLANTED_EFFECTS[planted]
    Y0 = _sim(contract, particles, theta, probe, device=device, deterministic=deterministic)
    return search_strength(
        lambda s: _rel_change(_sim(contract, particles, theta, probe, (build(s, particles, H),), device=device,
                                   deterministic=deterministic), Y0, particles.n_gs),
        s0, target, log)


def search_strength(response_change, s0: float, target: float, log: list) -> tuple[float, float]:
    """The strength ``s`` whose ``response_change(s)`` (relative change of the held-out
    response, [-]) is ``target`` within 10%: doubling/halving from ``s0`` to bracket, then
    bisection in log. Every evaluation is appended to ``log``; returns (strength, change)."""

    def change(s):
        try:
            c = response_change(s)
        except Exception as exc:  # out of range (e.g. nu >= 0.5) or unstable
            log.append({"strength": s, "error": str(exc)[:200]})
            return math.nan
        log.append({"strength": s, "change": c})
        return c

    s, c = s0, change(s0)
    lo = hi = None
    for _ in range(12):
        if not math.isfinite(c):
            s *= 0.7
            c = change(s)
            continue
        if c < target:
            lo = (s, c)
            if hi:
                break
            s *= 2.0
        else:
            hi = (s, c)
            if lo:
                break
            s *= 0.5
        c = change(s)
    if lo is None or hi is None:
        best = min((e for e in log if "change" in e),
                   key=lambda e: abs(math.log(e["change"] / target)) if e["change"] > 0 else math.inf)
        return best["strength"], best["change"]
    for _ in range(8):
        if abs(lo[1] / target - 1) <= 0.1:
            return lo
        if abs(hi[1] / target - 1) <= 0.1:
            return hi
        s = math.sqrt(lo[0] * hi[0])
        c = change(s)
        if not math.isfinite(c):
            break
        if c < target:
            lo = (s, c)
        else:
            hi = (s, c)
    return min((lo, hi), key=lambda p: abs(p[1] / target - 1))


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
        from ._worlds import make_world_case

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
