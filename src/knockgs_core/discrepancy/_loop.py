"""The discrepancy loop: calibrate, find the residual, attribute it, augment, report (private).

Steps (docs/discrepancy.md has the full description):

1. *Base calibration* of theta = (s_E, s_rho): the candidate library with local ridge on
   descriptors of the observed points when a library is given, else Levenberg-Marquardt
   (Gauss-Newton) steps through the simulator from (1, 1). Its predictions are "before".
2. *Residual*: measured minus re-simulated positions of the observed points. theta is
   first refined through the simulator (a few LM steps), so that what is left is what
   re-tuning E and rho cannot explain.
3. *Attribution*: for every catalogue effect, the signature (finite-difference response to
   a trial strength) is fitted jointly with the sensitivities to log s_E and log s_rho on
   the early frames (fit window); the share of the theta-only residual that it explains
   on the later frames (validation window, never fitted) ranks the effects; a BIC
   difference on the fit window is reported with it.
4. *Augmentation*: the best effect, if it explains enough on the validation window, is
   added and (theta, strengths) are recalibrated jointly (LM through the simulator); it
   is kept when the real residual drops enough. Repeat; stop with "no further effect".
5. If a significant residual remains that no effect explains, it is reported as
   unexplained, with its size.

:func:`run_discrepancy` runs these phases, one function each; the least-squares machinery
is in :mod:`._fitting`, the attribution in :mod:`._attribution`, the settings in
:mod:`._settings`.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Callable, Sequence

import numpy as np

from ..io import json_safe
from ..errors import InputError, SimulationError
from ..sim import viscous_stability_limit
from ._attribution import AttributionRound, _passes, attribute, within_floor
from ._catalogue import Candidate, CatalogueContext, default_catalogue, dev_strain_norm
from ._fitting import Parametrization, Problem, levenberg_marquardt, lm_fit, theta_sensitivities
from ._forward import ForwardModel, ModelSpec
from ._interval import interval_from_estimates, theta_per_misfit, worst_theta_per_misfit
from ._measured import Measurement
from ._model_error import ModelError, build_model_error
from ._settings import LoopSettings
from ._views import residual_views, view_summary

__all__ = ["LoopSettings", "LibrarySource", "DiscrepancyResult", "run_discrepancy"]


@dataclass(frozen=True)
class LibrarySource:
    """A candidate library for the base calibration: ``theta`` [n, 2], case ``names`` and
    the Probe-A rollouts (file paths or arrays [T, N, 3]) of the same contract. The
    descriptors are recomputed on the observed points and frames, so that library and
    measurement are seen through the same observation. Local ridge with ``k``, ``alpha``."""

    theta: np.ndarray
    names: tuple[str, ...]
    rollouts: tuple
    k: int = 10
    alpha: float = 1e-3


@dataclass
class DiscrepancyResult:
    """What the loop found. ``verdict_kind``: ``effect_found``, ``discretization`` (the
    residual is consistent with the model's discretization error), ``unexplained`` or
    ``none``. ``model_error``: the discretization term (refined model, coefficient, size;
    None when off); ``approximation``: the closest catalogue term to an unexplained residual
    whose time signature does not match (None otherwise); ``floor_statement``: where the
    residual lies within the model's discretization floor, the sentence that says so (how far
    the model is from its refined self; effects smaller than that cannot be named), else None;
    ``theta_interval`` [[lo, hi] of s_E, [lo, hi] of s_rho] (0 or inf where unbounded) with its
    parts in ``theta_uncertainty`` (:func:`._interval.interval_from_estimates`: the estimates,
    whether they are asymptotic, the continuum or why it is not given). ``identified`` lists
    the added effects' keys (empty: none);
    ``effects`` their estimated parameters; ``theta_*`` the estimates at each stage;
    ``unexplained`` says a significant residual remains that no catalogue effect explains
    (``residual`` gives its size); ``rounds`` hold the ranked attribution tables;
    ``metrics[probe][stage]`` the view summaries against the measurement (the calibration
    probe, and held-out probes whose measurement was given). ``predictions[probe][stage]``
    holds predicted positions [T, n_gs, 3] of the Gaussian-associated particles (not in
    the JSON)."""

    object: str
    profile: str
    probe: str
    heldout_probes: list[str]
    verdict: str
    verdict_kind: str
    identified: list[str]
    effects: list[dict]
    theta_base: tuple[float, float]
    theta_refit: tuple[float, float]
    theta_final: tuple[float, float]
    base_method: str
    unexplained: bool
    residual: dict
    noise: dict
    observation: dict
    rounds: list[dict]
    model_error: dict | None
    floor_statement: str | None
    approximation: dict | None
    theta_interval: list
    theta_uncertainty: dict
    metrics: dict
    n_simulations: int
    seconds: float
    settings: dict
    inputs: list[str] = field(default_factory=list)
    resolution: dict | None = None
    predictions: dict = field(default_factory=dict, repr=False)
    views: dict = field(default_factory=dict, repr=False)

    @property
    def identified_label(self) -> str:
        return "+".join(self.identified) if self.identified else "none"

    def to_dict(self) -> dict:
        d = {k: v for k, v in asdict(self).items() if k not in ("predictions", "views")}
        d["identified_label"] = self.identified_label
        return json_safe(d)


# --------------------------------------------------------------------------------------
# 1. base calibration
# --------------------------------------------------------------------------------------
def _library_estimate(problem: Problem, library: LibrarySource) -> tuple[tuple[float, float], dict]:
    from ..calibration import LocalRidge
    from ..descriptors import descriptor

    feats = []
    for item in library.rollouts:
        if isinstance(item, np.ndarray):
            X = item
        else:
            from ..rollout import read_rollout

            X = read_rollout(item).positions
        feats.append(descriptor(problem.corr.observe(X, problem.frames, problem.Y[0]), n_frames=None, source=str(item)[:80]))
    query = descriptor(problem.Y, n_frames=None, source=problem.m.source)
    ridge = LocalRidge(k=library.k, alpha=library.alpha)
    ridge.fit(np.array(feats), np.asarray(library.theta, dtype=float), list(library.names))
    est = ridge.predict(query[None, :])[0]
    details = {k: est.details.get(k) for k in ("neighbours", "fallback", "clipped") if k in est.details}
    return (est.E_scale, est.density_scale), details


def _base_calibration(problem: Problem, library: LibrarySource | None, settings: LoopSettings, log: list,
                      say: Callable[[str], None]) -> tuple[ModelSpec, str, dict | None]:
    """Phase 1, "before": theta from the library (local ridge) or by LM from (1, 1).
    Returns the model, the method's name and the library details (None without one)."""
    if library is not None:
        theta0, lib_details = _library_estimate(problem, library)
        base = ModelSpec(tuple(float(t) for t in theta0))
        say(f"base calibration (library, local ridge): theta = ({base.theta[0]:.4f}, {base.theta[1]:.4f})")
        return base, "library_local_ridge", lib_details
    start = ModelSpec((1.0, 1.0))
    par = Parametrization([], {}, settings)
    x, _, _ = levenberg_marquardt(lambda x: problem.residual(par.to_spec(x, start)), par.to_x(start), par.lower, par.upper,
                                  par.steps, settings.base_iterations, log)
    base = par.to_spec(x, start)
    say(f"base calibration (LM from (1, 1)): theta = ({base.theta[0]:.4f}, {base.theta[1]:.4f})")
    return base, "gauss_newton", None


