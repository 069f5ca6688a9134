"""Same code on CPU and CUDA: a knocked jelly block simulated on both devices, and a random
Gaussian scene rendered on both, compared. Float atomics make GPU sums order-dependent, so
the simulator comparison is a tolerance on the response, not bitwise. With ``--effects``, the
reproducible P2G (fixed-point sums, as the paper profile runs) under each effect
the discrepancy loop plants: two runs on the device bit for bit, and their response against
the device's default P2G and the CPU's. With ``--choices``, the solver's ``"auto"`` on the
device is checked against ``GPU_SOLVER_OPTIONS`` and ``GPU_STORAGE`` (what the CPU replays of
a GPU's substep), and the verification block (the ci levels' finest, `deterministic: true`)
simulated on the device is compared with that replay and with the CPU's own substep.

    python3 benchmarks/gpu_parity.py --device cuda:0 --effects --choices
"""

from __future__ import annotations

import argparse
import json

import numpy as np


def sim_parity(device: str) -> dict:
    from knockgs_core.sim import Box, DomainWalls, FixedCuboid, Probe, SimParams, build_model, make_state, simulate

    h = 1 / 32
    axis = np.arange(0.85 + h / 2, 1.15, h)
    zaxis = np.arange(0.8 + h / 2, 1.2, h)
    X = np.stack(np.meshgrid(axis, axis, zaxis, indexing="ij"), -1).reshape(-1, 3).astype(np.float32)
    params = SimParams(n_grid=32, dt=1e-3, boundaries=(DomainWalls(), FixedCuboid(Box((1.0, 1.0, 0.78), (0.3, 0.3, 0.05)))))
    out = {}
    for dev in ("cpu", device):
        model = build_model(X, E=1e4, nu=0.3, rho=1000.0, params=params, probe=Probe("knock", (-0.6, 0.0, 0.0), dt_ref=1e-3),
                            device=dev)
        out[dev] = simulate(model, make_state(model, X), frame_dt=0.02, n_frames=16).positions
    d_cpu = out["cpu"] - out["cpu"][0]
    d_gpu = out[device] - out[device][0]
    err = float(np.abs(d_gpu - d_cpu).max())
    scale = float(np.abs(d_cpu).max())
    return {"particles": len(X), "max_abs_diff": err, "max_displacement": scale, "relative": err / scale}


def effects_reproducible(device: str) -> dict:
    """A crowded block (8 particles a cell) knocked on a support, under each effect, for 30
    substeps: per effect, whether two reproducible runs on ``device`` give one MD5, and the
    largest differences (relative to the largest displacement) of a reproducible run against
    the device's default P2G and against the CPU's (the scatter)."""
    import hashlib

    from knockgs_core.sim import (Box, DomainWalls, FixedCuboid, Probe, SimParams, build_model, effect_examples,
                                  make_state, simulate_many)

    h = 1 / 64
    axis = np.arange(0.85 + h / 2, 1.15, h)
    zaxis = np.arange(0.8 + h / 2, 1.2, h)
    X = np.stack(np.meshgrid(axis, axis, zaxis, indexing="ij"), -1).reshape(-1, 3).astype(np.float32)
    params = SimParams(n_grid=32, dt=5e-4, guard_every=10,
                       boundaries=(DomainWalls(), FixedCuboid(Box((1.0, 1.0, 0.78), (0.3, 0.3, 0.05)))))
    effects = [None, *effect_examples(centre=(1.0, 1.0, 1.0))]
    out = {"particles": len(X)}
    for effect in effects:
        p = params if effect is None else effect.configure(params)
        runs = {}
        for name, dev, det in (("cpu", "cpu", False), ("default", device, False), ("fixed1", device, True),
                               ("fixed2", device, True)):
            model = build_model(X, E=2e4, nu=0.3, rho=1000.0, params=p, device=dev,
                                probe=Probe("knock", (-2.0, 0.0, 0.0), n_steps=4, dt_ref=5e-4))
            r = simulate_many([(model, make_state(model, X))], frame_dt=30 * p.dt, n_frames=2, deterministic=det)[0]
            runs[name] = r.positions[-1] - r.positions[0]
        scale = float(np.abs(runs["cpu"]).max())
        out[type(effect).__name__ if effect else "none"] = {
            "same_bits": hashlib.md5(runs["fixed1"].tobytes()).hexdigest() == hashlib.md5(runs["fixed2"].tobytes()).hexdigest(),
            "vs_default": float(np.abs(runs["fixed1"] - runs["default"]).max()) / scale,
            "vs_cpu": float(np.abs(runs["fixed1"] - runs["cpu"]).max()) / scale,
            "max_displacement": scale}
    return out


