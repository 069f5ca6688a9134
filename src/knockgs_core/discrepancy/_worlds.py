"""Cases in worlds the loop's model cannot match exactly (the truth side, private).

Two worlds make the "measured" data instead of the loop's own model:

- ``finer``: the same MPM on a grid twice as fine as the loop's (grid and interior fill at
  2 x the loop contract's n_grid and fill resolution, dt by the contracts' rule), with the
  Gaussians of the neighbouring finer profile (ci -> default; a different sampling of the
  same surface) and its own fill;
- ``fem``: the finite-element reference (:func:`knockgs_core.fem.fem_world_rollout`: the
  loop's particle set voxelized on its grid, P2 tetrahedra, Newmark).

Both are observed as noisy tracks without identity of a random 60 % of the world's surface
points (the finer world's Gaussian particles; for the FEM, the neighbouring finer profile's
Gaussians), with noise std 2 % of the calibration response's RMS displacement. The truth
kept for scoring (``clean.npz``) is the world's motion of the loop's Gaussian particles' rest
positions, so a run is scored as in the standard cases: finer world, its displacement field
there (Gaussian-weighted mean of the 8 nearest world particles, length the world's cell); FEM,
evaluated there. The planted effect lives in the world; its strength is searched in the
world, on the held-out probe, as in the standard cases.
"""

from __future__ import annotations

import dataclasses
from dataclasses import asdict
from pathlib import Path

import numpy as np

from ..io import write_json, write_npz
from ..errors import InputError
from ._measured import Measurement, write_measured
from ._planted import LEVELS, PLANTED_EFFECTS, CaseSpec, planted_change, search_strength

__all__ = ["FEM_EFFECTS", "FINER_EFFECTS", "world_cases", "world_contract", "finer_world_rollout", "make_world_case",
           "observe_world"]

#: the neighbouring finer profile whose Gaussians the worlds' surfaces are sampled from
_FINER_PROFILE = {"ci": "default", "default": "paper", "paper": "paper"}

#: planted effect -> (FemWorld settings at strength s and horizon H, starting strength, in the catalogue,
#: strength -> (parameter, value, unit)). Rayleigh damping is mass- and stiffness-proportional, with
#: equal shares at a period of half the record (beta = alpha (H / (4 pi))^2), so not the catalogue's damping.
FEM_EFFECTS = {
    "damping": (lambda s, H: {"rayleigh_alpha": s, "rayleigh_beta": s * (H / (4.0 * np.pi)) ** 2}, 1.0, True,
                lambda s: ("rayleigh_alpha", s, "1/s")),
    "gravity": (lambda s, H: {"gravity": s}, 0.02, True, lambda s: ("g", s, "m/s^2")),
    "stiffness_gradient_z": (lambda s, H: {"stiffness_slope": s}, 1.0, True, lambda s: ("slope", s, "")),
}
#: planted effects of the finer world (simulator effects of :data:`PLANTED_EFFECTS`)
FINER_EFFECTS = ("damping", "gravity", "plasticity", "stiffness_gradient_z", "support_slip", "vertical_push", "force_pulse")


def world_cases(targets: list[tuple[float, float]] | None = None, *, targets_path=None) -> list[CaseSpec]:
    """The world cases: the finer world with no effect and each of :data:`FINER_EFFECTS`,
    the FEM world with no effect and each of :data:`FEM_EFFECTS`, all at level ``high``
    (25 % held-out change), thetas cycling through the held-out targets of split ``main``
    in increasing order (as :func:`default_cases`), observed without identity."""
    if not targets:
        from ..contract import load_targets

        main = load_targets("main", targets_path)
        targets = sorted(zip(main["E_scale"].astype(float), main["density_scale"].astype(float)))
    names = [("finer_null", "none", "finer")] + [(f"finer_{e}", e, "finer") for e in FINER_EFFECTS]
    names += [("fem_null", "none", "fem")] + [(f"fem_{e}", e, "fem") for e in FEM_EFFECTS]
    return [CaseSpec(name=name, planted=eff, level="high", theta=targets[i % len(targets)], observation="gs_tracks",
                     seed=2000 + i, world=world) for i, (name, eff, world) in enumerate(names)]


def world_contract(contract, *, profile: str | None = None):
    """The finer world's contract: ``contract``'s object at ``profile`` (its Gaussians; None:
    the neighbouring finer profile), with grid and fill at twice ``contract``'s n_grid and fill resolution,
    ``contract``'s fill otherwise (its volume rule, and its inside filled or not: the same body,
    sampled more finely) and the contracts' time-step rule."""
    from ..contract import load_contract

    finer = load_contract(contract.source, profile or _FINER_PROFILE.get(contract.profile, contract.profile))
    n = 2 * contract.sim.n_grid
    # the loop contract's fill (whether and where the inside is filled, its volume rule: the
    # same body, e.g. a solid one of ``with_body``), on a grid twice as fine
    fill = dataclasses.replace(contract.fill, resolution=2 * contract.fill.resolution)
    out = dataclasses.replace(finer, sim=dataclasses.replace(finer.sim, n_grid=n), fill=fill)
    return dataclasses.replace(out, sim=dataclasses.replace(out.sim, dt=float(out.cfl_dt())))