# --------------------------------------------------------------------------------------
# the catalogue and the noise, sized at the base calibration
# --------------------------------------------------------------------------------------
def _noise(problem: Problem, spec: ModelSpec) -> dict:
    """Per-coordinate observation noise std and the residual floor per scalar."""
    meta = problem.m.meta.get("noise_std")
    identity = problem.corr.identity
    if meta is not None:
        sigma, how = float(meta), "declared in the measurement metadata"
    elif identity:
        X = problem.forward.rollout(spec, problem.probe)
        R0 = problem.Y[0] - X[problem.frames[0]][problem.corr.index]
        sigma, how = float(np.sqrt(np.mean(R0**2))), "frame-0 residual (identity: rest positions known)"
    else:
        R = problem.observe(spec) - problem.Y
        d2 = R[3:] - 2 * R[2:-1] + R[1:-2]
        sigma = float(np.sqrt(np.mean(d2**2) / 6.0)) if d2.size else 0.0
        how = "second time differences of the residual (no identity: an upper bound)"
    floor = sigma**2 * (1.0 if identity else 2.0)
    return {"std": sigma, "source": how, "floor_per_scalar": floor}


def _context(problem: Problem, spec: ModelSpec) -> CatalogueContext:
    """Scales of the response at ``spec`` that size the catalogue's trial strengths."""
    fw = problem.forward
    Yobs = problem.observe(spec)
    rms = float(np.sqrt(np.mean(np.sum((Yobs - Yobs[0]) ** 2, axis=-1))))
    F = fw.deformation(spec, problem.probe)
    strain = float(np.quantile(dev_strain_norm(F.reshape(-1, 3, 3)), 0.999)) if F is not None and F.size else 1e-3
    E, nu, rho = fw.base_materials()
    mu = float(np.mean(E / (2.0 * (1.0 + nu))))
    sim = fw.contract.sim
    p_modulus = spec.theta[0] * np.asarray(E, np.float64) * (1.0 - nu) / ((1.0 + nu) * (1.0 - 2.0 * nu))
    c_p = float(np.sqrt(np.max(p_modulus / (spec.theta[1] * np.asarray(rho, np.float64)))))
    return CatalogueContext(
        horizon=float(problem.times[-1]), rms_displacement=rms, max_dev_strain=strain, shear_modulus=mu,
        nu_range=(float(nu.min()), float(nu.max())), has_gravity=fw.has_gravity(), has_support=fw.has_still_support(),
        viscous_limit=viscous_stability_limit(sim.grid_lim / sim.n_grid, c_p, sim.dt),
    )


