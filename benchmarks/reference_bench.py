"""Our solver beside PhysGaussian's Warp MPM solver, in one process on one device.

The reference is read from a checkout of PhysGaussian (``--physgaussian``: the folder holding
``mpm_solver_warp/``; not shipped here, not imported by the package), its four modules copied
to a temporary folder with one change (:func:`load_reference`). Its modules import
``torch``, ``warp.torch`` and ``h5py`` at the top for helpers this benchmark does not call; they
are stood in for by empty modules, so no PyTorch is needed; nor are the
names ``warp.types.float32`` and ``int32`` (an older Warp's), which those helpers' default
arguments read at import and which are set to Warp's ``float32`` and ``int32``. Both solvers simulate the block of
``sim_bench.py`` (jelly, E = 1e4 Pa, nu = 0.3, rho = 2000 kg/m^3, 8 particles a cell in
[0, 2]^3, dt = 1e-4 s): ours knocked by its one-substep global probe, the reference started at
the velocity that probe gives (it has no probe; its substep cost does not depend on the
velocity). The reference's ``p2g2p`` wraps its kernels in synchronizing ``wp.ScopedTimer``s;
``--timers off`` (the default) replaces them by a no-op for its timed substeps, ``on`` keeps
them (as published). Each solver runs 20 substeps of warm-up, then ``--steps`` substeps
``--repeats`` times; the median is reported. Ours with the contracts' affine FLIP and with
APIC (the reference's transfer), P2G ``auto``, particles in the lattice's and the cell order.

    python3 benchmarks/reference_bench.py --physgaussian PATH/TO/PhysGaussian --device cuda:0 \\
        --cases 681472:100 --steps 500 --repeats 3
"""

from __future__ import annotations

import argparse
import contextlib
import statistics
import sys
import tempfile
import time
import types
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from sim_bench import block, run_case  # noqa: E402

E, NU, RHO, DT, GRID_LIM, PPC = 1e4, 0.3, 2000.0, 1e-4, 2.0, 8


#: the reference's weight matrices built from three column vectors, ``wp.mat33(c0, c1, c2)``
#: (what older Warp's vector constructor meant: ``mat_t(c0, c1, c2)`` in Warp's ``mat.h`` sets
#: columns); Warp 1.19 refuses vectors there, so they are read as ``wp.matrix_from_cols``
COLUMN_MATRICES = ("dw = wp.mat33(", " w = wp.mat33(")  # in this order: the second is in the first
MODULES = ("engine_utils.py", "mpm_solver_warp.py", "mpm_utils.py", "warp_utils.py")


def load_reference(root: Path, workdir: Path):
    """PhysGaussian's solver module from the checkout ``root``: its four modules copied to
    ``workdir`` (``mpm_utils.py`` with :data:`COLUMN_MATRICES` as ``wp.matrix_from_cols``, two
    each in P2G and G2P; nothing else changed) and imported from there, the imports it does not
    use here stood in for."""
    solver_dir = root / "mpm_solver_warp"
    for name in MODULES:
        if not (solver_dir / name).is_file():
            raise SystemExit(f"--physgaussian: {solver_dir / name} not found")
    for name in MODULES:
        text = (solver_dir / name).read_text()
        if name == "mpm_utils.py":
            for pattern in COLUMN_MATRICES:
                if text.count(pattern) != 2:
                    raise SystemExit(f"--physgaussian: {solver_dir / name}: expected '{pattern}' twice (P2G, G2P), "
                                     f"found {text.count(pattern)}; another version of the reference")
                text = text.replace(pattern, pattern.replace("wp.mat33(", "wp.matrix_from_cols("))
        (workdir / name).write_text(text)
    import warp as wp

    for name in ("torch", "h5py"):
        sys.modules.setdefault(name, types.ModuleType(name))
    if "warp.torch" not in sys.modules:
        sys.modules["warp.torch"] = types.ModuleType("warp.torch")
    for name in ("float32", "int32"):  # default values of its torch helpers, from an older Warp's namespace
        if not hasattr(wp.types, name):
            setattr(wp.types, name, getattr(wp, name))
    sys.path.insert(0, str(workdir))
    import mpm_solver_warp as ref

    return ref, wp


@contextlib.contextmanager
def timers_off(wp):
    """The reference's ``wp.ScopedTimer`` as a no-op while inside."""

    class _NoTimer:
        def __init__(self, *args, **kwargs):
            pass

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

    saved = wp.ScopedTimer
    wp.ScopedTimer = _NoTimer
    try:
        yield
    finally:
        wp.ScopedTimer = saved


