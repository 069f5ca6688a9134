"""MPM against the finite-element reference on one problem: a block held by its bottom layer,
knocked by a uniform impulse.

The problem (:data:`BLOCK`, :data:`SUPPORT`, :data:`MATERIAL`): a block 0.5 x 0.5 x 0.75 m
([0.75, 1.25]^2 x [0.5, 1.25] in the normalized domain [0, 2]^3) of the Pillow's base material
at the library's stiffest, lightest candidate theta = (1.15, 0.75) (E = 1.15e4 Pa, nu = 0.3,
rho = 1500 kg/m^3); its bottom 0.25 m lie in a fixed support box (z <= 0.75), so 0.5 m stand
free. No gravity. At t = 0 a pulse of 1e-4 s gives every part of the block the same impulse
per mass ``impulse_velocity`` [m/s] along x (Probe A's kind of knock: a global probe).

- MPM (:mod:`knockgs_core.sim`): particles on a uniform lattice, ``particles_per_axis^3`` per
  grid cell, the block's faces on grid planes at every level (every cell full, every particle
  of the same mass ``rho dx^3 / ppc``), so the probe's force per particle
  ``m_p impulse_velocity / duration`` is a uniform force density; the support a sticky
  :class:`~knockgs_core.sim.FixedCuboid` whose top is the grid plane z = 0.75; the substep the
  largest frame-commensurate value with ``c_p dt / dx <= cfl``, so dt is refined with dx.
- FEM (:mod:`knockgs_core.fem`, no simulator code): a structured tetrahedral mesh of the
  block (one element layer in the held part, ``fem_cells`` per 0.5 m in the free part), the
  nodes in the same support box held, the same force density as a :class:`ForcePulse`,
  Newmark average acceleration with step ``fem_dt``.

Compared (the reference evaluated at each MPM level's particle rest positions): the displacement
trajectories ``u`` (frames, particles, 3) of every particle; their RMS-displacement curve
``sqrt(mean_p |u_p(t)|^2)``; its peak; the first-mode period from the mean x-displacement of
the particles (:func:`first_mode_period`); the trajectory RMSE ``sqrt(mean |u_mpm - u_fem|^2)``.
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Callable, Mapping, Sequence

import numpy as np
import pandas as pd
from scipy.optimize import minimize_scalar

from ..errors import InputError
from ..sim import Box, FixedCuboid, Probe, SimParams, build_model, make_state, simulate
from ._elasticity import assemble_elasticity, interpolation_matrix, lame, support_dofs
from ._mesh import Region, tensor_mesh
from ._newmark import ForcePulse, newmark

__all__ = [
    "MATERIAL",
    "BLOCK",
    "SUPPORT",
    "PROBE_DURATION",
    "VerificationSettings",
    "block_particles",
    "mpm_dt",
    "mpm_block_rollout",
    "fem_block_reference",
    "first_mode_period",
    "rms_curve",
    "response_gap",
    "verification_study",
    "verification_note",
    "mpm_period_limit",
    "mpm_period_order",
]

_SOURCE = "verification settings"
MATERIAL = {"E": 1.15e4, "nu": 0.3, "rho": 1500.0}
"""E [Pa], nu [-], rho [kg/m^3]: the Pillow's base material at theta = (1.15, 0.75)."""
BLOCK = ((0.75, 0.75, 0.5), (1.25, 1.25, 1.25))
"""The block's corners [m]: every face on a grid plane for n_grid a multiple of 8 (or of 12)."""
SUPPORT = Box(center=(1.0, 1.0, 0.375), half_size=(0.5, 0.5, 0.375 + 1e-4))
"""The support box: z <= 0.7501 (the grid plane z = 0.75 and the held bottom 0.25 m)."""
SUPPORT_TOP = 0.75
PROBE_DURATION = 1e-4
GRID_LIM = 2.0


