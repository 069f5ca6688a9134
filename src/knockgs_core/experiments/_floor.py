"""Where the model-error floor lives: an object's MPM against the finite-element reference.

For one object contract, its calibration probe (Probe A) and one theta (the base material,
(1, 1)), the MPM is run at several resolutions and compared with the finite-element reference
(:func:`knockgs_core.fem.fem_world_rollout`) of the same object, supports and impulse:

- *MPM levels* (``FloorSettings.n_grid``): the contract with its grid at ``n_grid``, its
  interior fill resolution scaled by the same factor (the Gaussians unchanged, the fill rebuilt
  by the asset build) and the substep by the contracts' rule (the largest frame-commensurate dt
  at most ``0.3 dx / c_p`` at the stiffest candidate), :func:`at_resolution`.
- *The reference*: the object's particle set built at ``fem_n_grid`` (fill refined likewise)
  and voxelized on that grid, P2 tetrahedra, Newmark (``FemWorld(n_grid=fem_n_grid)``). Its
  mesh depends on ``fem_n_grid`` only, never on the MPM level judged, so the comparison is not
  circular. Its own discretization is shown by the same construction on the coarser
  ``fem_check_n_grid`` (the *check*: the particle set built there, voxelized there): the check's
  gap to the reference bounds what the reference itself still changes (body, geometry
  staircase and mesh together). The check's body is built at its own grid because a cell
  carries the volume of the particles in it: a particle set binned on a grid its fill was not
  built on gives each cell a sampling share of its fill cells (the Vasedeck's particles built at
  96 and binned at 64: cell shares of 0.7-1.9 inside the body, and a response 43 % from the
  same body built at 64).
- *Compared* at the Gaussian-associated particles' rest positions (the same points at every
  level; the FEM is evaluated there), displacements ``u = x(t) - x(0)`` [m]:
  the trajectory RMSE over the Probe-A record (the frames a calibration sees) as a percentage
  of the reference's RMS displacement; the first-mode period of the points' mean displacement
  along the probe's force (:func:`~knockgs_core.fem.first_mode_period`, least-squares sinusoid)
  over a record ``record_factor`` times as long (a Probe-A record of 0.6 s holds less than one
  period of the Pillow); observed orders between successive levels.
- *Calibrated theta*: the theta the MPM at that level needs to reproduce the reference's
  Probe-A trajectory, by least squares in ``(log s_E, log s_rho)``: ``fit_steps`` Gauss-Newton
  steps from the base material with forward-difference sensitivities (step ``fit_step`` in
  log theta; each step's three rollouts simulated together). It is the theta a calibration
  that matched the whole trajectory would return: not the library's local ridge, which sees
  the 5-D descriptor only.

``cells_through`` measures how many grid cells a body has across: for each occupied cell of
the particle set on the level's grid, the shortest of its three axis-aligned runs of occupied
cells through it; the median over the cells (1 for a shell one cell thick).
``enclosed_empty`` counts the level's grid cells that hold no particle and whose six axis rays
all meet occupied cells (a void inside the body: the fill's hollow layer, a shell's inside).

The body's mass is the particles' (their rest volumes x rho): under the contract's
``fill.volumes: cell_share`` the occupied cells x dx^3 x rho, under ``enclosed`` or ``wall`` the
volume the particle set carries, the same at every grid. The reference's voxel body then has
another volume than the particles' body; each of its cells carries the volume of the particles
in it (E and rho scaled by that volume over dx^3: :mod:`knockgs_core.fem._world`), so its mass
and the mass's distribution over the cells are the particles'. ``fem_scale`` reports the
particles' volume over the voxel body's (1 under ``cell_share``, where the reference is the voxel
body itself).
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Mapping

import numpy as np
import pandas as pd

from ..contract import at_resolution  # re-exported: the studies and benchmarks import it from here
from ..sim import body_volume  # re-exported, as at_resolution
from ..errors import InputError

__all__ = ["FloorSettings", "at_resolution", "band_components", "band_limited", "cells_through", "enclosed_empty_cells",
           "body_volume", "probe_period", "fit_theta", "floor_study", "floor_note", "plot_floor"]

_SOURCE = "config floor"


@dataclass(frozen=True)
class FloorSettings:
    """The floor study's settings (the config's ``floor`` block mirrors them).

    ``n_grid``: the MPM levels, increasing; ``fem_n_grid``: the grid the reference's body is
    voxelized and meshed on; ``fem_check_n_grid``: the coarser grid of the reference's own
    check (< ``fem_n_grid``); ``fem_degree``: 1 (P1) or 2 (P2) tetrahedra;
    ``fem_steps_per_frame``: Newmark steps per exported frame; ``fem_body``: the reference's
    body, ``voxel`` (the occupied cells) or ``level_set`` (the fill's surface, meshed to it:
    :class:`~knockgs_core.fem.FemWorld`); ``fem_body_resolution``: the fill grid a
    ``level_set`` body is measured on (None: each construction's own fill; a fixed, fine grid
    gives the reference and its check one body); ``record_factor``: the record
    simulated, in Probe-A records (for the period); ``fit_steps``: Gauss-Newton steps of the
    theta fit (0: no fit); ``fit_step``: the finite-difference step in log theta; ``band_hz``
    [Hz]: the slow band compared besides the whole record (``rmse_band_pct`` and, with a fit,
    the theta fitted in it: :func:`band_limited`); None: the whole record only."""

    n_grid: tuple[int, ...] = (32, 48, 64)
    fem_n_grid: int = 48
    fem_check_n_grid: int = 32
    fem_degree: int = 2
    fem_steps_per_frame: int = 2
    fem_body: str = "voxel"
    fem_body_resolution: int | None = None
    record_factor: int = 4
    fit_steps: int = 2
    fit_step: float = 0.05
    band_hz: float | None = None

    def __post_init__(self):
        object.__setattr__(self, "n_grid", tuple(int(n) for n in self.n_grid))
        if not self.n_grid or any(n < 8 for n in self.n_grid) or any(b <= a for a, b in zip(self.n_grid, self.n_grid[1:])):
            raise InputError(_SOURCE, "n_grid", f"need increasing levels >= 8, got {list(self.n_grid)}")
        if not (8 <= int(self.fem_check_n_grid) < int(self.fem_n_grid)):
            raise InputError(_SOURCE, "fem_check_n_grid",
                             f"must be >= 8 and below fem_n_grid ({self.fem_n_grid}), got {self.fem_check_n_grid}")
        from ..fem import BODIES

        if self.fem_body not in BODIES:
            raise InputError(_SOURCE, "fem_body", f"must be one of {', '.join(BODIES)}, got {self.fem_body!r}")
        if self.fem_degree not in (1, 2):
            raise InputError(_SOURCE, "fem_degree", f"must be 1 or 2, got {self.fem_degree}")
        for name in ("fem_steps_per_frame", "record_factor"):
            if int(getattr(self, name)) < 1:
                raise InputError(_SOURCE, name, f"must be >= 1, got {getattr(self, name)}")
        if int(self.fit_steps) < 0:
            raise InputError(_SOURCE, "fit_steps", f"must be >= 0, got {self.fit_steps}")
        if not (0 < self.fit_step < 1 and math.isfinite(self.fit_step)):
            raise InputError(_SOURCE, "fit_step", f"must lie in (0, 1), got {self.fit_step}")
        band = self.band_hz
        if band is not None and (isinstance(band, bool) or not isinstance(band, (int, float))
                                 or not (math.isfinite(band) and band > 0)):
            raise InputError(_SOURCE, "band_hz", f"must be a finite frequency > 0 [Hz] or null, got {self.band_hz}")

    @classmethod
    def from_config(cls, block: Mapping) -> "FloorSettings":
        """Settings from the config's ``floor`` block (workflow-only keys ignored)."""
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in block.items() if k in names})

    def world(self, n_grid: int, *, body: str):
        """The reference's :class:`~knockgs_core.fem.FemWorld` meshed on ``n_grid`` with
        ``body`` (:func:`reference_body`): this block's degree and steps a frame, and a
        ``level_set`` body measured on ``fem_body_resolution``."""
        from ..fem import FemWorld

        return FemWorld(degree=int(self.fem_degree), steps_per_frame=int(self.fem_steps_per_frame), n_grid=int(n_grid),
                        body=body, body_resolution=self.fem_body_resolution if body == "level_set" else None)


