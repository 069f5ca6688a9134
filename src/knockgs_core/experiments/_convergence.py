"""Discretization error of the Probe-A response: a three-level convergence study per object.

One object, one fixed ``theta`` (by default the library's stiffest, lightest candidate, the
fastest response), its calibration probe (Probe A), and two refinements of the contract's
resolution profile:

- time: ``dt -> dt/2 -> dt/4`` at the profile's grid;
- space: ``n_grid -> 1.5 n_grid -> 2 n_grid`` with the same particle set (positions, rest
  volumes, Gaussian-associated and fill particles fixed), every level at one substep that
  satisfies the CFL bound of the finest grid (and is never longer than the profile's), so
  the time error does not change between the space levels.

The quantity is the displacement trajectory ``u = x(t) - x(0)`` of the Gaussian-associated
particles at every exported frame, shape (frames, n_gs, 3) [m]. For levels 1 (coarsest, the
profile's setting), 2, 3 (finest) with step sizes ``h1 > h2 > h3`` (``dt``, or ``dx =
grid_lim / n_grid``):

- ``change_1_2 = ||u1 - u2|| / ||u3||`` and ``change_2_3 = ||u2 - u3|| / ||u3||`` (relative L2
  norm over frames, particles and axes: a fraction of the RMS displacement);
- the observed order ``p`` solving ``(h1^p - h2^p) / (h2^p - h3^p) = change_1_2 / change_2_3``
  (``p = log2(change_1_2 / change_2_3)`` for a constant ratio 2), :func:`observed_order`;
- the Richardson-extrapolated limit ``u* = u3 + (u3 - u2) / ((h2 / h3)^p - 1)`` and the error
  of the profile's setting ``100 ||u1 - u*|| / ||u*||`` [%].

When the changes do not decrease as a positive order predicts (no asymptotic range), the
order and the Richardson error are the text :data:`NOT_ASYMPTOTIC` instead of a number.
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Callable, Literal, Sequence

import numpy as np
import pandas as pd

from ..errors import InputError
from ..reporting import save_figure

__all__ = [
    "NOT_ASYMPTOTIC",
    "REFINEMENTS",
    "SPACE_FACTORS",
    "TIME_FACTORS",
    "observed_order",
    "relative_change",
    "richardson_limit",
    "convergence_levels",
    "convergence_study",
    "convergence_note",
    "plot_convergence",
]

NOT_ASYMPTOTIC = "not in the asymptotic range"
REFINEMENTS: tuple[str, ...] = ("dt", "n_grid")
TIME_FACTORS = (1.0, 0.5, 0.25)      # dt multipliers, coarsest first
SPACE_FACTORS = (1.0, 1.5, 2.0)      # n_grid multipliers, coarsest first
P_MAX = 20.0                         # orders above this are not resolved (treated as no asymptotic range)

Refinement = Literal["dt", "n_grid"]


# --------------------------------------------------------------------------- order and extrapolation

def _order_ratio(p: float, h: Sequence[float]) -> float:
    """``(h1^p - h2^p) / (h2^p - h3^p)``; its limit ``ln(h1/h2) / ln(h2/h3)`` at p = 0."""
    h1, h2, h3 = h
    if p == 0.0:
        return math.log(h1 / h2) / math.log(h2 / h3)
    return (h1**p - h2**p) / (h2**p - h3**p)


def observed_order(h: Sequence[float], change_12: float, change_23: float, *, p_max: float = P_MAX) -> float | None:
    """Observed order ``p`` of three levels with step sizes ``h = (h1, h2, h3)``, ``h1 > h2 > h3 > 0``.

    Solves ``(h1^p - h2^p) / (h2^p - h3^p) = change_12 / change_23`` for ``p`` in ``(0, p_max]``
    (the model ``u_h = u* + C h^p``); for ``h1 / h2 = h2 / h3 = r`` this is
    ``log(change_12 / change_23) / log(r)``. Returns ``None`` when no such ``p`` exists: the
    changes do not decrease fast enough for a positive order (e.g. ``change_23 >= change_12``
    at a constant ratio), a zero change, or an order above ``p_max``.

    Raises ``ValueError`` for step sizes that are not positive, finite and strictly
    decreasing, or for negative or non-finite changes.
    """
    h = tuple(float(v) for v in h)
    if len(h) != 3 or not all(math.isfinite(v) and v > 0 for v in h) or not (h[0] > h[1] > h[2]):
        raise ValueError(f"step sizes must be three positive, finite, strictly decreasing values, got {h}")
    d12, d23 = float(change_12), float(change_23)
    if not (math.isfinite(d12) and math.isfinite(d23) and d12 >= 0 and d23 >= 0):
        raise ValueError(f"changes must be finite and >= 0, got ({change_12}, {change_23})")
    if d12 == 0.0 or d23 == 0.0:
        return None
    target = d12 / d23
    # the ratio grows monotonically with p (from ln(h1/h2)/ln(h2/h3) at p = 0): bracket, then bisect
    lo, hi = 0.0, float(p_max)
    if not (_order_ratio(lo, h) < target <= _order_ratio(hi, h)):
        return None
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if _order_ratio(mid, h) < target:
            lo = mid
        else:
            hi = mid
        if hi - lo < 1e-13:
            break
    return 0.5 * (lo + hi)


def relative_change(a: np.ndarray, b: np.ndarray, *, reference: np.ndarray) -> float:
    """``||a - b|| / ||reference||`` over all entries (float64): displacement trajectories
    ``(frames, particles, 3)`` [m] in, a dimensionless fraction out."""
    a, b, r = (np.asarray(v, dtype=np.float64) for v in (a, b, reference))
    if a.shape != b.shape or a.shape != r.shape:
        raise ValueError(f"trajectory shapes differ: {a.shape}, {b.shape}, {r.shape}")
    norm = float(np.linalg.norm(r))
    if not norm > 0:
        raise ValueError("the reference displacement is zero: the probe does not move the object")
    return float(np.linalg.norm(a - b)) / norm


def richardson_limit(u2: np.ndarray, u3: np.ndarray, *, h2: float, h3: float, p: float) -> np.ndarray:
    """Richardson extrapolation of the two finest levels: ``u3 + (u3 - u2) / ((h2 / h3)^p - 1)``
    (same shape as ``u2``, ``u3``; float64)."""
    u2, u3 = np.asarray(u2, dtype=np.float64), np.asarray(u3, dtype=np.float64)
    return u3 + (u3 - u2) / ((h2 / h3) ** p - 1.0)


# --------------------------------------------------------------------------- levels

def _space_dt(contract, n_grid_finest: int, frame_dt: float) -> float:
    """Largest frame-commensurate substep within the finest grid's CFL bound, and never
    longer than the profile's substep."""
    from ..contract import cfl_dt

    dt = cfl_dt(contract.materials, n_grid=n_grid_finest, grid_lim=contract.sim.grid_lim, frame_dts=[frame_dt])
    return min(float(contract.sim.dt), dt)


