"""Discretization error of the Probe-A response: a three-level convergence study per object.

One object, one fixed ``theta`` (by default the library's stiffest, lightest candidate, the
fastest response), its calibration probe (Probe A), and three refinements of the contract's
resolution profile (:data:`REFINEMENTS`):

- ``dt``, time: ``dt -> dt/2 -> dt/4`` at the profile's grid, the same particles;
- ``n_grid``, grid with the particles fixed: ``n_grid -> 1.5 n_grid -> 2 n_grid`` with the same
  particle set (positions, rest volumes, Gaussian-associated and fill particles fixed). This is
  the boundary study's "grid resolution changed" condition, not a discretization-error
  estimate: the particles per cell fall with the grid (to about one per cell at 2x), so the
  changes measure the particle sampling thinning out and are not expected to decrease;
- ``n_grid+fill``, grid and fill together: ``n_grid`` and the fill resolution both scaled by
  1.5 and 2, the Gaussian-associated particles fixed and the interior fill rebuilt for each grid
  by the asset build (:func:`~knockgs_core.assets.build_asset`) with the same specification per
  cell (density threshold, particles per cell, seed); rest volumes ``dx^3 / (particles in the
  cell)`` at each level's grid. The particles per cell stay as the profile's, so this is the
  spatial discretization error. Defined only for objects with an interior fill (without one,
  the particles are the Gaussians, which no level may change).

Both space refinements run every level at one substep that satisfies the CFL bound of the
finest grid (and is never longer than the profile's), so the time error does not change
between the space levels; their level 1 is the profile's grid and particles at that substep
(one rollout shared by the two).

The quantity is the displacement trajectory ``u = x(t) - x(0)`` of the Gaussian-associated
particles at every exported frame, shape (frames, n_gs, 3) [m]: the same particles at every
level of every refinement. For levels 1 (coarsest, the
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
    "FIXED",
    "REFINEMENTS",
    "SPACE_FACTORS",
    "TIME_FACTORS",
    "observed_order",
    "relative_change",
    "richardson_limit",
    "convergence_levels",
    "particles_per_cell",
    "refined_particles",
    "convergence_study",
    "convergence_note",
    "plot_convergence",
]

NOT_ASYMPTOTIC = "not in the asymptotic range"
REFINEMENTS: tuple[str, ...] = ("dt", "n_grid", "n_grid+fill")
TIME_FACTORS = (1.0, 0.5, 0.25)      # dt multipliers, coarsest first
SPACE_FACTORS = (1.0, 1.5, 2.0)      # n_grid multipliers, coarsest first
P_MAX = 20.0                         # orders above this are not resolved (treated as no asymptotic range)

Refinement = Literal["dt", "n_grid", "n_grid+fill"]
#: what each refinement holds fixed (the table's ``fixed`` column)
FIXED: dict[str, str] = {
    "dt": "n_grid; particles (positions, rest volumes)",
    "n_grid": "particles (positions, rest volumes); dt",
    "n_grid+fill": "Gaussian-associated particles; fill specification per cell; dt",
}


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
    ``{"dt": [{"dt": .., "n_grid": .., "fill_resolution": None}, ...], "n_grid": [...],
    "n_grid+fill": [...]}`` (``frame_dt`` [s]: the probe's export interval, which every substep
    divides). ``fill_resolution`` is ``None`` where the profile's particles are used unchanged,
    else the fill cells per axis the level's particles are rebuilt with (the profile's, scaled as
    ``n_grid``); ``"n_grid+fill"`` is present only when the contract has an interior fill."""
    dt0, n0 = float(contract.sim.dt), int(contract.sim.n_grid)
    grids = [int(round(n0 * f)) for f in SPACE_FACTORS]
    dt_space = _space_dt(contract, grids[-1], frame_dt)
    levels = {
        "dt": [{"dt": dt0 * f, "n_grid": n0, "fill_resolution": None} for f in TIME_FACTORS],
        "n_grid": [{"dt": dt_space, "n_grid": n, "fill_resolution": None} for n in grids],
    }
    if contract.fill.enabled:
        r0 = int(contract.fill.resolution)
        # level 1 is the profile's own particle set (the same rollout as the n_grid study's level 1)
        levels["n_grid+fill"] = [{"dt": dt_space, "n_grid": n, "fill_resolution": None if f == 1.0 else int(round(r0 * f))}
                                 for n, f in zip(grids, SPACE_FACTORS)]
    return levels


def _step_size(refinement: str, level: dict, grid_lim: float) -> float:
    return level["dt"] if refinement == "dt" else grid_lim / level["n_grid"]


def particles_per_cell(positions: np.ndarray, *, dx: float) -> float:
    """Mean particles per occupied grid cell of ``positions`` [m], shape (particle_count, 3), on a
    grid of spacing ``dx`` [m]: how densely the particles sample the grid."""
    cells = np.floor(np.asarray(positions, dtype=np.float64) / float(dx)).astype(np.int64)
    return len(cells) / len(np.unique(cells, axis=0))