def _with_record(contract, probe: str, n_frames: int):
    """``contract`` with ``probe`` exporting ``n_frames`` frames at its frame interval."""
    pr = contract.probes[probe]
    longer = dataclasses.replace(pr, export=dataclasses.replace(pr.export, n_frames=int(n_frames)))
    return dataclasses.replace(contract, probes={**contract.probes, probe: longer})


def cells_through(positions: np.ndarray, dx: float) -> float:
    """Median over the cells occupied by ``positions`` [N, 3] (cell size ``dx`` [m]) of the
    shortest of the three axis-aligned runs of occupied cells through each cell [cells]."""
    idx = np.floor(np.asarray(positions, dtype=np.float64) / dx).astype(np.int64)
    cells = np.unique(idx, axis=0)
    lo = cells.min(axis=0)
    occ = np.zeros(tuple(cells.max(axis=0) - lo + 1), dtype=bool)
    occ[tuple((cells - lo).T)] = True
    runs = []
    for axis in range(3):
        o = np.moveaxis(occ, axis, -1)
        length = np.zeros(o.shape, dtype=np.int64)
        for k in range(o.shape[-1]):                                  # run lengths along the axis
            prev = length[..., k - 1] if k else 0
            length[..., k] = np.where(o[..., k], prev + 1, 0)
        full = length.copy()
        for k in range(o.shape[-1] - 2, -1, -1):                      # each cell gets its run's length
            full[..., k] = np.where(o[..., k] & o[..., k + 1], full[..., k + 1], full[..., k])
        runs.append(np.moveaxis(full, -1, axis)[occ])
    return float(np.median(np.min(np.stack(runs), axis=0)))