def convergence_levels(contract, *, frame_dt: float) -> dict[str, list[dict]]:
    """The simulator settings of each refinement's three levels, coarsest first:
    ``{"dt": [{"dt": .., "n_grid": ..}, ...], "n_grid": [...]}`` (``frame_dt`` [s]: the probe's
    export interval, which every substep divides)."""
    dt0, n0 = float(contract.sim.dt), int(contract.sim.n_grid)
    grids = [int(round(n0 * f)) for f in SPACE_FACTORS]
    dt_space = _space_dt(contract, grids[-1], frame_dt)
    return {
        "dt": [{"dt": dt0 * f, "n_grid": n0} for f in TIME_FACTORS],
        "n_grid": [{"dt": dt_space, "n_grid": n} for n in grids],
    }


def _step_size(refinement: str, level: dict, grid_lim: float) -> float:
    return level["dt"] if refinement == "dt" else grid_lim / level["n_grid"]


# --------------------------------------------------------------------------- the study

def _fixed_volumes(contract, particles):
    """The particle set with its rest volumes frozen at the profile's grid (the simulator would
    otherwise derive them from the particles per cell of each grid: another body per level)."""
    if particles.volumes is not None:
        return particles
    from ..sim import particle_volumes

    return dataclasses.replace(particles, volumes=particle_volumes(particles.positions, contract.sim.dx))