# --------------------------------------------------------------------------------------
# 2. theta refined through the simulator
# --------------------------------------------------------------------------------------
def _refit_theta(problem: Problem, base: ModelSpec, library: LibrarySource | None, settings: LoopSettings,
                 log: list) -> ModelSpec:
    """Phase 2: after a library estimate, or with a discretization term, theta refined by a
    few LM steps (the LM base calibration without a term already is a fit through the
    simulator)."""
    if library is None and problem.term is None:
        return base
    par = Parametrization([], problem.forward.catalogue, settings)
    x, _, _ = levenberg_marquardt(lambda x: problem.residual(par.to_spec(x, base)), par.to_x(base), par.lower, par.upper,
                                  par.steps, settings.refit_iterations, log)
    return par.to_spec(x, base)


def _term_at(problem: Problem, me: ModelError, spec: ModelSpec, settings: LoopSettings):
    """The discretization term at ``spec``: the refined minus the model displacement at the
    observed points' rest positions and measured frames ``D`` [T, M, 3], the theta
    sensitivities ``J`` [rows, 2], the change of log theta that moves the model like the
    refinement ``shift`` [2], and the term [T, M, 3] (D less its projection on J; zero at
    frame 0)."""
    fw = problem.forward
    points = np.asarray(fw.particles.positions, dtype=np.float64)[problem.corr.index]
    D = me.difference(fw, spec, problem.probe, points)[problem.frames]
    J = theta_sensitivities(problem, spec, settings)
    flat = D[1:].reshape(-1)
    shift = np.linalg.lstsq(J, flat, rcond=None)[0]
    term = np.zeros_like(D)
    term[1:] = (flat - J @ shift).reshape(D[1:].shape)
    return D, J, shift, term


def _with_term(problem: Problem, me: ModelError, spec: ModelSpec, settings: LoopSettings) -> Problem:
    """``problem`` with the discretization term computed at ``spec``: the refined minus the
    model displacement at the observed points' rest positions and measured frames, less its
    projection on the theta sensitivities (what re-tuning theta can absorb is left to theta
    and reported in its interval, so the term never trades off against E or rho)."""
    fw = problem.forward
    D, J, shift, term = _term_at(problem, me, spec, settings)
    flat = D[1:].reshape(-1)
    me.record(spec, D, term, shift)
    out = problem.with_term(term, me.c_max)
    me.leftover_share, me.floor_ratios = None, None
    # the floor's shapes are needed only where the data show the term: at the model's own
    # resolution (c below half the ramp's start) the floor's weight is 0, and neither the
    # placements nor the second refinement are simulated
    if me.floor != "term" and out.coefficient(out.raw_residual(spec)) > 0.5 * settings.model_error_ramp[0]:
        # the floor: what other placements on the grid (or one more refinement step) change
        # that theta and the term cannot represent
        if me.floor == "shifts":
            changes = [Dk[problem.frames][1:].reshape(-1)
                       for Dk in me.placement_differences(fw, spec, problem.probe, problem.corr.index)]
        else:
            points = np.asarray(fw.particles.positions, dtype=np.float64)[problem.corr.index]
            changes = [me.difference(fw, spec, problem.probe, points, level=2)[problem.frames][1:].reshape(-1)]
        ratios, shapes = theta_per_misfit(np.column_stack([J, flat]), changes)
        out.floor_shape = shapes
        # the placements' ratios (the refinement's follows the recorded term: ModelError.theta_per_misfit)
        me.floor_ratios = ratios
        me.leftover_share = float(np.sum(shapes * shapes)) / max(float(sum(Dk @ Dk for Dk in changes)), 1e-300)
    return out


def _term_moved(problem: Problem, me: ModelError, spec: ModelSpec, settings: LoopSettings, *, adopt: bool = False) -> Problem:
    """``problem`` with the discretization term recomputed at ``spec`` and its floor's shapes
    kept: a model with an effect moves under refinement in its own way (a yield resolved on a
    finer grid sets in elsewhere), so an effect is judged with the term of the model that
    carries it. ``adopt``: ``me`` records the new term (the final model's); else ``me`` is
    left as it is."""
    D, _, shift, term = _term_at(problem, me, spec, settings)
    if adopt:
        me.record(spec, D, term, shift)
    return problem.with_term(term, me.c_max, floor_shape=problem.floor_shape)


