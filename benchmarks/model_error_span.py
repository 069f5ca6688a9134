"""What the discrepancy loop's discretization term can and cannot represent (CPU, minutes).

At one theta, under the calibration probe, at the Gaussian-associated particles' rest
positions (every other exported frame), this measures against the finer world of the
discrepancy cases (``_worlds.world_contract``: the next profile's Gaussians, grid and fill
twice as fine):

- the world's gap to the model, ``W - U``, relative to the world's displacement, and the
  share of its energy that theta's two sensitivities, and theta with the refinement term D
  (grid and fill refined by 1.5, the loop's ``model_error_refine``), represent;
- the grid placements of the floor (``_model_error.FLOOR_SHIFTS``: the particles and every
  box moved by half a cell): their change, and its part that theta and D leave (the floor's
  shapes), against the world gap's leftover;
- fill seeds and a shift of mass between the Gaussian and the fill particles: their change,
  and how much of the world gap they add to what theta and D represent;
- each catalogue effect's signature (its middle trial strength): the share of its energy
  that theta and D represent, i.e. what the term can take from it.

    python3 benchmarks/model_error_span.py --object pillow --profile ci --theta 0.8 1.3

prints a Markdown table (docs/discrepancy.md, "What the term can represent").
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--object", default="pillow")
    ap.add_argument("--profile", default="ci")
    ap.add_argument("--theta", type=float, nargs=2, default=(0.8, 1.3))
    args = ap.parse_args(argv)

    from knockgs_core.assets import build_asset
    from knockgs_core.contract import load_contract
    from knockgs_core.discrepancy import LoopSettings, Measurement
    from knockgs_core.discrepancy._catalogue import default_catalogue
    from knockgs_core.discrepancy._fitting import Problem
    from knockgs_core.discrepancy._forward import ForwardModel, ModelSpec
    from knockgs_core.discrepancy._loop import _context
    from knockgs_core.discrepancy._model_error import FLOOR_SHIFTS, displacement_at, refined_contract, translated
    from knockgs_core.discrepancy._worlds import world_contract
    from knockgs_core.sim import particle_volumes

    c = load_contract(args.object, args.profile)
    probe = c.roles["calibration"]
    theta = tuple(args.theta)
    asset = build_asset(c)
    n_gs = asset.particles.n_gs
    pts = np.asarray(asset.particles.positions, np.float64)[:n_gs]
    length = c.sim.grid_lim / (2 * c.sim.n_grid)
    fw = ForwardModel(c, asset.particles, device="cpu")

    def field(model: ForwardModel, spec: ModelSpec, shift=np.zeros(3)) -> np.ndarray:
        X = np.asarray(model.rollout(spec, probe), np.float64)[::2]
        return displacement_at(X[0] - shift, X - X[0], pts, length=length)

    def built(contract) -> ForwardModel:
        return ForwardModel(contract, build_asset(contract).particles, device="cpu")

    spec = ModelSpec(theta)
    U = field(fw, spec)
    W = field(built(world_contract(c)), spec)
    h = LoopSettings().theta_step
    J = np.column_stack([(field(fw, spec.with_theta((theta[0] * np.exp(h), theta[1]))) - U).ravel() / h,
                         (field(fw, spec.with_theta((theta[0], theta[1] * np.exp(h)))) - U).ravel() / h])
    D = (field(built(refined_contract(c, LoopSettings().model_error_refine)), spec) - U).ravel()
    norm_W = float(np.linalg.norm(W))

    def leftover(v, cols):
        A = np.column_stack(cols)
        return v - A @ np.linalg.lstsq(A, v, rcond=None)[0]

    def share(v, cols):
        e = leftover(v, cols)
        return 1.0 - float(e @ e) / max(float(v @ v), 1e-300)

    gap = (W - U).ravel()
    print(f"{args.object} {args.profile}, theta = {theta}, probe {probe}: |W| RMS "
          f"{np.sqrt(np.mean(np.sum(W ** 2, -1))):.4g} m\n")
    print("| change | size / \\|W\\| | theta represents | theta + D represent | leftover / \\|W\\| |")
    print("|---|---:|---:|---:|---:|")
    print(f"| world - model | {np.linalg.norm(gap) / norm_W:.3f} | {share(gap, [J]):.3f} | {share(gap, [J, D]):.3f} | "
          f"{np.linalg.norm(leftover(gap, [J, D])) / norm_W:.3f} |")
    print(f"| D (refined by 1.5) | {np.linalg.norm(D) / norm_W:.3f} | {share(D, [J]):.3f} | 1 | 0 |")
    dx = c.sim.grid_lim / c.sim.n_grid
    energies = []
    for s in FLOOR_SHIFTS:
        shift = np.asarray(s) * dx
        cs, ps = translated(c, asset.particles, shift)
        Dk = (field(ForwardModel(cs, ps, device="cpu"), spec, shift) - U).ravel()
        lk = leftover(Dk, [J, D])
        energies.append(float(lk @ lk))
        print(f"| placement {s} cells | {np.linalg.norm(Dk) / norm_W:.3f} | {share(Dk, [J]):.3f} | {share(Dk, [J, D]):.3f} | "
              f"{np.linalg.norm(lk) / norm_W:.3f} |")
    print(f"\nfloor (mean leftover energy of the placements) / world leftover energy: "
          f"{np.mean(energies) / float(leftover(gap, [J, D]) @ leftover(gap, [J, D])):.2f}\n")

    # other valid discretizations that are not placements: fill seeds, and mass moved between
    # the Gaussian-associated and the fill particles (5 % more on the Gaussian ones, the total kept)
    print("| other change | size / \\|W\\| | theta + D represent | theta + D + it represent the world gap |")
    print("|---|---:|---:|---:|")
    for k in (1, 2, 3):
        seeded = dataclasses.replace(c, fill=dataclasses.replace(c.fill, seed=c.fill.seed + k))
        Dk = (field(built(seeded), spec) - U).ravel()
        print(f"| fill seed + {k} | {np.linalg.norm(Dk) / norm_W:.3f} | {share(Dk, [J, D]):.3f} | {share(gap, [J, D, Dk]):.3f} |")
    vol = particle_volumes(np.asarray(asset.particles.positions), dx).astype(np.float64)
    gs = np.arange(len(vol)) < n_gs
    vol[gs] *= 1.05
    vol[~gs] -= (vol[gs].sum() / 1.05 * 0.05) * vol[~gs] / vol[~gs].sum()
    heavier = dataclasses.replace(asset.particles, volumes=vol.astype(np.float32))
    Dm = (field(ForwardModel(c, heavier, device="cpu"), spec) - U).ravel()
    print(f"| 5 % of the mass to the Gaussian particles | {np.linalg.norm(Dm) / norm_W:.3f} | {share(Dm, [J, D]):.3f} | "
          f"{share(gap, [J, D, Dm]):.3f} |\n")

    # catalogue signatures, sized as the loop sizes them at this theta (its own context)
    X = np.asarray(fw.rollout(spec, probe), np.float64)
    T = X.shape[0]
    seen = Measurement(points=X[:, :n_gs], frames=np.arange(T), times=None, particle=np.arange(n_gs), track=np.arange(n_gs))
    cands = {k.key: k for k in default_catalogue(_context(Problem(seen, fw, probe, LoopSettings()), spec))}
    fwc = ForwardModel(c, asset.particles, catalogue=cands, device="cpu")
    print("| effect (middle trial) | size / \\|W\\| | theta represents | theta + D represent |")
    print("|---|---:|---:|---:|")
    for key, cand in cands.items():
        u = cand.trials[len(cand.trials) // 2]
        S = (field(fwc, spec.with_effect(key, u)) - U).ravel()
        print(f"| {key} | {np.linalg.norm(S) / norm_W:.3f} | {share(S, [J]):.3f} | {share(S, [J, D]):.3f} |")


if __name__ == "__main__":
    main()