def enclosed_empty_cells(positions: np.ndarray, dx: float) -> int:
    """Cells of size ``dx`` [m] that hold none of ``positions`` [N, 3] m and whose six axis rays
    all meet a cell that holds one (the fill's six-ray test on the occupied cells) [cells]."""
    from ..assets import interior_cells

    idx = np.floor(np.asarray(positions, dtype=np.float64) / dx).astype(np.int64)
    lo = idx.min(axis=0)
    occ = np.zeros(tuple(idx.max(axis=0) - lo + 1), dtype=bool)
    occ[tuple((idx - lo).T)] = True
    return int(interior_cells(occ).sum())


def probe_period(times: np.ndarray, u: np.ndarray, direction) -> float:
    """First-mode period [s] of the mean displacement along ``direction`` (3,) of ``u``
    [T, P, 3] m sampled at ``times`` [T] s (:func:`~knockgs_core.fem.first_mode_period`)."""
    from ..fem import first_mode_period

    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    return first_mode_period(times, (np.asarray(u, dtype=np.float64) @ d).mean(axis=1))


def _rel(u: np.ndarray, ref: np.ndarray) -> float:
    """``100 ||u - ref|| / ||ref||`` [%] over frames, points and axes."""
    return 100.0 * float(np.linalg.norm(u - ref) / np.linalg.norm(ref))


def band_components(band_hz: float, frame_dt: float, n_frames: int) -> int:
    """How many of the slowest cosines of a record of ``n_frames`` frames ``frame_dt`` [s] apart
    lie at or below ``band_hz`` [Hz]: the orthonormal DCT-II's component ``k`` has the frequency
    ``k / (2 n_frames frame_dt)``, so ``floor(2 band_hz n_frames frame_dt) + 1``, at most
    ``n_frames``."""
    return int(min(int(n_frames), math.floor(2.0 * float(band_hz) * int(n_frames) * float(frame_dt) + 1e-9) + 1))


def band_limited(u: np.ndarray, components: int) -> np.ndarray:
    """``u`` [T, ...] (a record along its first axis) kept in its ``components`` slowest cosines:
    the orthonormal DCT-II along the record, the components from ``components`` on set to zero,
    transformed back (:func:`band_components` gives the count below a frequency). Orthonormal, so
    the band's RMS difference of two records is their difference's energy in those components,
    and all ``T`` components return ``u``."""
    from scipy.fft import dct, idct

    a = dct(np.asarray(u, dtype=np.float64), axis=0, norm="ortho")
    a[int(components):] = 0.0
    return idct(a, axis=0, norm="ortho")