def _fit_covariance(A: np.ndarray, r: np.ndarray, n_points: int) -> tuple[np.ndarray, np.ndarray]:
    """The covariance of the linearized least squares ``A x ~ -r`` (``A`` [rows, k], ``r``
    [rows], rows ordered (frame, point, axis) over ``n_points`` observed points) and the step
    [2] (log theta) that the linearization still asks for. The covariance is the sandwich with
    the residual clustered by observed point (``(A'A)^-1 (sum_p g_p g_p') (A'A)^-1``, g_p the
    sum of ``A r`` over a point's frames and axes, times ``P / (P - 1)``): a point's residual is
    correlated over its frames (a track's frame-0 noise enters every frame; a track matched to a
    neighbouring particle follows that particle's motion), which the white-noise formula
    ``s^2 (A'A)^-1`` would count as independent and so understate. Infinite where singular."""
    k = A.shape[1]
    try:
        B = np.linalg.inv(A.T @ A)
        remaining = -(B @ (A.T @ r))[:2]
    except np.linalg.LinAlgError:
        return np.full((k, k), np.inf), np.zeros(2)
    g = (A * r[:, None]).reshape(-1, n_points, 3, k).sum(axis=(0, 2))
    meat = g.T @ g * (n_points / max(n_points - 1, 1))
    return B @ meat @ B, remaining


def _theta_interval(problem: Problem, spec: ModelSpec, me: ModelError | None, settings: LoopSettings, *,
                    shows_error: bool, noise_floor: float = 0.0) -> dict:
    """The theta interval at the final model ``spec`` (:func:`._interval.interval_from_estimates`):
    the statistical part from the linearized least squares in log theta (2 standard deviations,
    :func:`_fit_covariance`, the discretization term among the columns, plus the Gauss-Newton
    step the fit still asks for); theta fitted by the refined model
    (``ModelError.theta_shift``: the theta change that moves the model like the refinement)
    and, where the loop has a second refinement (``model_error_floor = "second_refinement"``)
    and the data show the model's discretization error, theta fitted by that one too.
    ``shows_error``: whether the data show that error (the term's coefficient above the ramp's
    start, or a residual that nothing explains); else the interval is the statistical one.
    Where they do, the floor's share (:mod:`._interval`) is the largest theta-per-misfit ratio
    of the discretization changes the loop knows (``ModelError.theta_per_misfit``) times the
    norm of the residual above the noise (``noise_floor``: its variance per scalar, m^2)."""
    J = theta_sensitivities(problem, spec, settings)
    r = problem.residual(spec)
    A = np.column_stack([J, problem.term]) if problem.term is not None else J
    cov, remaining = _fit_covariance(A, r, problem.m.n_points)
    sd = np.sqrt(np.clip(np.diag(cov)[:2], 0.0, np.inf))
    logt = np.log(np.asarray(spec.theta, dtype=np.float64))
    refined = second = None
    if me is not None and me.theta_shift is not None:
        refined = logt - np.asarray(me.theta_shift, dtype=np.float64)
        if me.second is not None and shows_error:
            at = me.spec if me.spec is not None else spec
            points = np.asarray(problem.forward.particles.positions, dtype=np.float64)[problem.corr.index]
            D2 = me.difference(problem.forward, at, problem.probe, points, level=2)[problem.frames]
            J2 = theta_sensitivities(problem, at, settings)
            second = logt - np.linalg.lstsq(J2, D2[1:].reshape(-1), rcond=None)[0]
    excess = math.sqrt(max(float(r @ r) - r.size * float(noise_floor), 0.0))
    ratios = None if me is None else me.theta_per_misfit
    share = None if ratios is None or len(ratios) == 0 else excess * np.max(ratios, axis=0)
    out = interval_from_estimates(logt, sd, remaining=remaining, refined=refined, second=second,
                                  factor=me.factor if me is not None else 1.5, shows_error=shows_error, floor_share=share)
    out["shows_discretization_error"] = bool(shows_error)
    out["misfit_above_noise"] = excess
    response = float(np.linalg.norm((problem.Y - problem.Y[0])[1:]))
    out["theta_per_response_log"] = [float(response * x) for x in worst_theta_per_misfit(A)]
    out["theta_per_misfit"] = None if ratios is None else [[float(x) for x in row] for row in ratios]
    return out


