"""The model's own discretization error, estimated by a refined rollout (private).

Measured data comes from a continuum, the loop's model from a grid. The difference between
the model and the same model on a finer grid,

    D(t, x) = u_refined(t, x) - u_model(t, x)        [m], at the observed points,

is the direction in which the model's response moves under refinement. Under first-order
convergence in the cell size h (docs/verification.md: orders 0.8-1.1 against an independent
FEM), the model's error against the limit is ``D * r / (r - 1)`` for a refinement ratio r
(Richardson), so the data of a finer world or of the continuum is, near the calibrated theta,
the model plus ``c * D`` with ``c`` between 0 (data at the model's own resolution) and about
``r / (r - 1)`` (the continuum). The loop carries ``c * D`` as a structured term: ``c`` is
profiled out of every least-squares fit (one-sided, ``0 <= c <= c_max``), so an effect is
judged on what it explains beyond the discretization error; the term sets the verdict
"consistent with the model's discretization error" and widens the theta interval.

How much of the data's discretization error a term of this one shape misses (the *floor*
against which a residual is significant) is measured, not assumed: a second refinement, by
``r^2`` (three grids, as in a grid-convergence study), gives ``D2``, the change two steps
away; the part of ``D2`` that theta's sensitivities and ``c * D`` cannot represent
(``leftover``) is the shape the term misses one step further, and its energy is the floor.

The refined model is the loop's own contract with the grid and the interior fill refined by
``factor`` (the same Gaussians, a new fill, the contracts' time-step rule). Displacements of
the two models are compared at the same points through one smoothing kernel (Gaussian
weights of the k nearest particles, length the refined cell size), so that D holds the
discretization change and not the two particle sets' sampling.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ._forward import ForwardModel, ModelSpec

__all__ = ["refined_contract", "ModelError", "displacement_at", "build_model_error"]


def refined_contract(contract, factor: float):
    """``contract`` with its grid and fill resolution multiplied by ``factor`` (rounded) and
    the time step re-derived by the contracts' rule (the largest frame-commensurate dt at
    most 0.3 dx / c_p at the stiffest candidate). Gaussians and probes are unchanged."""
    if not (factor > 1.0 and math.isfinite(factor)):
        raise InputError("LoopSettings", "model_error_refine", f"must be a finite factor > 1, got {factor!r}")
    sim = contract.sim
    n_grid = int(round(sim.n_grid * factor))
    fill = dataclasses.replace(contract.fill, resolution=int(round(contract.fill.resolution * factor)))
    out = dataclasses.replace(contract, sim=dataclasses.replace(sim, n_grid=n_grid), fill=fill)
    dt = out.cfl_dt()
    return dataclasses.replace(out, sim=dataclasses.replace(out.sim, dt=float(dt)))


def displacement_at(rest: np.ndarray, displacement: np.ndarray, points: np.ndarray, *, length: float, k: int = 8) -> np.ndarray:
    """Displacement field sampled by particles (``rest`` [N, 3], ``displacement`` [T, N, 3],
    metres) at ``points`` [P, 3]: Gaussian-weighted mean (``exp(-(d / length)^2)``) of the
    ``k`` nearest particles. Returns [T, P, 3]."""
    from scipy.spatial import cKDTree

    rest = np.asarray(rest, dtype=np.float64)
    k = min(k, len(rest))
    d, idx = cKDTree(rest).query(np.asarray(points, dtype=np.float64), k=k)
    d, idx = d.reshape(len(points), k), idx.reshape(len(points), k)
    w = np.exp(-((d - d[:, :1]) / max(length, 1e-12)) ** 2)
    w /= w.sum(axis=1, keepdims=True)
    U = np.asarray(displacement, dtype=np.float64)
    return np.einsum("pk,tpkd->tpd", w, U[:, idx])


@dataclass
class ModelError:
    """The model's discretization term: ``change`` [T, M, 3] (m), D at the observed points for
    the calibration probe and the model ``spec`` it was computed at, and ``term``, its part
    that theta cannot absorb (the loop's structured term); ``theta_shift`` [2], the change of
    log theta that moves the model like the refinement does (least squares on D); ``refined`` the refined
    forward model; ``factor`` the refinement ratio r; ``c_max`` the bound of the coefficient;
    ``richardson`` ``r / (r - 1)``: the coefficient of the continuum limit under first-order
    convergence; ``length`` the kernel length [m]. ``second``: the model refined by ``r^2``
    (None: no floor measurement) and ``leftover`` [T, M, 3] (m): the part of its change that
    theta and the term cannot represent, ``leftover_share``: its energy as a share of that
    change's."""

    refined: ForwardModel
    factor: float
    c_max: float
    length: float
    second: ForwardModel | None = None
    spec: ModelSpec | None = None
    term: np.ndarray | None = None
    change: np.ndarray | None = None
    theta_shift: np.ndarray | None = None
    leftover: np.ndarray | None = None
    leftover_share: float | None = None

    @property
    def richardson(self) -> float:
        return self.factor / (self.factor - 1.0)

    def difference(self, model: ForwardModel, spec: ModelSpec, probe: str, points: np.ndarray, *,
                   level: int = 1) -> np.ndarray:
        """D [T, P, 3] = refined (``level`` 1: by r; 2: by r^2) minus model displacement at rest
        ``points`` [P, 3] under ``probe`` at ``spec`` (effects included; both rollouts on the
        same kernel)."""
        refined = self.refined if level == 1 else self.second
        if refined is None:
            raise InputError("LoopSettings", "model_error_second", "the second refinement was not built")
        X = np.asarray(model.rollout(spec, probe), dtype=np.float64)
        Xr = np.asarray(refined.rollout(spec, probe), dtype=np.float64)
        u = displacement_at(X[0], X - X[0], points, length=self.length)
        ur = displacement_at(Xr[0], Xr - Xr[0], points, length=self.length)
        return ur - u

    def to_dict(self) -> dict:
        c = self.refined.contract
        d = {"refine_factor": self.factor, "refined_n_grid": c.sim.n_grid, "refined_fill_resolution": c.fill.resolution,
             "refined_dt": c.sim.dt, "refined_particles": len(self.refined.particles.positions),
             "richardson_coefficient": self.richardson, "coefficient_max": self.c_max, "kernel_length": self.length}
        if self.second is not None:
            c2 = self.second.contract
            d.update({"second_n_grid": c2.sim.n_grid, "second_fill_resolution": c2.fill.resolution,
                      "second_particles": len(self.second.particles.positions), "leftover_share": self.leftover_share})
        return d


def build_model_error(model: ForwardModel, *, factor: float, c_max: float, second: bool = True) -> ModelError:
    """The refined model of ``model`` (its contract refined by ``factor``, particles rebuilt)
    and, with ``second``, the model refined by ``factor**2`` that measures the floor."""
    from ..assets import build_asset

    def refine(f):
        contract = refined_contract(model.contract, f)
        return ForwardModel(contract, build_asset(contract).particles, catalogue=dict(model.catalogue), device=model.device)

    refined = refine(factor)
    length = refined.contract.sim.grid_lim / refined.contract.sim.n_grid
    return ModelError(refined=refined, factor=float(factor), c_max=float(c_max), length=float(length),
                      second=refine(factor * factor) if second else None)