def refined_particles(contract, particles, *, n_grid: int, fill_resolution: int):
    """The particle set of an ``n_grid+fill`` level: the contract's asset rebuilt with the fill
    at ``fill_resolution`` cells per axis (same box, density threshold, particles per cell and
    seed) and rest volumes at the grid ``n_grid`` (``dx^3 / (particles in the cell)``); returns
    ``(contract variant, ParticleSet)``. The Gaussian-associated particles (the first ``n_gs``)
    must equal those of ``particles`` [m], shape (n_gs, 3): they are what the levels compare.
    """
    from ..assets import build_asset

    replace = dataclasses.replace
    variant = replace(contract, fill=replace(contract.fill, resolution=int(fill_resolution)),
                      sim=replace(contract.sim, n_grid=int(n_grid)))
    rebuilt = build_asset(variant).particles
    n_gs = int(particles.n_gs)
    if rebuilt.n_gs != n_gs or not np.array_equal(rebuilt.positions[:n_gs], np.asarray(particles.positions)[:n_gs]):
        raise InputError(f"object {contract.name}", "particles",
                         "the Gaussian-associated particles differ from the contract's asset build; the n_grid+fill "
                         "study rebuilds the fill around them and needs the particles of the same contract and profile")
    return variant, _fixed_volumes(variant, rebuilt)


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
    deterministic: bool = False,
    log: Callable[[str], None] | None = None,
) -> pd.DataFrame:
    """Three-level time and space convergence of the Probe-A response of one object.

    ``contract``: an object contract at its resolution profile (level 1 of every refinement
    is its setting, the space studies at the space substep); ``particles``: its particle set
    (a :class:`~knockgs_core.assets.ParticleSet`, the asset build of ``contract``: fixed for
    the ``dt`` and ``n_grid`` levels, its Gaussian-associated particles fixed for the
    ``n_grid+fill`` levels); ``theta = (s_E, s_rho)``; ``n_frames``: the first exported frames
    used (``None``: all of the probe's); ``refinements``: a subset of :data:`REFINEMENTS`
    (``n_grid+fill`` is skipped, with a log line, for an object without an interior fill);
    ``device``, ``deterministic``: every level's rollout's (:func:`knockgs_core.rollout.run_rollouts`).
    Returns one row per refinement: ``object, profile, s_E, s_rho, refinement, fixed`` (what the
    refinement holds fixed), ``level_1..3`` (dt [s] or n_grid), ``dt`` (the substep of the space
    levels; the profile's for the time study), ``n_grid`` (the grid of the time levels),
    ``n_frames``, ``particles_1..3`` (simulated particles of each level), ``particles_per_cell_1..3``
    (:func:`particles_per_cell` at each level's grid, 4 significant digits), ``rms_displacement_m``
    (finest level), ``change_1_2``, ``change_2_3`` (fractions of the finest level's RMS
    displacement), ``observed_order``, ``richardson_error_pct`` (numbers, or
    :data:`NOT_ASYMPTOTIC`), ``asymptotic`` (bool), ``cost_s_1..3`` (CPU seconds of each level's
    rollout; a level shared by two refinements is simulated once and its cost shown in both).
    """
    from ..rollout import run_rollout
    from ..sim import ExportSchedule

    unknown = [r for r in refinements if r not in REFINEMENTS]
    if unknown or not refinements or len(set(refinements)) != len(refinements):
        raise ValueError(f"refinements must be a non-empty subset of {REFINEMENTS} without repeats, got {list(refinements)}")
    probe_name = contract.roles["calibration"]
    probe = contract.resolve_probes(particles)[probe_name]
    total = probe.export.n_frames
    if n_frames is None:
        n_frames = total
    if not (isinstance(n_frames, (int, np.integer)) and 2 <= n_frames <= total):
        raise InputError(f"object {contract.name}", "convergence.n_frames",
                         f"must be an integer in [2, {total}] (the probe's exported frames), got {n_frames!r}")
    export = ExportSchedule(probe.export.frame_dt, int(n_frames))
    particles = _fixed_volumes(contract, particles)
    n_gs = int(particles.n_gs)
    say = log or (lambda _msg: None)

    cache: dict[tuple[float, int, int | None], tuple[np.ndarray, float, int, float]] = {}

    def simulate(level: dict) -> tuple[np.ndarray, float, int, float]:
        key = (float(level["dt"]), int(level["n_grid"]), level["fill_resolution"])
        if key not in cache:
            variant, ps = contract, particles
            if key[2] is not None:
                t0 = time.process_time()
                variant, ps = refined_particles(contract, particles, n_grid=key[1], fill_resolution=key[2])
                say(f"{contract.name}: fill rebuilt at {key[2]} cells per axis for n_grid {key[1]}: {ps.n_fill} fill "
                    f"particles, {time.process_time() - t0:.2f} CPU s")
            # the probe resolved against the level's particles (a matched total force stays matched)
            pr = dataclasses.replace(variant.resolve_probes(ps)[probe_name], export=export)
            t0 = time.process_time()
            ro = run_rollout(variant, theta, probe_name, particles=ps, probe=pr, device=device,
                             deterministic=deterministic, sim_overrides={"dt": key[0], "n_grid": key[1]})
            cost = time.process_time() - t0
            x = np.asarray(ro.positions[:, :n_gs], dtype=np.float64)
            cache[key] = (x - x[0], cost, len(ps.positions), particles_per_cell(ps.positions, dx=variant.sim.grid_lim / key[1]))
            fill = "" if key[2] is None else f", fill {key[2]}"
            say(f"{contract.name}: dt {key[0]:.10g} s, n_grid {key[1]}{fill}: {len(ps.positions)} particles, "
                f"{ro.meta['stats'].get('steps', '?')} substeps, {cost:.2f} CPU s")
        return cache[key]

    levels = convergence_levels(contract, frame_dt=export.frame_dt)
    rows = []
    for refinement in refinements:
        if refinement not in levels:
            say(f"{contract.name}: no interior fill, so no {refinement} study (the particles are the Gaussians)")
            continue
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
            "fixed": FIXED[refinement],
            **{f"level_{k + 1}": level[key] for k, level in enumerate(lv)},
            "dt": lv[0]["dt"],
            "n_grid": lv[0]["n_grid"],
            "n_frames": int(n_frames),
            **{f"particles_{k + 1}": r[2] for k, r in enumerate(runs)},
            **{f"particles_per_cell_{k + 1}": float(f"{r[3]:.4g}") for k, r in enumerate(runs)},
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
    rows = {r["refinement"]: r for _, r in table.iterrows()}
    if "dt" in rows:
        parts.append("Row dt: the time step refined at the profile's grid, the same particles.")
    for name in ("n_grid", "n_grid+fill"):
        if name in rows:
            row = rows[name]
            grids = f"grids {int(row['level_1'])}, {int(row['level_2'])}, {int(row['level_3'])}"
            break
    else:
        return " ".join(parts)
    if "n_grid" in rows:
        row = rows["n_grid"]
        parts.append(
            f"Row n_grid (particles fixed): the same {int(row['particles_1'])} particles (positions and rest volumes) on "
            f"{grids}: the boundary study's 'grid resolution changed' condition. It is not expected to converge: the "
            f"particles per occupied cell fall with the grid ({row['particles_per_cell_1']:.3g}, "
            f"{row['particles_per_cell_2']:.3g}, {row['particles_per_cell_3']:.3g}), so its changes measure the particle "
            "sampling thinning out, not the discretization error.")
    if "n_grid+fill" in rows:
        row = rows["n_grid+fill"]
        parts.append(
            f"Row n_grid+fill (grid and fill refined together): {grids} with the interior fill rebuilt for each by the "
            "asset build at the fill resolution scaled as the grid, the same specification per cell (density threshold, "
            "particles per cell, seed) and rest volumes at each level's grid (particles simulated: "
            f"{int(row['particles_1'])}, {int(row['particles_2'])}, {int(row['particles_3'])}; per occupied cell: "
            f"{row['particles_per_cell_1']:.3g}, {row['particles_per_cell_2']:.3g}, {row['particles_per_cell_3']:.3g}); "
            "the Gaussian-associated particles, which the changes compare, are the same at every level. This row is the "
            "spatial discretization error.")
    elif "n_grid" in rows:
        parts.append("No n_grid+fill row: the object has no interior fill (its particles are the Gaussians, which no "
                     "level may change).")
    parts.append(
        f"The space rows run every level at dt = {row['dt']:.6g} s, within the CFL bound of the finest grid, so the "
        "time error does not change between their levels (their level 1 is the profile's grid and particles at that dt, "
        "not the profile's dt).")
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
    labels = {"n_grid": "n_grid, particles fixed", "n_grid+fill": "n_grid + fill"}
    for ax, row in zip(axes[0], table.itertuples(index=False)):
        label = labels.get(row.refinement, row.refinement)
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
            ax.set_title(f"{label}: observed order p = {p:.2f} (ratios {r12:.3g}, {r23:.3g})", fontsize=9)
        else:
            ax.set_title(f"{label}: {NOT_ASYMPTOTIC}", fontsize=9)
        ax.set_xlabel("dt [s]" if row.refinement == "dt" else "dx [m]")
        ax.set_ylabel("% of the RMS displacement")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    save_figure(fig, path, dpi=120)
    plt.close(fig)
