"""Attribution: rank the catalogue effects by how much of the residual each explains (private).

One round (module docs of :mod:`knockgs_core.discrepancy._loop`, step 3) at a model
``spec``: the *screen* fits every candidate's trial signatures jointly with the theta
sensitivities (linear least squares on the fit window); the *refinement* fits the best
screened candidates, and every threshold-type one, nonlinearly through the simulator, as
it fits theta alone; candidates are scored by the share of the theta-only residual they
remove on the validation window. Each candidate gets an :class:`AttributionRow`; the round
is an :class:`AttributionRound`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from ..errors import InputError, SimulationError
from ._catalogue import Candidate
from ._fitting import Problem, lm_fit, theta_sensitivities
from ._forward import ModelSpec
from ._settings import LoopSettings

__all__ = ["AttributionRow", "AttributionRound", "attribute", "EXCLUSIVE"]

#: effects that take over the same support cannot be combined
EXCLUSIVE = ({"support_slip", "support_friction"},)


@dataclass
class AttributionRow:
    """One candidate's line in the ranked attribution table.

    Screen: the best ``trial_strength`` (strength units of the candidate), its fitted
    ``coefficient`` and the implied ``strength_estimate`` (``value_estimate`` in the
    effect's own ``parameter`` and ``unit``), and the shares of the theta-only residual
    energy removed on the fit and validation windows (``screen_explained_*``, [-]);
    ``error`` when no trial simulated. Refinement (``refined``): the nonlinear estimate
    (``strength_estimate``, ``value_estimate``, ``theta_estimate``), ``explained_fit``,
    ``delta_bic`` (fit window) and the score ``explained_val``; ``refine_error`` when it
    failed. ``explained_excess``: the same validation energy removed, as a share of the part
    of the theta-only residual above the noise and the discretization floor (NaN where there
    is none): what the effect explains beyond the floor. Time signature (sustained and permanent candidates, refined):
    ``signature_share``, the smallest share of the candidate's contribution that the data
    hold in a third of the record where it is visible above the noise and the discretization
    floor (:func:`_window_shares`),
    and ``signature_ok`` (at least ``LoopSettings.signature_min``): a load that stays on acts
    from t = 0 to the end, a push that starts later or ends does not. ``own_term``: the
    refined model was scored with the discretization term recomputed at it (where the data
    show the term, or where the theta-only model's floor would leave the candidate short).
    With an own term, ``floor_weight`` and ``model_floor_val`` [m^2]: the discretization floor
    that the candidate's own model shows (at least the theta-only model's), and
    ``significant``: whether the theta-only validation residual exceeds the noise and that
    floor; the candidate is judged beyond it (:meth:`AttributionRound.decision_share`).
    ``refined_spec`` and ``refined_problem``: the refined model and the problem it was scored
    in, used by the decision, never written.
    """

    key: str
    label: str
    error: str | None = None
    trial_strength: float = math.nan
    coefficient: float = math.nan
    strength_estimate: float = math.nan
    parameter: str = ""
    value_estimate: float = math.nan
    unit: str = ""
    screen_explained_fit: float = -math.inf
    screen_explained_val: float = -math.inf
    refined: bool = False
    refine_error: str | None = None
    theta_estimate: list | None = None
    explained_fit: float = math.nan
    explained_val: float = -math.inf
    delta_bic: float = math.nan
    explained_excess: float = math.nan
    signature_share: float = math.nan
    signature_ok: bool = True
    own_term: bool = False
    floor_weight: float = math.nan
    model_floor_val: float = math.nan
    significant: bool | None = None
    rank: int = 0
    refined_spec: ModelSpec | None = field(default=None, repr=False)
    refined_problem: Problem | None = field(default=None, repr=False)

    def to_dict(self) -> dict:
        """The row as written to ``result.json`` and read by the report (only the fields its
        stage set, in the order they were set)."""
        if self.error is not None:
            return {"key": self.key, "label": self.label, "error": self.error, "explained_val": self.explained_val,
                    "refined": self.refined, "rank": self.rank}
        d = {
            "key": self.key,
            "label": self.label,
            "trial_strength": self.trial_strength,
            "coefficient": self.coefficient,
            "strength_estimate": self.strength_estimate,
            "parameter": self.parameter,
            "value_estimate": self.value_estimate,
            "unit": self.unit,
            "screen_explained_fit": self.screen_explained_fit,
            "screen_explained_val": self.screen_explained_val,
            "refined": self.refined,
        }
        if self.refined:
            d.update({"theta_estimate": self.theta_estimate, "explained_fit": self.explained_fit,
                      "explained_val": self.explained_val, "delta_bic": self.delta_bic})
            if not math.isnan(self.signature_share):
                d.update({"signature_share": self.signature_share, "signature_ok": self.signature_ok})
            if self.own_term:
                d.update({"own_term": True, "floor_weight": self.floor_weight, "model_floor_val": self.model_floor_val,
                          "significant": self.significant})
            if self.refine_error is not None:
                d["refine_error"] = self.refine_error
        else:
            if self.refine_error is not None:
                d["refine_error"] = self.refine_error
            d["explained_val"] = self.explained_val
        if not math.isnan(self.explained_excess):
            d["explained_excess"] = self.explained_excess
        d["rank"] = self.rank
        return d


@dataclass
class AttributionRound:
    """One round of attribution at the model (``theta``, ``effects``) and its decision.

    ``n_fit``, ``n_val``: residual scalars in the fit and validation windows;
    ``rss_theta_fit``, ``rss_theta_val`` [m^2]: residual energy after the nonlinear
    theta-only refit on the fit window (``theta_fit_window``); ``screen_rss_theta_val``:
    the same after the linearized theta fit; ``noise_floor_val`` [m^2]: the noise's share of
    the validation energy; ``model_floor_val`` [m^2]: the discretization floor there
    (:meth:`Problem.model_floor`, 0 without a term); ``excess_val``: validation energy over both floors, minus 1;
    ``significant``: above ``LoopSettings.min_excess`` (a residual beyond the model's
    discretization error); ``excess_noise_val`` and ``visible``: the same against the noise
    alone (a residual there is to attribute: candidates are refined and tried); ``table``: the ranked rows;
    ``decision``: what the loop did next; ``tried``: the joint recalibrations attempted;
    with a discretization term, ``term_coefficient`` (its profiled c at the theta-only
    refit) and ``rss_theta_val_without_term`` (the validation energy there with c = 0).
    """

    theta: list
    effects: list
    n_fit: int
    n_val: int
    rss_theta_fit: float
    rss_theta_val: float
    theta_fit_window: list
    screen_rss_theta_val: float
    noise_floor_val: float
    excess_val: float
    excess_noise_val: float
    visible: bool
    significant: bool
    table: list[AttributionRow]
    decision: str | None = None
    tried: list[dict] | None = None
    model_floor_val: float = 0.0
    floor_weight: float = 0.0
    term_coefficient: float | None = None
    rss_theta_val_without_term: float | None = None

    @property
    def best(self) -> AttributionRow | None:
        return self.table[0] if self.table else None

    def decision_share(self, row: AttributionRow) -> float:
        """The share of the residual that ``row`` must explain (``LoopSettings.min_explained``):
        of the part above the noise and the discretization floor where that part is
        significant (an effect is judged on what it explains beyond the floor), else of the
        whole theta-only validation residual. The floor is the candidate's own where it was
        scored with its own term (``AttributionRow.model_floor_val``), else the round's."""
        own = not math.isnan(row.model_floor_val)
        significant = row.significant if own else self.significant
        model_floor = row.model_floor_val if own else self.model_floor_val
        if significant and model_floor > 0 and not math.isnan(row.explained_excess):
            return row.explained_excess
        return row.explained_val

    def to_dict(self) -> dict:
        d = {
            "theta": self.theta, "effects": self.effects, "n_fit": self.n_fit, "n_val": self.n_val,
            "rss_theta_fit": self.rss_theta_fit, "rss_theta_val": self.rss_theta_val, "theta_fit_window": self.theta_fit_window,
            "screen_rss_theta_val": self.screen_rss_theta_val, "noise_floor_val": self.noise_floor_val,
            "excess_val": self.excess_val, "excess_noise_val": self.excess_noise_val, "visible": self.visible,
            "significant": self.significant,
            "table": [row.to_dict() for row in self.table], "decision": self.decision,
        }
        if self.tried is not None:
            d["tried"] = self.tried
        if self.term_coefficient is not None:
            d["model_floor_val"] = self.model_floor_val
            d["floor_weight"] = self.floor_weight
            d["term_coefficient"] = self.term_coefficient
            d["rss_theta_val_without_term"] = self.rss_theta_val_without_term
        return d


@dataclass(frozen=True)
class _Linearization:
    """The model ``spec`` linearized in log theta: observed positions ``base`` [T, M, 3],
    the residual ``r`` (measured minus simulated, flattened), the columns ``J`` of the
    sensitivities to log s_E and log s_rho (and the discretization term when the problem
    has one), their bounds ``lower``/``upper``, the theta-only fit ``a`` on the fit window
    and its residual energies on the fit and validation windows [m^2]."""

    base: np.ndarray
    r: np.ndarray
    J: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    a: np.ndarray
    rss_fit: float
    rss_val: float


def _fit_rows(A, r, rows, lower=None, upper=None):
    """Least squares of ``A x = r`` on ``rows``, with bounds on x when given."""
    if lower is None or not (np.any(np.isfinite(lower)) or np.any(np.isfinite(upper))):
        coef, *_ = np.linalg.lstsq(A[rows], r[rows], rcond=None)
        return coef
    from scipy.optimize import lsq_linear

    return lsq_linear(A[rows], r[rows], bounds=(lower, upper), method="bvls").x


def _rss(A, coef, r, rows):
    e = r[rows] - A[rows] @ coef
    return float(e @ e)


def _linearize(problem: Problem, spec: ModelSpec, settings: LoopSettings) -> _Linearization:
    base = problem.observe(spec)
    r = (problem.Y - base)[1:].reshape(-1)  # measured minus simulated: what a change must add
    cols = list(theta_sensitivities(problem, spec, settings, base).T)
    lower, upper = [-np.inf, -np.inf], [np.inf, np.inf]
    if problem.term is not None:
        cols.append(problem.term)
        lower.append(0.0)
        upper.append(problem.term_max)
    J = np.column_stack(cols)
    lower, upper = np.array(lower), np.array(upper)
    F, V = problem.fit_rows, problem.val_rows
    a = _fit_rows(J, r, F, lower, upper)
    return _Linearization(base, r, J, lower, upper, a, _rss(J, a, r, F), _rss(J, a, r, V))


def _screen(problem: Problem, spec: ModelSpec, cand: Candidate, lin: _Linearization) -> AttributionRow:
    """The candidate's best trial signature fitted jointly with the theta sensitivities (and
    the discretization term)."""
    F, V, r, J, a = problem.fit_rows, problem.val_rows, lin.r, lin.J, lin.a
    nj = J.shape[1]
    lower = np.append(lin.lower, 0.0 if cand.one_sided else -np.inf)
    upper = np.append(lin.upper, np.inf)
    bounded = problem.term is not None
    best = None
    for u in cand.trials:
        try:
            S = (problem.observe(spec.with_effect(cand.key, u)) - lin.base)[1:].reshape(-1)
        except (SimulationError, InputError) as exc:
            best = best or {"trial": u, "error": str(exc)[:200]}
            continue
        A = np.column_stack([J, S])
        if bounded:
            coef = _fit_rows(A, r, F, lower, upper)
        else:
            coef = _fit_rows(A, r, F)
            if cand.one_sided and coef[nj] < 0:
                coef = np.append(a, 0.0)
        rF = _rss(A, coef, r, F)
        if best is None or "error" in best or rF < best["rss_fit"]:
            best = {"trial": u, "coef": float(coef[nj]), "rss_fit": rF, "rss_val": _rss(A, coef, r, V)}
    if best is None or "error" in best:
        return AttributionRow(cand.key, cand.label, error=(best or {}).get("error", "no trial"))
    u_est = float(np.clip(best["coef"] * best["trial"], *cand.bounds))
    return AttributionRow(
        cand.key, cand.label, trial_strength=best["trial"], coefficient=best["coef"], strength_estimate=u_est,
        parameter=cand.parameter, value_estimate=cand.value(u_est), unit=cand.unit,
        screen_explained_fit=1.0 - best["rss_fit"] / max(lin.rss_fit, 1e-300),
        screen_explained_val=1.0 - best["rss_val"] / max(lin.rss_val, 1e-300),
    )


def _window_shares(problem: Problem, fitted: ModelSpec, key: str, floor: float, *, floor_weight: float = 0.0,
                   limit: float = math.inf) -> list[float]:
    """How much of the candidate's contribution the data hold in each third of the record.

    At the candidate's fitted model, S is its contribution (the rollout minus the same
    without it) and R what the data need on top of the model without it (measured minus that
    rollout, minus the fitted discretization term). For each third W of the frames after
    t = 0, ``a_W = <R_W, S_W> / <S_W, S_W>`` (1: the data hold the contribution there; 0: they
    have none). Windows where the share cannot be read give NaN: where the contribution is
    too small to be seen in the noise (standard error of ``a_W``, ``sqrt(floor) / |S_W|``,
    above 0.1), or where the discretization floor alone could move the share by ``limit``
    (the RMS over the floor's shapes f_k of ``<f_k,W, S_W> / <S_W, S_W>``, times the square
    root of ``floor_weight``). A load that stays on acts from t = 0 and in every window; a
    push that starts later or has ended does not."""
    without = problem.observe(fitted.with_effect(key, 0.0))
    S = (problem.observe(fitted) - without)[1:]
    R = (problem.Y - without)[1:]
    if problem.term is not None:
        c = problem.coefficient(problem.raw_residual(fitted))
        R = R - c * problem.term.reshape(R.shape)
    shapes = None
    if floor_weight > 0 and problem.floor_shape is not None:
        shapes = problem.floor_shape.reshape((-1,) + S.shape)
    out = []
    for w in np.array_split(np.arange(S.shape[0]), 3):
        s_w, r_w = S[w].reshape(-1), R[w].reshape(-1)
        ss = float(s_w @ s_w)
        if ss <= 0 or math.sqrt(max(floor, 0.0) / ss) > 0.1:
            out.append(math.nan)
            continue
        if shapes is not None:
            moved = [float(f[w].reshape(-1) @ s_w) / ss for f in shapes]
            if math.sqrt(floor_weight * float(np.mean(np.square(moved)))) >= limit:
                out.append(math.nan)
                continue
        out.append(float(r_w @ s_w) / ss)
    return out


def _refine(problem: Problem, spec: ModelSpec, row: AttributionRow, cand: Candidate, rss_theta: tuple[float, float],
            settings: LoopSettings, log: list, floor: float = 0.0, lin: _Linearization | None = None,
            retarget: Callable[[ModelSpec], Problem] | None = None, floor_weight: float = 0.0) -> None:
    """Fit the candidate nonlinearly (theta, the strengths in ``spec`` and its own) on the fit
    window and score it against the theta-only refit energies ``rss_theta`` (fit,
    validation); updates ``row`` in place. ``retarget``: ``spec -> problem`` with the
    discretization term recomputed at ``spec``; given, the fitted model is scored with its own
    term."""
    F = problem.fit_rows
    # start from the best (on the fit window) of the screen's estimate and its trials, each as
    # it is and with theta re-tuned by one Gauss-Newton step of the linearization ``lin``: an
    # effect that theta has partly absorbed (a yield softens like a lower E) comes in only
    # while theta moves back
    start, start_cost = None, math.inf
    lo, hi = (math.log(b) for b in settings.theta_bounds)
    for u0 in dict.fromkeys((row.strength_estimate,) + tuple(cand.trials)):
        if u0 == 0.0:
            continue
        trial = spec.with_effect(cand.key, u0)
        tries = [trial]
        if lin is not None:
            try:
                r_u = (problem.Y - problem.observe(trial))[1:].reshape(-1)
            except (SimulationError, InputError):
                continue
            step = _fit_rows(lin.J, r_u, F, lin.lower, lin.upper)[:2]
            logt = np.clip(np.log(np.asarray(spec.theta, dtype=np.float64)) + step, lo, hi)
            tries.append(trial.with_theta(tuple(float(x) for x in np.exp(logt))))
        for t in tries:
            try:
                rr = problem.residual(t)[F]
            except (SimulationError, InputError):
                continue
            c0 = float(rr @ rr)
            if c0 < start_cost:
                start, start_cost = t, c0
    if start is None:
        row.explained_val = row.screen_explained_val
        return
    try:
        fitted, rr = lm_fit(problem, start, list(spec.effect_keys) + [cand.key], F, settings, settings.refine_iterations, log)
    except SimulationError as exc:
        row.refine_error = str(exc)[:200]
        row.explained_val = row.screen_explained_val
        return
    row.refined = True
    row.refined_spec = fitted
    row.refined_problem = problem
    _score(problem, row, rr, rss_theta)
    u = dict(fitted.effects)[cand.key]
    row.strength_estimate = u
    row.value_estimate = cand.value(u)
    row.theta_estimate = list(fitted.theta)
    scored = problem
    if retarget is not None:
        _own_term(problem, row, retarget, rss_theta, floor_weight)
        scored = row.refined_problem
    if cand.time_signature and u != 0.0:
        try:
            shares = [a for a in _window_shares(scored, fitted, cand.key, floor, floor_weight=floor_weight,
                                                limit=settings.signature_min) if not math.isnan(a)]
        except (SimulationError, InputError):
            shares = []
        row.signature_share = min(shares) if shares else math.nan
        row.signature_ok = bool(not shares or row.signature_share >= settings.signature_min)


def _score(problem: Problem, row: AttributionRow, rr: np.ndarray, rss_theta: tuple[float, float]) -> None:
    """``row``'s shares of the theta-only energies ``rss_theta`` (fit, validation) removed by
    its residual ``rr``, and its BIC difference on the fit window."""
    F, V = problem.fit_rows, problem.val_rows
    rF, rV = float(rr[F] @ rr[F]), float(rr[V] @ rr[V])
    row.explained_fit = 1.0 - rF / max(rss_theta[0], 1e-300)
    row.explained_val = 1.0 - rV / max(rss_theta[1], 1e-300)
    row.delta_bic = F.size * math.log(max(rF, 1e-300) / max(rss_theta[0], 1e-300)) + math.log(F.size)


def _own_term(problem: Problem, row: AttributionRow, retarget: Callable[[ModelSpec], Problem], rss_theta: tuple[float, float],
              floor_weight: float, *, only_above: bool = False) -> None:
    """Rescore the refined ``row`` with the discretization term recomputed at its fitted model
    and judge it beyond the floor that model shows: the floor's weight at the term's
    coefficient there (:meth:`Problem.floor_weight`), at least the theta-only model's
    ``floor_weight``. Where theta has absorbed part of an effect, the theta-only model shows
    less of the discretization error than the model with the effect does (a stiffer body
    decays like a damped one). ``only_above``: ``row`` is left as it is unless its model's
    weight exceeds ``floor_weight``."""
    try:
        scored = retarget(row.refined_spec)
        raw = scored.raw_residual(row.refined_spec)
    except (SimulationError, InputError) as exc:
        row.refine_error = f"the term at the refined model: {str(exc)[:160]}"
        return
    c = scored.coefficient(raw)
    own_weight = scored.floor_weight(c)
    if only_above and not own_weight > floor_weight:
        return
    _score(problem, row, raw + c * scored.term, rss_theta)
    row.own_term = True
    row.refined_problem = scored
    row.floor_weight = max(float(floor_weight), own_weight)
    row.model_floor_val = scored.model_floor(scored.val_rows, row.floor_weight)


def _judge(rows: list[AttributionRow], rss_val: float, noise_val: float, model_floor_val: float, settings: LoopSettings) -> None:
    """Each row's share of the validation energy above the noise and the discretization floor
    (``explained_excess``; its own floor where it has one) and, with its own floor, whether the
    theta-only residual is significant beyond it."""
    for row in rows:
        own = not math.isnan(row.model_floor_val)
        floor_val = noise_val + (row.model_floor_val if own else model_floor_val)
        above = rss_val - floor_val
        row.explained_excess = row.explained_val * rss_val / above if above > 0 and math.isfinite(row.explained_val) else math.nan
        if own:
            row.significant = bool((rss_val / floor_val - 1.0 if floor_val > 0 else math.inf) > settings.min_excess)


def attribute(problem: Problem, spec: ModelSpec, candidates: list[Candidate], floor: float, settings: LoopSettings,
              log: list, retarget: Callable[[ModelSpec], Problem] | None = None) -> AttributionRound:
    """Rank the candidates at ``spec``: screen every candidate not yet in the model (nor
    excluded by one that is); refine the ``refine_top`` best screened ones and every
    threshold-type one, unless the theta-only residual is not significant against the noise
    ``floor`` [m^2 per residual scalar]; rank refined candidates first, by validated share.
    ``retarget`` (``spec -> problem`` with the discretization term recomputed at ``spec``):
    where the data show the term (its floor applies, ``Problem.floor_weight`` > 0), each
    refined candidate is scored with the term of its own fitted model and judged beyond the
    floor that model shows; where they do not, but no candidate among the ``max_tries`` best
    passes, those are rescored so, and keep their own term where their model shows a floor
    (theta may have absorbed the effect and, with it, the signs of the discretization error)."""
    F, V = problem.fit_rows, problem.val_rows
    lin = _linearize(problem, spec, settings)
    present = set(spec.effect_keys)
    blocked = set().union(*(g for g in EXCLUSIVE if g & present)) if present else set()
    by_key = {c.key: c for c in candidates}
    rows = [_screen(problem, spec, cand, lin) for cand in candidates if cand.key not in present and cand.key not in blocked]
    rows.sort(key=lambda row: -row.screen_explained_val)

    theta_fit, r_theta = lm_fit(problem, spec, list(spec.effect_keys), F, settings, settings.refine_iterations, log)
    rss_nl_theta_F, rss_nl_theta_V = float(r_theta[F] @ r_theta[F]), float(r_theta[V] @ r_theta[V])
    raw = problem.raw_residual(theta_fit)
    term_c = problem.coefficient(raw)
    rss_raw_V = float(raw[V] @ raw[V])
    weight = problem.floor_weight(term_c)
    model_floor_V = problem.model_floor(V, weight)
    floor_V = V.size * floor + model_floor_V
    excess = rss_nl_theta_V / floor_V - 1.0 if floor_V > 0 else math.inf
    significant = bool(excess > settings.min_excess)
    noise_V = V.size * floor
    excess_noise = rss_nl_theta_V / noise_V - 1.0 if noise_V > 0 else math.inf
    visible = bool(excess_noise > settings.min_excess)
    screened = [row.key for row in rows if row.error is None]
    chosen = screened[: settings.refine_top]
    chosen += [key for key in screened if by_key[key].threshold and key not in chosen]
    if not visible:  # nothing above the noise to explain: the screen is reported, no refinement is needed
        chosen = []
    own = retarget if (retarget is not None and weight > 0) else None
    rss_theta = (rss_nl_theta_F, rss_nl_theta_V)
    for row in rows:
        if row.key in chosen:
            _refine(problem, spec, row, by_key[row.key], rss_theta, settings, log, floor, lin, own, weight)
        else:
            row.explained_val = row.screen_explained_val
    _judge(rows, rss_nl_theta_V, noise_V, model_floor_V, settings)
    att = AttributionRound(
        theta=list(spec.theta), effects=[list(e) for e in spec.effects], n_fit=F.size, n_val=V.size,
        rss_theta_fit=rss_nl_theta_F, rss_theta_val=rss_nl_theta_V, theta_fit_window=list(theta_fit.theta),
        screen_rss_theta_val=lin.rss_val, noise_floor_val=V.size * floor, model_floor_val=model_floor_V, floor_weight=weight,
        excess_val=excess, excess_noise_val=excess_noise, visible=visible,
        significant=significant, table=rows,
        term_coefficient=term_c if problem.term is not None else None,
        rss_theta_val_without_term=rss_raw_V if problem.term is not None else None,
    )
    if retarget is not None and own is None and problem.term is not None and chosen:
        _rescore_unpassed(problem, att, retarget, rss_theta, settings)
    rows.sort(key=lambda row: (not row.refined, -row.explained_val))
    for rank, row in enumerate(rows, 1):
        row.rank = rank
    return att


def _rescore_unpassed(problem: Problem, att: AttributionRound, retarget: Callable[[ModelSpec], Problem],
                      rss_theta: tuple[float, float], settings: LoopSettings) -> None:
    """Where the theta-only model shows no discretization floor and no candidate among the
    ``max_tries`` best of ``att`` passes on that floor, rescore those with their own term
    (:func:`_own_term`); each keeps it only where its model shows a floor (else it is judged
    as before)."""
    att.table.sort(key=lambda row: (not row.refined, -row.explained_val))
    top = [row for row in att.table[: settings.max_tries] if row.refined]
    if not top or any(_passes(att, row, settings) for row in top):
        return
    for row in top:
        if row.explained_val > 0 and row.delta_bic < 0 and row.signature_ok:
            _own_term(problem, row, retarget, rss_theta, att.floor_weight, only_above=True)
    _judge(att.table, att.rss_theta_val, att.noise_floor_val, att.model_floor_val, settings)


def within_floor(att: AttributionRound, row: AttributionRow | None = None) -> bool:
    """Whether the theta-only residual of ``att`` lies within the model's discretization floor:
    a floor applies (the candidate's own where ``row`` was scored with its own term, else the
    round's) and the residual is not significant beyond noise and floor. There no effect can
    be named: one smaller than the floor cannot be told from the model's own error."""
    own = row is not None and not math.isnan(row.model_floor_val)
    model_floor = row.model_floor_val if own else att.model_floor_val
    significant = row.significant if own else att.significant
    return bool(model_floor > 0 and not significant)


def _passes(att: AttributionRound, row: AttributionRow, settings: LoopSettings) -> bool:
    """Whether ``row`` passes the attribution's rule for a joint recalibration: refined,
    explaining ``min_explained`` of the residual (:meth:`AttributionRound.decision_share`), a
    negative BIC difference, a matching time signature, and a residual beyond the
    discretization floor (:func:`within_floor`)."""
    return bool(row.refined and att.decision_share(row) >= settings.min_explained and row.delta_bic < 0
                and row.signature_ok and not within_floor(att, row))
