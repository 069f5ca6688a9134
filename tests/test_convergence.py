"""Discretization checks of the simulator and of the object contracts at the ci profile.

(a) The simulated particles form one body at the grid resolution: particles closer than
    1.5 dx share most of their quadratic B-spline stencil and move together, so a group of
    particles farther than that from the rest is a separate body. Every group must contain a
    particle held by a support (fixed cuboid or particle translation box); a free group
    would fly off after the knock.
(b) Time convergence of the transfer on a free-free bar (no probe, no support): the
    affine-FLIP transfer converges at first order in dt (observed order from three dt), also
    with every choice a GPU makes (the paper profile's substep, replayed on the CPU), and
    the energy APIC loses grows as dt shrinks (a numerical damping per substep) while the
    affine-FLIP transfer's loss does not.
(c) Halving the substep changes the Probe-A response (displacement trajectories of the
    Gaussian-associated particles, first 10 exported frames) by less than 2 %
    (relative L2) for the Pillow (measured 0.45 %) and the Vasedeck (0.99 %); the Ficus
    (3.0 % over these frames, 6.5 % over all 31) is held to 4 %, which APIC (42 %) failed.

Measured numbers: docs/assets.md, "Connectivity and substep convergence".
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from knockgs_core.assets import build_asset
from knockgs_core.contract import load_contract
from knockgs_core.rollout import run_rollout
from knockgs_core.sim import (GPU_SOLVER_OPTIONS, GPU_STORAGE, ExportSchedule, MPMSolver, SimParams, build_model, make_state,
                              simulate)

OBJECTS = ("pillow", "ficus", "vasedeck")
LINK_CELLS = 1.5       # particles closer than this many cells belong to one body
#: relative L2 change, dt -> dt / 2, first 10 frames at ci: the 2 % target for every object
#: (measured 0.45, 0.83, 1.08 %; the Ficus was 3.0 % with the polar iterations capped at 4)
DT_TOLERANCE = {"pillow": 0.02, "vasedeck": 0.02, "ficus": 0.02}
N_FRAMES = 11          # t = 0 and the first 10 exported frames
THETA = (1.15, 0.75)   # stiffest, lightest candidate: the fastest response


def held_mask(contract, positions: np.ndarray) -> np.ndarray:
    """Particles inside a support box (fixed cuboid or particle translation) at t = 0."""
    held = np.zeros(len(positions), dtype=bool)
    for bc in contract.sim.boundaries:
        box = getattr(bc, "box", None)
        if box is not None:
            held |= box.contains(positions)
    return held


def free_bodies(contract, positions: np.ndarray, *, link_cells: float = LINK_CELLS) -> list[int]:
    """Sizes of the particle groups (linked below ``link_cells * dx``) that hold no
    supported particle, largest first; empty when the object is one supported body."""
    pos = np.asarray(positions, dtype=np.float64)
    tree = cKDTree(pos)
    pairs = tree.sparse_distance_matrix(tree, link_cells * contract.sim.dx, output_type="coo_matrix")
    _, label = connected_components(pairs, directed=False)
    anchored = np.zeros(label.max() + 1, dtype=bool)
    anchored[label[held_mask(contract, pos)]] = True
    sizes = np.bincount(label)
    return sorted((int(s) for s in sizes[~anchored]), reverse=True)


def relative_change(a: np.ndarray, b: np.ndarray) -> float:
    """Relative L2 difference of the displacement trajectories ``a`` against ``b`` (T, N, 3)."""
    da = (a - a[0]).astype(np.float64)
    db = (b - b[0]).astype(np.float64)
    return float(np.linalg.norm(da - db) / np.linalg.norm(db))


# --------------------------------------------------------------------------- (a) one body

@pytest.mark.parametrize("profile", ["ci", "default"])
@pytest.mark.parametrize("name", OBJECTS)
def test_simulated_particles_form_one_supported_body(name, profile):
    c = load_contract(name, profile)
    ps = build_asset(c).particles
    assert held_mask(c, ps.positions).any()
    assert free_bodies(c, ps.positions) == []


def test_a_detached_leaf_cluster_is_found():
    """The check fails on a Ficus whose top leaf cluster is lifted 3 cells off the plant."""
    c = load_contract("ficus", "ci")
    pos = np.array(build_asset(c).particles.positions, dtype=np.float64)
    top = np.linalg.norm(pos - pos[np.argmax(pos[:, 2])], axis=1) < 1.5 * c.sim.dx
    pos[top, 2] += 3.0 * c.sim.dx
    assert free_bodies(c, pos) == [int(top.sum())]


# --------------------------------------------------------------------------- (b) the transfer

BAR_DT = 5e-3          # the Pillow ci substep; the bar's c_p dt / dx is 0.25 there
BAR_E, BAR_NU, BAR_RHO = 1.15e4, 0.3, 1500.0   # the Pillow base material at theta (1.15, 0.75)


def _bar():
    """A free-free bar 1 x 0.25 x 0.25 m, 8 particles per cell at n_grid 32, started with a
    smooth velocity field: the first axial mode plus a momentum-free transverse bend."""
    dx = 2.0 / 32
    lo, ext = np.array([0.5, 0.875, 0.875]), np.array([1.0, 0.25, 0.25])
    cells = np.stack(np.meshgrid(*[np.arange(int(round(e / dx))) for e in ext], indexing="ij"), -1).reshape(-1, 3)
    sub = np.stack(np.meshgrid(*[np.array([0.25, 0.75])] * 3, indexing="ij"), -1).reshape(-1, 3)
    x = (lo + (cells[:, None, :] + sub[None]) * dx).reshape(-1, 3)
    s = (x[:, 0] - lo[0]) / ext[0]
    v = np.zeros_like(x)
    v[:, 0] = 0.02 * np.cos(np.pi * s)
    v[:, 2] = 0.01 * np.cos(2 * np.pi * s)
    return x, v


def _bar_run(transfer: str, dt: float, *, n_frames: int = 31, deformation_storage: str = "float64"):
    """Displacements (T, N, 3) [m] every 20 ms and the final total energy [J] of the bar, F
    stored as ``deformation_storage`` (``Model.deformation_storage``; its displacement gradient
    in float32 component by component, as on a GPU)."""
    model, x, v = _bar_model(transfer, dt, gpu_storage=deformation_storage == "displacement")
    state = make_state(model, x, v)
    out = simulate(model, state, frame_dt=0.02, n_frames=n_frames)
    return out.positions.astype(np.float64) - x[None], _energy(model, state), _energy0(model, v)


def _bar_model(transfer: str, dt: float, *, gpu_storage: bool):
    """The bar's model, F stored as on a GPU where ``gpu_storage`` (F - I in float32, matrices
    component by component), its positions and initial velocities."""
    x, v = _bar()
    model = build_model(x, E=BAR_E, nu=BAR_NU, rho=BAR_RHO,
                        params=SimParams(n_grid=32, dt=dt, boundaries=(), transfer=transfer),
                        **(GPU_STORAGE if gpu_storage else {}))
    return model, x, v


def _energy0(model, v) -> float:
    return float(0.5 * (model.mass_host.astype(np.float64) * (v.astype(np.float64) ** 2).sum(1)).sum())


def _energy(model, state) -> float:
    """Kinetic plus fixed-corotated elastic energy [J]: psi = mu |F - R|^2 + lam / 2 (J - 1)^2."""
    m = model.mass_host.astype(np.float64)
    v = state.particle_v.numpy().astype(np.float64)
    F = state.deformation_gradients()
    U, S, Vt = np.linalg.svd(F)
    R = U @ Vt
    J = np.linalg.det(F)
    mu, lam = (a.numpy().astype(np.float64) for a in (model.particle_mu, model.particle_lam))
    psi = mu * ((F - R) ** 2).sum((1, 2)) + 0.5 * lam * (J - 1.0) ** 2
    return float(0.5 * (m * (v**2).sum(1)).sum() + (model.particle_vol.numpy().astype(np.float64) * psi).sum())


@pytest.mark.slow
def test_affine_flip_converges_at_first_order_in_dt():
    """Observed order of the bar's trajectory change under dt -> dt/2 -> ... -> dt/16
    (measured 0.114, 0.067, 0.038, 0.020 %: orders 0.77, 0.82, 0.89, rising to 1); APIC's
    change grows instead (1.74, 3.14 %: order -0.85). With F in float32 the changes stalled at
    0.04 % from dt/8 on (orders 0.64, -0.06): the rounding floor of F's update."""
    runs = [_bar_run("affine_flip", BAR_DT / 2**k)[0] for k in range(5)]
    _first_order(runs)
    apic = [_bar_run("apic", BAR_DT / 2**k)[0] for k in range(3)]
    apic_changes = [np.linalg.norm(a - b) / np.linalg.norm(b) for a, b in zip(apic, apic[1:])]
    changes = [np.linalg.norm(a - b) / np.linalg.norm(b) for a, b in zip(runs, runs[1:])]
    assert apic_changes[1] > apic_changes[0] > 3 * changes[0], apic_changes


