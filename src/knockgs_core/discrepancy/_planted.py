"""What a synthetic case plants, and how strongly (private; the truth side).

The vocabulary both kinds of case are made from: :class:`CaseSpec`, the planted effects
(:data:`PLANTED_EFFECTS`), the levels of held-out change aimed at (:data:`LEVELS`), the
worlds that make the data (:data:`WORLDS`), and :func:`search_strength`, the search of an
effect's strength for a level. The standard cases (:mod:`._cases`, world ``same``) and the
world cases (:mod:`._worlds`, worlds ``finer`` and ``fem``) build on it; the loop
(:func:`run_discrepancy`) never imports it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from .. import sim  # its effects are looked up when a case is built: the table reads without Warp
from ..sim import Box

__all__ = ["PLANTED_EFFECTS", "LEVELS", "WORLDS", "CaseSpec", "planted_change", "search_strength"]


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
    "damping": (lambda s, ps, H: sim.VelocityDamping(rate=s), 1.0, True, lambda s: ("rate", s, "1/s")),
    "gravity": (lambda s, ps, H: sim.Gravity(g=s), 0.02, True, lambda s: ("g", s, "m/s^2")),
    "plasticity": (lambda s, ps, H: sim.VonMisesPlasticity(yield_stress=1.0 / s), 1.0 / 40.0, True,
                   lambda s: ("yield_stress", 1.0 / s, "Pa")),
    # a shear-dominated response barely sees nu: a 12-25% change needs a large drop
    "poisson": (lambda s, ps, H: sim.PoissonShift(delta_nu=-s), 0.3, True, lambda s: ("delta_nu", -s, "")),
    "stiffness_gradient_z": (lambda s, ps, H: sim.StiffnessGradient(slope=s, axis=2), 1.0, True, lambda s: ("slope", s, "")),
    "support_slip": (lambda s, ps, H: sim.SupportSlip(slip_time=s), 0.005, True, lambda s: ("slip_time", s, "s")),
    "force_pulse": (lambda s, ps, H: sim.BodyForcePulse(accel=s, direction=(0.0, 1.0, 0.0), box=_top_box(ps),
                                                    start=0.2 * H, end=0.6 * H),
                    0.05, False, lambda s: ("accel", s, "m/s^2")),
    "hidden_mass": (lambda s, ps, H: sim.HiddenMass(fraction=s, box=_end_box(ps)), 0.5, False, lambda s: ("fraction", s, "")),
    # a transient push on the whole body along -z: not a sustained load
    "vertical_push": (lambda s, ps, H: sim.BodyForcePulse(accel=s, direction=(0.0, 0.0, -1.0), box=_top_box(ps, frac=1.0),
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


def planted_change(Y, Y0) -> float:
    """The RMS of ``Y - Y0`` over the RMS displacement of ``Y0`` from its first frame (both
    [T, n, 3], m): a planted effect's change of a response, as the strength search measures it."""
    d = Y - Y0
    D = Y0 - Y0[0]
    return float(np.sqrt(np.mean(np.sum(d**2, -1))) / np.sqrt(np.mean(np.sum(D**2, -1))))


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