@dataclasses.dataclass(frozen=True)
class VerificationSettings:
    """The MPM-vs-FEM verification's settings (the config's ``verification`` block mirrors
    these defaults). ``n_grid``: the MPM levels, coarsest first (multiples of 8 or 12, so the
    block's faces lie on grid planes); ``particles_per_axis``: particles per cell and axis;
    ``cfl``: ``c_p dt / dx`` bound of the MPM substep; ``fem_cells``: FEM cells per 0.5 m;
    ``fem_degree``: 1 (P1) or 2 (P2) tetrahedra; ``fem_dt`` [s]: the Newmark step;
    ``frame_dt`` [s], ``n_frames``: the exported frames; ``impulse_velocity`` [m/s]: the
    probe's impulse per unit mass along x."""

    n_grid: tuple[int, ...] = (16, 24, 32, 48)
    particles_per_axis: int = 2
    cfl: float = 0.3
    fem_cells: int = 8
    fem_degree: int = 2
    fem_dt: float = 0.01
    frame_dt: float = 0.05
    n_frames: int = 61
    impulse_velocity: float = 0.002

    def __post_init__(self):
        object.__setattr__(self, "n_grid", tuple(int(n) for n in self.n_grid))
        if len(self.n_grid) < 2 or any(b <= a for a, b in zip(self.n_grid, self.n_grid[1:])):
            raise InputError(_SOURCE, "n_grid", f"need at least two increasing levels, got {list(self.n_grid)}")
        for n in self.n_grid:
            dx = GRID_LIM / n
            on_grid = all(abs(c / dx - round(c / dx)) < 1e-9 for c in (*BLOCK[0], *BLOCK[1], SUPPORT_TOP))
            if not on_grid or BLOCK[0][2] < 3 * dx:
                raise InputError(_SOURCE, "n_grid", f"n_grid {n} puts the block's faces off the grid planes "
                                 f"(use multiples of 8 or of 12, at least 16)")
        if int(self.particles_per_axis) < 1:
            raise InputError(_SOURCE, "particles_per_axis", f"must be >= 1, got {self.particles_per_axis}")
        if not (0 < self.cfl <= 1):
            raise InputError(_SOURCE, "cfl", f"must be in (0, 1], got {self.cfl}")
        if int(self.fem_cells) < 1:
            raise InputError(_SOURCE, "fem_cells", f"must be >= 1, got {self.fem_cells}")
        if self.fem_degree not in (1, 2):
            raise InputError(_SOURCE, "fem_degree", f"must be 1 or 2, got {self.fem_degree}")
        for name in ("fem_dt", "frame_dt"):
            if not (getattr(self, name) > 0 and math.isfinite(getattr(self, name))):
                raise InputError(_SOURCE, name, f"must be finite and > 0, got {getattr(self, name)}")
        if int(self.n_frames) < 3:
            raise InputError(_SOURCE, "n_frames", f"must be >= 3, got {self.n_frames}")
        if not (self.impulse_velocity > 0 and math.isfinite(self.impulse_velocity)):
            raise InputError(_SOURCE, "impulse_velocity", f"must be finite and > 0 [m/s], got {self.impulse_velocity}")

    @classmethod
    def from_config(cls, block: Mapping) -> "VerificationSettings":
        """Settings from the config's ``verification`` block (workflow-only keys ignored)."""
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in block.items() if k in names})

    @property
    def times(self) -> np.ndarray:
        return np.arange(int(self.n_frames)) * float(self.frame_dt)


def _p_wave_speed() -> float:
    mu, lam = lame(MATERIAL["E"], MATERIAL["nu"])
    return math.sqrt((lam + 2.0 * mu) / MATERIAL["rho"])


