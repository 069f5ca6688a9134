"""Rest volumes of an asset's particles: how much of the body each particle carries (private).

The contract's ``fill.volumes`` chooses the rule:

- ``cell_share`` (PhysGaussian): every particle gets ``dx^3 / (particles in its grid cell)``
  on the simulation grid, computed by the simulator. The body is the grid cells that hold a
  particle, so its volume (and mass) changes with the grid: a surface crossing a cell counts
  the whole cell, a body ``dx`` thick around the surface too many.
- ``enclosed``: the body is the volume the Gaussian surface encloses, measured on the fill
  grid (:func:`~knockgs_core.assets._fill.body_fraction`: interior cells whole, the shell's
  cells by their depth below the surface). Each fill-grid cell's share of the body goes to the
  particles in it, equally; a share of a cell that holds no particle goes to the particles of
  the nearest cell that does. The total is the body's volume whatever the simulation grid, and
  converges as the fill grid is refined.
- ``wall``: a thin-walled body (a vase): every Gaussian particle carries ``wall_thickness``
  times its share of the surface area (:func:`surface_areas`), so the total is the wall's
  volume, thickness x area, whatever the grid.
"""

from __future__ import annotations

import numpy as np

from knockgs_core.errors import InputError

from ._fill import FillGrid, body_fraction

__all__ = ["PASSENGER_SHARE", "VOLUME_RULES", "box_share", "enclosed_volumes", "passengers", "surface_areas",
           "wall_volumes"]

#: the contract's ``fill.volumes`` choices
VOLUME_RULES = ("cell_share", "enclosed", "wall")
#: a passenger particle's volume, x the median body particle's
PASSENGER_SHARE = 1e-4

#: neighbours of a surface point that bound its area cell
_AREA_NEIGHBOURS = 20
#: directions of the polar integral of an area cell
_AREA_ANGLES = 96


def passengers(positions: np.ndarray, boxes) -> np.ndarray:
    """Boolean mask [N] of the ``positions`` [N, 3] m inside any of ``boxes`` (closed)."""
    x = np.asarray(positions, np.float64)
    out = np.zeros(len(x), dtype=bool)
    for b in boxes:
        out |= b.contains(x)
    return out