def probe_velocity(X: np.ndarray, n_grid: int, device: str) -> tuple[np.ndarray, np.ndarray]:
    """Our block's particle volumes [m^3] (N,) and the velocity [m/s] (3,) its one-substep
    global probe gives every particle (the particles' masses are equal)."""
    from knockgs_core.sim import Probe, SimParams, build_model

    model = build_model(X, E=E, nu=NU, rho=RHO, params=SimParams(n_grid=n_grid, dt=DT),
                        probe=Probe("standard_x", (-0.18, 0.0, 0.0)), device=device)
    mass = model.particle_mass.numpy()
    return model.particle_vol.numpy(), np.asarray(model.probe_force, dtype=np.float64) * DT / float(mass[0])


def run_reference(ref, wp, X: np.ndarray, vol: np.ndarray, v0: np.ndarray, n_grid: int, steps: int, repeats: int,
                  device: str, timers: bool) -> dict:
    """Median seconds of ``steps`` reference substeps (after 20 of warm-up), and the mean
    particle velocity at the end (momentum is conserved: it should stay ``v0``)."""
    n = len(X)
    sim = ref.MPM_Simulator_WARP(n, n_grid=n_grid, grid_lim=GRID_LIM, device=device)
    st = sim.mpm_state
    st.particle_x = wp.array(X, dtype=wp.vec3, device=device)
    st.particle_vol = wp.array(vol.astype(np.float32), dtype=float, device=device)
    st.particle_v = wp.array(np.broadcast_to(v0, (n, 3)).astype(np.float32), dtype=wp.vec3, device=device)
    wp.launch(ref.set_mat33_to_identity, dim=n, inputs=[st.particle_F_trial], device=device)
    sim.set_parameters_dict({"material": "jelly", "E": E, "nu": NU, "density": RHO, "g": [0.0, 0.0, 0.0],
                             "grid_lim": GRID_LIM, "n_grid": n_grid}, device=device)
    sim.finalize_mu_lam(device=device)
    quiet = contextlib.nullcontext() if timers else timers_off(wp)
    step = 0
    with quiet:
        for _ in range(20):
            sim.p2g2p(step, DT, device=device)
            step += 1
        wp.synchronize_device(device)
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            for _ in range(steps):
                sim.p2g2p(step, DT, device=device)
                step += 1
            wp.synchronize_device(device)
            times.append(time.perf_counter() - t0)
    x = st.particle_x.numpy().astype(np.float64)
    v = st.particle_v.numpy().astype(np.float64)
    if not (np.isfinite(x).all() and np.isfinite(v).all()):
        raise SystemExit("the reference's block blew up")
    med = statistics.median(times)
    return {"median_s": med, "ms_per_substep": 1e3 * med / steps, "mean_v": v.mean(0), "times": times}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--physgaussian", required=True, type=Path, help="a PhysGaussian checkout (holds mpm_solver_warp/)")
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--cases", nargs="+", default=["681472:100"], help="PARTICLES:N_GRID")
    ap.add_argument("--steps", type=int, default=500)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--timers", nargs="+", choices=["off", "on"], default=["off"],
                    help="the reference's synchronizing per-kernel timers, each measured")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as workdir:  # the reference's modules, removed at the end
        ref, wp = load_reference(args.physgaussian, Path(workdir))
        wp.init()
        print(f"# device {wp.get_device(args.device).name if args.device != 'cpu' else 'cpu'} ({args.device}), "
              f"Warp {wp.__version__}")
        print("| particles | n_grid | solver | ms/substep | reference (timers off) / this |")
        print("|---:|---:|---|---:|---:|")
        for case in args.cases:
            n, g = (int(v) for v in case.split(":"))
            X = block(n, g, grid_lim=GRID_LIM, ppc=PPC)
            vol, v0 = probe_velocity(X, g, args.device)
            base = None
            notes = []
            for timers in args.timers:
                r = run_reference(ref, wp, X, vol, v0, g, args.steps, args.repeats, args.device, timers == "on")
                if timers == "off":
                    base = r["ms_per_substep"]
                ratio = "" if base is None else f"{base / r['ms_per_substep']:.2f}"
                print(f"| {len(X):,} | {g} | PhysGaussian (timers {timers}) | {r['ms_per_substep']:.3f} | {ratio} |",
                      flush=True)
                notes.append(f"PhysGaussian (timers {timers}): mean velocity {r['mean_v'][0]:.6e} m/s in x after "
                             f"{20 + args.steps * args.repeats} substeps, started at {v0[0]:.6e} (momentum is conserved)")
            for transfer in ("affine_flip", "apic"):
                for order in ("lattice", "cell"):
                    r = run_case(n, g, args.steps, args.repeats, args.device, transfer=transfer, order=order, ppc=PPC)
                    ratio = "" if base is None else f"{base / r['ms_per_substep']:.2f}"
                    print(f"| {r['particles']:,} | {g} | ours, {transfer}, {order} order, P2G {r['p2g']} | "
                          f"{r['ms_per_substep']:.3f} | {ratio} |", flush=True)
            for note in notes:
                print(note)


if __name__ == "__main__":
    main()
