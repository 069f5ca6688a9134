"""How many warm-started polar iterations the particles take under each polar step and update
(``SolverConfig.polar_step``, ``SolverConfig.polar_update``), and how far each ends from the SVD's
rotation.

Part 1: an object's rollout state every ``--steps / 3`` substeps (the solver's own, CPU by
default); the polar loop of ``_kernels.polar_rotation`` replayed with a counter from the state's
rotations (one substep behind, as the solver warm-starts it) for each step and update. Part 2: random
deformation gradients ``F = R S`` (stretches up to 1.2, 3 and 10), started cold (identity), or
1e-3 or 0.3 rad off the SVD's rotation, with and without the 0.1-rad guard above which a
correction is taken whole.

    python3 benchmarks/polar_iterations.py --object pillow --profile default --steps 300
"""

from __future__ import annotations

import argparse

import numpy as np
import warp as wp

from knockgs_core.sim import _kernels as K


@wp.kernel
def counted_polar(F: wp.array(dtype=wp.mat33), q0: wp.array(dtype=wp.quat), max_iter: int, step: float, guard: float,
                  rational: int, iters: wp.array(dtype=wp.int32), last: wp.array(dtype=float),
                  out: wp.array(dtype=wp.quat)):
    """``_kernels.polar_rotation`` with its iterations counted, the last correction angle and
    the guard (the angle above which the step is 1) as arguments."""
    p = wp.tid()
    A = F[p]
    q = q0[p]
    a0 = wp.vec3(A[0, 0], A[1, 0], A[2, 0])
    a1 = wp.vec3(A[0, 1], A[1, 1], A[2, 1])
    a2 = wp.vec3(A[0, 2], A[1, 2], A[2, 2])
    n = int(0)
    angle = float(0.0)
    for _ in range(max_iter):
        R = wp.quat_to_matrix(q)
        r0 = wp.vec3(R[0, 0], R[1, 0], R[2, 0])
        r1 = wp.vec3(R[0, 1], R[1, 1], R[2, 1])
        r2 = wp.vec3(R[0, 2], R[1, 2], R[2, 2])
        num = wp.cross(r0, a0) + wp.cross(r1, a1) + wp.cross(r2, a2)
        den = wp.abs(wp.dot(r0, a0) + wp.dot(r1, a1) + wp.dot(r2, a2)) + 1.0e-9
        n += 1
        if rational == 1:
            small = num * (1.0 / den)
            angle2 = wp.dot(small, small)
            angle = wp.sqrt(angle2)
            if angle2 < 1.0e-14:
                break
            if angle2 < guard * guard:
                h = (0.5 * step) * small
                q = wp.normalize(wp.quat(h[0], h[1], h[2], 1.0) * q)
                continue
        omega = num / den
        angle = wp.length(omega)
        if angle < 1.0e-7:
            break
        scale = float(1.0)
        if angle < guard:
            scale = step
        q = wp.normalize(wp.quat_from_axis_angle(omega / angle, scale * angle) * q)
    iters[p] = n
    last[p] = angle
    out[p] = q


@wp.kernel
def solver_polar(F: wp.array(dtype=wp.mat33), q0: wp.array(dtype=wp.quat), step: float, rational: int,
                 out: wp.array(dtype=wp.quat)):
    """The solver's own ``_kernels.polar_rotation`` (the counted copy above is checked against it)."""
    p = wp.tid()
    out[p] = K.polar_rotation(F[p], q0[p], 32, step, rational)


