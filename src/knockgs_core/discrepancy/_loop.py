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
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Callable, Sequence

import numpy as np

from ..errors import InputError, SimulationError
from ._catalogue import CATALOGUE_KEYS, CatalogueContext, default_catalogue, dev_strain_norm
from ._forward import ForwardModel, ModelSpec
from ._measured import Correspondence, Measurement, match_points
from ._views import residual_views, view_summary

__all__ = ["LoopSettings", "LibrarySource", "DiscrepancyResult", "run_discrepancy"]

#: effects that take over the same support cannot be combined
_EXCLUSIVE = ({"support_slip", "support_friction"},)


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
        validation window to be tried.
    min_confirm: the joint nonlinear recalibration must remove this share of the residual
        energy above the noise floor to keep the effect.
    max_effects: most effects added; max_tries: candidates tried per round.
    base_iterations, refit_iterations, joint_iterations, refine_iterations: LM iteration
        budgets (base calibration, theta refit, final joint fit, attribution refinement).
    refine_top: screened candidates refined nonlinearly (besides the threshold-type ones).
    theta_bounds: allowed range of each scale.
    catalogue: catalogue keys to consider (None: all that apply).
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

    def __post_init__(self):
        if not (0.2 <= self.fit_fraction <= 0.9):
            raise InputError("LoopSettings", "fit_fraction", "must be in [0.2, 0.9]")
        if self.catalogue is not None:
            bad = set(self.catalogue) - set(CATALOGUE_KEYS)
            if bad:
                raise InputError("LoopSettings", "catalogue", f"unknown keys {sorted(bad)}; known: {list(CATALOGUE_KEYS)}")


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
    """What the loop found. ``identified`` lists the added effects' keys (empty: none);
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
    metrics: dict
    n_simulations: int
    seconds: float
    settings: dict
    inputs: list[str] = field(default_factory=list)
    predictions: dict = field(default_factory=dict, repr=False)
    views: dict = field(default_factory=dict, repr=False)

    @property
    def identified_label(self) -> str:
        return "+".join(self.identified) if self.identified else "none"

    def to_dict(self) -> dict:
        d = {k: v for k, v in asdict(self).items() if k not in ("predictions", "views")}
        d["identified_label"] = self.identified_label
        return _jsonable(d)


def _jsonable(obj):
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, (np.floating, float)):
        v = float(obj)
        return v if math.isfinite(v) else (None if math.isnan(v) else ("inf" if v > 0 else "-inf"))
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj


# --------------------------------------------------------------------------------------
# the problem: measurement, correspondence, forward model
# --------------------------------------------------------------------------------------
class _Problem:
    def __init__(self, measured: Measurement, forward: ForwardModel, probe: str, settings: LoopSettings):
        self.m = measured
        self.forward = forward
        self.probe = probe
        self.settings = settings
        export = forward.probe_export(probe)
        self.frames = measured.frame_indices(export.frame_dt, export.n_frames)
        self.times = self.frames * export.frame_dt
        self.corr: Correspondence = match_points(measured, forward.particles.positions, forward.particles.n_gs)
        T = measured.n_frames
        if T < 4:
            raise InputError(measured.source, "frame", f"need at least 4 measured frames, got {T}")
        n_fit = int(math.ceil(settings.fit_fraction * (T - 1)))
        n_fit = min(max(n_fit, 1), T - 2)
        rows_per_frame = measured.n_points * 3
        self.fit_rows = np.arange(n_fit * rows_per_frame)
        self.val_rows = np.arange(n_fit * rows_per_frame, (T - 1) * rows_per_frame)
        self.fit_frames = n_fit
        self.Y = measured.points

    def observe(self, spec: ModelSpec) -> np.ndarray:
        X = self.forward.rollout(spec, self.probe)
        return self.corr.observe(X, self.frames, self.Y[0])

    def residual(self, spec: ModelSpec) -> np.ndarray:
        """Simulated minus measured, frames after t = 0, flattened (frame, point, axis)."""
        return (self.observe(spec) - self.Y)[1:].reshape(-1)


# --------------------------------------------------------------------------------------
# least squares through the simulator
# --------------------------------------------------------------------------------------
class _Parametrization:
    """x = [log s_E, log s_rho, u_1 / scale_1, ...] for the effects of ``keys``."""

    def __init__(self, keys: Sequence[str], catalogue: dict, settings: LoopSettings):
        self.keys = list(keys)
        self.cat = catalogue
        lo, hi = settings.theta_bounds
        self.lower = np.array([math.log(lo), math.log(lo)] + [catalogue[k].bounds[0] / catalogue[k].scale for k in self.keys])
        self.upper = np.array([math.log(hi), math.log(hi)] + [catalogue[k].bounds[1] / catalogue[k].scale for k in self.keys])
        self.steps = np.array([settings.theta_step] * 2 + [settings.effect_step] * len(self.keys))

    def to_x(self, spec: ModelSpec) -> np.ndarray:
        eff = dict(spec.effects)
        return np.array([math.log(spec.theta[0]), math.log(spec.theta[1])] + [eff.get(k, 0.0) / self.cat[k].scale for k in self.keys])

    def to_spec(self, x: np.ndarray, template: ModelSpec) -> ModelSpec:
        spec = template.with_theta((math.exp(x[0]), math.exp(x[1])))
        for k, xi in zip(self.keys, x[2:]):
            spec = spec.with_effect(k, float(xi) * self.cat[k].scale)
        return spec


def _levenberg_marquardt(fun: Callable[[np.ndarray], np.ndarray], x0, lower, upper, steps, max_iter: int, log: list):
    """Bounded LM with forward-difference Jacobians; ``fun`` may raise SimulationError
    (treated as an infinite cost). Returns (x, residual, cost)."""

    def safe(x):
        try:
            r = fun(x)
        except (SimulationError, InputError) as exc:
            log.append({"event": "simulation_failed", "x": x.tolist(), "error": str(exc)[:200]})
            return None
        return r if np.all(np.isfinite(r)) else None

    x = np.clip(np.asarray(x0, dtype=np.float64), lower, upper)
    r = safe(x)
    if r is None:
        raise SimulationError(f"the starting model fails to simulate (x = {x.tolist()})")
    cost = float(r @ r)
    lam = 1e-3
    for it in range(max_iter):
        J = np.empty((r.size, x.size))
        for j in range(x.size):
            h = steps[j] if x[j] + steps[j] <= upper[j] else -steps[j]
            xj = x.copy()
            xj[j] += h
            rj = safe(xj)
            J[:, j] = 0.0 if rj is None else (rj - r) / h
        A = J.T @ J
        g = J.T @ r
        improved = False
        for _ in range(4):
            D = np.diag(np.diag(A)) + 1e-12 * np.eye(x.size) * max(np.trace(A), 1e-30)
            try:
                dx = -np.linalg.solve(A + lam * D, g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            xn = np.clip(x + dx, lower, upper)
            rn = safe(xn)
            cn = math.inf if rn is None else float(rn @ rn)
            if cn < cost:
                rel = (cost - cn) / max(cost, 1e-300)
                x, r, cost = xn, rn, cn
                lam = max(lam * 0.3, 1e-7)
                improved = True
                break
            lam *= 8.0
        log.append({"event": "iteration", "iteration": it, "cost": cost, "x": x.tolist(), "lambda": lam, "improved": improved})
        if not improved or rel < 1e-4:
            break
    return x, r, cost


# --------------------------------------------------------------------------------------
# base calibration
# --------------------------------------------------------------------------------------
def _library_estimate(problem: _Problem, library: LibrarySource) -> tuple[tuple[float, float], dict]:
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
    est = LocalRidge(k=library.k, alpha=library.alpha).fit(np.array(feats), np.asarray(library.theta, dtype=float), list(library.names)).predict(query[None, :])[0]
    details = {k: est.details.get(k) for k in ("neighbours", "fallback", "clipped") if k in est.details}
    return (est.E_scale, est.density_scale), details


# --------------------------------------------------------------------------------------
# attribution
# --------------------------------------------------------------------------------------
def _fit_rows(A, r, rows):
    coef, *_ = np.linalg.lstsq(A[rows], r[rows], rcond=None)
    return coef


def _rss(A, coef, r, rows):
    e = r[rows] - A[rows] @ coef
    return float(e @ e)


def _lm_fit(problem: _Problem, spec: ModelSpec, keys, rows, settings: LoopSettings, iterations: int, log: list) -> tuple[ModelSpec, np.ndarray]:
    """LM over theta and the strengths of ``keys`` on the residual rows ``rows``, from ``spec``;
    returns the fitted spec and its full residual (all rows)."""
    par = _Parametrization(keys, problem.forward.catalogue, settings)
    x, _, _ = _levenberg_marquardt(lambda x: problem.residual(par.to_spec(x, spec))[rows], par.to_x(spec), par.lower, par.upper,
                                   par.steps, iterations, log)
    fitted = par.to_spec(x, spec)
    return fitted, problem.residual(fitted)


def _attribute(problem: _Problem, spec: ModelSpec, candidates: list, floor: float, settings: LoopSettings, log: list) -> dict:
    """Rank the candidates at ``spec`` (module docs, step 3).

    Screen: every candidate's trial signatures, fitted jointly with the theta sensitivities
    (linear least squares on the fit window). Refinement: the ``refine_top`` best screened
    candidates and every threshold-type candidate are fitted nonlinearly (LM through the
    simulator over theta, the strengths already in the model and the candidate's, on the
    fit window), as is theta alone; scores compare their residuals on the validation window.
    The refinement is skipped when the theta-only residual is not significant.
    """
    base = problem.observe(spec)
    r = (problem.Y - base)[1:].reshape(-1)  # measured minus simulated: what a change must add
    h = settings.theta_step
    J = np.empty((r.size, 2))
    for j in range(2):
        th = list(spec.theta)
        th[j] *= math.exp(h)
        J[:, j] = (problem.observe(spec.with_theta(th)) - base)[1:].reshape(-1) / h
    F, V = problem.fit_rows, problem.val_rows
    nF, nV = F.size, V.size
    a = _fit_rows(J, r, F)
    rss_theta_F, rss_theta_V = _rss(J, a, r, F), _rss(J, a, r, V)
    rows = []
    present = set(spec.effect_keys)
    blocked = set().union(*(g for g in _EXCLUSIVE if g & present)) if present else set()
    by_key = {c.key: c for c in candidates}
    for cand in candidates:
        if cand.key in present or cand.key in blocked:
            continue
        best = None
        for u in cand.trials:
            try:
                S = (problem.observe(spec.with_effect(cand.key, u)) - base)[1:].reshape(-1)
            except (SimulationError, InputError) as exc:
                best = best or {"trial": u, "error": str(exc)[:200]}
                continue
            A = np.column_stack([J, S])
            coef = _fit_rows(A, r, F)
            if cand.one_sided and coef[2] < 0:
                coef = np.array([a[0], a[1], 0.0])
            rF = _rss(A, coef, r, F)
            if best is None or "error" in best or rF < best["rss_fit"]:
                best = {"trial": u, "coef": float(coef[2]), "rss_fit": rF, "rss_val": _rss(A, coef, r, V)}
        if best is None or "error" in best:
            rows.append({"key": cand.key, "label": cand.label, "error": (best or {}).get("error", "no trial"), "explained_val": -math.inf, "refined": False})
            continue
        u_est = float(np.clip(best["coef"] * best["trial"], *cand.bounds))
        rows.append({
            "key": cand.key,
            "label": cand.label,
            "trial_strength": best["trial"],
            "coefficient": best["coef"],
            "strength_estimate": u_est,
            "parameter": cand.parameter,
            "value_estimate": cand.value(u_est),
            "unit": cand.unit,
            "screen_explained_fit": 1.0 - best["rss_fit"] / max(rss_theta_F, 1e-300),
            "screen_explained_val": 1.0 - best["rss_val"] / max(rss_theta_V, 1e-300),
            "refined": False,
        })
    rows.sort(key=lambda row: -row.get("screen_explained_val", -math.inf))

    # nonlinear refinement ---------------------------------------------------------------
    keys0 = list(spec.effect_keys)
    theta_fit, r_theta = _lm_fit(problem, spec, keys0, F, settings, settings.refine_iterations, log)
    rss_nl_theta_F, rss_nl_theta_V = float(r_theta[F] @ r_theta[F]), float(r_theta[V] @ r_theta[V])
    excess = rss_nl_theta_V / (nV * floor) - 1.0 if floor > 0 else math.inf
    significant = bool(excess > settings.min_excess)
    chosen = [row["key"] for row in rows if "error" not in row][: settings.refine_top]
    chosen += [row["key"] for row in rows if "error" not in row and by_key[row["key"]].threshold and row["key"] not in chosen]
    if not significant:  # nothing to explain: the screen is reported, no refinement is needed
        chosen = []
    for row in rows:
        if row["key"] not in chosen:
            row["explained_val"] = row.get("screen_explained_val", -math.inf)
            continue
        cand = by_key[row["key"]]
        # start from the better (on the fit window) of the screen's estimate and its trials
        start, start_cost = None, math.inf
        for u0 in dict.fromkeys((row["strength_estimate"],) + tuple(cand.trials)):
            if u0 == 0.0:
                continue
            trial = spec.with_effect(cand.key, u0)
            try:
                rr = problem.residual(trial)[F]
            except (SimulationError, InputError):
                continue
            c0 = float(rr @ rr)
            if c0 < start_cost:
                start, start_cost = trial, c0
        if start is None:
            row["explained_val"] = row.get("screen_explained_val", -math.inf)
            continue
        try:
            fitted, rr = _lm_fit(problem, start, keys0 + [cand.key], F, settings, settings.refine_iterations, log)
        except SimulationError as exc:
            row["refine_error"] = str(exc)[:200]
            row["explained_val"] = row.get("screen_explained_val", -math.inf)
            continue
        rF, rV = float(rr[F] @ rr[F]), float(rr[V] @ rr[V])
        u = dict(fitted.effects)[cand.key]
        row.update({
            "refined": True,
            "strength_estimate": u,
            "value_estimate": cand.value(u),
            "theta_estimate": list(fitted.theta),
            "explained_fit": 1.0 - rF / max(rss_nl_theta_F, 1e-300),
            "explained_val": 1.0 - rV / max(rss_nl_theta_V, 1e-300),
            "delta_bic": nF * math.log(max(rF, 1e-300) / max(rss_nl_theta_F, 1e-300)) + math.log(nF),
            "refined_spec": fitted,
        })
    rows.sort(key=lambda row: (not row["refined"], -row["explained_val"]))
    for rank, row in enumerate(rows, 1):
        row["rank"] = rank
    return {
        "theta": list(spec.theta),
        "effects": [list(e) for e in spec.effects],
        "n_fit": nF,
        "n_val": nV,
        "rss_theta_fit": rss_nl_theta_F,
        "rss_theta_val": rss_nl_theta_V,
        "theta_fit_window": list(theta_fit.theta),
        "screen_rss_theta_val": rss_theta_V,
        "noise_floor_val": nV * floor,
        "excess_val": excess,
        "significant": significant,
        "table": rows,
    }


# --------------------------------------------------------------------------------------
# the loop
# --------------------------------------------------------------------------------------
def _noise(problem: _Problem, spec: ModelSpec) -> dict:
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


def _context(problem: _Problem, spec: ModelSpec) -> CatalogueContext:
    fw = problem.forward
    Yobs = problem.observe(spec)
    rms = float(np.sqrt(np.mean(np.sum((Yobs - Yobs[0]) ** 2, axis=-1))))
    F = fw.deformation(spec, problem.probe)
    strain = float(np.quantile(dev_strain_norm(F.reshape(-1, 3, 3)), 0.999)) if F is not None and F.size else 1e-3
    E, nu, _ = fw.base_materials()
    mu = float(np.mean(E / (2.0 * (1.0 + nu))))
    return CatalogueContext(
        horizon=float(problem.times[-1]), rms_displacement=rms, max_dev_strain=strain, shear_modulus=mu,
        nu_range=(float(nu.min()), float(nu.max())), has_gravity=fw.has_gravity(), has_support=fw.has_still_support(),
    )


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
    progress: Callable[[str], None] | None = None,
) -> DiscrepancyResult:
    """Run the discrepancy loop on ``measured`` (the calibration-probe response) for
    ``contract`` simulated on ``particles``.

    ``probe`` defaults to the measurement's metadata, then the contract's calibration
    probe. ``heldout_probes`` are predicted before and after (never used in the loop);
    ``heldout_measured`` maps some of them to their measurements, used only to score those
    predictions in the result. ``library`` selects the library base calibration, else LM
    from (1, 1). Returns a :class:`DiscrepancyResult`.
    """
    say = progress or (lambda msg: None)
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

    fw = ForwardModel(contract, particles, device=device)
    pb = _Problem(measured, fw, probe, settings)
    log: list = []

    # 1. base calibration ------------------------------------------------------------
    start = ModelSpec((1.0, 1.0))
    if library is not None:
        theta0, lib_details = _library_estimate(pb, library)
        base = ModelSpec(tuple(float(t) for t in theta0))
        base_method = "library_local_ridge"
        say(f"base calibration (library, local ridge): theta = ({base.theta[0]:.4f}, {base.theta[1]:.4f})")
    else:
        par = _Parametrization([], fw.catalogue, settings)
        x, _, _ = _levenberg_marquardt(lambda x: pb.residual(par.to_spec(x, start)), par.to_x(start), par.lower, par.upper, par.steps, settings.base_iterations, log)
        base = par.to_spec(x, start)
        base_method = "gauss_newton"
        lib_details = None
        say(f"base calibration (LM from (1, 1)): theta = ({base.theta[0]:.4f}, {base.theta[1]:.4f})")

    # catalogue sized by the calibrated response
    ctx = _context(pb, base)
    cands = default_catalogue(ctx, keys=settings.catalogue)
    fw.catalogue = {c.key: c for c in cands}
    noise = _noise(pb, base)
    floor = noise["floor_per_scalar"]

    # 2. theta refined through the simulator --------------------------------------------
    if library is not None:
        par = _Parametrization([], fw.catalogue, settings)
        x, _, _ = _levenberg_marquardt(lambda x: pb.residual(par.to_spec(x, base)), par.to_x(base), par.lower, par.upper, par.steps, settings.refit_iterations, log)
        refit = par.to_spec(x, base)
    else:
        refit = base
    say(f"theta refit: ({refit.theta[0]:.4f}, {refit.theta[1]:.4f})")

    # 3-5. attribution and augmentation ------------------------------------------------
    spec = refit
    rounds = []
    unexplained = False
    stop_reason = ""
    while True:
        att = _attribute(pb, spec, cands, floor, settings, log)
        att["decision"] = None
        rounds.append(att)
        top = att["table"][0] if att["table"] else None
        say(f"round {len(rounds)}: excess over noise {att['excess_val']:.3g}; best {top['key'] if top else '-'} explains {top['explained_val'] if top else float('nan'):.3f}")
        if not att["significant"]:
            att["decision"] = "no significant residual left"
            stop_reason = "no_residual"
            break
        if len(spec.effects) >= settings.max_effects:
            att["decision"] = f"stop: at most {settings.max_effects} effects are added"
            stop_reason = "max_effects"
            unexplained = True
            break
        tried = []
        accepted = None
        rss_cur = float(np.sum(pb.residual(spec) ** 2))
        for row in att["table"][: settings.max_tries]:
            if not row["refined"] or row["explained_val"] < settings.min_explained or row["delta_bic"] >= 0:
                continue
            key = row["key"]
            start_spec = row["refined_spec"]
            try:
                new, rr = _lm_fit(pb, start_spec, list(start_spec.effect_keys), slice(None), settings, settings.joint_iterations, log)
            except SimulationError as exc:
                tried.append({"key": key, "error": str(exc)[:200]})
                continue
            cost = float(rr @ rr)
            excess_all = max(rss_cur - rr.size * floor, 1e-12 * rss_cur)
            gain = (rss_cur - cost) / excess_all
            new = ModelSpec(new.theta, tuple((k, u) for k, u in new.effects if u != 0.0 or k == key))
            tried.append({"key": key, "rss_before": rss_cur, "rss_after": cost, "gain_over_excess": gain, "theta": list(new.theta), "effects": [list(e) for e in new.effects]})
            if gain >= settings.min_confirm and dict(new.effects)[key] != 0.0:
                accepted = (key, new)
                break
        att["tried"] = tried
        for row in att["table"]:
            row.pop("refined_spec", None)
        if accepted is None:
            att["decision"] = "residual unexplained by the catalogue"
            stop_reason = "unexplained"
            unexplained = True
            break
        key, spec = accepted
        att["decision"] = f"added {key}"
        say(f"added {key}: theta = ({spec.theta[0]:.4f}, {spec.theta[1]:.4f}), strengths {dict(spec.effects)}")
    for att in rounds:
        for row in att["table"]:
            row.pop("refined_spec", None)
    final = spec

    # predictions and views ------------------------------------------------------------
    stages = {"before": base, "refit": refit, "after": final}
    n_gs = particles.n_gs
    predictions = {}
    for pr in [probe] + heldout_probes:
        predictions[pr] = {name: np.asarray(fw.rollout(s, pr)[:, :n_gs], dtype=np.float32) for name, s in stages.items()}
    metrics, views = {}, {}
    for pr, meas in [(probe, measured)] + [(p, heldout_measured[p]) for p in heldout_probes if p in heldout_measured]:
        sub = _Problem(meas, fw, pr, settings) if pr != probe else pb
        metrics[pr], views[pr] = {}, {}
        for name, s in stages.items():
            v = residual_views(meas.points, sub.observe(s), sub.times)
            views[pr][name] = v
            metrics[pr][name] = view_summary(v)

    # residual size at the end --------------------------------------------------------
    r_end = pb.residual(final)
    n_end = r_end.size
    rss_end = float(r_end @ r_end)
    excess_end = max(rss_end - n_end * floor, 0.0)
    Yd = pb.Y - pb.Y[0]
    rms_meas = float(np.sqrt(np.mean(np.sum(Yd**2, axis=-1))))
    residual = {
        "rms_per_point": math.sqrt(3.0 * rss_end / n_end),
        "excess_rms_per_point": math.sqrt(3.0 * excess_end / n_end),
        "noise_rms_per_point": math.sqrt(3.0 * floor),
        "measured_rms_displacement": rms_meas,
        "excess_fraction_of_response": math.sqrt(3.0 * excess_end / n_end) / max(rms_meas, 1e-30),
        "stop_reason": stop_reason,
    }
    identified = list(final.effect_keys)
    effects = []
    for k, u in final.effects:
        c = fw.catalogue[k]
        effects.append({"key": k, "label": c.label, "strength": u, "parameter": c.parameter, "value": c.value(u), "unit": c.unit})
    if unexplained:
        found = f"added {', '.join(identified)}; " if identified else ""
        verdict = (f"{found}a residual remains that no catalogue effect explains: "
                   f"RMS {residual['excess_rms_per_point']:.3g} m above the noise "
                   f"({100 * residual['excess_fraction_of_response']:.1f}% of the measured RMS displacement)")
    elif identified:
        verdict = "effects found: " + ", ".join(f"{e['key']} ({e['parameter']} = {e['value']:.4g} {e['unit']})".replace(" )", ")") for e in effects) + "; no further effect"
    else:
        verdict = "no missing effect found"
    say(verdict)
    return DiscrepancyResult(
        object=contract.name,
        profile=getattr(contract, "profile", ""),
        probe=probe,
        heldout_probes=heldout_probes,
        verdict=verdict,
        identified=identified,
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
        rounds=rounds,
        metrics=metrics,
        n_simulations=fw.n_simulations,
        seconds=fw.seconds,
        settings=asdict(settings),
        predictions=predictions,
        views=views,
    )
