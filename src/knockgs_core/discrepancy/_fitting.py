"""Least squares through the simulator: the problem (measurement, correspondence, forward
model, fit and validation windows), the parametrization of a model and bounded
Levenberg-Marquardt (private)."""

from __future__ import annotations

import copy
import math
from typing import Callable, Sequence

import numpy as np

from ..errors import InputError, SimulationError
from ._forward import ForwardModel, ModelSpec
from ._measured import Correspondence, Measurement, match_points
from ._settings import LoopSettings

__all__ = ["Problem", "Parametrization", "levenberg_marquardt", "lm_fit", "theta_sensitivities"]


def theta_sensitivities(problem: Problem, spec: ModelSpec, settings: LoopSettings, base: np.ndarray | None = None) -> np.ndarray:
    """Forward-difference sensitivities of the observed positions to log s_E and log s_rho
    (step ``settings.theta_step``), frames after t = 0, flattened: [rows, 2]. ``base``: the
    model's observed positions at ``spec`` [T, M, 3] when already simulated."""
    base = problem.observe(spec) if base is None else base
    h = settings.theta_step
    cols = []
    for j in range(2):
        th = list(spec.theta)
        th[j] *= math.exp(h)
        cols.append((problem.observe(spec.with_theta(th)) - base)[1:].reshape(-1) / h)
    return np.column_stack(cols)


# --------------------------------------------------------------------------------------
# the problem: measurement, correspondence, forward model
# --------------------------------------------------------------------------------------
class Problem:
    """The measurement ``m`` seen through the forward model: observed frames and times [s],
    the point correspondence, and the residual rows of the fit window (``fit_rows``) and
    of the validation window (``val_rows``) in the flattened residual."""

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
        self.term: np.ndarray | None = None
        self.term_max = 0.0
        self.floor_shape: np.ndarray | None = None  # [K, rows]

    def observe(self, spec: ModelSpec) -> np.ndarray:
        """The model's positions [T, M, 3] at the observed points and frames (no term)."""
        X = self.forward.rollout(spec, self.probe)
        return self.corr.observe(X, self.frames, self.Y[0])

    def raw_residual(self, spec: ModelSpec) -> np.ndarray:
        """Simulated minus measured without the discretization term, frames after t = 0,
        flattened (frame, point, axis)."""
        return (self.observe(spec) - self.Y)[1:].reshape(-1)

    def coefficient(self, raw: np.ndarray) -> float:
        """The discretization term's coefficient c for a raw residual: least squares on the
        fit window, clipped to [0, ``term_max``] (0 without a term)."""
        if self.term is None:
            return 0.0
        t, r = self.term[self.fit_rows], raw[self.fit_rows]
        tt = float(t @ t)
        return float(np.clip(-float(t @ r) / tt, 0.0, self.term_max)) if tt > 0 else 0.0

    def residual(self, spec: ModelSpec) -> np.ndarray:
        """Simulated (plus the discretization term, its coefficient profiled out on the fit
        window) minus measured, frames after t = 0, flattened (frame, point, axis)."""
        raw = self.raw_residual(spec)
        if self.term is None:
            return raw
        return raw + self.coefficient(raw) * self.term

    def floor_weight(self, c: float) -> float:
        """How much of the discretization floor applies when the data show the term with
        coefficient ``c``: 0 up to ``c0``, rising linearly to 1 at ``c1``
        (``LoopSettings.model_error_ramp``), and ``c^2`` beyond ``c = 1`` (0 without a term).
        Data at the model's own resolution (c near 0) carry no discretization error of the
        model; data a sizeable part of a refinement step away carry at least the change of one
        step, and data further away at least the term as fitted."""
        if self.term is None:
            return 0.0
        c0, c1 = self.settings.model_error_ramp
        return float(np.clip((c - c0) / (c1 - c0), 0.0, 1.0) * max(1.0, c * c))

    def model_floor(self, rows, weight: float = 1.0) -> float:
        """The discretization floor [m^2] of the residual rows ``rows``: ``weight`` times the
        mean energy there of the floor's shapes (what other placements on the grid, or a second
        refinement, change that theta and the term cannot represent) or, without them, of the
        term itself (the model's change under refinement that theta cannot absorb); 0 without
        a term."""
        if self.term is None:
            return 0.0
        t = (self.floor_shape if self.floor_shape is not None else self.term[None, :])[:, rows]
        return float(weight) * float(np.mean(np.sum(t * t, axis=1)))

    def with_term(self, term: np.ndarray | None, term_max: float, *, floor_shape: np.ndarray | None = None) -> Problem:
        """The same problem with the discretization term ``term`` [T, M, 3] (m, frame 0
        included) whose coefficient is profiled in [0, ``term_max``], and the floor's shape
        ``floor_shape`` ([K, rows]: K shapes of flattened rows after frame 0, or one [rows];
        None: the term's)."""
        other = copy.copy(self)
        other.term = None if term is None else np.asarray(term, dtype=np.float64)[1:].reshape(-1)
        other.term_max = float(term_max)
        other.floor_shape = None
        if floor_shape is not None:
            shape = np.asarray(floor_shape, dtype=np.float64)
            other.floor_shape = shape.reshape(shape.shape[0] if shape.ndim > 1 else 1, -1)
        return other

    def with_forward(self, forward: ForwardModel) -> Problem:
        """The same problem simulated by ``forward`` (e.g. once it has its catalogue)."""
        other = copy.copy(self)
        other.forward = forward
        return other


# --------------------------------------------------------------------------------------
# least squares through the simulator
# --------------------------------------------------------------------------------------
class Parametrization:
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
        strengths = [eff.get(k, 0.0) / self.cat[k].scale for k in self.keys]
        return np.array([math.log(spec.theta[0]), math.log(spec.theta[1])] + strengths)

    def to_spec(self, x: np.ndarray, template: ModelSpec) -> ModelSpec:
        spec = template.with_theta((math.exp(x[0]), math.exp(x[1])))
        for k, xi in zip(self.keys, x[2:]):
            spec = spec.with_effect(k, float(xi) * self.cat[k].scale)
        return spec


def levenberg_marquardt(fun: Callable[[np.ndarray], np.ndarray], x0, lower, upper, steps, max_iter: int, log: list):
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


def lm_fit(problem: Problem, spec: ModelSpec, keys: Sequence[str], rows, settings: LoopSettings, iterations: int,
           log: list) -> tuple[ModelSpec, np.ndarray]:
    """LM over theta and the strengths of ``keys`` on the residual rows ``rows``, from ``spec``;
    returns the fitted spec and its full residual (all rows)."""
    par = Parametrization(keys, problem.forward.catalogue, settings)
    x, _, _ = levenberg_marquardt(lambda x: problem.residual(par.to_spec(x, spec))[rows], par.to_x(spec), par.lower, par.upper,
                                  par.steps, iterations, log)
    fitted = par.to_spec(x, spec)
    return fitted, problem.residual(fitted)