def run(F: np.ndarray, q0: np.ndarray, step: float, guard: float, rational: int, device: str):
    n = len(F)
    it = wp.zeros(n, dtype=wp.int32, device=device)
    la = wp.zeros(n, dtype=float, device=device)
    qo = wp.zeros(n, dtype=wp.quat, device=device)
    wp.launch(counted_polar, dim=n, inputs=[wp.array(F.astype(np.float32), dtype=wp.mat33, device=device),
                                            wp.array(q0.astype(np.float32), dtype=wp.quat, device=device), 32, step, guard,
                                            rational],
              outputs=[it, la, qo], device=device)
    return it.numpy(), la.numpy(), qo.numpy()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--object", default="pillow")
    ap.add_argument("--profile", default="default")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--polar-steps", type=float, nargs="+", default=[1.0, 1.5, 1.8])
    ap.add_argument("--updates", nargs="+", choices=["axis_angle", "rational"], default=["axis_angle", "rational"],
                    help="how an iteration rotates by a correction below the guard (SolverConfig.polar_update)")
    args = ap.parse_args()

    from scipy.spatial.transform import Rotation

    from _object_model import object_particles, probe_a_model

    from knockgs_core.contract import load_contract
    from knockgs_core.sim import MPMSolver, make_state

    c = load_contract(args.object, args.profile)
    ps = object_particles(c, order="asset")
    model = probe_a_model(c, ps, args.device)
    state = make_state(model, ps.positions)
    solver = MPMSolver(model)
    print(f"{args.object} {args.profile}: {len(ps.positions)} particles, the solver's polar step {solver.polar_step}")
    print("| substep | polar step | update | mean iterations | most | histogram | last angle p99 [rad] |")
    print("|---:|---:|---|---:|---:|---|---:|")
    for s in range(args.steps):
        solver.step(state)
        if (s + 1) % max(1, args.steps // 3) == 0:
            F = state.deformation_gradients()
            for step, update in ((st, up) for st in args.polar_steps for up in args.updates):
                rational = int(update == "rational")
                it, la, q = run(F, state.particle_rot.numpy(), step, 0.1, rational, args.device)
                ref = wp.zeros(len(F), dtype=wp.quat, device=args.device)
                wp.launch(solver_polar, dim=len(F), inputs=[wp.array(F.astype(np.float32), dtype=wp.mat33, device=args.device),
                                                            state.particle_rot, step, rational], outputs=[ref],
                          device=args.device)
                if not np.array_equal(ref.numpy(), q):
                    raise SystemExit("the counted copy no longer computes the solver's polar_rotation")
                hist = {int(k): int(v) for k, v in enumerate(np.bincount(it)) if v}
                print(f"| {s + 1} | {step} | {update} | {it.mean():.2f} | {it.max()} | {hist} | {np.quantile(la, 0.99):.2e} |")

    rng = np.random.default_rng(0)
    n = 20000
    R = Rotation.random(n, random_state=1).as_matrix()
    U = Rotation.random(n, random_state=2).as_matrix()
    print("\n| stretch up to | start | polar step | guard [rad] | update | mean iterations | at the cap of 32 | |R - R_svd| max "
          "| p99.9 |")
    print("|---:|---|---:|---:|---|---:|---:|---:|---:|")
    for smax in (1.2, 3.0, 10.0):
        S = np.einsum("nij,nj,nkj->nik", U, np.exp(rng.uniform(-np.log(smax), np.log(smax), (n, 3))), U)
        F = np.einsum("nij,njk->nik", R, S).astype(np.float32)
        u, _, vt = np.linalg.svd(F.astype(np.float64))
        R_svd = u @ vt
        starts = {"cold": np.tile([0.0, 0.0, 0.0, 1.0], (n, 1)),
                  "1e-3 rad off": (Rotation.from_matrix(R_svd) * Rotation.from_rotvec(rng.normal(size=(n, 3)) * 1e-3)).as_quat(),
                  "0.3 rad off": (Rotation.from_matrix(R_svd) * Rotation.from_rotvec(rng.normal(size=(n, 3)) * 0.3)).as_quat()}
        for start, q0 in starts.items():
            for step, guard, update in ((1.0, 0.1, "axis_angle"), (1.5, 1e9, "axis_angle"), (1.5, 0.1, "axis_angle"),
                                        (1.5, 0.1, "rational")):
                if update not in args.updates:
                    continue
                it, _, qo = run(F, q0, step, guard, int(update == "rational"), args.device)
                err = np.abs(Rotation.from_quat(qo.astype(np.float64)).as_matrix() - R_svd).max(axis=(1, 2))
                print(f"| {smax} | {start} | {step} | {guard:g} | {update} | {it.mean():.2f} | {100 * np.mean(it == 32):.2f} % | "
                      f"{err.max():.1e} | {np.quantile(err, 0.999):.1e} |")


if __name__ == "__main__":
    main()