def _band_columns(u: np.ndarray, ref: np.ndarray, band: int | None, fit: dict | None) -> dict:
    """A row's slow-band columns: the RMSE of ``u`` against ``ref`` [T, P, 3] in the band's ``band``
    slowest cosines (:func:`band_components`), and the band's theta fit (NaN where there is no band
    or no fit)."""
    nan = float("nan")
    if band is None:
        return {"rmse_band_pct": nan, "s_E_fit_band": nan, "s_rho_fit_band": nan, "fit_band_residual_pct": nan}
    return {"rmse_band_pct": _rel(band_limited(u, band), band_limited(ref, band)),
            "s_E_fit_band": float(fit["theta"][0]) if fit else nan, "s_rho_fit_band": float(fit["theta"][1]) if fit else nan,
            "fit_band_residual_pct": fit["residual_pct"] if fit else nan}


def fit_theta(simulate: Callable[[list], list], target: np.ndarray, *, start=(1.0, 1.0), steps: int = 2,
              step: float = 0.05, first: np.ndarray | None = None) -> dict:
    """Least-squares theta of a model against ``target`` displacements [T, P, 3] m:
    ``steps`` Gauss-Newton steps in ``(log s_E, log s_rho)`` from ``start``, forward-difference
    sensitivities of step ``step``. ``simulate(thetas)`` returns the model's displacements
    [T, P, 3] at each theta of the list (simulated together); ``first``, the model at
    ``start`` when already known. A step is limited to 0.5 in log theta. Returns ``theta``
    (2,), ``residual_pct`` (``100 ||u(theta) - target|| / ||target||``) and ``start_residual_pct``."""
    y = np.log(np.asarray(start, dtype=np.float64))
    target = np.asarray(target, dtype=np.float64)
    u = first
    start_res = None
    for _ in range(int(steps)):
        thetas = [tuple(np.exp(y + step * e)) for e in np.eye(2)]
        out = simulate(([tuple(np.exp(y))] if u is None else []) + thetas)
        if u is None:
            u, out = out[0], out[1:]
        r = (u - target).ravel()
        if start_res is None:
            start_res = 100.0 * float(np.linalg.norm(r) / np.linalg.norm(target))
        J = np.stack([(o - u).ravel() / step for o in out], axis=1)
        dy = np.linalg.lstsq(J, -r, rcond=None)[0]
        dy *= min(1.0, 0.5 / max(float(np.abs(dy).max()), 1e-300))
        y = y + dy
        u = None
    u = simulate([tuple(np.exp(y))])[0] if u is None else u
    res = _rel(u, target)
    return {"theta": np.exp(y), "residual_pct": res, "start_residual_pct": res if start_res is None else start_res}


def level_simulator(contract, particles, probe: str, n_points: int, *, device: str | None = None,
                    deterministic: bool = False) -> Callable[[list], list]:
    """``simulate(thetas)`` for :func:`fit_theta`: the displacements [T, n_points, 3] m of the first
    ``n_points`` particles under ``probe`` at each theta of the list, simulated together, each
    theta once (a second fit, such as the band's, starts where the first did)."""
    from ..rollout import run_rollouts

    done: dict = {}

    def simulate(thetas):
        new = list(dict.fromkeys(th for th in thetas if th not in done))
        if new:
            out = run_rollouts(contract, [(th, probe) for th in new], particles=particles, device=device,
                               deterministic=deterministic)
            for th, r in zip(new, out):
                x = np.asarray(r.positions, dtype=np.float64)[:, : int(n_points)]
                done[th] = x - x[0]
        return [done[th] for th in thetas]

    return simulate


def _order(e_coarse: float, e_fine: float, h_coarse: float, h_fine: float) -> float:
    """Observed order ``log(e_coarse / e_fine) / log(h_coarse / h_fine)`` (NaN if an error is 0)."""
    if not (e_coarse > 0 and e_fine > 0):
        return float("nan")
    return math.log(e_coarse / e_fine) / math.log(h_coarse / h_fine)