def finer_world_rollout(world_contract, world_particles, theta, probe: str, *, planted: str = "none", strength=None,
                        horizon: float, device=None, deterministic: bool = False, export_F: bool = False):
    """One rollout of the finer world: ``world_contract`` (:func:`world_contract`) on its
    particles at ``theta`` under ``probe``, with the planted effect ``planted`` of
    :data:`PLANTED_EFFECTS` at ``strength`` (none when ``planted`` is ``"none"`` or ``strength``
    is None; ``horizon`` [s] is the record the effect's strength is stated over). Returns the
    :func:`knockgs_core.rollout.run_rollout` result (positions [T, N, 3] m; deformation
    gradients [T, N, 3, 3] with ``export_F``, for rendering)."""
    from ..rollout import run_rollout
    from ..sim import with_effects

    effects = () if planted == "none" or strength is None else (PLANTED_EFFECTS[planted][0](strength, world_particles, horizon),)
    p = with_effects(world_contract.sim, *effects)
    return run_rollout(world_contract, theta, probe, particles=world_particles, device=device, deterministic=deterministic,
                       export_F=export_F, sim_overrides={"effects": p.effects, "boundaries": p.boundaries})


def _surface_points(contract) -> np.ndarray:
    """Rest positions of the Gaussian particles of the neighbouring finer profile [P, 3]."""
    from ..assets import build_asset
    from ..contract import load_contract

    ps = build_asset(load_contract(contract.source, _FINER_PROFILE.get(contract.profile, contract.profile))).particles
    return np.asarray(ps.positions[: ps.n_gs], dtype=np.float64)


class _World:
    """Simulates one world: ``run(theta, probe, strength)`` returns (clean positions of the
    loop's Gaussian particles [T, n_gs, 3], positions of the world's surface points [T, P, 3]).
    ``device`` and ``deterministic``: the finer world's rollouts'; ``world_profile``: whose
    Gaussians it simulates (None: the neighbouring finer profile's)."""

    def __init__(self, spec: CaseSpec, contract, particles, horizon: float, *, device=None, deterministic: bool = False,
                 world_profile: str | None = None):
        self.spec, self.contract, self.particles, self.H, self.device = spec, contract, particles, horizon, device
        self.deterministic = deterministic
        self.loop_points = np.asarray(particles.positions[: particles.n_gs], dtype=np.float64)
        if spec.world == "finer":
            from ..assets import build_asset

            self.wc = world_contract(contract, profile=world_profile)
            self.wp = build_asset(self.wc).particles
            self.surface = np.arange(self.wp.n_gs)
            self.description = {"world": "finer", "profile": self.wc.profile, "n_grid": self.wc.sim.n_grid,
                                "fill_resolution": self.wc.fill.resolution, "dt": self.wc.sim.dt,
                                "particles": len(self.wp.positions), "gaussian_particles": self.wp.n_gs}
            if spec.planted not in ("none", *FINER_EFFECTS):
                raise InputError("case", "planted", f"'{spec.planted}' is not planted in the finer world")
        else:
            from ..fem import FemWorld, fem_world_mesh

            self.surface_points = _surface_points(contract)
            geo = fem_world_mesh(contract, particles)
            self.base = FemWorld()
            self.description = {"world": "fem", "element": "P2 tetrahedra on the loop's occupied grid cells",
                                "cells": len(geo["cells"]), "dx": geo["dx"], "volume": geo["volume"],
                                "steps_per_frame": self.base.steps_per_frame, "surface_points": len(self.surface_points)}
            if spec.planted not in ("none", *FEM_EFFECTS):
                raise InputError("case", "planted", f"'{spec.planted}' is not planted in the FEM world")

    def run(self, theta, probe, strength=None):
        planted = self.spec.planted
        if self.spec.world == "finer":
            from ._model_error import displacement_at

            ro = finer_world_rollout(self.wc, self.wp, theta, probe, planted=planted, strength=strength, horizon=self.H,
                                     device=self.device, deterministic=self.deterministic)
            X = np.asarray(ro.positions, np.float64)
            U = X - X[0]
            length = self.wc.sim.grid_lim / self.wc.sim.n_grid
            L = self.loop_points[None] + displacement_at(X[0], U, self.loop_points, length=length)
            return L, X[:, self.surface]
        from ..fem import fem_world_rollout

        world = self.base if strength is None else dataclasses.replace(self.base, **FEM_EFFECTS[planted][0](strength, self.H))
        pts = np.concatenate([self.loop_points, self.surface_points])
        Y = fem_world_rollout(self.contract, self.particles, theta, probe, pts, world=world)
        n = len(self.loop_points)
        return Y[:, :n], Y[:, n:]