# --------------------------------------------------------------------------------------
# 3-5. attribution and augmentation
# --------------------------------------------------------------------------------------
def _try_candidates(problem: Problem, spec: ModelSpec, att: AttributionRound, floor: float, settings: LoopSettings,
                    log: list) -> tuple[tuple[str, ModelSpec, bool] | None, list[dict]]:
    """Phase 4: jointly recalibrate (theta, strengths) with each of the best ``max_tries``
    rows that pass the screen, from its refined model, on all calibration frames; the first
    that removes ``min_confirm`` of the residual energy above the noise and the discretization
    floor (or, where the residual lies within that floor, lowers it at all: the validation
    window has already shown that the effect explains most of it) is accepted. A row scored
    with its own discretization term (``AttributionRow.own_term``) is fitted with that term and
    judged against the floor its model shows.
    Returns (key, new model, whether it carries its own term) or None, and the record of the
    tries."""
    tried = []
    rss_cur = float(np.sum(problem.residual(spec) ** 2))
    for row in att.table[: settings.max_tries]:
        if not _passes(att, row, settings):
            continue
        key = row.key
        start_spec = row.refined_spec
        fit_problem = row.refined_problem if row.refined_problem is not None else problem
        try:
            new, rr = lm_fit(fit_problem, start_spec, list(start_spec.effect_keys), slice(None), settings,
                             settings.joint_iterations, log)
        except SimulationError as exc:
            tried.append({"key": key, "error": str(exc)[:200]})
            continue
        cost = float(rr @ rr)
        # the share of the energy above the noise and the discretization floor that the joint fit
        # removes (any gain when the residual lies within the floor: the validation window has
        # already shown that the effect explains most of it)
        weight = att.floor_weight if math.isnan(row.floor_weight) else row.floor_weight
        excess_all = rss_cur - rr.size * floor - fit_problem.model_floor(slice(None), weight)
        within = excess_all <= 0.0
        gain = (rss_cur - cost) / excess_all if not within else None
        new = ModelSpec(new.theta, tuple((k, u) for k, u in new.effects if u != 0.0 or k == key))
        tried.append({"key": key, "rss_before": rss_cur, "rss_after": cost, "gain_over_excess": gain, "within_floor": within,
                      "theta": list(new.theta), "effects": [list(e) for e in new.effects]})
        confirmed = cost < rss_cur if within else gain >= settings.min_confirm
        if confirmed and dict(new.effects)[key] != 0.0:
            return (key, new, row.own_term), tried
    return None, tried


def _augment(problem: Problem, spec: ModelSpec, candidates: list[Candidate], floor: float, settings: LoopSettings, log: list,
             say: Callable[[str], None], retarget: Callable[[ModelSpec], Problem] | None = None
             ) -> tuple[ModelSpec, Problem, list[AttributionRound], bool, str]:
    """Phases 3-5 from the model ``spec``: attribute, add the best confirmed effect, repeat
    until no residual is visible above the noise, ``max_effects`` are in, or no candidate
    passes. ``retarget`` (``spec -> problem`` with the discretization term recomputed at
    ``spec``) lets candidates be scored with their own term; an effect added so moves the
    term to the new model. Returns the final model, the problem at it, the rounds, whether a
    residual stays unexplained (one significant beyond the noise and the discretization
    floor), and why the loop stopped (``no_residual``, ``max_effects``, ``discretization``:
    none passes and the residual is within the floor, ``unexplained``)."""
    rounds = []
    while True:
        att = attribute(problem, spec, candidates, floor, settings, log, retarget)
        rounds.append(att)
        top = att.best
        say(f"round {len(rounds)}: excess over noise {att.excess_noise_val:.3g}, over noise and floor {att.excess_val:.3g}; "
            f"best {top.key if top else '-'} "
            f"explains {top.explained_val if top else float('nan'):.3f}"
            + (f" ({top.explained_excess:.3f} beyond the floor)" if top and att.model_floor_val > 0 else ""))
        if not att.visible:
            att.decision = "no residual above the noise left"
            return spec, problem, rounds, False, "no_residual"
        if len(spec.effects) >= settings.max_effects:
            att.decision = f"stop: at most {settings.max_effects} effects are added"
            return spec, problem, rounds, att.significant, "max_effects"
        accepted, att.tried = _try_candidates(problem, spec, att, floor, settings, log)
        if accepted is None:
            if not att.significant:
                att.decision = ("the residual is within the model's discretization floor: no effect is named "
                                "(one smaller than the floor cannot be told from the model's own error)")
                return spec, problem, rounds, False, "discretization"
            att.decision = "residual unexplained by the catalogue"
            return spec, problem, rounds, True, "unexplained"
        key, spec, own_term = accepted
        if own_term:
            problem = retarget(spec)
        att.decision = f"added {key}"
        say(f"added {key}: theta = ({spec.theta[0]:.4f}, {spec.theta[1]:.4f}), strengths {dict(spec.effects)}")


# --------------------------------------------------------------------------------------
# predictions, scores and the verdict
# --------------------------------------------------------------------------------------
def _predict_and_score(problem: Problem, stages: dict[str, ModelSpec], probes: Sequence[str], measured: dict[str, Measurement],
                       settings: LoopSettings) -> tuple[dict, dict, dict]:
    """Predicted Gaussian-particle positions [T, n_gs, 3] (float32) of every stage under
    every probe, and the residual views and their summaries for the probes in ``measured``
    (the calibration probe first). Predictions are the model's own (theta and the added
    effects): the discretization term is an analysis device of the attribution, not a part
    of the predictive model. Returns (predictions, metrics, views)."""
    fw = problem.forward
    n_gs = fw.particles.n_gs
    predictions = {}
    for pr in probes:
        predictions[pr] = {name: np.asarray(fw.rollout(s, pr)[:, :n_gs], dtype=np.float32) for name, s in stages.items()}
    metrics, views = {}, {}
    for pr, meas in measured.items():
        sub = Problem(meas, fw, pr, settings) if pr != problem.probe else problem
        metrics[pr], views[pr] = {}, {}
        for name, s in stages.items():
            v = residual_views(meas.points, sub.observe(s), sub.times)
            views[pr][name] = v
            metrics[pr][name] = view_summary(v)
    return predictions, metrics, views


