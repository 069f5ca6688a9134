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
against which a residual is significant) is measured, not assumed, in one of two ways:

- ``shifts`` (the default): the same model with its particles, and every box of its
  contract, moved against the fixed grid by half a cell along x, y, z and the diagonal
  (:data:`FLOOR_SHIFTS`). Each placement is as valid a discretization of the object as the
  model's own; where the model is not resolved its response depends on the placement (at ci
  by 5-24 % of the Probe-A response, ``benchmarks/model_error_span.py``). The floor is the
  mean energy of the placements' changes ``D_k`` that theta's sensitivities and ``c * D``
  cannot represent (the floor's shapes). It costs one model rollout per placement.
- ``second_refinement``: a second refinement, by ``r^2`` (three grids, as in a
  grid-convergence study), gives ``D2``, the change two steps away; its part that theta's
  sensitivities and ``c * D`` cannot represent is the shape the term misses one step
  further. At ci it overestimates the floor that a finer world leaves (docs/discrepancy.md).

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

__all__ = ["FLOOR_SHIFTS", "FLOOR_KINDS", "refined_contract", "translated", "ModelError", "displacement_at",
           "build_model_error"]

#: placements of the floor's ensemble: shifts of the particles against the grid, in cells
FLOOR_SHIFTS = ((0.5, 0.0, 0.0), (0.0, 0.5, 0.0), (0.0, 0.0, 0.5), (0.5, 0.5, 0.5))
#: how the discretization floor is measured (``LoopSettings.model_error_floor``)
FLOOR_KINDS = ("shifts", "second_refinement", "term")


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


def _moved(obj, shift):
    """``obj`` with every :class:`~knockgs_core.sim.Box` in it (through dataclass fields,
    tuples, lists and dicts) moved by ``shift`` [m]; untouched parts are returned as they are."""
    from ..sim import Box

    if isinstance(obj, Box):
        return Box(tuple(float(c) + float(s) for c, s in zip(obj.center, shift)), obj.half_size)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        changes = {}
        for f in dataclasses.fields(obj):
            if f.init:
                value = getattr(obj, f.name)
                new = _moved(value, shift)
                if new is not value:
                    changes[f.name] = new
        return dataclasses.replace(obj, **changes) if changes else obj
    if isinstance(obj, (tuple, list)):
        items = [_moved(x, shift) for x in obj]
        return type(obj)(items) if any(a is not b for a, b in zip(items, obj)) else obj
    if isinstance(obj, dict):
        items = {k: _moved(v, shift) for k, v in obj.items()}
        return items if any(items[k] is not obj[k] for k in obj) else obj
    return obj


def translated(contract, particles, shift):
    """The same discretized object placed elsewhere on the same grid: ``contract`` with every
    box (supports, probe and region boxes) and ``particles`` moved by ``shift`` [m] (3,).
    Particle order, volumes and count are unchanged, so particle i of the result is particle i
    of ``particles``. Returns (contract, particles)."""
    shift = np.asarray(shift, dtype=np.float64).reshape(3)
    if not np.all(np.isfinite(shift)):
        raise InputError("translated", "shift", f"must be finite, got {shift.tolist()}")
    moved = (np.asarray(particles.positions, dtype=np.float64) + shift).astype(np.float32)
    return _moved(contract, tuple(shift.tolist())), dataclasses.replace(particles, positions=moved)


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
    convergence; ``length`` the kernel length [m]. ``floor``: how the floor is measured
    (:data:`FLOOR_KINDS`); ``second``: the model refined by ``r^2`` (``second_refinement``);
    ``placements``: the model at the grid placements :data:`FLOOR_SHIFTS` (``shifts``);
    ``leftover_share``: the energy of the parts of their changes that theta and the term cannot
    represent (the floor's shapes, held by the problem), as a share of those changes';
    ``floor_ratios`` [K, 2]: for each of the floor's changes, the change of log theta it asks of
    the fit per unit of the misfit it leaves (|theta part| / norm of the part theta and the term
    cannot represent, 1/m): the bias in theta that a model error of that shape leaves behind a
    post-fit misfit of a given size; :attr:`theta_per_misfit` adds the recorded term's own
    (|theta_shift| / norm of the term), so it follows the model the term was last recorded at."""

    refined: ForwardModel
    factor: float
    c_max: float
    length: float
    second: ForwardModel | None = None
    placements: tuple[ForwardModel, ...] = ()
    floor: str = "shifts"
    spec: ModelSpec | None = None
    term: np.ndarray | None = None
    change: np.ndarray | None = None
    theta_shift: np.ndarray | None = None
    leftover_share: float | None = None
    floor_ratios: np.ndarray | None = None

    @property
    def richardson(self) -> float:
        return self.factor / (self.factor - 1.0)

    @property
    def theta_per_misfit(self) -> np.ndarray | None:
        """[K, 2] 1/m: the floor's ratios (``floor_ratios``), then the refinement's at the
        recorded term: its theta part ``theta_shift`` over its misfit, the term (none where the
        term is zero). None before a term is recorded."""
        if self.term is None:
            return None
        misfit = float(np.linalg.norm(self.term))
        own = np.abs(np.asarray(self.theta_shift, dtype=np.float64))[None, :] / misfit if misfit > 0 else np.zeros((0, 2))
        return own if self.floor_ratios is None else np.vstack([self.floor_ratios, own])

    def record(self, spec: ModelSpec, change: np.ndarray, term: np.ndarray, theta_shift: np.ndarray) -> None:
        """Keep the term computed at ``spec`` (``change`` D and ``term`` [T, M, 3], the theta
        change ``theta_shift`` [2] that moves the model like the refinement) as the model's."""
        self.spec, self.change, self.term, self.theta_shift = spec, change, term, theta_shift

    def difference(self, model: ForwardModel, spec: ModelSpec, probe: str, points: np.ndarray, *,
                   level: int = 1) -> np.ndarray:
        """D [T, P, 3] = refined (``level`` 1: by r; 2: by r^2) minus model displacement at rest
        ``points`` [P, 3] under ``probe`` at ``spec`` (effects included; both rollouts on the
        same kernel)."""
        refined = self.refined if level == 1 else self.second
        if refined is None:
            raise InputError("LoopSettings", "model_error_floor",
                             "the second refinement was not built (model_error_floor is not 'second_refinement')")
        X = np.asarray(model.rollout(spec, probe), dtype=np.float64)
        Xr = np.asarray(refined.rollout(spec, probe), dtype=np.float64)
        u = displacement_at(X[0], X - X[0], points, length=self.length)
        ur = displacement_at(Xr[0], Xr - Xr[0], points, length=self.length)
        return ur - u

    def placement_differences(self, model: ForwardModel, spec: ModelSpec, probe: str, index: np.ndarray) -> list[np.ndarray]:
        """D_k [T, P, 3] for each placement k: its displacement minus the model's, of the
        particles ``index`` [P] under ``probe`` at ``spec`` (the same particles: no kernel)."""
        X = np.asarray(model.rollout(spec, probe), dtype=np.float64)[:, index]
        U = X - X[0]
        out = []
        for placed in self.placements:
            Xk = np.asarray(placed.rollout(spec, probe), dtype=np.float64)[:, index]
            out.append((Xk - Xk[0]) - U)
        return out

    def to_dict(self) -> dict:
        c = self.refined.contract
        d = {"refine_factor": self.factor, "refined_n_grid": c.sim.n_grid, "refined_fill_resolution": c.fill.resolution,
             "refined_dt": c.sim.dt, "refined_particles": len(self.refined.particles.positions),
             "richardson_coefficient": self.richardson, "coefficient_max": self.c_max, "kernel_length": self.length,
             "floor": self.floor}
        if self.second is not None:
            c2 = self.second.contract
            d.update({"second_n_grid": c2.sim.n_grid, "second_fill_resolution": c2.fill.resolution,
                      "second_particles": len(self.second.particles.positions)})
        if self.placements:
            d["placement_shifts_cells"] = [list(s) for s in FLOOR_SHIFTS[: len(self.placements)]]
        if self.floor != "term":
            d["leftover_share"] = self.leftover_share
        return d


def build_model_error(model: ForwardModel, *, factor: float, c_max: float, floor: str = "shifts") -> ModelError:
    """The refined model of ``model`` (its contract refined by ``factor``, particles rebuilt)
    and what measures the floor (``floor``, :data:`FLOOR_KINDS`): the model at the grid
    placements :data:`FLOOR_SHIFTS` (``shifts``), the model refined by ``factor**2``
    (``second_refinement``), or nothing (``term``: the term's own energy is the floor). The
    models made here simulate on ``model``'s device with its ``deterministic``."""
    from ..assets import build_asset

    if floor not in FLOOR_KINDS:
        raise InputError("LoopSettings", "model_error_floor", f"unknown '{floor}'; known: {list(FLOOR_KINDS)}")

    def refine(f):
        contract = refined_contract(model.contract, f)
        return ForwardModel(contract, build_asset(contract).particles, catalogue=dict(model.catalogue), device=model.device,
                            deterministic=model.deterministic)

    refined = refine(factor)
    length = refined.contract.sim.grid_lim / refined.contract.sim.n_grid
    placements = ()
    if floor == "shifts":
        dx = model.contract.sim.grid_lim / model.contract.sim.n_grid
        placements = tuple(
            ForwardModel(*translated(model.contract, model.particles, np.asarray(s) * dx), catalogue=dict(model.catalogue),
                         device=model.device, deterministic=model.deterministic)
            for s in FLOOR_SHIFTS)
    return ModelError(refined=refined, factor=float(factor), c_max=float(c_max), length=float(length),
                      second=refine(factor * factor) if floor == "second_refinement" else None, placements=placements,
                      floor=floor)