def floor_study(contract, settings: FloorSettings = FloorSettings(), *, theta=(1.0, 1.0), device: str | None = None,
                deterministic: bool = False, log: Callable[[str], None] | None = None,
                reference_cache=None) -> pd.DataFrame:
    """The floor table of ``contract``'s object (one base material region): one row per MPM
    level of ``settings.n_grid`` (coarsest first), then the reference's check and the reference
    (module docstring). Columns: ``model`` (``mpm``, ``fem (check)``, ``fem (reference)``),
    ``n_grid``, ``dx_m``, ``dt_s``, ``particles`` (MPM particles, or the FEM's DOFs),
    ``cells_through``, ``mass_kg`` (the body's: the particles' rest volumes x rho; the FEM's voxel
    volume x rho x ``fem_scale``), ``rmse_pct``
    (Probe-A record), ``period_s``, ``period_fem_s``, ``period_error_pct``, ``order_rmse`` and
    ``order_period`` (to the previous level), ``s_E_fit``, ``s_rho_fit`` and
    ``fit_residual_pct`` (the theta fit; NaN without one), ``band_hz``, ``rmse_band_pct``,
    ``s_E_fit_band``, ``s_rho_fit_band`` and ``fit_band_residual_pct`` (the same in the record's
    slow band, ``settings.band_hz``: :func:`band_limited`; NaN without one), ``cost_s`` (wall seconds of the
    level's rollouts and fit, or of the FEM run), ``enclosed_empty`` (:func:`enclosed_empty_cells`
    on the row's grid), ``fem_scale`` (the particles' volume over the FEM's voxel body's; NaN for
    the MPM). ``theta``: the material compared;
    ``device``, ``deterministic``: the MPM rollouts'. ``reference_cache``: a folder where each
    finite-element run (the reference and its check) is kept once computed and read back by a
    later study with the same inputs (:func:`_fem_run`): the reference depends on the fill, the
    grid and the FEM settings, not on the MPM levels, and at the default profile's n_grid 48 it
    costs minutes of one CPU core."""
    from ..assets import build_asset
    from ..rollout import run_rollouts

    say = log or (lambda msg: None)
    if set(contract.region_names) != {"base"}:
        raise InputError(contract.source, "regions", "the floor study's FEM reference supports one material region (base)")
    probe = contract.roles["calibration"]
    pr = contract.probes[probe]
    n_record = int(pr.export.n_frames)
    n_long = (n_record - 1) * int(settings.record_factor) + 1
    times = np.arange(n_long) * float(pr.export.frame_dt)
    direction = np.asarray(pr.force, dtype=np.float64)
    rho = contract.materials["base"].rho * float(theta[1])
    gs = build_asset(contract).particles
    points = np.asarray(gs.positions[: gs.n_gs], dtype=np.float64)   # the Gaussians: the same at every level

    # the reference: one particle set, voxelized on fem_n_grid (and on the coarser check grid)
    fem = {}
    bodies = _reference_runs(contract, settings)
    for name, (ref_contract, ref_particles, world) in bodies.items():
        fem[name] = _fem_run(ref_contract, ref_particles, points, world, theta, probe, cache=reference_cache)
        f = fem[name]
        say(f"{name}: n_grid {world.n_grid}, {f['cells']} cells, the body fills {f['scale']:.4f} of them, {f['cost']:.1f} s"
            + (" (kept from an earlier study)" if f["cached"] else ""))
    u_ref = fem["fem (reference)"]["u"]
    p_ref = probe_period(times, u_ref, direction)
    rec = slice(0, n_record)
    band = band_components(settings.band_hz, float(pr.export.frame_dt), n_record) if settings.band_hz else None

    rows = []
    for n in settings.n_grid:
        c = at_resolution(contract, n)
        particles = build_asset(c).particles
        same = particles.n_gs == len(points) and np.array_equal(particles.positions[: particles.n_gs], gs.positions[: gs.n_gs])
        if not same:
            raise RuntimeError(f"n_grid {n}: the Gaussian particles differ from the profile's")
        dx = c.sim.grid_lim / c.sim.n_grid
        t0 = time.perf_counter()
        long_c = _with_record(c, probe, n_long)
        X = np.asarray(run_rollouts(long_c, [(tuple(theta), probe)], particles=particles, device=device,
                                    deterministic=deterministic)[0].positions, dtype=np.float64)[:, : len(points)]
        u = X - X[0]

        simulate = level_simulator(c, particles, probe, len(points), device=device, deterministic=deterministic)

        fit = band_fit = None
        if settings.fit_steps:
            fit = fit_theta(simulate, u_ref[rec], start=theta, steps=settings.fit_steps, step=settings.fit_step, first=u[rec])
            if band:
                band_fit = fit_theta(lambda thetas, s=simulate: [band_limited(x, band) for x in s(thetas)],
                                     band_limited(u_ref[rec], band), start=theta, steps=settings.fit_steps,
                                     step=settings.fit_step, first=band_limited(u[rec], band))
        period = probe_period(times, u, direction)
        rows.append({"model": "mpm", "n_grid": n, "dx_m": dx, "dt_s": c.sim.dt, "particles": len(particles.positions),
                     "cells_through": cells_through(particles.positions, dx), "mass_kg": body_volume(particles, dx) * rho,
                     "rmse_pct": _rel(u[rec], u_ref[rec]), "period_s": period, "period_fem_s": p_ref,
                     "period_error_pct": 100.0 * (period - p_ref) / p_ref,
                     "s_E_fit": float(fit["theta"][0]) if fit else float("nan"),
                     "s_rho_fit": float(fit["theta"][1]) if fit else float("nan"),
                     "fit_residual_pct": fit["residual_pct"] if fit else float("nan"),
                     **_band_columns(u[rec], u_ref[rec], band, band_fit),
                     "cost_s": time.perf_counter() - t0,
                     "enclosed_empty": enclosed_empty_cells(particles.positions, dx), "fem_scale": float("nan")})
        r = rows[-1]
        say(f"MPM n_grid {n}: {r['particles']} particles, dt {r['dt_s']:.3g} s, RMSE {r['rmse_pct']:.1f} %, "
            f"period {r['period_s']:.4f} s ({r['period_error_pct']:+.1f} %), theta fit "
            f"({r['s_E_fit']:.3f}, {r['s_rho_fit']:.3f}), {r['cost_s']:.1f} s")
    for k, row in enumerate(rows):
        prev = rows[k - 1] if k else None
        row["order_rmse"] = _order(prev["rmse_pct"], row["rmse_pct"], prev["dx_m"], row["dx_m"]) if prev else float("nan")
        row["order_period"] = (_order(abs(prev["period_error_pct"]), abs(row["period_error_pct"]), prev["dx_m"], row["dx_m"])
                               if prev else float("nan"))
    for name in ("fem (check)", "fem (reference)"):
        f = fem[name]
        ref_particles = bodies[name][1]
        dx = contract.sim.grid_lim / f["n_grid"]
        period = probe_period(times, f["u"], direction)
        rows.append({"model": name, "n_grid": f["n_grid"], "dx_m": dx,
                     "dt_s": float(pr.export.frame_dt) / settings.fem_steps_per_frame,
                     "particles": f["dofs"], "cells_through": cells_through(ref_particles.positions, dx),
                     "mass_kg": f["volume"] * f["scale"] * rho, "rmse_pct": _rel(f["u"][rec], u_ref[rec]),
                     "period_s": period, "period_fem_s": p_ref, "period_error_pct": 100.0 * (period - p_ref) / p_ref,
                     "order_rmse": float("nan"), "order_period": float("nan"), "s_E_fit": float("nan"),
                     "s_rho_fit": float("nan"), "fit_residual_pct": float("nan"),
                     **_band_columns(f["u"][rec], u_ref[rec], band, None), "cost_s": f["cost"],
                     "enclosed_empty": enclosed_empty_cells(ref_particles.positions, dx), "fem_scale": f["scale"]})
    columns = ["model", "n_grid", "dx_m", "dt_s", "particles", "cells_through", "mass_kg", "rmse_pct", "period_s",
               "period_fem_s", "period_error_pct", "order_rmse", "order_period", "s_E_fit", "s_rho_fit",
               "fit_residual_pct", "band_hz", "rmse_band_pct", "s_E_fit_band", "s_rho_fit_band", "fit_band_residual_pct",
               "cost_s", "enclosed_empty", "fem_scale"]
    for row in rows:
        row["band_hz"] = float(settings.band_hz) if settings.band_hz else float("nan")
    return pd.DataFrame(rows, columns=columns)


