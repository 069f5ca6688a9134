"""Interior fill in the spirit of PhysGaussian (private).

1. Gaussian density on an ``n^3`` grid of cells spanning ``fill_box``:
   ``d(c) = sum_i o_i exp(-1/2 (c - mu_i)^T (Sigma_i + (h/2)^2 I)^-1 (c - mu_i))`` at cell
   centres ``c``. Each Gaussian is widened by half a cell so that thin surface Gaussians
   register in every cell their surface crosses (an axis-aligned row of cells always has
   a centre within h/2 of a crossing surface). Work is bounded: each Gaussian touches a
   fixed stencil of at most 7^3 cells.
2. Cells with ``d > density_threshold`` form the shell.
3. A non-shell cell is interior when rays from it along +x, -x, +y, -y, +z and -z all
   hit the shell (six cumulative maxima over the grid; no iteration).
4. Each interior cell receives ``max_particles_per_cell`` minus the number of Gaussian
   centres already in it, uniformly jittered inside the cell, from ``seed``.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from knockgs_core.errors import InputError

from ._gaussians import GaussianSet

__all__ = ["FillResult", "fill_interior", "density_grid", "interior_cells"]

#: widening of every Gaussian, in cells (standard deviation)
_SMOOTH_CELLS = 0.5
#: largest stencil radius in cells (bounded work for very large Gaussians)
_MAX_RADIUS = 3
#: Gaussians per vectorized batch
_CHUNK = 1 << 16


class FillResult(NamedTuple):
    """Fill particles ``positions`` [M, 3] float32 and the number of ``filled_cells``."""

    positions: np.ndarray
    filled_cells: int


def _box_bounds(fill_box, source, field):
    c = np.asarray(fill_box.center, dtype=np.float64)
    h = np.asarray(fill_box.half_size, dtype=np.float64)
    if c.shape != (3,) or h.shape != (3,) or not np.all(np.isfinite(c)) or not np.all(h > 0):
        raise InputError(source, field, f"needs a finite centre and positive half sizes, got {fill_box}")
    return c - h, c + h


def density_grid(gs: GaussianSet, *, lo, hi, resolution: int) -> np.ndarray:
    """Gaussian density (step 1 of the module docstring) on the ``resolution^3`` cells of
    the box ``[lo, hi]``; returns [n, n, n] float64 indexed (ix, iy, iz)."""
    n = int(resolution)
    lo = np.asarray(lo, np.float64)
    h = (np.asarray(hi, np.float64) - lo) / n
    flat = np.zeros(n ** 3, dtype=np.float64)
    if len(gs) == 0:
        return flat.reshape(n, n, n)
    covs = gs.covariances().astype(np.float64) + np.diag((_SMOOTH_CELLS * h) ** 2)[None]
    # stencil radius from the widest Gaussian along any axis (99.9th percentile, capped)
    sig = np.sqrt(np.diagonal(covs, axis1=1, axis2=2)) / h
    q = float(np.quantile(sig.max(axis=1), 0.999))
    radius = int(np.clip(np.ceil(3.0 * q - 0.5), 1, _MAX_RADIUS))
    r = np.arange(-radius, radius + 1)
    offsets = np.stack(np.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3)
    prec = np.linalg.inv(covs)
    means = gs.means.astype(np.float64)
    opac = gs.opacities.astype(np.float64)
    for s in range(0, len(gs), _CHUNK):
        mu, P, o = means[s:s + _CHUNK], prec[s:s + _CHUNK], opac[s:s + _CHUNK]
        base = np.floor((mu - lo) / h).astype(np.int64)
        for off in offsets:
            cell = base + off
            ok = np.all((cell >= 0) & (cell < n), axis=1)
            if not np.any(ok):
                continue
            c = cell[ok]
            d = lo + (c + 0.5) * h - mu[ok]
            m = np.einsum("ni,nij,nj->n", d, P[ok], d)
            w = o[ok] * np.exp(-0.5 * np.minimum(m, 200.0))
            flat += np.bincount((c[:, 0] * n + c[:, 1]) * n + c[:, 2], weights=w, minlength=n ** 3)
    return flat.reshape(n, n, n)


def interior_cells(shell: np.ndarray) -> np.ndarray:
    """Non-shell cells whose six axis rays all hit the shell (bool, same shape)."""
    inside = ~shell
    for axis in range(3):
        fwd = np.maximum.accumulate(shell, axis=axis)
        bwd = np.flip(np.maximum.accumulate(np.flip(shell, axis), axis=axis), axis)
        inside &= fwd & bwd
    return inside


def fill_interior(gs: GaussianSet, *, fill_box, resolution: int, density_threshold: float,
                  max_particles_per_cell: int, seed: int, source: object = "fill",
                  field_prefix: str = "") -> FillResult:
    """Fill particles for the interior of the surface described by ``gs``.

    Parameters
    ----------
    gs:
        The (simulated, normalized) Gaussians whose surface encloses the interior.
    fill_box:
        :class:`~knockgs_core.sim._config.Box` spanned by the fill grid.
    resolution:
        ``n`` cells per axis (cell size ``2 * half_size / n`` per axis).
    density_threshold:
        Shell cells have a density above it (see the module docstring).
    max_particles_per_cell:
        Particles per interior cell, less the Gaussian centres already in the cell.
    seed:
        Seed of the jitter (``numpy.random.default_rng``).

    Returns a :class:`FillResult` ``(positions [M, 3] float32, filled_cells)``: cells in C
    order (x slowest), particles jittered uniformly within each cell. Bounded work on any
    input: open or noisy clouds give few or no interior cells, never an endless search.
    """
    n = int(resolution)
    if n < 2 or n > 1024:
        raise InputError(source, f"{field_prefix}resolution", f"must lie in [2, 1024], got {resolution}")
    if int(max_particles_per_cell) < 1:
        raise InputError(source, f"{field_prefix}max_particles_per_cell",
                         f"must be >= 1, got {max_particles_per_cell}")
    if not np.isfinite(density_threshold) or density_threshold <= 0:
        raise InputError(source, f"{field_prefix}density_threshold",
                         f"must be finite and > 0, got {density_threshold}")
    lo, hi = _box_bounds(fill_box, source, f"{field_prefix}box")
    h = (hi - lo) / n
    dens = density_grid(gs, lo=lo, hi=hi, resolution=n)
    inside = interior_cells(dens > density_threshold)
    flat_inside = np.flatnonzero(inside.ravel())
    # Gaussian centres already in each interior cell count against the per-cell budget
    cell = np.floor((gs.means.astype(np.float64) - lo) / h).astype(np.int64)
    ok = np.all((cell >= 0) & (cell < n), axis=1)
    occupied = np.bincount((cell[ok, 0] * n + cell[ok, 1]) * n + cell[ok, 2], minlength=n ** 3)
    need = np.clip(int(max_particles_per_cell) - occupied[flat_inside], 0, None)
    cells = flat_inside[need > 0]
    need = need[need > 0]
    rng = np.random.default_rng(int(seed))
    idx = np.repeat(cells, need)
    ijk = np.stack(np.unravel_index(idx, (n, n, n)), axis=1).astype(np.float64)
    pos = lo + (ijk + rng.random((idx.size, 3))) * h
    return FillResult(pos.astype(np.float32), int(cells.size))