def _residual_size(problem: Problem, final: ModelSpec, floor: float, stop_reason: str) -> dict:
    """The residual left by the final model: RMS per point [m], its part above the noise,
    and that part as a share of the measured RMS displacement."""
    r_end = problem.residual(final)
    n_end = r_end.size
    rss_end = float(r_end @ r_end)
    excess_end = max(rss_end - n_end * floor, 0.0)
    Yd = problem.Y - problem.Y[0]
    rms_meas = float(np.sqrt(np.mean(np.sum(Yd**2, axis=-1))))
    return {
        "rms_per_point": math.sqrt(3.0 * rss_end / n_end),
        "excess_rms_per_point": math.sqrt(3.0 * excess_end / n_end),
        "noise_rms_per_point": math.sqrt(3.0 * floor),
        "measured_rms_displacement": rms_meas,
        "excess_fraction_of_response": math.sqrt(3.0 * excess_end / n_end) / max(rms_meas, 1e-30),
        "stop_reason": stop_reason,
    }


def _effects_found(catalogue: dict[str, Candidate], spec: ModelSpec) -> list[dict]:
    """The effects of ``spec`` with their labels and estimated parameters."""
    out = []
    for k, u in spec.effects:
        c = catalogue[k]
        out.append({"key": k, "label": c.label, "strength": u, "parameter": c.parameter, "value": c.value(u), "unit": c.unit})
    return out


def _model_error_summary(problem: Problem, final: ModelSpec, me: ModelError, floor: float, settings: LoopSettings,
                         coefficients: dict[str, float]) -> dict:
    """The discretization term at the final model: its coefficient, its RMS per point [m]
    (at that coefficient and per unit), its share of the measured RMS displacement, and
    whether the residual is significant without it and with it (validation window)."""
    raw = problem.raw_residual(final)
    c = problem.coefficient(raw)
    full = raw + c * problem.term
    V = problem.val_rows
    Yd = problem.Y - problem.Y[0]
    rms_meas = float(np.sqrt(np.mean(np.sum(Yd**2, axis=-1))))
    unit = math.sqrt(3.0 * float(problem.term @ problem.term) / problem.term.size)

    weight = problem.floor_weight(c)
    model_floor_V = problem.model_floor(V, weight)

    def excess(r, extra=0.0):
        den = V.size * floor + extra
        return float(r[V] @ r[V]) / den - 1.0 if den > 0 else math.inf

    change_rms = math.sqrt(float(np.mean(np.sum(me.change**2, axis=-1)))) if me.change is not None else math.nan
    floor_rms = math.sqrt(3.0 * model_floor_V / max(V.size, 1))
    return {
        **me.to_dict(),
        "computed_at_theta": list(me.spec.theta) if me.spec is not None else None,
        "change_rms_per_point": change_rms,
        "change_share_of_response": change_rms / max(rms_meas, 1e-30),
        "floor_share_of_response": floor_rms / max(rms_meas, 1e-30),
        "coefficient": c,
        "coefficient_refit": coefficients.get("refit", 0.0),
        "term_rms_per_point": c * unit,
        "term_rms_per_unit": unit,
        "term_share_of_response": c * unit / max(rms_meas, 1e-30),
        "floor_weight": weight,
        "floor_rms_per_point": floor_rms,
        "excess_without_term": excess(raw),
        "excess_with_term": excess(full, model_floor_V),
        "significant_without_term": bool(excess(raw) > settings.min_excess),
        "significant_with_term": bool(excess(full, model_floor_V) > settings.min_excess),
    }


def _approximation(rounds: list[AttributionRound], unexplained: bool, settings: LoopSettings) -> dict | None:
    """When a residual stays unexplained, the candidate that would have explained enough of it
    but whose time signature does not match (reported as an approximation, never added)."""
    if not unexplained or not rounds:
        return None
    for row in rounds[-1].table:
        if (row.refined and not row.signature_ok and rounds[-1].decision_share(row) >= settings.min_explained
                and row.delta_bic < 0):
            return {"key": row.key, "label": row.label, "explained_val": row.explained_val,
                    "signature_share": row.signature_share, "parameter": row.parameter, "value_estimate": row.value_estimate,
                    "note": (f"{row.label} would explain {100 * row.explained_val:.0f}% of the validation residual, but the "
                             f"data hold only {100 * row.signature_share:.0f}% of its contribution in one third of the "
                             f"record (at least {100 * settings.signature_min:.0f}% in each third for a load that stays "
                             "on or a permanent set): "
                             "an approximation, not added")}
    return None