def block_particles(n_grid: int, particles_per_axis: int = 2) -> np.ndarray:
    """Particle rest positions [m] (n, 3): ``particles_per_axis^3`` per grid cell of the block,
    on a lattice at the cell's sub-cell centres."""
    dx = GRID_LIM / n_grid
    lo, hi = np.asarray(BLOCK[0]), np.asarray(BLOCK[1])
    cells = np.round((hi - lo) / dx).astype(int)
    idx = np.stack(np.meshgrid(*[np.arange(c) for c in cells], indexing="ij"), -1).reshape(-1, 3)
    s = (np.arange(particles_per_axis) + 0.5) / particles_per_axis
    sub = np.stack(np.meshgrid(s, s, s, indexing="ij"), -1).reshape(-1, 3)
    return (lo + (idx[:, None, :] + sub[None]) * dx).reshape(-1, 3)


def mpm_dt(n_grid: int, settings: VerificationSettings) -> float:
    """The MPM substep [s]: the largest ``frame_dt / k`` with ``c_p dt / dx <= cfl``."""
    dt_max = settings.cfl * (GRID_LIM / n_grid) / _p_wave_speed()
    return settings.frame_dt / math.ceil(settings.frame_dt / dt_max - 1e-9)


def mpm_block_rollout(n_grid: int, settings: VerificationSettings, *, device: str | None = None,
                      deterministic: bool = False, solver_options: Mapping | None = None,
                      storage: Mapping | None = None) -> dict:
    """One MPM rollout of the block at ``n_grid``: ``x0`` rest positions [m] (n, 3), ``u``
    displacements [m] (frames, n, 3), ``dt`` [s], ``cpu_s`` CPU seconds of the rollout, and
    the probe's total impulse [N s] as the simulator accounts it (``impulse``).
    ``deterministic``, ``solver_options`` (:func:`~knockgs_core.sim.simulate_many`'s) and
    ``storage`` (:func:`~knockgs_core.sim.build_model`'s ``matrix_layout`` and ``deformation_storage``):
    the substep's choices where not the device's, e.g. a GPU's replayed on the CPU
    (:data:`~knockgs_core.sim.GPU_SOLVER_OPTIONS`, :data:`~knockgs_core.sim.GPU_STORAGE`)."""
    cpu0 = time.process_time()
    model, x = mpm_block_model(n_grid, settings, device=device, storage=storage)
    state = make_state(model, x)
    out = simulate(model, state, frame_dt=settings.frame_dt, n_frames=settings.n_frames, deterministic=deterministic,
                   solver_options=solver_options)
    cpu = time.process_time() - cpu0
    u = out.positions.astype(np.float64) - x[None].astype(np.float32).astype(np.float64)
    return {"x0": x, "u": u, "dt": model.params.dt, "cpu_s": cpu, "impulse": float(model.probe_impulse[0])}


def mpm_block_model(n_grid: int, settings: VerificationSettings, *, device: str | None = None,
                    storage: Mapping | None = None, knocked: Region | None = None, transfer: str | None = None):
    """The MPM model of the knocked block at ``n_grid`` (substep :func:`mpm_dt`, the probe's
    impulse ``settings.impulse_velocity`` per unit mass, the support held) and its particles'
    rest positions [m] (n, 3); ``storage`` as in :func:`mpm_block_rollout`. ``knocked``: the
    part of the block the probe selects (None: all of it); ``transfer``: the simulator's
    particle-grid transfer (None: its default)."""
    x = block_particles(n_grid, settings.particles_per_axis)
    dx = GRID_LIM / n_grid
    m_p = MATERIAL["rho"] * dx**3 / settings.particles_per_axis**3
    box = None if knocked is None else Box(center=tuple((np.asarray(knocked.lo) + np.asarray(knocked.hi)) / 2),
                                           half_size=tuple((np.asarray(knocked.hi) - np.asarray(knocked.lo)) / 2 + 1e-6))
    probe = Probe("verification", force=(m_p * settings.impulse_velocity / PROBE_DURATION, 0.0, 0.0), box=box,
                  n_steps=1, dt_ref=PROBE_DURATION)
    params = SimParams(n_grid=n_grid, grid_lim=GRID_LIM, dt=mpm_dt(n_grid, settings), boundaries=(FixedCuboid(SUPPORT),),
                       **({} if transfer is None else {"transfer": transfer}))
    return build_model(x, **MATERIAL, params=params, probe=probe, device=device, **_storage(storage)), x