def _placeless(contract):
    """``contract`` with its files named by their names alone (its own, the asset's PLY, the
    candidate and target tables), so that a kept run's name does not depend on where the
    checkout lies; what the files hold enters the key through the particles."""
    def name(path):
        return None if path is None else Path(path).name

    asset = dataclasses.replace(contract.asset, ply=name(contract.asset.ply))
    return dataclasses.replace(contract, source=name(contract.source), asset=asset,
                               candidates_path=name(contract.candidates_path), targets_path=name(contract.targets_path))


def _reference_runs(contract, settings: FloorSettings) -> dict:
    """{name: (contract, particles, world)} of the reference and its check: the particle set built
    at ``fem_n_grid`` (at ``fem_check_n_grid``), with the calibration probe's record
    ``record_factor`` times longer, meshed on ``fem_n_grid`` (on ``fem_check_n_grid``): its
    voxels, or its fill's surface (``fem_body``)."""
    from ..assets import build_asset

    probe = contract.roles["calibration"]
    n_long = (int(contract.probes[probe].export.n_frames) - 1) * int(settings.record_factor) + 1
    out = {}
    body = reference_body(contract, settings)
    for name, n in (("fem (reference)", settings.fem_n_grid), ("fem (check)", settings.fem_check_n_grid)):
        c = at_resolution(contract, n)
        out[name] = (_with_record(c, probe, n_long), build_asset(c).particles, settings.world(n, body=body))
    return out


