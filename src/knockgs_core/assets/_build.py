"""From an object contract to rendered Gaussians and simulated particles (private)."""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from knockgs_core.errors import InputError

from ._fill import body_distance, fill_grid, fill_interior
from ._gaussians import GaussianSet, _readonly
from ._particles import ParticleSet
from ._ply import read_ply
from ._procedural import make_procedural
from ._transform import Normalization, preprocess
from ._volumes import enclosed_volumes, passengers, wall_volumes

__all__ = ["BuiltAsset", "body_level_set", "build_asset", "load_source_gaussians"]

_CACHE: "OrderedDict[str, BuiltAsset]" = OrderedDict()
_CACHE_SIZE = 4


@dataclass(frozen=True, eq=False)
class BuiltAsset:
    """A physics-ready asset.

    ``gaussians``: every rendered Gaussian, preprocessed and normalized.
    ``static_mask``: [len(gaussians)] bool, support Gaussians rendered but not simulated.
    ``particles``: the simulated particles; ``particles.gaussian_index`` indexes
    ``gaussians`` and equals ``flatnonzero(~static_mask)``.
    ``normalization``: source frame -> normalized domain (its inverse renders in the
    source frame).
    ``probes``: the contract's probes resolved against ``particles`` (see
    :meth:`~knockgs_core.contract.ObjectContract.resolve_probes`).
    ``probe_counts``: particles selected by each probe.
    ``contract_hash``: hash of the contract it was built from.
    """

    gaussians: GaussianSet
    static_mask: np.ndarray
    particles: ParticleSet
    normalization: Normalization
    probes: dict
    probe_counts: dict
    contract_hash: str

    def summary(self) -> dict:
        """Counts for reports: Gaussians, static, GS particles, fill particles, filled cells."""
        ps = self.particles
        return {"gaussians": len(self.gaussians), "static_gaussians": int(self.static_mask.sum()),
                "gs_particles": ps.n_gs, "fill_particles": ps.n_fill, "fill_cells": ps.fill_cells,
                "particles": len(ps), "regions": ps.region_counts(),
                "probe_particles": dict(self.probe_counts)}


def load_source_gaussians(contract) -> GaussianSet:
    """The contract's Gaussians in their source frame, before preprocessing: the
    procedural asset at the profile's count, or the PLY file (subsampled without
    replacement to ``n_gaussians`` with ``asset.seed`` when it holds more)."""
    a = contract.asset
    if a.procedural is not None:
        return make_procedural(a.procedural, n_gaussians=a.n_gaussians, seed=a.seed)
    gs = read_ply(a.ply)
    if a.n_gaussians is not None and len(gs) < a.n_gaussians:
        import warnings

        from knockgs_core.errors import InputWarning

        warnings.warn(f"{a.ply}: holds {len(gs)} Gaussians, fewer than the {a.n_gaussians} of profile "
                      f"'{contract.profile}' ({contract.source}); all of them are used", InputWarning, stacklevel=2)
    if a.n_gaussians is not None and a.n_gaussians < len(gs):
        rng = np.random.default_rng(a.seed)
        gs = gs.subset(np.sort(rng.choice(len(gs), size=a.n_gaussians, replace=False)))
    return gs


def _check_supports(contract, positions: np.ndarray) -> None:
    held = np.zeros(len(positions), dtype=bool)
    fields = []
    for i, bc in enumerate(contract.sim.boundaries):
        box = getattr(bc, "box", None)
        if box is None:
            continue
        inside = box.contains(positions)
        held |= inside
        fields.append(f"sim.boundaries[{i}].box")
        if np.all(inside):
            raise InputError(contract.source, f"sim.boundaries[{i}].box",
                             f"the support holds every particle ({len(positions)}); nothing can respond")
    if fields and np.all(held):
        raise InputError(contract.source, fields[-1],
                         f"the supports together hold every particle ({len(positions)})")


