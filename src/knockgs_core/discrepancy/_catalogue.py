"""The catalogue of candidate effects a discrepancy analysis may add (private).

Each candidate exposes one scalar *strength* ``u`` with ``u = 0`` meaning "effect off",
so every candidate has the same shape in the attribution: the signature of a trial
strength, a coefficient, and a joint recalibration of ``u`` with (s_E, s_rho).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..sim import (Gravity, MaterialViscosity, PoissonShift, StiffnessGradient, SupportFriction, SupportSlip, VelocityDamping,
                   VonMisesPlasticity)

__all__ = ["Candidate", "CatalogueContext", "default_catalogue", "CATALOGUE_KEYS"]

CATALOGUE_KEYS = (
    "damping",
    "viscosity",
    "gravity",
    "plasticity",
    "poisson",
    "stiffness_gradient_x",
    "stiffness_gradient_y",
    "stiffness_gradient_z",
    "support_slip",
    "support_friction",
)


@dataclass(frozen=True)
class CatalogueContext:
    """Scales of the calibrated response that size the trial strengths.

    ``horizon`` [s]: last measured time; ``rms_displacement`` [m]: RMS displacement of the
    simulated calibration response over the observed points and frames; ``max_dev_strain``
    [-]: largest deviatoric Hencky strain norm of the simulated response (its 99.9th
    percentile over particles and frames); ``shear_modulus`` [Pa]: mean base shear modulus
    (theta not applied); ``nu_range``: min/max base Poisson ratio; ``has_gravity``: the
    contract has gravity (Coulomb friction needs a normal load); ``has_support``: it has a
    still sticky support; ``viscous_limit`` [s]: the explicit stability limit of a
    Kelvin-Voigt retardation time at the calibrated theta
    (:func:`knockgs_core.sim.viscous_stability_limit`)."""

    horizon: float
    rms_displacement: float
    max_dev_strain: float
    shear_modulus: float
    nu_range: tuple[float, float]
    has_gravity: bool
    has_support: bool
    viscous_limit: float = math.inf


@dataclass(frozen=True)
class Candidate:
    """One catalogue entry.

    ``make(u)`` builds the effect at strength ``u`` (``u = 0``: off); ``value(u)`` is the
    effect's own parameter at that strength (``unit``); ``trials``: strengths whose
    signatures are computed; ``scale``: the strength's natural size (the optimizer works in
    ``u / scale``); ``one_sided``: ``u >= 0`` only; ``bounds``: allowed strengths;
    ``threshold``: the response sets in only beyond some strength (a yield or a slip onset),
    so a linear screen can miss it and it is always refined nonlinearly; ``time_signature``:
    ``sustained`` (a load that stays on), ``permanent`` (a set that stays after the motion),
    or ``""`` (no sustained offset of its own): a sustained or permanent candidate is
    checked third by third of the record against the data (module :mod:`._attribution`)."""

    key: str
    label: str
    make: Callable[[float], object]
    value: Callable[[float], float]
    parameter: str
    unit: str
    trials: tuple[float, ...]
    scale: float
    one_sided: bool
    bounds: tuple[float, float]
    threshold: bool = False
    time_signature: str = ""

    def effect(self, u: float):
        return self.make(float(u))


def default_catalogue(ctx: CatalogueContext, *, keys=None) -> list[Candidate]:
    """The catalogue for a calibrated response with scales ``ctx``; ``keys`` selects entries
    (default: all that apply: Coulomb friction only with gravity, support terms only with a
    still sticky support)."""
    H = max(ctx.horizon, 1e-9)
    D = max(ctx.rms_displacement, 1e-12)
    eps = max(ctx.max_dev_strain, 1e-9)
    mu0 = max(ctx.shear_modulus, 1e-12)
    nu_lo, nu_hi = ctx.nu_range
    out: list[Candidate] = []

    out.append(Candidate(
        "damping", "velocity damping", lambda u: VelocityDamping(rate=u), lambda u: u, "rate", "1/s",
        trials=(0.5 / H, 1.5 / H, 4.0 / H), scale=1.0 / H, one_sided=True, bounds=(0.0, 200.0 / H)))
    # strength = retardation time beta [s] of stiffness-proportional (Kelvin-Voigt) viscosity; half
    # the explicit stability limit leaves room for theta to stiffen during the fits
    beta_max = min(0.5 * ctx.viscous_limit, 0.05 * H)
    out.append(Candidate(
        "viscosity", "material viscosity (stiffness-proportional damping)", lambda u: MaterialViscosity(retardation_time=u),
        lambda u: u, "retardation_time", "s", trials=tuple(sorted({min(f * H, 0.8 * beta_max) for f in (5e-4, 2e-3, 5e-3)})),
        scale=2e-3 * H, one_sided=True, bounds=(0.0, beta_max)))
    g = 2.0 * D / H**2
    out.append(Candidate(
        "gravity", "gravity (sag under self-weight)", lambda u: Gravity(g=u), lambda u: u, "g", "m/s^2",
        trials=(g, 5.0 * g), scale=g, one_sided=False, bounds=(-1e3 * g, 1e3 * g), time_signature="sustained"))
    # strength = inverse yield strain 2 mu0 / yield_stress (0 = never yields)
    out.append(Candidate(
        "plasticity", "von Mises plasticity (permanent set)",
        lambda u: VonMisesPlasticity(yield_stress=(2.0 * mu0 / u) if u > 0 else math.inf),
        lambda u: (2.0 * mu0 / u) if u > 0 else math.inf, "yield_stress", "Pa",
        trials=tuple(f / eps for f in (1.2, 1.6, 2.2, 3.0, 4.5, 7.0, 12.0, 20.0, 35.0)), scale=1.0 / eps, one_sided=True,
        bounds=(0.0, 200.0 / eps), threshold=True, time_signature="permanent"))
    out.append(Candidate(
        "poisson", "Poisson-ratio shift", lambda u: PoissonShift(delta_nu=u), lambda u: u, "delta_nu", "",
        trials=tuple(d for d in (-0.4, -0.1, 0.1) if -0.95 < nu_lo + d and nu_hi + d < 0.495), scale=0.1, one_sided=False,
        bounds=(-0.95 - nu_lo, 0.495 - nu_hi)))
    for axis, name in enumerate("xyz"):
        out.append(Candidate(
            f"stiffness_gradient_{name}", f"stiffness gradient along {name}",
            (lambda a: (lambda u: StiffnessGradient(slope=u, axis=a)))(axis), lambda u: u, "slope", "",
            trials=(-2.0, -0.5, 0.5, 2.0), scale=0.5, one_sided=False, bounds=(-8.0, 8.0)))
    if ctx.has_support:
        out.append(Candidate(
            "support_slip", "viscous slip at the support", lambda u: SupportSlip(slip_time=u), lambda u: u, "slip_time", "s",
            trials=tuple(f * H for f in (0.004, 0.01, 0.025, 0.06, 0.15)), scale=0.01 * H, one_sided=True, bounds=(0.0, 10.0 * H),
            threshold=True, time_signature="permanent"))
        if ctx.has_gravity:
            # strength = 1 / mu (0 = sticky)
            out.append(Candidate(
                "support_friction", "Coulomb friction at the support",
                lambda u: SupportFriction(mu=(1.0 / u) if u > 0 else math.inf), lambda u: (1.0 / u) if u > 0 else math.inf,
                "mu", "", trials=(1.0, 4.0), scale=1.0, one_sided=True, bounds=(0.0, 1e3), threshold=True,
                time_signature="permanent"))
    if keys is not None:
        keys = list(keys)
        unknown = set(keys) - set(CATALOGUE_KEYS)
        if unknown:
            raise ValueError(f"unknown catalogue keys {sorted(unknown)}; known: {list(CATALOGUE_KEYS)}")
        out = [c for c in out if c.key in keys]
    return out


def dev_strain_norm(F: np.ndarray) -> np.ndarray:
    """Deviatoric Hencky strain norm ``|dev log(sigma)|`` of deformation gradients [..., 3, 3]."""
    s = np.linalg.svd(np.asarray(F, dtype=np.float64), compute_uv=False)
    e = np.log(np.clip(s, 1e-9, None))
    dev = e - e.mean(axis=-1, keepdims=True)
    return np.linalg.norm(dev, axis=-1)