def _storage(storage: Mapping | None) -> dict:
    """``storage`` checked as :func:`~knockgs_core.sim.build_model`'s storage keywords."""
    storage = dict(storage or {})
    for key in storage:
        if key not in ("matrix_layout", "deformation_storage"):
            raise InputError(_SOURCE, "storage", f"unknown key {key!r}; takes matrix_layout and deformation_storage")
    return storage


def fem_block_reference(settings: VerificationSettings, *, cells: int | None = None, degree: int | None = None,
                        knocked: Region | None = None) -> dict:
    """The FEM response of the block: ``system`` (assembled), ``result`` (Newmark frames),
    ``cpu_s`` (assembly and integration), ``impulse`` [N s] the pulse delivers (the load's
    x sum times the duration; the whole block's). ``cells`` per 0.5 m and ``degree`` default to
    the settings'; ``knocked``: the part of the block the pulse acts on (None: all of it)."""
    cells = int(settings.fem_cells if cells is None else cells)
    degree = int(settings.fem_degree if degree is None else degree)
    cpu0 = time.process_time()
    (x0, y0, z0), (x1, y1, z1) = BLOCK
    per_m = cells / 0.5
    axis = lambda a, b: np.linspace(a, b, max(1, round((b - a) * per_m)) + 1)  # noqa: E731
    zs = np.concatenate([[z0], axis(SUPPORT_TOP, z1)])  # one element layer in the held part
    system = assemble_elasticity(tensor_mesh(axis(x0, x1), axis(y0, y1), zs), **MATERIAL, degree=degree)
    fixed = support_dofs(system, Region.from_center(SUPPORT.center, SUPPORT.half_size))
    density = MATERIAL["rho"] * settings.impulse_velocity / PROBE_DURATION
    pulse = ForcePulse((density, 0.0, 0.0), PROBE_DURATION, region=knocked)
    result = newmark(system, dt=settings.fem_dt, frame_dt=settings.frame_dt, n_frames=settings.n_frames,
                     fixed=fixed, pulses=[pulse])
    impulse = density * system.volume * PROBE_DURATION
    return {"system": system, "result": result, "cpu_s": time.process_time() - cpu0, "impulse": impulse,
            "cells": cells, "degree": degree, "h": 0.5 / cells}


def first_mode_period(times: np.ndarray, signal: np.ndarray) -> float:
    """Period [s] of the dominant oscillation of ``signal`` (frames,) sampled at ``times`` [s]:
    the angular frequency whose least-squares fit ``a sin(w t) + b cos(w t) + c`` leaves the
    smallest residual, scanned from a quarter cycle over the record to the Nyquist rate and
    refined by a bounded scalar search. At least about one cycle must be recorded."""
    t = np.asarray(times, dtype=np.float64)
    s = np.asarray(signal, dtype=np.float64)
    if t.shape != s.shape or t.ndim != 1 or len(t) < 3:
        raise InputError("first_mode_period", "signal",
                         f"need matching 1-D times and signal of >= 3 samples, got {t.shape}, {s.shape}")

    def residual(w: float) -> float:
        A = np.stack([np.sin(w * t), np.cos(w * t), np.ones_like(t)], axis=1)
        coef = np.linalg.lstsq(A, s, rcond=None)[0]
        return float(np.sum((A @ coef - s) ** 2))

    span = t[-1] - t[0]
    grid = np.linspace(2 * np.pi / (4 * span), np.pi / np.min(np.diff(t)), 4000)
    k = int(np.argmin([residual(w) for w in grid]))
    lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
    w = minimize_scalar(residual, bounds=(lo, hi), method="bounded", options={"xatol": 1e-12}).x
    return float(2 * np.pi / w)