def convergence_study(
    contract,
    particles,
    *,
    theta: tuple[float, float],
    n_frames: int | None = None,
    refinements: Sequence[Refinement] = REFINEMENTS,
    device: str | None = None,
    log: Callable[[str], None] | None = None,
) -> pd.DataFrame:
    """Three-level time and space convergence of the Probe-A response of one object.

    ``contract``: an object contract at its resolution profile (level 1 of both refinements
    is its setting, the space study at the space substep); ``particles``: its particle set
    (a :class:`~knockgs_core.assets.ParticleSet`, fixed for every level); ``theta = (s_E,
    s_rho)``; ``n_frames``: the first exported frames used (``None``: all of the probe's).
    Returns one row per refinement: ``object, profile, s_E, s_rho, refinement, level_1..3``
    (dt [s] or n_grid), ``dt`` (the substep of the space levels; the profile's for the time
    study), ``n_grid`` (the grid of the time levels), ``n_frames``, ``rms_displacement_m``
    (finest level), ``change_1_2``, ``change_2_3`` (fractions of the finest level's RMS
    displacement), ``observed_order``, ``richardson_error_pct`` (numbers, or
    :data:`NOT_ASYMPTOTIC`), ``asymptotic`` (bool), ``cost_s_1..3`` (CPU seconds of each
    level's rollout).
    """
    from ..rollout import run_rollout
    from ..sim import ExportSchedule

    unknown = [r for r in refinements if r not in REFINEMENTS]
    if unknown or not refinements:
        raise ValueError(f"refinements must be a non-empty subset of {REFINEMENTS}, got {list(refinements)}")
    probe_name = contract.roles["calibration"]
    probe = contract.resolve_probes(particles)[probe_name]
    total = probe.export.n_frames
    if n_frames is None:
        n_frames = total
    if not (isinstance(n_frames, (int, np.integer)) and 2 <= n_frames <= total):
        raise InputError(f"object {contract.name}", "convergence.n_frames",
                         f"must be an integer in [2, {total}] (the probe's exported frames), got {n_frames!r}")
    probe = dataclasses.replace(probe, export=ExportSchedule(probe.export.frame_dt, int(n_frames)))
    particles = _fixed_volumes(contract, particles)
    n_gs = int(particles.n_gs)
    say = log or (lambda _msg: None)

    cache: dict[tuple[float, int], tuple[np.ndarray, float]] = {}

    def simulate(level: dict) -> tuple[np.ndarray, float]:
        key = (float(level["dt"]), int(level["n_grid"]))
        if key not in cache:
            t0 = time.process_time()
            ro = run_rollout(contract, theta, probe_name, particles=particles, probe=probe, device=device,
                             sim_overrides={"dt": key[0], "n_grid": key[1]})
            cost = time.process_time() - t0
            x = np.asarray(ro.positions[:, :n_gs], dtype=np.float64)
            cache[key] = (x - x[0], cost)
            say(f"{contract.name}: dt {key[0]:.10g} s, n_grid {key[1]}: {ro.meta['stats'].get('steps', '?')} substeps, "
                f"{cost:.2f} CPU s")
        return cache[key]

    levels = convergence_levels(contract, frame_dt=probe.export.frame_dt)
    rows = []
    for refinement in refinements:
        lv = levels[refinement]
        runs = [simulate(level) for level in lv]
        u1, u2, u3 = (r[0] for r in runs)
        h = [_step_size(refinement, level, contract.sim.grid_lim) for level in lv]
        d12 = relative_change(u1, u2, reference=u3)
        d23 = relative_change(u2, u3, reference=u3)
        p = observed_order(h, d12, d23)
        if p is None:
            order, rich = NOT_ASYMPTOTIC, NOT_ASYMPTOTIC
        else:
            limit = richardson_limit(u2, u3, h2=h[1], h3=h[2], p=p)
            # 8 significant digits, as write_table prints floats (these cells may hold text, so it cannot)
            order, rich = float(f"{p:.8g}"), float(f"{100.0 * relative_change(u1, limit, reference=limit):.8g}")
        key = "dt" if refinement == "dt" else "n_grid"
        rows.append({
            "object": contract.name,
            "profile": contract.profile,
            "s_E": float(theta[0]),
            "s_rho": float(theta[1]),
            "refinement": refinement,
            **{f"level_{k + 1}": level[key] for k, level in enumerate(lv)},
            "dt": lv[0]["dt"],
            "n_grid": lv[0]["n_grid"],
            "n_frames": int(n_frames),
            "rms_displacement_m": float(np.sqrt(np.mean(np.sum(u3**2, axis=-1)))),
            "change_1_2": d12,
            "change_2_3": d23,
            "observed_order": order,
            "richardson_error_pct": rich,
            "asymptotic": p is not None,
            **{f"cost_s_{k + 1}": r[1] for k, r in enumerate(runs)},
        })
    return pd.DataFrame(rows)


