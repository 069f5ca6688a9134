"""Why the Pillow's MPM is softer than its FEM reference under ``fill.volumes: enclosed`` (CPU, minutes).

Each case is one body, one particle set and one support, simulated by the MPM (the contract's
solver, transfer and substep rule) and solved by the FEM (P2 on the body's voxels, the
contract's support box held: ``--fem-support``). Compared: the first-mode period of the MPM (the mean
x displacement under the calibration probe over a long record, least-squares sinusoid, and
the FFT peak) and the FEM's first natural period and the period of its most x-excited mode
(``natural_frequencies`` route: eigenvectors of ``K phi = w^2 M phi`` and their participation
in a uniform x load).

    python3 benchmarks/floor_bisect.py --cases box pillow_lattice pillow_enclosed --n-grid 32 --fem-support vertices

prints a Markdown table (docs/floor.md, "Why the MPM looked twice too soft under enclosed").
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np


def lattice(cells: np.ndarray, dx: float, per_axis: int = 2) -> np.ndarray:
    """``per_axis``^3 particles on a lattice in each of ``cells`` [K, 3] (cell ``dx`` [m]) [K p^3, 3]."""
    o = (np.arange(per_axis) + 0.5) / per_axis
    off = np.stack(np.meshgrid(o, o, o, indexing="ij"), -1).reshape(-1, 3)
    return ((cells[:, None, :] + off[None]) * dx).reshape(-1, 3)


def particle_set(positions: np.ndarray, volumes: np.ndarray | None, n_gs: int):
    from knockgs_core.assets import ParticleSet

    n = len(positions)
    return ParticleSet(positions=np.asarray(positions, np.float32),
                       volumes=None if volumes is None else np.asarray(volumes, np.float32), n_gs=int(n_gs),
                       gaussian_index=np.arange(int(n_gs)), region=np.zeros(n, np.int32))


def relattice(ps, dx: float, *, skin: bool, fill: bool):
    """``ps`` (volumes given) with a 2^3 lattice added to the cells (of size ``dx``) that hold only
    Gaussian particles (``skin``) and the fill particles of the other cells replaced by a 2^3
    lattice (``fill``); each cell's volume shared equally by its particles (the same body, cell
    by cell; the Gaussians first, kept in order)."""
    x = np.asarray(ps.positions, np.float64)
    idx = np.floor(x / dx).astype(np.int64)
    cells, inv = np.unique(idx, axis=0, return_inverse=True)
    inv = inv.ravel()
    vol = np.bincount(inv, weights=np.asarray(ps.volumes, np.float64), minlength=len(cells))
    has_fill = np.zeros(len(cells), bool)
    has_fill[inv[ps.n_gs:]] = True
    keep = np.ones(len(x), bool)
    add = np.zeros(len(cells), bool)
    if skin:
        add |= ~has_fill
    if fill:
        keep[ps.n_gs:] = False
        add |= has_fill
    extra = lattice(cells[add], dx)
    pos = np.concatenate([x[keep], extra])
    cell_of = np.concatenate([inv[keep], np.repeat(np.flatnonzero(add), 8)])
    count = np.bincount(cell_of, minlength=len(cells))
    return particle_set(pos, vol[cell_of] / count[cell_of], ps.n_gs)


def fem_modes(contract, particles, n_grid: int, *, scale: float | str = 1.0, n_modes: int = 6, degree: int = 2,
              support: str = "nodes") -> dict:
    """The FEM's first ``n_modes`` periods [s] of ``particles`` voxelized on ``n_grid`` (E and rho x
    ``scale``, or x each cell's volume fraction where ``scale`` is "cell"), each mode's share of a
    uniform x load's modal mass, and the voxel volume."""
    import scipy.sparse.linalg as spla

    from knockgs_core.fem import FemWorld, Region, assemble_elasticity, fem_world_mesh, fem_world_system, held_dofs, support_dofs

    world = FemWorld(degree=degree, n_grid=int(n_grid))
    geo = fem_world_mesh(contract, particles, world=world)
    m = contract.materials["base"]
    if scale == "cell":                                      # the FEM world's own body: each cell its particles' volume
        s, geo = fem_world_system(contract, particles, (1.0, 1.0), world=world)
    else:
        s = assemble_elasticity(geo["mesh"], E=m.E * scale, nu=m.nu, rho=m.rho * scale, degree=degree)
    fixed = []
    for bc in contract.sim.boundaries:
        if type(bc).__name__ == "FixedCuboid":
            region = Region.from_center(bc.box.center, bc.box.half_size)
            fixed.append(support_dofs(s, region) if support == "nodes" else held_dofs(s, region))
    fixed = np.unique(np.concatenate(fixed))
    free = np.setdiff1d(np.arange(s.n_dofs), fixed)
    K, M = s.K[free][:, free].tocsc(), s.M[free][:, free].tocsc()
    w2, phi = spla.eigsh(K, k=n_modes, M=M, sigma=-1e-8 * float(np.max(K.diagonal() / M.diagonal())), which="LM")
    order = np.argsort(w2)
    w2, phi = w2[order], phi[:, order]
    from knockgs_core.fem._elasticity import _dof_components

    comp = _dof_components(s)
    rx = (comp[free] == 0).astype(float)                     # rigid x motion
    part = (phi.T @ (M @ rx)) ** 2 / np.einsum("ij,ij->j", phi, M @ phi)
    total = rx @ (M @ rx)
    held_z = s.basis.doflocs[2][fixed]
    return {"periods": 2 * np.pi / np.sqrt(w2), "share_x": part / total, "volume": geo["volume"],
            "cells": len(geo["cells"]), "dofs": s.n_dofs, "held_top": float(held_z.max()) if len(held_z) else float("nan"),
            "mass": float(total)}