def rms_curve(u: np.ndarray) -> np.ndarray:
    """RMS displacement ``sqrt(mean_p |u_p(t)|^2)`` [m] of displacements ``u`` (frames, n, 3)."""
    return np.sqrt(np.mean(np.sum(np.asarray(u, dtype=np.float64) ** 2, axis=-1), axis=1))


def response_gap(times: np.ndarray, u: np.ndarray, u_ref: np.ndarray) -> dict:
    """The gap between displacements ``u`` and a reference ``u_ref`` (frames, n, 3) [m] of the
    same points: RMS-curve error [% of the reference curve's L2 norm], first-mode periods [s]
    and their difference [%], peak RMS displacements [mm] and their difference [%], trajectory
    RMSE [mm] and [% of the reference's RMS displacement]."""
    u, u_ref = np.asarray(u, dtype=np.float64), np.asarray(u_ref, dtype=np.float64)
    if u.shape != u_ref.shape:
        raise InputError("response_gap", "u", f"shape {u.shape} differs from the reference's {u_ref.shape}")
    c, c_ref = rms_curve(u), rms_curve(u_ref)
    period = first_mode_period(times, u[:, :, 0].mean(axis=1))
    period_ref = first_mode_period(times, u_ref[:, :, 0].mean(axis=1))
    rmse = float(np.sqrt(np.mean(np.sum((u - u_ref) ** 2, axis=-1))))
    scale = float(np.sqrt(np.mean(np.sum(u_ref**2, axis=-1))))
    return {
        "rms_curve_error_pct": 100.0 * float(np.linalg.norm(c - c_ref) / np.linalg.norm(c_ref)),
        "period_s": period,
        "period_ref_s": period_ref,
        "period_error_pct": 100.0 * (period - period_ref) / period_ref,
        "peak_rms_mm": 1e3 * float(c.max()),
        "peak_rms_ref_mm": 1e3 * float(c_ref.max()),
        "peak_error_pct": 100.0 * float(c.max() - c_ref.max()) / float(c_ref.max()),
        "traj_rmse_mm": 1e3 * rmse,
        "traj_rmse_pct": 100.0 * rmse / scale,
    }


def _order(e_coarse: float, e_fine: float, h_coarse: float, h_fine: float) -> str:
    """Observed order ``log(e_coarse / e_fine) / log(h_coarse / h_fine)`` of two levels, as text
    with two decimals ("-" when an error is zero)."""
    if not (e_coarse > 0 and e_fine > 0):
        return "-"
    return f"{math.log(e_coarse / e_fine) / math.log(h_coarse / h_fine):.2f}"