def convergence_note(table: pd.DataFrame) -> str:
    """The table note of a :func:`convergence_study` table: what was varied, what was held
    fixed and how the columns are computed."""
    first = table.iloc[0]
    parts = [
        f"Profile `{first['profile']}`, theta = ({first['s_E']:g}, {first['s_rho']:g}), Probe A, first "
        f"{int(first['n_frames'])} exported frames; displacement trajectories of the Gaussian-associated particles.",
        "change_i_j: relative L2 norm of the trajectory change between levels i and j, as a fraction of the finest "
        "level's RMS displacement; observed_order solves (h1^p - h2^p) / (h2^p - h3^p) = change_1_2 / change_2_3 "
        "(h = dt, or dx = grid_lim / n_grid); richardson_error_pct: error of level 1 (the profile's setting) against "
        f"the Richardson-extrapolated limit, in % of its RMS displacement; '{NOT_ASYMPTOTIC}' where the changes do not "
        "decrease as a positive order predicts; cost_s_k: CPU seconds of level k's rollout.",
    ]
    space = table[table["refinement"] == "n_grid"]
    if len(space):
        row = space.iloc[0]
        parts.append(
            f"Space levels: the same particles (positions and rest volumes fixed) on grids {int(row['level_1'])}, "
            f"{int(row['level_2'])}, {int(row['level_3'])}, all at dt = {row['dt']:.6g} s, within the CFL bound of the "
            "finest grid, so the time error does not change between them (level 1 of the space study is the profile's "
            "grid at that dt, not the profile's dt).")
    return " ".join(parts)


# --------------------------------------------------------------------------- figure

def plot_convergence(table: pd.DataFrame, path, *, grid_lim: float = 2.0, title: str = "") -> None:
    """Log-log figure of a :func:`convergence_study` table: per refinement, the change
    between successive levels against the coarser level's step size (dt [s] or dx [m]), the
    Richardson error of each level against the extrapolated limit when in the asymptotic range,
    and a line of the observed slope."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(table), figsize=(5.2 * len(table), 4.0), squeeze=False)
    for ax, row in zip(axes[0], table.itertuples(index=False)):
        levels = np.array([row.level_1, row.level_2, row.level_3], dtype=np.float64)
        h = levels if row.refinement == "dt" else grid_lim / levels
        changes = np.array([row.change_1_2, row.change_2_3])
        ax.loglog(h[:2], 100 * changes, "o-", color="tab:blue", label="change to the next level")
        if bool(row.asymptotic):
            p = float(row.observed_order)
            r12, r23 = h[0] / h[1], h[1] / h[2]
            # error of each level against the limit, from the model C h^p fitted to the two changes
            c = changes[1] / (h[1] ** p - h[2] ** p)
            err = 100 * c * h**p
            ax.loglog(h, err, "s--", mfc="none", color="tab:red", label="estimated error (Richardson)")
            ax.set_title(f"{row.refinement}: observed order p = {p:.2f} (ratios {r12:.3g}, {r23:.3g})", fontsize=9)
        else:
            ax.set_title(f"{row.refinement}: {NOT_ASYMPTOTIC}", fontsize=9)
        ax.set_xlabel("dt [s]" if row.refinement == "dt" else "dx [m]")
        ax.set_ylabel("% of the RMS displacement")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    save_figure(fig, path, dpi=120)
    plt.close(fig)