@pytest.mark.slow
def test_displacement_storage_keeps_the_first_order_in_dt():
    """The same bar with F stored as its displacement gradient F - I in float32 (the GPU's
    storage): no rounding floor, the same changes as F in float64 to three digits (measured
    0.1138, 0.0668, 0.0378, 0.0204 %: orders 0.769, 0.822, 0.886 against 0.885), where F in
    float32 stalled."""
    _first_order([_bar_run("affine_flip", BAR_DT / 2**k, deformation_storage="displacement")[0] for k in range(5)])


#: every choice a GPU makes where the CPU makes another (``"auto"`` in :class:`MPMSolver`), and
#: the paper profile's ``deterministic: true``
GPU_CONFIGURATION = dict(GPU_SOLVER_OPTIONS, deterministic=True)


def _bar_displacements(dt: float, solver_options: dict, *, gpu_storage: bool, n_frames: int = 31):
    """The bar stepped by ``MPMSolver(model, **solver_options)``, F stored as on a GPU where
    ``gpu_storage`` (F - I in float32, matrices component by component): the particles'
    displacements (T, N, 3) [m] every 20 ms, read as the state holds them, the final and the
    initial total energy [J], and the solver."""
    model, x, v = _bar_model("affine_flip", dt, gpu_storage=gpu_storage)
    state = make_state(model, x, v)
    solver = MPMSolver(model, **solver_options)
    frames = [state.particle_u.numpy().astype(np.float64)]
    solver.check(state)
    for _ in range(n_frames - 1):
        for _ in range(int(round(0.02 / dt))):
            solver.step(state)
            if state.step % model.params.guard_every == 0:
                solver.check(state)
        frames.append(state.particle_u.numpy().astype(np.float64))
    return np.asarray(frames), _energy(model, state), _energy0(model, v), solver