def build_asset(contract) -> BuiltAsset:
    """Build the asset of ``contract`` (a :class:`~knockgs_core.contract.ObjectContract`).

    Steps: source Gaussians -> :func:`preprocess` -> static support mask
    (``asset.static_boxes``) -> simulated Gaussians -> interior fill (if enabled; up to the
    surface under ``fill.volumes: enclosed``) -> material regions -> rest volumes (none under
    ``cell_share``: the simulator's; ``enclosed``, ``wall``: :mod:`._volumes`) -> checks (a
    support holding every particle, a probe box selecting none) -> resolved probes.
    Deterministic: the same contract gives identical arrays.
    Results are cached by contract hash (arrays are read-only).
    """
    key = contract.hash
    if key and key in _CACHE:
        _CACHE.move_to_end(key)
        return _CACHE[key]
    src = contract.source
    a = contract.asset
    gs_src = load_source_gaussians(contract)
    gs, norm = preprocess(gs_src, opacity_threshold=a.opacity_threshold, rotations=a.rotations,
                          crop=a.crop, source=src, field_prefix="asset.")
    static = np.zeros(len(gs), dtype=bool)
    for b in a.static_boxes:
        static |= b.contains(gs.means)
    if np.all(static):
        raise InputError(src, "asset.static_boxes",
                         f"every one of the {len(gs)} Gaussians is static; nothing to simulate")
    gi = np.flatnonzero(~static).astype(np.int64)
    sim_gs = gs.subset(gi)
    fill_pos = np.zeros((0, 3), dtype=np.float32)
    cells = 0
    f = contract.fill
    grid = None
    if f.enabled:
        grid = fill_grid(sim_gs, fill_box=f.box, resolution=f.resolution, density_threshold=f.density_threshold,
                         source=src, field_prefix="fill.")
        fill_pos, cells = fill_interior(sim_gs, fill_box=f.box, resolution=f.resolution,
                                        density_threshold=f.density_threshold,
                                        max_particles_per_cell=f.max_particles_per_cell,
                                        seed=f.seed, source=src, field_prefix="fill.",
                                        reach_surface=f.volumes == "enclosed", grid=grid)
        if f.volumes == "enclosed" and f.passenger_boxes:      # no fill inside a passenger
            fill_pos = fill_pos[~passengers(fill_pos, f.passenger_boxes)]
    positions = np.concatenate([sim_gs.means, fill_pos]).astype(np.float32)
    lim = contract.sim.grid_lim
    if np.any(positions < 0) or np.any(positions > lim):
        raise InputError(src, "asset", f"particles leave the domain [0, {lim}]^3")
    region = contract.assign_regions(positions)
    volumes = None                                   # cell_share: the simulator's, on its grid
    if f.volumes == "enclosed":
        body_grid = grid
        if f.body_resolution is not None and f.body_resolution != f.resolution:
            body_grid = fill_grid(sim_gs, fill_box=f.box, resolution=f.body_resolution,
                                  density_threshold=f.density_threshold, source=src, field_prefix="fill.")
        volumes = enclosed_volumes(positions, grid, sim_gs.means, passenger_boxes=f.passenger_boxes,
                                   body_grid=body_grid, source=src, field="fill.box")
    elif f.volumes == "wall":
        volumes = wall_volumes(positions, f.wall_thickness)
    particles = ParticleSet(positions=positions, volumes=volumes, n_gs=len(gi), gaussian_index=gi,
                            region=region, region_names=contract.region_names, fill_cells=cells)
    _check_supports(contract, positions)
    probes = contract.resolve_probes(particles)
    counts = {k: int(np.count_nonzero(contract.probe_selection(p, positions))) for k, p in probes.items()}
    built = BuiltAsset(gaussians=gs, static_mask=_readonly(static), particles=particles,
                       normalization=norm, probes=probes, probe_counts=counts,
                       contract_hash=contract.hash)
    if key:
        _CACHE[key] = built
        while len(_CACHE) > _CACHE_SIZE:
            _CACHE.popitem(last=False)
    return built


def body_level_set(contract, *, resolution: int | None = None):
    """The body that ``contract``'s fill encloses, as a function: points [P, 3] m (normalized
    domain) -> signed distance [P] m from its surface, positive inside.

    It is :func:`~._fill.body_distance` on the fill grid of the simulated Gaussians (the grid of
    ``fill.body_resolution`` cells where set, else ``fill.resolution``'s, or ``resolution``'s: a
    finer grid gives the same surface more finely), interpolated trilinearly between cell centres
    (points beyond the grid take its edge's value), less ``fill.passenger_boxes`` (the distance to a box's faces, negative inside
    it). Its zero level set bounds the volume the ``enclosed`` rule gives the particles. Needs
    ``fill.enabled`` (else :class:`~knockgs_core.errors.InputError`)."""
    from scipy import ndimage

    f = contract.fill
    if not f.enabled:
        raise InputError(contract.source, "fill.enabled", "the body's level set is measured on the fill grid: needs true")
    built = build_asset(contract)
    sim_gs = built.gaussians.subset(np.asarray(built.particles.gaussian_index))
    n = (f.body_resolution or f.resolution) if resolution is None else int(resolution)
    grid = fill_grid(sim_gs, fill_box=f.box, resolution=n,
                     density_threshold=f.density_threshold, source=contract.source, field_prefix="fill.")
    try:
        dist = body_distance(grid, sim_gs.means)
    except ValueError as exc:
        raise InputError(contract.source, "fill", f"no body to bound: {exc}") from None
    lo, h = np.asarray(grid.lo, np.float64), np.asarray(grid.h, np.float64)

    def distance(points: np.ndarray) -> np.ndarray:
        p = np.asarray(points, np.float64)
        d = ndimage.map_coordinates(dist, ((p - lo) / h - 0.5).T, order=1, mode="nearest")
        for b in f.passenger_boxes:
            d = np.minimum(d, _box_distance(p, b))
        return d

    return distance


def _box_distance(points: np.ndarray, box) -> np.ndarray:
    """Signed distance [P] m of ``points`` [P, 3] m from the faces of ``box``, positive outside."""
    q = np.abs(points - np.asarray(box.center, np.float64)) - np.asarray(box.half_size, np.float64)
    return np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)