def reference_body(contract, settings: FloorSettings) -> str:
    """The reference's body for ``contract``: ``settings.fem_body``, but ``voxel`` for an object
    without an interior fill, whose body is the grid cells its Gaussians occupy (``cell_share``:
    there is no enclosed surface to mesh)."""
    return settings.fem_body if contract.fill.enabled else "voxel"


def kept_reference_files(contract, settings: FloorSettings = FloorSettings(), *, theta=(1.0, 1.0), reference_cache) -> dict:
    """{name: (path, kept)} of the finite-element runs :func:`floor_study` would read from
    ``reference_cache`` (the reference and its check): where each is kept, and whether it is
    there. Cheap (the particle sets, no solve): to learn before a costly call whether the
    study will compute a reference."""
    from ..assets import build_asset

    probe = contract.roles["calibration"]
    gs = build_asset(contract).particles
    points = np.asarray(gs.positions[: gs.n_gs], dtype=np.float64)
    out = {}
    for name, (c, particles, world) in _reference_runs(contract, settings).items():
        path = Path(reference_cache) / f"fem_n{world.n_grid}_{_fem_key(c, particles, points, world, theta, probe)}.npz"
        out[name] = (path, path.is_file())
    return out


def _fem_key(contract, particles, points, world, theta, probe) -> str:
    """The name of a kept finite-element run (:func:`_fem_run`): 24 hex digits of a SHA-256."""
    from .. import fem as fem_package
    from ..assets import _build, _fill

    h = hashlib.sha256()
    for source in [*sorted(Path(fem_package.__file__).parent.rglob("*.py")), Path(_fill.__file__), Path(_build.__file__)]:
        h.update(source.read_bytes())           # the solver, and the fill's surface (body_level_set) a level-set body meshes
    with np.printoptions(threshold=sys.maxsize, precision=17):
        h.update(repr((_placeless(contract), world, tuple(float(t) for t in theta), probe)).encode())
    for a in (particles.positions, particles.volumes, points):
        h.update(b"none" if a is None else np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:24]


def _fem_run(contract, particles, points, world, theta, probe, *, cache=None) -> dict:
    """One finite-element run of the floor study: the displacement ``u`` [T, M, 3] m of
    ``points`` (the Gaussians' rest positions) from frame 0, the mesh's ``cells``, ``dofs`` and
    meshed body's ``volume`` [m^3], ``scale``, the particles' volume over the body's (a voxel
    cell carries its particles' own volume where they have one, module docstring), its ``cost`` [s] and whether
    it was read from ``cache`` (a folder, or None). A kept run is named by a SHA-256 of all it
    depends on: the finite-element package's source, the contract (its record's length
    included; not where its files lie, :func:`_placeless`), the world's settings, theta, the
    probe, and the particles and points."""
    from ..fem import body_scale, fem_world_mesh, fem_world_rollout

    path = None
    if cache is not None:
        path = Path(cache) / f"fem_n{world.n_grid}_{_fem_key(contract, particles, points, world, theta, probe)}.npz"
        if path.is_file():
            with np.load(path) as z:
                return {"u": z["u"], "n_grid": int(world.n_grid), "cells": int(z["cells"]), "dofs": int(z["dofs"]),
                        "volume": float(z["volume"]), "scale": float(z["scale"]), "cost": float(z["cost"]),
                        "cached": True}
    t0 = time.perf_counter()
    geo = fem_world_mesh(contract, particles, world=world)
    Y = fem_world_rollout(contract, particles, theta, probe, points, world=world, geo=geo)
    mesh = geo["mesh"]
    run = {"u": Y - Y[0], "n_grid": int(world.n_grid), "cells": len(geo["cells"]),
           "dofs": 3 * (len(mesh.p.T) + (len(mesh.edges.T) if world.degree == 2 else 0)),
           "volume": float(geo["volume"]), "scale": body_scale(particles, geo), "cost": time.perf_counter() - t0, "cached": False}
    if path is not None:
        from ..io import atomic_write

        with atomic_write(path) as fh:
            np.savez(fh, **{k: np.asarray(v) for k, v in run.items() if k not in ("cached", "n_grid")})
    return run