def mpm_period(contract, particles, *, seconds: float = 8.0, theta=(1.0, 1.0)) -> dict:
    """The MPM's period of the mean x displacement under the calibration probe over ``seconds``:
    least-squares sinusoid and FFT peak [s]; the MPM's mass [kg]."""
    from knockgs_core.experiments._floor import _with_record, body_volume
    from knockgs_core.fem import first_mode_period
    from knockgs_core.rollout import run_rollout

    probe = contract.roles["calibration"]
    fdt = float(contract.probes[probe].export.frame_dt)
    n = int(round(seconds / fdt)) + 1
    c = _with_record(contract, probe, n)
    t0 = time.perf_counter()
    X = np.asarray(run_rollout(c, (tuple(theta)), probe, particles=particles).positions, np.float64)
    cost = time.perf_counter() - t0
    u = (X - X[0])[:, :, 0].mean(axis=1)
    times = np.arange(n) * fdt
    spec = np.abs(np.fft.rfft((u - u.mean()) * np.hanning(n), n=16 * n))
    f = np.fft.rfftfreq(16 * n, fdt)
    dx = c.sim.grid_lim / c.sim.n_grid
    return {"period": first_mode_period(times, u), "fft": 1.0 / f[1 + np.argmax(spec[1:])], "cost": cost,
            "mass": body_volume(particles, dx) * contract.materials["base"].rho * theta[1], "u": u}


