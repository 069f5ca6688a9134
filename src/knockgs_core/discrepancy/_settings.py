"""Settings of the discrepancy loop (private)."""

from __future__ import annotations

from dataclasses import dataclass

from ..errors import InputError
from ._catalogue import CATALOGUE_KEYS
from ._model_error import FLOOR_KINDS

__all__ = ["LoopSettings"]


@dataclass(frozen=True)
class LoopSettings:
    """Settings of the loop (defaults are the documented ones; none is tuned per case).

    fit_fraction: share of the measured frames after t = 0 in the fit window (the rest is
        the validation window of the attribution).
    theta_step, effect_step: forward-difference steps, in log theta and in units of an
        effect's strength scale.
    min_excess: the theta-corrected validation residual must exceed the noise floor by this
        fraction (of the floor's energy) to count as significant.
    min_explained: an effect must explain this share of the theta-only residual on the
        validation window to be tried: of its part above the noise and the discretization
        floor where that part is significant (``AttributionRound.decision_share``).
    min_confirm: the joint nonlinear recalibration must remove this share of the residual
        energy above the noise floor to keep the effect.
    max_effects: most effects added; max_tries: candidates tried per round.
    base_iterations, refit_iterations, joint_iterations, refine_iterations: LM iteration
        budgets (base calibration, theta refit, final joint fit, attribution refinement).
    refine_top: screened candidates refined nonlinearly (besides the threshold-type ones).
    theta_bounds: allowed range of each scale.
    catalogue: catalogue keys to consider (None: all that apply).
    model_error_refine: grid and fill refinement ratio r of the refined model that estimates
        the model's discretization error (``_model_error``); None: no discretization term.
    model_error_max: bound of the term's coefficient c (``r / (r - 1)`` is the continuum
        limit under first-order convergence: 3 at r = 1.5).
    model_error_floor: how the discretization floor is measured (``_model_error``):
        ``shifts``, the mean energy of what moving the particles by half a cell against the
        grid changes that theta and the term cannot represent; ``second_refinement``, the same
        for a second refinement (ratio r^2); ``term``, the term's own energy (cruder, larger).
    model_error_updates: times the term is recomputed at the refitted theta (until theta moves
        less than 1%).
    model_error_ramp: (c0, c1): the discretization floor is the floor shape's energy times a
        weight that is 0 up to c = c0 and 1 from c = c1 (linear between): none for data at the
        model's own resolution, all of it from 0.4 of a refinement step on. c0 sits above the
        coefficients that planted effects alone project on the term in the standard cases
        (up to 0.09 at ci).
    model_error_own_term: where the data show the discretization term (its floor applies), a
        refined candidate is scored with the term recomputed at its own fitted model (one
        refined rollout each) and judged beyond the floor that model shows (at least the
        theta-only model's); where they do not and no candidate passes, the best ones are
        rescored so; an effect added so moves the term to the new model. False: every
        candidate is scored with the term and floor of the theta-only model.
    signature_min: a sustained-load or permanent-set candidate's contribution must be held by
        the data at least at this share in every third of the record where it is visible
        above the noise and where the discretization floor alone cannot move the share by
        as much (time signature).
    """

    fit_fraction: float = 2.0 / 3.0
    theta_step: float = 0.02
    effect_step: float = 0.05
    min_excess: float = 0.25
    min_explained: float = 0.5
    min_confirm: float = 0.3
    max_effects: int = 2
    max_tries: int = 2
    base_iterations: int = 8
    refit_iterations: int = 4
    joint_iterations: int = 8
    refine_iterations: int = 3
    refine_top: int = 3
    theta_bounds: tuple[float, float] = (0.2, 5.0)
    catalogue: tuple[str, ...] | None = None
    model_error_refine: float | None = 1.5
    model_error_max: float = 6.0
    model_error_floor: str = "shifts"
    model_error_updates: int = 4
    model_error_ramp: tuple[float, float] = (0.15, 0.4)
    model_error_own_term: bool = True
    signature_min: float = 0.5

    def __post_init__(self):
        if not (0.2 <= self.fit_fraction <= 0.9):
            raise InputError("LoopSettings", "fit_fraction", "must be in [0.2, 0.9]")
        if self.model_error_refine is not None and not (1.0 < self.model_error_refine <= 4.0):
            raise InputError("LoopSettings", "model_error_refine", "must be in (1, 4] or None")
        c0, c1 = self.model_error_ramp
        if not (0 <= c0 < c1):
            raise InputError("LoopSettings", "model_error_ramp", "must be (c0, c1) with 0 <= c0 < c1")
        if self.model_error_floor not in FLOOR_KINDS:
            raise InputError("LoopSettings", "model_error_floor", f"must be one of {list(FLOOR_KINDS)}")
        if not (self.model_error_max > 0):
            raise InputError("LoopSettings", "model_error_max", "must be > 0")
        if self.catalogue is not None:
            bad = set(self.catalogue) - set(CATALOGUE_KEYS)
            if bad:
                raise InputError("LoopSettings", "catalogue", f"unknown keys {sorted(bad)}; known: {list(CATALOGUE_KEYS)}")
