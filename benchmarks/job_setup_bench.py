"""The host-side set-up of one rollout job, before its first substep: what a library job does
besides its kernels. Times (median of ``--repeats``) the particles' read, their cell order, the
probes' resolution and, per candidate, the materials, :func:`knockgs_core.sim.build_model` and
:func:`knockgs_core.sim.make_state`; and the former ``make_state`` (F and the rotations built as
host arrays of identities and copied), whose state must equal today's.

    python3 -m knockgs_core asset make pillow --profile paper -o OUT/pillow.ply --normalized \
        --particles OUT/pillow.particles.npz
    python3 benchmarks/job_setup_bench.py --object pillow --profile paper --particles OUT/pillow.particles.npz
"""

from __future__ import annotations

import argparse

import numpy as np
import warp as wp

from _timing import median_time
from knockgs_core.assets import load_particles
from knockgs_core.contract import load_contract
from knockgs_core.rollout import _permuted, cell_order
from knockgs_core.sim import build_model, make_state


def _former_state(model, x):
    """The former make_state's arrays: identities tiled on the host, then copied."""
    n, dev, g = model.particle_count, model.device, model.params.n_grid
    g_old = g if model.params.transfer == "affine_flip" else 1
    eye = np.tile(np.eye(3, dtype=np.float32), (n, 1, 1))
    rot = np.tile(np.array([0, 0, 0, 1], dtype=np.float32), (n, 1))
    return (wp.array(x, dtype=wp.vec3, device=dev), wp.zeros(n, dtype=wp.vec3, device=dev),
            wp.array(np.zeros_like(x), dtype=wp.vec3, device=dev), wp.array(eye.astype(np.float64), dtype=wp.mat33d, device=dev),
            wp.zeros(n, dtype=wp.mat33, device=dev), wp.array(rot, dtype=wp.quat, device=dev),
            wp.zeros((g, g, g), dtype=wp.vec3, device=dev), wp.zeros((g, g, g), dtype=float, device=dev),
            wp.zeros((g_old,) * 3, dtype=wp.vec3, device=dev))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--object", default="pillow")
    ap.add_argument("--profile", default="paper")
    ap.add_argument("--particles", required=True, help="the object's particles .npz (knockgs asset make --particles)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args()
    contract = load_contract(args.object, args.profile)
    p = contract.sim
    r = args.repeats
    t_read, ps = median_time(lambda: load_particles(args.particles), r)
    t_order, perm = median_time(lambda: cell_order(ps, n_grid=p.n_grid, grid_lim=p.grid_lim), r)
    ps = _permuted(ps, perm)
    t_probes, probes = median_time(lambda: contract.resolve_probes(ps), r)
    probe = probes[contract.calibration_probe.name]
    n = len(ps.positions)
    scale = float(contract.probe_reference_particles) / n if contract.probe_reference_particles else 1.0
    t_mat, (E, nu, rho) = median_time(lambda: contract.particle_materials(ps, (1.0, 1.0)), r)
    t_model, model = median_time(lambda: build_model(ps.positions, E=E, nu=nu, rho=rho, params=p, volumes=ps.volumes,
                                                 probe=probe, probe_force_scale=scale, device=args.device), r)
    t_state, state = median_time(lambda: make_state(model, ps.positions), r)
    t_former, former = median_time(lambda: _former_state(model, ps.positions), r)
    now = (state.particle_x0.numpy(), state.particle_u.numpy(), state.particle_v.numpy(), state.deformation_gradients(),
           state.affine_velocities(), state.particle_rot.numpy())
    for a, before in zip(now, former):
        assert np.array_equal(a, before.numpy())
    print(f"{args.object} ({args.profile}, {n} particles) on {args.device}, median of {r} [s]")
    print(f"particles read {t_read:.3f}, cell order {t_order:.3f}, probes {t_probes:.3f}")
    print(f"a candidate: materials {t_mat:.3f}, build_model {t_model:.3f}, make_state {t_state:.3f} "
          f"(former {t_former:.3f}, the same state)")


if __name__ == "__main__":
    main()