def gpu_choices(device: str) -> dict:
    """What ``"auto"`` chooses on ``device`` for the verification block (8 particles a cell, no
    effects) against ``GPU_SOLVER_OPTIONS`` / ``GPU_STORAGE``, and the block's displacements on
    the device against the CPU's replay of the GPU's substep and the CPU's own substep, each
    relative to the RMS displacement (all three with the reproducible sums)."""
    from pathlib import Path

    import yaml

    from knockgs_core.fem import VerificationSettings, mpm_block_rollout
    from knockgs_core.fem._verification import mpm_block_model
    from knockgs_core.sim import GPU_SOLVER_OPTIONS, GPU_STORAGE, MPMSolver, make_state

    root = Path(__file__).resolve().parents[1]
    block = yaml.safe_load((root / "config/ci.yaml").read_text())["verification"]
    settings = VerificationSettings.from_config({k: v for k, v in block.items() if k != "enabled"})
    n_grid = settings.n_grid[-1]
    model, x = mpm_block_model(n_grid, settings, device=device)
    state = make_state(model, x)
    solver = MPMSolver(model)
    chosen = {key: getattr(solver, key) for key in GPU_SOLVER_OPTIONS}
    storage = {"matrix_layout": "components" if state.particle_C.ndim == 2 else "records",
               "deformation_storage": "displacement" if state.particle_F.ndim == 3 else "float64"}
    u = {"device": mpm_block_rollout(n_grid, settings, device=device, deterministic=True)["u"],
         "cpu_replay": mpm_block_rollout(n_grid, settings, device="cpu", deterministic=True,
                                         solver_options=GPU_SOLVER_OPTIONS, storage=GPU_STORAGE)["u"],
         "cpu": mpm_block_rollout(n_grid, settings, device="cpu", deterministic=True)["u"]}
    rms = float(np.sqrt(np.mean(np.sum(u["cpu"] ** 2, axis=-1))))

    def differs(a, b):
        return float(np.sqrt(np.mean(np.sum((u[a] - u[b]) ** 2, axis=-1)))) / rms

    return {"auto": chosen, "auto_storage": storage,
            "matches": chosen == dict(GPU_SOLVER_OPTIONS) and storage == dict(GPU_STORAGE),
            "n_grid": n_grid, "rms_displacement_m": rms,
            "device_vs_cpu_replay": differs("device", "cpu_replay"), "device_vs_cpu": differs("device", "cpu"),
            "cpu_replay_vs_cpu": differs("cpu_replay", "cpu")}


def render_parity(device: str) -> dict:
    from knockgs_core.render import Camera, render

    rng = np.random.default_rng(3)
    n = 2000
    means = rng.uniform(0.7, 1.3, (n, 3))
    A = rng.normal(size=(n, 3, 3)) * 0.02
    cov = np.einsum("nij,nkj->nik", A, A) + 1e-5 * np.eye(3)
    colors = rng.uniform(0, 1, (n, 3))
    opac = rng.uniform(0.3, 1.0, n)
    cam = Camera.look_at((1.0, -1.6, 1.3), (1.0, 1.0, 1.0), (0.0, 0.0, 1.0), fov_deg=40.0, width=160, height=120)
    a = render(means, cov, colors, opac, cam, device="cpu")
    b = render(means, cov, colors, opac, cam, device=device)
    return {"gaussians": n, "max_abs_diff_rgb": float(np.abs(a.rgb - b.rgb).max()),
            "max_abs_diff_alpha": float(np.abs(a.alpha - b.alpha).max())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--json")
    ap.add_argument("--effects", action="store_true",
                    help="also the reproducible P2G under each effect the discrepancy loop plants")
    ap.add_argument("--choices", action="store_true",
                    help="also the device's choices against what the CPU replays of a GPU's substep")
    args = ap.parse_args()
    res = {"sim": sim_parity(args.device)}
    if args.effects:
        res["effects"] = effects_reproducible(args.device)
    if args.choices:
        res["choices"] = gpu_choices(args.device)
    try:
        res["render"] = render_parity(args.device)
    except ImportError as exc:  # renderer not installed in this tree
        res["render"] = {"skipped": str(exc)}
    print(json.dumps(res, indent=1))
    if args.json:
        from knockgs_core.io import write_json

        write_json(args.json, res, indent=1)


if __name__ == "__main__":
    main()