@pytest.mark.slow
def test_the_gpu_configuration_keeps_the_first_order_in_dt():
    """The paper profile's GPU substep replayed on the CPU: P2G by cells summed in windows into
    fixed-point sums, G2P fused and summed along stencil lines, the polar step 1.5 by rational
    quaternions, F - I in float32 by components. The bar converges as under the CPU's choices
    (measured changes 0.1138, 0.0666, 0.0374, 0.0201 %: orders 0.773, 0.832, 0.898 against
    0.770, 0.827, 0.902), loses the same energy (5.124 % against 5.133 % at dt) and stays within
    9e-5 of the CPU's trajectory at dt (1.4e-4 at dt / 16). That difference is the polar step's:
    the iterations stop within float32 rounding of the rotation at another point, and the
    small strain's stress 2 mu (F - R) F^T takes it in; every other choice alone moves the bar
    by 3e-7 to 5e-7."""
    runs = [_bar_displacements(BAR_DT / 2**k, GPU_CONFIGURATION, gpu_storage=True) for k in range(5)]
    solver = runs[0][3]
    assert (solver.p2g, solver.cell_sums, solver._fixed is not None, solver.fuse) == ("cells", "windows", True, True)
    _first_order([r[0] for r in runs])
    cpu, e_cpu, e0, _ = _bar_displacements(BAR_DT, {}, gpu_storage=False)
    gpu, e_gpu, _, _ = runs[0]
    assert np.linalg.norm(gpu - cpu) / np.linalg.norm(cpu) < 3e-4
    assert abs(e_gpu - e_cpu) / e0 < 5e-4 and 0.02 < 1 - e_cpu / e0 < 0.08