def observe_world(clean: dict, surface: dict, *, probes: dict, meta: dict, source: str, noise_rel: float, seed: int,
                  measured_dir, truth_dir) -> tuple[dict, float]:
    """Observe a world's runs as the world cases are observed, and keep its truth.

    ``clean[role]`` [T, n, 3] (m): the world's motion of the loop's Gaussian particles, kept as
    ``truth_dir/clean.npz``; ``surface[role]`` [T, P, 3] (m): its surface points, of which a
    random 60 % are written as tracks without identity, with Gaussian noise of std ``noise_rel``
    times the calibration response's RMS displacement, to ``measured_dir/measured_{role}.parquet``
    (metadata ``meta`` plus the role's probe from ``probes``). Roles: ``calib`` and ``heldout``.
    Returns ({role: measured file}, the noise std in m)."""
    rng = np.random.default_rng(seed)
    Yc = clean["calib"]
    sigma = noise_rel * float(np.sqrt(np.mean(np.sum((Yc - Yc[0]) ** 2, -1))))
    n_surf = surface["calib"].shape[1]
    idx = rng.permutation(n_surf)[: max(1, int(0.6 * n_surf))]
    tracks = rng.permutation(len(idx)) + 1
    measured_dir, truth_dir = Path(measured_dir), Path(truth_dir)
    files = {}
    for role in ("calib", "heldout"):
        S = surface[role][:, idx]
        m = Measurement(points=S + rng.normal(0.0, sigma, size=S.shape), frames=np.arange(S.shape[0]), times=None,
                        particle=None, track=tracks, meta={**meta, "probe": probes[role]}, source=source)
        path = measured_dir / f"measured_{role}.parquet"
        write_measured(path, m)
        files[role] = str(path)
    write_npz(truth_dir / "clean.npz", calib=clean["calib"].astype(np.float32), heldout=clean["heldout"].astype(np.float32))
    return files, sigma


def make_world_case(spec: CaseSpec, contract, particles, *, measured_dir, truth_dir, calibration_probe: str,
                    heldout_probe: str, device=None, deterministic: bool = False, world_profile: str | None = None) -> dict:
    """Write the case ``spec`` (world ``finer`` or ``fem``) as :func:`make_case` does: the
    measured files (tracks without identity of the world's surface points, metadata object,
    the loop's profile, probe) to ``measured_dir``; ``truth.json`` and ``clean.npz`` (the world's
    motion of the loop's Gaussian particles) to ``truth_dir``. ``device`` and ``deterministic``:
    the finer world's rollouts'; ``world_profile``: whose Gaussians the finer world simulates
    and is observed at (None: the neighbouring finer profile's). Returns the truth record."""
    H = contract.probes[calibration_probe].export.horizon
    world = _World(spec, contract, particles, H, device=device, deterministic=deterministic, world_profile=world_profile)
    search, strength, achieved, param = [], None, 0.0, None
    if spec.planted != "none":
        table = PLANTED_EFFECTS if spec.world == "finer" else FEM_EFFECTS
        s0, in_cat, describe = table[spec.planted][1], table[spec.planted][2], table[spec.planted][3]
        target = LEVELS[spec.level] if isinstance(spec.level, str) else float(spec.level)
        Y0 = world.run(spec.theta, heldout_probe)[0]
        strength, achieved = search_strength(lambda s: planted_change(world.run(spec.theta, heldout_probe, s)[0], Y0),
                                             s0, target, search)
        p, v, u = describe(strength)
        param = {"parameter": p, "value": v, "unit": u}
        in_catalogue = bool(in_cat)
    else:
        in_catalogue = True
    clean, surface = {}, {}
    for role, pr in (("calib", calibration_probe), ("heldout", heldout_probe)):
        clean[role], surface[role] = world.run(spec.theta, pr, strength)
    files, sigma = observe_world(clean, surface, probes={"calib": calibration_probe, "heldout": heldout_probe},
                                 meta={"object": contract.name, "profile": contract.profile}, source=f"case {spec.name}",
                                 noise_rel=spec.noise_rel, seed=spec.seed, measured_dir=measured_dir, truth_dir=truth_dir)
    truth = {
        "case": spec.name,
        "world": spec.world,
        "world_description": world.description,
        "planted_effect": spec.planted,
        "in_catalogue": in_catalogue,
        "level": spec.level,
        "planted_parameter": param,
        "strength": strength,
        "heldout_change": achieved,
        "strength_search": search,
        "theta_true": list(spec.theta),
        "noise_std": sigma,
        "observation": spec.observation,
        "seed": spec.seed,
        "calibration_probe": calibration_probe,
        "heldout_probe": heldout_probe,
        "measured_files": files,
        "spec": asdict(spec),
    }
    write_json(Path(truth_dir) / "truth.json", truth)
    return truth