def _floor_statement(rounds: list[AttributionRound], model_error: dict | None) -> str | None:
    """Where the last round's residual lies within the model's discretization floor (visible
    above the noise, not significant beyond noise and floor), the plain statement of that floor:
    how far the model at this resolution is from its refined self, and that effects smaller than
    that cannot be named. None otherwise."""
    if model_error is None or not rounds:
        return None
    last = rounds[-1]
    if not (last.visible and within_floor(last)):
        return None
    return (f"the model at this resolution differs from its refined self by "
            f"{100 * model_error['change_share_of_response']:.1f}% of the measured response "
            f"({100 * model_error['floor_share_of_response']:.1f}% that theta and the discretization term cannot "
            "represent: the floor); effects smaller than that cannot be named, and the residual is within it")


def _verdict_kind(effects: list[dict], unexplained: bool, model_error: dict | None) -> str:
    if unexplained:
        return "unexplained"
    if effects:
        return "effect_found"
    if model_error is not None and model_error["significant_without_term"]:
        return "discretization"
    return "none"


def _verdict(effects: list[dict], unexplained: bool, residual: dict, model_error: dict | None = None,
             kind: str | None = None, floor_statement: str | None = None) -> str:
    """One sentence: the effects found, or that none is missing, or the unexplained residual;
    with the discretization term's size when it carries a significant part; led by the floor's
    statement (:func:`_floor_statement`) where the residual lies within the floor."""
    sentence = _verdict_sentence(effects, unexplained, residual, model_error, kind)
    return f"{floor_statement}; {sentence}" if floor_statement else sentence


def _verdict_sentence(effects: list[dict], unexplained: bool, residual: dict, model_error: dict | None,
                      kind: str | None) -> str:
    identified = [e["key"] for e in effects]
    term = ""
    if model_error is not None:
        term = (f"; the model's discretization floor is RMS {model_error['floor_rms_per_point']:.3g} m per point "
                f"(validation window), its term carries {model_error['term_rms_per_point']:.3g} m "
                f"(c = {model_error['coefficient']:.2f})")
    if unexplained:
        found = f"added {', '.join(identified)}; " if identified else ""
        return (f"{found}a residual remains that no catalogue effect explains: "
                f"RMS {residual['excess_rms_per_point']:.3g} m above the noise "
                f"({100 * residual['excess_fraction_of_response']:.1f}% of the measured RMS displacement){term}")
    if identified:
        found = ", ".join(f"{e['key']} ({e['parameter']} = {e['value']:.4g} {e['unit']})".replace(" )", ")") for e in effects)
        return "effects found: " + found + "; no further effect" + term
    if kind == "discretization":
        return "no missing effect found: the residual is consistent with the model's discretization error" + term
    return "no missing effect found" + term


# --------------------------------------------------------------------------------------
# the loop
# --------------------------------------------------------------------------------------
def _check_probes(measured: Measurement, contract, probe: str | None, heldout_probes: Sequence[str],
                  heldout_measured: dict | None) -> tuple[str, list[str], dict]:
    """The calibration probe (argument, else the measurement's metadata, else the contract's
    calibration probe), checked against the measurement and the held-out probes."""
    meta_probe = measured.meta.get("probe")
    probe = probe or meta_probe or contract.roles.get("calibration")
    if meta_probe and meta_probe != probe:
        raise InputError(measured.source, "probe", f"measured under '{meta_probe}', analysed as '{probe}'")
    meta_obj = measured.meta.get("object")
    if meta_obj and meta_obj != contract.name:
        raise InputError(measured.source, "object", f"measured object '{meta_obj}' is not the contract's '{contract.name}'")
    heldout_probes = list(heldout_probes)
    if probe in heldout_probes:
        raise InputError("discrepancy", "heldout_probes", f"the calibration probe '{probe}' cannot also be held out")
    heldout_measured = dict(heldout_measured or {})
    for name in heldout_measured:
        if name not in heldout_probes:
            raise InputError("discrepancy", "heldout_measured", f"'{name}' is not among the held-out probes {heldout_probes}")
    return probe, heldout_probes, heldout_measured


