"""An object's response computed by the finite-element reference: "measured" data that the
MPM model cannot match exactly (private).

The body is the object's particle set voxelized on the contract's grid: every grid cell that
holds a particle becomes a hexahedron (six tetrahedra). Where the particles carry no rest volumes
(``fill.volumes: cell_share``) each occupied cell is whole, as the MPM gives each occupied cell
the volume dx^3, and so is the mass. Where they carry their own (``enclosed``, ``wall``), a cell
carries the volume of its particles: its E and rho are scaled by that volume over dx^3 (the
finite-cell method's share of a cell the body fills in part), so the body's mass and its
distribution over the cells are the particles', and a surface cell the body half fills is half
as heavy and half as stiff instead of whole. Or (``FemWorld(body="level_set")``) the body is the
surface the contract's fill encloses (:func:`~knockgs_core.assets.body_level_set`), meshed to
it on the same grid (:func:`~._mesh.level_set_mesh`): whole material wherever the mesh is, a
boundary that converges at second order in the cell where the staircase converges at first;
the probe's load is then scaled to the particles' total, as the cut cells lose part of it. The still sticky
supports (the contract's ``fixed_cuboid`` boxes) hold the mesh vertices inside them, the grid
nodes the MPM holds, and what those vertices span (:func:`held_dofs`). The probe
acts as the MPM's does: the same force on every selected particle, so the force density of a
cell is proportional to the particles it holds; the total impulse is the contract's. A probe
shorter than the FEM step is applied as the velocity jump ``M^-1 J`` at t = 0. Quadratic
tetrahedra and Newmark's average acceleration (``_elasticity``, ``_newmark``) integrate the
small-strain response. Effects the MPM model does not have exactly can be planted: Rayleigh
damping (mass- and stiffness-proportional) and gravity.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse.linalg as spla
import skfem

from ..errors import InputError
from ._elasticity import ElasticSystem, assemble_elasticity, interpolate
from ..sim._config import probe_weights
from ._mesh import Region, level_set_mesh
from ._newmark import SOLVERS, RayleighDamping, newmark

#: the FEM world's bodies (:class:`FemWorld`'s ``body``)
BODIES = ("voxel", "level_set")

__all__ = ["BODIES", "FemWorld", "body_scale", "fem_world_mesh", "fem_world_rollout", "fem_world_system", "held_dofs"]


@dataclass(frozen=True)
class FemWorld:
    """Settings and planted effects of an FEM world (effects off by default).

    ``degree``: 2 (P2 tetrahedra; P1 locks in bending, docs/verification.md);
    ``steps_per_frame``: Newmark steps per export interval; ``rayleigh_alpha`` [1/s] and
    ``rayleigh_beta`` [s]: Rayleigh damping ``C = alpha M + beta K``; ``gravity`` [m/s^2]: a
    body acceleration along -z from t = 0, the body starting at rest and unloaded;
    ``stiffness_slope`` [-]: Young's modulus varying along z as the simulator's
    :class:`~knockgs_core.sim.StiffnessGradient` (``E exp(slope s)``, ``s = (z - mid) / extent``
    over the particles' extent along z, so the modulus ratio top/bottom is ``exp(slope)``);
    ``n_grid``: the grid the body is voxelized on (cell ``grid_lim / n_grid``); None: the
    contract's own, the MPM's cells. A fixed ``n_grid`` gives a mesh that does not change with
    the contract's resolution (the floor study, :mod:`knockgs_core.experiments._floor`);
    ``body``: ``voxel``, the grid cells that hold a particle (each carrying its particles' share
    where they have rest volumes), or ``level_set``, the body the contract's fill encloses
    (:func:`~knockgs_core.assets.body_level_set`) meshed to its surface
    (:func:`~._mesh.level_set_mesh`) with cubes of that cell: a mesh whose boundary converges
    at second order in the cell, where the voxels' staircase converges at first;
    ``body_resolution``: the fill grid the level set is measured on (None: the contract's
    ``fill.resolution``; a fixed, fine one gives one body whatever the particles' construction);
    ``solver``:
    Newmark's linear solver (:func:`~._newmark.newmark`: ``auto`` factorizes up to
    :data:`~._newmark.DIRECT_MAX_DOFS` free DOFs; ``direct`` always, where memory allows)."""

    degree: int = 2
    steps_per_frame: int = 2
    rayleigh_alpha: float = 0.0
    rayleigh_beta: float = 0.0
    gravity: float = 0.0
    stiffness_slope: float = 0.0
    n_grid: int | None = None
    body: str = "voxel"
    body_resolution: int | None = None
    solver: str = "auto"

    def __post_init__(self):
        if self.solver not in SOLVERS:
            raise InputError("FemWorld", "solver", f"must be one of {', '.join(SOLVERS)}, got {self.solver!r}")
        r = self.body_resolution
        if r is not None and (isinstance(r, bool) or int(r) != r or not 2 <= r <= 1024):
            raise InputError("FemWorld", "body_resolution", f"must be an integer in [2, 1024] or None, got {r!r}")
        if self.body not in BODIES:
            raise InputError("FemWorld", "body", f"must be one of {', '.join(BODIES)}, got {self.body!r}")
        if self.degree not in (1, 2):
            raise InputError("FemWorld", "degree", f"must be 1 or 2, got {self.degree!r}")
        if int(self.steps_per_frame) < 1:
            raise InputError("FemWorld", "steps_per_frame", f"must be >= 1, got {self.steps_per_frame!r}")
        if self.n_grid is not None and (isinstance(self.n_grid, bool) or int(self.n_grid) != self.n_grid or self.n_grid < 2):
            raise InputError("FemWorld", "n_grid", f"must be an integer >= 2 or None, got {self.n_grid!r}")
        for name in ("rayleigh_alpha", "rayleigh_beta", "gravity", "stiffness_slope"):
            v = getattr(self, name)
            signed = name in ("gravity", "stiffness_slope")
            if not (math.isfinite(v) and (v >= 0 or signed)):
                raise InputError("FemWorld", name, f"must be finite{' and >= 0' if not signed else ''}, got {v!r}")


def _cells(positions: np.ndarray, dx: float) -> tuple[np.ndarray, np.ndarray]:
    """Occupied grid cells (integer indices [K, 3]) and the particles each holds [K]."""
    idx = np.floor(np.asarray(positions, dtype=np.float64) / dx).astype(np.int64)
    cells, counts = np.unique(idx, axis=0, return_counts=True)
    return cells, counts


def _probe_cells(particles, selected: np.ndarray, dx: float) -> tuple[np.ndarray, np.ndarray]:
    """The cells [K, 3] that hold the particles a probe selects (``selected`` [N] bool) and each
    one's share of the probe [K], in particles of weight 1: the MPM's
    (:func:`~knockgs_core.sim.probe_weights`), so both solvers put one load on the body. Where
    the particles carry their own volumes a cell's share is its selected mass over the
    selection's mean particle mass (one material), else its count."""
    idx = np.floor(np.asarray(particles.positions, np.float64)[selected] / dx).astype(np.int64)
    cells, where, counts = np.unique(idx, axis=0, return_inverse=True, return_counts=True)
    if particles.volumes is None:
        return cells, counts.astype(np.float64)
    w = probe_weights(selected, particles.volumes)[selected]
    return cells, np.bincount(where.ravel(), weights=w, minlength=len(cells))


def fem_world_mesh(contract, particles, *, world: FemWorld = FemWorld()) -> dict:
    """The voxel mesh of ``particles`` on ``contract``'s grid (or ``world.n_grid``'s): ``mesh``
    (scikit-fem MeshTet), ``dx`` [m], ``cells`` [K, 3] occupied cell indices, ``counts`` [K]
    particles per cell, ``volume`` [m^3] (= K dx^3, the MPM's on its own grid), ``share`` [K]
    each cell's share of the body: its particles' rest volume over dx^3, or 1 where the
    particles carry none (module docstring). For ``world.body == "level_set"`` the mesh
    follows the fill's surface, ``volume`` is the mesh's and ``share`` is 1 (the material is
    whole wherever the mesh is)."""
    dx = contract.sim.grid_lim / (contract.sim.n_grid if world.n_grid is None else int(world.n_grid))
    cells, counts = _cells(particles.positions, dx)
    share = np.ones(len(cells))
    if world.body == "level_set":
        from ..assets import body_level_set

        pos = np.asarray(particles.positions, dtype=np.float64)
        lo, hi = (np.floor(pos.min(axis=0) / dx) - 2) * dx, (np.ceil(pos.max(axis=0) / dx) + 2) * dx   # on the grid's planes
        planes = [(k, float(c)) for box in _support_boxes(contract)
                  for k in range(3) for c in (box.center[k] - box.half_size[k], box.center[k] + box.half_size[k])]
        mesh = level_set_mesh(body_level_set(contract, resolution=world.body_resolution), lo, hi, dx, planes=planes)
        return {"mesh": mesh, "dx": dx, "cells": cells, "counts": counts, "volume": _mesh_volume(mesh), "share": share}
    if particles.volumes is not None:
        idx = np.floor(np.asarray(particles.positions, dtype=np.float64) / dx).astype(np.int64)
        _, inverse = np.unique(idx, axis=0, return_inverse=True)      # the order of ``cells``
        share = np.bincount(inverse.ravel(), weights=np.asarray(particles.volumes, np.float64), minlength=len(cells)) / dx**3
    lo = cells.min(axis=0)
    shape = cells.max(axis=0) - lo + 1
    axes = [dx * (lo[k] + np.arange(shape[k] + 1)) for k in range(3)]
    full = skfem.MeshTet.init_tensor(*axes)
    cent = full.p[:, full.t].mean(axis=1).T                          # tet centroids [n_tet, 3]
    ci = np.floor(cent / dx + 1e-9).astype(np.int64) - lo
    occ = np.zeros(shape, dtype=bool)
    occ[tuple((cells - lo).T)] = True
    keep = occ[ci[:, 0], ci[:, 1], ci[:, 2]]
    t = full.t[:, keep]
    used, inv = np.unique(t, return_inverse=True)
    mesh = skfem.MeshTet(np.ascontiguousarray(full.p[:, used]), np.ascontiguousarray(inv.reshape(t.shape)))
    return {"mesh": mesh, "dx": dx, "cells": cells, "counts": counts, "volume": float(len(cells) * dx**3), "share": share}


def body_scale(particles, geo: dict) -> float:
    """The particles' volume over the meshed body's (``geo``: :func:`fem_world_mesh`'s dict): their
    rest volumes' sum, or the occupied cells' volume where they carry none."""
    carried = float(np.sum(particles.volumes)) if particles.volumes is not None else len(geo["cells"]) * geo["dx"] ** 3
    return carried / geo["volume"]


def _support_boxes(contract) -> list:
    """The boxes of ``contract``'s still sticky supports (``FixedCuboid`` at rest)."""
    return [bc.box for bc in contract.sim.boundaries
            if getattr(bc, "box", None) is not None and type(bc).__name__ == "FixedCuboid"
            and not any(getattr(bc, "velocity", (0, 0, 0)))]


def _mesh_volume(mesh: skfem.MeshTet) -> float:
    """The volume [m^3] of a tetrahedral mesh."""
    corners = mesh.p[:, mesh.t]                                      # [3, 4, n_tet]
    edges = np.transpose(corners[:, 1:] - corners[:, :1], (2, 0, 1))
    return float(np.abs(np.linalg.det(edges)).sum() / 6.0)


def _cell_field(cells: np.ndarray, values: np.ndarray, dx: float):
    """A function of points ``x`` [3, ...] m: ``values`` [K] of the cell of ``cells`` [K, 3]
    each point lies in (the elements' quadrature points lie inside their voxel)."""
    lo = cells.min(axis=0)
    grid = np.zeros(tuple(cells.max(axis=0) - lo + 1))
    grid[tuple((cells - lo).T)] = values

    def field(x):
        j = [np.clip(np.floor(x[k] / dx).astype(np.int64) - lo[k], 0, grid.shape[k] - 1) for k in range(3)]
        return grid[j[0], j[1], j[2]]

    return field


def fem_world_system(contract, particles, theta, *, world: FemWorld = FemWorld(),
                     geo: dict | None = None) -> tuple[ElasticSystem, dict]:
    """The assembled body of ``particles`` (a :class:`~knockgs_core.assets.ParticleSet`) on its
    voxel mesh (:func:`fem_world_mesh`), of ``contract``'s base material at theta = (s_E, s_rho):
    each cell's E and rho scaled by its share of the body (module docstring), the modulus graded
    by ``world.stiffness_slope``. ``geo``: the mesh's dict when already built (it is not built
    again). Returns (the :class:`ElasticSystem`, the mesh's dict)."""
    m = contract.materials["base"]
    geo = fem_world_mesh(contract, particles, world=world) if geo is None else geo
    uniform = particles.volumes is None or world.body == "level_set"
    share = None if uniform else _cell_field(geo["cells"], geo["share"], geo["dx"])
    field = share
    if world.stiffness_slope:
        from ..sim import StiffnessGradient

        grad = StiffnessGradient(slope=float(world.stiffness_slope), axis=2)
        z = np.asarray(particles.positions, dtype=np.float64)[:, 2]
        field = lambda x: grad.factor(x[2], float(z.min()), float(z.max())) * (1.0 if share is None else share(x))  # noqa: E731
    system = assemble_elasticity(geo["mesh"], E=m.E * float(theta[0]), nu=m.nu, rho=m.rho * float(theta[1]),
                                 degree=world.degree, stiffness_field=field, mass_field=share)
    return system, geo


def held_dofs(system: ElasticSystem, region: Region) -> np.ndarray:
    """The DOFs a still sticky support box ``region`` holds on a voxel mesh: those of the mesh
    vertices inside it (the grid nodes the MPM's ``FixedCuboid`` holds) and, on P2, those of the
    edge nodes of edges whose two ends are held, so that the held part is what the held vertices
    span. An edge node inside the box on an edge that leaves it (a box top between two grid
    planes) stays free: holding it would clamp part of the element layer above the held plane.
    Sorted indices into the system's DOFs."""
    inside = region.contains(system.mesh.p.T)
    dofs = [system.basis.nodal_dofs[:, inside].ravel()]
    if system.basis.edge_dofs.size:
        a, b = system.mesh.edges
        dofs.append(system.basis.edge_dofs[:, inside[a] & inside[b]].ravel())
    return np.unique(np.concatenate(dofs)).astype(np.int64)


def _probe_load(system: ElasticSystem, cells: np.ndarray, counts: np.ndarray, dx: float, force: np.ndarray) -> np.ndarray:
    """Load vector [N] of a force density that puts ``force`` [N] on every particle: each
    occupied cell carries ``count * force / dx^3`` [N/m^3]."""
    lo = cells.min(axis=0)
    shape = cells.max(axis=0) - lo + 1
    density = np.zeros(tuple(shape), dtype=np.float64)
    density[tuple((cells - lo).T)] = counts / dx**3

    @skfem.LinearForm
    def load(v, w):
        x = w.x
        j = [np.floor(x[k] / dx).astype(np.int64) - lo[k] for k in range(3)]
        inside = (j[0] >= 0) & (j[0] < shape[0]) & (j[1] >= 0) & (j[1] < shape[1]) & (j[2] >= 0) & (j[2] < shape[2])
        i = [np.clip(j[k], 0, shape[k] - 1) for k in range(3)]
        d = np.where(inside, density[i[0], i[1], i[2]], 0.0)    # no load outside the selected cells' box
        return d * (force[0] * v[0] + force[1] * v[1] + force[2] * v[2])

    return load.assemble(system.basis)


def _into_mesh(mesh: skfem.MeshTet, points: np.ndarray, *, candidates: int = 16) -> np.ndarray:
    """``points`` [P, 3] moved into ``mesh`` where they lie outside it: onto the closest point
    of one of the ``candidates`` elements whose centroids are nearest (each candidate's closest
    point approximated by clipping the point's barycentric coordinates to the element)."""
    from scipy.spatial import cKDTree

    from ._elasticity import find_elements

    p = np.asarray(points, dtype=np.float64)
    out = np.flatnonzero(find_elements(mesh, p) < 0)
    if not out.size:
        return p
    corners = mesh.p[:, mesh.t].transpose(2, 1, 0)                 # [n_tet, 4, 3]
    k = min(int(candidates), len(corners))
    _, cand = cKDTree(corners.mean(axis=1)).query(p[out], k=k)
    cand = cand.reshape(len(out), k)
    c = corners[cand]                                                # [n_out, k, 4, 3]
    T = np.stack([c[..., 1, :] - c[..., 0, :], c[..., 2, :] - c[..., 0, :], c[..., 3, :] - c[..., 0, :]], axis=-1)
    lam = np.linalg.solve(T, (p[out, None, :] - c[..., 0, :])[..., None])[..., 0]
    bary = np.clip(np.concatenate([1.0 - lam.sum(axis=-1, keepdims=True), lam], axis=-1), 0.0, None)
    bary /= bary.sum(axis=-1, keepdims=True)
    q = np.einsum("okv,okvd->okd", bary, c)
    best = np.argmin(np.linalg.norm(q - p[out, None, :], axis=-1), axis=1)
    shrink = 1e-9 * (q[np.arange(len(out)), best] - c[np.arange(len(out)), best].mean(axis=1))
    res = p.copy()
    res[out] = q[np.arange(len(out)), best] - shrink                # just inside its element
    return res


def _inside(points: np.ndarray, cells: np.ndarray, dx: float) -> np.ndarray:
    """``points`` [P, 3] moved into the voxel body where they lie outside it: onto the closest
    point of the nearest occupied cell."""
    from scipy.spatial import cKDTree

    p = np.asarray(points, dtype=np.float64)
    occupied = {tuple(c) for c in cells.tolist()}
    own = np.floor(p / dx).astype(np.int64)
    out = np.array([tuple(c) not in occupied for c in own.tolist()], dtype=bool)
    if not out.any():
        return p
    _, j = cKDTree((cells + 0.5) * dx).query(p[out])
    lo = cells[j] * dx
    q = p.copy()
    q[out] = np.clip(p[out], lo + 1e-6 * dx, lo + dx * (1 - 1e-6))
    return q


def fem_world_rollout(contract, particles, theta, probe: str, points, *, world: FemWorld = FemWorld(),
                      geo: dict | None = None) -> np.ndarray:
    """Positions [T, P, 3] (float64, normalized domain [m]) of material points with rest
    positions ``points`` [P, 3] under ``probe`` at its export frames (T = export.n_frames, frame
    0 = rest), for the object of ``contract`` (one base material at theta = (s_E, s_rho)) on
    ``particles`` (a :class:`~knockgs_core.assets.ParticleSet`). Points outside the meshed body
    move with its closest point. ``geo``: :func:`fem_world_mesh`'s dict of the same arguments,
    when the caller has it (the mesh, and a level set's fill grid, are not built again)."""
    if probe not in contract.probes:
        raise InputError(f"object {contract.name}", "probe", f"unknown probe '{probe}'")
    if set(contract.region_names) != {"base"}:
        raise InputError(contract.source, "regions", "the FEM world supports one material region (base)")
    pr = contract.resolve_probes(particles)[probe]
    export = pr.export
    dt = export.frame_dt / int(world.steps_per_frame)
    if pr.start_time != 0.0 or pr.duration >= dt:
        raise InputError(contract.source, f"probes.{probe}", "the FEM world applies a probe shorter than its step at t = 0 only")
    system, geo = fem_world_system(contract, particles, theta, world=world, geo=geo)
    fixed = [held_dofs(system, Region.from_center(box.center, box.half_size)) for box in _support_boxes(contract)]
    fixed = np.unique(np.concatenate(fixed)) if fixed else np.zeros(0, dtype=np.int64)
    sel = contract.probe_selection(pr, particles.positions)
    cells, counts = _probe_cells(particles, sel, geo["dx"])
    scale = float(contract.probe_reference_particles) / len(particles.positions) if contract.probe_reference_particles else 1.0
    force = np.asarray(pr.force, dtype=np.float64) * scale
    J = _probe_load(system, cells, counts, geo["dx"], force) * pr.duration
    if world.body == "level_set":
        # the mesh's surface cuts the particles' cells: the cells' load inside it is scaled to
        # the particles' total, the contract's impulse
        inside = _probe_load(system, cells, counts, geo["dx"], np.array([1.0, 0.0, 0.0])).sum()
        J *= float(counts.sum()) / float(inside)
    free = np.setdiff1d(np.arange(system.n_dofs), fixed)
    v0 = np.zeros(system.n_dofs)
    v0[free] = spla.splu(system.M[free][:, free].tocsc()).solve(J[free])
    damping = RayleighDamping(world.rayleigh_alpha, world.rayleigh_beta)
    gravity = (0.0, 0.0, -float(world.gravity)) if world.gravity else None
    res = newmark(system, dt=dt, frame_dt=export.frame_dt, n_frames=export.n_frames, fixed=fixed, v0=v0,
                  damping=damping, gravity=gravity, solver=world.solver)
    x = np.asarray(points, dtype=np.float64)
    inside = _into_mesh(system.mesh, x) if world.body == "level_set" else _inside(x, geo["cells"], geo["dx"])
    u = interpolate(system, res.u, inside)
    return x[None] + u