def floor_note(table: pd.DataFrame, contract, settings: FloorSettings, *, theta=(1.0, 1.0)) -> str:
    """The table's note: the object, probe, theta, what is compared, the reference's check."""
    probe = contract.roles["calibration"]
    pr = contract.probes[probe]
    check = table[table.model == "fem (check)"].iloc[0]
    return (f"{contract.name} ({contract.profile} contract), Probe A ({probe}), theta ({theta[0]:g}, {theta[1]:g}). "
            f"MPM levels: grid and fill refined together, dt by the contracts' rule. Reference: the particle set at "
            f"n_grid {settings.fem_n_grid} "
            + ("voxelized on that grid" if reference_body(contract, settings) == "voxel" else
               "(its probe's particles), the body its fill encloses measured on "
               + (f"a fill grid of {settings.fem_body_resolution}" if settings.fem_body_resolution else "its fill grid")
               + " and meshed to that surface and to the supports' faces on that grid")
            + f", P{settings.fem_degree} tetrahedra, Newmark, "
            f"{settings.fem_steps_per_frame} steps per frame; its check (the same construction on n_grid "
            f"{settings.fem_check_n_grid}) is {check.rmse_pct:.1f} % and {check.period_error_pct:+.2f} % (period) from it. "
            f"rmse_pct: trajectory RMSE of the Gaussian particles over the Probe-A record ({pr.export.n_frames} frames), "
            f"% of the reference's RMS displacement; periods: mean displacement along the force over "
            f"{settings.record_factor}x the record. s_E_fit, s_rho_fit: {settings.fit_steps} Gauss-Newton steps of the "
            f"MPM at that level against the reference's Probe-A trajectory (least squares, not the library's local ridge). "
            + (f"rmse_band_pct, s_E_fit_band, s_rho_fit_band: the same in the record's slow band, its cosines at or below "
               f"{settings.band_hz:g} Hz ({band_components(settings.band_hz, pr.export.frame_dt, pr.export.n_frames)} "
               f"of {pr.export.n_frames}). " if settings.band_hz else "")
            + "particles: the FEM rows' DOFs. cells_through: median shortest axis run of occupied cells; "
            f"enclosed_empty: empty cells enclosed by occupied ones. Volume rule: fill.volumes {contract.fill.volumes}"
            + ("." if contract.fill.volumes == "cell_share" or reference_body(contract, settings) == "level_set"
               else " (each FEM cell carries its particles' volume: E and rho x that over dx^3; fem_scale: the body's "
                    "volume over the voxels').")
            + (" fem_scale: the particles' volume over the meshed body's." if reference_body(contract, settings) == "level_set"
               else ""))


def plot_floor(table: pd.DataFrame, path, *, title: str = "") -> None:
    """RMSE and |period error| [%] of the MPM levels against dx [m], log-log, with the observed
    order between the coarsest and the finest level in the legend; the reference's check as
    horizontal lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..reporting import save_figure

    mpm = table[table.model == "mpm"]
    check = table[table.model == "fem (check)"].iloc[0]
    fig, ax = plt.subplots(figsize=(5.2, 3.8))
    for col, label, colour in (("rmse_pct", "trajectory RMSE", "C0"), ("period_error_pct", "|period error|", "C1")):
        e = np.abs(mpm[col].to_numpy(dtype=float))
        h = mpm.dx_m.to_numpy(dtype=float)
        p = _order(e[0], e[-1], h[0], h[-1]) if len(e) > 1 else float("nan")
        ax.loglog(h, np.maximum(e, 1e-3), "o-", color=colour, label=f"{label} (order {p:.2f})")
        ax.axhline(max(abs(float(check[col])), 1e-3), color=colour, ls=":", lw=1, label=f"{label}, FEM check")
    ax.set_xlabel("MPM dx [m]")
    ax.set_ylabel("gap to the FEM reference [%]")
    ax.set_title(title)
    ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path, dpi=120)
    plt.close(fig)