def run_discrepancy(
    measured: Measurement,
    contract,
    particles,
    *,
    probe: str | None = None,
    heldout_probes: Sequence[str] = (),
    heldout_measured: dict | None = None,
    library: LibrarySource | None = None,
    settings: LoopSettings = LoopSettings(),
    device: str | None = None,
    deterministic: bool = False,
    progress: Callable[[str], None] | None = None,
) -> DiscrepancyResult:
    """Run the discrepancy loop on ``measured`` (the calibration-probe response) for
    ``contract`` simulated on ``particles``.

    ``probe`` defaults to the measurement's metadata, then the contract's calibration
    probe. ``heldout_probes`` are predicted before and after (never used in the loop);
    ``heldout_measured`` maps some of them to their measurements, used only to score those
    predictions in the result. ``library`` selects the library base calibration, else LM
    from (1, 1). ``device`` and ``deterministic``: every rollout's of the loop
    (:class:`ForwardModel`). Returns a :class:`DiscrepancyResult`.
    """
    # One function of ~100 lines on purpose: the loop's phases (base calibration, catalogue,
    # attribution rounds, refit, predictions) read in the order they run; each is a helper.
    say = progress or (lambda msg: None)
    probe, heldout_probes, heldout_measured = _check_probes(measured, contract, probe, heldout_probes, heldout_measured)
    pb = Problem(measured, ForwardModel(contract, particles, device=device, deterministic=deterministic), probe, settings)
    log: list = []

    base, base_method, lib_details = _base_calibration(pb, library, settings, log, say)
    ctx = _context(pb, base)
    cands = default_catalogue(ctx, keys=settings.catalogue)
    pb = pb.with_forward(pb.forward.with_catalogue({c.key: c for c in cands}))
    noise = _noise(pb, base)
    floor = noise["floor_per_scalar"]
    me = None
    if settings.model_error_refine is not None:
        me = build_model_error(pb.forward, factor=settings.model_error_refine, c_max=settings.model_error_max,
                               floor=settings.model_error_floor)
        pb = _with_term(pb, me, base, settings)
    refit = _refit_theta(pb, base, library, settings, log)
    if me is not None:
        # the term is computed at the theta it is used at: recompute it and refit until theta
        # moves less than 1% (the refined rollout at the final theta is the last one made)
        for _ in range(settings.model_error_updates):
            if max(abs(math.log(a / b)) for a, b in zip(refit.theta, me.spec.theta)) < 0.01:
                break
            pb = _with_term(pb, me, refit, settings)
            refit = _refit_theta(pb, refit, library, settings, log)
            say(f"theta refit with the discretization term at the new theta: ({refit.theta[0]:.4f}, {refit.theta[1]:.4f})")
    say(f"theta refit: ({refit.theta[0]:.4f}, {refit.theta[1]:.4f})")
    retarget = None
    if me is not None and settings.model_error_own_term:
        base_pb = pb
        retarget = lambda s: _term_moved(base_pb, me, s, settings)  # noqa: E731
    final, final_pb, rounds, unexplained, stop_reason = _augment(pb, refit, cands, floor, settings, log, say, retarget)
    if final_pb is not pb:  # an effect came in with its own term: the final model's term is the one reported
        pb = _term_moved(pb, me, final, settings, adopt=True)

    stages = {"before": base, "refit": refit, "after": final}
    coefficients = {name: pb.coefficient(pb.raw_residual(s)) for name, s in stages.items() if name != "before"}
    scored = {probe: measured, **{p: heldout_measured[p] for p in heldout_probes if p in heldout_measured}}
    predictions, metrics, views = _predict_and_score(pb, stages, [probe] + heldout_probes, scored, settings)
    residual = _residual_size(pb, final, floor, stop_reason)
    model_error = _model_error_summary(pb, final, me, floor, settings, coefficients) if me is not None else None
    shows_error = model_error is not None and (model_error["floor_weight"] > 0 or unexplained)
    theta_interval = _theta_interval(pb, final, me, settings, shows_error=shows_error, noise_floor=floor)
    fw = pb.forward
    effects = _effects_found(fw.catalogue, final)
    kind = _verdict_kind(effects, unexplained, model_error)
    approximation = _approximation(rounds, unexplained, settings)
    floor_statement = _floor_statement(rounds, model_error)
    verdict = _verdict(effects, unexplained, residual, model_error, kind, floor_statement)
    if approximation is not None:
        verdict += f"; closest catalogue term: {approximation['note']}"
    say(verdict)
    n_gs = particles.n_gs
    return DiscrepancyResult(
        object=contract.name,
        profile=getattr(contract, "profile", ""),
        probe=probe,
        heldout_probes=heldout_probes,
        verdict=verdict,
        verdict_kind=kind,
        identified=list(final.effect_keys),
        effects=effects,
        theta_base=base.theta,
        theta_refit=refit.theta,
        theta_final=final.theta,
        base_method=base_method,
        unexplained=unexplained,
        residual=residual,
        noise=noise,
        observation={
            "points": measured.n_points,
            "frames": measured.n_frames,
            "identity": pb.corr.identity,
            "gs_only": bool(np.all(pb.corr.index < n_gs)),
            "match_distance_median": float(np.median(pb.corr.match_distance)),
            "fit_frames": pb.fit_frames,
            "validation_frames": measured.n_frames - 1 - pb.fit_frames,
            "library": lib_details,
            "catalogue_context": asdict(ctx),
            "catalogue": [c.key for c in cands],
        },
        rounds=[att.to_dict() for att in rounds],
        model_error=model_error,
        floor_statement=floor_statement,
        approximation=approximation,
        theta_interval=theta_interval["interval"],
        theta_uncertainty=theta_interval,
        metrics=metrics,
        n_simulations=fw.n_simulations,
        seconds=fw.seconds,
        settings=asdict(settings),
        predictions=predictions,
        views=views,
    )