def case(name: str, n_grid: int):
    """(contract, MPM particles, FEM particles, FEM scale) of a case at ``n_grid``."""
    from knockgs_core.assets import build_asset
    from knockgs_core.contract import load_contract
    from knockgs_core.experiments import at_resolution
    from knockgs_core.experiments._floor import body_volume

    base = load_contract("pillow", "ci")
    enc = dataclasses.replace(base, fill=dataclasses.replace(base.fill, volumes="enclosed"))
    c = at_resolution(enc, n_grid)
    dx = c.sim.grid_lim / n_grid
    if name in ("block", "block_on_pillow_support"):
        # the verification block (docs/verification.md), on its own support (its bottom 0.25 m held)
        # or standing on the Pillow's (0.5 m free above the grid plane under the Pillow's bottom)
        from knockgs_core.fem import BLOCK, SUPPORT
        from knockgs_core.sim import FixedCuboid

        if name == "block":
            lo, hi = np.array(BLOCK[0]), np.array(BLOCK[1])
            walls = tuple(b for b in c.sim.boundaries if type(b).__name__ != "FixedCuboid")
            c = dataclasses.replace(c, sim=dataclasses.replace(c.sim, boundaries=walls + (FixedCuboid(SUPPORT),)))
        else:
            z0 = np.floor(0.9484 / dx) * dx
            lo, hi = np.array([0.75, 0.75, z0]), np.array([1.25, 1.25, z0 + 0.5])
        ranges = [np.arange(a, b) for a, b in zip(np.round(lo / dx).astype(int), np.round(hi / dx).astype(int))]
        cells = np.stack(np.meshgrid(*ranges, indexing="ij"), -1).reshape(-1, 3)
        x = lattice(cells, dx)
        p = particle_set(x, np.full(len(x), dx**3 / 8), len(x))
        return c, p, p, 1.0
    if name in ("box", "box_embedded", "box_random4"):   # a grid-aligned box the size of the Pillow's bounding box
        lo = np.floor(np.array([0.6, 0.7, 0.9484 - (0.25 if name == "box_embedded" else 0.0)]) / dx).astype(int)
        hi = np.ceil(np.array([1.4, 1.28, 1.36]) / dx).astype(int)
        cells = np.stack(np.meshgrid(*[np.arange(a, b) for a, b in zip(lo, hi)], indexing="ij"), -1).reshape(-1, 3)
        if name == "box_random4":        # the fill's pattern: 4 particles jittered uniformly in each cell
            x = ((cells[:, None, :] + np.random.default_rng(1).random((len(cells), 4, 3))) * dx).reshape(-1, 3)
            p = particle_set(x, np.full(len(x), dx**3 / 4), len(x))
            return c, p, particle_set(lattice(cells, dx), None, 0), 1.0
        x = lattice(cells, dx)
        p = particle_set(x, np.full(len(x), dx**3 / 8), len(x))
        return c, p, p, 1.0
    ps = build_asset(c).particles
    if name == "pillow_enclosed":        # the floor study's MPM level and its reference's scale
        geo_cells = np.unique(np.floor(np.asarray(ps.positions, np.float64) / dx).astype(int), axis=0)
        return c, ps, ps, body_volume(ps, dx) / (len(geo_cells) * dx**3)
    if name in ("pillow_enclosed_cellfem", "pillow_lattice_enclosed"):
        # the enclosed particles, or a 2^3 lattice per occupied cell carrying that cell's enclosed volume;
        # the FEM's E and rho x each cell's volume fraction (the same body, cell by cell)
        if name == "pillow_enclosed_cellfem":
            return c, ps, ps, "cell"
        idx = np.floor(np.asarray(ps.positions, np.float64) / dx).astype(int)
        cells, inv = np.unique(idx, axis=0, return_inverse=True)
        vol = np.bincount(inv.ravel(), weights=np.asarray(ps.volumes, np.float64))
        x = lattice(cells, dx)
        p = particle_set(x, np.repeat(vol / 8, 8), len(x))
        return c, p, p, "cell"
    if name in ("pillow_skin_lattice", "pillow_fill_lattice"):
        # the enclosed set with a 2^3 lattice added to its Gaussian-only cells, or replacing its fill
        return c, relattice(ps, dx, skin=name == "pillow_skin_lattice", fill=name == "pillow_fill_lattice"), ps, "cell"
    if name == "pillow_lattice":         # the Pillow's occupied cells, 2^3 lattice each: one body in both
        cells = np.unique(np.floor(np.asarray(ps.positions, np.float64) / dx).astype(int), axis=0)
        x = lattice(cells, dx)
        p = particle_set(x, np.full(len(x), dx**3 / 8), len(x))
        return c, p, p, 1.0
    raise SystemExit(f"unknown case {name}")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", default=["box", "pillow_lattice", "pillow_enclosed"])
    ap.add_argument("--n-grid", type=int, nargs="+", default=[32])
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--dt-factor", type=float, default=1.0, help="the MPM substep times this (frame-commensurate)")
    ap.add_argument("--fem-support", choices=["nodes", "vertices"], default="vertices",
                    help="nodes: every FEM node in the support box held (the FEM world's before 2026-12-06); vertices: "
                         "the vertices in it and the edge nodes between two of them (fem.held_dofs, the FEM world's)")
    ap.add_argument("--fem-only", action="store_true", help="the FEM's modes only (no MPM run)")
    ap.add_argument("--transfer", choices=["contract", "apic", "affine_flip"], default="contract")
    args = ap.parse_args(argv)
    print("| case | n_grid | particles | MPM mass [kg] | FEM mass [kg] | FEM cells | MPM period (fit / FFT) [s] |"
          " FEM T1 [s] | FEM most-x mode: T [s], share | MPM / FEM | cost [s] |")
    print("|---|---:|---:|---:|---:|---:|---|---:|---|---:|---:|")
    for n in args.n_grid:
        for name in args.cases:
            c, p_mpm, p_fem, scale = case(name, n)
            sim = c.sim
            if args.dt_factor != 1.0:
                sim = dataclasses.replace(sim, dt=sim.dt * args.dt_factor)
            if args.transfer != "contract":
                sim = dataclasses.replace(sim, transfer=args.transfer)
            c = dataclasses.replace(c, sim=sim)
            t0 = time.perf_counter()
            fem = fem_modes(c, p_fem, n, scale=scale, support=args.fem_support)
            if args.fem_only:
                mpm = {"period": float("nan"), "fft": float("nan"), "mass": float("nan")}
            else:
                mpm = mpm_period(c, p_mpm, seconds=args.seconds)
            k = int(np.argmax(fem["share_x"]))
            scale_txt = scale if isinstance(scale, str) else f"{scale:.3f}"
            print(f"| {name} (FEM x {scale_txt}) | {n} | {len(p_mpm.positions):,} | {mpm['mass']:.1f} | {fem['mass']:.1f} | "
                  f"{fem['cells']} | "
                  f"{mpm['period']:.3f} / {mpm['fft']:.3f} | {fem['periods'][0]:.3f} | mode {k + 1}: {fem['periods'][k]:.3f}, "
                  f"{fem['share_x'][k]:.2f} | {mpm['period'] / fem['periods'][k]:.3f} | {time.perf_counter() - t0:.0f} |",
                  flush=True)


if __name__ == "__main__":
    main()