def verification_study(settings: VerificationSettings, *, device: str | None = None, deterministic: bool = False,
                       log: Callable[[str], None] | None = None, solver_options: Mapping | None = None,
                       storage: Mapping | None = None) -> pd.DataFrame:
    """The verification table: one row per MPM level (coarsest first), then the FEM on a
    coarser mesh (3/4 of ``fem_cells``: the reference's own discretization change) and the
    reference itself, every row compared with the reference at the row's points (the MPM
    particles' rest positions; the FEM rows at the finest level's). Columns: ``model``,
    ``resolution`` (words), ``h_m`` (dx or mesh size), ``dt_s``, ``unknowns`` (particles or
    DOFs), the :func:`response_gap` columns, observed orders between successive MPM levels of
    the trajectory RMSE and of the period difference (text; ``-`` on the first level and the
    FEM rows) and ``cpu_s`` (CPU seconds of the rollout or of assembly plus integration).
    ``deterministic``, ``solver_options`` and ``storage``: the MPM substep's choices, as in
    :func:`mpm_block_rollout`."""
    say = log or (lambda msg: None)
    ref = fem_block_reference(settings)
    say(f"FEM reference: P{ref['degree']}, {ref['cells']} cells per 0.5 m, {ref['system'].n_dofs} DOFs, "
        f"{ref['result'].solver} solver, {ref['cpu_s']:.1f} s CPU")
    times = settings.times
    rows = []
    x_last = None
    for level, n_grid in enumerate(settings.n_grid):
        run = mpm_block_rollout(n_grid, settings, device=device, deterministic=deterministic,
                                solver_options=solver_options, storage=storage)
        if not math.isclose(run["impulse"], ref["impulse"], rel_tol=1e-5):
            raise RuntimeError(f"MPM impulse {run['impulse']:.6g} N s differs from the FEM's {ref['impulse']:.6g} N s")
        P = interpolation_matrix(ref["system"], run["x0"])
        n = len(run["x0"])
        u_ref = (P @ ref["result"].u.T).reshape(3, n, -1).transpose(2, 1, 0)
        gap = response_gap(times, run["u"], u_ref)
        rows.append({"model": "mpm", "resolution": f"n_grid {n_grid}, {settings.particles_per_axis ** 3} particles per cell",
                     "h_m": GRID_LIM / n_grid, "dt_s": run["dt"], "unknowns": n, **gap, "cpu_s": run["cpu_s"]})
        say(f"MPM n_grid {n_grid}: {n} particles, dt {run['dt']:.4g} s, {run['cpu_s']:.1f} s CPU; "
            f"period {gap['period_error_pct']:+.2f} %, trajectory RMSE {gap['traj_rmse_pct']:.2f} %")
        x_last = run["x0"]
    for k, row in enumerate(rows):
        prev = rows[k - 1] if k else None
        row["order_traj"] = _order(prev["traj_rmse_pct"], row["traj_rmse_pct"], prev["h_m"], row["h_m"]) if prev else "-"
        row["order_period"] = (_order(abs(prev["period_error_pct"]), abs(row["period_error_pct"]), prev["h_m"], row["h_m"])
                               if prev else "-")
    u_ref = _at(ref, x_last)
    coarse_cells = max(1, (3 * ref["cells"]) // 4)
    check = fem_block_reference(settings, cells=coarse_cells)
    for name, fem in (("fem (coarser mesh)", check), ("fem (reference)", ref)):
        gap = response_gap(times, _at(fem, x_last), u_ref)
        rows.append({"model": name, "resolution": f"P{fem['degree']}, {fem['cells']} cells per 0.5 m",
                     "h_m": fem["h"], "dt_s": settings.fem_dt, "unknowns": fem["system"].n_dofs, **gap,
                     "order_traj": "-", "order_period": "-", "cpu_s": fem["cpu_s"]})
    say(f"FEM coarser mesh ({coarse_cells} cells): period {rows[-2]['period_error_pct']:+.3f} %, "
        f"trajectory {rows[-2]['traj_rmse_pct']:.3f} % from the reference")
    columns = ["model", "resolution", "h_m", "dt_s", "unknowns", "rms_curve_error_pct", "period_s", "period_ref_s",
               "period_error_pct", "peak_rms_mm", "peak_rms_ref_mm", "peak_error_pct", "traj_rmse_mm", "traj_rmse_pct",
               "order_traj", "order_period", "cpu_s"]
    return pd.DataFrame(rows, columns=columns)


def _at(fem: dict, points: np.ndarray) -> np.ndarray:
    P = interpolation_matrix(fem["system"], points)
    n = len(points)
    return (P @ fem["result"].u.T).reshape(3, n, -1).transpose(2, 1, 0)


def verification_note(table: pd.DataFrame, settings: VerificationSettings) -> str:
    """The Markdown note under the table: the problem, the reference, what the columns mean."""
    mpm = table[table["model"] == "mpm"]
    ref = table[table["model"] == "fem (reference)"].iloc[0]
    check = table[table["model"] == "fem (coarser mesh)"].iloc[0]
    limit, own = mpm_period_limit(table), mpm_period_order(table)
    extrapolated = ("" if limit is None else
                    f" At first order, the MPM's two finest periods extrapolate to {limit:.4f} s, "
                    f"{100 * (limit / ref['period_ref_s'] - 1):+.2f} % from the reference's"
                    + ("" if own is None else f" (the observed order of its own three finest periods: {own:.2f})") + ".")
    return (
        f"Block 0.5 x 0.5 x 0.75 m held by its bottom 0.25 m (support box z <= 0.75), E = {MATERIAL['E']:g} Pa, "
        f"nu = {MATERIAL['nu']:g}, rho = {MATERIAL['rho']:g} kg/m^3, no gravity; at t = 0 a {PROBE_DURATION:g} s pulse "
        f"gives every part of the block {settings.impulse_velocity:g} m/s along x. {settings.n_frames} frames every "
        f"{settings.frame_dt:g} s. MPM: affine-FLIP, {settings.particles_per_axis ** 3} particles per cell, "
        f"c_p dt / dx <= {settings.cfl:g}. Reference: Newmark average acceleration (dt = {settings.fem_dt:g} s) on "
        f"{ref['resolution']} ({int(ref['unknowns'])} DOFs, consistent mass), first-mode period {ref['period_ref_s']:.4f} s, "
        f"peak RMS displacement {ref['peak_rms_ref_mm']:.4f} mm; on the coarser mesh ({check['resolution']}) it moves by "
        f"{check['period_error_pct']:+.3f} % in period and {check['traj_rmse_pct']:.3f} % in trajectory. "
        f"Errors are the MPM's (or the coarser FEM's) against the reference at the same points (the particles' rest "
        f"positions): RMS-curve and trajectory RMSE relative to the reference's norms; orders between successive MPM "
        f"levels ({len(mpm)} levels, dx refined with dt)." + extrapolated
    )


def _three_level_order(h: Sequence[float], values: Sequence[float]) -> float | None:
    """Observed order ``p`` of three levels (step sizes ``h1 > h2 > h3``, values ``f1, f2, f3``):
    solves ``(h1^p - h2^p) / (h2^p - h3^p) = (f1 - f2) / (f2 - f3)`` on ``(0, 20]`` by bisection;
    ``None`` when the changes do not shrink monotonically as a positive order predicts."""
    d12, d23 = values[0] - values[1], values[1] - values[2]
    if d12 == 0 or d23 == 0 or (d12 > 0) != (d23 > 0):
        return None
    target = d12 / d23
    ratio = lambda p: (h[0] ** p - h[1] ** p) / (h[1] ** p - h[2] ** p)  # noqa: E731
    lo, hi = 1e-9, 20.0
    if not (ratio(lo) < target <= ratio(hi)):
        return None
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if ratio(mid) < target else (lo, mid)
    return 0.5 * (lo + hi)


def mpm_period_limit(table: pd.DataFrame, *, order: float = 1.0) -> float | None:
    """Richardson extrapolation of the MPM's first-mode period [s] from its two finest levels,
    the MPM's own data only, at the given ``order`` (default first, the order the gaps show):
    ``T2 + (T2 - T1) / ((h1 / h2)^order - 1)``; ``None`` with fewer than two levels."""
    mpm = table[table["model"] == "mpm"]
    if len(mpm) < 2:
        return None
    (h1, h2), (T1, T2) = [float(v) for v in mpm["h_m"].iloc[-2:]], [float(v) for v in mpm["period_s"].iloc[-2:]]
    return T2 + (T2 - T1) / ((h1 / h2) ** order - 1)


def mpm_period_order(table: pd.DataFrame) -> float | None:
    """Observed order of the MPM's own period changes over its three finest levels (``None``
    with fewer levels or changes that do not shrink as a positive order predicts)."""
    mpm = table[table["model"] == "mpm"]
    if len(mpm) < 3:
        return None
    return _three_level_order([float(v) for v in mpm["h_m"].iloc[-3:]], [float(v) for v in mpm["period_s"].iloc[-3:]])
