"""The benchmarks' paper-scale object: its particles (cached in a file, held in cell order as
a GPU rollout holds them) and its Probe-A model."""

from __future__ import annotations

from pathlib import Path


def object_particles(contract, path: str | None = None, *, order: str = "cell"):
    """The object's particles: read from ``path`` where it exists, else built (and written
    there if given); in the stencil base cells' order (``order="cell"``,
    ``knockgs_core.rollout.cell_order``) or the asset's (``"asset"``)."""
    from knockgs_core.assets import build_asset, load_particles, save_particles
    from knockgs_core.rollout import _permuted, cell_order

    if path and Path(path).exists():
        ps = load_particles(path, contract=contract)
    else:
        ps = build_asset(contract).particles
        if path:
            save_particles(ps, path, contract=contract)
    if order == "cell":
        ps = _permuted(ps, cell_order(ps, n_grid=contract.sim.n_grid, grid_lim=contract.sim.grid_lim))
    return ps


def probe_a_model(contract, ps, device: str, theta: tuple[float, float] = (1.0, 1.0)):
    """The object's model under its calibration probe (Probe A) at ``theta`` on ``device``,
    the probe's force scaled to the contract's reference particle count as rollouts do."""
    from knockgs_core.sim import build_model

    probe = contract.resolve_probes(ps)[contract.roles["calibration"]]
    E, nu, rho = contract.particle_materials(ps, theta)
    ref = getattr(contract, "probe_reference_particles", None)
    return build_model(ps.positions, E=E, nu=nu, rho=rho, params=contract.sim, volumes=ps.volumes, probe=probe,
                       probe_force_scale=float(ref) / len(ps.positions) if ref else 1.0, device=device)