def _first_order(runs):
    """The bar's trajectory changes under dt halvings shrink at an order >= 0.7 that rises
    towards 1 (affine FLIP's first order), the first below 0.5 %."""
    changes = [np.linalg.norm(a - b) / np.linalg.norm(b) for a, b in zip(runs, runs[1:])]
    orders = np.log2(np.array(changes[:-1]) / np.array(changes[1:]))
    assert changes[0] < 0.005, changes
    assert np.all(orders >= 0.7) and orders[-1] >= 0.85, (changes, orders)
    assert np.all(np.diff(orders) > 0), (changes, orders)   # entering the asymptotic range


def test_apic_damping_is_per_substep_and_affine_flip_removes_it():
    """Energy (kinetic + particle-wise elastic) lost by the undamped free bar over 0.4 s.
    Both transfers share a loss that does not depend on dt (the energy estimate and the
    grid's spatial error: 4.2 % and 4.4 % at dt and dt/2 under affine FLIP); APIC loses in
    addition the non-affine velocity at every transfer, so its excess over affine FLIP
    nearly doubles when dt halves (measured 2.0 % and 3.8 %: a damping per substep)."""
    loss = {}
    for transfer in ("apic", "affine_flip"):
        for k in (0, 1):
            _, e1, e0 = _bar_run(transfer, BAR_DT / 2**k, n_frames=21)
            loss[transfer, k] = (e0 - e1) / e0
    excess = [loss["apic", k] - loss["affine_flip", k] for k in (0, 1)]
    assert excess[0] > 0.01, loss
    assert 1.6 < excess[1] / excess[0] < 2.4, loss
    assert abs(loss["affine_flip", 1] - loss["affine_flip", 0]) < 0.1 * loss["affine_flip", 0], loss


# --------------------------------------------------------------------------- (c) dt, objects

def _probe_a(contract, particles, dt: float) -> np.ndarray:
    probe = contract.resolve_probes(particles)[contract.roles["calibration"]]
    probe = dataclasses.replace(probe, export=ExportSchedule(probe.export.frame_dt, N_FRAMES))
    out = run_rollout(contract, THETA, probe.name, particles=particles, probe=probe, sim_overrides={"dt": dt})
    return out.positions[:, : particles.n_gs]


@pytest.mark.slow
@pytest.mark.parametrize("name", OBJECTS)
def test_halving_dt_keeps_the_probe_a_response(name):
    c = load_contract(name, "ci")
    assert c.sim.transfer == "affine_flip"
    ps = build_asset(c).particles
    dt = c.sim.dt
    coarse, fine = _probe_a(c, ps, dt), _probe_a(c, ps, dt / 2)
    assert np.all(np.isfinite(coarse)) and np.all(np.isfinite(fine))
    assert np.abs(fine - fine[0]).max() > 1e-4           # the knock moves the object
    assert relative_change(coarse, fine) < DT_TOLERANCE[name]