def _overlaps(grid: FillGrid, axis: int, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The share [n, K] of each of ``grid``'s cells along ``axis`` that lies in each interval
    [``lo``, ``hi``] [K] m."""
    a = grid.lo[axis] + np.arange(grid.shell.shape[axis]) * grid.h[axis]
    over = np.minimum(a[:, None] + grid.h[axis], hi[None]) - np.maximum(a[:, None], lo[None])
    return np.clip(over, 0.0, None) / grid.h[axis]


def box_share(grid: FillGrid, boxes) -> np.ndarray:
    """Each cell's share [n, n, n] float64 in [0, 1] of its volume inside ``boxes`` (axis-aligned,
    exact; boxes that overlap each other count their overlap once per box, clipped at 1)."""
    out = np.zeros(grid.shell.shape)
    for b in boxes:
        c, hs = np.asarray(b.center, np.float64), np.asarray(b.half_size, np.float64)
        side = [_overlaps(grid, a, c[a:a + 1] - hs[a], c[a:a + 1] + hs[a])[:, 0] for a in range(3)]
        out += np.einsum("i,j,k->ijk", *side)
    return np.minimum(out, 1.0)


def body_on(grid: FillGrid, body_grid: FillGrid, frac: np.ndarray) -> np.ndarray:
    """Each cell's share [n, n, n] of ``grid`` of a body measured as ``frac`` [m, m, m] (cell shares)
    on ``body_grid``, another grid of the same box: the body in a fine cell taken as spread over
    it, each cell of ``grid`` gets the shares of the fine cells it overlaps, by their overlap."""
    side = []
    for a in range(3):
        flo = body_grid.lo[a] + np.arange(body_grid.shell.shape[a]) * body_grid.h[a]
        side.append(_overlaps(grid, a, flo, flo + body_grid.h[a]))
    return np.einsum("iI,jJ,kK,IJK->ijk", side[0], side[1], side[2], frac, optimize=True)


def enclosed_volumes(positions: np.ndarray, grid: FillGrid, surface_points: np.ndarray, *,
                     passenger_boxes=(), body_grid: FillGrid | None = None, source: object = "fill",
                     field: str = "fill.box") -> np.ndarray:
    """Rest volumes [m^3] (N,) float32 of the particles at ``positions`` [N, 3] m under the
    ``enclosed`` rule (module docstring), the body measured on ``grid`` with its surface at
    ``surface_points`` [P, 3] m (the Gaussian centres) and ``passenger_boxes`` cut from it. Every
    particle must lie in the fill box (else :class:`~knockgs_core.errors.InputError` naming
    ``field``); particles in a cell with no share of the body (a Gaussian centre just outside the
    surface) share the nearest cell's that has one, so every body particle's volume is positive
    and their total is the body's; particles in the boxes get :data:`PASSENGER_SHARE` of the
    median body particle's. With ``body_grid`` (the same box, other cells: ``fill.body_resolution``)
    the body is measured there and its shares carried onto ``grid``'s cells (:func:`body_on`), so
    the particles of every grid carry one body."""
    x = np.asarray(positions, np.float64)
    n = grid.shell.shape[0]
    cell = grid.cell_of(x)
    if not np.all((cell >= 0) & (cell < n)):
        raise InputError(source, field, "the enclosed volume rule needs every particle inside the fill box; "
                         f"{int(np.sum(~np.all((cell >= 0) & (cell < n), axis=1)))} lie outside it")
    measured = grid if body_grid is None else body_grid
    frac = body_fraction(measured, surface_points)
    if passenger_boxes:
        frac = frac * (1.0 - box_share(measured, passenger_boxes))
    if measured is not grid:
        frac = body_on(grid, measured, frac)
    if not passenger_boxes:
        return _shares(cell, grid, frac, source, field)
    rides = passengers(x, passenger_boxes)
    if rides.all():
        raise InputError(source, "fill.passenger_boxes", "hold every particle: no body is left to ride on")
    out = np.empty(len(x), dtype=np.float32)
    out[~rides] = _shares(cell[~rides], grid, frac, source, field)
    out[rides] = PASSENGER_SHARE * float(np.median(out[~rides]))
    return out


def _shares(cell: np.ndarray, grid: FillGrid, frac: np.ndarray, source, field) -> np.ndarray:
    """Volumes [m^3] (N,) float32 of the particles in fill cells ``cell`` [N, 3]: each cell's
    share ``frac`` [n, n, n] of the body, split equally among its particles (the module
    docstring's rule)."""
    from scipy.spatial import cKDTree

    n = grid.shell.shape[0]
    cell_vol = float(np.prod(grid.h))
    key = (cell[:, 0] * n + cell[:, 1]) * n + cell[:, 2]
    held, inverse, count = np.unique(key, return_inverse=True, return_counts=True)
    vol = frac.ravel()[held] * cell_vol                                  # each held cell's own share
    body = np.flatnonzero(frac.ravel() > 0)
    empty = body[~np.isin(body, held)]
    if empty.size:                                                       # to the nearest held cell
        held_c = grid.centres(np.stack(np.unravel_index(held, (n, n, n)), axis=1))
        _, j = cKDTree(held_c).query(grid.centres(np.stack(np.unravel_index(empty, (n, n, n)), axis=1)))
        vol += np.bincount(j, weights=frac.ravel()[empty] * cell_vol, minlength=len(held))
    bare = vol <= 0
    if bare.any() and not bare.all():
        # particles in a cell the rule puts outside the body (a Gaussian centre just beyond the
        # surface): they share the volume of the nearest cell that has some, so the total stays
        # the body's and every particle has a mass
        keep = np.flatnonzero(~bare)
        cen = grid.centres(np.stack(np.unravel_index(held, (n, n, n)), axis=1))
        _, j = cKDTree(cen[keep]).query(cen[bare])
        owner = np.arange(len(held))
        owner[bare] = keep[j]
        inverse = owner[inverse]
        count = np.bincount(inverse, minlength=len(held))
    elif bare.all():
        raise InputError(source, field, "the fill grid finds no body around the particles (no shell cell)")
    out = vol[inverse] / count[inverse]
    return out.astype(np.float32)


def surface_areas(points: np.ndarray) -> np.ndarray:
    """Each surface point's share of the surface area [m^2] (P,) float64, for ``points``
    [P, 3] m sampled on a surface: the area of its Voronoi cell among its nearest neighbours
    in the tangent plane (the plane of least variance of the neighbours), integrated in polar
    coordinates; bounded by the distance to the farthest neighbour where the cell is open (an
    edge of the surface, whose points it over-counts). The cells tile the surface, so the shares add up to its area
    whatever the sampling density or pattern (curvature enters at second order)."""
    from scipy.spatial import cKDTree

    p = np.asarray(points, np.float64)
    if len(p) < _AREA_NEIGHBOURS + 1:
        raise InputError("surface", "points", f"need at least {_AREA_NEIGHBOURS + 1} surface points, got {len(p)}")
    dist, j = cKDTree(p).query(p, k=_AREA_NEIGHBOURS + 1)
    nb = p[j[:, 1:]] - p[:, None, :]                                     # [P, k, 3]
    _, vec = np.linalg.eigh(np.einsum("pki,pkj->pij", nb, nb))
    q = np.stack([np.einsum("pki,pi->pk", nb, vec[:, :, 2]), np.einsum("pki,pi->pk", nb, vec[:, :, 1])], axis=-1)
    ang = np.linspace(0.0, 2.0 * np.pi, _AREA_ANGLES, endpoint=False)
    u = np.stack([np.cos(ang), np.sin(ang)], axis=1)                     # [A, 2]
    proj = q @ u.T                                                       # [P, k, A]
    half = 0.5 * np.sum(q * q, axis=-1)[:, :, None]
    with np.errstate(divide="ignore"):
        reach = np.where(proj > 1e-12 * half, half / np.where(proj > 0, proj, 1.0), np.inf).min(axis=1)
    reach = np.minimum(reach, dist[:, -1:])
    return np.pi * np.mean(reach ** 2, axis=1)


def wall_volumes(points: np.ndarray, thickness: float) -> np.ndarray:
    """Rest volumes [m^3] (P,) float32 of particles at ``points`` [P, 3] m on a wall
    ``thickness`` [m] thick: ``thickness`` x :func:`surface_areas`."""
    return (float(thickness) * surface_areas(points)).astype(np.float32)
